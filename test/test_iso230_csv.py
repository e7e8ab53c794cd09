"""``mmd iso230-2`` on tables of readings (laser interferometer and rotary calibrator exports).

The known answer is a public ISO 230-2 data set with every run's deviation:

    ecmc motion system test report, "ISO 230-2 motion test", axis 1 of slit 11358 (BIFROST,
    European Spallation Source), generated 2021-11-03 by ecmcISO230_2.py; published in
    https://github.com/anderssandstrom/ecmccomgui, file tools/iso230-2-obsolete/report.md
    (commit 8488a9991bda72f4f2f7a1b9433db04b6d91d4fc). 5 targets (15.0 … 55.8 mm), 5 cycles
    per direction, reference encoder readings; its tables "Positioning deviation forward /
    backward direction" give x(i, j) = reference - target in mm to 5 decimals.

The test works every figure out again step by step from those deviations with plain
arithmetic (no numpy, nothing of ``mmd_ros.analysis``), checks ``mmd iso230-2`` against that,
and both against the figures the report publishes. The report computed from unrounded
readings and prints 5 decimals (0.01 µm): agreement is to that rounding. It departs from
ISO 230-2 in two figures, which are therefore compared with the standard's definition only:
its R is max(R↑) (0.0075 mm) where the standard takes max R_i (0.00835 mm in its own per-target
table), and its E is max - (the larger of the two directional minima) (0.01485 mm) where the
standard takes max(x̄↑, x̄↓) - min(x̄↑, x̄↓).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mmd_ros.cli.main import main

TARGETS_MM = [15.0, 25.2, 35.4, 45.6, 55.8]
# x(i, j) [mm] as the report prints them: "forward" (↑) and "backward" (↓) direction tables.
FORWARD_MM = [[0.00335, 0.00233, 0.00172, 0.00213, 0.00172],
              [-0.00026, 0.00015, 0.00096, 0.00056, 0.00056],
              [0.00102, -0.0004, 0.00225, 0.00306, 0.00449],
              [-0.00849, -0.0091, -0.00788, -0.0091, -0.01053],
              [0.00583, 0.00624, 0.00685, 0.00562, 0.00562]]
BACKWARD_MM = [[0.00518, 0.00518, 0.00416, 0.00335, 0.00314],
               [-0.00372, -0.00393, -0.00433, -0.00413, -0.00474],
               [-0.00183, -0.00163, -0.0002, -0.00061, 0.0],
               [-0.00768, -0.00809, -0.00707, -0.00809, -0.00849],
               [0.00705, 0.00725, 0.00705, 0.00705, 0.00644]]
# What the report publishes [mm] (per target: x̄↑, x̄↓, x̄, B_i, s↑, s↓, R↑, R↓, R_i).
PUBLISHED_TARGETS = {
    'mean_up': [0.00225, 0.00039, 0.00208, -0.00902, 0.00603],
    'mean_down': [0.0042, -0.00417, -0.00085, -0.00788, 0.00697],
    'mean': [0.00323, -0.00189, 0.00062, -0.00845, 0.0065],
    'reversal': [-0.00196, 0.00456, 0.00293, -0.00114, -0.00094],
    's_up': [0.00067, 0.00046, 0.00188, 0.00098, 0.00052],
    's_down': [0.00097, 0.00039, 0.00083, 0.00054, 0.00031],
    'R_up': [0.00268, 0.00186, 0.0075, 0.00393, 0.00208],
    'R_down': [0.00388, 0.00157, 0.00333, 0.00216, 0.00124],
    'R': [0.00524, 0.00628, 0.00835, 0.00419, 0.00259],
}
PUBLISHED_FIGURES = {'B': 0.00456, 'B_mean': 0.00069, 'R_up': 0.0075, 'R_down': 0.00388,
                     'E_up': 0.01505, 'E_down': 0.01485, 'M': 0.01495, 'A_up': 0.01806,
                     'A_down': 0.01655, 'A': 0.01858}
# The report's own (non-ISO) R and E, for the record; see the module docstring.
PUBLISHED_NOT_ISO = {'R': 0.0075, 'E': 0.01485}

# Rounding: inputs and outputs to 0.005 µm each; s, R and A carry the inputs' rounding
# through the standard deviation (up to ~0.006 µm per s) and its factors 2 and 4.
TOLERANCE_UM = {'mean_up': 0.011, 'mean_down': 0.011, 'mean': 0.011, 'reversal': 0.011,
                's_up': 0.011, 's_down': 0.011, 'R_up': 0.035, 'R_down': 0.035, 'R': 0.035,
                'B': 0.011, 'B_mean': 0.011, 'E_up': 0.011, 'E_down': 0.011, 'E': 0.011,
                'M': 0.011, 'A_up': 0.04, 'A_down': 0.04, 'A': 0.04}


def hand_iso230(up: list[list[float]], down: list[list[float]]) -> tuple[list[dict], dict]:
    """ISO 230-2 written out: per target and for the axis, from deviations (any unit)."""
    def mean(values: list[float]) -> float:
        return sum(values) / len(values)

    def s(values: list[float]) -> float:        # about the mean of its own direction
        centre = mean(values)
        return math.sqrt(sum((v - centre) ** 2 for v in values) / (len(values) - 1))

    per = []
    for u, d in zip(up, down):
        x_up, x_down, s_up, s_down = mean(u), mean(d), s(u), s(d)
        b = x_up - x_down
        per.append({'mean_up': x_up, 'mean_down': x_down, 'mean': (x_up + x_down) / 2,
                    'reversal': b, 's_up': s_up, 's_down': s_down, 'R_up': 4 * s_up,
                    'R_down': 4 * s_down,
                    'R': max(2 * s_up + 2 * s_down + abs(b), 4 * s_up, 4 * s_down)})
    col = {k: [p[k] for p in per] for k in per[0]}
    upper_up = [p['mean_up'] + 2 * p['s_up'] for p in per]
    lower_up = [p['mean_up'] - 2 * p['s_up'] for p in per]
    upper_down = [p['mean_down'] + 2 * p['s_down'] for p in per]
    lower_down = [p['mean_down'] - 2 * p['s_down'] for p in per]
    figures = {
        'B': max(abs(b) for b in col['reversal']),
        'B_mean': mean(col['reversal']),
        'R_up': max(col['R_up']), 'R_down': max(col['R_down']), 'R': max(col['R']),
        'E_up': max(col['mean_up']) - min(col['mean_up']),
        'E_down': max(col['mean_down']) - min(col['mean_down']),
        'E': max(col['mean_up'] + col['mean_down']) - min(col['mean_up'] + col['mean_down']),
        'M': max(col['mean']) - min(col['mean']),
        'A_up': max(upper_up) - min(lower_up),
        'A_down': max(upper_down) - min(lower_down),
        'A': max(upper_up + upper_down) - min(lower_up + lower_down),
    }
    return per, figures


def write_wide(path, up_mm, down_mm, *, delimiter=',') -> None:
    """The report's layout: one row per target, one column per run and direction, in mm."""
    n = len(up_mm[0])
    head = ['target [mm]'] + [f'+{j} [mm]' for j in range(1, n + 1)] + [f'-{j} [mm]' for j in range(1, n + 1)]
    lines = ['# ISO 230-2 run, reference encoder (ecmc report, slit 11358 axis 1)', delimiter.join(head)]
    for t, u, d in zip(TARGETS_MM, up_mm, down_mm):
        lines.append(delimiter.join(f'{v:g}' for v in [t, *u, *d]))
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')


def run_json(capsys, *args) -> dict:
    assert main(['iso230-2', *map(str, args), '--json']) == 0
    return json.loads(capsys.readouterr().out)


def test_published_data_set_known_answer(tmp_path, capsys):
    to_um = [[v * 1000 for v in row] for row in FORWARD_MM], [[v * 1000 for v in row] for row in BACKWARD_MM]
    per, figures = hand_iso230(*to_um)
    # the hand computation against the report's own numbers
    for key, published in PUBLISHED_TARGETS.items():
        for i, value in enumerate(published):
            assert per[i][key] == pytest.approx(value * 1000, abs=TOLERANCE_UM[key]), (key, i)
    for key, published in PUBLISHED_FIGURES.items():
        assert figures[key] == pytest.approx(published * 1000, abs=TOLERANCE_UM[key]), key
    # the report's R and E are not the standard's: R_i of its own table peak at 8.35 µm, and
    # the directional means span 15.99 µm
    assert figures['R'] == pytest.approx(max(PUBLISHED_TARGETS['R']) * 1000, abs=0.035)
    assert figures['R'] > PUBLISHED_NOT_ISO['R'] * 1000 + 0.5
    assert figures['E'] == pytest.approx(15.99, abs=0.011) and figures['E'] > figures['E_up']

    table = tmp_path / 'slit_axis1.csv'
    write_wide(table, FORWARD_MM, BACKWARD_MM)
    out = run_json(capsys, table)
    assert out['source'] == 'csv (wide layout)' and out['axis'] == 'x' and out['unit'] == 'um'
    result = out['results']['slit_axis1']
    assert result['n'] == 5 and [t['position'] for t in result['targets']] == pytest.approx(TARGETS_MM)
    for key in PUBLISHED_TARGETS:
        got = [t[key] for t in result['targets']]
        assert got == pytest.approx([p[key] for p in per], abs=1e-9), key
    for key, value in figures.items():
        assert result['figures'][key] == pytest.approx(value, abs=1e-9), key
    assert result['deviations_up'][3] == pytest.approx([v * 1000 for v in FORWARD_MM[3]])


def test_long_layout_with_two_instruments_gives_the_tables_3_4_rows(tmp_path, capsys):
    # one row per approach, deviations in µm without units; a second "mmd" instrument reads
    # 1 µm more on every up approach (a reversal of +1 µm against the laser)
    lines = ['instrument;target;run;direction;deviation']
    for name, extra in (('laser', 0.0), ('mmd', 1.0)):
        for t, u, d in zip(TARGETS_MM, FORWARD_MM, BACKWARD_MM):
            for j, v in enumerate(u, 1):
                lines.append(f'{name};{t};{j};up;{v * 1000 + extra:.2f}'.replace('.', ','))
            for j, v in enumerate(d, 1):
                lines.append(f'{name};{t};{j};down;{v * 1000:.2f}'.replace('.', ','))
    table = tmp_path / 'two.txt'                # the extension does not matter
    table.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    out = run_json(capsys, table)
    laser = out['results']['reference']            # 'laser' is the reference of the table
    _, figures = hand_iso230([[v * 1000 for v in row] for row in FORWARD_MM],
                             [[v * 1000 for v in row] for row in BACKWARD_MM])
    for key, value in figures.items():
        assert laser['figures'][key] == pytest.approx(value, abs=1e-9), key
    rows = {r['row']: r for r in out['table']}
    assert rows['mmd − reference figures']['B_mean'] == pytest.approx(1.0, abs=1e-9)
    assert rows['mmd − reference figures']['R_up'] == pytest.approx(0.0, abs=1e-9)
    capsys.readouterr()
    assert main(['iso230-2', str(table), '--out', str(tmp_path / 'rep')]) == 0
    text = capsys.readouterr().out
    assert 'R+' in text and 'mmd − reference figures' in text
    assert (tmp_path / 'rep' / 'iso230_mmd.png').stat().st_size > 1000
    assert json.loads((tmp_path / 'rep' / 'iso230.json').read_text())['axis'] == 'x'


def test_rotary_time_series_finds_the_dwells(tmp_path, capsys):
    # a rotary calibrator's capture at 50 Hz: 4 targets 0..30°, 2 cycles, +3″ on the way up
    # and -3″ down (B = 6″), dwelling 1 s at each target
    rate, arcsec = 50.0, 1 / 3600
    targets = [0.0, 10.0, 20.0, 30.0]
    path = []
    for _ in range(2):
        for sweep, dev in ((targets, 3 * arcsec), (targets[::-1], -3 * arcsec)):
            for t in sweep:
                path += [t - 5 * dev / arcsec * 0.2] * 10 + [t + dev] * int(rate)   # approach, dwell
    angle = np.repeat(np.asarray(path), 1)
    rows = ['time [s],calibrator [deg]'] + [f'{k / rate:.3f},{v:.7f}' for k, v in enumerate(angle)]
    table = tmp_path / 'c_axis.csv'
    table.write_text('\n'.join(rows) + '\n', encoding='utf-8')
    out = run_json(capsys, table, '--axis', 'C', '--targets', '0,10,20,30')
    r = out['results']['calibrator']
    assert out['unit'] == 'arcsec' and out['axis'] == 'psi' and r['n'] == 2
    assert r['figures']['B'] == pytest.approx(6.0, abs=0.01)
    assert r['figures']['R'] == pytest.approx(6.0, abs=0.01)


@pytest.mark.parametrize('text,args,problem', [
    ('target,direction,value\n0,+,1\n', [], 'needs a deviation'),
    ('target,run,direction,deviation\n0,1,+,1\n0,1,-,x2\n10,1,+,1\n10,1,-,1\n', [],
     "line 3, column 'deviation': 'x2' is not a number"),
    ('target,run,direction,deviation\n0,1,+,1\n0,1,-,2\n10,1,+,1\n', [],
     'target 10 mm has no runs in the down (-) direction'),
    ('target,run,direction,deviation\n0,1,+,1\n0,1,-,2\n', [], 'at least two targets'),
    ('target,run,direction,deviation\n0,1,+,1\n0,1,+,3\n0,1,-,2\n5,1,+,1\n5,1,-,1\n', [],
     'line 3 repeats run 1 up at target 0 mm'),
    ('target,run,direction,deviation\n0,1,sideways,1\n', [], "direction 'sideways'"),
    ('target,run,direction,deviation\n0,1,+\n', [], 'line 2 has 3 cells, the header 4'),
    ('target,run,direction,deviation\n0,1.5,+,1\n', [], 'must be a whole number'),
    ('target,run,direction,deviation\n0,1,+,nan\n', [], 'not a finite number'),
    ('target [parsec],+1,-1\n0,1,2\n', [], "unknown unit 'parsec'"),
    ('target [deg],+1,-1\n0,1,2\n10,1,2\n', [], 'pass --axis'),
    ('target [mm],+1,-1\n0,1,2\n10,1,2\n', ['--axis', 'psi'], 'axis psi is rotary'),
    ('position_a,position_b\n1,2\n', [], 'unrecognised columns'),
    ('just one column\n1\n', [], 'one column only'),
    ('# nothing but a comment\n', [], 'holds no table'),
    ('target,+1,+2\n0,1,2\n10,1,2\n', [], 'both directions'),
    ('target,+1,-1\n0,1,2\n10,1,2\n', ['--model', 'm.yaml'], '--model apply to an MCAP log'),
    ('target,+1,-1\n0,1,2\n10,1,2\n', ['--targets', '0,10'], 'time series only'),
    ('time,x\n0,1\n1,2\n0.5,3\n' + ''.join(f'{k},1\n' for k in range(2, 12)), [],
     'line 4: time does not increase'),
])
def test_malformed_tables_get_a_one_line_error(tmp_path, capsys, text, args, problem):
    table = tmp_path / 'bad.csv'
    table.write_text(text, encoding='utf-8')
    assert main(['iso230-2', str(table), *args]) == 2
    err = capsys.readouterr().err
    assert problem in err and err.count('\n') == 1 and 'Traceback' not in err, err
    assert str(table) in err or problem.startswith('--')


def test_content_decides_not_the_name(tmp_path, capsys):
    binary = tmp_path / 'readings.csv'
    binary.write_bytes(b'\x00\x01\x02 not text')
    assert main(['iso230-2', str(binary)]) == 2
    assert 'neither an MCAP log' in capsys.readouterr().err
    empty = tmp_path / 'empty.mcap'
    empty.write_bytes(b'')
    assert main(['iso230-2', str(empty)]) == 2
    assert 'is empty' in capsys.readouterr().err
    table = tmp_path / 'run.mcap'                  # a table, whatever its name says
    write_wide(table, FORWARD_MM, BACKWARD_MM, delimiter='\t')
    assert run_json(capsys, table)['source'] == 'csv (wide layout)'
