"""``mmd process`` end to end on a 10-minute 1 kHz log: MCAP read, CDF, thermal, FK, MCAP write.

Runs the real command (``mmd process LOG --json``) in child processes: the compiled path
(``--repeats`` times) and the numpy reference (``MMD_PURE_PYTHON=1``, once), in the same run, and
prints samples/s (the command's own timing, after its imports), the ratio of the two, user CPU
and peak RSS. Then the stages alone in this process (CPU time per sample: read block by block,
compute, write), which overlap in the command. ``--long LOG`` adds a long log (for example a
2-hour one made with ``mmd simulate``; keep such files out of the repository) for peak RSS.

The main figure is a device's own log: raw counts only (the simulated run's reference pose taken
out, as a real MMD records it). The same run with its 6-DOF reference pose in the log is
measured beside it (reading the reference doubles the data read), without and with the
covariance's coverage of that reference (the command's default when a log has one).

``--baseline DIR`` also runs another copy of the package (a directory holding ``mmd_ros``, e.g.
``git archive COMMIT mmd_ros | tar -x -C DIR``, with this tree's compiled ``_fast*.so`` copied
into ``DIR/mmd_ros/core``), its runs interleaved with this tree's on the device log: on a loaded
machine the ratio of the two medians says what a change bought when the rates themselves swing.

Target (issue 12): >= 500,000 samples/s. The machine is shared: compare the ratios and CPU
times more than the rates. ``--quick`` uses a 1-minute log. Never fails on timing.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from mmd_ros.core.model import Model
from mmd_ros.logs.layout import open_run, read_run, write_run
from mmd_ros.logs.processing import ProcessedLogWriter, process_run
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log


def peak_rss_mb(pid: int, stop: threading.Event, out: list[float]) -> None:
    """The child's peak resident set (VmHWM of its own image, polled until it ends). Not the
    rusage's ru_maxrss: that counts the parent's pages the child had between fork and exec."""
    while not stop.is_set():
        try:
            for line in Path(f'/proc/{pid}/status').read_text().splitlines():
                if line.startswith('VmHWM:'):
                    out.append(int(line.split()[1]) / 1024)
        except OSError:
            return
        stop.wait(0.05)


def command(log: Path, out: Path, pure: bool = False, coverage: bool = False,
            baseline: Path | None = None) -> dict:
    """``mmd process`` in a child: its JSON summary, wall time, user CPU and peak RSS.
    coverage: also the covariance's coverage of the reference (the command's default when the
    log has a reference pose; a real device's log has none)"""
    env = dict(os.environ)
    if pure:
        env['MMD_PURE_PYTHON'] = '1'
    if baseline is not None:
        env['PYTHONPATH'] = os.pathsep.join([str(baseline), env.get('PYTHONPATH', '')]).rstrip(os.pathsep)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, '-m', 'mmd_ros.cli.main', 'process', str(log),
                             '--out', str(out), '--json', '--quiet']
                            + ([] if coverage else ['--no-coverage']),
                            stdout=subprocess.PIPE, env=env)
    stop, rss = threading.Event(), [0.0]
    watch = threading.Thread(target=peak_rss_mb, args=(proc.pid, stop, rss))
    watch.start()
    text = proc.stdout.read()
    stop.set()
    watch.join()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f'mmd process failed on {log}')
    summary = json.loads(text)
    return {'samples': summary['samples'], 'seconds': summary['seconds'],
            'samples_per_s': summary['samples'] / summary['seconds'], 'wall_s': wall,
            'user_cpu_s': usage.ru_utime, 'peak_rss_mb': max(rss)}


def stages(log: Path, out: Path) -> dict:
    """CPU time per sample of reading, computing and writing, each alone [us]."""
    c0 = time.process_time()
    with open_run(log) as run:
        n = sum(len(b.stamps_ns) for b in run.blocks(65536))
    c1 = time.process_time()
    whole = read_run(log)
    model = Model()
    c2 = time.process_time()
    result = process_run(whole, model)
    c3 = time.process_time()
    with ProcessedLogWriter(out, whole.device, model, whole.calibration.to_yaml(),
                            int(whole.stamps_ns[0])) as writer:
        writer.write(result)
    c4 = time.process_time()
    return {'read': 1e6 * (c1 - c0) / n, 'compute': 1e6 * (c3 - c2) / n,
            'write': 1e6 * (c4 - c3) / n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--quick', action='store_true', help='a 1-minute log instead of 10 minutes')
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--long', type=Path, action='append', default=[],
                        help='another log to process once, for peak RSS (not created here)')
    parser.add_argument('--baseline', type=Path, default=None,
                        help='a directory holding another mmd_ros, run interleaved with this one')
    args = parser.parse_args()
    # The x-axis ISO run with 4.6 s dwells lasts 596 s; the quick one uses one cycle.
    params = ('dwell_s=4.6',) if not args.quick else ('n_cycles=1', 'dwell_s=1.4')
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / 'run.mcap'
        out = Path(tmp) / 'out.mcap'
        spec = SimulationSpec(scenario_params=params, reference='pose6')
        simulate_to_log(spec, log, progress=False)
        run = read_run(log)
        device_log = write_run(Path(tmp) / 'device.mcap', run.device, run.calibration,
                               run.stamps_ns, run.counts, metadata=run.metadata, model=run.model)
        del run
        size_mb = device_log.stat().st_size / 1e6
        runs, base = [], []
        for _ in range(args.repeats):
            runs.append(command(device_log, out))
            if args.baseline is not None:
                base.append(command(device_log, out, baseline=args.baseline))
        pure = command(device_log, out, pure=True)
        with_reference = [command(log, out) for _ in range(args.repeats)]
        with_coverage = [command(log, out, coverage=True) for _ in range(args.repeats)]
        stage = stages(device_log, out)
        longs = {str(p): command(p, Path(tmp) / 'long.mcap') for p in args.long}
    n = runs[0]['samples']
    rate = statistics.median(r['samples_per_s'] for r in runs)
    result = {
        'benchmark': 'process', 'samples': n, 'log_mb': size_mb, 'repeats': args.repeats,
        'load_average': list(os.getloadavg()),
        'samples_per_s_median': rate, 'samples_per_s_runs': [r['samples_per_s'] for r in runs],
        'numpy_path_samples_per_s': pure['samples_per_s'],
        'ratio_to_numpy': rate / pure['samples_per_s'],
        'user_cpu_us_per_sample_median': 1e6 * statistics.median(r['user_cpu_s'] for r in runs) / n,
        'numpy_path_user_cpu_us_per_sample': 1e6 * pure['user_cpu_s'] / n,
        'peak_rss_mb': max(r['peak_rss_mb'] for r in runs),
        'numpy_path_peak_rss_mb': pure['peak_rss_mb'],
        'stage_cpu_us_per_sample': stage,
        'with_reference_samples_per_s_median': statistics.median(
            r['samples_per_s'] for r in with_reference),
        'with_reference_samples_per_s_runs': [r['samples_per_s'] for r in with_reference],
        'with_coverage_samples_per_s_median': statistics.median(
            r['samples_per_s'] for r in with_coverage),
        'with_coverage_user_cpu_us_per_sample_median': 1e6 * statistics.median(
            r['user_cpu_s'] for r in with_coverage) / n,
        'with_coverage_peak_rss_mb': max(r['peak_rss_mb'] for r in with_coverage),
        'long_logs': longs,
    }
    if base:
        result['baseline'] = str(args.baseline)
        result['baseline_samples_per_s_runs'] = [r['samples_per_s'] for r in base]
        result['baseline_samples_per_s_median'] = statistics.median(r['samples_per_s'] for r in base)
        result['ratio_to_baseline'] = rate / result['baseline_samples_per_s_median']
    print(f'mmd process on a {n / 1000:.0f} s device log, raw counts only ({n} samples, {size_mb:.1f} MB): median '
          f'{rate:,.0f} samples/s over {args.repeats} runs '
          f'({", ".join(f"{r:,.0f}" for r in result["samples_per_s_runs"])})   [target >= 500,000]')
    print(f'  numpy path (MMD_PURE_PYTHON=1), same run: {pure["samples_per_s"]:,.0f} samples/s; '
          f'ratio {result["ratio_to_numpy"]:.1f}')
    if base:
        print(f'  baseline {args.baseline}, interleaved: median {result["baseline_samples_per_s_median"]:,.0f} '
              f'samples/s ({", ".join(f"{r:,.0f}" for r in result["baseline_samples_per_s_runs"])}); '
              f'ratio {result["ratio_to_baseline"]:.2f}')
    print(f'  user CPU {result["user_cpu_us_per_sample_median"]:.2f} us per sample '
          f'(numpy path {result["numpy_path_user_cpu_us_per_sample"]:.2f}); peak RSS '
          f'{result["peak_rss_mb"]:.0f} MB (numpy path {pure["peak_rss_mb"]:.0f} MB)')
    print(f'  the same run with its 6-DOF reference pose in the log: '
          f'{result["with_reference_samples_per_s_median"]:,.0f} samples/s; and with the coverage of '
          f'that reference by the covariance (the default on a log with a reference): {result["with_coverage_samples_per_s_median"]:,.0f} samples/s, user CPU '
          f'{result["with_coverage_user_cpu_us_per_sample_median"]:.2f} us per sample, peak RSS '
          f'{result["with_coverage_peak_rss_mb"]:.0f} MB')
    print('  stages alone, CPU per sample: ' + ', '.join(f'{k} {v:.2f} us' for k, v in stage.items())
          + ' (overlapped in the command)')
    for path, r in longs.items():
        print(f'  {path}: {r["samples"]:,} samples, {r["samples_per_s"]:,.0f} samples/s, '
              f'peak RSS {r["peak_rss_mb"]:.0f} MB')
    print(f'  load average {result["load_average"][0]:.2f} (a shared machine: compare the ratios)')
    print(json.dumps(result))


if __name__ == '__main__':
    main()
