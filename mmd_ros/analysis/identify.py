"""Close the loop: find the residual, trace it to an effect the model lacks, add the effect and
measure the error before and after (documented for users in msg_docs/analysis.md).

The input is a session: one or more logs of one device (an x-axis laser run, a y run, a rotary
run, a 6-DOF run...), each with its own reference (pose components or bar lengths), its own
datum offsets and its own calibration.

1. Residual. The current model runs over each log (the live pipeline); the residual is MMD
   minus reference in the reference's observation space (:mod:`mmd_ros.analysis.data`).
2. Trace. Each log's usable samples are cut into time blocks; of each pair of blocks one
   (drawn) is held out. Each catalogued effect (:mod:`mmd_ros.analysis.effects`) is linear in
   its parameters: its length signature is mapped into each log's observation space with the
   pose Jacobian (J^-1, only the known components) and weighted by that log's noise floor; the
   rows of all logs are fitted together (parameters of the device shared; parameters that
   belong to a calibration or a run, one set per calibration or run). Its columns are projected
   off what is already in the model (datum offsets per log, effects added before); directions
   with a singular value below ``rcond`` (unit-norm columns) cannot be separated, directions
   whose estimate is below ``min_t_param`` standard deviations are not determined by the data:
   both are reported, not fitted. With a zeroed reference a term of free constants (CDF
   points, harmonics, joint coordinates, a drift) is also held to move the mean of no component
   over a log further than the budget claims for it: the reference cannot see that mean.
   Least squares on the training blocks; judged on the held-out blocks. Stepwise: an effect
   passes when it lowers the held-out RMS by at least ``min_gain`` (and ``min_floor_gain`` of
   the noise floor), the gain is consistent over the held-out blocks
   (t >= ``min_t``) and the held-out information criterion falls by at least ``min_delta_ic``
   (its effective sample count the baseline residual's, one for every candidate of a step;
   when none passes, that of the residual the step's best candidate leaves, if more: the
   baseline holds the error being tested, whose own correlation is not the noise's).
   Nothing is added once the held-out residual is at the noise floor. Of those that pass, the
   one with the fewest identified parameters that removes at least ``parsimony`` of what the
   best removes is added.
3. Claims. An added effect must remove at least 1 - ``claim_ratio`` of the structure along its
   own coordinate; one that fits only part of a structure is not claimed and not kept.
4. Whole pose. An effect goes into the written model only when what it does to the pose
   components no reference saw is determined by the data, or stays below their noise floor
   (:func:`_unchecked`); otherwise it is reported and left out (``accept_unchecked`` keeps it).
5. Add. The effects kept become model terms; the extended model is validated by running the
   real pipeline again over every log (the "after" numbers). With two or more logs each log is
   also predicted by the model fitted on the others (leave-one-run-out): the headline figure.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from mmd_ros.analysis.axis_motion import AxisMotion, axis_motion
from mmd_ros.analysis.data import (
    FitContext, Observation, Processed, Split, binned_r2, effective_samples, fit_lag,
    make_observation, make_split, noise_floor, observed_motion, quantisation_floor,
    reference_noise, report_factors, residual_features, run_pipeline, sample_noise,
)
from mmd_ros.analysis.effects import CATALOGUE, Effect, Parameter, catalogue
from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.glitches import Step, bar_residual, residual_steps
from mmd_ros.analysis.uncertainty import (
    CLAIM_LEVEL, FittedEffect, ResidualRun, base_budget, beyond_claim, claimed_sigma,
    fitted_effects, measured_read_noise, calibration_constants, with_fit_uncertainty)
from mmd_ros.core.accuracy import (ABSOLUTE_WITHIN_SIGMAS, GROSS_ERROR, ReferenceScale,
                                   read_datum)
from mmd_ros.core.budget import LENGTH_TERMS, SAG_TERMS
from mmd_ros.core.calibration import Calibration, calibration_for
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.lag import (
    LAG_SAMPLES, ReferenceLag, is_reference_lag, paired_rows,
)
from mmd_ros.core.model import Model, ModelTerm, TermContext
from mmd_ros.core.terms import GravitySagTerm, SamplingSkewTerm, limited_to_seen
from mmd_ros.core.units import ARCSEC_PER_RAD, M_PER_MM, M_PER_UM
from mmd_ros.logs.layout import RunLog, stated_absolute

__all__ = ['Analysis', 'AnalysisOptions', 'Candidate', 'ComponentError', 'Found', 'RunSummary',
           'Unchecked', 'analyze', 'component_errors']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

POSE_NAMES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
#: Samples per log at which an effect's consequence on unobserved components is evaluated.
CONSEQUENCE_SAMPLES = 600
#: Relative step of the central difference of an effect's correction in a continuous setting
#: (a 13 µm period's step turns the phase by 0.008 cycle 100 mm of scale away).
SETTING_STEP = 1e-6


@dataclass
class AnalysisOptions:
    """Settings of :func:`analyze` (defaults documented in msg_docs/analysis.md)."""

    effects: list[str] | None = None
    exclude: tuple[str, ...] = ()
    n_blocks: int = 40
    max_samples: int = 2500
    min_gain: float = 0.05
    min_floor_gain: float = 0.1
    min_t: float = 3.0
    min_delta_ic: float = 10.0
    max_effects: int = 6
    rcond: float = 1e-3
    min_t_param: float = 2.0
    parsimony: float = 0.9
    floor_factor: float = 1.5
    claim_ratio: float = 0.35
    datum: str = 'auto'
    seed: int = 0
    cyclic_periods_m: tuple[float, ...] | None = None
    accept_unchecked: bool = False
    leave_one_out: bool = True
    #: start from the bars' gravity sag the device description states, when the model has no
    #: sag term (the figures "before" then include it; the model as given is reported apart)
    stated_sag: bool = True
    under_claim: float = 1.25
    #: a one-axis run's unseen components read as the machine's motion (analysis/axis_motion.py)
    axis_motion: bool = True
    #: whose clock every log's reference ran on, 'shared' or 'own', over what the logs say
    #: (their metadata ``reference_clock``); None: as they say (:func:`_reference_lag`)
    reference_clock: str | None = None
    #: the most samples the analysis holds over all its logs: logs longer together are read at
    #: every k-th sample, k the smallest that keeps them within it (:func:`_thinned`)
    max_log_samples: int = 1_200_000


@dataclass
class Candidate:
    """One effect tested at one step of the selection."""

    effect: str
    title: str
    hyper: Any
    hyper_label: str
    n_params: int
    n_identifiable: int
    unidentifiable: list[str]
    note: str
    rms_ratio: float = math.nan      # held-out RMS with the effect / without (whitened)
    gain: float = math.nan           # 1 - rms_ratio
    delta_ic: float = math.nan
    t_stat: float = math.nan
    n_eff: float = math.nan
    #: the effective independent samples of the held-out residual the effect leaves
    n_left: float = math.nan
    verdict: str = ''
    mse0: float = math.nan           # held-out mean square (whitened) before / with the effect
    mse1: float = math.nan
    basis: FloatArray | None = field(default=None, repr=False)  # (P, r): reduced -> parameters
    norms: FloatArray | None = field(default=None, repr=False)  # (P,): column norms of the fit
    #: directions dropped as within 2 sigma of zero, (P, w) in unit-norm scale, and their sigma
    weak: tuple[FloatArray, FloatArray] | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k not in ('basis', 'hyper', 'norms', 'weak')}
        out['hyper'] = self.hyper
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}


@dataclass
class Unchecked:
    """What an effect would do to a pose component that no reference determines."""

    effect: str
    run: str
    component: str
    unit: str
    change: float         # RMS change of the component over the run's samples [report unit]
    uncertainty: float    # its 1-sigma uncertainty, RMS there, undetermined directions included
    floor: float          # the component's noise floor [report unit]
    largest: float        # the largest change at one sample [report unit]
    #: the other logs whose references see the component (they do not determine this change)
    seen_by: list[str] = field(default_factory=list)
    #: the parameters most of the uncertainty comes from, largest first
    mostly_from: list[str] = field(default_factory=list)

    def message(self) -> str:
        u = _unit(self.unit)
        text = (f'found in {self.run}; would change {self.component} by {self.change:.3g} {u} '
                f'RMS, up to {self.largest:.3g} {u} (± {self.uncertainty:.2g} {u} RMS with what '
                f'the data leave undetermined, floor {self.floor:.2g} {u}), which ')
        source = (f' (its uncertainty mostly from {", ".join(self.mostly_from)})'
                  if self.mostly_from else '')
        if self.seen_by:
            logs = (self.seen_by[0] + ' sees' if len(self.seen_by) == 1 else
                    ', '.join(self.seen_by[:-1]) + f' and {self.seen_by[-1]} see')
            return (text + f'{logs} but do{"es" if len(self.seen_by) == 1 else ""} not '
                    f'determine where {self.run} goes{source}; record a run that sees '
                    f'{self.component} there')
        return text + f'these runs cannot check{source}; record a run that sees {self.component}'

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, 'message': self.message()}


@dataclass
class Found:
    """An effect added to the model, with its fitted parameters."""

    effect: str
    title: str
    term_type: str
    hyper: Any
    hyper_label: str
    parameters: list[Parameter]
    value: FloatArray
    sigma: FloatArray
    identifiable: NDArray[np.bool_]
    step_gain: float
    interpretation: list[str]
    explained: float = math.nan
    claimed: bool = True
    reason: str = ''
    unchecked: list[Unchecked] = field(default_factory=list)
    covariance: FloatArray | None = None  # (P, P) of the parameters [SI], the setting held
    #: a continuous setting one sigma away and the parameters that go with it (or None)
    setting_shift: tuple[Any, FloatArray] | None = None
    #: a form of the effect the data could not rule out (``Effect.undetermined_forms``)
    alternatives: list[Any] = field(default_factory=list)

    def parameter_rows(self) -> list[dict[str, Any]]:
        rows = []
        for p, v, s, ok in zip(self.parameters, self.value, self.sigma, self.identifiable):
            rows.append({'name': p.name, 'unit': p.unit, 'value': float(v * p.factor),
                         'ci95': float(1.96 * s * abs(p.factor)) if ok else None,
                         'identifiable': bool(ok)})
        return rows

    def as_dict(self) -> dict[str, Any]:
        return {'effect': self.effect, 'title': self.title, 'term': self.term_type,
                'hyper': self.hyper_label, 'parameters': self.parameter_rows(),
                'held_out_gain_at_step': self.step_gain, 'explained': self.explained,
                'claimed': self.claimed, 'reason': self.reason, 'interpretation': self.interpretation,
                'unchecked': [u.as_dict() for u in self.unchecked]}


@dataclass(frozen=True)
class ComponentError:
    """Error statistics of one observed component on some samples, in report units."""

    name: str
    unit: str
    n: int
    rms: float
    max_abs: float
    mean: float
    std: float

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def component_errors(obs: Observation, residual: FloatArray, idx: IntArray) -> list[ComponentError]:
    """Per-component and overall (per unit) statistics of ``residual`` at samples ``idx``."""
    r = residual[idx] * obs.to_report
    out = []
    for k, (name, unit) in enumerate(zip(obs.names, obs.units)):
        v = r[:, k][np.isfinite(r[:, k])]
        if v.size:
            out.append(ComponentError(name, unit, int(v.size), float(np.sqrt(np.mean(v * v))),
                                      float(np.max(np.abs(v))), float(v.mean()), float(v.std())))
    for unit in sorted(set(obs.units)):
        cols = [k for k, u in enumerate(obs.units) if u == unit]
        if len(cols) > 1:
            v = r[:, cols]
            v = v[np.all(np.isfinite(v), axis=1)]
            out.append(ComponentError(f'overall ({unit})', unit, int(v.size),
                                      float(np.sqrt(np.mean(v * v))), float(np.max(np.abs(v))),
                                      float(v.mean()), float(v.std())))
    return out


@dataclass
class RunSummary:
    """One log of the session: its reference, noise floor and errors before and after.

    before, after : held-out time blocks of this run, the model fitted on every run
    loro_before, loro_after : the whole run, the model fitted on the other runs only
        (leave-one-run-out; None with a single run)
    """

    name: str
    ident: str
    calibration: str
    reference: str
    components: list[str]
    units: list[str]
    samples: int
    floor: dict[str, float]
    before: list[ComponentError]
    after: list[ComponentError] | None = None
    loro_before: list[ComponentError] | None = None
    loro_after: list[ComponentError] | None = None
    loro_note: str = ''
    #: the leave-one-run-out "after" on the samples whose six bar lengths all lie within the
    #: lengths the other runs covered (the range the model written from them is valid for),
    #: and the share of the run's samples there
    loro_in_range: list[ComponentError] | None = None
    loro_in_range_share: float | None = None
    log_problem: dict[str, Any] | None = None  # what was lost reading this log (LogProblem.as_dict)
    #: held-out blocks, the model as given: without the stated terms the analysis started from
    #: (None when it started from none; ``before`` includes them)
    given: list[ComponentError] | None = None
    #: the reference's lag behind the MMD, when taken as the reference's (else None)
    lag: ReferenceLag | None = None
    #: whether the reference was compared zeroed or absolute, and why
    datum: ReferenceDatum | None = None

    def as_dict(self) -> dict[str, Any]:
        def rows(stats: list[ComponentError] | None) -> list[dict[str, Any]] | None:
            return [s.as_dict() for s in stats] if stats is not None else None
        return {'log': self.name, 'ident': self.ident, 'calibration': self.calibration,
                'reference': self.reference, 'components': self.components, 'units': self.units,
                'samples': self.samples, 'noise_floor': self.floor,
                'held_out_as_given': rows(self.given), 'held_out_before': rows(self.before),
                'held_out_after': rows(self.after),
                'leave_one_run_out_before': rows(self.loro_before),
                'leave_one_run_out_after': rows(self.loro_after), 'leave_one_run_out_note': self.loro_note,
                'leave_one_run_out_after_in_range': rows(self.loro_in_range),
                'leave_one_run_out_in_range_share': self.loro_in_range_share,
                'log_problem': self.log_problem,
                'reference_lag': None if self.lag is None else self.lag.as_dict(),
                'reference_datum': None if self.datum is None else self.datum.as_dict()}


@dataclass
class Analysis:
    """Everything :func:`analyze` found; :mod:`mmd_ros.analysis.report` writes it out.

    The per-sample fields (obs, split, times_s, floor, before, residuals, features, stats) are
    those of the first log (figures); ``runs`` has every log's figures.
    """

    log: str
    options: AnalysisOptions
    obs: Observation
    split: Split
    times_s: FloatArray
    floor: FloatArray
    before: Processed
    after: Processed | None
    residual_before: FloatArray
    residual_after: FloatArray | None
    steps: list[list[Candidate]]
    found: list[Found]
    not_claimed: list[Found]
    stats_before: list[ComponentError]
    stats_after: list[ComponentError] | None
    stats_predicted: list[ComponentError] | None
    structure_before: list[tuple[str, float]]
    structure_after: list[tuple[str, float]]
    at_floor: bool
    validated: bool
    model: Model | None
    conclusion: str
    features: dict[str, FloatArray] = field(repr=False, default_factory=dict)
    contributions: dict[str, FloatArray] = field(repr=False, default_factory=dict)
    per_bar_before: list[ComponentError] | None = None
    per_bar_after: list[ComponentError] | None = None
    seconds: float = 0.0
    not_applicable: dict[str, str] = field(default_factory=dict)
    runs: list[RunSummary] = field(default_factory=list)
    unchecked: list[Found] = field(default_factory=list)
    validation: str = ''
    log_problem: dict[str, Any] | None = None  # the first log not read whole (LogProblem.as_dict)
    #: nothing found, but the residual (or the read noise where bars stood still) beyond what the
    #: budget claims: the model written carries it as an uncertainty only (why, as text; '' else)
    uncertainty_only: str = ''
    #: what the analysis started from beyond the model as given: effects the device description
    #: states (the bars' gravity sag), one line each; not fitted, written with a written model
    stated: list[str] = field(default_factory=list)
    #: what the data say of the stated sag: its error's estimate and sigma [nm] (None when the
    #: data do not exercise the bars' inclination), the figure's stated uncertainty [nm] (or
    #: None), whether the data dispute it, and the sigma claimed with the model
    #: (:func:`_check_statement`); None when the analysis started from no statement
    stated_check: dict[str, Any] | None = None
    #: steps in a bar's residual (counts lost or gained), per log: (log name, step)
    glitches: list[tuple[str, Step]] = field(default_factory=list)
    #: the logs were analysed at every k-th sample (:attr:`AnalysisOptions.max_log_samples`)
    every: int = 1
    #: their samples as recorded, over all the logs
    recorded_samples: int = 0

    @property
    def changed(self) -> bool:
        return self.model is not None

    def as_dict(self) -> dict[str, Any]:
        floor = {n: float(f * s) for n, f, s in zip(self.obs.names, self.floor, self.obs.to_report)}
        return {
            'log': self.log,
            'logs': [r.name for r in self.runs],
            'validation': self.validation,
            'reference': {'kind': self.obs.kind, 'components': self.obs.names,
                          'units': self.obs.units, 'datum_offset_removed': self.obs.datum,
                          'description': self.obs.description},
            'samples': {'total': int(self.times_s.size),
                        'analysed_every': self.every, 'recorded_in_all_logs': self.recorded_samples,
                        'usable': int(self.split.train_idx.size + self.split.test_idx.size),
                        'train': int(self.split.train_idx.size), 'held_out': int(self.split.test_idx.size),
                        'blocks': self.split.n_blocks},
            'noise_floor': floor,
            'before': [s.as_dict() for s in self.stats_before],
            'before_per_bar': [s.as_dict() for s in self.per_bar_before] if self.per_bar_before else None,
            'structure_before': [{'feature': f, 'r2': r} for f, r in self.structure_before],
            'steps': [[c.as_dict() for c in step] for step in self.steps],
            'not_applicable': self.not_applicable,
            'found': [f.as_dict() for f in self.found],
            'not_claimed': [f.as_dict() for f in self.not_claimed],
            'unchecked': [f.as_dict() for f in self.unchecked],
            'after': [s.as_dict() for s in self.stats_after] if self.stats_after else None,
            'after_per_bar': [s.as_dict() for s in self.per_bar_after] if self.per_bar_after else None,
            'predicted_after': [s.as_dict() for s in self.stats_predicted] if self.stats_predicted else None,
            'runs': [r.as_dict() for r in self.runs],
            'validated_with_pipeline': self.validated,
            'remaining': {'at_noise_floor': self.at_floor,
                          'structure': [{'feature': f, 'r2': r} for f, r in self.structure_after]},
            'model_changed': self.changed,
            'uncertainty_only': self.uncertainty_only or None,
            'stated': self.stated,
            'stated_check': self.stated_check,
            'reading_steps': [{'log': log, **step.as_dict()} for log, step in self.glitches],
            'conclusion': self.conclusion,
            'seconds': self.seconds,
            'options': {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.options.__dict__.items()},
            'log_problem': self.log_problem,
        }


# -- one log of the session ----------------------------------------------------------------------
@dataclass
class _Run:
    """A log prepared for the analysis."""

    index: int
    run: RunLog
    name: str
    ident: str
    cal_key: str
    calibration: Calibration
    obs: Observation
    ctx: FitContext
    split: Split
    floor: FloatArray
    raw: FloatArray          # MMD - reference, NaN-free (zeros where not usable)
    res_before: FloatArray   # NaN where not usable, datum removed (training mean)
    usable: NDArray[np.bool_]
    #: with a zeroed reference, the budget's sigma of each observed component (k,) [m, rad]:
    #: how far the fit may move a component's mean, which the reference cannot see
    datum_sigma: FloatArray | None = None
    #: a one-axis run's unseen pose components, read as the machine's motion along its axis
    axis: AxisMotion | None = None
    #: the residual of the model as given, without the stated terms (``res_before`` when none)
    res_given: FloatArray | None = None
    #: the reference's lag behind the MMD, when it is taken as the reference's
    lag: ReferenceLag | None = None
    #: whether the reference is compared zeroed or absolute, and why
    datum: ReferenceDatum | None = None

    def group(self, scope: str) -> str:
        return {'device': 'device', 'calibration': self.cal_key, 'run': self.ident}[scope]


def calibration_key(calibration: Calibration) -> str:
    """Identity of a calibration: a hash of its file contents (12 hex digits)."""
    return calibration.key()


def _check_one_device(runs: list[RunLog]) -> None:
    first = runs[0]
    for run in runs[1:]:
        a, b = first.device, run.device
        same = (a.name == b.name and a.channel_names == b.channel_names
                and np.allclose(a.geometry.upper, b.geometry.upper, atol=1e-9)
                and np.allclose(a.geometry.lower, b.geometry.lower, atol=1e-9))
        if not same:
            raise AnalysisError(f'{run.path} is a log of device {b.name!r} and {first.path} of '
                                f'{a.name!r} (or their joints differ): one analysis takes logs of '
                                'one device; analyse each device on its own')
        # two MMDs of one description differ by their terminals (the channels' delays are the
        # terminal's): the serial numbers their calibrations were made with, where both say
        ta, tb = (None if r.calibration is None else r.calibration.terminal for r in (first, run))
        if ta is not None and tb is not None and ta.serial and tb.serial and ta.serial != tb.serial:
            raise AnalysisError(f'{run.path} was calibrated with {tb.describe()} and {first.path} '
                                f'with {ta.describe()}: one analysis takes logs of one device '
                                '(its terminal\'s channel delays are among what it fits); '
                                'analyse each device on its own')


def _prepare(index: int, run: RunLog, model: Model, calibration: Calibration | None,
             o: AnalysisOptions, say: Callable[[str], None], datum: ReferenceDatum,
             stated: tuple[ModelTerm, ...] = (), before: Processed | None = None) -> _Run:
    """One log made ready for the selection; ``before`` the pass of ``model`` over it, when
    made already."""
    calibration = calibration or run.calibration
    if calibration is None:
        raise AnalysisError(f'{run.path} carries no calibration; pass --calibration FILE')
    if run.counts.shape[0] == 0:
        raise AnalysisError(f'{run.path} has no samples')
    unreadable = int(run.unreadable.sum())
    if unreadable:     # (they poison every signature that follows the motion)
        raise AnalysisError(f'{run.path}: {unreadable} sample(s) with a count that is not a '
                            'number; leave them out first (RunLog.without_flagged, as mmd '
                            'analyze does)')
    try:
        obs = make_observation(run.reference_pose, run.reference_lengths, datum.datum,
                               run.metadata.get('reference_sigma'),
                               o.reference_clock or run.metadata.get('reference_clock'))
    except AnalysisError as exc:
        raise AnalysisError(f'{run.path}: {exc}') from None
    times = run.times_s
    if before is None:
        say(f'{run.path.name}: running the current model over {times.size} samples')
        before = run_pipeline(run.device, calibration, model, times, run.counts)
    if run.reference_pose is not None:     # (a reference in mm or degrees fits nothing true)
        scale = ReferenceScale()
        scale.add(before.poses, run.reference_pose, before.measured('pose'))
        blunder = scale.text()
        if blunder:
            raise AnalysisError(f'{run.path}: {blunder}. Correct the reference in a copy of the '
                                'log first')
    obs, lag = _reference_lag(obs, run.device, before, times)
    if lag is not None:
        say(f'{run.path.name}: {lag.text(LAG_TAKEN)}')
    usable = obs.usable & before.measured(obs.kind)
    try:
        split = make_split(times, usable, o.n_blocks, o.max_samples, o.seed + index)
    except AnalysisError as exc:
        raise AnalysisError(f'{run.path}: {exc}') from None
    raw = obs.residual(before)
    if obs.sigma is None:
        obs = replace(obs, sigma=reference_noise(obs, before, raw, split.train_idx), sigma_estimated=True)
    ctx = FitContext(run.device, calibration, model, times, run.counts, before, obs, o,
                     epoch_s=run.epoch_s)
    res_before = _datum_corrected(obs, raw, before.measured(obs.kind), split.train_idx)
    floor = noise_floor(obs, run.device, before, np.nan_to_num(res_before), split.train_idx, ctx.thermal_on)
    floor = np.maximum(floor, 1e-12)
    ctx.residual, ctx.floor, ctx.train_idx = res_before, floor, split.train_idx
    datum_sigma = np.maximum(claimed_sigma(ctx, split.fit_train), 1e-12) if obs.datum else None
    axis = None
    if o.axis_motion and obs.kind == 'pose' and len(obs.components) == 1:
        c = obs.components[0]
        axis = axis_motion(before.poses, obs.reference[:, 0], c, times, usable,
                           _pose_floor(ctx, split.train_idx))
    given = None
    if stated:
        change = _stated_change(run.device, before, stated, obs)
        given = _datum_corrected(obs, raw - change, before.measured(obs.kind), split.train_idx)
    return _Run(index, run, str(run.path), run.content_hash(), calibration_key(calibration),
                calibration, obs, ctx, split, floor, np.nan_to_num(raw), res_before, usable, datum_sigma,
                axis, res_given=given, lag=lag, datum=datum)


#: What the analysis does with a reference's lag
LAG_TAKEN = 'fitted per log beside the effects and taken out of every figure'
#: A reference's lag left to the nuisance (after pairing samples) from which its second order,
#: the acceleration's, is fitted too [s]
SECOND_ORDER_LAG_S = 2e-4


def _reference_lag(obs: Observation, device: DeviceDescription, processed: Processed,
                   times_s: FloatArray) -> tuple[Observation, ReferenceLag | None]:
    """The observation with the reference's lag behind the MMD taken as a nuisance of the
    log (``Observation.lag``), when it is the reference's: the log says that its reference
    runs on a clock of its own, or, not saying, the common delay between the two is beyond
    what the MMD's channels can latch (:func:`~mmd_ros.core.lag.is_reference_lag`). A common
    delay within that is the MMD's (the skew term's common mode): a reference sampled at the
    MMD's instants has none, and the twin's logs say ``reference_clock: shared``. A reference
    on its own clock 10 µs late had a common skew of 10 µs written, and the model made new
    motion 2.7-18 times worse against the true pose; 5 ms late, no skew could hold it, and a
    false 230 µm step and an uncertainty of 2000-10000 times the error were reported.

    A delay of a sample period or more is taken out by pairing each MMD sample with the
    reference's that many samples later (no interpolation: the reference's noise stays as
    stated), the rest (within half a period) by the nuisance: the velocity, and from
    :data:`SECOND_ORDER_LAG_S` on, smoothed, and the acceleration too (:func:`observed_motion`;
    2.6 ms late at 200 Hz, a rest of 2.4 ms with the backward difference's velocity alone left
    x 0.067 µm of held-out residual against a floor of 0.046, now 0.035 against 0.038)."""
    if obs.clock == 'shared':
        return obs, None
    # (whether there is a lag to take, from evenly spread samples: the inverse Jacobians of a
    # 10-minute 1 kHz log took 3.3 s)
    every = np.flatnonzero(obs.usable & processed.measured(obs.kind))
    few = every[np.unique(np.linspace(0, every.size - 1, min(every.size, LAG_SAMPLES))
                          .astype(np.int64))] if every.size else every
    seen = replace(obs, reference=obs.reference[few], usable=obs.usable[few],
                   lag=observed_motion(obs, device, processed, times_s, False, few))
    coef, sd, _ = fit_lag(seen, obs.residual(processed)[few], np.arange(few.size))
    delay = float(coef[0])
    if not is_reference_lag(delay, sd, obs.clock):
        return obs, None
    timed = replace(obs, lag=observed_motion(obs, device, processed, times_s, False))
    period = float(np.median(np.diff(times_s))) if times_s.size > 1 else 0.0
    shift = int(round(delay / period)) if period > 0 else 0
    if shift:
        timed = _shifted(timed, times_s, shift, period)
    if abs(delay - shift * period) >= SECOND_ORDER_LAG_S:
        motion = observed_motion(obs, device, processed, times_s, True)
        known = np.all(np.isfinite(motion), axis=(1, 2))
        timed = replace(timed, lag=np.nan_to_num(motion), usable=timed.usable & known)
    every = np.flatnonzero(timed.usable & processed.measured(obs.kind))
    coef, sd, _ = fit_lag(timed, timed.residual(processed), every)
    delay = shift * period + float(coef[0])
    return timed, ReferenceLag(delay, sd, obs.clock == 'own', shift * period)


def _shifted(obs: Observation, times_s: FloatArray, shift: int, period: float) -> Observation:
    """The observation with each sample's reference taken ``shift`` samples later (earlier
    when negative): where the two samples are not ``shift`` periods apart (a gap, the log's
    ends) the reference is unknown (:func:`~mmd_ros.core.lag.paired_rows`)."""
    src, ok = paired_rows(times_s, shift, period)
    reference = np.where(ok[:, None], obs.reference[src], np.nan)
    return replace(obs, reference=reference, usable=ok & obs.usable[src])


@dataclass
class ReferenceDatum:
    """Whether a log's reference is compared absolute or zeroed (an offset per component
    removed), and why.

    source : 'option' (AnalysisOptions.datum, ``mmd analyze --absolute-reference`` or
        ``--zeroed-reference``), 'stated' (the log's metadata ``reference_absolute``), 'found'
        (neither: decided from the offsets below), 'lengths' (a bar-length reference is
        absolute: the bars' true centre distances)
    offsets, within : when found, the median reference − MMD offset of each observed component
        over the log and the bound :func:`~mmd_ros.core.accuracy.read_datum` held it to, the
        claim for the MMD's error there times ``ABSOLUTE_WITHIN_SIGMAS`` (k,) [m, rad]; names
        and units their components'
    starts_at_zero : when found, the reference reads zero (within ``within``) in every
        component at its first sample: it may have been zeroed there
    """

    zeroed: bool
    source: str
    offsets: FloatArray | None = None
    within: FloatArray | None = None
    names: tuple[str, ...] = ()
    units: tuple[str, ...] = ()
    starts_at_zero: bool = False

    @property
    def datum(self) -> str:
        return 'offset' if self.zeroed else 'none'

    def text(self) -> str:
        what = ('zeroed (a constant offset per component removed)' if self.zeroed else
                'absolute in {L} (compared as it is)')
        if self.source == 'option':
            return f'the reference is taken as {what}, as asked'
        if self.source == 'stated':
            return f'the reference is taken as {what}, as the log states (reference_absolute)'
        if self.source == 'lengths':
            return f'the bar-length reference is {what}'
        if self.offsets is None:
            return f'the log does not say whether its reference is absolute: taken as {what}'
        report = report_factors(self.units)
        parts = ', '.join(f'{n} {o * s:.3g} {_unit(u)} (claim ×{ABSOLUTE_WITHIN_SIGMAS:g}: '
                          f'{w * s:.3g})' for n, o, w, s, u in
                          zip(self.names, self.offsets, self.within, report, self.units))
        if np.all(np.abs(self.offsets) <= self.within):
            why = 'all within what the MMD\'s error may be'
        elif self.starts_at_zero:
            why = ('not all within what the MMD\'s error may be, and the reference reads zero '
                   'where the log starts (zeroed there)')
        elif not self.zeroed:
            why = (f'beyond what the budget claims, but within {GROSS_ERROR[0] / M_PER_UM:g} µm '
                   f'and {GROSS_ERROR[1] * ARCSEC_PER_RAD:g}″ and the reference does not read '
                   'zero where the log starts (an error of the MMD: what is there to find)')
        else:
            why = (f'beyond {GROSS_ERROR[0] / M_PER_UM:g} µm or '
                   f'{GROSS_ERROR[1] * ARCSEC_PER_RAD:g}″ (the pose where it was zeroed)')
        return (f'the log does not state whether its reference is absolute '
                f'(reference_absolute); its offsets from the MMD, {parts}, are {why}: taken as '
                f'{what} (mmd analyze --absolute-reference or --zeroed-reference says otherwise)')

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {'zeroed': self.zeroed, 'source': self.source}
        if self.offsets is not None:
            out['offsets'] = dict(zip(self.names, self.offsets.tolist()))
            out['within'] = dict(zip(self.names, self.within.tolist()))
            out['starts_at_zero'] = self.starts_at_zero
        return out


def _reference_datum(run: RunLog, model: Model, calibration: Calibration | None,
                     o: AnalysisOptions) -> tuple[ReferenceDatum, Processed | None]:
    """Whether ``run``'s reference is zeroed or absolute: as the options say, else as the log
    states, else as its offsets from the MMD show. An absolute reference differs from the MMD
    by the MMD's error; a zeroed one by the pose where it was zeroed too. Compared zeroed, an
    absolute reference's constant part (the calibration's points, the bars' common mode, a
    per-bar offset) is lost; compared absolute, a zeroed reference's offset would be taken for
    the MMD's error. A log that does not say is taken as absolute when every component is
    within what the budget of the model as given claims, or beyond it when the reference does
    not read zero where the log starts and no offset is a pose it could have been zeroed at
    (:func:`~mmd_ros.core.accuracy.read_datum`). Also the pass of ``model`` over the log that
    decided it (None when none was needed)."""
    if o.datum in ('offset', 'none'):
        return ReferenceDatum(o.datum == 'offset', 'option'), None
    try:
        obs = make_observation(run.reference_pose, run.reference_lengths, 'none',
                               run.metadata.get('reference_sigma'))
    except AnalysisError:     # (its preparation says what is wrong with it)
        return ReferenceDatum(True, 'found'), None
    if obs.kind == 'lengths':
        return ReferenceDatum(False, 'lengths'), None
    stated = stated_absolute(run.metadata)
    if stated is not None:
        return ReferenceDatum(not stated, 'stated'), None
    calibration = calibration or run.calibration
    if calibration is None or run.counts.shape[0] == 0 or run.unreadable.any():
        return ReferenceDatum(True, 'found'), None
    before = run_pipeline(run.device, calibration, model, run.times_s, run.counts)
    ok = obs.usable & before.measured('pose')
    if not ok.any():
        return ReferenceDatum(True, 'found'), before
    offsets = -np.median(obs.residual(before)[ok], axis=0)
    ctx = FitContext(run.device, calibration, model, run.times_s, run.counts, before, obs, o,
                     epoch_s=run.epoch_s)
    claim = claimed_sigma(ctx, np.flatnonzero(ok))
    own = np.zeros_like(claim) if obs.sigma is None else obs.sigma
    read = read_datum(offsets, np.hypot(claim, own), obs.reference[np.flatnonzero(ok)[0]],
                      obs.components)
    return (ReferenceDatum(not read.absolute, 'found', offsets, read.within, tuple(obs.names),
                           tuple(obs.units), read.starts_at_zero), before)


def _needs_statement(logs: list[RunLog], datums: list[ReferenceDatum]) -> bool:
    """Whether the analysis starts from what the device states (:func:`_stated_terms`): every
    log has a reference pose (a bar-length reference reads bars off the MMD, on which a
    pose-dependent term has no say) and none sees the bars' common mode (an absolute reference
    of every bar determines the sag: started from the statement there, the fitted sag no longer
    took the common-mode errors its signature shares, and new motion's errors grew by 10-36 %,
    24 twins)."""
    for run, datum in zip(logs, datums):
        if not run.has_reference_pose:
            return False
        try:
            obs = make_observation(run.reference_pose, run.reference_lengths, datum.datum)
        except AnalysisError:
            continue            # (its preparation says what is wrong with it)
        if obs.sees_every_bar and not obs.datum:
            return False
    return True


def _stated_terms(device: DeviceDescription, model: Model, o: AnalysisOptions) -> list[ModelTerm]:
    """What the device description states that the model does not correct, as terms the
    analysis starts from: the bars' gravity sag (``bars.gravity_sag_nm``; the calibration reads
    a bar lying flat, so on the MMD it reads g n_z^2 short). A zeroed reference does not see the
    bars' common mode, which the sag moves most: a fit started without it moved that mode with
    the sag's sign through its terms of free constants (z's error on new motion after a zeroed
    fit 0.189 µm, 0.063 µm started from the stated sag: 12 twins calibrated one-sided). The
    gravity_sag effect fits what the statement missed on top of it."""
    sag = device.gravity_sag_m
    if not o.stated_sag or not sag or any(t.type_name in SAG_TERMS for t in model.terms):
        return []
    g = device.geometry
    return [GravitySagTerm(g.upper, g.lower, np.full(6, sag), device.up)]


def _stated_change(device: DeviceDescription, processed: Processed, stated: tuple[ModelTerm, ...],
                   obs: Observation) -> FloatArray:
    """What the stated terms changed in a run's observed residual, (N, k) [m, rad] (zero where
    no pose): their bar corrections at the run's poses mapped through the inverse Jacobian
    (linear: a stated term moves a bar by nanometres)."""
    p = processed
    ctx = TermContext(np.zeros(p.poses.shape[0]), np.zeros((p.poses.shape[0], 8)), p.lengths_m,
                      p.cdf_lengths_m, p.reference_error_m, p.temp_change_c, p.poses)
    dl = np.nan_to_num(sum(t.correction(ctx) for t in stated))
    if obs.kind == 'lengths':
        return dl[:, obs.components]
    change = np.zeros_like(p.poses)
    ok = np.flatnonzero(p.valid & np.all(np.isfinite(p.poses), axis=1))
    if ok.size:
        j = jacobian(device.geometry, p.poses[ok])
        change[ok] = np.linalg.solve(j, dl[ok][:, :, None])[:, :, 0]
    return change[:, obs.components]


def _pose_floor(ctx: FitContext, train_idx: IntArray) -> FloatArray:
    """Noise floor of each of the six pose components of a log, (6,) [m, rad]: encoder
    quantisation propagated, and the MMD's own sample-to-sample noise in that component."""
    return ctx.cached('pose_floor', lambda: np.hypot(
        quantisation_floor(ctx.device, ctx.base.poses[train_idx], ctx.thermal_on),
        sample_noise(ctx.base.poses, ctx.base, train_idx)))


def _normal(d: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The design ``d`` (m, p) with unit-norm columns, their norms and the pseudo-inverse of
    its Gram matrix: coefficients of data Y are gram_inv @ (dn^T Y) / norms."""
    norms = np.linalg.norm(d, axis=0)
    norms[norms == 0] = 1.0
    dn = d / norms
    return dn, norms, np.linalg.pinv(dn.T @ dn, rcond=1e-13, hermitian=True)


# -- observation rows --------------------------------------------------------------------------
class _Rows:
    """Weighted observation rows of a set of samples of one log: y (m,), nuisance (m, q).

    With a zeroed reference (an offset per component removed, the nuisance columns) the data
    say nothing of how a term moves the mean of a component over the log. A term of one
    physical law carries the mean its law gives; in a term of free constants
    (``Effect.free_mean``) a direction seen only through how it varies can carry any mean
    along: a localised scale error, fitted with the CDF points and harmonics, put 2.4 µrad of
    constant pitch into a run whose varying part it halved. ``prior_sigma`` (k,) [m, rad], on
    training rows: k rows more, each such a term's mean change of a component over these
    samples in units of that sigma (what the budget claims for it), target 0 (zero for the
    other terms); scaled by sqrt(m / N_eff) so that m correlated rows do not outweigh them.

    With ``axis`` (a one-axis run, analysis/axis_motion.py), n u rows more after the observed
    ones: the MMD's reading of each unseen component, weighted by its floor, with the
    machine's motion along the axis projected out of them and of every column.
    Rows: the observed components (``n_data``, sample-major), the unseen ones (``n_unseen``),
    then the held means.
    """

    def __init__(self, ctx: FitContext, idx: IntArray, residual: FloatArray, weights: FloatArray,
                 block: IntArray, prior_sigma: FloatArray | None = None,
                 axis: AxisMotion | None = None) -> None:
        self.ctx, self.idx, self.w = ctx, idx, weights
        obs = ctx.obs
        k = len(obs.components)
        self.k = k
        self.jinv = None
        self.axis_jinv: FloatArray | None = None
        if obs.kind == 'pose':
            jinv = np.linalg.inv(jacobian(ctx.device.geometry, ctx.base.poses[idx]))
            self.jinv = jinv[:, obs.components, :]  # (n, k, 6)
            if axis is not None:
                self.axis_jinv = jinv[:, axis.components, :]   # (n, u, 6)
                self.axis_w = 1.0 / axis.floor
        data = -residual[idx] * weights
        self.y = data.reshape(-1)
        self.n_data = self.y.size
        self.blocks = np.repeat(block[idx], k)
        if obs.datum:
            nuis = np.zeros((idx.size, k, k))
            nuis[:, np.arange(k), np.arange(k)] = weights
            self.nuisance = nuis.reshape(-1, k)
        else:
            self.nuisance = np.zeros((idx.size * k, 0))
        if obs.lag is not None:     # the reference's lag behind the MMD: its motion's columns
            lag = (obs.lag[idx] * weights[None, :, None]).reshape(idx.size * k, -1)
            self.nuisance = np.concatenate([self.nuisance, lag], axis=1)
        self.n_unseen = 0
        if self.axis_jinv is not None:
            self._add_axis_rows(axis, idx, block)
        self.prior_w: FloatArray | None = None
        if prior_sigma is not None and obs.datum and idx.size:
            inflation = max(idx.size * k / max(effective_samples(data - data.mean(axis=0)), 1.0), 1.0)
            self.prior_w = math.sqrt(inflation) / (idx.size * weights * prior_sigma)
            self.y = np.concatenate([self.y, np.zeros(k)])
            self.blocks = np.concatenate([self.blocks, np.full(k, -1)])
            self.nuisance = np.concatenate([self.nuisance, np.zeros((k, self.nuisance.shape[1]))])

    def project(self, cols: FloatArray, hold_mean: bool = False) -> FloatArray:
        """Length-space columns (n, 6, P) to weighted observation columns (n k, P), and the
        rows of the mean of each component when it is held (``prior_sigma``; zero rows for an
        effect whose physics fixes its mean, ``hold_mean`` False)."""
        if self.jinv is not None:
            obs = self.jinv @ cols
        else:
            obs = cols[:, self.ctx.obs.components, :]
        obs = obs * self.w[None, :, None]
        out = obs.reshape(-1, cols.shape[2])
        if self.axis_jinv is not None:
            unseen = (self.axis_jinv @ cols) * self.axis_w[None, :, None]
            out = np.concatenate([out, self._off_machine(unseen).reshape(-1, cols.shape[2])])
        if self.prior_w is not None:
            held = np.sum(obs, axis=0) * self.prior_w[:, None] if hold_mean else np.zeros((self.k, out.shape[1]))
            out = np.concatenate([out, held])
        return out

    def _add_axis_rows(self, axis: AxisMotion, idx: IntArray, block: IntArray) -> None:
        # The machine's motion is a nuisance of these rows alone: it is projected out of them
        # (and of every column, in project) instead of being fitted beside the effects, which
        # is the same least-squares fit (Frisch-Waugh-Lovell) at a fraction of the size. In
        # the held-out part it is fitted on those rows themselves: what is judged there is
        # whether the effects explain what the machine's motion cannot.
        u = len(axis.components)
        self.axis_q = _orthonormal(axis.basis(idx))                 # (n, q)
        self.n_unseen = idx.size * u
        values = -axis.values[idx] * self.axis_w
        self.y = np.concatenate([self.y, self._off_machine(values[:, :, None])[:, :, 0].reshape(-1)])
        self.blocks = np.concatenate([self.blocks, np.repeat(block[idx], u)])
        self.nuisance = np.concatenate([self.nuisance, np.zeros((self.n_unseen, self.nuisance.shape[1]))])

    def _off_machine(self, x: FloatArray) -> FloatArray:
        """(n, u, P) unseen-component rows with the machine's motion projected out."""
        flat = x.reshape(x.shape[0], -1)      # (two matrix products: BLAS, not einsum's loop)
        return (flat - self.axis_q @ (self.axis_q.T @ flat)).reshape(x.shape)

    def unseen_piece(self, e: FloatArray) -> FloatArray:
        """The unseen components' rows of this log's slice of a stacked vector, (n, u)
        (for a log that has them: ``n_unseen`` > 0)."""
        return e[self.n_data:self.n_data + self.n_unseen].reshape(-1, self.axis_jinv.shape[1])


class _Part:
    """The rows of every log for one part (training or held-out), stacked."""

    def __init__(self, runs: list[_Run], which: str) -> None:
        self.rows = []
        for r in runs:
            idx = r.split.fit_train if which == 'train' else r.split.fit_test
            self.rows.append(_Rows(r.ctx, idx, r.raw, 1.0 / r.floor, r.split.block + 100_000 * r.index,
                                   r.datum_sigma if which == 'train' else None, r.axis))
        self.runs = runs
        self.y = np.concatenate([x.y for x in self.rows])
        self.blocks = np.concatenate([x.blocks for x in self.rows])
        sizes = [x.y.size for x in self.rows]
        self.starts = np.concatenate(([0], np.cumsum(sizes)))
        q = [x.nuisance.shape[1] for x in self.rows]
        self.nuisance = np.zeros((self.y.size, sum(q)))
        col = 0
        for x, a, b, n in zip(self.rows, self.starts[:-1], self.starts[1:], q):
            self.nuisance[a:b, col:col + n] = x.nuisance
            col += n

    def pieces(self, e: FloatArray) -> list[FloatArray]:
        """A stacked vector split per log, each (n_r, k_r) (its samples' rows only)."""
        return [e[a:a + x.n_data].reshape(-1, x.k) for x, a in zip(self.rows, self.starts[:-1])]

    def n_eff(self, e: FloatArray) -> float:
        """Effective number of independent samples of a stacked residual (per log, summed;
        a one-axis run's unseen components counted too)."""
        pieces = self.pieces(e) + [x.unseen_piece(e[a:]) for x, a in zip(self.rows, self.starts[:-1])
                                   if x.n_unseen]
        return float(sum(effective_samples(p) for p in pieces if p.size))


def _orthonormal(b: FloatArray) -> FloatArray:
    """Orthonormal basis of the column space of ``b``: columns scaled to unit norm, then the
    eigenvectors of the (small) Gram matrix; directions with eigenvalue below 1e-12 of the
    largest are dropped. Matrix products only: fast for tall matrices."""
    if b.shape[1] == 0:
        return b
    norms = np.linalg.norm(b, axis=0)
    b = b[:, norms > 0] / norms[norms > 0]
    w, v = np.linalg.eigh(b.T @ b)
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    return (b @ v[:, keep]) / np.sqrt(w[keep])


@dataclass
class _Active:
    effect: Effect
    hyper: Any
    basis: FloatArray  # (P, r)
    step_gain: float
    explained: float = math.nan  # share of the initial held-out mean square it removed
    norms: FloatArray | None = None
    #: False for an effect whose whole-pose consequence the data do not determine: it stays in
    #: the fit (the data hold it; leaving it out would bend the others) but is not written
    written: bool = True
    #: directions dropped as within 2 sigma of zero, (P, w) in unit-norm scale, and their sigma
    weak: tuple[FloatArray, FloatArray] | None = None

    def refitted(self, hyper: Any, fit: dict[str, Any]) -> _Active:
        """The same effect at setting ``hyper`` with the directions of a :meth:`_Selector.reduce`
        fit (its gains and written flag kept)."""
        return replace(self, hyper=hyper, basis=fit['basis'], norms=fit['norms'], weak=fit['weak'])

    def weak_basis(self) -> FloatArray | None:
        """The directions dropped as weak in parameter scale, (P, w) (as :attr:`basis` is),
        or None when there are none."""
        if self.weak is None or not self.weak[0].shape[1]:
            return None
        norms = np.asarray(self.norms, dtype=np.float64)
        inv = np.zeros_like(norms)
        inv[norms > 0] = 1.0 / norms[norms > 0]
        return self.weak[0] * inv[:, None]


class _Selector:
    """Stepwise selection on the fit subsets of the training and held-out blocks of all logs."""

    def __init__(self, runs: list[_Run], options: AnalysisOptions) -> None:
        self.runs, self.options = runs, options
        self.train = _Part(runs, 'train')
        self.test = _Part(runs, 'test')
        self.groups = {scope: sorted({r.group(scope) for r in runs}, key=lambda g: min(
            r.index for r in runs if r.group(scope) == g)) for scope in ('device', 'calibration', 'run')}
        self.active: list[_Active] = []
        self._sig: dict[tuple[str, Any, str], FloatArray] = {}
        self._hypers: dict[str, list[Any]] = {}
        self._base: dict[str, FloatArray] = {}
        self._base_key: dict[str, Any] = {}
        self._base_q: dict[str, FloatArray] = {}
        self._step: dict[str, Any] = {}
        self._gram: dict[tuple[str, Any], FloatArray] = {}

    @property
    def ctx(self) -> FitContext:
        return self.runs[0].ctx

    def hypers(self, effect: Effect) -> list[Any]:
        if effect.name not in self._hypers:
            self._hypers[effect.name] = effect.hypers([r.ctx for r in self.runs])
        return self._hypers[effect.name]

    def n_groups(self, effect: Effect) -> int:
        return len(self.groups[effect.scope])

    def group_index(self, effect: Effect, run: _Run) -> int | None:
        key = run.group(effect.scope)
        groups = self.groups[effect.scope]
        return groups.index(key) if key in groups else None

    def parameters(self, effect: Effect, hyper: Any) -> list[Parameter]:
        """The effect's parameters, one set per group of its scope (calibration, run)."""
        base = effect.parameters(self.ctx, hyper)
        groups = self.groups[effect.scope]
        if len(groups) == 1:
            return base
        out = []
        for g in range(len(groups)):
            label = ', '.join(r.run.path.name for r in self.runs if r.group(effect.scope) == groups[g])
            out += [Parameter(f'{p.name} [{label}]', p.unit, p.factor, p.bound) for p in base]
        return out

    def coverage(self, effect: Effect, hyper: Any) -> tuple[NDArray[np.bool_], str]:
        n_p = len(effect.parameters(self.ctx, hyper))
        avail = np.zeros(n_p * self.n_groups(effect), dtype=bool)
        notes = []
        for r in self.runs:
            ok, note = effect.coverage(r.ctx, hyper, r.split.train_idx)
            g = self.group_index(effect, r)
            avail[g * n_p:(g + 1) * n_p] |= ok
            if note and not ok.all():
                notes.append(note if len(self.runs) == 1 else f'{r.run.path.name}: {note}')
        return avail, '; '.join(notes) if not avail.all() else ''

    def ties(self, effect: Effect, hyper: Any, avail: NDArray[np.bool_],
             touched: NDArray[np.bool_]) -> FloatArray | None:
        """How the parameters of all groups the data do not exercise follow the others
        (:meth:`Effect.ties`, group by group, block-diagonal), or None."""
        n_p = len(effect.parameters(self.ctx, hyper))
        n_g = self.n_groups(effect)
        out, changed = np.eye(n_p * n_g), False
        for g in range(n_g):
            ctx = next(r.ctx for r in self.runs if self.group_index(effect, r) == g)
            part = slice(g * n_p, (g + 1) * n_p)
            t = effect.ties(ctx, hyper, avail[part], touched[part])
            if t is not None:
                out[part, part], changed = t, True
        return out if changed else None

    def columns(self, effect: Effect, hyper: Any, part: str, bar: int | None = None) -> FloatArray:
        """The effect's observation columns; with ``bar``, of its correction on that bar only
        (the six bars' columns are made together, from one signature per log)."""
        key = (effect.name, hyper, part, bar)
        if key not in self._sig:
            p = self.train if part == 'train' else self.test
            n_p = len(effect.parameters(self.ctx, hyper))
            bars = [None] if bar is None else list(range(6))
            out = {b: np.zeros((p.y.size, n_p * self.n_groups(effect))) for b in bars}
            for rows, r, a, b in zip(p.rows, p.runs, p.starts[:-1], p.starts[1:]):
                g = self.group_index(effect, r)
                sig = effect.signature(r.ctx, hyper, rows.idx)
                for i in bars:
                    one = sig if i is None else np.where((np.arange(6) == i)[None, :, None], sig, 0.0)
                    out[i][a:b, g * n_p:(g + 1) * n_p] = rows.project(one, effect.free_mean)
            for i in bars:
                self._sig[(effect.name, hyper, part, i)] = out[i]
        return self._sig[key]

    def column_gram(self, effect: Effect, hyper: Any) -> FloatArray:
        """C^T C of the effect's training columns (cached with them)."""
        key = (effect.name, hyper)
        if key not in self._gram:
            c = self.columns(effect, hyper, 'train')
            self._gram[key] = c.T @ c
        return self._gram[key]

    def base(self, part: str) -> FloatArray:
        key = (part, tuple((a.effect.name, a.hyper, a.basis.shape) for a in self.active))
        if self._base_key.get(part) != key:
            rows = self.train if part == 'train' else self.test
            blocks = [rows.nuisance] + [self.columns(a.effect, a.hyper, part) @ a.basis for a in self.active]
            self._base[part] = np.concatenate(blocks, axis=1)
            self._base_key[part] = key
            self._base_q.pop(part, None)
        return self._base[part]

    def base_q(self) -> FloatArray:
        """Orthonormal basis of the training base columns (cached per active set)."""
        b = self.base('train')
        if 'train' not in self._base_q:
            self._base_q['train'] = _orthonormal(b)
        return self._base_q['train']

    def _fit(self, d: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Coefficients and their covariance (residual variance inflated for the
        autocorrelation of the residual: m / N_eff). Columns are scaled to unit norm (the datum
        columns and the effects' columns differ by orders of magnitude), then QR."""
        m, p = d.shape
        if p == 0:
            return np.zeros(0), np.zeros((0, 0))
        dn, norms, gram_inv = _normal(d)
        coef = gram_inv @ (dn.T @ y) / norms
        e = y - d @ coef
        sigma2 = float(e @ e) / max(m - p, 1)
        inflation = max(m / self.train.n_eff(e), 1.0)
        return coef, gram_inv / np.outer(norms, norms) * sigma2 * inflation

    def _step_basis(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Of the current base columns B (training): orthonormal basis Q, T = Q^T B, the
        training target projected off B (y_p) and Q^T y (cached per active set)."""
        q = self.base_q()
        key = self._base_key.get('train')
        if self._step.get('key') != key:
            y = self.train.y
            qy = q.T @ y
            yp = y - q @ qy
            self._step = {'key': key, 'T': q.T @ self.base('train'), 'qy': qy, 'yp': yp,
                          'qt_yp': q.T @ yp}
        return q, self._step['T'], self._step['yp'], self._step['qy']

    def training_ic(self, fit: dict[str, Any]) -> float:
        """Information criterion of one setting on the training rows, N ln(MSE) + p ln(N).

        N is the effective number of independent samples of the residual *before* the
        candidate (the same for every setting and effect compared at this step): counting it
        from each candidate's own residual rewarded a worse fit, whose more correlated residual
        gave a smaller N and so a smaller N ln(MSE) (issue 10: a relay of 20 µm with MSE 49.8
        scored 4957 against 8860 for a play set with MSE 2.3)."""
        _, _, yp, _ = self._step_basis()
        if 'n_eff' not in self._step:
            self._step['n_eff'] = self.train.n_eff(yp)
        n = self._step['n_eff']
        e = fit['e_train']
        return n * math.log(max(float(np.mean(e ** 2)), 1e-300)) + fit['basis'].shape[1] * math.log(n)

    def baseline(self) -> tuple[FloatArray, FloatArray]:
        q, t, yp, qy = self._step_basis()
        coef_b = np.linalg.lstsq(t, qy, rcond=None)[0] if t.size else np.zeros(0)
        return yp, self.test.y - self.base('test') @ coef_b

    def reduce(self, effect: Effect, hyper: Any) -> dict[str, Any]:
        """Fit of one candidate at one hyperparameter, in the directions the data identify.

        The candidate's unit-norm columns Cn are projected off the base B (Cp); the SVD
        Cp = U S V^T gives its distinct directions. Directions with s <= rcond are structurally
        unidentifiable; of the others, those whose estimate is below min_t_param standard
        deviations are not determined by the data. Both are reported, not fitted. With
        R = Cn V the coefficients are beta_j = u_j^T y_p / s_j.
        """
        params = self.parameters(effect, hyper)
        names = [p.name for p in params]
        avail, note = self.coverage(effect, hyper)
        c = self.columns(effect, hyper, 'train')
        cc = self.column_gram(effect, hyper)
        norms = np.sqrt(np.maximum(np.diag(cc), 0.0))
        tie = self.ties(effect, hyper, avail, norms > 0)
        tied = np.zeros(len(names), dtype=bool) if tie is None else np.diag(tie) == 0.0
        lost = [f'{names[j]} (not exercised: follows those seen, {effect.hyper_label(hyper)})'
                for j in np.flatnonzero(tied)]
        if tie is not None:
            c = c @ tie                       # (the columns of the tied ones fall to zero)
            cc = tie.T @ cc @ tie
            norms = np.sqrt(np.maximum(np.diag(cc), 0.0))
        usable = avail & (norms > 0)
        lost += [f'{names[j]} (not exercised)' for j in np.flatnonzero(~usable & ~tied)]
        out: dict[str, Any] = {'names': names, 'lost': lost, 'note': note,
                               'basis': np.zeros((len(names), 0)), 'norms': norms, 'weak': None}
        if not usable.any():
            return out
        q, t, yp, qy = self._step_basis()
        # Cp = Cn - Q Q^T Cn is never formed (the columns are (n k) x P, the costliest arrays
        # of the search): its Gram matrix is Cn^T Cn - (Q^T Cn)^T (Q^T Cn), and what the fit
        # needs of Cp are products with a vector, each Cn x - Q (Q^T Cn x)
        scale = 1.0 / norms[usable]
        qtc, ytc = (q.T @ c)[:, usable] * scale, (yp @ c)[usable] * scale
        gram = cc[np.ix_(usable, usable)] * np.outer(scale, scale) - qtc.T @ qtc

        def cp_times(x: FloatArray) -> FloatArray:
            z = scale * x
            full = np.zeros(c.shape[1])
            full[usable] = z
            return c @ full - q @ (qtc @ x) if q.shape[1] else c @ full

        # SVD of Cp through its Gram matrix (P x P): Cp = U S V^T with V, S^2 from eigh
        w, vecs = np.linalg.eigh(gram)
        order = np.argsort(w)[::-1]
        w, vecs = np.maximum(w[order], 0.0), vecs[:, order]
        sv = np.sqrt(w)
        keep = sv > self.options.rcond
        vt = vecs.T
        sub = [names[j] for j in np.flatnonzero(usable)]
        dropped = vt[~keep]
        for row in dropped[:3]:
            top = np.argsort(-np.abs(row))[:3]
            lost.append('direction ' + ' '.join(f'{row[k]:+.2f}·{sub[k]}' for k in top))
        if dropped.shape[0] > 3:
            lost.append(f'… and {dropped.shape[0] - 3} more directions')
        sv, vt = sv[keep], vt[keep]
        cpty = ytc - qtc.T @ self._step['qt_yp']
        proj = (vt @ cpty) / sv               # = U^T y_p (U S = Cp V)
        beta = proj / sv
        e = yp - cp_times(vt.T @ beta)
        m = yp.size
        dof = max(m - q.shape[1] - sv.size, 1)
        inflation = max(m / self.train.n_eff(e), 1.0)
        sd = np.sqrt(float(e @ e) / dof * inflation) / sv
        weak = np.abs(beta) < self.options.min_t_param * sd
        if weak.any():
            lost.append(f'{int(weak.sum())} directions not determined by the data '
                        f'(|estimate| < {self.options.min_t_param:g} σ)')
        # a direction that needs physically implausible parameter values is not identified
        # either (it would corrupt what the reference does not observe)
        bounds = np.array([p.bound for p in params])[usable]
        size = np.abs(vt.T * beta[None, :]) / norms[usable, None]   # (P_usable, r)
        wild = np.any(size > bounds[:, None], axis=0) & ~weak
        if wild.any():
            lost.append(f'{int(wild.sum())} directions that would need implausible values '
                        '(beyond the physical bounds of their parameters)')
        drop = weak | wild
        # the directions dropped as weak are determined, to be within 2 sigma of zero: their
        # share of an unseen component's uncertainty is their sigma, not the size of the others
        # (unit-norm parameter scale, as the basis times its norms)
        keep_weak = weak & ~wild
        weak_dirs = np.zeros((len(names), int(keep_weak.sum())))
        weak_dirs[usable] = vt[keep_weak].T
        out.update(weak=(weak_dirs, sd[keep_weak]))
        if drop.any():
            e = e + cp_times(vt[drop].T @ beta[drop])
            sv, vt, beta = sv[~drop], vt[~drop], beta[~drop]
        v = vt.T
        basis = np.zeros((len(names), v.shape[1]))
        basis[usable] = v / norms[usable, None]
        if tie is not None:
            basis = tie @ basis
        coef_b = (np.linalg.lstsq(t, qy - qtc @ v @ beta, rcond=None)[0] if t.size else np.zeros(0))
        out.update(basis=basis, beta=beta, e_train=e, coef_b=coef_b)
        return out

    def check(self, effect: Effect, nuisance: tuple[tuple[Effect, FloatArray, Any], ...] = ()
              ) -> tuple[FloatArray, FloatArray] | None:
        """What the data say of an effect's parameters on top of the active effects, fitted
        jointly with the parameters of the ``nuisance`` effects (effect, sd, setting), each
        with the prior N(0, sd^2) its sd (P,) [SI] gives (what is known of errors that share
        part of the effect's signature, which a fit may have left undetermined; without them a
        direction the two share would fall below ``rcond`` and the estimate would keep only
        the rest): the effect's posterior mean and sigma (P,) [SI] (flat prior), NaN for those
        the data do not exercise; None when they exercise none. The residual's variance is
        inflated by its correlation, as :meth:`reduce` does; the sigma is the larger of that
        and the spread of the estimate over groups of the training blocks
        (:meth:`_group_jackknife`)."""
        c = self.columns(effect, None, 'train')
        own = self.coverage(effect, None)[0] & (np.linalg.norm(c, axis=0) > 0)
        if not own.any():
            return None
        cols, sds = [c[:, own]], [np.full(int(own.sum()), np.inf)]
        for e, sd, hyper in nuisance:
            cn = self.columns(e, hyper, 'train')
            # every parameter that moves the data, however little: the prior holds the weak ones
            # (with the points no sample came near left out, a one-sided routine's friction
            # steps there went into the sag: d -312 to +163 nm, sigma 23-49 nm, where the twins'
            # sag lay within 24 nm of the stated 100 +- 15, 7 of 12 disputed; with them -158 to
            # +89 nm, sigma 40-60 nm)
            use = (np.linalg.norm(cn, axis=0) > 0) & (sd > 0)
            cols.append(cn[:, use])
            sds.append(sd[use])
        x = np.concatenate(cols, axis=1)
        norms = np.linalg.norm(x, axis=0)
        q, _, yp, _ = self._step_basis()
        x = x / norms
        if q.shape[1]:
            x = x - q @ (q.T @ x)
        precision = 1.0 / (np.concatenate(sds) * norms) ** 2     # the priors, unit-norm scale
        gram, xty = x.T @ x, x.T @ yp
        sigma2 = float(yp @ yp) / max(yp.size - q.shape[1], 1)
        for _ in range(2):      # the residual variance, from the fit it weighs
            a = gram + sigma2 * np.diag(precision)
            beta = np.linalg.solve(a, xty)
            e = yp - x @ beta
            dof = max(yp.size - q.shape[1] - float(np.trace(np.linalg.solve(a, gram))), 1.0)
            sigma2 = float(e @ e) / dof * max(yp.size / self.train.n_eff(e), 1.0)
        cov = sigma2 * np.linalg.inv(gram + sigma2 * np.diag(precision))
        m = int(own.sum())
        jackknife = self._group_jackknife(x, yp, gram, xty, sigma2 * precision)
        var = np.maximum(np.diag(cov)[:m], jackknife[:m])
        out = np.full((2, own.size), np.nan)
        out[0, own] = beta[:m] / norms[:m]
        out[1, own] = np.sqrt(var) / norms[:m]
        return out[0], out[1]

    def _group_jackknife(self, x: FloatArray, y: FloatArray, gram: FloatArray, xty: FloatArray,
                         ridge: FloatArray) -> FloatArray:
        """Variance (P,) of the estimate solve(gram + diag(ridge), x^T y) over the training
        rows, from the estimates without each of ``JACKKNIFE_GROUPS`` groups of consecutive time
        blocks (delete-a-group jackknife: (G - 1)/G sum of squared deviations); zeros with
        fewer than 4 groups. A residual whose structure lasts longer than a block (what the
        active effects leave, smooth in time) moves the estimate from group to group more than
        its variance inflated by the autocorrelation says: on 5 s runs the sag's error estimate
        lay 0.8-6.5 of that sigma from the truth."""
        blocks = self.train.blocks
        ids = np.unique(blocks[blocks >= 0])
        groups = [g for g in np.array_split(ids, min(JACKKNIFE_GROUPS, ids.size)) if g.size]
        if len(groups) < 4:
            return np.zeros(x.shape[1])
        a = gram + np.diag(ridge)
        ests = []
        for g in groups:
            rows = np.isin(blocks, g)
            xg, yg = x[rows], y[rows]
            # (lstsq: a parameter only one group exercises leaves the rest singular)
            ests.append(np.linalg.lstsq(a - xg.T @ xg, xty - xg.T @ yg, rcond=None)[0])
        ests = np.array(ests)
        n = len(groups)
        return (n - 1) / n * np.sum((ests - ests.mean(axis=0)) ** 2, axis=0)

    def _best_setting(self, effect: Effect) -> tuple[Any, dict[str, Any] | None, float]:
        """The setting with the lowest training information criterion: the grid (or the
        candidates), then, for a continuous setting, a golden-section search in its logarithm
        within the bounds the effect gives around the best one."""
        grid = self.hypers(effect)
        scores: list[tuple[float, Any, dict[str, Any]]] = []
        first_fit = None
        for hyper in grid:
            fit = self.reduce(effect, hyper)
            first_fit = first_fit or (hyper, fit)
            if fit['basis'].shape[1]:
                scores.append((self.training_ic(fit), hyper, fit))
        if not scores:
            return (first_fit[0], first_fit[1], math.inf) if first_fit else (None, None, math.inf)
        ic, hyper, fit = min(scores, key=lambda t: t[0])
        tried = hyper
        bounds = effect.refine_bounds(hyper, grid, [r.ctx for r in self.runs])
        if bounds is not None:
            lo, hi = math.log(bounds[0]), math.log(bounds[1])
            # a setting that is measured (a period) is the one whose fit leaves the least error:
            # the count of directions kept as determined jumps from one period to the next by
            # the 2-sigma test, not by the model's size, and with its penalty a C-axis run's
            # 13 µm period came out 4.3e-5 too long (the least error was at 2.3e-5, the truth 0)
            measure = ((lambda f: float(np.mean(f['e_train'] ** 2))) if effect.setting_measured
                       else self.training_ic)
            cache: dict[float, tuple[float, dict[str, Any]]] = {}

            def score(x: float) -> float:
                if x not in cache:
                    f = self.reduce(effect, effect.with_setting_value(tried, math.exp(x)))
                    cache[x] = (measure(f) if f['basis'].shape[1] else math.inf, f)
                return cache[x][0]

            # only a measured setting's bracket moves on: a friction travel's bounds are the
            # grid's, and searching past them made a 10-minute run's analysis 1.3 x as long
            x = _golden_minimum(score, lo, hi, moves=4 if effect.setting_measured else 0)
            if cache[x][0] < measure(fit):
                ic, hyper, fit = (self.training_ic(cache[x][1]), effect.with_setting_value(tried, math.exp(x)),
                                  cache[x][1])
        return hyper, fit, ic

    def evaluate(self, effect: Effect, e0_test: FloatArray) -> Candidate:
        """``effect`` at its best setting against the baseline's held-out residual ``e0_test``,
        judged with the baseline's effective samples (:meth:`judge`)."""
        hyper, fit, _ = self._best_setting(effect)
        if fit is None:
            cand = Candidate(effect.name, effect.title, None, '', 0, 0, [],
                             'no setting to try (for a cyclic error: no period stands out in the '
                             'residual\'s spectrum)', basis=np.zeros((0, 0)))
            cand.verdict = 'unidentifiable'
            return cand
        basis = fit['basis']
        best = Candidate(effect.name, effect.title, hyper, effect.hyper_label(hyper),
                         len(fit['names']), basis.shape[1], fit['lost'], fit['note'], basis=basis,
                         norms=fit['norms'], weak=fit['weak'])
        if basis.shape[1] == 0:
            best.verdict = 'unidentifiable'
            return best
        pred = self.columns(effect, hyper, 'test') @ (basis @ fit['beta'])
        if fit['coef_b'].size:
            pred = pred + self.base('test') @ fit['coef_b']
        e1 = self.test.y - pred
        mse0, mse1 = float(np.mean(e0_test ** 2)), float(np.mean(e1 ** 2))
        best.mse0, best.mse1 = mse0, mse1
        best.rms_ratio = math.sqrt(mse1 / mse0) if mse0 > 0 else 1.0
        best.gain = 1.0 - best.rms_ratio
        best.n_left = self.test.n_eff(e1)
        # consistency over the held-out blocks: the logarithm of each block's mean-square
        # ratio, not its difference, which the blocks of fast motion dominated (a skew's
        # error grows with speed; a 24 % gain on a realistic twin, 14 of 20 blocks better,
        # scored t 2.95 by differences and 3.5 by ratios)
        blocks = self.test.blocks
        ids = np.unique(blocks)
        tiny = 1e-300
        per = np.array([math.log(max(float(np.mean(e0_test[blocks == b] ** 2)), tiny)
                                 / max(float(np.mean(e1[blocks == b] ** 2)), tiny)) for b in ids])
        if per.size > 1 and per.std(ddof=1) > 0:
            best.t_stat = float(per.mean() / (per.std(ddof=1) / math.sqrt(per.size)))
        else:
            best.t_stat = math.inf if per.mean() > 0 else 0.0
        self.judge(best, self.test.n_eff(e0_test))
        return best

    def judge(self, best: Candidate, n_eff: float) -> None:
        """The held-out criterion and verdict of an evaluated candidate with ``n_eff``
        effective samples: one count for every candidate of a step (each candidate's own
        residual's would reward the fit that leaves a smoother residual)."""
        mse0, mse1 = best.mse0, best.mse1
        best.n_eff = n_eff
        best.delta_ic = (n_eff * math.log(max(mse1, 1e-300) / max(mse0, 1e-300))
                         + best.n_identifiable * math.log(n_eff))
        o = self.options
        floor_gain = math.sqrt(mse0) - math.sqrt(mse1)
        if best.gain >= o.min_gain and floor_gain >= o.min_floor_gain and best.t_stat >= o.min_t \
                and best.delta_ic <= -o.min_delta_ic:
            best.verdict = 'significant'
        else:
            reasons = []
            if best.gain < o.min_gain:
                reasons.append(f'gain {100 * best.gain:.1f} % < {100 * o.min_gain:g} %')
            elif floor_gain < o.min_floor_gain:
                reasons.append(f'RMS falls by {floor_gain:.2f} < {o.min_floor_gain:g} of the noise floor')
            if best.t_stat < o.min_t:
                reasons.append(f't {best.t_stat:.1f} < {o.min_t:g}')
            if best.delta_ic > -o.min_delta_ic:
                reasons.append(f'ΔIC {best.delta_ic:.0f} > -{o.min_delta_ic:g}')
            best.verdict = 'not significant (' + ', '.join(reasons) + ')'

    def refine(self, settings: bool = True) -> None:
        """Re-choose the hyperparameters (and identified directions) of each active effect with
        the others in place: a setting chosen before a later effect was added may no longer be
        the best (backfitting, one pass). ``settings=False`` keeps each effect's setting and
        re-chooses only its identified directions (leave-one-run-out refits the settings the
        analysis chose)."""
        for k in range(len(self.active)):
            a = self.active[k]
            others = self.active[:k] + self.active[k + 1:]
            self.active = others
            if not settings or len(self.hypers(a.effect)) < 2:
                fit = self.reduce(a.effect, a.hyper)
                best = (a.hyper, fit) if fit['basis'].shape[1] else None
            else:
                hyper, fit, ic = self._best_setting(a.effect)
                best = (hyper, fit) if fit is not None and math.isfinite(ic) else None
            if best is not None:
                a = a.refitted(*best)
            self.active = others[:k] + [a] + others[k:]

    def own_structure_ratio(self, active: _Active, theta: FloatArray, e_pred: FloatArray,
                            partners: list[tuple[_Active, FloatArray]] = ()) -> tuple[float, str]:
        """How much of the structure along the effect's own coordinate is left when it is in
        the model, relative to when it is not: V_with / V_without on the held-out fit samples
        of every log, V the variance explained by bin means of the feature (the effect's
        diagnostic feature that carries most structure without it). With an absolute reference
        the bins' means are counted from zero, not from the log's mean, for a term whose law
        gives its mean: there an offset is structure the data see (a bar's sag under gravity
        moves a pose by nearly the same amount everywhere in a small workspace). A term of free
        constants (``Effect.free_mean``: a drift's offsets, CDF points) fits any offset, so
        that it does says nothing of its own coordinate. ``partners``: effects taken out with it
        (those that follow the same coordinate share what they explain)."""
        contrib = self.columns(active.effect, active.hyper, 'test') @ theta
        for b, t in partners:
            contrib = contrib + self.columns(b.effect, b.hyper, 'test') @ t
        with_all = self.test.pieces(e_pred)
        without_all = self.test.pieces(e_pred + contrib)
        v_with: dict[str, float] = {}
        v_without: dict[str, float] = {}
        for rows, r, w_e, wo in zip(self.test.rows, self.test.runs, with_all, without_all):
            tot_with = float(np.sum((w_e - w_e.mean(axis=0)) ** 2))
            tot_without = float(np.sum((wo - wo.mean(axis=0)) ** 2))
            # the offset the data see (none after a datum is removed), for a term whose law
            # gives its mean: free constants carry any mean, which says nothing of their law
            counted = not r.obs.datum and not active.effect.free_mean
            off_with = float(len(w_e) * np.sum(w_e.mean(axis=0) ** 2)) if counted else 0.0
            off_without = float(len(wo) * np.sum(wo.mean(axis=0) ** 2)) if counted else 0.0
            for name, values in active.effect.diagnostics(r.ctx, active.hyper).items():
                f = values[rows.idx]
                v_without[name] = v_without.get(name, 0.0) + binned_r2(wo, f) * tot_without + off_without
                v_with[name] = v_with.get(name, 0.0) + binned_r2(w_e, f) * tot_with + off_with
        if not v_without:
            return 0.0, ''
        name = max(v_without, key=lambda n: v_without[n])
        if v_without[name] <= 0:
            return 0.0, ''
        return v_with[name] / v_without[name], name

    def final_fit(self) -> tuple[list[tuple[FloatArray, FloatArray, FloatArray]], FloatArray]:
        """Joint fit of all active effects: (theta, sigma, covariance of the reduced
        coefficients) per effect, and the held-out weighted residual predicted by the
        linearised model."""
        d_tr = self.base('train')
        d_te = self.base('test')
        coef, cov = self._fit(d_tr, self.train.y)
        out = []
        start = self.train.nuisance.shape[1]
        for a in self.active:
            r = a.basis.shape[1]
            beta = coef[start:start + r]
            cb = cov[start:start + r, start:start + r]
            theta = a.basis @ beta
            sig = np.sqrt(np.maximum(np.einsum('pr,rs,ps->p', a.basis, cb, a.basis), 0.0))
            out.append((theta, sig, cb))
            start += r
        return out, self.test.y - d_te @ coef

    def setting_shift(self, a: _Active, theta: FloatArray) -> tuple[Any, FloatArray] | None:
        """A continuous setting (a cyclic error's period, a friction turn-over travel) one
        standard deviation away, and the effect's parameters that go with it: (hyper + sd,
        theta + the change); None for a setting that is not continuous.

        The fitted parameters' covariance holds the setting fixed, but the data determine it
        only so well: from a C-axis run a 13 µm period came out 4.3e-5 too long, which turned
        the cyclic error's phase by a fifth of a cycle 63 mm from the calibration's first
        point, and a 6-DOF run of the same device had 46 % of its samples in the 95 %
        ellipsoid. The setting's variance is linearised: the fit is repeated with one more
        column, the change of the effect's correction per unit setting (central difference),
        and with the directions dropped as weak (they trade with the setting); its sigma is
        scaled by the Birge ratio of the setting's estimates from each bar
        (:meth:`_setting_consistency`), and the parameters that go with the setting one sigma
        away are fitted again there (:meth:`_refit_change`)."""
        h = a.effect.setting_value(a.hyper)
        if h is None or h <= 0 or a.basis.shape[1] == 0:
            return None
        dh = SETTING_STEP * h
        up, down = (a.effect.with_setting_value(a.hyper, v) for v in (h + dh, h - dh))
        slopes = np.stack([(self.columns(a.effect, up, 'train', i) - self.columns(a.effect, down, 'train', i))
                           @ theta / (2 * dh) for i in range(6)], axis=1)
        slope = slopes.sum(axis=1)
        start = self._column_start(a)
        weak = a.weak_basis()
        own = [a.basis] if weak is None else [a.basis, weak]
        columns = self.columns(a.effect, a.hyper, 'train')
        design = np.concatenate([self.base('train')] + [columns @ b for b in own[1:]] + [slope[:, None]], axis=1)
        _, cov = self._fit(design, self.train.y)
        var = float(cov[-1, -1])
        if not np.isfinite(var) or var <= 0:
            return None
        sd = math.sqrt(var) * self._setting_consistency(design[:, :-1], slopes)
        shifted = a.effect.with_setting_value(a.hyper, h + sd)
        return shifted, np.asarray(theta) + self._refit_change(a, own, start, shifted)

    def _refit_change(self, a: _Active, own: list[FloatArray], start: int, shifted: Any) -> FloatArray:
        """The change of ``a``'s parameters (in its kept and weak directions ``own``) when the
        data are fitted again with its setting at ``shifted``: the parameters that go with that
        setting. Refitted, not linearised: a period one sigma off turns the phase by a fifth
        of a cycle or more at the far end of a bar, where a linear change of the amplitudes
        no longer follows it."""
        basis = np.concatenate(own, axis=1)
        base = self.base('train')
        rest = [base[:, :start], base[:, start + a.basis.shape[1]:]]
        fitted = []
        for hyper in (a.hyper, shifted):
            design = np.concatenate([rest[0], self.columns(a.effect, hyper, 'train') @ basis, rest[1]], axis=1)
            coef, _ = self._fit(design, self.train.y)
            fitted.append(basis @ coef[start:start + basis.shape[1]])
        return fitted[1] - fitted[0]

    def _column_start(self, a: _Active) -> int:
        """The first column of active effect ``a`` in :meth:`base` (after the datum offsets and
        the effects before it)."""
        start = self.train.nuisance.shape[1]
        for other in self.active:
            if other is a:
                break
            start += other.basis.shape[1]
        return start

    def run_constant_sigma(self) -> list[FloatArray]:
        """Per active effect, the standard deviation its parameters take from the errors a
        calibration draws once and a run carries throughout
        (:func:`~mmd_ros.analysis.uncertainty.calibration_constants`: each point's own error
        along the bar, the drift's, plate's and reference bar's constants), which the fit's
        residual variance does not show: such an error x enters the data as J^-1 x (absolute)
        or its variation (zeroed), and the fit maps it, G^-1 D^T X, into every parameter whose
        signature it resembles (the bars' sag, n_z^2 of nearly equal bars, takes their common
        constant: fitted with the twin's full pose it fell 6-22 sigma from the truth)."""
        d = self.base('train')
        if d.shape[1] == 0:
            return []
        x, cov = [], None
        total = sum(rows.idx.size for rows in self.train.rows)
        for rows, r in zip(self.train.rows, self.train.runs):
            cols, q = calibration_constants(r.ctx, rows.idx)
            x.append(rows.project(cols))
            q = q * (rows.idx.size / max(total, 1))
            cov = q if cov is None else cov + q
        dn, norms, gram_inv = _normal(d)
        moved = gram_inv @ (dn.T @ np.concatenate(x)) / norms[:, None]   # per unit of each
        out, start = [], self.train.nuisance.shape[1]
        for a in self.active:
            m = a.basis @ moved[start:start + a.basis.shape[1]]
            out.append(np.sqrt(np.maximum(np.einsum('pi,ij,pj->p', m, cov, m), 0.0)))
            start += a.basis.shape[1]
        return out

    def parameter_consistency(self, a: _Active, theta: FloatArray) -> float:
        """Birge ratio of the bars' agreement on an effect's fitted correction, at least 1
        (:meth:`_setting_consistency`): the effect's columns are replaced by each bar's share of
        its correction with the fitted parameters, each bar scaled on its own. A parameter that
        serves every bar (the bars' gravity sag, one figure for bars of one design) is measured
        by each bar on its own, and an error the model lacks moves each bar's figure its own
        way, which the fit's curvature does not see: the sag fitted with the twin's full pose
        fell 6-22 sigma from the truth (6 realistic twins, absolute fits). An effect with
        parameters of every bar's own fits each bar's share exactly: ratio 1."""
        if a.basis.shape[1] == 0 or not np.any(theta):
            return 1.0
        rows = self.train.rows[0]
        few = rows.idx[::max(rows.idx.size // 200, 1)]
        sig = a.effect.signature(self.train.runs[0].ctx, a.hyper, few)
        if np.max(np.sum(np.any(sig != 0.0, axis=0), axis=0)) <= 1:
            return 1.0      # (every parameter acts on one bar: each bar's share is its own fit)
        start = self._column_start(a)
        base = self.base('train')
        design = np.delete(base, np.arange(start, start + a.basis.shape[1]), axis=1)
        shares = np.stack([self.columns(a.effect, a.hyper, 'train', i) @ theta for i in range(6)],
                          axis=1)
        return self._setting_consistency(design, shares)

    def _setting_consistency(self, design: FloatArray, slopes: FloatArray) -> float:
        """Birge ratio of one setting's estimates from each bar: sqrt(chi^2 / (n - 1)) of the
        n bars' estimates about their weighted mean, at least 1.

        One setting serves every bar (a scale type has one signal period), and each bar that
        carries the effect measures it on its own: the fit is repeated with the change of each
        bar's correction per unit setting as a column of its own (``slopes``, (m, 6)). Where
        the model is right the bars agree within their covariance and the ratio is about 1;
        an error the model lacks moves each bar's estimate its own way, and the setting's
        sigma from the curvature alone did not see it: a 13 µm period from a C-axis run fell
        RMS 1.9 sigma from the truth (20 twins), the bars' estimates with chi^2 8-55 for 5
        degrees of freedom; scaled by the ratio, and with the search's bracket moved on
        (:func:`_golden_minimum`), RMS 1.11 over ten twins (1.41 with a one-axis run's unseen
        components read as the machine's motion)."""
        moving = np.linalg.norm(slopes, axis=0)
        bars = np.flatnonzero(moving > 1e-9 * max(float(moving.max()), 1e-300))
        if bars.size < 2:
            return 1.0
        coef, cov = self._fit(np.concatenate([design, slopes[:, bars]], axis=1), self.train.y)
        est, c = coef[-bars.size:], cov[-bars.size:, -bars.size:]
        w = np.linalg.pinv(c, hermitian=True)
        ones = np.ones(bars.size)
        mean = float(ones @ w @ est) / float(ones @ w @ ones)
        dev = est - mean
        chi2 = float(dev @ w @ dev)
        return math.sqrt(max(chi2 / (bars.size - 1), 1.0)) if np.isfinite(chi2) else 1.0

    def theta_for(self, effect: Effect, theta: FloatArray, run: _Run) -> FloatArray | None:
        """The parameters of ``effect`` that apply to ``run`` (its calibration's or run's set),
        or None when none of the fitted logs shares its group."""
        n_p = theta.size // self.n_groups(effect)
        g = self.group_index(effect, run)
        if g is None:
            return None
        return theta[g * n_p:(g + 1) * n_p]


def _golden_minimum(score: Callable[[float], float], lo: float, hi: float, steps: int = 16,
                    moves: int = 4) -> float:
    """The x in [lo, hi] with the least ``score(x)``, by golden-section search; a minimum at an
    end of the bracket moves the bracket on past that end by its width, up to ``moves`` times
    (to no more than ``moves`` widths beyond where it began).

    The bracket an effect gives around its first estimate is not always wide enough: a 13 µm
    period read from the spectrum of a C-axis run came 5.5e-4 short, the bracket (one bin
    either side) reached only to 1.9e-4 short, and the search stopped at that end, while the
    least error was 2e-5 from the truth: 32 of the period's σ away, which no σ claims."""
    golden = (math.sqrt(5) - 1) / 2
    seen: dict[float, float] = {}

    def f(x: float) -> float:
        if x not in seen:
            seen[x] = score(x)
        return seen[x]

    direction = 0
    for _ in range(moves + 1):
        a, b = lo, hi
        c1, c2 = b - golden * (b - a), a + golden * (b - a)
        for _ in range(steps):
            # (the point kept inside the smaller bracket is the one scored already: one new
            # score per step; computed afresh it missed the scores kept by an ulp, 146 scores
            # where 119 do on a 10-minute ISO run)
            if f(c1) < f(c2):
                b, c2 = c2, c1
                c1 = b - golden * (b - a)
            else:
                a, c1 = c1, c2
                c2 = a + golden * (b - a)
        # an end that never moved holds the minimum; the bracket moves on in one direction only
        step = -1 if a == lo else 1 if b == hi else 0
        if step == 0 or step == -direction:
            break
        direction = step
        width = hi - lo
        lo, hi = (lo - width, lo) if step < 0 else (hi, hi + width)
    return min(seen, key=seen.__getitem__)


# -- the analysis ------------------------------------------------------------------------------
def _datum_corrected(obs: Observation, residual: FloatArray, valid: NDArray[np.bool_],
                     train_idx: IntArray) -> FloatArray:
    """Residual with NaN where not usable and, for a zeroed reference, its training-part mean
    per component removed; for a reference that lags the MMD (``obs.lag``), that lag too,
    fitted over the training part (:func:`fit_lag`)."""
    r = residual.copy()
    r[~(valid & obs.usable)] = np.nan
    if obs.lag is not None:
        coef, _, offsets = fit_lag(obs, r, train_idx)
        return r - offsets - obs.lag @ coef
    if obs.datum:
        known = r[train_idx]
        known = known[np.all(np.isfinite(known), axis=1)]
        r = r - (known.mean(axis=0) if known.size else 0.0)
    return r


def _build_model(model: Model, terms: list[ModelTerm], records: dict[str, Any],
                 seen_m: FloatArray | None = None) -> Model:
    """The extended model: the input model's terms, the new terms (a length-dependent series
    held beyond the bar lengths ``seen_m`` (6, 2) [m] its fit saw within the values it takes
    within them), and the records of this analysis (``analysis`` history, ``validity``) in the
    file's extra keys. The one place where an analysed model is assembled."""
    terms = limited_to_seen(terms, seen_m)
    extra = dict(model.extra)
    for key, value in records.items():
        if key == 'analysis':
            history = list(extra.get('analysis') or []) if isinstance(extra.get('analysis'), list) else []
            history.append(value)
            extra['analysis'] = history
        else:
            extra[key] = value
    return Model(model.thermal_mode, model.plate_expansion, model.length_sigma_m,
                 [*model.terms, *terms], extra, '<extended model>', copy.deepcopy(model.uncertainty))


def _terms_for(sel: _Selector, chosen: list[tuple[_Active, FloatArray]], run: _Run) -> list[ModelTerm]:
    """Model terms of the chosen effects as they apply to ``run`` (per-calibration and per-run
    parameters of its own group; an effect none of whose fitted logs shares it is left out)."""
    terms: list[ModelTerm] = []
    for a, theta in chosen:
        t = sel.theta_for(a.effect, theta, run)
        if t is not None:
            terms.extend(a.effect.make_terms(run.ctx, a.hyper, t))
    # a common skew of the channels is the reference's lag where that lag is fitted: one log
    # whose reference shares the MMD's clock determines it (the skew is the device's)
    lagging = all(r.obs.lag is not None for r in sel.runs)
    for term in terms:
        if isinstance(term, SamplingSkewTerm):
            term.common_fitted = not lagging
    return terms


def _seen_lengths(runs: list[_Run]) -> tuple[FloatArray, FloatArray]:
    """The lowest and highest CDF length of each bar over the usable samples of ``runs``,
    (6,) each [m] (inf and -inf for a bar no sample saw)."""
    lo = np.full(6, np.inf)
    hi = np.full(6, -np.inf)
    for r in runs:
        lengths = r.ctx.base.cdf_lengths_m[r.usable]
        if lengths.size:
            lo = np.minimum(lo, lengths.min(axis=0))
            hi = np.maximum(hi, lengths.max(axis=0))
    return lo, hi


def analyze(runs: RunLog | list[RunLog], model: Model | None = None,
            calibration: Calibration | None = None, options: AnalysisOptions | None = None,
            progress: Callable[[str], None] | None = None) -> Analysis:
    """Close the loop on one log or a session of logs of one device (module docstring).

    runs : logs in our layout with raw counts and a reference (pose components or bar lengths)
    model : the current model; default the first log's, else CDF + thermal
    calibration : default each log's own
    progress : called with a line of text at each stage (for stderr)
    """
    runs = [runs] if isinstance(runs, RunLog) else list(runs)
    if not runs:
        raise AnalysisError('no log to analyse')
    # Many mid-size matrix products: on shared cores, multi-threaded BLAS waits for cores and
    # runs them 5-10x slower than one thread (measured: 33 s against 264 s for the tests).
    with threadpool_limits(limits=1, user_api='blas'):
        return _analyze(runs, model, calibration, options, progress)


def _select(sel: _Selector, effects: list[Effect], o: AnalysisOptions,
            say: Callable[[str], None], before: list[list[Candidate]] = ()) -> list[list[Candidate]]:
    """Stepwise selection (module docstring, 2); ``before``: the steps of an earlier selection
    this one goes on from (their numbering and first baseline)."""
    steps: list[list[Candidate]] = []

    def activate(cand: Candidate, eff: Effect) -> None:
        first = (list(before) + steps)[0]
        initial = first[0].mse0 if first else math.nan
        sel.active.append(_Active(eff, cand.hyper, cand.basis, cand.gain,
                                  (cand.mse0 - cand.mse1) / initial if initial > 0 else math.nan,
                                  cand.norms, weak=cand.weak))

    while len(sel.active) < o.max_effects:
        remaining = [e for e in effects if e.name not in {a.effect.name for a in sel.active}]
        if not remaining:
            break
        _, e0 = sel.baseline()
        # nothing is added to a residual that is already at the noise floor
        pieces = sel.test.pieces(e0)
        ratio = max(float(np.sqrt(np.mean(p ** 2, axis=0)).max()) for p in pieces if p.size)
        if ratio <= o.floor_factor:
            break
        say(f'step {len(before) + len(steps) + 1}: testing {len(remaining)} effects')
        cands = [sel.evaluate(e, e0) for e in remaining]
        judged = [c for c in cands if math.isfinite(c.mse1) and math.isfinite(c.n_left)]
        if judged and not any(c.verdict == 'significant' for c in cands):
            # the baseline's sample count holds the error being tested, whose correlation is
            # not the noise's: when nothing passes with it, the count of what the best
            # candidate leaves judges again (a linear scale error seen by an x laser, 87 times
            # the floor's mean square, counted 14 independent samples of 8000: calibration
            # points that left 1.1 times it, t 15.9, failed the criterion, nothing was found)
            count = min(judged, key=lambda c: c.mse1).n_left
            if count > judged[0].n_eff:
                for c in judged:
                    sel.judge(c, count)
        cands.sort(key=lambda c: (c.verdict != 'significant', c.delta_ic if math.isfinite(c.delta_ic) else math.inf))
        steps.append(cands)
        significant = [c for c in cands if c.verdict == 'significant']
        if not significant:
            pair = _joint_pair(sel, effects, cands, e0, o)
            if pair is None:
                break
            for cand, eff in pair:
                activate(cand, eff)
            first, second = pair[0][0], pair[1][0]
            first.verdict = f'added jointly with {second.effect} (neither alone passed)'
            second.verdict = f'added jointly with {first.effect}'
            cands[:] = [first, second] + [c for c in cands if c.effect not in (first.effect, second.effect)]
            sel.refine()
            continue
        # parsimony: the effect with the fewest identifiable parameters whose held-out
        # information criterion falls nearly as much as the best one's (the fall in the mean
        # square alone cannot tell 98.8 % from 99.85 %; the criterion's logarithm can); when
        # one of them has parameters that outlast the run, among those, measured against the
        # best of them (a drift's per-bar offsets, the CDF points 1.05 times its fall on a
        # realistic twin, took the calibration's constants into the run's own parameters, which
        # the model written leaves out; on another the sag, 0.886 of a drift's fall, is 0.915
        # of the best lasting one's)
        most = min(c.delta_ic for c in significant)
        near = [c for c in significant if c.delta_ic <= o.parsimony * most]
        lasting = [c for c in significant if CATALOGUE[c.effect].scope != 'run']
        if any(CATALOGUE[c.effect].scope != 'run' for c in near):
            most = min(c.delta_ic for c in lasting)
            near = [c for c in lasting if c.delta_ic <= o.parsimony * most]
        best = min(near, key=lambda c: (c.n_identifiable, c.delta_ic))
        cands.remove(best)
        cands.insert(0, best)
        best.verdict = 'added'
        activate(best, next(e for e in effects if e.name == best.effect))
        if len(sel.active) > 1:
            sel.refine()
    return steps


#: Groups of consecutive training blocks the check of a statement leaves out in turn.
JACKKNIFE_GROUPS = 8
#: When no single effect passes, the pairs among this many of the best candidates are tried.
PAIR_CANDIDATES = 3


def _joint_pair(sel: _Selector, effects: list[Effect], cands: list[Candidate], e0: FloatArray,
                o: AnalysisOptions) -> list[tuple[Candidate, Effect]] | None:
    """Two effects that pass together when neither passes alone, or None.

    Stepwise selection adds one effect at a time; two effects of similar signature (a channel
    delay and friction both follow the direction of motion) each explain only part of a
    residual that holds both, inconsistently over the blocks, and neither passes (a realistic
    twin: skew 11 % with t 2.8, friction 8 % with t 2.3, ten times the noise floor left). Of
    the ``PAIR_CANDIDATES`` best candidates that lower the held-out error, each pair is fitted
    jointly (the better one first, the other's setting chosen with it in place) and judged
    against the step's baseline by the same rules, the criterion charged for both effects'
    parameters; the pair whose criterion falls most is returned, the better one first."""
    hopeful = [c for c in cands if c.basis is not None and c.basis.shape[1] and c.gain > 0
               and math.isfinite(c.delta_ic)]
    hopeful = sorted(hopeful, key=lambda c: c.delta_ic)[:PAIR_CANDIDATES]
    by_name = {e.name: e for e in effects}
    best: tuple[float, list[tuple[Candidate, Effect]]] | None = None
    for i, first in enumerate(hopeful):
        for other in hopeful[i + 1:]:
            sel.active.append(_Active(by_name[first.effect], first.hyper, first.basis, first.gain,
                                      norms=first.norms, weak=first.weak))
            try:
                joint = sel.evaluate(by_name[other.effect], e0)
            finally:
                sel.active.pop()
            if joint.verdict != 'significant':
                continue
            joint.delta_ic += first.n_identifiable * math.log(joint.n_eff)
            if joint.delta_ic > -o.min_delta_ic:
                continue
            if best is None or joint.delta_ic < best[0]:
                best = (joint.delta_ic, [(first, by_name[first.effect]), (joint, by_name[other.effect])])
    return None if best is None else best[1]


def _parameter_covariance(a: _Active, theta: FloatArray, cov_beta: FloatArray,
                          every_bar: bool = False) -> FloatArray:
    """Covariance (P, P) of an effect's parameters as written [SI]: the identified directions'
    from the fit; and, unless a reference sees every bar (``every_bar``: its residual then
    measures what the terms leave, analysis/uncertainty.py), the other directions of the
    exercised parameters (not identified, or needing implausible values) with the mean square
    s^2 of the written parameters each: the minimum-norm fit set them to zero, an arbitrary
    choice (with a laser along x the friction amplitudes' other combinations left 1 µrad of
    roll that nothing claimed). A direction dropped as within ``min_t_param`` sigma of zero is
    determined, to be small: sigma^2 s^2 / (sigma^2 + s^2), the two taken as independent
    estimates (a weak direction of a laser run had sigma 0.8 µm where s was 0.3 µm)."""
    cov = a.basis @ cov_beta @ a.basis.T
    if every_bar:
        return cov
    norms = np.asarray(a.norms if a.norms is not None else np.zeros(a.basis.shape[0]), dtype=np.float64)
    used = norms > 0
    if not used.any() or a.basis.shape[1] == 0:
        return cov
    values = np.asarray(theta)[used]
    known = [a.basis[used]]
    weak = a.weak_basis()
    if weak is not None:
        weak = weak[used]
        known.append(weak)
    q = _orthonormal(np.concatenate(known, axis=1))
    rest = np.eye(int(used.sum())) - q @ q.T
    # as large as the written parameters are (the minimum-norm values of what was determined:
    # their spread is no measure of what was not)
    size2 = float(np.mean(values ** 2))
    block = size2 * 0.5 * (rest + rest.T)
    if weak is not None:
        # a weak direction's sigma, unless the data say less of it than that size does
        # (the two combined as independent estimates)
        length = np.linalg.norm(weak, axis=0)
        unit = weak / np.maximum(length, 1e-300)
        sd2 = (a.weak[1] * length) ** 2
        var = sd2 * size2 / np.maximum(sd2 + size2, 1e-300) if size2 > 0 else sd2
        block = block + (unit * var) @ unit.T
    cov[np.ix_(used, used)] += block
    return cov


def _unchecked(sel: _Selector, a: _Active, theta: FloatArray, cov_beta: FloatArray) -> list[Unchecked]:
    """What the effect would do to the pose components (or bars) a log's reference does not
    see, where the data do not determine it.

    At up to ``CONSEQUENCE_SAMPLES`` samples of each log, the term's change of every unobserved
    component is z = b^T theta (b: the component's row of J^-1 times the signature). Its
    uncertainty has a determined part, b^T V cov V^T b from the fit, and an undetermined part:
    the minimum-norm fit sets the parameter directions the data do not identify to zero, an
    arbitrary choice; with V_n the identified directions in the fit's unit-norm parameter scale,
    the part of b outside them, |b_n - V_n V_n^T b_n|, times the typical size of the identified
    coordinates, is what the unidentified ones could do; a direction dropped because its
    estimate is within ``min_t_param`` sigma of zero is determined (to be small) and counts with
    its sigma. A change whose RMS over the log's samples is larger than the component's noise
    floor (quantisation propagated, and the MMD's own sample-to-sample noise in that component)
    by more than the analysis' own "at the floor" factor, and less than twice its uncertainty's
    RMS there, is unchecked: the data do not tell it from none. (Judged sample by sample, any
    change of an unseen component that passes through zero in a log, as a pitch that follows
    the x travel does, was somewhere within twice its sigma: with a z laser run beside x, y, C
    and 6-DOF runs, the CDF points and the scale term the 6-DOF run determines were left out,
    the z run's pitch under the points 0.56″ ± 0.28″ at its largest; another 6-DOF run kept
    3-13 times its noise floor.)
    """
    out: list[Unchecked] = []
    basis = a.basis
    if basis.shape[1] == 0:
        return out
    norms = np.array(a.norms if a.norms is not None else np.ones(basis.shape[0]), dtype=np.float64)
    good = norms > 0
    norms[~good] = np.median(norms[good]) if good.any() else 1.0
    v_n = basis * norms[:, None]                   # orthonormal identified directions
    weak = a.weak
    beta = np.linalg.lstsq(basis, theta, rcond=None)[0]
    scale = float(np.sqrt(np.mean(beta ** 2))) if beta.size else 0.0
    n_p = theta.size // sel.n_groups(a.effect)
    # parameters that follow others (Effect.ties) act through them, as the fit saw them
    tie = sel.ties(a.effect, a.hyper, sel.coverage(a.effect, a.hyper)[0],
                   np.linalg.norm(sel.columns(a.effect, a.hyper, 'train'), axis=0) > 0)
    params = sel.parameters(a.effect, a.hyper)
    for r in sel.runs:
        g = sel.group_index(a.effect, r)
        if g is None:
            continue
        ctx, obs = r.ctx, r.obs
        idx = np.concatenate([r.split.fit_train, r.split.fit_test])
        idx = np.sort(idx)[:: max(1, idx.size // CONSEQUENCE_SAMPLES)]
        sig = a.effect.signature(ctx, a.hyper, idx)                  # (n, 6, P)
        full = np.zeros(sig.shape[:2] + (theta.size,))
        full[:, :, g * n_p:(g + 1) * n_p] = sig
        if tie is not None:
            full = full @ tie
        if obs.kind == 'pose':
            jinv = np.linalg.inv(jacobian(ctx.device.geometry, ctx.base.poses[idx]))
            b = np.einsum('nij,njp->nip', jinv, full)                 # (n, 6, PG)
            unseen = [c for c in range(6) if c not in obs.components]
            floor = _pose_floor(ctx, r.split.train_idx)
            names = POSE_NAMES
            to_report = np.array([1 / M_PER_UM] * 3 + [ARCSEC_PER_RAD] * 3)
            units = ['um'] * 3 + ['arcsec'] * 3
        else:
            b = full
            unseen = [c for c in range(6) if c not in obs.components]
            floor = np.full(6, ctx.device.encoder_resolution_m / math.sqrt(12.0))
            names = [f'bar{i + 1}' for i in range(6)]
            to_report = np.full(6, 1 / M_PER_UM)
            units = ['um'] * 6
        for c in unseen:
            bc = b[:, c, :]                                           # (n, PG)
            z = bc @ theta
            det = bc @ basis                                          # (n, r)
            var = np.einsum('nr,rs,ns->n', det, cov_beta, det)
            bn = bc / norms
            perp = bn - (bn @ v_n) @ v_n.T
            if weak is not None and weak[0].shape[1]:
                along = bn @ weak[0]                                  # (n, w)
                perp = perp - along @ weak[0].T
                var = var + (along ** 2) @ (weak[1] ** 2)
            undet = np.linalg.norm(perp, axis=1) * scale
            u = np.sqrt(np.maximum(var, 0.0) + undet ** 2)
            size, sigma = np.sqrt(np.mean(z ** 2)), np.sqrt(np.mean(u ** 2))
            if sel.options.floor_factor * floor[c] < size < 2.0 * sigma:
                # each parameter's share of the mean u^2: its row of the determined part
                # (b_p (Sigma b)_p) and the square of its undetermined part
                shared = bc @ (basis @ cov_beta @ basis.T)
                share = np.mean(bc * shared + (perp * scale) ** 2, axis=0)
                if weak is not None and weak[0].shape[1]:
                    share += np.mean(((along * weak[1]) @ weak[0].T) ** 2, axis=0)
                out.append(Unchecked(a.effect.name, r.run.path.name, names[c], units[c],
                                     float(size * to_report[c]), float(sigma * to_report[c]),
                                     float(floor[c] * to_report[c]),
                                     float(np.max(np.abs(z)) * to_report[c]),
                                     _seen_by(sel, a.effect, r, c),
                                     _largest_shares(params, share)))
    return out


def _seen_by(sel: _Selector, effect: Effect, run: _Run, component: int) -> list[str]:
    """The other logs whose references see ``component`` of the kind ``run``'s does (a pose
    component, or a bar's length) and that share the effect's parameters for ``run`` (none
    for a run's own, a drift's; of a per-calibration effect, those of its calibration)."""
    group = sel.group_index(effect, run)
    return [o.run.path.name for o in sel.runs if o is not run and o.obs.kind == run.obs.kind
            and component in o.obs.components and sel.group_index(effect, o) == group]


def _largest_shares(params: list[Parameter], share: FloatArray, most: int = 3) -> list[str]:
    """The names of the parameters (``params``: every group's, :meth:`_Selector.parameters`)
    with the largest ``share`` (PG,) of an uncertainty, largest first: at most ``most``, and
    no more once those named make up 80 % of it."""
    order = np.argsort(-share)
    total = float(np.sum(np.maximum(share, 0.0)))
    out: list[str] = []
    carried = 0.0
    for p in order[:most]:
        if share[p] <= 0.0 or (out and carried >= 0.8 * total):
            break
        out.append(params[p].name)
        carried += float(share[p])
    return out


def _analyze(logs: list[RunLog], model: Model | None, calibration: Calibration | None,
             options: AnalysisOptions | None, progress: Callable[[str], None] | None) -> Analysis:
    started = time.perf_counter()
    o = options or AnalysisOptions()
    say = progress or (lambda text: None)
    _check_one_device(logs)
    for run in logs if calibration is not None else []:
        calibration_for(run.calibration, calibration, str(run.path))   # (refused: raises)
    recorded = sum(run.n_samples for run in logs)
    logs, one_in = _thinned(logs, recorded, o.max_log_samples, say)
    model = model or logs[0].model or Model()
    datums, passes = [], []
    for run in logs:
        datum, made = _reference_datum(run, model, calibration, o)
        if datum.source == 'found':
            say(f'{run.path.name}: {datum.text()}')
        datums.append(datum)
        passes.append(made)
    stated = _stated_terms(logs[0].device, model, o) if _needs_statement(logs, datums) else []
    if stated:      # (the passes made to decide were of the model without them)
        model = replace(model, terms=[*model.terms, *stated])
        passes = [None] * len(logs)
    runs = [_prepare(k, run, model, calibration, o, say, datum, tuple(stated), made)
            for k, (run, datum, made) in enumerate(zip(logs, datums, passes))]
    stated_text = [_stated_text(t) for t in stated]
    seen: dict[str, str] = {}
    for r in runs:
        if r.ident in seen:
            raise AnalysisError(f'{r.name} and {seen[r.ident]} are the same run (same raw counts): '
                                'give each run once')
        seen[r.ident] = r.name
    first = runs[0]
    features = residual_features(first.ctx)
    structure_before = _structure(first.res_before / first.floor, first.split.fit_test, features)

    # -- trace: stepwise selection on the linearised model
    effects = [e for e in catalogue(o.effects) if e.name not in o.exclude]
    not_applicable: dict[str, str] = {}
    for e in effects:
        why = [e.applicable(r.ctx) for r in runs]
        if all(why):
            not_applicable[e.name] = why[0] or ''
    effects = [e for e in effects if e.name not in not_applicable]
    sel = _Selector(runs, o)
    steps = _select(sel, effects, o, say)

    # -- claims, whole-pose check, validation with the pipeline
    found: list[Found] = []
    not_claimed: list[Found] = []
    unchecked: list[Found] = []
    growing: list[ModelTerm] = []      # (the terms of the bars' lengths among them)
    validated = False
    afters: list[tuple[Processed, FloatArray]] | None = None
    stats_pred = None
    chosen: list[tuple[_Active, FloatArray]] = []
    set_aside: list[_Active] = []
    retried: set[str] = set()
    # a reference that sees every bar measures what the terms leave (the model's residual);
    # without one, what the data did not determine must be claimed by the terms themselves
    every_bar = any(r.obs.sees_every_bar for r in runs)
    for _ in range(4 * o.max_effects + 2):
        if not sel.active:
            break
        fits, e_pred = sel.final_fit()
        constant = sel.run_constant_sigma()
        current = []
        for a, (theta, sigma, cb), sys_sigma in zip(sel.active, fits, constant):
            params = sel.parameters(a.effect, a.hyper)
            ident = np.linalg.norm(a.basis, axis=1) > 0
            first_theta = sel.theta_for(a.effect, theta, first)
            # what is claimed of a parameter: the calibration's constants it took, and for one
            # that serves every bar how far the bars agree on it (the pose's claim keeps the
            # least-squares part: its residual stands for the rest)
            sigma = np.hypot(sigma * sel.parameter_consistency(a, theta), sys_sigma)
            shift = sel.setting_shift(a, theta)
            if shift is not None:
                # what is claimed of each parameter includes its setting's uncertainty
                sigma = np.hypot(sigma, shift[1] - theta)
            current.append(Found(a.effect.name, a.effect.title, a.effect.term_type, a.hyper,
                                 a.effect.hyper_label(a.hyper), params, theta, sigma, ident,
                                 a.step_gain, a.effect.interpret(
                                     first.ctx, a.hyper, first_theta if first_theta is not None else theta,
                                     sigma[:first_theta.size] if first_theta is not None else sigma),
                                 covariance=_parameter_covariance(a, theta, cb, every_bar),
                                 setting_shift=shift,
                                 alternatives=a.effect.undetermined_forms(a.hyper, [r.ctx for r in runs])))
        # an effect must remove most of the structure along its own coordinate; one that fits
        # only part of it follows something else (the worst is dropped, then all are refitted)
        worst_k, worst_ratio, worst_txt = -1, 0.0, ''
        for k, (a, f) in enumerate(zip(sel.active, current)):
            ratio, feature = sel.own_structure_ratio(a, f.value, e_pred)
            if ratio > o.claim_ratio:
                # effects that follow the same coordinate (a scale error and the CDF points
                # both follow a bar's length) share what they explain: each alone leaves it
                # to the other, and dropping both left 10 x the floor along that length
                partners = [(b, g.value) for j, (b, g) in enumerate(zip(sel.active, current))
                            if j != k and feature in b.effect.diagnostics(first.ctx, b.hyper)]
                if partners and sel.own_structure_ratio(a, f.value, e_pred, partners)[0] <= o.claim_ratio:
                    continue
            if ratio > o.claim_ratio and ratio > worst_ratio:
                worst_k, worst_ratio = k, ratio
                worst_txt = (f'{100 * (1 - ratio):.0f} % of the structure along its own coordinate '
                             f'({feature}) removed, less than {100 * (1 - o.claim_ratio):.0f} %: it '
                             'follows part of something else')
        if worst_k >= 0:
            f = current[worst_k]
            f.claimed, f.reason = False, worst_txt
            not_claimed[:] = [g for g in not_claimed if g.effect != f.effect] + [f]
            set_aside.append(sel.active.pop(worst_k))
            # what it took from the residual may be another effect's, which the selection
            # passed over for it (a drift's free offsets took a gravity sag's constant): the
            # selection goes on without it
            aside = {a.effect.name for a in set_aside}
            steps += _select(sel, [e for e in effects if e.name not in aside], o, say, steps)
            continue
        # an effect set aside while a partner that followed the same coordinate was in the
        # model (a scale error judged with the CDF points in place) is tried once more now
        # that the rest is claimed: the last one set aside first
        retry = next((a for a in reversed(set_aside) if a.effect.name not in retried), None)
        if retry is not None:
            retried.add(retry.effect.name)
            fit = sel.reduce(retry.effect, retry.hyper)    # its directions with the rest in place
            if fit['basis'].shape[1]:
                sel.active.append(retry.refitted(retry.hyper, fit))
            continue
        not_claimed[:] = [g for g in not_claimed
                          if g.effect not in {a.effect.name for a in sel.active}]
        # the whole pose: what no reference saw must be determined, or stay at the floor
        flagged = []
        for k, (a, f, (theta, _s, cb)) in enumerate(zip(sel.active, current, fits)):
            if not a.written:
                continue
            f.unchecked = _unchecked(sel, a, theta, cb)
            if f.unchecked and not o.accept_unchecked:
                flagged.append(k)
        if flagged:
            # the one that would move an unseen component most (in floors) is set aside first
            # (kept in the fit, not written); the others are checked again
            def size(f: Found) -> float:
                return max(u.change / max(u.floor, 1e-300) for u in f.unchecked)
            k = max(flagged, key=lambda j: size(current[j]))
            f = current[k]
            f.claimed = False
            worst = max(f.unchecked, key=lambda u: u.change / max(u.floor, 1e-300))
            f.reason = worst.message() + ' (not written; --accept-unchecked writes it)'
            unchecked.append(f)
            if f.term_type in LENGTH_TERMS:
                growing.extend(_terms_for(sel, [(sel.active[k], f.value)], runs[-1]))
            sel.active[k].written = False
            continue
        if not any(a.written for a in sel.active):
            break
        say('validating the extended model with the pipeline')
        chosen = [(a, f.value) for a, f in zip(sel.active, current) if a.written]
        afters = []
        total_b = total_a = 0.0
        for r in runs:
            trial = _build_model(model, _terms_for(sel, chosen, r), {})
            after = run_pipeline(r.run.device, r.calibration, trial, r.run.times_s, r.run.counts)
            res_after = _datum_corrected(r.obs, r.obs.residual(after), after.measured(r.obs.kind),
                                         r.split.train_idx)
            afters.append((after, res_after))
            test = r.split.test_idx
            both = test[np.all(np.isfinite(res_after[test]), axis=1) & np.all(np.isfinite(r.res_before[test]), axis=1)]
            total_b += float(np.sum((r.res_before[both] / r.floor) ** 2))
            total_a += float(np.sum((res_after[both] / r.floor) ** 2))
        validated = total_b > 0 and math.sqrt(total_a) <= (1.0 - 0.5 * o.min_gain) * math.sqrt(total_b)
        worse = _made_worse(runs, afters) if validated else ''
        if worse:
            # a component some reference sees gets worse: the last effect written is set aside
            # (kept in the fit, not written) and the rest validated again
            k = max(j for j, a in enumerate(sel.active) if a.written)
            f = current[k]
            f.claimed = False
            f.reason = (f'with it the pipeline makes {worse}: not written (a correction that is only '
                        'half of an effect, e.g. friction without the friction state the bars had on '
                        'the calibration points, can do that)')
            unchecked.append(f)
            sel.active[k].written = False
            afters, chosen, validated = None, [], False
            continue
        if not validated:
            for f in current:
                f.claimed = False
                f.reason = ('the pipeline with the terms did not confirm the linearised gain '
                            f'(held-out sum of squares {total_b:.3g} → {total_a:.3g} floors²)')
            not_claimed += [f for a, f in zip(sel.active, current) if a.written]
            sel.active = []
            afters = None
            chosen = []
            break
        found = [f for a, f in zip(sel.active, current) if a.written]
        for a, f in zip(sel.active, current):
            f.explained = a.explained
        first_pred = sel.test.pieces(e_pred)[0]
        stats_pred = component_errors(first.obs, -first_pred * first.floor, np.arange(first_pred.shape[0]))
        break

    # -- what the data say of the statement the analysis started from, claimed with the model
    statement, check = _check_statement(sel, stated, first.ctx.device.gravity_sag_sigma_m)
    if check is not None:
        stated_text[0] += _check_text(check)

    # -- figures per log, and what remains
    summaries: list[RunSummary] = []
    for k, r in enumerate(runs):
        res_after = afters[k][1] if afters else None
        reference = r.obs.description
        if r.axis is not None:
            reference += (f'; {", ".join(POSE_NAMES[c] for c in r.axis.components)} read as the '
                          f'machine\'s motion along {r.obs.names[0]}')
        summaries.append(RunSummary(
            r.name, r.ident, r.cal_key, reference, r.obs.names, r.obs.units,
            int(r.usable.sum()), {n: float(f * s) for n, f, s in zip(r.obs.names, r.floor, r.obs.to_report)},
            component_errors(r.obs, r.res_before, r.split.test_idx),
            component_errors(r.obs, res_after, r.split.test_idx) if res_after is not None else None,
            log_problem=r.run.problem.as_dict() if r.run.problem else None,
            given=(component_errors(r.obs, r.res_given, r.split.test_idx)
                   if r.res_given is not None else None), lag=r.lag, datum=r.datum))
    final = [afters[k][1] if afters else r.res_before for k, r in enumerate(runs)]
    ratios = [np.sqrt(np.nanmean((res[r.split.fit_test] / r.floor) ** 2, axis=0)) for r, res in zip(runs, final)]
    at_floor = bool(all(np.all(x <= o.floor_factor) for x in ratios))
    res_after_first = afters[0][1] if afters else None
    structure_after = [] if at_floor else _structure(final[0] / first.floor, first.split.fit_test, features)

    # -- the model file: for other runs, so without what belongs to the run fitted (a drift's
    # offset and rate: a reading that settles after handling, or a glitch of a few counts, was
    # fitted as one, and its rate carried on over a 300 s run moved z by 0.9 µm); its size is
    # claimed as their uncertainty (analysis/uncertainty.py)
    extended = None
    lasting: list[tuple[_Active, FloatArray]] = []
    lasting_cov: dict[str, FloatArray] = {}
    if chosen:
        lasting, lasting_cov = _lasting_fit(sel, chosen, every_bar)
        extended = _build_model(model, _terms_for(sel, lasting, runs[-1]),
                                _records(runs, found, summaries, stated=stated_text),
                                np.stack(_seen_lengths(runs), axis=1))

    # -- leave one run out: each log predicted by the model fitted on the others
    unseen: list[ResidualRun] = []
    partial: list[tuple[int, str]] = []
    validation = ('within-run: held-out time blocks of one log, interleaved with the blocks the '
                  'model was fitted on (not independent validation)')
    if len(runs) > 1:
        validation = ('leave-one-run-out: each log predicted by the model fitted on the others '
                      '(the pipeline re-run); within-run held-out blocks as a second figure')
        if chosen and o.leave_one_out:
            say('leave-one-run-out: refitting without each log')
            partial = _leave_one_out(runs, sel.active, model, o, summaries, unseen)
        elif chosen:
            # asked not to refit: no figure rather than the "before" one under an "after" name
            validation = ('within-run: held-out time blocks of each log (leave-one-run-out was '
                          'not computed: turned off)')
        else:
            for s, r in zip(summaries, runs):
                every = np.flatnonzero(r.usable)
                whole = _datum_corrected(r.obs, r.obs.residual(r.ctx.base), r.ctx.base.measured(r.obs.kind), every)
                s.loro_before = component_errors(r.obs, whole, every)
                s.loro_after = s.loro_before
                s.loro_note = 'nothing added: the model is unchanged'

    if extended is not None:
        # the model's own uncertainty: its terms' parameter covariance and the residual left,
        # on logs the fit never saw when there are several (analysis/uncertainty.py)
        refit = {id(a): t for a, t in lasting}
        written = [replace(f, covariance=lasting_cov.get(f.effect, f.covariance)) for f in found]
        effects = fitted_effects(sel, [(a, refit.get(id(a), t)) for a, t in chosen], written,
                                 runs[-1], [t for _, t in chosen]) + statement
        # the residual of logs the fit never saw, when each was predicted with every term the
        # model writes: a log predicted without some (the others did not determine them) left
        # what they remove in its residual, and the demo's session model (x, y lasers, C
        # rotary, 6-DOF, absolute), whose 6-DOF log was predicted without the calibration's
        # points and the scale terms, claimed 3-17 times the error of new 6-DOF runs
        if partial and afters:
            unseen = unseen + [ResidualRun(runs[k].ctx, *afters[k], runs[k].split.test_idx)
                               for k, _ in partial]
        if unseen:
            extended = with_fit_uncertainty(
                extended, runs[-1].ctx, effects, unseen, unseen=True, growing=growing,
                residual_from=None if not partial else (
                    'logs the fit did not see (leave-one-run-out), and held-out blocks of the '
                    'logs it predicted without some of its terms: '
                    + '; '.join(text for _, text in partial)))
        elif afters:
            extended = with_fit_uncertainty(extended, runs[-1].ctx, effects, [
                ResidualRun(r.ctx, after, res, r.split.test_idx)
                for r, (after, res) in zip(runs, afters)], growing=growing)

    # -- nothing written, and a residual the budget claims too little for, or a read noise where
    # the bars stood still that a stream in motion would not claim: the model's terms stay and
    # its uncertainty carries them (an error no catalogued effect explains, an interference at
    # a frequency no term follows, is still one the covariance must cover)
    uncertainty_only = ''
    if extended is None:
        every = [np.flatnonzero(r.usable) for r in runs]
        level = 1.0 - (1.0 - CLAIM_LEVEL) / sum(len(r.obs.components) for r in runs)
        beyond = [(float(x[j] / max(lim[j], o.under_claim)), float(x[j]), r, j)
                  for r, idx in zip(runs, every)
                  for x, lim in [beyond_claim(r.ctx, r.res_before, idx, level)] for j in range(x.size)]
        excess, ratio, r, k = max(beyond, key=lambda t: t[0], default=(0.0, 0.0, first, 0))
        if excess > 1.0:
            uncertainty_only = (f'{r.obs.names[k]} of {r.run.path.name} has {ratio:.2g} × the RMS the '
                                'budget claims')
        else:
            uncertainty_only = _noise_beyond_claim(runs, o.under_claim)
        if uncertainty_only:
            extended = _build_model(model, [], _records(runs, [], summaries, uncertainty_only,
                                                        stated_text))
            extended = with_fit_uncertainty(
                extended, runs[-1].ctx, statement,
                [ResidualRun(r.ctx, r.ctx.base, r.res_before, idx) for r, idx in zip(runs, every)],
                growing=growing,
                residual_from='the logs analysed, every usable sample (no term was fitted to them)')

    first_summary = summaries[0]
    contributions: dict[str, FloatArray] = {}
    per_bar_after = None
    if res_after_first is not None:
        per_bar_after = _per_bar(first.ctx, res_after_first, first.split.test_idx)
        for f in found:
            contributions[f.effect] = (first.res_before - res_after_first if len(found) == 1
                                       else _contribution(sel, first, f))
    glitches = _glitches(runs, afters)
    conclusion = _conclusion(runs, summaries, found, not_claimed, unchecked, at_floor,
                             structure_after, validation, uncertainty_only, stated_text, glitches)
    common = extended.uncertainty.fit.record.get('common_mode_nm') if extended is not None else None
    if common:
        seen = list(dict.fromkeys(n for r in runs for n in r.obs.names))
        unseen = ', '.join(n for n in POSE_NAMES if n not in seen)
        conclusion += (f' The references see {", ".join(seen)} only: what the bars\' error does to '
                       f'{unseen} is claimed from the budget\'s shape scaled to what they showed, and '
                       f'an error the six bars share (it moves z) as large as the whole excess '
                       f'({common:.3g} nm): a prior, not a measurement; record a run that sees '
                       f'{unseen}.')
    return Analysis(first.name, o, first.obs, first.split, first.run.times_s, first.floor, first.ctx.base,
                    afters[0][0] if afters else None, first.res_before, res_after_first, steps, found,
                    not_claimed, first_summary.before, first_summary.after, stats_pred,
                    structure_before, structure_after, at_floor, validated and bool(found), extended,
                    conclusion, features, contributions, _per_bar(first.ctx, first.res_before, first.split.test_idx),
                    per_bar_after, time.perf_counter() - started, not_applicable, summaries, unchecked,
                    validation, next((s.log_problem for s in summaries if s.log_problem), None),
                    uncertainty_only, stated_text, check, glitches, one_in, recorded)


#: What the analysis holds per sample of its logs, about: the pipeline's passes of each trial
#: model, the effects' signatures and the stateful features they are made of (measured: 1.8 GB
#: for a 10-minute 1 kHz log, 4.8 GB for 30 minutes) [bytes].
BYTES_PER_SAMPLE = 2700


def _thinned(logs: list[RunLog], total: int, most: int, say: Callable[[str], None]
             ) -> tuple[list[RunLog], int]:
    """The logs at every k-th sample, k the smallest that keeps their ``total`` samples within
    ``most``, and k (1: as recorded). The analysis holds about :data:`BYTES_PER_SAMPLE` per
    sample, so that an hour at 1 kHz would need 10 GB; the effects it fits are of the bars'
    lengths, their motion and time, which a lower rate still samples (a friction state turns
    over within micrometres of travel, a latch skew follows the velocity a backward difference
    over k samples gives, up to the 0.1 s beyond which it is not formed)."""
    if most < 1:
        raise AnalysisError(f'max_log_samples must be at least 1, got {most}')
    if total <= most:
        return logs, 1
    k = -(-total // most)
    rate = logs[0].device.sample_rate_hz / k
    say(f'{total} samples in the logs: one in {k} analysed ({rate:.4g} Hz at the terminal\'s '
        f'rate), to hold at most {most} (about {BYTES_PER_SAMPLE * most / 1e9:.1f} GB; '
        '--max-log-samples)')
    return [run.every(k) for run in logs], k


#: How far (in its sigma) the data's estimate of a stated figure's error may lie from what the
#: statement allows before the data dispute it (and their estimate replaces the statement's
#: uncertainty): 3, a 0.3 % chance for a true statement.
DISPUTE_SIGMAS = 3.0


def _check_statement(sel: _Selector, stated: list[ModelTerm], prior_m: float | None = None
                     ) -> tuple[list[FittedEffect], dict[str, Any] | None]:
    """What the data say of the stated sag the analysis started from (:func:`_stated_terms`),
    with the effects the fit applies in place, and what the model then claims of its error, as
    an effect whose parameter covariance the pose claims.

    A zeroed reference sees how the sag varies with the pose, n_z^2, which follows each bar's
    length closely: errors of the calibration points carry the same signature. Alone, the
    sag's error estimate took them (after a one-sided routine, true statements were put -285
    to +109 nm off, sigma 17-37 nm, 8 twins); so it is estimated jointly with every
    calibration point's error, each as uncertain as the budget claims it (``sel.check``'s
    nuisance, :func:`_point_sd`): -158 to +89 nm on the same seeds with their sag drawn
    +- 15 % (d against each twin's own), sigma 40-60 nm. That is
    the error d +- s of the statement as the data see it.

    ``prior_m``, the figure's stated uncertainty sigma_p (``bars.gravity_sag_uncertainty_nm``),
    is what is known of it beforehand: the claim is the posterior's, sqrt(m^2 + v) with m = d
    sigma_p^2 / (sigma_p^2 + s^2), v = sigma_p^2 s^2 / (sigma_p^2 + s^2) (the statement is kept:
    m is claimed, not applied), unless the data dispute the statement (|d| beyond
    DISPUTE_SIGMAS sqrt(s^2 + sigma_p^2)): then, as without a stated uncertainty, sqrt(d^2 + s^2),
    what an error estimated d +- s with nothing known of it beforehand leaves. Where the data
    do not exercise the bars' inclination, or determine the sag no better than the figure
    itself (s >= the figure: ``undetermined``), the statement is not checked: sigma_p is
    claimed, or without it the whole figure. None and no effect when there is no statement,
    or a fitted sag in its place."""
    if not stated or any(a.effect.name == 'gravity_sag' for a in sel.active):
        return [], None
    effect, points = catalogue(['gravity_sag', 'calibration_points'])
    got = sel.check(effect, ((points, _point_sd(sel, points), None), *_undetermined(sel, points)))
    check: dict[str, Any] = {'error_nm': None, 'sigma_nm': None, 'disputed': False,
                             'undetermined': False,
                             'prior_nm': None if prior_m is None else prior_m * 1e9}
    figure = float(np.max(np.abs(stated[0].params()['sag_um']))) * M_PER_UM
    unchecked = prior_m if prior_m is not None else figure
    if got is None or not np.all(np.isfinite(got[0])) or not float(got[1][0]) > 0.0:
        claimed = unchecked
    else:
        d, s = float(got[0][0]), float(got[1][0])
        check.update(error_nm=d * 1e9, sigma_nm=s * 1e9)
        if s >= figure:
            # the data do not determine the sag to its own size: what they put it at is what
            # the fit's other effects and the points' errors leave along the inclination, not
            # a check (an x-axis laser and an A-axis run put an exact 100 nm statement's error
            # at +7.0 +- 2.6 µm; claimed, the roll of that A run was 32 times its error)
            check['undetermined'] = True
            claimed = unchecked
        elif prior_m is not None and abs(d) <= DISPUTE_SIGMAS * math.hypot(s, prior_m):
            p2, s2 = prior_m * prior_m, s * s
            claimed = math.sqrt((d * p2 / (p2 + s2)) ** 2 + p2 * s2 / (p2 + s2)) if p2 else 0.0
        else:
            check['disputed'] = prior_m is not None
            claimed = math.hypot(d, s)
    check['claimed_nm'] = claimed * 1e9
    return [FittedEffect(effect, None, np.array([[claimed * claimed]]), np.zeros(1))], check


def _undetermined(sel: _Selector, skip: Effect) -> list[tuple[Effect, FloatArray, Any]]:
    """The active effects (but ``skip``) as nuisance of a check (:meth:`_Selector.check`): each
    parameter with the standard deviation the model claims of it (:func:`_parameter_covariance`
    without a reference of every bar: the directions the data did not determine as large as the
    written values). The fit set those directions to zero; a check that took that as known let
    them into its estimate (a 5 s run's kinematic term: the sag's error put at 33 µm, 6.5 sigma
    off an exact statement)."""
    if not sel.active:
        return []
    fits, _ = sel.final_fit()
    out = []
    for a, (theta, _, cb) in zip(sel.active, fits):
        if a.effect.name != skip.name:
            sd = np.sqrt(np.maximum(np.diag(_parameter_covariance(a, theta, cb)), 0.0))
            out.append((a.effect, sd, a.hyper))
    return out


def _point_sd(sel: _Selector, points: Effect) -> FloatArray:
    """What the calibrations say of their points' errors, per parameter of the
    calibration_points effect [m]: each bar's point uncertainty as the budget claims it (the
    capture, the seating, the encoders' sub-divisional error and, after a one-sided routine,
    the friction state each point was captured in), the largest over the logs' calibrations."""
    per_bar = np.zeros(6)
    for r in sel.runs:
        b = base_budget(r.ctx)
        per_bar = np.maximum(per_bar, np.sqrt(b.point_var_m2 + b.point_friction_m2
                                              + b.subdivision_left_m2))
    n = len(sel.parameters(points, None))
    return np.resize(per_bar, n)


def _check_text(check: dict[str, Any]) -> str:
    """What :func:`_check_statement` found, as the tail of the statement's line."""
    prior = check['prior_nm']
    known = '' if prior is None else f' (stated ± {prior:.0f} nm)'
    claim = f'claimed with the model as ± {check["claimed_nm"]:.0f} nm (one sigma)'
    if check['error_nm'] is None:
        return (f'; the data do not exercise the bars\' inclination: not checked{known}, '
                + claim)
    said = (f'; the data put its error at {check["error_nm"]:+.0f} ± '
            f'{1.96 * check["sigma_nm"]:.0f} nm (95 %, with every calibration point\'s error)')
    if check['undetermined']:
        return (said + f', no better than the figure itself: not checked{known}, ' + claim)
    if check['disputed']:
        return said + f', which disputes the statement{known}: {claim}'
    if prior is not None:
        return said + f'{known}: together, {claim}'
    return said + ', ' + claim


def _stated_text(term: ModelTerm) -> str:
    """One line on a term the analysis started from (:func:`_stated_terms`)."""
    sag = float(np.mean(term.params()['sag_um'])) * 1e3
    return (f'the bars\' gravity sag the device description states (bars.gravity_sag_nm: a '
            f'horizontal bar reads {sag:.4g} nm long), not fitted')


def _noise_beyond_claim(runs: list[_Run], limit: float) -> str:
    """Why the read noise measured where the logs' bars stood still must go into the model
    (a stream that never stands still claims the calibration's figure), or '': when it makes a
    bar's per-sample claim (its count's quantisation and the read noise) more than ``limit``
    times larger than the calibration's figure does."""
    noise = measured_read_noise([r.ctx for r in runs])
    if noise is None:
        return ''
    calibrated = max((r.calibration.uncertainty.read_noise_m or 0.0 for r in runs), default=0.0)
    q2 = runs[0].ctx.device.encoder_resolution_m ** 2 / 12.0
    grow = np.sqrt((q2 + noise[:6] ** 2) / (q2 + calibrated ** 2))
    j = int(np.argmax(grow))
    if grow[j] <= limit:
        return ''
    return (f'bar{j + 1}\'s read noise where it stood still, {noise[j] * 1e9:.3g} nm against the '
            f'calibration\'s {calibrated * 1e9:.3g} nm, makes its per-sample claim {grow[j]:.2g} × '
            'larger')


def _records(runs: list[_Run], found: list[Found], summaries: list[RunSummary],
             uncertainty_only: str = '', stated: list[str] | None = None) -> dict[str, Any]:
    """The records a written model carries of its analysis: the ``analysis`` history entry
    (logs, references, what was added and the held-out figures) and the ``validity`` range."""
    entry = {
        'created': datetime.now(timezone.utc).isoformat(timespec='seconds'),
        'logs': [r.name for r in runs], 'log': runs[0].name,
        'reference': '; '.join(f'{r.run.path.name}: {r.obs.description}' for r in runs),
        'added': [{'effect': f.effect, 'term': f.term_type, 'setting': f.hyper_label,
                   'parameters': f.parameter_rows(), 'in_terms': _lasting(f)} for f in found],
        'held_out_rms_before': {s.name: s.rms for s in summaries[0].before},
        'held_out_rms_after': {s.name: s.rms for s in summaries[0].after or []},
        'units': {s.name: s.unit for s in summaries[0].before},
        'per_calibration_parameters_of': runs[-1].cal_key,
        'per_calibration_uncertainty': runs[-1].calibration.uncertainty.to_dict(),
    }
    terminal = runs[-1].calibration.terminal
    if terminal is not None and terminal.serial:
        entry['per_calibration_terminal'] = terminal.serial
    if uncertainty_only:
        entry['uncertainty_only'] = uncertainty_only
    if stated:
        entry['stated'] = stated
    return {'analysis': _ascii(entry), 'validity': _ascii(_validity(runs))}


def _lasting_fit(sel: _Selector, chosen: list[tuple[_Active, FloatArray]], every_bar: bool = False
                 ) -> tuple[list[tuple[_Active, FloatArray]], dict[str, FloatArray]]:
    """The chosen effects whose parameters outlast the run, with their parameters as the model
    for other runs needs them: fitted again without the run's own effects (a drift), holding
    their means. In the joint fit a drift's offsets, held with them, took the opposite of the
    CDF points' mean change; the points written without it moved yaw's mean 48 times, and
    pitch's 6 times, what the budget claims, where refitted alone at most 1.7 times (a
    localised length error, zeroed reference).

    Each one's identified directions are chosen again without them: chosen beside a drift,
    the CDF points did not identify the bars' constants its offsets had taken (they could not
    be told apart), and refitted in those directions alone they could not take them back. A
    twin warmed 5 °C, whose 30 s absolute fit found a drift with no rate to speak of (its
    offsets, 0.18-0.59 µm, the bars' thermal mismatch there), wrote points that left 240 nm
    of x in the fitted run and 406 nm in a new one; with the directions chosen again, 50 nm
    and 69 nm, as a twin whose fit found no drift.

    returns : the lasting effects with their parameters, and the covariance of the parameters
        of each one refitted (by effect name; :func:`_parameter_covariance`)
    """
    lasting = [(a, t) for a, t in chosen if a.effect.scope != 'run']
    if not lasting or len(lasting) == len(chosen):
        return lasting, {}
    everyone = sel.active
    sel.active = [a for a in everyone if a.effect.scope != 'run']
    try:
        sel.refine(settings=False)
        fits, _ = sel.final_fit()
        refit = {a.effect.name: (a, theta, cb) for a, (theta, _, cb) in zip(sel.active, fits)}
    finally:
        sel.active = everyone
    covariance = {name: _parameter_covariance(a, theta, cb, every_bar)
                  for name, (a, theta, cb) in refit.items()}
    return [(a, refit[a.effect.name][1]) for a, _ in lasting], covariance


def _lasting(f: Found) -> bool:
    """Whether a found effect's terms go into the model written: not those of an effect whose
    parameters belong to the run fitted (``Effect.scope == 'run'``)."""
    return CATALOGUE[f.effect].scope != 'run'


def _made_worse(runs: list[_Run], afters: list[tuple[Processed, FloatArray]]) -> str:
    """The first observed component whose held-out RMS the written model makes worse by more
    than its noise floor, as text ('' when none)."""
    for r, (_, res_after) in zip(runs, afters):
        test = r.split.test_idx
        both = test[np.all(np.isfinite(res_after[test]), axis=1) & np.all(np.isfinite(r.res_before[test]), axis=1)]
        if not both.size:
            continue
        before = np.sqrt(np.mean(r.res_before[both] ** 2, axis=0))
        after = np.sqrt(np.mean(res_after[both] ** 2, axis=0))
        for k in np.flatnonzero(after > before + r.floor):
            s = r.obs.to_report[k]
            return (f'{r.obs.names[k]} of {r.run.path.name} worse ({before[k] * s:.3g} → '
                    f'{after[k] * s:.3g} {_unit(r.obs.units[k])}, floor {r.floor[k] * s:.2g})')
    return ''


def _validity(runs: list[_Run]) -> dict[str, Any]:
    """What the model was fitted and validated on: the runs (by content hash), their references,
    the range of each bar's length and of the temperature (nodes warn outside them)."""
    lo, hi = _seen_lengths(runs)
    t_lo, t_hi = math.inf, -math.inf
    for r in runs:
        base = r.ctx.base
        sel = r.usable
        if sel.any():
            temp = base.temp_change_c[sel] + (r.calibration.ambient_c or 0.0)
            t_lo, t_hi = min(t_lo, float(temp.min())), max(t_hi, float(temp.max()))
    return {
        'runs': [{'log': r.name, 'ident': r.ident, 'calibration': r.cal_key,
                  'reference': r.obs.names, 'reference_kind': r.obs.kind,
                  'samples': int(r.usable.sum()), 'duration_s': float(r.run.times_s[-1])} for r in runs],
        'bar_range_mm': [[float(a / M_PER_MM), float(b / M_PER_MM)] for a, b in zip(lo, hi)],
        'temperature_c': [t_lo, t_hi],
        'temperature_is_absolute': all(r.calibration.ambient_c is not None for r in runs),
    }


def _leave_one_out(runs: list[_Run], active: list[_Active], model: Model,
                   o: AnalysisOptions, summaries: list[RunSummary],
                   unseen: list[ResidualRun] | None = None) -> list[tuple[int, str]]:
    """Each log predicted by the effects found (same settings) refitted on the other logs (the
    ones not written stay in the fit, as in the analysis); the pipeline re-run over the whole
    log with the written ones that the other logs determine on their own (:func:`_unchecked`).
    Parameters of a calibration or run that no other log shares cannot be predicted and are
    left out for that log (said in the note). The figure is also given on the samples within
    the bar lengths the other logs covered (:func:`_within_lengths`). Returns the logs
    predicted without some of the written terms (index, and what was left out): their
    residual there is not the written model's, and is not added to ``unseen``."""
    partial = []
    for k, r in enumerate(runs):
        others = [x for x in runs if x is not r]
        sel = _Selector(others, o)
        for a in active:
            fit = sel.reduce(a.effect, a.hyper)
            sel.active.append(a.refitted(a.hyper, fit))
        # the directions each effect identifies, chosen again with the others in place (as the
        # analysis does): reduced one after another, an early effect's directions were judged
        # against a residual still holding the later ones, and lost those it then could not
        # separate from their scatter
        sel.refine(settings=False)
        fits, _ = sel.final_fit()
        # the model the analysis would write from the other logs: an effect whose consequence on
        # the components their references do not see is not determined by them is left out, as
        # the analysis leaves it out (a model fitted on laser runs alone is not applied to the
        # 6-DOF run with terms only that run determined)
        refit, unsure = [], []
        for a, (theta, _s, cb) in zip(sel.active, fits):
            if not a.written:
                continue
            if not o.accept_unchecked and _unchecked(sel, a, theta, cb):
                unsure.append(a.effect.name)
                continue
            refit.append((a, theta))
        missing = [a.effect.name for a, _ in refit if sel.group_index(a.effect, r) is None]
        # as the model written for other runs: without what belongs to the runs fitted (a
        # drift), the lasting terms refitted without it (:func:`_lasting_fit`)
        refit, _ = _lasting_fit(sel, refit)
        trial = _build_model(model, _terms_for(sel, refit, r), {}, np.stack(_seen_lengths(others), axis=1))
        after = run_pipeline(r.run.device, r.calibration, trial, r.run.times_s, r.run.counts)
        every = np.flatnonzero(r.usable)
        res_a = _datum_corrected(r.obs, r.obs.residual(after), after.measured(r.obs.kind), every)
        res_b = _datum_corrected(r.obs, r.obs.residual(r.ctx.base), r.ctx.base.measured(r.obs.kind), every)
        both = every[np.all(np.isfinite(res_a[every]), axis=1)]
        if unseen is not None and not (missing or unsure):   # for the written model's uncertainty
            unseen.append(ResidualRun(r.ctx, after, res_a, both))
        summaries[k].loro_before = component_errors(r.obs, res_b, both)
        summaries[k].loro_after = component_errors(r.obs, res_a, both)
        inside = both[_within_lengths(r, others)[both]]
        summaries[k].loro_in_range_share = float(inside.size / both.size) if both.size else None
        if inside.size:
            summaries[k].loro_in_range = component_errors(r.obs, res_a, inside)
        notes = []
        if missing:
            notes.append('per-calibration or per-run parameters of ' + ', '.join(missing)
                         + ' cannot be predicted for this log (no other log shares its '
                         'calibration): left out')
        if missing or unsure:
            partial.append((k, f'{r.run.path.name} without {", ".join(missing + unsure)}'))
        if unsure:
            notes.append(', '.join(unsure) + ' not applied: what it does to the components the '
                         'other logs do not see is not determined by them')
        summaries[k].loro_note = '; '.join(notes)
    return partial


def _within_lengths(run: _Run, others: list[_Run]) -> NDArray[np.bool_]:
    """Samples of ``run`` whose six CDF bar lengths all lie within the range the usable samples
    of ``others`` covered (the validity range a model fitted on them records), shape (N,)."""
    lo, hi = _seen_lengths(others)
    lengths = run.ctx.base.cdf_lengths_m
    return np.all((lengths >= lo) & (lengths <= hi), axis=1)


def _ascii(value: Any) -> Any:
    """The model file's analysis record in plain ASCII (the YAML writer escapes the rest) and
    numbers to six significant digits."""
    if isinstance(value, str):
        return value.replace('µ', 'u').replace('°', 'deg').replace('″', 'arcsec').replace('…', '...')
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return float(f'{value:.6g}') if math.isfinite(value) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, dict):
        return {_ascii(k): _ascii(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_ascii(v) for v in value]
    return value


def _contribution(sel: _Selector, run: _Run, f: Found) -> FloatArray:
    """Linearised contribution of one effect to the residual of ``run`` at its held-out fit
    samples (NaN elsewhere), in observation units."""
    shape = run.raw.shape
    out = np.full(shape, np.nan)
    eff = catalogue([f.effect])[0]
    k = sel.runs.index(run)
    rows = sel.test.rows[k]
    a = sel.test.starts[k]
    cols = sel.columns(eff, f.hyper, 'test')[a:a + rows.n_data] @ f.value
    out[rows.idx] = -(cols.reshape(-1, rows.k) / rows.w)
    return out


def _per_bar(ctx: FitContext, residual: FloatArray, idx: IntArray) -> list[ComponentError] | None:
    """Bar-length view of a full 6-DOF pose residual: J dp per bar (µm)."""
    obs = ctx.obs
    if obs.kind != 'pose' or len(obs.components) != 6:
        return None
    sel = idx[np.all(np.isfinite(residual[idx]), axis=1)]
    dd = obs.bar_residual(ctx.device, ctx.base.poses[sel], residual[sel])[0]
    bars = Observation('lengths', list(range(6)), [f'bar{i + 1}' for i in range(6)], ['um'] * 6,
                       np.zeros((sel.size, 6)), np.ones(sel.size, bool), False)
    return component_errors(bars, dd, np.arange(sel.size))


def _glitches(runs: list[_Run], afters: list[tuple[Processed, FloatArray]] | None
              ) -> list[tuple[str, Step]]:
    """Steps in each log's bar residual (:mod:`mmd_ros.analysis.glitches`), as the fit leaves
    it when it added terms (the effects it explains hide a step of a few counts: friction
    turns over as sharply at each reversal), else the model's as given."""
    out = []
    for k, r in enumerate(runs):
        processed, residual = afters[k] if afters else (r.ctx.base, r.res_before)
        ok = r.usable & np.all(np.isfinite(residual), axis=1)
        if r.obs.kind == 'pose':
            ok &= np.all(np.isfinite(processed.poses), axis=1)
        idx = np.flatnonzero(ok)
        bars = bar_residual(r.run.device, r.run.times_s, processed.poses, r.obs, residual, idx,
                            processed.cdf_lengths_m)
        if bars is not None:
            times, values, which, lengths = bars
            out += [(r.run.path.name, step) for step in residual_steps(
                times, values, which, r.run.device.encoder_resolution_m, lengths)]
    return out


def _structure(weighted: FloatArray, idx: IntArray, features: dict[str, FloatArray]) -> list[tuple[str, float]]:
    """Features sorted by the share of the residual variance their binned means explain."""
    r = weighted[idx]
    ok = np.all(np.isfinite(r), axis=1)
    out = [(name, binned_r2(r[ok], v[idx][ok])) for name, v in features.items()]
    return sorted(out, key=lambda t: -t[1])


def _fmt(stats: list[ComponentError] | None) -> str:
    if not stats:
        return '–'
    return ', '.join(f'{s.name} {s.rms:.3g} {_unit(s.unit)}' for s in stats)


def _loro_worse(summaries: list[RunSummary]) -> list[str]:
    """The components a model fitted on the other logs made worse by more than their noise
    floor on a log it did not see, as text."""
    out = []
    for s in summaries:
        if s.loro_before is None or s.loro_after is None:
            continue
        for b, a in zip(s.loro_before, s.loro_after):
            floor = s.floor.get(b.name, math.nan)
            if a.rms > b.rms + floor:
                out.append(f'{b.name} of {Path(s.name).name} worse ({b.rms:.3g} → '
                           f'{a.rms:.3g} {_unit(b.unit)}, floor {floor:.2g} {_unit(b.unit)})')
    return out


def _capital(text: str) -> str:
    return text[:1].upper() + text[1:]


def _unit(unit: str) -> str:
    return 'µm' if unit == 'um' else '″' if unit == 'arcsec' else unit


def _conclusion(runs: list[_Run], summaries: list[RunSummary], found: list[Found],
                not_claimed: list[Found], unchecked: list[Found], at_floor: bool,
                structure: list[tuple[str, float]], validation: str, uncertainty_only: str = '',
                stated: list[str] | None = None, glitches: list[tuple[str, Step]] = ()) -> str:
    parts = [f'{r.run.path.name}: {_capital(r.datum.text())}.' for r in runs
             if r.datum is not None and r.datum.source == 'found']
    parts += [f'{r.run.path.name}: {_capital(r.lag.text(LAG_TAKEN))}.'
              for r in runs if r.lag is not None]
    if stated:
        parts.append(f'Started from {"; ".join(stated)}: the figures before include it (held-out '
                     'RMS of the model as given → with it: ' + '; '.join(
                         f'{r.run.path.name} {_fmt(s.given)} → {_fmt(s.before)}'
                         for r, s in zip(runs, summaries)) + ').')
    first = runs[0]
    floor_txt = '; '.join(', '.join(f'{n} {f:.3g} {_unit(u)}' for (n, f), u in zip(s.floor.items(), s.units))
                          for s in summaries)
    features = ', '.join(f'{name} (R² {r2:.2f})' for name, r2 in structure[:3] if r2 >= 0.05)
    several = len(runs) > 1
    if found:
        names = ', '.join(f.title for f in found)
        if several and summaries[0].loro_after is not None:
            parts.append(f'Found: {names}. Leave-one-run-out RMS (each log predicted by the model '
                         'fitted on the others): ' + '; '.join(
                             f'{r.run.path.name} {_fmt(s.loro_before)} → {_fmt(s.loro_after)}'
                             for r, s in zip(runs, summaries)) + '.')
            worse = _loro_worse(summaries)
            if worse:
                parts.append(f'Fitted on the other logs, the model makes {"; ".join(worse)}: what '
                             'they determined does not carry over to that motion, and the model '
                             'written from all of them is not validated there by a log it did '
                             'not see (record another run of that motion).')
        else:
            which = (f'of {runs[0].run.path.name}, one of the logs' if several
                     else 'of the one log')
            parts.append(f'Found: {names}. Held-out RMS {_fmt(summaries[0].before)} → '
                         f'{_fmt(summaries[0].after)} (pipeline re-run with the extended model; '
                         f'within-run figure: time blocks {which} the model was fitted on).')
    if glitches:
        parts.append('A step in a bar\'s reading: ' + '; '.join(s.text(log) for log, s in glitches)
                     + ' (counts lost or gained at that instant: a dirty scale, a signal that '
                     'dropped out, a packet decoded wrong; no effect of the catalogue has that '
                     'shape, and what follows time, a drift, takes part of it).')
    own = [f.title for f in found if not _lasting(f)]
    if own:
        parts.append(f'Not in the model\'s terms: {", ".join(own)} (it belongs to the run it was '
                     'fitted on, whose figures include it; applied to another run it would be an '
                     'extrapolation no data checked: its size is claimed as that run\'s '
                     'uncertainty instead).')
    if unchecked:
        parts.append('Not written: ' + '; '.join(f'{f.title}: {f.reason}' for f in unchecked) + '.')
    if not_claimed:
        parts.append('Not claimed: ' + '; '.join(f'{f.title} ({f.reason})' for f in not_claimed) + '.')
    unchanged = ('The model is unchanged.' if not uncertainty_only else
                 f'No term is added, but {uncertainty_only}: the model written carries it '
                 'as an uncertainty only (uncertainty.fit), for the pose covariance to cover it.')
    if at_floor:
        if not found:
            parts.append(f'No significant effect: the held-out residual ({_fmt(summaries[0].before)}) '
                         f'is at the noise floor ({floor_txt}). {unchanged}')
        else:
            parts.append(f'What remains is at the noise floor ({floor_txt}).')
    else:
        lead = ('No catalogued effect explains the residual; unexplained' if not found and not unchecked
                else 'Unexplained')
        parts.append(f'{lead} structure remains above the noise floor ({floor_txt})'
                     + (f', correlated with {features}' if features else '') + '.'
                     + (f' {unchanged}' if not found else ''))
    if not several:
        parts.append('Validation is within-run only (one log); record further runs for a '
                     'leave-one-run-out figure.')
    del first
    return ' '.join(parts)
