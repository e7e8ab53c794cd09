"""Hostile but fair input, every way in (issue 14, items 7–9).

A table of malformed inputs across the ``mmd`` subcommands and the file kinds they read (model,
calibration, device, ambient profile, machine description, test program, log and the YAML
strings inside a log; in every file kind an unknown key is refused, with the key it resembles), run in-process
through ``mmd_ros.cli.main.main``. Each must end with exit status 2 and a message naming what was
wrong; the test fails on any traceback (an exception other than SystemExit out of ``main``), on
any silent acceptance (status 0), and on any file left in the output folder. A few run as real
subprocesses. Valid runs with ``--json`` print strict JSON (no bare NaN).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mmd_ros.cli.main import main
from mmd_ros.core.device import find_config
from mmd_ros.core.yamlio import MAX_YAML_BYTES
from mmd_ros.logs.layout import TOPIC_MODEL, read_run, write_run
from mmd_ros.logs.writer import LogWriter
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log

#: Nine levels of nine aliases: 9^9 = 387 million leaves from ten lines ("billion laughs").
BOMB = 'format_version: 1\na: &a ["x","x","x","x","x","x","x","x","x"]\n' + ''.join(
    f'{b}: &{b} [{", ".join([f"*{a}"] * 9)}]\n' for a, b in zip('abcdefgh', 'bcdefghi'))
RECURSIVE = 'format_version: 1\nthermal: &t {mode: auto, loop: *t}\n'


def model(body: str) -> str:
    return f'format_version: 1\n{body}\n'


def hysteresis(**params: str) -> str:
    fields = {'amplitude_um': '0.3', 'travel_um': '5.0', **params}
    inner = ', '.join(f'{k}: {v}' for k, v in fields.items())
    return model(f'terms: [{{type: hysteresis, {inner}}}]')


def term(kind: str, **params: str) -> str:
    inner = ', '.join(f'{k}: {v}' for k, v in params.items())
    return model(f'terms: [{{type: {kind}, {inner}}}]')


WITH_MODEL = 'process {log} --model m.yaml'
WITH_CALIBRATION = 'process {log} --calibration c.yaml'


def edited(kind: str, old: str, new: str):
    """A file of ``kind`` ('device' or 'cal', valid text from the fixture) with one edit."""
    def text(env):
        assert old in env[kind]
        return env[kind].replace(old, new, 1)
    return text


SIX3 = '[[1,2,3],[1,2,3],[1,2,3],[1,2,3],[1,2,3],[1,2,3]]'
MACHINE = find_config('machine_xyzac.yaml').read_text()


@pytest.fixture(scope='module')
def env(tmp_path_factory):
    """A valid log, and the prototype's device file and calibration as text to damage."""
    root = tmp_path_factory.mktemp('inputs')
    log = root / 'run.mcap'
    simulate_to_log(SimulationSpec(scenario='hold', scenario_params=('duration_s=2',)), log, progress=False)
    run = read_run(log)
    device_text = find_config('mmd_prototype.yaml').read_text()
    cal_text = run.calibration.to_yaml()
    logs = root / 'logs'
    logs.mkdir()
    (logs / 'text.mcap').write_bytes(b'hello, not a log\n')
    (logs / 'empty.mcap').write_bytes(b'')

    def special(name, write):
        with LogWriter(logs / name) as w:
            write(w)

    t0 = int(run.stamps_ns[0])

    def with_model(text):
        def write(w):
            w.write_string('/mmd/device_description', t0, run.device.to_yaml())
            w.write_string('/mmd/calibration', t0, cal_text)
            w.write_string(TOPIC_MODEL, t0, text)
            w.write_joint_states('/mmd/raw_counts', run.stamps_ns, run.device.channel_names, run.counts)
        return write

    special('model_bomb.mcap', with_model(BOMB))
    special('model_nan.mcap', with_model(model('length_sigma_um: .nan')))

    def device_list(w):
        w.write_string('/mmd/device_description', t0, '[1, 2, 3]')
        w.write_joint_states('/mmd/raw_counts', run.stamps_ns, run.device.channel_names, run.counts)

    special('device_list.mcap', device_list)

    def device_typo(w):
        w.write_string('/mmd/device_description', t0,
                       run.device.to_yaml().replace('fixed_length_mm:', 'fixed_lenght_mm:'))
        w.write_joint_states('/mmd/raw_counts', run.stamps_ns, run.device.channel_names, run.counts)

    special('device_typo.mcap', device_typo)

    def wrong_names(w):
        w.write_string('/mmd/device_description', t0, run.device.to_yaml())
        w.write_joint_states('/mmd/raw_counts', run.stamps_ns, [f'c{k}' for k in range(8)], run.counts)

    special('wrong_names.mcap', wrong_names)

    def bad_metadata(w):
        with_model(model(''))(w)
        w.write_metadata('mmd_run', {'scenario': '{not json'})

    special('bad_metadata.mcap', bad_metadata)
    stamps = run.stamps_ns.copy()
    stamps[1000:] -= 5_000_000_000
    write_run(logs / 'backwards.mcap', run.device, run.calibration, stamps, run.counts,
              reference_pose=run.reference_pose)
    stamps = run.stamps_ns.copy()
    stamps[1::2] = stamps[::2][:stamps[1::2].size]
    write_run(logs / 'repeated.mcap', run.device, run.calibration, stamps, run.counts,
              reference_pose=run.reference_pose)
    return {'log': log, 'device': device_text, 'cal': cal_text, 'logs': logs}


# (id, files {name: text | bytes | callable(env)}, argv with {log} {out} {dir} placeholders, expected)
CASES = [
    # -- model files: every field checked, unknown keys refused, sizes bounded --------------------
    ('model sigma nan', {'m.yaml': model('length_sigma_um: .nan')}, WITH_MODEL, 'length_sigma_um'),
    ('model sigma inf', {'m.yaml': model('length_sigma_um: .inf')}, WITH_MODEL, 'length_sigma_um'),
    ('model sigma bool', {'m.yaml': model('length_sigma_um: true')}, WITH_MODEL, 'length_sigma_um'),
    ('model sigma negative', {'m.yaml': model('length_sigma_um: -1')}, WITH_MODEL, 'length_sigma_um'),
    ('model sigma text', {'m.yaml': model('length_sigma_um: abc')}, WITH_MODEL, 'length_sigma_um'),
    ('model travel nan', {'m.yaml': hysteresis(travel_um='.nan')}, WITH_MODEL, 'travel_um'),
    ('model travel zero', {'m.yaml': hysteresis(travel_um='0')}, WITH_MODEL, 'travel_um'),
    ('model amplitude text', {'m.yaml': hysteresis(amplitude_um='"abc"')}, WITH_MODEL, 'amplitude_um'),
    ('model amplitude bools', {'m.yaml': hysteresis(amplitude_um='[true, true, true, true, true, true]')},
     WITH_MODEL, 'amplitude_um'),
    ('model amplitude length', {'m.yaml': hysteresis(amplitude_um='[1, 2]')}, WITH_MODEL, 'amplitude_um'),
    ('model amplitude inf', {'m.yaml': hysteresis(amplitude_um='.inf')}, WITH_MODEL, 'amplitude_um'),
    ('model unknown key', {'m.yaml': model('thermall: {mode: auto}')}, WITH_MODEL, 'did you mean thermal'),
    ('model unknown thermal key', {'m.yaml': model('thermal: {mode: auto, plate_expansio: true}')},
     WITH_MODEL, 'thermal.plate_expansio'),
    ('model unknown term key', {'m.yaml': hysteresis(travl_um='5')}, WITH_MODEL, 'travl_um'),
    ('model thermal mode', {'m.yaml': model('thermal: {mode: twice}')}, WITH_MODEL, 'thermal.mode'),
    ('model plate bool', {'m.yaml': model('thermal: {plate_expansion: 1}')}, WITH_MODEL,
     'plate_expansion'),
    ('model terms not list', {'m.yaml': model('terms: {type: hysteresis}')}, WITH_MODEL, 'terms'),
    ('model term type', {'m.yaml': model('terms: [{type: magic}]')}, WITH_MODEL, 'terms[0].type'),
    ('model not a mapping', {'m.yaml': '[1, 2, 3]\n'}, WITH_MODEL, 'format_version'),
    ('model empty', {'m.yaml': ''}, WITH_MODEL, 'format_version'),
    ('model binary', {'m.yaml': b'\x89PNG\r\n\x1a\n\x00\x00\xff\xfe' * 10}, WITH_MODEL,
     'not a text file'),
    ('model bomb', {'m.yaml': BOMB}, 'process {log} --json --model m.yaml', 'expands to'),
    ('model recursive alias', {'m.yaml': RECURSIVE}, WITH_MODEL, 'recursion'),
    ('model deep nesting', {'m.yaml': 'format_version: 1\nx: ' + '[' * 5000 + ']' * 5000 + '\n'},
     WITH_MODEL, 'm.yaml'),
    ('model oversized', {'m.yaml': lambda env: 'format_version: 1\n#' + 'x' * (MAX_YAML_BYTES + 10)},
     WITH_MODEL, 'larger than'),
    ('model is a folder', {'m.yaml/keep': 'x'}, WITH_MODEL, 'cannot be read'),
    ('model missing', {}, 'process {log} --model nothing.yaml', 'nothing.yaml'),
    ('model invalid yaml', {'m.yaml': 'format_version: 1\nthermal: [\n'}, WITH_MODEL, 'not valid YAML'),
    ('cyclic channels bools', {'m.yaml': term('cyclic_error', period_um='20', resolution_nm='50',
                                              channels='[true, 1, 2, 3, 4, 5]', count_origin='0',
                                              sin_nm='0', cos_nm='0')}, WITH_MODEL, 'channels'),
    ('cyclic calibration counts repeated', {'m.yaml': term(
        'cyclic_error', period_um='20', resolution_nm='50', channels='[0, 1, 2, 3, 4, 5]',
        count_origin='0', sin_nm='0', cos_nm='0', calibration_counts=str([[1, 1]] * 6))},
     WITH_MODEL, 'calibration_counts'),
    ('thermal gain inf', {'m.yaml': term('thermal_gain', gain='.inf')}, WITH_MODEL, 'gain'),
    ('knots text', {'m.yaml': term('cdf_offsets', knots_mm='[["a", "b"]]', offsets_um='[[0, 0]]')},
     WITH_MODEL, 'knots_mm'),
    ('drift rate text', {'m.yaml': term('drift', rate_um_per_h='"fast"')}, WITH_MODEL, 'rate_um_per_h'),
    ('joint offsets shape', {'m.yaml': term('joint_offsets', upper_mm='[[1, 2]]', lower_mm=SIX3)},
     WITH_MODEL, 'upper_mm'),
    ('sag vertical bools', {'m.yaml': term('gravity_sag', upper_mm=SIX3, lower_mm=SIX3, sag_um='0',
                                           vertical='[true, false, true]')}, WITH_MODEL, 'vertical'),
    # -- calibration files ------------------------------------------------------------------------
    ('calibration binary', {'c.yaml': b'\x00\xff' * 64}, WITH_CALIBRATION, 'not a text file'),
    ('calibration valid text', {'c.yaml': edited('cal', 'valid: true', 'valid: "no"')}, WITH_CALIBRATION, 'valid'),
    ('calibration ambient nan', {'c.yaml': lambda env: env['cal'] + 'ambient_c: .nan\n'},
     WITH_CALIBRATION, 'ambient_c'),
    ('calibration counts text', {'c.yaml': edited('cal', 'counts:\n', 'counts:\n    - abc\n')}, WITH_CALIBRATION,
     'counts'),
    ('calibration no bars', {'c.yaml': 'format_version: 1\ndevice: x\n'}, WITH_CALIBRATION, 'bars'),
    ('calibration thermal zero text', {'c.yaml': lambda env: env['cal'] + 'thermal_zero_um: {ref1: abc}\n'},
     WITH_CALIBRATION, 'thermal_zero_um.ref1'),
    ('calibration bomb', {'c.yaml': BOMB}, WITH_CALIBRATION, 'expands to'),
    ('calibration unknown key', {'c.yaml': lambda env: env['cal'] + 'ambient_cc: 20.0\n'},
     WITH_CALIBRATION, 'did you mean ambient_c'),
    ('calibration unknown bar key', {'c.yaml': edited('cal', 'distances_mm:', 'distance_mm:')},
     WITH_CALIBRATION, 'distance_mm'),
    ('calibration unknown terminal key',
     {'c.yaml': lambda env: env['cal'] + 'terminal: {serial: T1, simulated: true, chanels: {}}\n'},
     WITH_CALIBRATION, 'terminal.chanels'),
    # -- device files -----------------------------------------------------------------------------
    ('device bomb', {'d.yaml': BOMB}, 'simulate --device d.yaml', 'expands to'),
    ('device range bools', {'d.yaml': edited('device', 'range_mm: [250.0,', 'range_mm: [true,')},
     'simulate --device d.yaml', 'bars.range_mm'),
    ('device rate nan', {'d.yaml': edited('device', 'sample_rate_hz: 1000.0', 'sample_rate_hz: .nan')},
     'simulate --device d.yaml', 'terminal.sample_rate_hz'),
    ('device rate too high', {'d.yaml': edited('device', 'sample_rate_hz: 1000.0', 'sample_rate_hz: 1.0e+6')},
     'simulate --device d.yaml', '10000'),
    ('device bar bool', {'d.yaml': edited('device', 'bar: 1}', 'bar: true}')}, 'simulate --device d.yaml', 'bar'),
    ('device binary', {'d.yaml': b'\xfe\xff\x00' * 30}, 'workspace --device d.yaml', 'not a text file'),
    ('device joints text', {'d.yaml': edited('device', '[98.4808, -17.3648, 0.0]', '[a, b, c]')},
     'error-budget --device d.yaml', 'joints.upper_design_mm'),
    ('device unknown key', {'d.yaml': edited('device', 'terminal:\n', 'termnal:\n')},
     'simulate --device d.yaml', 'did you mean terminal'),
    ('device unknown section key', {'d.yaml': edited('device', 'fixed_length_mm:', 'fixed_lenght_mm:')},
     'workspace --device d.yaml', 'bars.fixed_lenght_mm'),
    ('device unknown channel key', {'d.yaml': edited('device', 'role: unused}', 'role: unused, bars: 7}')},
     'simulate --device d.yaml', 'terminal.channels[7].bars'),
    ('device unknown pair key', {'d.yaml': edited('device', '{name: dr1,', '{name: dr1, sigma_um: 1,')},
     'error-budget --device d.yaml', 'reference_plate.pairs[0].sigma_um'),
    # -- machine descriptions and test programs ---------------------------------------------------
    ('machine unknown axis key', {'x.yaml': lambda env: MACHINE.replace('direction: [1, 0, 0]', 'directon: [1, 0, 0]', 1)},
     'machine analyze {log} --machine x.yaml', 'axes[0].directon'),
    ('machine unknown mmd key', {'x.yaml': lambda env: MACHINE.replace('upper_offset_mm', 'upper_ofset_mm')},
     'machine analyze {log} --machine x.yaml', 'did you mean upper_offset_mm'),
    ('machine unknown key', {'x.yaml': lambda env: MACHINE + 'chain: {}\n'},
     'machine analyze {log} --machine x.yaml', 'did you mean chains'),
    ('machine travel a bool', {'x.yaml': lambda env: MACHINE.replace('travel_mm: [-300, 300]', 'travel_mm: [-300, true]')},
     'machine analyze {log} --machine x.yaml', 'axes[0].travel_mm'),
    ('program unknown key', {'p.yaml': 'runs: [{axis: X, targets_mm: [1, 2, 3], folow: true}]\n'},
     'machine analyze {log} --machine machine_xyzac.yaml --program p.yaml', 'did you mean follow'),
    ('program follow text', {'p.yaml': 'runs: [{axis: X, targets_mm: [1, 2, 3], follow: "no"}]\n'},
     'machine analyze {log} --machine machine_xyzac.yaml --program p.yaml', 'runs[0].follow'),
    # -- ambient profiles -------------------------------------------------------------------------
    ('ambient unknown key', {'a.yaml': 'initial_cc: 20\n'}, 'simulate --ambient a.yaml', 'did you mean initial_c'),
    ('ambient unknown ramp key', {'a.yaml': 'initial_c: 20\nramps: [{duration_s: 5, end_c: 21, time_constant: 9}]\n'},
     'simulate --ambient a.yaml', 'ramps[0].time_constant'),
    ('ambient bomb', {'a.yaml': BOMB}, 'simulate --ambient a.yaml', 'expands to'),
    ('ambient initial nan', {'a.yaml': 'initial_c: .nan\n'}, 'simulate --ambient a.yaml', 'initial_c'),
    ('ambient ramp inf', {'a.yaml': 'initial_c: 20\nramps: [{duration_s: .inf, end_c: 21, time_constant_s: 9}]\n'},
     'simulate --ambient a.yaml', 'duration_s'),
    ('ambient binary', {'a.yaml': b'\x00\x01\xff' * 20}, 'simulate --ambient a.yaml', 'not a text file'),
    # -- logs and what they carry -----------------------------------------------------------------
    ('log text', {}, 'process {logs}/text.mcap', 'not an MCAP file'),
    ('log empty', {}, 'process {logs}/empty.mcap', 'empty or not an MCAP'),
    ('log missing', {}, 'process nothing.mcap', 'nothing.mcap'),
    ('log model bomb', {}, 'process --json {logs}/model_bomb.mcap', 'expands to'),
    ('log model nan', {}, 'process --json {logs}/model_nan.mcap', 'length_sigma_um'),
    ('log device not mapping', {}, 'process {logs}/device_list.mcap', 'device_description'),
    ('log device unknown key', {}, 'process {logs}/device_typo.mcap', 'did you mean fixed_length_mm'),
    ('log channel names', {}, 'process {logs}/wrong_names.mcap', 'do not match'),
    ('log stamps backwards', {}, 'process {logs}/backwards.mcap', 'go backwards'),
    ('log stamps backwards analyze', {}, 'analyze {logs}/backwards.mcap --out {out}', 'go backwards'),
    ('log stamps backwards iso', {}, 'iso230-2 {logs}/backwards.mcap --axis x --out {out}', 'go backwards'),
    ('log segment beyond', {}, 'process {logs}/backwards.mcap --segment 3', 'segment'),
    ('log stamps repeated', {}, 'process {logs}/repeated.mcap', 'repeat the stamp'),
    ('log stamps repeated iso', {}, 'iso230-2 {logs}/repeated.mcap --axis x --out {out}',
     'repeat the stamp'),
    # -- simulate options -------------------------------------------------------------------------
    ('simulate rate huge', {}, 'simulate --rate 1e9', '--rate'),
    ('simulate rate zero', {}, 'simulate --rate 0', '--rate'),
    ('simulate rate nan', {}, 'simulate --rate nan', '--rate'),
    ('simulate start nan', {}, 'simulate --start nan', '--start'),
    ('simulate calibrate inf', {}, 'simulate --calibrate-at inf', '--calibrate-at'),
    ('simulate duration inf', {}, 'simulate --scenario hold --param duration_s=inf', 'duration_s'),
    ('simulate duration huge', {}, 'simulate --scenario hold --param duration_s=1e12', 'duration_s'),
    ('simulate duration negative', {}, 'simulate --scenario thermal_soak --param duration_s=-5', 'duration_s'),
    ('simulate samples too many', {}, 'simulate --scenario thermal_soak --param duration_s=600000 --rate 10000',
     'samples'),
    ('simulate cycles huge', {}, 'simulate --param n_cycles=100000', 'n_cycles'),
    ('simulate dwell nan', {}, 'simulate --param dwell_s=nan', 'dwell_s'),
    ('simulate seed negative', {}, 'simulate --seed -1', '--seed'),
    ('simulate seed 2^64', {}, 'simulate --seed 18446744073709551616', '18446744073709551615'),
    ('simulate scenario seed negative', {}, 'simulate --param seed=-1', 'seed'),
    ('simulate travel tiny', {},        # a 1.6 km bow past the overrun: all memory, once
     'simulate --param travel_m=1e-7 --param n_targets=3 --param n_cycles=2 --rate 250',
     'travel_m must be at least 0.001 m'),
    ('simulate travel zero', {}, 'simulate --param travel_m=0', 'travel_m must be'),
    ('simulate overrun negative', {}, 'simulate --param overrun_m=-1e-3', 'overrun_m must be > 0'),
    ('simulate overrun beyond travel', {}, 'simulate --param travel_m=1e-3',
     'overrun_m must be at most'),
    ('simulate jitter negative', {}, 'simulate --param target_jitter_m=-1e-3',
     'target_jitter_m must'),
    ('simulate session travel zero', {},
     'simulate --scenario machine_session --param linear_travel_mm=[0,0]',
     'linear_travel_mm must be'),
    ('simulate angle negative', {}, 'simulate --scenario random_motion --param max_angle_rad=-1',
     'max_angle_rad must be >= 0'),
    ('simulate radius negative', {}, 'simulate --scenario random_motion --param radius_m=-0.01',
     'radius_m must be >= 0'),
    ('simulate ambient cold', {}, 'simulate --ambient constant:-300', '[-100, 200]'),
    ('simulate ambient hot', {}, 'simulate --ambient constant:1000', '[-100, 200]'),
    ('simulate one sample', {}, 'simulate --scenario hold --param duration_s=9 --rate 0.01',
     'at least 0.112 Hz'),
    # (blamed on the device file before: the twin's description states these figures)
    ('simulate effect hysteresis', {}, 'simulate --effect hysteresis_m=1e-4',
     'effect hysteresis_m=0.0001:'),
    ('simulate effect sag', {}, 'simulate --effect gravity_sag_m=1e-3',
     'effect gravity_sag_m=0.001'),
    ('simulate effect seating', {}, 'simulate --effect placement_repeatability_m=1e-3',
     'effect placement_repeatability_m=0.001:'),
    ('simulate effect nan', {}, 'simulate --effect hysteresis_m=nan', 'hysteresis_m'),
    ('simulate unknown param', {}, 'simulate --param nonsense=1', 'nonsense'),
    ('simulate param typo', {}, 'simulate --scenario hold --param duraton_s=1', 'did you mean duration_s'),
    ('simulate effect typo', {}, 'simulate --effect hysteresis=1e-6', 'did you mean hysteresis_m'),
    ('simulate param alias bomb', {}, ['simulate', '--scenario', 'hold', '--param',
                                       'pose=[&a [1,1,1,1,1,1,1,1,1], &b [*a,*a,*a,*a,*a,*a,*a,*a,*a], '
                                       '&c [*b,*b,*b,*b,*b,*b,*b,*b,*b], &d [*c,*c,*c,*c,*c,*c,*c,*c,*c], '
                                       '&e [*d,*d,*d,*d,*d,*d,*d,*d,*d], &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]]'],
     'expands to'),
    ('simulate reference', {}, 'simulate --reference sonar', 'sonar'),
    # -- analyze options --------------------------------------------------------------------------
    ('analyze blocks zero', {}, 'analyze {log} --blocks 0 --out {out}', '--blocks'),
    ('analyze min gain nan', {}, 'analyze {log} --min-gain nan --out {out}', '--min-gain'),
    ('analyze min gain one', {}, 'analyze {log} --min-gain 1 --out {out}', '--min-gain'),
    ('analyze max effects negative', {}, 'analyze {log} --max-effects -1 --out {out}', '--max-effects'),
    ('analyze max samples zero', {}, 'analyze {log} --max-samples 0 --out {out}', '--max-samples'),
    ('analyze cyclic period zero', {}, 'analyze {log} --cyclic-period-um 0 --out {out}', '--cyclic-period-um'),
    ('analyze cyclic period text', {}, 'analyze {log} --cyclic-period-um 20,x --out {out}', '--cyclic-period-um'),
    ('analyze unknown effect', {}, 'analyze {log} --effects gremlins --out {out}', 'gremlins'),
    ('analyze seed negative', {}, 'analyze {log} --seed -3 --out {out}', '--seed'),
    ('analyze model nan', {'m.yaml': model('length_sigma_um: .nan')}, 'analyze {log} --model m.yaml --out {out}',
     'length_sigma_um'),
    # -- iso230-2 options -------------------------------------------------------------------------
    ('iso min dwell zero', {}, 'iso230-2 {log} --axis x --min-dwell 0 --out {out}', '--min-dwell'),
    ('iso targets nan', {}, 'iso230-2 {log} --axis x --targets 1,nan --out {out}', '--targets'),
    ('iso axis unknown', {}, 'iso230-2 {log} --axis w --out {out}', 'unknown axis'),
    ('iso after model bomb', {'m.yaml': BOMB}, 'iso230-2 {log} --axis x --after m.yaml --out {out}', 'expands to'),
    ('iso segment zero', {}, 'iso230-2 {log} --axis x --segment 0', '--segment'),
    # -- process options --------------------------------------------------------------------------
    ('process segment text', {}, 'process {log} --segment two', '--segment'),
    # -- design tools -----------------------------------------------------------------------------
    ('error budget samples one', {}, 'error-budget --samples 1 --out {out}', '--samples'),
    ('error budget eps step nan', {}, 'error-budget --eps-step-um nan --out {out}', '--eps-step-um'),
    ('error budget grid huge', {}, 'error-budget --eps-max-um 10 --eps-step-um 0.001 --out {out}', 'grid steps'),
    ('error budget pose short', {}, 'error-budget --pose 1 2 --out {out}', '--pose'),
    ('error budget pose nan', {}, 'error-budget --pose 0 0 nan --out {out}', '--pose'),
    ('workspace step zero', {}, 'workspace --step-mm 0 --out {out}', '--step-mm'),
    ('workspace angle samples huge', {}, 'workspace --angle-samples 1000 --out {out}', '--angle-samples'),
    ('workspace levels nan', {}, 'workspace --levels-deg 0 nan --out {out}', '--levels-deg'),
    # -- replay (checked before ROS is touched) ---------------------------------------------------
    ('replay rate nan', {}, 'replay {log} --rate nan', '--rate'),
    ('replay subscribers negative', {}, 'replay {log} --wait-for-subscribers -1', '--wait-for-subscribers'),
]

DEFAULT_OUT = {'process': ['--out', '{out}/p.mcap', '--csv', '{out}/p.csv'],
               'simulate': ['--out', '{out}/s.mcap', '--quiet']}


def test_the_table_covers_every_command_and_file_kind():
    assert len(CASES) >= 60
    commands = {(c[2] if isinstance(c[2], str) else ' '.join(c[2])).split()[0] for c in CASES}
    assert commands == {'process', 'simulate', 'analyze', 'iso230-2', 'error-budget', 'workspace', 'replay',
                        'machine'}
    names = ' '.join(c[0] for c in CASES)
    for kind in ('model', 'calibration', 'device', 'ambient', 'log', 'machine', 'program'):
        assert kind in names


@pytest.mark.parametrize('case', CASES, ids=[c[0] for c in CASES])
def test_malformed_input_is_refused_in_one_line_leaving_nothing(case, env, tmp_path, monkeypatch, capsys):
    name, files, argv, expected = case
    monkeypatch.chdir(tmp_path)
    for fname, content in files.items():
        path = tmp_path / fname
        path.parent.mkdir(parents=True, exist_ok=True)
        content = content(env) if callable(content) else content
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    out = tmp_path / 'out'
    out.mkdir()
    args = argv.split() if isinstance(argv, str) else list(argv)
    if '--out' not in args:
        args += DEFAULT_OUT.get(args[0], [])
    args = [a.format(log=env['log'], logs=env['logs'], out=out) for a in args]
    started = time.perf_counter()
    try:
        status = main(args)
    except SystemExit as exc:       # argparse refusing an option
        status = exc.code
    elapsed = time.perf_counter() - started
    captured = capsys.readouterr()
    assert status == 2, f'{name}: accepted (status {status}): {args}\n{captured.err}'
    last = captured.err.strip().splitlines()[-1]
    assert 'error:' in last and expected in last, f'{name}: {captured.err}'
    assert sum('error:' in line for line in captured.err.splitlines()) == 1, f'{name}: {captured.err}'
    assert 'Traceback' not in captured.err
    assert not any(out.iterdir()), f'{name}: left {sorted(p.name for p in out.iterdir())}'
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.') and p.suffix in ('.part', '.tmp')]
    assert elapsed < 30 and len(captured.out) < 10_000, f'{name}: {elapsed:.1f} s, {len(captured.out)} bytes out'


@pytest.mark.parametrize('argv,expected', [
    (['process', '{log}', '--model', '{bin}', '--out', '{out}/p.mcap'], 'not a text file'),
    (['simulate', '--scenario', 'hold', '--start', 'nan', '--out', '{out}/s.mcap'], '--start'),
    (['process', '{log}', '--json', '--model', '{bomb}', '--out', '{out}/p.mcap'], 'expands to'),
])
def test_the_installed_command_prints_no_traceback(argv, expected, env, tmp_path):
    (tmp_path / 'bin.yaml').write_bytes(b'\x89PNG\r\n\x1a\n\x00\xff' * 50)
    (tmp_path / 'bomb.yaml').write_text(BOMB)
    out = tmp_path / 'out'
    out.mkdir()
    args = [a.format(log=env['log'], bin=tmp_path / 'bin.yaml', bomb=tmp_path / 'bomb.yaml', out=out)
            for a in argv]
    done = subprocess.run([sys.executable, '-m', 'mmd_ros.cli.main', *args], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert 'Traceback' not in done.stderr and expected in done.stderr
    assert len(done.stdout) < 1000 and not any(out.iterdir())


def test_a_run_description_of_plain_strings_is_read_as_text_and_said(env, tmp_path, capsys):
    """Another program wrote a value of the run description as a plain string (an MCAP
    metadata record is a map of strings): the log was refused whole ("not valid JSON"),
    samples and all. It is read, the value kept as its text, and a warning names it."""
    from mmd_ros.logs.layout import read_run
    log = str(env['logs'] / 'bad_metadata.mcap')
    assert main(['process', log, '--json', '--out', str(tmp_path / 'p.mcap')]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)['metadata_as_text'] == ['scenario']
    assert 'not JSON, kept as their text: scenario' in captured.err
    run = read_run(log)
    assert run.metadata == {'scenario': '{not json'} and run.counts.shape[0] > 0


def strict_json(text: str):
    def refuse(constant):
        raise AssertionError(f'{constant} is not JSON')
    return json.loads(text, parse_constant=refuse)


def test_json_output_is_strict_json(env, tmp_path, capsys):
    """``--json`` never prints NaN or Infinity (a hold has no ISO targets: figures are unknown)."""
    log = str(env['log'])
    assert main(['process', log, '--json', '--out', str(tmp_path / 'p.mcap')]) == 0
    strict_json(capsys.readouterr().out)
    assert main(['simulate', '--scenario', 'hold', '--param', 'duration_s=1', '--json', '--out',
                 str(tmp_path / 's.mcap')]) == 0
    strict_json(capsys.readouterr().out)
    status = main(['iso230-2', log, '--axis', 'z', '--targets', '299.9,300,300.1', '--json'])
    out = capsys.readouterr().out
    if status == 0:
        strict_json(out)
    assert main(['error-budget', '--samples', '20', '--parts', 'fig2', '--eps-max-um', '0.2',
                 '--json', '--no-progress']) == 0
    strict_json(capsys.readouterr().out)


def test_a_bomb_never_reaches_the_output(env, tmp_path):
    """The 10-line bomb once made ``mmd process --json`` write 540 MB: now refused in milliseconds."""
    from mmd_ros.core.errors import ConfigError
    from mmd_ros.core.yamlio import parse_yaml
    started = time.perf_counter()
    with pytest.raises(ConfigError, match='expands to 4.9e\\+08 nodes'):
        parse_yaml(BOMB, 'bomb.yaml')
    assert time.perf_counter() - started < 1.0
    data = parse_yaml('format_version: 1\nbase: &b {mode: auto}\nthermal: *b\n', 'ok.yaml')
    assert data['thermal'] == {'mode': 'auto'}      # an alias of reasonable size is fine
    assert Path(env['log']).exists()
