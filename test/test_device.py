"""Device description: Table 1 and 2 values, and refusal of bad files naming the key."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import yaml

from mmd_ros.core.device import find_config, load_device, parse_device
from mmd_ros.core.errors import ConfigError

PATH = find_config('mmd_prototype.yaml')
RAW = yaml.safe_load(PATH.read_text())


def test_prototype_values():
    dev = load_device(PATH)
    assert dev.geometry.upper[3] == pytest.approx(np.array([-64.2967, 76.5904, 0.0427]) * 1e-3)
    assert dev.design_geometry.lower[1] == pytest.approx(np.array([89.9903, 107.2462, 0.0]) * 1e-3)
    assert dev.reference_distances_m[3] == pytest.approx(0.3229806)
    assert dev.pair('dr4').sockets == ('R3', 'R6')
    assert dev.bar_range_m == pytest.approx((0.25, 0.376))
    assert dev.encoder_resolution_m == pytest.approx(50e-9)
    assert np.degrees(dev.upper_tilt_rad) == pytest.approx(38.58)
    assert dev.measuring_channels == [0, 1, 2, 3, 4, 5]
    assert [c.pair for c in dev.reference_channels] == ['dr4']
    assert parse_device(yaml.safe_load(dev.to_yaml())).geometry.upper == pytest.approx(dev.geometry.upper)


def test_second_reference_bar_file_inherits():
    dev = load_device(find_config('mmd_two_reference_bars.yaml'))
    assert [c.pair for c in dev.reference_channels] == ['dr1', 'dr7']
    assert dev.reference_distances_m[0] == pytest.approx(0.2500105)


def _set(data, path, value):
    node = data
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value


@pytest.mark.parametrize('path,value,key', [
    (('joints', 'upper_measured_mm'), [[1, 2, 3]] * 5, 'joints.upper_measured_mm'),
    (('joints', 'lower_design_mm'), KeyError, 'joints.lower_design_mm'),
    (('joints', 'use'), 'cad', 'joints.use'),
    (('reference_plate', 'pairs', 3, 'measured_mm'), 'x', 'reference_plate.pairs[3].measured_mm'),
    (('reference_plate', 'pairs', 2, 'measured_mm'), 279.5, 'reference_plate.pairs[2].measured_mm'),
    (('bars', 'encoder_resolution_nm'), -50, 'bars.encoder_resolution_nm'),
    (('bars', 'range_mm'), [376, 250], 'bars.range_mm'),
    (('terminal', 'channels', 6, 'pair'), 'dr9', 'terminal.channels[6].pair'),
    (('terminal', 'channels', 2, 'bar'), 1, 'terminal.channels'),
    (('terminal', 'counter_bits'), 31, 'terminal.counter_bits'),
    (('terminal', 'latch_skew_us'), -5, 'terminal.latch_skew_us'),
    (('bars', 'subdivision_error_nm'), 30, 'bars.signal_period_um'),     # a bound without its period
    (('bars', 'signal_period_um'), 20, 'bars.subdivision_error_nm'),
    (('bars', 'subdivision_error_nm'), -30, 'bars.subdivision_error_nm'),
    (('bars', 'friction_hysteresis_nm'), -10, 'bars.friction_hysteresis_nm'),
    (('bars', 'gravity_sag_nm'), -100, 'bars.gravity_sag_nm'),
    (('bars', 'gravity_sag_nm'), 'long', 'bars.gravity_sag_nm'),
    (('bars', 'gravity_sag_uncertainty_nm'), 15, 'bars.gravity_sag_uncertainty_nm'),  # no figure
    (('bars', 'drift_nm_per_h'), -20, 'bars.drift_nm_per_h'),
    (('bars', 'rod_cte_uncertainty_ppm_per_c'), -1.5, 'bars.rod_cte_uncertainty_ppm_per_c'),
    (('bars', 'rod_cte_uncertainty_ppm_per_c'), 80, 'bars.rod_cte_uncertainty_ppm_per_c'),
    (('reference_plate', 'seating_repeatability_nm'), -30,
     'reference_plate.seating_repeatability_nm'),
    (('reference_plate', 'seating_repeatability_nm'), 'x',
     'reference_plate.seating_repeatability_nm'),
    (('plates', 'vertical'), [0, 0, 0], 'plates.vertical'),
    (('plates', 'vertical'), [0, 1], 'plates.vertical'),
    (('plates', 'vertical'), 'up', 'plates.vertical'),
    (('format_version',), 2, 'format_version'),
])
def test_bad_files_are_refused_naming_the_key(path, value, key):
    data = copy.deepcopy(RAW)
    _set(data, path, value)
    with pytest.raises(ConfigError) as info:
        parse_device(data, 'bad.yaml')
    assert info.value.key == key
    assert 'bad.yaml' in str(info.value)


def test_the_vertical_as_mounted_is_stated_as_a_direction_and_level_otherwise():
    """``plates.vertical``: the upward direction in {L} as the MMD is mounted (a horizontal
    spindle puts the lower plate on its side), any length, kept as a unit vector; not stated,
    the lower plate is taken level."""
    device = parse_device(copy.deepcopy(RAW), 'level.yaml')
    assert device.vertical is None
    assert device.up.tolist() == [0.0, 0.0, 1.0]
    side = device.with_vertical([-2.0, 0.0, 2.0])
    assert side.up == pytest.approx([-math.sqrt(0.5), 0.0, math.sqrt(0.5)])
    assert parse_device(side.raw, 'again.yaml').up == pytest.approx(side.up)


def test_a_stated_sag_carries_its_uncertainty_when_stated():
    """``bars.gravity_sag_uncertainty_nm`` qualifies the stated figure: kept in metres, written
    back by ``with_gravity_sag``, refused negative; None unless stated."""
    device = parse_device(copy.deepcopy(RAW), 'plain.yaml')
    assert device.gravity_sag_m is None and device.gravity_sag_sigma_m is None
    stated = device.with_gravity_sag(100e-9, 15e-9)
    assert stated.gravity_sag_m == pytest.approx(100e-9)
    assert stated.gravity_sag_sigma_m == pytest.approx(15e-9)
    assert parse_device(stated.raw, 'again.yaml').gravity_sag_sigma_m == pytest.approx(15e-9)
    assert device.with_gravity_sag(100e-9).gravity_sag_sigma_m is None
    data = copy.deepcopy(stated.raw)
    data['bars']['gravity_sag_uncertainty_nm'] = -1
    with pytest.raises(ConfigError) as info:
        parse_device(data, 'bad.yaml')
    assert info.value.key == 'bars.gravity_sag_uncertainty_nm'


def test_a_stated_drift_rate_is_kept_per_second_and_written_back_per_hour():
    """``bars.drift_nm_per_h``: the bound on a bar's reading drift rate, kept in m/s; None
    unless stated."""
    device = parse_device(copy.deepcopy(RAW), 'plain.yaml')
    assert device.drift_m_per_s is None
    stated = device.with_reading_drift(20e-9 / 3600.0)
    assert stated.raw['bars']['drift_nm_per_h'] == pytest.approx(20.0)
    assert parse_device(stated.raw, 'again.yaml').drift_m_per_s == pytest.approx(20e-9 / 3600.0)


def test_a_stated_rod_cte_uncertainty_is_kept_per_kelvin_and_written_back_in_ppm():
    """``bars.rod_cte_uncertainty_ppm_per_c``: the standard uncertainty of the bars' effective
    rod CTE, kept in 1/°C; None unless stated."""
    device = parse_device(copy.deepcopy(RAW), 'plain.yaml')
    assert device.rod_cte_sigma_per_c is None
    stated = device.with_rod_cte_uncertainty(1.5e-6)
    assert stated.raw['bars']['rod_cte_uncertainty_ppm_per_c'] == pytest.approx(1.5)
    assert parse_device(stated.raw, 'again.yaml').rod_cte_sigma_per_c == pytest.approx(1.5e-6)


def test_a_signal_period_given_in_metres_is_caught():
    data = copy.deepcopy(RAW)
    data['bars'].update(subdivision_error_nm=30, signal_period_um=20e-6)
    with pytest.raises(ConfigError, match='in um'):
        parse_device(data, 'bad.yaml')


def test_joints_given_in_metres_are_caught():
    data = copy.deepcopy(RAW)
    data['joints']['upper_measured_mm'] = (np.array(data['joints']['upper_measured_mm']) * 1e3).tolist()
    with pytest.raises(ConfigError, match='in mm'):
        parse_device(data, 'bad.yaml')
