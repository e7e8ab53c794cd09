"""A one-axis run's unseen pose components read as the machine's motion along its axis
(analysis/axis_motion.py): the machine's error motions, of any smooth shape, are projected out;
what moves with speed is kept, and determines the channel delays from one laser run."""

from __future__ import annotations

import numpy as np
import pytest

from mmd_ros.analysis.axis_motion import MACHINE_LIMIT, axis_motion
from mmd_ros.analysis.data import run_pipeline
from mmd_ros.analysis.identify import AnalysisOptions, analyze
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.model import Model
from mmd_ros.twin import AmbientProfile, Effects, TwinDevice, make_scenario
from mmd_ros.twin.recording import run_log

DEVICE = load_device(find_config('mmd_prototype.yaml'))
RES = DEVICE.encoder_resolution_m
MEAS = list(DEVICE.measuring_channels)
ROOM = AmbientProfile.constant(21.0)
ARCSEC = np.radians(1.0 / 3600.0)


def iso_moves(n_cycles: int = 3, rate: float = 200.0):
    """An ISO-like run along one axis: minimum-jerk moves of 20 mm between 11 targets, both
    ways, 0.5 s dwells. Returns times [s], position [m] (about 0), direction (+1, -1)."""
    targets = np.linspace(-0.1, 0.1, 11)
    path = []
    for _ in range(n_cycles):
        for seq in (targets, targets[::-1]):
            for a, b in zip(seq[:-1], seq[1:]):
                tau = np.linspace(0.0, 1.0, int(1.5 * rate), endpoint=False)
                path.append(a + (b - a) * (10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5))
                path.append(np.full(int(0.5 * rate), b))
    s = np.concatenate(path)
    t = np.arange(s.size) / rate
    return t, s, travel_direction(s)


def travel_direction(s):
    """+1 / -1 for the direction of the last step of s (backward differences), held where s
    stands still."""
    step = np.diff(s, prepend=s[0])
    direction = np.sign(step)
    for i in range(1, s.size):
        if abs(step[i]) < 1e-9:
            direction[i] = direction[i - 1]
    return direction


def machine_of_another_shape(s, direction, t):
    """Error motions of the other five components along an axis s (about 0, +-0.1 m): a bow,
    waviness of 7 and 13 mm, a reversal that changes along the travel, a cubic, thermal drift
    over the run. (N, 6) [m, rad], the axis' own component zero."""
    u = (t - t[0]) / (t[-1] - t[0])
    dp = np.zeros((s.size, 6))
    dp[:, 1] = 1.5e-6 * (1 - (s / 0.1) ** 2) + 0.2e-6 * np.sin(2 * np.pi * s / 0.007) \
        + direction * (0.4e-6 + 0.3e-6 * s / 0.1)
    dp[:, 2] = 1e-6 * (s / 0.1) ** 3 + 0.8e-6 * u
    dp[:, 3] = ARCSEC * (2 * s / 0.1 + 0.5 * np.sin(2 * np.pi * s / 0.013) + 0.5 * direction)
    dp[:, 4] = ARCSEC * (-3 * (s / 0.1) ** 2 + u)
    dp[:, 5] = ARCSEC * (1.5 * s / 0.1 + 0.3 * direction * (1 + s / 0.1))
    return dp


def test_the_machine_s_motion_is_projected_out_and_what_moves_with_speed_is_kept():
    """On a synthetic ISO run: the machine's smooth error motions (a bow, a reversal along the
    travel, drift) leave almost nothing after the projection; a speed-proportional signal (a
    channel delay's) keeps much of its size, since it is zero at every dwell and largest in
    the middle of each move, which no smooth function of position and direction follows."""
    t, s, direction = iso_moves()
    poses = np.zeros((t.size, 6))
    smooth = machine_of_another_shape(s, direction, t)
    smooth[:, 1] -= 0.2e-6 * np.sin(2 * np.pi * s / 0.007)        # waviness is not smooth at 5 mm knots
    smooth[:, 3] -= ARCSEC * 0.5 * np.sin(2 * np.pi * s / 0.013)
    speed = np.gradient(s, t)
    delay = np.outer(speed * 30e-6, [0, 1, 1, 5e-6, 5e-6, 5e-6])    # 30 µs of the axis' speed
    floor = np.array([4e-8] * 3 + [1e-7] * 3)
    usable = np.ones(t.size, dtype=bool)
    for signal, kept in ((smooth, False), (delay, True)):
        poses[:, 0] = s
        poses[:, 1:] = signal[:, 1:]
        motion = axis_motion(poses, s, 0, t, usable, floor)
        assert motion is not None and motion.components == [1, 2, 3, 4, 5]
        idx = np.arange(t.size)
        q = np.linalg.qr(motion.basis(idx))[0]
        left = motion.values - q @ (q.T @ motion.values)
        share = np.sqrt(np.mean(left ** 2, axis=0) / np.mean(motion.values ** 2, axis=0))
        if kept:
            assert np.all(share > 0.3), share
        else:
            # what stays is the reversal's first samples, before the axis moved 1e-5 m/s
            # (the direction is read from the reference; one sample per reversal here)
            assert np.all(share < 0.04), share


def test_a_run_that_is_not_one_axis_gives_no_such_rows():
    """Random 6-DOF motion with a laser along x: the other components move on their own,
    millimetres that no function of x explains (beyond MACHINE_LIMIT times their floor); and a
    coordinate that hardly moves is no axis."""
    twin = TwinDevice(DEVICE, Effects.ideal(), seed=1)
    calibration = twin.calibrate(0.0, ROOM, approaches=2)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=20', 'seed=3']), ROOM, start_s=600.0,
                        reference='pose6', sample_rate_hz=200.0)
    proc = run_pipeline(DEVICE, calibration, Model(), run.times_s, run.counts.astype(np.float64))
    floor = np.array([4e-8] * 3 + [1e-7] * 3)
    assert MACHINE_LIMIT * floor[1] < np.ptp(proc.poses[:, 1])
    assert axis_motion(proc.poses, run.true_poses[:, 0], 0, run.times_s, proc.valid, floor) is None
    still = np.full(run.times_s.size, 0.01) + 1e-4 * np.sin(run.times_s)
    assert axis_motion(proc.poses, still, 0, run.times_s, proc.valid, floor) is None


def test_one_laser_run_gives_the_channel_delays_under_machine_motion_of_another_shape():
    """A twin whose channels latch up to 50 µs late, one x-axis ISO run with a laser along x.
    The laser sees one combination of the six delays; the MMD's other five components see the
    rest, and the machine's error motions there (of a shape the twin does not make: waviness,
    a reversal that changes along the travel, drift; added to the bars as J dp) are projected
    out. Measured: every delay within 0.4 µs of the truth without the machine's motion, within
    0.9 µs with it."""
    twin = TwinDevice(DEVICE, Effects.ideal().with_assignments(('sampling_skew_s=5e-5',)), seed=1)
    calibration = twin.calibrate(0.0, ROOM, approaches=2)
    run = twin.simulate(make_scenario('iso_linear', ['axis=x', 'n_cycles=5']), ROOM, start_s=600.0,
                        reference='laser_x', sample_rate_hz=200.0)
    s = run.true_poses[:, 0] - np.median(run.true_poses[:, 0])
    direction = travel_direction(s)
    counts = run.counts.astype(np.float64)
    dp = machine_of_another_shape(s, direction, run.times_s)
    counts[:, MEAS] += np.rint(np.einsum('nij,nj->ni', jacobian(DEVICE.geometry, run.true_poses), dp) / RES)
    true = twin.physics.skew_s[MEAS]
    for axis in (True, False):
        result = analyze(run_log(twin, calibration, run, 600.0, counts),
                         options=AnalysisOptions(effects=['sampling_skew'], axis_motion=axis))
        found = {f.effect: f for f in result.found}
        if axis:
            assert 'sampling_skew' in found, result.conclusion
            est = np.asarray(found['sampling_skew'].value)
            print('delays [µs]', np.round(est * 1e6, 1), 'true', np.round(true * 1e6, 1))
            assert np.all(np.abs(est - true) < 2e-6)
        else:
            # from the laser's component alone the delays are not determined: not written
            assert 'sampling_skew' not in found and result.unchecked, result.conclusion


def test_a_rotary_axis_that_passes_180_degrees_is_one_travel():
    """A rotary calibrator reads angles in (-180, 180]: a C-axis run from 170 to 190 degrees
    jumps from +180 to -180 in the reference, but the axis travels 20 degrees on."""
    t, s, _ = iso_moves(n_cycles=1)
    angle = np.pi + np.radians(10.0) * s / 0.1
    wrapped = (angle + np.pi) % (2 * np.pi) - np.pi
    poses = np.zeros((t.size, 6))
    poses[:, 5] = wrapped
    poses[:, 0] = 1e-6 * np.sin(angle)          # a radial error motion: a function of the angle
    motion = axis_motion(poses, wrapped, 5, t, np.ones(t.size, dtype=bool), np.array([4e-8] * 3 + [1e-7] * 3))
    assert motion is not None and 0 in motion.components
    assert np.ptp(motion.coordinate) == pytest.approx(np.radians(20.0), rel=1e-6)
