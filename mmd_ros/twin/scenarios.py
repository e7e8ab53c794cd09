"""What the simulated device is made to do: the experiments of sections 4.1 and 5.

- :class:`IsoLinear`: ISO 230-2 run along x, y or z of {L} (section 5.2): 11 targets over
  200 mm (120 mm along z) around the start pose at 300 mm height, 5 bidirectional cycles.
- :class:`IsoRotary`: ISO 230-2 run of a rotary axis (section 5.3): A (phi 0..15°) or
  C (psi -40..+40°), about the origin of {U}.
- :class:`RandomMotion`: random smooth 6-DOF moves inside the workspace, with dwells.
- :class:`Hold`: the MMD standing still at one pose.
- :class:`ThermalSoak`: the six measuring bars resting on reference pairs (section 4.1: all on
  323 mm pairs of further reference plates) while the room temperature changes.
- :class:`MachineSession`: the MMD bolted into a five-axis machine tool with known geometric
  errors (:mod:`mmd_ros.twin.machine`): the ISO runs of every axis one after the other, with the
  machine's commanded axis values recorded as joint states.

Scenarios are frozen dataclasses in SI units that round-trip through plain dicts
(:meth:`Scenario.to_dict`, :func:`scenario_from_dict`) and accept ``name=value`` assignments
(:func:`make_scenario`). ``build(device)`` gives the motion: a
:class:`~mmd_ros.twin.trajectories.Trajectory` or :class:`RestingBars`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.machine import load_machine
from mmd_ros.twin.codec import assign, from_plain, to_plain
from mmd_ros.twin.errors import TwinError
from mmd_ros.twin.machine import (
    MachineErrorSizes, MachineTrajectory, MachineTruth, MmdSetup, RunPlan, TwinMachine, plan_session,
)
from mmd_ros.twin.mechanism import bar_legs, rotation_matrices, within_workspace
from mmd_ros.twin.trajectories import (
    AXES, MachineErrors, MotionLimits, Trajectory, TrajectoryBuilder, iso_cycle,
)

__all__ = ['HOME_POSE', 'SCENARIOS', 'Hold', 'IsoLinear', 'IsoRotary', 'MachineSession',
           'RandomMotion', 'RestingBars', 'Scenario', 'ThermalSoak', 'make_scenario',
           'scenario_from_dict']

Pose = tuple[float, float, float, float, float, float]

#: Start pose of the paper's runs: upper plate 300 mm above the lower one, no rotation.
HOME_POSE: Pose = (0.0, 0.0, 0.3, 0.0, 0.0, 0.0)
#: Longest run, dwell or lead a scenario may ask for [s]: a week (the paper's longest test, the
#: thermal soak of section 4.1, lasts 20 h). Bounds what one ``mmd simulate`` can write.
MAX_DURATION_S = 7 * 24 * 3600.0
#: Most targets and cycles of an ISO 230-2 run (the standard asks for 5 cycles, and 5 targets
#: per metre of travel at least).
MAX_TARGETS = 1000
MAX_CYCLES = 1000
#: Shortest travel of a linear ISO 230-2 run [m]: the targets must lie well apart compared with
#: the machine's micrometre errors for the dwells to be told apart.
MIN_TRAVEL_M = 1e-3
#: Workspace margins of random waypoints [m], [rad].
_MARGIN_M = 1e-3
_MARGIN_RAD = math.radians(1.0)


@dataclass(frozen=True)
class RestingBars:
    """Bars lying on reference socket pairs instead of moving with the MMD.

    pairs : names of the pairs the six measuring bars rest on, in bar order
    duration_s : length of the run [s]
    """

    pairs: tuple[str, ...]
    duration_s: float


class Scenario:
    """Base of the scenarios: serialisation and the reference instrument it uses by default."""

    kind: ClassVar[str]

    @property
    def default_reference(self) -> str:
        return 'pose6'

    def build(self, device: DeviceDescription) -> Trajectory | RestingBars:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        return {'kind': self.kind, **to_plain(self)}

    def with_assignments(self, assignments: Iterable[str]) -> Scenario:
        return assign(self, assignments)


def _check_duration(kind: str, name: str, value: float, *, zero: bool = False) -> None:
    """A duration of a scenario: finite, > 0 (or >= 0 with ``zero``) and at most a week."""
    low_ok = value >= 0 if zero else value > 0
    if not (low_ok and value <= MAX_DURATION_S):
        raise TwinError(f'{kind}: {name} must be in {"[" if zero else "("}0, {MAX_DURATION_S:g}] s '
                        f'(at most a week), got {value}')


def _check_common(scenario: Any) -> None:
    if not (2 <= scenario.n_targets <= MAX_TARGETS and 1 <= scenario.n_cycles <= MAX_CYCLES):
        raise TwinError(f'{scenario.kind}: needs n_targets in [2, {MAX_TARGETS}] and n_cycles in '
                        f'[1, {MAX_CYCLES}], got {scenario.n_targets} and {scenario.n_cycles}')
    _check_duration(scenario.kind, 'dwell_s', scenario.dwell_s, zero=True)
    _check_duration(scenario.kind, 'lead_s', scenario.lead_s, zero=True)


def _check_travel(kind: str, name: str, travel: float, unit: str, scale: float = 1.0) -> None:
    """The travel of a linear ISO run (``scale`` times it in m): at least MIN_TRAVEL_M, finite."""
    if not (travel * scale >= MIN_TRAVEL_M and math.isfinite(travel)):
        raise TwinError(f'{kind}: {name} must be at least {MIN_TRAVEL_M / scale:g} {unit} (the '
                        'targets must lie well apart compared with the machine\'s micrometre '
                        f'errors), got {travel}')


def _check_overrun(kind: str, name: str, overrun: float, unit: str,
                   travel: float | None = None) -> None:
    """The overrun of an ISO run: > 0 (each end target is approached from beyond it) and, with
    ``travel``, at most the travel (the machine's errors are known over the travel, not far
    beyond it: a bow extrapolated 2 mm past a travel of 0.1 µm moved the machine a kilometre).
    The travel is checked when the run is built: assignments may change both, in any order."""
    if not (overrun > 0 and math.isfinite(overrun)):
        raise TwinError(f'{kind}: {name} must be > 0 {unit} (past the end targets before '
                        f'reversing), got {overrun}')
    if travel is not None and overrun > travel:
        raise TwinError(f'{kind}: {name} must be at most the travel of the run, {travel:g} '
                        f'{unit} (the machine\'s errors are known over its travel), got '
                        f'{overrun:g}')


def _check_seed(kind: str, name: str, seed: int) -> None:
    if seed < 0:
        raise TwinError(f'{kind}: {name} must be an integer >= 0, got {seed}')


def _check_jitter(kind: str, name: str, jitter: float) -> None:
    if not (jitter >= 0 and math.isfinite(jitter)):
        raise TwinError(f'{kind}: {name} must be >= 0 (interior targets move by up to this '
                        f'much), got {jitter}')


@dataclass(frozen=True)
class IsoLinear(Scenario):
    """ISO 230-2 linear positioning run along ``axis`` of {L}, centred on the start pose.

    travel_m : distance from first to last target; None gives 200 mm (x, y) or 120 mm (z)
    target_jitter_m : irregular target spacing as ISO 230-2 recommends: interior targets move by
        up to this much (uniform, drawn from ``seed``); 0 keeps them evenly spaced
    overrun_m : travel beyond the end targets before reversing
    machine : the machine's positioning errors (``MachineErrors.none()`` for a perfect one)
    seed : draws target jitter and the machine's repeatability
    """

    kind: ClassVar[str] = 'iso_linear'
    axis: str = 'x'
    travel_m: float | None = None
    n_targets: int = 11
    n_cycles: int = 5
    dwell_s: float = 0.5
    lead_s: float = 1.0
    overrun_m: float = 2e-3
    target_jitter_m: float = 0.0
    start_pose: Pose = HOME_POSE
    limits: MotionLimits = MotionLimits()
    machine: MachineErrors = MachineErrors()
    seed: int = 0

    def __post_init__(self) -> None:
        if self.axis not in AXES[:3]:
            raise TwinError(f'iso_linear: axis must be x, y or z, got {self.axis!r}')
        _check_common(self)
        _check_travel(self.kind, 'travel_m', self.travel, 'm')
        _check_overrun(self.kind, 'overrun_m', self.overrun_m, 'm')
        _check_jitter(self.kind, 'target_jitter_m', self.target_jitter_m)
        _check_seed(self.kind, 'seed', self.seed)

    @property
    def travel(self) -> float:
        """Distance from the first to the last target [m] (travel_m or the axis's default)."""
        return self.travel_m if self.travel_m is not None else (0.12 if self.axis == 'z' else 0.2)

    @property
    def default_reference(self) -> str:
        return f'laser_{self.axis}'

    def build(self, device: DeviceDescription) -> Trajectory:
        axis = AXES.index(self.axis)
        travel = self.travel
        _check_overrun(self.kind, 'overrun_m', self.overrun_m, 'm', travel)
        positions = self.start_pose[axis] + np.linspace(-travel / 2, travel / 2, self.n_targets)
        jitter = np.random.default_rng([self.seed, 1]).uniform(-1.0, 1.0, self.n_targets)
        jitter[[0, -1]] = 0.0
        positions = positions + self.target_jitter_m * jitter
        if np.any(np.diff(positions) <= 0):
            spacing = travel / (self.n_targets - 1)
            raise TwinError(f'iso_linear: target_jitter_m ({self.target_jitter_m:g} m) is too '
                            f'large for the target spacing ({spacing:g} m): targets would swap '
                            'places; keep it below half the spacing')
        return iso_cycle(self.start_pose, axis, positions, self.overrun_m, self.n_cycles,
                         self.dwell_s, self.lead_s, self.limits, self.machine,
                         np.random.default_rng([self.seed, 2]))


_ROTARY_SPAN = {'phi': (0.0, 15.0), 'theta': (-10.0, 10.0), 'psi': (-40.0, 40.0)}


@dataclass(frozen=True)
class IsoRotary(Scenario):
    """ISO 230-2 angular positioning run of ``axis`` (phi = A, theta = B, psi = C) about the
    origin of {U}.

    first_rad, last_rad : first and last target; None gives the paper's spans: phi 0..15°,
        psi -40..+40° (theta -10..+10°)
    """

    kind: ClassVar[str] = 'iso_rotary'
    axis: str = 'psi'
    first_rad: float | None = None
    last_rad: float | None = None
    n_targets: int = 11
    n_cycles: int = 5
    dwell_s: float = 0.5
    lead_s: float = 1.0
    overrun_rad: float = math.radians(0.5)
    start_pose: Pose = HOME_POSE
    limits: MotionLimits = MotionLimits()
    machine: MachineErrors = MachineErrors()
    seed: int = 0

    def __post_init__(self) -> None:
        if self.axis not in AXES[3:]:
            raise TwinError(f'iso_rotary: axis must be phi, theta or psi, got {self.axis!r}')
        _check_common(self)
        _check_overrun(self.kind, 'overrun_rad', self.overrun_rad, 'rad')
        _check_seed(self.kind, 'seed', self.seed)

    @property
    def default_reference(self) -> str:
        return f'rotary_{self.axis}'

    def build(self, device: DeviceDescription) -> Trajectory:
        axis = AXES.index(self.axis)
        first = self.first_rad if self.first_rad is not None else math.radians(_ROTARY_SPAN[self.axis][0])
        last = self.last_rad if self.last_rad is not None else math.radians(_ROTARY_SPAN[self.axis][1])
        if not last > first:
            raise TwinError(f'iso_rotary: last_rad must exceed first_rad, got {first} and {last}')
        return iso_cycle(self.start_pose, axis, np.linspace(first, last, self.n_targets),
                         self.overrun_rad, self.n_cycles, self.dwell_s, self.lead_s, self.limits,
                         self.machine, np.random.default_rng([self.seed, 2]))


@dataclass(frozen=True)
class Hold(Scenario):
    """The MMD standing still at ``pose`` for ``duration_s``."""

    kind: ClassVar[str] = 'hold'
    duration_s: float = 10.0
    pose: Pose = HOME_POSE

    def build(self, device: DeviceDescription) -> Trajectory:
        _check_duration(self.kind, 'duration_s', self.duration_s)
        builder = TrajectoryBuilder(self.pose, MotionLimits())
        builder.dwell(self.duration_s)
        return builder.build()


@dataclass(frozen=True)
class RandomMotion(Scenario):
    """Random smooth 6-DOF moves around ``centre_pose``, each followed by a random dwell.

    radius_m : waypoints lie in a ball of this radius around the centre position
    max_angle_rad : and within +-this of the centre angles, each angle independently
    dwell_s : longest dwell after a move (each uniform in [0, dwell_s])
    seed : draws the waypoints
    """

    kind: ClassVar[str] = 'random_motion'
    duration_s: float = 60.0
    centre_pose: Pose = HOME_POSE
    radius_m: float = 0.05
    max_angle_rad: float = math.radians(5.0)
    dwell_s: float = 0.5
    limits: MotionLimits = MotionLimits()
    seed: int = 0

    def __post_init__(self) -> None:
        for name, unit in (('radius_m', 'm'), ('max_angle_rad', 'rad')):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise TwinError(f'random_motion: {name} must be >= 0 {unit}, got {value}')
        _check_duration(self.kind, 'dwell_s', self.dwell_s, zero=True)
        _check_seed(self.kind, 'seed', self.seed)

    def build(self, device: DeviceDescription) -> Trajectory:
        _check_duration(self.kind, 'duration_s', self.duration_s)
        if self.radius_m == 0 and self.max_angle_rad == 0:
            raise TwinError('random_motion: radius_m and max_angle_rad are both 0: nothing would '
                            'move; use the hold scenario to stand still')
        rng = np.random.default_rng(self.seed)
        geo = device.measured_geometry
        centre = np.array(self.centre_pose, dtype=np.float64)
        path = np.linspace(0.0, 1.0, 17)[:, None]
        builder = TrajectoryBuilder(centre, self.limits)
        while builder.time_s < self.duration_s:
            for _ in range(200):
                direction = rng.standard_normal(3)
                offset = direction / np.linalg.norm(direction) * self.radius_m * rng.uniform() ** (1 / 3)
                angles = rng.uniform(-self.max_angle_rad, self.max_angle_rad, 3)
                candidate = centre + np.concatenate([offset, angles])
                poses = builder.pose + path * (candidate - builder.pose)
                rot = rotation_matrices(poses)
                if within_workspace(device, bar_legs(geo.upper, geo.lower, poses, rot), rot,
                                    _MARGIN_M, _MARGIN_RAD).all():
                    break
            else:
                raise TwinError('random_motion: no reachable waypoint in 200 draws; '
                                'reduce radius_m or max_angle_rad, or move centre_pose')
            builder.move(candidate)
            builder.dwell(rng.uniform(0.0, self.dwell_s))
        return builder.build(duration_s=self.duration_s)


@dataclass(frozen=True)
class ThermalSoak(Scenario):
    """Section 4.1: the six measuring bars rest on reference pairs (``pairs``, in bar order)
    while the room temperature changes; the reference bar rests on its own pair."""

    kind: ClassVar[str] = 'thermal_soak'
    duration_s: float = 20 * 3600.0
    pairs: tuple[str, ...] = ('dr4',) * 6

    @property
    def default_reference(self) -> str:
        return 'bar_lengths'

    def build(self, device: DeviceDescription) -> RestingBars:
        names = [p.name for p in device.pairs]
        if len(self.pairs) != 6 or any(p not in names for p in self.pairs):
            raise TwinError(f'thermal_soak: pairs must name six reference pairs of {names}, '
                            f'got {list(self.pairs)}')
        _check_duration(self.kind, 'duration_s', self.duration_s)
        return RestingBars(tuple(self.pairs), float(self.duration_s))


#: Default spans of the rotary runs [deg], as far as the MMD reaches with the linear axes
#: following (``mmd workspace``: at the home pose, 300 mm between the plates, it turns up to
#: 66° about z alone and tilts up to 21° about x or y alone). C over ±60° (the paper's ±40°
#: leaves the axis line's position uncertain to about 2.7 µm, ±60° to 1.5 µm: over a partial
#: turn the location is told from the component errors only by the span); A over ±15° (the
#: tilt range, less the plates' misalignment, the reversal overrun and a margin; the following
#: moves Y by ±90 mm, inside the Y run); B within the MMD's tilt range.
ROTARY_SPANS_DEG = {'A': (-15.0, 15.0), 'B': (-10.0, 10.0), 'C': (-60.0, 60.0)}


@dataclass(frozen=True)
class MachineSession(Scenario):
    """The MMD in a five-axis machine tool: the ISO 230-2 standard test cycle of each axis in
    ``runs`` (the order a metrologist uses: the linear axes first, which fix the machine's frame
    and squareness, then the rotary table flat (C), then the tilting axis), from the reference
    position of the machine description. During a rotary run the linear axes follow so that
    the tool point stays on the same workpiece point (R-test style), which keeps the MMD in its
    workspace. The machine's commanded axis values are recorded as joint states.

    machine_file : machine description (config/ or a path)
    linear_travel_mm : (X and Y, Z) travel of the linear runs, centred on the reference
    rotary_spans_deg : 'A:0:15' style spans of the rotary runs (defaults: A ±15, B ±10, C ±60)
    target_jitter_mm : irregular target spacing as ISO 230-2 recommends (interior targets move by
        up to this much)
    errors : the machine's errors (sizes, seed, errors switched off)
    setup_seed, misalignment_deg, offset_mm : how the plates are bolted (drawn)
    follow_targets : add the linear axes' positions during a rotary run (those the following
        visits, and the reference of an axis that stays put) to their own runs' targets (as a
        metrologist does, so that the rotary analysis needs no interpolation of the linear
        errors)
    """

    kind: ClassVar[str] = 'machine_session'
    machine_file: str = 'machine_xyzac.yaml'
    runs: tuple[str, ...] = ('X', 'Y', 'Z', 'C', 'A')
    linear_travel_mm: tuple[float, float] = (200.0, 120.0)
    rotary_spans_deg: tuple[str, ...] = ()
    n_linear_targets: int = 11
    n_rotary_targets: int = 9
    n_cycles: int = 5
    dwell_s: float = 0.5
    lead_s: float = 1.0
    overrun_mm: float = 2.0
    overrun_deg: float = 0.5
    target_jitter_mm: float = 0.0
    speed_mm_per_s: float = 100.0
    accel_mm_per_s2: float = 1000.0
    angular_speed_deg_per_s: float = 20.0
    angular_accel_deg_per_s2: float = 80.0
    errors: MachineErrorSizes = MachineErrorSizes()
    setup_seed: int = 0
    misalignment_deg: float = 0.3
    offset_mm: float = 5.0
    follow: bool = True
    follow_targets: bool = True

    def __post_init__(self) -> None:
        if self.n_linear_targets < 3 or self.n_rotary_targets < 3 or self.n_cycles < 1:
            raise TwinError('machine_session: needs n_linear_targets >= 3, n_rotary_targets >= 3 '
                            'and n_cycles >= 1')
        if self.dwell_s <= 0 or self.lead_s < 0:
            raise TwinError('machine_session: dwell_s must be > 0 and lead_s >= 0')
        if not self.runs:
            raise TwinError('machine_session: runs must name at least one axis')
        for travel in self.linear_travel_mm:
            _check_travel(self.kind, 'linear_travel_mm', travel, 'mm', 1e-3)
        _check_overrun(self.kind, 'overrun_mm', self.overrun_mm, 'mm')
        _check_overrun(self.kind, 'overrun_deg', self.overrun_deg, 'deg')
        _check_jitter(self.kind, 'target_jitter_mm', self.target_jitter_mm)
        _check_seed(self.kind, 'setup_seed', self.setup_seed)

    @property
    def default_reference(self) -> str:
        return 'pose6'

    def spans(self) -> dict[str, tuple[float, float]]:
        """Rotary spans [rad] by axis name."""
        out = {k: (math.radians(a), math.radians(b)) for k, (a, b) in ROTARY_SPANS_DEG.items()}
        for item in self.rotary_spans_deg:
            try:
                name, lo, hi = item.split(':')
                out[name.strip().upper()] = (math.radians(float(lo)), math.radians(float(hi)))
            except ValueError:
                raise TwinError(f'machine_session: rotary_spans_deg entries look like A:0:15, '
                                f'got {item!r}') from None
        return out

    def plans(self, machine: Any) -> list[RunPlan]:
        """The runs: axis, targets, cycles, overrun, following."""
        _check_overrun(self.kind, 'overrun_mm', self.overrun_mm, 'mm', min(self.linear_travel_mm))
        spans = self.spans()
        rng = np.random.default_rng([self.errors.seed, 14])
        extra = self._following_positions(machine, spans) if self.follow_targets else {}
        out = []
        for name in self.runs:
            try:
                axis = machine.axis(name)
            except Exception as exc:
                raise TwinError(f'machine_session: runs: {exc}') from None
            if axis.rotary:
                if axis.name not in spans:
                    raise TwinError(f'machine_session: no span for rotary axis {axis.name}; give '
                                    f'rotary_spans_deg={axis.name}:LOW:HIGH')
                lo, hi = spans[axis.name]
                targets = np.linspace(lo, hi, self.n_rotary_targets)
                out.append(RunPlan(axis.name, targets, self.n_cycles, math.radians(self.overrun_deg),
                                   self.follow))
            else:
                travel = (self.linear_travel_mm[1] if axis.component == 2 else self.linear_travel_mm[0]) * 1e-3
                targets = axis.reference + np.linspace(-travel / 2, travel / 2, self.n_linear_targets)
                jitter = rng.uniform(-1.0, 1.0, targets.size) * self.target_jitter_mm * 1e-3
                jitter[[0, -1]] = 0.0
                jitter[np.argmin(np.abs(targets - axis.reference))] = 0.0  # keep the reference
                targets = targets + jitter
                if np.any(np.diff(targets) <= 0):
                    spacing_mm = travel * 1e3 / (self.n_linear_targets - 1)
                    raise TwinError(f'machine_session: target_jitter_mm ({self.target_jitter_mm:g})'
                                    f' is too large for the spacing of the {axis.name} targets '
                                    f'({spacing_mm:g} mm): targets would swap places; keep it '
                                    'below half the spacing')
                for value in extra.get(axis.name, []):   # (within 1 mm of a target: that one)
                    if np.min(np.abs(targets - value)) > 1e-3 and targets[0] <= value <= targets[-1]:
                        targets = np.sort(np.append(targets, value))
                out.append(RunPlan(axis.name, targets, self.n_cycles, self.overrun_mm * 1e-3, False))
        return out

    def _following_positions(self, machine: Any, spans: dict[str, tuple[float, float]]
                             ) -> dict[str, list[float]]:
        """Linear axis values the rotary runs' following visits at their targets."""
        out: dict[str, list[float]] = {}
        if not self.follow:
            return out
        nominal = TwinMachine(machine)
        for name in self.runs:
            axis = machine.axis(name)
            if not axis.rotary or axis.name not in spans:
                continue
            k = machine.index(axis.name)
            q = np.tile(machine.reference, (self.n_rotary_targets, 1))
            q[:, k] = np.linspace(*spans[axis.name], self.n_rotary_targets)
            q = nominal.follow(q)
            for a in machine.linear_axes:
                j = machine.index(a.name)
                # every value, the reference too: an axis that stays put still turns the
                # following axes' motion by its angular errors there
                out.setdefault(a.name, []).extend(float(v) for v in np.unique(q[:, j]))
        return out

    def machine(self) -> TwinMachine:
        """The twin's machine of this session: description, drawn errors, drawn setup."""
        description = load_machine(self.machine_file)
        plans = self.plans(description)
        travel = {p.axis: (float(p.targets[0]), float(p.targets[-1])) for p in plans}
        truth = MachineTruth.draw(description, self.errors, travel, {p.axis: p.targets for p in plans})
        setup = MmdSetup.draw(description, self.setup_seed, misalignment_deg=self.misalignment_deg,
                              offset_mm=self.offset_mm)
        return TwinMachine(description, truth, setup)

    def build(self, device: DeviceDescription) -> MachineTrajectory:
        machine = self.machine()
        return plan_session(machine, self.plans(machine.machine), dwell_s=self.dwell_s,
                            lead_s=self.lead_s, speed=self.speed_mm_per_s * 1e-3,
                            accel=self.accel_mm_per_s2 * 1e-3,
                            angular_speed=math.radians(self.angular_speed_deg_per_s),
                            angular_accel=math.radians(self.angular_accel_deg_per_s2),
                            seed=self.errors.seed)


SCENARIOS: dict[str, type[Scenario]] = {
    cls.kind: cls for cls in (Hold, IsoLinear, IsoRotary, MachineSession, RandomMotion, ThermalSoak)}


def scenario_from_dict(data: Any) -> Scenario:
    """The scenario a :meth:`Scenario.to_dict` mapping describes (``kind`` names the class)."""
    if not isinstance(data, dict) or data.get('kind') not in SCENARIOS:
        raise TwinError(f'a scenario needs kind: one of {sorted(SCENARIOS)}, got {data!r}')
    params = {k: v for k, v in data.items() if k != 'kind'}
    return from_plain(SCENARIOS[data['kind']], params, f'{data["kind"]}.')


def make_scenario(kind: str, assignments: Iterable[str] = ()) -> Scenario:
    """Scenario ``kind`` with its defaults changed by ``name=value`` assignments."""
    if kind not in SCENARIOS:
        raise TwinError(f'unknown scenario {kind!r}; choose one of {sorted(SCENARIOS)}')
    return SCENARIOS[kind]().with_assignments(assignments)
