"""What a one-axis run says in the pose components its reference does not see.

An ISO 230-2 run with a laser along x (or a rotary calibrator on C) sees one pose component.
The MMD reads all six. In the other five it reads the machine's own motion, which for a run
along one axis is, by ISO 230-1, the error motions of that axis: functions of the axis
position (straightness, angular error motions), with a reversal that depends on the direction
of travel, and a slow thermal drift in time. None of that depends on the speed. An error of
the device that does, a channel latched later than the sample time (its error is the bar's
speed times the delay, zero at a dwell and largest in the middle of a move), shows in those
five components as what the machine's motion cannot be.

So for such a run each unseen component c is fitted as

    reading_c(t) = g_c(s) + h_c(s) · dir(t) + q_c(t) + (effects' correction in c)

with s the reference's coordinate (the axis position), g a cubic B-spline with
:data:`FINE_INTERVALS` intervals over the travel, h a coarse one (:data:`COARSE_INTERVALS`)
times the direction of the last travel (+1, -1), and q a spline in time with knots at least
:data:`DRIFT_KNOT_S` apart: the nuisance of the fit, whose coefficients nobody reads. What the
effects do to c is then determined where it is not one of those shapes: the velocity of an ISO
run's minimum-jerk moves varies along each move and is zero at the targets, which the coarse
direction term cannot follow. On the realistic twin (x, y, z and C runs, two-sided
calibration) the six channel delays come within 0.5 µs of the truth with these rows; from
the references' components alone they were not determined (σ 30-180 µs).

A run whose unseen components are not a function of the reference's coordinate (6-DOF motion
with a laser along one axis) gives no such rows: a component is used only when the nuisance
alone explains its reading to within :data:`MACHINE_LIMIT` times its noise floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline

__all__ = ['AxisMotion', 'axis_motion']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Intervals of the spline in the axis position for the direction-independent error motion
#: (5 mm over a 200 mm travel).
FINE_INTERVALS = 40
#: Intervals of the spline in the axis position for the reversal (its change along the travel).
COARSE_INTERVALS = 4
#: Least spacing of the knots of the drift spline in time [s].
DRIFT_KNOT_S = 60.0
#: A component is read as the machine's motion only when the nuisance alone leaves an RMS
#: within this many times its noise floor (a few hundred nm of an effect pass; the millimetres
#: of a component that moves on its own do not).
MACHINE_LIMIT = 500.0
#: Least travel of the reference's coordinate for a run to count as a one-axis run [m, rad].
LEAST_TRAVEL = (1e-3, np.radians(1.0))
#: Speed of the coordinate below which the direction of travel is held [m/s, rad/s].
STILL_SPEED = (1e-5, np.radians(1e-3))


@dataclass
class AxisMotion:
    """The unseen components of a one-axis run read as the machine's motion.

    components : unseen pose components used (indices 0..5)
    values : (N, u) the MMD's reading of them, less their median [m, rad]
    floor : (u,) their noise floor [m, rad]
    coordinate, direction, times : (N,) the axis position [m, rad], the direction of the last
        travel (+1, -1; 0 before the first), the sample times [s]
    """

    components: list[int]
    values: FloatArray
    floor: FloatArray
    coordinate: FloatArray
    direction: FloatArray
    times: FloatArray
    _knots: tuple[FloatArray, FloatArray, FloatArray | None]

    def basis(self, idx: IntArray) -> FloatArray:
        """The nuisance columns of one component at samples ``idx``, (n, q)."""
        fine, coarse, drift = self._knots
        s = self.coordinate[idx]
        cols = [_design(s, fine), _design(s, coarse) * self.direction[idx, None]]
        if drift is not None:
            # the constant is in the position spline already
            cols.append(_design(self.times[idx], drift)[:, 1:])
        return np.concatenate(cols, axis=1)


def _knots(lo: float, hi: float, intervals: int) -> FloatArray:
    inner = np.linspace(lo, hi, intervals + 1)
    return np.concatenate([[lo] * 3, inner, [hi] * 3])


def _design(x: FloatArray, knots: FloatArray) -> FloatArray:
    """Cubic B-spline basis at ``x`` (clipped to the knots' span), (n, len(knots) - 4)."""
    x = np.clip(x, knots[3], knots[-4])
    return BSpline.design_matrix(x, knots, 3).toarray()


def _direction(coordinate: FloatArray, times: FloatArray, still: float) -> FloatArray:
    """+1 / -1 for the direction of the last travel faster than ``still``, held through dwells."""
    speed = np.zeros_like(coordinate)
    dt = np.diff(times)
    speed[1:] = np.diff(coordinate) / np.where(dt > 0, dt, np.inf)
    moving = np.abs(speed) > still
    last = np.where(moving, np.arange(coordinate.size), -1)
    last = np.maximum.accumulate(last)
    out = np.where(last >= 0, np.sign(speed[np.maximum(last, 0)]), 0.0)
    return out


def axis_motion(poses: FloatArray, reference: FloatArray, component: int, times: FloatArray,
                usable: NDArray[np.bool_], floor: FloatArray) -> AxisMotion | None:
    """The unseen components of a run whose reference sees one pose component ``component``,
    read as the machine's motion along that coordinate; None when the run is not a one-axis
    run (the coordinate hardly moves) or no component passes the test of the module docstring.

    poses : (N, 6) the MMD's poses [m, rad]; reference : (N,) the reference's coordinate
    usable : (N,) samples with a valid pose and a reference; floor : (6,) noise floor per
    component [m, rad]
    """
    idx = np.flatnonzero(usable & np.isfinite(reference))
    if idx.size < 50:
        return None
    angular = component >= 3
    s = np.where(np.isfinite(reference), reference, np.nanmedian(reference[idx]))
    if angular:
        s[idx] = np.unwrap(s[idx])      # a rotary axis that passes +-180 degrees travels on
    lo, hi = float(np.min(s[idx])), float(np.max(s[idx]))
    if hi - lo < LEAST_TRAVEL[angular]:
        return None
    direction = _direction(s, times, STILL_SPEED[angular])
    span = float(times[idx[-1]] - times[idx[0]])
    n_drift = int(span // DRIFT_KNOT_S)
    knots = (_knots(lo, hi, FINE_INTERVALS), _knots(lo, hi, COARSE_INTERVALS),
             _knots(float(times[idx[0]]), float(times[idx[-1]]), n_drift) if n_drift >= 1 else None)
    unseen = [c for c in range(6) if c != component]
    values = poses[:, unseen] - np.median(poses[idx][:, unseen], axis=0)
    values = np.where(np.isfinite(values), values, 0.0)
    motion = AxisMotion(unseen, values, np.maximum(floor[unseen], 1e-12), s, direction, times, knots)
    # the nuisance alone must explain a component to within MACHINE_LIMIT of its floor
    sub = idx[:: max(1, idx.size // 5000)]
    b = motion.basis(sub)
    coef, *_ = np.linalg.lstsq(b, values[sub], rcond=None)
    rms = np.sqrt(np.mean((values[sub] - b @ coef) ** 2, axis=0))
    keep = rms <= MACHINE_LIMIT * motion.floor
    if not keep.any():
        return None
    motion.components = [c for c, k in zip(unseen, keep) if k]
    motion.values, motion.floor = values[:, keep], motion.floor[keep]
    return motion
