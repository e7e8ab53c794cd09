"""Model terms of the analysis catalogue (:mod:`mmd_ros.analysis.effects`): physical effects the
paper's compensation (CDF, Eq. 10; thermal, Eqs. 11–13) leaves out, as corrections of the bar
lengths that the pipeline applies from a model file.

Every term is linear in its parameters: its correction is ``sum_k theta_k * s_k`` with a
signature ``s_k`` of shape (N, 6) that depends on the samples only. The signatures are exposed
as ``features(...)`` so that the analysis fits exactly what the pipeline later applies.

Sign convention (all terms): the correction is ADDED to the compensated lengths, so it is minus
the reading error the effect causes. A term whose physics needs the pose (kinematic, plate,
sag) sets ``needs_pose`` and uses the pipeline's first-pass pose; the joint positions it needs
are stored in its parameters (``upper_mm``, ``lower_mm``), because a term does not see the
device description.

Streaming: terms with state (play operator, filters, previous sample, start time) carry it from
one call to the next, so a run processed sample by sample (the ROS node) gives the batch result.
The pipeline calls non-pose terms a second time on the same block when the model also has pose
terms; a stateful term here recognises such a replay (same first time stamp and length) and
starts again from the state it had before the first call, so the replay gives the same result.

    terms:
      - type: thermal_gain            # bar's thermal error vs the reference bar: gain and lag
        gain: [0.1, -0.05, 0, 0, 0, 0]
        lag_s: [120, 0, 0, 0, 0, 0]
      - type: cyclic_error            # encoder sub-division error at the signal period
        period_um: 20.0
        ...
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from mmd_ros.core import validate
from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.model import (
    HysteresisTerm, ModelTerm, TermContext, play_operator, register_term, six_values,
)
from mmd_ros.core.piecewise import segment
from mmd_ros.core.rotation import rotation_matrix
from mmd_ros.core.units import M_PER_MM, M_PER_NM, M_PER_UM, PPM

__all__ = [
    'CdfOffsetsTerm', 'CyclicErrorTerm', 'DriftTerm', 'FrictionTerm', 'GravitySagTerm', 'HysteresisTerm',
    'JointOffsetsTerm', 'PlateScaleTerm', 'SamplingSkewTerm', 'ScaleNonlinearityTerm', 'ThermalGainTerm',
    'ThermalInterpolationTerm', 'dahl_state', 'ema', 'friction_state', 'leg_geometry', 'lengths_within',
    'limited_to_seen', 'play_positions',
]

FloatArray = NDArray[np.float64]

#: Time constant of the low-pass used to take time derivatives of thermal quantities [s].
DERIVATIVE_FILTER_S = 300.0
#: A gap between samples longer than this is not motion (velocity of the skew term) [s].
MAX_GAP_S = 0.1


# -- helpers -----------------------------------------------------------------------------------
def lengths_within(range_m: FloatArray, knots_m: FloatArray, n: int) -> tuple[FloatArray, NDArray[np.bool_]]:
    """``n`` lengths evenly spread over each bar's ``range_m`` (6, 2) [m] cut to its CDF span
    (``knots_m``, (6, k)), shape (n, 6), and which bars have any (6,); a bar with none gets its
    first calibration distance throughout."""
    lo = np.maximum(range_m[:, 0], knots_m[:, 0])
    hi = np.minimum(range_m[:, 1], knots_m[:, -1])
    ok = np.isfinite(lo) & np.isfinite(hi) & (hi >= lo)
    grid = np.linspace(0.0, 1.0, n)[:, None]
    return np.where(ok, lo, knots_m[:, 0]) + grid * np.where(ok, hi - lo, 0.0), ok


def limited_to_seen(terms: list[ModelTerm], seen_m: FloatArray | None) -> list[ModelTerm]:
    """``terms`` with each length-dependent series held, beyond the bar lengths ``seen_m``
    (6, 2) [m] a fit saw, within the values it takes within them (``limited_to``); the others
    as they are. None leaves every term as it is."""
    if seen_m is None:
        return list(terms)
    return [t.limited_to(seen_m) if hasattr(t, 'limited_to') else t for t in terms]


def _number(params: dict[str, Any], key: str, source: str, default: float | None = None, *,
            positive: bool = False) -> float:
    value = params.get(key, default)
    return validate.number(value, source, key, low=0.0 if positive else None, low_open=positive)


def _matrix(params: dict[str, Any], key: str, source: str, shape: tuple[int, ...],
            default: Any = None) -> FloatArray:
    return validate.floats(params.get(key, default), source, key, shape)


def _knots(params: dict[str, Any], source: str) -> FloatArray:
    """Six increasing lists of calibration distances [mm], one per bar."""
    knots = validate.floats(params.get('knots_mm'), source, 'knots_mm', (6, -1),
                            what='six increasing lists of calibration distances (one per bar)')
    if knots.shape[1] < 2 or not np.all(np.diff(knots, axis=1) > 0):
        raise ConfigError(source, 'knots_mm', 'must be six increasing lists of calibration '
                          f'distances (one per bar), got {params.get("knots_mm")!r}')
    return knots


def _geometry(params: dict[str, Any], source: str) -> tuple[FloatArray, FloatArray]:
    return (_matrix(params, 'upper_mm', source, (6, 3)) * M_PER_MM,
            _matrix(params, 'lower_mm', source, (6, 3)) * M_PER_MM)


def _geometry_params(upper_m: FloatArray, lower_m: FloatArray) -> dict[str, Any]:
    return {'upper_mm': (np.asarray(upper_m) / M_PER_MM).tolist(),
            'lower_mm': (np.asarray(lower_m) / M_PER_MM).tolist()}


def leg_geometry(upper_m: FloatArray, lower_m: FloatArray, poses: FloatArray
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rotated upper joints, bar unit vectors and dd/ds of N poses.

    upper_m, lower_m : ndarray, shape (6, 3) — a_i in {U}, b_i in {L} [m]
    poses : ndarray, shape (N, 6) [m, rad]
    returns : R a_i (N, 6, 3) [m]; n_i (N, 6, 3), unit vector of bar i from b_i to its upper
        joint, in {L}; and dd_i/ds (N, 6) [m], the change of d_i when both plates' joint
        positions are scaled by s (Eq. 6 with s a_i, s b_i), n_i . (R a_i - b_i)
    """
    rot = rotation_matrix(poses[:, 3:])
    ra = np.matmul(rot, np.asarray(upper_m).T).transpose(0, 2, 1)   # (einsum: 2x slower here)
    legs = ra + poses[:, None, :3] - lower_m[None]
    units = legs / np.sqrt(np.einsum('nki,nki->nk', legs, legs))[:, :, None]
    ddds = np.einsum('nki,nki->nk', units, ra - lower_m[None])
    return ra, units, ddds


def vertical_cosines(upper_m: FloatArray, lower_m: FloatArray, poses: FloatArray,
                     vertical: FloatArray) -> FloatArray:
    """n_i . v of N poses, (N, 6): each bar's unit vector (from b_i to its upper joint, in
    {L}, as :func:`leg_geometry` gives it) along the unit vector ``vertical`` (3,). From
    products with the rotation's nine entries only, (N, 9) by (9, 6), never the (N, 6, 3) legs:
    600,000 poses' took 1.0-1.5 s through the legs (the gravity sag's features, read three
    times by an analysis of a 10-minute 1 kHz log), 0.23 s so, most of it the rotations.

    |R a_i + p - b_i|^2 = |a_i|^2 + |p - b_i|^2 + 2 (R a_i).(p - b_i), and (R a_i).w =
    sum_jk R_jk a_ik w_j for w = v, b_i; (R a_i).p = a_i.(R^T p)."""
    a = np.asarray(upper_m, dtype=np.float64)
    b = np.asarray(lower_m, dtype=np.float64)
    v = np.asarray(vertical, dtype=np.float64)
    rot = rotation_matrix(poses[:, 3:])
    flat = rot.reshape(-1, 9)
    p = np.asarray(poses[:, :3], dtype=np.float64)
    along = (flat @ np.einsum('j,ik->jki', v, a).reshape(9, 6)
             + (p @ v)[:, None] - (b @ v)[None, :])
    ra_b = flat @ np.einsum('ij,ik->jki', b, a).reshape(9, 6)
    ra_p = np.einsum('njk,nj->nk', rot, p) @ a.T
    p_b = (np.einsum('nj,nj->n', p, p)[:, None] - 2.0 * (p @ b.T)
           + np.einsum('ij,ij->i', b, b)[None, :])
    length2 = np.einsum('ij,ij->i', a, a)[None, :] + p_b + 2.0 * (ra_p - ra_b)
    return along / np.sqrt(length2)


def ema(x: FloatArray, times_s: FloatArray, tau_s: float,
        state: tuple[FloatArray, float] | None) -> tuple[FloatArray, tuple[FloatArray, float]]:
    """First-order low-pass of x with time constant tau_s, exact for any sample spacing.

    L_k = L_{k-1} + (1 - exp(-dt_k / tau)) (x_k - L_{k-1}); L starts at the first sample.

    x : ndarray, shape (N, m)
    times_s : ndarray, shape (N,) [s]
    state : (L, t) after the previous call, or None at the start of a run
    returns : L, shape (N, m), and the state after the last sample
    """
    n = x.shape[0]
    if n == 0:
        return x.copy(), state  # type: ignore[return-value]
    if state is None:
        prev, t_prev = x[0].astype(np.float64).copy(), float(times_s[0])
    else:
        prev, t_prev = state
    dt = np.diff(np.concatenate(([t_prev], times_s)))
    dt = np.maximum(dt, 0.0)
    a = -np.expm1(-dt / tau_s)
    out = np.empty_like(x, dtype=np.float64)
    if n > 1 and np.ptp(a[1:]) <= 1e-3 * max(float(np.mean(a[1:])), 1e-300):
        # regular sampling: one recursive filter for the whole block
        out[0] = prev + a[0] * (x[0] - prev)
        coef = float(np.mean(a[1:]))
        if n > 1:
            out[1:], _ = lfilter([coef], [1.0, coef - 1.0], x[1:], axis=0,
                                 zi=((1.0 - coef) * out[0])[None, :])
    else:
        cur = prev.copy()
        for k in range(n):
            cur = cur + a[k] * (x[k] - cur)
            out[k] = cur
    return out, (out[-1].copy(), float(times_s[-1]))


class _Replayable(ModelTerm):
    """Base of stateful terms: state in ``self._state``, replay of the same block detected."""

    def _initial_state(self) -> Any:
        return None

    def reset(self) -> None:
        self._state = self._initial_state()
        self._replay: tuple[tuple[float, int], Any] | None = None

    def _begin(self, ctx: TermContext) -> None:
        n = ctx.times_s.shape[0]
        if n == 0:
            return
        key = (float(ctx.times_s[0]), int(n))
        if self._replay is not None and self._replay[0] == key:
            self._state = copy.deepcopy(self._replay[1])
        else:
            self._replay = (key, copy.deepcopy(self._state))


# -- friction ----------------------------------------------------------------------------------
def play_positions(lengths_m: FloatArray, deadband_m: float, start: FloatArray | None, *,
                   compiled: bool | None = None) -> FloatArray:
    """Output of a play (backlash) of half-width ``deadband_m`` on each column, (N, M): it
    follows the input only when the input is more than ``deadband_m`` away, so the rounding
    flicker of a bar at rest does not move it. ``start``: the play's position before the
    first sample (None: the first sample). ``compiled``: the compiled loop (default: when it
    is in use; the same numbers); False: Python."""
    x = np.ascontiguousarray(lengths_m, dtype=np.float64)
    out = np.empty_like(x)
    if x.shape[0] == 0:
        return out
    play = np.array(x[0] if start is None else start, dtype=np.float64)
    play_operator(x, deadband_m, play, positions=out, compiled=compiled)
    return out


def dahl_state(positions: FloatArray, travel_m: float,
               state: tuple[FloatArray, FloatArray, FloatArray, FloatArray], *,
               compiled: bool | None = None
               ) -> tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray, FloatArray]]:
    """Dahl friction state along the play's output (see :func:`friction_state`).

    positions : ndarray, shape (N, M) — output of :func:`play_positions` [m]
    state : (position before the first sample, direction, anchor position, anchor state)
    compiled : the compiled loop (default: when it is in use; the same numbers but for the
        last bit of an exp); False: numpy
    """
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    n, m = pos.shape
    last, direction, anchor_x, anchor_s = (np.array(v, dtype=np.float64) for v in state)
    out = np.empty_like(pos)
    if n == 0:
        return out, (last, direction, anchor_x, anchor_s)
    if use_compiled(compiled):
        fast.dahl_state(pos, float(travel_m), last, direction, anchor_x, anchor_s, out)
        return out, (last, direction, anchor_x, anchor_s)
    for j in range(m):
        pj = pos[:, j]
        prev = np.concatenate(([last[j]], pj[:-1]))
        step = np.sign(pj - prev)
        fill = np.maximum.accumulate(np.where(step != 0, np.arange(n), -1))
        dirs = np.where(fill >= 0, step[np.maximum(fill, 0)], direction[j])
        before = np.concatenate(([direction[j]], dirs[:-1]))
        turns = np.flatnonzero(dirs != before)
        # the state where each new direction begins: a sequential recurrence over the turns,
        # on plain floats (numpy scalars cost several times more per step)
        xs = [float(anchor_x[j])] + prev[turns].tolist()
        ss = [float(anchor_s[j])]
        for t, sigma in enumerate(before[turns].tolist()):
            a = ss[t]
            ss.append(a if sigma == 0 else
                      sigma - (sigma - a) * math.exp(-sigma * (xs[t + 1] - xs[t]) / travel_m))
        ax = np.array(xs)
        as_ = np.array(ss)
        seg = np.cumsum(dirs != before)
        s = dirs - (dirs - as_[seg]) * np.exp(-dirs * (pj - ax[seg]) / travel_m)
        out[:, j] = np.clip(np.where(dirs == 0, as_[seg], s), -1.0, 1.0)
        last[j], direction[j], anchor_x[j], anchor_s[j] = pj[-1], dirs[-1], ax[-1], as_[-1]
    return out, (last, direction, anchor_x, anchor_s)


def friction_state(lengths_m: FloatArray, travel_m: float, deadband_m: float,
                   state: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None
                   ) -> tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray, FloatArray]]:
    """Friction state s in [-1, 1] of each bar along its motion (Dahl's model of friction).

    Friction does not flip when the motion reverses: it turns over gradually with the travel
    since the reversal. Within a stretch of motion in direction sigma that began at position
    x_a with state s_a, ds/dx = sigma (1 - sigma s) / travel, so

        s(x) = sigma - (sigma - s_a) exp(-sigma (x - x_a) / travel),

    which is a relay for travel -> 0 and a slow turn-over for a long travel (the transition's
    shape is one parameter, fitted by the analysis). The motion is the bar's length seen through
    a play of half-width ``deadband_m`` (one encoder count): the rounding flicker of a bar at
    rest is not motion and does not wear the state down.

    lengths_m : ndarray, shape (N, M) [m]
    state : (play position, direction, anchor position, anchor state), each (M,), or None at
        the start of a run (state 0, no direction yet)
    returns : s, shape (N, M), and the state after the last sample
    """
    x = np.asarray(lengths_m, dtype=np.float64)
    if state is None:
        first = x[0] if x.shape[0] else np.zeros(x.shape[1])
        state = (first.copy(), np.zeros(x.shape[1]), first.copy(), np.zeros(x.shape[1]))
    positions = play_positions(x, deadband_m, state[0])
    return dahl_state(positions, travel_m, state)


@register_term
class FrictionTerm(_Replayable):
    """Friction hysteresis with a gradual turn-over (section 5.3; Dahl's friction model).

    Friction in the ball joints and guides makes bar i read ``amplitude_i * s_i`` too long, with
    s_i the friction state of :func:`friction_state` (+1 after a long lengthening, -1 after a
    long shortening, turning over within about ``travel`` after a reversal). Correction:
    ``-amplitude_i * s_i``, driven by the compensated lengths. Unlike the relay of
    :class:`~mmd_ros.core.model.HysteresisTerm`, the transition has a shape, and its travel is
    estimated from the data.
    """

    type_name = 'friction'

    def __init__(self, amplitude_m: FloatArray, travel_m: float, deadband_m: float) -> None:
        self.amplitude_m = np.asarray(amplitude_m, dtype=np.float64)
        self.travel_m = float(travel_m)
        self.deadband_m = float(deadband_m)
        self.reset()

    def correction(self, ctx: TermContext) -> FloatArray:
        self._begin(ctx)
        if ctx.lengths_m.shape[0] == 0:
            return np.zeros_like(ctx.lengths_m)
        s, self._state = friction_state(ctx.lengths_m, self.travel_m, self.deadband_m, self._state)
        return -self.amplitude_m * s

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> FrictionTerm:
        return cls(six_values(params, 'amplitude_um', source) * M_PER_UM,
                   _number(params, 'travel_um', source, positive=True) * M_PER_UM,
                   _number(params, 'deadband_um', source, 0.05) * M_PER_UM)

    def params(self) -> dict[str, Any]:
        return {'amplitude_um': (self.amplitude_m / M_PER_UM).tolist(),
                'travel_um': self.travel_m / M_PER_UM, 'deadband_um': self.deadband_m / M_PER_UM}


# -- thermal -----------------------------------------------------------------------------------
@register_term
class ThermalGainTerm(_Replayable):
    """Per-bar thermal behaviour against the reference bar (section 3.3, Eq. 13 assumes all
    bars behave alike; section 4.1 saw "minor differences" between them).

    Bar i's thermal error is (1 + g_i) times the error the model subtracts (eps_i, from Eqs.
    11–13) and lags it by lag_i seconds (its time constant differs):
    eps_i,true ~ (1 + g_i) eps_i - lag_i d(eps_i)/dt. Correction: -g_i eps_i + lag_i deps_i/dt,
    the derivative from a first-order low-pass of ``filter_s``: (eps - L) / filter_s.
    """

    type_name = 'thermal_gain'

    def __init__(self, gain: FloatArray, lag_s: FloatArray, filter_s: float = DERIVATIVE_FILTER_S) -> None:
        self.gain = np.asarray(gain, dtype=np.float64)
        self.lag_s = np.asarray(lag_s, dtype=np.float64)
        self.filter_s = float(filter_s)
        self.reset()

    @staticmethod
    def features(bar_error_m: FloatArray, times_s: FloatArray, filter_s: float,
                 state: Any) -> tuple[FloatArray, FloatArray, Any]:
        """Signatures per unit gain and per second of lag, each (N, 6) [m, m/s], and the state.

        bar_error_m : ndarray, shape (N, 6) — thermal error the model subtracts per bar [m]
        """
        low, state = ema(bar_error_m, times_s, filter_s, state)
        return -bar_error_m, (bar_error_m - low) / filter_s, state

    def correction(self, ctx: TermContext) -> FloatArray:
        self._begin(ctx)
        g, r, self._state = self.features(ctx.cdf_lengths_m - ctx.lengths_m, ctx.times_s,
                                          self.filter_s, self._state)
        return self.gain * g + self.lag_s * r

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> ThermalGainTerm:
        return cls(six_values(params, 'gain', source),
                   six_values({'lag_s': params.get('lag_s', 0.0)}, 'lag_s', source),
                   _number(params, 'filter_s', source, DERIVATIVE_FILTER_S, positive=True))

    def params(self) -> dict[str, Any]:
        return {'gain': self.gain.tolist(), 'lag_s': self.lag_s.tolist(), 'filter_s': self.filter_s}


@register_term
class ThermalInterpolationTerm(ModelTerm):
    """The Eq. (12) interpolation that Eq. (13) drops (section 3.3).

    A bar of length d_i at the temperature change of the reference bar (on d_ref) has a thermal
    error that differs from the reference's by -alpha_scale (d_i - d_ref) dT, i.e. in proportion
    to (d_i - d_ref) eps (eps, Eq. 11, is itself proportional to dT). Correction:
    k (d_i - d_ref) eps with one coefficient k [1/m] for all bars (k = -alpha_scale / (deps/dT)).
    """

    type_name = 'thermal_interpolation'

    def __init__(self, coefficient_per_m: float, reference_distance_m: float) -> None:
        self.coefficient_per_m = float(coefficient_per_m)
        self.reference_distance_m = float(reference_distance_m)
        self.reset()

    @staticmethod
    def features(lengths_m: FloatArray, reference_error_m: FloatArray,
                 reference_distance_m: float) -> FloatArray:
        """Signature per unit coefficient, (N, 6) [m^2]: (d_i - d_ref) eps of the first
        reference bar (zero when the model has no reference bar)."""
        if reference_error_m.shape[1] == 0:
            return np.zeros_like(lengths_m)
        return (lengths_m - reference_distance_m) * reference_error_m[:, :1]

    def correction(self, ctx: TermContext) -> FloatArray:
        return self.coefficient_per_m * self.features(ctx.lengths_m, ctx.reference_error_m,
                                                      self.reference_distance_m)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> ThermalInterpolationTerm:
        return cls(_number(params, 'coefficient_per_m', source),
                   _number(params, 'reference_distance_mm', source, positive=True) * M_PER_MM)

    def params(self) -> dict[str, Any]:
        return {'coefficient_per_m': self.coefficient_per_m,
                'reference_distance_mm': self.reference_distance_m / M_PER_MM}


@register_term
class PlateScaleTerm(_Replayable):
    """Error of the plates' expansion estimate (end of section 3.3).

    The model scales both plates' joints by 1 + alpha_plate (dT + offset) with dT from the
    reference bar. The true scale may differ by ds = s0 + k dT - alpha_plate lag d(dT)/dt: a
    scale error at the thermal zero (s0), a CTE error (k), and plates lagging the bars by
    ``lag_s``. Since d_i(s) = s |R a_i + t/s - b_i|, a scale error ds changes each length by
    ds * n_i . (R a_i - b_i); the correction is minus that (pose-dependent: first-pass pose).
    """

    type_name = 'plate_scale'
    needs_pose = True

    def __init__(self, upper_m: FloatArray, lower_m: FloatArray, scale_offset: float,
                 cte_per_c: float, lag_s: float, plate_cte_per_c: float,
                 filter_s: float = DERIVATIVE_FILTER_S) -> None:
        self.upper_m = np.asarray(upper_m, dtype=np.float64)
        self.lower_m = np.asarray(lower_m, dtype=np.float64)
        self.scale_offset = float(scale_offset)
        self.cte_per_c = float(cte_per_c)
        self.lag_s = float(lag_s)
        self.plate_cte_per_c = float(plate_cte_per_c)
        self.filter_s = float(filter_s)
        self.reset()

    @staticmethod
    def features(upper_m: FloatArray, lower_m: FloatArray, poses: FloatArray,
                 temp_change_c: FloatArray, times_s: FloatArray, filter_s: float,
                 state: Any) -> tuple[FloatArray, FloatArray, FloatArray, Any]:
        """Signatures per unit scale offset [m], per unit CTE error [m/°C] and per unit of
        alpha_plate * lag [m / (°C/s)], each (N, 6), and the filter state."""
        _, _, ddds = leg_geometry(upper_m, lower_m, poses)
        low, state = ema(temp_change_c[:, None], times_s, filter_s, state)
        rate = (temp_change_c[:, None] - low) / filter_s
        return -ddds, -ddds * temp_change_c[:, None], ddds * rate, state

    def correction(self, ctx: TermContext) -> FloatArray:
        self._begin(ctx)
        if ctx.poses is None:
            return np.zeros_like(ctx.lengths_m)
        s0, k, r, self._state = self.features(self.upper_m, self.lower_m, ctx.poses,
                                              ctx.temp_change_c, ctx.times_s, self.filter_s,
                                              self._state)
        return self.scale_offset * s0 + self.cte_per_c * k + self.plate_cte_per_c * self.lag_s * r

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> PlateScaleTerm:
        upper, lower = _geometry(params, source)
        return cls(upper, lower, _number(params, 'scale_offset_ppm', source, 0.0) * PPM,
                   _number(params, 'cte_ppm_per_c', source, 0.0) * PPM,
                   _number(params, 'lag_s', source, 0.0),
                   _number(params, 'plate_cte_ppm_per_c', source, 0.5) * PPM,
                   _number(params, 'filter_s', source, DERIVATIVE_FILTER_S, positive=True))

    def params(self) -> dict[str, Any]:
        return {'scale_offset_ppm': self.scale_offset / PPM, 'cte_ppm_per_c': self.cte_per_c / PPM,
                'lag_s': self.lag_s, 'plate_cte_ppm_per_c': self.plate_cte_per_c / PPM,
                'filter_s': self.filter_s, **_geometry_params(self.upper_m, self.lower_m)}


# -- kinematics --------------------------------------------------------------------------------
@register_term
class JointOffsetsTerm(ModelTerm):
    """Errors of the 42 kinematic parameters (section 2.2): the 36 joint coordinates and the six
    bar length offsets, applied as a length correction at the first-pass pose.

    With true joints a_i + da_i, b_i + db_i and bar i reading dl_i long, the lengths the nominal
    geometry needs at the true pose are the measured ones plus
    c_i = -n_i . (R da_i - db_i) - dl_i (to first order; the second-order error is |da|^2 / d,
    below a picometre for micrometre errors).
    """

    type_name = 'joint_offsets'
    needs_pose = True

    def __init__(self, upper_m: FloatArray, lower_m: FloatArray, upper_offset_m: FloatArray,
                 lower_offset_m: FloatArray, length_offset_m: FloatArray) -> None:
        self.upper_m = np.asarray(upper_m, dtype=np.float64)
        self.lower_m = np.asarray(lower_m, dtype=np.float64)
        self.upper_offset_m = np.asarray(upper_offset_m, dtype=np.float64).reshape(6, 3)
        self.lower_offset_m = np.asarray(lower_offset_m, dtype=np.float64).reshape(6, 3)
        self.length_offset_m = np.asarray(length_offset_m, dtype=np.float64).reshape(6)
        self.reset()

    @staticmethod
    def features(upper_m: FloatArray, lower_m: FloatArray, poses: FloatArray
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Signatures: d c_i / d da_i (N, 6, 3), d c_i / d db_i (N, 6, 3), d c_i / d dl_i (N, 6).

        dc_i/dda_i = -R^T n_i (in {U}); dc_i/ddb_i = n_i; dc_i/ddl_i = -1.
        """
        rot = rotation_matrix(poses[:, 3:])
        _, units, _ = leg_geometry(upper_m, lower_m, poses)
        upper = -np.einsum('nji,nkj->nki', rot, units)
        return upper, units, -np.ones(units.shape[:2])

    def correction(self, ctx: TermContext) -> FloatArray:
        if ctx.poses is None:
            return np.zeros_like(ctx.lengths_m)
        up, low, length = self.features(self.upper_m, self.lower_m, ctx.poses)
        return (np.einsum('nki,ki->nk', up, self.upper_offset_m)
                + np.einsum('nki,ki->nk', low, self.lower_offset_m) + length * self.length_offset_m)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> JointOffsetsTerm:
        upper, lower = _geometry(params, source)
        zeros = np.zeros((6, 3)).tolist()
        return cls(upper, lower,
                   _matrix(params, 'upper_um', source, (6, 3), zeros) * M_PER_UM,
                   _matrix(params, 'lower_um', source, (6, 3), zeros) * M_PER_UM,
                   _matrix(params, 'length_um', source, (6,), [0.0] * 6) * M_PER_UM)

    def params(self) -> dict[str, Any]:
        return {'upper_um': (self.upper_offset_m / M_PER_UM).tolist(),
                'lower_um': (self.lower_offset_m / M_PER_UM).tolist(),
                'length_um': (self.length_offset_m / M_PER_UM).tolist(),
                **_geometry_params(self.upper_m, self.lower_m)}


@register_term
class GravitySagTerm(ModelTerm):
    """Gravity sag with the bar's inclination.

    A bar bends under its weight in proportion to the weight's component across its axis, so it
    reads long by g_i (1 - n_z^2) (n_z: component of its axis along the vertical). The bars are
    calibrated lying horizontally on the reference plate (n_z = 0), which puts g_i into the CDF,
    so a bar on the MMD reads short by g_i n_z^2. Correction: +g_i n_z^2 (first-pass pose; the
    vertical is ``vertical`` in {L}, default +z: the lower plate level); none where there is no
    pose (bars on the reference plate lie flat, as calibrated).
    """

    type_name = 'gravity_sag'
    needs_pose = True

    def __init__(self, upper_m: FloatArray, lower_m: FloatArray, sag_m: FloatArray,
                 vertical: FloatArray | None = None) -> None:
        self.upper_m = np.asarray(upper_m, dtype=np.float64)
        self.lower_m = np.asarray(lower_m, dtype=np.float64)
        self.sag_m = np.asarray(sag_m, dtype=np.float64)
        v = np.array([0.0, 0.0, 1.0]) if vertical is None else np.asarray(vertical, dtype=np.float64)
        self.vertical = v / np.linalg.norm(v)
        self.reset()

    @staticmethod
    def features(upper_m: FloatArray, lower_m: FloatArray, poses: FloatArray,
                 vertical: FloatArray) -> FloatArray:
        """Signature per unit sag, (N, 6): n_z,i^2 (:func:`vertical_cosines`)."""
        return vertical_cosines(upper_m, lower_m, poses, vertical) ** 2

    def correction(self, ctx: TermContext) -> FloatArray:
        if ctx.poses is None:
            return np.zeros_like(ctx.lengths_m)
        nz2 = self.features(self.upper_m, self.lower_m, ctx.poses, self.vertical)
        return self.sag_m * np.nan_to_num(nz2)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> GravitySagTerm:
        upper, lower = _geometry(params, source)
        vertical = _matrix(params, 'vertical', source, (3,), [0.0, 0.0, 1.0])
        if np.linalg.norm(vertical) == 0:
            raise ConfigError(source, 'vertical', 'must not be the zero vector')
        return cls(upper, lower, six_values(params, 'sag_um', source) * M_PER_UM, vertical)

    def params(self) -> dict[str, Any]:
        return {'sag_um': (self.sag_m / M_PER_UM).tolist(), 'vertical': self.vertical.tolist(),
                **_geometry_params(self.upper_m, self.lower_m)}


# -- scale -------------------------------------------------------------------------------------
@register_term
class ScaleNonlinearityTerm(ModelTerm):
    """Smooth scale error between the CDF points (section 3.2: "the calibration point is free of
    geometric error and the overall accuracy depends on the number of the calibration points").

    A bar's scale error e_i(x) over its calibrated span is written as a short Fourier series,
    e_i(x) = sum_k a_ik sin(2 pi k xi) + b_ik cos(2 pi k xi), xi = (x - x_1)/(x_n - x_1) with
    x = f_i(q) the CDF length. The CDF (Eq. 10) removes e_i at its points and, between them,
    its linear interpolant, so what is left is e_i minus its piecewise-linear interpolant through
    the knots; that vanishes at every calibration point. Correction: minus the remainder.

    The series is fitted where the data saw each bar; beyond those lengths it is an
    extrapolation that no data checked, and a series of the CDF span's harmonics can swing
    there far beyond anything it did where it was seen (a fit over 289-351 mm of a bar made
    3 µm of correction at 275 mm, where the error was 0.2 µm). With ``seen_m``, the lengths a
    fit saw, the correction beyond them is held within the range of values it takes within
    them.
    """

    type_name = 'scale_nonlinearity'

    def __init__(self, knots_m: FloatArray, sin_m: FloatArray, cos_m: FloatArray,
                 seen_m: FloatArray | None = None) -> None:
        self.knots_m = np.asarray(knots_m, dtype=np.float64)
        self.sin_m = np.asarray(sin_m, dtype=np.float64)
        self.cos_m = np.asarray(cos_m, dtype=np.float64)
        self.harmonics = self.sin_m.shape[1]
        self.seen_m = None if seen_m is None else np.asarray(seen_m, dtype=np.float64).reshape(6, 2)
        self._limits = None if self.seen_m is None else self._range_within(self.seen_m)
        self.reset()

    def limited_to(self, seen_m: FloatArray) -> ScaleNonlinearityTerm:
        """The same series, its correction beyond the lengths ``seen_m`` (6, 2) [m] held within
        the values it takes within them."""
        seen = np.array(seen_m, dtype=np.float64).reshape(6, 2)
        never = ~np.all(np.isfinite(seen), axis=1)     # a bar no sample saw: no correction
        seen[never] = self.knots_m[never, :1]
        return ScaleNonlinearityTerm(self.knots_m, self.sin_m, self.cos_m, seen)

    def _raw(self, x_m: FloatArray) -> FloatArray:
        b = self.basis(x_m, self.knots_m, self.harmonics)
        coef = np.concatenate([self.sin_m, self.cos_m], axis=1)  # (6, 2K)
        return np.einsum('nkj,kj->nk', b, coef)

    def _range_within(self, seen_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Lowest and highest correction of each bar over its lengths in ``seen_m`` (within
        the CDF span), (6,) each [m]; 0 and 0 for a bar seen nowhere there."""
        lengths, ok = lengths_within(seen_m, self.knots_m, 401)
        c = self._raw(lengths)
        return np.where(ok, c.min(axis=0), 0.0), np.where(ok, c.max(axis=0), 0.0)

    @staticmethod
    def basis(x_m: FloatArray, knots_m: FloatArray, harmonics: int) -> FloatArray:
        """Signature per unit coefficient, (N, 6, 2K): columns sin k = 1..K then cos k = 1..K,
        each minus its piecewise-linear interpolant through the bar's knots, negated.

        x_m : ndarray, shape (N, 6) — CDF lengths f_i(q_i) [m]
        knots_m : ndarray, shape (6, n) — each bar's calibration distances, increasing [m]
        """
        n, out = x_m.shape[0], np.empty(x_m.shape + (2 * harmonics,))
        for i in range(x_m.shape[1]):
            kn = knots_m[i]
            span = kn[-1] - kn[0]
            xi = (x_m[:, i] - kn[0]) / span
            xk = (kn - kn[0]) / span
            seg, w = segment(x_m[:, i], kn)
            for k in range(1, harmonics + 1):
                for j, fn in enumerate((np.sin, np.cos)):
                    at_knots = fn(2 * np.pi * k * xk)
                    interp = at_knots[seg] + w * (at_knots[seg + 1] - at_knots[seg])
                    out[:, i, (k - 1) + j * harmonics] = -(fn(2 * np.pi * k * xi) - interp)
        return out if n else np.zeros((0, 6, 2 * harmonics))

    def correction(self, ctx: TermContext) -> FloatArray:
        x = ctx.cdf_lengths_m
        c = self._raw(x)
        if self._limits is None:
            return c
        with np.errstate(invalid='ignore'):
            beyond = (x < self.seen_m[:, 0]) | (x > self.seen_m[:, 1])
        return np.where(beyond, np.clip(c, *self._limits), c)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> ScaleNonlinearityTerm:
        knots = _knots(params, source)
        what = 'six equal-length lists of harmonic amplitudes'
        sin = validate.floats(params.get('sin_um'), source, 'sin_um', (6, -1), what=what)
        cos = validate.floats(params.get('cos_um'), source, 'cos_um', sin.shape, what=what)
        seen = params.get('seen_mm')
        if seen is not None:
            seen = validate.floats(seen, source, 'seen_mm', (6, 2),
                                   what='six [lowest, highest] lengths the fit saw') * M_PER_MM
        return cls(knots * M_PER_MM, sin * M_PER_UM, cos * M_PER_UM, seen)

    def params(self) -> dict[str, Any]:
        out = {'knots_mm': (self.knots_m / M_PER_MM).tolist(),
               'sin_um': (self.sin_m / M_PER_UM).tolist(), 'cos_um': (self.cos_m / M_PER_UM).tolist()}
        if self.seen_m is not None:
            out['seen_mm'] = (self.seen_m / M_PER_MM).tolist()
        return out


@register_term
class CdfOffsetsTerm(ModelTerm):
    """Errors of the calibration points themselves (section 3.2): a bar seated on a reference
    pair with an offset (seating repeatability, or the friction state its guide was left in when
    it was put down) makes its CDF point (q_i^j, d_r^j) wrong by c_ij, and Eq. (10) carries that
    error linearly between the points. Correction: minus the piecewise-linear interpolant of the
    c_ij through the bar's knots at its CDF length (extrapolated with the end segments, as the
    CDF is).
    """

    type_name = 'cdf_offsets'

    def __init__(self, knots_m: FloatArray, offsets_m: FloatArray) -> None:
        self.knots_m = np.asarray(knots_m, dtype=np.float64)
        self.offsets_m = np.asarray(offsets_m, dtype=np.float64)
        self.reset()

    @staticmethod
    def basis(x_m: FloatArray, knots_m: FloatArray) -> FloatArray:
        """Signature per unit knot error, (N, 6, n): minus the hat function of knot j at bar i's
        CDF length (its weight in the piecewise-linear interpolation).

        x_m : ndarray, shape (N, 6) — CDF lengths [m]
        knots_m : ndarray, shape (6, n) — each bar's calibration distances, increasing [m]
        """
        n_k = knots_m.shape[1]
        out = np.zeros(x_m.shape + (n_k,))
        rows = np.arange(x_m.shape[0])
        for i in range(x_m.shape[1]):
            kn = knots_m[i]
            seg, w = segment(x_m[:, i], kn)
            out[rows, i, seg] = -(1.0 - w)
            out[rows, i, seg + 1] = -w
        return out

    def correction(self, ctx: TermContext) -> FloatArray:
        return np.einsum('nkj,kj->nk', self.basis(ctx.cdf_lengths_m, self.knots_m), self.offsets_m)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> CdfOffsetsTerm:
        knots = _knots(params, source)
        return cls(knots * M_PER_MM, _matrix(params, 'offsets_um', source, knots.shape) * M_PER_UM)

    def params(self) -> dict[str, Any]:
        return {'knots_mm': (self.knots_m / M_PER_MM).tolist(),
                'offsets_um': (self.offsets_m / M_PER_UM).tolist()}


@register_term
class CyclicErrorTerm(ModelTerm):
    """Encoder sub-division (cyclic) error: the interpolation of the incremental scale's sine
    signals errs periodically with the signal period. Bar i reads a_i sin(phi) + b_i cos(phi)
    + a2_i sin(2 phi) + b2_i cos(2 phi) too long, phi = 2 pi (q_i - q0_i) resolution / period,
    counted from ``count_origin`` (the bar's calibration count on the first reference pair, so
    the phase refers to the scale, not to the power-on count). The fundamental is what offsets
    of the two signals make, the second harmonic what their unequal amplitudes and a phase
    other than 90 degrees make (Heydemann, Appl. Opt. 20, 1981). With ``calibration_counts`` (each bar's counts at its calibration
    points) the error as the calibrated bar reads it: the calibration read the same scale, so
    the CDF's line through its points (Eq. 10) carries the error's values at those counts, and
    the bar reads the error minus that line. Correction: minus that. Re-fit after a new
    calibration.
    """

    type_name = 'cyclic_error'

    def __init__(self, period_m: float, resolution_m: float, channels: list[int],
                 count_origin: FloatArray, sin_m: FloatArray, cos_m: FloatArray,
                 calibration_counts: list[FloatArray] | None = None,
                 sin2_m: FloatArray | None = None, cos2_m: FloatArray | None = None) -> None:
        self.period_m = float(period_m)
        self.resolution_m = float(resolution_m)
        self.channels = [int(c) for c in channels]
        self.count_origin = np.asarray(count_origin, dtype=np.float64)
        self.sin_m = np.asarray(sin_m, dtype=np.float64)
        self.cos_m = np.asarray(cos_m, dtype=np.float64)
        self.sin2_m = np.zeros(6) if sin2_m is None else np.asarray(sin2_m, dtype=np.float64)
        self.cos2_m = np.zeros(6) if cos2_m is None else np.asarray(cos2_m, dtype=np.float64)
        self.calibration_counts = (None if calibration_counts is None else
                                   [np.sort(np.asarray(q, dtype=np.float64)) for q in calibration_counts])
        self.reset()

    @staticmethod
    def features(counts: FloatArray, channels: list[int], count_origin: FloatArray,
                 resolution_m: float, period_m: float,
                 calibration_counts: list[FloatArray] | None = None) -> list[FloatArray]:
        """Signatures per unit sine and cosine amplitude of the fundamental and of the second
        harmonic, [s, c, s2, c2], each (N, 6). With the counts of each bar's calibration
        points, the error as the calibrated bar reads it: the calibration read the same scale,
        so each point's distance took the error at that count, and the CDF's line through the
        points carries it between them (Eq. 10)."""
        scale = resolution_m / period_m
        phase = 2 * np.pi * ((counts[:, channels] - count_origin) * scale)
        out = [-np.sin(phase), -np.cos(phase), -np.sin(2 * phase), -np.cos(2 * phase)]
        if calibration_counts is not None:
            for i, knots in enumerate(calibration_counts):
                at = 2 * np.pi * ((knots - count_origin[i]) * scale)
                values = (np.sin(at), np.cos(at), np.sin(2 * at), np.cos(2 * at))
                for sig, v in zip(out, values):
                    sig[:, i] += _through_points(counts[:, channels[i]], knots, v)
        return out

    def correction(self, ctx: TermContext) -> FloatArray:
        s, c, s2, c2 = self.features(ctx.counts, self.channels, self.count_origin,
                                     self.resolution_m, self.period_m, self.calibration_counts)
        return self.sin_m * s + self.cos_m * c + self.sin2_m * s2 + self.cos2_m * c2

    def mean_square_m2(self) -> FloatArray:
        """Each bar's mean square of the error the term compensates, (6,) [m^2]."""
        return 0.5 * (self.sin_m ** 2 + self.cos_m ** 2 + self.sin2_m ** 2 + self.cos2_m ** 2)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> CyclicErrorTerm:
        channels = params.get('channels')
        if not (isinstance(channels, list) and len(channels) == 6
                and all(validate.number_problem(c, low=0, high=63, integer=True) is None
                        for c in channels)):
            raise ConfigError(source, 'channels', f'must list the terminal channels of bars 1..6, got {channels!r}')
        points = params.get('calibration_counts')
        knots = None
        if points is not None:
            knots = list(validate.floats(points, source, 'calibration_counts', (6, -1),
                                         what='six lists of the calibration points\' counts (one per bar)'))
            if knots[0].size < 2 or not all(np.all(np.diff(np.sort(k)) > 0) for k in knots):
                raise ConfigError(source, 'calibration_counts', 'must list at least two distinct '
                                  f'counts per bar, got {points!r}')
        second = [six_values({key: params.get(key, 0.0)}, key, source) * M_PER_NM
                  for key in ('sin2_nm', 'cos2_nm')]
        return cls(_number(params, 'period_um', source, positive=True) * M_PER_UM,
                   _number(params, 'resolution_nm', source, positive=True) * M_PER_NM, channels,
                   six_values(params, 'count_origin', source),
                   six_values(params, 'sin_nm', source) * M_PER_NM,
                   six_values(params, 'cos_nm', source) * M_PER_NM, knots, *second)

    def params(self) -> dict[str, Any]:
        out = {'period_um': self.period_m / M_PER_UM, 'resolution_nm': self.resolution_m / M_PER_NM,
               'channels': self.channels, 'count_origin': self.count_origin.tolist(),
               'sin_nm': (self.sin_m / M_PER_NM).tolist(), 'cos_nm': (self.cos_m / M_PER_NM).tolist(),
               'sin2_nm': (self.sin2_m / M_PER_NM).tolist(), 'cos2_nm': (self.cos2_m / M_PER_NM).tolist()}
        if self.calibration_counts is not None:
            out['calibration_counts'] = [k.tolist() for k in self.calibration_counts]
        return out


def _through_points(x: FloatArray, knots: FloatArray, values: FloatArray) -> FloatArray:
    """The line through (knots, values) at x, the end segments extended (as the CDF is)."""
    i, u = segment(x, knots)
    return values[i] + u * (values[i + 1] - values[i])


# -- timing ------------------------------------------------------------------------------------
@register_term
class SamplingSkewTerm(_Replayable):
    """Per-channel timing skew: channel i latches its count tau_i after the sample time, so a
    moving bar reads d_i(t + tau_i) ~ d_i + tau_i v_i. Correction: -tau_i v_i, with v_i the
    backward difference of the CDF lengths (causal, so the stream gives the batch result; zero
    across gaps longer than ``max_gap_s``).

    common_fitted : the delays' common part was fitted (against a reference on the MMD's clock);
        False: only how they differ between the channels (against a reference on a clock of
        its own, whose lag a common delay cannot be told from), and the terminal's stated
        latch skew stays in the uncertainty budget for the common part
    """

    type_name = 'sampling_skew'

    def __init__(self, skew_s: FloatArray, max_gap_s: float = MAX_GAP_S,
                 common_fitted: bool = True) -> None:
        self.skew_s = np.asarray(skew_s, dtype=np.float64)
        self.max_gap_s = float(max_gap_s)
        self.common_fitted = bool(common_fitted)
        self.reset()

    @staticmethod
    def features(cdf_lengths_m: FloatArray, times_s: FloatArray, max_gap_s: float,
                 state: Any) -> tuple[FloatArray, Any]:
        """Signature per second of skew, (N, 6) [m/s]: minus the bar velocities."""
        n = cdf_lengths_m.shape[0]
        if n == 0:
            return np.zeros((0, 6)), state
        if state is None:
            prev_d, prev_t = cdf_lengths_m[:1], times_s[:1]
        else:
            prev_d, prev_t = state[0][None], np.array([state[1]])
        d = np.concatenate([prev_d, cdf_lengths_m])
        t = np.concatenate([prev_t, times_s])
        dt = np.diff(t)
        ok = (dt > 0) & (dt <= max_gap_s)
        vel = np.where(ok[:, None], np.diff(d, axis=0) / np.where(ok, dt, 1.0)[:, None], 0.0)
        return -vel, (cdf_lengths_m[-1].copy(), float(times_s[-1]))

    def correction(self, ctx: TermContext) -> FloatArray:
        self._begin(ctx)
        v, self._state = self.features(ctx.cdf_lengths_m, ctx.times_s, self.max_gap_s, self._state)
        return self.skew_s * v

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> SamplingSkewTerm:
        return cls(six_values(params, 'skew_us', source) * 1e-6,
                   _number(params, 'max_gap_s', source, MAX_GAP_S, positive=True),
                   validate.boolean(params.get('common_fitted', True), source, 'common_fitted'))

    def params(self) -> dict[str, Any]:
        out: dict[str, Any] = {'skew_us': (self.skew_s / 1e-6).tolist(),
                               'max_gap_s': self.max_gap_s}
        if not self.common_fitted:
            out['common_fitted'] = False
        return out


@register_term
class DriftTerm(_Replayable):
    """Slow drift of each bar's reading since its calibration: over a run it is an offset at the
    run's first sample plus a rate, c_i + v_i (t - t_first), or, with ``settling_s`` tau, plus a
    settling, c_i + a_i exp(-(t - t_first) / tau) (a reading that settles after handling, as a
    bar and its joints warm or relax). Correction: minus that. The offset belongs to the run
    analysed (it grows with the time since calibration); the rate carries over.
    """

    type_name = 'drift'

    def __init__(self, offset_m: FloatArray, rate_m_per_s: FloatArray,
                 settling_s: float | None = None) -> None:
        self.offset_m = np.asarray(offset_m, dtype=np.float64)
        self.rate_m_per_s = np.asarray(rate_m_per_s, dtype=np.float64)   # (a_i with settling_s)
        self.settling_s = None if settling_s is None else float(settling_s)
        self.reset()

    @staticmethod
    def features(times_s: FloatArray, state: Any, settling_s: float | None = None
                 ) -> tuple[FloatArray, FloatArray, Any]:
        """Signatures per unit offset and per unit rate (per unit settling amplitude with
        ``settling_s``), (N, 6) each [1, s (1)]; state: t_first."""
        if times_s.shape[0] == 0:
            return np.zeros((0, 6)), np.zeros((0, 6)), state
        t0 = float(times_s[0]) if state is None else state
        elapsed = times_s - t0
        # (one exp per sample, then the six bars: a settling search scores tens of settings)
        shape = elapsed if settling_s is None else np.exp(-elapsed / settling_s)
        return -np.ones((elapsed.size, 6)), np.repeat(-shape[:, None], 6, axis=1), t0

    def correction(self, ctx: TermContext) -> FloatArray:
        self._begin(ctx)
        c, r, self._state = self.features(ctx.times_s, self._state, self.settling_s)
        return self.offset_m * c + self.rate_m_per_s * r

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> DriftTerm:
        offset = six_values({'offset_um': params.get('offset_um', 0.0)}, 'offset_um', source)
        if 'settling_s' in params:
            return cls(offset * M_PER_UM, six_values(params, 'settling_um', source) * M_PER_UM,
                       _number(params, 'settling_s', source, positive=True))
        rate = six_values(params, 'rate_um_per_h', source) * M_PER_UM / 3600.0
        return cls(offset * M_PER_UM, rate)

    def params(self) -> dict[str, Any]:
        if self.settling_s is not None:
            return {'offset_um': (self.offset_m / M_PER_UM).tolist(),
                    'settling_um': (self.rate_m_per_s / M_PER_UM).tolist(),
                    'settling_s': self.settling_s}
        return {'offset_um': (self.offset_m / M_PER_UM).tolist(),
                'rate_um_per_h': (self.rate_m_per_s * 3600.0 / M_PER_UM).tolist()}
