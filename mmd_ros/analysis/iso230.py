"""ISO 230-2 (2014) evaluation of the positioning of a linear or rotary axis (sections 5.2–5.3,
Tables 3–4 of the paper).

At each target position P_i (i = 1..m) the axis is approached n times from each direction
(j = 1..n); the deviation is x_ij = P_ij - P_i (actual minus target position). Per target:

    mean unidirectional deviation     x̄_i↑ = (1/n) sum_j x_ij↑      (x̄_i↓ likewise)
    reversal value                    B_i = x̄_i↑ - x̄_i↓
    mean bidirectional deviation      x̄_i = (x̄_i↑ + x̄_i↓) / 2
    estimator of the unidirectional   s_i↑ = sqrt(1/(n-1) sum_j (x_ij↑ - x̄_i↑)^2)
      axis standard uncertainty
    unidirectional repeatability      R_i↑ = 4 s_i↑                  (R_i↓ likewise)
    bidirectional repeatability       R_i = max(2 s_i↑ + 2 s_i↓ + |B_i|, R_i↑, R_i↓)

and for the axis:

    B = max |B_i|           B̄ = (1/m) sum_i B_i
    R↑ = max R_i↑   R↓ = max R_i↓   R = max R_i
    E↑ = max x̄_i↑ - min x̄_i↑      E↓ likewise
    E  = max(x̄_i↑, x̄_i↓) - min(x̄_i↑, x̄_i↓)     (bidirectional systematic deviation)
    M  = max x̄_i - min x̄_i                         (range of the mean bidirectional deviation)
    A↑ = max(x̄_i↑ + 2 s_i↑) - min(x̄_i↑ - 2 s_i↑)    A↓ likewise
    A  = max(x̄_i↑ + 2 s_i↑, x̄_i↓ + 2 s_i↓) - min(x̄_i↑ - 2 s_i↑, x̄_i↓ - 2 s_i↓)

The standard asks for n = 5 cycles; any n >= 2 is evaluated (n = 1 gives no s_i: R and A are
then NaN). A rotary axis is evaluated the same way in angles. The table layout follows the
paper's Tables 3–4: B, M, E, R↑ (R+), R↓ (R-), A.

Measurements come from a log: the dwells of the axis are detected (stationary stretches of the
moved coordinate), assigned to the targets (given, from the log's ``iso_targets`` metadata, or
clustered from the dwells) and their approach direction is the direction of the motion that
ended in them. A dwell counts as an approach only as part of a pass: its neighbouring dwell in
time lies at an adjacent target approached in the same direction (so the return to the start
pose after the test is not counted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.core.units import ARCSEC_PER_RAD, M_PER_MM, M_PER_UM

__all__ = [
    'AXIS_ALIASES', 'Approach', 'Dwell', 'FIGURES', 'IsoResult', 'PAPER_FIGURES', 'approaches',
    'axis_index', 'detect_dwells', 'evaluate', 'evaluate_run', 'figure_table', 'target_table',
]

FloatArray = NDArray[np.float64]

#: Pose component index of each axis name (the paper's phi/theta/psi and ROS roll/pitch/yaw).
AXIS_ALIASES = {'x': 0, 'y': 1, 'z': 2, 'phi': 3, 'roll': 3, 'a': 3, 'theta': 4, 'pitch': 4,
                'b': 4, 'psi': 5, 'yaw': 5, 'c': 5}
AXIS_NAMES = ['x', 'y', 'z', 'phi', 'theta', 'psi']
#: Axis figures, in the order reports list them.
FIGURES = ['A', 'A_up', 'A_down', 'B', 'B_mean', 'E', 'E_up', 'E_down', 'M', 'R', 'R_up', 'R_down']
#: The paper's table (Tables 3–4): B, M, E, R+, R-, A.
PAPER_FIGURES = [('B', 'B'), ('M', 'M'), ('E', 'E'), ('R_up', 'R+'), ('R_down', 'R-'), ('A', 'A')]
FIGURE_LABELS = {'A': 'A', 'A_up': 'A↑', 'A_down': 'A↓', 'B': 'B', 'B_mean': 'B̄', 'E': 'E',
                 'E_up': 'E↑', 'E_down': 'E↓', 'M': 'M', 'R': 'R', 'R_up': 'R↑', 'R_down': 'R↓'}


def axis_index(axis: str) -> int:
    """Pose component (0..5) of an axis name (x, y, z, phi/roll/A, theta/pitch/B, psi/yaw/C)."""
    key = axis.strip().lower()
    if key not in AXIS_ALIASES:
        raise AnalysisError(f'unknown axis {axis!r}; use one of x, y, z, phi (roll, A), '
                            'theta (pitch, B), psi (yaw, C)')
    return AXIS_ALIASES[key]


@dataclass
class IsoResult:
    """ISO 230-2 evaluation of one axis by one instrument. Values in SI (m or rad).

    positions : (m,) target positions; dev_up, dev_down : (m, n) deviations, NaN where an
    approach is missing; per-target arrays (m,); figures : name -> value
    """

    instrument: str
    axis: str
    positions: FloatArray
    dev_up: FloatArray
    dev_down: FloatArray
    mean_up: FloatArray
    mean_down: FloatArray
    mean: FloatArray
    reversal: FloatArray
    s_up: FloatArray
    s_down: FloatArray
    r_up: FloatArray
    r_down: FloatArray
    r_bi: FloatArray
    figures: dict[str, float]
    n_up: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    n_down: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def rotary(self) -> bool:
        return axis_index(self.axis) >= 3

    @property
    def unit(self) -> str:
        """Report unit of deviations: µm or arc-seconds."""
        return 'arcsec' if self.rotary else 'um'

    @property
    def scale(self) -> float:
        """SI to report unit of deviations."""
        return ARCSEC_PER_RAD if self.rotary else 1.0 / M_PER_UM

    @property
    def position_unit(self) -> str:
        return 'deg' if self.rotary else 'mm'

    @property
    def position_scale(self) -> float:
        return 180.0 / math.pi if self.rotary else 1.0 / M_PER_MM

    @property
    def n(self) -> int:
        """Approaches per target and direction (the smallest count)."""
        counts = np.concatenate([self.n_up, self.n_down]) if self.n_up.size else np.array([0])
        return int(counts.min())

    def figures_report(self) -> dict[str, float]:
        return {k: v * self.scale for k, v in self.figures.items()}

    def as_dict(self) -> dict[str, Any]:
        sc, ps = self.scale, self.position_scale

        def arr(a: FloatArray, f: float) -> list[float | None]:
            return [None if not math.isfinite(v) else float(v * f) for v in np.asarray(a, dtype=float)]

        return {
            'instrument': self.instrument, 'axis': self.axis, 'unit': self.unit,
            'position_unit': self.position_unit, 'n': self.n,
            'figures': {k: (None if not math.isfinite(v) else v) for k, v in self.figures_report().items()},
            'targets': [{
                'position': float(p * ps), 'n_up': int(nu), 'n_down': int(nd),
                'mean_up': mu, 'mean_down': md, 'mean': mb, 'reversal': b, 's_up': su,
                's_down': sd, 'R_up': ru, 'R_down': rd, 'R': rb,
            } for p, nu, nd, mu, md, mb, b, su, sd, ru, rd, rb in zip(
                self.positions, self.n_up, self.n_down, arr(self.mean_up, sc), arr(self.mean_down, sc),
                arr(self.mean, sc), arr(self.reversal, sc), arr(self.s_up, sc), arr(self.s_down, sc),
                arr(self.r_up, sc), arr(self.r_down, sc), arr(self.r_bi, sc))],
            'deviations_up': [arr(row, sc) for row in self.dev_up],
            'deviations_down': [arr(row, sc) for row in self.dev_down],
        }


def _stats(dev: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    n = np.sum(np.isfinite(dev), axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        mean = np.where(n > 0, np.nansum(dev, axis=1) / np.maximum(n, 1), np.nan)
        ss = np.nansum((dev - mean[:, None]) ** 2, axis=1)
        s = np.where(n > 1, np.sqrt(ss / np.maximum(n - 1, 1)), np.nan)
    return mean, s, n


def evaluate(positions: Any, dev_up: Any, dev_down: Any, *, axis: str = 'x',
             instrument: str = '') -> IsoResult:
    """ISO 230-2 figures from deviations (module docstring).

    positions : array_like, shape (m,) — target positions [m or rad]
    dev_up, dev_down : array_like, shape (m, n) — deviations x_ij of the approaches in the
        positive and negative direction [m or rad]; NaN for a missing approach
    """
    pos = np.asarray(positions, dtype=np.float64)
    up = np.atleast_2d(np.asarray(dev_up, dtype=np.float64))
    down = np.atleast_2d(np.asarray(dev_down, dtype=np.float64))
    if up.shape[0] != pos.size or down.shape[0] != pos.size:
        raise AnalysisError(f'deviations must have one row per target ({pos.size}), got '
                            f'{up.shape[0]} and {down.shape[0]}')
    mu, su, nu = _stats(up)
    md, sd, nd = _stats(down)
    if np.any(nu == 0) or np.any(nd == 0):
        # (in the units --targets takes: mm, or degrees on a rotary axis)
        scale, unit = (180.0 / np.pi, '°') if axis_index(axis) >= 3 else (1e3, 'mm')
        missing = ', '.join(f'{p * scale:g}' for p, a, b in zip(pos, nu, nd) if a == 0 or b == 0)
        raise AnalysisError(f'targets {missing} {unit} were not approached from both directions')
    mean = 0.5 * (mu + md)
    rev = mu - md
    ru, rd = 4.0 * su, 4.0 * sd
    rb = np.fmax(np.fmax(2 * su + 2 * sd + np.abs(rev), ru), rd)
    with np.errstate(invalid='ignore'):
        figures = {
            'A_up': float(np.max(mu + 2 * su) - np.min(mu - 2 * su)),
            'A_down': float(np.max(md + 2 * sd) - np.min(md - 2 * sd)),
            'A': float(max(np.max(mu + 2 * su), np.max(md + 2 * sd))
                       - min(np.min(mu - 2 * su), np.min(md - 2 * sd))),
            'B': float(np.max(np.abs(rev))),
            'B_mean': float(np.mean(rev)),
            'E_up': float(np.ptp(mu)),
            'E_down': float(np.ptp(md)),
            'E': float(max(mu.max(), md.max()) - min(mu.min(), md.min())),
            'M': float(np.ptp(mean)),
            'R_up': float(np.max(ru)),
            'R_down': float(np.max(rd)),
            'R': float(np.max(rb)),
        }
    return IsoResult(instrument, axis, pos, up, down, mu, md, mean, rev, su, sd, ru, rd, rb,
                     figures, nu.astype(np.int64), nd.astype(np.int64))


# -- measurements from a log -------------------------------------------------------------------
@dataclass(frozen=True)
class Dwell:
    """A stationary stretch of the moved coordinate: samples [start, stop), its value (median of
    the middle part), the direction of the motion that ended in it (+1, -1, 0: none)."""

    start: int
    stop: int
    value: float
    direction: int


def detect_dwells(times_s: FloatArray, coord: FloatArray, *, min_dwell_s: float = 0.15,
                  window_s: float = 0.05) -> list[Dwell]:
    """Stationary stretches of ``coord`` lasting at least ``min_dwell_s``.

    A sample is stationary when the coordinate changes by less than a threshold over
    ``window_s`` on either side: 10 times the sample-to-sample noise (estimated from the
    quietest fifth of the differences) or 1e-5 of the travel, whichever is larger.
    """
    t = np.asarray(times_s, dtype=np.float64)
    x = np.asarray(coord, dtype=np.float64)
    ok = np.isfinite(x)
    if ok.sum() < 10:
        raise AnalysisError('the axis coordinate has fewer than 10 known samples')
    idx = np.flatnonzero(ok)
    x = np.interp(np.arange(x.size), idx, x[idx])
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    if not dt > 0:
        raise AnalysisError(f'the sample times must increase: their median step is {dt:g} s '
                            '(repeated or unsorted stamps?)')
    h = max(1, int(round(window_s / dt)))
    d1 = np.abs(np.diff(x))
    # sample-to-sample noise from the quietest fifth of the differences (the axis moves most of
    # the time; for Gaussian noise the 20th percentile of |N(0, sqrt(2) s)| is 0.253 sqrt(2) s)
    noise = float(np.percentile(d1, 20)) / (0.253 * math.sqrt(2.0)) if d1.size else 0.0
    thr = max(10.0 * noise * math.sqrt(2.0), 1e-5 * float(np.ptp(x)), 1e-12)
    ahead = np.abs(x[np.minimum(np.arange(x.size) + h, x.size - 1)] - x)
    behind = np.abs(x - x[np.maximum(np.arange(x.size) - h, 0)])
    still = (ahead < thr) & (behind < thr)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], still.astype(np.int8), [0]))))
    out = []
    lookback = max(1, int(round(0.2 / dt)))
    for start, stop in zip(edges[::2], edges[1::2]):
        if t[stop - 1] - t[start] < min_dwell_s:
            continue
        n = stop - start
        mid = slice(start + n // 5, stop - n // 5) if n >= 5 else slice(start, stop)
        value = float(np.median(x[mid]))
        before = x[max(0, start - lookback):start]
        step = value - float(before[0]) if before.size else 0.0
        direction = int(np.sign(step)) if abs(step) > thr else 0
        out.append(Dwell(int(start), int(stop), value, direction))
    return out


@dataclass(frozen=True)
class Approach:
    """A dwell assigned to target ``target`` in ``direction`` (+1 / -1), cycle ``cycle``."""

    dwell: Dwell
    target: int
    direction: int
    cycle: int


def _nice_targets(values: FloatArray) -> FloatArray:
    """Cluster dwell positions into targets; each target is its cluster median rounded to a
    power of ten below 1/50 of the spacing (recovers round commanded positions)."""
    v = np.sort(values)
    span = float(np.ptp(v)) if v.size else 0.0
    gaps = np.flatnonzero(np.diff(v) > max(0.02 * span, 1e-12))
    clusters = np.split(v, gaps + 1)
    centres = np.array([np.median(c) for c in clusters])
    if centres.size < 2:
        raise AnalysisError('found dwells at fewer than two positions: not an ISO 230-2 run')
    spacing = float(np.min(np.diff(centres)))
    quantum = 10.0 ** math.floor(math.log10(spacing / 50.0))
    return np.round(centres / quantum) * quantum


def approaches(dwells: list[Dwell], targets: FloatArray | None) -> tuple[FloatArray, list[Approach]]:
    """Assign dwells to targets and keep those that are part of a pass (module docstring).

    targets : (m,) target positions, or None to cluster them from the dwells
    returns : the targets (sorted) and the approaches
    """
    moving = [d for d in dwells if d.direction != 0]
    if targets is None:
        targets = _nice_targets(np.array([d.value for d in moving]))
    tg = np.sort(np.asarray(targets, dtype=np.float64))
    if tg.size < 2:
        raise AnalysisError('ISO 230-2 needs at least two targets')
    tol = 0.25 * float(np.min(np.diff(tg)))
    labelled = []
    for d in dwells:
        i = int(np.argmin(np.abs(tg - d.value)))
        labelled.append((d, i if abs(tg[i] - d.value) <= tol and d.direction != 0 else -1))
    keep = []
    for k, (d, i) in enumerate(labelled):
        if i < 0:
            continue
        neighbours = [labelled[j] for j in (k - 1, k + 1) if 0 <= j < len(labelled)]
        if any(j >= 0 and o.direction == d.direction and abs(j - i) == 1 for o, j in neighbours):
            keep.append((d, i))
    cycles: dict[tuple[int, int], int] = {}
    out = []
    for d, i in keep:
        key = (i, d.direction)
        out.append(Approach(d, i, d.direction, cycles.get(key, 0)))
        cycles[key] = cycles.get(key, 0) + 1
    return tg, out


def deviation_arrays(targets: FloatArray, found: list[Approach], values: list[float]
                     ) -> tuple[FloatArray, FloatArray]:
    """(m, n) arrays of deviations for each direction from per-approach values."""
    m = targets.size
    n_up = max([a.cycle + 1 for a in found if a.direction > 0] or [0])
    n_dn = max([a.cycle + 1 for a in found if a.direction < 0] or [0])
    up, dn = np.full((m, max(n_up, 1)), np.nan), np.full((m, max(n_dn, 1)), np.nan)
    for a, v in zip(found, values):
        (up if a.direction > 0 else dn)[a.target, a.cycle] = v
    return up, dn


def _wrap(a: FloatArray) -> FloatArray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def evaluate_run(times_s: FloatArray, axis: str, signals: dict[str, FloatArray],
                 detect_with: FloatArray, targets: FloatArray | None = None, *,
                 min_dwell_s: float = 0.15) -> dict[str, IsoResult]:
    """ISO 230-2 of one axis for several instruments of the same run.

    signals : instrument name -> (N,) reading of the axis coordinate [m or rad]; an entry whose
        name ends in '- reference' (or is 'error') is taken as a deviation itself (a difference
        of two instruments at every sample), the others are positions compared with the targets
    detect_with : (N,) the coordinate used to find dwells (the reference if known)
    """
    rotary = axis_index(axis) >= 3
    dwells = detect_dwells(times_s, detect_with, min_dwell_s=min_dwell_s)
    tg, found = approaches(dwells, targets)
    if not found:
        raise AnalysisError('no approaches to the targets found: the axis never dwelt at them')
    out = {}
    for name, sig in signals.items():
        values = []
        for a in found:
            n = a.dwell.stop - a.dwell.start
            mid = slice(a.dwell.start + n // 5, a.dwell.stop - n // 5) if n >= 5 else slice(a.dwell.start, a.dwell.stop)
            seg = np.asarray(sig[mid], dtype=np.float64)
            seg = seg[np.isfinite(seg)]
            if seg.size == 0:
                values.append(np.nan)
                continue
            if name == 'error' or name.endswith('- reference'):
                dev = float(np.mean(_wrap(seg) if rotary else seg))
            else:
                diff = seg - tg[a.target]
                dev = float(np.mean(_wrap(diff) if rotary else diff))
            values.append(dev)
        up, dn = deviation_arrays(tg, found, values)
        out[name] = evaluate(tg, up, dn, axis=AXIS_NAMES[axis_index(axis)], instrument=name)
    return out


def figure_table(rows: list[tuple[str, dict[str, float]]], unit: str, *,
                 figures: list[tuple[str, str]] | None = None, markdown: bool = False) -> str:
    """The paper's table (Tables 3–4): one row per instrument, columns B M E R+ R- A (or
    ``figures``: (key, label) pairs), values in ``unit`` (already converted)."""
    cols = figures or PAPER_FIGURES
    head = ['measuring system'] + [label for _, label in cols]
    lines = []
    if markdown:
        lines.append('| ' + ' | '.join(head) + ' |')
        lines.append('|' + '---|' * len(head))
        for name, figs in rows:
            lines.append('| ' + ' | '.join([name] + [_f(figs.get(k)) for k, _ in cols]) + ' |')
        lines.append(f'\nUnit: {"arc-seconds" if unit == "arcsec" else "µm"}.')
    else:
        width = max([len(head[0])] + [len(n) for n, _ in rows]) + 2
        lines.append(f'{head[0]:<{width}}' + ''.join(f'{h:>9}' for h in head[1:]) + f'   [{_unit(unit)}]')
        for name, figs in rows:
            lines.append(f'{name:<{width}}' + ''.join(f'{_f(figs.get(k)):>9}' for k, _ in cols))
    return '\n'.join(lines)


def target_table(result: IsoResult, *, markdown: bool = False) -> str:
    """Per-target values: x̄↑, x̄↓, x̄, B_i, s↑, s↓, R_i↑, R_i↓, R_i."""
    sc, ps = result.scale, result.position_scale
    head = [f'P_i [{result.position_unit}]', 'x̄↑', 'x̄↓', 'x̄', 'B_i', 's↑', 's↓', 'R↑', 'R↓', 'R_i']
    rows = []
    for k in range(result.positions.size):
        vals = [result.mean_up[k], result.mean_down[k], result.mean[k], result.reversal[k],
                result.s_up[k], result.s_down[k], result.r_up[k], result.r_down[k], result.r_bi[k]]
        rows.append([f'{result.positions[k] * ps:.4g}'] + [_f(v * sc) for v in vals])
    if markdown:
        out = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
        out += ['| ' + ' | '.join(r) + ' |' for r in rows]
        return '\n'.join(out)
    out = [''.join(f'{h:>10}' for h in head)]
    out += [''.join(f'{c:>10}' for c in r) for r in rows]
    return '\n'.join(out)


def _f(v: float | None) -> str:
    return '–' if v is None or not math.isfinite(v) else f'{v:.2f}'


def _unit(unit: str) -> str:
    return '″' if unit == 'arcsec' else 'µm'
