"""Error of measured poses or bar lengths against a reference, in report units (µm, arc-seconds).

A reference may give only some components (a laser along one axis, a rotary calibrator's
angle): unknown components are NaN and are left out of the statistics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.units import arcsec, um

__all__ = ['ComponentStats', 'error_stats', 'format_stats', 'length_error', 'pose_error']

FloatArray = NDArray[np.float64]
POSE_NAMES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']


@dataclass(frozen=True)
class ComponentStats:
    """Statistics of one error component, in ``unit`` (µm or arcsec)."""

    name: str
    unit: str
    n: int
    mean: float
    std: float
    rms: float
    max_abs: float

    def as_dict(self) -> dict[str, float | int | str]:
        return asdict(self)


def pose_error(poses: FloatArray, reference: FloatArray) -> FloatArray:
    """Measured minus reference, shape (N, 6) [m, rad]; angles wrapped to (-pi, pi]; NaN where
    the reference does not know a component."""
    err = np.asarray(poses, dtype=np.float64) - np.asarray(reference, dtype=np.float64)
    err[:, 3:] = (err[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    return err


def length_error(lengths: FloatArray, reference: FloatArray) -> FloatArray:
    """Measured minus reference bar lengths, shape (N, 6) [m]."""
    return np.asarray(lengths, dtype=np.float64) - np.asarray(reference, dtype=np.float64)


def _stats(name: str, unit: str, values: FloatArray) -> ComponentStats:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return ComponentStats(name, unit, 0, np.nan, np.nan, np.nan, np.nan)
    return ComponentStats(name, unit, int(v.size), float(v.mean()), float(v.std()),
                          float(np.sqrt(np.mean(v * v))), float(np.max(np.abs(v))))


def error_stats(errors: FloatArray, valid: NDArray[np.bool_] | None = None, *,
                kind: str = 'pose') -> list[ComponentStats]:
    """Per-component statistics of pose errors (µm, arcsec) or bar-length errors (µm).

    errors : ndarray, shape (N, 6) — from :func:`pose_error` or :func:`length_error`
    valid : ndarray, shape (N,), optional — samples to include
    kind : 'pose' adds the 3-D position error norm where x, y and z are all known
    """
    e = np.asarray(errors, dtype=np.float64)
    if valid is not None:
        e = e[np.asarray(valid, dtype=bool)]
    if kind == 'lengths':
        return [_stats(f'bar{i + 1}', 'um', um(e[:, i])) for i in range(e.shape[1])]
    out = [_stats(POSE_NAMES[i], 'um', um(e[:, i])) for i in range(3)]
    out += [_stats(POSE_NAMES[i], 'arcsec', arcsec(e[:, i])) for i in range(3, 6)]
    out.append(_stats('position', 'um', um(np.linalg.norm(e[:, :3], axis=1))))
    return [s for s in out if s.n > 0]


def format_stats(stats: list[ComponentStats], title: str) -> str:
    """A fixed-width table of the statistics."""
    lines = [title, f'  {"component":<10} {"unit":>7} {"n":>9} {"mean":>10} {"std":>10} {"rms":>10} {"max|e|":>10}']
    for s in stats:
        lines.append(f'  {s.name:<10} {s.unit:>7} {s.n:>9d} {s.mean:>10.4f} {s.std:>10.4f} '
                     f'{s.rms:>10.4f} {s.max_abs:>10.4f}')
    return '\n'.join(lines)
