"""A small rclpy client of a running mmd device, for the demo, the benchmark and the tests.

:class:`MmdClient` runs its own context and EventsExecutor in a background thread, collects
what the device publishes (poses, reference, raw-count stamps, diagnostics) and calls its
services and parameters with deadlines. It is what a ROS user does with ``ros2 topic echo``,
``ros2 service call`` and ``ros2 param set``, from Python.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from mmd_ros.nodes.convert import from_time, stamp_of_serialized
from mmd_ros.nodes.qos import DIAGNOSTICS, data_qos

__all__ = ['CalibrationLog', 'MmdClient', 'guided_calibration', 'next_placement']

_NEXT = re.compile(r'(?:Next: )?place (\S+) on (\S+)(?: \([^)]*\))?(?: from (short|long))?')


def next_placement(message: str) -> tuple[str, str] | None:
    """(bar, pair) of the "Next: place <bar> on <pair>" in a calibrate_bar answer (or of a
    diagnostics ``next_step``), or None; the pair as "<pair> <short|long>" when the routine
    asks for an approach (what the simulated operator's ``place`` command takes)."""
    m = _NEXT.search(message.split('Next:', 1)[1] if 'Next:' in message else message)
    if not m:
        return None
    return (m.group(1), f'{m.group(2)} {m.group(3)}' if m.group(3) else m.group(2))


class MmdClient:
    """Talks to the device in ``namespace`` (see the module docstring).

    topics : which per-sample topics to collect: 'pose', 'reference', 'raw' (stamps only),
        'pose_stamps' (the poses' stamps and arrival times only, read from the serialised
        message without building message objects: what a lean consumer costs), 'pose_batch'
        (the poses of ``pose_batch``, one ``nav_msgs/Path`` per transfer, collected as 'pose'
        collects those of ``pose``)
    """

    def __init__(self, namespace: str = '/mmd', *, topics: tuple[str, ...] = ('pose', 'reference'),
                 name: str = 'mmd_client', depth: int = 5000) -> None:
        self.ns = namespace.rstrip('/')
        self.context = Context()
        rclpy.init(context=self.context, args=[])
        self.node = rclpy.create_node(name, context=self.context)
        self._clients: dict[tuple[Any, str], Any] = {}
        self._lock = threading.Lock()
        self.poses: list[tuple[int, float, float, float, float, float, float, float]] = []
        self.pose_arrivals: list[int] = []
        self.pose_stamps: list[int] = []
        self.reference: dict[int, np.ndarray] = {}
        self.raw_stamps: list[int] = []
        self.raw_counts: list[np.ndarray] = []
        self.diagnostics: dict[str, Any] = {}
        self.diagnostic_history: list[tuple[float, dict[str, Any]]] = []
        qos = data_qos('reliable', depth)
        n = self.node
        self.batches = 0
        self._subscriptions: dict[str, Any] = {}
        wanted = {
            'pose': (PoseStamped, 'pose', self._on_pose, False),
            'pose_batch': (Path, 'pose_batch', self._on_pose_batch, False),
            'pose_stamps': (PoseStamped, 'pose', self._on_pose_bytes, True),
            'reference': (JointState, 'reference/pose', self._on_reference, False),
            'raw': (JointState, 'raw_counts', self._on_raw, False),
        }
        for key, (cls, topic, callback, raw) in wanted.items():
            if key in topics:
                self._subscriptions[key] = n.create_subscription(cls, f'{self.ns}/{topic}', callback,
                                                                 qos, raw=raw)
        n.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, DIAGNOSTICS)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(n)
        self._running = True
        self._thread = threading.Thread(target=self._spin, name='mmd-client', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while self._running and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - shutting down
                if not self._running:
                    return

    def drop(self, *topics: str) -> None:
        """Stop collecting ``topics`` (keys as in the constructor): a per-sample subscription
        this process no longer needs only makes it fall behind on everything else, service
        answers included."""
        for key in topics:
            sub = self._subscriptions.pop(key, None)
            if sub is not None:
                self.node.destroy_subscription(sub)

    # -- collected data ------------------------------------------------------------------------
    def _on_pose(self, msg: PoseStamped) -> None:
        p = msg.pose
        row = (from_time(msg.header.stamp), p.position.x, p.position.y, p.position.z,
               p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
        arrival = time.time_ns()
        with self._lock:
            self.poses.append(row)
            self.pose_stamps.append(row[0])
            self.pose_arrivals.append(arrival)

    def _on_pose_batch(self, msg: Path) -> None:
        arrival = time.time_ns()
        rows = []
        for ps in msg.poses:
            p = ps.pose
            rows.append((from_time(ps.header.stamp), p.position.x, p.position.y, p.position.z,
                         p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
        with self._lock:
            self.batches += 1
            self.poses.extend(rows)
            self.pose_stamps.extend(r[0] for r in rows)
            self.pose_arrivals.extend([arrival] * len(rows))

    def _on_pose_bytes(self, data: bytes) -> None:
        arrival = time.time_ns()
        stamp = stamp_of_serialized(data)
        with self._lock:
            self.pose_stamps.append(stamp)
            self.pose_arrivals.append(arrival)

    def _on_reference(self, msg: JointState) -> None:
        with self._lock:
            self.reference[from_time(msg.header.stamp)] = np.asarray(msg.position, dtype=np.float64)

    def _on_raw(self, msg: JointState) -> None:
        with self._lock:
            self.raw_stamps.append(from_time(msg.header.stamp))
            self.raw_counts.append(np.asarray(msg.position, dtype=np.float64))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = time.monotonic()
        with self._lock:
            for st in msg.status:
                entry = {'level': st.level[0] if isinstance(st.level, (bytes, bytearray)) else int(st.level),
                         'message': st.message, 'hardware_id': st.hardware_id,
                         'values': {kv.key: kv.value for kv in st.values}, 'time': now}
                self.diagnostics[st.name] = entry
                self.diagnostic_history.append((now, {'name': st.name, **entry}))
            del self.diagnostic_history[:-5000]

    def pose_array(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (N,) [ns] and poses (N, 6) [m, rad] received so far."""
        with self._lock:
            rows = list(self.poses)
        if not rows:
            return np.zeros(0, np.int64), np.zeros((0, 6))
        a = np.array(rows, dtype=np.float64)
        stamps = np.array([r[0] for r in rows], dtype=np.int64)
        from mmd_ros.core.rotation import quaternion_to_angles
        return stamps, np.column_stack([a[:, 1:4], quaternion_to_angles(a[:, 4:8])])

    def errors_against_reference(self, since_ns: int = 0) -> np.ndarray:
        """Pose minus reference (N, 6) [m, rad] at the stamps both have."""
        stamps, poses = self.pose_array()
        with self._lock:
            ref = dict(self.reference)
        keep = [i for i, s in enumerate(stamps) if s >= since_ns and int(s) in ref]
        if not keep:
            return np.zeros((0, 6))
        r = np.array([ref[int(stamps[i])] for i in keep])
        e = poses[keep] - r
        e[:, 3:] = (e[:, 3:] + np.pi) % (2 * np.pi) - np.pi
        return e

    def status(self, suffix: str) -> dict[str, Any] | None:
        """The latest diagnostic status whose name ends with ``suffix`` (e.g. ': terminal')."""
        with self._lock:
            for name, entry in self.diagnostics.items():
                if name.endswith(suffix):
                    return entry
        return None

    def wait_for(self, predicate, timeout: float, poll: float = 0.05) -> bool:
        """Poll ``predicate()`` until it is true or ``timeout`` [s] passed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(poll)
        return bool(predicate())

    # -- services and parameters ---------------------------------------------------------------
    def _call(self, srv_type: Any, name: str, request: Any, timeout: float) -> Any:
        # One client per service, kept: a reply is lost when the service answers before it has
        # matched the client's reply reader (rmw_fastrtps waits 100 ms for that), the known
        # client/service discovery race of ROS 2; a client made for each call met it afresh
        # every time (seen: a calibrate_bar call of the guided routine never answered)
        key = (srv_type, name)
        client = self._clients.get(key)
        fresh = client is None
        if fresh:
            client = self._clients[key] = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f'service {name} not available after {timeout:.0f} s')
        if fresh:
            time.sleep(0.3)  # for the service to match our reply reader too
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            client.remove_pending_request(future)
            raise TimeoutError(f'service {name} did not answer within {timeout:.0f} s')
        return future.result()

    def trigger(self, service: str, timeout: float = 30.0) -> tuple[bool, str]:
        """Call a ``std_srvs/Trigger`` service (relative names are in the device namespace)."""
        name = service if service.startswith('/') else f'{self.ns}/{service}'
        res = self._call(Trigger, name, Trigger.Request(), timeout)
        return bool(res.success), str(res.message)

    def set_param(self, node: str, name: str, value: Any, timeout: float = 30.0) -> tuple[bool, str]:
        """Set one parameter of ``node`` (e.g. 'pose_node'); (successful, reason)."""
        fqn = node if node.startswith('/') else f'{self.ns}/{node}'
        msg: ParameterMsg = Parameter(name, value=value).to_parameter_msg()
        res = self._call(SetParameters, f'{fqn}/set_parameters', SetParameters.Request(parameters=[msg]),
                         timeout)
        r = res.results[0]
        return bool(r.successful), str(r.reason)

    def close(self, timeout: float = 30.0) -> None:
        """Stop the spinning thread, then destroy the node and the context. Destroying them
        while the thread is still inside the executor can crash the process (on a loaded
        machine the thread can take seconds to come back): if it does not end within
        ``timeout`` [s], they are left to the process's exit."""
        self._running = False
        self._thread.join(timeout)
        if self._thread.is_alive():
            return
        try:
            self.executor.shutdown()
        except Exception:  # noqa: BLE001
            pass
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@dataclass
class CalibrationLog:
    """What :func:`guided_calibration` did: every answer, and the refusals it recovered from."""

    answers: list[tuple[bool, str]] = field(default_factory=list)
    refused_moving: int = 0
    seconds: float = 0.0


def guided_calibration(client: MmdClient, *, sim_node: str, wait_s: float, retry_s: float,
                       timeout_s: float = 300.0, max_steps: int = 200,
                       before_capture: Callable[[int, str, str], None] | None = None,
                       show: Callable[[str], None] | None = None) -> CalibrationLog:
    """Run the calibration routine through ``calibrate_bar`` with the simulated operator.

    Reads the first placement from the calibration diagnostics (``next_step``), then for each
    one: tells the simulated world (``sim_command`` of ``sim_node``) to place the bar, waits
    ``wait_s`` for it to settle, and calls the service; an answer that the bar is still moving
    is retried after ``retry_s``; any other refusal raises. Ends when an answer names no next
    placement. ``before_capture(k, bar, pair)`` may inject faults before capture k.
    """
    log = CalibrationLog()
    start = time.monotonic()
    deadline = start + timeout_s
    step = None
    while step is None:
        st = client.status(': calibration')
        if st is not None:
            step = next_placement(st['values'].get('next_step', ''))
            if step is None:
                raise RuntimeError(f'the calibration has no next step: {st["values"]}')
        elif time.monotonic() > deadline:
            raise TimeoutError('no calibration diagnostics received')
        else:
            time.sleep(0.1)
    k = 0
    while step is not None:
        if k >= max_steps or time.monotonic() > deadline:
            raise TimeoutError(f'calibration not finished after {k} captures')
        bar, pair = step
        ok, why = client.set_param(sim_node, 'sim_command', f'place {bar} {pair}')
        if not ok:
            raise RuntimeError(f'simulated operator could not place {bar} on {pair}: {why}')
        time.sleep(wait_s)
        if before_capture is not None:
            before_capture(k, bar, pair)
        while True:
            ok, message = client.trigger('calibrate_bar')
            log.answers.append((ok, message))
            if show is not None:
                show(message)
            if ok:
                break
            if 'still moving' in message or 'samples in the settling window' in message:
                log.refused_moving += 1
                if time.monotonic() > deadline:
                    raise TimeoutError(message)
                time.sleep(retry_s)
                continue
            raise RuntimeError(f'capture {k} refused: {message}')
        k += 1
        step = next_placement(message) if 'Next: place' in message else None
    log.seconds = time.monotonic() - start
    return log
