"""The model file, the hysteresis term, and stream = batch in the pipeline."""

from __future__ import annotations

import numpy as np
import pytest

from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.model import HysteresisTerm, Model, ModelUncertainty, TermContext, load_model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.twin import AmbientProfile, Effects, TwinDevice, make_scenario

DEVICE = load_device(find_config('mmd_prototype.yaml'))


def test_model_file_round_trip(tmp_path):
    model = Model(thermal_mode='single', plate_expansion=False,
                  terms=[HysteresisTerm(np.arange(1, 7) * 0.1e-6, 4e-6)],
                  uncertainty=ModelUncertainty(thermal_mismatch_fraction=0.1, read_noise_m=7e-9))
    path = model.save(tmp_path / 'model.yaml')
    assert 'length_sigma_um' not in path.read_text()   # no fixed sigma is written any more
    back = load_model(path)
    assert back.thermal_mode == 'single' and back.plate_expansion is False
    assert back.uncertainty.thermal_mismatch_fraction == pytest.approx(0.1)
    assert back.uncertainty.read_noise_m == pytest.approx(7e-9)
    assert isinstance(back.terms[0], HysteresisTerm)
    assert back.terms[0].amplitude_m == pytest.approx(np.arange(1, 7) * 0.1e-6)
    assert back.terms[0].travel_m == pytest.approx(4e-6)
    assert load_model(None).terms == []   # the default: CDF + thermal only


@pytest.mark.parametrize('text,key', [
    ('format_version: 2\n', 'format_version'),
    ('format_version: 1\nthermal: {mode: twice}\n', 'thermal.mode'),
    ('format_version: 1\nterms: [{type: magic}]\n', 'terms[0].type'),
    ('format_version: 1\nterms: [{type: hysteresis, amplitude_um: [1, 2]}]\n', 'amplitude_um'),
    ('format_version: 1\nlength_sigma_um: -1\n', 'length_sigma_um'),
    ('format_version: 1\nuncertainty: {thermal_mismatch_fraction: 2}\n',
     'uncertainty.thermal_mismatch_fraction'),
    ('format_version: 1\nuncertainty: {read_noise_nm: -1}\n', 'uncertainty.read_noise_nm'),
    ('format_version: 1\nuncertainty: {fit: {residual_nm2: [[1, 2], [3, 4]]}}\n',
     'uncertainty.fit.residual_nm2'),
    ('format_version: 1\nuncertainty: {fit: {replaces: [everything]}}\n', 'uncertainty.fit.replaces'),
    ('format_version: 1\nuncertainty: {fit: {flank_nm2: [1, 2, 3, 4, 5, -6]}}\n',
     'uncertainty.fit.flank_nm2'),
    ('format_version: 1\nuncertainty: {fit: {flank_nm2: [1, 2, 3]}}\n', 'uncertainty.fit.flank_nm2'),
    ('format_version: 1\nuncertainty: {fit: {rest_terms_nm2: [[1, 2], [2, 1]]}}\n',
     'uncertainty.fit.rest_terms_nm2'),
    ('format_version: 1\nuncertainty: {fit: {rest_terms_nm2: ' + str((-np.eye(6)).tolist()) + '}}\n',
     'uncertainty.fit.rest_terms_nm2'),
    ('format_version: 1\nuncertainty: {fit: {thermal_state_nm: [1, 2, 3, 4, 5, 6]}}\n',
     'uncertainty.fit.thermal_state_nm'),
    ('format_version: 1\nuncertainty: {fit: {thermal_state_nm: [1, 2, 3, 4, 5, 6, 2e6]}}\n',
     'uncertainty.fit.thermal_state_nm'),
    ('format_version: 1\nuncertainty: {fit: {thermal_state_c: 500}}\n',
     'uncertainty.fit.thermal_state_c'),
    ('format_version: 1\nuncertainty: {sigma_um: 0.4}\n', 'uncertainty.sigma_um'),
    ('format_version: 1\nuncertainty: {fit: {profile: {excess_nm2: ' + str(np.eye(6).tolist())
     + ', lengths_mm: [[300, 301]], factor: [[1, 1]]}}}\n', 'uncertainty.fit.profile.lengths_mm'),
    ('format_version: 1\nuncertainty: {fit: {profile: {excess_nm2: ' + str(np.eye(6).tolist())
     + ', lengths_mm: [[301, 300], [], [], [], [], []], factor: [[1, 1], [], [], [], [], []]}}}\n',
     'uncertainty.fit.profile.factor[0]'),
    ('format_version: 1\nuncertainty: {fit: {profile: {excess_nm2: ' + str(np.eye(6).tolist())
     + ', lengths_mm: [[300, 301], [], [], [], [], []], factor: [[1, -1], [], [], [], [], []]}}}\n',
     'uncertainty.fit.profile.factor[0]'),
    ('format_version: 1\nuncertainty: {fit: {profile: {lengths_mm: [], factor: []}}}\n',
     'uncertainty.fit.profile.excess_nm2'),
    ('format_version: 1\nvalidity: {bar_range_mm: ' + str([[340, 300]] + [[300, 340]] * 5)
     + '}\n', 'validity.bar_range_mm'),
    ('format_version: 1\nvalidity: {bar_range_mm: [[300, 340]]}\n', 'validity.bar_range_mm'),
    ('format_version: 1\nvalidity: {temperature_c: [.nan, 1]}\n', 'validity.temperature_c'),
    ('format_version: 1\nvalidity: {temperature_c: [24, 21]}\n', 'validity.temperature_c'),
    ('format_version: 1\nvalidity: [1, 2]\n', 'validity'),
])
def test_bad_model_files_name_the_key(tmp_path, text, key):
    path = tmp_path / 'model.yaml'
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_model(path)
    assert info.value.key == key and str(path) in str(info.value)


def test_hysteresis_direction_follows_motion_with_a_play_of_travel():
    term = HysteresisTerm(np.full(6, 1e-6), travel_m=5e-6)
    x = np.concatenate([np.linspace(0, 100e-6, 101), np.linspace(100e-6, 97e-6, 4),   # small dither back
                        np.full(10, 97e-6), np.linspace(97e-6, 0, 98)])
    lengths = np.repeat(x[:, None], 6, axis=1)
    ctx = TermContext(np.arange(len(x)) * 1e-3, np.zeros((len(x), 8)), lengths, lengths,
                      np.zeros((len(x), 1)), np.zeros(len(x)))
    corr = term.correction(ctx)[:, 0]
    assert corr[0] == 0.0                        # no motion yet: no direction
    assert corr[50] == pytest.approx(-1e-6)      # lengthening
    assert corr[110] == pytest.approx(-1e-6)     # 3 um back and a dwell: still forward (play 2 x 5 um)
    assert corr[-1] == pytest.approx(1e-6)       # shortening
    # the same in pieces (streaming) as in one call
    term.reset()
    pieces = np.concatenate([term.correction(TermContext(ctx.times_s[k:k + 7], ctx.counts[k:k + 7],
                                                         lengths[k:k + 7], lengths[k:k + 7],
                                                         ctx.reference_error_m[k:k + 7], ctx.temp_change_c[k:k + 7]))
                             for k in range(0, len(x), 7)])
    assert np.array_equal(pieces[:, 0], corr)


def test_streamed_samples_give_the_batch_result():
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=5)
    room = AmbientProfile.constant(21.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=3']), room, start_s=400.0)
    model = Model(terms=[HysteresisTerm(np.full(6, 0.3e-6), 5e-6)])
    batch = Pipeline(DEVICE, calibration, model).process(run.times_s, run.counts, with_covariance=True)
    stream = Pipeline(DEVICE, calibration, Model.from_dict(model.to_dict()))
    for k in range(0, run.n_samples, 97):   # every 97th sample, in order, carries the term's state
        sample = stream.process_sample(run.times_s[k], run.counts[k], with_covariance=True)
        if k == 0:
            continue
        assert sample.valid == batch.valid[k]
    stream.reset()
    poses = []
    for k in range(run.n_samples):
        poses.append(stream.process_sample(run.times_s[k], run.counts[k]).pose)
    assert np.max(np.abs(np.array(poses)[:, :3] - batch.poses[:, :3])) < 1e-11
    assert np.max(np.abs(np.array(poses)[:, 3:] - batch.poses[:, 3:])) < 1e-11
    last = stream.process_sample(run.times_s[-1], run.counts[-1], with_covariance=True)
    assert last.covariance is not None and np.allclose(last.covariance, batch.covariance[-1], rtol=1e-6)


def test_two_pipelines_of_one_model_keep_their_own_term_state():
    """Issue 10, section 4: a model whose terms carry state (play operator, previous sample)
    used by a second pipeline starts that pipeline from a fresh state, whatever the first one
    processed; and the model object itself is left untouched."""
    from mmd_ros.core.terms import SamplingSkewTerm
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=5)
    room = AmbientProfile.constant(21.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=2']), room, start_s=400.0)
    model = Model(terms=[HysteresisTerm(np.full(6, 0.5e-6), 2e-6), SamplingSkewTerm(np.full(6, 40e-6))])
    fresh = Pipeline(DEVICE, calibration, Model.from_dict(model.to_dict())).process(run.times_s, run.counts)
    first = Pipeline(DEVICE, calibration, model)
    first.process(run.times_s[::-1].copy(), run.counts[::-1].copy())   # leaves its terms in some state
    second = Pipeline(DEVICE, calibration, model).process(run.times_s, run.counts)
    assert np.array_equal(second.compensated.lengths_m, fresh.compensated.lengths_m)
    assert model.terms[0]._play is None   # the model's own terms never ran


@pytest.mark.parametrize('profiled', [False, True])
def test_node_stages_transfer_by_transfer_give_the_batch_result(profiled):
    """What compensation_node, fk_node and pose_node compute, 8 samples per transfer, is what
    ``Pipeline.process`` gives for the whole run, covariance included (also with a fit's
    residual claimed where along the bars it lay, ``uncertainty.fit.profile``)."""
    from mmd_ros.core.model import FitUncertainty, LengthProfile
    from mmd_ros.core.streaming import Compensator, Kinematics
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=6)
    room = AmbientProfile.constant(20.5)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=1']), room, start_s=300.0)
    model = Model()
    if profiled:      # a residual of 50 nm per bar, ten times its variance over bar 1's middle
        excess = np.diag(np.full(6, 50e-9)) ** 2
        lo, hi = run.true_lengths[:, 0].min(), run.true_lengths[:, 0].max()
        at = np.linspace(lo, hi, 9)
        profile = LengthProfile(excess, [at] + [np.zeros(0)] * 5,
                                [np.where(np.abs(at - at[4]) < 0.3 * (hi - lo), 10.0, 0.5)]
                                + [np.zeros(0)] * 5)
        model = Model(uncertainty=ModelUncertainty(fit=FitUncertainty(excess, profile=profile)))
        flat = Pipeline(DEVICE, calibration, Model(uncertainty=ModelUncertainty(
            fit=FitUncertainty(excess)))).process(run.times_s, run.counts, with_covariance=True)
    batch = Pipeline(DEVICE, calibration, model).process(run.times_s, run.counts, with_covariance=True)
    compensator = Compensator(DEVICE, model)
    compensator.set_calibration(calibration, 'test')
    kinematics = Kinematics(DEVICE)
    stamps = np.round(run.times_s * 1e9).astype(np.int64)
    poses, covariances, valid = [], [], []
    for a in range(0, run.n_samples, 8):
        comp = compensator.process(stamps[a:a + 8], run.counts[a:a + 8])
        kinematics.budget = compensator.budget
        kin = kinematics.solve(comp.lengths_m, comp.plate_scale, comp.reference_error_m,
                               comp.temp_change_c, comp.bar_error_m, comp.fit_columns_m)
        poses.append(kin.poses)
        valid.append(kin.valid)
        covariances.append(kin.covariance)
    valid = np.concatenate(valid)
    assert valid.mean() > 0.99 and np.array_equal(valid, batch.valid)
    poses = np.concatenate(poses)[valid]
    assert np.max(np.abs(poses - batch.poses[valid])) < 1e-11
    cov = np.concatenate([c for c in covariances if c is not None])
    # the Jacobians are taken at the last Newton iterates, a few nm apart: tiny off-diagonal
    # terms differ by parts in 1e4 of themselves, parts in 1e6 of the variances
    scale = np.max(np.diagonal(cov, axis1=1, axis2=2))
    np.testing.assert_allclose(cov, batch.covariance[valid], rtol=1e-6, atol=1e-5 * scale)
    assert np.all(np.diagonal(cov, axis1=1, axis2=2) > 0)
    if profiled:      # (the profile changed the claim: it is applied, the same way, by both)
        assert not np.allclose(np.diagonal(flat.covariance[valid], axis1=1, axis2=2),
                               np.diagonal(cov, axis1=1, axis2=2), rtol=1e-2, atol=0.0)
    without = Kinematics(DEVICE, compensator.budget, with_covariance=False)
    assert without.solve(comp.lengths_m, comp.plate_scale).covariance is None
    assert Kinematics(DEVICE).solve(comp.lengths_m, comp.plate_scale).covariance is None


def test_node_stages_start_a_replayed_run_afresh():
    """A replay into running stages (compensation_node, fk_node) sends stamps that go back,
    after a live stream that left term states, warm starts and a read-noise estimate behind:
    after ``new_run`` the stages compute the run exactly as a fresh pipeline does, covariance
    included; without it, the stateful term gives other lengths."""
    from mmd_ros.core.streaming import Compensator, Kinematics
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=8)
    room = AmbientProfile.constant(20.5)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=1']), room, start_s=300.0)
    model = Model(terms=[HysteresisTerm(np.full(6, 0.5e-6), 2e-6)])
    batch = Pipeline(DEVICE, calibration, Model.from_dict(model.to_dict())).process(
        run.times_s, run.counts, with_covariance=True)
    stamps = np.round(run.times_s * 1e9).astype(np.int64)

    def stream(compensator, kinematics, order):
        lengths, poses, covariances = [], [], []
        for a in range(0, run.n_samples, 8):
            rows = order[a:a + 8]
            comp = compensator.process(stamps[rows], run.counts[rows])
            kinematics.budget = compensator.budget
            kin = kinematics.solve(comp.lengths_m, comp.plate_scale, comp.reference_error_m,
                                   comp.temp_change_c, comp.bar_error_m, comp.fit_columns_m,
                                   stamps_ns=stamps[rows])
            lengths.append(comp.lengths_m)
            poses.append(kin.poses)
            covariances.append(kin.covariance)
        return np.concatenate(lengths), np.concatenate(poses), np.concatenate(covariances)

    def stages():
        compensator = Compensator(DEVICE, model)
        compensator.set_calibration(calibration, 'test')
        return compensator, Kinematics(DEVICE)

    forward = np.arange(run.n_samples)
    fresh = stream(*stages(), forward)
    compensator, kinematics = stages()
    stream(compensator, kinematics, forward[::-1].copy())   # the "live" stream before the replay
    stale, _, _ = stream(compensator, kinematics, forward)
    assert np.abs(stale - batch.compensated.lengths_m).max() > 1e-7   # the state carried over
    compensator.new_run()
    kinematics.new_run()
    replayed = stream(compensator, kinematics, forward)
    assert np.array_equal(replayed[0], batch.compensated.lengths_m)
    assert batch.valid.mean() > 0.99
    for got, want in zip(replayed, fresh):
        np.testing.assert_array_equal(got, want)


def test_kinematics_diagnostics_count_what_the_samples_show():
    """The kinematics figures of /diagnostics (kept per transfer at 1 kHz) against the
    per-sample outputs: iterations, residual, unconverged and out-of-range samples."""
    from mmd_ros.core.kinematics import FkStatus, inverse_kinematics
    from mmd_ros.core.streaming import Kinematics
    from mmd_ros.nodes.reports import kinematics_report
    t = np.arange(64) * 1e-3
    poses = np.column_stack([0.01 * np.sin(t), 0 * t, 0.3 + 0 * t, 0 * t, 0.02 * t, 0 * t])
    lengths = inverse_kinematics(DEVICE.geometry, poses) + np.random.default_rng(2).normal(0, 5e-8, (64, 6))
    lengths[10, 4] = np.nan                                      # a bar out of its span
    lengths[40] = [0.25, 0.376, 0.25, 0.376, 0.25, 0.376]        # no pose has these lengths
    lengths[50, 2] = 0.2                                         # shorter than any bar
    scale = np.full(64, 1.0 + 2e-6)
    kinematics = Kinematics(DEVICE, 0.3e-6)
    outs = [kinematics.solve(lengths[a:a + 8], scale[a:a + 8]) for a in range(0, 64, 8)]
    its = np.concatenate([o.iterations for o in outs])
    res = np.concatenate([o.residual_m for o in outs])
    valid = np.concatenate([o.valid for o in outs])
    values = kinematics_report(kinematics).values
    status = np.concatenate([o.status for o in outs])
    solved = np.arange(64) != 10
    assert values['samples'] == 64 and values['out_of_range'] == 1
    assert values['not_converged'] == 2 and values['poses_published'] == 61 == valid.sum()
    assert values['fk_not_converged'] == 1 and values['fk_bar_range'] == 1
    assert status[40] == FkStatus.NOT_CONVERGED and status[50] == FkStatus.BAR_RANGE
    assert status[10] == FkStatus.OUT_OF_SPAN and its[50] == 0
    assert values['iterations_mean'] == round(its[solved].mean(), 3)
    # the warm start and both home seeds were tried
    assert values['iterations_max'] == its.max() == 3 * kinematics.fk.max_iter
    assert values['residual_max_m'] == np.nanmax(res) and np.isnan(res[10])
    # the next period starts afresh
    kinematics.solve(lengths[:8], scale[:8])
    again = kinematics_report(kinematics).values
    assert again['iterations_max'] < kinematics.fk.max_iter
    assert again['samples'] == 72 and again['out_of_range'] == 1  # totals since the start


def test_compiled_play_operator_equals_python():
    """HysteresisTerm.directions (the sequential play operator that mmd analyze runs for every
    travel it tries): compiled and Python agree sample for sample, carrying the state across
    calls, with NaN lengths in the stream."""
    from mmd_ros.core.compiled import AVAILABLE, NOT_IN_USE
    assert AVAILABLE, NOT_IN_USE
    rng = np.random.default_rng(8)
    lengths = 0.3 + np.cumsum(rng.normal(0, 2e-6, (5000, 6)), axis=0)
    lengths[1234, 2] = np.nan
    outs = []
    for compiled in (False, True):
        term = HysteresisTerm(np.full(6, 0.3e-6), 4e-6)
        outs.append(np.concatenate([term.directions(lengths[k:k + 777], compiled=compiled)
                                    for k in range(0, len(lengths), 777)]))
    np.testing.assert_array_equal(outs[0], outs[1])
    assert set(np.unique(outs[1])) == {-1.0, 0.0, 1.0}


def test_compiled_friction_state_equals_python():
    """The Dahl friction state (mmd analyze evaluates it for every turn-over travel it tries):
    the compiled play gives Python's positions exactly, the compiled Dahl recursion numpy's
    states to the last bits of an exp, carrying the state across calls of any size."""
    from mmd_ros.core.compiled import AVAILABLE, NOT_IN_USE
    from mmd_ros.core.terms import dahl_state, play_positions
    assert AVAILABLE, NOT_IN_USE
    rng = np.random.default_rng(9)
    n = 20000   # a slow swing with encoder-sized noise: thousands of reversals
    lengths = 0.3 + 20e-6 * np.sin(np.arange(n) / 900)[:, None] + rng.normal(0, 60e-9, (n, 6))
    lengths[4321, 1] = np.nan     # a sample without signal: the play holds
    pos = [play_positions(lengths, 50e-9, None, compiled=c) for c in (False, True)]
    np.testing.assert_array_equal(pos[0], pos[1])
    first = pos[0][0]
    start = (first.copy(), np.zeros(6), first.copy(), np.zeros(6))
    whole, end = dahl_state(pos[0], 2e-6, start, compiled=False)
    parts, state = [], start
    for k in range(0, n, 1237):
        out, state = dahl_state(pos[0][k:k + 1237], 2e-6, state, compiled=True)
        parts.append(out)
    np.testing.assert_allclose(np.concatenate(parts), whole, rtol=0, atol=1e-14)
    for a, b in zip(state, end):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)
    turns = np.count_nonzero(np.diff(np.sign(np.diff(pos[0][:, 0]))[np.diff(pos[0][:, 0]) != 0]))
    assert turns > 100 and whole.min() < -0.8 and whole.max() > 0.8   # the state swings


def test_the_compiled_friction_state_far_past_its_turn_over_is_numpy_s():
    """Bars that move millimetres between reversals, the state turning within micrometres: the
    compiled recursion skips the exp where the state has turned (past 40 travels, where what
    is left is below the last bit of +-1) and gives numpy's states there exactly, elsewhere to
    the last bits of an exp."""
    from mmd_ros.core.terms import dahl_state, play_positions
    t = np.linspace(0.0, 6.0 * np.pi, 30000)
    lengths = 0.3 + 1e-3 * np.sin(t)[:, None] * np.linspace(0.5, 1.0, 6)
    pos = play_positions(lengths, 50e-9, None, compiled=False)
    start = (pos[0].copy(), np.zeros(6), pos[0].copy(), np.full(6, 0.3))
    out = [dahl_state(pos, 2e-6, start, compiled=c)[0] for c in (False, True)]
    turned = np.abs(out[0]) == 1.0
    assert 0.5 < turned.mean() < 1.0                # (most samples, not all: reversals)
    np.testing.assert_array_equal(out[1][turned], out[0][turned])
    np.testing.assert_allclose(out[1], out[0], rtol=0, atol=1e-14)


def test_the_bars_vertical_cosines_are_their_legs_unit_vectors_along_the_vertical():
    """The gravity sag's features from the rotation's entries alone equal those of the legs
    themselves (leg_geometry), for any pose and any vertical."""
    from mmd_ros.core.device import find_config, load_device
    from mmd_ros.core.terms import leg_geometry, vertical_cosines
    geometry = load_device(find_config('mmd_prototype.yaml')).geometry
    rng = np.random.default_rng(4)
    poses = np.column_stack([rng.uniform(-0.1, 0.1, (500, 2)), rng.uniform(0.2, 0.3, 500),
                             rng.uniform(-0.5, 0.5, (500, 3))])
    for vertical in ([0.0, 0.0, 1.0], [0.3, -0.2, 0.93]):
        v = np.asarray(vertical) / np.linalg.norm(vertical)
        _, units, _ = leg_geometry(geometry.upper, geometry.lower, poses)
        assert np.allclose(vertical_cosines(geometry.upper, geometry.lower, poses, v), units @ v,
                           rtol=0, atol=1e-13)
