"""Kinematics of the MMD: inverse kinematics Eq. (6), the bar-length Jacobian, forward kinematics
by Newton's method, and pose covariance.

Conventions: a pose is ``[x, y, z, phi, theta, psi]`` of {U} in {L} [m, rad] (Eq. 1, angles as
in :mod:`mmd_ros.core.rotation`); bar ``i`` joins ``a_i`` on the upper plate (in {U}) to ``b_i``
on the lower plate (in {L}); its centre distance is ``d_i = |R a_i + t - b_i|`` (Eqs. 2, 6).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.errors import KinematicsError
from mmd_ros.core.rotation import angle_rate_axes, rotation_matrix

if TYPE_CHECKING:
    from mmd_ros.core.device import DeviceDescription

__all__ = [
    'BAR_RANGE_SLACK_M', 'CHUNK', 'TILT_SLACK_RAD', 'BatchSolution', 'FkLimits', 'FkStatus',
    'ForwardKinematics', 'Geometry', 'Solution', 'StreamSolution', 'inverse_kinematics',
    'jacobian', 'pose_covariance', 'propagate_covariance',
]

FloatArray = NDArray[np.float64]

#: Samples per batch chunk: small enough that the working arrays stay in cache.
CHUNK = 8192


@dataclass(frozen=True)
class Geometry:
    """Ball-joint centres of one device.

    upper : ndarray, shape (6, 3) — a_i in {U} [m]
    lower : ndarray, shape (6, 3) — b_i in {L} [m]
    """

    upper: FloatArray
    lower: FloatArray

    def __post_init__(self) -> None:
        for name in ('upper', 'lower'):
            value = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if value.shape != (6, 3):
                raise KinematicsError(f'{name} joints must have shape (6, 3), got {value.shape}')
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def scaled(self, factor_upper: float, factor_lower: float | None = None) -> Geometry:
        """The same device with both plates expanded by ``factor`` (1 + alpha * dT)."""
        if factor_lower is None:
            factor_lower = factor_upper
        return Geometry(self.upper * factor_upper, self.lower * factor_lower)

    @property
    def platform_radius(self) -> float:
        """Mean distance of the upper joints from the {U} origin [m]."""
        return float(np.mean(np.linalg.norm(self.upper, axis=1)))


def _legs(geometry: Geometry, poses: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotated upper joints R a_i (N, 6, 3) and leg vectors l_i = R a_i + t - b_i (N, 6, 3)."""
    rot = rotation_matrix(poses[:, 3:])
    ra = np.einsum('nij,kj->nki', rot, geometry.upper)
    legs = ra + poses[:, None, :3] - geometry.lower[None]
    return ra, legs


def inverse_kinematics(geometry: Geometry, poses: ArrayLike) -> FloatArray:
    """Eq. (6): centre distances of the six bars.

    poses : array_like, shape (6,) or (N, 6) [m, rad]
    returns : ndarray, shape (6,) or (N, 6) — d_i [m]
    """
    p = np.asarray(poses, dtype=np.float64)
    single = p.ndim == 1
    _, legs = _legs(geometry, np.atleast_2d(p))
    lengths = np.sqrt(np.einsum('nki,nki->nk', legs, legs))
    return lengths[0] if single else lengths


def _jacobian_from_legs(poses: FloatArray, ra: FloatArray, legs: FloatArray,
                        lengths: FloatArray) -> FloatArray:
    units = legs / lengths[..., None]
    jac = np.empty(poses.shape[:1] + (6, 6))
    jac[..., :3] = units
    # dd_i/d(angle k) = n_i . (w_k x R a_i) = w_k . (R a_i x n_i)
    moment = np.cross(ra, units)
    jac[..., 3:] = moment @ angle_rate_axes(poses[:, 3:])
    return jac


def jacobian(geometry: Geometry, poses: ArrayLike) -> FloatArray:
    """Jacobian of the centre distances with respect to the pose, dd/dp.

    poses : array_like, shape (6,) or (N, 6) [m, rad]
    returns : ndarray, shape (6, 6) or (N, 6, 6) — rows bars, columns x y z [1] and
        phi theta psi [m/rad]
    """
    p = np.asarray(poses, dtype=np.float64)
    single = p.ndim == 1
    p2 = np.atleast_2d(p)
    ra, legs = _legs(geometry, p2)
    lengths = np.sqrt(np.einsum('nki,nki->nk', legs, legs))
    jac = _jacobian_from_legs(p2, ra, legs, lengths)
    return jac[0] if single else jac


def pose_covariance(jac: ArrayLike, length_covariance: ArrayLike) -> FloatArray:
    """Pose covariance propagated from the bar-length covariance: J^-1 S J^-T.

    jac : array_like, shape (..., 6, 6) — dd/dp at the solution
    length_covariance : array_like, shape (6, 6), (6,) variances, or (..., 6, 6) [m^2]
    returns : ndarray, shape (..., 6, 6) — in [m, rad] squared units
    """
    j = np.asarray(jac, dtype=np.float64)
    s = np.asarray(length_covariance, dtype=np.float64)
    if s.ndim == 1:
        s = np.diag(s)
    jinv = np.linalg.inv(j)
    return jinv @ s @ np.swapaxes(jinv, -1, -2)


def nominal_pose(geometry: Geometry, lengths: FloatArray) -> FloatArray:
    """A starting pose for Newton's method: the upper plate level and centred, at the height
    whose mean squared bar length matches the measured one.

    lengths : ndarray, shape (N, 6) [m]
    returns : ndarray, shape (N, 6)
    """
    horizontal = geometry.upper[:, :2] - geometry.lower[:, :2]
    h2 = float(np.mean(np.sum(horizontal ** 2, axis=1)))
    z2 = np.mean(lengths ** 2, axis=1) - h2
    guess = np.zeros((lengths.shape[0], 6))
    guess[:, 2] = np.sqrt(np.maximum(z2, 1e-6)) + float(np.mean(geometry.lower[:, 2] - geometry.upper[:, 2]))
    return guess


def _evaluate_soa(a: FloatArray, b: FloatArray, p: FloatArray
                  ) -> tuple[FloatArray, list[FloatArray], list[FloatArray]]:
    """Lengths (N, 6), Jacobian columns and the upper plate's normal at poses ``p`` (N, 6), as
    component arrays.

    Structure of arrays: every quantity is an (N, 6) array per component, which keeps numpy on
    long contiguous loops (several times faster than (N, 6, 3) einsum/cross/matmul).
    Returns ``lengths``, ``cols`` with ``cols[k]`` the (N, 6) column dd/dp_k, and ``normal``,
    the three (N, 1) components of R e_z.
    """
    x, y, z = p[:, 0:1], p[:, 1:2], p[:, 2:3]
    cf, sf = np.cos(p[:, 3:4]), np.sin(p[:, 3:4])
    ct, st = np.cos(p[:, 4:5]), np.sin(p[:, 4:5])
    cp, sp = np.cos(p[:, 5:6]), np.sin(p[:, 5:6])
    stsf, stcf = st * sf, st * cf
    r00, r01, r02 = cp * ct, cp * stsf - sp * cf, sp * sf + cp * stcf
    r10, r11, r12 = sp * ct, cp * cf + sp * stsf, sp * stcf - cp * sf
    r20, r21, r22 = -st, ct * sf, ct * cf
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    rax = r00 * ax + r01 * ay + r02 * az
    ray = r10 * ax + r11 * ay + r12 * az
    raz = r20 * ax + r21 * ay + r22 * az
    lx = rax + (x - b[:, 0])
    ly = ray + (y - b[:, 1])
    lz = raz + (z - b[:, 2])
    lengths = np.sqrt(lx * lx + ly * ly + lz * lz)
    inv = 1.0 / lengths
    nx, ny, nz = lx * inv, ly * inv, lz * inv
    mx = ray * nz - raz * ny
    my = raz * nx - rax * nz
    mz = rax * ny - ray * nx
    j_phi = (cp * ct) * mx + (sp * ct) * my - st * mz
    j_theta = cp * my - sp * mx
    return lengths, [nx, ny, nz, j_phi, j_theta, mz], [r02, r12, r22]


def _stack_columns(cols: list[FloatArray]) -> FloatArray:
    """(N, 6) columns to (N, 6, 6) Jacobians, rows bars."""
    return np.stack(cols, axis=-1)


class FkStatus(IntEnum):
    """What became of one sample's forward kinematics: ``status`` of ``/mmd/fk_status``
    (``msg_docs/topics.md``). OK and RESEEDED are measurements; the others have no pose."""

    #: converged from the first start (the warm start, the batch's guess or the home seeds)
    #: to a pose that passed every test
    OK = 0
    #: the first start failed, jumped or landed on another assembly branch; a home seed gave a
    #: pose that passed every test (after a gap, a counter reset, a re-seated bar)
    RESEEDED = 1
    #: a length is not finite (a bar out of its calibrated span): not solved
    OUT_OF_SPAN = 2
    #: a length lies outside the bars' range: no pose has it
    BAR_RANGE = 3
    #: no start converged within the iteration cap
    NOT_CONVERGED = 4
    #: converged only to poses with a bar beyond a joint's tilt limit (another assembly branch)
    IMPLAUSIBLE = 5
    #: converged only to poses whose Jacobian is too ill-conditioned to trust (near a
    #: singularity)
    ILL_CONDITIONED = 6
    #: the warm start's pose moved faster than the device can since the last pose, and no home
    #: seed confirmed a pose
    DISCONTINUOUS = 7


#: Tolerance on the device's joint tilt limits in the plausibility test [rad]. The limits are
#: the joints' mechanical stops; the tilt computed from the CMM-measured joints is within 0.05°
#: of the true one (0.1 mm on a 250 mm bar). The other assembly branches Newton reaches from
#: unrelated starts lie at least 1.6° beyond a limit on the prototype (``bench/bench_fk.py``).
TILT_SLACK_RAD = math.radians(0.5)
#: Tolerance on the bars' range [m] (as for the reference distances in the device file).
BAR_RANGE_SLACK_M = 1e-3


@dataclass(frozen=True)
class FkLimits:
    """What a forward-kinematics solution must satisfy to be a measurement.

    bar_range_m : (shortest, longest) centre distance accepted [m]
    upper_tilt_rad, lower_tilt_rad : largest angle between a bar and the upper (lower) plate's
        normal [rad]; the default pi/2 only asks that the bars rise from the lower plate to the
        underside of the upper one
    max_condition : largest 1-norm condition number of the Jacobian with the angle columns
        scaled by the platform radius; over the prototype's workspace it is at most 26.5
        (measured), and at 1000 a one-count length error (50 nm) could move the pose by 50 µm
    max_speed_m_s : fastest pose change accepted from the warm start between two samples
        (angles times the platform radius) [m/s]; faster means a jump in the data, and the
        sample is re-solved from the home seeds. A machine tool's rapid traverse is up to
        about 1 m/s. Motion faster than this is still measured, at the cost of a re-seed.
    sample_period_s : time between samples when the caller gives none [s]
    """

    bar_range_m: tuple[float, float] = (0.0, math.inf)
    upper_tilt_rad: float = math.pi / 2
    lower_tilt_rad: float = math.pi / 2
    max_condition: float = 1000.0
    max_speed_m_s: float = 2.0
    sample_period_s: float = 1e-3

    def __post_init__(self) -> None:
        lo, hi = self.bar_range_m
        if not (0 <= lo < hi and 0 < self.upper_tilt_rad <= math.pi
                and 0 < self.lower_tilt_rad <= math.pi and self.max_condition >= 1
                and self.max_speed_m_s > 0 and self.sample_period_s > 0):
            raise KinematicsError(f'invalid forward-kinematics limits: {self}')

    @classmethod
    def from_device(cls, device: DeviceDescription, **overrides: float) -> FkLimits:
        """The device's bar range and joint tilt limits, with the tolerances
        :data:`BAR_RANGE_SLACK_M` and :data:`TILT_SLACK_RAD`, and its sample period."""
        lo, hi = device.bar_range_m
        values: dict = dict(
            bar_range_m=(max(lo - BAR_RANGE_SLACK_M, 0.0), hi + BAR_RANGE_SLACK_M),
            upper_tilt_rad=min(device.upper_tilt_rad + TILT_SLACK_RAD, math.pi),
            lower_tilt_rad=min(device.lower_tilt_rad + TILT_SLACK_RAD, math.pi),
            sample_period_s=1.0 / device.sample_rate_hz)
        values.update(overrides)
        return cls(**values)


@dataclass(frozen=True)
class Solution:
    """One forward-kinematics solution.

    pose : ndarray, shape (6,) — [m, rad]; NaN unless ``converged``
    converged : a start converged to a pose that passed every test (``status`` OK or
        RESEEDED); only such a pose is a measurement
    status : :class:`FkStatus` — why the sample is, or is not, a measurement
    iterations : Newton iterations taken, over every start tried
    residual_m : max |d - IK(pose)| at the last evaluation, before the final step [m]; an
        upper bound of the residual at ``pose``
    condition : 1-norm condition number of the Jacobian with angle columns scaled by the
        platform radius (dimensionless), at the last start that passed the tilt test; NaN if none
    jacobian : ndarray, shape (6, 6) — dd/dp at the last evaluation; NaN unless ``converged``
    """

    pose: FloatArray
    converged: bool
    status: FkStatus
    iterations: int
    residual_m: float
    condition: float
    jacobian: FloatArray


@dataclass(frozen=True)
class BatchSolution:
    """Forward-kinematics solutions of N samples; fields as in :class:`Solution`, shape (N, ...).

    status : ndarray of int8 — :class:`FkStatus` values
    jacobian_inverse : ndarray, shape (N, 6, 6), or None when not asked for — dp/dd at the
        solution (NaN unless converged), for :func:`propagate_covariance`
    """

    poses: FloatArray
    converged: NDArray[np.bool_]
    status: NDArray[np.int8]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    condition: FloatArray
    jacobian_inverse: FloatArray | None


@dataclass(frozen=True)
class StreamSolution:
    """Streaming solutions of N consecutive samples; fields as in :class:`Solution`, shape
    (N, ...). A sample with a non-finite length is not solved: NaN pose, residual, condition and
    Jacobian, status OUT_OF_SPAN, 0 iterations."""

    poses: FloatArray
    converged: NDArray[np.bool_]
    status: NDArray[np.int8]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    condition: FloatArray
    jacobians: FloatArray


#: Offsets in the packed constants the compiled solver reads (``P_*`` in ``_fast.c``).
_P_AB, _P_HOME, _P_HOME_LENGTHS, _P_HOME_JINV, _P_SCALARS, _P_SIZE = 0, 36, 42, 48, 84, 96


class ForwardKinematics:
    """Forward kinematics by Newton's method with the analytic Jacobian, and a plausibility test
    of every solution.

    The streaming path :meth:`solve` warm-starts from the previous poses (section 2.1:
    "initializing the iterative process with the previously estimated pose"), extrapolated at
    constant velocity from the last two solutions so that at 1 kHz two iterations usually
    suffice. The batch path :meth:`solve_batch` solves every sample on its own, from a given
    guess or from the home pose corrected by one linearised step.

    Convergence test on the pose step: Newton's error after a step of size s is at most
    ``kappa * s**2`` once in the quadratic regime, so a sample is converged when that bound is
    below ``tol_m`` in position and ``tol_rad * r`` in angle (r: platform radius; steps measured
    with angles scaled by r). Over the prototype's workspace kappa was measured at <= 21 /m;
    ``kappa_per_m`` = 1000 /m leaves a margin of 50. The residual at the pose is then bounded
    by the Jacobian's norm times that error.

    Newton converges to whichever solution of the forward kinematics is nearest its start, and
    a Stewart platform's has several (assembly branches): from a stale warm start after a jump
    in the data it can land on one the device cannot reach. So a converged pose is accepted
    only when every bar is within the joints' tilt limits at both plates — which bounds the
    height of every upper joint above its lower joint to [d_min cos(lower limit), d_max] — its
    Jacobian is well conditioned, the lengths are within the bars' range, and (warm start only)
    it moved no faster than ``limits.max_speed_m_s`` since the last pose. A start that fails is
    followed by the home seeds: the home pose plus one linearised step, then the home pose.
    What no start solves is flagged (``converged`` False, NaN pose, ``status`` the reason) and
    must not be used as a measurement.

    limits : :class:`FkLimits`; default: generic ones (no tilt or range limits of a device) —
        pass ``FkLimits.from_device(device)`` (or use :meth:`for_device`) for measurements
    """

    def __init__(self, geometry: Geometry, *, limits: FkLimits | None = None,
                 tol_m: float = 1e-12, tol_rad: float = 1e-12, max_iter: int = 20,
                 max_step_rad: float = 0.5, kappa_per_m: float = 1000.0) -> None:
        if not (tol_m > 0 and tol_rad > 0 and max_iter >= 1 and kappa_per_m > 0):
            raise KinematicsError('tolerances and kappa must be > 0 and max_iter >= 1')
        self.geometry = geometry
        self.limits = limits or FkLimits()
        self.tol_m = float(tol_m)
        self.tol_rad = float(tol_rad)
        self.max_iter = int(max_iter)
        self.max_step_rad = float(max_step_rad)
        radius = geometry.platform_radius
        self._radius = radius
        self._scale = np.array([1.0, 1.0, 1.0] + [1.0 / radius] * 3)
        # Largest accepted step, translation [m] and rotation [rad]: kappa * (step*)^2 = tol.
        self._step_m = math.sqrt(self.tol_m / kappa_per_m)
        self._step_rad = math.sqrt(self.tol_rad * radius / kappa_per_m) / radius
        self._cos_upper = math.cos(self.limits.upper_tilt_rad)
        self._cos_lower = math.cos(self.limits.lower_tilt_rad)
        # Scalar copies for the per-sample path: plain floats beat numpy on 6x3 arrays.
        self._ab = [(tuple(map(float, a)), tuple(map(float, b)))
                    for a, b in zip(geometry.upper, geometry.lower)]
        self._home = self._find_home()
        self._home_lengths = inverse_kinematics(geometry, self._home)
        self._home_jinv = np.linalg.inv(jacobian(geometry, self._home))
        self._packed = self._pack()
        self._history: list[list[float]] = []
        self._elapsed = 0.0

    @classmethod
    def for_device(cls, device: DeviceDescription, **kwargs) -> ForwardKinematics:
        """The solver of a device's geometry in use, with its limits (:meth:`FkLimits.from_device`)."""
        kwargs.setdefault('limits', FkLimits.from_device(device))
        return cls(device.geometry, **kwargs)

    def _find_home(self) -> FloatArray:
        """The level, centred pose with every bar near mid-range of its lengths at z."""
        mid = np.full((1, 6), 0.313)
        guess = nominal_pose(self.geometry, mid)
        return guess[0]

    def _pack(self) -> FloatArray:
        """The constants of the compiled solver, laid out as ``P_*`` in ``_fast.c``."""
        lim = self.limits
        v = np.zeros(_P_SIZE)
        v[_P_AB:_P_HOME] = np.hstack([self.geometry.upper, self.geometry.lower]).ravel()
        v[_P_HOME:_P_HOME_LENGTHS] = self._home
        v[_P_HOME_LENGTHS:_P_HOME_JINV] = self._home_lengths
        v[_P_HOME_JINV:_P_SCALARS] = self._home_jinv.ravel()
        v[_P_SCALARS:] = [self._step_m, self._step_rad, self.max_step_rad, self.max_iter,
                          lim.bar_range_m[0], lim.bar_range_m[1], self._cos_upper,
                          self._cos_lower, lim.max_condition, self._radius, lim.max_speed_m_s,
                          lim.sample_period_s]
        v.setflags(write=False)
        return v

    def reset(self) -> None:
        """Forget the warm start (after a gap in the data, for example)."""
        self._history = []
        self._elapsed = 0.0

    # -- one sample, in Python: the reference of the compiled solver ---------------------------
    def _evaluate(self, p: list[float], d: list[float]
                  ) -> tuple[list[list[float]], list[float], tuple[float, float, float]]:
        """Jacobian rows, residual d - IK(p) and the upper plate's normal R e_z at pose ``p``,
        in scalar maths."""
        x, y, z, phi, theta, psi = p
        cf, sf = math.cos(phi), math.sin(phi)
        ct, st = math.cos(theta), math.sin(theta)
        cp, sp = math.cos(psi), math.sin(psi)
        # the operations and their grouping are _evaluate_soa's, so that both round alike
        stsf, stcf = st * sf, st * cf
        r00, r01, r02 = cp * ct, cp * stsf - sp * cf, sp * sf + cp * stcf
        r10, r11, r12 = sp * ct, cp * cf + sp * stsf, sp * stcf - cp * sf
        r20, r21, r22 = -st, ct * sf, ct * cf
        w0x, w0y = cp * ct, sp * ct
        rows = []
        res = []
        for i, ((ax, ay, az), (bx, by, bz)) in enumerate(self._ab):
            rax = r00 * ax + r01 * ay + r02 * az
            ray = r10 * ax + r11 * ay + r12 * az
            raz = r20 * ax + r21 * ay + r22 * az
            lx, ly, lz = rax + (x - bx), ray + (y - by), raz + (z - bz)
            length = math.sqrt(lx * lx + ly * ly + lz * lz)
            inv = 1.0 / length
            nx, ny, nz = lx * inv, ly * inv, lz * inv
            mx, my, mz = ray * nz - raz * ny, raz * nx - rax * nz, rax * ny - ray * nx
            rows.append([nx, ny, nz, w0x * mx + w0y * my - st * mz, cp * my - sp * mx, mz])
            res.append(d[i] - length)
        return rows, res, (r02, r12, r22)

    def _newton(self, d: list[float], p: list[float]) -> tuple[
            bool, list[float], list[list[float]], _Lu, tuple[float, float, float], float, int]:
        """Newton from ``p``: (converged, pose, Jacobian rows, their LU factors, plate normal
        and residual of the last evaluation, evaluations)."""
        rows: list[list[float]] = []
        lu: _Lu = ([], [])
        normal = (math.nan, math.nan, math.nan)
        residual = math.nan
        tol_m, tol_rad, max_step = self._step_m, self._step_rad, self.max_step_rad
        for iterations in range(1, self.max_iter + 1):
            rows, res, normal = self._evaluate(p, d)
            residual = max(abs(r) for r in res)
            lu = _lu6(rows)
            if lu is None:
                return False, p, rows, ([], []), normal, residual, iterations
            s = _lu_solve6(lu, res)
            rot = max(abs(s[3]), abs(s[4]), abs(s[5]))
            if rot > max_step:  # damp wild steps far from the solution
                s = [v * (max_step / rot) for v in s]
            p = [pi + si for pi, si in zip(p, s)]
            if max(abs(s[0]), abs(s[1]), abs(s[2])) < tol_m and rot < tol_rad:
                return all(math.isfinite(v) for v in p), p, rows, lu, normal, residual, iterations
        return False, p, rows, lu, normal, residual, self.max_iter

    def _check_one(self, rows: list[list[float]], lu: _Lu, normal: tuple[float, float, float]
                   ) -> tuple[FkStatus, float, list[list[float]]]:
        """The acceptance tests of one converged pose (as :meth:`_check`, in scalar maths):
        status, condition (NaN when the tilt test failed) and J^-1 rows."""
        for n in rows:
            cos_upper = n[0] * normal[0] + n[1] * normal[1] + n[2] * normal[2]
            if not n[2] >= self._cos_lower or not cos_upper >= self._cos_upper:
                return FkStatus.IMPLAUSIBLE, math.nan, []
        jinv = _lu_inverse6(lu)
        inv_r = float(self._scale[3])
        # column sums of |J S| and |S^-1 J^-1|, rows added in order (as the compiled code)
        col_j = [0.0] * 6
        for row in rows:
            col_j = [c + abs(v if k < 3 else v * inv_r) for k, (c, v) in enumerate(zip(col_j, row))]
        col_inv = [0.0] * 6
        for i, row in enumerate(jinv):
            if i < 3:
                col_inv = [c + abs(v) for c, v in zip(col_inv, row)]
            else:
                col_inv = [c + abs(v / inv_r) for c, v in zip(col_inv, row)]
        cond = max(col_j) * max(col_inv)
        if not cond <= self.limits.max_condition:
            return FkStatus.ILL_CONDITIONED, cond, jinv
        return FkStatus.OK, cond, jinv

    def _home_step(self, d: list[float]) -> list[float]:
        """:meth:`_linearised_guess` of one sample, in scalar maths."""
        hl, hj = self._home_lengths.tolist(), self._home_jinv.tolist()
        out = []
        for j, h in enumerate(self._home.tolist()):
            acc = 0.0
            for m in range(6):
                acc += (d[m] - hl[m]) * hj[j][m]
            out.append(h + acc)
        return out

    def _continuous(self, p: list[float], prev: list[float], elapsed: float) -> bool:
        """Whether ``p`` is within ``max_speed * elapsed`` of ``prev`` (angles times r)."""
        r = self._radius
        moved = max(abs(u - v) * (1.0 if j < 3 else r) for j, (u, v) in enumerate(zip(p, prev)))
        return moved <= self.limits.max_speed_m_s * elapsed

    def _solve_seeds(self, d: list[float], first: list[float] | None, prev: list[float] | None,
                     elapsed: float) -> tuple[Solution, FloatArray]:
        """One sample from its starts (``first``, then the home seeds); the solution and J^-1."""
        nan6 = np.full(6, np.nan)
        nan66 = np.full((6, 6), np.nan)
        if not all(math.isfinite(v) for v in d):
            return Solution(nan6, False, FkStatus.OUT_OF_SPAN, 0, math.nan, math.nan, nan66), nan66
        lo, hi = self.limits.bar_range_m
        if not all(lo <= v <= hi for v in d):
            return Solution(nan6, False, FkStatus.BAR_RANGE, 0, math.nan, math.nan, nan66), nan66
        starts = ([lambda: first] if first is not None else []) + [
            lambda: self._home_step(d), self._home.tolist]
        worst = FkStatus.NOT_CONVERGED
        iterations = 0
        residual = condition = math.nan
        for k, start in enumerate(starts):
            ok, p, rows, lu, normal, residual, its = self._newton(d, list(start()))
            iterations += its
            status = FkStatus.NOT_CONVERGED
            if ok:
                status, cond, jinv = self._check_one(rows, lu, normal)
                if status != FkStatus.IMPLAUSIBLE:
                    condition = cond
                if status == FkStatus.OK and k == 0 and prev is not None \
                        and not self._continuous(p, prev, elapsed):
                    status = FkStatus.DISCONTINUOUS
                if status == FkStatus.OK:
                    return Solution(np.array(p), True, FkStatus.OK if k == 0 else FkStatus.RESEEDED,
                                    iterations, residual, condition, np.array(rows)), np.array(jinv)
            worst = max(worst, status)
        return Solution(nan6, False, worst, iterations, residual, condition, nan66), nan66

    def _check(self, jac: FloatArray, lu: FloatArray, ipiv: NDArray[np.intp], normal: FloatArray
               ) -> tuple[NDArray[np.int8], FloatArray, FloatArray]:
        """The acceptance tests of M converged poses from their last evaluation, in numpy with
        the operations of ``_fast.c``'s ``check``.

        jac : ndarray, shape (M, 6, 6); lu, ipiv : its factors (:func:`_lu_many`);
        normal : ndarray, shape (M, 3) — R e_z
        returns : status (M,) (OK, IMPLAUSIBLE or ILL_CONDITIONED), condition (M,) and J^-1
            (M, 6, 6), NaN where the tilt test failed
        """
        m = jac.shape[0]
        cos_upper = (jac[:, :, 0] * normal[:, 0:1] + jac[:, :, 1] * normal[:, 1:2]
                     + jac[:, :, 2] * normal[:, 2:3])
        upright = (np.all(jac[:, :, 2] >= self._cos_lower, axis=1)
                   & np.all(cos_upper >= self._cos_upper, axis=1))
        status = np.where(upright, FkStatus.OK, FkStatus.IMPLAUSIBLE).astype(np.int8)
        condition = np.full(m, np.nan)
        jinv = np.full((m, 6, 6), np.nan)
        idx = np.flatnonzero(upright)
        if idx.size:
            inv = _lu_solve_many(lu[idx], ipiv[idx], np.broadcast_to(np.eye(6), (idx.size, 6, 6)))
            jinv[idx] = inv
            scaled = np.abs(jac[idx] * self._scale)
            scaled_inv = np.abs(inv / self._scale[:, None])
            col_j, col_inv = scaled[:, 0, :], scaled_inv[:, 0, :]
            for i in range(1, 6):   # in order, as the compiled code adds
                col_j = col_j + scaled[:, i, :]
                col_inv = col_inv + scaled_inv[:, i, :]
            condition[idx] = np.max(col_j, axis=1) * np.max(col_inv, axis=1)
            bad = ~(condition[idx] <= self.limits.max_condition)
            status[idx[bad]] = FkStatus.ILL_CONDITIONED
        return status, condition, jinv

    # -- streaming -----------------------------------------------------------------------------
    def solve(self, lengths: ArrayLike, guess: ArrayLike | None = None, *,
              dt_s: float | None = None, compiled: bool | None = None) -> Solution:
        """Forward kinematics of one sample of a stream.

        lengths : array_like, shape (6,) — centre distances [m]; a non-finite one gives status
            OUT_OF_SPAN (not solved, the warm start kept)
        guess : array_like, shape (6,), optional — first start pose (no continuity test);
            default: extrapolated from the previous solutions, else the home seeds
        dt_s : time since the previous sample [s]; default ``limits.sample_period_s``
        compiled : the compiled solver (default: when it is in use, and no ``guess``); False:
            Python, the reference (the same result, bit for bit)
        """
        if guess is None and use_compiled(compiled):
            s = self.solve_stream(np.asarray(lengths, dtype=np.float64).reshape(1, -1),
                                  dt_s=None if dt_s is None else [dt_s], compiled=True)
            return Solution(s.poses[0], bool(s.converged[0]), FkStatus(int(s.status[0])),
                            int(s.iterations[0]), float(s.residual_m[0]), float(s.condition[0]),
                            s.jacobians[0])
        return self._solve_python(lengths, guess, dt_s)

    def _solve_python(self, lengths: ArrayLike, guess: ArrayLike | None,
                      dt_s: float | None) -> Solution:
        """:meth:`solve` in Python."""
        d = [float(v) for v in np.asarray(lengths, dtype=np.float64).ravel()]
        if len(d) != 6:
            raise KinematicsError(f'need six centre distances, got {lengths!r}')
        self._elapsed += self.limits.sample_period_s if dt_s is None else float(dt_s)
        first = prev = None
        history = self._history
        if guess is not None:
            first = [float(v) for v in np.asarray(guess, dtype=np.float64)]
        elif len(history) == 2:
            first = [2.0 * u - v for u, v in zip(history[1], history[0])]
            prev = history[1]
        elif history:
            first = prev = list(history[0])
        sol, _ = self._solve_seeds(d, first, prev, self._elapsed)
        if sol.converged:
            self._history = (history + [sol.pose.tolist()])[-2:]
            self._elapsed = 0.0
        elif sol.status != FkStatus.OUT_OF_SPAN:
            self._history = []
        return sol

    def solve_stream(self, lengths: ArrayLike, *, dt_s: ArrayLike | None = None,
                     compiled: bool | None = None) -> StreamSolution:
        """Forward kinematics of N consecutive samples, as :meth:`solve` called on each in turn
        (the same warm starts, iterations and tests).

        lengths : array_like, shape (N, 6) — centre distances [m]
        dt_s : array_like, shape (N,), optional — time since the previous sample [s] (from the
            stamps); default ``limits.sample_period_s`` each
        compiled : use the compiled solver (``_fast.c``; a transfer of 8 samples measured 12 us
            instead of 350 us, ``bench/bench_fk.py``); default: when it is in use
            (:mod:`mmd_ros.core.compiled`). False: the Python path.
        """
        d = np.ascontiguousarray(lengths, dtype=np.float64)
        if d.ndim != 2:
            d = np.atleast_2d(d)
        n = d.shape[0]
        if d.shape[1:] != (6,):
            raise KinematicsError(f'lengths must have shape (N, 6), got {d.shape}')
        dt = None if dt_s is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(dt_s, dtype=np.float64), (n,)))
        if use_compiled(compiled):
            out = StreamSolution(np.empty((n, 6)), np.empty(n, dtype=bool),
                                 np.empty(n, dtype=np.int8), np.empty(n, dtype=np.int64),
                                 np.empty(n), np.empty(n), np.empty((n, 6, 6)))
            state = np.zeros(14)
            if self._history:
                state[:6 * len(self._history)] = np.ravel(self._history)
            state[12] = len(self._history)
            state[13] = self._elapsed
            fast.solve_stream(self._packed, d, dt, state, out.poses, out.status, out.converged,
                              out.iterations, out.residual_m, out.condition, out.jacobians)
            kept = int(state[12])
            self._history = state[:6 * kept].reshape(kept, 6).tolist()
            self._elapsed = float(state[13])
            return out
        sols = [self._solve_python(d[i], None, None if dt is None else dt[i]) for i in range(n)]
        return StreamSolution(
            np.array([s.pose for s in sols]).reshape(n, 6),
            np.array([s.converged for s in sols], dtype=bool),
            np.array([s.status for s in sols], dtype=np.int8),
            np.array([s.iterations for s in sols], dtype=np.int64),
            np.array([s.residual_m for s in sols], dtype=np.float64),
            np.array([s.condition for s in sols], dtype=np.float64),
            np.array([s.jacobian for s in sols]).reshape(n, 6, 6))

    # -- batch ---------------------------------------------------------------------------------
    def _linearised_guess(self, d: FloatArray) -> FloatArray:
        """Home pose plus one Newton step taken with the home Jacobian: p0 + J0^-1 (d - d0)."""
        return self._home + (d - self._home_lengths) @ self._home_jinv.T

    def solve_batch(self, lengths: ArrayLike, guess: ArrayLike | None = None, *,
                    with_inverse: bool = False, workers: int | None = None,
                    compiled: bool | None = None) -> BatchSolution:
        """Forward kinematics of N independent samples.

        lengths : array_like, shape (N, 6) — centre distances [m]; a row with a non-finite
            value is not solved (status OUT_OF_SPAN)
        guess : array_like, shape (6,) or (N, 6), optional — first start poses (a row with a
            non-finite value: none for that sample); default the home seeds
        with_inverse : return the Jacobian inverses dp/dd (for covariance propagation)
        workers : threads; default: the machine's cores, at most 4
        compiled : use the compiled solver (default: when it is in use); False: numpy, the
            reference implementation

        Samples are solved in chunks of :data:`CHUNK` on a pool of threads: the compiled solver
        releases the GIL, numpy's array operations release it too. The condition number is
        always computed (it is one of the tests).
        """
        d = np.ascontiguousarray(np.atleast_2d(np.asarray(lengths, dtype=np.float64)))
        n = d.shape[0]
        if d.shape[1:] != (6,):
            raise KinematicsError(f'lengths must have shape (N, 6), got {d.shape}')
        g = None if guess is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(guess, dtype=np.float64), (n, 6)))
        out = BatchSolution(np.empty((n, 6)), np.empty(n, dtype=bool), np.empty(n, dtype=np.int8),
                            np.empty(n, dtype=np.int64), np.empty(n), np.empty(n),
                            np.empty((n, 6, 6)) if with_inverse else None)
        if use_compiled(compiled):
            _in_parts(lambda part: self._compiled(d, g, 0, out, part), n, CHUNK, workers)
        else:
            _in_parts(lambda part: self._solve_chunk(d[part], None if g is None else g[part], out,
                                                     part), n, CHUNK, workers)
        return out

    def _compiled(self, d: FloatArray, guess: FloatArray | None, stride: int,
                  out: BatchSolution, part: slice) -> None:
        """Samples ``part`` of ``d`` through the compiled batch solver (see ``_fast.c``)."""
        fast.solve_batch(self._packed, d, guess, stride, part.start, part.stop, out.poses[part],
                         out.status[part], out.converged[part], out.iterations[part],
                         out.residual_m[part], out.condition[part],
                         None if out.jacobian_inverse is None else out.jacobian_inverse[part])

    def solve_series(self, lengths: ArrayLike, *, stride: int = 16, with_inverse: bool = False,
                     compiled: bool | None = None) -> BatchSolution:
        """Forward kinematics of N consecutive samples of one motion (a log).

        Every ``stride``-th sample is solved first; the others start from the poses interpolated
        between those, so most converge in one or two iterations instead of three or four.
        Results are those of :meth:`solve_batch` (same tests); a sample whose neighbouring seeds
        failed starts from the home seeds. The compiled path (default when in use) gives the
        numpy path's results bit for bit.
        """
        d = np.ascontiguousarray(np.atleast_2d(np.asarray(lengths, dtype=np.float64)))
        n = d.shape[0]
        if n < 4 * stride:
            return self.solve_batch(d, with_inverse=with_inverse, compiled=compiled)
        if not use_compiled(compiled):
            seeds = self.solve_batch(d[::stride], compiled=False)
            guess = _series_guess(seeds.poses, seeds.converged, n, stride)
            return self.solve_batch(d, guess, with_inverse=with_inverse, compiled=False)
        # compiled: each thread solves the seeds its part needs and interpolates as it goes
        out = BatchSolution(np.empty((n, 6)), np.empty(n, dtype=bool), np.empty(n, dtype=np.int8),
                            np.empty(n, dtype=np.int64), np.empty(n), np.empty(n),
                            np.empty((n, 6, 6)) if with_inverse else None)
        _in_parts(lambda part: self._compiled(d, None, stride, out, part), n,
                  max(stride, CHUNK // stride * stride))
        return out

    def _solve_chunk(self, d: FloatArray, guess: FloatArray | None, out: BatchSolution,
                     part: slice) -> None:
        """numpy: the reference of the compiled batch solver. Each start is tried on the
        samples the previous ones left unsolved, all of them at once."""
        n = d.shape[0]
        finite = np.all(np.isfinite(d), axis=1)
        lo, hi = self.limits.bar_range_m
        in_range = finite & np.all((d >= lo) & (d <= hi), axis=1)
        status = np.where(finite, FkStatus.BAR_RANGE, FkStatus.OUT_OF_SPAN).astype(np.int8)
        worst = np.full(n, FkStatus.NOT_CONVERGED, dtype=np.int8)
        poses = np.full((n, 6), np.nan)
        iterations = np.zeros(n, dtype=np.int64)
        residual = np.full(n, np.nan)
        condition = np.full(n, np.nan)
        jinv = None if out.jacobian_inverse is None else np.full((n, 6, 6), np.nan)
        # a guess row with a non-finite value is no guess: that sample starts from the home seeds
        guessed = np.zeros(n, dtype=bool) if guess is None else np.all(np.isfinite(guess), axis=1)
        first = np.where(guessed, 0, 1)
        starts = [lambda idx: guess[idx], lambda idx: self._home_steps(d[idx]),
                  lambda idx: np.broadcast_to(self._home, (idx.size, 6))]
        pending = np.flatnonzero(in_range)
        for k, start in enumerate(starts):
            if k == 0:
                waiting, pending = pending[~guessed[pending]], pending[guessed[pending]]
            elif k == 1:
                pending = np.sort(np.concatenate([pending, waiting]))
            if pending.size == 0:
                continue
            p, ok, jac, lu, ipiv, normal, res, its = self._newton_many(d[pending],
                                                                       np.array(start(pending)))
            iterations[pending] += its
            residual[pending] = res
            st = np.full(pending.size, FkStatus.NOT_CONVERGED, dtype=np.int8)
            conv = np.flatnonzero(ok)
            if conv.size:
                st[conv], cond, inv = self._check(jac[conv], lu[conv], ipiv[conv], normal[conv])
                has = st[conv] != FkStatus.IMPLAUSIBLE
                condition[pending[conv[has]]] = cond[has]
                accepted = conv[st[conv] == FkStatus.OK]
                done = pending[accepted]
                status[done] = np.where(first[done] == k, FkStatus.OK, FkStatus.RESEEDED)
                poses[done] = p[accepted]
                if jinv is not None:
                    jinv[done] = inv[st[conv] == FkStatus.OK]
            worst[pending] = np.maximum(worst[pending], st)
            pending = pending[st != FkStatus.OK]
        status[pending] = worst[pending]
        out.poses[part] = poses
        out.status[part] = status
        out.converged[part] = status <= FkStatus.RESEEDED
        out.iterations[part] = iterations
        out.residual_m[part] = residual
        out.condition[part] = condition
        if jinv is not None:
            out.jacobian_inverse[part] = jinv

    def _home_steps(self, d: FloatArray) -> FloatArray:
        """:meth:`_linearised_guess` of M samples (M, 6), summed in the compiled code's order."""
        dd = d - self._home_lengths
        out = np.empty_like(dd)
        for j in range(6):
            acc = np.zeros(len(dd))
            for m in range(6):
                acc = acc + dd[:, m] * self._home_jinv[j, m]
            out[:, j] = self._home[j] + acc
        return out

    def _newton_many(self, d: FloatArray, poses: FloatArray) -> tuple[
            FloatArray, NDArray[np.bool_], FloatArray, FloatArray, NDArray[np.intp], FloatArray,
            FloatArray, NDArray[np.int64]]:
        """Newton on M samples at once, each until its own step test: poses (M, 6), converged
        (M,), and of each sample's last evaluation the Jacobian (M, 6, 6), its LU factors
        (M, 6, 6) and pivots (M, 6), the plate normal (M, 3) and the residual (M,); evaluations
        (M,). The arithmetic is the compiled solver's, operation for operation."""
        m = d.shape[0]
        converged = np.zeros(m, dtype=bool)
        iterations = np.zeros(m, dtype=np.int64)
        residual = np.full(m, np.nan)
        last_jac = np.full((m, 6, 6), np.nan)
        last_lu = np.full((m, 6, 6), np.nan)
        last_ipiv = np.zeros((m, 6), dtype=np.intp)
        last_normal = np.full((m, 3), np.nan)
        a, b = self.geometry.upper, self.geometry.lower
        active = np.arange(m)
        for _ in range(self.max_iter):
            if active.size == 0:
                break
            p = poses[active]
            cur, cols, normal = _evaluate_soa(a, b, p)
            res = d[active] - cur
            residual[active] = np.max(np.abs(res), axis=1)
            jac = _stack_columns(cols)
            last_jac[active] = jac
            last_normal[active] = np.hstack(normal)
            iterations[active] += 1
            lu, ipiv, ok = _lu_many(jac)
            last_lu[active] = lu
            last_ipiv[active] = ipiv
            with np.errstate(all='ignore'):   # a singular Jacobian stops its sample (not ok)
                step = _lu_solve_many(lu, ipiv, res[:, :, None])[:, :, 0]
                rot = np.max(np.abs(step[:, 3:]), axis=1)
                big = rot > self.max_step_rad
                if np.any(big):
                    step[big] *= (self.max_step_rad / rot[big])[:, None]
                new = p + step
            poses[active[ok]] = new[ok]
            done = (ok & (np.max(np.abs(step[:, :3]), axis=1) < self._step_m)
                    & (rot < self._step_rad))
            converged[active[done]] = True
            active = active[ok & ~done]
        converged &= np.all(np.isfinite(poses), axis=1)
        return poses, converged, last_jac, last_lu, last_ipiv, last_normal, residual, iterations


_POOLS: dict[int, ThreadPoolExecutor] = {}


def _in_parts(run: Callable[[slice], object], n: int, step: int, workers: int | None = None) -> None:
    """``run`` on the parts [k, k + step) of range(n), on a pool of ``workers`` threads (default:
    the machine's cores, at most 4) when there is more than one part. The compiled helpers and
    numpy's array operations release the GIL, so the parts run on every core."""
    starts = range(0, n, step)
    workers = workers or min(os.cpu_count() or 1, 4)
    parts = [slice(k, min(k + step, n)) for k in starts]
    if workers > 1 and len(parts) > 1:
        list(_pool(workers).map(run, parts))
    else:
        for part in parts:
            run(part)


def _pool(workers: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads kept for the process (created on first use)."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix='mmd-batch')
    return _POOLS[workers]


def propagate_covariance(jac_inverse: ArrayLike, length_covariance: ArrayLike,
                         plate_scale: ArrayLike | None = None, *,
                         compiled: bool | None = None) -> FloatArray:
    """Pose covariance of N samples from their bar-length covariance: D J^-1 S J^-T D.

    jac_inverse : array_like, shape (N, 6, 6) — dp/dd at each solution
    length_covariance : array_like, shape (N, 6, 6) per sample or (6, 6) shared — S [m^2]
    plate_scale : array_like, shape (N,), optional — the plates' expansion factor s: FK solved
        d / s with the nominal joints, so the translation rows and columns are times s
        (D = diag(s, s, s, 1, 1, 1))
    compiled : use the compiled helper (default: when it is in use; it releases the GIL and
        runs on every core for large N); False: numpy
    returns : ndarray, shape (N, 6, 6) — [m, rad]^2
    """
    jinv = np.ascontiguousarray(jac_inverse, dtype=np.float64)
    n = jinv.shape[0]
    if jinv.shape != (n, 6, 6):
        raise KinematicsError(f'jac_inverse must have shape (N, 6, 6), got {jinv.shape}')
    s_cov = np.ascontiguousarray(length_covariance, dtype=np.float64)
    if s_cov.shape not in ((6, 6), (n, 6, 6)):
        raise KinematicsError(f'length_covariance must have shape (6, 6) or ({n}, 6, 6), '
                              f'got {s_cov.shape}')
    scale = None if plate_scale is None else np.ascontiguousarray(
        np.broadcast_to(np.asarray(plate_scale, dtype=np.float64), (n,)))
    if use_compiled(compiled):
        out = np.empty((n, 6, 6))
        _in_parts(lambda part: fast.pose_covariance(
            jinv[part], s_cov if s_cov.ndim == 2 else s_cov[part],
            None if scale is None else scale[part], out[part]), n, CHUNK)
        return out
    cov = jinv @ s_cov @ np.swapaxes(jinv, -1, -2)
    if scale is not None:
        d = np.ones((n, 6))
        d[:, :3] = scale[:, None]
        cov = cov * d[:, :, None] * d[:, None, :]
    return cov


def _series_guess(seeds: FloatArray, ok: NDArray[np.bool_], n: int, stride: int) -> FloatArray:
    """Start poses for N samples interpolated linearly between solved seed samples (every
    ``stride``-th); NaN where a neighbouring seed did not converge."""
    seeds = np.where(ok[:, None], seeds, np.nan)
    k = np.arange(n)
    i = np.minimum(k // stride, len(seeds) - 1)
    j = np.minimum(i + 1, len(seeds) - 1)
    span = np.maximum((j - i) * stride, 1)
    frac = ((k - i * stride) / span)[:, None]
    return (1.0 - frac) * seeds[i] + frac * seeds[j]


_Lu = tuple[list[list[float]], list[int]]


def _lu6(a: list[list[float]]) -> _Lu | None:
    """LU factorisation with partial pivoting of one 6x6 matrix (rows), as ``_fast.c``'s
    ``lu6``: (factors, pivots), or None at an exactly zero pivot."""
    lu = [list(row) for row in a]
    ipiv = []
    for k in range(6):
        piv, big = k, abs(lu[k][k])
        for i in range(k + 1, 6):
            if abs(lu[i][k]) > big:
                piv, big = i, abs(lu[i][k])
        ipiv.append(piv)
        if lu[piv][k] == 0.0:
            return None
        if piv != k:
            lu[k], lu[piv] = lu[piv], lu[k]
        pivot_row = lu[k]
        for i in range(k + 1, 6):
            row = lu[i]
            f = row[k] / pivot_row[k]
            row[k] = f
            for j in range(k + 1, 6):
                row[j] -= f * pivot_row[j]
    return lu, ipiv


def _lu_solve6(factors: _Lu, b: list[float]) -> list[float]:
    """Solve A x = b with the factors of :func:`_lu6` (``_fast.c``'s ``lu_solve6``)."""
    lu, ipiv = factors
    x = list(b)
    for k, p in enumerate(ipiv):
        if p != k:
            x[k], x[p] = x[p], x[k]
    for k in range(6):
        for i in range(k + 1, 6):
            x[i] -= lu[i][k] * x[k]
    for i in range(5, -1, -1):
        s = x[i]
        for j in range(i + 1, 6):
            s -= lu[i][j] * x[j]
        x[i] = s / lu[i][i]
    return x


def _lu_inverse6(factors: _Lu) -> list[list[float]]:
    """The inverse (rows) from the factors of :func:`_lu6`: :func:`_lu_solve6` of the six unit
    vectors, all columns at once (``_fast.c``'s ``lu_inverse6``)."""
    lu, ipiv = factors
    x = [[1.0 if i == j else 0.0 for j in range(6)] for i in range(6)]
    for k, p in enumerate(ipiv):
        x[k], x[p] = x[p], x[k]
    for k in range(6):
        xk = x[k]
        for i in range(k + 1, 6):
            f = lu[i][k]
            x[i] = [a - f * b for a, b in zip(x[i], xk)]
    for i in range(5, -1, -1):
        s = x[i]
        for j in range(i + 1, 6):
            f = lu[i][j]
            s = [a - f * b for a, b in zip(s, x[j])]
        d = lu[i][i]
        x[i] = [v / d for v in s]
    return x


def _lu_many(a: FloatArray) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.bool_]]:
    """:func:`_lu6` of M matrices (M, 6, 6) at once: factors, pivots (M, 6), and ok (M,), False
    where a pivot is exactly zero (those factors are not usable)."""
    lu = np.array(a, dtype=np.float64)
    m = lu.shape[0]
    ipiv = np.zeros((m, 6), dtype=np.intp)
    ok = np.ones(m, dtype=bool)
    rows = np.arange(m)
    with np.errstate(all='ignore'):
        for k in range(6):
            piv = k + np.argmax(np.abs(lu[:, k:, k]), axis=1)   # the first largest
            ipiv[:, k] = piv
            ok &= lu[rows, piv, k] != 0.0
            top = lu[rows, k].copy()
            lu[rows, k] = lu[rows, piv]
            lu[rows, piv] = top
            f = lu[:, k + 1:, k] / lu[:, k:k + 1, k]
            lu[:, k + 1:, k] = f
            lu[:, k + 1:, k + 1:] -= f[:, :, None] * lu[:, k:k + 1, k + 1:]
    return lu, ipiv, ok


def _lu_solve_many(lu: FloatArray, ipiv: NDArray[np.intp], b: FloatArray) -> FloatArray:
    """:func:`_lu_solve6` of M systems with K right-hand sides: b (M, 6, K) → x (M, 6, K)."""
    x = np.array(b, dtype=np.float64)
    rows = np.arange(x.shape[0])
    for k in range(6):
        p = ipiv[:, k]
        top = x[rows, k].copy()
        x[rows, k] = x[rows, p]
        x[rows, p] = top
    for k in range(6):
        x[:, k + 1:] -= lu[:, k + 1:, k, None] * x[:, k:k + 1]
    for i in range(5, -1, -1):
        s = x[:, i].copy()
        for j in range(i + 1, 6):
            s -= lu[:, i, j, None] * x[:, j]
        x[:, i] = s / lu[:, i, i, None]
    return x
