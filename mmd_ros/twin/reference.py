"""Reference instruments sampled in sync with the terminal (sections 4.2, 5.2, 5.3).

The paper triggers the laser interferometer (XL80) together with the MMD; the rotary axis
calibrator (XR20-W) gives angles. The twin reads the true, actual pose:

- ``pose6``: all six components (a six-dimensional reference the paper wished it had);
- ``laser_x``, ``laser_y``, ``laser_z``: one position component of the origin of {U} in {L};
- ``rotary_phi``, ``rotary_theta``, ``rotary_psi``: one angle;
- ``bar_lengths``: the true centre distances of the six measuring bars (a bar resting on a
  reference pair, section 4.1, or a bar beside an interferometer, section 4.2).

Pose kinds return shape (N, 6) with NaN in the components the instrument does not measure;
``bar_lengths`` returns (N, 6). Positions and lengths are absolute (the laser's reset to zero
at the start pose is left to the evaluation).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from mmd_ros.twin.errors import TwinError
from mmd_ros.twin.physics import STREAM_REFERENCE, hashed_normal, stream_key
from mmd_ros.twin.trajectories import AXES

__all__ = ['POSE_NOISE', 'REFERENCE_KINDS', 'reference_names', 'reference_values']

FloatArray = NDArray[np.float64]

#: Noise (standard deviation) of the reference per pose component: 1 nm, the XL80's
#: resolution, and 0.1 arc-second for angles.
POSE_NOISE = np.array([1e-9, 1e-9, 1e-9] + [math.radians(0.1 / 3600.0)] * 3)

REFERENCE_KINDS = ('pose6', 'laser_x', 'laser_y', 'laser_z', 'rotary_phi', 'rotary_theta',
                   'rotary_psi', 'bar_lengths')


def _components(kind: str) -> list[int]:
    if kind == 'pose6':
        return list(range(6))
    return [AXES.index(kind.partition('_')[2])]


def reference_names(kind: str, bar_names: list[str]) -> list[str]:
    """Column names of the reference array."""
    if kind not in REFERENCE_KINDS:
        raise TwinError(f'unknown reference {kind!r}; choose one of {list(REFERENCE_KINDS)}')
    return list(bar_names) if kind == 'bar_lengths' else list(AXES)


def reference_values(kind: str, poses: FloatArray, lengths: FloatArray, seed: int,
                     sample_index: NDArray[np.int64]) -> FloatArray:
    """What the instrument reads.

    poses : ndarray, shape (N, 6) — actual poses (NaN when bars rest on the plate)
    lengths : ndarray, shape (N, 6) — true centre distances of the measuring bars [m]
    sample_index : ndarray of int, shape (N,) — terminal sample, addresses the noise
    returns : ndarray, shape (N, 6)
    """
    if kind == 'bar_lengths':
        return lengths.copy()
    out = np.full(poses.shape, np.nan)
    for k in _components(kind):
        out[:, k] = poses[:, k] + POSE_NOISE[k] * hashed_normal(
            stream_key(seed, STREAM_REFERENCE, k), sample_index)
    return out
