"""Figures of the analysis tools as PNG files (matplotlib's object API on the Agg canvas; no
global pyplot state). Values are plotted in report units: µm, arc-seconds, mm, degrees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import NDArray

from mmd_ros.analysis.identify import Analysis
from mmd_ros.analysis.iso230 import IsoResult

__all__ = ['analysis_figures', 'iso230_figure']

FloatArray = NDArray[np.float64]
_DPI = 110
_UNIT = {'um': 'µm', 'arcsec': '″'}
BEFORE, AFTER, FWD, BWD = '#c0392b', '#2471a3', '#27ae60', '#2e86c1'


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=_DPI)
    return path


def _thin(idx: NDArray[np.int64], n: int = 6000) -> NDArray[np.int64]:
    return idx[:: max(1, idx.size // n)]


def _components(a: Analysis) -> list[int]:
    """Observed components to plot (at most six)."""
    return list(range(min(len(a.obs.names), 6)))


def analysis_figures(a: Analysis, out_dir: Path) -> dict[str, str]:
    """Write the figures of an analysis; returns caption -> file name."""
    out_dir.mkdir(parents=True, exist_ok=True)
    figs: dict[str, str] = {}
    figs['Residual against time (held-out blocks shaded)'] = _time(a, out_dir / 'residual_time.png').name
    figs['Residual against position'] = _position(a, out_dir / 'residual_position.png').name
    for f in a.found:
        path = _signature(a, f.effect, out_dir / f'signature_{f.effect}.png')
        if path is not None:
            figs[f'Residual against the signature of {f.title}'] = path.name
    figs['Held-out residual before and after'] = _histogram(a, out_dir / 'histogram.png').name
    return figs


def _grid(n: int, width: float = 10.0, height: float = 2.2) -> tuple[Figure, list]:
    fig = Figure(figsize=(width, max(2.8, height * n)), layout='constrained')
    axes = [fig.add_subplot(n, 1, k + 1) for k in range(n)]
    return fig, axes


def _time(a: Analysis, path: Path) -> Path:
    comps = _components(a)
    fig, axes = _grid(len(comps))
    idx = _thin(np.concatenate([a.split.train_idx, a.split.test_idx]))
    idx.sort()
    t = a.times_s
    edges = np.linspace(t[a.split.train_idx.min()] if a.split.train_idx.size else 0.0, t[-1], a.split.n_blocks + 1)
    for ax, k in zip(axes, comps):
        scale = a.obs.to_report[k]
        for b in range(a.split.n_blocks):
            sel = a.split.block == b
            if np.any(sel & a.split.test):
                ax.axvspan(edges[b], edges[b + 1], color='0.92', lw=0)
        ax.plot(t[idx], a.residual_before[idx, k] * scale, '.', ms=1.5, color=BEFORE, label='before')
        if a.residual_after is not None:
            ax.plot(t[idx], a.residual_after[idx, k] * scale, '.', ms=1.5, color=AFTER, label='after')
        ax.set_ylabel(f'{a.obs.names[k]} [{_UNIT[a.obs.units[k]]}]')
        ax.grid(alpha=0.3)
    axes[0].legend(loc='upper right', markerscale=6, fontsize=8)
    axes[-1].set_xlabel('time [s]')
    fig.suptitle('MMD − reference against time')
    return _save(fig, path)


def _main_coordinate(a: Analysis) -> tuple[str, FloatArray, str]:
    """The coordinate that moves most: a pose component (mm or degrees) or a bar length."""
    base = a.before
    usable = np.concatenate([a.split.train_idx, a.split.test_idx])
    if a.obs.kind == 'pose':
        p = base.poses[usable]
        spans = np.ptp(p, axis=0) / np.array([0.1, 0.1, 0.1, 0.2, 0.2, 0.2])
        k = int(np.argmax(spans))
        names = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
        if k < 3:
            return f'pose {names[k]} [mm]', base.poses[:, k] * 1e3, 'mm'
        return f'pose {names[k]} [deg]', np.degrees(base.poses[:, k]), 'deg'
    d = base.pre_lengths_m[usable]
    k = int(np.argmax(np.ptp(d, axis=0)))
    return f'bar{k + 1} length [mm]', base.pre_lengths_m[:, k] * 1e3, 'mm'


def _direction(values: FloatArray, times: FloatArray) -> FloatArray:
    """Sign of the recent motion of a coordinate (held through dwells)."""
    v = np.gradient(values, times)
    tol = 1e-3 * max(float(np.nanmax(np.abs(v))), 1e-12)
    sign = np.where(np.abs(v) > tol, np.sign(v), 0.0)
    idx = np.where(sign != 0, np.arange(sign.size), 0)
    np.maximum.accumulate(idx, out=idx)
    return sign[idx]


def _position(a: Analysis, path: Path) -> Path:
    comps = _components(a)
    label, coord, _ = _main_coordinate(a)
    direction = _direction(np.nan_to_num(coord), a.times_s)
    fig, axes = _grid(len(comps), width=10.0)
    idx = _thin(a.split.test_idx)
    for ax, k in zip(axes, comps):
        scale = a.obs.to_report[k]
        for sign, colour, name in ((1, FWD, 'forward'), (-1, BWD, 'backward')):
            sel = idx[direction[idx] == sign]
            ax.plot(coord[sel], a.residual_before[sel, k] * scale, '.', ms=1.5, color=colour,
                    alpha=0.6, label=f'before, {name}')
            if a.residual_after is not None:
                ax.plot(coord[sel], a.residual_after[sel, k] * scale, 'x', ms=2, color=AFTER if sign > 0 else '0.3',
                        alpha=0.5, label=f'after, {name}')
        ax.set_ylabel(f'{a.obs.names[k]} [{_UNIT[a.obs.units[k]]}]')
        ax.grid(alpha=0.3)
    axes[0].legend(loc='upper right', markerscale=5, fontsize=7, ncol=2)
    axes[-1].set_xlabel(label)
    fig.suptitle('Held-out residual against position (forward / backward motion)')
    return _save(fig, path)


def _signature(a: Analysis, effect: str, path: Path) -> Path | None:
    contrib = a.contributions.get(effect)
    if contrib is None:
        return None
    comps = _components(a)
    fig = Figure(figsize=(10, max(3.0, 2.6 * len(comps))), layout='constrained')
    idx = _thin(a.split.test_idx)
    idx = idx[np.all(np.isfinite(contrib[idx]), axis=1)]
    if idx.size == 0:
        return None
    label, coord, _ = _main_coordinate(a)
    direction = _direction(np.nan_to_num(coord), a.times_s)
    for row, k in enumerate(comps):
        scale = a.obs.to_report[k]
        ax1 = fig.add_subplot(len(comps), 2, 2 * row + 1)
        ax2 = fig.add_subplot(len(comps), 2, 2 * row + 2)
        c = contrib[idx, k] * scale
        for sign, colour, name in ((1, FWD, 'forward'), (-1, BWD, 'backward'), (0, '0.5', 'at rest')):
            sel = direction[idx] == sign
            if sel.any():
                ax1.plot(c[sel], a.residual_before[idx[sel], k] * scale, '.', ms=2, color=colour, label=name)
        lim = [np.nanmin(c), np.nanmax(c)]
        ax1.plot(lim, lim, 'k--', lw=0.8)
        ax1.set_xlabel(f'{effect} signature, fitted [{_UNIT[a.obs.units[k]]}]')
        ax1.set_ylabel(f'{a.obs.names[k]} before [{_UNIT[a.obs.units[k]]}]')
        ax1.grid(alpha=0.3)
        if a.residual_after is not None:
            ax2.plot(c, a.residual_after[idx, k] * scale, '.', ms=2, color=AFTER)
        ax2.set_xlabel(f'{effect} signature, fitted [{_UNIT[a.obs.units[k]]}]')
        ax2.set_ylabel(f'{a.obs.names[k]} after [{_UNIT[a.obs.units[k]]}]')
        ax2.grid(alpha=0.3)
        if row == 0:
            ax1.legend(fontsize=7, markerscale=4)
    fig.suptitle(f'Held-out residual against the fitted {effect} (slope 1 before: it is explained)')
    return _save(fig, path)


def _histogram(a: Analysis, path: Path) -> Path:
    units = sorted(set(a.obs.units))
    fig = Figure(figsize=(5 * len(units), 3.6), layout='constrained')
    for j, unit in enumerate(units):
        ax = fig.add_subplot(1, len(units), j + 1)
        cols = [k for k, u in enumerate(a.obs.units) if u == unit]
        scale = a.obs.to_report[cols[0]]
        before = (a.residual_before[a.split.test_idx][:, cols] * scale).ravel()
        before = before[np.isfinite(before)]
        series = [('before', before, BEFORE)]
        if a.residual_after is not None:
            after = (a.residual_after[a.split.test_idx][:, cols] * scale).ravel()
            series.append(('after', after[np.isfinite(after)], AFTER))
        lo = min(np.percentile(s, 0.5) for _, s, _ in series)
        hi = max(np.percentile(s, 99.5) for _, s, _ in series)
        bins = np.linspace(lo, hi, 60) if hi > lo else 30
        for name, s, colour in series:
            rms = float(np.sqrt(np.mean(s * s)))
            ax.hist(s, bins=bins, alpha=0.55, color=colour, label=f'{name}: RMS {rms:.3g} {_UNIT[unit]}')
        ax.set_xlabel(f'held-out residual [{_UNIT[unit]}] ({", ".join(a.obs.names[k] for k in cols)})')
        ax.set_ylabel('samples')
        ax.legend(fontsize=8)
    return _save(fig, path)


def iso230_figure(result: IsoResult, path: Path) -> Path:
    """The standard's plot: deviations of each approach, mean ± 2 s per direction and the mean
    bidirectional deviation against the target position (as the paper's Figs. 16–17)."""
    sc, ps = result.scale, result.position_scale
    pos = result.positions * ps
    fig = Figure(figsize=(8, 4.5), layout='constrained')
    ax = fig.add_subplot(1, 1, 1)
    span = float(np.ptp(pos)) if pos.size > 1 else 1.0
    shift = 0.004 * span
    series = ((result.dev_up, result.mean_up, result.s_up, FWD, 'forward ↑', -shift),
              (result.dev_down, result.mean_down, result.s_down, BWD, 'backward ↓', shift))
    for dev, mean, s, colour, name, dx in series:
        for j in range(dev.shape[1]):
            ax.plot(pos + dx, dev[:, j] * sc, '.', color=colour, ms=4, alpha=0.6,
                    label=name if j == 0 else None)
        ax.fill_between(pos, (mean - 2 * s) * sc, (mean + 2 * s) * sc, color=colour, alpha=0.18, lw=0)
        ax.plot(pos, mean * sc, '-', color=colour, lw=1)
    ax.plot(pos, result.mean * sc, '-', color='#c0392b', lw=1.5, label='mean bidirectional x̄')
    f = result.figures_report()
    unit = _UNIT[result.unit]
    ax.set_title(f'ISO 230-2, axis {result.axis}, {result.instrument}: A {f["A"]:.2f}, B {f["B"]:.2f}, '
                 f'E {f["E"]:.2f}, M {f["M"]:.2f} {unit} (n = {result.n})', fontsize=9)
    ax.set_xlabel(f'target position [{result.position_unit}]')
    ax.set_ylabel(f'deviation [{unit}]')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)
