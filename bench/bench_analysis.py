"""``mmd analyze`` on the demo's realistic ISO x-axis run (5 cycles, 1 kHz, laser along x), on
the 10-minute ISO x-axis run of ``bench_process.py`` (pose reference) and on a 10-minute random
6-DOF run with a full pose reference: time of each stage (wall and CPU: the machine is shared),
and ``mmd iso230-2``'s evaluation of the ISO runs.

Prints the figures and a final JSON line, with the process' peak resident memory after each
case (a peak so far: the cases run in one process). ``--quick`` uses shorter runs. Never fails
on timing. Target (issue 12): ``mmd analyze`` on the 10-minute log under 20 s.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from pathlib import Path

from mmd_ros.analysis import analyze, write_report
from mmd_ros.analysis.iso230_report import iso230_of_run
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
from mmd_ros.logs.layout import read_run


def one(name: str, spec: SimulationSpec, folder: Path, iso: bool) -> dict:
    log = folder / f'{name}.mcap'
    simulate_to_log(spec, log, progress=False)
    t0 = time.perf_counter()
    run = read_run(log)
    t1, c1 = time.perf_counter(), time.process_time()
    result = analyze(run)
    t2, c2 = time.perf_counter(), time.process_time()
    write_report(result, folder / name)
    t3 = time.perf_counter()
    n = run.counts.shape[0]
    out = {'samples': n, 'read_s': t1 - t0, 'analyze_s': t2 - t1, 'analyze_cpu_s': c2 - c1,
           'report_s': t3 - t2, 'found': [f.effect for f in result.found]}
    text = (f'{name}: {n} samples; read {t1 - t0:.2f} s, analyze {t2 - t1:.2f} s (CPU {c2 - c1:.2f} s, '
            f'{n / (t2 - t1):,.0f} samples/s), report {t3 - t2:.2f} s')
    if iso:
        t4, c4 = time.perf_counter(), time.process_time()
        iso230_of_run(run)
        out['iso230_s'], out['iso230_cpu_s'] = time.perf_counter() - t4, time.process_time() - c4
        text += f'; iso230-2 {out["iso230_s"]:.2f} s (CPU {out["iso230_cpu_s"]:.2f} s)'
    # (ru_maxrss is in kB on Linux)
    out['peak_rss_mb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(text + f'; found {out["found"]}; peak memory so far {out["peak_rss_mb"]:,.0f} MB')
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--quick', action='store_true')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        x_params = ('n_cycles=2',) if args.quick else ()
        rm = ('duration_s=60',) if args.quick else ('duration_s=600',)
        long_x = ('n_cycles=1', 'dwell_s=1.4') if args.quick else ('dwell_s=4.6',)
        out = {
            'x_axis_laser': one('x_axis_laser', SimulationSpec(scenario_params=x_params), folder, True),
            'x_axis_10min_pose6': one('x_axis_10min_pose6', SimulationSpec(
                scenario_params=long_x, reference='pose6'), folder, True),
            'random_pose6': one('random_pose6', SimulationSpec(
                scenario='random_motion', scenario_params=rm, reference='pose6'), folder, False),
        }
    print(f'load average {os.getloadavg()[0]:.2f} (a shared machine: CPU times are steadier)')
    print(json.dumps({'bench': 'analysis', 'load_average': list(os.getloadavg()), **out}))


if __name__ == '__main__':
    main()
