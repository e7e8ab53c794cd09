"""``mmd machine analyze`` on a full five-axis session: the ISO 230-2 standard test cycle (11
targets over 200 mm / 120 mm, 5 bidirectional cycles; C ±60° and A ±15° with 9 targets, the
linear axes following) of X, Y, Z, C and A of the XYZAC machine at 1 kHz, realistic MMD.

Times the stages (reading the log and computing every sample's pose with its covariance,
finding the runs, the identification, the Monte Carlo uncertainty, the files and figures) and
prints a JSON line. Target: the analysis (without figures) under 30 s. ``--quick``: 2 cycles.
Never fails on timing.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from mmd_ros.core.machine import load_machine
from mmd_ros.machine import IdentifyOptions, SessionOptions, analyze_session, write_outputs
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--quick', action='store_true', help='2 cycles instead of 5')
    parser.add_argument('--draws', type=int, default=200, help='Monte Carlo draws (default 200)')
    args = parser.parse_args()
    cycles = 2 if args.quick else 5
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        log = folder / 'session.mcap'
        t0 = time.perf_counter()
        _, _, summary = simulate_to_log(SimulationSpec(
            scenario='machine_session', scenario_params=(f'n_cycles={cycles}',), effects='realistic',
            seed=1), log, progress=False)
        t_sim = time.perf_counter() - t0
        machine = load_machine('machine_xyzac.yaml')
        t0, c0 = time.perf_counter(), time.process_time()
        result = analyze_session([log], machine, SessionOptions(identify=IdentifyOptions(draws=args.draws)))
        t_analysis, cpu_analysis = time.perf_counter() - t0, time.process_time() - c0
        t0 = time.perf_counter()
        write_outputs(result, folder / 'out', figures=False)
        t_files = time.perf_counter() - t0
        t0 = time.perf_counter()
        write_outputs(result, folder / 'out_figures', figures=True)
        t_figures = time.perf_counter() - t0
    s = result.seconds
    approaches = sum(len(a.targets) * 2 * a.n_cycles for a in result.axes.values())
    print(f'session: {summary["samples"]} samples ({summary["duration_s"]:.0f} s at 1 kHz), '
          f'{len(result.axes)} runs, {approaches} approaches; simulated in {t_sim:.1f} s')
    print(f'analysis {t_analysis:.1f} s (CPU {cpu_analysis:.1f} s; load average '
          f'{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores): poses (read, pipeline with covariance, runs) '
          f'{s["poses"]:.1f} s, identification {s["evaluate"]:.2f} s, Monte Carlo '
          f'({args.draws} draws) {s["monte_carlo"]:.1f} s')
    print(f'files {t_files:.1f} s, files with figures {t_figures:.1f} s')
    print(json.dumps({'bench': 'machine', 'samples': summary['samples'], 'cycles': cycles,
                      'draws': args.draws, 'analysis_s': round(t_analysis, 2),
                      'analysis_cpu_s': round(cpu_analysis, 2), 'load': round(os.getloadavg()[0], 1),
                      'poses_s': round(s['poses'], 2), 'identify_s': round(s['evaluate'], 3),
                      'monte_carlo_s': round(s['monte_carlo'], 2), 'files_s': round(t_files, 2),
                      'figures_s': round(t_figures, 2), 'target_s': 30.0}))


if __name__ == '__main__':
    main()
