"""Steps in a bar's residual: counts lost or gained at one instant.

An encoder that misses or adds counts (a dirty scale, a signal that dropped out for a moment, a
packet the terminal decoded wrong) reads a constant amount off from that instant on. No effect
of the catalogue has that shape: fitted, a step went into a drift (the line through it), which a
model then carried to other runs. Against a reference that determines every bar (a full pose,
mapped to the bars by J dp; or bar lengths) the residual of each bar shows it as a step.

For each bar, over the usable samples in time order, the difference of the residual's means over
the ``w`` samples after and before each sample, s(t), peaks at a step with its size and falls off
linearly over w either side; elsewhere it is the noise and structure of the residual. A peak is a
step when it is at least ``STEP_SIGMAS`` robust standard deviations of s (its median absolute
deviation over the run) and the level stays: the means over up to a quarter of the run either
side differ by at least half of it and by ``STEP_MIN_COUNTS`` counts (a bar that crosses a
localised error, a bump 3 mm wide, peaks at its entry and exit with the level back between:
five such peaks of 8-11 sigma on one log). It is then taken out and the next one looked for,
up to ``MAX_STEPS`` per bar.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.kinematics import jacobian

__all__ = ['Step', 'residual_steps']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: A step stands this many robust standard deviations of the window difference above it.
STEP_SIGMAS = 6.0
#: ... and is at least this many encoder counts.
STEP_MIN_COUNTS = 2.0
#: Steps looked for per bar and log.
MAX_STEPS = 3


@dataclass(frozen=True)
class Step:
    """A step in one bar's residual."""

    bar: int           # 0..5
    time_s: float      # the log's time of the first sample after it [s]
    size_m: float      # the residual after minus before [m]
    counts: float      # size in encoder counts
    sigmas: float      # size in robust standard deviations of the window difference

    def text(self, log: str) -> str:
        return (f'bar{self.bar + 1} of {log} reads {self.size_m * 1e6:+.3f} µm '
                f'({self.counts:+.1f} counts) off from {self.time_s:.3f} s on')

    def as_dict(self) -> dict:
        return {'bar': self.bar + 1, 'time_s': round(self.time_s, 4), 'size_um': round(self.size_m * 1e6, 4),
                'counts': round(self.counts, 2), 'sigmas': round(self.sigmas, 1)}


def bar_residual(device, poses: FloatArray, obs, residual: FloatArray,
                 idx: IntArray) -> tuple[FloatArray, list[int]] | None:
    """Each bar's residual at the samples ``idx`` (those with a finite residual), (n, b), and
    the bars (b of them): J dp for a full pose, the bars a bar-length reference gives; None
    when the reference does not determine the bars."""
    if obs.kind == 'lengths':
        return residual[idx], list(obs.components)
    if len(obs.components) != 6:
        return None
    return np.einsum('nij,nj->ni', jacobian(device.geometry, poses[idx]), residual[idx]), list(range(6))


def residual_steps(times_s: FloatArray, values: FloatArray, bars: list[int],
                   resolution_m: float) -> list[Step]:
    """Steps in the residual ``values`` (n, b) of ``bars`` at ``times_s`` (n,) (module docstring)."""
    n = values.shape[0]
    w = int(min(500, max(20, n // 20)))
    out: list[Step] = []
    if n < 4 * w:
        return out
    for j, bar in enumerate(bars):
        g = values[:, j].astype(np.float64).copy()
        for _ in range(MAX_STEPS):
            c = np.concatenate(([0.0], np.cumsum(g)))
            t = np.arange(w, n - w + 1)
            s = (c[t + w] - c[t]) / w - (c[t] - c[t - w]) / w
            scale = 1.4826 * float(np.median(np.abs(s - np.median(s))))
            k = int(np.argmax(np.abs(s)))
            peak = float(s[k])
            if scale <= 0 or abs(peak) < STEP_SIGMAS * scale:
                break
            at = int(t[k])
            if min(at, n - at) < 4 * w:     # too near an end to tell a step from a bump
                break
            span = max(w, n // 4)
            size = float(np.mean(g[at:at + span]) - np.mean(g[max(at - span, 0):at]))
            if abs(size) < max(0.5 * abs(peak), STEP_MIN_COUNTS * resolution_m) or size * peak < 0:
                break
            out.append(Step(bar, float(times_s[at]), size, size / resolution_m, abs(peak) / scale))
            g[at:] -= size
    return out
