"""Figures of the design tools as PNG files: Figs. 2, 3, 4 and 8 of Lei & Chen (2024) and the
tolerance frontier. Matplotlib's object API on the Agg canvas; no global pyplot state."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Patch, Rectangle

from mmd_ros.core.units import arcsec, mm, um
from mmd_ros.design.error_budget import PAPER_EQ9_UM, Accuracy, Study, eq9_design_matrix
from mmd_ros.design.workspace import CONSTRAINTS, Section

__all__ = ['binding_figure', 'error_budget_figures', 'section_figure']

_DPI = 120


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=_DPI)
    return path


def _label(pose: np.ndarray) -> str:
    return '(' + ', '.join(f'{v:g}' for v in np.round(mm(pose[:3]), 2)) + ')'


def error_budget_figures(study: Study, out_dir: Path) -> list[Path]:
    """Write the figures of the parts in ``study``; returns their paths."""
    written = []
    if study.fig2_joint is not None and study.fig2_distance is not None:
        written.append(_fig2(study, out_dir / 'fig2_error_budget.png'))
    if study.surface is not None:
        written.append(_fig3(study, out_dir / 'fig3_eq9_surface.png'))
    if study.fig4_top is not None and study.fig4_inside is not None:
        written.append(_fig4(study, out_dir / 'fig4_design_point.png'))
    if study.frontier is not None:
        written.append(_frontier(study, out_dir / 'tolerance_frontier.png'))
    return written


def _errorbars(ax: Axes, x: np.ndarray, rows: Sequence[Accuracy], which: str, offset: float,
               label: str) -> None:
    if which == 'position':
        mean = um(np.array([a.position_mean_m for a in rows]))
        std = um(np.array([a.position_std_m for a in rows]))
    else:
        mean = arcsec(np.array([a.rotation_mean_rad for a in rows]))
        std = arcsec(np.array([a.rotation_std_rad for a in rows]))
    ax.errorbar(x + offset, mean, yerr=2 * std, fmt='o-', ms=3, capsize=2, lw=1, label=label)


def _fig2(study: Study, path: Path) -> Path:
    fig = Figure(figsize=(11, 8), layout='constrained')
    axes = fig.subplots(2, 2)
    eps = um(study.fig2_eps_m)
    width = 0.6 * (eps[1] - eps[0] if eps.size > 1 else 0.1)
    tables = (study.fig2_joint, study.fig2_distance)
    titles = ('(a) ball-joint position errors', '(b) centre-distance errors')
    xlabels = (r'$\|\epsilon_j\|_\infty$ [µm]', r'$\|\epsilon_d\|_\infty$ [µm]')
    assert tables[0] is not None and tables[1] is not None
    for col, (table, title, xl) in enumerate(zip(tables, titles, xlabels)):
        n = len(table)
        for k, (pose, row) in enumerate(zip(study.poses, table)):
            off = (k - (n - 1) / 2) * width / max(n, 1)
            _errorbars(axes[0, col], eps, row, 'position', off, _label(pose))
            _errorbars(axes[1, col], eps, row, 'rotation', off, _label(pose))
        axes[0, col].axhline(um(study.target_position_m), color='k', ls='--', lw=0.8)
        axes[0, col].set_title(f'Fig. 2{title}: position error')
        axes[1, col].set_title('rotation error (not in the paper)')
        axes[0, col].set_ylabel('mean ± 2 std [µm]')
        axes[1, col].set_ylabel('mean ± 2 std [arcsec]')
        axes[1, col].set_xlabel(xl)
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
    axes[0, 0].legend(title='setting position [mm]', fontsize=7)
    fig.suptitle(f'Error budget, reading {study.reading}, N = {study.samples}')
    return _save(fig, path)


def _fig3(study: Study, path: Path) -> Path:
    sf = study.surface
    assert sf is not None
    fig = Figure(figsize=(12, 5.5), layout='constrained')
    ax = fig.add_subplot(1, 2, 1, projection='3d')
    ej, ed = np.meshgrid(um(sf.eps_joint_m), um(sf.eps_dist_m), indexing='ij')
    fine_j, fine_d = np.meshgrid(np.linspace(ej.min(), ej.max(), 41),
                                 np.linspace(ed.min(), ed.max(), 41), indexing='ij')
    design = eq9_design_matrix(fine_j, fine_d)
    ax.plot_surface(fine_j, fine_d, (design @ sf.coefficients_um).reshape(fine_j.shape),
                    cmap='viridis', alpha=0.6, lw=0)
    ax.plot_wireframe(fine_j, fine_d, (design @ PAPER_EQ9_UM).reshape(fine_j.shape),
                      color='k', lw=0.4, rstride=5, cstride=5)
    ax.scatter(ej.ravel(), ed.ravel(), um(sf.position_m).ravel(), color='r', s=6)
    ej0, ed0 = (um(v) for v in study.design_point_m)
    ax.scatter([ej0], [ed0], [float((eq9_design_matrix([ej0], [ed0]) @ sf.coefficients_um)[0])],
               color='lime', s=40, edgecolor='k')
    ax.set_xlabel(r'$\|\epsilon_j\|_\infty$ [µm]')
    ax.set_ylabel(r'$\|\epsilon_d\|_\infty$ [µm]')
    ax.set_zlabel('accuracy [µm]', labelpad=6)
    ax.set_box_aspect(None, zoom=0.85)
    ax.set_title(f'Fig. 3 at {_label(sf.pose)} mm: points, fit (colour), paper (wire)')
    ax2 = fig.add_subplot(1, 2, 2)
    diff = (sf.evaluate_um(sf.coefficients_um) - sf.evaluate_um(PAPER_EQ9_UM))
    im = ax2.pcolormesh(um(sf.eps_joint_m), um(sf.eps_dist_m), diff.T, cmap='coolwarm',
                        vmin=-np.abs(diff).max(), vmax=np.abs(diff).max(), shading='nearest')
    fig.colorbar(im, ax=ax2, label='fitted minus paper Eq. (9) [µm]')
    ax2.set_xlabel(r'$\|\epsilon_j\|_\infty$ [µm]')
    ax2.set_ylabel(r'$\|\epsilon_d\|_\infty$ [µm]')
    ax2.set_title(f'RMS {sf.rms_um(PAPER_EQ9_UM):.4f} µm; fitted ' +
                  ', '.join(f'{c:.2f}' for c in sf.coefficients_um), fontsize=9)
    return _save(fig, path)


def _fig4(study: Study, path: Path) -> Path:
    fig = Figure(figsize=(12, 7), layout='constrained')
    axes = fig.subplots(2, 2)
    groups = ((study.fig4_top, '(a) top edge of the cylinder'),
              (study.fig4_inside, '(b) inside the cylinder'))
    for col, (rows, title) in enumerate(groups):
        assert rows is not None
        x = np.arange(len(rows))
        _errorbars(axes[0, col], x, rows, 'position', 0.0, 'position')
        _errorbars(axes[1, col], x, rows, 'rotation', 0.0, 'rotation')
        axes[0, col].axhline(um(study.target_position_m), color='k', ls='--', lw=0.8)
        axes[0, col].set_title(f'Fig. 4{title}')
        axes[0, col].set_ylabel('position error, mean ± 2 std [µm]')
        axes[1, col].set_ylabel('rotation error, mean ± 2 std [arcsec]')
        for ax in axes[:, col]:
            ax.set_xticks(x, [_label(a.pose) for a in rows], rotation=60, fontsize=6)
            ax.grid(alpha=0.3)
    ej, ed = (um(v) for v in study.design_point_m)
    fig.suptitle(f'eps_j = {ej:g} µm, eps_d = {ed:g} µm, reading {study.reading}')
    return _save(fig, path)


def _frontier(study: Study, path: Path) -> Path:
    assert study.frontier is not None
    fig = Figure(figsize=(6, 5.5), layout='constrained')
    ax = fig.subplots()
    ej = um(np.array([f.eps_joint_m for f in study.frontier]))
    ed = um(np.array([f.eps_dist_m for f in study.frontier]))
    ax.plot(ej, ed, 'o-', label=f'largest bounds for {um(study.target_position_m):g} µm')
    if study.ratio_point is not None:
        ax.plot([um(study.ratio_point.eps_joint_m)], [um(study.ratio_point.eps_dist_m)], 's',
                color='C1', label='on the design ratio')
    ax.plot([um(study.design_point_m[0])], [um(study.design_point_m[1])], '*', ms=12,
            color='lime', mec='k', label='design bounds (paper)')
    top = max(ej.max(), ed.max()) * 1.15
    gj, gd = np.meshgrid(np.linspace(0, top, 121), np.linspace(0, top, 121), indexing='ij')
    paper = (eq9_design_matrix(gj, gd) @ PAPER_EQ9_UM).reshape(gj.shape)
    ax.contour(gj, gd, paper, levels=[um(study.target_position_m)], colors='k',
               linestyles='--', linewidths=0.8)
    ax.plot([], [], 'k--', lw=0.8, label='paper Eq. (9) at the target')
    ax.set_xlim(0, top)
    ax.set_ylim(0, top)
    ax.set_xlabel(r'$\|\epsilon_j\|_\infty$ [µm]')
    ax.set_ylabel(r'$\|\epsilon_d\|_\infty$ [µm]')
    ax.set_title(f'Tolerance frontier, reading {study.reading}')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


# -- workspace ---------------------------------------------------------------------------------
def _crop(ax: Axes, sections: Sequence[Section], margin_mm: float = 30.0) -> None:
    """Limit the axes to the inside of the sections plus a margin."""
    ext = [sec.extent() for sec in sections]
    ext = [e for e in ext if e is not None]
    if not ext:
        return
    u0 = min(mm(e[0][0]) for e in ext) - margin_mm
    u1 = max(mm(e[0][1]) for e in ext) + margin_mm
    v0 = min(mm(e[1][0]) for e in ext) - margin_mm
    v1 = max(mm(e[1][1]) for e in ext) + margin_mm
    ax.set_xlim(u0, u1)
    ax.set_ylim(v0, v1)


def section_figure(sections: Sequence[tuple[float, Section]], path: Path, *,
                   title: str, cylinder: tuple[float, float, float] | None = None,
                   sphere: tuple[Sequence[float], float] | None = None) -> Path:
    """Fig. 8: nested cross-sections, one per rotation range (largest range on top).

    sections : (rotation range [deg], section) pairs, smallest range first
    cylinder : (radius, z_low, z_high) [m] drawn on an x–z section, or radius on x–y
    sphere : (centre (3,), radius) [m]
    """
    fig = Figure(figsize=(8, 6), layout='constrained')
    ax = fig.subplots()
    colours = [f'C{k}' for k in range(len(sections))]
    handles = []
    for (level, sec), colour in zip(sections, colours):
        if not np.any(sec.inside):
            handles.append(Patch(color=colour, label=f'±{level:g}° (empty)'))
            continue
        ax.contourf(mm(sec.u_m), mm(sec.v_m), sec.inside.T.astype(float), levels=[0.5, 1.5],
                    colors=[colour], alpha=0.85)
        handles.append(Patch(color=colour, label=f'±{level:g}°'))
    plane = sections[0][1].plane if sections else 'xz'
    if cylinder is not None:
        r, z0, z1 = (mm(v) for v in cylinder)
        if plane == 'xz':
            ax.add_patch(Rectangle((-r, z0), 2 * r, z1 - z0, fill=False, ls='--', ec='k'))
        else:
            ax.add_patch(Circle((0, 0), r, fill=False, ls='--', ec='k'))
        handles.append(Patch(fill=False, ls='--', ec='k', label='paper cylinder'))
    if sphere is not None:
        c, r = sphere
        u, v = (c[0], c[2]) if plane == 'xz' else (c[0], c[1])
        ax.add_patch(Circle((mm(u), mm(v)), mm(r), fill=False, ec='k', ls=':', lw=1.5))
        handles.append(Patch(fill=False, ec='k', ls=':', label='paper sphere'))
    _crop(ax, [sec for _, sec in sections])
    ax.set_aspect('equal')
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('z [mm]' if plane == 'xz' else 'y [mm]')
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=8, loc='upper right')
    return _save(fig, path)


def binding_figure(section: Section, first_violated: np.ndarray, path: Path, *,
                   title: str) -> Path:
    """Which constraint is violated most outside a section (-1 inside).

    first_violated : ndarray, shape (U, V) — index into :data:`CONSTRAINTS`, -1 inside
        (see :meth:`Workspace.most_violated`)
    """
    fig = Figure(figsize=(8, 6), layout='constrained')
    ax = fig.subplots()
    colours = ['white'] + [f'C{k}' for k in range(len(CONSTRAINTS))]
    cmap = ListedColormap(colours)
    ax.pcolormesh(mm(section.u_m), mm(section.v_m), first_violated.T + 1, cmap=cmap,
                  vmin=-0.5, vmax=len(CONSTRAINTS) + 0.5, shading='nearest')
    _crop(ax, [section], margin_mm=60.0)
    handles = [Patch(color='white', ec='k', label='inside')] + [
        Patch(color=f'C{k}', label=name) for k, name in enumerate(CONSTRAINTS)]
    ax.legend(handles=handles, fontsize=8, loc='upper right')
    ax.set_aspect('equal')
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('z [mm]' if section.plane == 'xz' else 'y [mm]')
    ax.set_title(title)
    return _save(fig, path)

