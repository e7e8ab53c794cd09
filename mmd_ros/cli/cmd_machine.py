"""``mmd machine``: a machine tool's geometric errors from an MMD session.

    mmd machine analyze LOG... --machine FILE [--model M] [--program P] --out DIR
    mmd machine tables DIR/machine.json --out DIR [--units mm|inch]
    mmd machine volumetric DIR/machine.json --out DIR [--tool-offset-mm X Y Z]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from mmd_ros.cli.log_args import add_device_argument, log_device
from mmd_ros.core.machine import load_machine
from mmd_ros.core.model import load_model
from mmd_ros.core.progress import Progress
from mmd_ros.core.units import ARCSEC_PER_RAD
from mmd_ros.machine import (
    IdentifyOptions, SessionOptions, analyze_session, error_table, linear_map, load_program,
    load_result, rotary_map, write_compensation, write_csv, write_location_yaml, write_outputs,
)
from mmd_ros.machine.errors import MachineAnalysisError

__all__ = ['register']


def _progress(enabled: bool):
    bars: dict[str, Progress] = {}

    def tick(label: str, done: int, total: int) -> None:
        if not enabled:
            return
        bar = bars.get(label)
        if bar is None:
            bar = bars[label] = Progress(label, total)
        bar.update(done)
        if done >= total:
            bar.close()
    return tick


def _check_numbers(args: argparse.Namespace) -> None:
    """Refuse numeric options the analysis cannot use, naming the option and its value."""
    if args.draws < 2:
        raise MachineAnalysisError(f'--draws must be >= 2, got {args.draws}: every uncertainty is '
                                   'the spread of the Monte Carlo draws, which needs at least two')
    for option, value, zero in (('--limit-um', args.limit_um, False),
                                ('--limit-arcsec', args.limit_arcsec, False),
                                ('--mmd-accuracy-um', args.mmd_accuracy_um, True),
                                ('--mmd-accuracy-arcsec', args.mmd_accuracy_arcsec, True)):
        if not (math.isfinite(value) and (value >= 0 if zero else value > 0)):
            raise MachineAnalysisError(f'{option} must be a finite number '
                                       f'{">=" if zero else ">"} 0, got {value:g}')
    if not all(math.isfinite(v) and v >= 0 for v in args.rotary_components):
        raise MachineAnalysisError(f'--rotary-components must be two numbers >= 0 (µm, arc-seconds), '
                                   f'got {args.rotary_components}')


def _analyze(args: argparse.Namespace) -> int:
    _check_numbers(args)
    machine = load_machine(args.machine)
    quiet = args.json or args.quiet
    options = SessionOptions(
        model=load_model(args.model) if args.model else None, model_path=args.model,
        instrument=args.instrument,
        program=load_program(args.program, machine) if args.program else None,
        identify=IdentifyOptions(draws=args.draws, limit_m=args.limit_um * 1e-6,
                                 limit_rad=args.limit_arcsec / ARCSEC_PER_RAD,
                                 mmd_bound_m=args.mmd_accuracy_um * 1e-6,
                                 mmd_bound_rad=args.mmd_accuracy_arcsec / ARCSEC_PER_RAD,
                                 component_m=args.rotary_components[0] * 1e-6,
                                 component_rad=args.rotary_components[1] / ARCSEC_PER_RAD),
        calibration_path=args.calibration, device=log_device(args), progress=not quiet)
    result = analyze_session(args.logs, machine, options, progress=_progress(not quiet))
    written = None
    if args.out:
        written = write_outputs(result, Path(args.out), options, units=args.units,
                                figures=not args.no_figures)
    if args.json:
        data = result.as_dict()
        if written:
            data['written'] = written
        json.dump(data, sys.stdout, indent=2)
        sys.stdout.write('\n')
        return 0
    print(f'machine {machine.name}: {len(result.axes)} axis run(s) from {len(args.logs)} log(s), '
          f'instrument {result.instrument}, model {result.model_text}')
    print(error_table(result))
    nd = result.not_determined()
    if nd:
        print('not determined by this session:')
        for line in nd:
            print(f'  {line}')
    print(f'analysis took {result.seconds.get("total", 0.0):.1f} s '
          f'(poses {result.seconds.get("poses", 0.0):.1f} s, Monte Carlo {result.seconds.get("monte_carlo", 0.0):.1f} s)')
    if written:
        print(f'wrote {written["report"]}, {len(written["files"])} files and {len(written["figures"])} figures')
    return 0


def _load(path: str, machine_file: str | None):
    try:
        data = json.loads(Path(path).read_text(encoding='utf-8'))
    except OSError as exc:
        raise MachineAnalysisError(f'{path}: cannot be read: {exc.strerror}') from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MachineAnalysisError(f'{path}: not a machine.json of mmd machine analyze '
                                   f'({exc.__class__.__name__})') from None
    if not isinstance(data, dict):
        raise MachineAnalysisError(f'{path}: not a machine result (machine.json)')
    machine = load_machine(machine_file or data.get('machine_file') or '')
    return load_result(data, machine)


def _tables(args: argparse.Namespace) -> int:
    result = _load(args.result, args.machine)
    out = Path(args.out)
    files = [str(p) for p in write_compensation(result, out / 'compensation', args.units)]
    files.append(str(write_csv(result, out / 'error_motions.csv')))
    files.append(str(write_location_yaml(result, out / 'location_errors.yaml')))
    if args.json:
        json.dump({'files': files}, sys.stdout, indent=2)
        sys.stdout.write('\n')
    else:
        print('\n'.join(f'wrote {f}' for f in files))
    return 0


def _volumetric(args: argparse.Namespace) -> int:
    from mmd_ros.machine.plots import volumetric_figure  # matplotlib: only when drawing
    result = _load(args.result, args.machine)
    offset = [v * 1e-3 for v in args.tool_offset_mm]
    maps = {'linear axes': linear_map(result, points=args.points, tool_offset=offset)}
    if any(a.rotary for a in result.axes.values()):
        maps['rotary axes'] = rotary_map(result, points=args.points, tool_offset=offset)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {}
    for key, vmap in maps.items():
        stem = f'volumetric_{key.split()[0]}'
        (out / f'{stem}.csv').write_text(vmap.csv(), encoding='utf-8')
        volumetric_figure(vmap, out / f'{stem}.png', f'volumetric error, {key}')
        mag = vmap.magnitude * 1e6
        summary[key] = {'points': int(mag.size), 'max_um': float(mag.max()),
                        'rms_um': float((mag ** 2).mean() ** 0.5)}
    if args.json:
        json.dump({'tool_offset_mm': args.tool_offset_mm, 'maps': summary}, sys.stdout, indent=2)
        sys.stdout.write('\n')
    else:
        for key, s in summary.items():
            print(f'{key}: {s["points"]} points, max {s["max_um"]:.2f} µm, RMS {s["rms_um"]:.2f} µm')
        print(f'wrote {out}/volumetric_*.csv and .png')
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'machine', help='a machine tool\'s geometric errors from an MMD session',
        description='ISO 230-1 error motions and squareness of the linear axes, ISO 230-7 '
        'component and location errors of the rotary axes, each with its uncertainty; a '
        'kinematic model with the volumetric error; compensation files (LinuxCNC, CSV, YAML).',
        epilog='Definitions, signs and file formats: msg_docs/machine.md.')
    msub = p.add_subparsers(dest='machine_command', metavar='SUBCOMMAND')
    msub.required = True

    a = msub.add_parser('analyze', help='identify the errors from the logs of a session',
                        description='Find the axis runs in the logs (from the machine\'s joint '
                        'states /mmd/machine/joint_states, or a test program), evaluate every '
                        'error with its uncertainty and, with --out, write report.md, '
                        'machine.json, figures, compensation files and volumetric maps.')
    a.add_argument('logs', nargs='+', help='MCAP logs of the session (one or several runs each)')
    a.add_argument('--machine', required=True, help='machine description (e.g. machine_xyzac.yaml)')
    a.add_argument('--model', help='the MMD\'s model file (e.g. from mmd analyze); default each log\'s')
    a.add_argument('--program', help='test program (YAML or CSV) when the logs have no joint states: '
                   'one log per program run, in order')
    a.add_argument('--instrument', choices=['mmd', 'reference'], default='mmd',
                   help='the MMD (default), or the log\'s six-dimensional reference instrument')
    a.add_argument('--calibration', help='calibration file instead of the one in each log')
    add_device_argument(a)
    a.add_argument('--draws', type=int, default=200,
                   help='Monte Carlo draws, at least 2 (default 200)')
    a.add_argument('--limit-um', type=float, default=2.0, dest='limit_um',
                   help='a length error whose standard uncertainty exceeds this is "not determined" (default 2)')
    a.add_argument('--limit-arcsec', type=float, default=2.0, dest='limit_arcsec',
                   help='likewise for angles [arc-seconds] (default 2)')
    a.add_argument('--mmd-accuracy-um', type=float, default=0.0, dest='mmd_accuracy_um',
                   help='a stated accuracy of the MMD\'s position (± bound per component, e.g. its '
                   'data sheet), added to its pose covariance (default 0: the covariance alone)')
    a.add_argument('--mmd-accuracy-arcsec', type=float, default=0.0, dest='mmd_accuracy_arcsec',
                   help='likewise for its rotations [arc-seconds]')
    a.add_argument('--rotary-components', type=float, nargs=2, metavar=('UM', 'ARCSEC'),
                   default=(1.0, 1.0), dest='rotary_components',
                   help='size (RMS over a full turn) of the rotary axes\' component error motions '
                   '(radial/axial, tilt/positioning), e.g. from the table\'s acceptance test: over '
                   'a partial turn they can pass for location errors, which are uncertain by that '
                   'much (default 1 µm 1″)')
    a.add_argument('--units', choices=['mm', 'inch'], default='mm',
                   help='machine units of the LinuxCNC compensation files (default mm)')
    a.add_argument('--no-figures', action='store_true', help='skip the figures')
    a.add_argument('--out', help='folder for the report, figures and files')
    a.add_argument('--json', action='store_true', help='print the result as JSON on stdout')
    a.add_argument('--quiet', action='store_true', help='no progress on stderr')
    a.set_defaults(func=_analyze)

    t = msub.add_parser('tables', help='compensation files from a machine.json',
                        description='LinuxCNC axis compensation files (COMP_FILE_TYPE 0), the CSV '
                        'of every error motion and the location-error YAML.')
    t.add_argument('result', help='machine.json written by mmd machine analyze --out')
    t.add_argument('--machine', help='machine description (default: the one named in the result)')
    t.add_argument('--units', choices=['mm', 'inch'], default='mm')
    t.add_argument('--out', required=True, help='output folder')
    t.add_argument('--json', action='store_true')
    t.set_defaults(func=_tables)

    v = msub.add_parser('volumetric', help='volumetric error maps from a machine.json',
                        description='The tool tip\'s error against the workpiece over the measured '
                        'ranges: a grid of the linear axes, and of the rotary axes with the linear '
                        'axes following.')
    v.add_argument('result', help='machine.json written by mmd machine analyze --out')
    v.add_argument('--machine', help='machine description (default: the one named in the result)')
    v.add_argument('--tool-offset-mm', type=float, nargs=3, default=[0.0, 0.0, 0.0],
                   dest='tool_offset_mm', metavar=('X', 'Y', 'Z'),
                   help='tool tip relative to the MMD\'s functional point, spindle frame [mm]')
    v.add_argument('--points', type=int, default=9, help='grid points per axis (default 9)')
    v.add_argument('--out', required=True, help='output folder')
    v.add_argument('--json', action='store_true')
    v.set_defaults(func=_volumetric)
