"""``mmd error-budget``: Monte Carlo error budget of the kinematic parameters (section 2.2).

Reproduces Fig. 2 (a, b), the Fig. 3 surface with the Eq. (9) fit, Fig. 4, adds rotation
errors and answers the inverse question (largest tolerances for a target accuracy) for any
device description. See ``msg_docs/design_tools.md``.
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
from mmd_ros.core.units import M_PER_MM, M_PER_UM
from mmd_ros.design.error_budget import (
    DEFAULT_READING, JACKKNIFE_GROUPS, METHODS, PAPER_EQ9_UM, PAPER_POSITIONS_M, PARTS, READINGS,
    ErrorBudget, TopEdgeCylinder, eq9_summary, planned_runs, run_study)
from mmd_ros.design.errors import DesignError
from mmd_ros.logs.outputs import check_output_folder

__all__ = ['register', 'run']

#: Bounds of the options: Monte Carlo samples per run, tolerance bounds [µm], grid values per axis.
MAX_SAMPLES = 1_000_000
MAX_EPS_UM = 100.0
MAX_GRID = 100
FINITE = validate.arg_number()

_EQ9_TERMS = ('1', 'e_j', 'e_d', 'e_j^2', 'e_j e_d', 'e_d^2')


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'error-budget',
        help='Monte Carlo error budget of joint and bar tolerances (paper section 2.2)',
        description='Monte Carlo error budget of section 2.2: the true device has its joint '
                    'positions and centre distances perturbed, the software uses the nominal '
                    'ones; accuracy = mean + 2 std of the pose error over N samples. Prints '
                    'Fig. 2 (a, b), the Eq. (9) fit of Fig. 3 beside the paper, Fig. 4, rotation '
                    'errors, and the largest tolerances that keep a target accuracy.',
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_device_arguments(p, 'nominal joint set of the device description')
    p.add_argument('--pose', action='append', nargs='+', type=FINITE, metavar='V',
                   help='setting pose X Y Z [PHI THETA PSI] in mm and degrees; repeat for '
                        'several; default the five positions of Fig. 2 at zero rotation. '
                        'Fig. 3 is computed at the first one')
    p.add_argument('--samples', '-n', type=validate.arg_number(low=2, high=MAX_SAMPLES, integer=True),
                   default=10_000, help='N per Monte Carlo run')
    p.add_argument('--seed', type=validate.arg_number(low=0, integer=True), default=0, help='random seed')
    p.add_argument('--perturbation', choices=sorted(READINGS), default=DEFAULT_READING,
                   help='how errors up to a bound are drawn: ' + '; '.join(
                       f'{k}: {v}' for k, v in READINGS.items()))
    p.add_argument('--method', choices=METHODS, default='newton',
                   help='newton: full forward kinematics per sample; linear: first-order model')
    p.add_argument('--eps-max-um', type=validate.arg_number(low=0.0, low_open=True, high=MAX_EPS_UM),
                   default=1.0,
                   help='largest bound of Fig. 2 and of the Fig. 3 grid [µm]')
    p.add_argument('--eps-step-um', type=validate.arg_number(low=0.0, low_open=True, high=MAX_EPS_UM),
                   default=0.1, help='grid step of the bounds [µm]')
    p.add_argument('--design-point', nargs=2, type=validate.arg_number(low=0.0, high=MAX_EPS_UM),
                   default=(0.4, 0.8),
                   metavar=('EPS_J', 'EPS_D'), help='bounds of Fig. 4 and the design ratio [µm]')
    p.add_argument('--cylinder', nargs=3, type=FINITE, default=(100.0, 248.0, 323.0),
                   metavar=('RADIUS', 'Z_LOW', 'Z_HIGH'),
                   help='cylindrical workspace of Fig. 4 [mm]')
    p.add_argument('--target-um', type=validate.arg_number(low=0.0, low_open=True), default=2.0,
                   help='position accuracy the tolerances must keep [µm]')
    p.add_argument('--target-arcsec', type=validate.arg_number(low=0.0, low_open=True), default=None,
                   help='also keep this rotation accuracy [arc-seconds]')
    p.add_argument('--parts', default=','.join(PARTS),
                   help=f'comma-separated parts to run, of {",".join(PARTS)}')
    p.add_argument('--compare-readings', action='store_true',
                   help='also fit Eq. (9) under every perturbation reading and compare')
    p.add_argument('--out', type=Path, default=None, help='write PNG figures into this folder')
    p.add_argument('--json', action='store_true', help='print a JSON summary on stdout')
    p.add_argument('--no-progress', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run)


def _poses(raw: list[list[float]] | None) -> np.ndarray:
    if not raw:
        return np.hstack([PAPER_POSITIONS_M, np.zeros((len(PAPER_POSITIONS_M), 3))])
    poses = []
    for values in raw:
        if len(values) not in (3, 6):
            raise DesignError(f'--pose takes X Y Z or X Y Z PHI THETA PSI, got {values}')
        v = list(values) + [0.0] * (6 - len(values))
        poses.append([v[0] * M_PER_MM, v[1] * M_PER_MM, v[2] * M_PER_MM]
                     + [math.radians(a) for a in v[3:]])
    return np.array(poses)


def _grid(eps_max_um: float, step_um: float) -> np.ndarray:
    if not (eps_max_um > 0 and step_um > 0 and step_um <= eps_max_um):
        raise DesignError('need 0 < --eps-step-um <= --eps-max-um')
    count = int(round(eps_max_um / step_um))
    if count > MAX_GRID:
        raise DesignError(f'--eps-max-um / --eps-step-um gives {count} grid steps; at most {MAX_GRID}')
    return np.linspace(0.0, count * step_um, count + 1) * M_PER_UM


def run(args: argparse.Namespace) -> int:
    check_output_folder('--out', args.out, [find_config(args.device)], ('*.png',))
    parts = [s.strip() for s in args.parts.split(',') if s.strip()]
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise DesignError(f'--parts: unknown {sorted(unknown)}; use some of {list(PARTS)}')
    device, geometry = device_geometry(args)
    poses = _poses(args.pose)
    eps = _grid(args.eps_max_um, args.eps_step_um)
    design = (args.design_point[0] * M_PER_UM, args.design_point[1] * M_PER_UM)
    if min(design) < 0 or max(design) <= 0:
        raise DesignError('--design-point bounds must be >= 0 and not both zero')
    cylinder = TopEdgeCylinder(*(v * M_PER_MM for v in args.cylinder))
    target_rot = None if args.target_arcsec is None else math.radians(args.target_arcsec / 3600)

    readings = sorted(READINGS) if args.compare_readings else []
    total = planned_runs(parts, len(poses), eps) + len(readings) * eps.size ** 2
    progress = Progress('error-budget', total, enabled=not args.no_progress)
    done = [0]

    def tick(_: int) -> None:
        done[0] += 1
        progress.update(done[0])

    budget = ErrorBudget(geometry, reading=args.perturbation, method=args.method,
                         samples=args.samples, seed=args.seed, on_run=tick)
    study = run_study(budget, poses, parts=parts, eps_values_m=eps, design_point_m=design,
                      cylinder=cylinder, target_position_m=args.target_um * M_PER_UM,
                      target_rotation_rad=target_rot)
    comparison = []
    for k, reading in enumerate(readings):
        other = ErrorBudget(geometry, reading=reading, method=args.method, samples=args.samples,
                            seed=args.seed + 1 + k, on_run=tick)
        comparison.append((reading, other.surface(poses[0], eps, eps)))
    progress.close()

    summary: dict[str, Any] = {'device': device.name, 'joints': args.joints, 'seed': args.seed}
    summary.update(study.summary())
    if comparison:
        summary['readings'] = {
            reading: {**eq9_summary(sf),
                      'rms_fit_vs_paper_um': round(sf.rms_um(PAPER_EQ9_UM), 4),
                      'rms_points_vs_paper_um': round(sf.rms_um(PAPER_EQ9_UM, 'points'), 4)}
            for reading, sf in comparison}
    if args.out is not None:
        from mmd_ros.design import plots
        args.out.mkdir(parents=True, exist_ok=True)
        summary['figures'] = [str(f) for f in plots.error_budget_figures(study, args.out)]
    if args.json:
        jsonio.dump(summary, sys.stdout, indent=1)
    else:
        _print_report(summary)
    return 0


def _fmt(values: Any, width: int = 8, digits: int = 3) -> str:
    return ''.join(f'{v:{width}.{digits}f}' for v in values)


def _eq9_cells(f: dict[str, Any]) -> str:
    """The fitted Eq. (9) coefficients, each as value ± standard error when known."""
    cells = f.get('eq9_text') or [f'{v:.4f}' for v in f['eq9_fitted']]
    return ''.join(f'{c:>16s}' for c in cells)


def _print_report(s: dict[str, Any]) -> None:
    out = sys.stdout.write
    out(f"mmd error-budget: device {s['device']} ({s['joints']} joints), reading "
        f"{s['reading']}, method {s['method']}, N = {s['samples']}, seed {s['seed']}\n"
        f"  reading: {s['reading_description']}\n"
        "  accuracy = mean + 2 std of |t_est - t| [µm]; rotation = mean + 2 std of the "
        "rotation-error angle [arcsec]\n")
    labels = [f"({', '.join(f'{v:g}' for v in p)})" for p in s['setting_positions_mm']]
    for key, title in (('fig2_joint', 'Fig. 2(a): joint errors only'),
                       ('fig2_distance', 'Fig. 2(b): centre-distance errors only')):
        if key not in s:
            continue
        f = s[key]
        out(f"\n{title}; P1..P{len(labels)} = " + ', '.join(labels) + ' mm\n')
        head = ''.join(f'{"P" + str(k + 1):>8s}' for k in range(len(labels)))
        out(f'  eps [µm]  position [µm]{" " * max(0, 8 * len(labels) - 13)}  rotation [arcsec]\n')
        out(f'          {head}  {head}\n')
        for i, e in enumerate(f['eps_um']):
            out(f"  {e:6.2f}  {_fmt([row[i] for row in f['position_um']])}  "
                f"{_fmt([row[i] for row in f['rotation_arcsec']])}\n")
        out(f"  slope   {_fmt(f['slope_um_per_um'])}  µm/µm\n")
        out(f"  eps for {s['target_um']:g} µm at the worst position: "
            f"{min(f['eps_for_target_um']):.3f} µm\n")
    if 'fig3' in s:
        f = s['fig3']
        out(f"\nFig. 3 at ({', '.join(f'{v:g}' for v in f['position_mm'])}) mm: Eq. (9) fitted "
            f"over eps_j, eps_d in {f['eps_um'][0]:g}..{f['eps_um'][-1]:g} µm "
            f"({len(f['eps_um'])} x {len(f['eps_um'])} grid)\n")
        out('  term     ' + ''.join(f'{t:>16s}' for t in _EQ9_TERMS) + '\n')
        out('  fitted   ' + _eq9_cells(f) + '\n')
        out('  paper    ' + ''.join(f'{v:16.2f}' for v in f['eq9_paper']) + '\n')
        if f.get('eq9_standard_error') is not None:
            out(f"  ± is the Monte Carlo standard error (jackknife over {JACKKNIFE_GROUPS} groups "
                "of each run's samples); fitted − paper in standard errors: "
                + ', '.join(f'{v:+.1f}' for v in f['eq9_paper_deviation_se']) + '\n')
        out(f"  surface RMS, fitted vs paper Eq. (9): {f['rms_fit_vs_paper_um']:.4f} µm; "
            f"Monte Carlo points vs paper: {f['rms_points_vs_paper_um']:.4f} µm "
            f"(max {f['max_abs_points_vs_paper_um']:.3f}); points vs own fit: "
            f"{f['rms_points_vs_fit_um']:.4f} µm\n")
    for key, title in (('design_point', 'At the design bounds, setting positions'),
                       ('fig4_top', 'Fig. 4(a): design bounds, top edge of the cylinder'),
                       ('fig4_inside', 'Fig. 4(b): design bounds, inside the cylinder')):
        if key not in s:
            continue
        f = s[key]
        ej, ed = s['design_point_um']
        out(f"\n{title} (eps_j = {ej:g} µm, eps_d = {ed:g} µm): "
            f"max {f['max_position_um']:.3f} µm "
            f"at ({', '.join(f'{v:g}' for v in f['worst_position_mm'])}) mm, max rotation "
            f"{f['max_rotation_arcsec']:.2f} arcsec\n")
        for pos, acc, rot in zip(f['positions_mm'], f['position_um'], f['rotation_arcsec']):
            out(f"  ({pos[0]:8.2f}, {pos[1]:8.2f}, {pos[2]:7.2f})  {acc:6.3f} µm  "
                f"{rot:5.2f} arcsec\n")
    if 'tolerance' in s:
        f = s['tolerance']
        extra = '' if s['target_arcsec'] is None else f" and {s['target_arcsec']:g} arcsec"
        out(f"\nLargest bounds keeping {s['target_um']:g} µm{extra} at the setting positions and "
            "the top edge (worst of them):\n"
            f"  joints alone: eps_j <= {f['joint_only_um']:.3f} µm; centre distances alone: "
            f"eps_d <= {f['dist_only_um']:.3f} µm\n")
        r = f['at_design_ratio']
        out(f"  at the design ratio: eps_j <= {r['eps_joint_um']:.3f} µm with eps_d <= "
            f"{r['eps_dist_um']:.3f} µm (check run: {r['check_max_position_um']:.3f} µm, "
            f"{r['check_max_rotation_arcsec']:.2f} arcsec)\n")
        out('  frontier:  angle   eps_j [µm]  eps_d [µm]  binding\n')
        for p in f['frontier']:
            out(f"           {p['angle_deg']:5.1f}  {p['eps_joint_um']:10.3f}  "
                f"{p['eps_dist_um']:10.3f}  {p['binding']}\n")
    if 'readings' in s:
        out('\nEq. (9) under each perturbation reading (Fig. 3 grid at the first position):\n')
        out('  reading        ' + ''.join(f'{t:>16s}' for t in _EQ9_TERMS)
            + '   RMS vs paper [µm]\n')
        for reading, f in s['readings'].items():
            out(f"  {reading:14s} {_eq9_cells(f)}   {f['rms_fit_vs_paper_um']:.4f}\n")
    if 'figures' in s:
        out('\nFigures: ' + ', '.join(s['figures']) + '\n')
