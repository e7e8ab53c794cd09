"""The live step of ``make demo``: ``pose_node`` on the simulated terminal, driven over ROS 2.

Starts ``pose_node`` as a separate process (simulated terminal streaming the digital twin,
bars in their case, no calibration yet, recording on), runs the guided calibration of section
3.2 through ``/mmd/calibrate_bar`` with a simulated operator who places each bar where the
answer says, mounts the bars, prints the live pose stream for ``stream_s`` seconds while it is
recorded, stops the node with Ctrl-C (SIGINT: the log is closed cleanly) and processes the
recorded log as ``mmd process`` does, with the error against the twin's reference.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ['live_step']

ARCSEC_PER_RAD = 180 / math.pi * 3600


def _pose_node_command() -> list[str]:
    exe = Path(sys.prefix) / 'bin' / 'pose_node'
    return [str(exe)] if exe.exists() else [sys.executable, '-m', 'mmd_ros.nodes.pose_node']


def live_step(out_dir: Path, *, stream_s: float = 20.0, heading=print) -> int:
    """Run the live demonstration; returns 0, or 1 when something failed (said why)."""
    try:
        from mmd_ros.nodes.client import MmdClient, guided_calibration
    except ImportError as exc:
        print(f'skipped: ROS 2 (rclpy) is not available here ({exc})')
        return 0
    from mmd_ros.logs.processing import process_run, summarize
    from mmd_ros.core.accuracy import ComponentStats, format_stats
    from mmd_ros.core.model import Model
    from mmd_ros.logs.layout import read_run

    live = out_dir / 'live'
    shutil.rmtree(live, ignore_errors=True)
    live.mkdir(parents=True)
    cal_file, log_file = live / 'calibration.yaml', live / 'live.mcap'
    settle, transition = 0.3, 0.25
    args = {'sim_mounted': 'false', 'sim_factory_calibration': 'false', 'sim_transition_s': transition,
            'settle_window_s': settle, 'ambient_c': 20.0, 'calibration_file': cal_file,
            'output': log_file}
    ros_args = ['--ros-args'] + [a for k, v in args.items() for a in ('-p', f'{k}:={v}')]
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(150 + os.getpid() % 80), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_HOME=str(live / 'ros_home'))
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_HOME'):
        os.environ[key] = env[key]
    print('ros2 run mmd_ros pose_node ' + ' '.join(ros_args))
    node_log = open(live / 'pose_node.log', 'w')  # noqa: SIM115
    proc = subprocess.Popen(_pose_node_command() + ros_args, env=env, stdout=node_log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    client = None
    try:
        client = MmdClient(topics=('pose', 'reference'))
        if not client.wait_for(lambda: client.status(': calibration') is not None, 60):
            print(f'pose_node did not come up; see {live / "pose_node.log"}')
            return 1
        term = client.status(': terminal')
        print(f'pose_node is up: {term["message"] if term else "terminal starting"}')
        print(f'calibration: {client.status(": calibration")["message"]}')

        heading('4a. calibrate: ros2 service call /mmd/calibrate_bar std_srvs/srv/Trigger, 50 times')
        count = [0]

        def show(message: str) -> None:
            count[0] += 1
            if count[0] == 1 or ' calibrated: ' in message or message.startswith('refused'):
                text = message.replace(' Next: ', '\n      next: ')
                print(f'  [{count[0]:2d}] {text}')

        log = guided_calibration(client, sim_node='pose_node', wait_s=transition + settle + 0.2,
                                 retry_s=0.3, timeout_s=300, show=show)
        print(f'{sum(ok for ok, _ in log.answers)} captures (the points and the reference bar\'s '
              f'drift reading) in {log.seconds:.0f} s ({log.refused_moving} capture(s) refused '
              f'while a bar was still settling); saved to {cal_file}')

        heading(f'4b. measure: ros2 topic echo /mmd/pose, {stream_s:.0f} s of random 6-DOF motion')
        client.set_param('pose_node', 'sim_command', 'mount')
        time.sleep(transition + 0.5)
        since = time.time_ns()
        t_end = time.monotonic() + stream_s
        last_n, last_t = len(client.poses), time.monotonic()
        columns = ('t s', 'rate Hz', 'x mm', 'y mm', 'z mm', 'roll "', 'pitch "', 'yaw "', '|e| µm')
        widths = (5, 8, 10, 10, 10, 9, 9, 9, 7)
        print('  ' + ' '.join(f'{c:>{w}}' for c, w in zip(columns, widths)) + '  diagnostics')
        while time.monotonic() < t_end:
            time.sleep(0.5)
            now = time.monotonic()
            n = len(client.poses)
            rate = (n - last_n) / (now - last_t)
            last_n, last_t = n, now
            stamps, poses = client.pose_array()
            if not len(poses):
                continue
            p = poses[-1]
            err = client.errors_against_reference(since)
            e = float(np.linalg.norm(err[-1, :3])) * 1e6 if len(err) else float('nan')
            k = client.status(': kinematics') or {'values': {}}
            c = client.status(': compensation') or {'values': {}}
            r = client.status(': recorder') or {'values': {}}
            diag = (f'FK {k["values"].get("iterations_mean", "?")} it, '
                    f'dT {c["values"].get("temp_change_c", "?")} °C, '
                    f'log {r["values"].get("size_mb", "?")} MB')
            print(f'  {stream_s - (t_end - now):5.1f} {rate:8.0f} {p[0] * 1e3:10.4f} {p[1] * 1e3:10.4f} '
                  f'{p[2] * 1e3:10.4f} {p[3] * ARCSEC_PER_RAD:9.1f} {p[4] * ARCSEC_PER_RAD:9.1f} '
                  f'{p[5] * ARCSEC_PER_RAD:9.1f} {e:7.2f}  {diag}')
        err = client.errors_against_reference(since)
        for name, status in sorted(client.diagnostics.items()):
            level = ('OK', 'WARN', 'ERROR', 'STALE')[min(status['level'], 3)]
            print(f'  {name}: {level} {status["message"][:100]}')
        from mmd_ros.core.accuracy import error_stats
        print(format_stats(error_stats(err), f'live poses against the twin\'s reference ({len(err)} '
                           'samples received):'))
    except Exception as exc:  # noqa: BLE001 - a demo says what went wrong and ends
        print(f'live step failed: {exc}; see {live / "pose_node.log"}')
        return 1
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the recording is closed cleanly
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
        node_log.close()

    heading('4c. process the recorded log (mmd process)')
    run = read_run(log_file)
    t0 = time.perf_counter()
    result = process_run(run, run.model or Model())
    info = summarize(run, result)
    print(f'{log_file} ({log_file.stat().st_size / 1e6:.1f} MB, closed cleanly: '
          f'{run.problem is None}): {info["samples"]} samples, {info["valid"]} valid poses, '
          f'processed in {time.perf_counter() - t0:.2f} s')
    if 'pose_error' in info:
        print(format_stats([ComponentStats(**s) for s in info['pose_error']],
                           'error of the recorded run against the twin\'s reference (MMD - reference):'))
    return 0
