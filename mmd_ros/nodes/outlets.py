"""Where a stage's messages go: a ROS publisher and, inside ``pose_node``, the recorder.

An :class:`Outlet` is one topic. Per-sample topics are handed over as CDR rows of a whole
transfer (:class:`mmd_ros.nodes.convert.Rows`): each row is published as bytes and the same
rows go to the recorder's queue, so the log holds exactly the published bytes. Other messages
are published as objects and, for the recorder, serialised once.

Threading: rclpy publishers are thread-safe, but a process must not publish from a thread of
its own (the terminal reader) while it also *subscribes* to that topic: with rclpy's
EventsExecutor that deadlocks in ``publish``. The nodes never subscribe to what they publish
from a reader thread (``pose_node`` passes samples between its stages by direct calls).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message

from mmd_ros.logs.recorder import QueuedRecorder

__all__ = ['Outlet']


class Outlet:
    """One topic a node publishes (and records, when it has a recorder).

    node : the publishing node; topic : name relative to the node's namespace
    msg_cls : message class; type_name : 'package/msg/Type' for logs
    qos : QoS profile; log_qos : 'reliable', 'sensor' or 'latched' (what logs say was offered)
    recorder : record everything published here too (pose_node), or None
    """

    def __init__(self, node: Node, topic: str, msg_cls: Any, type_name: str, qos: QoSProfile,
                 log_qos: str = 'reliable', recorder: QueuedRecorder | None = None) -> None:
        self.publisher = node.create_publisher(msg_cls, topic, qos)
        self.topic = self.publisher.topic_name
        self.type_name = type_name
        self.log_qos = log_qos
        self.recorder = recorder
        self.published = 0

    def rows(self, rows: NDArray[np.uint8], stamps_ns: NDArray[np.int64]) -> None:
        """Publish N serialised messages (rows of equal size) stamped ``stamps_ns``."""
        n = rows.shape[0]
        if n == 0:
            return
        data = rows.tobytes()
        size = rows.shape[1]
        publish = self.publisher.publish
        for i in range(0, n * size, size):
            publish(data[i:i + size])
        self.published += n
        if self.recorder is not None:
            self.recorder.put_rows([(self.topic, self.type_name, rows)], stamps_ns, self.log_qos)

    def payload(self, data: bytes, stamp_ns: int) -> None:
        """Publish one serialised message."""
        self.publisher.publish(data)
        self.published += 1
        if self.recorder is not None:
            self.recorder.put_message(self.topic, self.type_name, stamp_ns, data, self.log_qos)

    def message(self, msg: Any, stamp_ns: int) -> None:
        """Publish one message object."""
        self.publisher.publish(msg)
        self.published += 1
        if self.recorder is not None:
            self.recorder.put_message(self.topic, self.type_name, stamp_ns,
                                      serialize_message(msg), self.log_qos)

    @property
    def subscribers(self) -> int:
        return self.publisher.get_subscription_count()
