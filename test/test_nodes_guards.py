"""What keeps a wrong or lost number out of the live stream, without a running graph.

- a calibration is bound to the terminal and bars it was made with; another terminal, the
  simulator's calibration on hardware, or moved bars are refused (or used by override, ERROR);
- a calibration file that cannot be written: the stage runs with what it has and says ERROR;
- samples the terminal flagged (encoder signal lost) give no length and no pose, live and
  through ``raw_counts`` between processes;
- ``pose_batch`` (``nav_msgs/Path``) carries exactly the poses and stamps of ``pose``.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace

import numpy as np
import pytest
from test_nodes_support import needs_ros, seen

from mmd_ros.core.calibration import (
    Calibration, TerminalBinding, binding_problem, channel_roles, load_calibration,
)
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.model import Model
from mmd_ros.core.streaming import Compensator, Kinematics
from mmd_ros.hardware import SimTerminal, SimUsbBackend, TerminalDriver
from mmd_ros.hardware.twin_source import TwinSource
from mmd_ros.twin import AmbientProfile, Effects, TwinDevice, make_scenario


@pytest.fixture(scope='module')
def device():
    return load_device(find_config('mmd_prototype.yaml'))


@pytest.fixture(scope='module')
def source(device):
    twin = TwinDevice(device, Effects.realistic(), seed=4)
    return TwinSource(twin, AmbientProfile.constant(20.0),
                      make_scenario('random_motion', ['duration_s=5']), block=50)


def bound(cal: Calibration, serial: str, simulated: bool, device) -> Calibration:
    return replace(cal, terminal=TerminalBinding(serial, simulated, channel_roles(device.channels)))


def test_a_calibration_is_refused_on_another_terminal_on_hardware_or_with_moved_bars(device, source):
    roles = channel_roles(device.channels)
    assert roles['bar3'] == 'measuring bar 3' and roles['ref1'] == 'reference bar on dr4'
    sim1 = TerminalBinding('MMD-SIM-0001', True, roles)
    real = TerminalBinding('MMD-0042', False, roles)
    factory = source.factory_calibration()  # says it is the twin's, records no terminal
    assert 'digital twin' in factory.quality['source'] and factory.terminal is None
    assert binding_problem(factory, sim1) is None
    assert 'simulated terminal' in binding_problem(factory, real)
    cal = bound(factory, 'MMD-SIM-0001', True, device)
    assert binding_problem(cal, sim1) is None
    assert 'MMD-SIM-0002' in binding_problem(cal, replace(sim1, serial='MMD-SIM-0002'))
    assert 'real hardware' in binding_problem(cal, real)
    # the simulated terminal pretending to be a real one: the file says simulated
    cal_real = bound(replace(factory, quality={}), 'MMD-0042', False, device)
    assert binding_problem(cal_real, real) is None
    assert 'MMD-0043' in binding_problem(cal_real, replace(real, serial='MMD-0043'))
    assert binding_problem(cal_real, replace(real, serial='')) is None  # serial not known yet
    assert 'made with terminal MMD-0042' in binding_problem(cal_real, sim1)
    assert 'real hardware' in binding_problem(cal_real, replace(sim1, serial=''))
    # bar2 and bar3 swapped between channels since the calibration
    swapped = dict(roles, bar2='measuring bar 3', bar3='measuring bar 2')
    why = binding_problem(cal_real, replace(real, channels=swapped))
    assert 'bar2 (measuring bar 2 then, measuring bar 3 now)' in why
    # the binding survives the file
    again = Calibration.from_yaml(cal_real.to_yaml())
    assert again.terminal == cal_real.terminal and again == cal_real
    with pytest.raises(ConfigError, match='terminal.simulated'):
        Calibration.from_yaml(cal_real.to_yaml().replace('simulated: false', 'simulated: maybe'))


class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, text: str) -> None:
        self.lines.append(('info', text))

    def warn(self, text: str) -> None:
        self.lines.append(('warn', text))

    def error(self, text: str) -> None:
        self.lines.append(('error', text))


def stage(device, path, *, any_terminal=False, terminal=None, factory=None, refused=None):
    from mmd_ros.nodes.calibration_stage import CALIBRATION_PARAMS, CalibrationConfig, CalibrationStage
    values = {p.name: p.default for p in CALIBRATION_PARAMS}
    values.update(calibration_file=str(path), calibration_any_terminal=any_terminal)
    published: list[Calibration] = []
    st = CalibrationStage(CalibrationConfig.from_values(values), device, thermal_mode='reference',
                          publish=published.append, logger=Log(), factory=factory,
                          terminal=terminal, on_refused=refused)
    st.start()
    return st, published


@needs_ros
def test_the_stage_restores_a_calibration_an_interrupted_save_left_as_bak(device, source, tmp_path):
    """Killed between the old writer's two renames, only cal.yaml.bak and a temporary remain:
    the next start uses the complete earlier calibration (not a new factory one), puts the
    file back, and says so in the log and the diagnostics until the next save."""
    roles = channel_roles(device.channels)
    path = tmp_path / 'cal.yaml'
    old = bound(source.factory_calibration(), 'MMD-SIM-0001', True, device)
    old = replace(old, created='2026-01-01T00:00:00Z')
    old.save(path)
    os.rename(path, tmp_path / 'cal.yaml.bak')
    (tmp_path / '.cal.yaml.99.beef.tmp').write_text(old.to_yaml()[:300])

    def factory():
        raise AssertionError('a new factory calibration written over the recoverable one')

    st, published = stage(device, path, terminal=TerminalBinding('MMD-SIM-0001', True, roles),
                          factory=factory)
    assert st.routine.calibration is not None and st.routine.calibration.created == old.created
    assert published[0].bars == old.bars
    assert load_calibration(path) == old and load_calibration(tmp_path / 'cal.yaml.bak') == old
    warned = [text for level, text in st.log.lines if level == 'warn']
    assert any('restored' in t and 'cal.yaml.bak' in t for t in warned), st.log.lines
    r = st.report()
    assert r.level == 1 and 'restored' in r.message and 'cal.yaml.bak' in r.values['recovered']
    st._save(st.routine.calibration)           # the next save: the warning has done its work
    assert st.report().level == 0 and st.report().values['recovered'] == ''
    # the file damaged by hand: refused by name, the calibration in use stays; the .bak copied
    # over it (recovery.md) is reloaded at the next poll and published
    in_use = st.routine.calibration
    path.write_text(path.read_text().replace('counts:', 'counts: [1, 2]\n    x:', 1))
    st.poll_file()
    assert st.routine.calibration is in_use and st.report().level == 2
    assert str(path) in st.report().message
    n = len(published)
    path.write_bytes((tmp_path / 'cal.yaml.bak').read_bytes())
    st.poll_file()
    assert not st.file_problem and len(published) == n + 1 and published[-1].bars == old.bars
    # a backup that is no calibration: ERROR, said, and the simulator's factory takes over
    os.unlink(path)
    (tmp_path / 'cal.yaml.bak').write_text('not: a calibration\n')
    st, published = stage(device, path, terminal=TerminalBinding('MMD-SIM-0001', True, roles),
                          factory=source.factory_calibration)
    errors = [text for level, text in st.log.lines if level == 'error']
    assert any('cal.yaml.bak, which cannot be used' in t for t in errors), st.log.lines
    assert (tmp_path / 'cal.yaml.bak').read_text() == 'not: a calibration\n'


@needs_ros
def test_the_stage_refuses_a_foreign_file_binds_what_it_saves_and_keeps_the_foreign_one(
        device, source, tmp_path):
    roles = channel_roles(device.channels)
    path = tmp_path / 'cal.yaml'
    bound(source.factory_calibration(), 'MMD-SIM-0001', True, device).save(path)
    text = path.read_text()
    # a real terminal (serial not known until it is opened): the twin's calibration is refused
    st, published = stage(device, path, terminal=TerminalBinding('', False, roles))
    r = st.report()
    assert st.routine.calibration is None and not published
    assert r.level == 2 and 'simulated terminal' in r.message and str(path) in r.message
    assert path.read_text() == text  # untouched
    # by override it is used, and the diagnostics still say ERROR
    st, published = stage(device, path, any_terminal=True, terminal=TerminalBinding('', False, roles))
    assert st.routine.calibration is not None and len(published) == 1
    assert published[0].terminal.serial == 'MMD-SIM-0001'  # it still says where it came from
    assert st.report().level == 2 and 'override' in st.report().message
    # the simulator with another serial: fine at start (serial unknown), withdrawn once opened
    withdrawn = []
    st, published = stage(device, path, terminal=TerminalBinding('', True, roles),
                          refused=lambda: withdrawn.append(1))
    assert st.routine.calibration is not None and st.report().level == 0
    assert published[0].terminal.serial == 'MMD-SIM-0001'
    st.set_terminal(TerminalBinding('MMD-SIM-0002', True, roles))
    assert withdrawn == [1] and st.routine.calibration is None
    assert st.report().level == 2 and 'MMD-SIM-0002' in st.report().message
    # a new calibration replaces the foreign file, which is kept; the new one is bound
    note = st._save(source.factory_calibration())
    assert 'foreign file was kept as cal.yaml.foreign' in note, note
    assert (tmp_path / 'cal.yaml.foreign').read_text() == text
    saved = load_calibration(path)
    assert saved.terminal == TerminalBinding('MMD-SIM-0002', True, roles)
    assert not st.file_problem and not st.foreign  # (the refusal stays an event for 10 s)


@needs_ros
def test_a_calibration_that_cannot_be_written_leaves_the_stage_running_with_an_error(
        device, source, tmp_path):
    # as root, permissions do not stop a write; a path under a regular file does
    blocker = tmp_path / 'not_a_folder'
    blocker.write_text('a file\n')
    path = blocker / 'cal.yaml'
    st, published = stage(device, path, terminal=TerminalBinding('MMD-SIM-0001', True, {}),
                          factory=source.factory_calibration)
    assert st.routine.calibration is not None and len(published) == 1  # measuring goes on
    r = st.report()
    assert r.level == 2 and 'cannot be saved' in r.message and str(path) in r.message
    assert r.values['saved'] is False
    # a capture's save fails the same way, without an exception
    note = st._save(source.factory_calibration())
    assert 'COULD NOT SAVE' in note and st.report().level == 2
    # a folder that can be written: the probe passes, a save clears the error
    ok, _ = stage(device, tmp_path / 'sub' / 'cal.yaml', terminal=TerminalBinding('X', True, {}),
                  factory=source.factory_calibration)
    assert ok.report().level == 0 and (tmp_path / 'sub' / 'cal.yaml').exists()


def test_flagged_samples_give_no_length_and_no_pose(device, source):
    term = SimTerminal(source, serial='TWIN-1', paced=False, power_on_reset=False)
    cal = source.factory_calibration()
    comp = Compensator(device, Model())
    assert comp.set_calibration(cal, 'test') is None
    kin = Kinematics(device, 1e-7)
    from mmd_ros.nodes.sim_commands import run_commands
    with TerminalDriver(backend=SimUsbBackend(term)) as drv:
        for _ in range(3):
            drv.read_batch(1.0)
        good = drv.read_batch(1.0)
        assert good.status_codes() is None
        assert run_commands('signal_lost bar3', source, term) == 'bar3: encoder signal lost'
        lost = drv.read_batch(1.0)
        while not lost.channel_status.any():
            lost = drv.read_batch(1.0)
        codes = lost.status_codes()
        assert codes.shape == (lost.n, 8) and set(np.unique(codes[:, 2])) == {1}
        assert not codes[:, [0, 1, 3, 4, 5, 6, 7]].any()
        run_commands('signal_lost ref1', source, term)
        both = drv.read_batch(1.0)
        while not both.signal_lost[:, 6].all():
            both = drv.read_batch(1.0)
        run_commands('signal_ok bar3; signal_ok ref1', source, term)
    stamps = np.arange(good.n, dtype=np.int64)
    out = comp.process(stamps, good.counts.astype(float), good.status_codes())
    assert np.isfinite(out.lengths_m).all() and kin.solve(out.lengths_m, out.plate_scale).valid.all()
    out = comp.process(stamps[:lost.n], lost.counts.astype(float), lost.status_codes())
    assert np.isnan(out.lengths_m[:, 2]).all() and np.isfinite(out.lengths_m[:, [0, 1, 3, 4, 5]]).all()
    k = kin.solve(out.lengths_m, out.plate_scale)
    assert not k.valid.any() and not k.converged.any()
    assert (k.status_values()[:, 1] == 0).all()  # fk_status valid 0
    # the reference bar without signal: its thermal compensation is unknown, so is every length
    out = comp.process(stamps[:both.n], both.counts.astype(float), both.status_codes())
    assert np.isnan(out.lengths_m).all()
    assert comp.stats.no_signal == lost.n + both.n
    from mmd_ros.nodes.reports import compensation_report
    r = compensation_report(comp, 2.0, 'default')
    assert r.level == 1 and 'encoder signal lost' in r.message and 'bar3' in r.message
    assert r.values['samples_without_signal'] == lost.n + both.n
    assert np.isnan(r.values['reading_drift_um'])       # the twin's calibration states no time
    # the plates' scale as the covariance claims it at the thermal drift last known
    dt = comp.stats.last_temp_change_c
    assert dt != 0.0 and comp.budget.plate_scale_rel > 0.0
    assert r.values['plate_scale_ppm'] == pytest.approx(
        comp.budget.plate_scale_rel * abs(dt) * 1e6, abs=1e-4)


@needs_ros
def test_flagged_samples_cross_processes_in_raw_counts_and_batches_are_the_poses(device):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    from rclpy.serialization import deserialize_message

    from mmd_ros.nodes.convert import RawBatch, Rows, from_time, pose_from_msg
    rows = Rows(device.channel_names, ['ref1'])
    stamps = 1_700_000_000_000_000_000 + np.arange(5, dtype=np.int64) * 1_000_000
    counts = np.arange(40.0).reshape(5, 8)
    status = np.zeros((5, 8), np.uint8)
    status[2, 2] = 1
    status[3, 6] = 3
    batch = RawBatch(device.channel_names)
    for i in range(5):
        encode = rows.raw_with_status if status[i].any() else rows.raw.encode
        args = (stamps[i:i + 1], counts[i:i + 1]) + ((status[i:i + 1],) if status[i].any() else ())
        batch.add(encode(*args)[0].tobytes())
    # a flagged row is the message rclpy itself would make (compared decoded: rclpy leaves
    # its alignment padding uninitialised)
    from sensor_msgs.msg import JointState

    from mmd_ros.nodes.convert import header
    msg = JointState(header=header(int(stamps[3])), name=device.channel_names,
                     position=list(counts[3]), effort=[float(v) for v in status[3]])
    row = rows.raw_with_status(stamps[3:4], counts[3:4], status[3:4])[0].tobytes()
    assert deserialize_message(row, JointState) == msg
    s, v, st = batch.take_all()
    assert np.array_equal(s, stamps) and np.array_equal(v, counts) and np.array_equal(st, status)
    assert batch.foreign == 0
    batch.add(rows.raw.encode(stamps, counts)[0].tobytes())
    assert batch.take_all()[2] is None  # good samples: the compact layout, no status
    # a transfer's poses as one Path: the same stamps and values as the PoseStamped rows
    rng = np.random.default_rng(3)
    for n in (1, 7, 8, 13):
        t = stamps[0] + np.arange(n, dtype=np.int64) * 1_000_000 + 123
        poses = np.column_stack([rng.normal(0, 0.05, (n, 3)), rng.normal(0, 0.3, (n, 3))])
        path = deserialize_message(rows.pose_batch(t, poses), Path)
        assert path.header.frame_id == 'mmd_lower' and from_time(path.header.stamp) == t[-1]
        assert [from_time(p.header.stamp) for p in path.poses] == list(t)
        singles = [deserialize_message(r.tobytes(), PoseStamped) for r in rows.poses(t, poses)]
        for p, q in zip(path.poses, singles):
            assert p == q
            np.testing.assert_allclose(pose_from_msg(p.pose), pose_from_msg(q.pose), atol=0)
        assert all(math.isfinite(p.pose.orientation.w) for p in path.poses)



@needs_ros
def test_pose_node_refuses_a_foreign_calibration_runs_unsaved_and_drops_samples_without_signal(
        device, source, tmp_path):
    """Two simulated devices over real DDS: /a/mmd whose calibration file was made with another
    terminal; /b/mmd whose calibration cannot be written, and which then loses bar3's signal."""
    import time

    from test_nodes_support import Nodes, params

    from mmd_ros.nodes.client import MmdClient
    cal_a = tmp_path / 'a.yaml'
    bound(source.factory_calibration(), 'MMD-SIM-0001', True, device).save(cal_a)
    text_a = cal_a.read_text()
    (tmp_path / 'not_a_folder').write_text('a file\n')
    cal_b = tmp_path / 'not_a_folder' / 'b.yaml'
    nodes = Nodes(tmp_path)
    nodes.apply_env()
    clients = []
    common = dict(record=False, diagnostics_period_s=0.5, qos_depth=5000)
    try:
        nodes.start('pose_node', '--ros-args', '-r', '__ns:=/a/mmd', *params(
            calibration_file=str(cal_a), sim_serial='MMD-SIM-0002', **common)[1:], tag='a')
        nodes.start('pose_node', '--ros-args', '-r', '__ns:=/b/mmd', *params(
            calibration_file=str(cal_b), **common)[1:], tag='b')
        a = MmdClient('/a/mmd', topics=('pose',), name='client_a')
        b = MmdClient('/b/mmd', topics=('pose_batch',), name='client_b', depth=20000)
        b_single = MmdClient('/b/mmd', topics=('pose',), name='client_b1', depth=20000)
        clients += [a, b, b_single]
        # /b measures with the twin's factory calibration it could not save, and says so
        assert b.wait_for(lambda: len(b.poses) > 2000, 90), nodes.dump()
        st = b.status('/b/mmd/pose_node: calibration')
        assert st['level'] == 2 and 'cannot be saved' in st['message'], st
        assert 'is a file, not a folder' in st['message']
        assert st['values']['saved'] == 'false'
        assert not cal_b.parent.is_dir() and 'Traceback' not in nodes.output('b')
        # /a: streaming, but its calibration is refused: no pose, the file untouched
        term = lambda: a.status('/a/mmd/pose_node: terminal')  # noqa: E731
        assert a.wait_for(lambda: term() is not None and int(term()['values']['samples_published']) > 3000,
                          60), nodes.dump()
        st = a.status('/a/mmd/pose_node: calibration')
        assert st['level'] == 2 and 'MMD-SIM-0001' in st['message'] and 'MMD-SIM-0002' in st['message']
        assert len(a.poses) == 0 and cal_a.read_text() == text_a
        assert a.status('/a/mmd/pose_node: compensation')['values']['calibration_valid'] == 'false'

        # the batched stream carries the same poses as the per-sample topic
        with b._lock, b_single._lock:
            batched = {s: p for s, *p in b.poses}
            single = list(b_single.poses)
        common_rows = [(s, p) for s, *p in single if s in batched]
        # (the per-sample subscriber may fall far behind on a loaded machine: that is the point)
        assert len(common_rows) >= 100, (len(common_rows), len(single))
        assert all(batched[s] == p for s, p in common_rows)

        # bar3 loses its encoder signal for a second: no pose, every flagged sample counted
        t0 = time.monotonic()
        assert b.set_param('/b/mmd/pose_node', 'sim_command', 'signal_lost bar3')[0]
        time.sleep(1.0)
        assert b.set_param('/b/mmd/pose_node', 'sim_command', 'signal_ok bar3')[0]
        n = len(b.poses)
        assert b.wait_for(lambda: len(b.poses) > n + 1000, 30)
        assert seen(b, t0, '/b/mmd/pose_node: compensation', 'encoder signal lost', level=1)
        assert seen(b, t0, '/b/mmd/pose_node: kinematics', 'without encoder signal', level=1)
        assert seen(b, t0, '/b/mmd/pose_node: terminal', 'not measurements', level=1)
        time.sleep(1.2)  # the next diagnostics
        flagged = int(b.status('/b/mmd/pose_node: terminal')['values']['samples_flagged'])
        comp = b.status('/b/mmd/pose_node: compensation')['values']
        assert flagged > 500 and int(comp['samples_without_signal']) == flagged
        stamps = np.sort(np.array([s for s, *_ in b.poses], dtype=np.int64))
        steps = np.diff(stamps)
        assert steps.max() > (flagged - 20) * 1e6  # no pose while the signal was lost
        assert np.count_nonzero(steps > 50e6) == 1
    except BaseException:
        print(nodes.dump())
        raise
    finally:
        for c in clients:
            c.close()
        nodes.stop_all()
