"""Rigid-body helpers of the machine analysis: homogeneous transforms in batches, small-error
screws, and MMD poses (Eq. 3) as transforms with their covariance in screw coordinates.

A *screw* here is a 6-vector [v, w]: the translation v [m] of a stated point and the rotation
vector w [rad] of a small rigid motion, both in one frame's axes. A pose's covariance from the
pipeline is over [x, y, z, phi, theta, psi]; :func:`pose_covariance_to_screw` maps it to the
covariance of [dp, dw] with dw the rotation of {U} about {L}'s axes (left perturbation).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from mmd_ros.core.rotation import angle_rate_axes, rotation_matrix

__all__ = ['apply', 'compose_screw', 'inverse', 'pose_covariance_to_screw', 'pose_to_transform',
           'rotvec', 'screw_between', 'transform', 'rotation_from_rotvec']

FloatArray = NDArray[np.float64]


def transform(rot: ArrayLike, trans: ArrayLike) -> FloatArray:
    """Homogeneous transforms (N, 4, 4) from rotations (N, 3, 3) and translations (N, 3)."""
    r = np.asarray(rot, dtype=np.float64)
    t = np.asarray(trans, dtype=np.float64)
    n = np.broadcast_shapes(r.shape[:-2], t.shape[:-1])
    out = np.zeros(n + (4, 4))
    out[..., :3, :3] = r
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def inverse(t: FloatArray) -> FloatArray:
    """Inverse of homogeneous transforms (..., 4, 4)."""
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    return transform(rt, -np.einsum('...ij,...j->...i', rt, t[..., :3, 3]))


def apply(t: FloatArray, points: ArrayLike) -> FloatArray:
    """Transform points: t (..., 4, 4), points (..., 3) → (..., 3)."""
    p = np.asarray(points, dtype=np.float64)
    return np.einsum('...ij,...j->...i', t[..., :3, :3], p) + t[..., :3, 3]


def _skew(w: FloatArray) -> FloatArray:
    k = np.zeros(w.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return k


def rotation_from_rotvec(w: ArrayLike) -> FloatArray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) [rad] (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    small = theta < 1e-4
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(theta) / np.where(small, 1.0, theta))
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0,
                 (1.0 - np.cos(theta)) / np.where(small, 1.0, t2))
    k = _skew(w)
    return np.eye(3) + a * k + b * (k @ k)


def rotvec(r: ArrayLike) -> FloatArray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) [rad], for angles below
    about 170° (the log map; scipy for the rare larger ones)."""
    m = np.asarray(r, dtype=np.float64)
    vee = 0.5 * np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                          m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    s = np.linalg.norm(vee, axis=-1)
    c = 0.5 * (np.trace(m, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(s, c)
    small = s < 1e-8
    factor = np.where(small, 1.0 + theta * theta / 6.0, theta / np.where(small, 1.0, s))
    out = vee * factor[..., None]
    large = c < -0.98
    if np.any(large):
        flat = out.reshape(-1, 3)
        idx = np.flatnonzero(large.ravel())
        flat[idx] = Rotation.from_matrix(m.reshape(-1, 3, 3)[idx]).as_rotvec()
        out = flat.reshape(out.shape)
    return out


def compose_screw(w: ArrayLike, point: ArrayLike, v: ArrayLike) -> FloatArray:
    """The rigid motion that rotates by ``w`` (..., 3) about ``point`` (..., 3) and then
    translates by ``v`` (..., 3): the point moves by exactly ``v``. Shape (..., 4, 4)."""
    w = np.asarray(w, dtype=np.float64)
    r = rotation_from_rotvec(w)
    p = np.broadcast_to(np.asarray(point, dtype=np.float64), w.shape)
    return transform(r, p - np.einsum('...ij,...j->...i', r, p) + np.asarray(v, dtype=np.float64))


def screw_between(actual: FloatArray, nominal: FloatArray, point: ArrayLike) -> FloatArray:
    """Error screw [v, w] (..., 6) of ``actual`` against ``nominal`` (both (..., 4, 4), the
    same frame): v is the displacement of the body point that ``nominal`` puts at ``point``
    (..., 3, in that frame), w the rotation vector of actual · nominal⁻¹ (left perturbation)."""
    e = actual @ inverse(nominal)
    p = np.asarray(point, dtype=np.float64)
    v = apply(e, p) - p
    return np.concatenate([v, rotvec(e[..., :3, :3])], axis=-1)


def pose_to_transform(poses: ArrayLike) -> FloatArray:
    """Poses [x, y, z, phi, theta, psi] (..., 6) of {U} in {L} as transforms T_L_U (..., 4, 4),
    Eq. (3)."""
    p = np.asarray(poses, dtype=np.float64)
    return transform(rotation_matrix(p[..., 3:]), p[..., :3])


def pose_covariance_to_screw(poses: ArrayLike, covariance: ArrayLike) -> FloatArray:
    """Covariance (..., 6, 6) of [dp, dw] from that of [x, y, z, phi, theta, psi]: dw = E da
    with E the axes about which the angles turn {U} (:func:`angle_rate_axes`)."""
    p = np.asarray(poses, dtype=np.float64)
    c = np.asarray(covariance, dtype=np.float64)
    jac = np.zeros(p.shape[:-1] + (6, 6))
    jac[..., :3, :3] = np.eye(3)
    jac[..., 3:, 3:] = angle_rate_axes(p[..., 3:])
    return jac @ c @ np.swapaxes(jac, -1, -2)
