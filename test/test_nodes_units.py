"""Pieces of the nodes without a running graph: time mapping, the twin's world as a terminal
source, simulation commands, message conversion, alignment of a calibration to a session."""

from __future__ import annotations

import numpy as np
import pytest
from test_nodes_support import needs_ros

from mmd_ros.core.calibration_routine import CalibrationRoutine
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.hardware import SimTerminal, SimUsbBackend, TerminalDriver
from mmd_ros.hardware.twin_source import TwinSource
from mmd_ros.nodes.clock import StampMapper
from mmd_ros.twin import AmbientProfile, Effects, TwinDevice, TwinError, make_scenario

MS = 1_000_000


@pytest.fixture(scope='module')
def device():
    return load_device(find_config('mmd_prototype.yaml'))


def make_source(device, **kw):
    twin = TwinDevice(device, Effects.realistic(), seed=4)
    return TwinSource(twin, AmbientProfile.constant(20.0),
                      make_scenario('random_motion', ['duration_s=5']), **kw)


def test_each_placement_from_one_side_seats_the_bar_anew(device):
    """The simulated operator seats a bar anew at each placement from short or long: the
    routine's drift check reads the reference bar on its resting pair from both sides before
    the measuring bars and again at the end, and with one seating for both the change between
    them would come out exact where the plate's seating repeatability scatters it."""
    src = make_source(device, mounted=False, transition_s=0.1, block=50)
    ref = device.reference_channels[0]
    means = []
    for approach in ('short', 'long', 'short', 'long'):
        src.place(ref.name, ref.pair, approach)
        src.read(300)                                  # (moved and seated)
        means.append(src.read(400)[1][:, ref.index].mean())
    assert src.where()[ref.name] == f'{ref.pair}@long'
    room = AmbientProfile.constant(20.0)
    times = src.start_s + np.arange(400) / device.sample_rate_hz
    seats = [src.twin.counts_on_pair(ref.index, ref.pair, times, room, approach=a, seat=k).mean()
             for k, a in enumerate((1.0, -1.0, 1.0, -1.0), start=1)]
    np.testing.assert_allclose(means, seats, atol=0.2)  # (read noise, the room's constant)
    assert abs(means[2] - means[0]) > 0.05                # another seating, not the same


def test_stamp_mapper_converges_without_going_back():
    rng = np.random.default_rng(0)
    m = StampMapper(MS)
    true_offset = 1_700_000_000 * 10**9
    stamps = []
    for k in range(0, 20_000, 8):  # 20 s of 8-sample transfers, clocks drifting by 20 ppm
        dev = (np.arange(k, k + 8) * MS).astype(np.int64)
        latency = int(50_000 + rng.exponential(400_000)) + (30 * MS if k == 0 else 0)
        host = true_offset + int(dev[-1] * (1 + 20e-6)) + latency
        stamps.append(m.map(dev, host))
    s = np.concatenate(stamps)
    assert np.all(np.diff(s) > 0.5 * MS)  # never backwards, never closer than half a period
    taken = true_offset + (np.arange(20_000) * MS * (1 + 20e-6)).astype(np.int64)
    err = s - taken
    assert abs(err[0]) > 20 * MS  # a late first transfer...
    assert np.all(np.abs(err[-5000:]) < 0.2 * MS)  # ...is forgotten; the drift is followed
    m.new_epoch()  # the terminal's clock restarts: stamps continue after the last one
    s2 = m.map(np.arange(8, dtype=np.int64) * MS, int(taken[-1]) + 9 * MS)
    assert s2[0] > s[-1] and m.epochs == 2


def test_twin_source_world(device):
    src = make_source(device, mounted=False, transition_s=0.1, block=50)
    src.read(10)
    assert np.all(src.reference_at(np.arange(10) * MS) != src.reference_at(np.arange(10) * MS))  # NaN
    src.place('bar2', 'dr3')
    src.read(200)
    t, c = src.read(100)
    # bar2 now reads dr3 as the twin's own calibration did when it placed it once (the two-sided
    # routine's point is the mean of two placements, a friction hysteresis away)
    cal = src.twin.calibrate(0.0, AmbientProfile.constant(20.0), approaches=1)
    q = cal.bars['bar2'].counts[2]
    assert np.abs(c[:, 1] - q).max() < 5
    assert src.where()['bar2'] == 'dr3' and src.where()['bar1'] == 'off'
    src.disturb('bar2', 0.5, 20e-6)
    _, moving = src.read(300)
    assert np.ptp(moving[:, 1]) > 300  # 20 µm = 400 counts
    src.mount()
    src.read(400)  # the bump of bar2 ends, the bars seat
    t, c = src.read(100)
    ref = src.reference_at(t)
    assert np.isfinite(ref).all()  # all six mounted and seated: the reference reads
    pipe = Pipeline(device, src.factory_calibration())
    err = [pipe.process_sample(0.0, c[i]).pose - ref[i] for i in range(100)]
    assert np.abs(np.array(err)[:, :3]).max() < 10e-6
    src.hold('bar1', 0.24)
    src.read(200)
    _, c = src.read(10)
    assert pipe.process_sample(0.0, c[-1]).out_of_range[0]  # held below dr1
    with pytest.raises(TwinError):
        src.place('bar9', 'dr1')
    with pytest.raises(TwinError):
        src.hold('bar1', 5.0)


def test_near_wrap_and_counter_reset_through_the_terminal(device):
    src = make_source(device, near_wrap_margin=100)
    term = SimTerminal(src, serial='TWIN-1', paced=False, power_on_reset=False)
    from mmd_ros.nodes.sim_commands import SimCommandError, run_commands
    with TerminalDriver(backend=SimUsbBackend(term)) as drv:
        b = drv.read_batch(1.0)
        assert np.all(np.abs(b.counts[0, :7] - (2**31 - 101)) < 3)
        assert run_commands('reset_counters', src, term) == 'counters reset'
        batches = [drv.read_batch(1.0) for _ in range(3)]
        reset = next(x for x in batches if x.counter_reset)
        first = reset.device_time_ns[reset.reset_index]
        assert first == 0  # the terminal's clock restarted...
        ref_k = src.reference_at(np.array([first]))
        assert np.isfinite(ref_k).all()  # ...and the world still finds that sample's reference
        with pytest.raises(SimCommandError, match='unknown command'):
            run_commands('jump', src, term)
        with pytest.raises(SimCommandError, match='takes 2 argument'):
            run_commands('place bar1', src, term)
        assert 'placed' in run_commands('place bar1 dr1; move bar1 1', src, term)


def test_calibration_follows_a_session_that_started_past_the_wrap(device):
    src = make_source(device, near_wrap_margin=100)
    cal = src.factory_calibration()
    routine = CalibrationRoutine(device, cal)
    _, counts = src.read(1)
    # a driver session that first saw bars 1-3 just past the wrap: the same counters, one lap down
    session = np.where(np.arange(8) < 3, counts[0] - 2**32, counts[0]).astype(np.float64)
    moved = routine.align(session)
    assert moved is not None and moved.quality['aligned_to_session'] == ['bar1', 'bar2', 'bar3']
    for k, name in enumerate(device.channel_names[:7]):
        shift = np.array(moved.bars[name].counts) - np.array(cal.bars[name].counts)
        assert np.all(shift == (session[k] - counts[0][k]))
    assert routine.align(session) is None  # already there


@needs_ros
def test_rows_are_messages_rclpy_reads(device):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    from mmd_ros.nodes.convert import RawBatch, Rows, pose_from_msg
    rows = Rows(device.channel_names, ['ref1'])
    stamps = np.array([1_700_000_000_123_456_789, 1_700_000_000_124_456_789])
    values = np.arange(16.0).reshape(2, 8)
    raw = rows.raw.encode(stamps, values)
    msg = deserialize_message(raw[1].tobytes(), JointState)
    assert list(msg.name) == device.channel_names and list(msg.position) == list(values[1])
    assert msg.header.stamp.sec == 1_700_000_000 and msg.header.stamp.nanosec == 124_456_789
    poses = np.array([[0.01, -0.02, 0.3, 0.01, -0.02, 0.3]] * 2)
    cov = np.tile(np.eye(6) * 1e-12, (2, 1, 1))
    m = deserialize_message(rows.poses(stamps, poses, cov)[0].tobytes(), PoseWithCovarianceStamped)
    assert m.header.frame_id == 'mmd_lower'
    np.testing.assert_allclose(pose_from_msg(m.pose.pose), poses[0], atol=1e-15)
    assert m.pose.covariance[0] == 1e-12
    batch = RawBatch(device.channel_names)
    for r in raw:
        batch.add(r.tobytes())
    s, v = batch.take()
    assert list(s) == list(stamps) and np.array_equal(v, values) and batch.foreign == 0
    # the stamp read straight from rclpy's own serialisation, as the lean subscriber reads it
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message

    from mmd_ros.nodes.convert import header, stamp_of_serialized
    for ns in (1_700_000_000_999_999_999, 5):
        assert stamp_of_serialized(serialize_message(PoseStamped(header=header(ns, 'mmd_lower')))) == ns
    assert stamp_of_serialized(rows.poses(stamps, poses)[1].tobytes()) == stamps[1]


def test_the_scenario_restarts_when_it_ends(device):
    twin = TwinDevice(device, Effects.ideal(), seed=5)
    src = TwinSource(twin, AmbientProfile.constant(20.0), make_scenario('hold', ['duration_s=0.7']),
                     block=64)
    t = np.concatenate([src.read(n)[0] for n in [5, 300, 1, 900, 37, 800]])
    assert src.restarts == 2 and t.size == 2043
    assert np.isfinite(src.reference_at(t[-1000:])).all()


@needs_ros
def test_sim_effects_takes_every_preset_of_the_cli(device):
    """``sim_effects:=none`` gives the twin the CLI's ``--effects none`` (no error source at all);
    every preset of the twin is a value of the parameter, and nothing else is."""
    from mmd_ros.nodes.params import check
    from mmd_ros.nodes.terminal import TERMINAL_PARAMS, TerminalConfig, TerminalStage
    from mmd_ros.twin.effects import PRESETS
    param = next(p for p in TERMINAL_PARAMS if p.name == 'sim_effects')
    assert all(check(param, name) is None for name in PRESETS) and 'none' in PRESETS
    assert 'must be one of' in check(param, 'nothing')
    values = {p.name: p.default for p in TERMINAL_PARAMS} | {'sim_effects': 'none',
                                                            'sim_scenario': 'hold'}
    stage = TerminalStage(TerminalConfig.from_values(values), device, None, None, None, None)
    assert stage.source.twin.effects == Effects.none()
    _, counts = stage.source.read(2000)
    # no read noise, no drift, a room at 20 °C: the bars held still read one count each
    assert np.ptp(counts[:, :6], axis=0).max() == 0
