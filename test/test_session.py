"""Issue 10: models that hold beyond the run they were fitted on.

A session of short logs of one simulated device (the realistic twin, seed 1): an x-axis laser
run, y and z laser runs, a C-axis rotary run and random 6-DOF runs. A model fitted on some of
them is applied to the others (the pipeline re-run), component by component against each
component's noise floor. And the estimators of the catalogue on effects shaped as the twin does
not shape them, injected into a clean log's counts by this test: a friction whose state turns
over along a sech² curve, a cyclic error at 13 µm.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from foreign_effects import sech_friction
from mmd_ros.analysis import AnalysisOptions, analyze
from mmd_ros.analysis.data import make_observation, noise_floor, run_pipeline
from mmd_ros.cli.main import main
from mmd_ros.core.accuracy import coverage, pose_error
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.model import Model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.terms import CdfOffsetsTerm
from mmd_ros.core.validity import CALIBRATION_TERMS, Validity, other_calibration
from mmd_ros.logs.layout import read_run, write_run
from mmd_ros.logs.processing import BLOCK, process_log
from mmd_ros.twin import AmbientProfile, Effects, TwinDevice, make_scenario
from mmd_ros.twin.recording import SimulationSpec, ambient_profile, run_log, simulate_to_log

RATE = 200.0
ISO = ('n_cycles=5',)
DEVICE = load_device(find_config('mmd_prototype.yaml'))


@pytest.fixture(scope='module')
def session(tmp_path_factory):
    """Short logs of one realistic device (same calibration), made once for the module."""
    folder = tmp_path_factory.mktemp('session')
    specs = {
        'x': ('iso_linear', ISO + ('axis=x',), None),
        'y': ('iso_linear', ISO + ('axis=y',), None),
        'z': ('iso_linear', ISO + ('axis=z',), None),
        'c': ('iso_rotary', ISO + ('axis=psi',), None),
        'pose_a': ('random_motion', ('duration_s=60', 'seed=3'), None),
        'pose_b': ('random_motion', ('duration_s=60', 'seed=7'), None),
    }
    out = {}
    start = 600.0
    for name, (scenario, params, reference) in specs.items():
        path = folder / f'{name}.mcap'
        spec = SimulationSpec(scenario=scenario, scenario_params=params, effects='realistic',
                              seed=1, ambient='constant:22', reference=reference,
                              sample_rate_hz=RATE, start_s=start)
        simulate_to_log(spec, path, progress=False)
        out[name] = path
        start += 400.0
    return out


def component_rms(path: Path, model: Model) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Per observed component: RMS of MMD - reference over the whole run (datum removed) under
    ``model``, and the component's noise floor (report units)."""
    run = read_run(path)
    obs = make_observation(run.reference_pose, run.reference_lengths)
    proc = run_pipeline(run.device, run.calibration, model, run.times_s, run.counts)
    ok = obs.usable & proc.valid
    r = obs.residual(proc)[ok]
    r = r - r.mean(axis=0)
    plain = run_pipeline(run.device, run.calibration, Model(), run.times_s, run.counts)
    idx = np.flatnonzero(obs.usable & plain.valid)
    floor = noise_floor(obs, run.device, plain, np.nan_to_num(obs.residual(plain)), idx, True)
    return obs.names, np.sqrt(np.mean(r ** 2, axis=0)) * obs.to_report, floor * obs.to_report


NO_LORO = AnalysisOptions(leave_one_out=False)


def test_a_session_model_claims_the_residual_of_its_own_terms_where_others_could_not_predict_them(
        session):
    """x, y lasers, a C rotary run and a 6-DOF run, absolute (as the twin's logs say): the
    6-DOF run, predicted from the others, is predicted without the calibration's points and the
    scale terms (they do not determine them); its leave-one-run-out residual is not the written
    model's, and sizing the model's uncertainty from it claimed 3.0-10.5 times the error of
    another 6-DOF run (the demo's session: 2.9-17.4). That log's held-out blocks stand for it
    now: 98.1 % of the other run in the 95 % ellipsoid, ratios 0.88-1.01 (measured again on
    2026-11-29, the same before and after that day's changes; 97.5 %, 0.73-0.95, when first
    measured; 95.8 %, 0.66-0.96, while the residual's parts along each bar's length were
    claimed between the bars as the fitted runs' motion tied them; the demo's three new runs
    96.6-96.9 %, 0.94-1.23)."""
    from mmd_ros.logs.processing import process_run, summarize
    result = analyze([read_run(session[k]) for k in ('x', 'y', 'c', 'pose_a')])
    assert all(r.datum.source == 'stated' and not r.datum.zeroed for r in result.runs)
    assert 'not applied' in result.runs[-1].loro_note, result.runs[-1].loro_note
    record = result.model.uncertainty.fit.record
    assert 'held-out blocks of the logs it predicted without' in record['residual_from']
    run = read_run(session['pose_b'])
    judged = summarize(run, process_run(run, result.model, with_covariance=True))
    cover = judged['uncertainty_coverage']
    ratios = [c['ratio'] for c in cover['per_component']]
    print('another 6-DOF run:', cover['ellipsoid_coverage'], np.round(ratios, 2))
    assert cover['ellipsoid_coverage'] >= 0.93 and 0.6 < min(ratios) and max(ratios) < 1.5


@pytest.fixture(scope='module')
def x_only(session):
    return analyze(read_run(session['x']), options=NO_LORO)


@pytest.fixture(scope='module')
def one_axis_session(session):
    return analyze([read_run(session[k]) for k in ('x', 'y', 'z', 'c')], options=NO_LORO)


def test_a_model_fitted_on_the_x_laser_makes_no_component_of_other_runs_worse(session, x_only):
    """The demo's case in issue 10: fitted on x only, the old model made pitch 2.6x worse on a
    6-DOF run. What the x laser cannot check is not written now."""
    model = x_only.model or Model()
    assert x_only.unchecked, 'the x run holds effects whose pitch, roll... it cannot see'
    assert any('record a run that sees' in f.reason for f in x_only.unchecked)
    for other in ('pose_b', 'y'):
        names, before, floor = component_rms(session[other], Model())
        _, after, _ = component_rms(session[other], model)
        for n, b, a, f in zip(names, before, after, floor):
            assert a <= b + f, (other, n, b, a, f)


def test_one_axis_references_write_nothing_that_makes_a_6dof_run_worse(session, one_axis_session):
    """x, y, z and C runs see one component each: whatever they write must not make any
    component of a 6-DOF run worse by more than its noise floor."""
    model = one_axis_session.model or Model()
    names, before, floor = component_rms(session['pose_b'], Model())
    _, after, _ = component_rms(session['pose_b'], model)
    for n, b, a, f in zip(names, before, after, floor):
        assert a <= b + f, (n, b, a, f)


def test_an_absolute_session_brings_another_6dof_run_to_the_noise_floor(session):
    """x, y, z, C and one 6-DOF run against absolute references (as the twin's logs say),
    fitted jointly; applied to a second 6-DOF run of the same device (other motion, not in the
    fit): every component within 1.5 times its noise floor (issue 10, section 3), and the pose
    covariance covers its error. The CDF points and the scale term were not written while a
    term's change of a component a run does not see was judged sample by sample: the z run's
    pitch under the points, 0.56″ at its largest, ± 0.28″, passed through zero somewhere
    within twice its sigma, and the other run was left 3-13 times its floor (x 0.57 µm, y 0.45
    µm); judged over each run (RMS), the 6-DOF run determines both terms and they are written:
    x 0.055 µm, y 0.051 µm, z 0.029 µm, 0.11″ 0.11″ 0.13″, 96.5 % in the 95 % ellipsoid."""
    result = analyze([read_run(session[k]) for k in ('x', 'y', 'z', 'c', 'pose_a')],
                     options=NO_LORO)
    written = [f.effect for f in result.found]
    assert {'calibration_points', 'scale_nonlinearity'} <= set(written), result.conclusion
    assert not result.unchecked, result.conclusion
    names, before, floor = component_rms(session['pose_b'], Model())
    _, after, _ = component_rms(session['pose_b'], result.model)
    print('before', np.round(before, 3), 'after', np.round(after, 3), 'floor', np.round(floor, 3))
    for n, a, f in zip(names, after, floor):
        assert a <= 1.5 * f, (n, a, f)
    run = read_run(session['pose_b'])
    res = Pipeline(run.device, run.calibration, result.model).process(run.times_s, run.counts,
                                                                       with_covariance=True)
    judged = coverage(pose_error(res.poses, run.reference_pose), res.covariance, res.valid,
                      absolute=True, reference_sigma=np.array(run.metadata['reference_sigma']))
    ratios = [r['ratio'] for r in judged['per_component']]
    print('covered', judged['ellipsoid_coverage'], np.round(ratios, 2))
    assert 0.93 <= judged['ellipsoid_coverage'] and 0.8 < min(ratios) and max(ratios) < 1.25


def test_a_session_with_a_6dof_run_improves_every_component_of_another(session):
    """x, y, z, C and one 6-DOF run fitted jointly (the 6-DOF run's reference zeroed, the
    default); applied to a second 6-DOF run of the same device (other motion, not in the fit):
    every component improves, and the pose covariance covers that run's error against its
    absolute reference. It covered 55.3 % when the calibration's sources stayed whole beside
    the zeroed residual, before the claim of the constant error the runs leave unknown; then
    98.2 % (ratios 0.77-1.72), and 100.0 % (0.66-1.96) since the residual's parts along each
    bar's length are claimed independent between the bars (0.74-1.52 since the scale term is
    written: judged sample by sample, the z run's roll under it, 0.11″ ± 0.06″ at its largest,
    had passed through zero within twice its sigma).
    The session's CDF points are not written (with the reference zeroed they would move roll
    in the z run by 0.23″ RMS ± 0.12″, which its runs cannot check), and they leave the friction
    state each point of its one-sided calibration was captured in (+-0.15-0.45 µm per bar and
    pair). While the budget did not claim that, the error was 7-12 times (in sigma) what the
    calibration described, its mean read from its variation did not hold, and a new run was
    covered 89.3 % with the fitted run's block means for how far a run's mean moves (83.2 % with
    four blocks; 99.4 % with the shape's whole spread claimed for where a run dwells). The
    points' friction is now claimed from the bars' stated friction (the device description):
    the calibration describes the error, and the runs read its mean."""
    result = analyze([read_run(session[k]) for k in ('x', 'y', 'z', 'c', 'pose_a')],
                     options=dataclasses.replace(NO_LORO, datum='offset'))
    assert result.model is not None, result.conclusion
    # the points are unchecked in a laser run's unseen component that the 6-DOF run sees but,
    # zeroed, does not determine there: the report says so and names where it is unsure
    points = next(f for f in result.unchecked if f.effect == 'calibration_points')
    print(points.reason)
    assert all(u.seen_by == ['pose_a.mcap'] for u in points.unchecked), points.unchecked
    assert all(u.mostly_from and all(p.startswith('bar') for p in u.mostly_from)
               for u in points.unchecked), points.unchecked
    assert 'pose_a.mcap sees but does not determine' in points.reason, points.reason
    # what its model leaves along the bars is what the calibration describes: its points'
    # friction states (one-sided), whose size the device description states
    assert max(result.model.uncertainty.fit.record['shape_factor']) < 1.5
    names, before, floor = component_rms(session['pose_b'], Model())
    _, after, _ = component_rms(session['pose_b'], result.model)
    for n, b, a in zip(names, before, after):
        assert a < b, (n, b, a)
    assert after[0] < 0.6 * before[0] and after[1] < 0.6 * before[1]
    run = read_run(session['pose_b'])
    res = Pipeline(run.device, run.calibration, result.model).process(run.times_s, run.counts,
                                                                       with_covariance=True)
    judged = coverage(pose_error(res.poses, run.reference_pose), res.covariance, res.valid,
                      absolute=True, reference_sigma=np.array(run.metadata['reference_sigma']))
    print('6-DOF run the session never saw:', judged['ellipsoid_coverage'],
          [round(r['ratio'], 2) for r in judged['per_component']])
    assert judged['ellipsoid_coverage'] >= 0.93


def test_an_unchecked_term_names_only_the_logs_that_could_determine_it():
    """Which other logs see the component a run does not: those whose references see it and
    that share the effect's parameters for that run. A drift's are each run's own (no other
    log determines them, "these runs cannot check"); the CDF points' are the calibration's
    (the logs of another calibration do not determine them)."""
    from types import SimpleNamespace
    from mmd_ros.analysis.identify import Unchecked, _seen_by

    def log(name, kind, components, cal):
        return SimpleNamespace(run=SimpleNamespace(path=Path(name)), cal=cal, name=name,
                               obs=SimpleNamespace(kind=kind, components=components))
    x, c = log('x.mcap', 'pose', [0], 1), log('c.mcap', 'pose', [5], 1)
    a = log('pose_a.mcap', 'pose', list(range(6)), 1)
    b = log('pose_b.mcap', 'pose', list(range(6)), 2)             # (another calibration)
    lengths = log('bars.mcap', 'lengths', list(range(6)), 1)
    groups = {'run': lambda r: r.name, 'calibration': lambda r: r.cal}
    sel = SimpleNamespace(runs=[x, c, a, b, lengths],
                          group_index=lambda e, r: groups[e.scope](r))
    points, drift = SimpleNamespace(scope='calibration'), SimpleNamespace(scope='run')
    assert _seen_by(sel, points, x, 5) == ['c.mcap', 'pose_a.mcap']
    assert _seen_by(sel, points, x, 1) == ['pose_a.mcap']
    assert _seen_by(sel, drift, x, 5) == []
    one = Unchecked('calibration_points', 'x.mcap', 'yaw', 'arcsec', 1.0, 0.6, 0.05, 1.3,
                    ['pose_a.mcap'], ['bar5 point 6 (357.0 mm)'])
    two = dataclasses.replace(one, seen_by=['c.mcap', 'pose_a.mcap'])
    none = dataclasses.replace(one, seen_by=[], mostly_from=[])
    assert 'pose_a.mcap sees but does not determine where x.mcap goes (its uncertainty ' \
           'mostly from bar5 point 6 (357.0 mm)); record a run that sees yaw there' in one.message()
    assert 'c.mcap and pose_a.mcap see but do not determine' in two.message()
    assert none.message().endswith('which these runs cannot check; record a run that sees yaw')


def test_leave_one_run_out_figures_in_the_json(session, tmp_path, capsys):
    assert main(['analyze', str(session['pose_a']), str(session['x']), '--json', '--quiet',
                 '--effects', 'hysteresis,sampling_skew']) == 0
    data = json.loads(capsys.readouterr().out)
    assert data['validation'].startswith('leave-one-run-out')
    assert [Path(r['log']).name for r in data['runs']] == ['pose_a.mcap', 'x.mcap']
    for r in data['runs']:
        assert r['leave_one_run_out_before'] and r['leave_one_run_out_after']
        assert r['held_out_before'] and r['noise_floor']
    assert data['model_file'] is None
    # the model's uncertainty is read on the last log's context with that log's samples (with
    # the first log's, a last log shorter than it was indexed past its end: IndexError)
    short = tmp_path / 'short_a.mcap'
    simulate_to_log(SimulationSpec(scenario='iso_rotary', scenario_params=(
        'axis=phi', 'n_targets=3', 'n_cycles=1'), effects='realistic', seed=1,
        ambient='constant:22', sample_rate_hz=RATE, start_s=3400.0), short, progress=False)
    assert read_run(short).times_s.size < 4000 < read_run(session['x']).times_s.size
    assert main(['analyze', str(session['x']), str(short), '--json', '--quiet',
                 '--effects', 'hysteresis,sampling_skew']) == 0
    data = json.loads(capsys.readouterr().out)
    assert [Path(r['log']).name for r in data['runs']] == ['x.mcap', 'short_a.mcap']
    assert main(['analyze', str(session['x']), '--json', '--quiet', '--effects', 'hysteresis']) == 0
    single = json.loads(capsys.readouterr().out)
    assert single['validation'].startswith('within-run')
    assert 'within-run only' in single['conclusion']


def test_a_log_that_the_other_logs_model_makes_worse_is_named():
    """Leave-one-run-out is the headline: a component that a model fitted on the other logs
    makes worse by more than its noise floor is named in the conclusion's terms (an x ISO run
    and an A-axis run: hysteresis and skew from the x run made the A run's roll 0.819 → 1.03″,
    floor 0.12″, while the figures only listed it)."""
    from mmd_ros.analysis.identify import ComponentError, RunSummary, _loro_worse

    def errors(rms):
        return [ComponentError('roll', 'arcsec', 100, rms, 2 * rms, 0.0, rms)]

    summary = RunSummary('/logs/a.mcap', 'id', 'cal', 'rotary', ['roll'], ['arcsec'], 100,
                         {'roll': 0.12}, errors(0.8), loro_before=errors(0.819),
                         loro_after=errors(1.03))
    assert _loro_worse([summary]) == ['roll of a.mcap worse (0.819 → 1.03 ″, floor 0.12 ″)']
    summary.loro_after = errors(0.93)            # within the floor
    assert _loro_worse([summary]) == []
    summary.loro_after = None                    # one log: no such figure
    assert _loro_worse([summary]) == []


def test_the_model_file_says_what_it_was_validated_on(session, tmp_path, capsys):
    out = tmp_path / 'a'
    assert main(['analyze', str(session['pose_a']), '--out', str(out), '--quiet', '--no-figures',
                 '--effects', 'hysteresis,sampling_skew']) == 0
    model = Model.from_yaml((out / 'model.yaml').read_text())
    validity = Validity.from_model(model)
    run = read_run(session['pose_a'])
    assert validity is not None and validity.runs == (run.content_hash(),)
    assert validity.absolute and validity.temperature_c[0] <= 22.0 <= validity.temperature_c[1] + 0.1
    proc = run_pipeline(run.device, run.calibration, Model(), run.times_s, run.counts)
    bars, temp = validity.outside(proc.cdf_lengths_m, np.full(run.times_s.size, 22.0))
    assert not bars.any() and temp == 0
    bars, temp = validity.outside(proc.cdf_lengths_m + 5e-3, np.full(run.times_s.size, 26.0))
    assert bars.all() and temp == run.times_s.size
    assert 'bar1 outside' in validity.describe(bars, temp)
    # the live compensation warns outside that range
    from mmd_ros.core.streaming import Compensator
    comp = Compensator(run.device, model)
    comp.set_calibration(run.calibration, 'test')
    counts = run.counts[:50].copy()
    comp.process(np.arange(50, dtype=np.int64), counts)
    assert not comp.stats.period_outside_bars.any()
    far = counts.copy()
    beyond = validity.bar_range_m[0, 1] + 3e-3 - proc.cdf_lengths_m[0, 0]   # 3 mm past its range
    far[:, 0] += beyond / run.device.encoder_resolution_m * np.sign(
        run.calibration.bars['bar1'].counts[-1] - run.calibration.bars['bar1'].counts[0])
    comp.process(np.arange(50, 100, dtype=np.int64), far)
    assert comp.stats.period_outside_bars[0] > 0
    # the model names its calibration: with another one (the device calibrated again, another
    # device of the same description), the live compensation and mmd process say so
    assert comp.model_mismatch is None and other_calibration(model, run.calibration) is None
    bar = run.calibration.bars['bar1']
    again = dataclasses.replace(run.calibration, bars={**run.calibration.bars, 'bar1': (
        dataclasses.replace(bar, counts=(bar.counts[0] + 3.0, *bar.counts[1:])))})
    comp.set_calibration(again, 'again')
    assert comp.model_mismatch and again.key() in comp.model_mismatch
    assert run.calibration.key() in comp.model_mismatch
    again.save(tmp_path / 'again.yaml')
    capsys.readouterr()
    assert main(['process', str(session['pose_a']), '--model', str(out / 'model.yaml'),
                 '--calibration', str(tmp_path / 'again.yaml'), '--out',
                 str(tmp_path / 'p.mcap'), '--no-coverage', '--json']) == 0
    captured = capsys.readouterr()
    assert 'warning: the model was fitted with calibration' in captured.err
    assert again.key() in json.loads(captured.out)['model_calibration']
    terms = Model(terms=[CdfOffsetsTerm(np.tile(np.linspace(0.25, 0.376, 7), (6, 1)),
                                        np.zeros((6, 7)))], extra=model.extra)
    assert 'its cdf_offsets term(s) correct' in other_calibration(terms, again)
    # ISO 230-2 "after" on the run the model was fitted on says it is in-sample, on another not
    capsys.readouterr()
    assert main(['iso230-2', str(session['x']), '--after', str(out / 'model.yaml'), '--json']) == 0
    assert json.loads(capsys.readouterr().out)['in_sample'] == {'MMD before': False, 'MMD after': False}


def on_terminal(calibration, serial: str):
    """``calibration`` as if made with the (hardware) terminal ``serial``, as the nodes' are."""
    from mmd_ros.core.calibration import TerminalBinding
    return dataclasses.replace(calibration, terminal=TerminalBinding(serial, False))


def test_a_model_of_another_terminal_is_refused_with_both_serials(session, tmp_path, capsys):
    """A model names the terminal its logs were calibrated with; a calibration made by the
    nodes names its own. Another terminal is another device (or at least other channel
    delays): the pipeline, and so the nodes and every command, refuse the model, naming both,
    where before it was applied (a twin's model on another twin's log made x 2.10 µm RMS where
    the default model left 1.34, and its 95 % ellipsoid held none of the poses)."""
    from mmd_ros.core.errors import ModelError
    from mmd_ros.core.streaming import Compensator
    run = read_run(session['pose_a'])
    ours = on_terminal(run.calibration, 'MMD-0042')
    fitted = analyze(dataclasses.replace(run, calibration=ours),
                     options=AnalysisOptions(effects=['sampling_skew'])).model
    assert fitted is not None
    model = Model.from_yaml(fitted.to_yaml())
    assert model.extra['analysis'][-1]['per_calibration_terminal'] == 'MMD-0042'
    Pipeline(run.device, ours, model)                       # its own terminal: used
    Pipeline(run.device, dataclasses.replace(run.calibration, terminal=None),
             model)                                         # a calibration naming none: used
    theirs = on_terminal(ours, 'MMD-0043')
    with pytest.raises(ModelError, match='model refused.*MMD-0042.*MMD-0043'):
        Pipeline(run.device, theirs, model)
    comp = Compensator(run.device, model)
    assert comp.set_calibration(theirs, 'test').startswith('model refused') and 'MMD-0043' in comp.problem
    assert comp.set_calibration(ours, 'test') is None
    model.save(tmp_path / 'model.yaml')
    capsys.readouterr()
    # the log's own calibration names the twin's terminal (mmd simulate: MMD-SIM-<seed>)
    assert main(['process', str(session['pose_a']), '--model', str(tmp_path / 'model.yaml'),
                 '--out', str(tmp_path / 'p.mcap')]) == 2
    err = capsys.readouterr().err
    assert 'model refused' in err and 'MMD-0042' in err and 'MMD-SIM-0001' in err, err
    assert 'Traceback' not in err
    assert not (tmp_path / 'p.mcap').exists()


def test_a_calibration_of_another_terminal_cannot_read_a_log_s_counts(session, tmp_path, capsys):
    """``--calibration`` replaces a log's own; when the log's calibration names the terminal
    its counts came from, a calibration made with another cannot read them (its counter
    zeros, its bars on those channels): ``mmd process`` and ``mmd analyze`` refuse it, naming
    both (so does ``mmd iso230-2``; ``mmd machine analyze`` reads through ``mmd process``'s
    pipeline), as the live nodes refuse it, where before they computed poses from it."""
    run = read_run(session['pose_a'])
    ours = on_terminal(run.calibration, 'MMD-0042')
    log = tmp_path / 'bound.mcap'
    write_run(log, run.device, ours, run.stamps_ns[:2000], run.counts[:2000],
              reference_pose=run.reference_pose[:2000])
    theirs = on_terminal(ours, 'MMD-0043')
    theirs.save(tmp_path / 'theirs.yaml')
    ours.save(tmp_path / 'ours.yaml')
    capsys.readouterr()
    for command in (['process', str(log), '--out', str(tmp_path / 'p.mcap')],
                    ['analyze', str(log), '--out', str(tmp_path / 'a'), '--quiet'],
                    ['iso230-2', str(log), '--axis', 'x']):
        assert main(command + ['--calibration', str(tmp_path / 'theirs.yaml')]) == 2, command
        err = capsys.readouterr().err
        assert 'calibration refused' in err and 'MMD-0042' in err and 'MMD-0043' in err, err
    assert not (tmp_path / 'p.mcap').exists() and not (tmp_path / 'a' / 'model.yaml').exists()
    # a calibration of the same terminal reads them
    assert main(['process', str(log), '--out', str(tmp_path / 'q.mcap'), '--no-coverage',
                 '--calibration', str(tmp_path / 'ours.yaml')]) == 0


def test_the_terms_a_model_holds_of_its_calibration_are_the_catalogue_s():
    """core.validity names the term types of a calibration (the analysis is above it): the
    effects of scope 'calibration' in the catalogue."""
    from mmd_ros.analysis.effects import CATALOGUE
    scoped = {e.term_type for e in CATALOGUE.values() if e.scope == 'calibration'}
    assert scoped == set(CALIBRATION_TERMS)


def test_logs_of_two_devices_are_refused(session, tmp_path, capsys):
    other = tmp_path / 'other.mcap'
    spec = SimulationSpec(scenario='random_motion', scenario_params=('duration_s=5',),
                          effects='ideal', device='mmd_two_reference_bars.yaml', sample_rate_hz=RATE)
    simulate_to_log(spec, other, progress=False)
    assert main(['analyze', str(session['pose_a']), str(other), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'one analysis takes logs of one device' in err and 'Traceback' not in err
    # two MMDs of one description: their calibrations name the terminals they were made with
    from mmd_ros.analysis.errors import AnalysisError
    a, b = (read_run(session[k]) for k in ('pose_a', 'pose_b'))
    a, b = (dataclasses.replace(r, calibration=on_terminal(r.calibration, serial))
            for r, serial in ((a, 'MMD-0042'), (b, 'MMD-0043')))
    with pytest.raises(AnalysisError, match='MMD-0043.*MMD-0042.*one device'):
        analyze([a, b])
    # and two twins of one description: `mmd simulate` names each one's terminal by its seed
    # (before, the seed 1 and seed 2 twins were fitted as one device)
    second = tmp_path / 'second.mcap'
    simulate_to_log(dataclasses.replace(SimulationSpec(
        scenario='random_motion', scenario_params=('duration_s=5',), effects='realistic',
        sample_rate_hz=RATE), seed=2), second, progress=False)
    assert read_run(session['pose_a']).calibration.terminal.serial == 'MMD-SIM-0001'
    capsys.readouterr()
    assert main(['analyze', str(session['pose_a']), str(second), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'MMD-SIM-0001' in err and 'MMD-SIM-0002' in err and 'Traceback' not in err, err
    # the nodes' simulated terminal of a seed is that twin: its calibrations and mmd
    # simulate's go together (a model of one is used with the other), another seed's do not
    from mmd_ros.core.calibration import TerminalBinding, binding_problem
    from mmd_ros.nodes.terminal import TERMINAL_PARAMS, TerminalConfig, sim_serial_of
    values = {p.name: p.default for p in TERMINAL_PARAMS}         # the nodes' defaults: seed 1
    logged = read_run(session['pose_a']).calibration
    live = TerminalBinding(TerminalConfig.from_values(values).sim_serial, True,
                           logged.terminal.channels)
    assert live.serial == 'MMD-SIM-0001' and binding_problem(logged, live) is None
    assert 'MMD-SIM-0007' in binding_problem(logged, dataclasses.replace(
        live, serial=sim_serial_of({**values, 'sim_seed': 7})))


# -- the realistic twin calibrated from both sides ---------------------------------------------
def above_floor(stats, floor: dict[str, float], factor: float) -> list[str]:
    """The components of ``stats`` (ComponentError rows or their dicts) above ``factor`` times
    their noise floor, as text (empty when none)."""
    rows = {(s['name'] if isinstance(s, dict) else s.name): (s['rms'] if isinstance(s, dict) else s.rms)
            for s in stats}
    return [f'{n} {rows[n]:.3g} > {factor} x {f:.3g}' for n, f in floor.items() if rows[n] > factor * f]


@pytest.fixture(scope='module')
def two_sided(tmp_path_factory):
    """Logs of the realistic device calibrated two-sided (each CDF point seated once from
    shorter and once from longer, so that the friction state on the points averages out):
    three 30 s random 6-DOF runs, the x, y, z and C laser runs and a 6-DOF run kept aside."""
    folder = tmp_path_factory.mktemp('two_sided')
    specs = {f'pose{k}': ('random_motion', ('duration_s=30', f'seed={100 + k}')) for k in range(3)}
    specs.update({'x': ('iso_linear', ISO + ('axis=x',)), 'y': ('iso_linear', ISO + ('axis=y',)),
                  'z': ('iso_linear', ISO + ('axis=z',)), 'c': ('iso_rotary', ISO + ('axis=psi',)),
                  'aside': ('random_motion', ('duration_s=40', 'seed=7'))})
    out, start = {}, 600.0
    for name, (scenario, params) in specs.items():
        out[name] = folder / f'{name}.mcap'
        simulate_to_log(SimulationSpec(scenario=scenario, scenario_params=params, effects='realistic',
                                       seed=1, ambient='constant:22', sample_rate_hz=RATE,
                                       start_s=start, calibration_approaches=2), out[name], progress=False)
        start += 300.0
    return out


def test_realistic_6dof_runs_close_to_the_floor_within_run_and_on_runs_the_fit_never_saw(two_sided, capsys):
    """Issue 10 section 3: three random 6-DOF runs of the realistic twin (full-pose reference),
    analysed jointly: every component of every run within 1.5 x its noise floor on held-out
    blocks, and predicted by the model fitted on the other two runs (leave-one-run-out) within
    1.5 x where its bar lengths lie within those the other runs covered (the share outside
    that range is reported, not hidden) and over all its samples."""
    logs = [str(two_sided[f'pose{k}']) for k in range(3)]
    assert main(['analyze', *logs, '--json', '--quiet']) == 0
    data = json.loads(capsys.readouterr().out)
    assert {'hysteresis', 'sampling_skew'} <= {f['effect'] for f in data['found']}, data['conclusion']
    for r in data['runs']:
        floor = r['noise_floor']
        assert not above_floor(r['held_out_after'], floor, 1.5), (r['log'], 'within-run')
        share = r['leave_one_run_out_in_range_share']
        assert 0.5 < share <= 1.0
        assert not above_floor(r['leave_one_run_out_after_in_range'], floor, 1.5), (r['log'], 'LORO')
        # and over all its samples, bar lengths the other runs never reached included (5-15 %
        # of each run here; a run a fifth outside was 2 x in a 1 kHz session, msg_docs/analysis.md)
        assert not above_floor(r['leave_one_run_out_after'], floor, 1.5), (r['log'], 'LORO, all samples')
        # before: several times the floor, so the figure above is the loop's doing
        assert above_floor(r['leave_one_run_out_before'], floor, 5.0)


def test_x_y_z_c_laser_runs_improve_every_component_of_a_6dof_run(two_sided):
    """Issue 10 cross-motion: the x, y, z and C laser runs of a two-sided calibration, fitted
    jointly with the whole catalogue, applied to a 6-DOF run kept aside: every component
    improves. Each reference sees one component; in the five others the MMD reads the
    machine's motion along the run's axis, a function of the axis position, and what moves
    with speed is the device's (analysis/axis_motion.py). Those rows determine the six channel
    delays (measured within 0.5 µs of the twin's, 1.2-49 µs), so what they do to roll and pitch
    is known and they are written. Measured: x 1.24 -> 0.51 µm, y 1.53 -> 0.34, z 0.41 -> 0.11,
    roll 0.60 -> 0.26 ″, pitch 0.50 -> 0.35, yaw 0.72 -> 0.42 (the scale term those runs find
    is not written: its effect on the unseen components is not determined)."""
    runs = [read_run(two_sided[k]) for k in ('x', 'y', 'z', 'c')]
    result = analyze(runs, options=NO_LORO)
    written = {f.effect: f for f in result.found}
    assert {'hysteresis', 'sampling_skew'} <= set(written), result.conclusion
    true_skew = TwinDevice(DEVICE, Effects.preset('realistic'), seed=1).physics.skew_s[list(DEVICE.measuring_channels)]
    assert np.allclose(written['sampling_skew'].value, true_skew, atol=2e-6), (written['sampling_skew'].value, true_skew)
    # leave-one-run-out turned off: no figure, not the "before" one given as both
    assert all(s.loro_after is None for s in result.runs)
    assert 'not computed' in result.validation and 'Leave-one-run-out' not in result.conclusion
    names, before, floor = component_rms(two_sided['aside'], Model())
    _, after, _ = component_rms(two_sided['aside'], result.model)
    print('before', before, 'after', after)
    for n, b, a in zip(names, before, after):
        assert a < b, (n, b, a)
    assert np.all(after[:3] < 0.5 * before[:3]), (before, after)


def test_without_the_unseen_components_one_axis_runs_write_no_skew(two_sided):
    """The same runs read only in the component each reference sees (``axis_motion`` off):
    the friction amplitudes and channel delays are determined only in four combinations of six
    bars, so what they do to roll and pitch is not determined and nothing is written (the
    report says which run to record)."""
    runs = [read_run(two_sided[k]) for k in ('x', 'y', 'z', 'c')]
    checked = analyze(runs, options=AnalysisOptions(leave_one_out=False, effects=['hysteresis', 'sampling_skew'],
                                                    axis_motion=False))
    assert checked.model is None and checked.unchecked
    assert all('record a run that sees' in f.reason or 'worse' in f.reason for f in checked.unchecked)


# -- selection: effects that share a signature -------------------------------------------------
@functools.lru_cache(maxsize=5)
def bench_twin_analysis(k: int):
    """``mmd analyze`` (absolute reference) of the k-th realistic twin of ``bench_uncertainty.py
    --after``: 60 s of random 6-DOF motion after its two-sided calibration. Cached (~60 MB
    each): the tests here judge k = 5 and 7, test_uncertainty.py k = 2-5 and 7."""
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=k + 1)
    room = ambient_profile('section_4_1')
    calibration = twin.calibrate(-211.0 * k, room, approaches=2)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=60', f'seed={100 + k}']), room,
                        start_s=600.0, reference='pose6')
    return analyze(run_log(twin, calibration, run, 600.0), options=AnalysisOptions(datum='none'))


@pytest.mark.parametrize('k', [5, 7])
def test_effects_that_follow_the_same_coordinate_are_found_together(k):
    """Two realistic twins of the 24 of ``bench_uncertainty.py --after`` on which the loop used
    to stop early, 10-12 x the noise floor left:

    - k = 5: a channel delay (11 % held-out gain, t 2.8) and friction (8 %, t 2.3) both follow
      the direction of motion and each explained part of it; neither passed alone and nothing
      was written (x 0.57 µm). They are now tried as a pair;
    - k = 7: the scale term, judged while the CDF point offsets that follow the same bar
      length were in the model, was set aside as not claimed, then the points too (x 0.50
      µm). What is set aside is now tried again once the rest is claimed.

    Every component within 2.5 x its floor on held-out blocks (measured 1.0-2.1 x)."""
    result = bench_twin_analysis(k)
    found = [f.effect for f in result.found]
    assert {'sampling_skew', 'hysteresis', 'scale_nonlinearity'} <= set(found), result.conclusion
    if k == 5:
        assert any(c.verdict.startswith('added jointly') for c in result.steps[0]), result.steps[0]
    floor = result.runs[0].floor
    assert not above_floor(result.stats_after, floor, 2.5), result.conclusion


def test_a_drift_does_not_take_what_the_device_s_effects_explain():
    """Twin k = 5 of ``bench_uncertainty.py --after`` (absolute reference): at the third step
    a drift (11 parameters: a per-bar offset and rate) took the twins' gravity sag's constant
    (one parameter), its held-out criterion 0.886 of the drift's, just under the 0.9 that
    parsimony allows. Written, the drift's rate, fitted over 60 s, claimed 94 nm on every bar
    of a run 100 s later (35 nm seen); it was then set aside as not structure along its own
    coordinate (time). A drift's parameters belong to its run, and the model written leaves
    them out: while an effect whose parameters outlast the run passes, parsimony chooses among
    those, and the sag (0.915 of the best of them, the kinematic parameters) is added."""
    result = bench_twin_analysis(5)
    found = [f.effect for f in result.found]
    assert 'gravity_sag' in found and 'drift' not in found, result.conclusion
    step = next(step for step in result.steps if any(c.effect == 'gravity_sag' and c.verdict == 'added'
                                                         for c in step))
    drift = next(c for c in step if c.effect == 'drift')
    assert drift.verdict == 'significant' and drift.delta_ic < min(
        c.delta_ic for c in step if c.effect != 'drift'), [(c.effect, c.delta_ic) for c in step]
    assert not above_floor(result.stats_after, result.runs[0].floor, 1.5), result.conclusion


@pytest.mark.parametrize('sag_m', [0.1e-6, 0.0])
def test_with_an_absolute_reference_an_offset_is_structure_an_effect_must_explain(sag_m):
    """The realistic preset's 0.1 µm gravity sag moves z by nearly the same amount over a
    6-DOF run's small workspace: 5.5 x the floor in z with an absolute reference. The check
    that an effect removes most of the structure along its own coordinate counted that
    structure about the log's mean, saw 9 % of it removed and set the sag aside (z stayed at
    5.5 x). With an absolute reference the offset is counted too; without a sag, nothing is
    claimed."""
    twin = TwinDevice(DEVICE, Effects.ideal().with_assignments([f'gravity_sag_m={sag_m}']), seed=2)
    room = AmbientProfile.constant(22.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=30', 'seed=102']), room,
                        start_s=600.0, reference='pose6')
    result = analyze(run_log(twin, calibration, run, 600.0), options=AnalysisOptions(datum='none'))
    assert not result.not_claimed, [(f.effect, f.reason) for f in result.not_claimed]
    floor = result.runs[0].floor
    if not sag_m:
        assert not result.found, result.conclusion
        return
    assert [f.effect for f in result.found] == ['gravity_sag'], result.conclusion
    assert above_floor(result.stats_before, {'z': floor['z']}, 3.0), result.stats_before
    assert not above_floor(result.stats_after, floor, 1.5), result.conclusion


def test_the_sag_is_fitted_along_the_vertical_the_log_s_description_states():
    """An MMD on its side (+x of {L} up, between a horizontal spindle and its table): its bars
    sag along x, which moves x, not z. The log's device description states the vertical
    (``plates.vertical``), and the gravity_sag effect's signature and term go along it: 0.5 um
    fitted at 0.536 um, x 0.088 -> 0.032 um (floor 0.038)."""
    side = DEVICE.with_vertical([1.0, 0.0, 0.0])
    twin = TwinDevice(side, Effects.ideal().with_assignments(['gravity_sag_m=5e-7']), seed=2)
    room = AmbientProfile.constant(22.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=30', 'seed=102']), room,
                        start_s=600.0, reference='pose6')
    result = analyze(run_log(twin, calibration, run, 600.0), options=AnalysisOptions(datum='none'))
    assert [f.effect for f in result.found] == ['gravity_sag'], result.conclusion
    term = next(t for t in result.model.terms if t.type_name == 'gravity_sag')
    assert term.vertical.tolist() == [1.0, 0.0, 0.0]
    assert 0.4e-6 < float(term.sag_m[0]) < 0.6e-6, term.sag_m
    floor = result.runs[0].floor
    assert above_floor(result.stats_before, {'x': floor['x']}, 2.0), result.stats_before
    assert not above_floor(result.stats_after, floor, 1.5), result.conclusion


# -- estimators on effects shaped otherwise ----------------------------------------------------
def injected_log(tmp_path: Path, name: str, error_of, scenario: str = 'random_motion',
                 params: tuple[str, ...] = ('duration_s=40',), reference: str = 'pose6',
                 effects: Effects | None = None, lag_s: float = 0.0,
                 metadata: dict | None = None) -> Path:
    """A clean log of the ideal twin (by default 40 s of 6-DOF motion; another twin with
    ``effects``) whose measuring-bar counts carry ``error_of(true_lengths, counts)`` (N, 6) [m]
    of reading error; its 6-DOF reference read ``lag_s`` late (the pose then, with the
    reference's noise), as another program's logger on its own clock would."""
    twin = TwinDevice(DEVICE, effects or Effects.ideal(), seed=2)
    room = AmbientProfile.constant(21.0)
    calibration = twin.calibrate(0.0, room)
    scene = make_scenario(scenario, list(params))
    run = twin.simulate(scene, room, start_s=600.0, sample_rate_hz=RATE, reference=reference)
    counts = run.counts.astype(np.float64)
    meas = list(DEVICE.measuring_channels)
    if error_of is not None:
        counts[:, meas] += np.rint(error_of(run.true_lengths, counts) / DEVICE.encoder_resolution_m)
    ref = run.reference
    if lag_s:
        ref = ref - run.true_poses + scene.build(DEVICE).pose(run.times_s - lag_s)
    stamps = (np.round((600.0 + run.times_s) * 1e9)).astype(np.int64)
    return write_run(tmp_path / name, DEVICE, calibration, stamps, counts, reference_pose=ref,
                     metadata=metadata)


def judged_on_new_motion(model: Model, error_of) -> tuple[float, list[float]]:
    """20 s of other 6-DOF motion of :func:`injected_log`'s twin (the same calibration), its
    counts carrying ``error_of(true_lengths, counts)`` [m] too, processed with ``model``: the
    share of its samples in the 95 % ellipsoid (against the true pose) and predicted /
    observed sigma per component."""
    twin = TwinDevice(DEVICE, Effects.ideal(), seed=2)
    room = AmbientProfile.constant(21.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=20', 'seed=5']), room,
                        start_s=600.0, sample_rate_hz=RATE, reference='pose6')
    counts = run.counts.astype(np.float64)
    meas = list(DEVICE.measuring_channels)
    counts[:, meas] += np.rint(error_of(run.true_lengths, counts) / DEVICE.encoder_resolution_m)
    res = Pipeline(DEVICE, calibration, model).process(run.times_s, counts, with_covariance=True)
    judged = coverage(pose_error(res.poses, run.true_poses), res.covariance, res.valid,
                      absolute=True)
    ratios = [round(r['ratio'], 2) for r in judged['per_component']]
    print('new run:', judged['ellipsoid_coverage'], ratios)
    return judged['ellipsoid_coverage'], ratios


def overall(result, after: bool = True) -> float:
    stats = result.stats_after if after and result.stats_after else result.stats_before
    return next(s.rms for s in stats if s.name == 'overall (um)')


def test_a_friction_turning_over_along_another_curve_is_found_and_removed(tmp_path):
    """sech² turn-over over 6 µm, 0.3 µm amplitude: named hysteresis, its travel fitted, and
    the held-out error brought close to the clean log's."""
    amp = np.array([0.2, 0.35, 0.3, 0.25, 0.4, 0.3]) * 1e-6
    log = injected_log(tmp_path, 'sech.mcap', lambda d, q: -amp * sech_friction(d, 6e-6))
    clean = analyze(read_run(injected_log(tmp_path, 'clean.mcap', None)))
    result = analyze(read_run(log))
    assert result.found and result.found[0].effect == 'hysteresis', result.conclusion
    assert overall(result, after=False) > 3 * overall(clean, after=False)
    assert overall(result) < 1.5 * overall(clean, after=False), (overall(result), overall(clean, after=False))
    fitted = -result.found[0].value
    assert np.allclose(fitted, amp, atol=0.06e-6), fitted


def test_the_friction_setting_chosen_is_the_one_best_on_held_out_data(tmp_path):
    """Issue 10 (a): the training criterion picks the turn-over travel; when the choice matters
    (held-out errors of the settings differ by more than 2x), its held-out error is within 10 %
    of the best setting's."""
    from mmd_ros.analysis.effects import CATALOGUE
    from mmd_ros.analysis.identify import _prepare, _reference_datum, _Selector
    amp = np.full(6, 0.3e-6)
    run = read_run(injected_log(tmp_path, 'sech2.mcap', lambda d, q: -amp * sech_friction(d, 10e-6)))
    o = AnalysisOptions()
    datum, _ = _reference_datum(run, Model(), None, o)
    sel = _Selector([_prepare(0, run, Model(), None, o, lambda t: None, datum)], o)
    effect = CATALOGUE['hysteresis']
    _, e0 = sel.baseline()
    chosen = sel.evaluate(effect, e0)
    held_out = {}
    for travel in effect.hypers([sel.ctx]) + [chosen.hyper]:
        fit = sel.reduce(effect, travel)
        pred = sel.columns(effect, travel, 'test') @ (fit['basis'] @ fit['beta'])
        if fit['coef_b'].size:
            pred = pred + sel.base('test') @ fit['coef_b']
        held_out[travel] = float(np.mean((sel.test.y - pred) ** 2))
    best, worst = min(held_out.values()), max(held_out.values())
    assert worst > 2 * best
    assert held_out[chosen.hyper] <= 1.1 * best, (chosen.hyper, held_out)


@pytest.mark.parametrize('absolute', [False, True])
def test_a_scale_error_that_fills_a_laser_s_residual_is_found_and_claimed(tmp_path, absolute):
    """A linear scale error of every bar (5-8 ppm about the middle of the travel, 0.25-0.35 µm
    at its ends) seen by an x-axis laser over 40 s of 6-DOF motion: 87 times the noise
    floor's mean square. The CDF points left 1.1 times it on the held-out blocks (t 15.9), but
    the criterion counted the baseline residual's effective samples, 14 of 8000 (their
    correlation the error's own), and nothing was found: "no catalogued effect explains the
    residual", which was carried as an uncertainty only, a new run's samples 90.2 % in the
    95 % ellipsoid (66.7 % with a bar beyond the fitted lengths). When nothing passes, the
    count of what the best candidate leaves judges again: the points are found, reported as
    what an x laser cannot check, and their growth beyond the lengths seen is claimed: 100 %
    and 100 %. Against the laser's reading absolute (as the log says), the scale's constant part
    is seen too, and named a change of the bars' length offsets (kinematic), not written
    either; a new run 94.2 % (y's error 1.5 times its claim: a prior, x alone seen)."""
    ends = np.array([0.30, -0.25, 0.35, 0.30, -0.28, 0.32]) * 1e-6
    mid, slope = [], []          # (about the middle of each bar's travel in the fitted log)

    def scale(d, q):
        mid.append(0.5 * (d.max(axis=0) + d.min(axis=0)))
        slope.append(ends / (0.5 * np.ptp(d, axis=0)))
        return slope[0] * (d - mid[0])
    log = injected_log(tmp_path, 'scale.mcap', scale, reference='laser_x',
                       metadata={'reference_absolute': absolute})
    result = analyze(read_run(log))
    named = ['kinematic'] if absolute else ['calibration_points']
    assert [f.effect for f in result.unchecked] == named, result.conclusion
    assert 'No catalogued effect' not in result.conclusion, result.conclusion
    assert result.model is not None, result.conclusion
    covered, _ = judged_on_new_motion(result.model, lambda d, q: slope[0] * (d - mid[0]))
    assert covered >= 0.93


def test_a_cyclic_error_at_a_period_of_no_list_is_found_from_the_spectrum(tmp_path):
    """13 µm, 80 nm: not a standard signal period; its period is estimated from the data."""
    names = DEVICE.channel_names
    channels = list(DEVICE.measuring_channels)

    def cyclic(d, counts):
        phase = 2 * np.pi * counts[:, channels] * DEVICE.encoder_resolution_m / 13e-6
        return 80e-9 * np.sin(phase + np.arange(6))

    result = analyze(read_run(injected_log(tmp_path, 'cyc13.mcap', cyclic)))
    found = {f.effect: f for f in result.found}
    assert 'cyclic_error' in found, result.conclusion
    period, in_calibration = found['cyclic_error'].hyper
    assert math.isclose(period, 13e-6, rel_tol=2e-3) and not in_calibration, found['cyclic_error'].hyper
    amp = np.hypot(found['cyclic_error'].value[:6], found['cyclic_error'].value[6:12])
    assert np.allclose(amp, 80e-9, atol=15e-9), amp
    del names


def test_a_cyclic_error_s_second_harmonic_is_fitted_with_its_fundamental(tmp_path):
    """An encoder whose signals have unequal amplitudes or are not in quadrature errs at half
    its signal period too (Heydemann): 60 nm at 20 µm and 30 nm at 10 µm. The fundamental alone
    was fitted (amplitudes 49-65 nm) and left 0.051 µm where the clean log has 0.028; both
    harmonics are fitted now."""
    channels = list(DEVICE.measuring_channels)

    def cyclic(d, counts):
        phase = 2 * np.pi * counts[:, channels] * DEVICE.encoder_resolution_m / 20e-6
        return 60e-9 * np.sin(phase + np.arange(6)) + 30e-9 * np.sin(2 * phase + 2.0 * np.arange(6))

    result = analyze(read_run(injected_log(tmp_path, 'cyc2.mcap', cyclic)))
    clean = analyze(read_run(injected_log(tmp_path, 'clean.mcap', None)))
    found = {f.effect: f for f in result.found}
    assert 'cyclic_error' in found, result.conclusion
    assert math.isclose(found['cyclic_error'].hyper[0], 20e-6, rel_tol=2e-3)
    value = np.asarray(found['cyclic_error'].value).reshape(4, 6)
    assert np.allclose(np.hypot(value[0], value[1]), 60e-9, atol=12e-9), value
    assert np.allclose(np.hypot(value[2], value[3]), 30e-9, atol=12e-9), value
    assert overall(result) < 1.5 * overall(clean, after=False), (overall(result), overall(clean, after=False))


def test_a_cyclic_error_is_found_from_the_spectrum_of_a_laser_run_that_dwells():
    """The same error on an x-axis ISO 230-2 run with a laser along x. The run dwells at its
    targets: thousands of samples on a few counts, whose sums made a comb as wide as the
    spectrum, so no period stood out and the error (63 % of the held-out RMS) was not found
    unless its period was given. The spectrum now averages each count's samples. With one
    component seen, what the term does to y is not determined: found, and not written."""
    import tempfile
    channels = list(DEVICE.measuring_channels)

    def cyclic(d, counts):
        phase = 2 * np.pi * counts[:, channels] * DEVICE.encoder_resolution_m / 13e-6
        return 80e-9 * np.sin(phase + np.arange(6))

    with tempfile.TemporaryDirectory() as tmp:
        run = read_run(injected_log(Path(tmp), 'laser.mcap', cyclic, 'iso_linear',
                                    ('axis=x', 'n_cycles=5'), 'laser_x'))
    result = analyze(run)
    cyc = [f for f in result.found + result.unchecked if f.effect == 'cyclic_error']
    assert cyc, result.conclusion
    assert math.isclose(cyc[0].hyper[0], 13e-6, rel_tol=2e-3), cyc[0].hyper


@pytest.mark.parametrize('seed', [1, 2])
def test_a_clean_iso_run_with_a_laser_at_24c_adds_nothing(tmp_path, seed):
    """Issue 10 (d): on the ideal twin at 24.2 °C with a 1-D laser the residual is at the floor:
    nothing is added (the kinematic term used to be, on every seed)."""
    path = tmp_path / f'clean{seed}.mcap'
    simulate_to_log(SimulationSpec(scenario='iso_linear', scenario_params=ISO, effects='ideal',
                                   seed=seed, ambient='constant:24.2', sample_rate_hz=RATE),
                    path, progress=False)
    result = analyze(read_run(path))
    assert result.found == [] and result.model is None, [f.effect for f in result.found]
    assert result.at_floor


@pytest.mark.parametrize('kind', ['settling', 'lost counts'])
def test_what_belongs_to_one_run_is_not_carried_to_a_longer_one(tmp_path, kind):
    """A reading that settles over each run's first seconds (0.3 µm, 15 s), or five counts lost
    on one bar half-way through, is fitted as a drift: an offset and a rate of that run. The
    model used to carry both to other runs, where the rate went on: on 300 s of new motion
    without either error it made z 0.95 µm (0.05 without the model) and x 1.4 µm. What
    belongs to the run fitted is now left out of the model's terms (its size is claimed as
    uncertainty): on 120 s of new motion the model makes no component worse by more than a
    tenth of the clean error. Against the reference absolute (the log does not say, and its
    offsets from the MMD read absolute) the lost counts are named for what they are, a step in
    bar3's reading."""
    amp = np.array([0.30, -0.25, 0.35, -0.30, 0.28, -0.32]) * 1e-6

    def error_of(d, counts):
        n = d.shape[0]
        if kind == 'settling':
            return amp * np.exp(-np.arange(n)[:, None] / RATE / 15.0)
        out = np.zeros((n, 6))
        out[n // 2:, 2] = 5 * DEVICE.encoder_resolution_m
        return out

    result = analyze(read_run(injected_log(tmp_path, 'own.mcap', error_of)))
    if kind == 'lost counts':
        assert result.runs[0].datum.source == 'found' and not result.runs[0].datum.zeroed
        assert [(s.bar, round(s.counts)) for _, s in result.glitches] == [(2, 5)], \
            result.conclusion
    else:
        assert 'drift' in [f.effect for f in result.found], result.conclusion
    assert not any(t.type_name == 'drift' for t in result.model.terms)
    twin = TwinDevice(DEVICE, Effects.ideal(), seed=2)
    room = AmbientProfile.constant(21.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(make_scenario('random_motion', ['duration_s=120', 'seed=5']), room,
                        start_s=700.0, sample_rate_hz=RATE, reference='pose6')
    errors = {}
    for name, model in (('without', Model()), ('with', result.model)):
        res = Pipeline(DEVICE, calibration, model).process(run.times_s, run.counts)
        ok = res.valid & np.all(np.isfinite(run.true_poses), axis=1)
        errors[name] = np.sqrt(np.mean(pose_error(res.poses, run.true_poses)[ok] ** 2, axis=0))
    assert np.all(errors['with'] <= 1.1 * errors['without']), errors


def test_a_reference_that_does_not_say_whether_it_is_absolute_is_read_from_its_offsets(tmp_path):
    """Another program's log of a device whose bars read 0.2-0.3 µm off each (a constant per
    bar), its reference the true pose, not saying whether that is absolute: compared zeroed
    (what every such log was), nothing was found, the offsets' pose-dependent part left as an
    uncertainty, and new motion had 0.0 % of its samples in the 95 % ellipsoid (yaw's error 7.7
    times its claim). The offsets from the MMD are beyond what the budget claims (yaw 1.8″),
    but the reference does not read zero where the log starts and no offset is a pose it could
    have been zeroed at: taken as absolute, the offsets are found (kinematic: the bars' length
    offsets) and new motion is covered 97.8 %, ratios 0.98-1.19. The same reference zeroed
    where the log starts, or half-way, is taken as zeroed; a statement or an option decides
    over the offsets. ``mmd process`` reads them alike for its coverage figures."""
    from mmd_ros.logs.processing import process_run, summarize
    from mmd_ros.analysis.identify import ReferenceDatum, _reference_datum
    offsets = np.array([0.3, -0.2, 0.25, -0.3, 0.2, -0.25]) * 1e-6

    def error_of(d, q):
        return np.broadcast_to(offsets, d.shape).copy()
    path = injected_log(tmp_path, 'offsets.mcap', error_of)
    result = analyze(read_run(path), options=NO_LORO)
    datum = result.runs[0].datum
    assert datum.source == 'found' and not datum.zeroed and not datum.starts_at_zero
    assert 'taken as absolute' in result.conclusion, result.conclusion
    assert result.as_dict()['runs'][0]['reference_datum']['zeroed'] is False
    assert [f.effect for f in result.found] == ['kinematic'], result.conclusion
    covered, ratios = judged_on_new_motion(result.model, error_of)
    assert covered > 0.93 and max(ratios) < 1.5, ratios
    run = read_run(path)
    for k in (0, run.counts.shape[0] // 2):      # zeroed where the log starts, half-way
        zeroed = dataclasses.replace(run, reference_pose=run.reference_pose - run.reference_pose[k])
        decided, _ = _reference_datum(zeroed, Model(), None, NO_LORO)
        assert decided.zeroed and decided.source == 'found', decided
        assert decided.starts_at_zero is (k == 0)
    stated = dataclasses.replace(run, metadata={**run.metadata, 'reference_absolute': False})
    assert _reference_datum(stated, Model(), None, NO_LORO)[0].zeroed
    as_text = dataclasses.replace(run, metadata={'reference_absolute': 'False'})  # (not JSON)
    assert _reference_datum(as_text, Model(), None, NO_LORO)[0] == ReferenceDatum(True, 'stated')
    asked = dataclasses.replace(NO_LORO, datum='offset')
    assert _reference_datum(run, Model(), None, asked)[0].zeroed
    processed = process_run(run, Model(), with_covariance=True)
    read = summarize(run, processed)
    assert read['reference_datum'] == {'zeroed': False, 'source': 'found'}
    assert not read['uncertainty_coverage']['offset_removed']
    zeroed = dataclasses.replace(run, reference_pose=run.reference_pose - run.reference_pose[0])
    assert summarize(zeroed, processed)['reference_datum'] == {'zeroed': True, 'source': 'found'}
    assert summarize(stated, processed)['reference_datum'] == {'zeroed': True, 'source': 'stated'}


def test_a_reference_noise_the_log_does_not_state_is_read_from_the_data(tmp_path):
    """Another program's log of a clean device whose 6-DOF reference has 1 nm and 0.1″ of noise
    and does not say so: that noise was taken for the MMD's, and the analysis wrote an
    uncertainty of roll 4.6 times the budget's into an unchanged model. It is now read from the
    data (the residual's white noise beyond the MMD's own), said in the reference's line, and
    nothing is written."""
    result = analyze(read_run(injected_log(tmp_path, 'clean.mcap', None)))
    obs = result.obs
    assert obs.sigma_estimated
    assert np.allclose(obs.sigma[3:], 0.1 / 206264.8, rtol=0.15), obs.sigma
    assert np.all(obs.sigma[:3] < 5e-9), obs.sigma
    assert 'which the log does not state, read from the data' in result.runs[0].reference
    assert result.model is None and not result.uncertainty_only, result.conclusion


def test_a_reference_noise_read_beside_the_mmd_s_own_leaves_the_mmd_s_claim_whole(tmp_path):
    """The same unstated 0.1″ reference on a device whose bars read 30 nm of white noise more
    than its description says (its own roll noise then 0.05″): the reference's noise is the
    difference of two white noises read from the data (the error's and the MMD's own), and
    each was the robust spread of their departures, whose scatter is a standard deviation's
    over 37 % of the samples: roll read 6 % high (514 nrad where the reference had 485), the
    MMD's excess in roll lost a third of its size, and a new run's roll was claimed 0.76
    times its error (93.2 % in the 95 % ellipsoid; 1.07 and 95.8 % with the noise stated).
    Now the standard deviation of the departures within 5 robust sigmas of their median:
    96.3 %, 0.99-1.08."""
    def noise(n: int) -> np.ndarray:
        return np.random.default_rng(11 + n).normal(0.0, 30e-9, (n, 6))
    log = injected_log(tmp_path, 'noisy.mcap', lambda d, q: noise(d.shape[0]))
    result = analyze(read_run(log))
    assert result.obs.sigma_estimated and result.model is not None, result.conclusion
    assert np.allclose(result.obs.sigma[3:], 0.1 / 206264.8, rtol=0.03), result.obs.sigma
    covered, ratios = judged_on_new_motion(result.model, lambda d, q: noise(q.shape[0]))
    assert covered >= 0.93 and min(ratios) >= 0.85, ratios


def test_counts_lost_at_one_instant_are_reported_as_a_step(tmp_path):
    """Five counts lost on bar 3 half-way through a log (of the ideal twin, and of the
    realistic one): no effect has that shape, and the analysis fitted the line through it as a
    drift without a word. The bars' residual the fit leaves is now searched for steps: that one
    is reported (bar, time, size: 4.6 and 4.4 counts), and none on the clean log or on a
    realistic twin's 60 s log."""
    def lost(d, counts):
        out = np.zeros((d.shape[0], 6))
        out[d.shape[0] // 2:, 2] = -5 * DEVICE.encoder_resolution_m
        return out

    for effects in (None, Effects.realistic()):
        result = analyze(read_run(injected_log(tmp_path, 'lost.mcap', lost, effects=effects)))
        assert [(log, s.bar) for log, s in result.glitches] == [('lost.mcap', 2)], result.glitches
        step = result.glitches[0][1]
        assert step.time_s == pytest.approx(20.0, abs=0.05) and step.counts == pytest.approx(-5.0, abs=1.0)
        assert 'A step in a bar\'s reading: bar3 of lost.mcap' in result.conclusion
    assert analyze(read_run(injected_log(tmp_path, 'clean.mcap', None))).glitches == []
    assert bench_twin_analysis(5).glitches == []


def test_a_friction_the_model_lacks_turns_with_the_bar_and_is_not_reported_as_counts_lost(tmp_path):
    """The realistic twin's 10 s log analysed without the friction effect (left out, as a
    friction of a shape the catalogue does not follow would be): its turns were reported as
    counts lost or gained, +0.86, -0.88 and -0.87 µm on bar 6, each at a turn of that bar.
    A step within a few points of a turn of the bar is the friction's; five counts lost on bar
    3 half-way through the same log, away from its turns, are still reported."""
    from mmd_ros.analysis.glitches import residual_steps, turns
    spec = SimulationSpec(scenario='random_motion', scenario_params=('duration_s=10',),
                          effects='realistic', reference='pose6', sample_rate_hz=RATE)
    simulate_to_log(spec, tmp_path / 'turns.mcap', progress=False)
    run = read_run(tmp_path / 'turns.mcap')
    result = analyze(run, options=AnalysisOptions(exclude=('hysteresis',)))
    assert result.glitches == [], result.glitches
    # a bar going back and forth, its friction flipping at each turn, and five counts lost
    # half-way along a leg: searched without the bar's travel, the turns are taken for steps
    t = np.linspace(0.0, 1.0, 4000)
    tri = 20e-6 * np.abs((t * 7.0) % 2.0 - 1.0)
    flips = np.sign(np.gradient(tri))
    friction = 0.3e-6 * flips                                   # reads +-0.3 µm as it moves
    lost = np.where(np.arange(t.size) >= 2142, -5 * DEVICE.encoder_resolution_m, 0.0)
    noise = np.random.default_rng(0).normal(0.0, 10e-9, t.size)
    values = (friction + lost + noise)[:, None]
    assert len(turns(tri)) == 6
    plain = residual_steps(t, values, [2], DEVICE.encoder_resolution_m)
    assert len(plain) == 3 and all(abs(s.counts) > 10 for s in plain)   # turns taken for steps
    found = residual_steps(t, values, [2], DEVICE.encoder_resolution_m, tri[:, None])
    assert [round(s.counts) for s in found] == [-5] and found[0].time_s == pytest.approx(
        t[2142], abs=3e-3)


def test_mmd_process_reads_the_reference_noise_a_log_does_not_state(tmp_path, capsys):
    """The same clean log through ``mmd process --covariance``: the reference's 0.1″ was not
    added to the predicted sigma, and the coverage read 14.0 % (roll 0.22 times its error),
    as if the MMD claimed far too little. It is read from the data now, and said."""
    log = injected_log(tmp_path, 'clean.mcap', None)
    assert main(['process', str(log), '--covariance', '--json', '--out', str(tmp_path / 'p.mcap')]) == 0
    report = json.loads(capsys.readouterr().out)['uncertainty_coverage']
    assert report['reference_sigma_estimated'] == ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
    rows = {r['name']: r for r in report['per_component']}
    assert rows['roll']['reference_sigma'] == pytest.approx(0.1, rel=0.15), rows['roll']
    assert report['ellipsoid_coverage'] > 0.93, report


def test_a_reference_on_a_clock_of_its_own_puts_its_lag_into_no_term(tmp_path, capsys):
    """A clean device's 6-DOF reference logged by another program 10 µs late, the log saying
    that the reference runs on its own clock (``reference_clock: own``): a common delay of the
    bars' channels and the reference's lag are one signature, and the analysis wrote a skew of
    10 µs on every channel; on new motion against the true pose the model made every component
    2.7-18 times worse than no model (27.7 % in the 95 % ellipsoid). The lag is now a nuisance of
    the log, reported, and no skew takes it; a log that does not say keeps the skew (a delay
    within what a channel can latch is the MMD's), unless ``mmd analyze --reference-clock own``
    says it for the log."""
    log = injected_log(tmp_path, 'own.mcap', None, lag_s=10e-6, metadata={'reference_clock': 'own'})
    result = analyze(read_run(log))
    lag = result.runs[0].lag
    assert lag is not None and lag.stated and lag.delay_s == pytest.approx(10e-6, abs=0.3e-6), lag
    assert 'reads 10 µs late' in result.conclusion, result.conclusion
    assert not result.found and result.model is None, result.conclusion
    unsaid = injected_log(tmp_path, 'unsaid.mcap', None, lag_s=10e-6)
    assert analyze(read_run(unsaid)).runs[0].lag is None
    assert main(['analyze', str(unsaid), '--json', '--reference-clock', 'own', '--quiet']) == 0
    data = json.loads(capsys.readouterr().out)
    assert data['runs'][0]['reference_lag']['clock_stated_own'], data['runs'][0]
    assert not data['found'] and data['model_file'] is None, data['conclusion']


@pytest.mark.parametrize('lag_s,gap', [(5e-3, False), (2.6e-3, False), (2.6e-3, True),
                                       (-3e-3, False)])
def test_a_reference_late_by_more_than_a_channel_can_latch_is_taken_as_lagging(tmp_path, lag_s,
                                                                                gap):
    """The same reference 5 ms late, in a log that does not say whose clock it runs on (time
    stamps taken on receipt): no skew could hold it, a false 230 µm step on bar 4 was reported,
    and the uncertainty written claimed 2000-10000 times a new run's error (2.6 ms: 119 µm,
    1000-5200 times; 3 ms early: 138 µm, 1200-6000 times). A delay beyond the
    2 ms any channel can latch late is the reference's: paired a whole sample period later and
    the rest fitted as a nuisance (smoothed velocity and acceleration: at 200 Hz 2.6 ms is
    half a period from either sample), nothing is found, nothing claimed, no step; also with a
    1 s gap in the log and 0.5 s without a reference (the smoothed motion is not known within
    a window of the gap: with zeros there, what the lag left beside it was claimed as an
    error)."""
    run = read_run(injected_log(tmp_path, 'late.mcap', None, lag_s=lag_s))
    if gap:
        keep = np.ones(run.stamps_ns.size, dtype=bool)
        keep[3000:3200] = False
        ref = run.reference_pose.copy()
        ref[5000:5100] = np.nan
        run = read_run(write_run(tmp_path / 'gap.mcap', run.device, run.calibration,
                                 run.stamps_ns[keep], run.counts[keep], reference_pose=ref[keep]))
    result = analyze(run)
    lag = result.runs[0].lag
    assert lag is not None and not lag.stated and lag.delay_s == pytest.approx(lag_s, abs=1e-6), lag
    assert not result.found and not result.glitches, result.conclusion
    assert result.model is None and not result.uncertainty_only, result.conclusion
    reported = json.loads(json.dumps(result.runs[0].as_dict()))['reference_lag']
    assert reported['delay_s'] == lag.delay_s


@pytest.mark.parametrize('lag_s,block,gap', [(5e-3, BLOCK, False), (-3e-3, 700, True)])
def test_mmd_process_compares_a_lagging_reference_at_the_mmd_s_instants(tmp_path, lag_s, block,
                                                                         gap):
    """The same clean 6-DOF log, its reference 5 ms late (3 ms early) in a log that does not
    say whose clock it runs on: ``mmd process`` compared each MMD sample with the reference's
    reading of the same stamp, and reported 164 µm of position error (RMS; 85 µm at 2.6 ms)
    and 13.6 % of the samples in the 95 % ellipsoid, the MMD's own being 0.048 µm and 97.9 %.
    The delay is now read (beyond what a channel can latch: the reference's), the run compared
    once more at the MMD's instants (the reading a period later, the rest along the MMD's
    smoothed motion): the figures of the log without a lag, also block by block (700 samples)
    across a 1 s gap and 0.5 s without a reference."""
    def processed(path: Path, **kw) -> dict:
        return process_log(read_run(path), tmp_path / f'{path.stem}.out.mcap', Model(), **kw)

    true = processed(injected_log(tmp_path, 'true.mcap', None))
    assert 'reference_lag' in true and not true['reference_lag']['taken_out'], true
    late = injected_log(tmp_path, 'late.mcap', None, lag_s=lag_s)
    if gap:
        run = read_run(late)
        keep = np.ones(run.stamps_ns.size, dtype=bool)
        keep[3000:3200] = False
        ref = run.reference_pose.copy()
        ref[5000:5100] = np.nan
        late = write_run(tmp_path / 'gap.mcap', run.device, run.calibration, run.stamps_ns[keep],
                         run.counts[keep], reference_pose=ref[keep])
    summary = processed(late, block=block)
    lag = summary['reference_lag']
    assert lag['taken_out'] and lag['delay_s'] == pytest.approx(lag_s, abs=1e-6), lag
    rms = {s['name']: s['rms'] for s in summary['pose_error']}
    for s in true['pose_error']:
        assert rms[s['name']] < 1.2 * s['rms'] + (0.005 if s['unit'] == 'um' else 0.01), (s, rms)
    judged = summary['uncertainty_coverage']
    assert 0.93 <= judged['ellipsoid_coverage'] <= 0.99, judged
    assert all(0.8 <= r['ratio'] <= 1.3 for r in judged['per_component']), judged
    if block != BLOCK:      # block by block as at once
        whole = processed(late)
        assert [s['rms'] for s in whole['pose_error']] == pytest.approx(
            [s['rms'] for s in summary['pose_error']], rel=1e-9)
        assert whole['reference_lag']['delay_s'] == pytest.approx(lag['delay_s'], rel=1e-9)


def test_mmd_process_takes_a_small_lag_out_only_when_the_reference_is_on_its_own_clock(
        tmp_path, capsys):
    """10 µs late, within what the MMD's channels can latch: left in the error (it is the
    MMD's own sampling skew, as far as a log that does not say can tell), and said; stated
    on another clock (``--reference-clock own``, or the log's ``reference_clock: own``) it
    is taken out; a log on the MMD's clock (shared) is not read for one."""
    late = injected_log(tmp_path, 'late.mcap', None, lag_s=10e-6)
    assert main(['process', str(late), '--out', str(tmp_path / 'a.mcap')]) == 0
    assert 'within what its channels can latch, so left in the error' in capsys.readouterr().out
    assert main(['process', str(late), '--out', str(tmp_path / 'b.mcap'), '--json',
                 '--reference-clock', 'own']) == 0
    own = json.loads(capsys.readouterr().out)
    assert own['reference_lag']['taken_out'] and own['reference_lag']['clock_stated_own']
    assert own['reference_lag']['delay_s'] == pytest.approx(10e-6, abs=0.3e-6)
    assert own['uncertainty_coverage']['ellipsoid_coverage'] > 0.93, own['uncertainty_coverage']
    shared = injected_log(tmp_path, 'shared.mcap', None, lag_s=10e-6,
                          metadata={'reference_clock': 'shared'})
    assert main(['process', str(shared), '--out', str(tmp_path / 'c.mcap'), '--json']) == 0
    said = json.loads(capsys.readouterr().out)
    assert 'reference_lag' not in said, said
    assert said['uncertainty_coverage']['ellipsoid_coverage'] < 0.5, said
    # (and, as mmd analyze, the option says whether the reference is zeroed over the log)
    assert said['reference_datum'] == {'zeroed': False, 'source': 'found'}
    assert main(['process', str(shared), '--out', str(tmp_path / 'd.mcap'), '--json',
                 '--zeroed-reference']) == 0
    zeroed = json.loads(capsys.readouterr().out)
    assert zeroed['reference_datum'] == {'zeroed': True, 'source': 'option'}
    assert zeroed['uncertainty_coverage']['offset_removed']


def test_one_log_on_the_mmd_s_clock_determines_the_common_skew_of_a_session(tmp_path):
    """Two logs of a realistic twin (channels latching within [0, 50 µs]), one whose reference
    runs on its own clock: its lag is fitted, and the other log, on the MMD's clock, determines
    the skew's common delay, which is written (the term had taken whether it was fitted from
    the last log alone). With both on their own clocks it is not."""
    twin = TwinDevice(DEVICE, Effects.realistic(), seed=2)
    true_mean = float(np.mean(twin.physics.skew_s[list(DEVICE.measuring_channels)]))
    own = injected_log(tmp_path, 'own.mcap', None, effects=Effects.realistic(),
                       metadata={'reference_clock': 'own'})
    shared = injected_log(tmp_path, 'shared.mcap', None, params=('duration_s=40', 'seed=7'),
                          effects=Effects.realistic(), metadata={'reference_clock': 'shared'})
    # zeroed: an absolute reference sees the calibration's point errors too, which neither
    # effect offered here explains
    options = AnalysisOptions(leave_one_out=False, effects=['hysteresis', 'sampling_skew'],
                              datum='offset')
    for logs, fitted in (([shared, own], True), ([own], False)):
        result = analyze([read_run(p) for p in logs], options=options)
        skew = [t for t in result.model.terms if t.type_name == 'sampling_skew']
        assert len(skew) == 1 and skew[0].common_fitted is fitted, result.conclusion
        if fitted:
            assert np.mean(skew[0].skew_s) == pytest.approx(true_mean, abs=3e-6)
        else:
            assert abs(np.mean(skew[0].skew_s)) < 5e-6, skew[0].skew_s
