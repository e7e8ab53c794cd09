"""A log replayed as fast as possible through compensation_node and fk_node, with and without
flow control.

Simulates a random-motion log of ``--seconds`` (1 kHz), starts compensation_node and fk_node
with a queue of ``--depth`` messages, and replays the log at rate 0, once with flow control
(the default: the replay waits for the stages' ``pipeline/progress``) and once without. For
each: the replay's wall time, the time it waited for the stages, and per stage the samples
received and lost (the replay's summary, from the stages' sequence-number counts).

Usage: ``python bench/bench_replay.py [--seconds 8] [--depth 1000] [--load N]``. Prints the
figures and a JSON line; never fails on timing.
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

BIN = Path(sys.prefix) / 'bin'


def cmd(name: str) -> list[str]:
    exe = BIN / name
    return [str(exe)] if exe.exists() else [sys.executable, '-m', f'mmd_ros.nodes.{name}']


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--seconds', type=float, default=8.0, help='length of the simulated log')
    parser.add_argument('--depth', type=int, default=1000, help='qos_depth of every node')
    parser.add_argument('--load', type=int, default=0, help='busy processes keeping the cores busy')
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix='bench_replay_'))
    os.environ.update(ROS_HOME=str(work / 'ros_home'), ROS_DOMAIN_ID=str(60 + os.getpid() % 40),
                      ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    from mmd_ros.nodes.client import MmdClient
    from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
    log = work / 'run.mcap'
    spec = SimulationSpec(scenario='random_motion', scenario_params=(f'duration_s={args.seconds}',),
                          ambient='constant:20', seed=3)
    n = simulate_to_log(spec, log, progress=False)[2]['samples']
    depth = ['-p', f'qos_depth:={args.depth}']
    procs = [subprocess.Popen(cmd(name) + ['--ros-args', *depth], stdout=open(work / f'{name}.log', 'w'),  # noqa: SIM115
                              stderr=subprocess.STDOUT, start_new_session=True)
             for name in ('compensation_node', 'fk_node')]
    procs += [subprocess.Popen([sys.executable, '-c', 'while True: pass'], start_new_session=True)
              for _ in range(args.load)]
    client = MmdClient(topics=())
    results = []
    try:
        time.sleep(3.0)
        for flow in (True, False):
            since = time.monotonic()
            t0 = time.monotonic()
            out = subprocess.run(cmd('replay_node') + [
                '--ros-args', '-p', f'log:={log}', '-p', 'rate:=0.0', '-p', 'wait_for_subscribers:=1',
                '-p', f'flow_control:={"true" if flow else "false"}', *depth],
                capture_output=True, text=True, timeout=600)
            wall = time.monotonic() - t0
            done = [e for t, e in list(client.diagnostic_history) if t >= since
                    and e['name'].endswith(': replay') and e['values'].get('state') == 'done']
            v = done[-1]['values'] if done else {}
            stages = {k[:-len(' received')]: {'received': int(v[k]), 'lost': int(v[k[:-len('received')] + 'lost'])}
                      for k in v if k.endswith(' received')}
            r = {'flow_control': flow, 'samples': n, 'depth': args.depth, 'exit': out.returncode,
                 'replay_s': float(v.get('seconds', 'nan')), 'held_s': float(v.get('held_s', 'nan')),
                 'process_s': round(wall, 2), 'stages': stages}
            results.append(r)
            print(f'flow control {"on " if flow else "off"}: {n} samples sent in {r["replay_s"]:.2f} s '
                  f'({r["held_s"]:.2f} s waiting for the stages; the process ran {wall:.1f} s), '
                  f'queues of {args.depth}')
            for key, st in stages.items():
                print(f'   {key}: {st["received"]} received, {st["lost"]} lost')
    finally:
        client.close()
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT if p.args[0] != sys.executable else signal.SIGKILL)
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps({'benchmark': 'replay', 'load_processes': args.load,
                      'load_average': os.getloadavg(), 'results': results}))


if __name__ == '__main__':
    main()
