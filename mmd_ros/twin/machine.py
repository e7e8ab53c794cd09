"""The machine tool the twin's MMD is bolted into, with known geometric errors as its truth.

Written independently of :mod:`mmd_ros.machine` (the analysis), which never reads this truth:
only the tests compare the two. The machine is a :class:`~mmd_ros.core.machine.MachineDescription`
(axes, chains, pivots) plus :class:`MachineTruth`:

- every linear axis: positioning, two straightness and three angular error motions as smooth
  functions of its position (polynomial and periodic parts), a reversal (a play operator that
  takes up over ``play_travel``), and a repeatability drawn at each approach;
- squareness of the linear axes (EC0Y, EB0Z, EA0Z: X is the reference, Y lies in the xy plane);
- every rotary axis: location errors of its axis line (two positions at its pivot, two
  orientations), angular positioning error (scale and harmonics), reversal, repeatability, and
  component error motions (radial, axial, tilt) made of harmonics 2 and 3 of the angle, so that
  over a full turn the axis average line is exactly the located line.

Sign convention (as the analysis, ``msg_docs/machine.md``): an error motion is the error of the
TOOL relative to the WORKPIECE in machine coordinates, whichever side carries the axis; a
table-carried axis moves its carriage by the inverse. Linear error motions act about the
functional point at the reference position (a point fixed to the carriage), rotary component
errors about the axis' pivot; all error functions are zero at the reference position except the
rotary component harmonics.

The kinematic chain here uses 4×4 homogeneous transforms and scipy rotations; the MMD sees the
pose of {U} (on the spindle) in {L} (on the table) through setup transforms drawn by
:class:`MmdSetup` (the plates are never bolted exactly square).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from mmd_ros.core.machine import MachineDescription
from mmd_ros.twin.errors import TwinError

__all__ = ['MachineErrorSizes', 'MachineTruth', 'MachineTrajectory', 'MmdSetup', 'SmoothError',
           'TwinMachine', 'iso_names', 'plan_session']

FloatArray = NDArray[np.float64]

ARCSEC = math.pi / 180.0 / 3600.0
UM = 1e-6
_XYZ, _ABC = 'XYZ', 'ABC'


def iso_names(axis: str, component: int, rotary: bool) -> dict[str, Any]:
    """ISO 230-1/-7 names of an axis' errors.

    returns : {'translation': [3 names], 'rotation': [3 names], 'location': {name: (kind, j)}}
        where translation j / rotation j is along / about machine x, y, z; location lists the
        rotary axis' position (kind 'position') and orientation ('orientation') errors
    """
    out = {'translation': [f'E{_XYZ[j]}{axis}' for j in range(3)],
           'rotation': [f'E{_ABC[j]}{axis}' for j in range(3)], 'location': {}}
    if rotary:
        for j in range(3):
            if j != component:
                out['location'][f'E{_XYZ[j]}0{axis}'] = ('position', j)
        for j in range(3):
            if j != component:
                out['location'][f'E{_ABC[j]}0{axis}'] = ('orientation', j)
    return out


@dataclass(frozen=True)
class MachineErrorSizes:
    """Sizes of the drawn errors (ranges over the tested travel unless said otherwise), a seed,
    and errors switched off by ISO name (e.g. ``EX0C``, ``EYX``, ``EC0Y``, ``ECC``, or ``BX`` for
    the X axis' reversal). ``period_fraction``: period of the linear axes' periodic errors as a
    fraction of the tested travel (a target spacing well below half of it resolves them)."""

    positioning_um: float = 2.0
    straightness_um: float = 2.5
    angular_arcsec: float = 5.0
    periodic_um: float = 0.3
    reversal_um: float = 1.0
    repeatability_um: float = 0.1
    squareness_arcsec: float = 6.0
    location_um: float = 12.0
    orientation_arcsec: float = 12.0
    rotary_positioning_arcsec: float = 5.0
    rotary_reversal_arcsec: float = 2.0
    rotary_repeatability_arcsec: float = 0.1
    radial_um: float = 0.3
    tilt_arcsec: float = 0.5
    period_fraction: float = 0.4
    play_travel_mm: float = 0.02
    rotary_play_travel_deg: float = 0.005
    seed: int = 0
    switch_off: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for f in ('repeatability_um', 'rotary_repeatability_arcsec', 'play_travel_mm',
                  'rotary_play_travel_deg'):
            if getattr(self, f) < 0:
                raise TwinError(f'machine errors: {f} must be >= 0')
        if self.seed < 0:
            raise TwinError(f'machine errors: seed must be an integer >= 0, got {self.seed}')


@dataclass(frozen=True)
class SmoothError:
    """f(q) = sum_k c_k u^k + sum_j a_j sin(2 pi q / period_j + phase_j) - f(q_ref) - (g0 + g1 u).

    u = (q - centre) / half [q in m or rad]; the line g0 + g1 u is removed when the function is
    a straightness (no slope over the tested travel: the slope of an axis is its squareness).
    """

    centre: float
    half: float
    coeffs: tuple[float, ...] = ()
    amplitudes: tuple[float, ...] = ()
    periods: tuple[float, ...] = ()
    phases: tuple[float, ...] = ()
    line: tuple[float, float] = (0.0, 0.0)
    reference: float = 0.0

    def raw(self, q: ArrayLike) -> FloatArray:
        q = np.asarray(q, dtype=np.float64)
        u = (q - self.centre) / self.half
        out = np.zeros_like(q)
        for k, c in enumerate(self.coeffs, start=1):
            out = out + c * u ** k
        for a, p, ph in zip(self.amplitudes, self.periods, self.phases):
            out = out + a * np.sin(2 * np.pi * q / p + ph)
        return out - (self.line[0] + self.line[1] * u)

    def __call__(self, q: ArrayLike) -> FloatArray:
        return self.raw(q) - float(self.raw(np.array(self.reference)))

    @staticmethod
    def zero() -> SmoothError:
        return SmoothError(0.0, 1.0)

    @classmethod
    def draw(cls, rng: np.random.Generator, centre: float, half: float, reference: float,
             size: float, periodic: float, period: float, *, degree: int = 3,
             straightness: bool = False, samples: FloatArray | None = None) -> SmoothError:
        """A function whose range over [centre - half, centre + half] is ``size`` plus a periodic
        part of amplitude ``periodic`` and period about ``period``. A straightness has its
        least-squares line over ``samples`` (the run's targets; default the whole travel)
        removed: that line would be squareness, which the truth keeps apart."""
        if size == 0 and periodic == 0:
            return cls(centre, half, reference=reference)
        coeffs = tuple(rng.normal(0.0, 1.0, degree))
        u = np.linspace(-1.0, 1.0, 201)
        q = centre + half * u
        vals = cls(centre, half, coeffs, reference=reference).raw(q)
        scale = size / max(float(np.ptp(vals)), 1e-300)
        amps, periods, phases = (), (), ()
        if periodic > 0:
            amps = (periodic,)
            periods = (period * rng.uniform(0.8, 1.25),)
            phases = (rng.uniform(0, 2 * np.pi),)
        f = cls(centre, half, tuple(c * scale for c in coeffs), amps, periods, phases, (0.0, 0.0), reference)
        if straightness:
            at = q if samples is None else np.asarray(samples, dtype=np.float64)
            g1, g0 = np.polyfit((at - centre) / half, f.raw(at), 1)
            f = replace(f, line=(float(g0), float(g1)))
        return f


@dataclass(frozen=True)
class Harmonics:
    """sum_n a_n cos(n theta) + b_n sin(n theta) for n in ``orders`` (rotary component errors)."""

    orders: tuple[int, ...] = ()
    cos: tuple[float, ...] = ()
    sin: tuple[float, ...] = ()

    def __call__(self, theta: ArrayLike) -> FloatArray:
        t = np.asarray(theta, dtype=np.float64)
        out = np.zeros_like(t)
        for n, a, b in zip(self.orders, self.cos, self.sin):
            out = out + a * np.cos(n * t) + b * np.sin(n * t)
        return out

    @classmethod
    def draw(cls, rng: np.random.Generator, size: float, orders: tuple[int, ...] = (2, 3)) -> Harmonics:
        if size == 0:
            return cls()
        amp = rng.normal(0.0, 1.0, (len(orders), 2))
        amp *= size / max(float(np.sqrt((amp ** 2).sum())), 1e-300)
        return cls(orders, tuple(amp[:, 0]), tuple(amp[:, 1]))


@dataclass(frozen=True)
class LinearAxisTruth:
    """Errors of one linear axis: translation[j], rotation[j] along/about machine x, y, z (the
    one along the axis is its positioning error; the angular ones are zero at the reference)."""

    translation: tuple[SmoothError, SmoothError, SmoothError]
    rotation: tuple[SmoothError, SmoothError, SmoothError]
    reversal: float          # x̄↑ - x̄↓ of the positioning [m]
    repeatability: float     # standard deviation of an approach [m]
    play_travel: float       # travel over which the reversal takes up [m]


@dataclass(frozen=True)
class RotaryAxisTruth:
    """Errors of one rotary axis: location (position offsets [m] of the line at the pivot along
    machine x, y, z and orientation [rad] about x, y, z; the components along / about the axis
    are zero), angular positioning error (a smooth function of the angle), reversal,
    repeatability, and component harmonics: translation[j] at the pivot, rotation[j] about x, y,
    z (the one about the axis is zero: that is the positioning error)."""

    position: FloatArray
    orientation: FloatArray
    positioning: SmoothError
    reversal: float
    repeatability: float
    play_travel: float
    translation: tuple[Harmonics, Harmonics, Harmonics]
    rotation: tuple[Harmonics, Harmonics, Harmonics]


@dataclass(frozen=True)
class MachineTruth:
    """The machine's errors: per axis truth and the squareness of the linear axes [rad]."""

    linear: dict[str, LinearAxisTruth]
    rotary: dict[str, RotaryAxisTruth]
    squareness: dict[str, float]   # 'EC0Y', 'EB0Z', 'EA0Z' (keys use the axis names)

    @classmethod
    def draw(cls, machine: MachineDescription, sizes: MachineErrorSizes,
             travel: dict[str, tuple[float, float]],
             targets: dict[str, FloatArray] | None = None) -> MachineTruth:
        """Errors of the given sizes over the tested ``travel`` (axis name -> (low, high));
        straightness without a least-squares slope over the runs' ``targets``."""
        rng = np.random.default_rng([sizes.seed, 11])
        off = {s.upper() for s in sizes.switch_off}
        linear: dict[str, LinearAxisTruth] = {}
        rotary: dict[str, RotaryAxisTruth] = {}
        for axis in machine.axes:
            lo, hi = travel.get(axis.name, axis.travel)
            centre, half = 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9)
            names = iso_names(axis.name, axis.component, axis.rotary)
            if not axis.rotary:
                trans, rot = [], []
                for j in range(3):
                    along = j == axis.component
                    size = (sizes.positioning_um if along else sizes.straightness_um) * UM
                    f = SmoothError.draw(rng, centre, half, axis.reference, size,
                                         sizes.periodic_um * UM, sizes.period_fraction * 2 * half,
                                         straightness=not along,
                                         samples=(targets or {}).get(axis.name))
                    trans.append(SmoothError.zero() if names['translation'][j] in off else f)
                for j in range(3):
                    f = SmoothError.draw(rng, centre, half, axis.reference,
                                         sizes.angular_arcsec * ARCSEC, 0.1 * sizes.angular_arcsec * ARCSEC,
                                         sizes.period_fraction * 2 * half, degree=2)
                    rot.append(SmoothError.zero() if names['rotation'][j] in off else f)
                rev_name = f'B{axis.name}'
                linear[axis.name] = LinearAxisTruth(
                    tuple(trans), tuple(rot),
                    0.0 if rev_name in off else sizes.reversal_um * UM * rng.uniform(0.5, 1.0) * rng.choice([-1, 1]),
                    sizes.repeatability_um * UM, sizes.play_travel_mm * 1e-3)
            else:
                position = np.zeros(3)
                orientation = np.zeros(3)
                for name, (kind, j) in names['location'].items():
                    if name in off:
                        continue
                    if kind == 'position':
                        position[j] = sizes.location_um * UM * rng.uniform(0.5, 1.0) * rng.choice([-1, 1])
                    else:
                        orientation[j] = sizes.orientation_arcsec * ARCSEC * rng.uniform(0.5, 1.0) * rng.choice([-1, 1])
                positioning = SmoothError.draw(rng, centre, half, axis.reference,
                                               sizes.rotary_positioning_arcsec * ARCSEC,
                                               0.1 * sizes.rotary_positioning_arcsec * ARCSEC,
                                               math.radians(30.0), degree=2)
                if names['rotation'][axis.component] in off:
                    positioning = SmoothError.zero()
                trans = tuple(Harmonics() if names['translation'][j] in off
                              else Harmonics.draw(rng, sizes.radial_um * UM) for j in range(3))
                rot = tuple(Harmonics() if j == axis.component or names['rotation'][j] in off
                            else Harmonics.draw(rng, sizes.tilt_arcsec * ARCSEC) for j in range(3))
                rev_name = f'B{axis.name}'
                rotary[axis.name] = RotaryAxisTruth(
                    position, orientation, positioning,
                    0.0 if rev_name in off else sizes.rotary_reversal_arcsec * ARCSEC * rng.uniform(0.5, 1.0) * rng.choice([-1, 1]),
                    sizes.rotary_repeatability_arcsec * ARCSEC,
                    math.radians(sizes.rotary_play_travel_deg), trans, rot)
        squareness = {}
        lin = {a.component: a.name for a in machine.linear_axes}
        for key in (f'EC0{lin[1]}', f'EB0{lin[2]}', f'EA0{lin[2]}'):
            squareness[key] = 0.0 if key in off else \
                sizes.squareness_arcsec * ARCSEC * rng.uniform(0.5, 1.0) * rng.choice([-1, 1])
        return cls(linear, rotary, squareness)


@dataclass(frozen=True)
class MmdSetup:
    """How the plates actually sit: {L} on the table and {U} on the spindle.

    lower_offset : ndarray, shape (3,) — {L} origin minus its nominal position [m]
    lower_rotation : ndarray, shape (3,) — rotation vector of {L} against its nominal [rad]
    upper_offset : ndarray, shape (3,) — {U} origin minus its nominal offset [m]
    upper_rotation : ndarray, shape (3,) — rotation vector of {U} in the spindle frame [rad]
    """

    lower_offset: FloatArray
    lower_rotation: FloatArray
    upper_offset: FloatArray
    upper_rotation: FloatArray

    @classmethod
    def draw(cls, machine: MachineDescription, seed: int, *, misalignment_deg: float = 0.3,
             offset_mm: float = 5.0) -> MmdSetup:
        rng = np.random.default_rng([seed, 12])
        return cls(
            lower_offset=np.append(rng.uniform(-offset_mm, offset_mm, 2) * 1e-3, 0.0),
            lower_rotation=np.radians(rng.uniform(-misalignment_deg, misalignment_deg, 3)),
            upper_offset=rng.normal(0.0, machine.upper_offset_uncertainty, 3),
            upper_rotation=np.radians(rng.uniform(-misalignment_deg, misalignment_deg, 3)))

    @classmethod
    def exact(cls) -> MmdSetup:
        z = np.zeros(3)
        return cls(z, z, z, z)


def _transform(rot: FloatArray, trans: FloatArray) -> FloatArray:
    """Homogeneous transforms from rotations (N, 3, 3) and translations (N, 3): (N, 4, 4)."""
    n = rot.shape[0]
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = trans
    out[:, 3, 3] = 1.0
    return out


def _inverse(t: FloatArray) -> FloatArray:
    rt = np.swapaxes(t[:, :3, :3], 1, 2)
    return _transform(rt, -np.einsum('nij,nj->ni', rt, t[:, :3, 3]))


def _about(rotvec: FloatArray, point: FloatArray, shift: FloatArray) -> FloatArray:
    """Rotate by ``rotvec`` (N, 3) about ``point`` (N, 3) or (3,), then translate by ``shift``."""
    rot = Rotation.from_rotvec(rotvec).as_matrix()
    point = np.broadcast_to(point, rotvec.shape)
    return _transform(rot, point - np.einsum('nij,nj->ni', rot, point) + shift)


class TwinMachine:
    """The machine's true kinematics: axis values → pose of the tool in the workpiece frame, and
    the pose of {U} in {L} that the MMD sees.

    machine : the nominal description
    truth : the errors (None: a perfect machine)
    setup : where the plates sit (None: exactly as described)
    """

    def __init__(self, machine: MachineDescription, truth: MachineTruth | None = None,
                 setup: MmdSetup | None = None) -> None:
        self.machine = machine
        self.truth = truth
        self.setup = setup or MmdSetup.exact()
        self.names = machine.axis_names
        self.fp = machine.functional_point

    # -- chain ---------------------------------------------------------------------------------
    def _direction(self, axis: Any) -> FloatArray:
        """Actual direction of a linear axis with its squareness (X reference, Y in xy)."""
        d = axis.direction.copy()
        if self.truth is None:
            return d
        sq = self.truth.squareness
        rotvec = np.zeros(3)
        if axis.component == 1:
            rotvec[2] = sq.get(f'EC0{axis.name}', 0.0)
        elif axis.component == 2:
            rotvec[0] = sq.get(f'EA0{axis.name}', 0.0)
            rotvec[1] = sq.get(f'EB0{axis.name}', 0.0)
        # rotate about x first, then y (d = (EB0Z, -EA0Z, 1) to first order)
        r = Rotation.from_rotvec([0.0, rotvec[1], 0.0]) * Rotation.from_rotvec([rotvec[0], 0.0, 0.0]) \
            * Rotation.from_rotvec([0.0, 0.0, rotvec[2]])
        return r.apply(d)

    def _axis_transform(self, k: int, q: FloatArray, play: FloatArray, noise: FloatArray) -> FloatArray:
        """Transform of axis k's carriage in its parent frame at values q (N,), (N, 4, 4)."""
        axis = self.machine.axes[k]
        s = 1.0 if axis.side == 'tool' else -1.0
        n = q.size
        dq = q - axis.reference
        if not axis.rotary:
            t = self.truth.linear[axis.name] if self.truth else None
            d = self._direction(axis)
            eff = dq.copy()
            trans = np.zeros((n, 3))
            rot = np.zeros((n, 3))
            if t is not None:
                for j in range(3):
                    if j == axis.component:
                        eff = eff + t.translation[j](q) * abs(axis.direction[j]) / axis.direction[j]
                    else:
                        trans[:, j] = t.translation[j](q)
                    rot[:, j] = t.rotation[j](q)
                eff = eff + 0.5 * t.reversal * play + noise
            move = _transform(np.broadcast_to(np.eye(3), (n, 3, 3)), s * eff[:, None] * d)
            err = _about(rot, self.fp, trans)
            if s < 0:
                err = _inverse(err)
            return move @ err
        t = self.truth.rotary[axis.name] if self.truth else None
        d = axis.direction
        c = axis.pivot.copy()
        angle = dq.copy()
        comp_t = np.zeros((n, 3))
        comp_r = np.zeros((n, 3))
        if t is not None:
            c = c + t.position
            d = Rotation.from_rotvec(t.orientation).apply(d)
            angle = angle + t.positioning(q) + 0.5 * t.reversal * play + noise
            for j in range(3):
                comp_t[:, j] = t.translation[j](q)
                comp_r[:, j] = t.rotation[j](q)
        turn = _about(s * angle[:, None] * d, c, np.zeros((n, 3)))
        err = _about(comp_r, c, comp_t)
        if s < 0:
            err = _inverse(err)
        return err @ turn

    def _chain(self, side: tuple[str, ...], q: FloatArray, play: FloatArray, noise: FloatArray) -> FloatArray:
        n = q.shape[0]
        out = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        for name in side:
            k = self.names.index(name)
            out = out @ self._axis_transform(k, q[:, k], play[:, k], noise[:, k])
        return out

    def relative(self, q: ArrayLike, play: ArrayLike | None = None,
                 noise: ArrayLike | None = None) -> FloatArray:
        """Pose of the tool frame in the workpiece frame (both = machine coordinates at the
        reference position), shape (N, 4, 4).

        q : array_like, shape (N, n_axes) — commanded axis values [m, rad]
        play : array_like, shape (N, n_axes) — reversal state of each axis in [-1, 1]
        noise : array_like, shape (N, n_axes) — repeatability offset of each axis [m, rad]
        """
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        zeros = np.zeros_like(q)
        play = zeros if play is None else np.atleast_2d(np.asarray(play, dtype=np.float64))
        noise = zeros if noise is None else np.atleast_2d(np.asarray(noise, dtype=np.float64))
        tool = self._chain(self.machine.tool_chain, q, play, noise)
        work = self._chain(self.machine.workpiece_chain, q, play, noise)
        return _inverse(work) @ tool

    def plates(self) -> tuple[FloatArray, FloatArray]:
        """Actual T_W_L ({L} on the table) and T_T_U ({U} on the spindle), (4, 4) each."""
        m, s = self.machine, self.setup
        r_l = Rotation.from_euler('ZYX', m.lower_rotation[::-1]) * Rotation.from_rotvec(s.lower_rotation)
        t_wl = _transform(r_l.as_matrix()[None], (m.lower_position + s.lower_offset)[None])[0]
        t_tu = _transform(Rotation.from_rotvec(s.upper_rotation).as_matrix()[None],
                          (self.fp + s.upper_offset)[None])[0]
        return t_wl, t_tu

    def mmd_poses(self, q: ArrayLike, play: ArrayLike | None = None,
                  noise: ArrayLike | None = None) -> FloatArray:
        """Pose of {U} in {L}, shape (N, 6): [x, y, z, phi, theta, psi] (Eq. 3 angles)."""
        t_wl, t_tu = self.plates()
        t = _inverse(t_wl[None]) @ self.relative(q, play, noise) @ t_tu
        angles = Rotation.from_matrix(t[:, :3, :3]).as_euler('ZYX')[:, ::-1]
        return np.column_stack([t[:, :3, 3], angles])

    def error_screw(self, q: ArrayLike, play: ArrayLike | None = None, *,
                    at: ArrayLike | None = None, at_workpiece: ArrayLike | None = None) -> FloatArray:
        """True error of the tool relative to the workpiece against the perfect machine, shape
        (N, 6): the translation of a point fixed to the tool and the rotation vector, both in
        machine axes (the workpiece frame turned back by its nominal rotation).

        at : (3,) or (N, 3) — the point in the tool frame at the reference position (default:
            the functional point)
        at_workpiece : (3,) — instead, the tool point that the perfect machine puts on this
            workpiece point (machine coordinates) at each q

        This is the ISO 230-1/-7 quantity the analysis estimates (the tests compare them).
        """
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        actual = self.relative(q, play)
        perfect = TwinMachine(self.machine)
        nominal = perfect.relative(q)
        if at_workpiece is not None:
            w = np.broadcast_to(np.asarray(at_workpiece, dtype=np.float64), (q.shape[0], 3))
            inv = _inverse(nominal)
            point = np.einsum('nij,nj->ni', inv[:, :3, :3], w) + inv[:, :3, 3]
        else:
            point = np.broadcast_to(self.fp if at is None else np.asarray(at, dtype=np.float64),
                                    (q.shape[0], 3))
        p_act = np.einsum('nij,nj->ni', actual[:, :3, :3], point) + actual[:, :3, 3]
        p_nom = np.einsum('nij,nj->ni', nominal[:, :3, :3], point) + nominal[:, :3, 3]
        zeros = np.zeros_like(q)
        r_mw = perfect._chain(self.machine.workpiece_chain, q, zeros, zeros)[:, :3, :3]
        dp = np.einsum('nij,nj->ni', r_mw, p_act - p_nom)
        rel = actual[:, :3, :3] @ np.swapaxes(nominal[:, :3, :3], 1, 2)
        dw = np.einsum('nij,nj->ni', r_mw, Rotation.from_matrix(rel).as_rotvec())
        return np.column_stack([dp, dw])

    # -- following (the controller's nominal kinematics, as a TCP function does) ----------------
    def follow(self, q: ArrayLike, fixed: ArrayLike | None = None) -> FloatArray:
        """Axis values with the linear axes moved so that the nominal tool point stays on the
        workpiece point where it is at the reference (R-test style following).

        q : array_like, shape (N, n_axes) — values of the rotary axes (linear ones ignored)
        returns : ndarray, shape (N, n_axes)
        """
        nominal = TwinMachine(self.machine)
        q = np.atleast_2d(np.array(q, dtype=np.float64))
        lin = [self.names.index(a.name) for a in self.machine.linear_axes]
        target = self.fp if fixed is None else np.asarray(fixed, dtype=np.float64)
        for k in lin:
            q[:, k] = self.machine.axes[k].reference
        for _ in range(3):  # the tool point is affine in the linear axes: one step is exact
            t = nominal.relative(q)
            p = np.einsum('nij,j->ni', t[:, :3, :3], self.fp) + t[:, :3, 3]
            jac = np.zeros((q.shape[0], 3, len(lin)))
            for col, k in enumerate(lin):
                dq = q.copy()
                dq[:, k] += 1e-3
                t2 = nominal.relative(dq)
                jac[:, :, col] = (np.einsum('nij,j->ni', t2[:, :3, :3], self.fp) + t2[:, :3, 3] - p) / 1e-3
            step = np.linalg.solve(jac, (target - p)[:, :, None])[:, :, 0]
            q[:, lin] += step
        return q


# -- the session's motion ---------------------------------------------------------------------
@dataclass(frozen=True)
class RunPlan:
    """One ISO run of a session: axis, commanded targets and whether the linear axes follow."""

    axis: str
    targets: FloatArray
    n_cycles: int
    overrun: float
    follow: bool


@dataclass
class MachineTrajectory:
    """The session in joint space: commanded axis values at knots, quintic blends between them.

    knots_s : (K + 1,) knot times [s]; commands : (K + 1, n_axes) commanded axis values at knots
    noise : (K + 1, n_axes) repeatability offsets reached at each knot
    runs : the plans, in order, with (start_s, end_s) of each
    """

    machine: TwinMachine
    knots_s: FloatArray
    commands: FloatArray
    noise: FloatArray
    duration_s: float
    runs: list[tuple[RunPlan, float, float]] = field(default_factory=list)
    targets: Any = None
    _play_knots: FloatArray | None = None

    def __post_init__(self) -> None:
        # reversal state of every axis at each knot: a play operator over the commanded motion
        travel = self._play_travel()
        play = np.zeros_like(self.commands)
        play[0] = -1.0
        for k in range(1, self.commands.shape[0]):
            play[k] = np.clip(play[k - 1] + (self.commands[k] - self.commands[k - 1]) / travel, -1.0, 1.0)
        self._play_knots = play

    def _play_travel(self) -> FloatArray:
        truth = self.machine.truth
        out = np.ones(len(self.machine.names))
        for k, name in enumerate(self.machine.names):
            if truth is None:
                continue
            t = truth.linear.get(name) or truth.rotary.get(name)
            out[k] = max(t.play_travel, 1e-12)
        return out

    def _segment(self, t: FloatArray) -> NDArray[np.intp]:
        return np.clip(np.searchsorted(self.knots_s, t, side='right') - 1, 0, self.knots_s.size - 2)

    def state(self, times_s: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Commanded values, reversal states and repeatability offsets, (N, n_axes) each."""
        t = np.asarray(times_s, dtype=np.float64)
        j = self._segment(t)
        start, span = self.knots_s[j], self.knots_s[j + 1] - self.knots_s[j]
        tau = np.clip((t - start) / np.where(span > 0, span, 1.0), 0.0, 1.0)
        s = (tau ** 3 * (10.0 + tau * (6.0 * tau - 15.0)))[:, None]
        q = self.commands[j] + s * (self.commands[j + 1] - self.commands[j])
        noise = self.noise[j] + s * (self.noise[j + 1] - self.noise[j])
        travel = self._play_travel()
        play = np.clip(self._play_knots[j] + (q - self.commands[j]) / travel, -1.0, 1.0)
        return q, play, noise

    def joints(self, times_s: ArrayLike) -> FloatArray:
        """Commanded axis values (what the controller's joint states report), (N, n_axes)."""
        return self.state(times_s)[0]

    def pose(self, times_s: ArrayLike) -> FloatArray:
        """True pose of {U} in {L}, (N, 6)."""
        q, play, noise = self.state(times_s)
        return self.machine.mmd_poses(q, play, noise)


def plan_session(machine: TwinMachine, runs: list[RunPlan], *, dwell_s: float, lead_s: float,
                 speed: float, accel: float, angular_speed: float, angular_accel: float,
                 seed: int) -> MachineTrajectory:
    """Knots of a session: each run is the ISO 230-2 standard test cycle of its axis (overrun
    before the first target, n cycles up and down with a dwell at each target, return home),
    runs one after the other from the reference position."""
    names = machine.names
    ref = machine.machine.reference
    rng = np.random.default_rng([seed, 13])
    sigma = np.zeros(len(names))
    if machine.truth is not None:
        for k, name in enumerate(names):
            t = machine.truth.linear.get(name) or machine.truth.rotary.get(name)
            sigma[k] = t.repeatability
    rotary = np.array([a.rotary for a in machine.machine.axes])
    knots, cmds, noise = [0.0], [ref.copy()], [np.zeros(len(names))]

    def duration(a: FloatArray, b: FloatArray) -> float:
        d = np.abs(b - a)
        lin = float(d[~rotary].max()) if (~rotary).any() else 0.0
        ang = float(d[rotary].max()) if rotary.any() else 0.0
        return max(1.875 * lin / speed, math.sqrt(5.774 * lin / accel),
                   1.875 * ang / angular_speed, math.sqrt(5.774 * ang / angular_accel))

    def go(q: FloatArray, at_target: bool) -> None:
        dt = duration(cmds[-1], q)
        if dt <= 0:
            return
        knots.append(knots[-1] + dt)
        moving = np.abs(q - cmds[-1]) > 0
        cmds.append(q)
        # axes that moved stop somewhere new within their repeatability; the others stay put
        new = rng.normal(0.0, 1.0, len(names)) * sigma if at_target else np.zeros(len(names))
        noise.append(np.where(moving, new, noise[-1]))

    def wait(seconds: float) -> None:
        if seconds > 0:
            knots.append(knots[-1] + seconds)
            cmds.append(cmds[-1].copy())
            noise.append(noise[-1].copy())

    def command(axis: int, value: float, follow: bool) -> FloatArray:
        q = ref.copy()
        q[axis] = value
        return machine.follow(q[None])[0] if follow else q

    spans = []
    for plan in runs:
        k = names.index(plan.axis)
        start = knots[-1]
        wait(lead_s)
        go(command(k, plan.targets[0] - plan.overrun, plan.follow), False)
        for _ in range(plan.n_cycles):
            for direction, order in ((+1, range(plan.targets.size)), (-1, range(plan.targets.size - 1, -1, -1))):
                for i in order:
                    go(command(k, plan.targets[i], plan.follow), True)
                    wait(dwell_s)
                end = plan.targets[-1] + plan.overrun if direction > 0 else plan.targets[0] - plan.overrun
                go(command(k, end, plan.follow), False)
        go(command(k, ref[k], plan.follow), False)
        wait(lead_s)
        spans.append((plan, start, knots[-1]))
    return MachineTrajectory(machine, np.array(knots), np.array(cmds), np.array(noise),
                             knots[-1], spans)
