"""The transport interface: whatever delivers terminal samples to the rest of mmd_ros.

Three things stand behind it: :class:`~mmd_ros.hardware.driver.TerminalDriver` on a real
terminal (pyusb, libusb), the same driver on a simulated terminal
(:class:`~mmd_ros.hardware.sim_backend.SimUsbBackend`), and a replayed log. A consumer (the
driver node, a recorder, the CLI) is written against :class:`Transport` only and never learns
which one it has.

A log replayer that stores each transfer's ``SampleBatch.raw`` bytes can feed them back
through :class:`~mmd_ros.hardware.stream.FrameStream` and get the same batches, gaps, resets
and statistics as the live stream gave.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from mmd_ros.hardware.protocol import DeviceInfo
from mmd_ros.hardware.stream import DriverStats, SampleBatch

__all__ = ['Transport']


@runtime_checkable
class Transport(Protocol):
    """A source of :class:`SampleBatch` es.

    ``open()`` connects, starts the stream and returns the terminal's :class:`DeviceInfo`.
    ``read_batch(timeout)`` blocks for at most ``timeout`` seconds (a transport default when
    None) and returns the next batch, possibly empty; it raises
    :class:`~mmd_ros.hardware.errors.TerminalTimeoutError` when nothing arrived in time and
    :class:`~mmd_ros.hardware.errors.TerminalDisconnectedError` when the source went away
    (a replayed log that ended raises ``EOFError``). ``close()`` stops the stream and frees
    the device; it is safe to call twice. ``stats`` is a snapshot of the counters.

    One thread reads; stop it before calling ``close()`` from another.
    """

    def open(self) -> DeviceInfo: ...

    def close(self) -> None: ...

    def read_batch(self, timeout: float | None = None) -> SampleBatch: ...

    @property
    def stats(self) -> DriverStats: ...
