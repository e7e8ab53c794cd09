"""``recorder_node``: every mmd topic and ``/diagnostics`` into one MCAP log (rosbag2 layout).

Subscribes to the topics with ``raw=True`` and writes the CDR bytes exactly as they were
published (:class:`~mmd_ros.logs.recorder.Recorder`): log time and publish time are the
message's ``header.stamp`` (the receive time for ``std_msgs/String``). The latched device
description, calibration and model are in every file. Chunks are flushed and fsynced every
``flush_period_s``, so after a SIGKILL the log reads back up to the last flush; SIGINT and
SIGTERM close it cleanly (summary and indexes); rotation by size or time; a full disk stops
the recording with an error in ``/diagnostics`` and keeps what was written.
"""

from __future__ import annotations

import sys

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String

from mmd_ros.nodes.common import COMMON_PARAMS, NAMESPACE, run
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, HEADER, JS, POSE, POSE_COV, STRING
from mmd_ros.nodes.diagnostics import Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, ParameterError, declare
from mmd_ros.nodes.progress import CountedInputs, ProgressPublisher
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos
from mmd_ros.nodes.recorder_stage import RECORDER_PARAMS, RecorderConfig, RecorderStage, raw_writer

__all__ = ['RecorderNode', 'TOPICS', 'main']

#: Every topic of an mmd device (relative to its namespace): type and kind of QoS.
TOPICS: dict[str, tuple[type, str, str]] = {
    'device_description': (String, STRING, 'latched'),
    'calibration': (String, STRING, 'latched'),
    'model': (String, STRING, 'latched'),
    'terminal/counter_reset': (Header, HEADER, 'latched'),
    'terminal/info': (String, STRING, 'latched'),
    'raw_counts': (JointState, JS, 'data'),
    'reference/pose': (JointState, JS, 'data'),
    'reference/bar_lengths': (JointState, JS, 'data'),
    'bar_lengths': (JointState, JS, 'data'),
    'thermal': (JointState, JS, 'data'),
    'fk_status': (JointState, JS, 'data'),
    'pose': (PoseStamped, POSE, 'data'),
    'pose_with_covariance': (PoseWithCovarianceStamped, POSE_COV, 'data'),
    'machine/joint_states': (JointState, JS, 'data'),
    '/diagnostics': (DiagnosticArray, DIAGNOSTIC_ARRAY, 'diagnostics'),
}

PARAMS = [
    Param('topics', ' '.join(TOPICS), 'topics to record, space-separated, relative to the '
          'namespace (default: all of them)'),
]


class RecorderNode(Node):
    """Raw subscriptions → :class:`RecorderStage`."""

    def __init__(self) -> None:
        super().__init__('recorder_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + RECORDER_PARAMS + PARAMS)
        unknown = [t for t in v['topics'].split() if t not in TOPICS]
        if unknown:
            raise ParameterError(f'parameter topics: unknown {unknown}; known: {" ".join(TOPICS)}')
        self.stage = RecorderStage(RecorderConfig.from_values(v), self.get_fully_qualified_name(),
                                   self.get_logger())
        data = data_qos(v['qos'], v['qos_depth'])
        data_kind = 'sensor' if v['qos'] == 'sensor' else 'reliable'
        self.received = 0
        self.inputs = CountedInputs(self)
        for topic in v['topics'].split():
            cls, type_name, kind = TOPICS[topic]
            qos = {'latched': LATCHED, 'data': data, 'diagnostics': DIAGNOSTICS}[kind]
            log_qos = {'latched': 'latched', 'data': data_kind, 'diagnostics': 'reliable'}[kind]
            callback = raw_writer(self.stage.queue, self.get_clock(), self.resolve_topic_name(topic),
                                  type_name, log_qos, cls is not String, self._count)
            if kind == 'data':  # per-sample topics: losses counted, progress published
                self.inputs.subscribe(cls, topic, callback, qos)
            else:
                self.create_subscription(cls, topic, callback, qos, raw=True)
        self.out_diag = Outlet(self, '/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self.progress = ProgressPublisher(self, self.inputs, [], v['qos_depth'])

    def _report(self) -> list:
        r = self.stage.report()
        self.inputs.report(r)
        return [r]

    def _count(self) -> None:
        self.received += 1

    def destroy_node(self) -> None:
        self.stage.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(RecorderNode, args)


if __name__ == '__main__':
    sys.exit(main())
