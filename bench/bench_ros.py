"""ROS 2 benchmark at 1 kHz: ``pose_node`` and the separate-process pipeline.

For each configuration the executables run on the simulated terminal (the digital twin in
random 6-DOF motion, recording on) and this process subscribes to ``/mmd/pose`` over DDS:

- **samples lost**: samples the terminal took in the measured span (from the stamps: one per
  millisecond) that did not arrive as a pose here; and those the driver reports lost on the wire
  (target 0);
- **latency**: from the moment a frame's USB transfer left the terminal backend (the node's
  ``timing_log``: the host time when the driver's bulk read returned it) to the moment its pose
  arrived in this process's subscription callback (target p99 <= 2 ms). The subscriber builds
  ``PoseStamped`` objects (``--subscriber objects``, rclpy's usual way) or reads the stamp from
  the serialised message (``bytes``): a transfer's poses arrive together, so a Python
  subscriber's own cost per message delays the later ones;
- **CPU** per process over the measured span, in % of one core (target ``pose_node`` <= 60 %);
- **memory**: resident set size after warm-up and at the end, and its growth (target flat).

Usage: ``python bench/bench_ros.py [--quick] [--duration S] [--repeat N] [--only pose_node|split]
[--param NAME:=VALUE] [--keep DIR]``. Default 600 s per configuration; ``--quick`` 60 s. With ``--repeat`` the
configurations alternate N times and the medians over the runs are printed too (single runs on a
shared 2-core machine vary by a factor of 1.5 in latency). Prints the figures and a JSON line;
never fails on timing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BIN = Path(sys.prefix) / 'bin'
WARMUP_S = 10.0
CLK_TCK = os.sysconf('SC_CLK_TCK')
PAGE = os.sysconf('SC_PAGE_SIZE')


def cmd(name: str) -> list[str]:
    exe = BIN / name
    return [str(exe)] if exe.exists() else [sys.executable, '-m', f'mmd_ros.nodes.{name}']


def cpu_ticks(pid: int) -> int:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return int(fields[11]) + int(fields[12])


def rss_mb(pid: int) -> float:
    return int(Path(f'/proc/{pid}/statm').read_text().split()[1]) * PAGE / 1e6


def factory_calibration(path: Path) -> None:
    """The calibration pose_node would write by itself (the twin's, seed 1, before power-on)."""
    from mmd_ros.twin.recording import ambient_profile
    from mmd_ros.core.device import find_config, load_device
    from mmd_ros.hardware.twin_source import TwinSource
    from mmd_ros.twin import Effects, TwinDevice, make_scenario
    device = load_device(find_config('mmd_prototype.yaml'))
    twin = TwinDevice(device, Effects.realistic(), seed=1)
    src = TwinSource(twin, ambient_profile('constant:20.0'),
                     make_scenario('random_motion', ['duration_s=300.0']))
    cal = src.factory_calibration()
    from dataclasses import replace
    replace(cal, created=time.strftime('%Y-%m-%dT%H:%M:%S+00:00', time.gmtime())).save(path)


def run_config(name: str, duration_s: float, work: Path, extra: list[str] = (),
               subscriber: str = 'objects') -> dict:
    from mmd_ros.nodes.client import MmdClient
    work.mkdir(parents=True, exist_ok=True)
    timing = work / 'timing.bin'
    cal = work / 'calibration.yaml'
    depth = ['-p', 'qos_depth:=5000']
    terminal = [a for kv in extra for a in ('-p', kv)]
    if name == 'pose_node':
        launches = {'pose_node': cmd('pose_node') + ['--ros-args', '-p', f'timing_log:={timing}',
                                                     '-p', f'calibration_file:={cal}',
                                                     '-p', f'output:={work / "log.mcap"}'] + depth + terminal}
    else:
        factory_calibration(cal)
        launches = {
            'encoder_node': cmd('encoder_node') + ['--ros-args', '-p', f'timing_log:={timing}'] + depth + terminal,
            'calibration_node': cmd('calibration_node') + ['--ros-args', '-p', f'calibration_file:={cal}'] + depth,
            'compensation_node': cmd('compensation_node') + ['--ros-args'] + depth,
            'fk_node': cmd('fk_node') + ['--ros-args'] + depth,
            'recorder_node': cmd('recorder_node') + ['--ros-args', '-p', f'output:={work / "log.mcap"}'] + depth,
        }
    env = dict(os.environ, ROS_HOME=str(work / 'ros_home'))
    procs = {k: subprocess.Popen(v, env=env, stdout=open(work / f'{k}.log', 'w'),  # noqa: SIM115
                                 stderr=subprocess.STDOUT, start_new_session=True)
             for k, v in launches.items()}
    topic = 'pose' if subscriber == 'objects' else 'pose_stamps'
    client = MmdClient(topics=(topic,), name='bench_subscriber', depth=5000)
    try:
        if not client.wait_for(lambda: len(client.pose_stamps) > 1000, 90):
            raise RuntimeError(f'{name}: no poses; see {work}')
        time.sleep(WARMUP_S)
        with client._lock:
            n0 = len(client.pose_stamps)
        ticks0 = {k: cpu_ticks(p.pid) for k, p in procs.items()}
        rss0 = {k: rss_mb(p.pid) for k, p in procs.items()}
        t0 = time.monotonic()
        rss_trace = []
        while time.monotonic() - t0 < duration_s:
            time.sleep(min(10.0, duration_s / 6))
            rss_trace.append({k: rss_mb(p.pid) for k, p in procs.items()})
        elapsed = time.monotonic() - t0
        ticks1 = {k: cpu_ticks(p.pid) for k, p in procs.items()}
        rss1 = {k: rss_mb(p.pid) for k, p in procs.items()}
        with client._lock:
            stamps = client.pose_stamps[n0:]
            arrivals = client.pose_arrivals[n0:]
        term = (client.status(': terminal') or {}).get('values', {})
    finally:
        client.close()
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
    stamps = np.array(stamps, dtype=np.int64)
    arrivals = np.array(arrivals, dtype=np.int64)
    # drop the last 2 s: those samples may still be on their way
    keep = stamps <= stamps.max() - 2_000_000_000
    stamps, arrivals = stamps[keep], arrivals[keep]
    span = int(round((stamps.max() - stamps.min()) / 1e6)) + 1
    lost = span - np.unique(stamps).size
    log = np.fromfile(timing, dtype=np.int64).reshape(-1, 2)
    left = dict(zip(log[:, 0].tolist(), log[:, 1].tolist()))
    known = [(s, a - left[s]) for s, a in zip(stamps.tolist(), arrivals.tolist()) if s in left]
    lat = np.array([d for _, d in known]) * 1e-6
    # every sample's latency, in arrival order, for a closer look (--keep)
    np.savez(work / 'latency.npz', stamp_ns=np.array([s for s, _ in known], np.int64), latency_ms=lat)
    cpu = {k: (ticks1[k] - ticks0[k]) / CLK_TCK / elapsed * 100 for k in procs}
    result = {
        'config': name, 'subscriber': subscriber, 'duration_s': round(elapsed, 1), 'samples_expected': span,
        'poses_received': int(np.unique(stamps).size), 'samples_lost': int(lost),
        'lost_on_wire': int(term.get('missing_samples', -1)),
        'latency_ms': {'p50': float(np.percentile(lat, 50)), 'p99': float(np.percentile(lat, 99)),
                       'p999': float(np.percentile(lat, 99.9)), 'max': float(lat.max()),
                       'n': int(lat.size)},
        'cpu_percent': {k: round(v, 1) for k, v in cpu.items()},
        'cpu_percent_total': round(sum(cpu.values()), 1),
        'rss_mb_start': {k: round(v, 1) for k, v in rss0.items()},
        'rss_mb_end': {k: round(v, 1) for k, v in rss1.items()},
        'rss_mb_growth': {k: round(rss1[k] - rss0[k], 1) for k in procs},
        'rss_mb_trace': [{k: round(v, 1) for k, v in r.items()} for r in rss_trace],
    }
    return result


def show(r: dict) -> None:
    lat = r['latency_ms']
    print(f'== {r["config"]}: {r["duration_s"]:.0f} s at 1 kHz, subscriber takes {r["subscriber"]}')
    print(f'  samples lost: {r["samples_lost"]} of {r["samples_expected"]} (on the wire: '
          f'{r["lost_on_wire"]})   [target 0]')
    print(f'  latency backend -> /mmd/pose in another process: p50 {lat["p50"]:.2f} ms, '
          f'p99 {lat["p99"]:.2f} ms, p99.9 {lat["p999"]:.2f} ms, max {lat["max"]:.1f} ms   '
          '[target p99 <= 2 ms]')
    for k, v in r['cpu_percent'].items():
        print(f'  {k:18s} CPU {v:5.1f} % of a core, RSS {r["rss_mb_start"][k]:.1f} -> '
              f'{r["rss_mb_end"][k]:.1f} MB ({r["rss_mb_growth"][k]:+.1f})')
    print(f'  total CPU {r["cpu_percent_total"]:.1f} %   [target pose_node <= 60 %; memory flat]')


def medians(runs: list[dict]) -> dict:
    """Median figures of repeated runs of one configuration."""
    def med(get) -> float:
        return round(float(np.median([get(r) for r in runs])), 3)
    return {
        'config': runs[0]['config'], 'runs': len(runs),
        'samples_lost_max': max(r['samples_lost'] for r in runs),
        'lost_on_wire_max': max(r['lost_on_wire'] for r in runs),
        'latency_ms_median': {k: med(lambda r, k=k: r['latency_ms'][k]) for k in ('p50', 'p99', 'p999')},
        'cpu_percent_median': {k: med(lambda r, k=k: r['cpu_percent'][k]) for k in runs[0]['cpu_percent']},
        'cpu_percent_total_median': med(lambda r: r['cpu_percent_total']),
        'rss_mb_growth_max': max(max(r['rss_mb_growth'].values()) for r in runs),
    }


def show_medians(m: dict) -> None:
    lat = m['latency_ms_median']
    print(f'== {m["config"]}: medians of {m["runs"]} runs')
    print(f'  samples lost: at most {m["samples_lost_max"]} (on the wire: {m["lost_on_wire_max"]})')
    print(f'  latency p50 {lat["p50"]:.2f} ms, p99 {lat["p99"]:.2f} ms, p99.9 {lat["p999"]:.2f} ms')
    print(f'  CPU total {m["cpu_percent_total_median"]:.1f} % of a core; '
          f'RSS growth at most {m["rss_mb_growth_max"]:+.1f} MB')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--quick', action='store_true', help='60 s per configuration')
    parser.add_argument('--duration', type=float, default=None, help='seconds per configuration')
    parser.add_argument('--only', choices=['pose_node', 'split'], default=None)
    parser.add_argument('--repeat', type=int, default=1, help='runs of each configuration')
    parser.add_argument('--subscriber', choices=['objects', 'bytes'], default='objects',
                        help='objects: the subscriber builds PoseStamped objects (rclpy\'s usual '
                             'way); bytes: it takes the serialised message and reads the stamp')
    parser.add_argument('--keep', type=Path, default=None, metavar='DIR',
                        help='keep each run\'s files in DIR (node logs, MCAP, latency.npz: every '
                             'sample\'s stamp and latency); default: a temporary directory')
    parser.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                        help='an extra parameter for the terminal (pose_node or encoder_node), '
                             'e.g. frames_per_transfer:=2; repeatable')
    args = parser.parse_args()
    duration = args.duration or (60.0 if args.quick else 600.0)
    os.environ['ROS_DOMAIN_ID'] = str(60 + os.getpid() % 40)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    work = args.keep or Path(tempfile.mkdtemp(prefix='bench_ros_'))
    names = [args.only] if args.only else ['pose_node', 'split']
    results = []
    try:
        for k in range(args.repeat):
            for name in names:
                r = run_config(name, duration, work / f'{name}_{k}', args.param, args.subscriber)
                show(r)
                results.append(r)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    summary = [medians([r for r in results if r['config'] == name]) for name in names]
    if args.repeat > 1:
        for m in summary:
            show_medians(m)
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    print(json.dumps({'benchmark': 'ros', 'duration_s': duration, 'params': args.param,
                      'subscriber': args.subscriber, 'load_average': load,
                      'repeat': args.repeat, 'medians': summary, 'results': results}))


if __name__ == '__main__':
    main()
