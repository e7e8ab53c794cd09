"""Quality of service of the mmd topics, in one place (documented in ``msg_docs/nodes.md``).

- ``reliable`` (the default of every per-sample topic): reliable, volatile, keep last
  ``depth`` (1000 = one second at 1 kHz): nothing is lost while the reader keeps up, which is
  what a recorder or a compensation chain needs.
- ``sensor``: best effort, keep last 5 (``rclpy.qos.qos_profile_sensor_data``), for a live
  display that prefers the newest sample to a late one. A best-effort publisher is not heard by
  a reliable subscriber: set ``qos:=sensor`` on both sides.
- ``latched``: reliable, transient local, keep last 1, for the device description, the
  calibration, the model and counter-reset events: a late subscriber still gets the last one.
- ``/diagnostics``: reliable, keep last 100.
"""

from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data,
)

__all__ = ['DATA_QOS_KINDS', 'DIAGNOSTICS', 'LATCHED', 'data_qos']

DATA_QOS_KINDS = ('reliable', 'sensor')

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
DIAGNOSTICS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)


def data_qos(kind: str = 'reliable', depth: int = 1000) -> QoSProfile:
    """QoS of a per-sample topic: ``reliable`` with a queue of ``depth``, or ``sensor``."""
    if kind == 'sensor':
        return qos_profile_sensor_data
    if kind != 'reliable':
        raise ValueError(f'qos must be one of {DATA_QOS_KINDS}, got {kind!r}')
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
