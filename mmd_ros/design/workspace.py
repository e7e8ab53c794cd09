"""Reachable workspace of an MMD: the end of section 2.3 and Fig. 8 of Lei & Chen (2024).

A position ``t`` of {U} in {L} is in the workspace for a set of orientations when, at every
orientation R of the set, every bar satisfies (bar i from ``b_i`` to ``R a_i + t``, unit axis
``u_i``, length ``d_i`` by Eq. 6):

- ``bar_short`` / ``bar_long``: d_min <= d_i <= d_max (250–376 mm on the prototype);
- ``upper_tilt``: angle(u_i, R e_z) <= the upper ball-joint limit (38.58°);
- ``lower_tilt``: angle(u_i, e_z) <= the lower ball-joint limit (47.62°);
- ``separation``: the distance between the centre lines of every pair of bars >= 42 mm,
  measured between the segments of the centre lines with ``end_clearance`` left out at each
  end (the ball and its stem; see :class:`WorkspaceLimits`).

Fig. 8 asks for all three angles "concurrently" within ±k°: :func:`orientation_set` samples
that cube of angles (by default its 27 corners, edge and face centres and centre).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.kinematics import Geometry
from mmd_ros.core.rotation import rotation_matrix
from mmd_ros.core.units import M_PER_MM, mm
from mmd_ros.design.errors import DesignError

__all__ = [
    'BINDING_THRESHOLD_M', 'Boundary', 'CONSTRAINTS', 'Cylinder', 'DEFAULT_END_CLEARANCE_M',
    'DiscProfile', 'Extent', 'Level', 'PAPER_CYLINDER_M', 'PAPER_RANGES_M',
    'PAPER_ROTATION_LEVELS_DEG', 'PAPER_SPHERE_M', 'RELAXATION', 'Section', 'Workspace',
    'WorkspaceLimits', 'WorkspaceStudy', 'fibonacci_sphere', 'largest_rotation_range',
    'orientation_set', 'run_workspace_study',
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Constraint names, in the column order of :meth:`Workspace.margins`.
CONSTRAINTS = ('bar_short', 'bar_long', 'upper_tilt', 'lower_tilt', 'separation')

#: Rotation ranges of Fig. 8 [deg], all three angles together.
PAPER_ROTATION_LEVELS_DEG = (0.0, 3.0, 6.0, 9.0, 12.0)

#: Length of each bar end left out of the centre-line separation check [m]. The upper joints
#: of bars 1-2, 3-4 and 5-6 are 34.7 mm apart on the prototype, so whole segments are never
#: 42 mm apart; the bar bodies start some way from the ball centres. See msg_docs/design_tools.md.
DEFAULT_END_CLEARANCE_M = 30.0 * M_PER_MM

_PAIRS = np.array(list(itertools.combinations(range(6), 2)))

#: How far :meth:`WorkspaceLimits.relaxed` eases each constraint to test whether it binds
#: [m or rad]: a result that improves when one constraint alone is eased this much is bound by
#: it (a binding constraint moves an extreme by about this much; one that does not bind, by
#: nothing at all).
RELAXATION = {'bar_short': 1.0 * M_PER_MM, 'bar_long': 1.0 * M_PER_MM,
              'upper_tilt': math.radians(0.5), 'lower_tilt': math.radians(0.5),
              'separation': 1.0 * M_PER_MM}

#: Smallest improvement under a relaxation that counts as "the constraint binds" [m]: well
#: above the solvers' tolerances (1e-5 mm for the extremes, 0.02 mm for the marches) and well
#: below what a binding constraint gives for the relaxations above (tenths of a millimetre).
BINDING_THRESHOLD_M = 0.05 * M_PER_MM


@dataclass(frozen=True)
class WorkspaceLimits:
    """Mechanical limits of section 2.3, SI.

    bar_range_m : (shortest, longest) centre distance [m]
    upper_tilt_rad, lower_tilt_rad : largest angle between a bar and a plate normal [rad]
    min_separation_m : smallest distance between two bar centre lines [m]
    end_clearance_m : length at each end of a bar left out of the separation check [m]
    """

    bar_range_m: tuple[float, float]
    upper_tilt_rad: float
    lower_tilt_rad: float
    min_separation_m: float
    end_clearance_m: float = DEFAULT_END_CLEARANCE_M

    def __post_init__(self) -> None:
        lo, hi = self.bar_range_m
        if not 0 < lo < hi:
            raise DesignError('bar range must satisfy 0 < shortest < longest, '
                              f'got {self.bar_range_m}')
        if not (0 < self.upper_tilt_rad <= math.pi / 2 and 0 < self.lower_tilt_rad <= math.pi / 2):
            raise DesignError('tilt limits must lie in (0, 90°]')
        if self.min_separation_m < 0:
            raise DesignError('the minimum bar separation must be >= 0')
        if not 0 <= self.end_clearance_m < lo / 2:
            raise DesignError(f'end clearance must lie in [0, {lo / 2 * 1e3:.1f}) mm (half the '
                              f'shortest bar), got {self.end_clearance_m * 1e3:.1f} mm')

    @classmethod
    def from_device(cls, device: DeviceDescription, *,
                    end_clearance_m: float = DEFAULT_END_CLEARANCE_M) -> WorkspaceLimits:
        return cls(device.bar_range_m, device.upper_tilt_rad, device.lower_tilt_rad,
                   device.min_bar_separation_m, end_clearance_m)

    def relaxed(self, constraint: str, amount: float | None = None) -> WorkspaceLimits:
        """These limits with one constraint eased by ``amount`` (default :data:`RELAXATION`,
        in m or rad): the shortest bar shorter, the longest longer, a tilt limit larger (at most
        90°), the separation smaller (at least 0)."""
        if constraint not in CONSTRAINTS:
            raise DesignError(f'unknown constraint {constraint!r}; use one of {CONSTRAINTS}')
        step = RELAXATION[constraint] if amount is None else amount
        lo, hi = self.bar_range_m
        if constraint == 'bar_short':
            return replace(self, bar_range_m=(max(lo - step, 2.0 * self.end_clearance_m + 1e-6), hi))
        if constraint == 'bar_long':
            return replace(self, bar_range_m=(lo, hi + step))
        if constraint == 'upper_tilt':
            return replace(self, upper_tilt_rad=min(self.upper_tilt_rad + step, math.pi / 2))
        if constraint == 'lower_tilt':
            return replace(self, lower_tilt_rad=min(self.lower_tilt_rad + step, math.pi / 2))
        return replace(self, min_separation_m=max(self.min_separation_m - step, 0.0))


def orientation_set(max_angle_rad: float, points_per_axis: int = 3, mode: str = 'cube'
                    ) -> FloatArray:
    """Orientations with phi, theta, psi within [-k, k] (Fig. 8).

    mode : 'cube' — all three angles together (the paper's "concurrently"): a grid of
        ``points_per_axis`` values per angle, 3 giving the 27 corners, edge and face centres and
        centre of the cube of angles; 'axes' — one angle at a time, ``points_per_axis`` values
        of each with the other two zero
    returns : ndarray, shape (M, 3) — phi, theta, psi [rad]; one row of zeros when k == 0
    """
    if max_angle_rad < 0:
        raise DesignError(f'rotation range must be >= 0, got {max_angle_rad}')
    if mode not in ('cube', 'axes'):
        raise DesignError(f"orientation mode must be 'cube' or 'axes', got {mode!r}")
    if max_angle_rad == 0:
        return np.zeros((1, 3))
    if points_per_axis < 2:
        raise DesignError('need at least 2 samples per angle (the two ends of the range)')
    values = np.linspace(-max_angle_rad, max_angle_rad, points_per_axis)
    if mode == 'cube':
        return np.array(list(itertools.product(values, repeat=3)))
    rows = [np.zeros(3)]
    for axis in range(3):
        for v in values:
            if v != 0.0:
                row = np.zeros(3)
                row[axis] = v
                rows.append(row)
    return np.array(rows)


def fibonacci_sphere(count: int) -> FloatArray:
    """Nearly uniform unit directions, shape (count, 3)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _segment_distance(p1: list[FloatArray], d1: list[FloatArray], p2: list[FloatArray],
                      d2: list[FloatArray]) -> FloatArray:
    """Shortest distance between segments p1 + s d1 and p2 + t d2, s, t in [0, 1]
    (Ericson, Real-Time Collision Detection, section 5.1.9).

    Each argument is a list of the x, y, z components, arrays of one shape (structure of
    arrays keeps numpy on long loops); d1, d2 non-zero.
    returns : ndarray, that shape
    """
    r = [p1[k] - p2[k] for k in range(3)]
    a = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
    e = d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2]
    b = d1[0] * d2[0] + d1[1] * d2[1] + d1[2] * d2[2]
    c = d1[0] * r[0] + d1[1] * r[1] + d1[2] * r[2]
    f = d2[0] * r[0] + d2[1] * r[1] + d2[2] * r[2]
    denom = a * e - b * b
    parallel = denom <= 1e-12 * a * e
    s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denom), 0, 1))
    t = (b * s + f) / e
    s = np.where(t < 0.0, np.clip(-c / a, 0, 1), np.where(t > 1.0, np.clip((b - c) / a, 0, 1), s))
    t = np.clip(t, 0.0, 1.0)
    dist2 = sum((r[k] + s * d1[k] - t * d2[k]) ** 2 for k in range(3))
    return np.sqrt(dist2)


@dataclass(frozen=True)
class Section:
    """A planar cross-section of the workspace (Fig. 8).

    plane : 'xz' (at y = ``level_m``) or 'xy' (at z = ``level_m``)
    u_m, v_m : ndarray, shape (U,), (V,) — grid of the two in-plane axes [m]
    inside : ndarray, shape (U, V) — in the workspace for every orientation of the set
    """

    plane: str
    level_m: float
    u_m: FloatArray
    v_m: FloatArray
    inside: BoolArray

    def extent(self) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """(u_min, u_max), (v_min, v_max) of the inside grid points [m]; None when empty."""
        if not np.any(self.inside):
            return None
        iu, iv = np.nonzero(self.inside)
        return ((float(self.u_m[iu.min()]), float(self.u_m[iu.max()])),
                (float(self.v_m[iv.min()]), float(self.v_m[iv.max()])))


@dataclass(frozen=True)
class Extent:
    """Range of one coordinate over the workspace.

    low_m, high_m : the extreme coordinates found [m]
    low_point_m, high_point_m : ndarray, shape (3,) — where [m]
    low_binding, high_binding : the constraints that bind each extreme: easing one of them
        alone (:data:`RELAXATION`) moves the extreme outward
    low_gain_m, high_gain_m : per constraint, how far the extreme moves when it alone is
        eased [m]
    """

    axis: str
    low_m: float
    high_m: float
    low_point_m: FloatArray
    high_point_m: FloatArray
    low_binding: tuple[str, ...]
    high_binding: tuple[str, ...]
    low_gain_m: dict[str, float] = field(default_factory=dict)
    high_gain_m: dict[str, float] = field(default_factory=dict)

    @property
    def range_m(self) -> float:
        return self.high_m - self.low_m


@dataclass(frozen=True)
class Boundary:
    """Distance from a centre to the workspace boundary along several directions.

    distance_m : ndarray, shape (K,) [m] — 0 when the centre itself is outside
    directions : ndarray, shape (K, 3)
    binding : constraints violated just beyond the boundary, per direction
    """

    centre_m: FloatArray
    directions: FloatArray
    distance_m: FloatArray
    binding: list[tuple[str, ...]]

    @property
    def nearest(self) -> int:
        return int(np.argmin(self.distance_m))


@dataclass(frozen=True)
class DiscProfile:
    """The largest horizontal disc about a vertical axis inside the workspace, per height.

    z_m : ndarray, shape (Z,) — heights [m], from the lowest to the highest where the axis
        is inside
    radius_m : ndarray, shape (Z,) [m]
    binding : the constraints limiting each disc
    """

    axis_xy_m: tuple[float, float]
    z_m: FloatArray
    radius_m: FloatArray
    binding: list[tuple[str, ...]]


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder inside the workspace: diameter, height, bottom and top [m], and the
    constraints that stop it growing (at the bottom and top for the tallest cylinder of a given
    diameter, at its narrowest height for the widest cylinder of a given height)."""

    axis_xy_m: tuple[float, float]
    diameter_m: float
    height_m: float
    z_low_m: float
    z_high_m: float
    binding: tuple[str, ...]


class Workspace:
    """Workspace of one device for one set of orientations.

    Parameters
    ----------
    geometry : joints a_i (in {U}) and b_i (in {L})
    limits : the mechanical limits
    orientations : array_like, shape (M, 3) — phi, theta, psi [rad]; a position is inside
        when it satisfies every limit at every one of them
    """

    def __init__(self, geometry: Geometry, limits: WorkspaceLimits,
                 orientations: ArrayLike = ((0.0, 0.0, 0.0),)) -> None:
        self.geometry = geometry
        self.limits = limits
        self.orientations = np.atleast_2d(np.asarray(orientations, dtype=np.float64))
        if self.orientations.shape[1] != 3:
            raise DesignError(f'orientations must have shape (M, 3), got {self.orientations.shape}')
        self._rotations = rotation_matrix(self.orientations)
        self._cos_upper = math.cos(limits.upper_tilt_rad)
        self._cos_lower = math.cos(limits.lower_tilt_rad)

    # -- constraints ---------------------------------------------------------------------------
    def margins(self, positions: ArrayLike, rotation: ArrayLike) -> FloatArray:
        """Signed margin of each constraint at one orientation, >= 0 when satisfied.

        positions : array_like, shape (N, 3) [m]
        rotation : array_like, shape (3, 3) — L_R_U
        returns : ndarray, shape (N, 5), columns :data:`CONSTRAINTS` — bar length and
            separation margins [m], tilt margins (limit - angle) [rad]
        """
        t = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        out = np.empty((t.shape[0], len(CONSTRAINTS)))
        d, u, cos_upper, cos_lower = self._bars(t, np.asarray(rotation, dtype=np.float64))
        out[:, 0] = np.min(d, axis=1) - self.limits.bar_range_m[0]
        out[:, 1] = self.limits.bar_range_m[1] - np.max(d, axis=1)
        out[:, 2] = self.limits.upper_tilt_rad - np.arccos(np.clip(cos_upper.min(axis=1), -1, 1))
        out[:, 3] = self.limits.lower_tilt_rad - np.arccos(np.clip(cos_lower.min(axis=1), -1, 1))
        out[:, 4] = self._separation(d, u) - self.limits.min_separation_m
        return out

    def _bars(self, t: FloatArray, rot: FloatArray
              ) -> tuple[FloatArray, list[FloatArray], FloatArray, FloatArray]:
        """Lengths (N, 6), unit axes as x, y, z components (N, 6) each, and the cosines of
        the upper and lower tilt angles (N, 6), for positions t (N, 3) at rotation rot."""
        ra = self.geometry.upper @ rot.T                                   # R a_i, (6, 3)
        b = self.geometry.lower
        legs = [t[:, k:k + 1] + (ra[:, k] - b[:, k]) for k in range(3)]   # (N, 6) each
        d = np.sqrt(legs[0] ** 2 + legs[1] ** 2 + legs[2] ** 2)
        u = [leg / d for leg in legs]
        normal = rot[:, 2]
        cos_upper = u[0] * normal[0] + u[1] * normal[1] + u[2] * normal[2]
        return d, u, cos_upper, u[2]

    def _separation(self, d: FloatArray, u: list[FloatArray]) -> FloatArray:
        """Smallest distance between the bar centre lines, ``end_clearance`` left out at
        each end, over the 15 pairs: shape (N,) [m]."""
        c = self.limits.end_clearance_m
        b = self.geometry.lower
        span = d - 2.0 * c
        i, j = _PAIRS[:, 0], _PAIRS[:, 1]
        start = [b[:, k] + c * u[k] for k in range(3)]
        direction = [span * u[k] for k in range(3)]
        sep = _segment_distance([s[:, i] for s in start], [v[:, i] for v in direction],
                                [s[:, j] for s in start], [v[:, j] for v in direction])
        return np.min(sep, axis=1)

    def constraint_values(self, position: ArrayLike) -> FloatArray:
        """Every constraint at one position, for every orientation of the set and every bar or
        pair of bars, >= 0 where satisfied: the smooth pieces an optimiser works with.

        position : array_like, shape (3,) [m]
        returns : ndarray, shape (M * 39,) — for the M orientations: d_i - d_min and
            d_max - d_i [mm] (6 each), 1000 (cos tilt - cos limit) upper and lower (6 each),
            pair separations - limit [mm] (15)
        """
        t = np.asarray(position, dtype=np.float64).reshape(3)
        rot = self._rotations
        legs = t + np.einsum('mij,kj->mki', rot, self.geometry.upper) - self.geometry.lower
        d = np.sqrt(np.einsum('mki,mki->mk', legs, legs))                       # (M, 6)
        u = legs / d[..., None]
        cos_upper = np.einsum('mki,mi->mk', u, rot[:, :, 2])
        lim = self.limits
        c = lim.end_clearance_m
        start = self.geometry.lower + c * u
        along = (d - 2.0 * c)[..., None] * u
        i, j = _PAIRS[:, 0], _PAIRS[:, 1]
        sep = _segment_distance([start[:, i, k] for k in range(3)], [along[:, i, k] for k in range(3)],
                                [start[:, j, k] for k in range(3)], [along[:, j, k] for k in range(3)])
        lo, hi = lim.bar_range_m
        return np.concatenate([((d - lo) / M_PER_MM).ravel(), ((hi - d) / M_PER_MM).ravel(),
                               (1e3 * (cos_upper - self._cos_upper)).ravel(),
                               (1e3 * (u[..., 2] - self._cos_lower)).ravel(),
                               ((sep - lim.min_separation_m) / M_PER_MM).ravel()])

    def _optimum(self, axis: int, sign: float, start: FloatArray) -> FloatArray:
        """The local maximum of sign * t[axis] subject to every constraint, by SLSQP from an
        inside point (coordinates in mm; converged to 1e-10 of the objective). Returns the
        optimiser's point [m], which may lie outside by rounding (constraints met to 1e-6 mm);
        ``start`` itself when the optimiser ends anywhere else."""
        x0 = np.asarray(start, dtype=np.float64) / M_PER_MM
        grad = np.zeros(3)
        grad[axis] = -sign

        res = minimize(lambda x: -sign * x[axis], x0, jac=lambda x: grad, method='SLSQP',
                       constraints=[{'type': 'ineq',
                                     'fun': lambda x: self.constraint_values(x * M_PER_MM)}],
                       options={'ftol': 1e-10, 'maxiter': 300})
        point = res.x * M_PER_MM
        if (not np.all(np.isfinite(point)) or sign * (point[axis] - start[axis]) < 0
                or float(np.min(self.constraint_values(point))) < -1e-6):
            return np.asarray(start, dtype=np.float64)
        return point

    def extreme(self, axis: int, sign: float, start: ArrayLike,
                tol_m: float = 0.01 * M_PER_MM) -> tuple[float, FloatArray] | None:
        """The extreme of the workspace along ``sign`` * axis reached from an inside point:
        SLSQP on :meth:`constraint_values` to the local maximum, then the inside point
        nearest to it on the segment back to ``start``, found by bisection to ``tol_m`` (an
        extreme can be a cusp, where the workspace does not continue along the axis).

        returns : the coordinate [m] and the point (3,) [m] — inside, and within ``tol_m`` of
            the optimiser's answer — or None when the optimiser got nowhere beyond ``start``
        """
        begin = np.asarray(start, dtype=np.float64)
        point = self._optimum(axis, sign, begin)
        if self.inside(point[None])[0]:
            return float(point[axis]), point
        lo, hi = 0.0, 1.0                      # fractions of the way from begin to point
        step = point - begin
        length = float(np.linalg.norm(step))
        if length == 0.0:
            return None
        while (hi - lo) * length > tol_m:
            mid = 0.5 * (lo + hi)
            if self.inside((begin + mid * step)[None])[0]:
                lo = mid
            else:
                hi = mid
        end = begin + lo * step
        return float(end[axis]), end

    def binding_of_extreme(self, axis: int, sign: float, point: ArrayLike, *,
                           threshold_m: float = BINDING_THRESHOLD_M
                           ) -> tuple[tuple[str, ...], dict[str, float]]:
        """Which constraints bind an extreme: each is eased alone (:meth:`WorkspaceLimits.relaxed`)
        and the extreme sought again from ``point``; those under which it moves outward by more
        than ``threshold_m`` bind.

        returns : the binding constraints and, per constraint, how far the extreme moved [m]
        """
        p = np.asarray(point, dtype=np.float64)
        base = float(self._optimum(axis, sign, p)[axis])
        gains = {}
        for name in CONSTRAINTS:
            eased = self.with_limits(self.limits.relaxed(name))
            gains[name] = sign * (float(eased._optimum(axis, sign, p)[axis]) - base)
        return tuple(n for n in CONSTRAINTS if gains[n] > threshold_m), gains

    def _satisfied(self, t: FloatArray, rot: FloatArray) -> BoolArray:
        """All constraints at one orientation, the separation only where the rest hold."""
        lim = self.limits
        d, u, cos_upper, cos_lower = self._bars(t, rot)
        ok = (np.all((d >= lim.bar_range_m[0]) & (d <= lim.bar_range_m[1]), axis=1)
              & np.all(cos_upper >= self._cos_upper, axis=1)
              & np.all(cos_lower >= self._cos_lower, axis=1))
        idx = np.flatnonzero(ok)
        if idx.size:
            sep = self._separation(d[idx], [v[idx] for v in u])
            ok[idx] = sep >= lim.min_separation_m
        return ok

    def inside(self, positions: ArrayLike) -> BoolArray:
        """Whether each position satisfies every limit at every orientation of the set.

        positions : array_like, shape (N, 3) [m]
        returns : ndarray, shape (N,)
        """
        t = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        ok = np.ones(t.shape[0], dtype=bool)
        for rot in self._rotations:
            idx = np.flatnonzero(ok)
            if idx.size == 0:
                break
            ok[idx] = self._satisfied(t[idx], rot)
        return ok

    def violated(self, position: ArrayLike) -> tuple[str, ...]:
        """Names of the constraints violated at one position for some orientation of the set."""
        t = np.asarray(position, dtype=np.float64).reshape(1, 3)
        bad = np.zeros(len(CONSTRAINTS), dtype=bool)
        for rot in self._rotations:
            bad |= self.margins(t, rot)[0] < 0.0
        return tuple(name for name, flag in zip(CONSTRAINTS, bad) if flag)

    def most_violated(self, positions: ArrayLike) -> NDArray[np.int64]:
        """Index into :data:`CONSTRAINTS` of the constraint violated most at each position
        over the orientations (margins compared in mm and degrees), -1 where all hold.

        positions : array_like, shape (N, 3) [m]
        returns : ndarray, shape (N,)
        """
        t = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        scale = np.array([M_PER_MM, M_PER_MM, math.radians(1.0), math.radians(1.0), M_PER_MM])
        worst = np.full((t.shape[0], len(CONSTRAINTS)), np.inf)
        for rot in self._rotations:
            worst = np.minimum(worst, self.margins(t, rot) / scale)
        out = np.argmin(worst, axis=1)
        out[np.min(worst, axis=1) >= 0.0] = -1
        return out

    # -- analyses ------------------------------------------------------------------------------
    def bounding_box(self) -> FloatArray:
        """A box sure to contain the workspace: within d_max of every b_i - R a_i, above the
        lower plate. Returns ndarray, shape (2, 3) — low and high corners [m]."""
        d_max = self.limits.bar_range_m[1]
        lows, highs = [], []
        for rot in self._rotations:
            centres = self.geometry.lower - self.geometry.upper @ rot.T
            lows.append(np.max(centres, axis=0) - d_max)
            highs.append(np.min(centres, axis=0) + d_max)
        low, high = np.max(lows, axis=0), np.min(highs, axis=0)
        low[2] = max(low[2], 0.0)
        return np.array([low, high])

    def section(self, plane: str, level_m: float, step_m: float = 2.0 * M_PER_MM,
                box: FloatArray | None = None) -> Section:
        """A cross-section on a grid: 'xz' at y = level or 'xy' at z = level (Fig. 8)."""
        box = self.bounding_box() if box is None else box
        if plane == 'xz':
            axes, fixed = (0, 2), 1
        elif plane == 'xy':
            axes, fixed = (0, 1), 2
        else:
            raise DesignError(f"plane must be 'xz' or 'xy', got {plane!r}")
        u = _grid(box[0, axes[0]], box[1, axes[0]], step_m)
        v = _grid(box[0, axes[1]], box[1, axes[1]], step_m)
        uu, vv = np.meshgrid(u, v, indexing='ij')
        pts = np.empty(uu.shape + (3,))
        pts[..., axes[0]], pts[..., axes[1]], pts[..., fixed] = uu, vv, level_m
        inside = self.inside(pts.reshape(-1, 3)).reshape(uu.shape)
        return Section(plane, float(level_m), u, v, inside)

    def extents(self, step_m: float = 4.0 * M_PER_MM, tol_m: float = 0.01 * M_PER_MM,
                progress: Callable[[float], None] | None = None) -> list[Extent]:
        """Ranges in x, y and z of the whole workspace.

        A 3-D grid of ``step_m`` finds the inside points; from the outermost ones each extreme
        is refined (:meth:`extreme`: SLSQP on the constraints, then a boundary point to
        ``tol_m`` along the axis) and its binding constraints found by easing each alone
        (:meth:`binding_of_extreme`).
        """
        box = self.bounding_box()
        axes = [_grid(box[0, k], box[1, k], step_m) for k in range(3)]
        inside_pts = []
        # Slab by slab in z keeps memory small and allows progress reports.
        xx, yy = np.meshgrid(axes[0], axes[1], indexing='ij')
        plane = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)
        for k, z in enumerate(axes[2]):
            plane[:, 2] = z
            ok = self.inside(plane)
            if np.any(ok):
                inside_pts.append(plane[ok].copy())
            if progress is not None:
                progress((k + 1) / len(axes[2]))
        if not inside_pts:
            raise DesignError('the workspace is empty for these limits and orientations')
        pts = np.vstack(inside_pts)
        out = []
        for k, name in enumerate('xyz'):
            ends = []
            for sign in (-1.0, 1.0):
                value, point = self._refine_extreme(pts, k, sign, step_m, tol_m)
                binding, gains = self.binding_of_extreme(k, sign, point)
                ends.append((value, point, binding, gains))
            (lo_val, lo_pt, lo_bind, lo_gain), (hi_val, hi_pt, hi_bind, hi_gain) = ends
            out.append(Extent(name, lo_val, hi_val, lo_pt, hi_pt, lo_bind, hi_bind,
                              lo_gain, hi_gain))
        return out

    def _refine_extreme(self, pts: FloatArray, axis: int, sign: float, step_m: float,
                        tol_m: float, starts: int = 3) -> tuple[float, FloatArray]:
        """The extreme along ``sign`` * axis from the inside grid points ``pts``: :meth:`extreme`
        from the ``starts`` outermost ones (and a plain march along the axis from each, should
        the optimiser find nothing); the best of them."""
        key = sign * pts[:, axis]
        best = pts[np.argsort(-key)[:starts]]
        found = [r for r in (self.extreme(axis, sign, p, tol_m) for p in best) if r is not None]
        direction = np.zeros(3)
        direction[axis] = sign
        marched = self._march_from(best, direction, step_m, tol_m)
        found += [(float(p[axis]), p) for p in marched]
        return max(found, key=lambda r: sign * r[0])

    def _march_from(self, starts: FloatArray, direction: FloatArray, step_m: float,
                    tol_m: float) -> FloatArray:
        """End points of marches from inside ``starts`` along one direction."""
        dist, _ = self._march(starts, np.repeat(direction[None], len(starts), axis=0),
                              max_m=4 * step_m, step_m=step_m / 4, tol_m=tol_m)
        return starts + dist[:, None] * direction

    def _march(self, starts: FloatArray, directions: FloatArray, max_m: float, step_m: float,
               tol_m: float) -> tuple[FloatArray, BoolArray]:
        """Along each ray from an inside start, the distance to the first outside point,
        marching by ``step_m`` then bisecting to ``tol_m``. Returns distances (K,) [m] and
        whether the boundary was found before ``max_m``."""
        k = len(starts)
        lo = np.zeros(k)
        hi = np.full(k, np.inf)
        active = np.arange(k)
        r = 0.0
        while active.size and r < max_m:
            r = min(r + step_m, max_m)
            ok = self.inside(starts[active] + r * directions[active])
            hi[active[~ok]] = r
            lo[active[ok]] = r
            active = active[ok]
        found = np.isfinite(hi)
        idx = np.flatnonzero(found)
        while idx.size:
            mid = 0.5 * (lo[idx] + hi[idx])
            ok = self.inside(starts[idx] + mid[:, None] * directions[idx])
            lo[idx[ok]] = mid[ok]
            hi[idx[~ok]] = mid[~ok]
            idx = idx[(hi[idx] - lo[idx]) > tol_m]
        return lo, found

    def boundary(self, centre_m: ArrayLike, directions: ArrayLike, *, max_m: float = 0.3,
                 step_m: float = 2.0 * M_PER_MM, tol_m: float = 0.02 * M_PER_MM) -> Boundary:
        """Distance from ``centre_m`` to the boundary along each direction, marching outward
        (the region is taken as star-shaped about the centre to the march resolution).

        centre_m : array_like, shape (3,) [m];  directions : array_like, shape (K, 3), unit
        """
        c = np.asarray(centre_m, dtype=np.float64).reshape(3)
        dirs = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        if not self.inside(c[None])[0]:
            return Boundary(c, dirs, np.zeros(len(dirs)), [self.violated(c)] * len(dirs))
        dist, found = self._march(np.repeat(c[None], len(dirs), axis=0), dirs, max_m, step_m,
                                  tol_m)
        binding = [self.violated(c + (r + 2 * tol_m) * u) if f else ()
                   for r, u, f in zip(dist, dirs, found)]
        return Boundary(c, dirs, dist, binding)

    def largest_sphere(self, centre_m: ArrayLike, directions: int = 400, **kw: float
                       ) -> Boundary:
        """Distances to the boundary over ``directions`` nearly uniform directions; the
        largest sphere about the centre has the radius ``boundary.distance_m.min()``."""
        return self.boundary(centre_m, fibonacci_sphere(directions), **kw)

    def disc_radius(self, z_m: ArrayLike, axis_xy_m: tuple[float, float] = (0.0, 0.0), *,
                    directions: int = 120, step_m: float = 5.0 * M_PER_MM,
                    tol_m: float = 0.02 * M_PER_MM) -> tuple[FloatArray, list[tuple[str, ...]]]:
        """The largest disc about a vertical axis inside the workspace at each height.

        z_m : array_like, shape (Z,) [m]
        returns : radii, ndarray, shape (Z,) [m] (0 where the axis is outside), and the
            constraints limiting each
        """
        z = np.atleast_1d(np.asarray(z_m, dtype=np.float64))
        ang = np.arange(directions) * (2 * math.pi / directions)
        ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(directions)], axis=1)
        centres = np.stack([np.full(z.size, axis_xy_m[0]), np.full(z.size, axis_xy_m[1]), z], 1)
        radius = np.zeros(z.size)
        inside = self.inside(centres)
        binding: list[tuple[str, ...]] = [() if ok else self.violated(c)
                                          for c, ok in zip(centres, inside)]
        idx = np.flatnonzero(inside)
        if idx.size:
            starts = np.repeat(centres[idx], directions, axis=0)
            dirs = np.tile(ring, (idx.size, 1))
            box = self.bounding_box()
            dist, _ = self._march(starts, dirs, max_m=float(np.max(box[1] - box[0])),
                                  step_m=step_m, tol_m=tol_m)
            dist = dist.reshape(idx.size, directions)
            nearest = np.argmin(dist, axis=1)
            for row, k in enumerate(idx):
                radius[k] = dist[row, nearest[row]]
                binding[k] = self.violated(centres[k] + (radius[k] + 2 * tol_m)
                                           * ring[nearest[row]])
        return radius, binding

    def disc_profile(self, axis_xy_m: tuple[float, float] = (0.0, 0.0), *,
                     z_step_m: float = 2.0 * M_PER_MM) -> DiscProfile:
        """:meth:`disc_radius` over the heights of the bounding box, trimmed to where the
        axis is inside."""
        box = self.bounding_box()
        z = _grid(box[0, 2], box[1, 2], z_step_m)
        radius, binding = self.disc_radius(z, axis_xy_m)
        keep = np.flatnonzero(radius > 0)
        if keep.size == 0:
            raise DesignError('the vertical axis lies outside the workspace at every height')
        sl = slice(keep[0], keep[-1] + 1)
        return DiscProfile(axis_xy_m, z[sl], radius[sl], binding[sl])

    def tallest_cylinder(self, diameter_m: float, profile: DiscProfile,
                         tol_m: float = 0.01 * M_PER_MM, *, binding: bool = True) -> Cylinder:
        """The tallest cylinder of ``diameter_m`` about the profile's axis: the longest run of
        heights where the disc fits, its ends refined by bisection. With ``binding``, the
        constraints that stop it growing (:meth:`_cylinder_end_binding`)."""
        ok = profile.radius_m >= diameter_m / 2
        runs = _runs(ok)
        axis = profile.axis_xy_m
        if not runs:
            k = int(np.argmax(profile.radius_m))
            return Cylinder(axis, diameter_m, 0.0, float(profile.z_m[k]), float(profile.z_m[k]),
                            profile.binding[k])
        first, last = max(runs, key=lambda r: profile.z_m[r[1]] - profile.z_m[r[0]])

        def fits(z: float) -> bool:
            return bool(self.disc_radius([z], axis)[0][0] >= diameter_m / 2)

        z_low = float(profile.z_m[first])
        if first > 0:
            z_low = _bisect(fits, float(profile.z_m[first - 1]), z_low, tol_m)
        z_high = float(profile.z_m[last])
        if last < profile.z_m.size - 1:
            z_high = _bisect(fits, float(profile.z_m[last + 1]), z_high, tol_m)
        return Cylinder(axis, diameter_m, z_high - z_low, z_low, z_high,
                        self._cylinder_end_binding(diameter_m, axis, z_low, z_high)
                        if binding else ())

    def _cylinder_end_binding(self, diameter_m: float, axis: tuple[float, float], z_low: float,
                              z_high: float) -> tuple[str, ...]:
        """The constraints that stop a cylinder of ``diameter_m`` from growing past its ends:
        eased alone, the disc fits :data:`BINDING_THRESHOLD_M` beyond the bottom or the top."""
        out = []
        for name in CONSTRAINTS:
            eased = self.with_limits(self.limits.relaxed(name))
            radii = eased.disc_radius([z_low - BINDING_THRESHOLD_M, z_high + BINDING_THRESHOLD_M],
                                      axis)[0]
            if np.any(radii >= diameter_m / 2):
                out.append(name)
        return tuple(out)

    def widest_cylinder(self, height_m: float, profile: DiscProfile,
                        tol_m: float = 0.01 * M_PER_MM, *, binding: bool = True) -> Cylinder:
        """The widest cylinder of ``height_m`` about the profile's axis. On the profile grid
        the best bottom height is found; then, for a disc radius that rises and falls with
        height, the bottom is refined to where the discs at bottom and top are equal. With
        ``binding``, the constraints that stop it growing: each eased alone widens it by more
        than twice :data:`BINDING_THRESHOLD_M`."""
        z, r = profile.z_m, profile.radius_m
        axis = profile.axis_xy_m
        dz = float(z[1] - z[0]) if z.size > 1 else 1.0
        steps = int(math.floor(height_m / dz + 1e-9))
        if z.size == 0 or z[-1] - z[0] < height_m:
            ends = tuple(dict.fromkeys(profile.binding[0] + profile.binding[-1]))
            return Cylinder(axis, 0.0, height_m, math.nan, math.nan, ends)
        windows = [float(np.min(r[k:k + steps + 1])) for k in range(r.size - steps)]
        k = int(np.argmax(windows))

        def radius(z0: float) -> float:
            return float(self.disc_radius([z0], axis)[0][0])

        def gap(z0: float) -> float:
            return radius(z0) - radius(z0 + height_m)

        def width(z0: float) -> float:
            return min(radius(z0), radius(z0 + height_m))

        candidates = [float(z[k])]
        lo, hi = float(z[max(k - 1, 0)]), min(float(z[min(k + 1, z.size - 1)]),
                                               float(z[-1]) - height_m)
        if lo < hi and gap(lo) < 0.0 < gap(hi):
            # The radius may jump (a bar-length limit ends abruptly): keep both sides.
            a = _bisect(lambda v: gap(v) < 0.0, hi, lo, tol_m)
            candidates += [a, min(a + 2 * tol_m, hi)]
        z0 = max(candidates, key=width)
        r_low, r_high = radius(z0), radius(z0 + height_m)
        inner = float(np.min(r[(z > z0) & (z < z0 + height_m)], initial=np.inf))
        diameter = 2 * min(r_low, r_high, inner)
        if not binding:
            return Cylinder(axis, diameter, height_m, z0, z0 + height_m, ())
        # Binding by easing each constraint alone: the widest cylinder again, on the profile
        # of a window a few steps around this one, against the same computation unchanged.
        window = _grid(z0 - 2 * dz, z0 + height_m + 2 * dz, dz)

        def widest_near(ws: Workspace) -> float:
            radii, binds = ws.disc_radius(window, axis, directions=60)
            keep = radii > 0
            if keep.sum() < 2:
                return 0.0
            local = DiscProfile(axis, window[keep], radii[keep], [b for b, k in zip(binds, keep) if k])
            return ws.widest_cylinder(height_m, local, tol_m, binding=False).diameter_m

        base = widest_near(self)
        names = tuple(n for n in CONSTRAINTS
                      if widest_near(self.with_limits(self.limits.relaxed(n))) - base
                      > 2 * BINDING_THRESHOLD_M)
        return Cylinder(axis, diameter, height_m, z0, z0 + height_m, names)

    def sphere_inside(self, centre_m: ArrayLike, radius_m: float, *, directions: int = 400,
                      shells: int = 5) -> bool:
        """Whether a ball lies inside: its centre and ``shells`` concentric spheres up to
        ``radius_m``, each sampled in ``directions`` directions, are all inside."""
        c = np.asarray(centre_m, dtype=np.float64).reshape(1, 3)
        dirs = fibonacci_sphere(directions)
        radii = np.linspace(radius_m / shells, radius_m, shells)
        pts = np.vstack([c] + [c + rr * dirs for rr in radii])
        return bool(np.all(self.inside(pts)))

    def with_orientations(self, orientations: ArrayLike) -> Workspace:
        """The same device and limits for another set of orientations."""
        return Workspace(self.geometry, self.limits, orientations)

    def with_limits(self, limits: WorkspaceLimits) -> Workspace:
        """The same device and orientations under other limits."""
        return Workspace(self.geometry, limits, self.orientations)

    def sphere_binding(self, sphere: Boundary, *, margin_m: float = 3.0 * M_PER_MM
                       ) -> tuple[str, ...]:
        """The constraints that stop the largest sphere about ``sphere.centre_m`` growing: each
        eased alone, the distances to the boundary are sought again along the directions
        within ``margin_m`` of the nearest (the others are farther whatever is eased), and the
        constraint binds if the smallest grows by more than :data:`BINDING_THRESHOLD_M`."""
        dist = sphere.distance_m
        r = float(dist.min())
        if r <= 0:
            return sphere.binding[sphere.nearest]
        near = dist < r + margin_m
        far = float(dist[~near].min()) if np.any(~near) else np.inf
        dirs = sphere.directions[near]
        # an eased workspace holds the original one: march on from just inside its boundary
        back = np.maximum(dist[near] - 2 * BINDING_THRESHOLD_M, 0.0)
        starts = sphere.centre_m + back[:, None] * dirs
        out = []
        for name in CONSTRAINTS:
            eased = self.with_limits(self.limits.relaxed(name))
            more, _ = eased._march(starts, dirs, max_m=margin_m + 4 * BINDING_THRESHOLD_M,
                                   step_m=BINDING_THRESHOLD_M, tol_m=0.02 * M_PER_MM)
            if min(float(np.min(back + more)), far) - r > BINDING_THRESHOLD_M:
                out.append(name)
        return tuple(out)


def _runs(flags: BoolArray) -> list[tuple[int, int]]:
    """Index ranges [first, last] of the runs of True."""
    out = []
    start = None
    for k, flag in enumerate(np.append(flags, False)):
        if flag and start is None:
            start = k
        elif not flag and start is not None:
            out.append((start, k - 1))
            start = None
    return out


def _bisect(good: Callable[[float], bool], bad_at: float, good_at: float, tol: float) -> float:
    """The boundary between a point where ``good`` is False and one where it is True."""
    while abs(good_at - bad_at) > tol:
        mid = 0.5 * (bad_at + good_at)
        if good(mid):
            good_at = mid
        else:
            bad_at = mid
    return good_at


def _mm(value_m: float, digits: int) -> float:
    """Metres to millimetres, rounded, as a plain float (for reports)."""
    return round(float(mm(value_m)), digits)


def _grid(low: float, high: float, step: float) -> FloatArray:
    """Grid points on multiples of ``step`` covering [low, high]."""
    return np.arange(math.floor(low / step), math.ceil(high / step) + 1) * step


# -- the statements of section 2.1, 2.3 and Fig. 8 ---------------------------------------------
#: The paper's workspace statements: translational ranges in x, y, z [m] (section 2.1), the
#: inscribed cylinder at zero rotation, diameter and height [m] (sections 1, 2.1), and the
#: sphere at ±12°, centre and diameter [m] (Fig. 8).
PAPER_RANGES_M = (0.348, 0.348, 0.130)
PAPER_CYLINDER_M = (0.200, 0.075)
PAPER_SPHERE_M = ((0.0, 0.0, 0.300), 0.050)


@dataclass(frozen=True)
class Level:
    """The workspace for one rotation range: sections, ranges, largest sphere at the centre and
    the constraints that bind it (:meth:`Workspace.sphere_binding`)."""

    range_deg: float
    orientations: int
    xz: Section
    xy: Section
    extents: list[Extent] | None
    sphere: Boundary
    sphere_binding: tuple[str, ...] = ()


@dataclass(frozen=True)
class WorkspaceStudy:
    """Results of :func:`run_workspace_study`."""

    limits: WorkspaceLimits
    mode: str
    points_per_axis: int
    levels: list[Level]
    ranges_m: tuple[float, float, float]
    cylinder_m: tuple[float, float]
    sphere_centre_m: FloatArray
    sphere_diameter_m: float
    tallest: Cylinder
    widest: Cylinder
    sphere_range_deg: float
    sphere_level_deg: float

    def summary(self) -> dict[str, object]:
        """Results and the verdict on each statement, in mm and degrees."""
        lim = self.limits
        out: dict[str, object] = {
            'binding_test': {'relaxation': {n: (_mm(v, 3) if n in ('bar_short', 'bar_long', 'separation')
                                                else round(math.degrees(v), 3))
                                            for n, v in RELAXATION.items()},
                             'relaxation_units': 'mm for bar_short, bar_long, separation; '
                                                 'degrees for the tilts',
                             'threshold_mm': _mm(BINDING_THRESHOLD_M, 3),
                             'meaning': 'a constraint binds a result when easing it alone by its '
                                        'relaxation improves the result by more than the '
                                        'threshold (twice it for a diameter)'},
            'limits': {'bar_range_mm': [_mm(v, 3) for v in lim.bar_range_m],
                       'upper_tilt_deg': round(math.degrees(lim.upper_tilt_rad), 3),
                       'lower_tilt_deg': round(math.degrees(lim.lower_tilt_rad), 3),
                       'min_separation_mm': _mm(lim.min_separation_m, 3),
                       'end_clearance_mm': _mm(lim.end_clearance_m, 3)},
            'orientations': {'mode': self.mode, 'points_per_axis': self.points_per_axis},
            'levels': [],
        }
        levels = []
        for lv in self.levels:
            entry: dict[str, object] = {'range_deg': lv.range_deg, 'orientations': lv.orientations}
            for name, sec in (('xz', lv.xz), ('xy', lv.xy)):
                ext = sec.extent()
                entry[f'{name}_section'] = {
                    'level_mm': _mm(sec.level_m, 3),
                    'extent_mm': None if ext is None else [[_mm(v, 1) for v in e] for e in ext]}
            if lv.extents is not None:
                entry['ranges'] = {e.axis: {'low_mm': _mm(e.low_m, 2),
                                            'high_mm': _mm(e.high_m, 2),
                                            'range_mm': _mm(e.range_m, 2),
                                            'low_binding': list(e.low_binding),
                                            'high_binding': list(e.high_binding),
                                            'low_gain_mm': {n: _mm(v, 3) for n, v in e.low_gain_m.items()},
                                            'high_gain_mm': {n: _mm(v, 3) for n, v in e.high_gain_m.items()}}
                                   for e in lv.extents}
            k = lv.sphere.nearest
            entry['sphere'] = {'centre_mm': [_mm(v, 3) for v in lv.sphere.centre_m],
                               'largest_diameter_mm': _mm(2 * lv.sphere.distance_m[k], 2),
                               'binding': list(lv.sphere_binding)}
            levels.append(entry)
        out['levels'] = levels
        zero = self.levels[0]
        statements = []
        if zero.extents is not None:
            for e, stated in zip(zero.extents, self.ranges_m):
                statements.append({
                    'statement': f'translational range in {e.axis} of {mm(stated):g} mm at zero '
                                 'rotation',
                    'holds': bool(e.range_m >= stated - 1e-9),
                    'measured_mm': _mm(e.range_m, 2),
                    'binding': sorted(set(e.low_binding) | set(e.high_binding))})
        d, h = self.cylinder_m
        statements.append({
            'statement': f'inscribed cylinder of {mm(d):g} mm diameter and {mm(h):g} mm height '
                         'at zero rotation',
            'holds': bool(self.tallest.height_m >= h - 1e-9),
            'tallest_at_diameter_mm': _mm(self.tallest.height_m, 2),
            'tallest_z_mm': [_mm(self.tallest.z_low_m, 2), _mm(self.tallest.z_high_m, 2)],
            'tallest_binding': list(self.tallest.binding),
            'widest_at_height_mm': _mm(self.widest.diameter_m, 2),
            'widest_z_mm': [_mm(self.widest.z_low_m, 2), _mm(self.widest.z_high_m, 2)],
            'widest_binding': list(self.widest.binding)})
        top = [lv for lv in self.levels if lv.range_deg == self.sphere_level_deg][0]
        k = top.sphere.nearest
        statements.append({
            'statement': f'sphere of {mm(self.sphere_diameter_m):g} mm diameter at '
                         f'({", ".join(f"{mm(v):g}" for v in self.sphere_centre_m)}) mm at '
                         f'±{self.sphere_level_deg:g}°',
            'holds': bool(2 * top.sphere.distance_m[k] >= self.sphere_diameter_m - 1e-9),
            'largest_diameter_mm': _mm(2 * top.sphere.distance_m[k], 2),
            'binding': list(top.sphere_binding),
            'largest_rotation_range_deg': round(self.sphere_range_deg, 2)})
        out['statements'] = statements
        return out


def largest_rotation_range(workspace: Workspace, centre_m: ArrayLike, radius_m: float, *,
                           points_per_axis: int = 3, mode: str = 'cube', high_rad: float = 0.6,
                           tol_rad: float = math.radians(0.01)) -> float:
    """The largest k such that the ball fits for every orientation within ±k [rad], by
    bisection (0 when it does not fit even at zero rotation)."""
    def fits(k: float) -> bool:
        ws = workspace.with_orientations(orientation_set(k, points_per_axis, mode))
        return ws.sphere_inside(centre_m, radius_m)

    if not fits(0.0):
        return 0.0
    if fits(high_rad):
        return high_rad
    return _bisect(fits, high_rad, 0.0, tol_rad)


def run_workspace_study(geometry: Geometry, limits: WorkspaceLimits, *,
                        levels_deg: Sequence[float] = PAPER_ROTATION_LEVELS_DEG,
                        points_per_axis: int = 3, mode: str = 'cube',
                        section_step_m: float = 2.0 * M_PER_MM, xy_level_m: float = 0.300,
                        extent_step_m: float = 4.0 * M_PER_MM, extents_all_levels: bool = True,
                        ranges_m: tuple[float, float, float] = PAPER_RANGES_M,
                        cylinder_m: tuple[float, float] = PAPER_CYLINDER_M,
                        sphere: tuple[Sequence[float], float] = PAPER_SPHERE_M,
                        sphere_directions: int = 200,
                        progress: Callable[[float], None] | None = None) -> WorkspaceStudy:
    """Fig. 8 and the paper's workspace statements for one device.

    For every rotation range: the x–z section at y = 0 and the x–y section at ``xy_level_m``,
    the ranges in x, y, z (all levels, or only the first), and the largest sphere about the
    stated centre. At zero rotation (the first level must be 0): the tallest cylinder of the
    stated diameter and the widest of the stated height about the z axis. At the largest
    range: whether the stated sphere fits, and the largest range at which it does.
    """
    levels_deg = sorted(float(v) for v in levels_deg)
    if not levels_deg or levels_deg[0] != 0.0:
        raise DesignError('the rotation levels must include 0 (the cylinder and the ranges '
                          'are stated at zero rotation)')
    base = Workspace(geometry, limits)
    box = base.bounding_box()
    centre = np.asarray(sphere[0], dtype=np.float64)
    steps = 3 * len(levels_deg) + 4
    done = [0]

    def tick(frac: float = 1.0) -> None:
        if frac >= 1.0:
            done[0] += 1
        if progress is not None:
            progress(min(1.0, (done[0] + (frac if frac < 1.0 else 0.0)) / steps))

    out_levels = []
    for k, level in enumerate(levels_deg):
        ws = base.with_orientations(orientation_set(math.radians(level), points_per_axis, mode))
        xz = ws.section('xz', 0.0, section_step_m, box)
        xy = ws.section('xy', xy_level_m, section_step_m, box)
        tick()
        extents = None
        if extents_all_levels or k == 0:
            try:
                extents = ws.extents(extent_step_m, progress=lambda f: tick(min(f, 0.999)))
            except DesignError:
                extents = None
        tick()
        sph = ws.largest_sphere(centre, sphere_directions)
        tick()
        out_levels.append(Level(level, len(ws.orientations), xz, xy, extents, sph,
                                ws.sphere_binding(sph)))
    profile = base.disc_profile()
    tick()
    tallest = base.tallest_cylinder(cylinder_m[0], profile)
    tick()
    widest = base.widest_cylinder(cylinder_m[1], profile)
    tick()
    top_level = levels_deg[-1]
    sphere_range = largest_rotation_range(base, centre, sphere[1] / 2,
                                          points_per_axis=points_per_axis, mode=mode)
    tick()
    return WorkspaceStudy(limits, mode, points_per_axis, out_levels, ranges_m, cylinder_m,
                          centre, float(sphere[1]), tallest, widest, math.degrees(sphere_range),
                          top_level)
