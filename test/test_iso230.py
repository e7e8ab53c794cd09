"""ISO 230-2 evaluation: a hand-worked known answer, dwell detection and target assignment on a
synthetic axis run with known deviations, and ``mmd iso230-2`` on a simulated linear-axis log."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.iso230 import approaches, detect_dwells, evaluate, evaluate_run, figure_table
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
from mmd_ros.cli.main import main

UM = 1e-6

# Three targets, five approaches per direction (deviations in µm). Worked by hand:
#   target 0 ↑ 2 3 4 3 3 : x̄↑ 3, Σ(x - x̄)² = 2, s↑ = sqrt(2/4) = 0.70711
#            ↓ 1 1 2 0 1 : x̄↓ 1,                  s↓ = 0.70711
#   target 1 ↑ 5 5 5 5 5 : x̄↑ 5,                  s↑ = 0
#            ↓ 4 2 3 3 3 : x̄↓ 3,                  s↓ = 0.70711
#   target 2 ↑ -1 0 1 0 0: x̄↑ 0,                  s↑ = 0.70711
#            ↓ -3 x 5    : x̄↓ -3,                 s↓ = 0
# x̄_i = 2, 4, -1.5; B_i = 2, 2, 3 -> B = 3, B̄ = 7/3
# R_i↑ = 4 s↑ = 2.8284, 0, 2.8284; R_i↓ = 2.8284, 2.8284, 0 -> R↑ = R↓ = 2.8284
# R_i = max(2s↑ + 2s↓ + |B_i|, R_i↑, R_i↓) = 4.8284, 3.4142, 4.4142 -> R = 4.8284
# E↑ = 5 - 0 = 5; E↓ = 3 - (-3) = 6; E = 5 - (-3) = 8; M = 4 - (-1.5) = 5.5
# A↑ = max(4.4142, 5, 1.4142) - min(1.5858, 5, -1.4142) = 6.4142
# A↓ = max(2.4142, 4.4142, -3) - min(-0.4142, 1.5858, -3) = 7.4142
# A  = max(all x̄ + 2s) - min(all x̄ - 2s) = 5 - (-3) = 8
UP = [[2, 3, 4, 3, 3], [5, 5, 5, 5, 5], [-1, 0, 1, 0, 0]]
DOWN = [[1, 1, 2, 0, 1], [4, 2, 3, 3, 3], [-3, -3, -3, -3, -3]]
A = math.sqrt(0.5)
EXPECTED = {'B': 3.0, 'B_mean': 7 / 3, 'R_up': 4 * A, 'R_down': 4 * A, 'R': 4 * A + 2,
            'E_up': 5.0, 'E_down': 6.0, 'E': 8.0, 'M': 5.5, 'A_up': 5 + 2 * A, 'A_down': 6 + 2 * A,
            'A': 8.0}


def test_hand_worked_example():
    r = evaluate([0.0, 0.1, 0.2], np.array(UP) * UM, np.array(DOWN) * UM, axis='x', instrument='hand')
    for key, value in EXPECTED.items():
        assert r.figures[key] / UM == pytest.approx(value, abs=1e-9), key
    assert r.mean / UM == pytest.approx([2, 4, -1.5])
    assert r.reversal / UM == pytest.approx([2, 2, 3])
    assert r.r_bi / UM == pytest.approx([4 * A + 2, 2 * A + 2, 2 * A + 3])
    assert r.n == 5 and r.unit == 'um' and r.position_unit == 'mm'
    table = figure_table([('hand', r.figures_report())], r.unit)
    assert '3.00' in table and '8.00' in table and '5.50' in table


def test_rotary_axes_in_arcseconds_and_small_n():
    arcsec = math.radians(1 / 3600)
    r = evaluate([0.0, 0.5], [[1 * arcsec, 2 * arcsec], [0, 0]], [[0, 0], [-1 * arcsec, -1 * arcsec]], axis='psi')
    assert r.unit == 'arcsec' and r.figures_report()['B'] == pytest.approx(1.5)
    single = evaluate([0.0, 0.5], [[1e-6], [2e-6]], [[0.0], [1e-6]], axis='x')
    assert single.figures['B'] == pytest.approx(1e-6) and math.isnan(single.figures['A'])
    with pytest.raises(AnalysisError, match='targets 500 mm were not approached from both'):
        evaluate([0.0, 0.5], [[1e-6], [np.nan]], [[0.0], [1e-6]])
    # named in the units --targets takes: degrees on a rotary axis
    with pytest.raises(AnalysisError, match='targets -40 ° were not approached from both'):
        evaluate([math.radians(-40), 0.0], [[np.nan], [0.0]], [[0.0], [0.0]], axis='psi')


def synthetic_run(rate=200.0, n_cycles=3, seed=0):
    """An axis moving through 6 targets (0..250 mm, irregular) in ISO cycles with a 2 mm
    overrun, 0.4 s dwells and known per-approach deviations; 20 nm noise."""
    rng = np.random.default_rng(seed)
    targets = np.array([0.0, 0.0493, 0.1012, 0.1497, 0.2031, 0.25])
    knots, values, truth = [0.0], [0.1], []

    def go(x, dwell=0.0):
        knots.append(knots[-1] + max(0.3, abs(x - values[-1]) / 0.1))
        values.append(x)
        if dwell:
            knots.append(knots[-1] + dwell)
            values.append(x)

    knots.append(0.5)
    values.append(0.1)                      # lead dwell at the start pose (not a target)
    go(-0.002)
    for _ in range(n_cycles):
        for direction, order in ((1, range(6)), (-1, range(5, -1, -1))):
            for i in order:
                dev = (2e-6 * direction + 1e-6 * math.sin(i) + rng.normal(0, 0.3e-6))
                truth.append((i, direction, dev))
                go(targets[i] + dev, 0.4)
            go(targets[-1] + 0.002 if direction > 0 else -0.002)
    go(0.1, 0.5)                            # return to the start pose
    t = np.arange(0.0, knots[-1], 1.0 / rate)
    x = np.interp(t, knots, values) + rng.normal(0, 20e-9, t.size)
    return t, x, targets, truth


def test_dwells_and_approaches_recover_the_known_deviations():
    t, x, targets, truth = synthetic_run()
    dwells = detect_dwells(t, x)
    tg, found = approaches(dwells, targets)
    assert len(found) == len(truth)         # the lead dwell and the return do not count
    for a, (i, direction, dev) in zip(found, truth):
        assert (a.target, a.direction) == (i, direction)
        assert a.dwell.value - targets[i] == pytest.approx(dev, abs=0.05e-6)
    # targets clustered from the dwells when not given: the round commanded positions
    tg2, found2 = approaches(dwells, None)
    assert tg2 == pytest.approx(targets, abs=1e-9) and len(found2) == len(found)
    res = evaluate_run(t, 'x', {'laser': x}, x, targets)['laser']
    assert res.n == 3
    assert res.figures['B'] / UM == pytest.approx(4.0, abs=1.2)   # +-2 µm per direction


def test_dwells_need_increasing_times():
    """Every other stamp repeated (median step 0) used to divide by zero."""
    t, x, _, _ = synthetic_run()
    t[1::2] = t[::2][:t[1::2].size]
    with pytest.raises(AnalysisError, match='median step is 0 s'):
        detect_dwells(t, x)
    with pytest.raises(AnalysisError, match='must increase'):
        detect_dwells(t[::-1], x)


def test_mmd_iso230_on_a_simulated_linear_axis(tmp_path, capsys):
    log = tmp_path / 'x.mcap'
    spec = SimulationSpec(scenario='iso_linear', scenario_params=('n_cycles=2', 'dwell_s=0.3', 'lead_s=0.3'),
                          effects='ideal', ambient='constant:20', reference='laser_x', sample_rate_hz=100.0)
    simulate_to_log(spec, log, progress=False)
    assert main(['iso230-2', str(log), '--json']) == 0
    data = json.loads(capsys.readouterr().out)
    ref = data['results']['reference']
    assert data['axis'] == 'x' and data['unit'] == 'um' and ref['n'] == 2
    assert len(ref['targets']) == 11
    # the machine's own errors (10 µm/m over 200 mm, 2 µm reversal) seen by the laser
    assert 1.0 < ref['figures']['B'] < 3.5 and 1.0 < ref['figures']['E'] < 6.0
    # the ideal MMD agrees with the laser: its error stays at the quantisation level
    err = data['results']['MMD - reference']['figures']
    assert abs(err['B']) < 0.1 and err['A'] < 0.5
    out = tmp_path / 'iso'
    targets = ','.join(f'{v:g}' for v in np.linspace(-100, 100, 11))
    assert main(['iso230-2', str(log), '--out', str(out), f'--targets={targets}']) == 0
    text = capsys.readouterr().out
    assert 'R+' in text and 'reference' in text
    assert (out / 'iso230.md').is_file() and (out / 'iso230_reference.png').is_file()
    assert main(['iso230-2', str(log), '--axis', 'q']) == 2
    capsys.readouterr()
    # progress on stderr, as the other subcommands; --quiet silences it and keeps the report
    assert main(['iso230-2', str(log)]) == 0
    assert 'processing' in capsys.readouterr().err
    assert main(['iso230-2', str(log), '--quiet']) == 0
    captured = capsys.readouterr()
    assert captured.err == '' and 'R+' in captured.out


def test_s_is_taken_about_the_directional_mean_in_the_code_and_the_doc():
    # ISO 230-2: s_i↑ = sqrt(sum_j (x_ij↑ - x̄_i↑)² / (n - 1)), about the mean of its own
    # direction. Here x̄_i↑ = 3, x̄_i↓ = -3, x̄_i = 0: about x̄_i it would be sqrt(46/4).
    up, down = [[2.0, 3.0, 4.0, 3.0, 3.0]], [[-3.0, -3.0, -2.0, -4.0, -3.0]]
    r = evaluate([0.0], np.array(up) * UM, np.array(down) * UM)
    assert r.s_up[0] / UM == pytest.approx(math.sqrt(2 / 4))
    assert r.s_down[0] / UM == pytest.approx(math.sqrt(2 / 4))
    doc = (Path(__file__).resolve().parents[1] / 'msg_docs' / 'analysis.md').read_text(encoding='utf-8')
    row = next(line for line in doc.splitlines() if line.startswith('| s_i↑, s_i↓ |'))
    assert '(x_ij↑ − x̄_i↑)²' in row and '(x_ij − x̄_i)²' not in row
