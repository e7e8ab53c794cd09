"""The paper's angle convention, stated once: Eq. (3).

A pose is ``p = [x, y, z, phi, theta, psi]`` (Eq. 1): the position of the origin of {U} in {L}
[m] and roll, pitch, yaw [rad]. The rotation of {U} into {L} is

    L_R_U = Rz(psi) @ Ry(theta) @ Rx(phi)                                   (Eq. 3)

i.e. intrinsic z-y'-x'' (scipy ``Rotation.from_euler('ZYX', [psi, theta, phi])``).
Quaternions are ordered x, y, z, w (ROS and scipy agree).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['angle_rate_axes', 'angles_to_quaternion', 'matrix_to_angles', 'quaternion_to_angles',
           'rotation_angle', 'rotation_matrix']


def rotation_matrix(angles: ArrayLike) -> NDArray[np.float64]:
    """Eq. (3): rotation matrix ``L_R_U`` from roll, pitch, yaw.

    angles : array_like, shape (..., 3) — phi, theta, psi [rad]
    returns : ndarray, shape (..., 3, 3)
    """
    a = np.asarray(angles, dtype=np.float64)
    cf, sf = np.cos(a[..., 0]), np.sin(a[..., 0])
    ct, st = np.cos(a[..., 1]), np.sin(a[..., 1])
    cp, sp = np.cos(a[..., 2]), np.sin(a[..., 2])
    r = np.empty(a.shape[:-1] + (3, 3))
    r[..., 0, 0] = cp * ct
    r[..., 0, 1] = -sp * cf + cp * st * sf
    r[..., 0, 2] = sp * sf + cp * st * cf
    r[..., 1, 0] = sp * ct
    r[..., 1, 1] = cp * cf + sp * st * sf
    r[..., 1, 2] = -cp * sf + sp * st * cf
    r[..., 2, 0] = -st
    r[..., 2, 1] = ct * sf
    r[..., 2, 2] = ct * cf
    return r


def angle_rate_axes(angles: ArrayLike) -> NDArray[np.float64]:
    """Axes in {L} about which a change of phi, theta, psi rotates {U}.

    For Eq. (3), dR/d(angle k) @ v = w_k x (R @ v) with w_psi = e_z, w_theta = Rz(psi) e_y and
    w_phi = Rz(psi) Ry(theta) e_x. The Jacobian of the bar lengths uses this form.

    angles : array_like, shape (..., 3) [rad]
    returns : ndarray, shape (..., 3, 3) — column k is w_k
    """
    a = np.asarray(angles, dtype=np.float64)
    ct, st = np.cos(a[..., 1]), np.sin(a[..., 1])
    cp, sp = np.cos(a[..., 2]), np.sin(a[..., 2])
    w = np.zeros(a.shape[:-1] + (3, 3))
    w[..., 0, 0] = cp * ct
    w[..., 1, 0] = sp * ct
    w[..., 2, 0] = -st
    w[..., 0, 1] = -sp
    w[..., 1, 1] = cp
    w[..., 2, 2] = 1.0
    return w


def matrix_to_angles(r: ArrayLike) -> NDArray[np.float64]:
    """Inverse of Eq. (3) for |theta| < 90°.

    r : array_like, shape (..., 3, 3)
    returns : ndarray, shape (..., 3) — phi, theta, psi [rad]
    """
    m = np.asarray(r, dtype=np.float64)
    phi = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    theta = np.arcsin(np.clip(-m[..., 2, 0], -1.0, 1.0))
    psi = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.stack([phi, theta, psi], axis=-1)


def angles_to_quaternion(angles: ArrayLike) -> NDArray[np.float64]:
    """Quaternion x, y, z, w of Eq. (3): q = qz(psi) * qy(theta) * qx(phi).

    angles : array_like, shape (..., 3) [rad]
    returns : ndarray, shape (..., 4), unit norm, w >= 0 not enforced
    """
    a = np.asarray(angles, dtype=np.float64) * 0.5
    c, s = np.cos(a), np.sin(a)  # (one call each: a live transfer has only 8 rows)
    cf, ct, cp = c[..., 0], c[..., 1], c[..., 2]
    sf, st, sp = s[..., 0], s[..., 1], s[..., 2]
    ctcp, stsp, ctsp, stcp = ct * cp, st * sp, ct * sp, st * cp
    out = np.empty(a.shape[:-1] + (4,))
    np.subtract(sf * ctcp, cf * stsp, out=out[..., 0])
    np.add(cf * stcp, sf * ctsp, out=out[..., 1])
    np.subtract(cf * ctsp, sf * stcp, out=out[..., 2])
    np.add(cf * ctcp, sf * stsp, out=out[..., 3])
    return out


def quaternion_to_angles(q: ArrayLike) -> NDArray[np.float64]:
    """Roll, pitch, yaw of Eq. (3) from a quaternion x, y, z, w.

    q : array_like, shape (..., 4)
    returns : ndarray, shape (..., 3) [rad]
    """
    v = np.asarray(q, dtype=np.float64)
    x, y, z, w = v[..., 0], v[..., 1], v[..., 2], v[..., 3]
    phi = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    theta = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    psi = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack([phi, theta, psi], axis=-1)


def rotation_angle(r: ArrayLike) -> NDArray[np.float64]:
    """Angle [rad] in [0, pi] of rotation matrices, shape (..., 3, 3) -> (...): atan2 of the
    skew part's norm (2 sin) and the trace (1 + 2 cos), accurate at every angle (an arcsin of
    the skew part alone folds angles over 90°, an arccos of the trace loses small ones)."""
    m = np.asarray(r, dtype=np.float64)
    v = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                  m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    return np.arctan2(np.linalg.norm(v, axis=-1), np.trace(m, axis1=-2, axis2=-1) - 1.0)
