"""MCAP logs: round trips through real files, read back by our reader and by independent ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from mmd_ros.core.rotation import quaternion_to_angles
from mmd_ros.logs.errors import LogFormatError
from mmd_ros.logs.reader import LogReader
from mmd_ros.logs.schemas import schema_text
from mmd_ros.logs.writer import LogWriter

NAMES = [f'bar{i}' for i in range(1, 7)] + ['ref1', 'ch8']
T0 = 1_700_000_000_123_456_789


def _write(path, n=5000, chunk_size=64 * 1024):
    rng = np.random.default_rng(0)
    stamps = T0 + np.arange(n, dtype=np.int64) * 1_000_000
    counts = rng.integers(-2**40, 2**40, (n, 8)).astype(np.float64)
    poses = np.column_stack([rng.normal(0, 0.05, (n, 3)), rng.uniform(-0.5, 0.5, (n, 3))])
    cov = np.tile(np.diag(np.arange(1.0, 7.0) * 1e-12), (n, 1, 1))
    with LogWriter(path, chunk_size=chunk_size) as log:
        log.write_string('/mmd/device_description', T0, 'name: test\n')
        log.write_rows([
            ('/mmd/raw_counts', 'sensor_msgs/msg/JointState', log.joint_state_rows(NAMES, stamps, counts)),
            ('/mmd/pose', 'geometry_msgs/msg/PoseStamped', log.pose_rows('mmd_lower', stamps, poses)),
            ('/mmd/pose_with_covariance', 'geometry_msgs/msg/PoseWithCovarianceStamped',
             log.pose_rows('mmd_lower', stamps, poses, cov)),
        ], stamps)
    return stamps, counts, poses, cov


def test_round_trip_with_our_reader(tmp_path):
    path = tmp_path / 'run.mcap'
    stamps, counts, poses, cov = _write(path)
    log = LogReader(path)
    assert not log.truncated and log.profile == 'ros2'
    js = log.joint_states('/mmd/raw_counts')
    assert js.names == NAMES
    assert np.array_equal(js.stamps_ns, stamps) and np.array_equal(js.values, counts)
    st, values, frame = log.pose_values('/mmd/pose_with_covariance')
    assert frame == 'mmd_lower' and np.array_equal(st, stamps)
    assert np.allclose(values[:, :3], poses[:, :3], rtol=0, atol=0)
    assert np.allclose(quaternion_to_angles(values[:, 3:7]), poses[:, 3:], atol=1e-12)
    assert np.array_equal(values[:, 7:].reshape(-1, 6, 6), cov)
    assert log.latest_string('/mmd/device_description') == 'name: test\n'
    with pytest.raises(LogFormatError, match='not sensor_msgs'):
        log.joint_states('/mmd/pose')


def test_mcap_library_indexed_reader_and_generic_decoder_agree(tmp_path):
    path = tmp_path / 'run.mcap'
    stamps, counts, poses, _ = _write(path)
    with open(path, 'rb') as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary.statistics.message_count == 1 + 3 * len(stamps)
        assert summary.statistics.channel_message_counts[2] == len(stamps)
        assert len(summary.chunk_indexes) > 3
        seen = 0
        for schema, channel, message, decoded in reader.iter_decoded_messages(topics=['/mmd/raw_counts', '/mmd/pose']):
            k = int((message.log_time - T0) // 1_000_000)
            if channel.topic == '/mmd/raw_counts':
                assert list(decoded.position) == counts[k].tolist()
                assert list(decoded.name) == NAMES and list(decoded.velocity) == []
            else:
                assert decoded.pose.position.x == poses[k, 0]
                assert decoded.header.frame_id == 'mmd_lower'
            seen += 1
        assert seen == 2 * len(stamps)
        qos = yaml.safe_load(summary.channels[2].metadata['offered_qos_profiles'])
        assert qos[0]['reliability'] == 'reliable' and qos[0]['history'] == 'keep_last'


def test_rosbags_reads_the_log(tmp_path):
    from rosbags.highlevel import AnyReader
    path = tmp_path / 'run.mcap'
    stamps, counts, _, _ = _write(path, n=500)
    with AnyReader([Path(path)]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types['/mmd/raw_counts'] == 'sensor_msgs/msg/JointState'
        conns = [c for c in reader.connections if c.topic == '/mmd/raw_counts']
        got = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]
        latched = [c for c in reader.connections if c.topic == '/mmd/device_description'][0]
        assert latched.ext.offered_qos_profiles[0].durability.name == 'TRANSIENT_LOCAL'
    assert np.array_equal(np.array([m.position for m in got]), counts)


def test_schema_text_is_written_as_rosbag2_does():
    text = schema_text('geometry_msgs/msg/PoseStamped')
    assert text.startswith('std_msgs/Header header\nPose pose\n')
    assert '=' * 80 + '\nMSG: std_msgs/Header\n' in text
    assert 'MSG: builtin_interfaces/Time' in text and 'MSG: geometry_msgs/Quaternion' in text
    assert '/msg/' not in text


def test_truncated_log_keeps_what_was_written(tmp_path):
    path = tmp_path / 'run.mcap'
    stamps, counts, _, _ = _write(path, n=20000)
    data = path.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[: len(data) * 2 // 3])
    log = LogReader(cut)
    assert log.truncated and 'ended uncleanly' in str(log.problem)
    js = log.joint_states('/mmd/raw_counts')
    assert 0.4 * len(stamps) < len(js.stamps_ns) < len(stamps)
    assert np.array_equal(js.values, counts[: len(js.stamps_ns)])


def test_corrupt_chunk_is_detected(tmp_path):
    path = tmp_path / 'run.mcap'
    _write(path, n=20000)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(bytes(data))
    log = LogReader(bad)
    assert log.problem.kind == 'damaged' and len(log.problem.skipped) == 1
    assert len(log.joint_states('/mmd/raw_counts').stamps_ns) > 19000  # the rest is read


def test_flushed_log_survives_a_crash(tmp_path):
    path = tmp_path / 'live.mcap'
    log = LogWriter(path, chunk_size=1 << 30)
    stamps = T0 + np.arange(100, dtype=np.int64)
    log.write_joint_states('/mmd/raw_counts', stamps, NAMES, np.ones((100, 8)))
    log.flush()  # as the recorder does every second; then the process dies without close()
    js = LogReader(path).joint_states('/mmd/raw_counts')
    assert len(js.stamps_ns) == 100


def test_not_an_mcap_file(tmp_path):
    from mmd_ros.logs.errors import LogError
    p = tmp_path / 'x.mcap'
    p.write_bytes(b'hello world, not mcap')
    with pytest.raises(LogError, match='not an MCAP file'):
        LogReader(p)


def test_logs_from_other_writers_read_through_the_generic_path(tmp_path):
    """A log written by the mcap library (one message at a time, irregular sizes) reads the same."""
    from mcap_ros2.writer import Writer as Ros2Writer
    path = tmp_path / 'other.mcap'
    with open(path, 'wb') as handle:
        writer = Ros2Writer(handle)
        from mmd_ros.logs.schemas import schema_text
        schema = writer.register_msgdef('sensor_msgs/msg/JointState', schema_text('sensor_msgs/msg/JointState'))
        for k in range(300):
            names = NAMES if k % 2 else NAMES  # same names, values of varying size below
            writer.write_message('/mmd/raw_counts', schema, {
                'header': {'stamp': {'sec': 1, 'nanosec': k}, 'frame_id': 'x' * (k % 3)},
                'name': names, 'position': [float(k)] * 8, 'velocity': [], 'effort': []},
                log_time=1_000_000_000 + k, publish_time=1_000_000_000 + k)
        writer.finish()
    js = LogReader(path).joint_states('/mmd/raw_counts')
    assert js.names == NAMES and js.values.shape == (300, 8)
    assert np.array_equal(js.values[:, 0], np.arange(300.0))
    assert np.array_equal(js.stamps_ns, 1_000_000_000 + np.arange(300))


def test_machine_joint_states_heard_before_the_terminal_are_kept(tmp_path):
    """A recorder may hear the machine's controller seconds before the terminal's first sample
    (discovery on a busy machine): in a log of one segment every joint state belongs to the
    run (a live test lost them to a 1 s window before)."""
    from mmd_ros.core.device import find_config, load_device
    from mmd_ros.logs.layout import TOPIC_DEVICE, TOPIC_MACHINE_JOINTS, TOPIC_RAW, read_run
    device = load_device(find_config('mmd_prototype.yaml'))
    t0 = 1_800_000_000 * 10**9
    raw = t0 + np.arange(100) * 10**6
    joints = t0 - 1_600_000_000 + np.arange(10) * 20_000_000      # 1.6 s before, 0.2 s long
    with LogWriter(tmp_path / 'run.mcap') as log:
        log.write_string(TOPIC_DEVICE, int(joints[0]), device.to_yaml())
        log.write_rows([(TOPIC_MACHINE_JOINTS, 'sensor_msgs/msg/JointState', log.joint_state_rows(
            ['X', 'Y', 'Z', 'A', 'C'], joints, np.column_stack([1e-3 * np.arange(10), np.zeros((10, 4))])))],
            joints)
        log.write_rows([(TOPIC_RAW, 'sensor_msgs/msg/JointState', log.joint_state_rows(
            device.channel_names, raw, np.zeros((100, 8))))], raw)
    js = read_run(tmp_path / 'run.mcap').machine_joints
    assert js is not None and js.names == ['X', 'Y', 'Z', 'A', 'C']
    np.testing.assert_array_equal(js.stamps_ns, joints)
    assert js.positions[:, 0] == pytest.approx(1e-3 * np.arange(10))


@pytest.fixture(scope='module')
def motion_log(tmp_path_factory):
    """3 s of the twin's random 6-DOF motion with its reference pose at the MMD's stamps."""
    from mmd_ros.logs.layout import read_run
    from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
    path = tmp_path_factory.mktemp('reference_stamps') / 'motion.mcap'
    simulate_to_log(SimulationSpec(scenario='random_motion', scenario_params=('duration_s=3',),
                                   reference='pose6'), path, progress=False)
    return path, read_run(path)


def _with_reference_at(path, run, stamps, values):
    """``run``'s log with its reference pose replaced by ``values`` at ``stamps``."""
    from mmd_ros.logs.layout import (FRAME_LOWER, REFERENCE_POSE_NAMES, TOPIC_CALIBRATION,
                                     TOPIC_DEVICE, TOPIC_RAW, TOPIC_REF_POSE)
    st = run.stamps_ns
    with LogWriter(path) as log:
        log.write_string(TOPIC_DEVICE, int(st[0]), run.device.to_yaml())
        log.write_string(TOPIC_CALIBRATION, int(st[0]), run.calibration.to_yaml())
        log.write_rows([(TOPIC_RAW, 'sensor_msgs/msg/JointState',
                         log.joint_state_rows(run.device.channel_names, st, run.counts))], st)
        log.write_rows([(TOPIC_REF_POSE, 'sensor_msgs/msg/JointState',
                         log.joint_state_rows(REFERENCE_POSE_NAMES, stamps, values, FRAME_LOWER))],
                       stamps)
    return path


def test_a_reference_on_stamps_of_its_own_is_interpolated_to_the_raw_samples(tmp_path, motion_log,
                                                                            capsys):
    """An instrument logged on its own clock (250 Hz, 0.37 ms off the MMD's tick) matched no raw
    sample: no error at all. Read between its readings, it gives the error the same reference
    gives at the MMD's stamps, in memory and block by block alike, and says it interpolated."""
    import json

    from mmd_ros.cli.main import main
    from mmd_ros.logs.layout import read_run
    path, run = motion_log
    st = run.stamps_ns
    own = st[::4][:-1] + 370_000
    values = np.column_stack([np.interp(own, st, run.reference_pose[:, j]) for j in range(6)])
    log = _with_reference_at(tmp_path / 'own.mcap', run, own, values)
    back = read_run(log)
    got = np.isfinite(back.reference_pose[:, 0])
    assert got.mean() > 0.99 and '250 Hz' in back.reference_note
    # (the truth between readings 4 ms apart, against its linear interpolation: a T^2/8)
    assert np.max(np.abs(back.reference_pose[got, :3] - run.reference_pose[got, :3])) < 2e-6
    figures = []
    for extra in ([], ['--segment', '1']):     # block by block, and in memory
        assert main(['process', str(log), '--out', str(tmp_path / 'p.mcap'), '--json', '--force',
                     *extra]) == 0
        out = capsys.readouterr()
        summary = json.loads(out.out)
        assert '250 Hz' in summary['reference_note'] and 'interpolation' in out.err
        figures.append([s['rms'] for s in summary['pose_error']])
    assert main(['process', str(path), '--out', str(tmp_path / 'q.mcap'), '--json']) == 0
    shared = [s['rms'] for s in json.loads(capsys.readouterr().out)['pose_error']]
    np.testing.assert_allclose(figures[0], figures[1], rtol=1e-9)
    # the error differs from the shared reference's by at most what interpolating it changed
    # (|RMS(e + d) - RMS(e)| <= RMS(d)), here 2 % of z, less elsewhere
    both = got & np.all(np.isfinite(run.reference_pose), axis=1)
    moved = np.sqrt(np.mean((back.reference_pose[both] - run.reference_pose[both]) ** 2, axis=0))
    moved *= np.array([1e6] * 3 + [180 / np.pi * 3600] * 3)        # um, arcsec
    assert np.all(np.abs(np.array(figures[0][:6]) - shared[:6]) <= moved * 1.01 + 1e-4)


def test_a_reference_at_some_of_the_mmd_stamps_or_with_a_dropout_is_not_bridged(tmp_path,
                                                                               motion_log):
    """A slower reference on the MMD's own tick stays where its readings are (no note); one on
    its own stamps is not interpolated across a dropout; an angle turning past +-pi is
    interpolated the short way round."""
    from mmd_ros.logs.layout import read_run
    _, run = motion_log
    st = run.stamps_ns
    every4 = read_run(_with_reference_at(tmp_path / 'tick.mcap', run, st[::4],
                                         run.reference_pose[::4]))
    assert np.isfinite(every4.reference_pose[:, 0]).sum() == st[::4].size
    assert every4.reference_note == ''
    own = st[::4][:-1] + 370_000
    values = np.column_stack([np.interp(own, st, run.reference_pose[:, j]) for j in range(6)])
    gap = (own > st[1000]) & (own < st[1100])
    # yaw turning through +-pi: 3.1 rad, then -3.1 rad is 0.083 rad further on, not 6.2 back
    values[:, 5] = np.angle(np.exp(1j * (np.pi + 1e-3 * np.arange(own.size) - 0.3)))
    back = read_run(_with_reference_at(tmp_path / 'gap.mcap', run, own[~gap], values[~gap]))
    inside = (st > own[gap][0] - 4_000_000) & (st < own[gap][-1] + 4_000_000)
    assert np.all(np.isnan(back.reference_pose[inside & (st > own[gap][0]) & (st < own[gap][-1])]))
    yaw = back.reference_pose[:, 5]
    ok = np.flatnonzero(np.isfinite(yaw))
    step = np.abs(np.diff(yaw[ok]))[np.diff(ok) == 1]     # (from one raw sample to the next)
    turn = np.angle(np.exp(1j * step))
    assert np.max(np.abs(turn)) < 1e-3                      # 0.25 mrad per raw sample, no jump
    assert np.sum(step > np.pi) >= 1 and np.nanmax(np.abs(yaw)) > 3.13      # it did cross +-pi


def test_a_reference_on_another_epoch_is_said_never_to_meet_the_samples(tmp_path, motion_log):
    """A reference stamped an hour off (another clock's epoch) gave 'no sample has a value'
    without a hint why; now the reader says how far apart the two sets of stamps lie."""
    from mmd_ros.logs.layout import open_run, read_run
    _, run = motion_log
    log = _with_reference_at(tmp_path / 'epoch.mcap', run, run.stamps_ns - 3600 * 10**9,
                             run.reference_pose)
    back = read_run(log)
    assert np.isnan(back.reference_pose).all()
    span_s = (run.stamps_ns[-1] - run.stamps_ns[0]) * 1e-9
    assert f'end {3600 - span_s:.6g} s before theirs begin' in back.reference_note
    with open_run(log) as stream:
        for _ in stream.blocks(700):
            pass
        assert stream.reference_note == back.reference_note
