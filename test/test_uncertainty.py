"""The pose uncertainty (issue 10, section 2): the budget's formulas, and its coverage of the
twin's true pose.

A covariance is a claim about the distribution of the error. One run sees one draw of each
systematic error (a thermal zero, seven points per bar), so the coverage tests pool several
calibrations of the twin (different seeds, calibrated at different times of the room's
temperature course) and compare with the twin's true pose (not its reference instrument,
which adds its own noise).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math

import numpy as np
import pytest
from scipy.stats import chi2

from foreign_effects import sech_friction
from test_session import bench_twin_analysis
from mmd_ros.core.accuracy import coverage, pose_error
from mmd_ros.core.budget import LengthBudget, segments_seen
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import find_config, load_device, parse_device
from mmd_ros.core.model import FitUncertainty, Model, ModelUncertainty, load_model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.validity import Validity
from mmd_ros.core.uncertainty import (
    InterpolationError, NoiseEstimator, averaged_quantisation_var, capture_var, dither_var,
    fit_interpolation_error, hysteresis_claim, quantisation_cross_cov, read_noise_from_dither,
    region_quantile, tail_columns, two_sided_figures,
)
from mmd_ros.twin import Effects, TwinDevice, make_scenario
from mmd_ros.twin.recording import ambient_profile, run_log
from mmd_ros.twin.thermal import AmbientProfile, Ramp

DEVICE = load_device(find_config('mmd_prototype.yaml'))
RES = DEVICE.encoder_resolution_m
LIMIT = chi2.ppf(0.95, 6)


# -- the formulas ----------------------------------------------------------------------------
def test_averaged_quantisation_and_dither_against_a_simulation():
    """b^2 (the bias left in the mean of quantised readings) and g (the variance inside a
    window) over a uniformly unknown position within a count, against a seeded simulation."""
    rng = np.random.default_rng(0)
    assert averaged_quantisation_var(RES, 0.0) == pytest.approx(RES ** 2 / 12, rel=1e-3)
    for sigma in (0.0, 5e-9, 10e-9, 20e-9):
        x = rng.uniform(0, RES, 4000)
        reads = np.rint((x[:, None] + sigma * rng.standard_normal((4000, 400))) / RES) * RES
        bias = reads.mean(axis=1) - x      # quantisation bias and the averaging's standard error
        assert np.mean(bias ** 2) == pytest.approx(capture_var(RES, sigma, 400), rel=0.08, abs=2e-19)
        assert np.mean(reads.var(axis=1)) == pytest.approx(dither_var(RES, sigma), rel=0.08, abs=2e-19)
        assert read_noise_from_dither(RES, dither_var(RES, sigma)) == pytest.approx(sigma, abs=1e-12)
    # the correlation of two readings' biases: full at the same place, none half a count apart
    c = quantisation_cross_cov(RES, 0.0, 0.0, np.array([0.0, 0.25 * RES, 0.5 * RES]))
    assert c[0] == pytest.approx(RES ** 2 / 12, rel=0.02) and c[2] == pytest.approx(-RES ** 2 / 24, rel=0.02)


def test_noise_estimator_finds_the_read_noise_of_still_readings_and_streams_as_one_call():
    rng = np.random.default_rng(1)
    n = 64 * 200
    sigma = np.array([0.0, 5e-9, 12e-9])
    # still values (one count position per 0.5 s), and a slow thermal creep on the last column
    pos = np.repeat(rng.uniform(0, 100 * RES, (n // 512 + 1, 3)), 512, axis=0)[:n]
    pos[:, 2] += np.linspace(0, 2 * RES, n)
    values = np.rint((pos + sigma * rng.standard_normal((n, 3))) / RES) * RES
    est = NoiseEstimator(3, RES)
    whole = est.feed(values)
    final = est.sigma_m()
    assert final[0] < 1e-9 and final[1] == pytest.approx(5e-9, rel=0.25)
    assert final[2] == pytest.approx(12e-9, rel=0.2)
    assert np.all(np.isnan(whole[:64 * 19]))            # too few windows yet
    piecewise = NoiseEstimator(3, RES)
    parts = np.concatenate([piecewise.feed(values[k:k + 8]) for k in range(0, n, 8)])
    np.testing.assert_allclose(parts, whole, equal_nan=True)


def test_interpolation_error_is_zero_at_the_points_and_fitted_to_their_curvature():
    knots = np.tile(DEVICE.reference_distances_m, (7, 1))
    model = InterpolationError(1e-6, 0.03)
    v = model.variance(knots[:6].T.copy(), knots[:6])
    assert np.all(v < 1e-24)                                    # zero at the points
    mid = 0.5 * (knots[:6, :-1] + knots[:6, 1:])
    assert np.all(model.variance(mid.T.copy(), knots[:6]) > (0.1e-6) ** 2)
    # a smooth error of 1 um over the stroke: the fitted amplitude follows it, and a straight
    # line (what Eq. 10 removes exactly) is not mistaken for one
    rng = np.random.default_rng(2)
    xi = (knots - knots[:, :1]) / (knots[:, -1:] - knots[:, :1])
    wavy = 1e-6 * np.sin(2 * np.pi * 2 * xi + rng.uniform(0, 6, (7, 1)))
    fit = fit_interpolation_error(knots, wavy, np.full(knots.shape, (10e-9) ** 2))
    assert 0.4e-6 < fit.sigma_m < 3e-6
    line = fit_interpolation_error(knots, 3e-6 * xi + 1e-6, np.full(knots.shape, (10e-9) ** 2))
    assert line.sigma_m < 0.05e-6
    # the same calibration is fitted once (every budget of it asks); another is fitted anew
    again = fit_interpolation_error(knots.copy(), wavy.copy(), np.full(knots.shape, (10e-9) ** 2))
    assert again is fit
    other = wavy.copy()
    other[0, 3] += 0.5e-6
    assert fit_interpolation_error(knots, other, np.full(knots.shape, (10e-9) ** 2)) != fit


def test_two_sided_figures_from_synthetic_placements():
    rng = np.random.default_rng(3)
    h = np.array([0.2e-6, 0.4e-6])
    seat = 30e-9
    short = [rng.normal(0, seat, 7) - hh for hh in h]
    long = [rng.normal(0, seat, 7) + hh for hh in h]
    found, seating, dof = two_sided_figures(short, long, 0.0)
    np.testing.assert_allclose(found, h, atol=30e-9)
    assert dof == 12 and 15e-9 < seating < 50e-9


@pytest.mark.parametrize('uniform, gaussian, known', [(1.0, 0.0, 0.0), (1.0, 0.3, 1.0),
                                                      (0.3, 1.0, 0.5), (0.0, 1.0, 0.0)])
def test_the_region_of_bounded_errors_is_sized_by_their_form(uniform, gaussian, known):
    """Bar errors of a rectangular quantisation, a Gaussian noise and a fixed known error,
    through a Jacobian: a Gaussian's chi^2 ellipsoid holds 99.8 % of them where quantisation
    dominates; the region sized by their fourth cumulants holds 95 +- 1.5 % of the whole pose,
    of one component and of three, and is the chi^2 ellipsoid when all is Gaussian."""
    rng = np.random.default_rng(3)
    n = 100_000
    jinv = np.linalg.inv(rng.normal(size=(6, 6)) + 3.0 * np.eye(6))
    b = known * np.array([1.0, -1.0, 0.5, 0.0, 0.2, -0.3])
    bars = (uniform * math.sqrt(3.0) * rng.uniform(-1.0, 1.0, (n, 6))
            + gaussian * rng.normal(size=(n, 6)) + b)
    e = bars @ jinv.T
    cov = np.broadcast_to(jinv @ (np.eye(6) * (uniform ** 2 + gaussian ** 2) + np.outer(b, b))
                          @ jinv.T, (n, 6, 6))
    cols = tail_columns(np.broadcast_to(jinv, (n, 6, 6)), np.full((n, 6), -1.2 * uniform ** 4),
                        np.broadcast_to(b, (n, 6)), np.ones(n))
    for k in ([0, 1, 2, 3, 4, 5], [0], [0, 1, 2]):
        c, ek = cov[:, k][:, :, k], e[:, k]
        d2 = _d2(ek, c)
        q = region_quantile(c, cols[:, k])
        assert 0.935 <= np.mean(d2 <= q) <= 0.965, (k, np.mean(d2 <= q))
        if uniform == 0.0:
            np.testing.assert_allclose(q, chi2.ppf(0.95, len(k)), rtol=1e-9)
    if uniform == 1.0 and gaussian == 0.0:
        assert np.mean(_d2(e, cov) <= LIMIT) > 0.995


def test_the_hysteresis_claimed_is_what_the_bars_estimates_say_not_their_placements_scatter():
    """A two-sided calibration's h of a bar is its friction plus the mean of its seven pairs'
    seating differences: bars without friction on a plate seating within 0.3 um read 80 nm of
    it. Claimed as live friction, that over-stated every pose. Over 2000 simulated
    calibrations of six bars: without friction the claim's mean square stays below a third of
    the estimates'; with friction spread over the bars it matches the true mean square."""
    rng = np.random.default_rng(5)
    seat, pairs = 0.3e-6, 7
    v = seat ** 2 / 2.0 / pairs                      # (a half difference: seat^2 / 2 per pair)
    for spread in (0.0, 0.3e-6):
        true = spread * rng.uniform(0.5, 1.5, (2000, 6))
        found = true + rng.normal(0.0, math.sqrt(v), true.shape)
        claim = np.array([hysteresis_claim(f, v) for f in found])
        if spread:
            assert np.mean(claim ** 2) / np.mean(true ** 2) == pytest.approx(1.0, abs=0.05)
            np.testing.assert_allclose(claim, np.abs(found), rtol=0.05, atol=3 * math.sqrt(v))
        else:
            assert np.mean(found ** 2) == pytest.approx(v, rel=0.1)
            assert np.mean(claim ** 2) < v / 3.0
    # on the twin: a clean plate's loose seating, a realistic bar's friction
    twin = TwinDevice(DEVICE, Effects.ideal().with_assignments(['placement_repeatability_m=3e-7']),
                      seed=1)
    loose = twin.calibrate(0.0, ambient_profile('section_4_1'), approaches=2)
    raw = np.abs([loose.uncertainty.hysteresis_m[f'bar{i}'] for i in range(1, 7)])
    claimed = LengthBudget(twin.documented_device, loose, Model()).hysteresis_m
    print('no friction, 0.3 um seating: estimates nm', np.round(raw * 1e9),
          'claimed', np.round(claimed * 1e9))
    assert raw.max() > 50e-9 and np.all(claimed < 0.5 * raw.max())
    real = TwinDevice(DEVICE, Effects.realistic(), seed=4)
    calibration = real.calibrate(0.0, ambient_profile('section_4_1'), approaches=2)
    raw = np.abs([calibration.uncertainty.hysteresis_m[f'bar{i}'] for i in range(1, 7)])
    claimed = LengthBudget(real.documented_device, calibration, Model()).hysteresis_m
    np.testing.assert_allclose(claimed, raw, rtol=0.01)


# -- the budget and the files ----------------------------------------------------------------
@pytest.fixture(scope='module')
def realistic():
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=4)
    room = ambient_profile('section_4_1')
    calibration = twin.calibrate(0.0, room, approaches=2)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=4']), room, start_s=600.0,
                        reference='pose6')
    return twin, room, calibration, run


def test_sigma_d_is_symmetric_positive_and_shares_the_reference_bar(realistic):
    _, _, calibration, run = realistic
    pipeline = Pipeline(DEVICE, calibration)
    res = pipeline.process(run.times_s, run.counts, with_covariance=True)
    comp, th = res.compensated, res.compensated.thermal
    budget = pipeline.budget
    sigma_d = budget.covariance(comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m)
    assert np.allclose(sigma_d, np.swapaxes(sigma_d, 1, 2))
    assert np.all(np.linalg.eigvalsh(sigma_d) > 0)
    parts = budget.variances(comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m)
    ref = parts['reference_bar']
    assert np.allclose(ref, ref[:, :1, :1])                   # Eq. (13): the same for every pair
    assert np.count_nonzero(parts['quantisation'] - np.diag(np.diag(parts['quantisation'][0]))) == 0
    assert {'interpolation', 'calibration_points', 'hysteresis', 'calibration_drift',
            'thermal_mismatch'} <= set(parts)
    assert np.all(np.isfinite(res.covariance[res.valid]))
    summary = budget.summary()
    assert summary['hysteresis_nm'][0] > 100 and summary['interpolation']['sigma_um'] > 0.2
    json.dumps(summary)


def test_latch_skew_is_sized_from_the_terminal_s_stated_bound(realistic):
    """Channels latched at unknown delays in [0, tau] (the datasheet's bound): a bar moving at v
    reads v tau / 2 long on average (a known error shared through the speeds) and scatters by
    v tau / sqrt(12) on its own; v from the stream. Off when the device does not state tau
    (a note says so) and when the model compensates the skew."""
    from mmd_ros.core.terms import SamplingSkewTerm
    twin, _, calibration, run = realistic
    assert twin.documented_device.latch_skew_s == pytest.approx(50e-6)   # the twin's datasheet
    tau = 40e-6
    device = DEVICE.with_latch_skew(tau)
    assert device.latch_skew_s == pytest.approx(tau) and 'latch_skew_us: 40' in device.to_yaml()
    pipeline = Pipeline(device, calibration)
    comp = pipeline.compensate(run.times_s, run.counts)
    th = comp.thermal
    budget = pipeline.budget
    observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s)
    v = np.diff(comp.cdf_lengths_m, axis=0) / np.diff(run.times_s)[:, None]
    np.testing.assert_allclose(observed.velocity_m_s[1:], v, atol=1e-12)
    assert np.max(np.abs(v)) > 1e-4                         # the bars do move (> 0.1 mm/s)
    parts = budget.variances(comp.lengths_m, th.reference_error_m, th.temp_change_c,
                             th.bar_error_m, observed=observed)
    vv = observed.velocity_m_s[:, :, None] * observed.velocity_m_s[:, None, :]
    expected = tau ** 2 / 4 * vv + tau ** 2 / 12 * vv * np.eye(6)
    np.testing.assert_allclose(parts['latch_skew'], expected, rtol=1e-9, atol=1e-30)
    # one stream in pieces gives the same speeds as the whole run
    budget.reset()
    pieces = [budget.observe(comp.cdf_lengths_m[s], th.reference_error_m[s], run.times_s[s])
              for s in (slice(0, 7), slice(7, 300), slice(300, None))]
    np.testing.assert_allclose(np.concatenate([p.velocity_m_s for p in pieces]),
                               observed.velocity_m_s)
    unstated = LengthBudget(DEVICE, calibration, Model())
    assert unstated.latch_skew_s == 0 and any('latch skew' in n for n in unstated.notes)
    fitted = LengthBudget(device, calibration, Model(terms=[SamplingSkewTerm(np.zeros(6))]))
    assert fitted.latch_skew_s == 0


def test_the_encoders_sub_division_error_is_sized_from_their_stated_bound(realistic):
    """The encoders' sub-divisional error, a sine of amplitude a (the datasheet's bound) and
    unknown phase within each signal period: the live count reads e(q), and Eq. (10) carries
    the error its two calibration points read, (1 - u) e(q_j) + u e(q_j+1), at phases as good
    as independent: a^2 / 2 (1 + (1 - u)^2 + u^2) per bar. The reference bar's error moves by
    a^2 (1 - cos(2 pi eps / period)) from its thermal zero, the same for every bar (Eq. 13).
    A term at the signal period or a harmonic of it compensates its mean square (what it
    leaves stays claimed); a fit's residual of every bar replaces it."""
    from mmd_ros.core.terms import CyclicErrorTerm
    twin, _, calibration, run = realistic
    stated = twin.documented_device                # the twin's datasheet: its effects' figures
    assert stated.subdivision_error_m == pytest.approx(20e-9)
    assert stated.signal_period_m == pytest.approx(20e-6)
    a, period = 80e-9, 13e-6
    device = DEVICE.with_subdivision_error(a, period)
    assert 'subdivision_error_nm: 80' in device.to_yaml() and 'signal_period_um: 13' in device.to_yaml()
    comp = Pipeline(device, calibration).compensate(run.times_s, run.counts)
    th = comp.thermal
    x = comp.lengths_m

    def parts_of(model, dev=device):
        budget = LengthBudget(dev, calibration, model)
        return budget, budget.variances(x, th.reference_error_m, th.temp_change_c, th.bar_error_m)

    budget, parts = parts_of(Model())
    knots = budget.knots_m
    u = np.empty_like(x)
    for i, kn in enumerate(knots):
        j = np.clip(np.searchsorted(kn, x[:, i]) - 1, 0, kn.size - 2)
        u[:, i] = (x[:, i] - kn[j]) / (kn[j + 1] - kn[j])
    expected = a * a / 2 * (1 + (1 - u) ** 2 + u ** 2)
    np.testing.assert_allclose(parts['subdivision'], expected[:, :, None] * np.eye(6), rtol=1e-3, atol=1e-30)
    _, unstated = parts_of(Model(), DEVICE)
    eps = th.reference_error_m[:, 0]
    np.testing.assert_allclose(budget._reference_subdivision(np.array([0.0, period / 2, period])),
                               [0.0, 2 * a * a, 0.0], atol=1e-30)   # zero at its zero, 2 a^2 half a period off
    np.testing.assert_allclose(parts['reference_bar'] - unstated['reference_bar'],
                               (a * a * (1 - np.cos(2 * np.pi * eps / period)))[:, None, None]
                               * np.ones((6, 6)), rtol=1e-9, atol=1e-30)
    assert 'subdivision' not in unstated and any('sub-division' in n for n in LengthBudget(
        DEVICE, calibration, Model()).notes)
    # the streaming sum equals the sum of the sources
    np.testing.assert_allclose(budget.covariance(x, th.reference_error_m, th.temp_change_c, th.bar_error_m),
                               budget._covariance_by_sources(x, th.reference_error_m, th.temp_change_c,
                                                             th.bar_error_m, None, None),
                               rtol=1e-9, atol=1e-24)
    # a term at the signal period compensates what it fitted: the full sine on bars 1-3, half
    # the amplitude on bars 4-6 (three quarters of the mean square left there); the reference
    # bar's stays
    amp = np.r_[a, a, a, a / 2, a / 2, a / 2]
    ph = np.linspace(0, 3, 6)
    term = CyclicErrorTerm(period, RES, DEVICE.measuring_channels, np.zeros(6), amp * np.cos(ph), amp * np.sin(ph))
    _, compensated = parts_of(Model(terms=[term]))
    left = compensated['subdivision'][:, range(6), range(6)] / parts['subdivision'][:, range(6), range(6)]
    np.testing.assert_allclose(left, np.broadcast_to([0, 0, 0, 0.75, 0.75, 0.75], left.shape), atol=1e-9)
    np.testing.assert_allclose(compensated['reference_bar'], parts['reference_bar'])
    # ... so does one at its second harmonic (an encoder's error has both)
    half = CyclicErrorTerm(period / 2, RES, DEVICE.measuring_channels, np.zeros(6), np.full(6, a), np.zeros(6))
    assert 'subdivision' not in parts_of(Model(terms=[half]))[1]
    # ... but a term at another period compensates another effect: the encoders' error stays
    other = CyclicErrorTerm(0.7 * period, RES, DEVICE.measuring_channels, np.zeros(6), np.full(6, a), np.zeros(6))
    np.testing.assert_allclose(parts_of(Model(terms=[other]))[1]['subdivision'], parts['subdivision'])
    # a residual of every bar measured it
    fit = FitUncertainty(residual_m2=np.eye(6) * 1e-16, replaces=('subdivision',))
    _, replaced = parts_of(Model(uncertainty=ModelUncertainty(fit=fit)))
    assert 'subdivision' not in replaced


def test_a_fit_s_residual_stands_only_where_the_fit_saw_the_bars(realistic):
    """A fit whose residual replaced the calibration-derived sources: inside the lengths it saw
    (its validity record) they are gone, and where those lengths end inside a CDF segment
    (the model has a length term) what its residual held there beyond the claim stands for
    them; a bar outside gets them back, and beyond the lengths seen the square
    of how far the length terms' correction moved from its value at the nearest
    length the fit saw (an extrapolation no data checked). A friction term does not know a
    bar's state before it has moved: the budget keeps h^2 / 3 for it (a state anywhere in
    [-1, 1]), decaying as exp(-2 path / travel), without bias."""
    from mmd_ros.core.model import FIT_REPLACEABLE, HysteresisTerm
    from mmd_ros.core.terms import ScaleNonlinearityTerm
    _, _, calibration, run = realistic
    comp = Pipeline(DEVICE, calibration).compensate(run.times_s, run.counts)
    th = comp.thermal
    x = comp.lengths_m
    mid = np.median(comp.cdf_lengths_m, axis=0)
    knots = np.sort(np.array([calibration.bars[n].distances_m for n in ('bar1', 'bar2', 'bar3',
                                                                         'bar4', 'bar5', 'bar6')]))
    term = ScaleNonlinearityTerm(knots, np.full((6, 2), 0.3e-6), np.full((6, 2), -0.2e-6))
    flank_m2 = (np.arange(1.0, 7.0) * 20e-9) ** 2
    fit = FitUncertainty(np.zeros((6, 6)), tuple(FIT_REPLACEABLE), 1.0, [], np.zeros((6, 6)), {},
                         flank_m2=flank_m2)
    ranges = [[(m - 1e-3) / 1e-3, (m + 1e6) / 1e-3] for m in mid]    # bar i seen above its median
    hyst = HysteresisTerm(np.full(6, 0.2e-6), 1e-6)
    model = Model(terms=[term, hyst], uncertainty=ModelUncertainty(fit=fit),
                  extra={'validity': {'bar_range_mm': ranges}})
    budget = LengthBudget(DEVICE, calibration, model)
    observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s)
    parts = budget.variances(x, th.reference_error_m, th.temp_change_c, th.bar_error_m,
                             observed=observed)
    # the residual stands from the first CDF point whose segment's middle the fit saw, the
    # extrapolation claim from the lowest length it saw
    lowest = mid - 1e-3

    def first_checked(kn, lo):
        j = np.searchsorted(kn, lo, side='right') - 1    # the segment the lowest length is in
        return lo if j < 0 or 0.5 * (kn[j] + kn[j + 1]) >= lo else kn[j + 1]

    checked = np.array([first_checked(kn, lo) for kn, lo in zip(knots, lowest)])
    np.testing.assert_allclose(segments_seen(knots, np.array(ranges) * 1e-3)[:, 0], checked)
    assert np.any(checked > lowest)              # a segment seen short of its middle
    unchecked_part = comp.cdf_lengths_m < checked[None]
    assert unchecked_part.any() and (~unchecked_part).any()
    # the calibration's sources come back below the lowest length the fit saw (its residual
    # checked the error down to it, in a segment whose middle it did not see too) ...
    below = comp.cdf_lengths_m < lowest[None]
    assert below.any() and np.any(~below & unchecked_part)
    interp = parts['interpolation'][:, range(6), range(6)]
    assert np.all(interp[below] > 0) and np.all(interp[~below] == 0)
    # ... gradually: the share 1 - rho^2 of the interpolation error's variance that its value
    # at the bound leaves unknown a distance delta further (rho its own correlation)
    delta = lowest[None] - (x + th.bar_error_m)
    rho = budget.interpolation.correlation(delta[below])
    full = budget.interpolation.variance(x, budget.knots_m)[below]
    np.testing.assert_allclose(interp[below], full * (1.0 - rho ** 2), rtol=0.02,
                               atol=1e-4 * full.max())
    assert np.all(rho > 0.0) and np.all(rho < 1.0)
    unchecked = parts['unchecked_range'][:, range(6), range(6)]
    from mmd_ros.core.model import TermContext
    n = x.shape[0]
    cdf = x + th.bar_error_m
    edge = np.maximum(cdf, lowest[None])
    c = (term.correction(TermContext(np.zeros(n), np.zeros((n, 8)), x, cdf, th.reference_error_m,
                                     th.temp_change_c))
         - term.correction(TermContext(np.zeros(n), np.zeros((n, 8)), x, edge,
                                       th.reference_error_m, th.temp_change_c)))
    # and beyond the lengths the fit saw, the size of what the term corrected within them
    # (beyond a straight line): its shape beyond them is not known ...
    spread = np.empty(6)
    for i, (kn, lo) in enumerate(zip(knots, lowest)):
        g = np.linspace(lo, kn[-1], 1001)
        lengths = np.repeat(g[:, None], 6, axis=1)
        ci = term.correction(TermContext(np.zeros(g.size), np.zeros((g.size, 8)), lengths, lengths,
                                         np.zeros((g.size, 1)), np.zeros(g.size)))[:, i]
        spread[i] = np.mean((ci - np.polyval(np.polyfit(g, ci, 1), g)) ** 2)
    assert np.all(spread > 0)
    # within the lengths the fit saw, short of the first segment whose middle it saw: what its
    # residual showed there beyond the model's claim
    flank = ~below & unchecked_part
    assert flank.any()
    np.testing.assert_array_equal(budget.flank(cdf), flank)
    # ... whose share left unknown grows with the distance beyond: 1 - rho^2, as for the
    # calibration's sources (the error is continuous, and the residual checked it at the bound)
    rho_below = budget.interpolation.correlation(np.maximum(lowest[None] - cdf, 0.0))
    # (beyond the bound, what it claims beyond the unchecked points' own claim there: the two
    # describe one error, and the larger is claimed)
    points = parts['calibration_points'][:, range(6), range(6)]
    # (how far the correction moved, or, where larger, how far it moved from its continuation:
    # the conditional mean, given its values at 41 lengths within those seen, of a Gaussian
    # process of the interpolation's covariance and the points' own errors about a level)
    from mmd_ros.core.uncertainty import hat_weights
    gap = np.zeros_like(c)
    for i, (kn, lo) in enumerate(zip(knots, lowest)):
        at = np.linspace(lo, kn[-1], 41)
        lengths = np.repeat(at[:, None], 6, axis=1)
        seen = term.correction(TermContext(np.zeros(41), np.zeros((41, 8)), lengths, lengths,
                                           np.zeros((41, 1)), np.zeros(41)))[:, i]

        def prior(a, b):
            return (budget.interpolation.covariance(a, b, kn) + hat_weights(a, kn)
                    @ np.diag(np.full(kn.size, budget.point_nugget_m2[i])) @ hat_weights(b, kn).T)

        k_inv = np.linalg.inv(prior(at, at) + 1e-18 * np.eye(41))
        level = k_inv.sum(axis=0) @ seen / k_inv.sum()
        weights = k_inv @ (seen - level)
        mean = prior(cdf[:, i], at) @ weights - prior(edge[:, i], at) @ weights
        gap[:, i] = c[:, i] - mean
    moved = (np.maximum(c ** 2, gap ** 2) + spread[None] * (1.0 - rho_below ** 2)) * below
    assert np.any(gap[below] ** 2 > 1.5 * c[below] ** 2)     # (here the continuation counts)
    expected = np.maximum(moved - points, 0.0) * below + flank_m2 * flank
    # (the difference of two claims: within 3 % of their sum)
    assert np.all(np.abs(unchecked - expected)
                  <= 0.03 * (moved + points * below + expected) + 1e-4 * float(spread.max()))
    assert np.any(points[below] > 0) and np.any(unchecked[below] > 0)
    assert np.all(unchecked[~below & ~flank] == 0)
    # the friction state before a bar's first move: h^2 / 3, no known error; forgotten at
    # exp(-2 path / travel) as the bar moves
    h = parts['hysteresis'][:, range(6), range(6)]
    assert np.allclose(h[0], 0.2e-6 ** 2 / 3) and np.all(h >= 0) and np.all(h[-1] < 1e-3 * h[0])
    assert 'hysteresis' not in budget.sources(x, th.reference_error_m, th.temp_change_c,
                                              th.bar_error_m, observed=observed)[1]
    # the streaming sum equals the sum of the sources
    total = budget.covariance(x, th.reference_error_m, th.temp_change_c, th.bar_error_m,
                              observed=observed)
    np.testing.assert_allclose(total, budget._covariance_by_sources(
        x, th.reference_error_m, th.temp_change_c, th.bar_error_m, None, observed), rtol=1e-9,
        atol=1e-24)


def test_old_files_and_the_default_model_still_give_a_budget(realistic, tmp_path):
    _, _, calibration, run = realistic
    data = calibration.to_dict()
    del data['uncertainty']
    old = Calibration.from_dict(data)
    path = tmp_path / 'model.yaml'
    path.write_text('format_version: 1\nlength_sigma_um: 0.4\n')
    budget = LengthBudget(DEVICE, old, load_model(path))
    assert any('read noise' in note for note in budget.notes)
    assert budget.point_var_m2 == pytest.approx(RES ** 2 / 12, rel=1e-3)  # no dither known
    res = Pipeline(DEVICE, old, load_model(path)).process(run.times_s, run.counts, with_covariance=True)
    assert np.all(np.linalg.eigvalsh(res.covariance[res.valid]) > 0)
    assert 'length_sigma_um' not in load_model(path).to_yaml()


def test_a_fit_section_round_trips_and_its_directions_enter_every_sample(realistic, tmp_path):
    """One sigma of a fitted term along a direction, written as that term, adds c c^T per
    sample, and the mean of the directions not written (``rest_terms_nm2``) with it; the
    residual adds R; all survive the model file."""
    from mmd_ros.core.terms import SamplingSkewTerm
    _, _, calibration, run = realistic
    rest = np.full((6, 6), 0.3e-18) + np.eye(6) * 2e-18
    fit = FitUncertainty(residual_m2=np.eye(6) * (50e-9) ** 2, replaces=('interpolation',),
                         directions=[[SamplingSkewTerm(np.full(6, 5e-6))]],
                         mean_terms_m2=np.eye(6) * 1e-18, flank_m2=np.full(6, (70e-9) ** 2),
                         rest_terms_m2=rest)
    model = Model(uncertainty=ModelUncertainty(fit=fit))
    back = load_model(model.save(tmp_path / 'm.yaml'))
    assert back.uncertainty.fit.replaces == ('interpolation',)
    np.testing.assert_allclose(back.uncertainty.fit.residual_m2, fit.residual_m2)
    np.testing.assert_allclose(back.uncertainty.fit.flank_m2, fit.flank_m2)
    np.testing.assert_allclose(back.uncertainty.fit.rest_terms_m2, rest)
    p = Pipeline(DEVICE, calibration, back)
    res = p.process(run.times_s, run.counts, with_covariance=True)
    comp = res.compensated
    velocity = np.diff(comp.cdf_lengths_m, axis=0, prepend=comp.cdf_lengths_m[:1]) / 1e-3
    np.testing.assert_allclose(comp.fit_columns_m[:, :, 0], -5e-6 * velocity, atol=1e-12)
    parts = p.budget.variances(comp.lengths_m, comp.thermal.reference_error_m,
                               comp.thermal.temp_change_c, comp.thermal.bar_error_m,
                               comp.fit_columns_m)
    assert 'interpolation' not in parts and 'residual' in parts
    np.testing.assert_allclose(parts['fitted_terms'][:, 0, 0], comp.fit_columns_m[:, 0, 0] ** 2
                               + rest[0, 0])
    np.testing.assert_allclose(parts['fitted_terms'][:, 0, 1], comp.fit_columns_m[:, 0, 0]
                               * comp.fit_columns_m[:, 1, 0] + rest[0, 1])
    # the streaming sum holds it too
    without = FitUncertainty(**{**fit.__dict__, 'rest_terms_m2': np.zeros((6, 6))})
    args = (comp.lengths_m, comp.thermal.reference_error_m, comp.thermal.temp_change_c,
            comp.thermal.bar_error_m, comp.fit_columns_m)
    total, other = (LengthBudget(DEVICE, calibration, Model(uncertainty=ModelUncertainty(fit=f)))
                    .covariance(*args) for f in (fit, without))
    np.testing.assert_allclose(total - other, np.broadcast_to(rest, total.shape), atol=1e-24)


# -- coverage of the twin's true pose -----------------------------------------------------------
def _pooled(effects: Effects, ambient: str, k_runs: int, seconds: float = 5.0, approaches: int = 2,
            device=None, region: bool = False, lengths: bool = False):
    """Errors against the twin's true pose and covariances of several calibrations (the
    pipeline given ``device``, else the twin's documented description): predicted / observed
    sigma per axis and the share in the 95 % ellipsoid; with ``region`` also the share in the
    budget's own 95 % region (the ellipsoid sized by its sources' forms); with ``lengths``
    the six bars' lengths and their covariance against the true ones instead of the pose."""
    errors, covs, tails = [], [], []
    for k in range(k_runs):
        twin = TwinDevice(DEVICE, effects, seed=k + 1)
        room = ambient_profile(ambient)
        calibration = twin.calibrate(-211.0 * k, room, approaches=approaches)
        run = twin.simulate(make_scenario('random_motion', [f'duration_s={seconds}', f'seed={k}']),
                            room, start_s=600.0, reference='pose6')
        res = Pipeline(device or twin.documented_device, calibration).process(
            run.times_s, run.counts, with_covariance=True, tails_every=int(region),
            with_length_covariance=lengths)
        ok = res.valid
        if lengths:
            errors.append((res.compensated.lengths_m - run.true_lengths)[ok])
            covs.append(res.length_covariance[ok])
        else:
            errors.append(pose_error(res.poses, run.true_poses)[ok])
            covs.append(res.covariance[ok])
        tails.append(None if res.tails is None else res.tails[ok])
    e, c = np.concatenate(errors), np.concatenate(covs)
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0)) / np.sqrt(np.mean(e * e, axis=0))
    d2 = _d2(e, c)
    if not region:
        return ratio, float(np.mean(d2 <= LIMIT))
    q = region_quantile(c, np.concatenate(tails))
    return ratio, float(np.mean(d2 <= LIMIT)), float(np.mean(d2 <= q))


def test_clean_twin_is_covered():
    """`--effects ideal` (quantisation, 5 nm read noise, the room cooling during the routine):
    predicted / observed sigma within 0.8-1.25 on every axis. A Gaussian's 95 % ellipsoid
    covers more than 95 %: quantisation errors are bounded (uniform), not Gaussian; the
    budget's own 95 % region, sized by its sources' forms, covers less, and still 95 %
    (bench_uncertainty.py, 24 calibrations: 98.8 % and 97.6 %)."""
    ratio, cover, region = _pooled(Effects.ideal(), 'section_4_1', 6, seconds=4.0, region=True)
    print('ideal: ratio', np.round(ratio, 2), 'ellipsoid', cover, 'region', region)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert 0.95 <= region < cover - 0.005, (region, cover)


def test_twin_without_any_effect_is_covered():
    """`--effects ideal --effect read_noise_m=0 --ambient constant:20`. Every error is a count's
    quantisation. The budget over-states by the calibration points' quantisation, which this
    twin does not have: at exactly 20 °C and without noise every Table 2 distance (0.1 um
    digits = 2 counts) falls on a count. The z axis, dominated by the few common-mode terms,
    reads up to 1.4."""
    ratio, cover = _pooled(Effects.ideal().with_assignments(['read_noise_m=0']), 'constant:20', 3)
    assert np.all(ratio > 0.8), ratio
    assert np.all(ratio[[0, 1, 3, 4, 5]] < 1.25) and ratio[2] < 1.4, ratio
    assert cover >= 0.93


def test_realistic_twin_is_covered():
    """`--effects realistic`: the budget sizes hysteresis and seating (two-sided calibration),
    the interpolation error (fitted to the points), the routine's drift, the thermal mismatch
    (section 4.1), and the channels' latch skew from the terminal's stated bound (its
    datasheet; each channel's own delay stays hidden) times each bar's speed in the stream."""
    ratio, cover, region = _pooled(Effects.realistic(), 'section_4_1', 8, seconds=3.0, region=True)
    print('realistic: ratio', np.round(ratio, 2), 'ellipsoid', cover, 'region', region)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert cover >= 0.93, cover
    assert 0.93 <= region < cover, (region, cover)


def test_the_bars_lengths_are_covered():
    """What a log with reference bar lengths judges (``mmd process``'s
    ``length_uncertainty_coverage``): the six bars' length covariance Sigma_d against their true
    lengths, before the pose covariance propagates it; `--effects realistic`, 24 calibrations
    (a bar's ratio over fewer is one bar's few draws of the calibration's systematic errors:
    0.76 on one bar over 8). bench_uncertainty.py --lengths: ideal 0.91-1.00, 98.8 % (12
    calibrations); realistic 0.87-1.02, 97.5 % (24); after mmd analyze 1.01-1.17, 95.8 % (12)."""
    ratio, cover = _pooled(Effects.realistic(), 'section_4_1', 24, seconds=2.0, lengths=True)
    print('realistic lengths: ratio', np.round(ratio, 2), 'ellipsoid', cover)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert 0.93 <= cover <= 0.995, cover


def _one_sided_fit_and_new_motion(k: int, datum: str):
    """Realistic twin ``k`` calibrated with the paper's one-sided routine, ``mmd analyze`` of
    60 s of its random motion (``datum`` 'offset' zeroed, 'none' absolute), and 8 s of new
    motion processed with the model: (model, run, result with pose and length covariances)."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    room = ambient_profile('section_4_1')
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=k + 1)
    calibration = twin.calibrate(-211.0 * k, room, approaches=1)
    fitted = twin.simulate(make_scenario('random_motion', ['duration_s=60', f'seed={100 + k}']),
                           room, start_s=600.0, reference='pose6')
    model = analyze(run_log(twin, calibration, fitted, 600.0),
                    options=AnalysisOptions(datum=datum)).model
    run = twin.simulate(make_scenario('random_motion', ['duration_s=8', f'seed={k}']), room,
                        start_s=700.0, reference='pose6')
    res = Pipeline(twin.documented_device, calibration, model).process(
        run.times_s, run.counts, with_covariance=True, with_length_covariance=True)
    return model, run, res


def test_after_a_one_sided_routine_a_bar_beyond_the_fitted_lengths_is_claimed_as_it_grows():
    """Two realistic twins calibrated with the paper's one-sided routine, ``mmd analyze``'s
    zeroed fit of 60 s of random motion, new motion's samples with a bar beyond the
    lengths the fit saw (8 s, 423 and 800 of them). What the length terms corrected within those
    lengths was claimed whole from the bound on (a one-sided routine's points carry friction
    steps, which no smooth correlation carries), while the points a ``cdf_offsets`` term held
    at zero just beyond the bound counted as checked: measured 3.7-7.4 and 2.3-5.1 times the
    error. Those points now count as unchecked (the points' own source, their friction among
    it, comes back for them) and the rest of that claim grows from the bound as after a
    two-sided routine: 1.1-4.0 and 1.5-3.8 (24 twins: all samples beyond 1.47-2.21 -> 1.23-1.90,
    98.8 % -> 98.4 % in the 95 % ellipsoid; inside the fitted lengths unchanged)."""
    for k in (1, 3):
        model, run, res = _one_sided_fit_and_new_motion(k, 'offset')
        seen, cdf = Validity.from_model(model).bar_range_m, res.compensated.cdf_lengths_m
        out = res.valid & ~np.all((cdf >= seen[:, 0]) & (cdf <= seen[:, 1]), axis=1)
        ratio, covered = _judged(pose_error(res.poses, run.true_poses)[out], res.covariance[out])
        print(k, out.sum(), 'ratio', np.round(ratio, 2), 'coverage', round(covered, 3))
        assert out.sum() > 300 and covered >= 0.93
        assert np.max(ratio) < 4.5 and np.median(ratio) < 3.0, ratio


def test_beyond_the_fitted_lengths_the_correction_is_claimed_against_its_own_continuation():
    """A realistic twin calibrated one-sided, ``mmd analyze``'s absolute fit of 60 s of random
    motion; on new motion its bar 6 runs to 20 mm past the lengths the fit saw (358.1 mm, 1.1
    mm past a CDF point; the next at 376.0). Within them the length terms' correction bends
    down towards the bound; beyond it, the points' correction is held (the point no data saw
    at zero) and the bar's error goes on as its smooth error would: 347 nm RMS more than 3 mm
    past the bound, which the claim of how far the correction moved from the bound put at 104
    nm (no sample of the bar within 1.96 sigma; 13.1 % of the samples beyond in the pose's 95 %
    ellipsoid). The correction within the lengths seen, continued as the error the
    calibration's points were fitted with would continue it (the interpolation's Gaussian
    process about a level of its own, conditioned on it), is now claimed against what the terms
    apply there: 255 nm, every sample of the bar within 1.96 sigma, 98.9 % of the pose's in the
    ellipsoid."""
    model, run, res = _one_sided_fit_and_new_motion(3, 'none')
    seen, cdf = Validity.from_model(model).bar_range_m, res.compensated.cdf_lengths_m
    beyond = np.maximum(seen[:, 0] - cdf, cdf - seen[:, 1])
    out = res.valid & np.any(beyond > 0.0, axis=1)
    covered = float(np.mean(_d2(pose_error(res.poses, run.true_poses)[out],
                                res.covariance[out]) <= LIMIT))
    far = res.valid & (beyond[:, 5] > 3e-3)
    error = (res.compensated.lengths_m - run.true_lengths)[far, 5]
    sigma = np.sqrt(res.length_covariance[far, 5, 5])
    print('beyond', out.sum(), 'covered', round(covered, 3), 'bar 6 far', far.sum(), 'error',
          round(float(np.sqrt(np.mean(error ** 2))) * 1e9), 'claim',
          round(float(np.sqrt(np.mean(sigma ** 2))) * 1e9))
    assert far.sum() > 300 and np.sqrt(np.mean(error ** 2)) > 0.2e-6     # (the case is there)
    assert np.mean(np.abs(error) <= 1.96 * sigma) >= 0.9
    assert np.sqrt(np.mean(sigma ** 2)) < 2.0 * np.sqrt(np.mean(error ** 2))
    assert covered >= 0.93


def test_the_paper_s_one_sided_routine_is_covered_with_the_bars_stated_friction():
    """The paper's routine places each bar once on each pair: every point carries the
    friction state the bar was seated in (+-h, its sign unknown), and nothing of the routine
    measures h. From the bars' stated friction (``bars.friction_hysteresis_nm``, which the
    simulated bars state) the budget claims h^2 per point and the live friction; 12 twins in
    bench_uncertainty.py --approaches 1: 97.4 % (58.4 % with neither claimed, 66.6 % with the
    live part only); these 8 twins 95.6 %, 67.1 % with nothing stated. Without the statement
    the budget says what it does not claim."""
    ratio, cover = _pooled(Effects.realistic(), 'section_4_1', 8, seconds=3.0, approaches=1)
    print('one-sided, friction stated: ratio', np.round(ratio, 2), 'coverage', cover)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert 0.93 <= cover, cover
    unstated = TwinDevice(DEVICE, Effects.realistic(), seed=1).documented_device
    raw = copy.deepcopy(unstated.raw)
    del raw['bars']['friction_hysteresis_nm']
    unstated = parse_device(raw, 'test')
    ratio, cover = _pooled(Effects.realistic(), 'section_4_1', 8, seconds=3.0, approaches=1,
                           device=unstated)
    print('one-sided, nothing stated: ratio', np.round(ratio, 2), 'coverage', cover)
    assert cover < 0.8, cover
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=1)
    calibration = twin.calibrate(0.0, ambient_profile('section_4_1'), approaches=1)
    h = twin.documented_device.friction_hysteresis_m
    assert h == pytest.approx(0.3e-6 * math.sqrt(13.0 / 12.0), rel=1e-6)
    budget = LengthBudget(twin.documented_device, calibration, Model())
    np.testing.assert_allclose(budget.point_friction_m2, h * h)
    assert budget.summary()['calibration_point_friction_nm'] == [round(h * 1e9, 2)] * 6
    # at a point, its own variance and its friction state; none for a two-sided point
    x = budget.knots_m[:, 2][None, :]
    refs = np.zeros((1, len(DEVICE.reference_channels)))
    points = budget.variances(x, refs, np.zeros(1))['calibration_points']
    np.testing.assert_allclose(np.diagonal(points[0]), budget.point_var_m2 + h * h,
                               rtol=2e-3)      # (read from its table)
    blind = LengthBudget(unstated, calibration, Model())
    assert not np.any(blind.point_friction_m2)
    assert any('friction state each point was captured in' in n for n in blind.notes)
    two_sided = LengthBudget(twin.documented_device, twin.calibrate(0.0, ambient_profile(
        'section_4_1'), approaches=2), Model())
    assert not np.any(two_sided.point_friction_m2)


def test_a_fitted_friction_amplitude_replaces_the_type_s_stated_figure():
    """A friction term fitted on the device measured each bar's own amplitude; the budget took
    the larger of it and the type's stated RMS, so a bar with less friction than the type's was
    claimed at the type's (realistic twins: up to 1.9 times its own), in every point of a
    one-sided routine and in the term's start state. Now each bar's amplitude, with the
    variance the fit's principal directions give it."""
    from mmd_ros.core.terms import FrictionTerm
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=1)
    calibration = twin.calibrate(0.0, ambient_profile('section_4_1'), approaches=1)
    stated = twin.documented_device.friction_hysteresis_m
    amplitude = np.array([100.0, 200.0, 300.0, 400.0, 500.0, 150.0]) * 1e-9
    term = FrictionTerm(amplitude, 4e-6, 50e-9)
    budget = LengthBudget(twin.documented_device, calibration, Model(terms=[term]))
    assert np.sum(amplitude < stated) == 4
    np.testing.assert_allclose(budget.hysteresis_m, amplitude)
    np.testing.assert_allclose(budget.point_friction_m2, amplitude ** 2)
    # one sigma along a principal direction of the fit, written as a friction term
    sigma = np.array([30.0, 0.0, 40.0, 0.0, 0.0, 10.0]) * 1e-9
    fit = FitUncertainty(directions=[[FrictionTerm(sigma, 4e-6, 50e-9)]])
    model = Model(terms=[term], uncertainty=ModelUncertainty(fit=fit))
    budget = LengthBudget(twin.documented_device, calibration, model)
    np.testing.assert_allclose(budget.hysteresis_m, np.hypot(amplitude, sigma))
    # without a term, the type's stated figure, per point of the one-sided routine
    plain = LengthBudget(twin.documented_device, calibration, Model())
    np.testing.assert_allclose(plain.hysteresis_m, stated)


def test_the_plate_s_stated_seating_stands_for_what_a_one_sided_routine_did_not_measure():
    """Each placement seats the bar with an offset of its own (the plate's seating
    repeatability); a two-sided calibration measures it from the scatter of two placements per
    pair, the paper's one-sided routine does not. The plate's stated figure
    (``reference_plate.seating_repeatability_nm``, which the simulated plate states) then stands
    for it, in each point's variance. A clean twin whose bars seat within 0.3 um, calibrated
    one-sided: 24 calibrations covered 94.5 % (ratios 0.84-1.24 while the routine read no drift;
    z 2.13 now: each end of the drift reading is a seating, its change known to +-0.77 °C on
    this plate, claimed as (dT^2 - u^2)+ where the room held still); without the statement these
    8 covered 52 %, and the budget says what it does not claim. The stated seating sizes the
    drift reading's uncertainty too (the routine measured only its captures' noise): without
    it a change of that reading's noise was claimed as the routine's drift."""
    effects = Effects.ideal().with_assignments(['placement_repeatability_m=3e-7'])
    twin = TwinDevice(DEVICE, effects, seed=1)
    stated = twin.documented_device
    assert stated.seating_repeatability_m == pytest.approx(3e-7)
    raw = copy.deepcopy(stated.raw)
    del raw['reference_plate']['seating_repeatability_nm']
    unstated = parse_device(raw, 'test')
    ratio, cover = _pooled(effects, 'section_4_1', 24, seconds=3.0, approaches=1)
    print('one-sided, seating stated: ratio', np.round(ratio, 2), 'coverage', cover)
    others = np.delete(ratio, 2)
    assert np.all((others > 0.8) & (others < 1.3)) and 0.8 < ratio[2] < 2.5, ratio
    assert cover >= 0.93, cover
    ratio, cover = _pooled(effects, 'section_4_1', 8, seconds=3.0, approaches=1, device=unstated)
    print('one-sided, seating not stated: ratio', np.round(ratio, 2), 'coverage', cover)
    assert cover < 0.7, cover
    # the point's variance holds the stated seating; a two-sided calibration's own figure wins
    one_sided = twin.calibrate(0.0, ambient_profile('section_4_1'), approaches=1)
    with_it = LengthBudget(stated, one_sided, Model())
    without = LengthBudget(unstated, one_sided, Model())
    assert with_it.point_var_m2 - without.point_var_m2 == pytest.approx(9e-14, rel=1e-9)
    # the routine's drift, -0.49 °C read through two seatings of 0.3 um (+-0.77 °C): claimed
    # from the captures' noise alone (+-0.03 °C) it put 245 nm on a point
    assert one_sided.uncertainty.routine_temp_change_c < -0.3
    assert np.abs(without.drift_m).max() > 100e-9 and not np.any(with_it.drift_m)
    assert with_it.summary()['seating_from'] == 'device description'
    assert without.summary()['seating_nm'] is None
    assert any('reference_plate.seating_repeatability_nm' in n for n in without.notes)
    two_sided = twin.calibrate(0.0, ambient_profile('section_4_1'), approaches=2)
    measured = two_sided.uncertainty.seating_m
    assert measured is not None
    other = stated.with_seating_repeatability(5e-6)
    for device in (stated, other, unstated):
        budget = LengthBudget(device, two_sided, Model())
        assert budget.summary()['seating_from'] == 'calibration'
        assert budget.seating_m == measured
    assert LengthBudget(other, two_sided, Model()).point_var_m2 == pytest.approx(
        LengthBudget(unstated, two_sided, Model()).point_var_m2, rel=1e-12)


def test_the_bars_stated_gravity_sag_is_claimed_where_they_lean():
    """A bar calibrated lying on the plate reads g n_z^2 short on the MMD (n_z its axis'
    vertical component): a known error at a known pose, which the budget claims when the
    device description states g (``bars.gravity_sag_nm``, the simulated bars state the twin's).
    The realistic twin's 0.1 um sag on C-axis runs (which tilt the bars as the platform turns):
    6 calibrations 93.9 % in the ellipsoid (94.4 % with the twin's sag off), 88.2 % unstated.
    With a spread (each twin's bars one sag drawn about the figure, +- 15 %) the description
    states it as the figure's uncertainty: claimed as one draw for every bar, sigma^2 n_z^2
    n_z^2^T.
    A gravity_sag term in the model compensates it: the source is then off."""
    from mmd_ros.core.terms import GravitySagTerm
    effects = Effects.realistic()
    raw = copy.deepcopy(TwinDevice(DEVICE, effects, seed=1).documented_device.raw)
    del raw['bars']['gravity_sag_nm'], raw['bars']['gravity_sag_uncertainty_nm']
    unstated = parse_device(raw, 'test')
    room = ambient_profile('section_4_1')
    pooled = {True: ([], []), False: ([], [])}
    for k in range(6):
        twin = TwinDevice(DEVICE, effects, seed=k + 1)
        assert twin.documented_device.gravity_sag_m == pytest.approx(effects.gravity_sag_m)
        calibration = twin.calibrate(-211.0 * k, room, approaches=2)
        run = twin.simulate(make_scenario('iso_rotary', ['axis=psi', 'n_targets=6', 'n_cycles=2']),
                            room, start_s=600.0, reference='pose6')
        for stated, device in ((True, twin.documented_device), (False, unstated)):
            res = Pipeline(device, calibration).process(run.times_s, run.counts,
                                                        with_covariance=True)
            ok = res.valid & np.all(np.isfinite(run.true_poses), axis=1)
            pooled[stated][0].append(pose_error(res.poses, run.true_poses)[ok])
            pooled[stated][1].append(res.covariance[ok])
    cover = {}
    for stated, (errors, covs) in pooled.items():
        e, c = np.concatenate(errors), np.concatenate(covs)
        d2 = _d2(e, c)
        cover[stated] = float(np.mean(d2 <= LIMIT))
    print('C-axis runs, sag stated / not:', cover)
    assert cover[True] >= 0.93, cover
    assert cover[False] < cover[True] - 0.03, cover
    # the claim is the known error -g n_z^2 at each sample's pose, and nothing without a pose
    twin = TwinDevice(DEVICE, effects, seed=1)
    calibration = twin.calibrate(0.0, room, approaches=2)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=1', 'seed=3']), room,
                        start_s=600.0, reference='pose6')
    pipe = Pipeline(twin.documented_device, calibration)
    res = pipe.process(run.times_s, run.counts, with_covariance=True)
    comp, th = res.compensated, res.compensated.thermal
    budget = LengthBudget(twin.documented_device, calibration, Model())
    observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s, res.poses)
    _, bias = budget.sources(comp.lengths_m, th.reference_error_m, th.temp_change_c,
                             th.bar_error_m, None, observed)
    geo = DEVICE.geometry
    n_z2 = GravitySagTerm.features(geo.upper, geo.lower, res.poses, np.array([0.0, 0.0, 1.0]))
    assert 0.5 < float(np.min(n_z2)) and float(np.max(n_z2)) < 1.0     # (the bars stand steep)
    assert float(np.ptp(n_z2)) > 0.05
    assert np.allclose(bias['gravity_sag'], -effects.gravity_sag_m * n_z2, rtol=0, atol=1e-15)
    assert budget.summary()['gravity_sag_nm'] == pytest.approx(100.0)
    # the realistic twin's sag is its figure (stated +- 0); with a spread the description
    # states how far these bars' sag may lie from the figure: one draw for every bar, a
    # covariance sigma^2 n_z^2 n_z^2^T
    assert 'gravity_sag' not in budget.sources(comp.lengths_m, th.reference_error_m,
                                               th.temp_change_c, th.bar_error_m, None, observed)[0]
    spread = TwinDevice(DEVICE, effects.with_assignments(['gravity_sag_spread=0.15']), seed=1)
    sigma = 0.15 * effects.gravity_sag_m
    drawn = LengthBudget(spread.documented_device, calibration, Model())
    assert drawn.summary()['gravity_sag_uncertainty_nm'] == pytest.approx(sigma * 1e9)
    observed_drawn = drawn.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s, res.poses)
    cov = drawn.sources(comp.lengths_m, th.reference_error_m, th.temp_change_c,
                        th.bar_error_m, None, observed_drawn)[0]['gravity_sag']
    assert np.allclose(cov, sigma ** 2 * n_z2[:, :, None] * n_z2[:, None, :], rtol=1e-12, atol=0)
    fast_drawn = drawn.covariance(comp.lengths_m, th.reference_error_m, th.temp_change_c,
                                  th.bar_error_m, None, observed_drawn)
    _, bias_drawn = drawn.sources(comp.lengths_m, th.reference_error_m, th.temp_change_c,
                                  th.bar_error_m, None, observed_drawn)
    assert np.allclose(fast_drawn, sum(drawn.variances(
        comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m, None,
        observed_drawn).values()) - _cross_bias(bias_drawn), rtol=1e-9, atol=1e-24)
    fast = budget.covariance(comp.lengths_m, th.reference_error_m, th.temp_change_c,
                             th.bar_error_m, None, observed)
    assert np.allclose(fast, sum(budget.variances(
        comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m, None,
        observed).values()) - _cross_bias(bias), rtol=1e-9, atol=1e-24)
    assert 'gravity_sag' not in budget.sources(
        comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m, None,
        budget.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s))[1]
    notes = LengthBudget(unstated, calibration, Model()).notes
    assert any('bars.gravity_sag_nm' in n for n in notes)
    sag = GravitySagTerm(geo.upper, geo.lower, np.full(6, 1e-7))
    compensated = LengthBudget(twin.documented_device, calibration, Model(terms=[sag]))
    assert compensated.gravity_sag_m == 0.0 == compensated.gravity_sag_sigma_m
    assert compensated.summary()['gravity_sag_nm'] == 0.0


def test_the_sag_goes_with_the_vertical_the_mounting_states():
    """Between a horizontal spindle and its table the MMD lies on its side: its bars sag with
    their axes' component along that vertical, not along +z of {L}. The description states it
    (``plates.vertical``; the twin stands as its description says). Bars sagging 0.4 um, the
    MMD with +x of {L} up, random 6-DOF runs of 4 calibrations: 96.8 % in the 95 % ellipsoid
    with the vertical stated, 80.9 % with the lower plate taken level (the sag claimed along
    +z: z 1.37 times its error)."""
    effects = Effects.realistic().with_assignments(['gravity_sag_m=4e-7'])
    room = ambient_profile('section_4_1')
    side = DEVICE.with_vertical([1.0, 0.0, 0.0])
    pooled = {True: ([], []), False: ([], [])}
    for k in range(4):
        twin = TwinDevice(side, effects, seed=k + 1)
        stated = twin.documented_device
        raw = copy.deepcopy(stated.raw)
        del raw['plates']['vertical']
        level = parse_device(raw, 'level')
        calibration = twin.calibrate(-211.0 * k, room, approaches=2)
        run = twin.simulate(make_scenario('random_motion', ['duration_s=8', f'seed={k}']), room,
                            start_s=600.0, reference='pose6')
        for says, device in ((True, stated), (False, level)):
            res = Pipeline(device, calibration).process(run.times_s, run.counts,
                                                        with_covariance=True)
            ok = res.valid & np.all(np.isfinite(run.true_poses), axis=1)
            pooled[says][0].append(pose_error(res.poses, run.true_poses)[ok])
            pooled[says][1].append(res.covariance[ok])
    cover = {says: float(np.mean(_d2(np.concatenate(e), np.concatenate(c)) <= LIMIT))
             for says, (e, c) in pooled.items()}
    print('on its side, vertical stated / level:', cover)
    assert cover[True] >= 0.93, cover
    assert cover[False] < cover[True] - 0.08, cover
    assert stated.up.tolist() == [1.0, 0.0, 0.0]
    budget = LengthBudget(stated, calibration, Model())
    assert budget.summary()['vertical'] == [1.0, 0.0, 0.0]
    assert not any('plates.vertical' in n for n in budget.notes)
    assert any('plates.vertical' in n for n in LengthBudget(level, calibration, Model()).notes)


def test_the_readings_drift_since_calibration_is_claimed_from_the_stated_rate():
    """Each channel's reading drifts at its own rate within the bound the description states
    (``bars.drift_nm_per_h``; the twin states its largest): hours after the calibration its
    error is r t / sqrt(3) on each bar, and the reference bar's on every bar through Eq. 13.
    24 clean twins drifting up to 100 nm/h, run 4 h after calibrating in a still room: each
    bar's mean error over the run within its claimed sigma, in RMS over the twins, and along
    the bars' common mode (the reference bar's); with the samples' time unknown the same runs
    are 5 and more times their claim, and no sample of them lies in the 95 % ellipsoid."""
    room = ambient_profile('constant:20')
    effects = Effects.ideal().with_assignments(['drift_m_per_s=2.7777777778e-11'])
    z, inside, unknown, outside = [], [], [], []
    u = np.ones(6) / math.sqrt(6.0)
    start = 4 * 3600.0
    for seed in range(1, 25):
        twin = TwinDevice(DEVICE, effects, seed=seed)
        assert twin.documented_device.drift_m_per_s == pytest.approx(100e-9 / 3600.0)
        calibration = twin.calibrate(0.0, room, approaches=2, epoch_s=1_704_067_200)
        assert calibration.created.startswith('2024-01-01T00:')
        run = twin.simulate(make_scenario('random_motion', ['duration_s=2', f'seed={seed}']),
                            room, start_s=start, reference='pose6')
        for known in (True, False):
            pipeline = Pipeline(twin.documented_device, calibration)
            res = pipeline.process(run.times_s, run.counts, with_covariance=True,
                                   with_length_covariance=True,
                                   epoch_s=1_704_067_200 + start if known else None)
            ok = res.valid
            e = (res.compensated.lengths_m - run.true_lengths)[ok]
            cov = res.length_covariance[ok]
            sigma = np.sqrt(np.mean(np.diagonal(cov, axis1=1, axis2=2), axis=0))
            common = float(np.mean(e @ u)) / math.sqrt(float(np.mean(u @ cov @ u)))
            (z if known else unknown).append(np.r_[e.mean(axis=0) / sigma, common])
            d2 = np.einsum('ni,nij,nj->n', e, np.linalg.inv(cov), e)
            (inside if known else outside).append(d2 <= LIMIT)
    z, unknown = np.array(z), np.array(unknown)
    rms = np.sqrt(np.mean(z ** 2, axis=0))
    print('drift since calibration: RMS of mean error / sigma per bar, common mode',
          np.round(rms, 2), 'time unknown', np.round(np.sqrt(np.mean(unknown ** 2, axis=0)), 1))
    assert 0.8 < math.sqrt(np.mean(z[:, :6] ** 2)) < 1.25
    assert 0.7 < rms[6] < 1.35
    assert np.mean(np.concatenate(inside)) > 0.95
    assert np.sqrt(np.mean(unknown[:, :6] ** 2)) > 5.0
    assert np.mean(np.concatenate(outside)) < 0.05
    # the streaming sum (one reference bar) adds what the sources list
    budget = pipeline.budget
    comp, th = res.compensated, res.compensated.thermal
    observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s,
                              epoch_s=1_704_067_200 + start)
    args = (comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m, None, observed)
    cov, bias = budget.sources(*args)
    t = start + run.times_s - (calibration.created_s - 1_704_067_200)
    np.testing.assert_allclose(cov['reading_drift'][:, 0, 0], 2 * (100e-9 / 3600 * t) ** 2 / 3)
    np.testing.assert_allclose(cov['reading_drift'][:, 0, 1], (100e-9 / 3600 * t) ** 2 / 3)
    b = sum(bias.values()) if bias else np.zeros((t.size, 6))
    np.testing.assert_allclose(budget.covariance(*args),
                               sum(cov.values()) + b[:, :, None] * b[:, None, :], rtol=1e-9,
                               atol=1e-30)


@pytest.mark.parametrize('config', ['mmd_prototype.yaml', 'mmd_two_reference_bars.yaml'])
def test_the_reference_bar_s_own_thermal_behaviour_is_claimed_in_every_bar(config):
    """Bars do not expand alike, and the reference bar is one of them: what Eq. (13) subtracts
    from every bar holds its own deviation from the type, an error every bar shares. The stated
    fraction (``bars.thermal_mismatch_fraction``, 0.06) is what is left of one bar's error;
    half its variance is the bar's own, half the reference bar's (Eq. (12): each reference
    bar's with its interpolation weights). 24 clean twins whose bars' CTEs scatter 4.7 % (6 %
    of the error left per bar), calibrated at 24 °C and run 6 h later at 18 °C (3.3 µm of
    thermal error subtracted): each bar's mean error and the bars' common mode within the
    sigma claimed along them, in RMS over the twins, and every twin's samples in the 95 %
    ellipsoid. Claimed per bar alone the prototype's common mode was 1.39 times its claim and
    one twin was covered 17 %."""
    device = load_device(find_config(config))
    room = AmbientProfile(24.0, (Ramp(3600.0, 18.0, 600.0),))
    effects = Effects.ideal().with_assignments(['thermal_mismatch=0.047'])
    u = np.ones(6) / math.sqrt(6.0)
    start = 6 * 3600.0
    z, inside = [], []
    for seed in range(1, 25):
        twin = TwinDevice(device, effects, seed=seed)
        calibration = twin.calibrate(-4000.0, room, approaches=2, epoch_s=1_704_067_200)
        run = twin.simulate(make_scenario('random_motion', ['duration_s=2', f'seed={seed}']),
                            room, start_s=start, reference='pose6')
        pipeline = Pipeline(twin.documented_device, calibration)
        res = pipeline.process(run.times_s, run.counts, with_covariance=True,
                               with_length_covariance=True, epoch_s=1_704_067_200 + start)
        assert np.all(np.abs(res.compensated.thermal.reference_error_m) > 2.5e-6)
        ok = res.valid
        e = (res.compensated.lengths_m - run.true_lengths)[ok]
        cov = res.length_covariance[ok]
        sigma = np.sqrt(np.mean(np.diagonal(cov, axis1=1, axis2=2), axis=0))
        common = float(np.mean(e @ u)) / math.sqrt(float(np.mean(u @ cov @ u)))
        z.append(np.r_[e.mean(axis=0) / sigma, common])
        inside.append(np.mean(np.einsum('ni,nij,nj->n', e, np.linalg.inv(cov), e) <= LIMIT))
    z = np.array(z)
    rms = math.sqrt(np.mean(z[:, :6] ** 2)), math.sqrt(np.mean(z[:, 6] ** 2))
    print(config, 'thermal mismatch: RMS of mean error / sigma per bar, common mode',
          np.round(rms, 2), 'coverage per twin', np.round(inside, 3))
    assert 0.7 < rms[0] < 1.25
    assert 0.6 < rms[1] < 1.2
    assert min(inside) > 0.9
    # the form: half of each bar's share is common to every bar (one reference bar)
    if device.reference_channels[1:]:
        return
    th = res.compensated.thermal
    share = pipeline.budget.sources(res.compensated.lengths_m, th.reference_error_m,
                                    th.temp_change_c, th.bar_error_m)[0]['thermal_mismatch']
    np.testing.assert_allclose(share[:, 0, 0], (0.06 * th.reference_error_m[:, 0]) ** 2)
    np.testing.assert_allclose(share[:, 2, 5], share[:, 0, 0] / 2)


def test_without_a_stated_rate_or_the_calibration_s_time_the_drift_is_not_claimed():
    """The budget says what it leaves out: no rate stated, or a calibration without its time."""
    twin = TwinDevice(DEVICE, Effects.ideal().with_assignments(['drift_m_per_s=1e-11']), seed=1)
    room = ambient_profile('constant:20')
    timed = twin.calibrate(0.0, room, epoch_s=1_704_067_200)
    untimed = twin.calibrate(0.0, room)
    assert untimed.created == '' and timed.created_s == pytest.approx(
        1_704_067_200 + twin.calibration_schedule(0.0)[-1].end_s)
    assert any('bars.drift_nm_per_h' in n for n in LengthBudget(DEVICE, timed, Model()).notes)
    assert not any('reading drift' in n
                   for n in LengthBudget(twin.documented_device, timed, Model()).notes)
    budget = LengthBudget(twin.documented_device, untimed, Model())
    assert any('(created)' in n for n in budget.notes)
    x = np.full((3, 6), 0.3)
    observed = budget.observe(x, np.zeros((3, 1)), np.arange(3.0), epoch_s=2e9)
    assert observed.since_calibration_s is None
    assert 'reading_drift' not in budget.variances(x, np.zeros((3, 1)), np.zeros(3),
                                                   observed=observed)
    assert budget.summary()['drift_nm_per_h'] == pytest.approx(36.0)
    # a log stamped from 0 (a simulated clock) says nothing of the time since the calibration:
    # 54 years of drift are not claimed, and the notes say why
    timed_budget = LengthBudget(twin.documented_device, timed, Model())
    from_zero = timed_budget.observe(x, np.zeros((3, 1)), np.arange(3.0), epoch_s=0.0)
    assert from_zero.since_calibration_s is None
    assert any('wall clock' in n for n in timed_budget.notes)
    on_the_clock = timed_budget.observe(x, np.zeros((3, 1)), np.arange(3.0),
                                        epoch_s=timed.created_s + 3600.0)
    np.testing.assert_allclose(on_the_clock.since_calibration_s, [3600.0, 3601.0, 3602.0])
    # what the nodes' diagnostics report of it: one channel's sigma an hour on
    assert timed_budget.reading_drift_sigma_m(timed.created_s + 3600.0) == pytest.approx(
        36e-9 / math.sqrt(3.0))
    assert math.isnan(budget.reading_drift_sigma_m(timed.created_s + 3600.0))
    assert math.isnan(timed_budget.reading_drift_sigma_m(3600.0))


def test_after_a_fit_the_drift_is_counted_from_when_its_residual_was_measured(tmp_path):
    """A fit's residual holds what the readings had drifted by the time of its runs (an
    absolute reference measures it with the bars' constants; a zeroed fit claims its common
    mode from the budget at that time): the model records when (the mean time of the samples
    it was measured on), and the budget counts the drift on from there, or from a later
    calibration. Counted from the calibration instead, the 24 absolute fits of
    ``bench_uncertainty.py --after`` claimed z 1.16 times its error, 1.05 now."""
    from mmd_ros.analysis import analyze
    from mmd_ros.twin.recording import EPOCH_S
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=3)
    room = ambient_profile('section_4_1')
    calibration = twin.calibrate(-400.0, room, approaches=2, epoch_s=EPOCH_S)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=30', 'seed=100']), room,
                        start_s=2000.0, reference='pose6', sample_rate_hz=200.0)
    result = analyze(run_log(twin, calibration, run, 2000.0))
    fit = result.model.uncertainty.fit
    assert fit.measured_unix_s - EPOCH_S == pytest.approx(2015.0, abs=2.0)
    path = tmp_path / 'model.yaml'
    result.model.save(path)
    assert load_model(path).uncertainty.fit.measured_unix_s == pytest.approx(fit.measured_unix_s,
                                                                          abs=1e-3)
    budget = LengthBudget(twin.documented_device, calibration, result.model)
    assert budget.drift_from_s == pytest.approx(fit.measured_unix_s)
    observed = budget.observe(np.full((2, 6), 0.3), np.zeros((2, 1)), np.array([0.0, 1.0]),
                              epoch_s=EPOCH_S + 3815.0)
    np.testing.assert_allclose(observed.since_calibration_s, [1800.0, 1801.0], atol=2.0)
    later = dataclasses.replace(calibration, created='2024-01-01T02:00:00+00:00')
    assert LengthBudget(twin.documented_device, later, result.model).drift_from_s == \
        EPOCH_S + 7200.0
    assert LengthBudget(twin.documented_device, calibration, Model()).drift_from_s == \
        calibration.created_s


@pytest.mark.parametrize('approaches, again_approaches, seed', [(2, 2, 2), (1, 1, 4), (1, 2, 5)])
def test_a_model_on_a_new_calibration_claims_that_calibration_s_placements_and_drift(
        approaches, again_approaches, seed):
    """The device calibrated again after ``mmd analyze``: the model names the calibration it
    was fitted with (and the nodes and ``mmd process`` warn), and its fit's residual measured
    that calibration's placements and routine drift, a draw of their own. The new
    calibration's are claimed anew, and the first one's too where the model's terms hold
    them: its placements where they hold its points, its routine's drift, smooth along the
    bars, as the difference of the two where they hold the bars' length (the model records
    what that routine measured). A twin fitted on 10 s of its calibration at 0 s (two-sided),
    calibrated again at 3000 s as the room falls 0.41 °C over the routine, judged an hour
    later against its true pose: 98 % of the poses in the 95 % ellipsoid, 42 % before
    (though every axis was claimed 1.1-2.3 times its error: the error lay along the new
    routine's drift, which the covariance held known; four other twins' new runs against
    their reference in ``mmd process``, 6-66 %, 95-99 % now). Calibrated one-sided both times
    (the paper's routine, which reads its drift from the reference bar where it rests before
    its first placement), twin 4: 96.6 %, 83.2 % while that routine did not read its drift
    (twins 2, 3, 5: 93.6, 97.8, 90.1 % then, 100 % now). Fitted after a one-sided routine and
    used after a two-sided one, the model's points term applies the first routine's friction
    steps to points free of them, and they are claimed: twin 5 99.4 %, 37.0 % while only the
    new routine's friction states were (twins 2-4: 53.2, 36.9, 53.6 % then, 77.4, 99.7, 100 %
    now)."""
    from mmd_ros.analysis import analyze
    from mmd_ros.core.validity import fitted_calibration_figures
    from mmd_ros.logs.processing import process_run
    from mmd_ros.twin.recording import EPOCH_S
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=seed)
    room = ambient_profile('section_4_1')
    first = twin.calibrate(0.0, room, approaches=approaches, epoch_s=EPOCH_S)
    fitted = twin.simulate(make_scenario('random_motion', ['duration_s=10', 'seed=100']), room,
                           start_s=600.0, reference='pose6', sample_rate_hz=200.0)
    model = Model.from_yaml(analyze(run_log(twin, first, fitted, 600.0)).model.to_yaml())
    recorded = fitted_calibration_figures(model)
    assert recorded is not None and recorded.approaches == approaches
    assert recorded.routine_temp_change_c == pytest.approx(first.uncertainty.routine_temp_change_c,
                                                           abs=1e-6)
    assert any(t.type_name in ('cdf_offsets', 'scale_nonlinearity') for t in model.terms)
    again = twin.calibrate(3000.0, room, approaches=again_approaches, epoch_s=EPOCH_S)
    assert again.uncertainty.routine_temp_change_c < (-0.3 if again_approaches == 2 else -0.1)
    new = twin.simulate(make_scenario('random_motion', ['duration_s=10', 'seed=52']), room,
                        start_s=3600.0, reference='pose6', sample_rate_hz=200.0)
    out = process_run(run_log(twin, again, new, 3600.0), model, with_covariance=True)
    ok = out.valid
    ratio, inside = _judged(pose_error(out.poses, new.true_poses)[ok], out.covariance[ok])
    print('a model on a new calibration: ratio', np.round(ratio, 2), 'coverage', inside)
    assert inside >= 0.93 and ratio[2] > 0.8, (ratio, inside)
    budget = LengthBudget(twin.documented_device, again, model)
    assert budget.new_placements and any('another calibration' in n for n in budget.notes)
    # the difference of the two routines' drifts, not the new one's alone
    alone = LengthBudget(twin.documented_device, again, Model())
    np.testing.assert_allclose(budget.drift_m + LengthBudget(
        twin.documented_device, first, Model()).drift_m, alone.drift_m, atol=1e-15)
    # with the calibration it was fitted with, nothing of this
    assert not LengthBudget(twin.documented_device, first, model).new_placements


def test_after_an_absolute_fit_the_thermal_errors_are_claimed_from_the_fit_s_thermal_state(
        tmp_path):
    """Realistic twins calibrated at 20 °C in a room that then warms to 23 °C; ``mmd analyze``
    of 30 s of random motion 5 °C after the thermal zero against the absolute pose, and 8 s of
    new motion 100 s later. The bars' thermal mismatch, Eq. (13)'s approximation and the
    plates' scale, all proportional to the change since the thermal zero, were claimed from
    there, although the fitted CDF points took up what they were at the fitted run (or its
    residual holds it): inside the fitted lengths 4.0-5.2 times the error (twin 1). The fit
    records the thermal state of its samples (``thermal_state_nm``, ``thermal_state_c``) and
    the budget claims those errors of the change since: 0.88-1.16, 95.6 %.

    A fit that found a run's own drift: its offsets took the bars' constants there (0.18-0.59
    µm on twin 4, a rate of nothing to speak of), which are not written. Twin 4's CDF points,
    their directions chosen beside the drift, could not take them back when refitted without
    it: the model left x 240 nm RMS in the fitted run and 406 nm in the new one, 87.6 % in the
    95 % ellipsoid. Chosen again without it, the points carry them (x 50 and 69 nm), the
    thermal state is recorded as they do, and the drift's covariance is no longer claimed on
    top of theirs: 0.89-1.23, 95.1 %. Twin 3's terms have no CDF points to carry them: it
    records no state, and its claim stays whole (99.1 % inside the fitted lengths; with the
    state, 61 %)."""
    from mmd_ros.analysis import analyze
    room = AmbientProfile(20.0, (Ramp(7200.0, 23.0, 1500.0),))
    for k in (0, 2, 3):
        twin = TwinDevice(DEVICE, Effects.realistic(), seed=k + 1)
        calibration = twin.calibrate(-3000.0, room, approaches=2)
        fitted = twin.simulate(make_scenario('random_motion', ['duration_s=30', f'seed={100 + k}']),
                               room, start_s=20000.0, reference='pose6')
        result = analyze(run_log(twin, calibration, fitted, 20000.0))
        fit = result.model.uncertainty.fit
        assert any(f.effect == 'drift' for f in result.found) == (k > 0), result.conclusion
        written = [t.type_name for t in result.model.terms]
        assert ('cdf_offsets' in written) == (k != 2), written
        if k == 2:
            assert fit.thermal_state_m is None and fit.thermal_state_c is None
            continue
        # the state is the fitted run's: its bars' thermal corrections and temperature change
        thermal = Pipeline(twin.documented_device, calibration, Model()).process(
            fitted.times_s, fitted.counts).compensated.thermal
        np.testing.assert_allclose(fit.thermal_state_m[:6], thermal.bar_error_m.mean(axis=0),
                                   atol=5e-9)
        np.testing.assert_allclose(fit.thermal_state_m[6:], thermal.reference_error_m.mean(axis=0),
                                   atol=5e-9)
        assert fit.thermal_state_c == pytest.approx(float(np.mean(thermal.temp_change_c)), abs=0.01)
        assert abs(fit.thermal_state_c) > 4.0
        back = load_model(result.model.save(tmp_path / f'model{k}.yaml')).uncertainty.fit
        np.testing.assert_allclose(back.thermal_state_m, fit.thermal_state_m, atol=1e-12)
        assert back.thermal_state_c == pytest.approx(fit.thermal_state_c, abs=1e-5)
        # the plates' scale the nodes' diagnostics report is the one the covariance claims
        budget = LengthBudget(twin.documented_device, calibration, result.model)
        assert budget.plate_scale_rel > 0.0
        assert budget.plate_scale_sigma(fit.thermal_state_c) == pytest.approx(0.0, abs=1e-12)
        assert budget.plate_scale_sigma(fit.thermal_state_c - 1.0) == pytest.approx(
            budget.plate_scale_rel)
        run = twin.simulate(make_scenario('random_motion', ['duration_s=8', f'seed={k}']), room,
                            start_s=20100.0, reference='pose6')
        res = Pipeline(twin.documented_device, calibration, result.model).process(
            run.times_s, run.counts, with_covariance=True)
        seen, cdf = Validity.from_model(result.model).bar_range_m, res.compensated.cdf_lengths_m
        inside = res.valid & np.all((cdf >= seen[:, 0]) & (cdf <= seen[:, 1]), axis=1)
        error = pose_error(res.poses, run.true_poses)[inside]
        ratio, covered = _judged(error, res.covariance[inside])
        rms = np.sqrt(np.mean(error ** 2, axis=0))
        print(k, inside.sum(), 'x y z', np.round(rms[:3] * 1e9), 'nm, ratio', np.round(ratio, 2),
              'coverage', round(covered, 3))
        assert np.all(rms[:3] < 100e-9), rms       # (twin 4's points not carrying: x 406 nm)
        assert inside.sum() > 4000 and covered >= 0.93
        assert np.all((0.75 < ratio) & (ratio < 1.5)), ratio


def test_the_plates_scale_is_claimed_and_a_fitted_thermal_gain_replaces_the_mismatch(tmp_path):
    """The joints are scaled for the plates' expansion at the temperature change Eq. (11)
    implies through the description's sensitivity; that change is as uncertain, relatively,
    as the bars' effective rod CTE (``bars.rod_cte_uncertainty_ppm_per_c``; the twin states
    how far its rods lie from the description's) and the reference bar's own thermal
    deviation. A model whose ``thermal_gain`` was fitted has taken the bars' mismatch (own and
    reference bar's), so that source goes. A twin whose bars' CTEs scatter 20 % and expand at
    3.5 ppm/°C where the description says 2.0, its gains fitted on a 6 h soak of the bars on
    their pairs, judged 7 h after its calibration (the room 5.6 °C cooler, the plates' scale
    1.9 ppm off): with the mismatch still claimed x and y were claimed 4.4-4.7 times their
    error; now 1.04-1.25 but z 1.76 (Eq. (13)'s approximation is claimed at the temperature
    change the description's CTE implies, 1.7 times the bars' own), 98.6 % in the 95 %
    ellipsoid, 87.6 % with the rods' CTE taken as exact."""
    from mmd_ros.analysis import analyze
    from mmd_ros.core.terms import ThermalInterpolationTerm
    from mmd_ros.logs.layout import read_run
    from mmd_ros.logs.processing import process_run, summarize
    from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
    calibration = TwinDevice(DEVICE, Effects.ideal(), seed=1).calibrate(
        0.0, ambient_profile('constant:20'))
    assert any('bars.rod_cte_uncertainty_ppm_per_c' in n
               for n in LengthBudget(DEVICE, calibration, Model()).notes)
    off = LengthBudget(DEVICE, calibration, Model(thermal_mode='off'))
    assert off.plate_scale_rel == 0.0 and not any("plates' scale" in n for n in off.notes)
    assert TwinDevice(DEVICE, Effects.ideal()).documented_device.rod_cte_sigma_per_c == 0.0
    realistic = TwinDevice(DEVICE, Effects.realistic()).documented_device
    assert realistic.rod_cte_sigma_per_c == pytest.approx(1.5e-6)
    # a_p sqrt((L u_a / |S|)^2 + f^2 / 2), S of the reference bar in use (Eq. 13: the first)
    two = TwinDevice(load_device(find_config('mmd_two_reference_bars.yaml')),
                     Effects.realistic()).documented_device
    single = LengthBudget(two, TwinDevice(two, Effects.ideal()).calibrate(
        0.0, ambient_profile('constant:20')), Model(thermal_mode='single'))
    d, fixed = single.ref_distances_m[0], two.fixed_length_m
    sens = two.rod_cte_per_c * fixed + two.scale_cte_per_c * (d - fixed)
    assert single.plate_scale_rel == pytest.approx(two.plate_cte_per_c * math.sqrt(
        (fixed * 1.5e-6 / sens) ** 2 + two.thermal_mismatch_fraction ** 2 / 2))

    effects = ('thermal_mismatch=0.2', 'rod_cte_per_c=3.5e-6')
    soak, later = tmp_path / 'soak.mcap', tmp_path / 'later.mcap'
    simulate_to_log(SimulationSpec(scenario='thermal_soak', scenario_params=('duration_s=21600',),
                                   effects='ideal', effect_params=effects, seed=1,
                                   ambient='section_4_1', reference='bar_lengths',
                                   sample_rate_hz=0.2), soak, progress=False)
    simulate_to_log(SimulationSpec(scenario='random_motion', scenario_params=('duration_s=20',),
                                   effects='ideal', effect_params=effects, seed=1,
                                   ambient='section_4_1', reference='pose6', start_s=25000.0),
                    later, progress=False)
    model = analyze(read_run(soak)).model
    assert [t.type_name for t in model.terms] == ['thermal_gain']
    run = read_run(later)

    def judged(run) -> dict:
        return summarize(run, process_run(run, model, with_covariance=True))['uncertainty_coverage']

    claimed = judged(run)
    ratio = np.array([c['ratio'] for c in claimed['per_component']])
    budget = LengthBudget(run.device, run.calibration, model)
    assert budget.mismatch_fraction == 0.0 and budget.plate_scale_rel > 0.0
    # Eq. (13)'s approximation: what the gains leave, from the lengths they were fitted at (the
    # soak's pair, 323 mm); nothing once a thermal_interpolation term corrects it
    np.testing.assert_allclose(budget.approximation_from_m, 0.323, atol=1e-4)
    interpolated = Model(terms=[ThermalInterpolationTerm(-1.3, 0.323)])
    assert LengthBudget(run.device, run.calibration, interpolated).approximation_from_m is None
    # the same run and model, the description stating the rods' CTE exact: the temperature
    # change is then as uncertain as the reference bar's mismatch only
    without = judged(dataclasses.replace(run, device=run.device.with_rod_cte_uncertainty(0.0)))
    print('thermal gain fitted, 7 h later: ratios', np.round(ratio, 2), 'coverage',
          claimed['ellipsoid_coverage'], 'rods\' CTE taken exact', without['ellipsoid_coverage'])
    assert np.all(ratio[[0, 1, 3, 4, 5]] < 1.3) and np.all(ratio > 0.8)
    assert claimed['ellipsoid_coverage'] > 0.93 and without['ellipsoid_coverage'] < 0.9


def test_a_simulated_log_s_calibration_states_its_time_and_mmd_process_claims_the_drift(tmp_path):
    """``mmd simulate`` writes the calibration with the time its routine ended, on the clock
    its samples are stamped on; processing the log counts each sample's time from it."""
    from mmd_ros.logs.layout import read_run
    from mmd_ros.logs.processing import process_run
    from mmd_ros.twin.recording import EPOCH_S, SimulationSpec, simulate_to_log
    log = tmp_path / 'late.mcap'
    simulate_to_log(SimulationSpec(scenario='random_motion', scenario_params=('duration_s=1',),
                                   effects='ideal', effect_params=('drift_m_per_s=2.8e-11',),
                                   ambient='constant:20', start_s=3 * 3600.0, reference='pose6'),
                    log, progress=False)
    run = read_run(log)
    assert run.calibration.created_s is not None
    assert EPOCH_S < run.calibration.created_s < EPOCH_S + 600.0
    after = (run.stamps_ns[0] * 1e-9 - run.calibration.created_s) / 3600.0
    assert 2.8 < after < 3.0
    timed = process_run(run, Model(), with_covariance=True)
    untimed = process_run(dataclasses.replace(
        run, calibration=dataclasses.replace(run.calibration, created='')), Model(),
        with_covariance=True)
    pipeline = Pipeline(run.device, run.calibration)
    expected = pipeline.process(run.times_s, run.counts, with_covariance=True,
                                epoch_s=run.stamps_ns[0] * 1e-9).covariance
    ok = timed.valid
    np.testing.assert_allclose(timed.covariance[ok], expected[ok], rtol=1e-6)
    z_var = timed.covariance[ok, 2, 2], untimed.covariance[ok, 2, 2]
    assert np.all(z_var[0] > 4 * z_var[1])


def test_the_routine_s_drift_is_claimed_without_relying_on_its_sign():
    """The routine's temperature change is measured from two captures of a reference bar: on
    realistic twins whose room held still it read up to 0.23 °C (2.6 of its sigma), a drift
    profile of up to 107 nm that is not there. Summed as a signed error with the bars' gravity
    sag (-90 nm on every bar) it cancelled it; as a covariance of one change for every bar it
    stands beside it."""
    effects = Effects.realistic()
    twin = TwinDevice(DEVICE, effects, seed=16)
    room = ambient_profile('section_4_1')
    calibration = twin.calibrate(-211.0 * 15, room, approaches=2)
    still = TwinDevice(DEVICE, Effects.ideal(), seed=16).calibrate(-211.0 * 15, room, approaches=2)
    assert abs(still.uncertainty.routine_temp_change_c) < 0.01     # the room held still
    change, sigma = (calibration.uncertainty.routine_temp_change_c,
                     calibration.uncertainty.routine_temp_sigma_c)
    assert abs(change) > 2.0 * sigma
    run = twin.simulate(make_scenario('random_motion', ['duration_s=1', 'seed=2']), room,
                        start_s=700.0, reference='pose6')
    res = Pipeline(twin.documented_device, calibration).process(run.times_s, run.counts)
    comp, th = res.compensated, res.compensated.thermal
    budget = LengthBudget(twin.documented_device, calibration, Model())
    observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m, run.times_s, res.poses)
    args = (comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m, None, observed)
    cov, bias = budget.sources(*args)
    assert 'calibration_drift' not in bias and 'gravity_sag' in bias
    drift = np.diagonal(cov['calibration_drift'], axis1=1, axis2=2)
    e = np.sqrt(drift)
    assert np.allclose(cov['calibration_drift'], e[:, :, None] * e[:, None, :], rtol=1e-9)
    assert float(np.max(e)) > 50e-9 and float(np.min(bias['gravity_sag'])) < -80e-9
    total = np.diagonal(budget.covariance(*args), axis1=1, axis2=2)
    assert np.all(total >= drift + bias['gravity_sag'] ** 2)


def _cross_bias(bias: dict) -> np.ndarray:
    """What the known errors' joint b b^T holds beyond the sum of their own b_s b_s^T."""
    b = list(bias.values())
    total = sum(b)
    return (sum(x[:, :, None] * x[:, None, :] for x in b)
            - total[:, :, None] * total[:, None, :])


#: :func:`_after_the_loop`'s last four cases (tests judge some alike; each holds ~60 MB).
_LOOPS: dict = {}


def _after_the_loop(tmp_path, seed: int, fit_s: float = 60.0, datum: str = 'none',
                    calibrate_at_s: float = 0.0, clock: str = 'shared', **options):
    """mmd analyze on a log of a realistic twin with its full pose (the log's own reference
    noise stated; ``datum`` 'none' absolute, 'offset' zeroed; the twin calibrated at
    ``calibrate_at_s`` of the room's day; the log saying its reference runs on the MMD's
    clock, ``clock`` 'shared', or its own; ``options`` further AnalysisOptions), then that
    twin's model judged against its true pose on three new runs. A case asked for again is
    not computed again: its log stays in the ``tmp_path`` of the first test that asked for it."""
    from mmd_ros.analysis.identify import AnalysisOptions
    key = (seed, fit_s, calibrate_at_s, clock, repr(AnalysisOptions(datum=datum, **options)))
    if key not in _LOOPS:
        _LOOPS[key] = _loop(tmp_path, seed, fit_s, datum, calibrate_at_s, clock, **options)
        if len(_LOOPS) > 4:
            del _LOOPS[next(iter(_LOOPS))]
    return _LOOPS[key]


def _loop(tmp_path, seed: int, fit_s: float, datum: str, calibrate_at_s: float, clock: str,
          **options):
    """:func:`_after_the_loop`, computed."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    from mmd_ros.logs.layout import read_run
    from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
    log = tmp_path / f'fit{seed}.mcap'
    spec = SimulationSpec(scenario='random_motion', scenario_params=(f'duration_s={fit_s:g}',
                                                                     f'seed={99 + seed}'),
                          effects='realistic', reference='pose6', seed=seed,
                          calibration_approaches=2, calibrate_at_s=calibrate_at_s)
    simulate_to_log(spec, log, progress=False)
    fitted = read_run(log)
    fitted.metadata['reference_clock'] = clock
    result = analyze(fitted, options=AnalysisOptions(datum=datum, **options))
    model = Model.from_yaml(result.model.to_yaml()) if result.model is not None else Model()
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=seed)
    room = ambient_profile('section_4_1')
    calibration = fitted.calibration      # (the calibration the model was fitted with)
    errors, covs, inside = [], [], []
    validity = Validity.from_model(model)
    bars = None if validity is None else validity.bar_range_m
    for k in range(3):
        run = twin.simulate(make_scenario('random_motion', ['duration_s=4', f'seed={10 * seed + k}']),
                            room, start_s=700.0 + 20 * k, reference='pose6')
        res = Pipeline(twin.documented_device, calibration, model).process(
            run.times_s, run.counts, with_covariance=True)
        errors.append(pose_error(res.poses, run.true_poses)[res.valid])
        covs.append(res.covariance[res.valid])
        cdf = res.compensated.cdf_lengths_m[res.valid]
        inside.append(np.ones(cdf.shape[0], dtype=bool) if bars is None
                      else np.all((cdf >= bars[:, 0]) & (cdf <= bars[:, 1]), axis=1))
    return result, model, (errors, covs, inside), log


def test_after_the_loop_the_fit_s_uncertainty_is_in_the_model_and_covers(tmp_path):
    """`mmd analyze` with the twin's full pose: the written model carries the fitted terms'
    parameter covariance (as one-sigma directions), the residual of every bar (the
    reference's own noise taken out) in place of the calibration-derived sources over the
    lengths the fit saw, and that range. Five twins (five calibrations: each draws every
    systematic error once, and a pooled coverage of two says little of a 95 % claim), each
    judged with its own model on new motion: the 95 % ellipsoid covers 93-97 % (measured
    95.5 %) and no axis is under-stated (ratio > 0.8). Where every bar lies inside the
    lengths the fit saw (88 % of the samples), the ratio is within the issue's 0.8-1.25
    (measured 0.92-1.06), and over all samples too (0.95-1.10; 0.97-1.14 while the
    calibration's sources came back from the bound of the CDF segments whose middle the fit
    saw, 1.09-1.54 in y, pitch and yaw while the size of what the terms corrected was claimed
    whole from the bound on): the rest take a bar
    outside those lengths, where the length terms are claimed uncertain by their change from
    the last length the fit checked and by the size of what they corrected within those
    lengths, the share of it a smooth error leaves unknown growing with the distance
    (unchecked_range: on an error of another shape than the twin's, the test below, this is
    what covers it), and the calibration-derived sources come back as the distance grows; a
    bar in a CDF segment whose middle the fit did not see gets what the fit's residual held
    there beyond the claim (a twin whose fit saw only the flank of two bars' end segments was
    covered 66 % when nothing was claimed there): covered (measured 96.0 %, 97.0 % while the
    sources came back from the segments' bound, 98.3 % with the size claimed whole)."""
    from mmd_ros.core.model import FIT_REPLACEABLE
    errors, covs, inside = [], [], []
    for seed in (1, 2, 3, 4, 5):
        result, model, (e, c, m), log = _after_the_loop(tmp_path, seed)
        assert 'sampling_skew' in [f.effect for f in result.found]
        fit = model.uncertainty.fit
        assert fit is not None and fit.directions and fit.replaces == tuple(FIT_REPLACEABLE)
        assert np.all(np.diag(fit.residual_m2) > 0)
        assert 'bar_range_mm' in model.extra['validity']
        assert 'length_sigma_um' not in model.to_yaml()
        errors += e
        covs += c
        inside += m
    # a residual with an offset removed per component lacks the constant error: it replaces
    # the same sources and claims what the run leaves unknown of a constant per bar, whose
    # common mode (all six bars alike: temperature, gravity) the pose's variation cannot show
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    from mmd_ros.logs.layout import read_run
    zeroed = analyze(read_run(log), options=AnalysisOptions(datum='offset')).model
    assert zeroed is not None and zeroed.uncertainty.fit.replaces == tuple(FIT_REPLACEABLE)
    unseen = np.array(zeroed.uncertainty.fit.record['unseen_constant_nm'])
    assert np.all(unseen > 0)
    e, c = np.concatenate(errors), np.concatenate(covs)
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0)) / np.sqrt(np.mean(e * e, axis=0))
    d2 = _d2(e, c)
    print('after the loop: ratio', np.round(ratio, 2), 'coverage', np.mean(d2 <= LIMIT))
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert 0.93 <= np.mean(d2 <= LIMIT) <= 0.97, np.mean(d2 <= LIMIT)
    m = np.concatenate(inside)
    assert 0.5 < m.mean() < 1.0, m.mean()
    ratio_in = (np.sqrt(np.mean(np.diagonal(c[m], axis1=1, axis2=2), axis=0))
                / np.sqrt(np.mean(e[m] * e[m], axis=0)))
    print('inside the fit\'s lengths:', round(float(m.mean()), 3), 'ratio', np.round(ratio_in, 2))
    assert np.all((ratio_in > 0.8) & (ratio_in < 1.25)), ratio_in
    print('outside them: coverage', np.mean(d2[~m] <= LIMIT))
    assert np.mean(d2[~m] <= LIMIT) >= 0.93


def test_against_a_reference_on_its_own_clock_the_common_skew_is_claimed_not_fitted(tmp_path):
    """The same loop, the log saying that its reference runs on a clock of its own: a common
    delay of the channels (this terminal's latch within [0, 50 µs] after the tick) and the
    reference's lag are one signature, so the lag is fitted per log and the skew written
    corrects how the channels differ; the common part (about 25 µs, 0.25 µm at 10 mm/s) is
    claimed from the terminal's stated bound, along the bars' velocity (rank one: one delay
    of every bar, uniform in it). With no more than that, the fit compared the latch's claim
    with a residual the lag had emptied of it, measured no residual at all, and 12 twins were
    covered 76.6 % (one 61 %); 12 twins now 96.5 %, ratios 1.04-1.15 (bench_uncertainty.py
    --reference-clock own); these two 94.9 %, 0.84-0.89."""
    from mmd_ros.core.terms import SamplingSkewTerm
    from mmd_ros.logs.layout import read_run
    errors, covs = [], []
    for seed in (1, 8):
        result, model, (e, c, _), log = _after_the_loop(tmp_path, seed, clock='own')
        lag = result.runs[0].lag
        assert lag is not None and lag.stated and 10e-6 < lag.delay_s < 50e-6, lag
        skew = [t for t in model.terms if isinstance(t, SamplingSkewTerm)]
        assert len(skew) == 1 and not skew[0].common_fitted, model.to_yaml()
        assert abs(float(np.mean(skew[0].skew_s))) < 5e-6, skew[0].skew_s
        budget = LengthBudget(DEVICE.with_latch_skew(50e-6), read_run(log).calibration, model)
        assert budget.latch_common_only and budget.latch_skew_s == pytest.approx(50e-6)
        errors += e
        covs += c
    ratio, covered = _judged(np.concatenate(errors), np.concatenate(covs))
    print('own clock: ratio', np.round(ratio, 2), 'coverage', covered)
    assert np.all(ratio > 0.8) and 0.93 <= covered <= 0.99, (ratio, covered)


def test_the_fitted_parameters_intervals_cover_the_twin_s_true_values():
    """`mmd analyze` prints each parameter with its 95 % interval: a claim about the physical
    parameter, which the twin knows (each channel's latch delay, the bars' sag). The fit's
    curvature alone (the residual's variance and autocorrelation) left out what a calibration
    draws once and a run carries throughout: its points' own errors, carried along a bar's
    length by Eq. (10), and the constants of the drift, the plate and the reference bar enter
    the fit's parameters wherever their signatures resemble them. On these four realistic
    twins (60 s of 6-DOF motion, full absolute pose) 17 of 24 channel delays lay within their
    interval (RMS 1.75 sigma) and the sag 6-13 sigma from the truth; with those constants propagated
    through the fit, and the sag (one figure for six bars) scaled by how far the bars agree
    on it, 22 of 24 (RMS 1.18; 8 twins 91.7 %, zeroed 89.6 %) and the sag within 0.9 sigma."""
    skew_z, sag_z = [], []
    for k in (2, 3, 4, 5):
        twin = TwinDevice(DEVICE, Effects.realistic(), seed=k + 1)
        result = bench_twin_analysis(k)     # its analysis on 60 s of motion (k = 5: test_session's)
        for f in result.found:
            rows = f.parameter_rows()
            value = np.array([r['value'] for r in rows])
            sigma = np.array([r['ci95'] for r in rows], dtype=float) / 1.96
            if f.effect == 'sampling_skew':
                truth = twin.physics.skew_s[DEVICE.measuring_channels] / 1e-6
                skew_z += list((value - truth) / sigma)
            elif f.effect == 'gravity_sag':
                true_um = Effects.realistic().gravity_sag_m / 1e-6
                sag_z.append(float((value[0] - true_um) / sigma[0]))
    skew_z = np.array(skew_z)
    print('delays: within 1.96 sigma', np.mean(np.abs(skew_z) <= 1.96), 'RMS z',
          np.sqrt(np.mean(skew_z ** 2)), 'sag z', np.round(sag_z, 2))
    assert skew_z.size == 24
    assert np.mean(np.abs(skew_z) <= 1.96) >= 0.85 and np.sqrt(np.mean(skew_z ** 2)) <= 1.4
    assert len(sag_z) >= 3 and np.all(np.abs(sag_z) <= 2.0), sag_z


# -- mmd process reports it -------------------------------------------------------------------
#: The twin's own encoder cyclic error: 80 nm at a 13 µm signal period (the calibration reads it).
TWIN_CYCLIC = Effects.ideal().with_assignments(('cyclic_error_m=8e-8', 'cyclic_period_m=1.3e-5'))


def _foreign_twin(k: int, length_error, datum: str,
                  fit=('random_motion', ['duration_s=60', 'seed={seed}'], 'pose6'), of_counts=False,
                  effects: Effects | None = None, **options):
    """An ideal twin (seed k + 1) whose bars read ``length_error(d)`` [m] more than the twin
    makes them (d the true lengths of a run in time order: an effect in a shape of someone
    else's; with ``of_counts`` d is the bars' counts the twin makes; ``effects`` the twin's own,
    ideal by default), analysed on ``fit``
    (scenario, parameters, reference; by default 60 s of random
    motion with a full pose reference; ``datum``: 'none' absolute, 'offset' zeroed). Returns the
    analysis, the calibration, the twin and ``run_of(params, start)`` -> (run, counts) of
    random 6-DOF motion. ``options``: further AnalysisOptions."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    from mmd_ros.twin import AmbientProfile
    meas = list(DEVICE.measuring_channels)
    room = AmbientProfile.constant(21.0)
    twin = TwinDevice(DEVICE, effects or Effects.ideal(), seed=k + 1)
    calibration = twin.calibrate(-211.0 * k, room, approaches=2)

    def run_of(params, start, scenario='random_motion', reference='pose6'):
        run = twin.simulate(make_scenario(scenario, params), room, start_s=start,
                            reference=reference, sample_rate_hz=200.0)
        counts = run.counts.astype(np.float64)
        counts[:, meas] += np.rint(length_error(counts[:, meas] if of_counts else run.true_lengths) / RES)
        return run, counts

    scenario, params, reference = fit
    run, counts = run_of([p.format(seed=100 + k) for p in params], 600.0, scenario, reference)
    log = run_log(twin, calibration, run, 600.0, counts)
    return analyze(log, options=AnalysisOptions(datum=datum, **options)), calibration, twin, run_of


#: Per bar, the size of an error of another's shape injected into the twins' readings [m].
FOREIGN_AMPLITUDE_M = np.array([0.30, 0.25, 0.35, 0.30, 0.28, 0.32]) * 1e-6


def _travel(k: int, reference: str) -> np.ndarray:
    """The true bar lengths (N, 6) [m] of the 40 s of random motion twin k is analysed on."""
    from mmd_ros.twin import AmbientProfile
    twin = TwinDevice(DEVICE, Effects.ideal(), seed=k + 1)
    return twin.simulate(make_scenario('random_motion', ['duration_s=40', f'seed={100 + k}']),
                         AmbientProfile.constant(21.0), start_s=600.0, reference=reference,
                         sample_rate_hz=200.0).true_lengths


@functools.lru_cache(maxsize=4)
def _bowed_twin(k: int, reference: str):
    """Twin k (ideal) analysed with a zeroed reference (``reference``) on 40 s of random motion,
    its bars reading a quadratic bow of their scale about the middle of the travel that motion
    covers: 0.25-0.35 µm from middle to end, zero mean over the run, after the calibration (it
    did not see it). As :func:`_foreign_twin`; made once for the tests that judge it."""
    amplitude = FOREIGN_AMPLITUDE_M
    travel = _travel(k, reference)
    mid, half = 0.5 * (travel.max(0) + travel.min(0)), 0.5 * (travel.max(0) - travel.min(0))
    mean = np.mean((travel - mid) ** 2, axis=0)
    return _foreign_twin(k, lambda d: amplitude / half ** 2 * ((d - mid) ** 2 - mean), 'offset',
                         fit=('random_motion', ['duration_s=40', 'seed={seed}'], reference))


def test_after_a_zeroed_fit_the_constant_it_could_not_see_is_claimed_from_the_pose_s_variation(tmp_path):
    """With a zeroed reference (an offset per pose component removed)
    the calibration-derived sources used to stay whole after the fit: 5-7 times the error in
    x, y and the rotations (6 twins in bench_uncertainty.py --after --datum offset), although
    the fit's length terms had corrected what they stand for. A constant error of the bars
    moves the pose by J^-1 c, and 6-DOF motion varies J^-1: the residual determines every
    constant but the common mode, which keeps what the sources not tied to a bar's length
    claim of it (the routine's drift, the reference bar; the bars' stated gravity sag, here
    0.1 um, while the analysis did not start from it: 223-246 nm in the common mode, the test
    below). The calibration's length-shaped errors are read from how each bar's error
    varied with its length, in the common mode as between the bars (their prior alone, the mean
    of their pointwise variance, claimed roll and pitch 2.5-2.8 times the error on these twins
    between the bars: ratios 1.31 1.67 1.55 2.51 2.83 1.57). Four twins, calibrated at
    different times of the room's day (each its own draw of what the routine's thermal
    history leaves in the common mode: calibrated at one time, the four shared one, z +35 to
    +46 nm on every one after the loop, 90.4 % with z 0.81), each judged with its own model
    on new motion: ratios 1.05 1.15 1.26 1.22 1.11 1.16, 98.7 % (z 1.05, 98.2 %, before the
    model claimed what the data leave of the stated sag it starts from). Before the analysis started
    from the bars' stated sag, calibrated at one time: ratios 1.08 1.14 1.71 1.25 1.17 1.21
    (x y z roll pitch yaw;
    1.09 1.13 1.69 1.31 1.15 1.21, 98.4 %, before each bar's estimated mean of its
    length-shaped error was shrunk by the noise its run's halves show; z 1.54, 98.6 %, while
    the common mode kept the calibration's whole claim and the sag was not claimed), 98.2 % in
    the 95 % ellipsoid, conservative beyond the lengths the fit saw
    (bench_uncertainty.py); 99.7 % (ratios 1.34-1.72) while the claim held how far a run's
    mean moves with where it dwells as if a run could dwell anywhere the fit saw, also where
    the calibration described the shape the model leaves."""
    from mmd_ros.core.model import FIT_REPLACEABLE
    errors, covs = [], []
    for seed in (1, 2, 3, 4):
        result, model, (e, c, _), _ = _after_the_loop(tmp_path, seed, datum='offset',
                                                      calibrate_at_s=-211.0 * seed)
        fit = model.uncertainty.fit
        assert fit.replaces == tuple(FIT_REPLACEABLE)
        common, differential = fit.record['unseen_common_mode_nm'], fit.record['unseen_differential_nm']
        print(seed, [f.effect for f in result.found], 'unseen: common', common, 'differential', differential)
        assert common > 0.0 and differential > 0.0
        noise = fit.record['shape_noise_nm']      # (the halves of the fitted run disagree)
        assert len(noise) == 6 and min(noise) >= 0.0 and max(noise) > 0.0, noise
        if seed == 1:       # the report says what the zeroed reference left unknown
            from mmd_ros.analysis.report import write_report
            report = write_report(result, tmp_path, figures=False)['report'].read_text()
            assert f'{common} nm along the common mode of the six bars' in report
            assert "length-shaped errors (its points', the interpolation between them) were read" in report
        errors += e
        covs += c
    ratio, cover = _judged(np.concatenate(errors), np.concatenate(covs))
    print('zeroed, after the loop: ratio', np.round(ratio, 2), 'coverage', cover)
    assert 0.93 <= cover <= 0.995, cover
    assert np.all((ratio >= 0.8) & (ratio <= 2.0)), ratio


def test_a_zeroed_fit_starts_from_the_bars_stated_sag(tmp_path):
    """A zeroed reference (a laser or tracker zeroed at its start) does not see the bars' common
    mode, which their gravity sag moves most (z). Started from the model as given, the fit's
    terms of free constants moved that mode with the sag's sign, and the common mode's claim
    was the sag's: z's RMS error on new motion 0.104 um (24 twins calibrated two-sided, 0.189
    um one-sided). The analysis starts from the sag the device description states (here the
    twin's 0.1 um): 0.028 um (0.063 um one-sided; this twin 0.034 um against 0.076 um); the
    term is written with the model and the report gives the model as given apart."""
    z, common = {}, {}
    for stated in (True, False):
        folder = tmp_path / str(stated)
        folder.mkdir()
        result, model, (e, _c, _m), _ = _after_the_loop(folder, 1, datum='offset',
                                                       calibrate_at_s=-211.0, stated_sag=stated)
        z[stated] = float(np.sqrt(np.mean(np.concatenate(e)[:, 2] ** 2)))
        common[stated] = model.uncertainty.fit.record['unseen_common_mode_nm']
        sag = [t for t in model.terms if t.type_name == 'gravity_sag']
        if stated:
            assert len(sag) == 1 and np.allclose(sag[0].sag_m, Effects.realistic().gravity_sag_m)
            assert len(result.stated) == 1 and 'bars.gravity_sag_nm' in result.stated[0]
            assert model.extra['analysis'][-1]['stated'] == result.stated
            assert 'Started from' in result.conclusion
            assert all(r.given is not None for r in result.runs)
            assert result.as_dict()['runs'][0]['held_out_as_given']
        else:
            assert not sag and not result.stated and result.runs[0].given is None
    print('z RMS on new motion, stated / as given [um]:', z[True] * 1e6, z[False] * 1e6,
          'common mode claimed [nm]:', common)
    assert z[True] < 0.5 * z[False], z
    # the sag no longer claimed in the common mode once the model corrects it
    assert common[False] > 4.0 * common[True], common


def test_the_data_check_the_stated_sag_and_the_model_claims_what_they_leave():
    """The statement the analysis starts from may be wrong (someone else's bars, a rounded
    figure). A zeroed reference sees how the sag varies with the pose: with the fit's effects in
    place, and every calibration point's error beside it (as uncertain as the budget claims),
    the data estimate the statement's error d +- s. Without a stated uncertainty the model
    claims sqrt(d^2 + s^2) of sag as an uncertainty of the pose: stated 50 nm for the twin's
    100 nm, trusted whole, z's error on new motion 0.056 um was claimed 0.031 um, 73 % in the
    ellipsoid (12 twins). With one (a twin that states its figure +- 15 %, its bars' own sag
    drawn so), the posterior of the two."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    room = ambient_profile('section_4_1')
    checks = {}
    spread = Effects.realistic().with_assignments(['gravity_sag_spread=0.15'])
    for stated_nm in (100.0, 50.0, None):
        device = DEVICE if stated_nm is None else DEVICE.with_gravity_sag(stated_nm * 1e-9)
        twin = TwinDevice(device, spread if stated_nm is None else Effects.realistic(), seed=1)
        calibration = twin.calibrate(0.0, room, approaches=2)
        run = twin.simulate(make_scenario('random_motion', ['duration_s=60', 'seed=100']), room,
                            start_s=600.0, reference='pose6')
        result = analyze(run_log(twin, calibration, run, 600.0),
                         options=AnalysisOptions(datum='offset'))
        check = checks[stated_nm] = result.stated_check
        assert check is not None and check['sigma_nm'] > 0, result.stated
        directions = [t for group in result.model.uncertainty.fit.directions for t in group
                      if t.type_name == 'gravity_sag']
        assert directions, 'the statement\'s error is claimed with the model'
        if stated_nm is None:       # the twin's own statement: 100 +- 15 nm, its sag drawn
            assert check['prior_nm'] == pytest.approx(15.0) and not check['disputed']
            assert check['claimed_nm'] < math.hypot(check['error_nm'], check['sigma_nm'])
            true_error = float(twin.physics.sag_m) * 1e9 - 100.0
            assert abs(true_error) < 2.0 * check['claimed_nm'], (true_error, check)
            assert '(stated ± 15 nm): together, claimed with the model' in result.stated[0]
            continue
        assert check['prior_nm'] is None
        claimed = math.hypot(check['error_nm'], check['sigma_nm'])
        assert check['claimed_nm'] == pytest.approx(claimed)
        if stated_nm == 50.0:
            new = twin.simulate(make_scenario('random_motion', ['duration_s=8', 'seed=200']), room,
                                start_s=700.0, reference='pose6')
            res = Pipeline(twin.documented_device, calibration, result.model).process(
                new.times_s, new.counts, with_covariance=True)
            e = pose_error(res.poses, new.true_poses)[res.valid]
            z_claim = math.sqrt(float(np.mean(res.covariance[res.valid][:, 2, 2])))
            z_error = math.sqrt(float(np.mean(e[:, 2] ** 2)))
            print('stated 50 nm: z claimed', z_claim * 1e9, 'nm, error', z_error * 1e9, 'nm')
            assert z_claim >= 0.8 * z_error
    print('the data on the statement [nm]:', checks)
    # an exact statement is not disputed (s is smaller than d's scatter about the truth: 29 nm
    # RMS where s was 16-20 nm, 12 twins), and the half one is put 50 nm further off: the
    # check measures the statement's error on the same data
    assert abs(checks[100.0]['error_nm']) < 3.0 * checks[100.0]['sigma_nm']
    wrong = checks[50.0]
    assert wrong['error_nm'] - checks[100.0]['error_nm'] == pytest.approx(50.0, abs=5.0)
    assert wrong['claimed_nm'] > 0.5 * 50.0


def test_on_short_runs_the_check_of_an_exact_statement_seldom_disputes_it():
    """On 5 s of motion (one-sided calibration, zeroed reference) the check's sigma took the
    residual's variance as all it knew: the estimate of an exact statement's error lay 5.8,
    1.9, 5.1, 6.5, 0.8 and 2.9 sigma from zero on six twins (the one at 6.5 put it at 33 µm
    with a kinematic term in the fit). It now leaves the parameters the fit did not determine
    as free as the model claims them, and takes the spread of the estimate over groups of time
    blocks when that is larger: 1.5, 1.6, 5.0, 1.3, 0.3, 2.8 (one twin of six still disputes
    an exact statement: not traced further)."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    room = ambient_profile('section_4_1')
    z = []
    for k in range(6):
        twin = TwinDevice(DEVICE, Effects.realistic(), seed=k + 1)
        calibration = twin.calibrate(-211.0 * k, room, approaches=1)
        run = twin.simulate(make_scenario('random_motion', ['duration_s=5', f'seed={k}']), room,
                            start_s=600.0, reference='pose6')
        check = analyze(run_log(twin, calibration, run, 600.0),
                        options=AnalysisOptions(datum='offset')).stated_check
        z.append(check['error_nm'] / check['sigma_nm'])
    print('the exact statement\'s error over its sigma:', np.round(z, 2))
    assert sum(abs(v) > 3.0 for v in z) <= 1


def test_a_statement_the_data_do_not_check_is_claimed_whole():
    """Where the runs do not exercise the bars' inclination (or identify no direction of the
    sag), the stated figure is not checked and the model claims its stated uncertainty, or
    without one the whole figure; where they do, sqrt(d^2 + s^2) without a stated uncertainty,
    and with one sigma_p the posterior's sqrt(m^2 + v), unless d lies beyond 3 sqrt(s^2 +
    sigma_p^2) (the data dispute the statement), or unless s is no smaller than the figure (the
    data do not determine the sag to its own size: not checked); a sag the fit added itself,
    or no statement, claims nothing here."""
    from types import SimpleNamespace
    from mmd_ros.analysis.identify import _check_statement
    from mmd_ros.core.terms import GravitySagTerm
    geo = DEVICE.geometry
    stated = [GravitySagTerm(geo.upper, geo.lower, np.full(6, 1e-7))]

    def selector(got):
        def check(effect, nuisance=()):
            assert effect.name == 'gravity_sag'
            assert [(e.name, sd.shape) for e, sd, _ in nuisance] == [('calibration_points', (42,))]
            return got
        return SimpleNamespace(active=[], check=check, runs=[],
                               parameters=lambda effect, hyper: [None] * 42)

    for got in (None, (np.array([np.nan]), np.array([np.nan])), (np.zeros(1), np.zeros(1))):
        for prior, whole in ((None, 100.0), (15e-9, 15.0)):
            effects, check = _check_statement(selector(got), stated, prior)
            assert check['error_nm'] is None and check['claimed_nm'] == pytest.approx(whole)
            assert len(effects) == 1
            assert effects[0].covariance[0, 0] == pytest.approx((whole * 1e-9) ** 2)
    effects, check = _check_statement(selector((np.array([3e-8]), np.array([4e-8]))), stated)
    assert check['claimed_nm'] == pytest.approx(50.0) and check['error_nm'] == pytest.approx(30.0)
    assert effects[0].covariance[0, 0] == pytest.approx(2.5e-15) and not check['disputed']
    # with a stated uncertainty of 30 nm: m = 30 * 900 / 2500, v = 900 * 1600 / 2500
    effects, check = _check_statement(selector((np.array([3e-8]), np.array([4e-8]))), stated,
                                      30e-9)
    assert check['claimed_nm'] == pytest.approx(math.hypot(10.8, 24.0)), check
    assert check['prior_nm'] == pytest.approx(30.0) and not check['disputed']
    # d = 160 nm lies beyond 3 * 50 nm: the data dispute the statement and are claimed alone
    effects, check = _check_statement(selector((np.array([1.6e-7]), np.array([4e-8]))), stated,
                                      30e-9)
    assert check['disputed'] and check['claimed_nm'] == pytest.approx(math.hypot(160.0, 40.0))
    # s = 1.3 µm, no better than the 100 nm figure: not a check, however far d lies
    for prior, whole in ((None, 100.0), (15e-9, 15.0)):
        effects, check = _check_statement(selector((np.array([7e-6]), np.array([1.3e-6]))),
                                          stated, prior)
        assert check['undetermined'] and not check['disputed'], check
        assert check['claimed_nm'] == pytest.approx(whole) and check['error_nm'] > 0
    assert not _check_statement(selector((np.array([3e-8]), np.array([4e-8]))), stated
                                )[1]['undetermined']
    fitted = SimpleNamespace(effect=SimpleNamespace(name='gravity_sag'))
    assert _check_statement(SimpleNamespace(active=[fitted], check=None), stated) == ([], None)
    assert _check_statement(SimpleNamespace(active=[], check=None), []) == ([], None)


def test_the_report_names_the_bars_whose_length_error_the_calibration_does_not_describe():
    from mmd_ros.analysis.report import _shape_text
    described = _shape_text([12.0] * 6, [1.0] * 6)
    assert '12.0 nm RMS per bar' in described and 'held more' not in described
    wide = _shape_text([12.0] * 6, [1.0, 1.0, 4.0, 1.0, 100.0, 1.0])
    assert ('bar3 (2.0 ×), bar5 (10.0 ×) held more of that shape than the calibration '
            'describes') in wide


def test_a_constant_between_the_bars_is_read_from_the_pose_s_variation_and_the_common_mode_is_not():
    """The posterior behind a zeroed fit's claim, on a synthetic residual: 6-DOF motion, a
    constant bar error c seen through a zeroed reference (J^-1(t) c minus its mean over the
    log) plus white noise. The runs determine c between the bars (the estimate within 3
    sigma of it, sigma a small share of the prior) and say nothing of its common mode, which
    keeps the prior; two logs, each zeroed on its own, know more than one."""
    from types import SimpleNamespace
    from mmd_ros.analysis.data import Observation
    from mmd_ros.analysis.uncertainty import _unseen_constants
    from mmd_ros.core.kinematics import jacobian
    twin = TwinDevice(DEVICE, Effects.ideal(), seed=1)
    room = ambient_profile('constant:20')
    rng = np.random.default_rng(5)
    c = np.array([60.0, -40.0, 25.0, -10.0, 80.0, -55.0]) * 1e-9
    prior = np.eye(6) * (200e-9) ** 2
    noise = np.array([30e-9, 30e-9, 10e-9, 100e-9, 100e-9, 200e-9])

    def part(seed):
        run = twin.simulate(make_scenario('random_motion', ['duration_s=20', f'seed={seed}']), room,
                            start_s=0.0, sample_rate_hz=200.0)
        poses = run.true_poses[np.all(np.isfinite(run.true_poses), axis=1)]
        dp = np.einsum('nij,j->ni', np.linalg.inv(jacobian(DEVICE.geometry, poses)), c)
        residual = dp - dp.mean(axis=0) + rng.normal(size=dp.shape) * noise
        obs = Observation('pose', list(range(6)), ['x', 'y', 'z', 'roll', 'pitch', 'yaw'],
                          ['um'] * 3 + ['arcsec'] * 3, np.zeros_like(poses),
                          np.ones(poses.shape[0], bool), True)
        ctx = SimpleNamespace(obs=obs, device=DEVICE)
        run = SimpleNamespace(ctx=ctx, after=SimpleNamespace(poses=poses), residual=residual)
        return run, np.arange(poses.shape[0]), None, None

    one = part(1)
    unseen, estimate = _unseen_constants([one], prior)
    common = np.full(6, 1.0 / math.sqrt(6.0))
    between = np.eye(6) - np.outer(common, common)
    posterior = unseen - np.outer(estimate, estimate)
    sigma = np.sqrt(np.diag(between @ posterior @ between))
    print('between the bars: estimate - c [nm]', np.round((between @ (estimate - c)) * 1e9, 1),
          'sigma', np.round(sigma * 1e9, 1))
    assert np.all(np.abs(between @ (estimate - c)) <= 3 * sigma)
    assert np.all(sigma < 0.3 * 200e-9)
    assert abs(common @ estimate) < 1e-12                          # nothing read along it
    assert math.isclose(common @ posterior @ common, (200e-9) ** 2, rel_tol=1e-6)
    two, _ = _unseen_constants([one, part(2)], prior)
    assert np.trace(between @ two @ between) < np.trace(between @ unseen @ between)


def test_the_mean_of_a_length_shaped_error_is_read_from_how_it_varied_where_a_run_passed_the_points():
    """The calibration's length-shaped errors (each point's error carried linearly between
    the points, the smooth error between them that is zero at the points) are functions of a
    bar's length: a zeroed run that passed through the points saw how the function varied
    and so knows its mean; one that stayed between two points knows less of it. On draws of
    that Gaussian function for six bars, the conditional mean's estimate lies within 3 sigma
    of the true mean over the run; sigma is a tenth of the mean's prior where the bars swept
    several points (3 nm of 32 nm), several times more where they stayed mid-segment. A
    shape five times what the budget expects widens the covariance (the marginal
    likelihood's factor) and the estimate still holds. How far a new run's mean of the shape
    moves with where it dwells is claimed for the part of the shape beyond the description
    (the factor's share 1 - 1/a of its spread): nearly all of the spread for the shape five
    times the description, nothing for a shape it describes where the bars swept the points
    (the whole spread made the claim 1.2-1.3 times the error of new runs on the twin)."""
    from types import SimpleNamespace
    from mmd_ros.analysis.uncertainty import _shape_constants
    from mmd_ros.core.terms import CdfOffsetsTerm
    rng = np.random.default_rng(3)
    budget, grid = _shape_budget()
    knots = budget.knots_m
    hat = -CdfOffsetsTerm.basis(np.repeat(grid[:, None], 6, axis=1), knots)[:, 0, :]
    cov = budget.interpolation.covariance(grid, grid, knots[0]) + budget.point_var_m2 * hat @ hat.T
    ev, v = np.linalg.eigh(cov)
    draws = (v * np.sqrt(np.maximum(ev, 0.0))) @ rng.standard_normal((grid.size, 6))   # (G, 6)

    def zeroed_run(lo, hi):
        t = np.linspace(0.0, 1.0, 3000)
        lengths = lo + (hi - lo) * 0.5 * (1.0 - np.cos(2 * np.pi * 3 * t[:, None] + np.arange(6)))
        error = np.column_stack([np.interp(lengths[:, b], grid, draws[:, b]) for b in range(6)])
        residual = error - error.mean(axis=0) + rng.normal(size=error.shape) * 5e-9
        run = SimpleNamespace(ctx=SimpleNamespace(obs=SimpleNamespace(datum=True)),
                              after=SimpleNamespace(cdf_lengths_m=lengths))
        return (run, np.arange(t.size), residual, np.zeros_like(residual)), error.mean(axis=0)

    swept = None
    for lo, hi, size in ((0.22, 0.44, 1.0), (0.36, 0.39, 1.0), (0.22, 0.44, 5.0)):
        draws *= size
        part, truth = zeroed_run(lo, hi)
        draws /= size
        var, mean, moves, factor = _shape_constants([part], budget, 1.0, [])    # no term fitted
        error = np.column_stack([np.interp(lengths_b, grid, draws[:, b] * size) for b, lengths_b
                                 in enumerate(part[0].after.cdf_lengths_m.T)])
        spread = np.var(error, axis=0)
        lengths = part[0].after.cdf_lengths_m
        sigma = np.sqrt(var)
        k = np.array([_mean_sd(cov, grid, lengths[::10, b]) for b in range(6)])
        print(f'{lo * 1e3:.0f}-{hi * 1e3:.0f} mm: estimate - truth [nm]', np.round((mean - truth) * 1e9, 1),
              'sigma', np.round(sigma * 1e9, 1), 'prior', np.round(k * 1e9, 1), 'factor', factor,
              'moves / spread', np.round(moves / spread, 2))
        assert np.all(np.abs(mean - truth) <= 3 * sigma + 2e-9)
        if swept is None:
            assert np.all(sigma < 0.2 * k)
            swept = sigma
        elif size == 1.0:
            assert np.all(sigma > 3 * swept)
        else:     # five times the shape the budget expects: the covariance widened to it
            assert np.all(sigma > 2 * swept)
        if size == 5.0:
            assert np.all(factor >= 10.0) and np.all(moves >= 0.8 * spread)
        elif hi - lo > 0.1:     # (mid-segment, 30 mm of a shape is too little to tell a)
            assert np.all(moves <= 0.35 * spread)     # a = 1, or the grid's next step 1.47


def test_a_shape_s_mean_its_run_s_halves_disagree_on_is_not_claimed_whole():
    """The square of a noisy estimate overstates what it estimates by its noise. The shape's
    mean over a run, estimated from each half of the run, measures that noise: with white read
    noise the halves of a run whose bars swept the points agree to a nanometre; read noise that
    is not white (a slow random walk, as vibration or a warming readhead make) is read into
    each half's shape differently, and the halves disagree."""
    from types import SimpleNamespace
    from mmd_ros.analysis.uncertainty import _shape_constants, _shape_noise
    rng = np.random.default_rng(5)
    budget, grid = _shape_budget()
    knots = budget.knots_m
    cov = budget.interpolation.covariance(grid, grid, knots[0])
    ev, v = np.linalg.eigh(cov)
    draws = (v * np.sqrt(np.maximum(ev, 0.0))) @ rng.standard_normal((grid.size, 6))
    t = np.linspace(0.0, 1.0, 3000)
    lengths = 0.22 + 0.22 * 0.5 * (1.0 - np.cos(2 * np.pi * 3 * t[:, None] + np.arange(6)))
    error = np.column_stack([np.interp(lengths[:, b], grid, draws[:, b]) for b in range(6)])
    run = SimpleNamespace(ctx=SimpleNamespace(obs=SimpleNamespace(datum=True)),
                          after=SimpleNamespace(cdf_lengths_m=lengths))
    walk = np.cumsum(rng.normal(size=error.shape), axis=0)
    noise = {}
    for name, extra in (('white', rng.normal(size=error.shape) * 5e-9),
                        ('random walk', walk / np.std(walk, axis=0) * 30e-9)):
        residual = error + extra
        part = (run, np.arange(t.size), residual - residual.mean(axis=0), np.zeros_like(residual))
        noise[name] = np.sqrt(_shape_noise([part], budget, 1.0, []))
        mean = _shape_constants([part], budget, 1.0, [])[1]
        print(name, 'noise nm', np.round(noise[name] * 1e9, 1), 'estimate - truth',
              np.round((mean - error.mean(axis=0)) * 1e9, 1))
    assert np.all(noise['white'] < 2e-9)
    rms = {name: float(np.sqrt(np.mean(v * v))) for name, v in noise.items()}
    assert rms['random walk'] > 3.0 * rms['white'], rms
    short = (run, np.arange(300), error[:300], np.zeros((300, 6)))
    assert np.all(_shape_noise([short], budget, 1.0, []) == 0.0)      # (halves too short)


def _shape_budget():
    """What the shape's conditional reads of a budget, for six bars with seven points over
    200-500 mm: a 0.3 um smooth error of 40 mm correlation between them, 5 nm per point;
    and a grid of lengths over that span to draw the error on."""
    from types import SimpleNamespace
    from mmd_ros.core.uncertainty import InterpolationError
    knots = np.tile(np.linspace(0.20, 0.50, 7), (6, 1))
    budget = SimpleNamespace(interpolation=InterpolationError(0.3e-6, 0.04), knots_m=knots,
                             point_var_m2=(5e-9) ** 2, point_friction_m2=np.zeros(6),
                             resolution_m=50e-9, subdivision_left_m2=np.zeros(6))
    return budget, np.linspace(0.19, 0.51, 600)


def _mean_sd(cov: np.ndarray, grid: np.ndarray, lengths: np.ndarray) -> float:
    """The standard deviation of a Gaussian function's mean over ``lengths`` (its covariance
    ``cov`` tabulated on ``grid``, read at the nearest grid lengths)."""
    at = np.clip(np.searchsorted(grid, lengths), 0, grid.size - 1)
    return float(np.sqrt(np.mean(cov[np.ix_(at, at)])))


def test_what_a_fit_left_where_it_saw_only_a_segment_s_flank_is_measured_and_claimed_there(tmp_path):
    """Where a bar's fitted lengths end inside a CDF segment, its length term is least
    determined (the bar always arrives there from one side). On this realistic twin (the
    eighth of bench_uncertainty.py's 24) bar 5 sees 266-361 mm and the middle of its segments
    from 278 mm. Its analysis once left bar 5 0.29 µm off at 266-278 mm (the twin's gravity sag
    set aside, its share taken by the scale term): it now leaves 0.035 µm there on new motion,
    inside the claim. A length error of another shape, a 0.4 µm bump over those 12 mm that no
    term has, is what the fit's held-out residual holds there: claimed where along the bar it
    lay (the residual's profile, ``uncertainty.fit.profile``), 99 % of those samples within
    1.96 sigma, 66 % with the residual alike at every length and no flank claim. Before the
    profile, what the residual held there beyond the model's claim was claimed there alone
    (``flank_nm2``, 129 nm on bar 5, 9 nm on bar 4, nothing on the others): 82 % (96 nm, 79 %
    and 70 % while the calibration's sources came back in the flank); the profile leaves it
    nothing beyond its claim."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    from mmd_ros.core.kinematics import jacobian
    k, bar, low, high = 7, 4, 0.26628, 0.27803    # bar 5's flank [m], as the fit run sees it
    room = ambient_profile('section_4_1')
    twin = TwinDevice(DEVICE, Effects.preset('realistic'), seed=k + 1)
    calibration = twin.calibrate(-211.0 * k, room, approaches=2)
    fitted = twin.simulate(make_scenario('random_motion', ['duration_s=60', f'seed={100 + k}']),
                           room, start_s=600.0, reference='pose6')
    new = twin.simulate(make_scenario('random_motion', ['duration_s=60', f'seed={200 + k}']), room,
                        start_s=700.0, reference='pose6')
    meas = list(DEVICE.measuring_channels)

    def counts_of(run, size):
        u = np.clip((run.true_lengths[:, bar] - low) / (high - low), 0.0, 1.0)
        counts = run.counts.astype(np.float64)
        counts[:, meas[bar]] += np.rint(size * np.sin(np.pi * u) ** 2 / RES)
        return counts

    def at_the_flank(model, size):
        """RMS of bar 5's J dp and of its claimed sigma where it lies in the flank of new
        motion, and the share within 1.96 sigma."""
        pipeline = Pipeline(twin.documented_device, calibration, model)
        res = pipeline.process(new.times_s, counts_of(new, size), with_covariance=True)
        ok = res.valid
        error = np.einsum('nij,nj->ni', jacobian(twin.documented_device.geometry, res.poses[ok]),
                          pose_error(res.poses, new.true_poses)[ok])[:, bar]
        comp, th = res.compensated, res.compensated.thermal
        budget = pipeline.budget
        budget.reset()
        observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m, new.times_s)
        var = budget.covariance(comp.lengths_m[ok], th.reference_error_m[ok], th.temp_change_c[ok],
                                th.bar_error_m[ok], comp.fit_columns_m[ok], observed[ok])[:, bar, bar]
        there = budget.flank(comp.cdf_lengths_m[ok])[:, bar]
        assert there.sum() > 500
        return (math.sqrt(np.mean(error[there] ** 2)), math.sqrt(np.mean(var[there])),
                float(np.mean(np.abs(error[there]) <= 1.96 * np.sqrt(var[there]))))

    figures = {}
    for size in (0.0, 0.4e-6):
        # (without the bump, the analysis of test_session's bench_twin_analysis(7): the same log)
        result = bench_twin_analysis(k) if not size else analyze(
            run_log(twin, calibration, fitted, 600.0, counts_of(fitted, size)),
            options=AnalysisOptions(datum='none'))
        model = result.model
        flank = model.uncertainty.fit.flank_m2
        without = Model.from_dict(model.to_dict())
        without.uncertainty.fit.flank_m2 = np.zeros(6)
        without.uncertainty.fit.profile = None
        figures[size] = (flank, at_the_flank(model, size), at_the_flank(without, size))
        print(f'bump {size * 1e6:.1f} um: flank nm', np.round(np.sqrt(flank) * 1e9),
              'error, sigma, coverage with the claim', figures[size][1], 'without', figures[size][2])
    flank, (error, _, covered), _ = figures[0.0]
    assert error < 0.1e-6 and covered >= 0.95
    assert np.all(np.sqrt(flank) < 0.05e-6)
    flank, (error, sigma, covered), (_, sigma_without, covered_without) = figures[0.4e-6]
    assert error > 0.1e-6                                      # the bump is left there
    assert model.uncertainty.fit.profile is not None
    assert model.uncertainty.fit.profile.lengths_m[bar].size, 'no profile along bar 5'
    assert sigma > 1.1 * sigma_without and covered > covered_without + 0.05 and covered >= 0.95
    from mmd_ros.analysis.report import write_report
    report = write_report(result, tmp_path, figures=False)['report'].read_text()
    assert f'| bar5 | {math.sqrt(model.uncertainty.fit.residual_m2[bar, bar]) * 1e9:.1f} | – | ' \
        in report and 'uncertainty.fit.profile' in report


@pytest.mark.parametrize('datum', ['none', 'offset'])
def test_after_the_loop_a_scale_error_of_another_shape_is_covered_where_the_fit_did_not_look(datum):
    """The data judged by others come with effects the twin does not make. Here a length error
    of another shape than the twin's (a bow across the bar plus a 37 mm sine: not periodic over
    the CDF span) is added to the counts of four ideal twins; each is analysed on 60 s of
    random motion (full pose) and judged against its true pose on 8 s of other motion. The
    fit's harmonics once swung to 3 µm beyond the lengths it saw where the error was 0.2 µm,
    and the budget had no claim for an error that the calibration never saw: 91.0 % in the
    95 % ellipsoid, 61 % where a bar left the lengths the fit saw. Now the correction beyond
    them is held within what it did within them, the size of what it corrected there is
    claimed beyond them (growing from the bound as a smooth error's unknown share does), and a
    CDF point no sample came near is not fitted: measured 95.6 % (92.4 % there, 15 % of the
    samples; 95.8 % and 93.5 % with that size claimed whole from the bound on). With the
    zeroed reference the claim holds the constant per bar its residual suggests (the
    fit held its terms back from the means it could not see): 99.8 %, ratios 1.11-3.16 (89.1 %
    where every bar lay within the fitted lengths when that constant was not claimed)."""
    errors, covs, outside = [], [], []
    for k in range(4):
        g = np.random.default_rng(100 + k)
        bow, ripple, phase = g.uniform(-1, 1, 6) * 0.4e-6, g.uniform(0.1, 0.3, 6) * 1e-6, g.uniform(0, 6.3, 6)
        result, calibration, twin, run_of = _foreign_twin(k, lambda d: (
            bow * ((d - 0.33) / 0.06) ** 2 + ripple * np.sin(2 * np.pi * d / 0.037 + phase)), datum)
        assert 'scale_nonlinearity' in [f.effect for f in result.found], result.conclusion
        run, counts = run_of(['duration_s=8', f'seed={k}'], 700.0)
        res = Pipeline(twin.documented_device, calibration, result.model).process(
            run.times_s, counts, with_covariance=True)
        errors.append(pose_error(res.poses, run.true_poses)[res.valid])
        covs.append(res.covariance[res.valid])
        bars = Validity.from_model(result.model).bar_range_m
        cdf = res.compensated.cdf_lengths_m[res.valid]
        outside.append(~np.all((cdf >= bars[:, 0]) & (cdf <= bars[:, 1]), axis=1))
    e, c, out = np.concatenate(errors), np.concatenate(covs), np.concatenate(outside)
    d2 = _d2(e, c)
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0) / np.mean(e * e, axis=0))
    print('coverage', np.mean(d2 <= LIMIT), 'outside', np.mean(d2[out] <= LIMIT), out.mean(),
          'inside', np.mean(d2[~out] <= LIMIT), 'ratio', np.round(ratio, 2))
    assert 0.05 < out.mean() < 0.5
    assert np.mean(d2[out] <= LIMIT) >= 0.9
    if datum == 'none':
        assert 0.93 <= np.mean(d2 <= LIMIT) <= 0.97
    else:       # conservative by design, and no longer 3-5 x in every component
        assert np.mean(d2[~out] <= LIMIT) >= 0.95 and np.all((ratio >= 0.8) & (ratio <= 4.0)), ratio


@functools.lru_cache(maxsize=4)
def _bumped_twin(k: int):
    """Twin k (ideal) analysed zeroed on 60 s of random motion, its bars reading a localised
    length error (a 4 mm Gaussian bump of up to 0.5 µm, a shape no term has), as
    :func:`_foreign_twin`; made once for the tests that judge it."""
    g = np.random.default_rng(100 + k)
    centre, size = g.uniform(0.30, 0.36, 6), g.uniform(-1, 1, 6) * 0.5e-6
    return _foreign_twin(k, lambda d: size * np.exp(-0.5 * ((d - centre) / 0.004) ** 2), 'offset')


def test_a_zeroed_fit_of_a_localised_length_error_moves_no_mean_it_cannot_see():
    """A zeroed reference (``--datum offset``) sees how each component
    varies, not its mean. A localised length error (a 4 mm Gaussian bump of up to 0.5 µm on
    each bar, a shape no term has) was fitted with the CDF points and harmonics, whose
    combination carried 2.4 µrad of constant pitch that the zeroed residual could not show
    (0.44 µrad before): pitch 0.56 -> 2.34 µrad on new motion, and 0 % of it in the 95 %
    ellipsoid. The fit may now move a component's mean only as far as the budget claims for
    it, and the budget's calibration-derived sources are scaled to claim as much as the terms
    of free constants corrected: measured mean changes of at most 2.6 and 1.7 times the
    claimed sigma (pitch 1.4 and 0.9), 100 % in the ellipsoid on the new motion of both twins.
    The second twin's fit holds a drift, which the model written leaves out: its other terms
    are refitted without it (written as fitted with it, yaw's mean moved 48 times the claim).
    That drift is a settling of a few nm whose offsets (0.14-0.85 µm) stood in for the CDF
    points' constants, which the refitted points took over; claimed again as the run's own,
    new motion's sigma was 7.8-17.4 times its error. What the model's terms took over of a
    drift is now not claimed as the run's: 1.21-2.62 (the other twin 0.97-1.74); 0.97-2.61
    measured again, 0.81-1.46 with the points' directions chosen again without the drift and
    its parameter covariance no longer claimed (the other twin 1.04-1.91), 97.6 % of both."""
    errors, covs = [], []
    for k in (0, 1):
        result, calibration, twin, run_of = _bumped_twin(k)
        assert result.model is not None, result.conclusion
        fit, counts = run_of(['duration_s=60', f'seed={100 + k}'], 600.0)
        means, claimed = [], None
        for model in (Model(), result.model):
            res = Pipeline(twin.documented_device, calibration, model).process(
                fit.times_s, counts, with_covariance=claimed is None)
            means.append(np.mean(pose_error(res.poses, fit.true_poses)[res.valid], axis=0))
            if claimed is None:     # what the budget claims before the fit
                claimed = np.sqrt(np.mean(np.diagonal(res.covariance[res.valid], axis1=1, axis2=2), axis=0))
        print('mean change / claimed sigma', np.round((means[1] - means[0]) / claimed, 2))
        assert np.all(np.abs(means[1] - means[0]) <= 3.0 * claimed)
        run, counts = run_of(['duration_s=8', f'seed={k}'], 700.0)
        res = Pipeline(twin.documented_device, calibration, result.model).process(
            run.times_s, counts, with_covariance=True)
        errors.append(pose_error(res.poses, run.true_poses)[res.valid])
        covs.append(res.covariance[res.valid])
        ratio = np.sqrt(np.mean(np.diagonal(covs[-1], axis1=1, axis2=2), axis=0)
                        / np.mean(errors[-1] ** 2, axis=0))
        print('predicted / observed sigma', np.round(ratio, 2))
        assert np.all(ratio < 3.0), ratio
    e, c = np.concatenate(errors), np.concatenate(covs)
    d2 = _d2(e, c)
    print('coverage', np.mean(d2 <= LIMIT))
    assert np.mean(d2 <= LIMIT) >= 0.93


def test_a_local_error_a_fit_run_crossed_rarely_is_claimed_where_it_was_seen():
    """The localised length error above (a 4 mm Gaussian bump of up to 0.5 µm per bar) on four
    twins, zeroed: where a bar crossed its bump for a few seconds of the fitted run, one half
    of the run may not hold it and no profile along the bar predicts the other half better
    than the flat claim; a new run that dwells there was covered 60.5 % (one twin; 89.9 % of
    all four's samples). What stood out of the mean where it was seen is now claimed there.
    Where a profile does predict the other half, its estimate at each length starts from the
    mean excess and moves off it as far as the independent samples there allow: twin 2's bar 5
    crossed its -391 nm bump twice (97 of 12000 samples, 5 independent ones), its profile
    claimed 97 nm there where the error was 321 nm, and a new run that dwelt on it for 35 % of
    its samples was covered 79 %; what stands out of the mean is now claimed there too."""
    errors, covs, flats = [], [], []
    for k in range(4):
        result, calibration, twin, run_of = _bumped_twin(k)
        flat = copy.deepcopy(result.model)
        flat.uncertainty.fit.profile = None
        run, counts = run_of(['duration_s=8', f'seed={k}'], 700.0)
        for model, into in ((result.model, covs), (flat, flats)):
            res = Pipeline(twin.documented_device, calibration, model).process(
                run.times_s, counts, with_covariance=True)
            into.append(res.covariance[res.valid])
        errors.append(pose_error(res.poses, run.true_poses)[res.valid])
    each = [float(np.mean(_d2(e, c) <= LIMIT)) for e, c in zip(errors, covs)]
    e = np.concatenate(errors)
    with_, without = (float(np.mean(_d2(e, np.concatenate(c)) <= LIMIT)) for c in (covs, flats))
    print('coverage', round(with_, 3), 'each twin', np.round(each, 3),
          'claimed alike at every length', round(without, 3))
    assert without < 0.92 and with_ >= 0.93 and min(each) >= 0.93, each


def test_a_zeroed_fit_of_a_bow_beyond_its_points_leaves_the_level_it_cannot_see():
    """A quadratic bow of each bar's scale about the middle of its travel (0.25-0.35 µm from
    middle to end, zero mean over the fitted run), fitted with a zeroed pose reference: the
    CDF points just beyond the travel, which the samples reach only through the tail of their
    ramp, were held at zero, and the bow's level was fitted to meet them: every bar 0.15 µm
    low, z's mean on the fitted run moved 0.19-0.32 µm (the zeroed reference cannot see it),
    and on new motion z was worse than without the model on all four twins (0.06-0.17 ->
    0.20-0.33 µm). Those points may now lie on the line of the points seen beside them, and
    the data choose it (the setting 'line'): measured z
    mean moved at most 0.014 µm, and on new motion every component within its noise floor of
    the unchanged model or better (z 0.06-0.17 -> 0.01-0.07 µm)."""
    to_report = np.array([1e6] * 3 + [1e6 * math.pi / (180 * 3600)] * 3)     # (floors: µm, ″)
    for k in range(4):
        result, calibration, twin, run_of = _bowed_twin(k, 'pose6')
        assert [(f.effect, f.hyper) for f in result.found] == [('calibration_points', 'line')], \
            result.conclusion
        floor = np.array([result.runs[0].floor[n] for n in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')])
        figures = []
        for params, start in ((['duration_s=40', f'seed={100 + k}'], 600.0),
                              (['duration_s=20', f'seed={k}'], 700.0)):
            run, counts = run_of(params, start)
            for model in (Model(), result.model):
                res = Pipeline(twin.documented_device, calibration, model).process(
                    run.times_s, counts)
                e = pose_error(res.poses, run.true_poses)[res.valid]
                figures.append((e.mean(axis=0), np.sqrt(np.mean(e * e, axis=0))))
        (mean0, _), (mean1, _), (_, before), (_, after) = figures
        print(k, 'z mean moved', round((mean1[2] - mean0[2]) * 1e6, 3), 'µm; new motion',
              np.round(before * 1e6, 3), '->', np.round(after * 1e6, 3))
        assert abs(mean1[2] - mean0[2]) < 0.05e-6
        assert after[2] < before[2]
        assert np.all(after <= before + floor / to_report), (before, after)


def test_a_bow_beyond_the_lengths_the_fit_saw_is_claimed_as_it_grows():
    """The bowed twins' new motion where a bar lies beyond the lengths the fit saw: the CDF
    points' correction there follows points no data checked (held on the line of those seen,
    then zero), while the bow goes on growing. Claimed from how far the correction moved from
    its value at the bound, 48.5 % and 85.5 % of those samples were in the 95 % ellipsoid on
    two of the four twins; with the trend the points followed within the lengths seen,
    continued, 98.8-100 % on every twin."""
    for k in range(4):
        result, calibration, twin, run_of = _bowed_twin(k, 'pose6')
        run, counts = run_of(['duration_s=20', f'seed={k}'], 700.0)
        res = Pipeline(twin.documented_device, calibration, result.model).process(
            run.times_s, counts, with_covariance=True)
        bars = Validity.from_model(result.model).bar_range_m
        cdf = res.compensated.cdf_lengths_m
        beyond = res.valid & np.any((cdf < bars[:, 0]) | (cdf > bars[:, 1]), axis=1)
        e = pose_error(res.poses, run.true_poses)[beyond]
        covered = np.mean(_d2(e, res.covariance[beyond]) <= LIMIT)
        print(k, 'beyond', round(float(beyond.mean()), 3), 'covered', round(float(covered), 3))
        assert beyond.mean() > 0.05
        assert covered >= 0.93


#: Where along the travel of the fitted run each bar's bump lies, and its width (3 mm FWHM).
BUMP_AT = np.array([0.30, 0.60, 0.45, 0.70, 0.35, 0.55])
BUMP_SIGMA_M = 3e-3 / 2.3548


@pytest.mark.parametrize('datum', ['offset', 'none'])
def test_a_local_error_along_a_bar_is_claimed_where_it_lies(datum, tmp_path):
    """A local defect of each bar's scale (a Gaussian bump, 3 mm wide, 0.25-0.35 µm high, at
    30-70 % of the travel the fitted run covers): no term has its shape, so the model writes
    the residual as an uncertainty. Claimed alike at every length, new motion's samples with a
    bar on its bump fell outside the 95 % ellipsoid (the blind case: 88.6 % of all samples
    covered); the residual's profile along each bar puts the claim where the residual lay."""
    near_with, near_without, everywhere = [], [], []
    for k in range(4):
        travel = _travel(k, 'pose6')
        centre = travel.min(axis=0) + BUMP_AT * np.ptp(travel, axis=0)
        result, calibration, twin, run_of = _foreign_twin(
            k, lambda d: FOREIGN_AMPLITUDE_M * np.exp(-0.5 * ((d - centre) / BUMP_SIGMA_M) ** 2),
            datum, fit=('random_motion', ['duration_s=40', 'seed={seed}'], 'pose6'))
        fit = result.model.uncertainty.fit
        widths = fit.record.get('residual_profile_width_mm')
        print(k, result.conclusion.splitlines()[0], 'widths', widths)
        assert fit.profile is not None
        # (read on most bars, about as wide as the bump)
        assert sum(w is not None and 0.5 <= w <= 4.0 for w in widths) >= 4, widths
        flat = copy.deepcopy(result.model)
        flat.uncertainty.fit.profile = None
        run, counts = run_of(['duration_s=20', f'seed={k}'], 700.0)
        if k == 0:      # the profile goes into the model file and the report, and back
            from mmd_ros.analysis import write_report
            back = load_model(result.model.save(tmp_path / 'model.yaml'))
            report = write_report(result, tmp_path, figures=False)['report'].read_text()
            assert 'uncertainty.fit.profile' in report and 'bar2 ' in report
            sigma = [np.sqrt(np.diagonal(Pipeline(twin.documented_device, calibration, m).process(
                run.times_s[:400], counts[:400], with_covariance=True).covariance,
                axis1=1, axis2=2)) for m in (result.model, back, flat)]
            assert np.allclose(sigma[0], sigma[1], rtol=2e-3)    # (the file's rounding)
            assert not np.allclose(sigma[0], sigma[2], rtol=2e-2)
        near = np.any(np.abs(run.true_lengths - centre) < 2.0 * BUMP_SIGMA_M, axis=1)
        for model, into in ((result.model, near_with), (flat, near_without)):
            res = Pipeline(twin.documented_device, calibration, model).process(
                run.times_s, counts, with_covariance=True)
            inside = _d2(pose_error(res.poses, run.true_poses)[res.valid],
                         res.covariance[res.valid]) <= LIMIT
            into.append(inside[near[res.valid]])
            if model is result.model:
                everywhere.append(inside)
    with_, without = np.mean(np.concatenate(near_with)), np.mean(np.concatenate(near_without))
    print('on a bump', round(float(np.concatenate(near_with).size)), 'samples: covered',
          round(float(with_), 3), 'claimed alike at every length', round(float(without), 3),
          'all samples', round(float(np.mean(np.concatenate(everywhere))), 3))
    assert without < 0.9          # the bump is there, and a flat claim misses it
    assert with_ >= 0.93
    assert np.mean(np.concatenate(everywhere)) >= 0.93


def test_between_the_bars_a_residual_along_their_lengths_keeps_only_its_means_product():
    """Errors of each bar's own length (constants and sines of 20 mm, phases apart) on a run
    whose motion ties the six lengths together: what the residual holds between the bars
    through them is the motion's, and of it the claim keeps the product of their means over
    the run; the rest of the residual (white noise here, and what varies within the 1 mm bins
    of the length) and each bar's own square stay as they were."""
    from mmd_ros.analysis.uncertainty import _between_bars_along_lengths
    rng = np.random.default_rng(3)
    n = 20000
    lengths = 0.30 + 0.02 * np.sin(np.linspace(0.0, 40.0, n))[:, None] + np.zeros((1, 6))
    mean = np.array([100.0, -80.0, 40.0, -120.0, 60.0, 0.0]) * 1e-9
    phase = np.array([0.3, 2.1, 4.0, 1.2, 5.1, 3.3])
    dd = (mean + 300e-9 * np.sin(2.0 * np.pi * lengths / 20e-3 + phase)
          + rng.normal(0.0, 20e-9, (n, 6)))
    lengths[::97, 2] = np.nan               # (a bar without signal now and then: no length read)
    claimed = (dd.T @ dd - _between_bars_along_lengths(dd, lengths)) / n
    assert np.all(np.isfinite(claimed))
    seen = dd.T @ dd / n
    off = ~np.eye(6, dtype=bool)
    product = np.outer(dd.mean(axis=0), dd.mean(axis=0))[off]
    np.testing.assert_allclose(np.diag(claimed), np.diag(seen))
    tied = np.max(np.abs(seen[off] - product))
    assert tied > 2e-14                                     # (the motion's: (141 nm)^2)
    assert np.max(np.abs(claimed[off] - product)) < 0.05 * tied


def test_an_error_along_each_bar_seen_where_the_bars_moved_together_is_claimed_apart():
    """An error along each bar's scale of a shape no term has (a sine of 8 mm period, 0.25-0.35
    µm, its phase the bar's own), seen with a full pose reference on a z-axis run, where the
    six bars lengthen and shorten together: the residual is claimed as an uncertainty, and
    what its parts that follow the bars' lengths showed between the bars was that run's motion,
    which tied the bars' phases together. New 6-DOF motion takes the lengths apart: claimed
    with the z run's covariance between the bars, 0.7 % and 1.2 % of its samples were in the
    95 % ellipsoid (two twins); claimed independent between the bars beyond their means'
    product, 100 %, ratios 0.98-1.32."""
    phase = np.array([0.3, 2.1, 4.0, 1.2, 5.1, 3.3])
    for k in range(2):
        result, calibration, twin, run_of = _foreign_twin(
            k, lambda d: FOREIGN_AMPLITUDE_M * np.sin(2.0 * np.pi * d / 8e-3 + phase), 'none',
            fit=('iso_linear', ['axis=z'], 'pose6'))
        residual = result.model.uncertainty.fit.residual_m2
        assert np.all(np.sqrt(np.diag(residual)) > 0.1e-6), np.diag(residual)   # (it saw it)
        run, counts = run_of(['duration_s=20', f'seed={k}'], 700.0)
        res = Pipeline(twin.documented_device, calibration, result.model).process(
            run.times_s, counts, with_covariance=True)
        e, c = pose_error(res.poses, run.true_poses)[res.valid], res.covariance[res.valid]
        cover = np.mean(_d2(e, c) <= LIMIT)
        ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0) / np.mean(e * e, axis=0))
        print(k, 'covered', round(float(cover), 3), 'ratios', np.round(ratio, 2))
        assert cover >= 0.93 and np.all(ratio > 0.8) and np.all(ratio < 1.6)


def test_what_a_fit_left_along_a_bar_is_read_from_each_look_the_run_took_at_that_length():
    """Bench twin 6 of ``bench_uncertainty.py --approaches 1 --after``: the fit, unable to
    reach the calibration point at 250 mm of bar 5 (its samples stopped 10.5 mm short), left
    +90 to +180 nm over 264-277 mm, and new motion there +94 to +180 nm. The residual's
    profile along the bar was rejected: its 4287 held-out samples counted as 11 independent
    ones, the residual being correlated in time because it follows the length the bar moves
    smoothly along. Counted on what of it does not follow the length, the profile is read,
    and bar 5 is claimed there as large as its error (56 nm against 103-183 before)."""
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=6)
    room = ambient_profile('section_4_1')
    calibration = twin.calibrate(-211.0 * 5, room, approaches=1)
    fitted = twin.simulate(make_scenario('random_motion', ['duration_s=60', 'seed=105']), room,
                           start_s=600.0, reference='pose6')
    from mmd_ros.analysis import AnalysisOptions, analyze
    model = analyze(run_log(twin, calibration, fitted, 600.0),
                    options=AnalysisOptions(datum='none')).model
    assert model.uncertainty.fit.record['residual_profile_width_mm'][4] is not None
    run = twin.simulate(make_scenario('random_motion', ['duration_s=8', 'seed=5']), room,
                        start_s=700.0, reference='pose6')
    res = Pipeline(twin.documented_device, calibration, model).process(
        run.times_s, run.counts, with_covariance=True, with_length_covariance=True)
    cdf = res.compensated.cdf_lengths_m[:, 4]
    error = (res.compensated.lengths_m - run.true_lengths)[:, 4]
    there = res.valid & (cdf > 0.2645) & (cdf < 0.2770)
    rms = float(np.sqrt(np.mean(error[there] ** 2)))
    claim = float(np.sqrt(np.mean(res.length_covariance[there, 4, 4])))
    print(f'bar 5 over 264.5-277 mm: error {rms * 1e9:.0f} nm RMS, claimed {claim * 1e9:.0f} nm')
    assert there.sum() > 1000 and rms > 100e-9
    assert 0.8 * rms < claim < 1.5 * rms
    inside = _d2(pose_error(res.poses, run.true_poses)[there], res.covariance[there]) <= LIMIT
    assert np.mean(inside) >= 0.93, np.mean(inside)


def _d2(e, c):
    """Squared Mahalanobis distance of each pose error (n, 6) under its covariance (n, 6, 6)."""
    return np.einsum('ni,ni->n', e, np.linalg.solve(c, e[:, :, None])[:, :, 0])


def _judged(e, c) -> tuple[np.ndarray, float]:
    """Of pose errors (n, 6) and their covariances (n, 6, 6): predicted / observed sigma per
    component, and the share of the errors in the 95 % ellipsoid."""
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0) / np.mean(e * e, axis=0))
    return ratio, float(np.mean(_d2(e, c) <= LIMIT))


def _interference(k: int):
    """A 37 Hz, 30 nm reading error on every bar, each at its own phase (twin k's), as a
    length error of the samples at 200 Hz."""
    phase = np.random.default_rng(100 + k).uniform(0, 6.3, 6)
    return lambda d: 30e-9 * np.sin(2 * np.pi * 37.0 * np.arange(d.shape[0])[:, None] / 200.0 + phase)


def _new_motion(k: int, model, calibration, twin, run_of):
    """8 s of new random motion of twin k: the share of its samples in the 95 % ellipsoid with
    the unchanged model, and its pose errors and covariances with ``model``."""
    run, counts = run_of(['duration_s=8', f'seed={k}'], 700.0)
    out = []
    for m in (Model(), model):
        res = Pipeline(twin.documented_device, calibration, m).process(run.times_s, counts,
                                                                        with_covariance=True)
        out.append((pose_error(res.poses, run.true_poses)[res.valid], res.covariance[res.valid]))
    return float(np.mean(_d2(*out[0]) <= LIMIT)), out[1][0], out[1][1]


@pytest.mark.parametrize('datum', ['offset', 'none'])
def test_an_interference_no_term_follows_is_carried_as_an_uncertainty(datum):
    """A mount vibrating at 37 Hz adds 30 nm to every bar's reading, each at its own phase. No
    term follows time at 37 Hz and the budget estimates read noise only where a bar stands
    still, which random motion never does: nothing was found, no model was written, and new
    motion had 22.7 % of its samples in the 95 % ellipsoid (4 twins, zeroed reference). The
    residual, about twice what the budget claims, is now written as an uncertainty only (the
    model's terms unchanged): measured 99.4 % zeroed (ratios 1.01-1.12), 98.3 % absolute
    (0.98-1.02)."""
    errors, covs, without = [], [], []
    for k in range(4):
        result, calibration, twin, run_of = _foreign_twin(k, _interference(k), datum)
        assert result.found == [] and result.uncertainty_only, result.conclusion
        assert result.model.terms == [] and result.model.uncertainty.fit.residual_m2.trace() > 0
        assert 'uncertainty only' in result.conclusion
        before, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        without.append(before)
        errors.append(e)
        covs.append(c)
    e, c = np.concatenate(errors), np.concatenate(covs)
    d2 = _d2(e, c)
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0) / np.mean(e ** 2, axis=0))
    print('coverage', np.mean(d2 <= LIMIT), 'without the model', np.round(without, 3), 'ratio', np.round(ratio, 2))
    assert max(without) < 0.5            # the interference is there, and the default budget misses it
    # (an error of a sine's bounded spread, claimed at its variance, is inside the 95 %
    # ellipsoid more often than a Gaussian one: the ratios say the claim is right)
    assert 0.93 <= np.mean(d2 <= LIMIT) <= 0.995
    assert np.all((ratio >= 0.8) & (ratio <= 1.25))


def test_an_interference_seen_by_a_laser_is_carried_to_the_whole_pose():
    """The 37 Hz interference above, seen by an x-axis laser on an ISO run: nothing is found,
    and the residual beyond the budget's claim (1.7 x in x) cannot be told apart per bar, so the
    calibration's sources are scaled to claim it in every component, and the read noise the
    run showed where its bars stood still goes into the model. On 6-DOF motion of two twins:
    measured 99.9 % in the 95 % ellipsoid (20.8 % and 23.7 % with the unchanged model)."""
    covered, without = [], []
    for k in range(2):
        result, calibration, twin, run_of = _foreign_twin(
            k, _interference(k), 'offset', fit=('iso_linear', ['axis=x', 'n_cycles=5'], 'laser_x'))
        assert result.found == [] and result.uncertainty_only, result.conclusion
        assert result.model.terms == [] and result.model.uncertainty.fit.systematic_scale > 1.5
        before, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        without.append(before)
        covered.append(np.mean(_d2(e, c) <= LIMIT))
    print('coverage', np.round(covered, 4), 'without the model', np.round(without, 4))
    assert max(without) < 0.5 and min(covered) >= 0.93


def test_an_excess_grows_beyond_the_lengths_seen_only_where_the_unwritten_term_was_smooth():
    """What a partial reference showed is claimed to grow beyond the lengths the fit saw as a
    smooth error's expected square would (a random polynomial of degree 2 over those lengths:
    3 at their ends, 12.2 a fifth of their span further), and only for the share of the
    unwritten length term's correction beyond the calibration points' own errors: a bow grows,
    point errors the size of the points' own do not."""
    from mmd_ros.analysis.uncertainty import _growth_profile
    from mmd_ros.core.terms import CdfOffsetsTerm
    from mmd_ros.twin import AmbientProfile
    twin = TwinDevice(DEVICE, Effects.ideal(), seed=3)
    calibration = twin.calibrate(0.0, AmbientProfile.constant(21.0))
    budget = LengthBudget(DEVICE, calibration, Model())
    knots = budget.knots_m
    lo, hi = knots[:, 2], knots[:, 5]
    seen = [np.linspace(lo, hi, 50)]
    excess = np.diag(np.full(6, (50e-9) ** 2))
    u = (knots - 0.5 * (lo + hi)[:, None]) / (0.5 * (hi - lo))[:, None]
    bow = CdfOffsetsTerm(knots, 0.4e-6 * (u * u - 1.0 / 3.0))
    profile, share = _growth_profile(seen, excess, [bow], budget)
    assert np.all(share > 0.9), share
    at = np.column_stack([0.5 * (lo + hi), hi, hi + 0.2 * (hi - lo)])     # u = 0, 1, 1.4
    f = np.array([profile.factors(at[:, j][None, :])[0] for j in range(3)])
    assert np.allclose(f[0], 1.0) and np.all(f[1] > 2.5) and np.all(f[2] > 10.0), f
    assert np.all(profile.factors(lo[None, :] - 0.1) > f[2])       # (100 mm below: larger)
    nugget = np.sqrt(budget.point_nugget_m2)[:, None]
    jitter = CdfOffsetsTerm(knots, nugget * np.where(np.arange(knots.shape[1]) % 2, 1.0, -1.0))
    profile, share = _growth_profile(seen, excess, [jitter], budget)
    assert profile is None and np.all(share == 0.0), share
    assert _growth_profile(seen, excess, [], budget)[0] is None


def test_a_bow_seen_by_a_laser_claims_the_bars_common_mode_as_large_as_what_it_showed():
    """A quadratic bow of each bar's scale about the middle of its travel (0.25-0.35 µm from
    middle to end, after the calibration: it did not see it), seen by an x-axis laser on 6-DOF
    motion: the calibration points are found and not written (their effect on the other
    components is not determined), and x shows 3-5 times the budget's claim. The budget's
    sources, scaled on x, claim little of what the bars share, which x does not see and z does:
    z was claimed 0.58-0.68 times its error, 92.4 % of new motion within the fitted lengths in
    the 95 % ellipsoid (82.7 % on one twin). The common mode is now claimed as large as the whole
    excess: measured z 1.31-1.61, 96.7 % (93.2-100 %), and the conclusion says it is a prior.
    Where a bar of new motion lies beyond the lengths the fit saw (up to 17 mm, 19 % of the
    samples), the bow goes on growing and 12.2 % of those samples were in the ellipsoid (ratios
    0.31-1.10): the excess is now claimed to grow there as a smooth error's would (the points'
    correction was smooth, its share beyond the points' own errors 0.99-1.0 per bar): measured
    100 % (ratios 0.65-2.37), and within the fitted lengths 100 % (1.21-1.78)."""
    errors, covs, beyond_e, beyond_c = [], [], [], []
    for k in range(4):
        result, calibration, twin, run_of = _bowed_twin(k, 'laser_x')
        assert result.model.terms == [] and result.uncertainty_only, result.conclusion
        assert 'a prior, not a measurement' in result.conclusion
        record = result.model.uncertainty.fit.record
        assert record['common_mode_visibility'] < 0.1
        assert min(record['growing_share']) > 0.9, record
        run, counts = run_of(['duration_s=20', f'seed={k}'], 700.0)
        res = Pipeline(twin.documented_device, calibration, result.model).process(
            run.times_s, counts, with_covariance=True)
        seen = Validity.from_model(result.model).bar_range_m       # (the fit's lengths only)
        cdf = res.compensated.cdf_lengths_m
        inside = np.all((cdf >= seen[:, 0]) & (cdf <= seen[:, 1]), axis=1)
        error = pose_error(res.poses, run.true_poses)
        errors.append(error[res.valid & inside])
        covs.append(res.covariance[res.valid & inside])
        beyond_e.append(error[res.valid & ~inside])
        beyond_c.append(res.covariance[res.valid & ~inside])
    e, c = np.concatenate(errors), np.concatenate(covs)
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0) / np.mean(e ** 2, axis=0))
    each = [float(np.mean(_d2(x, y) <= LIMIT)) for x, y in zip(errors, covs)]
    out = float(np.mean(_d2(np.concatenate(beyond_e), np.concatenate(beyond_c)) <= LIMIT))
    print('coverage', np.round(each, 3), 'ratio', np.round(ratio, 2), 'beyond', round(out, 3),
          'of', sum(map(len, beyond_e)))
    assert ratio[2] >= 0.8 and np.all(ratio >= 0.8)
    assert np.mean(_d2(e, c) <= LIMIT) >= 0.93 and min(each) >= 0.88
    assert sum(map(len, beyond_e)) > 1000 and out >= 0.93


def test_an_interference_seen_at_standstill_is_carried_by_its_read_noise(tmp_path):
    """The 37 Hz interference above, seen on a C-axis ISO run with the rotary encoder as the
    reference: the run dwells, and where a bar stands still the stream's read-noise estimate
    shows it (28 nm against the calibration's 4.6 nm), so the run's own claim covers its
    residual and nothing is beyond it. A 6-DOF stream never stands still and claims the
    calibration's figure: 20.8 % and 23.7 % of new motion were in the 95 % ellipsoid with the
    unchanged model. The read noise the analysis measured now goes into the model, which a
    stream claims until it shows its own: measured 93.9 % and 91.8 % (the interference is one
    sinusoid on every bar, correlated between them, which a read noise per bar is not: x and y
    are claimed at 0.75 and 0.87 of their error, the rest at 0.91-1.19)."""
    covered, without = [], []
    for k in range(2):
        result, calibration, twin, run_of = _foreign_twin(
            k, _interference(k), 'offset', fit=('iso_rotary', ['axis=psi', 'n_cycles=3'], 'rotary_psi'))
        assert result.found == [] and 'read noise' in result.uncertainty_only, result.conclusion
        noise = result.model.uncertainty.fit.read_noise_m
        assert noise is not None and np.max(noise[:6]) > 20e-9
        path = result.model.save(tmp_path / f'model{k}.yaml')
        assert np.allclose(load_model(path).uncertainty.fit.read_noise_m, noise, atol=1e-13)
        before, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        without.append(before)
        covered.append(np.mean(_d2(e, c) <= LIMIT))
    print('coverage', np.round(covered, 4), 'without the model', np.round(without, 4))
    assert max(without) < 0.5 and min(covered) >= 0.9


@pytest.mark.parametrize('datum', ['offset', 'none'])
def test_a_drift_fitted_on_one_run_is_claimed_on_another(datum):
    """A reading that settles by up to 0.3 µm over 10-40 s from each run's start (a bar
    warming after handling) is fitted as a drift: an offset at the run's start and a rate,
    which belong to that run. Applied to another run they are an extrapolation no data checked:
    new motion had 7.7 % (zeroed reference) and 89.2 % (absolute) of its samples in the 95 %
    ellipsoid. Each bar's drift correction (as far as it drifted apart from the others), and
    the bars' together, is now claimed as uncertain as it is large, and as much again as it
    varied over the fitted run (another run may drift of its own), and the model's terms leave
    the drift out: measured 100 % and 100 % (conservative, pooled over the four twins: 1.7-4.1
    and 1.4-1.8 times the error, fitted as settlings; the fit cannot tell a drift that goes on
    from one that starts again with each run)."""
    errors, covs = [], []
    for k in range(4):
        g = np.random.default_rng(100 + k)
        size, tau = g.uniform(-1, 1, 6) * 0.3e-6, g.uniform(10, 40, 6)
        result, calibration, twin, run_of = _foreign_twin(k, lambda d: size * (
            1 - np.exp(-np.arange(d.shape[0])[:, None] / 200.0 / tau)), datum)
        assert [f.effect for f in result.found] == ['drift'], result.conclusion
        _, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        errors.append(e)
        covs.append(c)
    covered = np.mean(_d2(np.concatenate(errors), np.concatenate(covs)) <= LIMIT)
    print('coverage', covered)
    assert covered >= 0.93


@pytest.mark.parametrize('datum', ['offset', 'none'])
def test_a_settling_alike_on_every_bar_is_fitted_as_one_and_claimed_on_another_run(datum, tmp_path):
    """A reading that settles on every bar alike, 0.3 µm +- 15 % decaying over 15 s from each
    run's start (the bars warming together). A rate over the run does not explain it: fitted
    absolute, nothing was found on 3 of 4 twins (the residual carried as an uncertainty only)
    and a new 8 s run, all of it in the settling's first seconds, was 58-68 % covered (71.5 %
    pooled, z claimed 0.54 times its error). The drift's settling, its time constant estimated
    from the data, is found on every twin: measured 98.2 %, ratios 0.99-1.18. Zeroed, the
    reference does not see where the bars' common drift started: 55 % while each bar's whole
    drift was claimed as its own and the common start was not (z 0.60, the rest 4.4-7.0);
    now 98.5 %, 1.28-2.48 (the fit cannot tell a drift that goes on from one that starts
    again; 98.4 % and 99.0 % while the drift's parameter covariance was claimed as well)."""
    errors, covs = [], []
    for k in range(4):
        size = 0.3e-6 * (1 + 0.15 * np.random.default_rng(100 + k).uniform(-1, 1, 6))
        result, calibration, twin, run_of = _foreign_twin(k, lambda d: size * np.exp(
            -np.arange(d.shape[0])[:, None] / 200.0 / 15.0), datum)
        assert [f.effect for f in result.found] == ['drift'], result.conclusion
        tau = result.found[0].hyper
        assert tau is not None and 5.0 < tau < 45.0, tau            # (the truth: 15 s)
        if k == 0:    # the directions that claim it on other runs are written and read back
            model = load_model(result.model.save(tmp_path / 'model.yaml'))
            assert any(t.type_name == 'drift' and t.settling_s == pytest.approx(tau)
                       for d in model.uncertainty.fit.directions for t in d)
        _, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        errors.append(e)
        covs.append(c)
    e, c = np.concatenate(errors), np.concatenate(covs)
    ratio = np.sqrt(np.mean(np.diagonal(c, axis1=1, axis2=2), axis=0) / np.mean(e * e, axis=0))
    covered = np.mean(_d2(e, c) <= LIMIT)
    print(datum, 'coverage', covered, 'ratios', np.round(ratio, 2))
    assert covered >= 0.93 and np.all(ratio >= 0.8), ratio
    assert np.all(ratio < (1.3 if datum == 'none' else 3.0)), ratio


@functools.lru_cache(maxsize=2)
def _c_axis_cyclic(k: int):
    """Twin k (ideal) analysed zeroed on a C-axis ISO run (rotary encoder reference), its
    counts carrying an encoder cyclic error of 13 µm period and 80 nm (twin k's phase per bar),
    as :func:`_foreign_twin`; made once for the tests that judge it."""
    phase = np.random.default_rng(100 + k).uniform(0, 2 * np.pi, 6)
    return _foreign_twin(
        k, lambda q: 80e-9 * np.sin(2 * np.pi * q * RES / 13e-6 + phase), 'offset',
        fit=('iso_rotary', ['axis=psi', 'n_cycles=3'], 'rotary_psi'), of_counts=True)


def test_a_cyclic_error_s_period_fitted_on_a_c_axis_run_is_claimed_on_6dof_motion():
    """An encoder cyclic error of 13 µm period and 80 nm (twin k's phase per bar), fitted from
    a C-axis ISO run alone (rotary encoder reference) and applied to new 6-DOF motion. The run
    sweeps 36 mm of each bar, about 63 mm from the calibration's first point where the phase is
    counted: the period it gives is uncertain by about 1e-5, which turns the phase there by a
    twentieth of a cycle. Held as exact, the first twin's period came out 4.3e-5 too long, its
    amplitudes 57-108 nm, and 53.4 % of its new motion was in the 95 % ellipsoid (96.9 % on the
    second). The period is now refined to the least error and its uncertainty claimed as one
    more direction; and as one component cannot tell whether the calibration read the error,
    the change to that form is claimed too (conservative here, where it did not): measured
    100 % and 99.1 %, the periods 2.2 and 0.3 of their claimed sigma from the truth (the
    sigma scaled by the bars' Birge ratio; the test below checks it over ten twins)."""
    covered, z = [], []
    for k in range(2):
        result, calibration, twin, run_of = _c_axis_cyclic(k)
        assert [f.effect for f in result.found] == ['cyclic_error'], result.conclusion
        found = result.found[0]
        assert found.setting_shift is not None
        period, in_calibration = found.hyper
        assert not in_calibration, found.hyper      # added to the run's counts only
        sd = found.setting_shift[0][0] - period
        z.append((period - 13e-6) / sd)
        _, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        covered.append(np.mean(_d2(e, c) <= LIMIT))
    print('coverage', np.round(covered, 4), 'period error / its sigma', np.round(z, 2))
    assert np.all(np.abs(z) < 4)
    assert min(covered) >= 0.85 and np.mean(covered) >= 0.93


def test_a_cyclic_error_s_period_is_within_its_claimed_sigma_over_ten_twins():
    """The C-axis case above on ten twins, period only: what is claimed of it is a sigma, so
    over ten twins the error in units of it should have an RMS near 1. From the curvature of
    the fit alone it was 1.93 (one twin 3.7 sigma short): an error the model lacks, left at
    the dwell targets of an ISO run, moves the period the fit finds, and the six bars' own
    estimates of the one period disagreed (chi^2 8-55 for 5 degrees of freedom). Scaled by
    the Birge ratio of those estimates: measured RMS 1.11, nine of ten within 2 sigma; 1.41,
    nine of ten, with the rows of the components the calibrator does not see (axis_motion)."""
    z = []
    for k in range(10):      # (the first two are the twins of the test above)
        result, *_ = _c_axis_cyclic(k)
        found = [f for f in result.found if f.effect == 'cyclic_error']
        assert found and found[0].setting_shift is not None, result.conclusion
        period = found[0].hyper[0]
        z.append((period - 13e-6) / (found[0].setting_shift[0][0] - period))
    z = np.array(z)
    print('period error / its sigma', np.round(z, 2), 'RMS', np.sqrt(np.mean(z ** 2)))
    assert np.sqrt(np.mean(z ** 2)) <= 1.5
    assert np.sum(np.abs(z) <= 2.0) >= 8


def test_a_cyclic_error_seen_by_one_component_is_fitted_as_the_runs_read_it():
    """The cyclic error of the C-axis test above, added to the runs' counts only, on a twin
    without read noise. Offered the calibration's part too (a line through the CDF points on
    each bar, below), the fit took it, with a period 1e-4 off: one component cannot tell that
    line from other smooth errors, and new 6-DOF motion got worse in every component, 0.9 %
    of it in the 95 % ellipsoid. With one component seen only the runs' part is fitted (and
    the change to the other form claimed, below): measured 98.8 %, every component better."""
    phase = np.random.default_rng(100).uniform(0, 2 * np.pi, 6)
    result, calibration, twin, run_of = _foreign_twin(
        0, lambda q: 80e-9 * np.sin(2 * np.pi * q * RES / 13e-6 + phase), 'offset',
        fit=('iso_rotary', ['axis=psi', 'n_cycles=3'], 'rotary_psi'), of_counts=True,
        effects=Effects.ideal().with_assignments(('read_noise_m=0',)))
    period, in_calibration = result.found[0].hyper
    assert not in_calibration and math.isclose(period, 13e-6, rel_tol=2e-5), result.found[0].hyper
    run, counts = run_of(['duration_s=8', 'seed=0'], 700.0)
    rms, covered = [], 0.0
    for model in (Model(), result.model):
        res = Pipeline(twin.documented_device, calibration, model).process(run.times_s, counts,
                                                                            with_covariance=True)
        e = pose_error(res.poses, run.true_poses)[res.valid]
        rms.append(np.sqrt(np.mean((e - e.mean(axis=0)) ** 2, axis=0)))
        covered = float(np.mean(_d2(e, res.covariance[res.valid]) <= LIMIT))
    print('rms before', np.round(rms[0] * 1e6, 3), 'after', np.round(rms[1] * 1e6, 3), 'coverage', covered)
    assert np.all(rms[1] < rms[0]) and covered >= 0.93


def test_a_cyclic_error_the_calibration_read_too_is_fitted_as_the_calibrated_bar_reads_it():
    """The twin's own encoder cyclic error, 80 nm at 13 µm: the calibration read the same
    scale, so each CDF point took the error at its count, and the CDF carries those values,
    up to 80 nm, between the points. Fitted as the error of the runs alone (with the CDF
    points as a second effect), a zeroed analysis could not see the mean those
    points give a pose, and new motion of twins 1 and 3 had 77.3 % and 76.9 % of its samples
    in the 95 % ellipsoid (86.4 % over four twins; a constant 44 nm in z against 27 nm
    claimed). The term now carries the error through the calibration's points when the data
    say so (both are tried): one effect, whose law fixes the mean. Measured 99.9 % and 99.7 %
    (99.0 % over four twins, ratios 1.05-1.55, with the twin's encoder bound stated: the zeroed
    reference's claim holds what the runs leave unknown of a constant per bar)."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    room = ambient_profile('section_4_1')
    covered = []
    for k in (0, 2):
        twin = TwinDevice(DEVICE, TWIN_CYCLIC, seed=k + 1)
        calibration = twin.calibrate(-211.0 * k, room, approaches=2)
        run = twin.simulate(make_scenario('random_motion', ['duration_s=60', f'seed={100 + k}']), room,
                            start_s=600.0, reference='pose6')
        result = analyze(run_log(twin, calibration, run, 600.0),      # a zeroed reference
                         options=AnalysisOptions(datum='offset'))
        assert [f.effect for f in result.found] == ['cyclic_error'], result.conclusion
        period, in_calibration = result.found[0].hyper
        assert in_calibration and math.isclose(period, 13e-6, rel_tol=1e-3), result.found[0].hyper
        model = Model.from_yaml(result.model.to_yaml())        # as the file gives it
        assert 'calibration_counts' in model.terms[0].params()
        new = twin.simulate(make_scenario('random_motion', ['duration_s=8', f'seed={k}']), room,
                            start_s=700.0, reference='pose6')
        res = Pipeline(twin.documented_device, calibration, model).process(
            new.times_s, new.counts, with_covariance=True)
        e = pose_error(res.poses, new.true_poses)[res.valid]
        covered.append(np.mean(_d2(e, res.covariance[res.valid]) <= LIMIT))
    print('coverage', np.round(covered, 4))
    assert min(covered) >= 0.93


def test_a_cyclic_error_the_calibration_read_seen_by_one_component_is_claimed_with_that_part():
    """The twin's own 80 nm, 13 µm cyclic error (the calibration read it too) fitted from an
    x-axis laser run: one component cannot tell the calibration's part (a line through the CDF
    points on each bar) from other smooth errors, so only the runs' part is fitted, and new
    6-DOF motion had 47.1 % and 65.1 % of its samples in the 95 % ellipsoid (19.1 % and 38.9 %
    with the unchanged model). The change to the form with the calibration's part is now
    claimed as one more direction: measured 97.9 % and 99.9 %; 98.6 % and 100 % now that the
    twin states its encoders' bound (the budget claims what the fit left of it)."""
    covered = []
    for k in range(2):
        result, calibration, twin, run_of = _foreign_twin(
            k, lambda d: np.zeros_like(d), 'offset', fit=('iso_linear', ['axis=x', 'n_cycles=5'], 'laser_x'),
            effects=TWIN_CYCLIC)
        found = {f.effect: f for f in result.found}
        assert found['cyclic_error'].hyper[1] is False and found['cyclic_error'].alternatives, result.conclusion
        _, e, c = _new_motion(k, result.model, calibration, twin, run_of)
        covered.append(np.mean(_d2(e, c) <= LIMIT))
    print('coverage', np.round(covered, 4))
    assert min(covered) >= 0.93


def test_a_cyclic_error_a_c_axis_run_does_not_show_is_claimed_from_the_encoders_datasheet():
    """The twin's own 80 nm, 13 µm cyclic error (the calibration read it too), analysed on a
    C-axis ISO run (rotary encoder reference) of twins 1 and 4: those runs show no cyclic
    error, nothing is found, and the budget had no source for it: 19.1 % and 24.0 % of new 6-DOF
    motion were in the 95 % ellipsoid. The encoders' datasheet bound
    (``bars.subdivision_error_nm`` with its signal period, which the twin states as a
    datasheet would) is now a source of its own: measured 92.3 % and 98.4 % (95.3 % pooled;
    one twin is one draw of six phases: over eight calibrations of such twins before any
    analysis, 98.0 %, ratios 0.88-1.13, README). The rows of the components the calibrator
    does not see (analysis/axis_motion.py) are left out here: with them twin 4's run shows
    the error (the test below), twin 1's still does not."""
    covered = {'stated': [], 'unstated': []}
    for k in (0, 3):
        result, calibration, twin, run_of = _foreign_twin(
            k, lambda d: np.zeros_like(d), 'offset',
            fit=('iso_rotary', ['axis=psi', 'n_cycles=3'], 'rotary_psi'), effects=TWIN_CYCLIC,
            axis_motion=False)
        assert not result.found, result.conclusion         # the premise: the run does not show it
        run, counts = run_of(['duration_s=8', f'seed={k}'], 700.0)
        for name, device in (('stated', twin.documented_device), ('unstated', DEVICE)):
            res = Pipeline(device, calibration, result.model).process(run.times_s, counts,
                                                                      with_covariance=True)
            e = pose_error(res.poses, run.true_poses)[res.valid]
            covered[name].append(float(np.mean(_d2(e, res.covariance[res.valid]) <= LIMIT)))
    print('coverage', covered)
    assert max(covered['unstated']) < 0.5
    assert min(covered['stated']) >= 0.85 and np.mean(covered['stated']) >= 0.93


def _before_after(twin, calibration, model, run, counts):
    """RMS of each pose component's error about its mean, (2, 6), with the default model and
    with ``model``; and the share of the samples in ``model``'s 95 % ellipsoid."""
    rms = []
    for m in (Model(), model):
        res = Pipeline(twin.documented_device, calibration, m).process(run.times_s, counts, with_covariance=True)
        e = pose_error(res.poses, run.true_poses)[res.valid]
        rms.append(np.sqrt(np.mean((e - e.mean(axis=0)) ** 2, axis=0)))
    return np.array(rms), float(np.mean(_d2(e, res.covariance[res.valid]) <= LIMIT))


def test_a_cyclic_error_is_found_in_the_components_a_c_axis_calibrator_does_not_see():
    """Twin 4 of the test above. In the rotary calibrator's component its C-axis run shows
    no cyclic error; in the five others the MMD reads the machine's motion, a smooth function
    of the C angle (analysis/axis_motion.py), and a 13 µm period of bar length is not one.
    Read that way, the cyclic error and the calibration points it left are found from this
    run alone, and new 6-DOF motion improves in every component (measured x 0.127 -> 0.052 µm,
    yaw 0.210 -> 0.066 ″) and stays covered (96.8 %; 92.3 % while the fitted terms' directions
    beyond the eight written were not claimed)."""
    result, calibration, twin, run_of = _foreign_twin(
        3, lambda d: np.zeros_like(d), 'offset',
        fit=('iso_rotary', ['axis=psi', 'n_cycles=3'], 'rotary_psi'), effects=TWIN_CYCLIC)
    assert [f.effect for f in result.found][:1] == ['cyclic_error'], result.conclusion
    rms, covered = _before_after(twin, calibration, result.model, *run_of(['duration_s=8', 'seed=3'], 700.0))
    print('rms before', rms[0], 'after', rms[1], 'coverage', covered)
    assert np.all(rms[1] < 0.8 * rms[0]), rms
    assert covered >= 0.93
    fit = result.model.uncertainty.fit      # (more directions than are written: their mean)
    assert len(fit.directions) > 8
    assert np.trace(fit.rest_terms_m2) > 0.05 * np.trace(fit.mean_terms_m2)


def test_a_term_fitted_on_a_laser_claims_what_the_laser_did_not_determine():
    """A friction of another shape than the twin's (a sech² turn-over over 6 µm, 0.2–0.45 µm per
    bar) on an ideal twin, fitted on an x-axis ISO run with a laser along x and applied to
    6-DOF motion of that twin. The laser determines a few combinations of the six amplitudes;
    the minimum-norm fit set the others to zero and the covariance claimed nothing for them:
    0.2 % of the 6-DOF samples in the 95 % ellipsoid, 1.0 µrad of roll left (1.38 before). The
    term's covariance now holds those directions at the size of the written amplitudes:
    measured 97.6 % (ratios 2.9–5.7 with the friction travel's own uncertainty claimed too:
    conservative, the bars' amplitudes are closer to each other than to zero); 96.8 %, ratios
    1.07-1.41, now that the laser's unseen components determine every amplitude. The friction
    is still found and written, and improves every
    component of the 6-DOF run."""
    g = np.random.default_rng(100)
    amp = g.uniform(0.2, 0.45, 6) * 1e-6
    result, calibration, twin, run_of = _foreign_twin(
        0, lambda d: -amp * sech_friction(d, 6e-6), 'offset',
        fit=('iso_linear', ['axis=x', 'n_cycles=5'], 'laser_x'))
    assert [f.effect for f in result.found] == ['hysteresis'], result.conclusion
    rms, covered = _before_after(twin, calibration, result.model, *run_of(['duration_s=20', 'seed=0'], 900.0))
    assert np.all(rms[1] < rms[0]), rms
    print('coverage', covered)
    assert covered >= 0.93


def test_coverage_report_of_a_full_and_a_partial_reference():
    rng = np.random.default_rng(5)
    cov = np.broadcast_to(np.diag([1e-12] * 3 + [1e-10] * 3), (20000, 6, 6))
    err = rng.multivariate_normal(np.zeros(6), cov[0], 20000)
    full = coverage(err, cov, np.ones(20000, bool), absolute=True)
    assert full['ellipsoid_coverage'] == pytest.approx(0.95, abs=0.01)
    assert [r['ratio'] for r in full['per_component']] == pytest.approx([1.0] * 6, abs=0.03)
    partial = err.copy()
    partial[:, 1:] = np.nan
    partial[:, 0] += 5e-6                                         # a zeroed laser's offset
    one = coverage(partial, cov, np.ones(20000, bool), absolute=False)
    assert one['components'] == ['x'] and one['offset_removed']
    assert one['ellipsoid_coverage'] == pytest.approx(0.95, abs=0.01)
    assert one['per_component'][0]['ratio'] == pytest.approx(1.0, abs=0.03)


def test_mmd_process_json_reports_the_coverage(tmp_path, capsys):
    from mmd_ros.cli.main import main
    from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
    log = tmp_path / 'run.mcap'
    simulate_to_log(SimulationSpec(scenario='random_motion', scenario_params=('duration_s=3',),
                                   effects='ideal', reference='pose6', calibration_approaches=2),
                    log, progress=False)
    capsys.readouterr()
    assert main(['process', str(log), '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    report = summary['uncertainty_coverage']
    assert report['components'] == ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
    assert not report['offset_removed']                          # the twin's reference is absolute
    assert report['per_component'][3]['reference_sigma'] == pytest.approx(0.1)  # 0.1 arcsec
    for row in report['per_component']:
        assert 0.5 < row['ratio'] < 3.0 and math.isfinite(row['observed_sigma'])
    assert 0.8 < report['ellipsoid_coverage'] <= 1.0
    budget = json.loads(json.dumps(summary['uncertainty_budget']))
    assert budget['calibration_point_nm'] > 0 and any('reference plate' in n for n in budget['notes'])


def test_mmd_process_json_reports_the_coverage_of_reference_bar_lengths(tmp_path, capsys):
    """A log whose reference is the bars' lengths (no pose): the bars' length covariance
    Sigma_d, the budget's, judged against them, computed without --covariance as for a pose
    (one twin's calibration is one draw of its systematic errors: the test above judges the
    claim over several); and a bar that reads 1 µm long shows."""
    from mmd_ros.cli.main import main
    from mmd_ros.logs.layout import read_run, write_run
    from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
    log = tmp_path / 'run.mcap'
    simulate_to_log(SimulationSpec(scenario='random_motion', scenario_params=('duration_s=20',),
                                   effects='ideal', reference='bar_lengths',
                                   calibration_approaches=2), log, progress=False)
    capsys.readouterr()
    assert main(['process', str(log), '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert 'uncertainty_coverage' not in summary                # (no reference pose)
    report = summary['length_uncertainty_coverage']
    assert report['kind'] == 'lengths' and not report['offset_removed']
    assert report['components'] == [f'bar{k}' for k in range(1, 7)]
    for row in report['per_component']:
        assert row['unit'] == 'um' and 0.5 < row['ratio'] < 2.0, row
    assert 0.8 < report['ellipsoid_coverage'] <= 1.0
    # the same log with bar 3 reading 1 µm long: its row and the ellipsoid say so
    run = read_run(log)
    counts = run.counts.astype(np.float64)
    counts[:, list(DEVICE.measuring_channels)[2]] += round(1e-6 / RES)
    moved = tmp_path / 'moved.mcap'
    write_run(moved, run.device, run.calibration, run.stamps_ns, counts,
              reference_lengths=run.reference_lengths)
    assert main(['process', str(moved), '--json']) == 0
    report = json.loads(capsys.readouterr().out)['length_uncertainty_coverage']
    assert report['per_component'][2]['ratio'] < 0.1 and report['ellipsoid_coverage'] < 0.05
    assert main(['process', str(moved), '--out', str(tmp_path / 'text.mcap')]) == 0
    assert 'bar length uncertainty against the reference' in capsys.readouterr().out


def test_the_streaming_sum_is_the_sum_of_the_sources(realistic):
    """Sigma_d as the nodes add it up for every transfer equals the sources listed one by one
    (random ones plus b b^T of the known errors)."""
    _, _, calibration, run = realistic
    pipeline = Pipeline(DEVICE, calibration)
    res = pipeline.process(run.times_s, run.counts)
    comp, th = res.compensated, res.compensated.thermal
    budget = LengthBudget(DEVICE, calibration, Model())
    observed = budget.observe(comp.cdf_lengths_m, th.reference_error_m)
    args = (comp.lengths_m, th.reference_error_m, th.temp_change_c, th.bar_error_m, None, observed)
    assert np.any(observed.directions != 0)
    cov, bias = budget.sources(*args)
    b = sum(bias.values())
    expected = sum(cov.values()) + b[:, :, None] * b[:, None, :]
    np.testing.assert_allclose(budget.covariance(*args), expected, rtol=1e-9, atol=1e-30)


def test_compiled_friction_travel_equals_python():
    """The budget's friction state and travel (it follows every sample of a stream or a log):
    the compiled loop gives the Python loop's numbers exactly, carried across calls, with a
    bar out of range (NaN) in the stream."""
    from mmd_ros.core.budget import _Friction
    from mmd_ros.core.compiled import AVAILABLE, NOT_IN_USE
    assert AVAILABLE, NOT_IN_USE
    rng = np.random.default_rng(12)
    n = 6000
    x = 0.3 + 5e-6 * np.sin(np.arange(n) / 400)[:, None] + rng.normal(0, 20e-9, (n, 6))
    x[100:140, 3] = np.nan
    x[:5, 0] = np.nan      # no play position yet
    results = []
    for compiled in (False, True):
        fr = _Friction(50e-9, 2e-6)
        parts = [fr(x[k:k + 777], compiled=compiled) for k in range(0, n, 777)]
        results.append((np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                        fr._state.copy()))
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)
    state, settled = results[1][0], results[1][1]
    assert state.min() == -1.0 and state.max() == 1.0 and settled[-1].min() == 1.0


def test_the_friction_start_state_claim_follows_dahl_s_law(realistic):
    """A friction term starts a run from state 0; the bar's true state is anywhere in [-1, 1].
    Along a real motion, Monte Carlo over start states drawn in [-1, 1] through the term's own
    Dahl law: the variance of the term's error, h^2 var(s_true - s_term), is what the budget
    claims, h^2 / 3 exp(-2 path / travel), at the start and as the bar moves."""
    from mmd_ros.core.terms import FrictionTerm, friction_state
    _, _, calibration, run = realistic
    comp = Pipeline(DEVICE, calibration).compensate(run.times_s, run.counts)
    x = comp.cdf_lengths_m[:1500]
    travel, deadband, h = 4e-6, 50e-9, 0.3e-6
    term = FrictionTerm(np.full(6, h), travel, deadband)
    budget = LengthBudget(DEVICE, calibration, Model(terms=[term]))
    th = comp.thermal
    observed = budget.observe(x, th.reference_error_m[:1500], run.times_s[:1500])
    claimed = budget.variances(comp.lengths_m[:1500], th.reference_error_m[:1500],
                               th.temp_change_c[:1500], th.bar_error_m[:1500],
                               observed=observed)['hysteresis'][:, range(6), range(6)]
    model_s, _ = friction_state(x, travel, deadband, None)
    rng = np.random.default_rng(3)
    diffs = []
    for s0 in rng.uniform(-1.0, 1.0, (400, 6)):
        start = (x[0].copy(), np.zeros(6), x[0].copy(), s0)
        true_s, _ = friction_state(x, travel, deadband, start)
        diffs.append(true_s - model_s)
    amp = budget.hysteresis_m        # the term's amplitude (its fit's variance: none here)
    np.testing.assert_allclose(amp, h)
    mc = amp ** 2 * np.mean(np.square(diffs), axis=0)           # (N, 6)
    moving = claimed > 1e-3 * claimed[0]
    assert np.allclose(claimed[0], amp ** 2 / 3)
    assert moving.any() and (~moving).any()      # the bars forget their start within the run
    # 400 draws: the variance of a mean square of uniform draws is known to about 5 %
    np.testing.assert_allclose(mc[moving], claimed[moving], rtol=0.15)
    assert np.all((mc <= 2e-3 * claimed[0])[~moving])
