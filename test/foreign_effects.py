"""Effects in shapes the twin does not make, for tests that judge the analysis and the
uncertainty on data like other people's (added to a twin's counts as reading errors [m])."""

from __future__ import annotations

import math

import numpy as np


def sech_friction(lengths: np.ndarray, width_m: float) -> np.ndarray:
    """A friction state that turns over along s = sigma - (sigma - s_a) sech^2(u / w) after a
    reversal (slowly at first, unlike Dahl's exponential), u the travel since the reversal."""
    out = np.zeros_like(lengths)
    for j in range(lengths.shape[1]):
        x = lengths[:, j]
        sigma, s_a, x_a, s = 0.0, 0.0, x[0], 0.0
        for k in range(1, x.size):
            step = x[k] - x[k - 1]
            if abs(step) > 1e-12 and np.sign(step) != sigma:
                s_a, x_a, sigma = s, x[k - 1], float(np.sign(step))
            if sigma:
                u = min((x[k] - x_a) * sigma / width_m, 300.0)
                s = sigma - (sigma - s_a) / math.cosh(u) ** 2
            out[k, j] = s
    return out
