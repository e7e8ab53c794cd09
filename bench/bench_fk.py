"""Forward-kinematics benchmarks: per-sample (warm start, 1 kHz trajectory), per transfer as the
nodes solve it (8 samples, compiled and Python), the same with the pose covariance of the
uncertainty budget (what ``fk_node`` and ``pose_node`` add per transfer: the budget's
observation of the samples, Sigma_d and J^-1 Sigma_d J^-T) and batch throughput.

Prints the figures and a final JSON line. Targets (issue 2): per-sample median <= 50 us,
batch >= 300,000 samples/s at N = 100,000. Never fails on timing.
"""

from __future__ import annotations

import json
import statistics
import time

import numpy as np

from mmd_ros.core.compiled import AVAILABLE as COMPILED
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.kinematics import ForwardKinematics, inverse_kinematics


def trajectory(n: int) -> np.ndarray:
    """A smooth 6-DOF motion sampled at 1 kHz."""
    t = np.arange(n) * 1e-3
    return np.column_stack([0.08 * np.sin(0.5 * t), 0.06 * np.cos(0.3 * t), 0.30 + 0.02 * np.sin(0.2 * t),
                            0.05 * np.sin(0.4 * t), 0.04 * np.cos(0.25 * t), 0.5 * np.sin(0.1 * t)])


def main() -> None:
    geometry = load_device(find_config('mmd_prototype.yaml')).geometry
    fk = ForwardKinematics(geometry)

    lengths = inverse_kinematics(geometry, trajectory(20000))
    fk.reset()
    times = []
    iterations = []
    for d in lengths:
        t0 = time.perf_counter()
        sol = fk.solve(d)
        times.append(time.perf_counter() - t0)
        iterations.append(sol.iterations)
    per_sample = [statistics.median(times[k:k + 5000]) * 1e6 for k in range(0, len(times), 5000)]

    # the nodes' path: a transfer of 8 samples at a time through solve_stream, on noisy lengths
    noisy = lengths + np.random.default_rng(1).normal(0, 50e-9, lengths.shape)
    transfer = {}
    for compiled in ([False, True] if COMPILED else [False]):
        fk.reset()
        t_transfer = []
        for k in range(0, len(noisy), 8):
            t0 = time.perf_counter()
            fk.solve_stream(noisy[k:k + 8], compiled=compiled)
            t_transfer.append(time.perf_counter() - t0)
        transfer['compiled' if compiled else 'python'] = {
            'median_us': statistics.median(t_transfer) * 1e6,
            'p99_us': float(np.percentile(t_transfer, 99) * 1e6)}

    # the nodes' path with the covariance: a realistic twin's calibration (its budget has every
    # source: hysteresis, drift, interpolation...), 8 samples per transfer
    from mmd_ros.core.budget import LengthBudget
    from mmd_ros.core.model import Model
    from mmd_ros.core.streaming import Kinematics
    from mmd_ros.twin import AmbientProfile, Effects, TwinDevice
    device = load_device(find_config('mmd_prototype.yaml'))
    calibration = TwinDevice(device, Effects.realistic(), seed=1).calibrate(
        0.0, AmbientProfile.section_4_1())
    kin = Kinematics(device, LengthBudget(device, calibration, Model()))
    eps, dt, scale = np.full((8, 1), 0.05e-6), np.full(8, -0.1), np.ones(8)
    t_solve, t_cov = [], []
    for k in range(0, len(noisy), 8):
        t0 = time.perf_counter()
        out = kin.solve(noisy[k:k + 8], scale, eps, dt)
        t1 = time.perf_counter()
        out.covariance
        t_cov.append(time.perf_counter() - t1)
        t_solve.append(t1 - t0)
    with_cov = {'solve_and_observe_median_us': statistics.median(t_solve) * 1e6,
                'covariance_median_us': statistics.median(t_cov) * 1e6,
                'covariance_p99_us': float(np.percentile(t_cov, 99) * 1e6)}

    rng = np.random.default_rng(0)
    n = 100_000
    poses = np.column_stack([rng.uniform(-0.08, 0.08, (n, 2)), rng.uniform(0.27, 0.33, n),
                             rng.uniform(-0.2, 0.2, (n, 3))])
    batch_lengths = inverse_kinematics(geometry, poses)
    rates = []
    for _ in range(5):
        t0 = time.perf_counter()
        sol = fk.solve_batch(batch_lengths)
        rates.append(n / (time.perf_counter() - t0))
    assert sol.converged.all()

    result = {
        'benchmark': 'fk',
        'per_sample_median_us': statistics.median(per_sample),
        'per_sample_median_us_by_block': per_sample,
        'per_sample_p99_us': float(np.percentile(times, 99) * 1e6),
        'per_sample_median_iterations': statistics.median(iterations),
        'transfer_of_8_us': transfer,
        'transfer_of_8_with_covariance_us': with_cov,
        'batch_samples_per_s_median': statistics.median(rates),
        'batch_samples_per_s_runs': rates,
        'batch_n': n,
        'batch_mean_iterations': float(sol.iterations.mean()),
    }
    print(f'per-sample FK (warm start, 1 kHz trajectory): median {result["per_sample_median_us"]:.1f} us '
          f'(blocks {", ".join(f"{v:.1f}" for v in per_sample)}), p99 {result["per_sample_p99_us"]:.1f} us, '
          f'median {result["per_sample_median_iterations"]} iterations   [target <= 50 us]')
    for path, v in transfer.items():
        print(f'a transfer of 8 noisy samples (solve_stream, {path}): median {v["median_us"]:.1f} us, '
              f'p99 {v["p99_us"]:.1f} us')
    print(f'a transfer with the pose covariance (fk_node, pose_node): solve and observe median '
          f'{with_cov["solve_and_observe_median_us"]:.1f} us, then the covariance median '
          f'{with_cov["covariance_median_us"]:.1f} us, p99 {with_cov["covariance_p99_us"]:.1f} us')
    if not COMPILED:
        print('(the compiled helpers were not built: no C compiler when mmd_ros was installed)')
    print(f'batch FK, N = {n}: median {result["batch_samples_per_s_median"]:,.0f} samples/s over 5 runs, '
          f'{result["batch_mean_iterations"]:.2f} iterations on average   [target >= 300,000]')
    print(json.dumps(result))


if __name__ == '__main__':
    main()
