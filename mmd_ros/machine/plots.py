"""Figures of a machine session as PNG files (matplotlib's object API on the Agg canvas):
per axis its six error motions with ±2σ bands, rotary axes also in polar form, and the
volumetric error maps. Values in µm, arc-seconds, mm and degrees."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mmd_ros.analysis.plots import BWD, FWD, iso230_figure
from mmd_ros.machine.results import AxisResult, MachineResult, report_scale
from mmd_ros.machine.volumetric import VolumetricMap

__all__ = ['axis_figure', 'machine_figures', 'polar_figure', 'volumetric_figure']

_DPI = 110
MEAN = '#c0392b'


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=_DPI)
    return path


def axis_figure(a: AxisResult, path: Path) -> Path:
    """Six panels: each error motion up, down and mean with a ±2σ band around the mean."""
    ps, punit = a.position_scale
    fig = Figure(figsize=(11, 7.5))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.07, top=0.9, wspace=0.3, hspace=0.4)
    pos = a.targets * ps
    for k, m in enumerate(a.motions):
        ax = fig.add_subplot(2, 3, k + 1)
        scale, unit = report_scale(m.unit)
        ax.fill_between(pos, (m.mean - 2 * m.u_mean) * scale, (m.mean + 2 * m.u_mean) * scale,
                        color=MEAN, alpha=0.15, lw=0, label='mean ± 2σ')
        ax.plot(pos, m.up * scale, '^-', color=FWD, ms=4, lw=0.8, label='↑')
        ax.plot(pos, m.down * scale, 'v-', color=BWD, ms=4, lw=0.8, label='↓')
        ax.plot(pos, m.mean * scale, '-', color=MEAN, lw=1.4, label='mean')
        if m.deviation is not None:
            ax.plot(pos, m.deviation * scale, ':', color='k', lw=1, label='from LS line')
        ax.set_title(f'{m.name} ({m.kind}): {m.figure.value * scale:.2f} ± {m.figure.expanded * scale:.2f} {unit}',
                     fontsize=9)
        ax.set_xlabel(f'{a.axis} [{punit}]')
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
        if k == 0:
            ax.legend(fontsize=7)
    fig.suptitle(f'{a.axis} axis: error motions of the tool relative to the workpiece '
                 f'(n = {a.n_cycles} cycles)', fontsize=10)
    return _save(fig, path)


def polar_figure(a: AxisResult, path: Path) -> Path:
    """Radial error motions of a rotary axis around the angle (mean of both directions),
    exaggerated about a base circle."""
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot(1, 1, 1, projection='polar')
    theta = a.targets
    base = 3.0
    for m, colour in zip([m for m in a.motions if m.kind in ('radial', 'axial')], (FWD, BWD, MEAN)):
        val = m.mean * 1e6
        ax.plot(theta, base + val, 'o-', color=colour, ms=3, label=f'{m.name} [µm]')
        ax.fill_between(theta, base + val - 2e6 * m.u_mean, base + val + 2e6 * m.u_mean, color=colour,
                        alpha=0.12, lw=0)
    ax.plot(np.linspace(0, 2 * math.pi, 200), np.full(200, base), color='0.6', lw=0.6)
    ax.set_title(f'{a.axis}: radial and axial error motions (base circle {base:g} µm)', fontsize=9)
    ax.legend(fontsize=7, loc='lower right')
    return _save(fig, path)


def volumetric_figure(vmap: VolumetricMap, path: Path, title: str) -> Path:
    """Error magnitude at every grid point (a scatter coloured by |e|) with arrows of its
    horizontal part, against the two axes that vary most."""
    spread = np.ptp(vmap.q, axis=0)
    cols = np.argsort(spread)[::-1][:2]
    scale = np.array([180 / math.pi if n in 'ABC' else 1e3 for n in vmap.names])
    x, y = vmap.q[:, cols[0]] * scale[cols[0]], vmap.q[:, cols[1]] * scale[cols[1]]
    mag = vmap.magnitude * 1e6
    fig = Figure(figsize=(7.5, 6))
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.1, top=0.92)
    ax = fig.add_subplot(1, 1, 1)
    sc = ax.scatter(x, y, c=mag, cmap='viridis', s=40)
    fig.colorbar(sc, ax=ax, label='|error| [µm]')
    ax.quiver(x, y, vmap.error[:, 0] * 1e6, vmap.error[:, 1] * 1e6, color='w', alpha=0.8)
    unit = lambda n: '°' if n in 'ABC' else 'mm'  # noqa: E731
    ax.set_xlabel(f'{vmap.names[cols[0]]} [{unit(vmap.names[cols[0]])}]')
    ax.set_ylabel(f'{vmap.names[cols[1]]} [{unit(vmap.names[cols[1]])}]')
    ax.set_title(f'{title}: max {mag.max():.2f} µm, RMS {np.sqrt(np.mean(mag ** 2)):.2f} µm', fontsize=9)
    return _save(fig, path)


def machine_figures(result: MachineResult, out: Path, maps: dict[str, VolumetricMap]) -> dict[str, str]:
    """Every figure of a session; returns caption -> file name."""
    out.mkdir(parents=True, exist_ok=True)
    figs: dict[str, str] = {}
    for name, a in result.axes.items():
        figs[f'{name} axis: error motions'] = axis_figure(a, out / f'axis_{name}.png').name
        if a.rotary:
            figs[f'{name} axis: radial and axial (polar)'] = polar_figure(a, out / f'polar_{name}.png').name
        pos = a.motions[3 + result.machine.axis(name).component] if a.rotary else \
            a.motions[result.machine.axis(name).component]
        if pos.iso230 is not None:
            figs[f'{name} axis: ISO 230-2 positioning'] = iso230_figure(pos.iso230, out / f'iso230_{name}.png').name
    for key, vmap in maps.items():
        figs[f'Volumetric error: {key}'] = volumetric_figure(vmap, out / f'volumetric_{key.split()[0]}.png',
                                                             f'volumetric error, {key}').name
    return figs
