"""The twin's own inverse kinematics, Eqs. (2)-(6), and its workspace check.

Written independently of :mod:`mmd_ros.core.kinematics` so that the data the twin generates
does not share code with the software that evaluates it. The rotation of Eq. (3),
R = Rz(psi) Ry(theta) Rx(phi), is scipy's intrinsic ``from_euler('ZYX', [psi, theta, phi])``.
A pose is [x, y, z, phi, theta, psi] of {U} in {L} [m, rad]; bar i joins a_i (in {U}) to b_i
(in {L}).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from mmd_ros.core.device import DeviceDescription
from mmd_ros.twin.errors import WorkspaceError

__all__ = ['bar_legs', 'check_workspace', 'random_poses', 'rotation_matrices', 'within_workspace']

FloatArray = NDArray[np.float64]


def rotation_matrices(poses: ArrayLike) -> FloatArray:
    """Eq. (3) for many poses.

    poses : array_like, shape (N, 6) — [x, y, z, phi, theta, psi] [m, rad]
    returns : ndarray, shape (N, 3, 3) — L_R_U
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    return Rotation.from_euler('ZYX', p[:, [5, 4, 3]]).as_matrix()


def bar_legs(upper: ArrayLike, lower: ArrayLike, poses: ArrayLike,
             rotations: FloatArray | None = None, scale_upper: ArrayLike = 1.0,
             scale_lower: ArrayLike = 1.0) -> FloatArray:
    """Bar vectors L_a_i - L_b_i, Eqs. (2), (6); their norms are the centre distances d_i.

    upper : array_like, shape (6, 3) — a_i in {U} [m]
    lower : array_like, shape (6, 3) — b_i in {L} [m]
    poses : array_like, shape (N, 6) [m, rad]
    rotations : ndarray, shape (N, 3, 3), optional — Eq. (3) of ``poses`` if already known
    scale_upper, scale_lower : float or array_like, shape (N,) — thermal growth factors
        1 + alpha dT of the two plates
    returns : ndarray, shape (N, 6, 3) [m]
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    r = rotation_matrices(p) if rotations is None else rotations
    a = np.asarray(upper, dtype=np.float64)
    ra = (r.reshape(-1, 3) @ a.T).reshape(-1, 3, a.shape[0]).transpose(0, 2, 1)
    su = np.asarray(scale_upper, dtype=np.float64).reshape(-1, 1, 1)
    sl = np.asarray(scale_lower, dtype=np.float64).reshape(-1, 1, 1)
    return su * ra + p[:, None, :3] - sl * np.asarray(lower, dtype=np.float64)


def _limit_checks(device: DeviceDescription, legs: FloatArray, rotations: FloatArray,
                  margin_m: float, margin_rad: float) -> list[tuple[NDArray, FloatArray, str, str]]:
    """(violating (N, 6), value (N, 6), description, unit) for each limit of the device."""
    length = np.linalg.norm(legs, axis=2)
    lo, hi = device.bar_range_m
    cos_lower = np.clip(legs[:, :, 2] / length, -1.0, 1.0)
    cos_upper = np.clip(np.einsum('nk,njk->nj', rotations[:, :, 2], legs) / length, -1.0, 1.0)
    lower_limit = device.lower_tilt_rad - margin_rad
    upper_limit = device.upper_tilt_rad - margin_rad
    return [
        (length < lo + margin_m, length * 1e3, f'shorter than the bar range start {lo * 1e3:.3f} mm', 'mm'),
        (length > hi - margin_m, length * 1e3, f'longer than the bar range end {hi * 1e3:.3f} mm', 'mm'),
        (cos_lower < np.cos(lower_limit), np.degrees(np.arccos(cos_lower)),
         f'tilted beyond the lower joint limit {np.degrees(device.lower_tilt_rad):.2f}°', '°'),
        (cos_upper < np.cos(upper_limit), np.degrees(np.arccos(cos_upper)),
         f'tilted beyond the upper joint limit {np.degrees(device.upper_tilt_rad):.2f}°', '°'),
    ]


def within_workspace(device: DeviceDescription, legs: FloatArray, rotations: FloatArray,
                     margin_m: float = 0.0, margin_rad: float = 0.0) -> NDArray[np.bool_]:
    """Whether each pose keeps every bar in range and every joint within its tilt limit, with
    margins to spare.

    legs : ndarray, shape (N, 6, 3) — bar vectors [m]
    rotations : ndarray, shape (N, 3, 3) — L_R_U of each pose
    returns : ndarray of bool, shape (N,)
    """
    bad = np.zeros(legs.shape[0], dtype=bool)
    for violating, _, _, _ in _limit_checks(device, legs, rotations, margin_m, margin_rad):
        bad |= violating.any(axis=1)
    return ~bad


def check_workspace(device: DeviceDescription, times_s: ArrayLike, legs: FloatArray,
                    rotations: FloatArray, what: str) -> None:
    """Refuse motion that leaves the bars' range or tilts a bar beyond a joint's limit.

    times_s : array_like, shape (N,) — time of each pose [s]
    legs : ndarray, shape (N, 6, 3) — bar vectors [m]
    rotations : ndarray, shape (N, 3, 3) — L_R_U of each pose
    what : str — the scenario, for the message
    Raises :class:`WorkspaceError` naming the first offending time and bar.
    """
    t = np.asarray(times_s, dtype=np.float64)
    first = None
    for bad, value, text, unit in _limit_checks(device, legs, rotations, 0.0, 0.0):
        if np.any(bad):
            n, i = np.argwhere(bad)[0]
            if first is None or n < first[0]:
                first = (n, i, value[n, i], text, unit)
    if first is not None:
        n, i, value, text, unit = first
        raise WorkspaceError(
            f'{what}: at t = {t[n]:.3f} s bar {i + 1} is {value:.3f} {unit}, {text}; '
            'move the scenario (start pose, travel or angles) back into the workspace')


def random_poses(device: DeviceDescription, n: int, seed: int, *, inside: bool = True
                 ) -> tuple[FloatArray, FloatArray]:
    """n random poses across a box around the workspace, each unrelated to the one before
    (forward-kinematics jumps), and their centre distances, from this module's kinematics.

    inside : only poses the device can reach (every bar in range and within the joints' tilt
        limits); else every pose whose bars are in range
    returns : poses (n, 6) [m, rad], lengths (n, 6) [m]
    """
    rng = np.random.default_rng(seed)
    m = min(40 * n, 400_000)
    p = np.column_stack([rng.uniform(-0.16, 0.16, (m, 2)), rng.uniform(0.22, 0.38, m),
                         rng.uniform(-0.3, 0.3, (m, 2)), rng.uniform(-0.8, 0.8, m)])
    rot = rotation_matrices(p)
    legs = bar_legs(device.geometry.upper, device.geometry.lower, p, rot)
    d = np.linalg.norm(legs, axis=2)
    lo, hi = device.bar_range_m
    keep = within_workspace(device, legs, rot) if inside else np.all((d > lo) & (d < hi), axis=1)
    if keep.sum() < n:
        raise WorkspaceError(f'only {int(keep.sum())} of {m} random poses kept; ask for fewer')
    return p[keep][:n], d[keep][:n]
