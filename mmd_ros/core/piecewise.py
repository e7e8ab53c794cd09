"""Where a length lies among a bar's calibration points (ROS-free).

Eq. (10) interpolates linearly between adjacent calibration points; every quantity that
follows it (the CDF point offsets, the scale harmonics' interpolant, the interpolation error
and the points' weights in the uncertainty budget) needs the segment a length lies in and
how far along it. Beyond the end points the end segment is extended, as the CDF is
(:class:`~mmd_ros.core.calibration.CentreDistanceFunction`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def segment(x: FloatArray, points: FloatArray) -> tuple[IntArray, FloatArray]:
    """For each of ``x`` (any shape) among the increasing ``points`` (n,): the index j of its
    segment [p_j, p_j+1], 0 <= j <= n - 2, and the fraction u = (x - p_j) / (p_j+1 - p_j),
    below 0 or above 1 beyond the ends."""
    j = np.clip(np.searchsorted(points, x, side='right') - 1, 0, points.size - 2)
    return j, (x - points[j]) / (points[j + 1] - points[j])


def bar_segments(x_m: FloatArray, knots_m: FloatArray) -> tuple[IntArray, FloatArray]:
    """:func:`segment` of each bar's column of ``x_m`` (N, B) among its row of ``knots_m``
    (B, n): (N, B) each."""
    j = np.empty(x_m.shape, dtype=np.intp)
    u = np.empty(x_m.shape)
    for b in range(x_m.shape[1]):
        j[:, b], u[:, b] = segment(x_m[:, b], knots_m[b])
    return j, u
