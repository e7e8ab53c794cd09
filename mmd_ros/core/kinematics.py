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

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack

from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.errors import KinematicsError
from mmd_ros.core.rotation import angle_rate_axes, rotation_matrix

__all__ = [
    'CHUNK', 'BatchSolution', 'ForwardKinematics', 'Geometry', 'Solution', 'StreamSolution',
    'inverse_kinematics', 'jacobian', 'pose_covariance',
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
                  ) -> tuple[FloatArray, list[list[FloatArray]]]:
    """Lengths (N, 6) and Jacobian columns at poses ``p`` (N, 6), as component arrays.

    Structure of arrays: every quantity is an (N, 6) array per component, which keeps numpy on
    long contiguous loops (several times faster than (N, 6, 3) einsum/cross/matmul).
    Returns ``lengths`` and ``cols`` with ``cols[k]`` the (N, 6) column dd/dp_k.
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
    return lengths, [nx, ny, nz, j_phi, j_theta, mz]


def _stack_columns(cols: list[FloatArray]) -> FloatArray:
    """(N, 6) columns to (N, 6, 6) Jacobians, rows bars."""
    return np.stack(cols, axis=-1)


@dataclass(frozen=True)
class Solution:
    """One forward-kinematics solution.

    pose : ndarray, shape (6,) — [m, rad]; not a measurement when ``converged`` is False
    converged : the error bound of the last step fell below tolerance within the cap
    iterations : Newton iterations taken
    residual_m : max |d - IK(pose)| at the last evaluation, before the final step [m]; an
        upper bound of the residual at ``pose``
    condition : 1-norm condition number of the Jacobian with angle columns scaled by the
        platform radius (dimensionless); NaN when not asked for
    jacobian : ndarray, shape (6, 6) — dd/dp at the last evaluation
    """

    pose: FloatArray
    converged: bool
    iterations: int
    residual_m: float
    condition: float
    jacobian: FloatArray


@dataclass(frozen=True)
class BatchSolution:
    """Forward-kinematics solutions of N samples; fields as in :class:`Solution`, shape (N, ...).

    jacobian_inverse : ndarray, shape (N, 6, 6), or None when not asked for — dp/dd at the
        solution, for :func:`pose_covariance` style propagation
    """

    poses: FloatArray
    converged: NDArray[np.bool_]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    condition: FloatArray
    jacobian_inverse: FloatArray | None


@dataclass(frozen=True)
class StreamSolution:
    """Streaming solutions of N consecutive samples; fields as in :class:`Solution`, shape
    (N, ...). A sample with a non-finite length is not solved: NaN pose, residual and
    Jacobian, not converged, 0 iterations."""

    poses: FloatArray
    converged: NDArray[np.bool_]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    jacobians: FloatArray


class ForwardKinematics:
    """Forward kinematics by Newton's method with the analytic Jacobian.

    The streaming path :meth:`solve` warm-starts from the previous poses (section 2.1:
    "initializing the iterative process with the previously estimated pose"), extrapolated at
    constant velocity from the last two solutions so that at 1 kHz two iterations usually
    suffice. The batch path :meth:`solve_batch` iterates all samples at once, only on those not
    yet converged, from a given guess or from the home pose corrected by one linearised step.

    Convergence test on the pose step: Newton's error after a step of size s is at most
    ``kappa * s**2`` once in the quadratic regime, so a sample is converged when that bound is
    below ``tol_m`` in position and ``tol_rad * r`` in angle (r: platform radius; steps measured
    with angles scaled by r). Over the prototype's workspace kappa was measured at <= 21 /m;
    ``kappa_per_m`` = 1000 /m leaves a margin of 50. A sample not converged within ``max_iter``
    iterations is flagged (``converged`` False) and its pose must not be used as a measurement.
    """

    def __init__(self, geometry: Geometry, *, tol_m: float = 1e-12, tol_rad: float = 1e-12,
                 max_iter: int = 20, max_step_rad: float = 0.5,
                 kappa_per_m: float = 1000.0) -> None:
        if not (tol_m > 0 and tol_rad > 0 and max_iter >= 1 and kappa_per_m > 0):
            raise KinematicsError('tolerances and kappa must be > 0 and max_iter >= 1')
        self.geometry = geometry
        self.tol_m = float(tol_m)
        self.tol_rad = float(tol_rad)
        self.max_iter = int(max_iter)
        self.max_step_rad = float(max_step_rad)
        radius = geometry.platform_radius
        self._scale = np.array([1.0, 1.0, 1.0] + [1.0 / radius] * 3)
        # Largest accepted step, translation [m] and rotation [rad]: kappa * (step*)^2 = tol.
        self._step_m = math.sqrt(self.tol_m / kappa_per_m)
        self._step_rad = math.sqrt(self.tol_rad * radius / kappa_per_m) / radius
        # Scalar copies for the per-sample path: plain floats beat numpy on 6x3 arrays.
        self._ab = [(tuple(map(float, a)), tuple(map(float, b)))
                    for a, b in zip(geometry.upper, geometry.lower)]
        self._home = self._find_home()
        self._home_lengths = inverse_kinematics(geometry, self._home)
        self._home_jinv = np.linalg.inv(jacobian(geometry, self._home))
        self._ab_array = np.ascontiguousarray(np.hstack([geometry.upper, geometry.lower]))
        self._history: list[list[float]] = []

    def _find_home(self) -> FloatArray:
        """The level, centred pose with every bar near mid-range of its lengths at z."""
        mid = np.full((1, 6), 0.313)
        guess = nominal_pose(self.geometry, mid)
        return guess[0]

    def reset(self) -> None:
        """Forget the warm start (after a gap in the data, for example)."""
        self._history = []

    # -- streaming -----------------------------------------------------------------------------
    def _evaluate(self, p: list[float], d: list[float]) -> tuple[list[list[float]], list[float]]:
        """Jacobian rows and residual d - IK(p) at pose ``p``, in scalar maths."""
        x, y, z, phi, theta, psi = p
        cf, sf = math.cos(phi), math.sin(phi)
        ct, st = math.cos(theta), math.sin(theta)
        cp, sp = math.cos(psi), math.sin(psi)
        r00, r01, r02 = cp * ct, -sp * cf + cp * st * sf, sp * sf + cp * st * cf
        r10, r11, r12 = sp * ct, cp * cf + sp * st * sf, -cp * sf + sp * st * cf
        r20, r21, r22 = -st, ct * sf, ct * cf
        w0x, w0y = cp * ct, sp * ct
        rows = []
        res = []
        for i, ((ax, ay, az), (bx, by, bz)) in enumerate(self._ab):
            rax = r00 * ax + r01 * ay + r02 * az
            ray = r10 * ax + r11 * ay + r12 * az
            raz = r20 * ax + r21 * ay + r22 * az
            lx, ly, lz = rax + x - bx, ray + y - by, raz + z - bz
            length = math.sqrt(lx * lx + ly * ly + lz * lz)
            nx, ny, nz = lx / length, ly / length, lz / length
            mx, my, mz = ray * nz - raz * ny, raz * nx - rax * nz, rax * ny - ray * nx
            rows.append([nx, ny, nz, w0x * mx + w0y * my - st * mz, cp * my - sp * mx, mz])
            res.append(d[i] - length)
        return rows, res

    def solve(self, lengths: ArrayLike, guess: ArrayLike | None = None, *,
              with_condition: bool = False) -> Solution:
        """Forward kinematics of one sample.

        lengths : array_like, shape (6,) — centre distances [m]
        guess : array_like, shape (6,), optional — start pose; default: extrapolated from the
            previous solutions, else the home pose
        with_condition : also compute the Jacobian condition number
        """
        d = [float(v) for v in np.asarray(lengths, dtype=np.float64).ravel()]
        if len(d) != 6 or not all(math.isfinite(v) for v in d):
            raise KinematicsError(f'need six finite centre distances, got {lengths!r}')
        if guess is not None:
            p = [float(v) for v in np.asarray(guess, dtype=np.float64)]
        elif len(self._history) == 2:
            p = [2.0 * u - v for u, v in zip(self._history[1], self._history[0])]
        elif self._history:
            p = list(self._history[-1])
        else:
            p = self._linearised_guess(np.asarray(d)[None])[0].tolist()
        converged = False
        residual = math.inf
        rows: list[list[float]] = []
        iterations = 0
        tol_m, tol_rad, max_step = self._step_m, self._step_rad, self.max_step_rad
        for iterations in range(1, self.max_iter + 1):
            rows, res = self._evaluate(p, d)
            residual = max(abs(r) for r in res)
            _, _, step, info = lapack.dgesv(np.array(rows), np.array(res))
            if info != 0:
                break
            s = step.tolist()
            rot = max(abs(s[3]), abs(s[4]), abs(s[5]))
            if rot > max_step:  # damp wild steps far from the solution
                s = [v * (max_step / rot) for v in s]
            p = [pi + si for pi, si in zip(p, s)]
            if max(abs(s[0]), abs(s[1]), abs(s[2])) < tol_m and rot < tol_rad:
                converged = all(math.isfinite(v) for v in p)
                break
        if converged:
            self._history = (self._history + [p])[-2:]
        else:
            self._history = []
        jac = np.array(rows) if rows else np.full((6, 6), np.nan)
        condition = math.nan
        if with_condition and converged:
            condition = float(np.linalg.cond(jac * self._scale, 1))
        return Solution(np.array(p), converged, iterations, residual, condition, jac)

    def solve_stream(self, lengths: ArrayLike, *, compiled: bool | None = None) -> StreamSolution:
        """Forward kinematics of N consecutive samples, as :meth:`solve` called on each in turn
        (the same warm starts, iterations and convergence test).

        lengths : array_like, shape (N, 6) — centre distances [m]
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
        if use_compiled(compiled):
            out = StreamSolution(np.empty((n, 6)), np.empty(n, dtype=bool),
                                 np.empty(n, dtype=np.int64), np.empty(n), np.empty((n, 6, 6)))
            history = np.zeros((2, 6))
            if self._history:
                history[:len(self._history)] = self._history
            kept = fast.solve_stream(
                (self._step_m, self._step_rad, self.max_step_rad, self.max_iter), self._ab_array,
                self._home, self._home_lengths, self._home_jinv, d, history, len(self._history),
                out.poses, out.converged, out.iterations, out.residual_m, out.jacobians)
            self._history = history[:kept].tolist()
            return out
        out = StreamSolution(np.full((n, 6), np.nan), np.zeros(n, dtype=bool),
                             np.zeros(n, dtype=np.int64), np.full(n, np.nan),
                             np.full((n, 6, 6), np.nan))
        for i in np.flatnonzero(np.isfinite(d).all(axis=1)):
            sol = self.solve(d[i])
            out.poses[i] = sol.pose
            out.converged[i] = sol.converged
            out.iterations[i] = sol.iterations
            out.residual_m[i] = sol.residual_m
            out.jacobians[i] = sol.jacobian
        return out

    # -- batch ---------------------------------------------------------------------------------
    def _linearised_guess(self, d: FloatArray) -> FloatArray:
        """Home pose plus one Newton step taken with the home Jacobian: p0 + J0^-1 (d - d0)."""
        return self._home + (d - self._home_lengths) @ self._home_jinv.T

    def solve_batch(self, lengths: ArrayLike, guess: ArrayLike | None = None, *,
                    with_condition: bool = False, with_inverse: bool = False,
                    workers: int | None = None) -> BatchSolution:
        """Forward kinematics of N samples at once.

        lengths : array_like, shape (N, 6) — centre distances [m]; a row with a non-finite
            value is not solved and comes back not converged
        guess : array_like, shape (6,) or (N, 6), optional — start poses; default home pose
            plus one linearised step
        with_condition : compute each Jacobian's condition number (costs an inverse)
        with_inverse : return the Jacobian inverses dp/dd (for covariance propagation)
        workers : threads (numpy releases the GIL); default: the machine's cores, at most 4

        Samples are solved in chunks of :data:`CHUNK` that fit the CPU cache, which is faster
        than whole-array passes for large N.
        """
        d = np.atleast_2d(np.asarray(lengths, dtype=np.float64))
        n = d.shape[0]
        if d.shape[1:] != (6,):
            raise KinematicsError(f'lengths must have shape (N, 6), got {d.shape}')
        g = None if guess is None else np.broadcast_to(np.asarray(guess, dtype=np.float64), (n, 6))
        starts = range(0, n, CHUNK)
        if len(starts) <= 1:
            return self._solve_chunk(d, g, with_condition, with_inverse)
        workers = workers or min(os.cpu_count() or 1, 4)

        def run(start: int) -> BatchSolution:
            stop = start + CHUNK
            return self._solve_chunk(d[start:stop], None if g is None else g[start:stop],
                                     with_condition, with_inverse)

        if workers > 1:
            with ThreadPoolExecutor(workers) as pool:
                parts = list(pool.map(run, starts))
        else:
            parts = [run(start) for start in starts]
        return BatchSolution(
            np.concatenate([q.poses for q in parts]),
            np.concatenate([q.converged for q in parts]),
            np.concatenate([q.iterations for q in parts]),
            np.concatenate([q.residual_m for q in parts]),
            np.concatenate([q.condition for q in parts]),
            np.concatenate([q.jacobian_inverse for q in parts]) if with_inverse else None)

    def solve_series(self, lengths: ArrayLike, *, stride: int = 16, with_condition: bool = False,
                     with_inverse: bool = False) -> BatchSolution:
        """Forward kinematics of N consecutive samples of one motion (a log).

        Every ``stride``-th sample is solved first; the others start from the poses interpolated
        between those, so most converge in one or two iterations instead of three or four.
        Results are those of :meth:`solve_batch` (same convergence test); a sample whose
        neighbouring seeds failed starts from the default guess.
        """
        d = np.atleast_2d(np.asarray(lengths, dtype=np.float64))
        n = d.shape[0]
        if n < 4 * stride:
            return self.solve_batch(d, with_condition=with_condition, with_inverse=with_inverse)
        seeds = self.solve_batch(d[::stride])
        guess = _series_guess(seeds.poses, seeds.converged, n, stride)
        bad = ~np.all(np.isfinite(guess), axis=1)
        if np.any(bad):
            guess[bad] = self._linearised_guess(np.where(np.isfinite(d[bad]), d[bad], self._home_lengths))
        return self.solve_batch(d, guess, with_condition=with_condition, with_inverse=with_inverse)

    def _solve_chunk(self, d: FloatArray, guess: FloatArray | None, with_condition: bool,
                     with_inverse: bool) -> BatchSolution:
        n = d.shape[0]
        finite = np.all(np.isfinite(d), axis=1)
        if guess is None:
            poses = self._linearised_guess(np.where(finite[:, None], d, self._home_lengths))
        else:
            poses = np.array(guess)
        converged = np.zeros(n, dtype=bool)
        iterations = np.zeros(n, dtype=np.int64)
        residual = np.full(n, np.inf)
        last_jac = np.full((n, 6, 6), np.nan) if (with_condition or with_inverse) else None
        a, b = self.geometry.upper, self.geometry.lower
        active = np.flatnonzero(finite)
        for _ in range(self.max_iter):
            if active.size == 0:
                break
            p = poses[active]
            cur, cols = _evaluate_soa(a, b, p)
            res = d[active] - cur
            residual[active] = np.max(np.abs(res), axis=1)
            jac = _stack_columns(cols)
            if last_jac is not None:
                last_jac[active] = jac
            step, ok = _solve_many(jac, res)
            rot = np.max(np.abs(step[:, 3:]), axis=1)
            big = rot > self.max_step_rad
            if np.any(big):
                step[big] *= (self.max_step_rad / rot[big])[:, None]
                rot[big] = self.max_step_rad
            poses[active] = p + step
            iterations[active] += 1
            done = (ok & (np.max(np.abs(step[:, :3]), axis=1) < self._step_m)
                    & (rot < self._step_rad))
            converged[active[done]] = True
            active = active[ok & ~done]
        converged &= np.all(np.isfinite(poses), axis=1)
        condition = np.full(n, np.nan)
        jinv = None
        if last_jac is not None:
            jinv = np.full((n, 6, 6), np.nan)
            idx = np.flatnonzero(converged)
            if idx.size:
                jinv[idx] = np.linalg.inv(last_jac[idx])
                if with_condition:
                    scaled = last_jac[idx] * self._scale
                    scaled_inv = jinv[idx] / self._scale[:, None]
                    condition[idx] = (np.max(np.sum(np.abs(scaled), axis=1), axis=1)
                                      * np.max(np.sum(np.abs(scaled_inv), axis=1), axis=1))
        return BatchSolution(poses, converged, iterations, residual, condition,
                             jinv if with_inverse else None)


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


def _solve_many(jac: FloatArray, res: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Solve J x = r for a stack; a singular matrix gives x = 0 and ok False, not an exception."""
    try:
        return np.linalg.solve(jac, res[..., None])[..., 0], np.ones(len(res), dtype=bool)
    except np.linalg.LinAlgError:
        step = np.zeros_like(res)
        ok = np.zeros(len(res), dtype=bool)
        for k in range(len(res)):
            try:
                step[k] = np.linalg.solve(jac[k], res[k])
                ok[k] = True
            except np.linalg.LinAlgError:
                pass
        return step, ok
