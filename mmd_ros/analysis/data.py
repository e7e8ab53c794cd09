"""What the analysis works on: one pass of the pipeline over a log, the reference's observation
space, the time-blocked split, the noise floor and the features a residual is compared with.

Observation space. A reference gives either pose components (a full 6-DOF pose, or some of
them: a laser along one axis, a rotary calibrator's angle; unknown components NaN) or bar
lengths (bars on reference pairs, section 4.1). The residual is MMD minus reference in that
space. A small length correction dd (N, 6) moves the pose by J^-1 dd (J = dd/dp at the pose),
of which only the known components are observed; for a bar-length reference it is observed
directly.

Datum. A laser or rotary calibrator is zeroed at the start of a test (section 5.2), so its zero
is not the MMD's: for pose references the analysis removes one constant offset per known
component (fitted on the training part only), unless told the reference is absolute.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.core.accuracy import robust_std, white_noise
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.lag import effective_samples, fit_delay, smoothed_motion
from mmd_ros.core.model import HysteresisTerm, Model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.terms import MAX_GAP_S, SamplingSkewTerm, dahl_state, play_positions
from mmd_ros.core.units import ARCSEC_PER_RAD, M_PER_UM

__all__ = [
    'BLOCK', 'DIRECTION_TRAVEL_M', 'FitContext', 'MOVING_M', 'Observation', 'Processed', 'Split',
    'bar_quantisation', 'binned_r2', 'effective_samples', 'make_observation', 'make_split', 'noise_floor',
    'quantisation_floor', 'report_factors', 'residual_features', 'run_pipeline', 'sample_noise',
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Samples per pipeline call (bounds memory; the pipeline carries term state across calls).
BLOCK = 65536
POSE_LABELS = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
#: How far beyond its calibrated span a bar length still counts as measured [m].
RANGE_MARGIN_M = 20e-6
#: A bar whose length spans less than this is at rest (thermal creep is not motion) [m].
MOVING_M = 50e-6
#: Travel of the play operator used to label motion direction in features and plots [m].
DIRECTION_TRAVEL_M = 2e-6


@dataclass
class Processed:
    """One pass of the pipeline over a whole run (N samples).

    poses : (N, 6) [m, rad]; valid : (N,) converged and in range
    lengths_m : (N, 6) — final lengths (thermal and model terms) [m]
    cdf_lengths_m : (N, 6) — Eq. (10) [m]
    pre_lengths_m : (N, 6) — after thermal compensation, before the model's terms [m]
    reference_error_m : (N, k) — Eq. (11) [m]; temp_change_c, plate_scale : (N,)
    in_range : (N,) — every bar within its calibrated span, give or take ``RANGE_MARGIN_M``
        (the CDF extrapolates its end segments; a bar resting on the first or last pair drifts
        across the end point with temperature)
    """

    poses: FloatArray
    valid: BoolArray
    lengths_m: FloatArray
    cdf_lengths_m: FloatArray
    pre_lengths_m: FloatArray
    reference_error_m: FloatArray
    temp_change_c: FloatArray
    plate_scale: FloatArray
    in_range: BoolArray

    def measured(self, kind: str) -> BoolArray:
        """Samples that are measurements: a valid pose, or for bar lengths every bar in range."""
        return self.in_range if kind == 'lengths' else self.valid

    @property
    def bar_error_m(self) -> FloatArray:
        """Thermal error the model subtracts from each bar, (N, 6) [m]."""
        return self.cdf_lengths_m - self.pre_lengths_m


def run_pipeline(device: DeviceDescription, calibration: Calibration, model: Model,
                 times_s: FloatArray, counts: FloatArray,
                 progress: Callable[[int], None] | None = None,
                 status: NDArray[np.uint8] | None = None) -> Processed:
    """The live pipeline over a whole run, block by block in time order (as ``mmd process``).

    status : (N, 8) the terminal's channel status codes (``RunLog.status``): flagged samples
        get no pose (``valid`` False), as live; None when every sample is good
    """
    pipeline = Pipeline(device, calibration, model)  # its own copy of the terms' state
    lo, hi = pipeline.cdfs.distances_m.min(axis=1), pipeline.cdfs.distances_m.max(axis=1)
    parts = []
    for start in range(0, times_s.size, BLOCK):
        stop = start + BLOCK
        res = pipeline.process(times_s[start:stop], counts[start:stop],
                               status=None if status is None else status[start:stop])
        comp = res.compensated
        parts.append((res.poses, res.valid, comp.lengths_m, comp.cdf_lengths_m,
                      comp.cdf_lengths_m - comp.thermal.bar_error_m, comp.thermal.reference_error_m,
                      comp.thermal.temp_change_c, comp.thermal.plate_scale,
                      np.all((comp.cdf_lengths_m >= lo - RANGE_MARGIN_M)
                             & (comp.cdf_lengths_m <= hi + RANGE_MARGIN_M), axis=1)))
        if progress:
            progress(min(stop, times_s.size))
    if not parts:
        raise AnalysisError('the log has no samples')
    return Processed(*[np.concatenate([p[k] for p in parts]) for k in range(9)])


def report_factors(units: Any) -> FloatArray:
    """Factor from SI to report units for each unit ('um' or 'arcsec'): µm or arc-seconds."""
    return np.array([ARCSEC_PER_RAD if u == 'arcsec' else 1.0 / M_PER_UM for u in units])


@dataclass
class Observation:
    """The reference's observation space.

    kind : 'pose' or 'lengths'
    components : indices of the observed pose components (0..5) or bars (0..5)
    names, units : per observed component ('x' ... 'yaw' or 'bar1' ...; 'um' or 'arcsec')
    reference : (N, k) — reference values of the observed components [m, rad]
    usable : (N,) — reference known in every observed component
    datum : True when a constant offset per component is removed (zeroed instrument)
    sigma : (k,) the reference's own standard uncertainty per observed component [m, rad]
        (the log's ``reference_sigma``), 0 where not stated
    sigma_estimated : ``sigma`` is the reference's white noise as the data show it
        (:func:`reference_noise`), the log stating none
    clock : whose clock the reference was sampled on, as the log states it (metadata
        ``reference_clock``): 'shared' (at the MMD's sample instants), 'own' (another
        instrument's or program's: it may lag the MMD), None not stated
    lag : (N, k, c) the observed components' velocity (and acceleration) when the analysis
        takes a delay between the reference and the MMD as the reference's (a nuisance of each
        log, like a zeroed reference's offsets: :func:`observed_motion`), else None
    """

    kind: str
    components: list[int]
    names: list[str]
    units: list[str]
    reference: FloatArray
    usable: BoolArray
    datum: bool
    sigma: FloatArray | None = None
    sigma_estimated: bool = False
    clock: str | None = None
    lag: FloatArray | None = None

    @property
    def to_report(self) -> FloatArray:
        """Factor from SI to report units per component (µm or arc-seconds), shape (k,)."""
        return report_factors(self.units)

    @property
    def sees_every_bar(self) -> bool:
        """The reference sees all six pose components or bar lengths: what a term does to
        every bar is then determined (not only its effect on some components)."""
        return len(self.components) == 6

    @property
    def description(self) -> str:
        if self.kind == 'lengths':
            text = f'known bar lengths ({", ".join(self.names)})'
        elif len(self.components) == 6:
            text = 'full 6-DOF reference pose'
        else:
            text = f'reference pose components {", ".join(self.names)} (the others unknown)'
        if self.sigma_estimated and self.sigma is not None and np.any(self.sigma > 0):
            noise = ', '.join(f'{n} {v * f:.2g} {"″" if u == "arcsec" else "µm"}'
                              for n, v, f, u in zip(self.names, self.sigma, self.to_report, self.units))
            text += f'; its own noise, which the log does not state, read from the data: {noise}'
        return text

    def length_map(self, device: DeviceDescription, poses: FloatArray) -> FloatArray:
        """How a change of the six bar lengths moves the observed components at ``poses``
        (n, 6), (n, k, 6) [m/m, rad/m]: the rows of the inverse Jacobian for a pose reference,
        the bars themselves for a bar-length reference."""
        if self.kind == 'lengths':
            return np.broadcast_to(np.eye(6)[self.components], (poses.shape[0], len(self.components), 6))
        return np.linalg.inv(jacobian(device.geometry, poses))[:, self.components, :]

    def bar_residual(self, device: DeviceDescription, poses: FloatArray, residual: FloatArray
                     ) -> tuple[FloatArray, list[int]] | None:
        """The residual (n, k) as the bars see it at ``poses`` (n, 6), (n, b), and those bars:
        J dp for a full pose, the bars themselves for a bar-length reference; None when the
        reference does not determine the bars (some pose components only)."""
        if self.kind == 'lengths':
            return residual, list(self.components)
        if len(self.components) != 6:
            return None
        return np.einsum('nij,nj->ni', jacobian(device.geometry, poses), residual), list(range(6))

    def residual(self, processed: Processed) -> FloatArray:
        """MMD minus reference, (N, k) [m, rad]; angles wrapped to (-pi, pi]."""
        if self.kind == 'lengths':
            return processed.lengths_m[:, self.components] - self.reference
        err = processed.poses[:, self.components] - self.reference
        ang = np.array([c >= 3 for c in self.components])
        if np.any(ang):
            err[:, ang] = (err[:, ang] + np.pi) % (2 * np.pi) - np.pi
        return err


def make_observation(reference_pose: FloatArray | None, reference_lengths: FloatArray | None,
                     datum: str = 'auto', reference_sigma: Any = None,
                     reference_clock: Any = None) -> Observation:
    """The observation space of a log's reference (pose components, else bar lengths).

    datum : 'auto' (an offset per pose component; none for bar lengths), 'offset', 'none'
    reference_sigma : (6,) the reference pose's standard uncertainty [m, rad] (the log's
        metadata ``reference_sigma``), or None: not stated
    reference_clock : 'shared' or 'own' (the log's metadata ``reference_clock``), or None:
        not stated (anything else is no statement either)
    """
    if datum not in ('auto', 'offset', 'none'):
        raise AnalysisError(f'datum must be auto, offset or none, got {datum!r}')
    for kind, ref in (('pose', reference_pose), ('lengths', reference_lengths)):
        if ref is None:
            continue
        finite = np.isfinite(ref)
        comps = [k for k in range(ref.shape[1]) if finite[:, k].mean() >= 0.5]
        if not comps:
            continue
        usable = np.all(finite[:, comps], axis=1)
        if kind == 'pose':
            names = [POSE_LABELS[k] for k in comps]
            units = ['um' if k < 3 else 'arcsec' for k in comps]
        else:
            names = [f'bar{k + 1}' for k in comps]
            units = ['um'] * len(comps)
        use_datum = datum == 'offset' or (datum == 'auto' and kind == 'pose')
        sigma = None
        if kind == 'pose' and reference_sigma is not None:
            try:
                s = np.asarray(reference_sigma, dtype=np.float64).reshape(6)
                sigma = np.nan_to_num(s[comps], nan=0.0)
            except (TypeError, ValueError):
                sigma = None    # a malformed statement is no statement
        clock = reference_clock if reference_clock in ('shared', 'own') else None
        return Observation(kind, comps, names, units, ref[:, comps], usable, use_datum, sigma,
                           clock=clock)
    raise AnalysisError('the log has no reference (no /mmd/reference/pose or '
                        '/mmd/reference/bar_lengths with known values): nothing to compare the '
                        'MMD with; record a reference (see msg_docs/analysis.md)')


@dataclass
class Split:
    """Time-blocked split of the usable samples into a training and a held-out part.

    block : (N,) block number of each sample (-1: not usable)
    test : (N,) sample is in a held-out block
    train_idx, test_idx : sorted indices of usable samples of each part (all of them)
    fit_train, fit_test : sorted random subsets used for fitting (at most ``max_samples`` each)
    """

    block: NDArray[np.int64]
    test: BoolArray
    train_idx: NDArray[np.int64]
    test_idx: NDArray[np.int64]
    fit_train: NDArray[np.int64]
    fit_test: NDArray[np.int64]
    n_blocks: int


def make_split(times_s: FloatArray, usable: BoolArray, n_blocks: int = 24, max_samples: int = 4000,
               seed: int = 0) -> Split:
    """Cut the usable time span into ``n_blocks`` blocks of equal duration (fewer for short
    logs: at least 50 samples a block); of each consecutive pair of blocks one (drawn with
    ``seed``) is held out. Pairing keeps both parts spread over
    the whole run (every position, direction and temperature) without a period of the motion
    falling in step with the blocks."""
    idx = np.flatnonzero(usable)
    if idx.size < 200:
        raise AnalysisError(f'only {idx.size} samples have a reference and are measurements '
                            '(valid pose, bars in range); need at least 200 for a held-out split')
    n_blocks = max(4, min(n_blocks, idx.size // 50))
    n_blocks += n_blocks % 2
    t = times_s[idx]
    edges = np.linspace(t[0], t[-1], n_blocks + 1)
    b = np.clip(np.searchsorted(edges, t, side='right') - 1, 0, n_blocks - 1)
    block = np.full(times_s.size, -1, dtype=np.int64)
    block[idx] = b
    rng = np.random.default_rng(seed)
    held = np.zeros(n_blocks, dtype=bool)
    for pair in range(n_blocks // 2):
        held[2 * pair + int(rng.integers(2))] = True
    test = np.zeros(times_s.size, dtype=bool)
    test[idx] = held[b]
    train_idx, test_idx = idx[~held[b]], idx[held[b]]

    def pick(sel: NDArray[np.int64]) -> NDArray[np.int64]:
        if sel.size <= max_samples:
            return sel
        return np.sort(rng.choice(sel, max_samples, replace=False))

    return Split(block, test, train_idx, test_idx, pick(train_idx), pick(test_idx), n_blocks)


#: Mean variance of a linear interpolation between two independent points of equal variance,
#: relative to that variance: the mean of (1 - w)^2 + w^2 over the segment.
INTERPOLATED_SHARE = 2.0 / 3.0


def bar_quantisation(device: DeviceDescription) -> float:
    """Variance of a bar's length from rounding to encoder counts [m^2]: the sample's own count
    (uniform, res^2 / 12), and the CDF points' (Eq. 10): each point is an average of counts that
    the read noise may be too small to dither (5–10 nm against 50 nm counts), so it can be off
    by up to half a count, res^2 / 12 again, which the CDF interpolates between the points (on
    average 2/3 of it along a segment). Systematic, not noise: the twin at 24.2 °C leaves an
    S-shaped ±0.04 µm x error from it (points off by -14 … +9 nm)."""
    q = device.encoder_resolution_m ** 2 / 12.0
    return q * (1.0 + INTERPOLATED_SHARE)


def quantisation_floor(device: DeviceDescription, poses: FloatArray, thermal_on: bool) -> FloatArray:
    """Encoder quantisation propagated into the six pose components, (6,) [m, rad]; mean
    variance over (up to 500 of) ``poses``. Per bar, :func:`bar_quantisation` [m^2]; and the
    same as one count again common to all bars for the reference bar's rounding when thermal
    compensation is on.
    """
    q = device.encoder_resolution_m ** 2 / 12.0
    cov = np.eye(6) * bar_quantisation(device) + (q if thermal_on else 0.0) * np.ones((6, 6))
    sel = poses[:: max(1, poses.shape[0] // 500)]
    sel = sel[np.all(np.isfinite(sel), axis=1)]
    if sel.shape[0] == 0:
        return np.full(6, np.nan)
    jinv = np.linalg.inv(jacobian(device.geometry, sel))
    pc = jinv @ cov @ np.swapaxes(jinv, 1, 2)
    return np.sqrt(np.mean(np.diagonal(pc, axis1=1, axis2=2), axis=0))


def noise_floor(obs: Observation, device: DeviceDescription, processed: Processed,
                residual: FloatArray, idx: NDArray[np.int64], thermal_on: bool) -> FloatArray:
    """What the residual cannot go below, per observed component, (k,) [m or rad].

    Encoder quantisation (:func:`quantisation_floor`; for bar lengths
    :func:`bar_quantisation` and the reference bar's rounding), propagated into the observation
    space, plus the sample-to-sample
    noise of the residual itself (robust standard deviation of its differences / sqrt 2:
    reference noise, read noise), taken over the pairs of consecutive samples in which the bars
    moved least.
    """
    q = device.encoder_resolution_m ** 2 / 12.0
    if obs.kind == 'pose':
        quant = quantisation_floor(device, processed.poses[idx], thermal_on)[obs.components] ** 2
    else:
        quant = np.full(len(obs.components), bar_quantisation(device) + (q if thermal_on else 0.0))
    return np.sqrt(quant + sample_noise(residual, processed, idx) ** 2)


def sample_noise(values: FloatArray, processed: Processed, idx: NDArray[np.int64]) -> FloatArray:
    """Sample-to-sample noise of ``values`` (N, k), (k,): the robust standard deviation of the
    differences of consecutive samples / sqrt 2, over the slowest tenth of the pairs (at least
    50) in ``idx`` — a fast bar crosses a short-period error (cyclic error, a bump) between two
    samples, which is structure, not noise. Zero with fewer than 10 pairs."""
    consecutive = idx[np.flatnonzero(np.diff(idx) == 1)]
    if consecutive.size <= 10:
        return np.zeros(values.shape[1])
    motion = np.max(np.abs(processed.cdf_lengths_m[consecutive + 1]
                           - processed.cdf_lengths_m[consecutive]), axis=1)
    keep = max(50, consecutive.size // 10)
    if consecutive.size > keep:
        consecutive = consecutive[np.argsort(motion, kind='stable')[:keep]]
    diff = values[consecutive + 1] - values[consecutive]
    ok = np.all(np.isfinite(diff), axis=1)
    diff = diff[ok]
    if diff.shape[0] < 10:
        return np.zeros(values.shape[1])
    return robust_std(diff) / np.sqrt(2.0)


def reference_noise(obs: Observation, processed: Processed, residual: FloatArray,
                    idx: NDArray[np.int64]) -> FloatArray:
    """The reference's own white noise per observed component, (k,) [m, rad], for a log that
    does not state it: what the residual's white noise holds beyond the MMD's own in the same
    component, read from its own stream over the same samples (the two are independent;
    :func:`~mmd_ros.core.accuracy.white_noise`, which follows motion, so that the MMD's noise
    is read while it moves). Unstated, the reference's 0.1″ of angle noise on a clean log was
    taken for the MMD's and written as an uncertainty of roll 4.6 times the budget's."""
    own = processed.poses if obs.kind == 'pose' else processed.lengths_m
    mmd = white_noise(own[:, obs.components], idx)
    return np.sqrt(np.maximum(white_noise(residual, idx) ** 2 - mmd ** 2, 0.0))


def observed_motion(obs: Observation, device: DeviceDescription, processed: Processed,
                    times_s: FloatArray, smooth: bool,
                    rows: NDArray[np.int64] | None = None) -> FloatArray:
    """How fast the observed components move, (N, k, 1), or with ``smooth`` how fast and how
    they accelerate, (N, k, 2) [m/s, rad/s; m/s^2, rad/s^2], from the bars' CDF lengths mapped
    as the observation maps a change of the bars (:meth:`Observation.length_map`), zero where
    there is no pose, NaN where it is not known. A reference read a time δ late differs from
    the MMD by δ v - δ^2 a / 2 + ...; a common latch delay of the bars' channels gives the
    first.

    Without ``smooth`` the velocity is the skew term's backward difference (the sum of its
    signatures: a common skew and this lag are then one direction); its noise, about
    sqrt(2) sigma / dt per bar, times δ is a nanometre at 10 µs but 34 nm at 2.4 ms. With
    ``smooth``, a cubic Savitzky-Golay fit over :data:`~mmd_ros.core.lag.LAG_WINDOW` samples
    within each stretch of evenly spaced samples (:func:`~mmd_ros.core.lag.smoothed_motion`);
    NaN in a stretch shorter than that (a lag there cannot be taken out: with zeros beside a
    1 s gap the residual there was claimed as an error).
    ``rows``: those samples only, (len(rows), k, c)."""
    lengths = processed.cdf_lengths_m
    if not smooth:
        bars = [-SamplingSkewTerm.features(lengths, times_s, MAX_GAP_S, None)[0]]
    else:
        bars = list(smoothed_motion(times_s, lengths))
    poses, valid = processed.poses, processed.valid
    if rows is not None:
        bars, poses, valid = [b[rows] for b in bars], poses[rows], valid[rows]
    out = np.zeros((poses.shape[0], len(obs.components), len(bars)))
    for j, b in enumerate(bars):
        if obs.kind == 'lengths':
            out[:, :, j] = b[:, obs.components]
            continue
        ok = np.flatnonzero(valid & np.all(np.isfinite(poses), axis=1)
                            & np.all(np.isfinite(b), axis=1))
        out[~np.all(np.isfinite(b), axis=1), :, j] = np.nan
        if ok.size:
            jinv = obs.length_map(device, poses[ok])
            out[ok, :, j] = np.einsum('nkj,nj->nk', jinv, b[ok])
    return out


def fit_lag(obs: Observation, residual: FloatArray, idx: NDArray[np.int64]
            ) -> tuple[FloatArray, float, FloatArray]:
    """How the reference's lag behind the MMD explains the residual over the samples ``idx``:
    the residual (N, k) [m, rad] as the columns of ``obs.lag`` (N, k, c) times a coefficient
    each (the first the delay δ [s], positive when the reference reads late), with an offset
    per component beside them for a zeroed reference. Returns the coefficients (c,), the
    delay's standard deviation (the residual's correlation counted: :func:`effective_samples`)
    and the offsets (k,) [m, rad]. Components are weighted by the inverse of the residual's
    spread in each."""
    return fit_delay(residual[idx], obs.lag[idx], obs.datum)


def binned_r2(values: FloatArray, feature: FloatArray, n_bins: int = 20) -> float:
    """Share of the variance of ``values`` (n, k) explained by their mean in bins of ``feature``
    (quantile bins; a feature with at most 3 distinct values is treated as categories)."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    f = np.asarray(feature, dtype=np.float64)
    ok = np.isfinite(f) & np.all(np.isfinite(v), axis=1)
    v, f = v[ok], f[ok]
    if f.size < 4 * n_bins or np.ptp(f) == 0:
        return 0.0
    uniq = np.unique(f)
    if uniq.size <= 3:
        labels = np.searchsorted(uniq, f)
    else:
        edges = np.unique(np.quantile(f, np.linspace(0, 1, n_bins + 1)))
        labels = np.clip(np.searchsorted(edges, f, side='right') - 1, 0, max(edges.size - 2, 0))
    nl = int(labels.max()) + 1
    counts = np.bincount(labels, minlength=nl).astype(np.float64)
    total = float(np.sum((v - v.mean(axis=0)) ** 2))
    if total <= 0:
        return 0.0
    explained = 0.0
    for col in v.T:
        sums = np.bincount(labels, weights=col, minlength=nl)
        means = np.divide(sums, counts, out=np.zeros(nl), where=counts > 0)
        explained += float(np.sum(counts * (means - col.mean()) ** 2))
    return explained / total


#: Friction states a :class:`FitContext` keeps, of the turn-over travels last asked for.
FRICTION_STATES_KEPT = 4


@dataclass
class FitContext:
    """Everything the effect signatures need, with caches of the stateful features."""

    device: DeviceDescription
    calibration: Calibration
    model: Model
    times_s: FloatArray
    counts: FloatArray
    base: Processed
    obs: Observation
    options: Any = None
    cache: dict[Any, Any] = field(default_factory=dict)
    #: the residual of the model analysed, (N, k) [m, rad], NaN where not usable; its noise
    #: floor (k,) and the training samples (for estimates that look at the residual itself)
    residual: FloatArray | None = None
    floor: FloatArray | None = None
    train_idx: NDArray[np.int64] | None = None
    #: the Unix time of ``times_s`` = 0 (the log's first stamp) [s], or None: not known (the
    #: budget then claims no drift of the readings since the calibration)
    epoch_s: float | None = None

    def cached(self, key: Any, make: Callable[[], Any]) -> Any:
        if key not in self.cache:
            self.cache[key] = make()
        return self.cache[key]

    def directions(self, travel_m: float) -> FloatArray:
        """Motion direction of each bar (the hysteresis term's play operator), (N, 6)."""
        return self.cached(('dir', travel_m), lambda: HysteresisTerm(np.ones(6), travel_m).directions(
            self.base.pre_lengths_m))

    def both_ways(self, travel_m: float, idx: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which bars move each way (:meth:`directions`) at more than 1 % of the samples
        ``idx``, (6,). Kept for the last ``idx`` asked: the same for every turn-over travel a
        friction fit tries (126 times 17 ms on a 10-minute 1 kHz log)."""
        last = self.cache.get(('both_ways', travel_m))
        if last is not None and np.array_equal(last[0], idx):
            return last[1].copy()
        d = self.directions(travel_m)[idx]
        ok = (np.mean(d > 0, axis=0) > 0.01) & (np.mean(d < 0, axis=0) > 0.01)
        self.cache[('both_ways', travel_m)] = (np.array(idx, copy=True), ok)
        return ok.copy()

    def friction(self, travel_m: float) -> FloatArray:
        """Dahl friction state of each bar (the friction term's), (N, 6). The states of the
        last :data:`FRICTION_STATES_KEPT` turn-over travels asked for are kept: a search scores
        tens of travels, each state N x 6 values (kept all, 85 of them were 2.4 GB of a
        10-minute 1 kHz log's 4 GB peak), and one is made again in 15-50 ms."""
        kept = self.cache.setdefault('friction', {})
        state = kept.pop(travel_m, None)
        if state is None:
            x = self.base.pre_lengths_m
            pos = self.cached('play', lambda: play_positions(x, self.device.encoder_resolution_m, None))
            state = dahl_state(pos, travel_m, (x[0], np.zeros(6), x[0], np.zeros(6)))[0]
            while len(kept) >= FRICTION_STATES_KEPT:
                kept.pop(next(iter(kept)))          # (the least recently asked for)
        kept[travel_m] = state
        return state

    def velocities(self) -> FloatArray:
        """Bar velocities (backward differences of the CDF lengths, the skew term's), (N, 6) [m/s]."""
        return self.cached('vel', lambda: -SamplingSkewTerm.features(
            self.base.cdf_lengths_m, self.times_s, SamplingSkewTerm(np.zeros(6)).max_gap_s, None)[0])

    @property
    def thermal_on(self) -> bool:
        return self.model.thermal_mode != 'off' and self.base.reference_error_m.shape[1] > 0


def residual_features(ctx: FitContext) -> dict[str, FloatArray]:
    """Quantities a residual may follow, each (N,): time, the pose components that move, each
    bar's length, velocity and motion direction, and the thermal error of the reference bar."""
    base = ctx.base
    out: dict[str, FloatArray] = {'time': ctx.times_s}
    usable = ctx.obs.usable & base.measured(ctx.obs.kind)
    if ctx.obs.kind == 'pose':
        p = base.poses[usable]
        for k in range(6):
            span = np.ptp(p[:, k]) if p.size else 0.0
            if span > (1e-5 if k < 3 else 1e-5):
                out[f'pose {POSE_LABELS[k]}'] = base.poses[:, k]
    moving = (np.ptp(base.pre_lengths_m[usable], axis=0) > MOVING_M if usable.any()
              else np.zeros(6, bool))
    for i in range(6):
        if moving[i]:
            out[f'bar{i + 1} length'] = base.pre_lengths_m[:, i]
            out[f'bar{i + 1} velocity'] = ctx.velocities()[:, i]
            out[f'bar{i + 1} direction'] = ctx.directions(DIRECTION_TRAVEL_M)[:, i]
    if ctx.thermal_on and np.ptp(base.reference_error_m[usable, 0]) > ctx.device.encoder_resolution_m:
        out['reference-bar thermal error'] = base.reference_error_m[:, 0]
    return out
