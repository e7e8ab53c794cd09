"""A log replayed as fast as possible through the separate nodes, over real DDS.

replay_node → compensation_node → fk_node (and recorder_node) as executables. With flow control
(the default) every sample reaches every stage, and the replay and the stages say so in
``/diagnostics``. Without it, into stages with a queue of 20 messages, samples are lost, and
every loss is counted: at each stage, received + lost = published to it.
"""

from __future__ import annotations

import time

import pytest
from test_nodes_support import Nodes, needs_ros, params

from mmd_ros.twin.recording import SimulationSpec, simulate_to_log

DEPTH = 20


def replay_status(client, since: float) -> dict | None:
    """The last replay diagnostics in state 'done' received after ``since``."""
    with client._lock:
        history = list(client.diagnostic_history)
    done = [e for t, e in history if t >= since and e['name'].endswith(': replay')
            and e['values'].get('state') == 'done']
    return done[-1]['values'] if done else None


def counted(client, suffix: str, key: str) -> tuple[int, int]:
    v = client.status(suffix)['values']
    return int(v[f'{key}_received']), int(v[f'{key}_lost'])


@needs_ros
def test_replay_at_rate_0_delivers_every_sample_or_counts_every_loss(tmp_path):
    from mmd_ros.nodes.client import MmdClient
    log = tmp_path / 'run.mcap'
    spec = SimulationSpec(scenario='random_motion', scenario_params=('duration_s=2',),
                          ambient='constant:20', seed=5)
    n = simulate_to_log(spec, log, progress=False)[2]['samples']
    nodes = Nodes(tmp_path)
    nodes.apply_env()
    client = None
    fast = dict(qos_depth=DEPTH, diagnostics_period_s=0.3)
    try:
        nodes.start('compensation_node', *params(**fast))
        nodes.start('fk_node', *params(**fast))
        nodes.start('recorder_node', *params(output=str(tmp_path / 'replayed.mcap'), **fast))
        client = MmdClient(topics=())
        assert client.wait_for(lambda: all(client.status(f'{s}: {t}') is not None for s, t in (
            ('compensation_node', 'compensation'), ('fk_node', 'kinematics'),
            ('recorder_node', 'recorder'))), 60), nodes.dump()

        # flow control: nothing lost, though every stage queues only 20 messages
        since = time.monotonic()
        nodes.start('replay_node', *params(log=str(log), rate=0.0, wait_for_subscribers=2,
                                           diagnostics_period_s=0.3), tag='paced')
        assert nodes.procs['paced'].wait(120) == 0, nodes.dump()
        assert client.wait_for(lambda: replay_status(client, since) is not None, 10), nodes.dump()
        summary = replay_status(client, since)
        assert int(summary['sent']) == n and int(summary['lost']) == 0, summary
        rows = [k[:-len(' received')] for k in summary if k.endswith(' received')]
        assert len(rows) >= 5, summary  # comp raw; fk lengths, thermal; recorder: every topic
        assert int(summary['/mmd/compensation_node /mmd/raw_counts published']) == n
        assert int(summary['/mmd/recorder_node /mmd/pose published']) > 0.9 * n
        for key in rows:
            assert int(summary[f'{key} received']) == int(summary[f'{key} published']), (key, summary)
            assert int(summary[f'{key} lost']) == 0, (key, summary)
        time.sleep(1.0)  # the stages' next diagnostics
        assert counted(client, 'compensation_node: compensation', 'raw_counts') == (n, 0)
        assert counted(client, 'fk_node: kinematics', 'bar_lengths') == (n, 0)
        assert int(client.status('fk_node: kinematics')['values']['samples']) == n
        assert counted(client, 'recorder_node: recorder', 'raw_counts') == (n, 0)

        # no flow control: samples are lost, and every one is counted somewhere
        since = time.monotonic()
        nodes.start('replay_node', *params(log=str(log), rate=0.0, wait_for_subscribers=2,
                                           flow_control=False, qos_depth=DEPTH,
                                           diagnostics_period_s=0.3), tag='unpaced')
        assert nodes.procs['unpaced'].wait(120) == 0, nodes.dump()
        assert client.wait_for(lambda: replay_status(client, since) is not None, 10), nodes.dump()
        summary = replay_status(client, since)
        assert int(summary['sent']) == n
        comp = '/mmd/compensation_node /mmd/raw_counts'
        received, lost = int(summary[f'{comp} received']), int(summary[f'{comp} lost'])
        assert received + lost == n and lost > 0, summary
        assert int(summary['lost']) >= lost
        time.sleep(1.0)
        # the stage itself counted what it received and the losses it saw (all but those after
        # its last message, which only the replay can know)
        got, seen_lost = counted(client, 'compensation_node: compensation', 'raw_counts')
        assert got - n == received and 0 < seen_lost <= lost
        assert any(e['name'].endswith('compensation_node: compensation') and e['level'] == 1
                   and 'lost before they reached this node' in e['message']
                   for t, e in client.diagnostic_history if t >= since)
    except BaseException:
        print(nodes.dump())
        raise
    finally:
        if client is not None:
            client.close()
        nodes.stop_all()


if __name__ == '__main__':
    pytest.main([__file__, '-v'])
