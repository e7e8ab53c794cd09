"""``mmd analyze`` on the demo's realistic ISO x-axis run (5 cycles, 1 kHz, laser along x) and
on a 10-minute random 6-DOF run with a full pose reference: time of each stage.

Prints the figures and a final JSON line. ``--quick`` uses shorter runs. Never fails on timing.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from mmd_ros.analysis import analyze, write_report
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
from mmd_ros.logs.layout import read_run


def one(name: str, spec: SimulationSpec, folder: Path) -> dict:
    log = folder / f'{name}.mcap'
    simulate_to_log(spec, log, progress=False)
    t0 = time.perf_counter()
    run = read_run(log)
    t1 = time.perf_counter()
    result = analyze(run)
    t2 = time.perf_counter()
    write_report(result, folder / name)
    t3 = time.perf_counter()
    n = run.counts.shape[0]
    print(f'{name}: {n} samples; read {t1 - t0:.2f} s, analyze {t2 - t1:.2f} s '
          f'({n / (t2 - t1):,.0f} samples/s), report {t3 - t2:.2f} s; found '
          f'{[f.effect for f in result.found]}')
    return {'samples': n, 'analyze_s': t2 - t1, 'report_s': t3 - t2,
            'found': [f.effect for f in result.found]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--quick', action='store_true')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        x_params = ('n_cycles=2',) if args.quick else ()
        rm = ('duration_s=60',) if args.quick else ('duration_s=600',)
        out = {
            'x_axis_laser': one('x_axis_laser', SimulationSpec(scenario_params=x_params), folder),
            'random_pose6': one('random_pose6', SimulationSpec(
                scenario='random_motion', scenario_params=rm, reference='pose6'), folder),
        }
    print(json.dumps({'bench': 'analysis', **out}))


if __name__ == '__main__':
    main()
