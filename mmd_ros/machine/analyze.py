"""A machine session from logs to results and files: the library behind ``mmd machine``."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.machine import MachineDescription
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run
from mmd_ros.machine.compensation import write_compensation, write_csv, write_location_yaml
from mmd_ros.machine.errors import MachineAnalysisError
from mmd_ros.machine.identify import IdentifyOptions, identify
from mmd_ros.machine.report import markdown_report
from mmd_ros.machine.results import MachineResult
from mmd_ros.machine.session import AxisRun, Program, extract_runs, log_poses
from mmd_ros.machine.volumetric import VolumetricMap, linear_map, rotary_map

__all__ = ['SessionOptions', 'analyze_session', 'separation_text', 'write_outputs']


@dataclass
class SessionOptions:
    """model : the MMD's model (e.g. from ``mmd analyze``); None takes each log's own
    instrument : 'mmd' (the MMD's poses) or 'reference' (a 6-D reference instrument in the log)
    program : a test program when the logs carry no joint states
    """

    model: Model | None = None
    model_path: str | None = None
    instrument: str = 'mmd'
    program: Program | None = None
    identify: IdentifyOptions = field(default_factory=IdentifyOptions)
    calibration_path: str | None = None
    #: the device description to read the logs with instead of their own, or None
    device: DeviceDescription | None = None
    progress: bool = False


def separation_text(result: MachineResult, options: SessionOptions) -> str:
    """How this session keeps the MMD's errors out of the machine's (for the report)."""
    if result.instrument == 'reference':
        return ('The poses are the log\'s six-dimensional reference instrument, taken as exact '
                '(no MMD uncertainty is carried).')
    ident = options.identify
    bound = ''
    if ident.mmd_bound_m > 0 or ident.mmd_bound_rad > 0:
        bound = (f' A stated accuracy of the MMD, ±{ident.mmd_bound_m * 1e6:g} µm and '
                 f'±{math.degrees(ident.mmd_bound_rad) * 3600:g}″ per component (uniform), is added '
                 'to it.')
    return (
        f'1. The MMD\'s poses were computed with {result.model_text}: a device model from '
        '`mmd analyze` removes the effects of the MMD it has identified (hysteresis, timing, '
        'scale, calibration points) before the machine is evaluated; with CDF + thermal only, '
        'those effects stay in the poses and only item 2 bounds them.\n'
        '2. Every approach carries the pose covariance the pipeline gives for its samples (the '
        'model\'s bar-length uncertainty budget through the kinematics, from the same pass over '
        'the log as the poses), averaged over the dwell but not divided by the number of '
        'samples: it stands for the MMD\'s systematic error at that pose, which a dwell does '
        'not average out. It is drawn independently between targets and once more as one '
        'trend along each run (the MMD\'s error follows the bar lengths and repeats from cycle '
        'to cycle; a trend is what would pass for squareness or location), and enters every '
        f'identified error through the Monte Carlo draws (the "MMD part").{bound}\n'
        '3. The repeatability between the cycles (machine and MMD together) adds the statistical '
        'part.\n'
        '4. The plates\' setup (where {L} sits on the table, {U} on the spindle) is not a machine '
        'error: it is removed by definition as ISO 230-1 does: the X run\'s line defines x, the '
        'Y run\'s the xy plane (their slopes are setup), the other slopes are squareness; each '
        'run is taken relative to its own reference position.')


def _model_text(options: SessionOptions, log_model: Model | None) -> str:
    model = options.model if options.model is not None else log_model
    if model is None or not model.terms:
        what = 'CDF + thermal only (no device model)'
    else:
        what = f'a device model of {len(model.terms)} term(s) ({", ".join(t.type_name for t in model.terms)})'
        fit = model.uncertainty.fit
        if fit is not None and fit.replaces and 'unseen_constant_nm' in fit.record:
            what += ('; its measured residual in place of the calibration-derived sources, fitted '
                     'with an offset per component removed, so the constant error its runs could '
                     'not see stays in the pose covariance (the common mode of the bars at the '
                     'calibration\'s claim; characterise with an absolute reference, `mmd analyze '
                     '--absolute-reference`, for it to shrink)')
        elif fit is not None and fit.replaces:
            what += '; its measured residual in place of the calibration-derived sources'
        elif fit is not None:
            what += ('; the calibration-derived sources stay in the pose covariance (its fit\'s '
                     'reference did not see every bar, or, in a model from before 2026-11-27, '
                     'removed an offset per component)')
    where = options.model_path or ('the given model' if options.model is not None else "the log's model")
    return f'{where}: {what}' if model is not None else what


def analyze_session(logs: list[str | Path], machine: MachineDescription,
                    options: SessionOptions | None = None,
                    progress: Callable[[str, int, int], None] | None = None) -> MachineResult:
    """Identify a machine's errors from the logs of a session (each log: one run or several,
    with joint states; or with a test program, one log per program run in order)."""
    options = options or SessionOptions()
    started = time.perf_counter()
    if options.program is not None and len(options.program.runs) != len(logs):
        raise MachineAnalysisError(f'the test program has {len(options.program.runs)} runs for '
                                   f'{len(logs)} logs: give one log per program run, in order')
    runs: list[AxisRun] = []
    model_texts = set()
    for i, path in enumerate(logs):
        run = read_run(path, device=options.device)
        poses = log_poses(run, options.model, instrument=options.instrument,
                          calibration_path=options.calibration_path, progress=options.progress)
        model_texts.add(_model_text(options, run.model))
        plan = options.program.runs[i] if options.program is not None else None
        found = extract_runs(run, machine, poses, program_run=plan,
                             min_dwell_s=options.program.min_dwell_s if options.program else 0.15)
        if not found:
            raise MachineAnalysisError(f'{path}: no axis run found (no axis stepped through '
                                       'targets and back)')
        runs.extend(found)
    t_poses = time.perf_counter() - started
    result = identify(runs, machine, options=options.identify, instrument=options.instrument,
                      model_text=', '.join(sorted(model_texts)), logs=[str(p) for p in logs],
                      progress=progress)
    result.seconds['poses'] = t_poses
    result.seconds['total'] = time.perf_counter() - started
    return result


def write_outputs(result: MachineResult, out: Path, options: SessionOptions | None = None, *,
                  units: str = 'mm', figures: bool = True, tool_offset=None) -> dict[str, object]:
    """Report, JSON, figures, compensation files, CSV, location YAML and volumetric maps."""
    from mmd_ros.machine.plots import machine_figures  # matplotlib: only when writing them
    options = options or SessionOptions()
    out.mkdir(parents=True, exist_ok=True)
    files: list[str] = []
    comp = write_compensation(result, out / 'compensation', units)
    files += [str(p.relative_to(out)) for p in comp]
    files.append(write_csv(result, out / 'error_motions.csv').name)
    files.append(write_location_yaml(result, out / 'location_errors.yaml').name)
    maps: dict[str, VolumetricMap] = {'linear axes': linear_map(result, tool_offset=tool_offset)}
    if result.machine.rotary_axes and any(a.rotary for a in result.axes.values()):
        maps['rotary axes'] = rotary_map(result, tool_offset=tool_offset)
    for key, vmap in maps.items():
        name = f'volumetric_{key.split()[0]}.csv'
        (out / name).write_text(vmap.csv(), encoding='utf-8')
        files.append(name)
    figs = machine_figures(result, out, maps) if figures else {}
    (out / 'machine.json').write_text(json.dumps(result.as_dict(), indent=2), encoding='utf-8')
    files.append('machine.json')
    summary = {k: {'points': int(v.magnitude.size), 'max_um': float(v.magnitude.max() * 1e6),
                   'rms_um': float(np.sqrt(np.mean(v.magnitude ** 2)) * 1e6)} for k, v in maps.items()}
    report = markdown_report(result, figs, files, separation_text(result, options), summary)
    (out / 'report.md').write_text(report, encoding='utf-8')
    return {'report': str(out / 'report.md'), 'files': files, 'figures': list(figs.values()),
            'volumetric': summary,
            'volumetric_max_um': {k: s['max_um'] for k, s in summary.items()}}
