"""Thermal compensation, Eqs. (11)–(13), against hand-computed cases of section 3.3."""

from __future__ import annotations

import numpy as np
import pytest

from mmd_ros.core.calibration import CentreDistanceFunction
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.thermal import CMM_TEMP_C, ReferenceBar, ThermalCompensation

DEVICE = load_device(find_config('mmd_prototype.yaml'))
TWO = load_device(find_config('mmd_two_reference_bars.yaml'))
DR = DEVICE.reference_distances_m
RES = 50e-9


def bar_counts(d, dt, *, a_r=2e-6, a_s=0.7e-6, fixed=0.25):
    """Fig. 10 bar: scale reading of a true centre distance d at a temperature change dt."""
    return np.round((d - fixed * (1 + a_r * dt)) / (1 + a_s * dt) / RES)


def make(device, channels):
    cdf = CentreDistanceFunction(bar_counts(DR, 0.0), DR)
    refs = [ReferenceBar(ch, device.pair(p).distance_m, cdf) for ch, p in channels]
    return cdf, refs


def test_sensitivity_and_paper_numbers():
    _, refs = make(DEVICE, [(6, 'dr4')])
    th = ThermalCompensation(DEVICE, refs)
    # -(2 ppm * 250 mm + 0.7 ppm * (322.9806 - 250) mm) per degree
    assert th.sensitivity_m_per_c()[0] == pytest.approx(-(2e-6 * 0.25 + 0.7e-6 * (0.3229806 - 0.25)))
    # Section 3.3: Eq. (13) leaves (376 - 323) mm x 0.7 ppm = 0.037 um per degree at the longest bar
    assert (0.376 - 0.323) * 0.7e-6 == pytest.approx(0.037e-6, abs=0.001e-6)


@pytest.mark.parametrize('dt', [-5.8, -2.0, 1.0, 3.0])
def test_eq13_residual_is_the_scale_term(dt):
    cdf, refs = make(DEVICE, [(6, 'dr4')])
    th = ThermalCompensation(DEVICE, refs, plate_expansion=False)
    d = np.array([0.2500105, 0.30, 0.3229806, 0.3760216, 0.34, 0.28])
    counts = np.zeros((1, 8))
    counts[0, :6] = bar_counts(d, dt)
    counts[0, 6] = bar_counts(DR[3], dt)
    f = cdf(counts[0, :6])[0]
    state = th.state(counts, f[None])
    corrected = f - state.bar_error_m[0]
    expected = -0.7e-6 * (d - DR[3]) * dt  # what Eq. (13) cannot remove
    assert corrected - d == pytest.approx(expected, abs=2 * RES)
    assert state.temp_change_c[0] == pytest.approx(dt, rel=0.02, abs=0.1)


@pytest.mark.parametrize('dt', [-5.8, 4.0])
def test_eq12_with_two_reference_bars_is_exact(dt):
    cdf, refs = make(TWO, [(6, 'dr1'), (7, 'dr7')])
    th = ThermalCompensation(TWO, refs, plate_expansion=False)
    assert th.mode == 'interpolate'
    d = np.array([0.26, 0.29, 0.31, 0.33, 0.35, 0.37])
    counts = np.zeros((1, 8))
    counts[0, :6] = bar_counts(d, dt)
    counts[0, 6] = bar_counts(DR[0], dt)
    counts[0, 7] = bar_counts(DR[6], dt)
    f = cdf(counts[0, :6])[0]
    corrected = f - th.state(counts, f[None]).bar_error_m[0]
    assert corrected == pytest.approx(d, abs=2 * RES)
    # Eq. (13) alone would be off by up to 0.7 ppm x 60 mm x |dt|
    eq13 = ThermalCompensation(TWO, refs[:1], plate_expansion=False)
    single = f - eq13.state(counts, f[None]).bar_error_m[0]
    assert np.max(np.abs(single - d)) > 0.5 * 0.7e-6 * 0.1 * abs(dt)


def test_plate_expansion_counts_from_the_cmm_temperature():
    _, refs = make(DEVICE, [(6, 'dr4')])
    th = ThermalCompensation(DEVICE, refs, ambient_at_zero_c=CMM_TEMP_C + 4.0)
    counts = np.zeros((1, 8))
    counts[0, 6] = bar_counts(DR[3], -2.0)
    state = th.state(counts, np.full((1, 6), 0.3))
    assert state.plate_scale[0] - 1 == pytest.approx(0.5e-6 * (4.0 - 2.0), rel=0.03)


def test_interpolate_mode_needs_two_bars():
    from mmd_ros.core.errors import ModelError
    _, refs = make(DEVICE, [(6, 'dr4')])
    with pytest.raises(ModelError, match='two reference bars'):
        ThermalCompensation(DEVICE, refs, mode='interpolate')


@pytest.mark.parametrize('room_c', [24.2, 28.0])
def test_calibrated_away_from_20c_the_pose_does_not_follow_the_bar_lengths(room_c):
    """Issue 10: the reference pairs are CMM distances at 20 °C; the bars are calibrated at the
    room's temperature, where the ZERODUR plate is a_ref (T - 20) longer. A CDF through the
    20 °C distances made every bar read short in proportion to its length, and x followed x
    (0.033 µm over 200 mm at 24.2 °C, 0.058 µm at 28 °C on this twin). Read noise large enough
    to dither the calibration averages, so that their own rounding does not hide the slope."""
    from mmd_ros.core.model import Model
    from mmd_ros.core.pipeline import Pipeline
    from mmd_ros.twin import AmbientProfile, Effects, TwinDevice, make_scenario
    twin = TwinDevice(DEVICE, Effects(read_noise_m=25e-9), seed=1)
    room = AmbientProfile.constant(room_c)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('iso_linear', ['n_cycles=1']), room, start_s=600.0,
                        sample_rate_hz=100.0)
    res = Pipeline(DEVICE, calibration, Model()).process(run.times_s, run.counts)
    x = run.true_poses[:, 0]
    err = res.poses[:, 0] - x
    slope = np.polyfit(x, err, 1)[0]
    assert abs(slope * 0.2) < 0.008e-6, slope * 0.2   # over the 200 mm of travel
