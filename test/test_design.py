"""Design tools: the Monte Carlo error budget (section 2.2) and the workspace (section 2.3,
Fig. 8) of Lei & Chen (2024). Known answers from the paper's own arithmetic, properties of the
error model, and the reproduction of Eq. (9) with a small N."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.kinematics import inverse_kinematics
from mmd_ros.core.units import M_PER_MM, M_PER_UM
from mmd_ros.design import (
    PAPER_EQ9_UM, PAPER_POSITIONS_M, READINGS, DesignError, ErrorBudget, TopEdgeCylinder, Workspace,
    WorkspaceLimits, fit_eq9, orientation_set, sample_unit_errors, tolerance_frontier)
from mmd_ros.design.error_budget import format_with_se, round_to_se, se_decimals
from mmd_ros.design.workspace import _segment_distance

TOP = np.r_[PAPER_POSITIONS_M[0], 0.0, 0.0, 0.0]       # (100, 0, 323) mm, Fig. 3


@pytest.fixture(scope='module')
def device():
    return load_device(find_config('mmd_prototype.yaml'))


@pytest.fixture(scope='module')
def geometry(device):
    return device.design_geometry


# -- known answers -----------------------------------------------------------------------------
def _horizontal_offset_mm() -> float:
    """|a_1 - b_1| in the plate plane from Table 1 (design): the same for every bar."""
    return math.hypot(98.4808 - 89.9903, -17.3648 - (-107.2462))


def test_home_pose_bar_length_is_the_table_1_arithmetic(geometry):
    z = 285.5
    expected = math.hypot(_horizontal_offset_mm(), z)          # 299.4345 mm
    lengths = inverse_kinematics(geometry, [0, 0, z * M_PER_MM, 0, 0, 0]) / M_PER_MM
    assert expected == pytest.approx(299.4345, abs=1e-4)
    np.testing.assert_allclose(lengths, expected, atol=2e-5)   # Table 1 is rounded to 0.1 µm


def test_z_range_is_set_by_the_bar_range_on_the_axis(device, geometry):
    h = _horizontal_offset_mm()
    expected = math.sqrt(376.0 ** 2 - h * h) - math.sqrt(250.0 ** 2 - h * h)   # 131.87 mm
    ws = Workspace(geometry, WorkspaceLimits.from_device(device))
    z = {e.axis: e for e in ws.extents(step_m=4 * M_PER_MM)}['z']
    assert z.range_m / M_PER_MM == pytest.approx(expected, abs=0.1)
    assert z.low_binding == ('bar_short',) and z.high_binding == ('bar_long',)
    assert z.range_m >= 0.130                                  # the paper's 130 mm holds


def test_whole_segments_never_keep_the_upper_joint_pairs_42_mm_apart(device, geometry):
    # Upper joints 1-2, 3-4, 5-6 are 2 * 100 mm * sin(10°) = 34.73 mm apart: whole centre-line
    # segments cannot satisfy 42 mm, hence the end clearance of the separation check.
    limits = WorkspaceLimits.from_device(device, end_clearance_m=0.0)
    home = Workspace(geometry, limits).margins([[0, 0, 0.2855]], np.eye(3))[0]
    assert (home[4] + 0.042) / M_PER_MM == pytest.approx(200 * math.sin(math.radians(10)), abs=1e-3)
    assert not Workspace(geometry, limits).inside([[0, 0, 0.2855]])[0]
    assert Workspace(geometry, WorkspaceLimits.from_device(device)).inside([[0, 0, 0.2855]])[0]


def test_tilt_margin_on_the_axis_is_atan_of_offset_over_height(device, geometry):
    z = 300.0
    ws = Workspace(geometry, WorkspaceLimits.from_device(device))
    m = ws.margins([[0, 0, z * M_PER_MM]], np.eye(3))[0]
    tilt = math.atan2(_horizontal_offset_mm(), z)
    assert m[2] == pytest.approx(device.upper_tilt_rad - tilt, abs=1e-6)
    assert m[3] == pytest.approx(device.lower_tilt_rad - tilt, abs=1e-6)


def test_segment_distance_matches_brute_force():
    rng = np.random.default_rng(4)
    p1, d1, p2, d2 = (rng.normal(size=(100, 3)) for _ in range(4))
    d2[:10] = d1[:10] * 0.5                                    # parallel pairs too
    got = _segment_distance(list(p1.T), list(d1.T), list(p2.T), list(d2.T))
    s = np.linspace(0, 1, 301)
    a = p1[:, None, :] + s[None, :, None] * d1[:, None, :]
    b = p2[:, None, :] + s[None, :, None] * d2[:, None, :]
    brute = np.min(np.linalg.norm(a[:, :, None] - b[:, None, :], axis=-1), axis=(1, 2))
    assert np.all(got <= brute + 1e-12)
    np.testing.assert_allclose(got, brute, atol=1e-2)


def test_orientation_sets():
    assert orientation_set(0.0).shape == (1, 3)
    cube = orientation_set(math.radians(12))
    assert cube.shape == (27, 3) and np.max(np.abs(cube)) == pytest.approx(math.radians(12))
    assert orientation_set(0.1, 5).shape == (125, 3)
    assert orientation_set(0.1, 3, 'axes').shape == (7, 3)
    with pytest.raises(DesignError):
        orientation_set(0.1, mode='sphere')


# -- error model -------------------------------------------------------------------------------
@pytest.mark.parametrize('reading', sorted(READINGS))
def test_readings_respect_their_bound(reading):
    joint, dist = sample_unit_errors(reading, 500, np.random.default_rng(1))
    assert joint.shape == (500, 2, 6, 3) and dist.shape == (500, 6)
    if reading == 'ball':
        assert np.all(np.linalg.norm(joint, axis=-1) <= 1.0 + 1e-12)
    else:
        bound = 0.5 if reading == 'band' else 1.0
        assert np.all(np.abs(joint) <= bound) and np.all(np.abs(dist) <= bound)
    if reading.startswith('onesided'):
        assert np.all(joint >= 0) and np.all(dist >= 0)
    if reading == 'onesided-max':
        np.testing.assert_allclose(np.max(joint.reshape(500, -1), axis=1), 1.0)
        np.testing.assert_allclose(np.max(dist, axis=1), 1.0)


@pytest.mark.parametrize('method', ['newton', 'linear'])
def test_zero_error_gives_zero_pose_error(geometry, method):
    acc = ErrorBudget(geometry, method=method, samples=200).accuracy(TOP, 0.0, 0.0)
    assert acc.position_m < 1e-13 and acc.rotation_rad < 1e-12


def test_errors_scale_linearly_and_match_the_first_order_model(geometry):
    pose = np.r_[PAPER_POSITIONS_M[2], 0.05, -0.08, 0.3]       # a rotated pose too
    runs = {}
    for method, scale in (('newton', 1.0), ('newton', 3.0), ('linear', 1.0)):
        budget = ErrorBudget(geometry, reading='box', method=method, samples=500, seed=7)
        runs[method, scale] = budget.errors(pose, scale * 0.5 * M_PER_UM, scale * 0.7 * M_PER_UM)
    one, three, lin = runs['newton', 1.0], runs['newton', 3.0], runs['linear', 1.0]
    np.testing.assert_allclose(three.position_m, 3 * one.position_m, rtol=1e-4)
    np.testing.assert_allclose(three.rotation_rad, 3 * one.rotation_rad, rtol=1e-4)
    np.testing.assert_allclose(lin.position_m, one.position_m, rtol=1e-4, atol=1e-12)
    np.testing.assert_allclose(lin.rotation_rad, one.rotation_rad, rtol=1e-4, atol=1e-12)


def test_fit_eq9_recovers_known_coefficients():
    ej, ed = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6), indexing='ij')
    design = np.stack([np.ones(ej.size), ej.ravel(), ed.ravel(), ej.ravel() ** 2,
                       (ej * ed).ravel(), ed.ravel() ** 2], axis=1)
    np.testing.assert_allclose(fit_eq9(ej, ed, design @ PAPER_EQ9_UM), PAPER_EQ9_UM, atol=1e-12)


def test_bad_requests_are_refused(geometry):
    with pytest.raises(DesignError):
        ErrorBudget(geometry, reading='gauss')
    with pytest.raises(DesignError):
        ErrorBudget(geometry, method='exact')
    with pytest.raises(DesignError):
        ErrorBudget(geometry).accuracy([0.1, 0.0], 1e-6, 1e-6)


# -- reproduction of section 2.2 ---------------------------------------------------------------
GRID = np.linspace(0.0, 1.0, 11) * M_PER_UM


def test_onesided_max_reproduces_eq9_and_box_does_not(geometry):
    paper = ErrorBudget(geometry, samples=2000, seed=11).surface(TOP, GRID, GRID)
    # MC noise at N = 2000 moves the coefficients by a few hundredths.
    tolerance = np.array([0.04, 0.12, 0.12, 0.12, 0.15, 0.12])
    assert np.all(np.abs(paper.coefficients_um - PAPER_EQ9_UM) <= tolerance), paper.coefficients_um
    assert paper.rms_um(PAPER_EQ9_UM) < 0.03
    box = ErrorBudget(geometry, reading='box', method='linear', samples=2000,
                      seed=11).surface(TOP, GRID, GRID)
    assert box.rms_um(PAPER_EQ9_UM) > 1.0                      # twice the paper's errors


def test_fig2_and_the_tolerances_of_the_paper(geometry):
    budget = ErrorBudget(geometry, samples=3000, seed=5)
    frontier = tolerance_frontier(budget, PAPER_POSITIONS_M, 2 * M_PER_UM,
                                  angles_rad=[0.0, math.atan2(0.8, 0.4), math.pi / 2])
    joint_only, ratio, dist_only = frontier
    # Section 2.2: 2 µm needs eps_j <= 0.8 µm alone, eps_d <= 1 µm alone; slope about 2.
    assert joint_only.eps_joint_m / M_PER_UM == pytest.approx(0.81, abs=0.04)
    assert dist_only.eps_dist_m / M_PER_UM == pytest.approx(1.04, abs=0.05)
    slope_joint = budget.accuracy(TOP, 1 * M_PER_UM, 0.0).position_m / M_PER_UM
    slope_dist = budget.accuracy(TOP, 0.0, 1 * M_PER_UM).position_m / M_PER_UM
    assert 2.2 < slope_joint < 2.7 and 1.75 < slope_dist < 2.1   # "an approximate slope of 2"
    # The design bounds (0.4, 0.8) µm lie just inside the frontier on their own ratio.
    assert 0.40 < ratio.eps_joint_m / M_PER_UM < 0.47
    assert ratio.eps_dist_m == pytest.approx(2 * ratio.eps_joint_m)
    assert tuple(ratio.worst_pose[:3]) == tuple(PAPER_POSITIONS_M[0])


def test_fig4_design_bounds_keep_2_um_on_the_top_edge(geometry):
    budget = ErrorBudget(geometry, samples=2000, seed=9)
    cyl = TopEdgeCylinder()
    top = budget.positions(cyl.top_edge(6), 0.4 * M_PER_UM, 0.8 * M_PER_UM)
    inside = budget.positions(cyl.interior(4), 0.4 * M_PER_UM, 0.8 * M_PER_UM)
    assert max(a.position_m for a in top) < 1.95 * M_PER_UM
    assert max(a.position_m for a in inside) < min(a.position_m for a in top)
    assert 1.5 < max(a.rotation_rad for a in top) / math.radians(1 / 3600) < 3.0


def test_eq9_standard_errors_match_the_spread_over_independent_seeds(geometry):
    # 40 independent Monte Carlo studies (N = 400 per run, 5 x 5 grid, first-order model):
    # the jackknife standard error each reports must match the scatter of the coefficients
    # between them. A wrong SE (e.g. batch means not divided by sqrt(G)) is off by 4x.
    eps = np.linspace(0.0, 1.0, 5) * M_PER_UM
    coef, se = [], []
    for seed in range(40):
        sf = ErrorBudget(geometry, samples=400, seed=1000 + seed, method='linear').surface(TOP, eps, eps)
        coef.append(sf.coefficients_um)
        se.append(sf.coefficients_se_um)
    coef, se = np.array(coef), np.array(se)
    ratio = coef.std(axis=0, ddof=1) / np.sqrt(np.mean(se ** 2, axis=0))
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    z = (coef - coef.mean(axis=0)) / se
    assert 0.75 < np.sum(z ** 2) / (6 * 39) < 1.3


def test_values_are_rounded_to_their_standard_error():
    assert format_with_se(1.66712, 0.0083) == '1.667 ± 0.008'
    assert format_with_se(1.66712, 0.014) == '1.667 ± 0.014'
    assert format_with_se(-1.2079, 0.041) == '-1.21 ± 0.04'
    assert round_to_se(0.10634, 0.0031) == (0.106, 0.003)
    assert se_decimals(0.25) == 2 and se_decimals(4.0) == 0


# -- workspace statements ----------------------------------------------------------------------
def test_workspace_statements(device, geometry):
    limits = WorkspaceLimits.from_device(device)
    base = Workspace(geometry, limits)
    ranges = {e.axis: e.range_m / M_PER_MM for e in base.extents(step_m=4 * M_PER_MM)}
    assert ranges['x'] == pytest.approx(304.1, abs=1.0)        # the paper says 348
    assert ranges['y'] == pytest.approx(289.0, abs=1.0)        # the paper says 348
    profile = base.disc_profile()
    tallest = base.tallest_cylinder(0.200, profile)
    assert tallest.height_m / M_PER_MM == pytest.approx(74.3, abs=0.3)   # the paper says 75
    assert tallest.z_low_m / M_PER_MM == pytest.approx(250.0, abs=0.1)   # shortest bar
    twelve = base.with_orientations(orientation_set(math.radians(12)))
    sphere = twelve.largest_sphere((0, 0, 0.3), directions=100)
    assert 2 * sphere.distance_m.min() / M_PER_MM == pytest.approx(15.9, abs=1.0)
    assert sphere.binding[sphere.nearest] == ('upper_tilt',)
    assert not twelve.sphere_inside((0, 0, 0.3), 0.025, directions=100)
    nine = base.with_orientations(orientation_set(math.radians(9)))
    assert nine.sphere_inside((0, 0, 0.3), 0.025, directions=100)


# Table 1, design joints: a_i (upper) and b_i (lower), x and y [mm]; z = 0 on both plates.
_UPPER_XY = np.array([[98.4808, -17.3648], [98.4808, 17.3648], [-34.2020, 93.9693],
                      [-64.2788, 76.6044], [-64.2788, -76.6044], [-34.2020, -93.9693]])
_LOWER_XY = np.array([[89.9903, -107.2462], [89.9903, 107.2462], [47.8828, 131.5570],
                      [-137.8731, 24.3107], [-137.8731, -24.3107], [47.8828, -131.5570]])


def _hand_extreme(axis: int, sign: float, *, d_max=376.0, d_min=250.0, tilt_deg=90.0) -> float:
    """The extreme of x (axis 0) or y (1) over the zero-rotation workspace [mm], by plain
    arithmetic on Table 1. At zero rotation a bar's leg is t + a_i - b_i and its tilt is the
    same angle at both plates. Fix the other horizontal coordinate u and the height z: bar i
    then bounds the coordinate w along the axis through its leg component l = w + a_i - b_i by
    |l| <= sqrt(d_max^2 - p^2 - z^2) (bar length) and |l| <= sqrt((z tan tilt)^2 - p^2) (tilt),
    p the leg's other horizontal component. The extreme over all bars at (u, z) is the
    tightest of them, kept where the shortest bar is still >= d_min; then (u, z) is scanned on a
    1 mm grid and refined twice (0.01 mm, 0.1 µm) around the best."""
    other = 1 - axis
    a_w, b_w = _UPPER_XY[:, axis], _LOWER_XY[:, axis]
    a_u, b_u = _UPPER_XY[:, other], _LOWER_XY[:, other]
    tan = math.tan(math.radians(tilt_deg)) if tilt_deg < 90 else math.inf

    def extreme_at(u, z):
        p = u[..., None] + a_u - b_u
        q = np.broadcast_to(z[..., None], p.shape)
        room = d_max ** 2 - p ** 2 - q ** 2
        reach = np.where(room >= 0, np.sqrt(np.abs(room)), -np.inf)
        if tan < math.inf:
            cone = (q * tan) ** 2 - p ** 2
            reach = np.minimum(reach, np.where(cone >= 0, np.sqrt(np.abs(cone)), -np.inf))
        hi = np.min(b_w - a_w + reach, axis=-1)
        lo = np.max(b_w - a_w - reach, axis=-1)
        w = hi if sign > 0 else lo
        shortest = np.min((w[..., None] + a_w - b_w) ** 2 + p ** 2 + q ** 2, axis=-1)
        ok = (hi >= lo) & (shortest >= d_min ** 2)
        return np.where(ok, sign * w, -np.inf)

    best = (0.0, 250.0)
    for half, step in ((250.0, 1.0), (2.0, 0.01), (0.02, 1e-4)):
        u = np.arange(best[0] - half, best[0] + half + step / 2, step)
        z = np.arange(best[1] - half, best[1] + half + step / 2, step)
        uu, zz = np.meshgrid(u, z, indexing='ij')
        values = extreme_at(uu, zz)
        k = np.unravel_index(np.argmax(values), values.shape)
        best, value = (uu[k], zz[k]), values[k]
    return sign * float(value)


@pytest.mark.parametrize('tilt_deg', [90.0, 38.58])
def test_xy_extremes_are_exact_and_their_binding_constraints_found_by_easing_each(device, geometry,
                                                                                tilt_deg):
    # Separation 0: the hand computation has no bar bodies. tilt 90°: no tilt limit at all.
    base = WorkspaceLimits.from_device(device)
    limits = WorkspaceLimits(base.bar_range_m, math.radians(tilt_deg), math.radians(90.0), 0.0)
    extents = {e.axis: e for e in Workspace(geometry, limits).extents(step_m=6 * M_PER_MM)}
    for axis, name in ((0, 'x'), (1, 'y')):
        e = extents[name]
        for sign, got, binding in ((-1, e.low_m, e.low_binding), (1, e.high_m, e.high_binding)):
            expected = _hand_extreme(axis, sign, tilt_deg=tilt_deg)
            # refined to 0.01 mm along the axis (main stopped up to 2 mm short)
            assert got / M_PER_MM == pytest.approx(expected, abs=0.015), (name, sign)
            # which constraints bind, by easing each alone in the hand computation too
            eased_long = _hand_extreme(axis, sign, tilt_deg=tilt_deg, d_max=377.0)
            eased_tilt = _hand_extreme(axis, sign, tilt_deg=min(tilt_deg + 0.5, 90.0))
            eased_short = _hand_extreme(axis, sign, tilt_deg=tilt_deg, d_min=249.0)
            hand = {'bar_long': eased_long, 'upper_tilt': eased_tilt, 'bar_short': eased_short}
            by_hand = {n for n, v in hand.items() if sign * (v - expected) > 0.05}
            assert set(binding) == by_hand, (name, sign, binding, hand)
    if tilt_deg == 90.0:
        # the bar range alone: 506.66 x 438.78 mm (main: 504.5 x 435.8)
        assert extents['x'].range_m / M_PER_MM == pytest.approx(506.66, abs=0.02)
        assert extents['y'].range_m / M_PER_MM == pytest.approx(438.78, abs=0.02)
    else:
        # at both x extremes the longest bar and the upper tilt limit bind together
        assert extents['x'].high_binding == ('bar_long', 'upper_tilt')


def test_the_cylinder_does_not_grow_when_a_tilt_limit_is_eased(device, geometry):
    limits = WorkspaceLimits.from_device(device)
    height = {}
    for name, lim in (('as is', limits), ('upper tilt +5°', limits.relaxed('upper_tilt', math.radians(5))),
                      ('longest bar +1 mm', limits.relaxed('bar_long'))):
        ws = Workspace(geometry, lim)
        height[name] = ws.tallest_cylinder(0.200, ws.disc_profile(), binding=False).height_m / M_PER_MM
    assert height['upper tilt +5°'] == pytest.approx(height['as is'], abs=0.02)
    assert height['longest bar +1 mm'] > height['as is'] + 0.5


def test_most_violated_marks_inside_and_outside(device, geometry):
    ws = Workspace(geometry, WorkspaceLimits.from_device(device))
    got = ws.most_violated([[0, 0, 0.30], [0, 0, 0.40], [0, 0, 0.20]])
    assert got.tolist() == [-1, 1, 0]                         # inside, bar_long, bar_short


# -- command line ------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    from mmd_ros.cli import cmd_error_budget, cmd_workspace
    parser = argparse.ArgumentParser(prog='mmd')
    sub = parser.add_subparsers(dest='command')
    cmd_error_budget.register(sub)
    cmd_workspace.register(sub)
    return parser


def test_error_budget_command_prints_json(capsys):
    args = _parser().parse_args(['error-budget', '--samples', '300', '--eps-step-um', '0.25',
                                 '--parts', 'fig3,tolerance', '--method', 'linear', '--json',
                                 '--no-progress'])
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['reading'] == 'onesided-max' and len(out['fig3']['eq9_fitted']) == 6
    # every coefficient comes with its standard error and is rounded to it
    for value, se, text in zip(out['fig3']['eq9_fitted'], out['fig3']['eq9_standard_error'],
                               out['fig3']['eq9_text']):
        assert 0 < se < 1 and text == format_with_se(value, se)
        assert value == round(value, se_decimals(se))
    assert out['fig3']['eq9_paper'] == PAPER_EQ9_UM.tolist()
    assert 0.3 < out['tolerance']['at_design_ratio']['eps_joint_um'] < 0.6


def test_error_budget_command_rejects_a_bad_pose():
    args = _parser().parse_args(['error-budget', '--pose', '1', '2', '--no-progress'])
    with pytest.raises(DesignError):
        args.func(args)


def test_workspace_command_writes_figures(tmp_path, capsys):
    args = _parser().parse_args(['workspace', '--levels-deg', '0', '12', '--extents', 'zero',
                                 '--step-mm', '6', '--json', '--no-progress',
                                 '--out', str(tmp_path)])
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    verdicts = [s['holds'] for s in out['statements']]
    assert verdicts == [False, False, True, False, False]      # x, y, z, cylinder, sphere
    # what binds, by easing each constraint alone: at the x extremes the upper tilt limit
    # (0.5° more moves them about 2.6 mm) and the longest bar (1 mm more, about 0.6 mm)
    x = out['levels'][0]['ranges']['x']
    assert x['high_binding'] == ['bar_long', 'upper_tilt'] == x['low_binding']
    assert x['high_gain_mm']['upper_tilt'] > 1.0 and x['high_gain_mm']['bar_long'] > 0.3
    assert abs(x['high_gain_mm']['lower_tilt']) < 0.01 and abs(x['high_gain_mm']['separation']) < 0.01
    assert out['statements'][0]['binding'] == ['bar_long', 'upper_tilt']
    # the Ø200 mm cylinder is bounded by the bar range at both ends, not by a tilt limit
    assert out['statements'][3]['tallest_binding'] == ['bar_short', 'bar_long']
    assert out['statements'][4]['binding'] == ['upper_tilt']          # the sphere at ±12°
    assert out['binding_test']['relaxation']['upper_tilt'] == 0.5
    assert out['statements'][-1]['largest_rotation_range_deg'] == pytest.approx(10.1, abs=0.3)
    assert len(out['figures']) == 4
    assert all((tmp_path / f.split('/')[-1]).stat().st_size > 1000 for f in out['figures'])
