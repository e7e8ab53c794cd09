"""From the terminal's sample clock to ROS time (ROS-free).

The terminal stamps every sample with its own clock (``time_ns`` since power-on or the last
counter reset, ``msg_docs/usb_protocol.md``). A ROS stamp is ``device_time + offset``, where
the offset is the host (ROS, system) time at which the terminal's clock read zero, plus the
smallest transfer latency seen:

- at the first transfer, ``offset = arrival time - device time of its last sample`` (the last
  sample of a transfer is taken just before the transfer leaves the terminal);
- then the offset follows the minimum of that difference over the last ``window_s`` seconds
  (the transfers that were least delayed), which also tracks the drift between the two clocks.
  It moves by at most ``slew_ppm`` of the elapsed time, so stamps keep their spacing to a few
  microseconds per second and never go backwards; during the first ``window_s`` it may step by
  up to 40 % of a sample period per transfer, to converge quickly from a late first transfer;
- after a counter reset (the terminal's clock restarted) the offset is estimated again, and
  never placed so that the first new sample is stamped before the last old one plus a period.

Stamps are therefore the time each sample was taken, on the host clock, to within the USB
latency (well under a millisecond) — consistent from sample to sample to the terminal's
crystal, and comparable with stamps of other ROS data on the same host.
"""

from __future__ import annotations

import collections

import numpy as np
from numpy.typing import NDArray

__all__ = ['StampMapper']

NS_PER_S = 1_000_000_000


class StampMapper:
    """Maps device times [ns] to ROS stamps [ns since the epoch].

    period_ns : the sample period [ns] (1,000,000 at 1 kHz)
    slew_ppm : fastest change of the offset once converged [parts per million of elapsed time]
    window_s : span of the running minimum [s]
    """

    def __init__(self, period_ns: int, *, slew_ppm: float = 500.0, window_s: float = 5.0) -> None:
        self.period_ns = int(period_ns)
        self.slew = float(slew_ppm) * 1e-6
        self.window_ns = int(window_s * NS_PER_S)
        self.offset_ns: int | None = None
        self._started_ns = 0
        self._last_host = 0
        self._last_stamp: int | None = None
        self._new_epoch = False
        self._window: collections.deque[tuple[int, int]] = collections.deque()
        self.epochs = 0

    def new_epoch(self) -> None:
        """The terminal's clock restarted (counter reset): re-estimate the offset."""
        self._new_epoch = True
        self._window.clear()

    def map(self, device_ns: NDArray[np.int64], host_ns: int) -> NDArray[np.int64]:
        """Stamps of the samples of one transfer that arrived at host time ``host_ns``."""
        dev = np.asarray(device_ns, dtype=np.int64)
        if dev.size == 0:
            return dev.copy()
        c = int(host_ns) - int(dev[-1])
        if self.offset_ns is None or self._new_epoch:
            offset = c
            if self._last_stamp is not None:
                offset = max(offset, self._last_stamp + self.period_ns - int(dev[0]))
            self.offset_ns = offset
            self._started_ns = int(host_ns)
            self._new_epoch = False
            self.epochs += 1
            self._window.clear()
        else:
            w = self._window
            while w and w[-1][1] >= c:  # a monotonic deque: running minimum
                w.pop()
            w.append((int(host_ns), c))
            while w[0][0] < host_ns - self.window_ns:
                w.popleft()
            target = w[0][1]
            elapsed = max(0, int(host_ns) - self._last_host)
            step = self.slew * elapsed
            if host_ns - self._started_ns < self.window_ns:
                step = max(step, 0.4 * self.period_ns)
            delta = target - self.offset_ns
            self.offset_ns += int(max(-step, min(step, delta)))
        self._last_host = int(host_ns)
        stamps = dev + self.offset_ns
        self._last_stamp = int(stamps[-1])
        return stamps
