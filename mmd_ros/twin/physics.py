"""Physics of one ball bar: from its true centre distance to the counts the terminal reads.

Thermal model (Fig. 10, section 3.3). A bar of centre distance d is the readhead assembly l_L,
the variable scale length l_D and the scale assembly's end l_S + l_R. The rods (l_L + l_S + l_R
= L, ``fixed_length_m``) expand with the rod CTE a_r, the scale with a_s, both from 20 °C.
With the balls held at distance d, the scale length between readhead and scale end is
d - L (1 + a_r dT), and the encoder counts graduations of a scale grown by (1 + a_s dT):

    u = (d - L (1 + a_r dT)) / (1 + a_s dT)                                   [m of scale]

so the reading falls as the bar warms, as the paper says. Two identical bars at the same
temperature differ in thermal error only by (d_i - d_j) a_s dT, the term Eq. (12) interpolates
and Eq. (13) neglects (0.037 µm/°C over 323..376 mm, section 3.3).

The reading the terminal counts is

    u + e_nl(u) + e_cyc(u) + e_bump(u) - h s + g (1 - n_z^2) + v t + noise

    e_nl     scale nonlinearity: harmonics 1 and 2 over the stroke, per-bar phases, peak
             ``scale_nonlinearity_m``
    e_cyc    cyclic (sub-division) error ``cyclic_error_m`` sin(2 pi u / period + phase)
    e_bump   optional Gaussian bump of one bar
    h s      friction hysteresis: s in [-1, 1] is a Dahl state that turns towards the sign of
             the motion exponentially in travel (``hysteresis_travel_m``); h = 0.5..1.5 x
             ``hysteresis_m``; the reading lags the motion
    g        gravity sag of a horizontal bar: a sagging bar is longer along its axis than the
             chord between its balls, so it reads long, by g (1 - n_z^2) for axis z-component n_z
    v t      slow drift, t on the twin's clock
    noise    Gaussian, ``read_noise_m``

and counts = offset + round(reading / resolution). Per-sample randomness (noise, reference
instrument noise) is a counter-based hash of the seed, the channel and the sample index on the
terminal's 1 kHz grid, so any stretch of time can be simulated alone, in chunks or at a lower
rate and agree sample for sample.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.device import DeviceDescription
from mmd_ros.twin.effects import Effects
from mmd_ros.twin.thermal import REFERENCE_TEMP_C

__all__ = ['BarPhysics', 'DahlState', 'dahl', 'hashed_normal', 'stream_key']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Random streams, one per effect, so that switching one effect leaves the others' draws alone.
STREAM_OFFSETS, STREAM_NONLINEARITY, STREAM_THERMAL, STREAM_HYSTERESIS = 1, 2, 3, 4
STREAM_CYCLIC, STREAM_SKEW, STREAM_DRIFT, STREAM_SEATING = 5, 6, 7, 8
STREAM_SAG = 9
STREAM_READ_NOISE, STREAM_REFERENCE = 101, 102

#: Half width of the random power-on count offset, and the per-channel base between channels.
COUNT_OFFSET_SPAN = 1_000_000
COUNT_OFFSET_BASE = 4_000_000
#: A length step below this is no motion for the friction state (rounding, thermal creep) [m].
STILL_M = 1e-12
#: Further seatings of a bar on a pair with their own seating offsets (seat 0 is the bar's
#: resting placement, ``seating_m``).
RESEATS = 4
#: Each bar's friction amplitude is this range times ``Effects.hysteresis_m`` (uniform).
HYSTERESIS_SPREAD = (0.5, 1.5)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix(x: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """splitmix64 finaliser (wrapping uint64 arithmetic on arrays)."""
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


def stream_key(*parts: int) -> NDArray[np.uint64]:
    """A 64-bit key from non-negative integers (seed, stream, channel...), shape (1,)."""
    key = np.zeros(1, dtype=np.uint64)
    for part in parts:
        key = _mix(key + np.array([part], dtype=np.uint64) * _GOLDEN + _GOLDEN)
    return key


def hashed_normal(key: NDArray[np.uint64], index: ArrayLike) -> FloatArray:
    """Standard normal numbers addressed by ``index``: the same index always gives the same
    number, whatever else is drawn (Box-Muller on two splitmix64 hashes).

    key : ndarray, shape (1,) — from :func:`stream_key`
    index : array_like of int — e.g. the sample index on the terminal's grid
    returns : ndarray of the shape of ``index``
    """
    i = np.asarray(index, dtype=np.int64).astype(np.uint64) * np.uint64(2)
    h1 = _mix(key + i * _GOLDEN)
    h2 = _mix(key + (i + np.uint64(1)) * _GOLDEN)
    u1 = ((h1 >> np.uint64(11)).astype(np.float64) + 1.0) * 2.0 ** -53
    u2 = (h2 >> np.uint64(11)).astype(np.float64) * 2.0 ** -53
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


# -- friction hysteresis -----------------------------------------------------------------------
@dataclass
class DahlState:
    """Friction state of M bars between chunks: the current motion direction and the anchor
    (position, state) where the current direction began. NaN positions mean "not started":
    the anchor is then placed at the first sample."""

    direction: FloatArray  # (M,) +1 or -1
    anchor_state: FloatArray  # (M,)
    anchor_m: FloatArray  # (M,)
    last_m: FloatArray  # (M,)

    @classmethod
    def start(cls, states: ArrayLike) -> DahlState:
        s = np.array(states, dtype=np.float64)
        nan = np.full_like(s, np.nan)
        return cls(np.ones_like(s), s, nan, nan.copy())

    def copy(self) -> DahlState:
        return DahlState(self.direction.copy(), self.anchor_state.copy(), self.anchor_m.copy(),
                         self.last_m.copy())


def dahl(lengths_m: FloatArray, state: DahlState, travel_m: float) -> tuple[FloatArray, DahlState]:
    """Dahl-like friction state along a motion, by segments of constant direction.

    Within a segment of direction sigma that began at (x_a, s_a),
    s(x) = sigma - (sigma - s_a) exp(-sigma (x - x_a) / travel); a dwell keeps s. The state
    carried between chunks is the anchor, not the last s, so that chunked and one-shot runs
    compute every sample with the same formula and agree exactly.

    lengths_m : ndarray, shape (N, M) — the motion driving each bar [m]
    state : DahlState of M bars (not modified)
    returns : s, shape (N, M), and the state after the last sample
    """
    x = np.asarray(lengths_m, dtype=np.float64)
    n, m = x.shape
    out = np.empty_like(x)
    new = state.copy()
    if n == 0:
        return out, new
    for j in range(m):
        xj = x[:, j]
        if np.isnan(new.last_m[j]):
            new.last_m[j] = new.anchor_m[j] = xj[0]
        prev = np.concatenate(([new.last_m[j]], xj[:-1]))
        dx = xj - prev
        moving = np.abs(dx) > STILL_M
        last_move = np.maximum.accumulate(np.where(moving, np.arange(n), -1))
        dirs = np.where(last_move >= 0, np.sign(dx[np.maximum(last_move, 0)]), new.direction[j])
        dirs_before = np.concatenate(([new.direction[j]], dirs[:-1]))
        turns = np.flatnonzero(dirs != dirs_before)
        anchor_x = np.empty(turns.size + 1)
        anchor_s = np.empty(turns.size + 1)
        anchor_x[0], anchor_s[0] = new.anchor_m[j], new.anchor_state[j]
        for k, i in enumerate(turns):
            sigma = dirs_before[i]
            anchor_x[k + 1] = prev[i]
            anchor_s[k + 1] = sigma - (sigma - anchor_s[k]) * np.exp(
                -sigma * (prev[i] - anchor_x[k]) / travel_m)
        seg = np.cumsum(dirs != dirs_before)
        s = dirs - (dirs - anchor_s[seg]) * np.exp(-dirs * (xj - anchor_x[seg]) / travel_m)
        out[:, j] = np.clip(s, -1.0, 1.0)
        new.direction[j] = dirs[-1]
        new.anchor_m[j], new.anchor_state[j] = anchor_x[-1], anchor_s[-1]
        new.last_m[j] = xj[-1]
    return out, new


# -- per-bar realisation -----------------------------------------------------------------------
@dataclass(frozen=True)
class BarPhysics:
    """The bars of one twin: their drawn parameters and the reading model.

    Every per-bar parameter is drawn from its own stream of ``default_rng([seed, stream])``
    whether its effect is on or not, so switching an effect changes that effect only.
    Arrays are per terminal channel (8,), or per channel and reference pair (8, 7).
    """

    device: DeviceDescription
    effects: Effects
    seed: int
    offsets_counts: IntArray = field(init=False, repr=False)
    rod_cte_per_c: FloatArray = field(init=False, repr=False)
    time_constant_s: FloatArray = field(init=False, repr=False)
    nonlinearity_m: FloatArray = field(init=False, repr=False)  # (8, 2) sine amplitudes
    nonlinearity_phase_rad: FloatArray = field(init=False, repr=False)  # (8, 2)
    hysteresis_m: FloatArray = field(init=False, repr=False)
    start_state: FloatArray = field(init=False, repr=False)  # friction state at a run's start
    pair_state: FloatArray = field(init=False, repr=False)  # (8, 7) friction state on a pair
    cyclic_phase_rad: FloatArray = field(init=False, repr=False)
    skew_s: FloatArray = field(init=False, repr=False)
    drift_m_per_s: FloatArray = field(init=False, repr=False)
    seating_m: FloatArray = field(init=False, repr=False)  # (8, 7)
    reseating_m: FloatArray = field(init=False, repr=False)  # (8, 7, RESEATS): seats 1, 2...
    sag_m: FloatArray = field(init=False, repr=False)  # () this twin's gravity sag, every bar

    def __post_init__(self) -> None:
        eff, dev = self.effects, self.device
        n, n_pairs = len(dev.channels), len(dev.pairs)

        def rng(stream: int) -> np.random.Generator:
            return np.random.default_rng([self.seed, stream])

        def put(name: str, value: NDArray) -> None:
            value = np.asarray(value)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

        draw = rng(STREAM_OFFSETS).integers(-COUNT_OFFSET_SPAN, COUNT_OFFSET_SPAN + 1, n)
        base = COUNT_OFFSET_BASE * (np.arange(n) - n // 2)
        put('offsets_counts', (draw + base) * int(eff.count_offsets))

        spread = np.clip(1.0 + eff.thermal_mismatch * rng(STREAM_THERMAL).standard_normal((2, n)),
                         0.2, None)
        put('rod_cte_per_c', eff.rod_cte(dev.rod_cte_per_c) * spread[0])
        put('time_constant_s', eff.bar_time_constant_s * spread[1])

        g = rng(STREAM_NONLINEARITY)
        weights = np.column_stack([np.ones(n), g.uniform(0.2, 0.6, n)])
        phases = g.uniform(0.0, 2.0 * np.pi, (n, 2))
        grid = np.linspace(0.0, 1.0, 1001)
        shape = (weights[:, :1] * np.sin(2 * np.pi * grid + phases[:, :1])
                 + weights[:, 1:] * np.sin(4 * np.pi * grid + phases[:, 1:]))
        put('nonlinearity_m', eff.scale_nonlinearity_m * weights / np.abs(shape).max(axis=1)[:, None])
        put('nonlinearity_phase_rad', phases)

        g = rng(STREAM_HYSTERESIS)
        put('hysteresis_m', eff.hysteresis_m * g.uniform(*HYSTERESIS_SPREAD, n))
        put('start_state', g.uniform(-1.0, 1.0, n))
        put('pair_state', g.choice([-1.0, 1.0], (n, n_pairs)))

        put('cyclic_phase_rad', rng(STREAM_CYCLIC).uniform(0.0, 2.0 * np.pi, n))
        put('skew_s', eff.sampling_skew_s * rng(STREAM_SKEW).uniform(0.0, 1.0, n))
        put('drift_m_per_s', eff.drift_m_per_s * rng(STREAM_DRIFT).uniform(-1.0, 1.0, n))
        put('seating_m', eff.placement_repeatability_m * rng(STREAM_SEATING).standard_normal((n, n_pairs)))
        put('reseating_m', eff.placement_repeatability_m * np.random.default_rng(
            [self.seed, STREAM_SEATING, 1]).standard_normal((n, n_pairs, RESEATS)))
        put('sag_m', eff.gravity_sag_m * max(
            1.0 + eff.gravity_sag_spread * float(rng(STREAM_SAG).standard_normal()), 0.0))

    def seating(self, channels: ArrayLike, pairs: ArrayLike, seat: int = 0) -> FloatArray:
        """Seating offsets [m] of bars on pairs (index arrays of one shape) at seating ``seat``:
        0 is the bar's resting placement, 1..RESEATS further placements."""
        ch, j = np.asarray(channels, dtype=np.intp), np.asarray(pairs, dtype=np.intp)
        if seat == 0:
            return self.seating_m[ch, j]
        if not 1 <= seat <= RESEATS:
            raise ValueError(f'seat must be in 0..{RESEATS}, got {seat}')
        return self.reseating_m[ch, j, seat - 1]

    @property
    def stroke_m(self) -> float:
        """The scale length a bar uses, d_max - d_min of its range [m]."""
        lo, hi = self.device.bar_range_m
        return hi - lo

    def scale_reading_m(self, channels: ArrayLike, lengths_m: FloatArray, bar_temp_c: FloatArray,
                        friction_state: FloatArray, times_s: FloatArray,
                        sample_index: IntArray, axis_z: FloatArray | None = None) -> FloatArray:
        """What each encoder reads before quantisation (module docstring).

        channels : array_like of int, shape (M,) — terminal channels of the columns
        lengths_m : ndarray, shape (N, M) — true centre distances at the read instant [m]
        bar_temp_c : ndarray, shape (N, M) — bar temperatures [°C]
        friction_state : ndarray, shape (N, M) — Dahl state s in [-1, 1]
        times_s : ndarray, shape (N,) — the twin's clock [s], for the drift
        sample_index : ndarray of int, shape (N,) — sample on the terminal grid, for the noise
        axis_z : ndarray, shape (N, M), optional — z-component of each bar axis in {L};
            None for bars lying horizontally (on the reference plate)
        returns : ndarray, shape (N, M) — reading in scale metres
        """
        ch = np.asarray(channels, dtype=np.intp)
        eff, dev = self.effects, self.device
        d_temp = bar_temp_c - REFERENCE_TEMP_C
        u = (lengths_m - dev.fixed_length_m * (1.0 + self.rod_cte_per_c[ch] * d_temp)) \
            / (1.0 + dev.scale_cte_per_c * d_temp)
        phase = 2.0 * np.pi * u / self.stroke_m
        reading = (u
                   + self.nonlinearity_m[ch, 0] * np.sin(phase + self.nonlinearity_phase_rad[ch, 0])
                   + self.nonlinearity_m[ch, 1] * np.sin(2.0 * phase + self.nonlinearity_phase_rad[ch, 1])
                   - self.hysteresis_m[ch] * friction_state
                   + self.drift_m_per_s[ch] * np.asarray(times_s)[:, None])
        if eff.cyclic_error_m:
            reading += eff.cyclic_error_m * np.sin(2.0 * np.pi * u / eff.cyclic_period_m
                                                   + self.cyclic_phase_rad[ch])
        if self.sag_m:
            reading += self.sag_m * (1.0 if axis_z is None else 1.0 - axis_z ** 2)
        if eff.bump is not None and eff.bump.channel in ch:
            col = ch == eff.bump.channel
            centre_u = eff.bump.centre_m - dev.fixed_length_m
            reading[:, col] += eff.bump.height_m * np.exp(
                -0.5 * ((u[:, col] - centre_u) / eff.bump.width_m) ** 2)
        if eff.read_noise_m:
            for k, c in enumerate(ch):
                reading[:, k] += eff.read_noise_m * hashed_normal(
                    stream_key(self.seed, STREAM_READ_NOISE, int(c)), sample_index)
        return reading

    def counts(self, channels: ArrayLike, reading_m: FloatArray) -> IntArray:
        """Quantise readings to the encoder resolution and add the count offsets.

        channels : array_like of int, shape (M,)
        reading_m : ndarray, shape (N, M) [m]
        returns : ndarray of int64, shape (N, M)
        """
        ch = np.asarray(channels, dtype=np.intp)
        steps = np.rint(reading_m / self.device.encoder_resolution_m).astype(np.int64)
        return self.offsets_counts[ch] + steps

    def summary(self) -> dict[str, list[float]]:
        """The drawn per-channel parameters, as plain lists (for a log's metadata)."""
        return {
            'offsets_counts': [int(v) for v in self.offsets_counts],
            'rod_cte_per_c': self.rod_cte_per_c.tolist(),
            'time_constant_s': self.time_constant_s.tolist(),
            'hysteresis_m': self.hysteresis_m.tolist(),
            'skew_s': self.skew_s.tolist(),
            'drift_m_per_s': self.drift_m_per_s.tolist(),
        }
