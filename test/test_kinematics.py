"""Kinematics: Eq. (3) convention, IK Eq. (6), Jacobian, Newton FK and pose covariance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mmd_ros.core.compiled import AVAILABLE as COMPILED, NOT_IN_USE
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.kinematics import ForwardKinematics, inverse_kinematics, jacobian, pose_covariance
from mmd_ros.core.rotation import (
    angles_to_quaternion, matrix_to_angles, quaternion_to_angles, rotation_matrix,
)

DEVICE = load_device(find_config('mmd_prototype.yaml'))
GEOMETRY = DEVICE.geometry
FK = ForwardKinematics(GEOMETRY)
LOW, HIGH = DEVICE.bar_range_m


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
    sol = FK.solve_batch(d[inside], with_condition=True)
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
    after sample: a noisy motion, a broken sample, a jump that needs damped steps, impossible
    lengths, and an iteration cap that leaves samples unconverged (the warm start restarts)."""
    assert COMPILED, NOT_IN_USE
    rng = np.random.default_rng(11)
    t = np.arange(3000) * 1e-3
    p = np.column_stack([0.1 * np.sin(t), 0.05 * np.cos(2 * t), 0.3 + 0.01 * t,
                         0.05 * np.sin(t), 0.02 * t, 0.6 * np.sin(0.5 * t)])
    d = inverse_kinematics(GEOMETRY, p) + rng.normal(0, 50e-9, (len(t), 6))
    d[700, 3] = np.nan
    d[1500:] = inverse_kinematics(GEOMETRY, p[1500:] + [0.08, -0.06, 0.02, 0.2, -0.2, 0.5])
    d[2200] = [0.25, 0.376, 0.25, 0.376, 0.25, 0.0001]
    for max_iter in (20, 3):
        runs = []
        for compiled in (False, True):
            fk = ForwardKinematics(GEOMETRY, max_iter=max_iter)
            # transfer by transfer, as the nodes call it: the warm start carries across calls
            parts = [fk.solve_stream(d[k:k + 8], compiled=compiled) for k in range(0, len(t), 8)]
            runs.append({f: np.concatenate([getattr(q, f) for q in parts])
                         for f in ('poses', 'converged', 'iterations', 'residual_m', 'jacobians')})
        py, c = runs
        assert np.array_equal(py['converged'], c['converged'])
        assert np.array_equal(py['iterations'], c['iterations'])
        for f in ('poses', 'residual_m', 'jacobians'):
            assert np.array_equal(np.isnan(py[f]), np.isnan(c[f])), f
            ok = np.isfinite(py[f])
            assert np.allclose(py[f][ok], c[f][ok], rtol=1e-9, atol=1e-12), f
        assert not c['converged'][700] and np.isnan(c['poses'][700]).all()
        assert not c['converged'][2200]
        if max_iter == 20:
            assert c['converged'].sum() == len(t) - 2
            assert c['iterations'][1500] > 3  # the jump took damped steps from a stale start
        else:
            assert 0 < c['converged'].sum() < len(t) - 2


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
