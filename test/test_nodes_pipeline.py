"""The separate-process pipeline over real DDS: calibration, poses, recording, replay.

encoder_node (simulated terminal streaming the twin), calibration_node, compensation_node and
fk_node run as executables. The test is the operator: it runs the guided calibration of
section 3.2 through ``/mmd/calibrate_bar`` (bumping a bar during one capture and using the
wrong sockets once), mounts the bars, checks the poses against the twin's reference, records
with recorder_node (closed with SIGINT: a complete MCAP file), and replays the log through the
compensation and kinematics nodes: the same poses as ``mmd process`` on that log.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from test_nodes_faults import check_machine_joints, publish_machine_joints
from test_nodes_support import Nodes, needs_ros, params

from mmd_ros.logs.processing import process_run
from mmd_ros.core.calibration import load_calibration
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run
from mmd_ros.logs.reader import LogReader

ARCSEC = np.pi / 180 / 3600
SETTLE = 0.25
TRANSITION = 0.2
#: Deep queues: the machine is shared, a node may be starved for a few seconds.
DEPTH = 20000


@needs_ros
def test_calibrate_measure_record_and_replay(tmp_path):
    from mmd_ros.nodes.client import MmdClient, guided_calibration
    nodes = Nodes(tmp_path)
    nodes.apply_env()
    cal_file = tmp_path / 'calibration.yaml'
    log_file = tmp_path / 'run.mcap'
    client = None
    try:
        nodes.start('encoder_node', *params(sim_mounted=False, sim_transition_s=TRANSITION, sim_seed=2,
                                            qos_depth=DEPTH))
        nodes.start('calibration_node', *params(calibration_file=str(cal_file),
                                                settle_window_s=SETTLE, ambient_c=20.0,
                                                qos_depth=DEPTH))
        nodes.start('compensation_node', *params(qos_depth=DEPTH))
        nodes.start('fk_node', *params(qos_depth=DEPTH))
        client = MmdClient(topics=('pose', 'reference'), depth=DEPTH)
        assert client.wait_for(lambda: client.status(': calibration') is not None
                               and client.status(': terminal') is not None, 60), nodes.dump()
        assert 'no calibration' in client.status(': calibration')['message']

        events = {}

        def faults(k: int, bar: str, pair: str) -> None:
            if k == 9:  # bar2's third point: someone bumps the bar during the capture
                assert client.set_param('encoder_node', 'sim_command', f'move {bar} 1.5')[0]
            if k == 16:  # bar3's third point: the operator uses the wrong sockets first
                assert client.set_param('encoder_node', 'sim_command', f'place {bar} dr6')[0]
                time.sleep(TRANSITION + SETTLE + 0.3)
                ok, message = client.trigger('calibrate_bar')
                events['wrong_pair'] = (ok, message)
                assert client.set_param('encoder_node', 'sim_command', f'place {bar} {pair}')[0]
                time.sleep(TRANSITION + SETTLE + 0.3)

        log = guided_calibration(client, sim_node='encoder_node', wait_s=TRANSITION + SETTLE + 0.15,
                                 retry_s=0.3, before_capture=faults, timeout_s=240)
        answers = [m for ok, m in log.answers]
        assert sum(ok for ok, _ in log.answers) == 49  # six bars and the reference bar, 7 pairs each
        assert log.refused_moving >= 1 and any('bar2 is still moving' in m for m in answers)
        ok, message = events['wrong_pair']
        assert not ok and 'does not fit dr3' in message and 'dr6' in message
        assert 'Calibration complete' in answers[-1] and 'thermal zero set' in answers[-1]
        assert 'Saved to' in answers[-1] and '.bak' in answers[-1]
        cal = load_calibration(cal_file)
        assert cal.valid and len(cal.bars) == 7 and (tmp_path / 'calibration.yaml.bak').exists()
        assert abs(cal.thermal_zero_m['ref1']) < 1e-9 and cal.ambient_c == 20.0

        assert client.set_param('encoder_node', 'sim_command', 'mount')[0]
        nodes.start('recorder_node', *params(output=str(log_file), flush_period_s=0.5, qos_depth=DEPTH))
        assert client.wait_for(lambda: (client.status(': recorder') or {}).get('values', {})
                               .get('state') == 'recording', 30), nodes.dump()
        publish_machine_joints(client, 10)
        since = time.time_ns() + int((TRANSITION + 1.0) * 1e9)
        assert client.wait_for(lambda: len(client.errors_against_reference(since)) >= 3000, 180), nodes.dump()
        err = client.errors_against_reference(since)
        assert np.abs(err[:, :3]).max() < 10e-6, np.abs(err[:, :3]).max(axis=0)
        assert np.abs(err[:, 3:]).max() < 15 * ARCSEC, np.abs(err[:, 3:]).max(axis=0) / ARCSEC
        assert np.sqrt(np.mean(err[:, :3] ** 2)) < 3e-6
        live_stamps, live_poses = client.pose_array()

        assert nodes.signal('recorder_node') == 0, nodes.dump()  # SIGINT: closed cleanly
        from mcap.reader import make_reader
        with open(log_file, 'rb') as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics.message_count > 15000
        reader = LogReader(log_file)
        assert reader.problem is None
        topics = reader.topics
        for name in ('/mmd/raw_counts', '/mmd/pose', '/mmd/bar_lengths', '/mmd/thermal',
                     '/mmd/pose_with_covariance', '/mmd/fk_status', '/mmd/reference/pose',
                     '/mmd/calibration', '/mmd/device_description', '/mmd/model', '/diagnostics',
                     '/mmd/machine/joint_states'):
            assert topics[name].count > 0, name

        # replay the log through the compensation and kinematics nodes
        nodes.signal('encoder_node')
        nodes.signal('calibration_node')
        with client._lock:
            client.poses.clear()
        run = read_run(log_file)
        check_machine_joints(run, 10)
        processed = process_run(run, Model())
        # half speed, so that the nodes keep up on a loaded machine; the log is as long as the
        # recording above took, which grows with the load, so the deadlines scale with it
        rate = 0.5
        replay_s = (run.stamps_ns[-1] - run.stamps_ns[0]) * 1e-9 / rate
        nodes.start('replay_node', *params(log=str(log_file), rate=rate, wait_for_subscribers=1,
                                            qos_depth=DEPTH))
        assert nodes.procs['replay_node'].wait(120 + 3 * replay_s) == 0, nodes.dump()
        n_valid = int(processed.valid.sum())
        assert client.wait_for(lambda: len(client.poses) >= n_valid, 30 + replay_s), \
            (len(client.poses), n_valid)
        stamps, poses = client.pose_array()
        assert len(stamps) == n_valid
        index = {int(s): i for i, s in enumerate(run.stamps_ns)}
        rows = np.array([index[int(s)] for s in stamps])
        assert processed.valid[rows].all()
        np.testing.assert_allclose(poses[:, :3], processed.poses[rows, :3], atol=1e-9)
        np.testing.assert_allclose(poses[:, 3:], processed.poses[rows, 3:], atol=1e-9)
        # and the live poses of those samples were the same too
        live = {int(s): p for s, p in zip(live_stamps, live_poses)}
        common = [i for i, s in enumerate(stamps) if int(s) in live]
        assert len(common) > 0.9 * len(stamps)
        np.testing.assert_allclose(np.array([live[int(stamps[i])] for i in common]), poses[common],
                                   atol=1e-9)
    except BaseException:
        print(nodes.dump())
        raise
    finally:
        if client is not None:
            client.close()
        nodes.stop_all()


if __name__ == '__main__':
    pytest.main([__file__, '-v'])
