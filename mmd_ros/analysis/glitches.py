"""Steps in a bar's residual: counts lost or gained at one instant.

An encoder that misses or adds counts (a dirty scale, a signal that dropped out for a moment, a
packet the terminal decoded wrong) reads a constant amount off from that instant on. No effect
of the catalogue has that shape: fitted, a step went into a drift (the line through it), which a
model then carried to other runs. Against a reference that determines every bar (a full pose,
mapped to the bars by J dp; or bar lengths) the residual of each bar shows it as a step.

For each bar, over the usable samples in time order (means of consecutive ones, at most
``MAX_POINTS``), the difference of the residual's means over the ``WINDOW`` points after and
before each point, s(t), peaks at a step with its size and falls off linearly either side;
elsewhere it is the noise and structure of the residual. A peak is a step when it is at least
``STEP_SIGMAS`` robust standard deviations of s (its median absolute deviation over the run),
not within a twentieth of the run of either end, and the level stays: the means over
``LEVEL_WINDOWS`` windows either side differ by at least half of it and by ``STEP_MIN_COUNTS``
counts (a bar that crosses a localised error, a bump 3 mm wide, peaks at its entry and exit
with the level back between). That difference is the step's size. It is then taken out and
the next one looked for, up to ``MAX_STEPS`` per bar.

Not where the bar turned: a bar's friction state turns over as it reverses (its reading
shifts by twice the friction at each turn, and back at the next), as sharp as counts lost. A
peak within ``WINDOW`` points of a turn of that bar's travel (from the extreme of its length
to where it has come back ``TURN_TRAVEL_M``) is not a step: with the friction not in the
model (left out, or of a shape it does not follow) the turns of a 10 s 6-DOF run were
reported as counts lost or gained, +0.86, -0.88 and -0.87 µm on one bar, all at its turns.
Counts lost at a turn of the bar are missed with them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.accuracy import robust_std

__all__ = ['Step', 'bar_residual', 'residual_steps', 'turns']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Samples (points) either side of each one whose means are compared: a step is sharp, the
#: structure a fit leaves is slow (five counts lost stood 8.5-18 robust sigma above it with 10
#: points, 4.4-8 with a twentieth of the log; realistic logs without a step peaked at 4.4-5.5
#: with 10, up to 35 with a twentieth)
WINDOW = 10
#: A step stands this many robust standard deviations of the window difference above it,
STEP_SIGMAS = 7.0
#: ... is at least this many encoder counts,
STEP_MIN_COUNTS = 2.0
#: ... and its level stays over this many windows either side: longer, what a fit took of the
#: step shows (five counts lost, 231 nm at the peak: 220 nm over 10 windows, 72 nm over 100
#: with a drift and the CDF points fitted)
LEVEL_WINDOWS = 10
#: Steps looked for per bar and log.
MAX_STEPS = 3
#: A bar has turned once it has come back this far from the extreme of its length [m] (the
#: budget's direction of travel flips after 2 µm of reverse travel).
TURN_TRAVEL_M = 2e-6


@dataclass(frozen=True)
class Step:
    """A step in one bar's residual."""

    bar: int           # 0..5
    time_s: float      # the log's time of the first sample after it [s]
    size_m: float      # the residual after minus before [m]
    counts: float      # size in encoder counts
    sigmas: float      # size in robust standard deviations of the window difference

    def text(self, log: str) -> str:
        return (f'bar{self.bar + 1} of {log} steps by {self.size_m * 1e6:+.3f} µm '
                f'({self.counts:+.1f} counts) at {self.time_s:.3f} s')

    def as_dict(self) -> dict:
        return {'bar': self.bar + 1, 'time_s': round(self.time_s, 4), 'size_um': round(self.size_m * 1e6, 4),
                'counts': round(self.counts, 2), 'sigmas': round(self.sigmas, 1)}


#: At most this many points are searched: means of consecutive samples (a 10-minute 1 kHz log
#: in groups of 30; a step stays a step, and the Jacobian of 600,000 poses took 2 s).
MAX_POINTS = 20_000


def bar_residual(device, times_s: FloatArray, poses: FloatArray, obs, residual: FloatArray,
                 idx: IntArray, lengths_m: FloatArray
                 ) -> tuple[FloatArray, FloatArray, list[int], FloatArray] | None:
    """Each bar's residual at the samples ``idx`` (finite residual and pose), as means of
    groups of consecutive ones (at most ``MAX_POINTS``): their times (n,), the residual (n, b),
    the bars (b of them): J dp for a full pose, the bars a bar-length reference gives, and
    those bars' lengths (n, b) from ``lengths_m`` (N, 6); None when the reference does not
    determine the bars."""
    size = -(-idx.size // MAX_POINTS) if idx.size else 1
    groups = np.arange(idx.size) // size

    def mean(values: FloatArray) -> FloatArray:
        sums = np.zeros((groups[-1] + 1 if idx.size else 0,) + values.shape[1:])
        np.add.at(sums, groups, values)
        return sums / np.bincount(groups).reshape((-1,) + (1,) * (values.ndim - 1))

    seen = obs.bar_residual(device, mean(poses[idx]), mean(residual[idx]))
    if seen is None:
        return None
    values, bars = seen
    return mean(times_s[idx]), values, bars, mean(lengths_m[idx])[:, bars]


def turns(lengths_m: FloatArray, travel_m: float = TURN_TRAVEL_M) -> list[tuple[int, int]]:
    """Where a bar's travel turned: (index of the extreme of its length, index where it had
    come back ``travel_m`` from it), in order. The first direction is the one the bar first
    moved ``travel_m`` in."""
    out: list[tuple[int, int]] = []
    x = np.asarray(lengths_m, dtype=np.float64)
    direction, extreme, hi, lo = 0, 0, 0, 0
    for k in range(1, x.size):
        if direction == 0:                   # (not yet moved travel_m: track both ends)
            hi = k if x[k] > x[hi] else hi
            lo = k if x[k] < x[lo] else lo
            if x[hi] - x[lo] > travel_m:
                direction, extreme = (1, hi) if hi > lo else (-1, lo)
            continue
        if direction * (x[k] - x[extreme]) >= 0:
            extreme = k                      # (further along this leg)
        elif direction * (x[extreme] - x[k]) > travel_m:
            out.append((extreme, k))
            direction, extreme = -direction, k
    return out


def residual_steps(times_s: FloatArray, values: FloatArray, bars: list[int],
                   resolution_m: float, lengths_m: FloatArray | None = None) -> list[Step]:
    """Steps in the residual ``values`` (n, b) of ``bars`` at ``times_s`` (n,), not where a
    bar's length ``lengths_m`` (n, b) turned (module docstring)."""
    n = values.shape[0]
    w = WINDOW
    out: list[Step] = []
    if n < 20 * w:
        return out
    t = np.arange(w, n - w + 1)
    for j, bar in enumerate(bars):
        g = values[:, j].astype(np.float64).copy()
        free = np.ones(t.size, bool)       # (points a step may lie at: not at a turn)
        for lo, hi in ([] if lengths_m is None else turns(lengths_m[:, j])):
            free[(t >= min(lo, hi) - w) & (t <= max(lo, hi) + w)] = False
        for _ in range(MAX_STEPS):
            c = np.concatenate(([0.0], np.cumsum(g)))
            s = (c[t + w] - c[t]) / w - (c[t] - c[t - w]) / w
            scale = float(robust_std(s))
            if not free.any():
                break
            k = int(np.argmax(np.where(free, np.abs(s), -1.0)))
            peak = float(s[k])
            if scale <= 0 or abs(peak) < STEP_SIGMAS * scale:
                break
            at = int(t[k])
            span = LEVEL_WINDOWS * w
            if min(at, n - at) < max(span, n // 20):    # near an end: a step or a bump?
                break
            size = float(np.mean(g[at:at + span]) - np.mean(g[at - span:at]))
            if abs(size) < max(0.5 * abs(peak), STEP_MIN_COUNTS * resolution_m) or size * peak < 0:
                break
            out.append(Step(bar, float(times_s[at]), size, size / resolution_m, abs(peak) / scale))
            g[at:] -= size
    return out
