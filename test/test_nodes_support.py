"""Shared by the node tests: starting the real executables over real DDS and cleaning up.

Every test gets its own ``ROS_DOMAIN_ID`` (from the process id, so that two test runs on one
machine do not hear each other), ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and a private
``ROS_HOME``. Executables run in their own session and are stopped through their process group
in ``finally``; their output goes to files in the test's temporary folder, shown on failure.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.prefix) / 'bin'
_counter = [0]


def domain_id() -> int:
    """A ROS domain id unique to this test (100..199)."""
    _counter[0] += 1
    return 100 + ((os.getpid() % 25) * 4 + _counter[0]) % 100


def ros_available() -> bool:
    try:
        import rclpy  # noqa: F401 - is it installed?
    except ImportError:
        return False
    return True


#: The reason of :data:`needs_ros`, by which conftest.py finds the tests that use DDS.
NO_ROS = 'rclpy is not installed'
needs_ros = pytest.mark.skipif(not ros_available(), reason=NO_ROS)


def command(name: str) -> list[str]:
    """The installed executable, or the module when the package is not installed."""
    exe = BIN / name
    if exe.exists():
        return [str(exe)]
    return [sys.executable, '-m', f'mmd_ros.nodes.{name}']


def params(**values: object) -> list[str]:
    out = ['--ros-args']
    for k, v in values.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        out += ['-p', f'{k}:={v}']
    return out


class Nodes:
    """Executables started by a test, in the test's own DDS domain."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.domain = domain_id()
        self.env = dict(os.environ)
        self.env.update(ROS_DOMAIN_ID=str(self.domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                        ROS_HOME=str(tmp / 'ros_home'), PYTHONUNBUFFERED='1',
                        AMENT_PREFIX_PATH=os.environ.get('AMENT_PREFIX_PATH') or sys.prefix)
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}

    def apply_env(self) -> None:
        """Put this domain into our own environment (for the rclpy client of the test)."""
        for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_HOME'):
            os.environ[key] = self.env[key]

    def start(self, name: str, *args: str, tag: str | None = None) -> subprocess.Popen:
        tag = tag or name
        log = self.tmp / f'{tag}.log'
        self.logs[tag] = log
        proc = subprocess.Popen(command(name) + list(args), env=self.env, cwd=self.tmp,
                                stdout=open(log, 'w'), stderr=subprocess.STDOUT,  # noqa: SIM115
                                start_new_session=True)
        self.procs[tag] = proc
        return proc

    def signal(self, tag: str, sig: int = signal.SIGINT, timeout: float = 30.0) -> int | None:
        """Send ``sig`` to the process group and wait for the process to end."""
        proc = self.procs[tag]
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                pass
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
            return None

    def output(self, tag: str) -> str:
        path = self.logs.get(tag)
        return path.read_text(errors='replace') if path and path.exists() else ''

    def dump(self) -> str:
        return '\n'.join(f'----- {tag} -----\n{self.output(tag)[-4000:]}' for tag in self.logs)

    def stop_all(self) -> None:
        for tag, proc in self.procs.items():
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + 15
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)


def gaps_from_stamps(stamps_ns, period_ns: int = 1_000_000) -> int:
    """Samples missing in a stream of stamps, from the steps between them."""
    import numpy as np
    s = np.sort(np.asarray(stamps_ns, dtype=np.int64))
    steps = np.rint(np.diff(s) / period_ns).astype(np.int64)
    return int(np.sum(np.maximum(steps - 1, 0)))


def seen(client, since: float, suffix: str, text: str, level: int | None = None) -> bool:
    """A diagnostics status ending in ``suffix`` said ``text`` after ``since`` (monotonic)."""
    with client._lock:
        history = list(client.diagnostic_history)
    return any(t >= since and e['name'].endswith(suffix) and text in e['message']
               and (level is None or e['level'] == level) for t, e in history)
