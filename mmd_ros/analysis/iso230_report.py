"""ISO 230-2 evaluation of one axis of a logged run, for the MMD under one or more models, the
reference instrument and their difference (``mmd iso230-2``, the demo)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from mmd_ros.analysis.data import run_pipeline
from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.iso230 import (
    AXIS_NAMES, FIGURE_LABELS, FIGURES, IsoResult, axis_index, evaluate_run, figure_table,
    target_table,
)
from mmd_ros.core.calibration import calibration_for, load_calibration
from mmd_ros.core.model import Model
from mmd_ros.core.units import M_PER_MM
from mmd_ros.logs.layout import RunLog

__all__ = ['INSTRUMENTS', 'Iso230Report', 'fitted_runs', 'iso230_of_run', 'parse_targets']

INSTRUMENTS = ('mmd', 'reference', 'error')


class Iso230Report:
    """Results of one log or table: per instrument (and per model) an :class:`IsoResult`.

    models : label -> description of each result compared with the reference (the MMD under
        each model, or the instruments of a table); their rows get the "− reference figures"
        rows of Tables 3–4
    source : what the results were read from ('mcap', or 'csv (... layout)')
    log_problem : what was lost reading the log (``LogProblem.as_dict``), or None
    in_sample : label -> whether that model was fitted on this very run
    """

    def __init__(self, log: str, axis: str, results: dict[str, IsoResult], models: dict[str, str],
                 source: str = 'mcap', log_problem: dict[str, Any] | None = None,
                 in_sample: dict[str, bool] | None = None) -> None:
        self.log, self.axis, self.results, self.models = log, axis, results, models
        self.source = source
        self.log_problem = log_problem
        self.in_sample = in_sample or {}

    def sample_note(self) -> str:
        """Whether the models were fitted on this run (then the figures are in-sample)."""
        inside = [label for label, v in self.in_sample.items() if v]
        if not inside:
            return ''
        return ('IN-SAMPLE: ' + ', '.join(inside) + (' was' if len(inside) == 1 else ' were')
                + ' fitted on this very run (its model file names the run by the hash of its raw '
                'counts); these figures do not show how the model does on other runs. Evaluate a '
                'run the model was not fitted on.')

    @property
    def unit(self) -> str:
        return next(iter(self.results.values())).unit

    def rows(self) -> list[tuple[str, dict[str, float]]]:
        """Table rows: each instrument, and the paper's 'MMD - reference' deviation of the
        figures (Tables 3–4) for each MMD row."""
        rows = [(name if name in self.models or name == 'reference' else f'{name} (per sample)',
                 r.figures_report()) for name, r in self.results.items()]
        ref = self.results.get('reference')
        if ref is not None:
            rf = ref.figures_report()
            for name, r in self.results.items():
                if name in self.models:
                    f = r.figures_report()
                    rows.append((f'{name} − reference figures', {k: f[k] - rf[k] for k in f}))
        return rows

    def as_dict(self) -> dict[str, Any]:
        return {'log': self.log, 'source': self.source, 'log_problem': self.log_problem,
                'axis': self.axis, 'unit': self.unit,
                'models': self.models, 'in_sample': self.in_sample, 'sample_note': self.sample_note(),
                'results': {k: v.as_dict() for k, v in self.results.items()},
                'table': [{'row': n, **{k: (None if not math.isfinite(v) else v) for k, v in f.items()}}
                          for n, f in self.rows()]}

    def markdown(self, figures: dict[str, str] | None = None) -> str:
        what = 'Log' if self.source == 'mcap' else 'Table'
        tail = '' if self.source == 'mcap' else f' ({self.source})'
        lines = [f'# ISO 230-2 evaluation of axis {self.axis}', '', f'{what}: `{self.log}`{tail}', '']
        if self.log_problem:
            lines += [f'**The log was not read whole:** {self.log_problem["message"]}', '']
        if self.sample_note():
            lines += [f'**{self.sample_note()}**', '']
        for tag, text in self.models.items():
            lines.append(f'- {tag}: {text}')
        lines += ['', '## Axis figures (the paper\'s Tables 3–4)', '',
                  figure_table(self.rows(), self.unit, markdown=True), '',
                  '## All figures', '',
                  figure_table(self.rows(), self.unit, markdown=True,
                               figures=[(k, FIGURE_LABELS[k]) for k in FIGURES]), '']
        for name, r in self.results.items():
            lines += [f'## {name}: per target (n = {r.n} approaches per direction)', '',
                      target_table(r, markdown=True), '']
            if figures and name in figures:
                lines += [f'![{name}]({figures[name]})', '']
        return '\n'.join(lines)


def iso230_of_run(run: RunLog, axis: str | None = None, models: dict[str, Model] | None = None, *,
                  instruments: tuple[str, ...] = INSTRUMENTS, targets: np.ndarray | None = None,
                  min_dwell_s: float = 0.15, calibration_path: str | None = None,
                  progress: Callable[[float], None] | None = None) -> Iso230Report:
    """ISO 230-2 of one axis of a run, for the MMD under each model and the reference.

    models : label -> model (default: the log's, else CDF + thermal) — e.g. before and after
    targets : target positions [m or rad]; default the log's ``iso_targets``, else clustered
    progress : called with the fraction (0..1) of the MMD processing done
    """
    meta = run.metadata.get('iso_targets') or {}
    axis = axis or meta.get('axis')
    if not axis:
        raise AnalysisError(f'{run.path} does not say which axis was tested; pass --axis')
    k = axis_index(axis)
    if targets is None and meta.get('positions') and axis_index(str(meta.get('axis'))) == k:
        targets = np.asarray(meta['positions'], dtype=np.float64)
    calibration = calibration_for(run.calibration, load_calibration(calibration_path)
                                  if calibration_path else None, str(run.path))
    ref = None
    if run.reference_pose is not None and np.isfinite(run.reference_pose[:, k]).mean() > 0.5:
        ref = run.reference_pose[:, k]
    models = models or {'MMD': run.model or Model()}
    signals: dict[str, np.ndarray] = {}
    total = max(1, len(models) * run.times_s.size)
    for number, (label, model) in enumerate(models.items()):
        done = number * run.times_s.size
        tick = None if progress is None else (lambda n, done=done: progress((done + n) / total))
        proc = run_pipeline(run.device, calibration, model, run.times_s, run.counts, progress=tick,
                            status=run.status)
        pose = np.where(proc.valid, proc.poses[:, k], np.nan)
        if 'mmd' in instruments:
            signals[label] = pose
        if 'error' in instruments and ref is not None:
            signals[f'{label} - reference'] = pose - ref  # evaluated as a deviation itself
    if 'reference' in instruments and ref is not None:
        signals['reference'] = ref
    if not signals:
        raise AnalysisError('nothing to evaluate: the log has no reference for the error or '
                            'reference instruments')
    detect = ref if ref is not None else next(iter(signals.values()))
    results = evaluate_run(run.times_s, AXIS_NAMES[k], signals, detect, targets, min_dwell_s=min_dwell_s)
    texts = {label: f'{len(m.terms)} term(s): {", ".join(t.type_name for t in m.terms) or "CDF + thermal only"}'
             for label, m in models.items()}
    ident = run.content_hash()
    in_sample = {label: ident in fitted_runs(m) for label, m in models.items()}
    for label, inside in in_sample.items():
        texts[label] += ' (fitted on this run: in-sample)' if inside else (
            ' (not fitted on this run)' if fitted_runs(models[label]) else '')
    return Iso230Report(str(run.path), AXIS_NAMES[k], results, texts, in_sample=in_sample,
                        log_problem=run.problem.as_dict() if run.problem else None)


def fitted_runs(model: Model) -> set[str]:
    """Content hashes of the runs a model was fitted on (its ``validity`` record; empty for a
    model that no analysis wrote)."""
    validity = model.extra.get('validity')
    if not isinstance(validity, dict):
        return set()
    return {str(r.get('ident')) for r in validity.get('runs') or [] if isinstance(r, dict) and r.get('ident')}


def parse_targets(text: str | None, axis: str) -> np.ndarray | None:
    """Target positions given as text (comma separated, mm or degrees) in SI, or None."""
    if not text:
        return None
    try:
        values = np.array([float(v) for v in text.split(',') if v.strip()])
    except ValueError:
        values = np.array([np.nan])
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise AnalysisError(f'--targets must be finite numbers separated by commas, got {text!r}')
    return np.radians(values) if axis_index(axis) >= 3 else values * M_PER_MM
