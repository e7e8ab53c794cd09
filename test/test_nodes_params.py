"""Node parameters and names: invalid values refused by name and range, namespaces, services.

Real executables over real DDS: a node given an invalid parameter refuses to start and says
which parameter and what is allowed; ``-r __ns:=/cell3/mmd`` moves a whole device; run-time
parameters (``bar``, ``sim_command``) refuse bad values with a reason.
"""

from __future__ import annotations

import subprocess
import time

import pytest
from test_nodes_support import Nodes, command, needs_ros, params


@needs_ros
@pytest.mark.parametrize('name, args, expected', [
    ('encoder_node', dict(sample_rate_hz=-5), 'parameter sample_rate_hz: must be an integer in [1, 10000] or 0'),
    ('calibration_node', dict(mode='sometimes'), "parameter mode: must be one of 'auto', 'full', 're_reference'"),
    ('recorder_node', dict(flush_period_s=0.0), 'parameter flush_period_s: must be a number in [0.05, 60]'),
    ('replay_node', dict(), 'parameter log: the MCAP log to replay is required'),
])
def test_invalid_parameters_are_refused_by_name(tmp_path, name, args, expected):
    nodes = Nodes(tmp_path)
    out = subprocess.run(command(name) + params(**args), env=nodes.env, cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stdout + out.stderr
    assert expected in out.stderr, out.stderr


@needs_ros
def test_an_unknown_parameter_in_a_parameters_file_is_refused(tmp_path):
    """A typo in a parameters file stops the node naming the file, the key and the close match;
    a parameter of another mmd_ros node, and rclpy's own, are accepted by the check."""
    from mmd_ros.nodes.params import unknown_overrides
    assert unknown_overrides(['flush_period_s', 'use_sim_time', 'qos_overrides./mmd/pose.publisher.depth',
                              'sim_effects'], []) is None
    nodes = Nodes(tmp_path)
    path = tmp_path / 'my_params.yaml'
    path.write_text('/**:\n  ros__parameters:\n    sim_efects: none\n')
    out = subprocess.run(command('encoder_node') + ['--ros-args', '--params-file', str(path)],
                         env=nodes.env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stdout + out.stderr
    line = out.stderr.strip().splitlines()[-1]
    assert f'parameter sim_efects (from {path} or -p)' in line and 'did you mean sim_effects?' in line, \
        out.stderr
    assert 'Traceback' not in out.stderr


@needs_ros
def test_a_device_in_another_namespace(tmp_path):
    from mmd_ros.nodes.client import MmdClient
    nodes = Nodes(tmp_path)
    nodes.apply_env()
    client = None
    try:
        nodes.start('encoder_node', '--ros-args', '-r', '__ns:=/cell3/mmd', '-p', 'sim_mounted:=false')
        nodes.start('calibration_node', '--ros-args', '-r', '__ns:=/cell3/mmd',
                    '-p', f'calibration_file:={tmp_path / "cal.yaml"}')
        client = MmdClient('/cell3/mmd', topics=('raw',))
        assert client.wait_for(lambda: len(client.raw_stamps) > 200, 60), nodes.dump()
        statuses = lambda: client.status('/cell3/mmd/calibration_node: calibration')  # noqa: E731
        assert client.wait_for(lambda: statuses() is not None, 30)
        # first the reference bar where it rests: the temperature before the routine
        assert statuses()['values']['next_step'].startswith('place ref1 on dr4')
        ok, why = client.set_param('calibration_node', 'bar', 'bar9')
        assert not ok and 'bar must be one of' in why
        ok, why = client.set_param('calibration_node', 'settle_window_s', 1.0)
        assert not ok  # read only: read once at start
        assert client.set_param('calibration_node', 'bar', 'ref1')[0]
        assert client.wait_for(lambda: statuses()['values']['next_step'].startswith('place ref1 on dr1'), 10)
        ok, why = client.set_param('encoder_node', 'sim_command', 'fly bar1 away')
        assert not ok and 'unknown command' in why
        ok, why = client.set_param('encoder_node', 'sim_command', 'place bar1 dr9')
        assert not ok and 'dr9' in why
        # the service answers in the namespace; on a loaded machine the settling window may not
        # be full yet, and the routine says so: try again, as the operator would
        deadline = time.monotonic() + 90
        while True:
            ok, message = client.trigger('calibrate_bar')
            if ok or 'samples in the settling window' not in message or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert ok and message.startswith('captured ref1 on dr1'), message
        assert 'Next: place ref1 on dr2' in message
        assert client.trigger('calibration/reset_session')[0]
    except BaseException:
        print(nodes.dump())
        raise
    finally:
        if client is not None:
            client.close()
        nodes.stop_all()


@needs_ros
def test_the_parameters_file_and_the_docs_match_the_declarations():
    import yaml

    from mmd_ros.nodes import compensation_node, fk_node, pose_node, recorder_node, replay_node
    from mmd_ros.nodes.calibration_stage import CALIBRATION_PARAMS
    from mmd_ros.nodes.common import COMMON_PARAMS, MODEL_PARAMS
    from mmd_ros.nodes.params import check
    from mmd_ros.nodes.recorder_stage import RECORDER_PARAMS
    from mmd_ros.nodes.terminal import TERMINAL_PARAMS
    from test_nodes_support import ROOT
    declared = {}
    for group in (COMMON_PARAMS, MODEL_PARAMS, TERMINAL_PARAMS, CALIBRATION_PARAMS, RECORDER_PARAMS,
                  compensation_node.PARAMS, fk_node.PARAMS, recorder_node.PARAMS,
                  replay_node.PARAMS, pose_node.POSE_PARAMS):
        for p in group:
            declared.setdefault(p.name, []).append(p)
    values = yaml.safe_load((ROOT / 'config' / 'mmd_nodes.yaml').read_text())['/**']['ros__parameters']
    for name, value in values.items():
        assert name in declared, name
        assert any(check(p, value) is None for p in declared[name]), (name, value)
    docs = (ROOT / 'msg_docs' / 'nodes.md').read_text()
    missing = [name for name in declared if f'`{name}`' not in docs]
    assert not missing
