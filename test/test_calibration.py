"""Centre distance function, Eq. (10), and calibration files."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmd_ros.core.calibration import (
    BarCalibration, Calibration, CdfBank, CentreDistanceFunction, load_calibration,
)
from mmd_ros.core.compiled import AVAILABLE as COMPILED, NOT_IN_USE
from mmd_ros.core.errors import CalibrationError, ConfigError

TABLE2_MM = np.array([250.0105, 278.0341, 299.9308, 322.9806, 340.9278, 357.0020, 376.0216])


def counts_for(distances_mm, offset=12345, scale=1.0, sign=1):
    return offset + sign * np.round((distances_mm - 250.0) * 1e-3 / 50e-9 * scale)


@settings(max_examples=100, deadline=None)
@given(st.integers(-2**40, 2**40), st.floats(0.99, 1.01), st.sampled_from([1, -1]))
def test_cdf_maps_its_calibration_points_exactly(offset, scale, sign):
    q = counts_for(TABLE2_MM, offset, scale, sign)
    cdf = CentreDistanceFunction(q, TABLE2_MM * 1e-3)
    d, out = cdf(q)
    assert np.allclose(d, TABLE2_MM * 1e-3, rtol=0, atol=1e-15)
    assert not out.any()
    # monotonic between the points, and invertible
    dense = np.linspace(q.min(), q.max(), 1001)
    dd, _ = cdf(dense)
    assert np.all(np.diff(dd) * sign >= 0)
    assert np.allclose(cdf.inverse(dd), dense, rtol=0, atol=1e-5)


def test_cdf_interpolates_linearly_and_extrapolates_with_flag():
    q = np.array([0, 100, 300, 400, 500, 600, 700], dtype=float)
    d = np.array([250, 260, 270, 280, 290, 300, 310], dtype=float) * 1e-3
    cdf = CentreDistanceFunction(q, d)
    value, out = cdf(np.array([50.0, 200.0, -100.0, 800.0]))
    assert value == pytest.approx([0.255, 0.265, 0.240, 0.320])
    assert out.tolist() == [False, False, True, True]


def test_non_monotonic_points_are_refused_with_a_reason():
    q = counts_for(TABLE2_MM)
    q[3], q[4] = q[4], q[3]
    with pytest.raises(CalibrationError, match='not strictly monotonic'):
        CentreDistanceFunction(q, TABLE2_MM * 1e-3)
    with pytest.raises(CalibrationError, match='distinct'):
        CentreDistanceFunction([0, 1, 2], [0.25, 0.25, 0.3])


def test_cdf_bank_equals_individual_cdfs():
    rng = np.random.default_rng(1)
    cdfs = [CentreDistanceFunction(counts_for(TABLE2_MM, rng.integers(-1e6, 1e6), rng.uniform(0.99, 1.01),
                                              rng.choice([1, -1])), TABLE2_MM * 1e-3) for _ in range(6)]
    bank = CdfBank(cdfs)
    counts = np.column_stack([np.linspace(c.counts[0] - 500, c.counts[-1] + 500, 5000) for c in cdfs])
    counts[:7] = np.array([c.counts for c in cdfs]).T  # exactly on the knots
    counts[9, 2] = np.nan
    # the compiled helpers (the 1 kHz path) and numpy give the same numbers, bit for bit
    assert COMPILED, NOT_IN_USE
    for compiled in (False, True):
        d, out = bank(counts, compiled=compiled)
        for k, cdf in enumerate(cdfs):
            dk, ok = cdf(counts[:, k])
            assert np.array_equal(d[:, k], dk, equal_nan=True) and np.array_equal(out[:, k], ok)
        assert np.isnan(d[9, 2]) and not out[9, 2]
    single, _ = bank(counts[7])
    assert np.array_equal(single, d[7])


def _calibration():
    bars = {f'bar{i}': BarCalibration(f'bar{i}', tuple(f'dr{j}' for j in range(1, 8)),
                                      tuple(counts_for(TABLE2_MM, 1000 * i).tolist()),
                                      tuple((TABLE2_MM * 1e-3).tolist())) for i in range(1, 7)}
    return Calibration('mmd_prototype', bars, {'ref1': 1e-8}, 23.5, '2026-11-22T00:00:00Z')


def test_calibration_file_round_trip_backup_and_corruption(tmp_path):
    cal = _calibration()
    path = tmp_path / 'cal.yaml'
    cal.save(path)
    back = load_calibration(path)
    assert back.bars['bar3'].counts == cal.bars['bar3'].counts
    assert np.allclose(back.bars['bar3'].distances_m, cal.bars['bar3'].distances_m, rtol=0, atol=1e-15)
    assert back.thermal_zero_m['ref1'] == pytest.approx(1e-8)
    assert back.ambient_c == 23.5
    cal.save(path)
    assert (tmp_path / 'cal.yaml.bak').exists()
    path.write_text('format_version: 1\nbars: {bar1: {pairs: [dr1], counts: [1, 2]}}\n')
    with pytest.raises(ConfigError, match=str(path)):
        load_calibration(path)
    path.write_text(': : not yaml [')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_calibration(path)
