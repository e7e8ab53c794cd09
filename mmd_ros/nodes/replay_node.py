"""``replay_node`` (and ``mmd replay``): a recorded log back onto the live topics.

Publishes the log's device description, its calibration (the last one in the log, as
``mmd process`` uses it) and its model on the latched topics, then every sample's
``raw_counts`` (and ``reference/pose`` when the log has one) with the recorded stamps, at the
original timing scaled by ``rate`` (0: as fast as possible), from a thread. The compensation and
kinematics nodes then recompute the poses from the log. Topics, parameters: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from mmd_ros.logs.layout import read_run
from mmd_ros.logs.replay import ReplaySchedule, log_problem_values, paced_batches
from mmd_ros.nodes.common import COMMON_PARAMS, NAMESPACE, run
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, JS, STRING, Rows, string_bytes
from mmd_ros.nodes.diagnostics import ERROR, OK, WARN, Diagnostics, Report
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, ParameterError, declare
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos

__all__ = ['ReplayNode', 'main']

PARAMS = [
    Param('log', '', 'the MCAP log to replay (required)'),
    Param('rate', 1.0, 'playback speed: 1 the original timing, 2 twice as fast; 0 as fast as '
          'possible', low=0.001, high=1000.0, allow_zero=True),
    Param('wait_for_subscribers', 0, 'wait until raw_counts has this many subscribers before '
          'starting', low=0, high=100),
    Param('wait_timeout_s', 30.0, 'give up waiting for subscribers after this long [s]',
          low=0.0, high=3600.0),
    Param('start_delay_s', 0.5, 'pause after the latched topics, before the first sample [s]',
          low=0.0, high=3600.0),
    Param('publish_reference', True, 'also publish the log\'s reference/pose'),
    Param('exit_when_done', True, 'shut down once the log has been replayed and acknowledged'),
]


class ReplayNode(Node):
    """A log's raw counts (and calibration) back onto the topics."""

    def __init__(self) -> None:
        super().__init__('replay_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + PARAMS)
        if not v['log']:
            raise ParameterError('parameter log: the MCAP log to replay is required (-p log:=run.mcap)')
        self.cfg = v
        self.run_log = read_run(v['log'])
        if self.run_log.problem:
            self.get_logger().warn(str(self.run_log.problem))
        dev = self.run_log.device
        self.rows = Rows(dev.channel_names, [c.name for c in dev.reference_channels])
        qos = data_qos(v['qos'], v['qos_depth'])
        self.out_raw = Outlet(self, 'raw_counts', JointState, JS, qos)
        self.out_reference = Outlet(self, 'reference/pose', JointState, JS, qos)
        self.out_device = Outlet(self, 'device_description', String, STRING, LATCHED, 'latched')
        self.out_calibration = Outlet(self, 'calibration', String, STRING, LATCHED, 'latched')
        self.out_model = Outlet(self, 'model', String, STRING, LATCHED, 'latched')
        self.out_diag = Outlet(self, '/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        self.schedule = ReplaySchedule(self.run_log.stamps_ns, v['rate'])
        self.sent = 0
        self.state = 'starting'
        self.error = ''
        self._stop = threading.Event()
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self._thread = threading.Thread(target=self._replay, name='mmd-replay', daemon=True)
        self._thread.start()

    def _replay(self) -> None:
        try:
            self._replay_log()
        except Exception as exc:  # noqa: BLE001 - report it; the node then ends
            if self.context.ok():
                self.state, self.error = 'error', f'replay failed: {exc!r}'
                self.get_logger().error(self.error)
        if self.cfg['exit_when_done'] and self.context.ok():
            time.sleep(1.5)  # a last diagnostics report
            self.context.try_shutdown()

    def _replay_log(self) -> None:
        log, cfg = self.run_log, self.cfg
        t0 = int(log.stamps_ns[0]) if log.stamps_ns.size else self.get_clock().now().nanoseconds
        self.out_device.payload(string_bytes(log.device.to_yaml()), t0)
        if log.calibration is not None:
            self.out_calibration.payload(string_bytes(log.calibration.to_yaml()), t0)
        if log.model is not None:
            self.out_model.payload(string_bytes(log.model.to_yaml()), t0)
        deadline = time.monotonic() + cfg['wait_timeout_s']
        while self.out_raw.subscribers < cfg['wait_for_subscribers'] and time.monotonic() < deadline:
            if self._stop.wait(0.05):
                return
        self._stop.wait(cfg['start_delay_s'])
        self.state = 'replaying'
        self.get_logger().info(f'replaying {log.path}: {self.schedule.n} samples at rate '
                               f'{cfg["rate"]:g}' + (' (as fast as possible)' if self.schedule.fast else ''))
        ref = log.reference_pose if cfg['publish_reference'] else None
        for a, b in paced_batches(self.schedule, max_batch=64, stop=self._stop):
            stamps = log.stamps_ns[a:b]
            self.out_raw.rows(self.rows.raw.encode(stamps, log.counts[a:b]), stamps)
            if ref is not None:
                known = np.isfinite(ref[a:b]).any(axis=1)
                if known.any():
                    self.out_reference.rows(self.rows.reference.encode(stamps[known], ref[a:b][known]),
                                            stamps[known])
            self.sent = b
            if self.schedule.fast and b % 1024 < 64:
                self.out_raw.publisher.wait_for_all_acked(Duration(seconds=5))
        self.out_raw.publisher.wait_for_all_acked(Duration(seconds=10))
        self.state = 'done'
        self.get_logger().info(f'replay done: {self.sent} samples')

    def _report(self) -> list:
        problem = self.run_log.problem
        r = Report('replay', ERROR if self.error else WARN if problem else OK,
                   self.error or f'{self.state}: {self.run_log.path}'
                   + (f' (the log was not read whole: {problem.kind})' if problem else ''))
        r.values.update({'state': self.state, 'log': str(self.run_log.path), 'samples': self.schedule.n,
                         'sent': self.sent, 'rate': self.cfg['rate']})
        r.values.update(log_problem_values(problem))
        return [r]

    def destroy_node(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(ReplayNode, args)


if __name__ == '__main__':
    sys.exit(main())
