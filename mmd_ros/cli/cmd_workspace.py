"""``mmd workspace``: reachable workspace of a device description (section 2.3, Fig. 8).

Computes the workspace for a set of rotation ranges, its cross-sections as in Fig. 8, and
checks the paper's statements (translational ranges, inscribed cylinder, sphere at ±12°),
naming the constraints that bind (each eased alone, the result improves). See ``msg_docs/design_tools.md``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from mmd_ros.cli.device_args import add_device_arguments, device_geometry
from mmd_ros.core import jsonio, validate
from mmd_ros.core.device import find_config
from mmd_ros.core.progress import Progress
from mmd_ros.core.units import M_PER_MM
from mmd_ros.design.workspace import (
    DEFAULT_END_CLEARANCE_M, PAPER_ROTATION_LEVELS_DEG, WorkspaceLimits, WorkspaceStudy,
    orientation_set, run_workspace_study)
from mmd_ros.logs.outputs import check_output_folder

__all__ = ['register', 'run']

#: Bounds of the options: values per angle (the orientations grow as its cube), smallest grid
#: step of the sections [mm] (the grid grows as its inverse square).
MAX_ANGLE_SAMPLES = 15
MIN_STEP_MM = 0.1
FINITE = validate.arg_number()


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'workspace',
        help='reachable workspace and the paper\'s workspace statements (Fig. 8)',
        description='Reachable workspace of a device description under its bar length range, '
                    'ball-joint tilt limits and minimum bar separation, for rotation ranges with '
                    'all three angles together (Fig. 8). Checks the translational ranges, the '
                    'inscribed cylinder at zero rotation and the sphere at the largest range, '
                    'and names the constraints that bind: those whose easing alone improves the result.',
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_device_arguments(p, 'joint set of the device description')
    p.add_argument('--levels-deg', nargs='+', type=validate.arg_number(low=0.0, high=90.0),
                   default=list(PAPER_ROTATION_LEVELS_DEG),
                   help='rotation ranges ±k [deg]; must include 0')
    p.add_argument('--orientations', choices=('cube', 'axes'), default='cube',
                   help='cube: phi, theta, psi within ±k together (the paper); axes: one angle '
                        'at a time')
    p.add_argument('--angle-samples', type=validate.arg_number(low=1, high=MAX_ANGLE_SAMPLES, integer=True),
                   default=3,
                   help='values of each angle in [-k, k] (3: the 27 corners, edge and face '
                        'centres of the cube of angles)')
    p.add_argument('--bar-range-mm', nargs=2, type=FINITE, default=None, metavar=('MIN', 'MAX'),
                   help='override the device\'s centre-distance range')
    p.add_argument('--upper-tilt-deg', type=FINITE, default=None,
                   help='override the largest bar angle to the upper plate normal')
    p.add_argument('--lower-tilt-deg', type=FINITE, default=None,
                   help='override the largest bar angle to the lower plate normal')
    p.add_argument('--min-separation-mm', type=FINITE, default=None,
                   help='override the smallest distance between bar centre lines')
    p.add_argument('--end-clearance-mm', type=FINITE, default=DEFAULT_END_CLEARANCE_M / M_PER_MM,
                   help='length at each bar end (ball and stem) left out of the separation check')
    p.add_argument('--ranges-mm', nargs=3, type=FINITE, default=(348.0, 348.0, 130.0),
                   metavar=('X', 'Y', 'Z'), help='stated translational ranges to check')
    p.add_argument('--cylinder-mm', nargs=2, type=FINITE, default=(200.0, 75.0),
                   metavar=('DIAMETER', 'HEIGHT'), help='stated inscribed cylinder to check')
    p.add_argument('--sphere-mm', nargs=4, type=FINITE, default=(0.0, 0.0, 300.0, 50.0),
                   metavar=('X', 'Y', 'Z', 'DIAMETER'),
                   help='stated sphere at the largest rotation range to check')
    p.add_argument('--step-mm', type=validate.arg_number(low=MIN_STEP_MM, high=1000.0), default=2.0,
                   help=f'grid step of the sections, at least {MIN_STEP_MM:g} mm')
    p.add_argument('--xy-level-mm', type=FINITE, default=300.0, help='height of the x–y section')
    p.add_argument('--extents', choices=('all', 'zero'), default='all',
                   help='3-D ranges at every rotation range or only at zero rotation')
    p.add_argument('--out', type=Path, default=None, help='write PNG figures into this folder')
    p.add_argument('--json', action='store_true', help='print a JSON summary on stdout')
    p.add_argument('--no-progress', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run)


def _limits(args: argparse.Namespace, device: Any) -> WorkspaceLimits:
    base = WorkspaceLimits.from_device(device, end_clearance_m=args.end_clearance_mm * M_PER_MM)
    return WorkspaceLimits(
        tuple(v * M_PER_MM for v in args.bar_range_mm) if args.bar_range_mm else base.bar_range_m,
        base.upper_tilt_rad if args.upper_tilt_deg is None else math.radians(args.upper_tilt_deg),
        base.lower_tilt_rad if args.lower_tilt_deg is None else math.radians(args.lower_tilt_deg),
        args.min_separation_mm * M_PER_MM if args.min_separation_mm is not None
        else base.min_separation_m,
        base.end_clearance_m)


def run(args: argparse.Namespace) -> int:
    check_output_folder('--out', args.out, [find_config(args.device)], ('*.png',))
    device, geometry = device_geometry(args)
    limits = _limits(args, device)
    progress = Progress('workspace', 1.0, enabled=not args.no_progress)
    sphere = (tuple(v * M_PER_MM for v in args.sphere_mm[:3]), args.sphere_mm[3] * M_PER_MM)
    study = run_workspace_study(
        geometry, limits, levels_deg=args.levels_deg, points_per_axis=args.angle_samples,
        mode=args.orientations, section_step_m=args.step_mm * M_PER_MM,
        xy_level_m=args.xy_level_mm * M_PER_MM, extents_all_levels=args.extents == 'all',
        ranges_m=tuple(v * M_PER_MM for v in args.ranges_mm),
        cylinder_m=tuple(v * M_PER_MM for v in args.cylinder_mm), sphere=sphere,
        progress=progress.update)
    progress.close()
    summary: dict[str, Any] = {'device': device.name, 'joints': args.joints}
    summary.update(study.summary())
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        summary['figures'] = [str(f) for f in _figures(study, geometry, args.out)]
    if args.json:
        jsonio.dump(summary, sys.stdout, indent=1)
    else:
        _print_report(summary)
    return 0


def _figures(study: WorkspaceStudy, geometry: Any, out: Path) -> list[Path]:
    from mmd_ros.design import plots
    from mmd_ros.design.workspace import Workspace

    written = []
    sections_xz = [(lv.range_deg, lv.xz) for lv in study.levels]
    sections_xy = [(lv.range_deg, lv.xy) for lv in study.levels]
    d, h = study.cylinder_m
    z0 = study.widest.z_low_m if math.isfinite(study.widest.z_low_m) else 0.0
    cyl = (d / 2, z0, z0 + h)
    sph = (study.sphere_centre_m, study.sphere_diameter_m / 2)
    mode = 'together' if study.mode == 'cube' else 'one at a time'
    written.append(plots.section_figure(
        sections_xz, out / 'fig8_workspace_xz.png', cylinder=cyl, sphere=sph,
        title=f'Fig. 8: workspace, x–z section at y = 0 (angles {mode})'))
    xy_level = study.levels[0].xy.level_m
    written.append(plots.section_figure(
        sections_xy, out / 'fig8_workspace_xy.png', cylinder=(d / 2, 0.0, 0.0),
        sphere=sph if abs(xy_level - sph[0][2]) < 1e-9 else None,
        title=f'Fig. 8: workspace, x–y section at z = {xy_level / M_PER_MM:g} mm'))
    for lv in (study.levels[0], study.levels[-1]):
        ws = Workspace(geometry, study.limits,
                       orientation_set(math.radians(lv.range_deg), study.points_per_axis,
                                       study.mode))
        uu, vv = np.meshgrid(lv.xz.u_m, lv.xz.v_m, indexing='ij')
        pts = np.stack([uu.ravel(), np.zeros(uu.size), vv.ravel()], axis=1)
        worst = ws.most_violated(pts).reshape(uu.shape)
        written.append(plots.binding_figure(
            lv.xz, worst, out / f'workspace_binding_xz_{lv.range_deg:g}deg.png',
            title=f'Most violated constraint, x–z at y = 0, ±{lv.range_deg:g}°'))
    return written


def _print_report(s: dict[str, Any]) -> None:
    out = sys.stdout.write
    lim = s['limits']
    out(f"mmd workspace: device {s['device']} ({s['joints']} joints)\n"
        f"  bars {lim['bar_range_mm'][0]:g}–{lim['bar_range_mm'][1]:g} mm, tilt <= "
        f"{lim['upper_tilt_deg']:g}° (upper) / {lim['lower_tilt_deg']:g}° (lower), centre lines "
        f">= {lim['min_separation_mm']:g} mm apart ({lim['end_clearance_mm']:g} mm left out at "
        f"each bar end)\n"
        f"  orientations: {s['orientations']['mode']}, {s['orientations']['points_per_axis']} "
        "values per angle\n\n")
    out('  ±deg  orient.   x range [mm]              y range [mm]              z range [mm]'
        '              sphere dia [mm]\n')
    for lv in s['levels']:
        cells = []
        for axis in 'xyz':
            r = lv.get('ranges', {}).get(axis)
            cells.append('-' if r is None else
                         f"{r['range_mm']:6.1f} ({r['low_mm']:7.1f}..{r['high_mm']:6.1f})")
        sph = lv['sphere']
        out(f"  {lv['range_deg']:4g}  {lv['orientations']:7d}   "
            + ''.join(f'{c:26s}' for c in cells)
            + f"{sph['largest_diameter_mm']:6.1f} ({', '.join(sph['binding']) or '-'})\n")
    test = s['binding_test']
    out(f"\n  A constraint binds when easing it alone (bars {test['relaxation']['bar_long']:g} mm, "
        f"tilts {test['relaxation']['upper_tilt']:g}°, separation "
        f"{test['relaxation']['separation']:g} mm) improves the result by more than "
        f"{test['threshold_mm']:g} mm.\n")
    out('\nStatements of the paper:\n')
    for st in s['statements']:
        verdict = 'HOLDS' if st['holds'] else 'DOES NOT HOLD'
        out(f"  {st['statement']}: {verdict}\n")
        if 'measured_mm' in st:
            out(f"    measured {st['measured_mm']:.2f} mm; binding (easing one alone widens "
                f"it): {', '.join(st['binding']) or '-'}\n")
        elif 'tallest_at_diameter_mm' in st:
            out(f"    tallest at that diameter: {st['tallest_at_diameter_mm']:.2f} mm "
                f"(z {st['tallest_z_mm'][0]:.2f}..{st['tallest_z_mm'][1]:.2f} mm; limited by "
                f"{', '.join(st['tallest_binding'])})\n"
                f"    widest at that height: {st['widest_at_height_mm']:.2f} mm "
                f"(z {st['widest_z_mm'][0]:.2f}..{st['widest_z_mm'][1]:.2f} mm; limited by "
                f"{', '.join(st['widest_binding'])})\n")
        else:
            out(f"    largest sphere there: {st['largest_diameter_mm']:.2f} mm (limited by "
                f"{', '.join(st['binding'])}); the stated sphere fits up to "
                f"±{st['largest_rotation_range_deg']:.2f}°\n")
    if 'figures' in s:
        out('\nFigures: ' + ', '.join(s['figures']) + '\n')
