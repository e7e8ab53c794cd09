"""The catalogue of physical effects the compensation model may lack.

Each effect is a parameterised correction of the bar lengths with a physical meaning and its own
signature: dd (N, 6) = sum_k theta_k s_k, where s_k is what the effect's model term
(:mod:`mmd_ros.core.terms`, or :class:`~mmd_ros.core.model.HysteresisTerm`) computes per unit
of parameter k. The analysis fits theta to the residual (mapped into the reference's
observation space) and the pipeline then applies exactly that term from the model file.

An effect also says which of its parameters the data can identify at all ("coverage": a bar that
never reverses shows no hysteresis, a bar that moves less than a signal period shows no cyclic
error, a temperature that does not change shows no thermal gain), and which features of the data
its signature follows (for the check that what remains of the residual is not still structured
along the effect's own coordinate).

| effect | term | signature per bar i (correction per unit parameter) |
|---|---|---|
| hysteresis | friction | -s_i(t), Dahl friction state turning over within a fitted travel |
| thermal_gain | thermal_gain | -eps_i(t) (gain), d eps_i/dt (lag) |
| thermal_interpolation | thermal_interpolation | (d_i - d_ref) eps(t), one coefficient |
| plate_expansion | plate_scale | -dd_i/ds x (1, dT, -alpha_p d(dT)/dt) |
| kinematic | joint_offsets | -R^T n_i, n_i (joints), -1 (length offset): 42 parameters |
| scale_nonlinearity | scale_nonlinearity | -(sin/cos 2 pi k xi - PL interpolant), k = 1..3 |
| calibration_points | cdf_offsets | -(hat function of CDF point j at d_i) |
| cyclic_error | cyclic_error | -sin, -cos of 2 pi (q_i - q0_i) res / period |
| sampling_skew | sampling_skew | -v_i(t) |
| gravity_sag | gravity_sag | n_z,i^2 (one g for all bars) |
| drift | drift | -1, -(t - t_first) |
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from mmd_ros.analysis.data import DIRECTION_TRAVEL_M, MOVING_M, FitContext
from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.core.lag import MAX_SKEW_S
from mmd_ros.core.model import ModelTerm
from mmd_ros.core.terms import (
    DERIVATIVE_FILTER_S, CdfOffsetsTerm, CyclicErrorTerm, DriftTerm, FrictionTerm, GravitySagTerm,
    JointOffsetsTerm,
    PlateScaleTerm, SamplingSkewTerm, ScaleNonlinearityTerm, ThermalGainTerm,
    ThermalInterpolationTerm, ema, leg_geometry,
)
from mmd_ros.core.thermal import thermal_sensitivity
from mmd_ros.core.units import M_PER_MM, M_PER_UM

__all__ = ['CATALOGUE', 'Effect', 'Parameter', 'catalogue']

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A thermal signature needs the reference bar's error to change by at least this much [m].
THERMAL_MIN_M = 0.5e-6
#: The Eq. (12) term needs bars this much longer or shorter than the reference bar [m].
INTERPOLATION_MIN_M = 10e-3
#: A plate CTE or lag needs the temperature to change by at least this much [°C].
PLATE_MIN_C = 0.2
#: Periods of a cyclic error searched in the residual's spectrum: from 4 counts up to this,
#: and at most an eighth of a bar's travel (longer is scale nonlinearity) [m].
CYCLIC_MAX_PERIOD_M = 2e-3
#: A spectral peak counts when its power is this many times the local median of the spectrum
#: (the largest of ~10^6 noise bins is about 20 times it).
CYCLIC_PEAK_RATIO = 30.0
#: Candidate periods taken from the spectrum.
CYCLIC_CANDIDATES = 3
#: Bins of the spectrum a band of the background's running median reads at most.
MEDIAN_SAMPLES = 65536
#: Starting grid of the friction turn-over travel (Dahl), refined between neighbours [m].
FRICTION_TRAVELS_M = tuple(0.1e-6 * 2.0 ** k for k in range(11))
#: Harmonics of the scale error over the calibrated span.
SCALE_HARMONICS = 3


@dataclass(frozen=True)
class Parameter:
    """A fitted parameter as reported: ``value_report = value_si * factor`` in ``unit``.
    ``bound`` is the largest physically plausible magnitude [SI]: a fitted direction that needs
    more is not identified by the data (it is reported, not fitted)."""

    name: str
    unit: str
    factor: float
    bound: float = math.inf


def _diag(values: FloatArray) -> FloatArray:
    """(n, 6) per-bar signature to (n, 6, 6) columns, column i acting on bar i only."""
    out = np.zeros(values.shape + (6,))
    idx = np.arange(6)
    out[:, idx, idx] = values
    return out


def _per_bar(blocks: list[FloatArray]) -> FloatArray:
    """Per-bar signatures [(n, 6), ...] (one per parameter kind) to (n, 6, 6 * kinds) columns
    ordered kind-major: all bars of kind 0, then kind 1..."""
    return np.concatenate([_diag(b) for b in blocks], axis=2)


def _usable(ctx: FitContext) -> BoolArray:
    return ctx.obs.usable & ctx.base.measured(ctx.obs.kind)


class Effect:
    """One physical effect of the catalogue (see the module docstring)."""

    name = ''
    term_type = ''
    title = ''
    physics = ''
    needs_pose = False
    #: Whose property the parameters are: 'device' (shared by every run), 'calibration' (they
    #: belong to one calibration: fitted per calibration, re-analyse after a new one) or 'run'.
    scope = 'device'
    #: The mean the term gives a pose component over a log is not fixed by how it varies: free
    #: constants (CDF point offsets, harmonics, joint coordinates, a drift's offsets at a run's
    #: start, held with its rates). With a zeroed reference the fit then holds that mean
    #: (identify.py, _Rows); a term of one physical law (sag, friction, skew, thermal) carries
    #: the mean its law gives
    free_mean = False
    #: The setting is a continuous quantity estimated from the data (a period, a travel): its
    #: uncertainty is claimed with the parameters' (identify.py, _Selector.setting_shift)
    continuous_setting = False
    #: The continuous setting is a measured quantity (a period): refined to the least error of
    #: the fit, not by the information criterion (identify.py, _Selector._best_setting)
    setting_measured = False

    def applicable(self, ctx: FitContext) -> str | None:
        """None when the effect can be tested on this log, else why not."""
        if self.needs_pose and ctx.obs.kind != 'pose':
            return ('the reference gives bar lengths of bars not on the MMD; a pose-dependent '
                    'effect does not change them')
        return None

    def hypers(self, ctxs: list[FitContext]) -> list[Any]:
        """Settings to try, given every run of the analysis."""
        return [None]

    def hyper_label(self, hyper: Any) -> str:
        return ''

    def refine_bounds(self, hyper: Any, tried: list[Any], ctxs: list[FitContext]
                      ) -> tuple[float, float] | None:
        """For a continuous setting: the interval around the best one tried in which to refine
        its value (golden section in its logarithm); None when the setting is not refined."""
        return None

    def setting_value(self, hyper: Any) -> float | None:
        """The continuous value of a setting (refined; its uncertainty claimed), or None."""
        return float(hyper) if self.continuous_setting and isinstance(hyper, float) else None

    def with_setting_value(self, hyper: Any, value: float) -> Any:
        """The setting ``hyper`` with its continuous value replaced by ``value``."""
        return float(value)

    def undetermined_forms(self, hyper: Any, ctxs: list[FitContext]) -> list[Any]:
        """Other settings of the same parameters that these logs could not tell from
        ``hyper`` (not tried: their difference is claimed, analysis/uncertainty.py)."""
        return []

    def parameters(self, ctx: FitContext, hyper: Any) -> list[Parameter]:
        raise NotImplementedError

    def signature(self, ctx: FitContext, hyper: Any, idx: NDArray[np.int64]) -> FloatArray:
        """Length correction per unit of each parameter at samples ``idx``, (n, 6, P)."""
        raise NotImplementedError

    def coverage(self, ctx: FitContext, hyper: Any, idx: NDArray[np.int64]) -> tuple[BoolArray, str]:
        """Which parameters the samples ``idx`` exercise, (P,), and why the others are not."""
        return np.ones(len(self.parameters(ctx, hyper)), dtype=bool), ''

    def ties(self, ctx: FitContext, hyper: Any, ok: BoolArray,
             touched: BoolArray) -> FloatArray | None:
        """How parameters the samples do not exercise enough (``ok`` False, (P,)) but touch
        (``touched``: a non-zero column) follow the others: T (P, P), theta = T theta_free, the
        identity but for their rows; None when none does."""
        return None

    def make_term(self, ctx: FitContext, hyper: Any, theta: FloatArray) -> ModelTerm:
        raise NotImplementedError

    def make_terms(self, ctx: FitContext, hyper: Any, theta: FloatArray) -> list[ModelTerm]:
        """The model term(s) that apply the fitted parameters ``theta``."""
        return [self.make_term(ctx, hyper, theta)]

    def diagnostics(self, ctx: FitContext, hyper: Any) -> dict[str, FloatArray]:
        """Features (N,) the effect's signature follows."""
        return {}

    def interpret(self, ctx: FitContext, hyper: Any, theta: FloatArray, sigma: FloatArray) -> list[str]:
        """Physical reading of the fitted values, in words."""
        return []


def _bar_names(kind: str, unit: str, factor: float, bound: float = math.inf) -> list[Parameter]:
    return [Parameter(f'bar{i + 1} {kind}', unit, factor, bound) for i in range(6)]


def _moving_bars(ctx: FitContext) -> BoolArray:
    u = _usable(ctx)
    return np.ptp(ctx.base.pre_lengths_m[u], axis=0) > MOVING_M if u.any() else np.zeros(6, bool)


# -- the catalogue -----------------------------------------------------------------------------
class Hysteresis(Effect):
    name = 'hysteresis'
    term_type = 'friction'
    title = 'friction hysteresis'
    physics = ('friction in the ball joints and guides makes a bar read differently when it '
               'lengthens and when it shortens (section 5.3); the friction state turns over '
               'gradually after a reversal (Dahl), within a travel estimated from the data')
    continuous_setting = True

    def hypers(self, ctxs):
        return list(FRICTION_TRAVELS_M)

    def refine_bounds(self, hyper, tried, ctxs):
        k = tried.index(hyper)
        return tried[max(k - 1, 0)], tried[min(k + 1, len(tried) - 1)]

    def hyper_label(self, hyper: Any) -> str:
        return f'turn-over travel {hyper / M_PER_UM:.3g} µm'

    def parameters(self, ctx: FitContext, hyper: Any) -> list[Parameter]:
        return _bar_names('amplitude', 'µm', 1 / M_PER_UM, 5e-6)

    def signature(self, ctx, hyper, idx):
        return _diag(-ctx.friction(hyper)[idx])

    def coverage(self, ctx, hyper, idx):
        ok = ctx.both_ways(DIRECTION_TRAVEL_M, idx)
        return ok, '' if ok.all() else 'bars that do not move both ways: ' + _bars(~ok)

    def make_term(self, ctx, hyper, theta):
        return FrictionTerm(np.asarray(theta), float(hyper), ctx.device.encoder_resolution_m)

    def diagnostics(self, ctx, hyper):
        d = ctx.directions(DIRECTION_TRAVEL_M)
        return {f'bar{i + 1} direction': d[:, i] for i in np.flatnonzero(_moving_bars(ctx))}

    def interpret(self, ctx, hyper, theta, sigma):
        amp = np.abs(np.asarray(theta)) / M_PER_UM
        sign = 'long' if np.mean(theta) > 0 else 'short'
        return [f'mean |amplitude| {amp.mean():.3f} µm (bars {amp.min():.3f} … {amp.max():.3f} µm): '
                f'the bars read {sign} while lengthening; the friction state turns over within about '
                f'{3 * hyper / M_PER_UM:.3g} µm of reverse travel (travel constant {hyper / M_PER_UM:.3g} µm)']


class ThermalGain(Effect):
    name = 'thermal_gain'
    term_type = 'thermal_gain'
    title = 'per-bar thermal gain and lag against the reference bar'
    physics = ('Eq. (13) assumes every bar has the reference bar\'s thermal error; a bar with a '
               'different CTE or time constant (section 4.1: "minor differences") has a residual '
               'proportional to that error (gain) and to its rate of change (lag)')

    def _features(self, ctx: FitContext) -> tuple[FloatArray, FloatArray]:
        def make():
            g, r, _ = ThermalGainTerm.features(ctx.base.bar_error_m, ctx.times_s,
                                               DERIVATIVE_FILTER_S, None)
            return g, r
        return ctx.cached('thermal_gain', make)

    def parameters(self, ctx, hyper):
        return _bar_names('gain', '%', 100.0, 1.0) + _bar_names('lag', 's', 1.0, 3600.0)

    def signature(self, ctx, hyper, idx):
        g, r = self._features(ctx)
        return _per_bar([g[idx], r[idx]])

    def coverage(self, ctx, hyper, idx):
        if not ctx.thermal_on:
            return np.zeros(12, bool), 'no thermal compensation in the model'
        span = np.ptp(ctx.base.bar_error_m[idx], axis=0)
        ok = np.tile(span >= THERMAL_MIN_M, 2)
        return ok, '' if ok.all() else (f'the thermal error changes by only {span.max() / M_PER_UM:.2f} µm '
                                         f'(< {THERMAL_MIN_M / M_PER_UM:g} µm)')

    def make_term(self, ctx, hyper, theta):
        return ThermalGainTerm(theta[:6], theta[6:], DERIVATIVE_FILTER_S)

    def diagnostics(self, ctx, hyper):
        return {'reference-bar thermal error': ctx.base.bar_error_m.mean(axis=1)}

    def interpret(self, ctx, hyper, theta, sigma):
        return [f'bar thermal errors differ from the reference bar\'s by {100 * np.min(theta[:6]):+.1f} … '
                f'{100 * np.max(theta[:6]):+.1f} %, lags {np.min(theta[6:]):+.0f} … {np.max(theta[6:]):+.0f} s']


class ThermalInterpolation(Effect):
    name = 'thermal_interpolation'
    term_type = 'thermal_interpolation'
    title = 'Eq. (12) length interpolation of the thermal error'
    physics = ('the scale between the reference bar\'s length and a bar\'s length expands too '
               '(section 3.3: 0.037 µm/°C from 323 to 376 mm); Eq. (13) drops this term, Eq. (12) '
               'interpolates it')

    def _ref_distance(self, ctx: FitContext) -> float:
        refs = ctx.device.reference_channels
        return ctx.device.pair(refs[0].pair).distance_m if refs else 0.0

    def parameters(self, ctx, hyper):
        return [Parameter('coefficient', '1/m', 1.0, 100.0)]

    def signature(self, ctx, hyper, idx):
        f = ThermalInterpolationTerm.features(ctx.base.pre_lengths_m[idx],
                                              ctx.base.reference_error_m[idx], self._ref_distance(ctx))
        return f[:, :, None]

    def coverage(self, ctx, hyper, idx):
        if not ctx.thermal_on:
            return np.zeros(1, bool), 'no thermal compensation in the model'
        eps = np.max(np.abs(ctx.base.reference_error_m[idx, 0]))
        spread = np.max(np.abs(ctx.base.pre_lengths_m[idx] - self._ref_distance(ctx)))
        if spread < INTERPOLATION_MIN_M:
            return np.zeros(1, bool), (f'the bars stay within {spread * 1e3:.1f} mm of the reference '
                                       f'bar\'s length (< {INTERPOLATION_MIN_M * 1e3:g} mm)')
        ok = eps >= THERMAL_MIN_M
        return np.array([ok]), '' if ok else (f'the thermal error stays below {eps / M_PER_UM:.2f} µm '
                                              f'(< {THERMAL_MIN_M / M_PER_UM:g} µm)')

    def make_term(self, ctx, hyper, theta):
        return ThermalInterpolationTerm(float(theta[0]), self._ref_distance(ctx))

    def diagnostics(self, ctx, hyper):
        return {'reference-bar thermal error': ctx.base.reference_error_m[:, 0]}

    def interpret(self, ctx, hyper, theta, sigma):
        dev = ctx.device
        d_ref = self._ref_distance(ctx)
        sens = thermal_sensitivity(dev, d_ref)
        alpha = -theta[0] * sens
        return [f'implies a scale CTE of {alpha * 1e6:.2f} ± {abs(sigma[0] * sens) * 1e6:.2f} ppm/°C '
                f'(device description: {dev.scale_cte_per_c * 1e6:g} ppm/°C)']


class PlateExpansion(Effect):
    name = 'plate_expansion'
    term_type = 'plate_scale'
    title = 'plate expansion'
    physics = ('the joints are scaled by the plates\' expansion estimated from the reference bar '
               '(end of section 3.3); a scale error at the thermal zero, a CTE error or plates '
               'lagging the bars change every length by ds * n_i . (R a_i - b_i)')
    needs_pose = True

    def parameters(self, ctx, hyper):
        return [Parameter('scale offset', 'ppm', 1e6, 100e-6), Parameter('CTE error', 'ppm/°C', 1e6, 10e-6),
                Parameter('plate lag', 's', 1.0, 1e4)]

    def _rate(self, ctx: FitContext) -> FloatArray:
        def make():
            t = ctx.base.temp_change_c
            low, _ = ema(t[:, None], ctx.times_s, DERIVATIVE_FILTER_S, None)
            return (t - low[:, 0]) / DERIVATIVE_FILTER_S
        return ctx.cached('plate_rate', make)

    def signature(self, ctx, hyper, idx):
        geo = ctx.device.geometry
        _, _, ddds = leg_geometry(geo.upper, geo.lower, ctx.base.poses[idx])
        dt = ctx.base.temp_change_c[idx, None]
        rate = self._rate(ctx)[idx, None]
        a_p = ctx.device.plate_cte_per_c
        return np.stack([-ddds, -ddds * dt, a_p * ddds * rate], axis=2)

    def coverage(self, ctx, hyper, idx):
        span = np.ptp(ctx.base.temp_change_c[idx]) if ctx.thermal_on else 0.0
        ok = np.array([True, span >= PLATE_MIN_C, span >= PLATE_MIN_C])
        return ok, '' if ok.all() else (f'the temperature changes by only {span:.2f} °C: the CTE error '
                                        'and lag are not identifiable')

    def make_term(self, ctx, hyper, theta):
        geo = ctx.device.geometry
        return PlateScaleTerm(geo.upper, geo.lower, theta[0], theta[1], theta[2],
                              ctx.device.plate_cte_per_c, DERIVATIVE_FILTER_S)

    def diagnostics(self, ctx, hyper):
        out = {'temperature change': ctx.base.temp_change_c}
        out.update(_pose_features(ctx))
        return out

    def interpret(self, ctx, hyper, theta, sigma):
        return [f'the plates\' scale differs from the model\'s by {theta[0] * 1e6:+.2f} ppm '
                f'(+{theta[1] * 1e6:.3f} ppm/°C of temperature change)']


def _pose_features(ctx: FitContext) -> dict[str, FloatArray]:
    u = _usable(ctx)
    names = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
    p = ctx.base.poses
    return {f'pose {names[k]}': p[:, k] for k in range(6) if u.any() and np.ptp(p[u, k]) > 1e-5}


class Kinematic(Effect):
    free_mean = True
    name = 'kinematic'
    term_type = 'joint_offsets'
    title = 'kinematic parameters (joint positions and bar length offsets)'
    physics = ('the 42 kinematic parameters (section 2.2: 36 joint coordinates and 6 bar lengths) '
               'differ from the device description; each changes a bar length by n_i . (R da_i - '
               'db_i) or by its offset')
    needs_pose = True

    def parameters(self, ctx, hyper):
        out = []
        for i in range(6):
            out += [Parameter(f'bar{i + 1} upper {c}', 'µm', 1 / M_PER_UM, 300e-6) for c in 'xyz']
            out += [Parameter(f'bar{i + 1} lower {c}', 'µm', 1 / M_PER_UM, 300e-6) for c in 'xyz']
            out.append(Parameter(f'bar{i + 1} length', 'µm', 1 / M_PER_UM, 100e-6))
        return out

    def signature(self, ctx, hyper, idx):
        geo = ctx.device.geometry
        up, low, length = JointOffsetsTerm.features(geo.upper, geo.lower, ctx.base.poses[idx])
        n = idx.size
        out = np.zeros((n, 6, 42))
        for i in range(6):
            out[:, i, 7 * i:7 * i + 3] = up[:, i]
            out[:, i, 7 * i + 3:7 * i + 6] = low[:, i]
            out[:, i, 7 * i + 6] = length[:, i]
        return out

    def make_term(self, ctx, hyper, theta):
        geo = ctx.device.geometry
        t = np.asarray(theta).reshape(6, 7)
        return JointOffsetsTerm(geo.upper, geo.lower, t[:, :3], t[:, 3:6], t[:, 6])

    def diagnostics(self, ctx, hyper):
        return _pose_features(ctx)

    def interpret(self, ctx, hyper, theta, sigma):
        t = np.asarray(theta).reshape(6, 7)
        joints = np.linalg.norm(t[:, :6].reshape(12, 3), axis=1)
        return [f'joint corrections up to {joints.max() / M_PER_UM:.2f} µm, length offsets '
                f'{np.min(t[:, 6]) / M_PER_UM:+.2f} … {np.max(t[:, 6]) / M_PER_UM:+.2f} µm '
                '(minimum-norm in the identifiable directions)']


class ScaleNonlinearity(Effect):
    free_mean = True
    name = 'scale_nonlinearity'
    term_type = 'scale_nonlinearity'
    title = 'scale nonlinearity between CDF points'
    physics = ('the CDF (Eq. 10) is exact at the seven calibration points and linear between them; '
               'a smooth scale error leaves what it cannot follow between the points')

    def _knots(self, ctx: FitContext) -> FloatArray:
        return _knots(ctx)

    def parameters(self, ctx, hyper):
        out = []
        for kind in ('sin', 'cos'):
            for k in range(1, SCALE_HARMONICS + 1):
                out += _bar_names(f'{kind} {k}', 'µm', 1 / M_PER_UM, 5e-6)
        return out

    def signature(self, ctx, hyper, idx):
        b = ScaleNonlinearityTerm.basis(ctx.base.cdf_lengths_m[idx], self._knots(ctx), SCALE_HARMONICS)
        return _per_bar([b[:, :, j] for j in range(2 * SCALE_HARMONICS)])

    def coverage(self, ctx, hyper, idx):
        knots = self._knots(ctx)
        seg = np.median(np.diff(knots, axis=1), axis=1)
        span = np.ptp(ctx.base.cdf_lengths_m[idx], axis=0)
        bars = span >= 0.25 * seg
        ok = np.tile(bars, 2 * SCALE_HARMONICS)
        return ok, '' if ok.all() else 'bars that move less than a quarter of a CDF segment: ' + _bars(~bars)

    def make_term(self, ctx, hyper, theta):
        t = np.asarray(theta).reshape(2 * SCALE_HARMONICS, 6).T  # (6, 2K): sin k.., cos k..
        return ScaleNonlinearityTerm(self._knots(ctx), t[:, :SCALE_HARMONICS], t[:, SCALE_HARMONICS:])

    def diagnostics(self, ctx, hyper):
        return {f'bar{i + 1} length': ctx.base.cdf_lengths_m[:, i] for i in np.flatnonzero(_moving_bars(ctx))}

    def interpret(self, ctx, hyper, theta, sigma):
        t = np.asarray(theta).reshape(2 * SCALE_HARMONICS, 6).T
        amp = np.sqrt(t[:, :SCALE_HARMONICS] ** 2 + t[:, SCALE_HARMONICS:] ** 2).sum(axis=1)
        return [f'scale error harmonics up to {amp.max() / M_PER_UM:.2f} µm over the span '
                f'(bar{int(np.argmax(amp)) + 1})']


#: Settings of the calibration points' effect: what a point beyond the lengths seen, whose ramp
#: the samples still reach, is (:meth:`CalibrationPoints.ties`).
POINTS_BEYOND = {'zero': 'points beyond the lengths seen held at zero',
                 'line': 'points beyond the lengths seen on the line of those seen'}


class CalibrationPoints(Effect):
    free_mean = True
    scope = 'calibration'
    name = 'calibration_points'
    term_type = 'cdf_offsets'
    title = 'errors of the calibration points'
    physics = ('a bar seated on a reference pair with an offset (seating repeatability, or the '
               'friction state its guide was left in, section 5.3) gives a wrong CDF point; Eq. (10) '
               'carries the error linearly between the points')

    def parameters(self, ctx, hyper):
        knots = _knots(ctx)
        return [Parameter(f'bar{i + 1} point {j + 1} ({knots[i, j] / M_PER_MM:.1f} mm)', 'µm',
                          1 / M_PER_UM, 5e-6) for j in range(knots.shape[1]) for i in range(6)]

    def signature(self, ctx, hyper, idx):
        b = CdfOffsetsTerm.basis(ctx.base.cdf_lengths_m[idx], _knots(ctx))
        return _per_bar([b[:, :, j] for j in range(b.shape[2])])

    def coverage(self, ctx, hyper, idx):
        """A point whose neighbourhood (a quarter of a segment either side) no sample reached is
        seen only through the tail of its ramp, where its offset and a scale error cannot be
        told apart: jointly with the scale term, 16 µm at a point 11 mm short of the lengths
        seen, against 42 µm of harmonics, where the error was 0.5 µm."""
        knots = _knots(ctx)
        seg = np.median(np.diff(knots, axis=1), axis=1)
        lengths = ctx.base.cdf_lengths_m[idx]
        span = np.ptp(lengths, axis=0)
        bars = span >= 0.25 * seg
        lo, hi = lengths.min(axis=0), lengths.max(axis=0)
        reach = 0.25 * seg[:, None]
        near = (knots + reach >= lo[:, None]) & (knots - reach <= hi[:, None])     # (6, n)
        ok = (near & bars[:, None]).T.reshape(-1)          # parameters ordered point by point
        notes = []
        if not bars.all():
            notes.append('bars that move less than a quarter of a CDF segment: ' + _bars(~bars))
        if (bars[:, None] & ~near).any():
            notes.append('points no sample came within a quarter of a segment of')
        return ok, '; '.join(notes)

    def hypers(self, ctxs):
        # (with a reference that sees every component's mean the data set the level, and a
        # point the calibration measured is better held at its own small error: on a realistic
        # twin the line took the slope on over a segment's flank, 0.11 µm off where zero left
        # 0.035)
        return list(POINTS_BEYOND) if any(ctx.obs.datum for ctx in ctxs) else ['zero']

    def hyper_label(self, hyper):
        return POINTS_BEYOND[hyper]

    def ties(self, ctx, hyper, ok, touched):
        """A point the samples did not come near, whose ramp they still reach, is either held at
        zero (an error of its own, not known: setting 'zero') or on the line through the two
        nearest points seen (between them, across a gap; setting 'line': the error goes on as
        it went, as a bow of the scale does); the data choose. Held at zero, it sets the level
        of what the fit saw, which a zeroed reference does not see: a bow of the bars' scale
        fitted so came out 0.15 µm low on every bar, moved z's mean 0.19-0.32 µm, and made new
        motion's z 1.8-3.6 times worse than the unchanged model."""
        if hyper != 'line':
            return None
        knots = _knots(ctx)
        n = knots.shape[1]
        ok, touched = ok.reshape(n, 6), touched.reshape(n, 6)      # (points, bars)
        tie, changed = np.eye(6 * n), False
        for i in range(6):
            seen = np.flatnonzero(ok[:, i])
            for j in np.flatnonzero(touched[:, i] & ~ok[:, i]) if seen.size else []:
                below, above = seen[seen < j], seen[seen > j]
                if below.size and above.size:
                    near, other = below[-1], above[0]
                elif below.size:
                    near, other = below[-1], (below[-2] if below.size > 1 else None)
                else:
                    near, other = above[0], (above[1] if above.size > 1 else None)
                row = j * 6 + i
                tie[row, row], changed = 0.0, True
                if other is None:
                    tie[row, near * 6 + i] = 1.0
                    continue
                r = (knots[i, j] - knots[i, near]) / (knots[i, near] - knots[i, other])
                tie[row, near * 6 + i], tie[row, other * 6 + i] = 1.0 + r, -r
        return tie if changed else None

    def make_term(self, ctx, hyper, theta):
        knots = _knots(ctx)
        return CdfOffsetsTerm(knots, np.asarray(theta).reshape(knots.shape[1], 6).T)

    def diagnostics(self, ctx, hyper):
        return {f'bar{i + 1} length': ctx.base.cdf_lengths_m[:, i] for i in np.flatnonzero(_moving_bars(ctx))}

    def interpret(self, ctx, hyper, theta, sigma):
        return [f'calibration point errors {np.min(theta) / M_PER_UM:+.2f} … {np.max(theta) / M_PER_UM:+.2f} µm '
                '(minimum-norm in the identifiable directions): errors of the points themselves, '
                'which a new calibration removes, or an error along the bar between them that the '
                'calibration did not read, which it does not']


class CyclicError(Effect):
    """The setting is (period, read in the calibration): the calibration read the same scale,
    so each of its points took the error at its count and the CDF carries those values between
    them (the error as a calibrated bar reads it, :class:`CyclicErrorTerm`); an error added to
    the runs only (another program's logs) lacks that part. With a reference that sees every
    bar both are tried and the data choose; otherwise the runs' part only."""

    name = 'cyclic_error'
    term_type = 'cyclic_error'
    title = 'encoder cyclic error'
    physics = ('the interpolation of the scale\'s sine signals errs periodically with the signal '
               'period; the error follows the scale position, not time, and the calibration '
               'read it too')
    scope = 'calibration'   # the phase is counted from the calibration's first point
    continuous_setting = True
    setting_measured = True

    def _setup(self, ctx: FitContext) -> tuple[list[int], FloatArray]:
        names = ctx.device.channel_names
        channels = list(ctx.device.measuring_channels)
        origin = []
        for ch in channels:
            bar = ctx.calibration.bars[names[ch]]
            order = np.argsort(bar.distances_m)
            origin.append(float(np.asarray(bar.counts)[order][0]))
        return channels, np.array(origin)

    @staticmethod
    def _knots(ctx: FitContext, hyper: tuple[float, bool]) -> list[FloatArray] | None:
        """Each bar's calibration counts, when the calibration read the error."""
        if not hyper[1]:
            return None
        names = ctx.device.channel_names
        return [np.sort(np.asarray(ctx.calibration.bars[names[ch]].counts, dtype=np.float64))
                for ch in ctx.device.measuring_channels]

    def hypers(self, ctxs):
        opts = getattr(ctxs[0].options, 'cyclic_periods_m', None)
        periods = list(opts) if opts else [p for p, _ in cyclic_periods(ctxs, self._setup)]
        # the calibration's part, a line through the points on each bar, is told apart from
        # other smooth errors only by a reference that sees every bar: from a C-axis run
        # without read noise it was chosen for an error the calibration had not read, with a
        # period 1e-4 off, and 6-DOF motion got worse (0.9 % in the ellipsoid)
        every_bar = any(c.obs.sees_every_bar for c in ctxs)
        return [(float(p), read) for p in periods for read in ((True, False) if every_bar else (False,))]

    def undetermined_forms(self, hyper, ctxs):
        # the calibration's part, not tried without a reference that sees every bar: a real
        # encoder's calibration reads its error, so its line through the points is claimed
        # (an 80 nm error the calibration read, fitted from an x-axis laser run, left 47 % and
        # 65 % of new 6-DOF motion in the ellipsoid)
        return [] if hyper[1] or any(c.obs.sees_every_bar for c in ctxs) else [(hyper[0], True)]

    def setting_value(self, hyper):
        return hyper[0]

    def with_setting_value(self, hyper, value):
        return (float(value), hyper[1])

    def hyper_label(self, hyper):
        return f'period {hyper[0] / M_PER_UM:.5g} µm' + ('' if hyper[1] else ', not in the calibration')

    def refine_bounds(self, hyper, tried, ctxs):
        # one bin of the spectrum either side: the phase drifts by a cycle over the travel
        travel = max((float(np.max(np.ptp(self._phase_position(c, c.train_idx), axis=0)))
                      for c in ctxs if c.train_idx is not None and c.train_idx.size), default=0.0)
        if travel <= 0:
            return None
        period = hyper[0]
        step = period * period / travel
        return max(period - step, 0.5 * period), period + step

    def parameters(self, ctx, hyper):
        return [p for kind in ('sin', 'cos', 'sin 2nd', 'cos 2nd') for p in _bar_names(kind, 'nm', 1e9, 2e-6)]

    def _phase_position(self, ctx: FitContext, idx: NDArray[np.int64]) -> FloatArray:
        channels, origin = self._setup(ctx)
        return (ctx.counts[np.ix_(idx, channels)] - origin) * ctx.device.encoder_resolution_m

    def signature(self, ctx, hyper, idx):
        channels, origin = self._setup(ctx)
        return _per_bar(CyclicErrorTerm.features(ctx.counts[idx], channels, origin,
                                                 ctx.device.encoder_resolution_m, hyper[0],
                                                 self._knots(ctx, hyper)))

    def coverage(self, ctx, hyper, idx):
        span = np.ptp(self._phase_position(ctx, idx), axis=0)
        bars = span >= 2 * hyper[0]
        return np.tile(bars, 4), '' if bars.all() else 'bars that move less than two signal periods: ' + _bars(~bars)

    def make_term(self, ctx, hyper, theta):
        channels, origin = self._setup(ctx)
        t = np.asarray(theta).reshape(4, 6)
        return CyclicErrorTerm(hyper[0], ctx.device.encoder_resolution_m, channels, origin,
                               t[0], t[1], self._knots(ctx, hyper), t[2], t[3])

    def diagnostics(self, ctx, hyper):
        all_idx = np.arange(ctx.times_s.size)
        u = self._phase_position(ctx, all_idx)
        return {f'bar{i + 1} scale phase': np.mod(u[:, i] / hyper[0], 1.0)
                for i in np.flatnonzero(_moving_bars(ctx))}

    def interpret(self, ctx, hyper, theta, sigma):
        t = np.asarray(theta).reshape(4, 6) * 1e9
        amp, amp2 = np.hypot(t[0], t[1]), np.hypot(t[2], t[3])
        where = ('read in the calibration too' if hyper[1] else
                 'not read by the calibration (its points do not carry it)')
        return [f'amplitude {amp.min():.0f} … {amp.max():.0f} nm at a {hyper[0] / M_PER_UM:g} µm period '
                f'(second harmonic {amp2.min():.0f} … {amp2.max():.0f} nm), {where}']


class SamplingSkew(Effect):
    name = 'sampling_skew'
    term_type = 'sampling_skew'
    title = 'per-channel timing skew'
    physics = ('a channel latched later than the sample time reads the bar where it is a moment '
               'later: an error proportional to the bar\'s velocity')

    def parameters(self, ctx, hyper):
        return _bar_names('skew', 'µs', 1e6, MAX_SKEW_S)

    def signature(self, ctx, hyper, idx):
        return _diag(-ctx.velocities()[idx])

    def coverage(self, ctx, hyper, idx):
        ok = np.max(np.abs(ctx.velocities()[idx]), axis=0) >= 1e-3
        return ok, '' if ok.all() else 'bars that move slower than 1 mm/s: ' + _bars(~ok)

    def make_term(self, ctx, hyper, theta):
        # (identify._terms_for says whether its common delay was fitted: not when every
        # log's reference lags, the lag a nuisance of each whose direction is the common one)
        return SamplingSkewTerm(theta)

    def diagnostics(self, ctx, hyper):
        v = ctx.velocities()
        return {f'bar{i + 1} velocity': v[:, i] for i in np.flatnonzero(_moving_bars(ctx))}

    def interpret(self, ctx, hyper, theta, sigma):
        span = f'channel delays {np.min(theta) * 1e6:+.1f} … {np.max(theta) * 1e6:+.1f} µs'
        if ctx.obs.lag is not None:
            return [span + ' about their mean, which the reference\'s lag hides (not fitted)']
        delays = f'{span} (mean {np.mean(theta) * 1e6:+.1f} µs'
        if ctx.obs.clock == 'shared':
            return [delays + ', the channels\' own: the log\'s reference shares the MMD\'s clock)']
        # (a reference logged on a clock of its own, lagging the MMD, reads as a common delay)
        return [delays + ': a common delay shifts the whole pose in time, as a reference that '
                'lags the MMD by as much would; a log whose reference runs on a clock of its own '
                'says reference_clock: own)']


class GravitySag(Effect):
    name = 'gravity_sag'
    term_type = 'gravity_sag'
    title = 'gravity sag with bar inclination'
    physics = ('a bar bends under its weight across its axis and reads long by g (1 - n_z^2); '
               'calibrated lying flat, it reads short by g n_z^2 on the MMD (one g: the bars are '
               'of one design; n_z along the vertical the device description states)')
    needs_pose = True

    def _nz2(self, ctx: FitContext, idx: NDArray[np.int64]) -> FloatArray:
        # (of every sample once, each trial taking its own: on a 10-minute 1 kHz log the
        # bars' vertical cosines were read 9 times, 2.5 s under a profiler; 4 now, 2.0 s)
        geo = ctx.device.geometry
        return ctx.cached('nz2', lambda: GravitySagTerm.features(
            geo.upper, geo.lower, ctx.base.poses, ctx.device.up))[idx]

    def parameters(self, ctx, hyper):
        return [Parameter('sag of a horizontal bar', 'µm', 1 / M_PER_UM, 20e-6)]

    def signature(self, ctx, hyper, idx):
        return self._nz2(ctx, idx)[:, :, None]

    def coverage(self, ctx, hyper, idx):
        span = np.max(np.ptp(self._nz2(ctx, idx), axis=0))
        ok = span >= 0.01
        return np.array([ok]), '' if ok else f'the bars\' inclination hardly changes (n_z^2 by {span:.3f})'

    def make_term(self, ctx, hyper, theta):
        geo = ctx.device.geometry
        return GravitySagTerm(geo.upper, geo.lower, np.full(6, float(theta[0])), ctx.device.up)

    def diagnostics(self, ctx, hyper):
        nz2 = self._nz2(ctx, np.arange(ctx.times_s.size))
        return {f'bar{i + 1} inclination n_z^2': nz2[:, i] for i in range(6)}

    def interpret(self, ctx, hyper, theta, sigma):
        return [f'a horizontal bar sags enough to read {theta[0] / M_PER_UM:+.2f} '
                f'± {1.96 * sigma[0] / M_PER_UM:.2f} µm long']


#: Time constants of a settling tried [s] (refined between the neighbours of the best one), of
#: those no longer than half the shortest run (a longer one is a rate over the run)
SETTLING_S = (3.0, 10.0, 30.0, 100.0, 300.0)


class Drift(Effect):
    scope = 'run'
    free_mean = True
    continuous_setting = True
    name = 'drift'
    term_type = 'drift'
    title = 'slow drift'
    physics = ('a bar\'s reading drifts slowly since its calibration: an offset at the start of '
               'the run and a rate, or a settling from the run\'s start (a bar and its joints '
               'warming or relaxing after handling) whose time constant is estimated from the data')

    def hypers(self, ctxs):
        shortest = min(float(np.ptp(c.times_s)) for c in ctxs) if ctxs else 0.0
        return [None] + [tau for tau in SETTLING_S if tau <= 0.5 * shortest]

    def refine_bounds(self, hyper, tried, ctxs):
        taus = sorted(t for t in tried if t is not None)
        if hyper is None or len(taus) < 2:
            return None
        k = taus.index(hyper)
        return taus[max(k - 1, 0)], taus[min(k + 1, len(taus) - 1)]

    def hyper_label(self, hyper: Any) -> str:
        return 'a rate' if hyper is None else f'a settling, time constant {hyper:.3g} s'

    def parameters(self, ctx, hyper):
        if hyper is not None:
            return (_bar_names('offset', 'µm', 1 / M_PER_UM, 50e-6)
                    + _bar_names('settling', 'µm', 1 / M_PER_UM, 50e-6))
        return (_bar_names('offset', 'µm', 1 / M_PER_UM, 50e-6)
                + _bar_names('rate', 'µm/h', 3600 / M_PER_UM, 100e-6 / 3600))

    def signature(self, ctx, hyper, idx):
        c, r, _ = DriftTerm.features(ctx.times_s, None, hyper)
        return _per_bar([c[idx], r[idx]])

    def make_term(self, ctx, hyper, theta):
        return DriftTerm(theta[:6], theta[6:], hyper)

    def diagnostics(self, ctx, hyper):
        return {'time': ctx.times_s}

    def interpret(self, ctx, hyper, theta, sigma):
        if hyper is not None:
            amp = theta[6:] / M_PER_UM
            return [f'settling {np.min(amp):+.3f} … {np.max(amp):+.3f} µm from the run\'s '
                    f'start, time constant {hyper:.3g} s']
        rates = theta[6:] * 3600 / M_PER_UM
        return [f'rates {np.min(rates):+.2f} … {np.max(rates):+.2f} µm/h']


def cyclic_periods(ctxs: list[FitContext], setup: Any) -> list[tuple[float, float]]:
    """Periods of a cyclic error in the residual, estimated from its spectrum against each
    bar's scale position (no list of standard periods: a scale of any signal period is found).

    For each run and moving bar i, the training residual (weighted by the noise floor) is
    projected onto the bar: g_i = sum_k r_k dp_k/dd_i (the column a length error of bar i
    makes in the observation space). Counts are integers, so g_i averaged per count of the bar
    is a regular series along the scale; its periodogram |FFT|^2, divided by its running median over
    a factor 1.3 of frequency (the background of other effects leaks to long periods), peaks at
    the cyclic error's spatial frequency. Peaks above ``CYCLIC_PEAK_RATIO`` are refined by a
    parabola through the log power of three bins and merged over bars and runs (a scale type
    has one period).

    returns : [(period [m], summed peak ratio)], strongest first, at most ``CYCLIC_CANDIDATES``
    """
    peaks: list[tuple[float, float]] = []
    for ctx in ctxs:
        if ctx.residual is None or ctx.train_idx is None or ctx.train_idx.size < 100:
            continue
        idx = ctx.train_idx
        r = np.nan_to_num(ctx.residual[idx])
        channels, origin = setup(ctx)
        res_m = ctx.device.encoder_resolution_m
        cols = ctx.obs.length_map(ctx.device, ctx.base.poses[idx]) / ctx.floor[None, :, None]
        g = np.einsum('nk,nki->ni', r, cols)                                   # (n, 6)
        q = np.rint(ctx.counts[np.ix_(idx, channels)] - origin).astype(np.int64)
        for i in np.flatnonzero(_moving_bars(ctx)):
            lo, span = int(q[:, i].min()), int(np.ptp(q[:, i])) + 1
            longest = min(CYCLIC_MAX_PERIOD_M / res_m, span / 8.0)
            if longest < 8 or not np.any(g[:, i]):
                continue
            # the mean of each count's samples: a run that dwells (an ISO run's targets) piles
            # thousands of samples on a few counts, whose sums made a comb as wide as the
            # spectrum and hid the peak (a 13 µm error with a 1-D laser was not found)
            hits = np.bincount(q[:, i] - lo, minlength=span)
            series = np.bincount(q[:, i] - lo, weights=g[:, i], minlength=span) / np.maximum(hits, 1)
            nfft = 1 << int(math.ceil(math.log2(2 * span)))
            # (in single precision: a spectrum of up to 2^23 bins whose peaks stand 30 times over
            # the background needs no more, and scipy's transform takes 0.6 of the time then)
            spectrum = scipy.fft.rfft(series.astype(np.float32), nfft)
            # the band of periods from ``longest`` down to 4 counts (cycles per count k / nfft),
            # and the power of its bins only (a spectrum of 2^22 bins holds twice as many)
            k0 = max(int(math.ceil(nfft / longest)), 0)
            while k0 > 0 and (k0 - 1) / nfft >= 1.0 / longest:
                k0 -= 1
            while k0 / nfft < 1.0 / longest:
                k0 += 1
            k1 = nfft // 4
            if k1 - k0 + 1 < 16:
                continue
            part = spectrum[k0 - 1:k1 + 2]
            power = part.real ** 2 + part.imag ** 2                  # bins k0 - 1 ... k1 + 1
            band_power = power[1:-1]
            background = _running_median_log(np.arange(k0, k1 + 1) / nfft, band_power, 1.3)
            ratio = band_power / np.maximum(background, 1e-300)
            for j in _local_maxima(ratio, CYCLIC_CANDIDATES):
                if ratio[j] < CYCLIC_PEAK_RATIO or j == 0 or j == ratio.size - 1:
                    continue
                k = k0 + j
                a, b, c = np.log(power[j:j + 3] + 1e-300)
                den = a - 2 * b + c
                shift = 0.5 * (a - c) / den if den < 0 else 0.0
                peaks.append((res_m / ((k + shift) / nfft), float(ratio[j])))
    merged: list[list[float]] = []   # [period weighted sum, weight]
    for period, weight in sorted(peaks, key=lambda t: -t[1]):
        for m in merged:
            if abs(period - m[0] / m[1]) <= 0.005 * period:
                m[0] += period * weight
                m[1] += weight
                break
        else:
            merged.append([period * weight, weight])
    out = sorted(((m[0] / m[1], m[1]) for m in merged), key=lambda t: -t[1])
    return out[:CYCLIC_CANDIDATES]


def _running_median_log(freq: FloatArray, power: FloatArray, factor: float,
                        most: int = MEDIAN_SAMPLES) -> FloatArray:
    """Median of ``power`` over frequencies within a factor ``factor`` of each frequency,
    computed on 200 log-spaced bands and interpolated. A band of more than ``most`` bins is
    read at an even stride (``most`` of them: on a test session's spectra the median moved by
    0.5-1.3 % at the worst of each spectrum's bands; the bands at short periods hold up to a
    million bins each, and a bin lies in about 12 of them: read whole, they took half the
    time of the period search)."""
    edges = np.geomspace(freq[0], freq[-1], 201)
    centres = np.sqrt(edges[:-1] * edges[1:])
    med = np.empty(centres.size)
    for k, c in enumerate(centres):
        lo, hi = np.searchsorted(freq, [c / factor, c * factor])
        hi = max(hi, lo + 1)
        med[k] = np.median(power[lo:hi:max(1, -(-(hi - lo) // most))])
    return np.interp(np.log(freq), np.log(centres), med)


def _local_maxima(values: FloatArray, count: int) -> list[int]:
    """Indices of the ``count`` largest local maxima of ``values``, largest first."""
    if values.size < 3:
        return []
    inner = np.flatnonzero((values[1:-1] >= values[:-2]) & (values[1:-1] > values[2:])) + 1
    return [int(i) for i in inner[np.argsort(-values[inner])][:count]]


def _knots(ctx: FitContext) -> FloatArray:
    """Calibration distances of bars 1..6, (6, n) [m]."""
    names = ctx.device.channel_names
    rows = [np.sort(np.asarray(ctx.calibration.bars[names[ch]].distances_m))
            for ch in ctx.device.measuring_channels]
    if len({r.size for r in rows}) != 1:
        raise AnalysisError('bars have different numbers of calibration points')
    return np.array(rows)


def _bars(mask: BoolArray) -> str:
    return ', '.join(f'bar{i + 1}' for i in np.flatnonzero(mask))


#: The catalogue, in the order the report lists it.
CATALOGUE: dict[str, Effect] = {e.name: e for e in (
    Hysteresis(), ThermalGain(), ThermalInterpolation(), PlateExpansion(), Kinematic(),
    ScaleNonlinearity(), CalibrationPoints(), CyclicError(), SamplingSkew(), GravitySag(), Drift())}


def catalogue(names: list[str] | None = None) -> list[Effect]:
    """The effects to test: all, or those named (unknown names are refused)."""
    if not names:
        return list(CATALOGUE.values())
    unknown = [n for n in names if n not in CATALOGUE]
    if unknown:
        raise AnalysisError(f'unknown effects {unknown}; the catalogue has {list(CATALOGUE)}')
    return [CATALOGUE[n] for n in names]
