"""Kinematics: Eq. (3) convention, IK Eq. (6), Jacobian, Newton FK and pose covariance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mmd_ros.core.compiled import AVAILABLE as COMPILED, NOT_IN_USE
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.kinematics import (
    TILT_SLACK_RAD, FkLimits, FkStatus, ForwardKinematics, inverse_kinematics, jacobian,
    pose_covariance, propagate_covariance,
)
from mmd_ros.core.rotation import (
    angles_to_quaternion, matrix_to_angles, quaternion_to_angles, rotation_angle, rotation_matrix,
)
from mmd_ros.twin.mechanism import bar_legs, random_poses, rotation_matrices, within_workspace

DEVICE = load_device(find_config('mmd_prototype.yaml'))
GEOMETRY = DEVICE.geometry
FK = ForwardKinematics(GEOMETRY)
LOW, HIGH = DEVICE.bar_range_m
SOLUTION_FIELDS = ('poses', 'converged', 'status', 'iterations', 'residual_m', 'condition')


def assert_identical(a, b, fields=SOLUTION_FIELDS):
    """Two solutions agree bit for bit (NaN where the other has NaN)."""
    for f in fields:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def unrelated_poses(n: int, seed: int, *, inside: bool = True):
    """Poses that jump between unrelated configurations and their lengths, from the twin's own
    kinematics (code independent of the solver's)."""
    return random_poses(DEVICE, n, seed, inside=inside)


def wrong(poses, truth):
    """Converged poses that are not the true one: position or rotation matrix off by more than
    1e-9 (angles compared as rotations, so that 2 pi apart is the same pose)."""
    ok = np.all(np.isfinite(poses), axis=1)
    off = np.zeros(len(truth), dtype=bool)
    r_est = rotation_matrices(np.where(ok[:, None], poses, 0.0))
    off[ok] = (np.max(np.abs(poses[ok, :3] - truth[ok, :3]), axis=1) > 1e-9) | \
        (np.max(np.abs(r_est[ok] - rotation_matrices(truth[ok])), axis=(1, 2)) > 1e-9)
    return off


def poses_in_workspace():
    """Poses whose six bars lie inside the bar range (a superset of the reachable workspace)."""
    return st.tuples(
        st.floats(-0.12, 0.12), st.floats(-0.12, 0.12), st.floats(0.24, 0.35),
        st.floats(-0.26, 0.26), st.floats(-0.26, 0.26), st.floats(-0.7, 0.7),
    ).map(np.array).filter(lambda p: bool(np.all((inverse_kinematics(GEOMETRY, p) > LOW)
                                                  & (inverse_kinematics(GEOMETRY, p) < HIGH))))


def test_rotation_is_eq3_zyx():
    rng = np.random.default_rng(3)
    angles = rng.uniform(-1, 1, (50, 3))
    expected = Rotation.from_euler('ZYX', angles[:, ::-1]).as_matrix()
    assert np.allclose(rotation_matrix(angles), expected, atol=1e-15)
    assert np.allclose(matrix_to_angles(expected), angles, atol=1e-12)
    q = angles_to_quaternion(angles)
    assert np.allclose(np.abs(np.sum(q * Rotation.from_matrix(expected).as_quat(), axis=1)), 1.0)
    assert np.allclose(quaternion_to_angles(q), angles, atol=1e-12)


def test_home_bar_length_of_design_geometry():
    # sqrt(|a_i - b_i|_xy^2 + 300^2) with Table 1's design joints: 313.2902 mm for every bar
    # (the table rounds to 0.1 um, so the six differ by a few nm).
    d = inverse_kinematics(DEVICE.design_geometry, [0, 0, 0.3, 0, 0, 0])
    horizontal = np.hypot(98.4808 - 89.9903, -17.3648 + 107.2462)
    assert d == pytest.approx(np.full(6, np.hypot(horizontal, 300.0) * 1e-3), abs=1e-8)
    assert d[0] * 1e3 == pytest.approx(313.2902, abs=1e-4)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(4)
    for _ in range(20):
        p = np.array([*rng.uniform(-0.08, 0.08, 2), rng.uniform(0.27, 0.33), *rng.uniform(-0.2, 0.2, 3)])
        h = 1e-7
        numeric = np.column_stack([
            (inverse_kinematics(GEOMETRY, p + h * e) - inverse_kinematics(GEOMETRY, p - h * e)) / (2 * h)
            for e in np.eye(6)])
        assert np.allclose(jacobian(GEOMETRY, p), numeric, atol=1e-8)


@settings(max_examples=300, deadline=None)
@given(poses_in_workspace())
def test_fk_inverts_ik_per_sample(p):
    FK.reset()
    sol = FK.solve(inverse_kinematics(GEOMETRY, p))
    assert sol.converged
    assert np.max(np.abs(sol.pose[:3] - p[:3])) < 1e-12   # 1e-9 mm
    assert np.max(np.abs(sol.pose[3:] - p[3:])) < 1e-12   # rad


def test_fk_inverts_ik_in_batch_over_the_workspace():
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(-0.12, 0.12, (20000, 2)), rng.uniform(0.24, 0.35, 20000),
                         rng.uniform(-0.26, 0.26, (20000, 2)), rng.uniform(-0.7, 0.7, 20000)])
    d = inverse_kinematics(GEOMETRY, p)
    inside = np.all((d > LOW) & (d < HIGH), axis=1)
    sol = FK.solve_batch(d[inside])
    assert inside.sum() > 3000
    assert sol.converged.all()
    assert np.max(np.abs(sol.poses[:, :3] - p[inside, :3])) < 1e-12
    assert np.max(np.abs(sol.poses[:, 3:] - p[inside, 3:])) < 1e-12
    assert np.all(np.isfinite(sol.condition)) and np.all(sol.condition >= 1)


def test_streaming_warm_start_tracks_a_trajectory_in_few_iterations():
    t = np.arange(3000) * 1e-3
    p = np.column_stack([0.1 * np.sin(t), 0.05 * np.cos(t), 0.3 + 0.01 * t, 0 * t, 0.02 * t, 0.3 * np.sin(t)])
    d = inverse_kinematics(GEOMETRY, p)
    FK.reset()
    iters = []
    for k in range(len(t)):
        sol = FK.solve(d[k])
        assert sol.converged
        assert np.max(np.abs(sol.pose - p[k])) < 1e-12
        iters.append(sol.iterations)
    assert np.median(iters) <= 2


def test_compiled_streaming_solver_does_what_the_python_one_does():
    """The compiled solver (_fast.c, the 1 kHz path) against ForwardKinematics.solve, sample
    after sample, bit for bit: a noisy motion, a broken sample, a jump that needs damped steps,
    impossible lengths, lengths beyond the bars' range, a run of jumps between unrelated poses,
    and an iteration cap that leaves samples unconverged (the warm start restarts)."""
    assert COMPILED, NOT_IN_USE
    rng = np.random.default_rng(11)
    t = np.arange(3000) * 1e-3
    # a motion inside the device's workspace, and at 1.5 s a jump to another (in the workspace)
    p = np.column_stack([0.05 * np.sin(t), 0.03 * np.cos(2 * t), 0.3 + 0.005 * t,
                         0.03 * np.sin(t), 0.01 * t, 0.3 * np.sin(0.5 * t)])
    p[1500:] += [0.01, -0.02, 0.0, 0.02, -0.02, -0.1]
    d = inverse_kinematics(GEOMETRY, p) + rng.normal(0, 50e-9, (len(t), 6))
    d[700, 3] = np.nan
    d[2200] = [0.25, 0.376, 0.25, 0.376, 0.25, 0.376]
    d[2300, 1] = 0.2
    d[2400:2600] = unrelated_poses(200, 3, inside=False)[1]
    dt = np.full(len(t), 1e-3)
    dt[1000] = 5.0                # a gap: the continuity test allows more
    for max_iter in (20, 3):
        runs = []
        for compiled in (False, True):
            fk = ForwardKinematics.for_device(DEVICE, max_iter=max_iter)
            # transfer by transfer, as the nodes call it: the warm start carries across calls
            parts = [fk.solve_stream(d[k:k + 8], dt_s=dt[k:k + 8], compiled=compiled)
                     for k in range(0, len(t), 8)]
            runs.append({f: np.concatenate([getattr(q, f) for q in parts])
                         for f in SOLUTION_FIELDS + ('jacobians',)})
        py, c = runs
        for f in py:
            np.testing.assert_array_equal(py[f], c[f], err_msg=f)
        assert c['status'][700] == FkStatus.OUT_OF_SPAN and np.isnan(c['poses'][700]).all()
        assert c['status'][2200] == FkStatus.NOT_CONVERGED
        assert c['status'][2300] == FkStatus.BAR_RANGE and c['iterations'][2300] == 0
        if max_iter == 20:
            jumps = c['status'][2400:2600]
            assert (jumps == FkStatus.RESEEDED).sum() > 20
            assert (jumps == FkStatus.IMPLAUSIBLE).sum() > 50
            assert c['converged'][:1500].sum() == 1499 and c['converged'][1500:2200].all()
            assert c['status'][1500] == FkStatus.RESEEDED  # the jump: re-solved from home
            assert c['iterations'][1500] > 3
        else:
            assert 0 < c['converged'].sum() < len(t) - 2


def test_jumps_between_unrelated_poses_give_no_wrong_pose():
    """Issue 13: poses that jump between unrelated configurations, each solved from the one
    before (as after a gap, a counter reset, a re-seated bar, or a cut log replayed without
    reset()). Against the true poses, every one the device can reach comes back converged and
    right; without the device's limits the same sequence gives wrong converged poses."""
    truth, d = unrelated_poses(2000, 7)
    paths = [True, False] if COMPILED else [False]
    for compiled in paths:
        n = 2000 if compiled else 500
        fk = ForwardKinematics.for_device(DEVICE)
        sol = fk.solve_stream(d[:n], compiled=compiled)
        assert not wrong(sol.poses, truth[:n]).any()
        assert sol.converged.all()
        assert (sol.status == FkStatus.RESEEDED).sum() > n / 20
        for batch in (fk.solve_batch(d[:n], compiled=compiled),
                      fk.solve_batch(d[:n], np.roll(truth[:n], 1, axis=0), compiled=compiled)):
            assert not wrong(batch.poses, truth[:n]).any() and batch.converged.all()
    unchecked = ForwardKinematics(GEOMETRY, limits=FkLimits(
        upper_tilt_rad=np.pi, lower_tilt_rad=np.pi, max_condition=1e300, max_speed_m_s=1e9))
    sol = unchecked.solve_stream(d)
    assert wrong(sol.poses, truth)[sol.converged].sum() > 20


def test_poses_beyond_the_joint_limits_are_not_called_converged():
    """The issue's own sampling (every bar in range, tilts not checked): no wrong converged
    pose; what the joints cannot reach comes back IMPLAUSIBLE, with no pose."""
    truth, d = unrelated_poses(2000, 8, inside=False)
    fk = ForwardKinematics.for_device(DEVICE)
    sol = fk.solve_stream(d)
    assert not wrong(sol.poses, truth).any()
    rot = rotation_matrices(truth)
    legs = bar_legs(GEOMETRY.upper, GEOMETRY.lower, truth, rot)
    reachable = within_workspace(DEVICE, legs, rot)
    beyond = ~within_workspace(DEVICE, legs, rot, margin_rad=-TILT_SLACK_RAD)
    assert reachable.sum() > 300 and beyond.sum() > 300
    assert sol.converged[reachable].all() and not sol.converged[beyond].any()
    assert np.all(sol.status[beyond] == FkStatus.IMPLAUSIBLE)
    assert np.isnan(sol.poses[~sol.converged]).all()
    batch = fk.solve_batch(d)
    assert not wrong(batch.poses, truth).any()
    assert np.array_equal(batch.converged, sol.converged)


def test_a_jump_is_re_solved_from_home_and_a_gap_allows_it():
    """Continuity at the measured rate: 5 mm in 1 ms is faster than the device moves (2 m/s),
    so the warm start's answer is not taken and the sample is re-solved from the home seeds;
    after a 1 s gap the same step is continuous."""
    a = np.array([0.01, 0.0, 0.30, 0.0, 0.0, 0.0])
    b = a + [0.005, 0.0, 0.0, 0.0, 0.0, 0.0]
    d = inverse_kinematics(GEOMETRY, np.array([a, a, a, b]))
    for compiled in ([False, True] if COMPILED else [False]):
        for dt, expected in ((1e-3, FkStatus.RESEEDED), (1.0, FkStatus.OK)):
            fk = ForwardKinematics.for_device(DEVICE)
            sol = fk.solve_stream(d, dt_s=[1e-3, 1e-3, 1e-3, dt], compiled=compiled)
            assert sol.status.tolist() == [FkStatus.OK] * 3 + [expected]
            assert np.max(np.abs(sol.poses[3] - b)) < 1e-12


def test_the_limits_reject_what_they_say():
    """Each test of the plausibility check on its own: conditioning and the bar range."""
    truth, d = unrelated_poses(300, 9)
    cond = ForwardKinematics.for_device(DEVICE).solve_batch(d).condition
    assert 10 < np.median(cond) < 30 and cond.max() < 50       # the prototype's workspace
    strict = ForwardKinematics.for_device(DEVICE, limits=FkLimits.from_device(
        DEVICE, max_condition=float(np.median(cond))))
    for compiled in ([False, True] if COMPILED else [False]):
        sol = strict.solve_batch(d, compiled=compiled)
        assert np.array_equal(sol.status == FkStatus.ILL_CONDITIONED, cond > np.median(cond))
        assert np.isnan(sol.poses[~sol.converged]).all()
        short = d.copy()
        short[::3, 4] = LOW - 2e-3
        sol = ForwardKinematics.for_device(DEVICE).solve_batch(short, compiled=compiled)
        assert np.array_equal(sol.status == FkStatus.BAR_RANGE, np.arange(len(d)) % 3 == 0)


def test_compiled_batch_solver_equals_numpy_bit_for_bit():
    """The batch path: compiled (threads, GIL released) against the numpy reference, on a log
    of motion with broken samples, jumps, impossible lengths and an iteration cap: the same
    flags, statuses and iterations, and the same poses, residuals, conditions and Jacobian
    inverses to the last bit."""
    assert COMPILED, NOT_IN_USE
    t = np.arange(12000) * 1e-3
    p = np.column_stack([0.1 * np.sin(t), 0.05 * np.cos(2 * t), 0.3 + 0.01 * np.sin(t),
                         0.05 * np.sin(t), 0.02 * np.cos(t), 0.6 * np.sin(0.5 * t)])
    d = inverse_kinematics(GEOMETRY, p) + np.random.default_rng(12).normal(0, 50e-9, (len(t), 6))
    d[5000, 2] = np.nan
    d[9000] = [0.25, 0.376, 0.25, 0.376, 0.25, 0.376]
    d[9100, 0] = 0.5
    d[10000:10500] = unrelated_poses(500, 4, inside=False)[1]
    for fk in (ForwardKinematics.for_device(DEVICE), ForwardKinematics.for_device(DEVICE, max_iter=3)):
        for run in (lambda c: fk.solve_batch(d, with_inverse=True, compiled=c),
                    lambda c: fk.solve_series(d, with_inverse=True, compiled=c),
                    lambda c: fk.solve_batch(d[::7], p[::7] + 1e-4, with_inverse=True, compiled=c)):
            numpy_path, compiled = run(False), run(True)
            assert_identical(numpy_path, compiled, SOLUTION_FIELDS + ('jacobian_inverse',))
            assert 0 < compiled.converged.sum() < len(compiled.converged)


def test_propagated_covariance_compiled_equals_numpy():
    """J^-1 S J^-T with the plates' scale, per-sample S and shared S, both paths."""
    assert COMPILED, NOT_IN_USE
    rng = np.random.default_rng(13)
    truth, d = unrelated_poses(3000, 5)
    jinv = FK.solve_batch(d, with_inverse=True).jacobian_inverse
    a = rng.normal(0, 1e-7, (3000, 6, 6))
    per_sample = a @ np.swapaxes(a, 1, 2)
    scale = 1 + rng.normal(0, 1e-5, 3000)
    for s in (per_sample, np.diag(np.full(6, 0.3e-6 ** 2))):
        ref = propagate_covariance(jinv, s, scale, compiled=False)
        fast = propagate_covariance(jinv, s, scale, compiled=True)
        np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    expected = np.linalg.inv(jacobian(GEOMETRY, truth[0])) @ per_sample[0] @ \
        np.linalg.inv(jacobian(GEOMETRY, truth[0])).T
    np.testing.assert_allclose(propagate_covariance(jinv[:1], per_sample[:1]), expected[None],
                               rtol=1e-9)


def test_impossible_lengths_are_flagged_not_returned():
    d = np.array([0.25, 0.376, 0.25, 0.376, 0.25, 0.0001])
    FK.reset()
    assert not FK.solve(d).converged
    batch = FK.solve_batch(np.vstack([d, inverse_kinematics(GEOMETRY, [0, 0, 0.3, 0, 0, 0]),
                                      np.full(6, np.nan)]))
    assert batch.converged.tolist() == [False, True, False]


def test_pose_covariance_matches_monte_carlo():
    p = np.array([0.05, -0.03, 0.31, 0.05, -0.04, 0.3])
    d = inverse_kinematics(GEOMETRY, p)
    sigma = 0.4e-6
    cov = pose_covariance(jacobian(GEOMETRY, p), np.full(6, sigma ** 2))
    rng = np.random.default_rng(6)
    sol = FK.solve_batch(d + rng.normal(0, sigma, (4000, 6)))
    empirical = np.cov(sol.poses.T)
    assert np.allclose(np.sqrt(np.diag(empirical)), np.sqrt(np.diag(cov)), rtol=0.08)
    assert np.allclose(cov, cov.T)


def test_series_solve_equals_batch_solve_on_a_motion():
    t = np.arange(20000) * 1e-3
    p = np.column_stack([0.1 * np.sin(t), 0.05 * np.cos(2 * t), 0.3 + 0 * t, 0.05 * np.sin(t), 0 * t, 0.6 * np.sin(0.5 * t)])
    d = inverse_kinematics(GEOMETRY, p)
    d[5000] = np.nan          # a broken sample in the middle must not spoil its neighbours
    series = FK.solve_series(d)
    batch = FK.solve_batch(d)
    assert series.converged.sum() == len(t) - 1 and not series.converged[5000]
    ok = series.converged
    assert np.max(np.abs(series.poses[ok] - p[ok])) < 1e-12
    assert np.max(np.abs(series.poses[ok] - batch.poses[ok])) < 1e-12
    assert series.iterations[ok].mean() < batch.iterations[ok].mean()


def test_rotation_angle_at_every_angle():
    """The angle of a rotation, small or beyond 90°, about any axis, against scipy's rotation
    vector."""
    rng = np.random.default_rng(4)
    angles = np.concatenate([[0.0, 1e-9, 1e-6], rng.uniform(0, np.pi - 1e-6, 200)])
    axes = rng.normal(size=(angles.size, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    from scipy.spatial.transform import Rotation
    mats = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    np.testing.assert_allclose(rotation_angle(mats), angles, rtol=1e-9, atol=1e-12)
    assert rotation_angle(np.eye(3)) == 0.0
