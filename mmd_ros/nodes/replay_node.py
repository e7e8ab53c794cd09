"""``replay_node`` (and ``mmd replay``): a recorded log back onto the live topics.

Publishes the log's device description, its calibration (the last one in the log, as
``mmd process`` uses it) and its model on the latched topics, then every sample's
``raw_counts`` (and ``reference/pose`` when the log has one) with the recorded stamps, at the
original timing scaled by ``rate`` (0: as fast as possible), from a thread. The compensation and
kinematics nodes then recompute the poses from the log.

Flow control: every stage downstream (compensation, kinematics, calibration and recorder nodes)
says on ``pipeline/progress`` how far it got; the replay never lets a stage fall more than half
its queue (``qos_depth``) behind, so nothing is dropped: ``rate`` 0 runs as fast as the slowest
stage keeps up, and a rate the stages cannot follow is slowed down to what they can. At the end
it waits until every stage has taken everything and reports, per stage, what was received and
what was lost (the stages count losses from the publishers' sequence numbers).
Topics, parameters: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from mmd_ros.core.flow import FlowControl, StageProgress
from mmd_ros.logs.layout import read_run
from mmd_ros.logs.replay import ReplaySchedule, log_problem_values, paced_batches
from mmd_ros.nodes.common import COMMON_PARAMS, NAMESPACE, request_stop, run
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, JS, STRING, Rows, string_bytes
from mmd_ros.nodes.diagnostics import ERROR, OK, WARN, Diagnostics, Report
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, ParameterError, declare
from mmd_ros.nodes.progress import PROGRESS_QOS, PROGRESS_TOPIC, RUN_TOPIC
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
    Param('flow_control', True, 'never let a stage downstream (pipeline/progress) fall more than '
          'qos_depth / 2 samples behind: nothing is dropped, rate 0 runs as fast as the slowest '
          'stage keeps up'),
    Param('flow_timeout_s', 10.0, 'a stage that makes no progress for this long is no longer '
          'waited for (the summary says so) [s]', low=0.1, high=3600.0),
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
        self.seconds = 0.0
        self.held_s = 0.0
        self.summary: list[dict[str, object]] = []
        self._lock = threading.Lock()
        self.run_name = f'{self.get_fully_qualified_name()} {time.time_ns()}'
        self.out_run = Outlet(self, RUN_TOPIC, String, STRING, LATCHED, 'latched')
        self.flow = FlowControl(self.run_name, max(1, v['qos_depth'] // 2), v['flow_timeout_s'])
        self.create_subscription(DiagnosticStatus, PROGRESS_TOPIC, self._on_progress, PROGRESS_QOS)
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
            # ... delivered: a subscriber still busy with the flood of samples has not taken it
            # yet, and a reliable message not acknowledged is gone with its publisher
            self.out_diag.publisher.wait_for_all_acked(Duration(seconds=10))
            request_stop()

    def _on_progress(self, msg: DiagnosticStatus) -> None:
        progress = StageProgress.from_pairs(msg.name, [(kv.key, kv.value) for kv in msg.values])
        with self._lock:
            self.flow.note_progress(progress)

    def _flow(self, batch: int | None) -> bool:
        """Update what was sent; True while a stage would fall too far behind with ``batch``
        more samples, or (``batch`` None) until every stage took everything."""
        with self._lock:
            self.flow.note_sent(self.out_raw.topic, self.out_raw.published)
            self.flow.note_sent(self.out_reference.topic, self.out_reference.published)
            if batch is not None:
                return bool(self.flow.waiting_for(batch))
            return not self.flow.drained()

    def _wait_for_stages(self, deadline: float, settle_s: float = 3.5, others_s: float = 5.0) -> None:
        """Until every stage publishing progress has been heard from, counts for this run (it
        heard ``pipeline/run``) and, if it takes raw_counts or reference/pose, is matched with
        this node's publisher; and no new stage appeared for ``settle_s`` (discovery of the
        other processes takes 2–3 s, more on a loaded machine, where a stage discovered after
        2 s was counted only from then and its samples reported lost). A subscriber of
        raw_counts that is no stage (one that never reports) is waited for ``others_s`` at
        most."""
        own = [self.out_raw.topic, self.out_reference.topic]
        known, since, settled_at = -1, time.monotonic(), None
        while time.monotonic() < deadline:
            with self._lock:
                heard, ready = len(self.flow.stages), self.flow.ready(own)
                readers = self.flow.readers(self.out_raw.topic)
            count = max(heard, self.count_publishers(PROGRESS_TOPIC))
            now = time.monotonic()
            if count != known:
                known, since, settled_at = count, now, None
            elif heard >= count and ready and now - since >= settle_s:
                settled_at = settled_at or now
                if readers >= self.out_raw.subscribers or now - settled_at >= others_s:
                    return
            if self._stop.wait(0.05):
                return

    def _replay_log(self) -> None:
        log, cfg = self.run_log, self.cfg
        t0 = int(log.stamps_ns[0]) if log.stamps_ns.size else self.get_clock().now().nanoseconds
        self.out_device.payload(string_bytes(log.device.to_yaml()), t0)
        if log.calibration is not None:
            self.out_calibration.payload(string_bytes(log.calibration.to_yaml()), t0)
        if log.model is not None:
            self.out_model.payload(string_bytes(log.model.to_yaml()), t0)
        self.out_run.payload(string_bytes(self.run_name), t0)
        deadline = time.monotonic() + cfg['wait_timeout_s']
        while self.out_raw.subscribers < cfg['wait_for_subscribers'] and time.monotonic() < deadline:
            if self._stop.wait(0.05):
                return
        self._stop.wait(cfg['start_delay_s'])
        flow = cfg['flow_control']
        self._wait_for_stages(max(deadline, time.monotonic() + 2.0))
        with self._lock:
            self.flow.begin([self.out_raw.topic, self.out_reference.topic])
        self.state = 'replaying'
        self.get_logger().info(f'replaying {log.path}: {self.schedule.n} samples at rate '
                               f'{cfg["rate"]:g}' + (' (as fast as possible)' if self.schedule.fast else '')
                               + (f', paced by {len(self.flow.counting())} stage(s)' if flow else ''))
        ref = log.reference_pose if cfg['publish_reference'] else None
        started = time.monotonic()
        batch = self.flow.batch(64) if flow else 64
        with self._lock:
            paced = bool(self.flow.counting())
        for a, b in paced_batches(self.schedule, max_batch=batch, stop=self._stop):
            if flow and self._flow(b - a):
                held = time.monotonic()
                while self._flow(b - a) and not self._stop.wait(0.001):
                    pass
                self.held_s += time.monotonic() - held
            stamps = log.stamps_ns[a:b]
            # a sample the terminal flagged goes out as it was recorded: codes in ``effort``
            for rows, part in self.rows.raw_parts(stamps, log.counts[a:b],
                                                  None if log.status is None else log.status[a:b]):
                self.out_raw.rows(rows, part)
            if ref is not None:
                known = np.isfinite(ref[a:b]).any(axis=1)
                if known.any():
                    self.out_reference.rows(self.rows.reference.encode(stamps[known], ref[a:b][known]),
                                            stamps[known])
            self.sent = b
            if (not flow or not paced) and self.schedule.fast and b % 1024 < 64:
                # no stage to pace by: at least let every subscriber acknowledge
                self.out_raw.publisher.wait_for_all_acked(Duration(seconds=5))
        self.seconds = time.monotonic() - started
        self.out_raw.publisher.wait_for_all_acked(Duration(seconds=10))
        while self._flow(None) and not self._stop.wait(0.01):
            pass
        with self._lock:
            self.summary = self.flow.summary()
        self.state = 'done'
        lost = sum(int(r['lost']) + int(r['missing']) for r in self.summary)  # type: ignore[call-overload]
        text = (f'replay done: {self.sent} samples sent in {self.seconds:.1f} s'
                + (f' ({self.held_s:.1f} s waiting for the stages)' if self.held_s > 0.05 else ''))
        if self.summary:
            text += '; ' + FlowControl.describe(self.summary)
        (self.get_logger().warn if lost else self.get_logger().info)(text)

    def _report(self) -> list:
        problem = self.run_log.problem
        r = Report('replay', ERROR if self.error else OK, self.error or f'{self.state}: {self.run_log.path}')
        if problem:
            r.worse(WARN, f'{self.state}: {self.run_log.path} (the log was not read whole: {problem.kind})')
        rows = self.summary
        lost = sum(int(row['lost']) + int(row['missing']) for row in rows)  # type: ignore[call-overload]
        if lost:
            r.worse(WARN, f'{lost} sample(s) did not reach a stage: ' + FlowControl.describe(rows))
        elif rows and not problem:
            r.message = f'{self.state}: every stage received every sample ({FlowControl.describe(rows)})'
        r.values.update({'state': self.state, 'run': self.run_name, 'log': str(self.run_log.path),
                         'samples': self.schedule.n,
                         'sent': self.sent, 'rate': self.cfg['rate'],
                         'seconds': round(self.seconds, 3), 'held_s': round(self.held_s, 3),
                         'stages': len({row['stage'] for row in rows}), 'lost': lost})
        r.values.update(log_problem_values(problem))
        for row in rows:
            key = f'{row["stage"]} {row["topic"]}'
            r.values[f'{key} published'] = row['published'] if row['published'] is not None else -1
            r.values[f'{key} received'] = row['received']
            r.values[f'{key} lost'] = int(row['lost']) + int(row['missing'])  # type: ignore[call-overload]
        return [r]

    def destroy_node(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(ReplayNode, args)


if __name__ == '__main__':
    sys.exit(main())
