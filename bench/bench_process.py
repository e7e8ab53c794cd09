"""``mmd process`` end to end on a 10-minute 1 kHz log: MCAP read, CDF, thermal, FK, MCAP write.

Prints samples/s (median of repeats) and a final JSON line. Target (issue 2): >= 100,000
samples/s on this 2-core machine. ``--quick`` uses a 1-minute log. Never fails on timing.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from mmd_ros.logs.processing import process_run, write_processed
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--quick', action='store_true', help='a 1-minute log instead of 10 minutes')
    parser.add_argument('--repeats', type=int, default=3)
    args = parser.parse_args()
    # The x-axis ISO run with 4.6 s dwells lasts 596 s; the quick one uses one cycle.
    params = ('dwell_s=4.6',) if not args.quick else ('n_cycles=1', 'dwell_s=1.4')
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / 'run.mcap'
        spec = SimulationSpec(scenario_params=params, reference='pose6')
        _, _, info = simulate_to_log(spec, log, progress=False)
        n = info['samples']
        stages: dict[str, list[float]] = {'read': [], 'compute': [], 'write': [], 'total': []}
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            run = read_run(log)
            t1 = time.perf_counter()
            model = Model()
            result = process_run(run, model)
            t2 = time.perf_counter()
            write_processed(Path(tmp) / 'out.mcap', run, model, result, run.calibration.to_yaml())
            t3 = time.perf_counter()
            for key, value in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t3 - t0)):
                stages[key].append(value)
        size_mb = log.stat().st_size / 1e6
    med = {k: statistics.median(v) for k, v in stages.items()}
    result = {
        'benchmark': 'process', 'samples': n, 'log_mb': size_mb, 'repeats': args.repeats,
        'samples_per_s_median': n / med['total'],
        'samples_per_s_runs': [n / t for t in stages['total']],
        'stage_us_per_sample': {k: 1e6 * v / n for k, v in med.items()},
    }
    print(f'mmd process on a {n / 1000:.0f} s log ({n} samples, {size_mb:.1f} MB): median '
          f'{result["samples_per_s_median"]:,.0f} samples/s over {args.repeats} runs   [target >= 100,000]')
    print('  per sample: ' + ', '.join(f'{k} {v:.2f} us' for k, v in result['stage_us_per_sample'].items()))
    print(json.dumps(result))


if __name__ == '__main__':
    main()
