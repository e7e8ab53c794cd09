"""Error of measured poses or bar lengths against a reference, in report units (µm, arc-seconds).

A reference may give only some components (a laser along one axis, a rotary calibrator's
angle): unknown components are NaN and are left out of the statistics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.units import arcsec, um

__all__ = [
    'ComponentStats', 'ErrorAccumulator', 'error_stats', 'format_stats', 'length_error',
    'pose_error',
]

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


class ErrorAccumulator:
    """:func:`error_stats` of a run given block by block (a log too long to hold in memory):
    count, shifted sums and largest magnitude per component, so that mean, std, rms and max|e|
    come out as for the whole run at once (to rounding).

    kind : as for :func:`error_stats`
    """

    def __init__(self, kind: str = 'pose') -> None:
        self.kind = kind
        self._parts: list[tuple[str, str]] | None = None
        self._n = self._shift = self._s1 = self._s2 = self._max = None

    def _columns(self, e: FloatArray) -> tuple[list[tuple[str, str]], FloatArray]:
        if self.kind == 'lengths':
            return [(f'bar{i + 1}', 'um') for i in range(e.shape[1])], um(e)
        cols = np.column_stack([um(e[:, :3]), arcsec(e[:, 3:6]),
                                um(np.linalg.norm(e[:, :3], axis=1))])
        names = [(POSE_NAMES[i], 'um') for i in range(3)] + \
            [(POSE_NAMES[i], 'arcsec') for i in range(3, 6)] + [('position', 'um')]
        return names, cols

    def add(self, errors: FloatArray, valid: NDArray[np.bool_] | None = None) -> None:
        """errors : ndarray, shape (N, 6) [m, rad]; valid : ndarray, shape (N,), optional"""
        e = np.asarray(errors, dtype=np.float64)
        if valid is not None:
            e = e[np.asarray(valid, dtype=bool)]
        names, v = self._columns(e)
        if self._parts is None:
            k = len(names)
            self._parts = names
            self._n = np.zeros(k, dtype=np.int64)
            self._shift = np.full(k, np.nan)
            self._s1, self._s2, self._max = np.zeros(k), np.zeros(k), np.zeros(k)
        ok = np.isfinite(v)
        for j in range(v.shape[1]):
            x = v[ok[:, j], j]
            if x.size == 0:
                continue
            if np.isnan(self._shift[j]):
                self._shift[j] = x[0]   # sums of x - x0 keep their digits when |mean| >> std
            d = x - self._shift[j]
            self._n[j] += x.size
            self._s1[j] += d.sum()
            self._s2[j] += (d * d).sum()
            self._max[j] = max(self._max[j], float(np.max(np.abs(x))))

    def stats(self) -> list[ComponentStats]:
        """Per-component statistics of everything added (components never known left out)."""
        if self._parts is None:
            return []
        out = []
        for j, (name, unit) in enumerate(self._parts):
            n = int(self._n[j])
            if n == 0:
                continue
            m1 = self._s1[j] / n
            var = max(self._s2[j] / n - m1 * m1, 0.0)
            mean = self._shift[j] + m1
            out.append(ComponentStats(name, unit, n, float(mean), float(np.sqrt(var)),
                                      float(np.sqrt(var + mean * mean)), float(self._max[j])))
        return out


def format_stats(stats: list[ComponentStats], title: str) -> str:
    """A fixed-width table of the statistics."""
    lines = [title, f'  {"component":<10} {"unit":>7} {"n":>9} {"mean":>10} {"std":>10} {"rms":>10} {"max|e|":>10}']
    for s in stats:
        lines.append(f'  {s.name:<10} {s.unit:>7} {s.n:>9d} {s.mean:>10.4f} {s.std:>10.4f} '
                     f'{s.rms:>10.4f} {s.max_abs:>10.4f}')
    return '\n'.join(lines)
