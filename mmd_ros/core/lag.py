"""A reference's lag behind the MMD.

A reference logged by another program on a clock of its own, or stamped when its reading
arrived, reads the motion a delay δ late (early when negative): against the MMD it shows
δ v - δ² a / 2 + ... as if it were the MMD's error (5 ms at 20 mm/s: 100 µm). A common delay
within what the MMD's channels can latch (:data:`MAX_SKEW_S`) is the MMD's own, a term of its
model (sampling skew); beyond it, or when the log says that its reference runs on a clock of
its own (metadata ``reference_clock: own``), the delay is the reference's and is taken out of
the comparison (:func:`is_reference_lag`): ``mmd analyze`` fits it per log beside the effects,
``mmd process`` pairs each MMD sample with the reference's reading of the same instant
(:func:`aligned_reference`) and compares those.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.signal import savgol_filter

__all__ = [
    'LAG_SAMPLES', 'LAG_WINDOW', 'MAX_SKEW_S', 'LagAccumulator', 'ReferenceLag',
    'aligned_reference', 'effective_samples', 'fit_delay', 'is_reference_lag', 'paired_rows',
    'smoothed_motion',
]

FloatArray = NDArray[np.float64]

#: The largest delay a channel of the MMD's terminal can latch its count with [s]: two sample
#: periods at 1 kHz (a terminal that stamps a packet with the tick after the one it latched
#: reads a whole period late). A common delay between the MMD and a reference beyond it is
#: the reference's.
MAX_SKEW_S = 2e-3
#: Samples of the cubic Savitzky-Golay fit the motion's velocity and acceleration are read from
LAG_WINDOW = 21
#: Samples whose residual decides whether a log's reference lags (evenly spread over it)
LAG_SAMPLES = 20_000


def effective_samples(series: FloatArray) -> float:
    """Effective number of independent samples of a residual series (AR(1) approximation,
    n (1 - rho) / (1 + rho) with rho the lag-1 autocorrelation), summed over columns.

    series : ndarray, shape (n,) or (n, k) in time order
    """
    s = np.asarray(series, dtype=np.float64)
    if s.ndim == 1:
        s = s[:, None]
    total = 0.0
    for col in s.T:
        c = col - col.mean()
        den = float(c @ c)
        rho = float(c[1:] @ c[:-1]) / den if den > 0 and c.size > 2 else 0.0
        rho = min(max(rho, 0.0), 0.999)
        total += c.size * (1 - rho) / (1 + rho)
    return max(total, 1.0)


def fit_delay(residual: FloatArray, motion: FloatArray, zeroed: bool
              ) -> tuple[FloatArray, float, FloatArray]:
    """How a delay explains a residual: ``residual`` (n, k) [m, rad] (in time order) as the
    columns of ``motion`` (n, k, c) times a coefficient each (the first the delay δ [s] when
    the first column is the velocity), with an offset per component beside them when
    ``zeroed``. Returns the coefficients (c,), the delay's standard deviation (the residual's
    correlation counted: :func:`effective_samples`) and the offsets (k,) [m, rad]; rows with a
    non-finite value are left out. Components are weighted by the inverse of the residual's
    spread in each."""
    k, c = residual.shape[1], motion.shape[2]
    ok = np.all(np.isfinite(residual), axis=1) & np.all(np.isfinite(motion), axis=(1, 2))
    r, v = residual[ok], motion[ok]
    if r.shape[0] < 3 + c:
        return np.zeros(c), math.inf, np.zeros(k)
    mean_r, mean_v = r.mean(axis=0), v.mean(axis=0)
    if zeroed:
        r, v = r - mean_r, v - mean_v
    scale = np.std(r, axis=0)
    w = np.where(scale > 0, 1.0 / np.where(scale > 0, scale, 1.0), 0.0)
    rw = (r * w).reshape(-1)
    vw = (v * w[None, :, None]).reshape(-1, c)
    gram = vw.T @ vw
    if gram[0, 0] <= 0:
        return np.zeros(c), math.inf, np.zeros(k)
    inv = np.linalg.pinv(gram)
    coef = inv @ (vw.T @ rw)
    e = (rw - vw @ coef).reshape(-1, k)
    dof = max(e.size - c - (k if zeroed else 0), 1)
    inflation = max(e.size / effective_samples(e), 1.0)
    sd = math.sqrt(max(float(np.sum(e * e)) / dof * inflation * inv[0, 0], 0.0))
    offsets = mean_r - mean_v @ coef if zeroed else np.zeros(k)
    return coef, sd, offsets


def is_reference_lag(delay_s: float, sd_s: float, clock: str | None) -> bool:
    """Whether a common delay between a log's reference and the MMD, ``delay_s`` ± ``sd_s``
    [s], is the reference's: the log says that the reference runs on its own clock
    (``clock`` 'own'), or, not saying (None), the delay is beyond :data:`MAX_SKEW_S` by 3
    standard deviations. Never when the log says the reference was sampled at the MMD's
    instants ('shared'), nor when the motion is too slow for a delay to show."""
    if clock == 'shared' or not sd_s <= MAX_SKEW_S:
        return False
    return clock == 'own' or abs(delay_s) - 3.0 * sd_s > MAX_SKEW_S


def stretches(times_s: FloatArray, known: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """The runs [a, b) of evenly spaced samples (each a median period from the one before,
    within a quarter of it) that are all ``known``."""
    n = times_s.size
    if n == 0:
        return []
    dt = np.diff(times_s)
    period = float(np.median(dt)) if dt.size else 1.0
    cuts = np.flatnonzero((np.abs(dt - period) > 0.25 * period) | ~known[1:] | ~known[:-1]) + 1
    edges = zip(np.concatenate(([0], cuts)), np.concatenate((cuts, [n])))
    return [(int(a), int(b)) for a, b in edges if known[a]]


def smoothed_motion(times_s: FloatArray, values: FloatArray, window: int = LAG_WINDOW
                    ) -> tuple[FloatArray, FloatArray]:
    """How fast ``values`` (N, m) change and how they accelerate, each (N, m) [unit/s,
    unit/s²], from a cubic Savitzky-Golay fit over ``window`` samples within each stretch of
    evenly spaced finite samples (:func:`stretches`); NaN in a stretch shorter than the
    window (next to a gap the motion is not known)."""
    velocity = np.full(values.shape, np.nan)
    acceleration = np.full(values.shape, np.nan)
    dt = np.diff(times_s)
    period = float(np.median(dt)) if dt.size else 1.0
    for a, b in stretches(times_s, np.all(np.isfinite(values), axis=1)):
        if b - a >= window:
            for d, out in ((1, velocity), (2, acceleration)):
                out[a:b] = savgol_filter(values[a:b], window, 3, deriv=d, delta=period, axis=0)
    return velocity, acceleration


def paired_rows(times_s: FloatArray, shift: int, period: float
                ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Each sample's partner ``shift`` samples later (earlier when negative), clipped into the
    samples, and whether it is one: inside the samples and ``shift`` periods away (within a
    quarter of one; not across a gap)."""
    n = times_s.size
    src = np.arange(n) + shift
    inside = (src >= 0) & (src < n)
    src = np.clip(src, 0, max(n - 1, 0))
    apart = np.abs(times_s[src] - times_s - shift * period) <= 0.25 * period
    return src, inside & apart


def aligned_reference(times_s: FloatArray, reference: FloatArray, poses: FloatArray,
                      shift: int, remainder_s: float, period: float) -> FloatArray:
    """The reference pose (N, 6) [m, rad] as it read at each MMD sample's instant, for a
    reference a delay ``shift`` periods + ``remainder_s`` late: its reading ``shift`` samples
    later (:func:`paired_rows`; no interpolation, so its noise stays its own), moved on by the
    remainder along the MMD's own motion there (ρ v - ρ² a / 2, :func:`smoothed_motion` of
    ``poses``). NaN where the partner is not a sample or the motion is not known."""
    src, ok = paired_rows(times_s, shift, period)
    out = np.where(ok[:, None], reference[src], np.nan)
    if remainder_s:
        velocity, acceleration = smoothed_motion(times_s, poses)
        out = out + remainder_s * velocity - 0.5 * remainder_s ** 2 * acceleration
    return out


@dataclass
class ReferenceLag:
    """A delay between a log's reference and the MMD taken as the reference's.

    delay_s, sd_s : the delay [s] (positive: the reference reads late) and its standard
        deviation
    stated : the log states that its reference runs on a clock of its own (else the delay is
        beyond what the MMD's channels can latch, :data:`MAX_SKEW_S`)
    """

    delay_s: float
    sd_s: float
    stated: bool
    #: the part of it taken out by pairing samples (a whole number of sample periods) [s]
    shifted_s: float = 0.0

    def text(self, done: str) -> str:
        """What a command says of it; ``done``: what it did with it."""
        why = ('the log states that its reference runs on a clock of its own '
               '(reference_clock: own), so a delay between the two is not the MMD\'s'
               if self.stated else
               f'beyond the {MAX_SKEW_S * 1e3:g} ms any channel of the MMD\'s terminal can '
               'latch late (a logger on another clock, time stamps taken on receipt); a log '
               'states reference_clock: own or shared to say whose a delay is')
        return (f'the reference reads {_duration(abs(self.delay_s))} '
                f'{"late" if self.delay_s >= 0 else "early"} (± {_duration(self.sd_s)}): '
                f'{why}; {done}')

    def as_dict(self) -> dict[str, Any]:
        return {'delay_s': self.delay_s, 'sd_s': self.sd_s, 'clock_stated_own': self.stated}


def _duration(seconds: float) -> str:
    return f'{seconds * 1e3:.3g} ms' if seconds >= 1e-3 else f'{seconds * 1e6:.3g} µs'


class LagAccumulator:
    """The delay between a reference pose and the MMD, read from a run given block by block:
    the error (MMD - reference) against the MMD's velocity (backward differences, the last
    sample of a block carried to the next), at about :data:`LAG_SAMPLES` samples spread
    evenly over the run, an offset per component beside it (:func:`fit_delay`).

    n_samples : the run's samples (for the stride)
    """

    def __init__(self, n_samples: int) -> None:
        self.stride = max(1, int(n_samples) // LAG_SAMPLES)
        self.period: float | None = None
        self._seen = 0
        self._last: tuple[float, FloatArray] | None = None
        self._errors: list[FloatArray] = []
        self._velocity: list[FloatArray] = []

    def add(self, times_s: FloatArray, poses: FloatArray, errors: FloatArray,
            valid: NDArray[np.bool_]) -> None:
        """times_s (N,) [s]; poses, errors (N, 6) [m, rad]; valid (N,): the measurements"""
        n = times_s.size
        if n == 0:
            return
        p = np.where(np.asarray(valid, dtype=bool)[:, None], poses, np.nan)
        t_prev = np.concatenate(([self._last[0] if self._last else np.nan], times_s[:-1]))
        p_prev = np.concatenate([self._last[1][None] if self._last else np.full((1, 6), np.nan),
                                 p[:-1]])
        dt = times_s - t_prev
        if self.period is None and n > 1:
            self.period = float(np.median(np.diff(times_s)))
        period = self.period or 1.0
        even = np.abs(dt - period) <= 0.25 * period
        velocity = np.where(even[:, None], (p - p_prev) / np.where(even, dt, 1.0)[:, None],
                            np.nan)
        keep = (self._seen + np.arange(n)) % self.stride == 0
        self._seen += n
        self._last = (float(times_s[-1]), p[-1].copy())
        self._errors.append(np.asarray(errors, dtype=np.float64)[keep])
        self._velocity.append(velocity[keep])

    def estimate(self) -> tuple[float, float] | None:
        """The delay and its standard deviation [s] (positive: the reference reads late), or
        None when no component is known."""
        if not self._errors:
            return None
        e, v = np.concatenate(self._errors), np.concatenate(self._velocity)
        known = np.isfinite(e).mean(axis=0) >= 0.5
        if not known.any():
            return None
        coef, sd, _ = fit_delay(e[:, known], v[:, known, None], zeroed=True)
        return float(coef[0]), sd
