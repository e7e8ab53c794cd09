"""``/diagnostics`` as ``diagnostic_msgs/DiagnosticArray`` at about 1 Hz, in diagnostic_updater's style.

Each stage of a node provides its status as a :class:`Report`: a level (OK, WARN, ERROR), a
one-line message and key/value pairs (numbers with their unit in the key). Status names are
``<node's full name>: <task>`` (for example ``/mmd/pose_node: terminal``); ``hardware_id`` is
the terminal's serial number. Faults are events: :class:`Events` keeps each one for
``hold_s`` seconds so that a 1 Hz report cannot miss it, while the cumulative counters
(``crc_errors``, ``missing_samples``...) keep the whole history.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from mmd_ros.nodes.convert import header
from mmd_ros.nodes.outlets import Outlet

__all__ = ['ERROR', 'Events', 'OK', 'Report', 'STALE', 'WARN', 'Diagnostics']

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        if math.isnan(value):
            return 'nan'
        return f'{value:.6g}'
    return str(value)


@dataclass
class Report:
    """One status: task name, level, message and key/value pairs."""

    task: str
    level: int = OK
    message: str = 'ok'
    values: dict[str, Any] = field(default_factory=dict)

    def worse(self, level: int, message: str) -> None:
        """Raise the level to ``level`` (messages of the worst level win, joined)."""
        if level > self.level:
            self.level, self.message = level, message
        elif level == self.level and level > OK and message not in self.message:
            self.message = f'{self.message}; {message}'

    def to_msg(self, prefix: str, hardware_id: str) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=bytes([self.level]), name=f'{prefix}: {self.task}', message=self.message,
            hardware_id=hardware_id,
            values=[KeyValue(key=k, value=_text(v)) for k, v in self.values.items()])


class Events:
    """Recent fault events, each reported for ``hold_s`` seconds after it happened."""

    def __init__(self, hold_s: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.hold_s = hold_s
        self._clock = clock
        self._events: dict[str, tuple[float, int, str]] = {}

    def note(self, key: str, message: str, level: int = WARN) -> None:
        self._events[key] = (self._clock(), level, message)

    def apply(self, report: Report) -> None:
        now = self._clock()
        for key, (t, level, message) in list(self._events.items()):
            if now - t > self.hold_s:
                del self._events[key]
            else:
                report.worse(level, message)


class Diagnostics:
    """Publishes the reports of a node's stages on /diagnostics every ``period_s``."""

    def __init__(self, node: Node, outlet: Outlet, providers: list[Callable[[], list[Report]]],
                 period_s: float = 1.0, hardware_id: Callable[[], str] = lambda: '') -> None:
        self.node = node
        self.outlet = outlet
        self.providers = providers
        self.prefix = node.get_fully_qualified_name()
        self.hardware_id = hardware_id
        self.last: list[Report] = []
        self.timer = node.create_timer(period_s, self.publish)

    def publish(self) -> None:
        reports: list[Report] = []
        for provider in self.providers:
            try:
                reports.extend(provider())
            except Exception as exc:  # noqa: BLE001 - a broken report must not stop the others
                reports.append(Report('diagnostics', ERROR, f'report failed: {exc!r}'))
        self.last = reports
        stamp = self.node.get_clock().now().nanoseconds
        hw = self.hardware_id()
        msg = DiagnosticArray(header=header(stamp),
                              status=[r.to_msg(self.prefix, hw) for r in reports])
        self.outlet.message(msg, stamp)
