"""Logs from outside our code: a log written by hand with the plain ``mcap`` packages, following
only ``msg_docs/topics.md`` (the calibration example is taken from the document itself), and the
twin with ``--effects none``, whose counts must be the documented count model exactly."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap_ros2.writer import Writer as Ros2Writer
from scipy.spatial.transform import Rotation

from mmd_ros.cli.main import main
from mmd_ros.logs.layout import read_run

ROOT = Path(__file__).resolve().parents[1]
TOPICS_MD = ROOT / 'msg_docs' / 'topics.md'
PROTOTYPE = ROOT / 'config' / 'mmd_prototype.yaml'
SEPARATOR = '=' * 80

# The .msg definitions, each followed by its dependencies as topics.md (## Logs) says.
STRING_MSG = 'string data\n'
JOINT_STATE_MSG = (
    'std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n'
    f'float64[] effort\n{SEPARATOR}\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n'
    f'string frame_id\n{SEPARATOR}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n')

#: Known poses x, y, z [m], roll, pitch, yaw [rad], held for a few samples each.
POSES = np.array([
    [0.0, 0.0, 0.300, 0.0, 0.0, 0.0],
    [0.040, -0.025, 0.285, 0.010, -0.020, 0.030],
    [-0.060, 0.030, 0.310, -0.030, 0.015, -0.050],
    [0.015, 0.070, 0.270, 0.040, 0.030, 0.120],
])
SAMPLES_PER_POSE = 5


def documented_calibration_example() -> dict:
    """The calibration YAML block of topics.md, as a user would copy it."""
    text = TOPICS_MD.read_text(encoding='utf-8')
    section = text.split('**The calibration YAML**', 1)[1]
    block = re.search(r'```yaml\n(.*?)```', section, re.S)
    assert block, 'topics.md lost its calibration example'
    return yaml.safe_load(block.group(1))


def bar_lengths(device: dict, pose: np.ndarray) -> np.ndarray:
    """|R a_i + t - b_i| with R = Rz(yaw) Ry(pitch) Rx(roll) (frames.md), from the joint set
    the description's ``joints.use`` names [m]."""
    use = device['joints']['use']
    upper = np.array(device['joints'][f'upper_{use}_mm']) * 1e-3
    lower = np.array(device['joints'][f'lower_{use}_mm']) * 1e-3
    rot = Rotation.from_euler('ZYX', [pose[5], pose[4], pose[3]]).as_matrix()
    return np.linalg.norm(upper @ rot.T + pose[:3] - lower, axis=1)


def test_a_log_written_by_hand_from_topics_md(tmp_path):
    device_text = PROTOTYPE.read_text(encoding='utf-8')
    device = yaml.safe_load(device_text)
    channels = [c['name'] for c in device['terminal']['channels']]
    step_m = device['bars']['encoder_resolution_nm'] * 1e-9
    d0_m = device['bars']['range_mm'][0] * 1e-3

    calibration = documented_calibration_example()
    template = calibration['bars']['bar1']
    distances_m = np.array(template['distances_mm']) * 1e-3
    # The example's counts are (d - 250 mm) / 50 nm, as the document says.
    np.testing.assert_allclose(template['counts'], np.round((distances_m - d0_m) / step_m), atol=0.5)

    # "Counts increase by one for every 50 nm": each bar from its own power-on offset. bar6
    # counts down as it lengthens, which the document says works when its calibration does too.
    offsets = {'bar1': 0, 'bar2': 12_345, 'bar3': -400_000, 'bar4': 3_000_000, 'bar5': 77,
               'bar6': 9_000_000, 'ref1': -1_234_567}
    sign = {name: (-1 if name == 'bar6' else 1) for name in offsets}

    def counts_of(name: str, length_m: np.ndarray) -> np.ndarray:
        return np.round(offsets[name] + sign[name] * (length_m - d0_m) / step_m)

    calibration['bars'] = {name: {'pairs': template['pairs'],
                                  'counts': counts_of(name, distances_m).tolist(),
                                  'distances_mm': template['distances_mm']}
                           for name in offsets}
    # the reference bar rests on its pair (dr4 on the prototype): its count stays there
    ref_pair = next(c['pair'] for c in device['terminal']['channels'] if c['role'] == 'reference')
    ref_count = calibration['bars']['ref1']['counts'][template['pairs'].index(ref_pair)]

    t0_ns = 1_700_000_000_000_000_000
    rows, stamps, truth = [], [], []
    for k, pose in enumerate(POSES):
        lengths = bar_lengths(device, pose)
        row = [float(counts_of(f'bar{i + 1}', lengths[i])) for i in range(6)] + [ref_count, 0.0]
        for j in range(SAMPLES_PER_POSE):
            stamps.append(t0_ns + (k * SAMPLES_PER_POSE + j) * 1_000_000)
            rows.append(row)
            truth.append(pose)

    log = tmp_path / 'by_hand.mcap'
    with open(log, 'wb') as handle:
        writer = Ros2Writer(handle)
        string = writer.register_msgdef('std_msgs/msg/String', STRING_MSG)
        joint_state = writer.register_msgdef('sensor_msgs/msg/JointState', JOINT_STATE_MSG)
        writer.write_message('/mmd/device_description', string, {'data': device_text}, t0_ns, t0_ns)
        writer.write_message('/mmd/calibration', string,
                             {'data': yaml.safe_dump(calibration, sort_keys=False)}, t0_ns, t0_ns)
        for stamp, row in zip(stamps, rows):
            msg = {'header': {'stamp': {'sec': stamp // 1_000_000_000,
                                        'nanosec': stamp % 1_000_000_000}, 'frame_id': ''},
                   'name': channels, 'position': row, 'velocity': [], 'effort': []}
            writer.write_message('/mmd/raw_counts', joint_state, msg, stamp, stamp)
        writer.finish()

    out_csv = tmp_path / 'poses.csv'
    assert main(['process', str(log), '--out', str(tmp_path / 'out.mcap'), '--csv', str(out_csv),
                 '--quiet']) == 0
    with open(out_csv, encoding='utf-8') as handle:
        table = list(csv.DictReader(handle))
    assert [int(r['stamp_ns']) for r in table] == stamps
    assert all(r['valid'] == '1' for r in table)
    got = np.array([[float(r[k]) for k in ('x_m', 'y_m', 'z_m', 'roll_rad', 'pitch_rad', 'yaw_rad')]
                    for r in table])
    err = got - np.array(truth)
    # one count is 50 nm, so each bar is within 25 nm: the pose within a few tenths of a µm
    assert np.abs(err[:, :3]).max() < 0.1e-6
    assert np.abs(err[:, 3:]).max() < np.radians(0.2 / 3600)
    lengths = np.array([[float(r[f'bar{i}_m']) for i in range(1, 7)] for r in table])
    expected = np.array([bar_lengths(device, p) for p in truth])
    assert np.abs(lengths - expected).max() <= 25e-9 + 1e-12


def test_effects_none_counts_are_the_documented_count_model(tmp_path):
    """``--effects none``: every count is the true length quantised, (d - 250 mm) / 50 nm, from
    the twin's own kinematics; the calibration is the topics.md example; the room stays at 20 °C."""
    pose = [0.01, -0.02, 0.29, 0.01, -0.02, 0.03]
    log = tmp_path / 'none.mcap'
    assert main(['simulate', '--scenario', 'hold', '--param', 'duration_s=0.2',
                 '--param', 'pose=' + ','.join(map(str, pose)), '--effects', 'none',
                 '--out', str(log), '--quiet', '--json']) == 0
    run = read_run(log)
    device = yaml.safe_load(PROTOTYPE.read_text(encoding='utf-8'))
    expected = np.round((bar_lengths(device, np.array(pose)) - 0.250) / 50e-9)
    np.testing.assert_array_equal(run.counts[:, :6], np.broadcast_to(expected, (run.counts.shape[0], 6)))
    example = documented_calibration_example()
    for name in ('bar1', 'ref1'):
        assert list(run.calibration.bars[name].counts) == example['bars'][name]['counts']
    assert np.all(run.counts[:, 6] == example['bars']['ref1']['counts'][3])   # ref1 on dr4
    assert run.calibration.ambient_c == pytest.approx(20.0)
    assert run.metadata['simulation']['ambient'] == 'constant:20'
    effects = run.metadata['effects']
    assert effects['read_noise_m'] == 0.0 and effects['count_offsets'] is False
    assert run.metadata['ambient'] == {'initial_c': 20.0, 'ramps': []}
