"""End to end: the twin (only effects the model knows) → log → ``mmd process`` recovers the true
pose to the limit set by 50 nm encoder quantisation."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mmd_ros.twin.recording import SimulationSpec, ambient_profile, simulate_to_log
from mmd_ros.cli.main import main
from mmd_ros.core.accuracy import pose_error
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.rotation import quaternion_to_angles
from mmd_ros.logs.reader import LogReader
from mmd_ros.twin import Effects, TwinDevice, make_scenario

SHORT_RUN = ('n_cycles=1', 'dwell_s=0.2', 'lead_s=0.2')


def quantisation_floor(device, poses, read_noise_m, lengths=None):
    """Pose error that encoder quantisation alone produces.

    Each measuring bar: uniform rounding (50 nm / sqrt(12)) and read noise, independent from
    sample to sample. The reference bar(s), when the temperature has moved since calibration:
    a static bar with little noise does not dither across counts, so its rounding error is a
    bias of up to half a count that Eq. (12)/(13) passes to every bar at once (common mode).
    ``lengths`` (N, 6) gives the Eq. (12) interpolation weights; None means no thermal change.
    """
    sigma = np.hypot(device.encoder_resolution_m / np.sqrt(12), read_noise_m)
    cov_d = np.tile(np.eye(6) * sigma ** 2, (len(poses), 1, 1))
    if lengths is not None:
        half_count = device.encoder_resolution_m / 2
        refs = device.reference_channels
        if len(refs) == 1:
            w = np.ones((len(poses), 6, 1))
        else:
            lo, hi = (device.pair(r.pair).distance_m for r in (refs[0], refs[-1]))
            f = (lengths - lo) / (hi - lo)
            w = np.stack([1 - f, f], axis=-1)
        cov_d = cov_d + half_count ** 2 * (w @ np.swapaxes(w, 1, 2))
    jinv = np.linalg.inv(jacobian(device.geometry, poses))
    cov = jinv @ cov_d @ np.swapaxes(jinv, 1, 2)
    return np.sqrt(np.mean(np.diagonal(cov, axis1=1, axis2=2), axis=0))


def true_run(spec):
    device = load_device(find_config(spec.device))
    twin = TwinDevice(device, Effects.preset(spec.effects).with_assignments(spec.effect_params), seed=spec.seed)
    room = ambient_profile(spec.ambient)
    twin.calibrate(spec.calibrate_at_s, room)
    return device, twin.simulate(make_scenario(spec.scenario, spec.scenario_params), room,
                                 start_s=spec.start_s, reference=spec.reference)


def processed_poses(path):
    stamps, values, frame = LogReader(path).pose_values('/mmd/pose')
    assert frame == 'mmd_lower'
    return np.column_stack([values[:, :3], quaternion_to_angles(values[:, 3:7])])


#: The room holds at 24.2 °C while the bars are calibrated, then cools as in section 4.1.
HOLD_THEN_COOL = """
initial_c: 24.2
ramps:
- {duration_s: 1800.0, end_c: 24.2, time_constant_s: 1.0}
- {duration_s: 28800.0, end_c: 18.4, time_constant_s: 9000.0}
"""
COOLED_START_S = 1800.0 + 3 * 3600.0  # 3 h into the cooling: the bars are ~3.5 °C colder


def _simulate_and_process(tmp_path, device_file, ambient, start_s):
    if ambient == 'hold_then_cool':
        ambient = str(tmp_path / 'room.yaml')
        Path(ambient).write_text(HOLD_THEN_COOL)
    spec = SimulationSpec(scenario='iso_linear', scenario_params=SHORT_RUN, effects='ideal',
                          seed=3, device=device_file, ambient=ambient, start_s=start_s,
                          reference='pose6')
    log = tmp_path / 'run.mcap'
    simulate_to_log(spec, log, progress=False)
    out = tmp_path / 'out.mcap'
    assert main(['process', str(log), '--out', str(out), '--quiet']) == 0
    device, run = true_run(spec)
    return device, run, out


@pytest.mark.parametrize('device_file,ambient,start_s', [
    ('mmd_prototype.yaml', 'constant:20', 600.0),
    # calibrated at 24.2 °C, measured 3.5 °C colder with two reference bars: Eq. (12) is exact
    ('mmd_two_reference_bars.yaml', 'hold_then_cool', COOLED_START_S),
])
def test_process_recovers_the_true_pose_to_the_quantisation_limit(tmp_path, device_file, ambient, start_s):
    device, run, out = _simulate_and_process(tmp_path, device_file, ambient, start_s)
    error = pose_error(processed_poses(out), run.true_poses)
    moved = ambient != 'constant:20'
    floor = quantisation_floor(device, run.true_poses[::500], Effects.ideal().read_noise_m,
                               run.true_lengths[::500] if moved else None)
    rms = np.sqrt(np.mean(error ** 2, axis=0))
    # tens of nanometres and hundredths of an arc-second: within 1.5x of the floor
    assert np.all(rms <= 1.5 * floor), (rms, floor)
    assert np.max(np.abs(error[:, :3])) < 0.2e-6


def test_one_reference_bar_leaves_exactly_the_residual_of_eq13(tmp_path):
    """Eq. (13) leaves -a_s (d - d_r^4) dT on each bar (section 3.3: 0.037 um/°C at 376 mm)."""
    device, run, out = _simulate_and_process(tmp_path, 'mmd_prototype.yaml', 'hold_then_cool',
                                             COOLED_START_S)
    lengths = LogReader(out).joint_states('/mmd/bar_lengths').values
    dt = run.bar_temp_c[:, :6] - 24.2
    predicted = -device.scale_cte_per_c * (run.true_lengths - device.pair('dr4').distance_m) * dt
    residual = lengths - run.true_lengths
    assert np.sqrt(np.mean(predicted ** 2)) > 30e-9  # the effect is there to be seen
    # what is left: the bar's own quantisation (15 nm rms) and the reference bar's rounding
    # bias (at most half a count, 25 nm, the same on every bar)
    left = residual - predicted
    common = np.mean(left)
    assert abs(common) <= 25e-9
    assert np.all(np.sqrt(np.mean((left - common) ** 2, axis=0)) < 1.5 * 15e-9)
    assert np.all(np.sqrt(np.mean(residual ** 2, axis=0)) > np.sqrt(np.mean((residual - predicted) ** 2, axis=0)))


def test_unknown_effects_show_up_as_error(tmp_path):
    """The realistic twin (hysteresis, lag mismatch, nonlinearity...) is NOT at the floor:
    the comparison above is able to fail."""
    spec = SimulationSpec(scenario_params=SHORT_RUN, effects='realistic', seed=3, reference='pose6')
    log = tmp_path / 'run.mcap'
    simulate_to_log(spec, log, progress=False)
    out = tmp_path / 'out.mcap'
    assert main(['process', str(log), '--out', str(out), '--quiet']) == 0
    device, run = true_run(spec)
    rms = np.sqrt(np.mean(pose_error(processed_poses(out), run.true_poses) ** 2, axis=0))
    floor = quantisation_floor(device, run.true_poses[::500], Effects.realistic().read_noise_m,
                               run.true_lengths[::500])
    assert np.any(rms > 3 * floor)


def test_console_scripts_write_json_and_csv(tmp_path):
    env = {**os.environ, 'MPLBACKEND': 'Agg'}
    log = tmp_path / 'run.mcap'
    sim = subprocess.run([sys.executable, '-m', 'mmd_ros.cli.main', 'simulate', '--out', str(log), '--json',
                          '--effects', 'ideal', '--ambient', 'constant:20', *sum([['--param', p] for p in SHORT_RUN], [])],
                         capture_output=True, text=True, timeout=300, env=env)
    assert sim.returncode == 0, sim.stderr
    summary = json.loads(sim.stdout)
    assert summary['samples'] > 10000 and summary['reference'] == 'laser_x'
    csv = tmp_path / 'poses.csv'
    proc = subprocess.run([sys.executable, '-m', 'mmd_ros.cli.main', 'process', str(log), '--json', '--csv', str(csv)],
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result['samples'] == summary['samples'] == result['valid']
    x = [s for s in result['pose_error'] if s['name'] == 'x'][0]
    assert x['n'] == result['samples'] and x['rms'] < 0.1   # µm
    assert [s['name'] for s in result['pose_error']] == ['x']  # a laser along x gives x only
    lines = csv.read_text().splitlines()
    assert len(lines) == summary['samples'] + 1 and lines[0].startswith('stamp_ns,x_m')


def test_bad_input_gives_a_one_line_error(tmp_path, capsys):
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(b'not a log')
    assert main(['process', str(bad)]) == 2
    assert 'not an MCAP file' in capsys.readouterr().err
    assert main(['process', str(tmp_path / 'missing.mcap')]) == 2
