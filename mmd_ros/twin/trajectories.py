"""True motion of {U} in {L}: smooth moves between poses, dwells, ISO 230-2 test cycles.

A :class:`Trajectory` is a chain of segments between knot poses. Each segment blends its two
poses with the minimum-jerk quintic s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 (zero velocity and
acceleration at both ends), linearly in the pose coordinates; a dwell is a segment whose two
poses are equal. It can be evaluated at any time, which the twin needs for the latch skew of
each channel. Move durations follow from speed and acceleration limits: the quintic peaks at
1.875 D / T in velocity and 5.774 D / T^2 in acceleration.

The poses are the machine's ACTUAL poses: :class:`MachineErrors` turns a commanded target
into where the machine really stops (positioning, reversal, repeatability, straightness,
angular errors), as a machine under ISO 230-2 test does. This is the one-axis machine of the
runs that evaluate the MMD itself (the paper's sections 5.2-5.3); the five-axis machine tool
with every error motion, squareness and rotary-axis errors, whose errors a machine session
evaluates, is :mod:`mmd_ros.twin.machine`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.twin.errors import TwinError

__all__ = ['AXES', 'MachineErrors', 'MotionLimits', 'TargetSpec', 'Trajectory',
           'TrajectoryBuilder', 'iso_cycle']

FloatArray = NDArray[np.float64]

#: Pose components, Eq. (1).
AXES = ('x', 'y', 'z', 'phi', 'theta', 'psi')
#: Peak velocity and acceleration of the quintic blend per unit distance and duration.
_PEAK_VELOCITY = 1.875
_PEAK_ACCEL = 10.0 / math.sqrt(3.0)
#: For a linear axis: the perpendicular axis that shows its straightness error, and the angle
#: of its angular (pitch) error.
_STRAIGHTNESS_AXIS = {0: 1, 1: 0, 2: 0}
_PITCH_AXIS = {0: 4, 1: 3, 2: 3}


@dataclass(frozen=True)
class MotionLimits:
    """Speed and acceleration limits of the machine's moves."""

    speed_m_per_s: float = 0.05
    accel_m_per_s2: float = 0.2
    angular_speed_rad_per_s: float = math.radians(10.0)
    angular_accel_rad_per_s2: float = math.radians(40.0)

    def __post_init__(self) -> None:
        for name in ('speed_m_per_s', 'accel_m_per_s2', 'angular_speed_rad_per_s',
                     'angular_accel_rad_per_s2'):
            if not getattr(self, name) > 0:
                raise TwinError(f'limits.{name} must be > 0, got {getattr(self, name)}')

    def move_duration_s(self, delta: ArrayLike) -> float:
        """Shortest quintic move over pose change ``delta`` (6,) within the limits [s]."""
        d = np.abs(np.asarray(delta, dtype=np.float64))
        lin, ang = d[:3].max(), d[3:].max()
        return max(_PEAK_VELOCITY * lin / self.speed_m_per_s,
                   math.sqrt(_PEAK_ACCEL * lin / self.accel_m_per_s2),
                   _PEAK_VELOCITY * ang / self.angular_speed_rad_per_s,
                   math.sqrt(_PEAK_ACCEL * ang / self.angular_accel_rad_per_s2))


@dataclass(frozen=True)
class MachineErrors:
    """Where a machine really stops when commanded to a target of one axis.

    Linear axis at position P from the middle of its travel, approached in direction r (+1/-1):
    error along the axis scale_per_m P + r reversal_m / 2 + N(0, repeatability_m); a bow of
    straightness_m in one perpendicular axis; an angular (pitch) error pitch_rad_per_m P.
    Rotary axis at angle A: angular_scale A + r angular_reversal_rad / 2
    + N(0, angular_repeatability_rad).
    """

    scale_per_m: float = 10e-6
    reversal_m: float = 2e-6
    repeatability_m: float = 0.3e-6
    straightness_m: float = 1e-6
    pitch_rad_per_m: float = 2.5e-5
    angular_scale: float = 2e-5
    angular_reversal_rad: float = math.radians(0.5 / 3600.0)
    angular_repeatability_rad: float = math.radians(0.3 / 3600.0)

    @classmethod
    def none(cls) -> MachineErrors:
        """A perfect machine: actual pose = commanded pose."""
        return cls(**{f.name: 0.0 for f in fields(cls)})

    def actual(self, commanded: ArrayLike, axis: int, centre: float, travel: float,
               direction: int, rng: np.random.Generator | None) -> FloatArray:
        """The actual pose for a commanded one (6,) moved along ``axis`` (0..5).

        centre, travel : middle and length of the axis travel [m or rad]
        direction : +1 / -1 approach direction, 0 for no defined approach
        rng : draws the repeatability; None at points that are not targets
        """
        pose = np.array(commanded, dtype=np.float64)
        position = pose[axis] - centre
        noise = 0.0 if rng is None else rng.standard_normal()
        if axis < 3:
            pose[axis] += self.scale_per_m * position + direction * self.reversal_m / 2 \
                + noise * self.repeatability_m
            bow = 1.0 - (2.0 * position / travel) ** 2 if travel > 0 else 0.0
            pose[_STRAIGHTNESS_AXIS[axis]] += self.straightness_m * bow
            pose[_PITCH_AXIS[axis]] += self.pitch_rad_per_m * position
        else:
            pose[axis] += self.angular_scale * pose[axis] + direction * self.angular_reversal_rad / 2 \
                + noise * self.angular_repeatability_rad
        return pose


@dataclass(frozen=True)
class TargetSpec:
    """Targets of an ISO 230-2 run.

    axis : str — pose component moved ('x'...'psi')
    positions : ndarray, shape (n,) — commanded target coordinates [m or rad]
    commanded_poses : ndarray, shape (n, 6) — commanded poses at the targets
    """

    axis: str
    positions: FloatArray
    commanded_poses: FloatArray


@dataclass(frozen=True)
class Trajectory:
    """Poses at knot times and what each segment between them is.

    knots_s : ndarray, shape (K + 1,) — increasing [s]
    poses : ndarray, shape (K + 1, 6) — actual poses at the knots
    target_index : ndarray of int, shape (K,) — target approached or dwelt at, -1 for none
    direction : ndarray of int, shape (K,) — approach direction +1 / -1, 0 for none
    approach : ndarray of int, shape (K,) — cycle number of the approach, -1 for none
    dwell : ndarray of bool, shape (K,) — the segment is a dwell
    duration_s : float — end of the run; the last pose is held after the last knot
    targets : TargetSpec or None
    """

    knots_s: FloatArray
    poses: FloatArray
    target_index: NDArray[np.int64]
    direction: NDArray[np.int64]
    approach: NDArray[np.int64]
    dwell: NDArray[np.bool_]
    duration_s: float
    targets: TargetSpec | None = None

    def _segment(self, t: FloatArray) -> NDArray[np.intp]:
        return np.clip(np.searchsorted(self.knots_s, t, side='right') - 1, 0, self.dwell.size - 1)

    def pose(self, times_s: ArrayLike) -> FloatArray:
        """Actual poses at ``times_s``.

        times_s : array_like, shape (N,) [s]
        returns : ndarray, shape (N, 6) [m, rad]
        """
        t = np.asarray(times_s, dtype=np.float64)
        j = self._segment(t)
        start, span = self.knots_s[j], self.knots_s[j + 1] - self.knots_s[j]
        tau = np.clip((t - start) / span, 0.0, 1.0)
        s = tau ** 3 * (10.0 + tau * (6.0 * tau - 15.0))
        return self.poses[j] + s[:, None] * (self.poses[j + 1] - self.poses[j])

    def labels(self, times_s: ArrayLike) -> dict[str, NDArray]:
        """Per-sample target index, direction, approach and dwell flag (segment labels)."""
        j = self._segment(np.asarray(times_s, dtype=np.float64))
        return {'index': self.target_index[j].astype(np.int16),
                'direction': self.direction[j].astype(np.int8),
                'approach': self.approach[j].astype(np.int16),
                'in_dwell': self.dwell[j]}


@dataclass
class TrajectoryBuilder:
    """Appends moves and dwells to a trajectory that starts at ``start`` (6,)."""

    start: ArrayLike
    limits: MotionLimits
    _knots: list[float] = field(default_factory=lambda: [0.0])
    _poses: list[FloatArray] = field(default_factory=list)
    _labels: list[tuple[int, int, int, bool]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._poses.append(np.array(self.start, dtype=np.float64))

    @property
    def time_s(self) -> float:
        return self._knots[-1]

    @property
    def pose(self) -> FloatArray:
        return self._poses[-1]

    def move(self, pose: ArrayLike, target: int = -1, direction: int = 0, approach: int = -1) -> None:
        """A move to ``pose`` as fast as the limits allow (nothing if already there)."""
        p = np.array(pose, dtype=np.float64)
        duration = self.limits.move_duration_s(p - self._poses[-1])
        if duration > 0:
            self._append(duration, p, (target, direction, approach, False))

    def dwell(self, seconds: float, target: int = -1, direction: int = 0, approach: int = -1) -> None:
        """Stand still for ``seconds``."""
        if seconds > 0:
            self._append(seconds, self._poses[-1], (target, direction, approach, True))

    def _append(self, duration: float, pose: FloatArray, labels: tuple[int, int, int, bool]) -> None:
        self._knots.append(self._knots[-1] + duration)
        self._poses.append(pose)
        self._labels.append(labels)

    def build(self, duration_s: float | None = None, targets: TargetSpec | None = None) -> Trajectory:
        if not self._labels:
            raise TwinError('a trajectory needs at least one move or dwell')
        labels = np.array(self._labels, dtype=np.int64)
        return Trajectory(
            knots_s=np.array(self._knots), poses=np.array(self._poses),
            target_index=labels[:, 0], direction=labels[:, 1], approach=labels[:, 2],
            dwell=labels[:, 3].astype(bool),
            duration_s=self._knots[-1] if duration_s is None else float(duration_s),
            targets=targets)


def iso_cycle(start: ArrayLike, axis: int, positions: ArrayLike, overrun: float, n_cycles: int,
              dwell_s: float, lead_s: float, limits: MotionLimits, machine: MachineErrors,
              rng: np.random.Generator) -> Trajectory:
    """The ISO 230-2 standard test cycle along one pose component.

    From the start pose, run past the first target by ``overrun``; then ``n_cycles`` times:
    approach every target in the positive direction and dwell, overrun the last target, approach
    every target in the negative direction and dwell, overrun the first; then return to the
    start. Every target is thus approached n_cycles times from each side. A dwell of ``lead_s``
    opens and closes the run.

    start : array_like, shape (6,) — commanded start pose
    axis : int — pose component moved (0..5)
    positions : array_like, shape (n,) — commanded target coordinates, increasing [m or rad]
    overrun : float — reversal travel beyond the end targets [m or rad]
    """
    base = np.array(start, dtype=np.float64)
    targets = np.asarray(positions, dtype=np.float64)
    centre = 0.5 * (targets[0] + targets[-1])
    travel = targets[-1] - targets[0]

    def actual(value: float, direction: int, is_target: bool) -> FloatArray:
        pose = base.copy()
        pose[axis] = value
        return machine.actual(pose, axis, centre, travel, direction, rng if is_target else None)

    home = actual(base[axis], 0, False)
    b = TrajectoryBuilder(home, limits)
    b.dwell(lead_s)
    b.move(actual(targets[0] - overrun, -1, False))
    for cycle in range(n_cycles):
        for direction, order in ((+1, range(targets.size)), (-1, range(targets.size - 1, -1, -1))):
            for i in order:
                b.move(actual(targets[i], direction, True), i, direction, cycle)
                b.dwell(dwell_s, i, direction, cycle)
            end = targets[-1] + overrun if direction > 0 else targets[0] - overrun
            b.move(actual(end, direction, False))
    b.move(home)
    b.dwell(lead_s)
    commanded = np.repeat(base[None, :], targets.size, axis=0)
    commanded[:, axis] = targets
    return b.build(targets=TargetSpec(AXES[axis], targets, commanded))
