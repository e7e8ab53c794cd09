"""Per-sample inputs that count what was lost, and the ``pipeline/progress`` topic.

Every node that takes a per-sample topic from another process subscribes through
:class:`CountedInputs`: each message's publisher sequence number (rclpy's message info) goes
through a :class:`~mmd_ros.core.flow.SequenceCounter`, so a message that the middleware dropped
(a reliable keep-last queue overrun by a reader that fell behind) is counted, reported in the
node's ``/diagnostics`` (WARN) and never goes unnoticed.

:class:`ProgressPublisher` publishes what the stage took and published on
``pipeline/progress`` (``diagnostic_msgs/DiagnosticStatus``: ``name`` the node, key/values of
:class:`~mmd_ros.core.flow.StageProgress`) about 20 times a second while samples flow, and
every 0.5 s otherwise; ``replay_node`` paces itself by it (:class:`~mmd_ros.core.flow.FlowControl`).
A replay names its run on the latched ``pipeline/run`` (``std_msgs/String``); the stage then
counts its inputs and outputs from zero for that run and says so in its reports.
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from std_msgs.msg import String
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from mmd_ros.core.flow import InputProgress, SequenceCounter, StageProgress
from mmd_ros.nodes.diagnostics import WARN, Events, Report
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.qos import LATCHED

__all__ = ['PROGRESS_QOS', 'PROGRESS_TOPIC', 'RUN_TOPIC', 'CountedInputs', 'ProgressPublisher',
           'with_message_info']

PROGRESS_TOPIC = 'pipeline/progress'
RUN_TOPIC = 'pipeline/run'
PROGRESS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)


class _WithInfo:
    """A subscription callback taking (message, message info) under every rclpy executor.

    rclpy gives a callback with two positional parameters the message info too; its
    ``EventsExecutor`` (rclpy 7.1.6, measured) then passes the (message, info) pair as one
    tuple argument, the other executors as two arguments. This accepts both.
    """

    __signature__ = inspect.Signature([
        inspect.Parameter('msg', inspect.Parameter.POSITIONAL_ONLY),
        inspect.Parameter('info', inspect.Parameter.POSITIONAL_ONLY)])

    def __init__(self, callback: Callable[[Any, dict[str, Any]], None]) -> None:
        self.callback = callback

    def __call__(self, *args: Any) -> None:
        if len(args) == 1:
            msg, info = args[0]
        else:
            msg, info = args
        self.callback(msg, info)


def with_message_info(callback: Callable[[Any, dict[str, Any]], None]) -> Callable[..., None]:
    """Wrap ``callback(msg, info)`` for ``create_subscription`` (see :class:`_WithInfo`)."""
    return _WithInfo(callback)


class CountedInputs:
    """A node's per-sample subscriptions, each with its :class:`SequenceCounter`."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.counters: dict[str, SequenceCounter] = {}
        self._subscriptions: dict[str, Any] = {}
        self._reported: dict[str, int] = {}
        self.events = Events()
        self.taken = 0
        #: called after every message taken (the progress publisher's prompt)
        self.on_taken: Callable[[], None] | None = None

    def subscribe(self, msg_cls: Any, topic: str, callback: Callable[[Any], None],
                  qos: QoSProfile) -> Any:
        """A raw subscription to ``topic`` whose messages are counted before ``callback``."""
        counter = SequenceCounter()
        name = self.node.resolve_topic_name(topic)
        self.counters[name] = counter

        def counted(payload: Any, info: dict[str, Any]) -> None:
            if counter.note(info.get('publication_sequence_number')):
                self._check_publishers(name)
            callback(payload)
            self.taken += 1
            if self.on_taken is not None:
                self.on_taken()

        sub = self.node.create_subscription(msg_cls, topic, with_message_info(counted), qos, raw=True)
        self._subscriptions[name] = sub
        return sub

    def _check_publishers(self, name: str) -> None:
        """A jump: with several publishers the numbers interleave and prove nothing."""
        if self._subscriptions[name].get_publisher_count() > 1:
            counter = self.counters[name]
            counter.ambiguous = True

    def progress(self) -> dict[str, InputProgress]:
        return {name: InputProgress.of(c, self._subscriptions[name].get_publisher_count())
                for name, c in self.counters.items()}

    def report(self, r: Report) -> None:
        """Add ``<topic>_received`` / ``_lost`` to a report; WARN (for 5 s) after new losses."""
        ns = self.node.get_namespace().rstrip('/') + '/'
        for name, c in self.counters.items():
            short = name[len(ns):] if name.startswith(ns) else name
            new = c.lost - self._reported.get(name, 0)
            self._reported[name] = c.lost
            if new:
                self.events.note(f'lost {name}', f'{new} message(s) of {name} lost before they '
                                 'reached this node (the publisher\'s sequence numbers jump): it fell '
                                 'behind by more than qos_depth; raise qos_depth or slow the replay', WARN)
            r.values[f'{short}_received'] = c.received
            r.values[f'{short}_lost'] = c.lost if c.supported and not c.ambiguous else 'unknown'
        self.events.apply(r)


class ProgressPublisher:
    """Publishes a stage's :class:`StageProgress` on ``pipeline/progress`` (module docstring).

    inputs : the stage's counted inputs; outputs : its per-sample outlets
    depth : queue depth of its inputs (a replay keeps at most half of it in flight)
    on_run : called when a replay begins a run, before the stage says it counts for it (and so
        before the replay sends the run's first sample): the stage starts its state afresh
    """

    def __init__(self, node: Node, inputs: CountedInputs, outputs: list[Outlet], depth: int,
                 period_s: float = 0.05, heartbeat_s: float = 0.5,
                 on_run: Callable[[], None] | None = None) -> None:
        self.node = node
        self.on_run = on_run
        self.depth = int(depth)
        self.inputs = inputs
        self.outputs = outputs
        self.heartbeat_s = heartbeat_s
        self.name = node.get_fully_qualified_name()
        self.publisher = node.create_publisher(DiagnosticStatus, PROGRESS_TOPIC, PROGRESS_QOS)
        self._last: StageProgress | None = None
        self._last_t = 0.0
        self.run = ''
        self._published_mark: dict[str, int] = {}
        node.create_subscription(String, RUN_TOPIC, self._on_run, LATCHED)
        self._taken_reported = 0
        # a busy stage may not get to its timer for a while: report from the input callbacks too
        self._prompt_every = max(8, min(256, self.depth // 4))
        inputs.on_taken = self._prompt
        self.timer = node.create_timer(period_s, self.publish)

    def _prompt(self) -> None:
        """A quarter of the queue taken since the last report: report now (a replay may be
        waiting for it)."""
        if self.inputs.taken - self._taken_reported >= self._prompt_every:
            self.publish()

    def _on_run(self, msg: String) -> None:
        """A replay begins a run: count from here."""
        if msg.data == self.run:
            return
        if self.on_run is not None:
            self.on_run()
        for counter in self.inputs.counters.values():
            counter.mark()
        self._published_mark = {o.topic: o.published for o in self.outputs}
        self.run = msg.data
        self.publish()

    def current(self) -> StageProgress:
        published = {o.topic: o.published for o in self.outputs}
        return StageProgress(self.name, self.inputs.progress(), published, self.depth, self.run,
                             {t: n - self._published_mark.get(t, 0) for t, n in published.items()})

    def publish(self) -> None:
        if not self.publisher.get_subscription_count():
            self._last = None  # no replay listens: nothing to say (and to spend on it)
            return
        now = time.monotonic()
        p = self.current()
        if p == self._last and now - self._last_t < self.heartbeat_s:
            return
        self._last, self._last_t = p, now
        self._taken_reported = self.inputs.taken
        self.publisher.publish(DiagnosticStatus(
            level=bytes([0]), name=self.name, message='progress',
            values=[KeyValue(key=k, value=v) for k, v in p.to_pairs()]))
