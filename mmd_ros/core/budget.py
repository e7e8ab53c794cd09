"""The uncertainty budget of the compensated bar lengths: Sigma_d (6 x 6) of every sample.

One :class:`LengthBudget` belongs to one device, calibration and model (as a
:class:`~mmd_ros.core.pipeline.Pipeline` does). What it needs per sample is what every stage of
the live pipeline has: the compensated lengths, the thermal state (Eq. 11 error of each
reference bar, the temperature change) and, when the model carries fitted terms, the
corrections of their one-sigma perturbations. The sources, their formulas and defaults are
listed in :mod:`mmd_ros.core.uncertainty` and documented in ``msg_docs/frames.md``.

Where the numbers come from:

- the device description: the encoder resolution, the scale CTE (Eq. 13's approximation), the
  reference distances' standard uncertainty (``reference_plate.distance_uncertainty_um``, when
  stated), the bars' thermal mismatch (``bars.thermal_mismatch_fraction``), the terminal's
  latch skew (``terminal.latch_skew_us``, its datasheet), the encoders' sub-divisional error
  (``bars.subdivision_error_nm`` and ``bars.signal_period_um``, their datasheet);
- the calibration: its points (hat functions of Eq. 10, the interpolation error fitted to
  them) and what the routine measured (read noise, hysteresis, seating repeatability);
- the stream: each channel's read noise where it stands still (:class:`NoiseEstimator`);
- the model file's ``uncertainty`` section: overrides, and what ``mmd analyze`` measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.calibration import Calibration
from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.model import Model, TermContext
from mmd_ros.core.piecewise import bar_segments
from mmd_ros.core.terms import (
    MAX_GAP_S, GravitySagTerm, SamplingSkewTerm, leg_geometry, lengths_within,
)
from mmd_ros.core.thermal import thermal_sensitivity
from mmd_ros.core.uncertainty import (
    CalibrationUncertainty, InterpolationError, NoiseEstimator, capture_var,
    fit_interpolation_error, hat_weights, hysteresis_claim, quantisation_cross_weights,
)
from mmd_ros.core.validity import Validity, fitted_calibration_figures, other_calibration

__all__ = ['DIRECTION_TRAVEL_M', 'FRICTION_FORGET_TRAVELS', 'FRICTION_START_VAR', 'FRICTION_TURNOVER_M',
           'KNOWN_ERROR_SHAPE', 'LengthBudget', 'Observed', 'SHAPES', 'SOURCES']

FloatArray = NDArray[np.float64]

#: Half-width of the play operator that tells a bar's motion direction for the hysteresis
#: source: it flips after 2 um of reverse travel [m].
DIRECTION_TRAVEL_M = 1e-6
#: Model terms that compensate the bars' friction hysteresis (the budget's hysteresis source
#: is then off: the fit's uncertainty and residual stand for what is left of it).
FRICTION_TERMS = ('hysteresis', 'friction')
#: Model terms that compensate the channels' latch skew (the latch_skew source is then off).
SKEW_TERMS = ('sampling_skew',)
#: Model terms that compensate the bars' gravity sag (the gravity_sag source is then off).
SAG_TERMS = ('gravity_sag',)
#: Model terms that compensate the bars' thermal mismatch: each bar's gain against the
#: reference bar is the bar's deviation less the reference bar's (the thermal_mismatch source
#: is then off: the fit's parameter covariance stands for what is left of it).
MISMATCH_TERMS = ('thermal_gain',)
#: Model terms that compensate the encoders' sub-divisional error on the measuring bars (at
#: the signal period or a harmonic of it: the subdivision source keeps what they leave).
CYCLIC_TERMS = ('cyclic_error',)
#: Fitted terms whose correction depends on a bar's length only (the unchecked_range source).
LENGTH_TERMS = ('scale_nonlinearity', 'cdf_offsets')
#: Of those, the terms whose correction follows points along a bar: beyond the last point the
#: fit saw, it follows points no data checked (held at zero, or on the line of those seen).
POINT_TERMS = ('cdf_offsets',)
#: The lengths within those a fit saw at which its length correction is conditioned on to continue
#: it beyond them (:class:`_Continuation`), and the conditioning's jitter [m^2]
CONTINUATION_POINTS = 41
CONTINUATION_JITTER_M2 = 1e-18
#: Travel after a reversal by which a bar's friction state has turned over (an assumption:
#: rolling guides turn within a few um; the calibration does not measure it) [m].
FRICTION_TURNOVER_M = 20e-6
#: Variance of the friction state at a run's start, in units of h^2: the state is known only
#: to lie in [-1, 1] (the history before the run is not recorded), a rectangular distribution
#: (GUM 4.3.7), so its variance is 1/3.
FRICTION_START_VAR = 1.0 / 3.0
#: A compensating term's state error after a path p since the run began is the start state's
#: times exp(-p / travel) (Dahl's law contracts two states at that rate); the budget follows the
#: path up to this many travels (what is left of the variance there, exp(-2 x 10), is nothing).
FRICTION_FORGET_TRAVELS = 10.0
#: The sources whose distribution is not Gaussian, independent per bar, with the excess kurtosis
#: of their form (E[x^4] / E[x^2]^2 - 3): a count's quantisation is rectangular over one count
#: (-1.2, GUM 4.3.7); an encoder's sub-divisional error is a sine of a phase that a moving bar
#: sweeps evenly (-1.5, the arcsine distribution); the latch skew's unknown share of a known
#: bound is rectangular (-1.2). The other sources are taken Gaussian (0): for the size of a
#: coverage region that is the cautious choice. A known error b (the sum of the errors the
#: budget knows but the compensation does not correct) is a fixed vector: -2 as one component
#: (its sign does not change d^2).
SHAPES = {'quantisation': -1.2, 'subdivision': -1.5, 'latch_skew': -1.2}
KNOWN_ERROR_SHAPE = -2.0


@dataclass
class _Terms:
    """The sources of N samples by form: per-bar variances (N, 6), a variance common to every
    bar (N,) (Eq. 13's reference bar) or per reference bar with weights (Eq. 12), full
    matrices (N, 6, 6), constant matrices (6, 6), and known errors (N, 6)."""

    diag: dict[str, FloatArray] = field(default_factory=dict)
    common: FloatArray | None = None
    weights: FloatArray | None = None
    weight_var: FloatArray | None = None
    full: dict[str, FloatArray] = field(default_factory=dict)
    constant: dict[str, FloatArray] = field(default_factory=dict)
    bias: dict[str, FloatArray] = field(default_factory=dict)

    def reference(self, n: int) -> FloatArray | None:
        """The reference bar's share as (N, 6, 6), or None."""
        if self.common is not None:
            return np.broadcast_to(self.common[:, None, None], (n, 6, 6)).copy()
        if self.weights is not None:
            return np.einsum('nik,nk,njk->nij', self.weights, self.weight_var, self.weights)
        return None


@dataclass(frozen=True)
class Observed:
    """What the budget learned from N samples (:meth:`LengthBudget.observe`).

    read_noise_m : (N, 6 + k) — read noise in force per column (measuring bars, reference bars)
    directions : (N, 6) — each bar's friction state as far as its motion tells: its direction
        (+1 lengthening, -1 shortening, 0 before its first move) times how far the state has
        turned since the last reversal, min(1, travel / FRICTION_TURNOVER_M)
    velocity_m_s : (N, 6) — each bar's speed of lengthening, a backward difference of its CDF
        length (0 where not known) [m/s]
    settled : (N, 6) — how far each bar has travelled since the run began, min(1, path /
        turnover): 0 before its first move (the state a compensating term cannot know yet);
        with a compensating term the turnover is FRICTION_FORGET_TRAVELS of its travel
    n_z2 : (N, 6) — each bar's n_z^2 at the sample's pose (its axis' vertical component,
        squared: its gravity sag reads it g n_z^2 short; None without a stated sag or a pose)
    since_calibration_s : (N,) — how long before or after the calibration each sample was
        taken (or a fit measured its residual, when later) [s, >= 0]; None when that is not
        known (or no drift rate is stated)
    scale_lever_m : (N, 6) — how much each bar's length changes per unit of the plates' scale
        at the sample's pose, n_i . (R a_i - b_i) [m] (0 where unsolved); None without a pose
        or without a claim of the plates' scale
    """

    read_noise_m: FloatArray
    directions: FloatArray
    velocity_m_s: FloatArray | None = None
    settled: FloatArray | None = None
    n_z2: FloatArray | None = None
    since_calibration_s: FloatArray | None = None
    scale_lever_m: FloatArray | None = None

    def __getitem__(self, index: Any) -> Observed:
        return Observed(*(None if v is None else v[index] for v in (
            self.read_noise_m, self.directions, self.velocity_m_s, self.settled, self.n_z2,
            self.since_calibration_s, self.scale_lever_m)))


@dataclass(frozen=True)
class _Trend:
    """The least-squares quadratic of each bar's CDF-point correction over the lengths a fit
    saw (scaled by what the points' own errors cannot explain), ``coefficients`` (3, 6) [m] in
    s = (length - ``middle_m``) / ``half_m`` (6,) each."""

    middle_m: FloatArray
    half_m: FloatArray
    coefficients: FloatArray

    def __call__(self, lengths_m: FloatArray) -> FloatArray:
        """The quadratic at the lengths (N, 6) [m], (N, 6) [m] (0 for a bar that saw none)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            s = np.where(self.half_m > 0.0, (lengths_m - self.middle_m) / self.half_m, 0.0)
        a, b, q = self.coefficients
        return a + s * (b + s * q)


def _left_covariance(interpolation: InterpolationError, knots_m: FloatArray, point_m2: float,
                     a_m: FloatArray, b_m: FloatArray) -> FloatArray:
    """Of one bar with points ``knots_m`` (n,): the prior covariance of the error the CDF leaves
    at ``a_m`` (p,) and ``b_m`` (q,), (p, q) [m^2]: the smooth scale error
    (:class:`InterpolationError`) less its interpolation through the points, plus each point's
    own error of variance ``point_m2`` [m^2] by its hat weight."""
    return (interpolation.covariance(a_m, b_m, knots_m)
            + (hat_weights(a_m, knots_m) * point_m2) @ hat_weights(b_m, knots_m).T)


@dataclass(frozen=True)
class _Continuation:
    """Each bar's length correction within the lengths a fit saw, continued beyond them as the
    error it corrects would continue: the conditional mean, given the correction's values c at
    the lengths ``at_m`` (k, 6) within them, of the error the CDF leaves
    (:func:`_left_covariance`, each point's own error ``point_m2`` (6,) [m^2]) about a level of
    its own (ordinary kriging: a level the data do not tie, as a zeroed reference leaves the
    bars' constants, goes on as it is, and cancels in the continuation's changes):
    ``weights`` (k, 6) [1/m] are (K + S)^-1 (c - level), S the correction's own covariance
    (the fit's)."""

    interpolation: InterpolationError
    knots_m: FloatArray
    point_m2: FloatArray
    at_m: FloatArray
    weights: FloatArray

    def change(self, lengths_m: FloatArray, from_m: FloatArray, where: NDArray[np.bool_]
               ) -> FloatArray:
        """How far the continuation moves from ``from_m`` to ``lengths_m`` (N, 6) [m] where
        ``where`` (N, 6) holds, else 0, (N, 6) [m]."""
        out = np.zeros(np.shape(lengths_m))
        for b in np.flatnonzero(where.any(axis=0) & np.any(self.weights != 0.0, axis=0)):
            i = where[:, b]
            k = self.knots_m[b], self.point_m2[b]
            at = self.at_m[:, b]
            out[i, b] = (_left_covariance(self.interpolation, *k, lengths_m[i, b], at)
                         - _left_covariance(self.interpolation, *k, from_m[i, b], at)
                         ) @ self.weights[:, b]
        return out


class _Velocity:
    """Each bar's speed as the sampling-skew term computes it (a backward difference of the CDF
    lengths, zero across gaps), carried from call to call."""

    def __init__(self, period_s: float) -> None:
        self.period_s = float(period_s)
        self.reset()

    def reset(self) -> None:
        self._state: Any = None

    def __call__(self, x: FloatArray, times_s: FloatArray | None) -> FloatArray:
        if times_s is None:   # the device's sample period apart
            last = self._state[1] if self._state is not None else -self.period_s
            times_s = last + self.period_s * np.arange(1, x.shape[0] + 1)
        minus_v, self._state = SamplingSkewTerm.features(x, np.asarray(times_s, dtype=np.float64),
                                                         MAX_GAP_S, self._state)
        return np.where(np.isfinite(minus_v), -minus_v, 0.0)


class _Friction:
    """Each bar's direction (a play operator of half-width ``w``), the travel since its last
    reversal and since the run began, carried from call to call."""

    def __init__(self, w: float, turnover: float) -> None:
        self.w, self.turnover = float(w), float(turnover)
        self.reset()

    def reset(self) -> None:
        # per bar: play, direction, flip at, path since the run began (NaN play: none yet)
        self._state = np.tile([math.nan, 0.0, math.nan, 0.0], (6, 1))

    def __call__(self, x: FloatArray, *, compiled: bool | None = None
                 ) -> tuple[FloatArray, FloatArray]:
        """The friction state as far as the motion tells, (N, 6) (see :class:`Observed`), and
        how far it has turned since the run began, min(1, path / turnover), (N, 6).
        ``compiled``: the compiled loop (default: when it is in use; the same numbers)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        n = x.shape[0]
        out = np.zeros((n, 6))
        settled = np.zeros((n, 6))
        if n == 0:
            return out, settled
        w, turn = self.w, self.turnover
        if use_compiled(compiled):
            fast.friction_travel(x, w, turn, self._state, out, settled)
            return out, settled
        for bar in range(6):  # a sequential recurrence: plain floats beat numpy rows here
            p, d, f, path = (float(v) for v in self._state[bar])
            col = x[:, bar].tolist()
            res = [0.0] * n
            done = [0.0] * n
            for k, v in enumerate(col):
                if v != v:      # NaN: out of range, the state stays
                    res[k] = d * min(1.0, abs(p - f) / turn) if d else 0.0
                    done[k] = min(1.0, path / turn)
                    continue
                if p != p:
                    p = f = v
                if p < v - w:
                    path += v - w - p
                    p = v - w
                    if d != 1.0:
                        d, f = 1.0, p
                elif p > v + w:
                    path += p - v - w
                    p = v + w
                    if d != -1.0:
                        d, f = -1.0, p
                if d:
                    res[k] = d * min(1.0, abs(p - f) / turn)
                done[k] = min(1.0, path / turn)
            out[:, bar] = res
            settled[:, bar] = done
            self._state[bar] = (p, d, f, path)
        return out, settled


#: Unix times before this (2001-09-09) are not a wall clock's: a log stamped from 0 (a simulated
#: clock, a clock since boot) does not say how long after the calibration its samples were taken.
WALL_CLOCK_FROM_S = 1e9
NOT_WALL_CLOCK = ('reading drift: the samples or the calibration are not stamped on a wall clock '
                  '(before 2001); the drift of the readings since the calibration is not claimed')


#: The budget's sources, in the order reports list them.
SOURCES = ('quantisation', 'read_noise', 'reference_bar', 'reading_drift', 'calibration_points',
           'calibration_drift', 'reference_distances', 'interpolation', 'subdivision',
           'thermal_approximation',
           'thermal_mismatch', 'plate_scale', 'hysteresis', 'latch_skew', 'gravity_sag',
           'unchecked_range',
           'fitted_terms',
           'residual')


def segments_seen(knots_m: FloatArray, range_m: FloatArray) -> FloatArray:
    """Each bar's span of the CDF segments whose middle lies within the lengths ``range_m``
    (6, 2) a fit saw, intersected with that range, (6, 2) [m]; [inf, -inf] for a bar that saw
    no segment's middle.

    What a smooth scale error leaves between two calibration points is zero at both and
    largest near the middle: a fit that did not reach a segment's middle saw only the
    flank of it, and a length term's correction over that segment is an extrapolation. On
    the twin, a bar seen from 270 mm in its segment 250-278 mm was corrected by -1 µm at
    265 mm where its error was +0.2 µm (the bar always arrived there shortening: its friction
    state and its scale error cannot be told apart at the end of what it saw), while the
    fit's parameter covariance claimed 0.07 µm.

    knots_m : ndarray, shape (6, n) — each bar's calibration distances, increasing [m]
    """
    out = np.tile([np.inf, -np.inf], (knots_m.shape[0], 1))
    for i, kn in enumerate(knots_m):
        lo, hi = range_m[i]
        middle = 0.5 * (kn[:-1] + kn[1:])
        seen = np.flatnonzero((middle >= lo) & (middle <= hi))
        if seen.size:
            out[i] = max(lo, kn[seen[0]]), min(hi, kn[seen[-1] + 1])
    return out


def _harmonic_of(period_m: float, signal_period_m: float) -> bool:
    """Whether a fitted cyclic term's period is the encoders' signal period or one of its first
    harmonics (p / 2 .. p / 4, where sub-divisional errors lie), within 2 %. A term at another
    period compensates another effect (a ball screw's lead, a foreign error), and the encoders'
    own stays claimed."""
    if signal_period_m <= 0.0:
        return False
    return any(abs(period_m * n / signal_period_m - 1.0) < 0.02 for n in range(1, 5))


def _friction_amplitudes(friction: list[Any], model: Model) -> FloatArray | None:
    """Per bar, the root of the second moment of the friction amplitude the model's terms of
    :data:`FRICTION_TERMS` apply, (6,) [m]: their amplitudes' sum squared plus the variance
    the fit's principal directions give it (:attr:`FitUncertainty.directions`, each a one-sigma
    correction written as terms); None without such a term with six amplitudes."""
    def amplitudes(terms: list[Any]) -> FloatArray | None:
        got = [np.asarray(getattr(t, 'amplitude_m', ()), dtype=np.float64) for t in terms
               if t.type_name in FRICTION_TERMS]
        got = [a for a in got if a.shape == (6,)]
        return sum(got) if got else None

    mean = amplitudes(friction)
    if mean is None:
        return None
    var = np.zeros(6)
    fit = model.uncertainty.fit if model.uncertainty is not None else None
    for group in (fit.directions if fit is not None else []):
        step = amplitudes(group)
        if step is not None:
            var += step * step
    return np.sqrt(mean * mean + var)


class LengthBudget:
    """Sigma_d of N samples for one device, calibration and model (see the module docstring).

    device, calibration, model : what the pipeline uses
    """

    def __init__(self, device: DeviceDescription, calibration: Calibration, model: Model) -> None:
        self.device = device
        self.resolution_m = res = device.encoder_resolution_m
        names = device.channel_names
        measuring = [names[k] for k in device.measuring_channels]
        self.reference_names = [c.name for c in device.reference_channels]
        figures = calibration.uncertainty
        self.figures = figures
        unc = model.uncertainty
        fit = unc.fit
        self.fit = fit
        self.notes: list[str] = []

        # -- the thermal compensation in use
        mode = model.thermal_mode
        refs = [c for c in device.reference_channels if c.name in calibration.bars]
        if mode == 'auto':
            mode = 'interpolate' if len(refs) >= 2 else 'single'
        if not refs:
            mode = 'off'
        self.thermal_mode = mode
        self.ref_distances_m = np.array([device.pair(c.pair).distance_m for c in refs])
        self.scale_cte = device.scale_cte_per_c

        # -- read noise: the model's figure, else the stream's, else the larger of the
        # calibration's and what an analysis measured where the bars of its logs stood still
        # (a mount vibrating at the machine, which a stream that never stands still cannot show)
        self.fixed_noise_m = unc.read_noise_m
        self.calibration_noise_m = figures.read_noise_m
        if self.fixed_noise_m is None and self.calibration_noise_m is None:
            self.notes.append('read noise: the calibration does not give it; estimated from the '
                              'stream where bars stand still, 0 until then')
        self.noise = NoiseEstimator(6 + len(refs), res)
        self.fallback_noise_m = np.full(self.noise.columns, self.calibration_noise_m or 0.0)
        measured = None if fit is None else fit.read_noise_m
        if measured is not None and measured.size == self.noise.columns:
            self.fallback_noise_m = np.maximum(self.fallback_noise_m, measured)

        # -- friction hysteresis measured by a two-sided calibration: a bar that last lengthened
        # reads short by h (the sign from its motion, a play operator). A term that compensates
        # it knows the state only once the bar has moved: until then the state is unknown, +-h
        # (h the larger of the calibration's and the term's amplitude). Not measured, the
        # device description's figure for its bars stands for each bar's. A measured h carries
        # the scatter of the placements it is the mean of: the budget claims what the bars'
        # estimates together say of each (:func:`hysteresis_claim`), not the scatter itself
        # (a point's variance holds its seating: what the routine measured, else the plate's
        # stated figure)
        self.seating_m = (figures.seating_m if figures.seating_m is not None
                          else device.seating_repeatability_m)
        self.point_var_m2 = figures.point_var(res, self.seating_m)
        friction = [t for t in model.terms if t.type_name in FRICTION_TERMS]
        self.friction_compensated = bool(friction)
        stated = device.friction_hysteresis_m or 0.0
        h = np.full(6, stated)
        on = [i for i, m in enumerate(measuring) if m in figures.hysteresis_m]
        if on:
            pairs = np.array([len(calibration.bars[measuring[i]].distances_m) for i in on])
            h[on] = hysteresis_claim(np.array([figures.hysteresis_m[measuring[i]] for i in on]),
                                     self.point_var_m2 / np.maximum(pairs, 1))
        fitted = _friction_amplitudes(friction, model)
        if fitted is not None:
            # a friction term fitted on this device measured each bar's own amplitude: it
            # replaces the type's stated figure and a calibration's estimate, claimed as its
            # second moment given the fit, the amplitude squared plus its variance (the fit's
            # principal directions). Floored by the type's RMS instead, a bar with less friction
            # than the type's was claimed up to 1.9 times it (realistic twins: each bar 0.5-1.5
            # times the type's, the fitted amplitude within 1.5 % of its own), in every point
            # of a one-sided routine and in the term's unknown start state
            h = fitted
        self.hysteresis_m = h
        # each point of a one-sided routine carries the friction state its bar was placed in:
        # seating moves a bar millimetres, far beyond the state's turn-over, so the state is
        # +-1 of unknown sign, independent between placements, h^2 per point (a two-sided
        # point is the mean of both states)
        self._one_sided = figures.approaches < 2
        self.point_friction_m2 = h * h if self._one_sided else np.zeros(6)
        if self._one_sided and not np.any(h > 0):
            self.notes.append('calibration points: the friction state each point was captured in '
                              'is not claimed: the device description states no friction '
                              '(bars.friction_hysteresis_nm) and no term compensates it')

        # -- calibration points (Eq. 10 hat functions), per measuring bar
        calibration.cdfs(measuring)  # every measuring bar has points (else CalibrationError)
        bars = [calibration.bars[m] for m in measuring]
        if len({len(b.distances_m) for b in bars}) != 1:
            raise CalibrationError('all bars need the same number of calibration points')
        knots, pair_idx, devs = [], [], []
        pair_names = [p.name for p in device.pairs]
        self._point_order = []
        for b in bars:
            d = np.asarray(b.distances_m)
            order = np.argsort(d)
            self._point_order.append(order)
            knots.append(d[order])
            pair_idx.append([pair_names.index(b.pairs[k]) if b.pairs[k] in pair_names else -1
                             for k in order])
        self.knots_m = np.array(knots)                         # (6, n) increasing
        self.pair_index = np.array(pair_idx, dtype=np.intp)     # (6, n)
        self._measuring = measuring
        self.drift_m = self._routine_drift(figures)            # (6, n) each point's thermal error
        if figures.routine_temp_change_c is None:
            self.notes.append('calibration drift: the routine did not measure the temperature '
                              'change over its course (a reference bar on its resting pair first)')
        if self.seating_m is None:
            self.notes.append('calibration points: the seating of each placement is not claimed: '
                              'the routine did not measure it and the device description does not '
                              'state it (reference_plate.seating_repeatability_nm)')
        if figures.read_noise_m is None:
            self.notes.append('calibration points: the calibration does not give its read noise; '
                              'each point taken as quantised without dither (Delta^2/12)')
        if self._one_sided:
            self.notes.append('calibration points: one placement per pair; the seating and the '
                              'friction state of each placement are not measured, and are claimed '
                              'from the device description\'s statements only (a two-sided '
                              'calibration measures both)')
        pair_sigma = np.array([p.sigma_m for p in device.pairs])
        self.pair_var_m2 = pair_sigma ** 2
        if not np.any(pair_sigma > 0):
            self.notes.append('reference distances: the device description states no uncertainty '
                              'of the reference plate (reference_plate.distance_uncertainty_um)')

        # -- interpolation between the points: a smooth scale error fitted to all bars' points
        all_bars = bars + [calibration.bars[c.name] for c in refs]
        all_bars = [b for b in all_bars if len(b.distances_m) == self.knots_m.shape[1]]
        for b in all_bars:
            cdf = b.cdf()
            d = np.asarray(cdf.distances_m)
            q = np.asarray(cdf.counts)
            sign = 1.0 if (d[-1] - d[0]) * (q[-1] - q[0]) > 0 else -1.0
            order = np.argsort(d)
            devs.append((sign * q * res - d)[order])
        all_knots = np.array([np.sort(b.distances_m) for b in all_bars])
        # (each point also read its count's sub-divisional error, its own at every point: a
        # nugget like the capture's, not a scale error between the points)
        sde_var = 0.5 * float(device.subdivision_error_m or 0.0) ** 2
        nugget = np.full(all_knots.shape, self.point_var_m2 + sde_var)
        if self._one_sided:      # (and the friction state it was placed in)
            nugget[:len(bars)] += self.point_friction_m2[:, None]
            nugget[len(bars):] += stated ** 2           # (the reference bars: the stated)
        self._point_nugget_m2 = self.point_var_m2 + sde_var + self.point_friction_m2    # (6,)
        self.interpolation: InterpolationError = fit_interpolation_error(
            all_knots, np.array(devs), nugget)

        # -- thermal
        frac = unc.thermal_mismatch_fraction
        if frac is None:
            frac = device.thermal_mismatch_fraction
        gains = any(t.type_name in MISMATCH_TERMS for t in model.terms)
        if frac is None and not gains:
            self.notes.append('thermal mismatch: the device description does not state '
                              'bars.thermal_mismatch_fraction')
        self.mismatch_fraction = float(frac or 0.0) if mode != 'off' and not gains else 0.0
        # a fit against absolute references that saw every bar measured the mismatch as it was
        # at its runs' thermal state (its terms of free constants took it up, or its residual
        # holds it): what is left is the mismatch of the change since
        self._mismatch_from: tuple[FloatArray, FloatArray] | None = None
        state = None if fit is None else fit.thermal_state_m
        if state is not None and self.mismatch_fraction:
            if state.size == 6 + len(refs):
                self._mismatch_from = (state[:6], state[6:])
            else:
                self.notes.append(f'thermal mismatch: the fit\'s thermal state has {state.size} '
                                  f'values, this device {6 + len(refs)} bars; claimed whole')
        # (and Eq. (13)'s approximation and the plates' scale, as they were at its runs' mean
        # temperature change)
        self._temp_change_from = 0.0 if fit is None or fit.thermal_state_c is None \
            else float(fit.thermal_state_c)
        self._plate_scale_init(device, model, mode, float(frac or 0.0))
        # Eq. (13)'s approximation, the error -alpha_s (d_i - d_ref) dT of a bar at length d_i
        # (known: claimed as such), from d_ref on; a thermal_interpolation term corrects it
        # (its coefficient's uncertainty is among the fitted terms'), and a bar's fitted
        # thermal_gain takes it at the lengths its fit saw the bar at: what it leaves is
        # -alpha_s (d_i - m_i) dT, m_i the middle of those lengths (a soak on pairs: the pair's)
        validity = Validity.from_model(model)
        self.approximation_from_m: FloatArray | None = None
        if mode == 'single':
            self.approximation_from_m = np.full(6, self.ref_distances_m[0])
            if any(t.type_name == 'thermal_interpolation' for t in model.terms):
                self.approximation_from_m = None
            elif gains and validity is not None:
                self.approximation_from_m = np.mean(validity.bar_range_m, axis=1)

        # -- the reference bar(s): live reading and the thermal zero (one capture)
        s_cal = figures.read_noise_m or 0.0
        self.zero_noise_m = s_cal
        self.zero_var_m2 = capture_var(res, s_cal, int(figures.capture_samples or 1))

        # -- the readings' drift since the calibration: at constant length and temperature a
        # channel's reading moves at a rate anywhere within the stated bound r (rectangular,
        # GUM 4.3.7), r t / sqrt(3) after a time t; the reference bar's through Eq. 13 into
        # every bar. Counted from the calibration's time (``created``), or, when a fit's
        # residual replaced it, from when that residual was measured (the later of the two):
        # the residual holds what had drifted by then. The samples' times on the same clock
        # come with them (:meth:`observe`)
        rate = device.drift_m_per_s
        self.drift_rate_m_per_s = float(rate or 0.0)
        self.calibrated_s = calibration.created_s
        measured = None if fit is None else fit.measured_unix_s
        if fit is not None and 'reading_drift' in fit.replaces and measured is not None:
            self.drift_from_s: float | None = (measured if self.calibrated_s is None
                                               else max(measured, self.calibrated_s))
            self._drift_factor = 1.0
        else:
            self.drift_from_s = self.calibrated_s
            self._drift_factor = 1.0 if fit is None else fit.systematic_scale
        if rate is None:
            self.notes.append('reading drift: the device description does not state the bars\' '
                              'drift rate (bars.drift_nm_per_h); the drift of the readings since '
                              'the calibration is not claimed')
        elif rate > 0.0 and self.drift_from_s is None:
            self.notes.append('reading drift: the calibration does not say when it was made '
                              '(created); the drift of the readings since then is not claimed')

        # (a compensating term starts from state 0, the start state's mean; its error is the
        # start state times exp(-path / travel), its own travel: the Dahl state's turn-over, or
        # a relay's play half-width; the path counted through the term's own play)
        travel = max([float(getattr(t, 'travel_m', 0.0)) for t in friction] or [0.0])
        if friction and travel > 0.0:
            self.friction_travel_m = travel
            deadband = min(float(getattr(t, 'deadband_m', DIRECTION_TRAVEL_M)) for t in friction)
            self._direction = _Friction(deadband, FRICTION_FORGET_TRAVELS * travel)
        else:
            self.friction_travel_m = FRICTION_TURNOVER_M
            self._direction = _Friction(DIRECTION_TRAVEL_M, FRICTION_TURNOVER_M)

        # -- the terminal's latch skew (its datasheet), unless a fitted term compensates it
        skew = device.latch_skew_s
        if skew is None:
            self.notes.append('latch skew: the device description does not state the terminal\'s '
                              '(terminal.latch_skew_us); a bar moving at v reads up to v x skew off')
        skews = [t for t in model.terms if t.type_name in SKEW_TERMS]
        # a skew fitted against a reference on a clock of its own corrects how the channels'
        # delays differ, not their common part, which that reference's lag hides: of the stated
        # skew [0, s] the common part stays, one delay of every bar (uniform: mean s/2 and
        # variance s^2/12 along the bars' velocity v, a rank-one covariance, not one per bar)
        self.latch_common_only = bool(skews) and not any(getattr(t, 'common_fitted', True)
                                                         for t in skews)
        self.latch_skew_s = (0.0 if skews and not self.latch_common_only
                             else float(skew or 0.0))
        self._velocity = _Velocity(1.0 / device.sample_rate_hz)

        # -- the bars' gravity sag (their characterisation), unless a fitted term compensates it:
        # a bar reads g (1 - n_z^2) long, n_z its axis' vertical component; calibrated lying on
        # the plate (n_z = 0) its CDF holds g, so on the MMD it reads g n_z^2 short, an error
        # of known size and sign at a known pose that the compensation does not correct
        sag = device.gravity_sag_m
        if sag is None:
            self.notes.append('gravity sag: the device description does not state the bars\' '
                              '(bars.gravity_sag_nm); a bar whose axis has the vertical '
                              'component n_z reads g n_z^2 short')
        compensated = any(t.type_name in SAG_TERMS for t in model.terms)
        self.gravity_sag_m = 0.0 if compensated else float(sag or 0.0)
        # and how far these bars' sag may lie from the figure, as a random error of every bar
        # alike (their n_z^2 times one draw), where the description states it
        self.gravity_sag_sigma_m = 0.0 if compensated else float(device.gravity_sag_sigma_m or 0.0)
        self._joints = (device.geometry.upper, device.geometry.lower)
        self._up = device.up        # n_z: along the upward vertical in {L} as mounted
        if self.gravity_sag_m and device.vertical is None:
            self.notes.append('gravity sag: the device description does not state the vertical '
                              'as mounted (plates.vertical); the lower plate is taken level (+z)')

        # -- the encoders' sub-divisional error (their datasheet): a bar reads e(q) at count q,
        # periodic in the signal period, with a phase no one knows; the calibration's points
        # carry theirs too. Its mean square a^2 / 2, less what fitted terms at the signal
        # period or its harmonics compensate (the harmonics of a periodic error add up in mean
        # square): a fit of the fundamental leaves the second harmonic claimed, and the reverse
        sde = device.subdivision_error_m
        if sde is None:
            self.notes.append('sub-division error: the device description does not state the '
                              'encoders\' (bars.subdivision_error_nm, bars.signal_period_um)')
        self.subdivision_m = float(sde or 0.0)
        self.signal_period_m = float(device.signal_period_m or 0.0)
        compensated = np.zeros(6)
        for t in model.terms:
            if t.type_name in CYCLIC_TERMS and _harmonic_of(float(t.period_m), self.signal_period_m):
                compensated += t.mean_square_m2()
        self.subdivision_left_m2 = np.maximum(0.5 * self.subdivision_m ** 2 - compensated, 0.0)

        # -- a fitted length-dependent term where the fit never saw the bar: its correction
        # there is an extrapolation that no data checked (the model's validity record)
        # the lengths a fit's residual checked (the calibration's tables come back beyond them)
        self._seen_range_m = (validity.bar_range_m if validity is not None and fit is not None
                              else None)
        self._length_terms = [t for t in model.terms if t.type_name in LENGTH_TERMS]
        # with a length term, of those the CDF segments whose middle the fit saw
        # (:func:`segments_seen`): where the lengths seen end inside a segment is its flank
        # (:meth:`flank`), and a point is checked only through a segment seen
        self._fit_range_m = (segments_seen(self.knots_m, self._seen_range_m)
                             if self._seen_range_m is not None and self._length_terms
                             else self._seen_range_m)
        self._fitted_range_m = (validity.bar_range_m if validity is not None and self._length_terms
                                else None)
        self._seen_var_m2, self._trend = (self._length_spread(self._fitted_range_m)
                                          if self._fitted_range_m is not None
                                          else (np.zeros(6), None))
        self._continuation: _Continuation | None = None     # (built when a bar first lies beyond)
        self.flank_m2 = fit.flank_m2 if fit is not None else np.zeros(6)   # (where flank() says)
        if self._length_terms and validity is None:
            self.notes.append('unchecked range: the model does not record the lengths its terms '
                              'were fitted on (validity.bar_range_mm)')

        # -- what a fit replaced, and how much of the rest it kept
        self.replaced = set(fit.replaces) if fit is not None else set()
        self.systematic_scale = fit.systematic_scale if fit is not None else 1.0
        # a fit made with another calibration (the device calibrated again since): its residual
        # measured that calibration's placements and routine drift, draws of their own. The
        # routine's drift is this calibration's, measured: claimed whole, or, where the model's
        # length terms took up the other routine's, as the difference of the two (when the
        # model records the other's). The placements (seating, capture): where a points term
        # (cdf_offsets) holds the other's, its correction carries them here beside this one's,
        # twice their variance; else the residual holds a draw of the same kind and stands for
        # this one's. The friction state a one-sided routine seats a bar in on a pair is the
        # bar's and the pair's (how the guide enters the sockets) and comes again with the same
        # routine; claimed when the routines differ (one side or two) or the model does not
        # say. (A model of calibration A on a run of calibration B of the same twin an
        # hour later, both two-sided, the room falling 0.41 °C over B's routine: 32, 33, 66
        # and 6 % of four twins' poses in the 95 % ellipsoid, z 0.28-1.07 times its error)
        self.new_placements = fit is not None and other_calibration(model, calibration) is not None
        self._new_share: float | FloatArray = 0.0   # of the points' variance, new draws
        if self.new_placements:
            before = fitted_calibration_figures(model)
            held = any(t.type_name == 'cdf_offsets' for t in model.terms)
            same_routine = before is not None and before.approaches == figures.approaches
            # of a point's variance p + f (placement, friction state), what is new: the
            # placements twice where a points term holds the other's (its correction, and
            # this one's own), else none (the residual measured a draw of the same kind);
            # the friction states unless the same routine seats them alike: this one's, and
            # the other's where a points term holds them (a one-sided routine's, or one not
            # recorded). A model fitted after a one-sided routine and used after a two-sided
            # one applied the first one's friction steps to points free of them: four twins
            # 2.5-40 % in the 95 % ellipsoid while only this routine's states were claimed
            p, f = self.point_var_m2, self.point_friction_m2
            f_held = (self.hysteresis_m ** 2 if held and (before is None or before.approaches < 2)
                      else np.zeros(6))
            new = (2.0 if held else 0.0) * p + (0.0 if same_routine else 1.0) * (f + f_held)
            self._new_share = np.where(p + f > 0, new / np.maximum(p + f, 1e-300), 0.0)
            # (a drift is smooth along the bars: a scale series takes it up as well as points)
            if before is not None and any(t.type_name in LENGTH_TERMS for t in model.terms):
                self.drift_m = self.drift_m - self._routine_drift(before)
            self.notes.append(
                'calibration: the model was fitted with another calibration; this one\'s '
                'routine drift is claimed' + (', and its placements beside the other\'s, which '
                                              'the model\'s terms of its points hold' if held
                                              else '')
                + ('' if same_routine else ', and the friction state of its placements'))
        self.residual_m2 = fit.residual_m2 if fit is not None else np.zeros((6, 6))
        self.mean_terms_m2 = fit.mean_terms_m2 if fit is not None else np.zeros((6, 6))
        self.rest_terms_m2 = fit.rest_terms_m2 if fit is not None else np.zeros((6, 6))
        self._subdivision_factor = self._kept('subdivision')
        # (the sag's error over the poses a fit's residual saw is in that residual)
        self._sag_kept = (math.sqrt(self._kept('gravity_sag'))
                          if self.gravity_sag_m or self.gravity_sag_sigma_m else 0.0)
        # what the per-sample path needs, decided once
        self._has_drift = bool(np.any(self.drift_m))
        self._has_pairs = bool(np.any(self.pair_var_m2 > 0))
        self._has_hysteresis = bool(np.any(self.hysteresis_m > 0))
        self._has_mean_terms = bool(np.any(self.mean_terms_m2))
        # (where along each bar the residual lay: claimed there, :class:`LengthProfile`)
        self._profile = fit.profile if fit is not None else None
        self._has_residual = bool(np.any(self.residual_m2)) or self._profile is not None
        self._cross_key: tuple[float, ...] | None = None
        self._tab: dict[str, FloatArray] | None = None
        # (the points no data checked: for bars within the lengths the fit saw, and beyond them)
        self._unchecked_points: tuple[NDArray[np.bool_], NDArray[np.bool_]] | None = None
        self._fast_parts: dict[str, Any] | None = None
        self._resolved: tuple[FloatArray, FloatArray] | None = None
        self._cross_w: FloatArray = np.zeros((0, 0))

    def _plate_scale_init(self, device: DeviceDescription, model: Model, mode: str,
                          mismatch: float) -> None:
        """The plates' scale: the joints are scaled by 1 + a_p (dT + offset), dT the
        temperature change the reference bar's Eq. (11) error implies through the description's
        sensitivity S = -(a_r L + a_s (d_ref - L)) (Fig. 10). dT is as uncertain, relatively, as
        S: the rods' effective CTE (``bars.rod_cte_uncertainty_ppm_per_c``, u_a: L u_a / |S|)
        and the reference bar's own deviation from the type (half the stated mismatch's
        variance, f^2 / 2; with two reference bars their mean, f^2 / 4). The scale's standard
        uncertainty is a_p |dT| u_rel; off without plate expansion or thermal compensation."""
        self.plate_scale_rel = 0.0          # u_rel a_p: the scale's sigma per °C of dT [1/°C]
        if mode == 'off' or not model.plate_expansion or not device.plate_cte_per_c:
            return
        used = self.ref_distances_m[:1] if mode == 'single' else self.ref_distances_m
        sens = np.abs(thermal_sensitivity(device, used))
        rod = device.rod_cte_sigma_per_c
        share = 0.5 if mode == 'single' else 0.25
        rel2 = (share * mismatch ** 2
                + float(np.mean(device.fixed_length_m * (rod or 0.0) / sens)) ** 2)
        self.plate_scale_rel = abs(device.plate_cte_per_c) * math.sqrt(rel2)
        if rod is None:
            self.notes.append('plates\' scale: the device description does not state the '
                              'uncertainty of the bars\' effective rod CTE '
                              '(bars.rod_cte_uncertainty_ppm_per_c); the temperature change '
                              'the plates\' expansion is estimated from is claimed as uncertain '
                              'as the reference bar\'s share of the thermal mismatch only')

    def _routine_drift(self, figures: CalibrationUncertainty) -> FloatArray:
        """Each point's thermal error from the routine's drift (6, n) [m], in increasing length.
        The measured change is noisy: the profile is scaled to the unbiased estimate of its
        square, and claimed as a covariance e e^T of one change for every bar, not as an error
        of known sign (realistic twins whose room held still read changes of up to 0.23 °C,
        2.6 of their sigma, with one seating at each end; summed with the bars' sag as a
        signed error it cancelled it). In a still room this claim averages 0.48 u^2: the
        routine reads both ends from both sides, which halves u^2
        (calibration_routine._routine_drift)."""
        drift = np.zeros(self.knots_m.shape)
        for i, (name, order) in enumerate(zip(self._measuring, self._point_order)):
            beta = figures.drift_m.get(name)
            if beta is not None and len(beta) == order.size:
                drift[i] = np.asarray(beta, dtype=np.float64)[order]
        temp, temp_sigma = figures.routine_temp_change_c, figures.routine_temp_sigma_c or 0.0
        if temp_sigma and figures.seating_m is None and self.seating_m:
            # a one-sided routine measured no seating: its captures' variance alone sized the
            # change's; each end is a seating of its own too, as the plate states
            temp_sigma *= math.sqrt(figures.point_var(self.resolution_m, self.seating_m)
                                    / figures.point_var(self.resolution_m))
        if temp:
            drift *= math.sqrt(max(temp * temp - temp_sigma ** 2, 0.0)) / abs(temp)
        return drift

    @property
    def point_nugget_m2(self) -> FloatArray:
        """Per measuring bar, the variance of each calibration point's own error, independent
        from point to point (placement, its count's sub-divisional error, after a one-sided
        routine the friction state it was seated in), (6,) [m^2]."""
        return self._point_nugget_m2

    def reset(self) -> None:
        """A new run: the stream's read-noise estimate and the bars' motion directions start
        again."""
        self.noise.reset()
        self._direction.reset()
        self._velocity.reset()

    # -- per-sample inputs ---------------------------------------------------------------------
    def bar_error(self, lengths_m: FloatArray, reference_error_m: FloatArray) -> FloatArray:
        """The thermal error the pipeline subtracted from each bar (Eq. 13 or Eq. 12), (N, 6) [m],
        from the compensated lengths and the Eq. (11) errors (for a stage that has only those)."""
        n = lengths_m.shape[0]
        eps = np.asarray(reference_error_m, dtype=np.float64).reshape(n, -1)
        if self.thermal_mode == 'off' or eps.shape[1] == 0:
            return np.zeros((n, 6))
        if self.thermal_mode == 'single':
            return np.repeat(eps[:, :1], 6, axis=1)
        lo, hi = self.ref_distances_m[0], self.ref_distances_m[-1]
        frac = (lengths_m - lo) / (hi - lo)
        return eps[:, :1] + frac * (eps[:, -1:] - eps[:, :1])

    def observe(self, cdf_lengths_m: FloatArray, reference_error_m: FloatArray,
                times_s: FloatArray | None = None, poses: FloatArray | None = None,
                epoch_s: float | None = None) -> Observed:
        """What the budget learns from N consecutive samples (call once per sample, in time
        order): the read-noise estimate from the CDF lengths (or the lengths plus the thermal
        error subtracted, which differ by terms that do not change while a bar stands still)
        and the reference bars' Eq. (11) errors, each bar's motion direction and its speed,
        and at the samples' poses each bar's gravity sag error and its length's change with the
        plates' scale.

        times_s : (N,) the samples' times [s]; None: the device's sample period apart
        poses : (N, 6) the samples' poses [m, rad] (NaN where unsolved: no sag claimed there);
            None: the sag's error and the plates' scale's are not known (not claimed)
        epoch_s : the Unix time [s] of ``times_s`` = 0 (a log's first stamp; 0 when the times
            are Unix times): with the calibration's ``created``, how long after it each sample
            was taken (the readings' drift since then); None: not known (not claimed)

        returns : what :meth:`covariance` needs of these samples
        """
        n = cdf_lengths_m.shape[0]
        k = self.noise.columns - 6
        values = np.empty((n, 6 + k))
        values[:, :6] = cdf_lengths_m
        if k:
            values[:, 6:] = np.asarray(reference_error_m, dtype=np.float64).reshape(n, -1)[:, :k]
        est = self.noise.feed(values)
        directions, settled = (self._direction(np.asarray(cdf_lengths_m, dtype=np.float64))
                               if self._has_hysteresis else (np.zeros((n, 6)), None))
        velocity = (self._velocity(np.asarray(cdf_lengths_m, dtype=np.float64), times_s)
                    if self.latch_skew_s else None)
        n_z2 = None
        if (self.gravity_sag_m or self.gravity_sag_sigma_m) and poses is not None:
            n_z2 = np.nan_to_num(GravitySagTerm.features(
                *self._joints, np.asarray(poses, dtype=np.float64), self._up))
        since = None
        if self.drift_rate_m_per_s and self.drift_from_s is not None and epoch_s is not None and n:
            t = (np.arange(n) / self.device.sample_rate_hz if times_s is None
                 else np.asarray(times_s, dtype=np.float64))
            if self._on_wall_clock(float(t[0]) + float(epoch_s)):
                since = np.abs(t + (float(epoch_s) - self.drift_from_s))
            elif NOT_WALL_CLOCK not in self.notes:
                self.notes.append(NOT_WALL_CLOCK)
        lever = None
        if self.plate_scale_rel and poses is not None:
            _, _, lever = leg_geometry(*self._joints, np.asarray(poses, dtype=np.float64))
            lever = np.nan_to_num(lever)
        return Observed(self._resolve(est), directions, velocity, settled, n_z2, since, lever)

    def _resolve(self, estimate: FloatArray) -> FloatArray:
        if self.fixed_noise_m is not None:
            return np.full(estimate.shape, self.fixed_noise_m)
        if estimate.strides[0] == 0:     # one estimate for every sample (a stream's transfer)
            row = estimate[0]
            if self._resolved is None or self._resolved[0] is not row:
                self._resolved = (row, np.where(np.isfinite(row), row, self.fallback_noise_m))
            return np.broadcast_to(self._resolved[1], estimate.shape)
        return np.where(np.isfinite(estimate), estimate, self.fallback_noise_m)

    def read_noise_m(self) -> FloatArray:
        """Read noise in force now per column (six measuring bars, then the reference bars) [m]."""
        return self._resolve(self.noise.sigma_m())

    # -- the budget ----------------------------------------------------------------------------
    def _kept(self, source: str) -> float:
        """Factor on a replaceable source: 0 when a fit measured it, else the fit's scale."""
        return 0.0 if source in self.replaced else self.systematic_scale

    def _terms(self, lengths_m: FloatArray, reference_error_m: FloatArray,
               temp_change_c: FloatArray, bar_error_m: FloatArray | None,
               fit_columns_m: FloatArray | None, observed: Observed | None) -> _Terms:
        """Every source of N samples, in the form that is cheapest to add up."""
        x = np.asarray(lengths_m, dtype=np.float64)
        n = x.shape[0]
        res2 = self.resolution_m ** 2
        eps = np.asarray(reference_error_m, dtype=np.float64).reshape(n, -1)
        if bar_error_m is None:
            bar_error_m = self.bar_error(x, eps)
        noise = (np.broadcast_to(self.read_noise_m(), (n, self.noise.columns))
                 if observed is None else observed.read_noise_m)
        t = _Terms()
        t.diag['quantisation'] = np.full((n, 6), res2 / 12.0)
        t.diag['read_noise'] = noise[:, :6] ** 2
        if self.thermal_mode != 'off':
            # live reading and thermal zero: their quantisation biases are correlated when the
            # reading is within a count of its zero (delta ~ eps, Eq. 11)
            cross = self._cross(noise[-1, 6:], eps)
            ref_var = np.maximum(res2 / 12.0 + noise[:, 6:] ** 2 + self.zero_var_m2 - 2.0 * cross,
                                 0.0) + self._reference_subdivision(eps)                # (N, k)
            if self.thermal_mode == 'single':
                t.common = ref_var[:, 0]
            else:
                lo, hi = self.ref_distances_m[0], self.ref_distances_m[-1]
                frac = (x - lo) / (hi - lo)
                t.weights = np.stack([1.0 - frac, frac], axis=2)
                t.weight_var = ref_var[:, [0, -1]]
        drift = self._reading_drift(observed)
        if drift is not None:
            t.full['reading_drift'] = self._add_shared(np.zeros((n, 6, 6)), drift[:, None],
                                                       drift[:, None], t.weights)
        # what depends on a bar's length only, through the hat functions of Eq. (10):
        # tabulated once per bar on a fine grid, read by linear interpolation
        tables = self._tables()
        pos = (x - self._grid_lo) / self._grid_step
        i0 = np.clip(pos.astype(np.intp), 0, self._grid_n - 2)
        f = pos - i0
        rows = np.arange(6)[None, :]
        factor, points = self._table_factors(x, bar_error_m, eps)
        for name, tab in tables.items():
            k = (self._subdivision_factor if name == 'subdivision'
                 else points if name == 'calibration_points'
                 else self._routine_drift_factor(factor) if name == 'calibration_drift' else factor)
            if not np.any(k):
                continue
            value = tab[rows, i0] * (1.0 - f) + tab[rows, i0 + 1] * f
            if name == 'calibration_drift':     # (one change for every bar: rank one)
                e = np.sqrt(k) * value
                t.full[name] = e[:, :, None] * e[:, None, :]
            else:
                t.diag[name] = k * value
        if self._has_pairs and self._kept('reference_distances'):
            seg, u = bar_segments(x, self.knots_m)
            h = np.zeros((n, 6, self.pair_var_m2.size))
            pj0, pj1 = self.pair_index[rows, seg], self.pair_index[rows, seg + 1]
            nn = np.arange(n)[:, None]
            h[nn, rows, pj0] += 1.0 - u
            h[nn, rows, pj1] += u
            t.full['reference_distances'] = self._kept('reference_distances') * np.einsum(
                'nip,p,njp->nij', h, self.pair_var_m2, h)
        if self.approximation_from_m is not None:
            t.bias['thermal_approximation'] = -(x - self.approximation_from_m) * self.scale_cte \
                * self._temp_change_since(temp_change_c)[:, None]
        if self.mismatch_fraction:
            # f is what is left of one bar's thermal error after Eq. (13): its own deviation
            # from the type and the reference bar's (one of the same bars), f^2 / 2 each
            half = 0.5 * self.mismatch_fraction ** 2
            own, ref = self._mismatch_of(bar_error_m, eps)
            t.full['thermal_mismatch'] = self._add_shared(
                np.zeros((n, 6, 6)), half * own ** 2, half * ref ** 2, t.weights)
        hysteresis = self._hysteresis(n, observed)
        if hysteresis is not None:
            if hysteresis[0] is not None:
                t.bias['hysteresis'] = hysteresis[0]
            t.diag['hysteresis'] = hysteresis[1]
        if self._fitted_range_m is not None:
            t.diag['unchecked_range'] = self._unchecked(
                x, bar_error_m, eps, temp_change_c, t.diag.get('calibration_points', 0.0))
        if self.latch_skew_s and observed is not None and observed.velocity_m_s is not None:
            v = observed.velocity_m_s
            t.bias['latch_skew'] = 0.5 * self.latch_skew_s * v
            if self.latch_common_only:
                var = self.latch_skew_s ** 2 / 12.0
                t.full['latch_skew'] = var * v[:, :, None] * v[:, None, :]
            else:
                t.diag['latch_skew'] = (self.latch_skew_s ** 2 / 12.0) * v * v
        scale = self._plate_scale(temp_change_c, observed)
        if scale is not None:
            t.full['plate_scale'] = scale[:, :, None] * scale[:, None, :]
        if self._sag_kept and observed is not None and observed.n_z2 is not None:
            t.bias['gravity_sag'] = (-self._sag_kept * self.gravity_sag_m) * observed.n_z2
            if self.gravity_sag_sigma_m:
                e = (self._sag_kept * self.gravity_sag_sigma_m) * observed.n_z2
                t.full['gravity_sag'] = e[:, :, None] * e[:, None, :]
        if fit_columns_m is not None and fit_columns_m.shape[-1]:
            t.full['fitted_terms'] = (fit_columns_m @ np.swapaxes(fit_columns_m, 1, 2)
                                      + self.rest_terms_m2)
        elif self._has_mean_terms:
            t.constant['fitted_terms'] = self.mean_terms_m2
        if self._has_residual:
            if self._profile is None:
                t.constant['residual'] = self.residual_m2
            else:
                t.full['residual'] = self.residual_m2 + self._profile.added(x + bar_error_m)
        return t

    def _plate_scale(self, temp_change_c: FloatArray, observed: Observed | None
                     ) -> FloatArray | None:
        """One sigma of the bars' lengths from the plates' scale, (N, 6) [m] (one error of
        every bar: its covariance is rank one), or None when not claimed
        (:meth:`_plate_scale_init`; the samples' poses give each bar's lever)."""
        if not self.plate_scale_rel or observed is None or observed.scale_lever_m is None:
            return None
        sigma = self.plate_scale_rel * np.abs(self._temp_change_since(temp_change_c))
        return sigma.reshape(-1, 1) * observed.scale_lever_m

    def plate_scale_sigma(self, temp_change_c: float) -> float:
        """One sigma of the plates' scale the pose covariance claims at the temperature change
        ``temp_change_c`` since the thermal zero [1] (:meth:`_plate_scale_init`; 0 when it
        claims none, NaN for an unknown change): of the change since the state a fit measured
        it at, as :meth:`_plate_scale` claims it."""
        return self.plate_scale_rel * abs(float(self._temp_change_since(temp_change_c))) \
            if math.isfinite(temp_change_c) else math.nan

    def _reading_drift(self, observed: Observed | None) -> FloatArray | None:
        """The variance of a channel's reading drift since the calibration, (N,) [m^2]: each
        channel's rate anywhere within the stated bound r, (r t)^2 / 3 after a time t; None
        when not claimed (no rate stated, or the calibration's or the samples' time unknown)."""
        if observed is None or observed.since_calibration_s is None:
            return None
        return self._drift_var(observed.since_calibration_s)

    def _drift_var(self, since_s: Any) -> Any:
        """(r t)^2 / 3 after the times ``since_s`` [s], times a fit's scale [m^2]."""
        return self._drift_factor * (self.drift_rate_m_per_s * since_s) ** 2 / 3.0

    def _on_wall_clock(self, unix_s: float) -> bool:
        """Whether a sample at ``unix_s`` and the time the drift is counted from are both
        stamped on a wall clock (:data:`WALL_CLOCK_FROM_S`)."""
        return min(unix_s, self.drift_from_s) >= WALL_CLOCK_FROM_S

    def reading_drift_sigma_m(self, unix_s: float) -> float:
        """One sigma of each channel's reading drift at the Unix time ``unix_s`` [m], counted
        as the budget counts it (from the calibration, or from when a fit measured its
        residual); NaN when the budget claims none (no rate stated, no time, no wall clock).
        A bar's length carries its own and, through Eq. (13), the reference bar's."""
        start = self.drift_from_s
        if not self.drift_rate_m_per_s or start is None or not self._on_wall_clock(unix_s):
            return math.nan
        return math.sqrt(self._drift_var(abs(unix_s - start)))

    def _temp_change_since(self, temp_change_c: Any) -> FloatArray:
        """The temperature change since the thermal zero [°C], or since the state at which a fit
        measured Eq. (13)'s approximation and the plates' scale (``fit.thermal_state_c``)."""
        return np.asarray(temp_change_c, dtype=np.float64) - self._temp_change_from

    def _mismatch_of(self, bar_error_m: FloatArray, eps: FloatArray
                     ) -> tuple[FloatArray, FloatArray]:
        """What the thermal_mismatch source is proportional to: each bar's thermal correction
        (N, 6) or (N, 1) and each reference bar's error (N, k) [m], as they are, or their
        change since the thermal state at which a fit measured the mismatch
        (``fit.thermal_state_m``)."""
        if self._mismatch_from is None:
            return bar_error_m, eps
        own, ref = self._mismatch_from
        return bar_error_m - own, eps - ref[:eps.shape[1]]

    def _add_shared(self, out: FloatArray, own: FloatArray, reference: FloatArray,
                    weights: FloatArray | None) -> FloatArray:
        """A source every measuring bar has of its own and the reference bar has too (the
        readings' drift, the bars' thermal mismatch) added to ``out`` (N, 6, 6) [m^2], which
        is returned: ``own`` (N, 6) or (N, 1), each measuring bar's variance, independent;
        ``reference`` (N, k), each reference bar's (or (N, 1), alike for them), which Eq. (13)
        subtracts from every bar alike (Eq. (12): each reference bar's with its interpolation
        ``weights``)."""
        idx = np.arange(6)
        out[:, idx, idx] += own
        if self.thermal_mode == 'single':
            out += reference[:, :1, None]
        elif weights is not None:
            out += np.einsum('nik,nk,njk->nij', weights, reference[:, [0, -1]], weights)
        return out

    def _tables(self) -> dict[str, FloatArray]:
        """Per bar, on a grid of lengths (G,) over the calibrated span and 10 mm beyond: the
        calibration points' and the interpolation's variance and the routine drift's error,
        (6, G) each, before a fit's factors (:meth:`_table_factors`)."""
        if self._tab is not None:
            return self._tab
        k = self.knots_m
        lo, hi = float(k.min()) - 0.01, float(k.max()) + 0.01
        self._grid_n = 8192
        self._grid_lo = lo
        self._grid_step = (hi - lo) / (self._grid_n - 1)
        grid = np.linspace(lo, hi, self._grid_n)
        x = np.repeat(grid[:, None], 6, axis=1)
        rows = np.arange(6)[None, :]
        seg, u = bar_segments(x, k)
        tab: dict[str, FloatArray] = {}
        tab['calibration_points'] = ((self.point_var_m2 + self.point_friction_m2)
                                     * ((1.0 - u) ** 2 + u ** 2)).T
        if self._has_drift:
            e = self.drift_m[rows, seg] * (1.0 - u) + self.drift_m[rows, seg + 1] * u
            tab['calibration_drift'] = e.T
        if self.interpolation.sigma_m > 0:
            tab['interpolation'] = self.interpolation.variance(x, k).T
        if np.any(self.subdivision_left_m2 > 0):
            # e(d) - (1 - u) e(x_j) - u e(x_j+1): the live count's error, and the points' that
            # Eq. (10) carries, at phases as good as independent (points mm apart, a period of
            # um), each of variance a^2 / 2 (a sine of amplitude a, its phase unknown) less
            # what a term compensates
            tab['subdivision'] = (self.subdivision_left_m2 * (1.0 + (1.0 - u) ** 2 + u ** 2)).T
        self._tab = {name: np.ascontiguousarray(v) for name, v in tab.items()}
        return self._tab

    def _table_factors(self, x: FloatArray, bar_error_m: FloatArray | None, eps: FloatArray
                       ) -> tuple[float | FloatArray, float | FloatArray]:
        """The factors on the tabulated calibration-derived sources: on the drift and the
        interpolation, and on the points' own errors. Each is what a fit kept of them
        (:meth:`_kept`, 0 when its residual replaced them) where the fit saw the bar, rising to
        1 beyond: its residual measured nothing there. A smooth scale error known at the bound
        of the lengths the fit saw (``_seen_range_m``: its residual checked the error there,
        and ``flank_m2`` holds what it left beyond the claim in a segment whose middle it did
        not see) is, a distance delta further, unknown by the share 1 - rho(delta)^2 of its
        variance (a Gaussian process conditioned on its value there, rho its correlation, the
        one :class:`InterpolationError` fitted to the calibration's points); the factor is
        kept + (1 - kept) (1 - rho^2). A step to 1 at the bound claimed, over 24 twins, 2-3
        times the error of the bars just beyond it; delta counted from the bound of the CDF
        segments whose middle the fit saw claimed 68 nm where the bars' error was 31 nm within
        1 mm beyond the lengths seen (8 twins), and over all samples of 24 twins roll and pitch
        1.31 and 1.30 times their error (1.17 and 1.17 from the lengths seen). The
        points' own errors are not smooth (a one-sided routine's points carry a friction state
        each, independent between points): their factor is kept + (1 - kept) times the share
        of their variance from points no data checked (:meth:`_unchecked_share`). Scalars, or
        (N, 6) each."""
        kept = self._kept('interpolation')
        if self._fit_range_m is None or kept >= 1.0:
            return kept, self._with_new_placements(kept)
        cdf = x + (self.bar_error(x, eps) if bar_error_m is None else bar_error_m)
        rho = self._correlation_beyond(cdf, self._seen_range_m)
        return (kept + (1.0 - kept) * (1.0 - rho * rho),
                self._with_new_placements(kept + (1.0 - kept) * self._unchecked_share(cdf)))

    def _with_new_placements(self, points: float | FloatArray) -> float | FloatArray:
        """The factor on the points' own errors with a calibration the fit was not made with:
        the share of their variance that is a new draw claimed whole (``_new_share``)."""
        if not self.new_placements:
            return points
        return points + (1.0 - points) * self._new_share

    def _routine_drift_factor(self, factor: float | FloatArray) -> float | FloatArray:
        """The factor on the routine's drift: the interpolation's (:meth:`_table_factors`),
        or 1 when this calibration is not the one the fit was made with (its own drift)."""
        return 1.0 if self.new_placements else factor

    def _unchecked_share(self, cdf: FloatArray) -> float | FloatArray:
        """The share of the points' variance at CDF lengths ``cdf`` (N, 6) from points no data
        checked. A point is checked when a segment ending at it holds lengths the fit saw
        (``_fit_range_m``): the error along a segment is a straight line, which the lengths
        seen in it determine. A bar beyond the next point depends on a point's error no data
        saw, by its hat weight: u^2 / ((1 - u)^2 + u^2) of the points' variance. For a bar
        beyond the lengths the fit saw (``_fitted_range_m``), a point beyond them that the
        model's ``cdf_offsets`` term holds at zero is not checked either, though a segment
        ending at it holds lengths seen: the fit's samples did not come near enough to fit it,
        and the term corrects nothing there (one-sided realistic twins, zeroed fits: a bar 130
        nm off within 2 mm beyond a bound in the middle of a segment, the point beyond held at
        zero; with the size claim of the unchecked range taken away, 9.2 % of that twin's
        samples beyond were covered; within those lengths the fit's residual checked the error
        there, and the flank claim holds what it left). 0 when every bar lies within the
        segments the fit saw, else (N, 6)."""
        lo, hi = self._fit_range_m[:, 0], self._fit_range_m[:, 1]
        with np.errstate(invalid='ignore'):
            if not np.any((cdf < lo) | (cdf > hi) | np.isnan(cdf)):
                return 0.0
        if self._unchecked_points is None:
            k = self.knots_m
            lo, hi = lo[:, None], hi[:, None]
            with np.errstate(invalid='ignore'):
                first = np.max(np.where(k <= lo, k, -np.inf), axis=1, keepdims=True)
                last = np.min(np.where(k >= hi, k, np.inf), axis=1, keepdims=True)
                first = np.where(np.isfinite(first), first, k[:, :1])    # (a range past an end)
                last = np.where(np.isfinite(last), last, k[:, -1:])
                # (a bar that saw no segment's middle: every point unchecked)
                within = (k < first) | (k > last) | ~(lo <= hi)
                held = np.zeros(k.shape, dtype=bool)
                if self._fitted_range_m is not None:
                    outside = ((k < self._fitted_range_m[:, :1])
                               | (k > self._fitted_range_m[:, 1:]))
                    for term in self._length_terms:
                        if term.type_name in POINT_TERMS:
                            held |= outside & (np.asarray(term.offsets_m) == 0.0)
            self._unchecked_points = (within, within | held)
        seg, u = bar_segments(np.nan_to_num(cdf), self.knots_m)
        rows = np.arange(6)[None, :]
        w0, w1 = (1.0 - u) ** 2, u * u

        def share(unchecked: NDArray[np.bool_]) -> FloatArray:
            return (w0 * unchecked[rows, seg] + w1 * unchecked[rows, seg + 1]) / (w0 + w1)

        within, beyond_seen = self._unchecked_points
        if not np.any(beyond_seen != within):
            return share(within)
        with np.errstate(invalid='ignore'):
            beyond = ((cdf < self._fitted_range_m[:, 0]) | (cdf > self._fitted_range_m[:, 1]))
        return np.where(beyond, share(beyond_seen), share(within))

    def _correlation_beyond(self, cdf_m: FloatArray, range_m: FloatArray) -> FloatArray:
        """Per sample and bar, the correlation rho(delta) of a smooth scale error (the one
        :class:`InterpolationError` fitted to the calibration's points) between a CDF length
        ``cdf_m`` (N, 6) and the nearest bound of ``range_m`` (6, 2), delta beyond it; 1 within."""
        with np.errstate(invalid='ignore'):
            beyond = np.maximum(range_m[:, 0] - cdf_m, cdf_m - range_m[:, 1])
        return np.where(beyond > 0.0, self.interpolation.correlation(np.nan_to_num(
            np.maximum(beyond, 0.0), posinf=1.0)), 1.0)

    def length_corrections(self, terms: list[Any], range_m: FloatArray, n: int = 201
                           ) -> tuple[FloatArray, NDArray[np.bool_], list[FloatArray]]:
        """Each length-dependent term's correction at ``n`` lengths evenly spread over each
        bar's ``range_m`` (6, 2) [m] within its CDF span: the lengths (n, 6), which bars have
        any (6,), and the corrections (n, 6) each, in the order of ``terms``."""
        lengths, ok = lengths_within(range_m, self.knots_m, n)     # the terms' span: the CDF's
        ctx = TermContext(np.zeros(n), np.zeros((n, 8)), lengths, lengths, np.zeros((n, 1)),
                          np.zeros(n))
        return lengths, ok, [term.correction(ctx) for term in terms]

    def smooth_share(self, spread_m2: FloatArray) -> FloatArray:
        """Per bar, the share of a points correction's variance ``spread_m2`` (6,) [m^2] that
        the calibration points' own errors (:attr:`point_nugget_m2`) cannot explain, (6,): 0
        where it is no larger than theirs."""
        with np.errstate(divide='ignore', invalid='ignore'):
            return np.where(spread_m2 > 0.0, np.clip(
                1.0 - self._point_nugget_m2 / spread_m2, 0.0, 1.0), 0.0)

    def _length_spread(self, range_m: FloatArray) -> tuple[FloatArray, _Trend]:
        """Per bar, the mean square of the length terms' correction over the lengths
        ``range_m`` (6, 2) the fit saw, about its straight-line fit there, (6,) [m^2]: the size
        of the length-dependent error the calibration left and the data revealed; and the
        trend of the point terms' correction there (its least-squares quadratic,
        :class:`_Trend`; see :meth:`_unchecked`)."""
        n = 201
        lengths, ok, corrections = self.length_corrections(self._length_terms, range_m, n)
        c = sum(corrections)
        s = np.linspace(-1.0, 1.0, n)
        a = np.column_stack([np.ones(n), s])
        rest = c - a @ np.linalg.lstsq(a, c, rcond=None)[0]
        points = sum((correction for term, correction in zip(self._length_terms, corrections)
                      if term.type_name in POINT_TERMS), np.zeros((n, 6)))
        quadratic = np.linalg.lstsq(np.column_stack([a, s * s]), points, rcond=None)[0]
        # as much of it as the points' own errors (independent from point to point) cannot
        # explain: a trend beyond them is an error of the bar's
        quadratic = quadratic * self.smooth_share(np.mean((points - points.mean(axis=0)) ** 2,
                                                          axis=0))
        trend = _Trend(0.5 * (lengths[0] + lengths[-1]), 0.5 * (lengths[-1] - lengths[0]),
                       np.where(ok, quadratic, 0.0))
        return np.where(ok, np.mean(rest * rest, axis=0), 0.0), trend

    def _continuation_of(self, range_m: FloatArray) -> _Continuation:
        """The length terms' correction over each bar's lengths ``range_m`` (6, 2) a fit saw,
        continued beyond them (:class:`_Continuation`): conditioned on its values at
        :data:`CONTINUATION_POINTS` lengths spread over them, each as uncertain as the fit's
        principal directions make it (:attr:`FitUncertainty.directions`), and a nanometre
        more (the conditioning's jitter)."""
        n = CONTINUATION_POINTS
        lengths, ok, corrections = self.length_corrections(self._length_terms, range_m, n)
        c = sum(corrections)
        own = np.zeros((6, n, n))
        for group in (self.fit.directions if self.fit is not None else []):
            terms = [t for t in group if t.type_name in LENGTH_TERMS]
            if terms:
                v = sum(self.length_corrections(terms, range_m, n)[2]).T       # (6, n)
                own += v[:, :, None] * v[:, None, :]
        weights = np.zeros((n, 6))
        for b in np.flatnonzero(ok):
            at = lengths[:, b]
            k = (_left_covariance(self.interpolation, self.knots_m[b], self._point_nugget_m2[b],
                                  at, at) + own[b] + CONTINUATION_JITTER_M2 * np.eye(n))
            by_ones, by_c = np.linalg.solve(k, np.column_stack([np.ones(n), c[:, b]])).T
            level = by_c.sum() / by_ones.sum()      # (generalised least squares)
            weights[:, b] = by_c - level * by_ones
        return _Continuation(self.interpolation, self.knots_m, self._point_nugget_m2, lengths,
                             weights)

    def flank(self, cdf_lengths_m: FloatArray) -> FloatArray:
        """Whether each bar's CDF length lies within the lengths the fit saw but in a CDF
        segment whose middle it did not see (:func:`segments_seen`), (N, 6) bool; all False
        without a length term or a validity record."""
        x = np.asarray(cdf_lengths_m, dtype=np.float64)
        if self._fitted_range_m is None or self._fit_range_m is None:
            return np.zeros(x.shape, dtype=bool)
        lo, hi = self._fitted_range_m[:, 0], self._fitted_range_m[:, 1]
        with np.errstate(invalid='ignore'):
            return ((x >= lo) & (x <= hi)
                    & ((x < self._fit_range_m[:, 0]) | (x > self._fit_range_m[:, 1])))

    def _unchecked(self, x: FloatArray, bar_error_m: FloatArray, eps: FloatArray,
                   temp_change_c: FloatArray, points_m2: FloatArray | float = 0.0
                   ) -> FloatArray:
        """The unchecked_range source, (N, 6) [m^2]. Within the lengths the fit saw, where a
        bar lies in a CDF segment whose middle the fit did not see (:meth:`flank`): what the
        fit's residual held there beyond the model's claim (``FitUncertainty.flank_m2``: a bar's
        error there is about the same on the fitted run and on new motion, and a residual
        averaged over every length does not show it; a 0.4 µm bump there of a shape no term
        has was measured at 96 nm, a lower bound, the fitted run's samples there lying nearer
        the bound than new motion's). For a
        bar whose CDF length lies outside the lengths the fit saw: the square of how far the
        length-dependent terms' correction has moved from its value at the nearest length the
        fit saw (the residual checked the correction there; what it does beyond, no data
        checked), or, where larger, of how far it has moved from the trend the CDF points'
        correction followed within those lengths, continued (:class:`_Trend`, as much of it as
        the points' own errors cannot explain): beyond the last point the fit saw, the points'
        correction follows points no data checked (held at zero, or on the line of those seen),
        where a smooth error of the bar goes on growing (a quadratic bow of every bar's scale,
        0.25-0.35 µm from the middle of the travel to its end: on new motion 48.5 % and
        85.5 % of the samples beyond in the 95 % ellipsoid on two of four twins, 98.8 % and
        99.2 % with the trend), or, where larger still, from that correction within those
        lengths continued as the error it corrects would continue (:class:`_Continuation`):
        there the terms hold (points at zero or on a line, the series within its values seen)
        where the bar's error follows its own smooth course (a one-sided twin's bar, absolute
        fit, its correction bending down to the bound: 347 nm RMS more than 3 mm beyond, the
        moved correction claiming 104 nm, no sample within 1.96 sigma; with the continuation
        255 nm, all of them); plus the mean
        square of what the terms corrected within those lengths beyond a straight line
        (:meth:`_length_spread`): there the data showed the calibration missing an error of
        that size along the bar, and beyond them its shape is not known (a smooth error need
        not be periodic over the CDF span, as the terms' series is; on an error of another
        shape than the twin's, 61 % of the samples beyond were covered without this). That
        error is continuous: at the bound the residual checked it, and a distance delta
        further it is unknown by the share 1 - rho(delta)^2 of its size, rho the correlation
        the calibration's sources return with (:meth:`_table_factors`). Claimed whole from the
        bound on, it was 196 nm RMS within 1 mm beyond, where the bars' error was 93 nm (24
        realistic twins, zeroed fits: 32 nm less each run's constant). After a one-sided
        routine too: what the terms corrected there holds the points' friction steps, which
        the points' own source claims where no data checked a point
        (:meth:`_unchecked_share`); claimed whole from the bound on while that source counted
        the points a ``cdf_offsets`` term held at zero as checked (24 such twins, samples
        beyond the fitted lengths: zeroed 1.47-2.21 times their error, 98.8 %, now 1.23-1.90,
        98.4 %; absolute 1.45-2.14, 98.0 %, now 1.20-1.71, 96.8 %; the growing share alone,
        before those points counted as unchecked, 87.0 % on 12 twins). Beyond those lengths,
        only what exceeds the calibration_points source's claim there, ``points_m2`` (N, 6):
        the error after the length terms beyond the bound is that of the points no data
        checked (their hat-weighted errors, which that source claims where no data checked a
        point) or a smooth error's continuation (claimed here), two descriptions of one error,
        claimed as the larger, not as their sum (one-sided realistic twins, absolute fits, 12:
        samples beyond 1.32 1.86 2.15 1.20 1.63 1.17 times their error, 95.1 %; as the larger
        1.16 1.63 1.95 1.08 1.44 1.03, 94.5 %)."""
        n = x.shape[0]
        cdf = x + bar_error_m       # before the thermal compensation (the terms' shift is small)
        lo, hi = self._fitted_range_m[:, 0], self._fitted_range_m[:, 1]
        temp = np.broadcast_to(np.asarray(temp_change_c, dtype=np.float64), (n,))

        def correction(lengths: FloatArray) -> FloatArray:
            ctx = TermContext(np.zeros(n), np.zeros((n, 8)), x, lengths, eps, temp)
            return sum(term.correction(ctx) for term in self._length_terms)

        with np.errstate(invalid='ignore'):
            out = (cdf < lo) | (cdf > hi)
        flank = (np.where(self.flank(cdf), self.flank_m2, 0.0) if np.any(self.flank_m2)
                 else np.zeros((n, 6)))
        if not out.any():
            return flank
        bound = np.clip(cdf, lo, hi)
        c = correction(cdf) - correction(bound)
        trend = self._trend(cdf) - self._trend(bound)
        moved = np.maximum(c * c, (c - trend) ** 2)
        if self._continuation is None:
            self._continuation = self._continuation_of(self._fitted_range_m)
        gap = c - self._continuation.change(cdf, bound, out)       # (0 within: there c is)
        moved = np.maximum(moved, gap * gap)
        rho = self._correlation_beyond(cdf, self._fitted_range_m)
        grown = moved + self._seen_var_m2 * (1.0 - rho * rho)
        return np.where(out, np.maximum(grown - points_m2, 0.0), flank)

    def _hysteresis(self, n: int, observed: Observed | None
                    ) -> tuple[FloatArray | None, FloatArray] | None:
        """The hysteresis source of N samples: its known error (N, 6) [m] (None when a term
        compensates it) and its variance (N, 6) [m^2]; None when it is off.

        Uncompensated: -h s and h^2 (1 - s^2), s the friction state as far as the motion tells
        (scaled by what a fit kept of it). Compensated: h^2 / 3 exp(-2 p / travel) only, p the
        path the bar has travelled since the run began (``Observed.settled`` = p / (10 travel)):
        the term starts from state 0, the true start state is anywhere in [-1, 1] (variance
        1/3), and Dahl's law forgets the difference at exp(-p / travel) (each run starts with
        it unknown; a fit's residual does not replace it).
        """
        if not self._has_hysteresis:
            return None
        if self.friction_compensated:
            settled = (np.zeros((n, 6)) if observed is None or observed.settled is None
                       else observed.settled)
            return None, (self.hysteresis_m ** 2 * FRICTION_START_VAR
                          * np.exp(-2.0 * FRICTION_FORGET_TRAVELS * settled))
        kept = self._kept('hysteresis')
        if not kept:
            return None
        s_dir = np.zeros((n, 6)) if observed is None else observed.directions
        return (-math.sqrt(kept) * self.hysteresis_m * s_dir,
                kept * self.hysteresis_m ** 2 * (1.0 - s_dir * s_dir))

    def _reference_subdivision(self, eps: FloatArray) -> FloatArray | float:
        """The reference bars' sub-divisional error between their live reading and their thermal
        zero, eps (Eq. 11) apart, (N, k) [m^2]: a sine of amplitude a and unknown phase differs
        at two counts by a variance of a^2 (1 - cos(2 pi eps / period)), 0 at the zero."""
        var = self._subdivision_factor * self.subdivision_m ** 2
        if not var:
            return 0.0
        return var * (1.0 - np.cos((2.0 * math.pi / self.signal_period_m) * eps))

    def _cross(self, noise_ref_m: FloatArray, eps: FloatArray) -> FloatArray:
        """quantisation_cross_cov of each reference bar's live reading and its zero at the
        distance eps, (N, k) [m^2]; the harmonics' weights are kept while the noise stays."""
        key = tuple(np.round(noise_ref_m * 1e12))
        if key != self._cross_key:
            self._cross_key = key
            w = np.stack([quantisation_cross_weights(self.resolution_m, float(v), self.zero_noise_m)
                          for v in noise_ref_m], axis=1) if len(key) else np.zeros((0, 0))
            # harmonics that no longer matter (read noise damps them) are left out
            keep = np.flatnonzero(np.max(w, axis=1) > 1e-6 * max(float(w.max()), 1e-300)) \
                if w.size else np.zeros(0, int)
            self._cross_w = w[:keep[-1] + 1] if keep.size else w[:1]
        if not len(key):
            return np.zeros((eps.shape[0], 0))
        k = np.arange(1, self._cross_w.shape[0] + 1)
        phase = np.cos((2.0 * math.pi / self.resolution_m) * eps[:, None, :len(key)] * k[None, :, None])
        return np.einsum('nkr,kr->nr', phase, self._cross_w)

    def sources(self, lengths_m: FloatArray, reference_error_m: FloatArray,
                temp_change_c: FloatArray, bar_error_m: FloatArray | None = None,
                fit_columns_m: FloatArray | None = None, observed: Observed | None = None
                ) -> tuple[dict[str, FloatArray], dict[str, FloatArray]]:
        """Each source of N samples: the random ones as covariances (N, 6, 6) [m^2], and the
        errors whose size and sign the device knows but the compensation does not correct as
        signed vectors (N, 6) [m] (their sum b enters Sigma_d as b b^T).

        lengths_m : (N, 6) compensated lengths [m]
        reference_error_m : (N, k) Eq. (11) errors [m]; temp_change_c : (N,) [°C]
        bar_error_m : (N, 6) thermal error subtracted; None computes it (:meth:`bar_error`)
        fit_columns_m : (N, 6, r) corrections of the fitted terms' one-sigma perturbations, or
            None (then their mean over the fit's samples is used)
        observed : what :meth:`observe` returned for these samples, or None: the read-noise
            estimate in force now, no motion direction known
        """
        t = self._terms(lengths_m, reference_error_m, temp_change_c, bar_error_m, fit_columns_m,
                        observed)
        n = np.asarray(lengths_m).shape[0]
        eye = np.eye(6)
        cov: dict[str, FloatArray] = {name: v[:, :, None] * eye for name, v in t.diag.items()}
        ref = t.reference(n)
        if ref is not None:
            cov['reference_bar'] = ref
        cov.update(t.full)
        for name, m in t.constant.items():
            cov[name] = np.broadcast_to(m, (n, 6, 6))
        return cov, dict(t.bias)

    def light_tails(self, lengths_m: FloatArray, reference_error_m: FloatArray,
                    temp_change_c: FloatArray, bar_error_m: FloatArray | None = None,
                    fit_columns_m: FloatArray | None = None, observed: Observed | None = None
                    ) -> tuple[FloatArray, FloatArray]:
        """What makes Sigma_d's error lighter-tailed than a Gaussian of that covariance, for the
        size of a coverage region (:func:`~mmd_ros.core.uncertainty.region_quantile`): per bar
        the fourth cumulant of its :data:`SHAPES` sources, sum of gamma_s var_s^2, (N, 6)
        [m^4, <= 0], and the known error b (N, 6) [m] (zeros when there is none). Same
        arguments as :meth:`sources`."""
        t = self._terms(lengths_m, reference_error_m, temp_change_c, bar_error_m, fit_columns_m,
                        observed)
        n = np.asarray(lengths_m).shape[0]
        cumulant = np.zeros((n, 6))
        for name, gamma in SHAPES.items():
            if name in t.diag:
                cumulant += gamma * t.diag[name] ** 2
        known = sum(t.bias.values()) if t.bias else np.zeros((n, 6))
        return cumulant, np.asarray(known, dtype=np.float64)

    def variances(self, lengths_m: FloatArray, reference_error_m: FloatArray,
                  temp_change_c: FloatArray, bar_error_m: FloatArray | None = None,
                  fit_columns_m: FloatArray | None = None,
                  observed: Observed | None = None) -> dict[str, FloatArray]:
        """Each source's share of Sigma_d of N samples, (N, 6, 6) each [m^2] (a known error b_s
        as b_s b_s^T: the shares of the known errors do not add up to their joint b b^T)."""
        cov, bias = self.sources(lengths_m, reference_error_m, temp_change_c, bar_error_m,
                                 fit_columns_m, observed)
        for name, b in bias.items():
            cov[name] = cov.get(name, 0.0) + b[:, :, None] * b[:, None, :]
        return {name: cov[name] for name in SOURCES if name in cov}

    def covariance(self, lengths_m: FloatArray, reference_error_m: FloatArray,
                   temp_change_c: FloatArray, bar_error_m: FloatArray | None = None,
                   fit_columns_m: FloatArray | None = None,
                   observed: Observed | None = None) -> FloatArray:
        """Sigma_d of N samples, (N, 6, 6) [m^2]: the random sources' covariances plus b b^T
        of the sum b of the known errors (what :meth:`sources` lists, added up in as few array
        operations as the streaming nodes can afford for every transfer)."""
        x = np.asarray(lengths_m, dtype=np.float64)
        n = x.shape[0]
        if self._has_pairs and self._kept('reference_distances') or self.thermal_mode == 'interpolate':
            return self._covariance_by_sources(x, reference_error_m, temp_change_c, bar_error_m,
                                               fit_columns_m, observed)
        eps = np.asarray(reference_error_m, dtype=np.float64).reshape(n, -1)
        if bar_error_m is None and (self._fitted_range_m is not None or self._profile is not None):
            bar_error_m = self.bar_error(x, eps)      # (the CDF lengths those sources follow)
        noise = (np.broadcast_to(self.read_noise_m(), (n, self.noise.columns))
                 if observed is None else observed.read_noise_m)
        fast = self._fast()
        pos = (x - self._grid_lo) * (1.0 / self._grid_step)
        i0 = np.clip(pos.astype(np.intp), 0, self._grid_n - 2)
        f = pos - i0
        g = 1.0 - f
        rows = fast['rows']
        diag = fast['q12'] + noise[:, :6] ** 2
        factor, points = self._table_factors(x, bar_error_m, eps)
        bias = np.zeros((n, 6))
        drift = None
        pts = 0.0
        if np.any(points):
            tab = fast['points']
            pts = points * (tab[rows, i0] * g + tab[rows, i0 + 1] * f)
            diag += pts
        if np.any(factor) and fast['interpolation'] is not None:
            tab = fast['interpolation']
            diag += factor * (tab[rows, i0] * g + tab[rows, i0 + 1] * f)
        drift_factor = self._routine_drift_factor(factor)
        if np.any(drift_factor) and fast['drift'] is not None:
            tab = fast['drift']
            drift = np.sqrt(drift_factor) * (tab[rows, i0] * g + tab[rows, i0 + 1] * f)
        if fast['subdivision'] is not None and self._subdivision_factor:
            tab = fast['subdivision']
            diag += self._subdivision_factor * (tab[rows, i0] * g + tab[rows, i0 + 1] * f)
        if self.thermal_mode == 'single':
            if self.approximation_from_m is not None:
                bias -= (x - self.approximation_from_m) * (
                    self.scale_cte * self._temp_change_since(temp_change_c))[:, None]
            # (each bar's own mismatch here; the reference bar's below)
            own, ref_change = self._mismatch_of(
                eps[:, :1] if bar_error_m is None else bar_error_m, eps)
            if self.mismatch_fraction:
                diag += 0.5 * (self.mismatch_fraction * own) ** 2
        hysteresis = self._hysteresis(n, observed)
        if hysteresis is not None:
            if hysteresis[0] is not None:
                bias += hysteresis[0]
            diag += hysteresis[1]
        if self._fitted_range_m is not None:
            diag += self._unchecked(x, bar_error_m, eps, temp_change_c, pts)
        common = None
        if self.latch_skew_s and observed is not None and observed.velocity_m_s is not None:
            v = observed.velocity_m_s
            bias += (0.5 * self.latch_skew_s) * v
            if self.latch_common_only:
                common = (self.latch_skew_s / math.sqrt(12.0)) * v
            else:
                diag += (self.latch_skew_s ** 2 / 12.0) * v * v
        sag = None
        if self._sag_kept and observed is not None and observed.n_z2 is not None:
            bias -= (self._sag_kept * self.gravity_sag_m) * observed.n_z2
            if self.gravity_sag_sigma_m:
                sag = (self._sag_kept * self.gravity_sag_sigma_m) * observed.n_z2
        total = bias[:, :, None] * bias[:, None, :]
        if sag is not None:
            total += sag[:, :, None] * sag[:, None, :]
        scale = self._plate_scale(temp_change_c, observed)
        if scale is not None:
            total += scale[:, :, None] * scale[:, None, :]
        if common is not None:
            total += common[:, :, None] * common[:, None, :]
        total[:, rows[0], rows[0]] += diag
        if drift is not None:
            total += drift[:, :, None] * drift[:, None, :]
        drift_var = self._reading_drift(observed)
        if drift_var is not None:
            self._add_shared(total, drift_var[:, None], drift_var[:, None], None)
        if self.thermal_mode == 'single':
            cross = self._cross(noise[-1, 6:], eps)[:, 0]
            ref = (np.maximum(fast['q12'] + noise[:, 6] ** 2 + self.zero_var_m2 - 2.0 * cross, 0.0)
                   + self._reference_subdivision(eps[:, 0])
                   + 0.5 * (self.mismatch_fraction * ref_change[:, 0]) ** 2)
            total += ref[:, None, None]
        if fit_columns_m is not None and fit_columns_m.shape[-1]:
            total += fit_columns_m @ np.swapaxes(fit_columns_m, 1, 2)
            total += self.rest_terms_m2     # (the directions not evaluated per sample)
        elif self._has_mean_terms:
            total += self.mean_terms_m2
        if self._has_residual:
            total += self.residual_m2
            if self._profile is not None:
                total += self._profile.added(x + bar_error_m)
        return total

    def _fast(self) -> dict[str, Any]:
        """What :meth:`covariance` reads for every call, made once."""
        if self._fast_parts is None:
            tables = self._tables()
            self._fast_parts = {
                'rows': np.arange(6)[None, :],
                'q12': self.resolution_m ** 2 / 12.0,
                'points': tables['calibration_points'],
                'interpolation': tables.get('interpolation'),
                'drift': tables.get('calibration_drift'),
                'subdivision': tables.get('subdivision'),
            }
        return self._fast_parts

    def _covariance_by_sources(self, x: FloatArray, reference_error_m: FloatArray,
                               temp_change_c: FloatArray, bar_error_m: FloatArray | None,
                               fit_columns_m: FloatArray | None, observed: Observed | None
                               ) -> FloatArray:
        t = self._terms(x, reference_error_m, temp_change_c, bar_error_m, fit_columns_m, observed)
        n = x.shape[0]
        total = np.zeros((n, 6, 6))
        idx = np.arange(6)
        total[:, idx, idx] = sum(t.diag.values())
        ref = t.reference(n)
        if ref is not None:
            total += ref
        for m in t.full.values():
            total += m
        for m in t.constant.values():
            total += m
        if t.bias:
            b = sum(t.bias.values())
            total += b[:, :, None] * b[:, None, :]
        return total

    def summary(self) -> dict[str, Any]:
        """The budget's numbers, for reports (SI units in the keys' names)."""
        noise = self.read_noise_m()
        return {
            'thermal_mode': self.thermal_mode,
            'resolution_nm': self.resolution_m * 1e9,
            'read_noise_nm': [round(float(v) * 1e9, 3) for v in noise],
            'read_noise_from': ('model file' if self.fixed_noise_m is not None else
                                ['stream' if w >= self.noise.min_windows else
                                 'analysis' if f > (self.calibration_noise_m or 0.0) else 'calibration'
                                 for w, f in zip(self.noise.windows, self.fallback_noise_m)]),
            'calibration_point_nm': round(math.sqrt(self.point_var_m2) * 1e9, 3),
            'seating_nm': None if self.seating_m is None else round(self.seating_m * 1e9, 3),
            'seating_from': ('calibration' if self.figures.seating_m is not None else
                             None if self.seating_m is None else 'device description'),
            'calibration_point_friction_nm': [round(float(v) * 1e9, 2)
                                              for v in np.sqrt(self.point_friction_m2)],
            'routine_temp_change_c': self.figures.routine_temp_change_c,
            'calibration_drift_nm': round(float(np.max(np.abs(self.drift_m))) * 1e9, 3),
            'thermal_zero_nm': round(math.sqrt(self.zero_var_m2) * 1e9, 3),
            'interpolation': self.interpolation.as_dict(),
            'thermal_mismatch_fraction': self.mismatch_fraction,
            'thermal_mismatch_from_nm': (None if self._mismatch_from is None else [
                round(float(v) * 1e9, 1) for v in np.concatenate(self._mismatch_from)]),
            'temp_change_from_c': round(self._temp_change_from, 4),
            'plate_scale_ppm_per_c': round(self.plate_scale_rel * 1e6, 6),
            'hysteresis_nm': [round(float(v) * 1e9, 2) for v in self.hysteresis_m],
            'latch_skew_us': round(self.latch_skew_s * 1e6, 3),
            'latch_skew_common_only': self.latch_common_only,
            'gravity_sag_nm': round(self.gravity_sag_m * 1e9, 3),
            'gravity_sag_uncertainty_nm': round(self.gravity_sag_sigma_m * 1e9, 3),
            'vertical': [round(float(v), 6) for v in self._up],
            'drift_nm_per_h': round(self.drift_rate_m_per_s * 1e9 * 3600.0, 6),
            'calibrated_unix_s': self.calibrated_s,
            'drift_counted_from_unix_s': self.drift_from_s,
            'subdivision_nm': round(self.subdivision_m * 1e9, 3),
            'signal_period_um': round(self.signal_period_m * 1e6, 6),
            'subdivision_left_nm': [round(math.sqrt(2.0 * v) * 1e9, 3) for v in self.subdivision_left_m2],
            'fit': None if self.fit is None else {
                'replaces': sorted(self.replaced), 'systematic_scale': self.systematic_scale,
                'made_with_another_calibration': self.new_placements,
                'residual_nm': [round(float(math.sqrt(max(v, 0.0))) * 1e9, 2)
                                for v in np.diag(self.residual_m2)],
                'directions': len(self.fit.directions)},
            'notes': list(self.notes),
        }
