"""Where a simulated terminal's samples come from: the :class:`SampleSource` protocol.

The simulated terminal (:mod:`mmd_ros.hardware.sim_backend`) asks its source for the next n
samples whenever its sample clock ticks, and frames them exactly as the hardware would
(32-bit wrapping counters, sequence numbers, status bits, CRC). Anything with ``info`` and
``read(n)`` can stand behind it: :class:`SyntheticSource` below for tests, the digital twin of
the device for system tests.

Plugging in a source::

    class TwinSource:
        info = SourceInfo(sample_rate_hz=1000.0, name='digital twin')
        def read(self, n):
            t_ns, counts = ...   # (n,) int64 [ns], (n, 8) int64 unwrapped [counts]
            return t_ns, counts

    backend = SimUsbBackend(SimTerminal(TwinSource(), serial='TWIN-01'))
    with TerminalDriver(backend=backend) as drv:
        batch = drv.read_batch()
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.hardware.protocol import N_CHANNELS

__all__ = ['SampleSource', 'SourceInfo', 'SyntheticSource']

NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class SourceInfo:
    """What a sample source produces.

    sample_rate_hz : float — the rate its timestamps follow [Hz]; the simulated terminal paces
        its sample clock at this rate
    n_channels : int — always 8 for this terminal
    name : str — for logs and diagnostics
    """

    sample_rate_hz: float = 1000.0
    n_channels: int = N_CHANNELS
    name: str = 'source'


@runtime_checkable
class SampleSource(Protocol):
    """The samples a simulated terminal frames and sends.

    ``read(n)`` returns the next ``n`` samples, in order, as ``(device_time_ns, counts)``:

    device_time_ns : ndarray, shape (n,), int64 — the terminal clock at each sample [ns],
        strictly increasing, non-negative
    counts : ndarray, shape (n, 8), int64 — **unwrapped** encoder counts [counts]; the terminal
        truncates them to its 32-bit wrapping counters when it frames them

    The terminal calls ``read`` from the thread that reads it over USB, with n between 1 and a
    few thousand (more after a long idle period, when a paced terminal catches up on the
    samples its clock took). Optionally a source has ``set_sample_rate(rate_hz: float)``; a
    terminal whose source lacks it refuses SET_SAMPLE_RATE with BAD_ARGUMENT.
    """

    @property
    def info(self) -> SourceInfo: ...

    def read(self, n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]: ...


class SyntheticSource:
    """Deterministic sinusoidal counts with a linear drift, a known truth for tests.

    Sample k (k = 0, 1, ...) is taken at ``t_k = start_time_ns + k / rate`` and channel c reads
    ``round(amplitude[c] * sin(2 pi frequency[c] t_k + phase[c])) + drift[c] * k + offset[c]``.

    sample_rate_hz : float — [Hz]
    amplitude_counts, frequency_hz, phase_rad, drift_counts_per_sample, offset_counts :
        array_like, shape (8,) or scalar — per channel
    start_time_ns : int — device time of sample 0 [ns]
    """

    def __init__(self, sample_rate_hz: float = 1000.0, *,
                 amplitude_counts: ArrayLike = (20_000, 40_000, 60_000, 80_000, 100_000, 120_000,
                                                5_000, 0),
                 frequency_hz: ArrayLike = (0.5, 0.7, 1.1, 1.3, 1.7, 1.9, 0.1, 0.0),
                 phase_rad: ArrayLike = (0.0, 0.4, 0.8, 1.2, 1.6, 2.0, 2.4, 0.0),
                 drift_counts_per_sample: ArrayLike = (0, 1, -1, 3, -3, 7, 0, 0),
                 offset_counts: ArrayLike = 0,
                 start_time_ns: int = 1_000_000_000) -> None:
        if not (sample_rate_hz > 0 and math.isfinite(sample_rate_hz)):
            raise ValueError(f'sample_rate_hz must be positive and finite, got {sample_rate_hz}')
        shape = (N_CHANNELS,)
        self.amplitude = np.broadcast_to(np.asarray(amplitude_counts, np.float64), shape).copy()
        self.frequency = np.broadcast_to(np.asarray(frequency_hz, np.float64), shape).copy()
        self.phase = np.broadcast_to(np.asarray(phase_rad, np.float64), shape).copy()
        self.drift = np.broadcast_to(np.asarray(drift_counts_per_sample, np.int64), shape).copy()
        self.offset = np.broadcast_to(np.asarray(offset_counts, np.int64), shape).copy()
        self._rate = float(sample_rate_hz)
        self._start_ns = int(start_time_ns)
        # a rate change starts a new segment: sample k >= k0 is at t0 + (k - k0) / rate
        self._k0 = 0
        self._t0_ns = int(start_time_ns)
        self._next = 0

    @property
    def info(self) -> SourceInfo:
        return SourceInfo(sample_rate_hz=self._rate, name='synthetic sinusoids')

    @property
    def samples_read(self) -> int:
        """Number of samples handed out so far (index of the next one)."""
        return self._next

    def set_sample_rate(self, rate_hz: float) -> None:
        """Change the rate from the next sample on (time stays continuous)."""
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f'rate_hz must be positive and finite, got {rate_hz}')
        self._t0_ns = int(self.time_at(np.array([self._next]))[0])
        self._k0 = self._next
        self._rate = float(rate_hz)

    def time_at(self, k: ArrayLike) -> NDArray[np.int64]:
        """Device time of samples ``k`` [ns] (for samples of the current rate segment)."""
        k = np.asarray(k, np.int64)
        return self._t0_ns + np.round((k - self._k0) * (NS_PER_S / self._rate)).astype(np.int64)

    def counts_at(self, k: ArrayLike) -> NDArray[np.int64]:
        """Unwrapped counts of samples ``k``, shape (len(k), 8) [counts]."""
        k = np.atleast_1d(np.asarray(k, np.int64))
        t_s = (self.time_at(k) - self._start_ns) * 1e-9
        wave = self.amplitude * np.sin(2 * np.pi * self.frequency * t_s[:, None] + self.phase)
        return np.round(wave).astype(np.int64) + self.drift * k[:, None] + self.offset

    def read(self, n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        k = np.arange(self._next, self._next + int(n), dtype=np.int64)
        self._next += int(n)
        return self.time_at(k), self.counts_at(k)
