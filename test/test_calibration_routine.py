"""The guided calibration routine (section 3.2, Eq. 11, quick re-reference), ROS-free.

Known truth comes from the digital twin: its bars on the reference pairs give the counts a
capture window holds, and its own calibration routine (:meth:`TwinDevice.calibrate`) is the
answer the guided routine must reproduce.
"""

from __future__ import annotations

import numpy as np
import pytest

from mmd_ros.core.calibration import Calibration
from mmd_ros.core.calibration_routine import (
    CalibrationRoutine, CaptureStats, RoutineSettings, Step, Window, bar_quality,
    capture_uncertainty,
)
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.thermal import thermal_sensitivity
from mmd_ros.twin import AmbientProfile, Effects, TwinDevice

RATE = 1000.0
WINDOW_S = 0.5


@pytest.fixture(scope='module')
def world():
    device = load_device(find_config('mmd_prototype.yaml'))
    twin = TwinDevice(device, Effects.realistic(), seed=3)
    return device, twin, AmbientProfile.constant(20.0)


class Plate:
    """Bars on reference pairs: capture windows from the twin at a running clock."""

    def __init__(self, device, twin, room, offset=None):
        self.device, self.twin, self.room = device, twin, room
        self.t = 10.0
        self.where = {c.name: c.pair for c in device.reference_channels}
        self.last = ''
        self.offset = np.zeros(8) if offset is None else np.asarray(offset, float)

    def window(self, moving: dict[str, float] | None = None, seconds: float = WINDOW_S,
               approach: float | None = None, seat: int = 0) -> Window:
        """The last placed bar seated from ``approach`` (+1 short, -1 long) at ``seat``."""
        times = self.t + np.arange(int(seconds * RATE)) / RATE
        self.t += seconds + 1.0
        counts = np.zeros((times.size, 8))
        for name, pair in self.where.items():
            k = self.device.channel_names.index(name)
            last = name == self.last
            counts[:, k] = self.twin.counts_on_pair(k, pair, times, self.room,
                                                    approach=approach if last else None,
                                                    seat=seat if last else 0)
        for name, amp_m in (moving or {}).items():
            k = self.device.channel_names.index(name)
            counts[:, k] += amp_m / self.device.encoder_resolution_m * np.sin(2 * np.pi * 2 * (times - times[0]))
        return Window.of(counts + self.offset, seconds)

    def place(self, step: Step) -> None:
        self.last = step.channel
        if step.channel not in [c.name for c in self.device.reference_channels]:
            self.where = {k: v for k, v in self.where.items()
                          if k in [c.name for c in self.device.reference_channels]}
        self.where[step.channel] = step.pair


def run_full(routine: CalibrationRoutine, plate: Plate) -> list:
    results = []
    step = routine.next_step()
    while step is not None:
        plate.place(step)
        res = routine.capture(step, plate.window(), f't{len(results)}', ambient_c=20.0)
        assert res.accepted, res.message
        results.append(res)
        step = res.next_step
    return results


def test_full_routine_matches_the_twins_own_calibration(world):
    device, twin, room = world
    routine = CalibrationRoutine(device)
    plate = Plate(device, twin, room)
    results = run_full(routine, plate)
    order = [(r.step.channel, r.step.pair) for r in results]
    schedule = [(device.channel_names[p.channel], p.pair)
                for p in twin.calibration_schedule(0.0, approaches=1)]
    # the paper's order, bar by bar, the reference bar last on dr4, after that bar read where
    # it rests (the temperature before the routine)
    assert order == schedule and order[0] == ('ref1', 'dr4') and results[0].step.kind == 'drift'
    cal = routine.calibration
    assert cal is not None and cal.valid and set(cal.bars) == set(device.channel_names[:7])
    assert [r.completed for r in results if r.completed] == device.channel_names[:7]
    assert 'Calibration complete' in results[-1].message
    truth = twin.calibrate(0.0, room, approaches=1)
    for name, bar in truth.bars.items():
        mine = cal.bars[name]
        assert mine.pairs == bar.pairs
        # the same points up to read noise averaged over a window (50 nm counts, 10 nm noise)
        q = np.linspace(min(bar.counts), max(bar.counts), 50)
        np.testing.assert_allclose(mine.cdf()(q)[0], bar.cdf()(q)[0], atol=0.05e-6)
        quality = cal.quality['bars'][name]
        assert abs(quality['scale_ppm']) < 200 and quality['nonlinearity_um'] < 10
    assert abs(cal.thermal_zero_m['ref1']) < 1e-12  # read where its last point was taken
    # the captures measured their own read noise (the twin's: 10 nm) for the uncertainty budget
    assert 5e-9 < cal.uncertainty.read_noise_m < 15e-9
    assert cal.uncertainty.capture_samples == int(WINDOW_S * RATE)
    assert cal.ambient_c == 20.0
    Pipeline(device, cal)  # a complete calibration makes a pipeline
    again = Calibration.from_yaml(cal.to_yaml())
    assert again.quality['bars']['bar3'] == cal.quality['bars']['bar3']


def test_the_one_sided_routine_reads_its_drift_from_the_reference_bar_where_it_rests(world):
    """The paper's routine with one placement per pair reads the reference bar first where it
    rests on its resting pair, as it comes: against its placement there at the end (the same
    friction state), the temperature change over the routine, in a constant room within its
    stated uncertainty."""
    device, twin, room = world
    routine = CalibrationRoutine(device)
    plate = Plate(device, twin, room)
    step, k = routine.next_step(), 0
    assert (step.kind, step.channel, step.pair, step.approach) == ('drift', 'ref1', 'dr4', '')
    while step is not None:
        plate.place(step)
        k += 1
        res = routine.capture(step, plate.window(seat=4 if k == 1 else 0),
                              f'2024-01-01T00:{k // 60:02d}:{k % 60:02d}+00:00')
        assert res.accepted, res.message
        step = res.next_step
    assert k == 1 + 7 * 7
    unc = routine.calibration.uncertainty
    assert unc.approaches == 1 and unc.routine_temp_change_c is not None
    assert abs(unc.routine_temp_change_c) < 3 * unc.routine_temp_sigma_c
    assert len(unc.drift_m['bar1']) == 7


def test_a_drift_reading_off_the_resting_pair_is_refused_or_not_taken_for_a_drift(world):
    """The drift step's reading of the reference bar is checked against its calibration (on
    another pair it is refused); with none to check it, a reading millimetres from its last
    placement there is not a temperature change and gives no drift."""
    device, twin, room = world
    plate = Plate(device, twin, room)
    elsewhere = Step('drift', 'ref1', 'dr6')       # the bar lies on dr6, the step says dr4
    first = CalibrationRoutine(device)
    step, k = first.next_step(), 0
    while step is not None:
        plate.place(elsewhere if step.kind == 'drift' else step)
        k += 1
        res = first.capture(step, plate.window(), f'2024-01-01T00:{k // 60:02d}:{k % 60:02d}+00:00')
        assert res.accepted, res.message
        step = res.next_step
    assert first.calibration.uncertainty.routine_temp_change_c is None
    again = CalibrationRoutine(device, first.calibration)
    step = again.next_step()
    plate.place(elsewhere)
    res = again.capture(step, plate.window(), 'now')
    assert not res.accepted and 'expects' in res.message and 'dr4' in res.message, res.message
    plate.place(step)
    assert again.capture(step, plate.window(), 'now').accepted


def test_a_moving_bar_and_a_wrong_pair_are_refused(world):
    device, twin, room = world
    routine = CalibrationRoutine(device)
    plate = Plate(device, twin, room)
    for _ in range(3):      # the reference bar where it rests, bar1 on dr1 and dr2
        step = routine.next_step()
        plate.place(step)
        assert routine.capture(step, plate.window(), 'now').accepted
    step = routine.next_step()
    assert (step.channel, step.pair) == ('bar1', 'dr3')
    plate.place(step)
    res = routine.capture(step, plate.window(moving={'bar1': 2e-6}), 'now')
    assert not res.accepted and 'still moving' in res.message
    assert 'Next: place bar1 on dr3' in res.message
    assert set(routine.session_points('bar1')) == {'dr1', 'dr2'}
    plate.place(Step('calibrate', 'bar1', 'dr5'))  # the operator used the wrong sockets
    res = routine.capture(step, plate.window(), 'now')
    assert not res.accepted and 'does not fit dr3' in res.message and 'dr5' in res.message
    plate.place(step)
    assert routine.capture(step, plate.window(), 'now').accepted


def test_too_few_samples_and_a_reset_window_are_refused(world):
    device, twin, room = world
    routine = CalibrationRoutine(device, settings=RoutineSettings(min_samples=100))
    plate = Plate(device, twin, room)
    step = routine.next_step()
    plate.place(step)
    w = plate.window(seconds=0.05)
    assert 'only 50 samples' in routine.capture(step, w, 'now').message
    w = plate.window()
    assert 'reset' in routine.capture(step, Window(w.counts, w.duration_s, True), 'now').message


def test_selection_override_and_thermal_zero_step(world):
    device, twin, room = world
    routine = CalibrationRoutine(device)
    plate = Plate(device, twin, room)
    with pytest.raises(CalibrationError, match='bar must be one of'):
        routine.next_step(bar='bar9')
    with pytest.raises(CalibrationError, match='pair must be one of'):
        routine.next_step(pair='dr9')
    # calibrate the reference bar alone, ending on dr7 instead of its resting pair dr4
    for pair in ['dr1', 'dr2', 'dr3', 'dr4', 'dr5', 'dr6', 'dr7']:
        step = routine.next_step(bar='ref1', pair=pair)
        assert (step.kind, step.channel, step.pair) == ('calibrate', 'ref1', pair)
        plate.place(step)
        res = routine.capture(step, plate.window(), 'now', bar='ref1')
        assert res.accepted, res.message
    assert res.completed == 'ref1' and 'back on its resting pair dr4' in res.message
    assert res.calibration is not None and 'ref1' not in res.calibration.thermal_zero_m
    step = routine.next_step()
    assert (step.kind, step.channel, step.pair) == ('thermal_zero', 'ref1', 'dr4')
    plate.place(step)
    res = routine.capture(step, plate.window(), 'later', ambient_c=21.5)
    assert res.accepted and 'thermal zero of ref1' in res.message
    assert abs(res.calibration.thermal_zero_m['ref1']) < 0.1e-6
    assert res.calibration.ambient_c == 21.5
    assert routine.next_step() == Step('calibrate', 'bar1', 'dr1')


def test_quick_re_reference_after_a_counter_reset(world):
    device, twin, room = world
    routine = CalibrationRoutine(device)
    plate = Plate(device, twin, room)
    run_full(routine, plate)
    before = routine.calibration
    lost = routine.invalidate('terminal counter reset', 'then')
    assert lost is not None and not lost.valid
    assert lost.quality['pending_re_reference'] == device.channel_names[:6] + ['ref1']
    reloaded = CalibrationRoutine(device, Calibration.from_yaml(lost.to_yaml()))
    assert reloaded.pending == routine.pending
    # the counters restarted: every channel's counts moved by an unknown offset
    offset = np.array([-5_000_000, 123_456, 7, -42, 9_999_999, 31, -2_000_000, 0], float)
    plate.offset = offset
    step = routine.next_step()
    assert (step.kind, step.channel, step.pair) == ('re_reference', 'ref1', 'dr4')
    early = Step('re_reference', 'bar2', 'dr4')
    plate.place(early)
    res = routine.capture(early, plate.window(), 'now')
    assert not res.accepted and 're-reference the reference bar ref1 first' in res.message
    while step is not None:
        plate.place(step)
        res = routine.capture(step, plate.window(), 'now')
        assert res.accepted, res.message
        step = res.next_step
    cal = routine.calibration
    assert cal.valid and not routine.pending and 'pending_re_reference' not in cal.quality
    assert 'valid again' in res.message
    for k, name in enumerate(device.channel_names[:7]):
        shift = np.array(cal.bars[name].counts) - np.array(before.bars[name].counts)
        assert np.ptp(shift) < 1e-6  # the shape is kept: one offset per bar
        assert abs(shift[0] - offset[k]) < 3.0  # the lost offset, to a few counts of noise


def test_bar_quality_of_a_straight_scale():
    from mmd_ros.core.calibration import BarCalibration
    d = np.linspace(0.25, 0.376, 7)
    bar = BarCalibration('bar1', tuple(f'dr{j}' for j in range(1, 8)), tuple(d / 50e-9), tuple(d))
    q = bar_quality(bar, 50e-9, 1e-8)
    assert q['scale_nm_per_count'] == pytest.approx(50.0)
    assert abs(q['scale_ppm']) < 1e-3 and q['nonlinearity_um'] < 1e-6 and q['noise_um'] == 0.01


def test_two_sided_routine_measures_hysteresis_seating_and_drift():
    """With approaches=2 the routine reads the reference bar on its resting pair first, from
    short and from long as it will be read there at the end, then asks for every pair twice
    (from short, from long); the points are the means, and the calibration records each bar's
    friction hysteresis (the twin's drawn one), the seating repeatability and the temperature
    drift over the routine."""
    device = load_device(find_config('mmd_prototype.yaml'))
    twin = TwinDevice(device, Effects.realistic(), seed=5)
    room = AmbientProfile.constant(20.0)
    routine = CalibrationRoutine(device, settings=RoutineSettings(approaches=2))
    plate = Plate(device, twin, room)
    ways = {'short': 1.0, 'long': -1.0}
    seated: dict[tuple[str, str], int] = {}     # each placement a seating of its own
    results, step, k = [], routine.next_step(), 0
    assert (step.kind, step.channel, step.pair, step.approach) == ('drift', 'ref1', 'dr4', 'short')
    while step is not None:
        plate.place(step)
        seat = seated.get((step.channel, step.pair), 0) + 1
        seated[(step.channel, step.pair)] = seat
        approach = ways[step.approach]
        k += 1
        window = plate.window(approach=approach, seat=seat)
        res = routine.capture(step, window, f'2024-01-01T00:{k // 60:02d}:{k % 60:02d}+00:00')
        assert res.accepted, res.message
        results.append(res)
        step = res.next_step
    assert len(results) == 2 + 7 * 7 * 2
    assert results[0].next_step.kind == 'drift' and results[0].next_step.approach == 'long'
    assert 'from short' in results[2].message and 'from long' in results[3].message
    unc = routine.calibration.uncertainty
    assert unc.approaches == 2 and unc.routine_temp_change_c is not None
    assert abs(unc.routine_temp_change_c) < 3 * unc.routine_temp_sigma_c   # a constant room
    truth = twin.physics.hysteresis_m[device.measuring_channels]
    found = np.array([unc.hysteresis_m[f'bar{i}'] for i in range(1, 7)])
    np.testing.assert_allclose(found, truth, atol=0.04e-6)
    assert 10e-9 < unc.seating_m < 60e-9


def test_the_routine_s_drift_compares_the_reference_bar_in_the_same_friction_states():
    """The temperature change over a two-sided routine is read from the reference bar on its
    resting pair from both sides before the measuring bars and again at the end: each side's
    mean, so its friction state (+-h, as large as the change itself here) cancels, and each end
    is two seatings, half the variance of one. A capture taken as it came is compared with the
    bar's last, resting placement."""
    device = load_device(find_config('mmd_prototype.yaml'))
    res = device.encoder_resolution_m
    d = device.pair('dr4').distance_m
    rate, h = -0.3 / 3600.0, 60e-9                 # a room cooling 0.3 °C/h; the bar's friction
    at = thermal_sensitivity(device, d)

    def capture(approach: str, t: float, kind: str = 'point') -> CaptureStats:
        reading = d + at * rate * t + {'short': h, 'long': -h, '': h}[approach]
        return CaptureStats('ref1', 'dr4', approach, reading / res, 1.0, 2000, t, kind)

    def read(counts):
        return np.asarray(counts, dtype=np.float64) * res, None

    points = [CaptureStats(f'bar{i}', p.name, w, p.distance_m / res, 1.0, 2000, 10.0 * k, 'point')
              for i in range(1, 7) for k, p in enumerate(device.pairs) for w in ('short', 'long')]
    ends = [capture('long', 500.0), capture('short', 505.0)]
    both = capture_uncertainty(device, points + ends + [capture('long', 0.0, 'drift'),
                                                        capture('short', 5.0, 'drift')],
                               {'ref1': read})
    assert both.routine_temp_change_c == pytest.approx(rate * (505.0 - 2.5), rel=1e-4)
    one = capture_uncertainty(device, points + ends + [capture('short', 5.0, 'drift')],
                              {'ref1': read})
    assert one.routine_temp_change_c == pytest.approx(rate * 500.0, rel=1e-4)
    # one capture at each end: twice the variance of two at each end
    assert both.routine_temp_sigma_c / one.routine_temp_sigma_c == pytest.approx(
        np.sqrt(0.5) * 502.5 / 500.0, rel=2e-3)     # (to the 1e-6 °C the file keeps)
    # each approach weighs alike, however many captures it has
    three = capture_uncertainty(device, points + ends + [capture('long', 0.0, 'drift'),
                                                         capture('long', 10.0, 'drift'),
                                                         capture('short', 5.0, 'drift')],
                                {'ref1': read})
    assert three.routine_temp_change_c == pytest.approx(rate * 500.0, rel=1e-4)
    assert three.routine_temp_sigma_c / one.routine_temp_sigma_c == pytest.approx(
        np.sqrt((0.375 + 0.5) / 2.0) * 500.0 / 497.5, rel=2e-3)
    # the start as it came (the state not known): against the bar's resting placement
    came = capture_uncertainty(device, points + ends + [capture('', 5.0, 'drift')],
                               {'ref1': read})
    assert came.routine_temp_change_c == pytest.approx(rate * 500.0, rel=1e-4)
    # the points carry the change from their capture times to the thermal zero's
    first = device.pairs[0].distance_m                   # bar1 on dr1, captured at 0 s
    assert both.drift_m['bar1'][0] == pytest.approx(
        -thermal_sensitivity(device, first) * rate * (0.0 - 505.0), rel=0, abs=1e-12)  # (file)
