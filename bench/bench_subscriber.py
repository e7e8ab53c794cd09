"""A Python subscriber of the poses at 1 kHz: per-sample ``/mmd/pose`` against ``/mmd/pose_batch``.

``pose_node`` (or, with ``--source split``, the separate nodes ending in ``fk_node``) runs on the
simulated terminal at 1 kHz; ``--load N`` busy processes keep the cores busy as other work
would. A plain rclpy subscriber in its own process (``rclpy.spin``, the single-threaded
executor, message objects: what most Python tooling and ``ros2 topic hz`` do; ``--executor
events`` for rclpy's EventsExecutor) subscribes for ``--seconds`` to

- ``pose``: one ``geometry_msgs/PoseStamped`` per sample, or
- ``pose_batch``: one ``nav_msgs/Path`` per transfer (8 samples), each pose with its stamp,

with reliable QoS, keep last ``--depth``. Figures per topic: samples received per second, the
samples published in that span that never reached the subscriber (from the stamps: one per
millisecond), and the subscriber's CPU in % of one core.

Usage: ``python bench/bench_subscriber.py [--seconds 30] [--load 2] [--source pose_node|split]
[--executor single|events] [--repeat N]``. Prints the figures and a JSON line; never fails on
timing.
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
CLK_TCK = os.sysconf('SC_CLK_TCK')


def cmd(name: str) -> list[str]:
    exe = BIN / name
    return [str(exe)] if exe.exists() else [sys.executable, '-m', f'mmd_ros.nodes.{name}']


def subscribe(topic: str, seconds: float, depth: int, executor: str, warmup_s: float) -> dict:
    """The subscriber process: count what arrives on ``topic`` for ``seconds``."""
    import numpy as np
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node('bench_subscriber')
    stamps: list[int] = []
    state = {'counting': False, 'messages': 0}

    def stamp(h) -> int:
        return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec

    def on_pose(msg: PoseStamped) -> None:
        if state['counting']:
            state['messages'] += 1
            stamps.append(stamp(msg.header))

    def on_batch(msg: PathMsg) -> None:
        if state['counting']:
            state['messages'] += 1
            stamps.extend(stamp(p.header) for p in msg.poses)

    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                     reliability=ReliabilityPolicy.RELIABLE)
    if topic == 'pose':
        node.create_subscription(PoseStamped, '/mmd/pose', on_pose, qos)
    else:
        node.create_subscription(PathMsg, '/mmd/pose_batch', on_batch, qos)
    if executor == 'events':
        from rclpy.experimental import EventsExecutor
        ex = EventsExecutor()
    else:
        from rclpy.executors import SingleThreadedExecutor
        ex = SingleThreadedExecutor()
    ex.add_node(node)
    end_warmup = time.monotonic() + warmup_s
    while time.monotonic() < end_warmup:
        ex.spin_once(timeout_sec=0.05)
    t = os.times()
    cpu0, t0 = t.user + t.system, time.monotonic()
    state['counting'] = True
    while time.monotonic() - t0 < seconds:
        ex.spin_once(timeout_sec=0.05)
    state['counting'] = False
    t = os.times()
    cpu = t.user + t.system - cpu0
    elapsed = time.monotonic() - t0
    s = np.unique(np.asarray(stamps, dtype=np.int64))
    # the samples published in the span the subscriber saw, one per millisecond; the last
    # second is left out (those may still be on their way when counting stopped)
    if s.size > 2:
        s = s[s <= s[-1] - 1_000_000_000]
    span = int(round((s[-1] - s[0]) / 1e6)) + 1 if s.size > 1 else 0
    return {'topic': topic, 'executor': executor, 'seconds': round(elapsed, 2),
            'messages': state['messages'], 'samples': int(len(stamps)),
            'samples_per_s': round(len(stamps) / elapsed, 1),
            'samples_published_in_span': span, 'missed': int(span - s.size),
            'cpu_percent': round(100 * cpu / elapsed, 1)}


def start_source(source: str, work: Path, env: dict) -> dict[str, subprocess.Popen]:
    def launch(name: str, *args: str) -> subprocess.Popen:
        return subprocess.Popen(cmd(name) + ['--ros-args', *args], env=env,
                                stdout=open(work / f'{name}.log', 'w'),  # noqa: SIM115
                                stderr=subprocess.STDOUT, start_new_session=True)
    cal = work / 'calibration.yaml'
    if source == 'pose_node':
        return {'pose_node': launch('pose_node', '-p', f'calibration_file:={cal}',
                                    '-p', f'output:={work / "log.mcap"}')}
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_ros import factory_calibration
    factory_calibration(cal)
    return {'encoder_node': launch('encoder_node'),
            'calibration_node': launch('calibration_node', '-p', f'calibration_file:={cal}'),
            'compensation_node': launch('compensation_node'),
            'fk_node': launch('fk_node')}


def stop(procs, sig: int = signal.SIGINT) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, sig)
    for p in procs:
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--seconds', type=float, default=30.0, help='measured span per topic')
    parser.add_argument('--load', type=int, default=2, help='busy processes keeping the cores busy')
    parser.add_argument('--source', choices=['pose_node', 'split'], default='pose_node')
    parser.add_argument('--executor', choices=['single', 'events'], default='single')
    parser.add_argument('--depth', type=int, default=1000, help='subscriber queue (keep last)')
    parser.add_argument('--repeat', type=int, default=1, help='alternate the topics N times')
    parser.add_argument('--subscribe', choices=['pose', 'pose_batch'], help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.subscribe:  # the subscriber process
        print(json.dumps(subscribe(args.subscribe, args.seconds, args.depth, args.executor, 5.0)))
        return
    work = Path(tempfile.mkdtemp(prefix='bench_sub_'))
    env = dict(os.environ, ROS_HOME=str(work / 'ros_home'), ROS_DOMAIN_ID=str(60 + os.getpid() % 40),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    procs = start_source(args.source, work, env)
    load = [subprocess.Popen([sys.executable, '-c', 'while True: pass'], start_new_session=True)
            for _ in range(args.load)]
    results = []
    try:
        time.sleep(8.0)  # the source's start and discovery
        for _ in range(args.repeat):
            for topic in ('pose', 'pose_batch'):
                out = subprocess.run([sys.executable, __file__, '--subscribe', topic,
                                      '--seconds', str(args.seconds), '--depth', str(args.depth),
                                      '--executor', args.executor],
                                     env=env, capture_output=True, text=True,
                                     timeout=args.seconds + 120)
                if out.returncode != 0:
                    raise RuntimeError(out.stderr[-2000:])
                r = json.loads(out.stdout.strip().splitlines()[-1])
                results.append(r)
                print(f'{args.source} -> /mmd/{topic:10s} ({args.executor} executor, {args.load} busy '
                      f'processes): {r["samples_per_s"]:7.1f} samples/s received, '
                      f'{r["missed"]} of {r["samples_published_in_span"]} published samples '
                      f'missed, subscriber CPU {r["cpu_percent"]:.1f} % of a core '
                      f'({r["messages"]} messages)')
    finally:
        stop(list(procs.values()))
        stop(load, signal.SIGKILL)
        shutil.rmtree(work, ignore_errors=True)
    try:
        loadavg = os.getloadavg()
    except OSError:
        loadavg = None
    print(json.dumps({'benchmark': 'subscriber', 'source': args.source, 'load_processes': args.load,
                      'load_average': loadavg, 'executor': args.executor, 'depth': args.depth,
                      'results': results}))


if __name__ == '__main__':
    main()
