"""The digital twin as the sample source of the simulated terminal: a small physical world.

:class:`TwinSource` is a :class:`~mmd_ros.hardware.source.SampleSource`: a
:class:`~mmd_ros.hardware.sim_backend.SimTerminal` asks it for the samples its 1 kHz clock
takes, and it answers with what the terminal's eight channels would count in a world where

- each **measuring bar** is either *mounted* between the plates (its length follows the
  machine's motion, a :class:`~mmd_ros.twin.Scenario` streamed by
  :meth:`~mmd_ros.twin.TwinDevice.stream`), *on a reference pair* of the reference plate
  (:meth:`~mmd_ros.twin.TwinDevice.counts_on_pair`), or *off* (lying still in its case);
- each **reference bar** rests on its pair, unless the operator puts it on another one;
- moving a bar takes ``transition_s``: its count travels smoothly to the new place and wobbles
  while it seats; :meth:`TwinSource.disturb` moves a bar that should stand still (a bar
  bumped during a capture).

The operator (a test, the demo, or a person through the ROS node's ``sim_command``
parameter) changes the world with :meth:`place`, :meth:`remove`, :meth:`hold`, :meth:`mount`
and :meth:`disturb`; a change takes effect at the next sample the terminal takes. The reference
instrument (the twin's ``pose6`` reading of the true pose, 1 nm / 0.1 arc-second noise) is
kept per sample and read back by device time with :meth:`reference_at`; it is NaN unless the
six measuring bars are mounted and seated. Everything runs on the twin's clock: sample k is
at ``start_s + k / rate`` seconds, device time ``k / rate``.

Simulation only: a real terminal has no such thing.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.calibration import BarCalibration, Calibration
from mmd_ros.hardware.source import SourceInfo
from mmd_ros.twin import AmbientProfile, Scenario, SimulatedRun, TwinDevice, TwinError
from mmd_ros.twin.physics import RESEATS

__all__ = ['TwinSource']

NS_PER_S = 1_000_000_000
#: Length a bar lying in its case reads [m] (anything within the range).
CASE_LENGTH_M = 0.3
#: How a bar is seated on a pair: the friction state of its guide ('' as it comes: the pair's).
#: Seated so, each placement of a bar on a pair is a seating of its own (the twin's seatings
#: 1..RESEATS in turn); as it comes, the bar's resting placement there (seating 0).
APPROACH_STATES: dict[str, float | None] = {'': None, 'short': 1.0, 'long': -1.0}
#: Wobble of a bar seating in its sockets: amplitude [m] and frequency [Hz].
SEAT_WOBBLE_M = 5e-6
SEAT_WOBBLE_HZ = 3.0
DISTURB_HZ = 2.0


@dataclass
class _Transition:
    start: int
    end: int
    origin: float  # count before the move [counts]


@dataclass
class _Disturbance:
    start: int
    end: int
    amplitude: float  # [counts]


class TwinSource:
    """The twin's world as a terminal sample source (see the module docstring).

    twin : the simulated device
    ambient : room temperature on the twin's clock
    scenario : what the machine does while the bars are mounted (restarted when it ends)
    start_s : the twin's clock at the terminal's power-on (sample 0) [s]
    mounted : the measuring bars start mounted (else off, in their case)
    transition_s : time a bar takes to move and seat [s]
    near_wrap_margin : 0, or start every counter this many counts below the 32-bit wrap
        (2^31 - 1), so that it wraps as soon as its bar moves
    block : samples computed at once (the world looks this far ahead, except after a change)
    history_s : how long reference readings are kept [s]
    """

    def __init__(self, twin: TwinDevice, ambient: AmbientProfile, scenario: Scenario, *,
                 start_s: float = 600.0, mounted: bool = True, transition_s: float = 0.5,
                 near_wrap_margin: int = 0, block: int = 200, history_s: float = 120.0) -> None:
        if transition_s < 0 or block < 1 or history_s <= 0:
            raise TwinError('need transition_s >= 0, block >= 1 and history_s > 0')
        self.twin = twin
        self.device = twin.device
        self.ambient = ambient
        self.scenario = scenario
        self.start_s = float(start_s)
        self.rate = float(self.device.sample_rate_hz)
        self.transition = int(round(transition_s * self.rate))
        self.block = int(block)
        names = self.device.channel_names
        self.names = names
        self._measuring = list(self.device.measuring_channels)
        self._resting = {c.index: c.pair for c in self.device.reference_channels}
        self._bars = self._measuring + list(self._resting)
        self._lock = threading.RLock()
        self._next = 0
        # world state per channel: 'mounted', 'off', a pair name (as it comes),
        # '<pair>@<short|long>' or 'length:<metres>'; and the twin's seating it is in
        self._state: dict[int, str] = {}
        self._seat: dict[int, int] = {}
        self._seatings: dict[tuple[int, str], int] = {}     # approach placements per bar, pair
        for c in self._measuring:
            self._state[c] = 'mounted' if mounted else 'off'
        self._state.update(self._resting)
        self._last = np.zeros(8)
        self._case = {c: float(self.twin.counts_for_lengths(c, [CASE_LENGTH_M], [self.start_s],
                                                            ambient)[0]) for c in self._measuring}
        self._transitions: dict[int, _Transition] = {}
        self._disturb: dict[int, _Disturbance] = {}
        self._cache: dict[int, tuple[int, NDArray[np.float64]]] = {}
        self._stream: Iterator[SimulatedRun] | None = None
        self._stream_k0 = 0
        self._stream_buf: list[tuple[int, SimulatedRun]] = []
        self._stream_at = 0  # first k not yet in the stream buffer
        self.restarts = 0
        cap = int(history_s * self.rate)
        self._ref_k = np.full(cap, -1, dtype=np.int64)
        self._ref = np.full((cap, 6), np.nan)
        self._epoch_k = 0
        self._reset_pending = False
        self.count_offset = np.zeros(8, dtype=np.int64)
        if mounted:
            self._start_stream(0)
        first = self._compose(0, 1, commit=False)
        self._last = first[0].copy()
        if near_wrap_margin:
            self.count_offset = ((1 << 31) - 1 - int(near_wrap_margin)
                                 - np.round(first[0]).astype(np.int64))

    # -- SampleSource --------------------------------------------------------------------------
    @property
    def info(self) -> SourceInfo:
        return SourceInfo(sample_rate_hz=self.rate, name=f'digital twin of {self.device.name} '
                          f'(seed {self.twin.seed}, {self.scenario.kind})')

    def twin_time(self, k: ArrayLike) -> NDArray[np.float64]:
        """The twin's clock at samples ``k`` [s]."""
        return self.start_s + np.asarray(k, dtype=np.float64) / self.rate

    def read(self, n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        with self._lock:
            k0 = self._next
            if self._reset_pending:  # the terminal restarts its clock at this read
                self._reset_pending = False
                self._epoch_k = k0
            values = self._compose(k0, k0 + int(n), commit=True)
            self._next = k0 + int(n)
            self._last = values[-1].copy()
            k = np.arange(k0, k0 + int(n), dtype=np.int64)
            t_ns = np.round(k * (NS_PER_S / self.rate)).astype(np.int64)
            return t_ns, np.round(values).astype(np.int64) + self.count_offset

    # -- the world -----------------------------------------------------------------------------
    def _channel(self, bar: str) -> int:
        if bar not in self.names or self.names.index(bar) not in self._bars:
            raise TwinError(f'no bar {bar!r}; bars are {[self.names[c] for c in self._bars]}')
        return self.names.index(bar)

    def _move(self, c: int, state: str, seat: int = 0) -> None:
        """Change channel c's state (and seating) from the next sample on (lock held)."""
        if self._state.get(c) == state and self._seat.get(c, 0) == seat:
            return
        self._state[c] = state
        self._seat[c] = seat
        self._transitions[c] = _Transition(self._next, self._next + self.transition, float(self._last[c]))
        self._cache.pop(c, None)

    def place(self, bar: str, pair: str, approach: str = '') -> None:
        """The operator puts ``bar`` on reference ``pair`` (taking it off the MMD if mounted):
        as it comes (its resting placement there), or seated from ``short`` or ``long`` (the
        friction state of its guide +1 or -1; each such placement seats it anew)."""
        c = self._channel(bar)
        self.device.pair(pair)
        if approach not in APPROACH_STATES:
            raise TwinError(f'approach must be short, long or empty, got {approach!r}')
        with self._lock:
            if not approach:
                self._move(c, pair)
                return
            n = self._seatings.get((c, pair), 0)
            self._seatings[(c, pair)] = n + 1
            self._move(c, f'{pair}@{approach}', 1 + n % RESEATS)

    def hold(self, bar: str, length_m: float) -> None:
        """The operator holds ``bar`` at a centre distance of ``length_m`` (for example beside a
        gauge, or beyond the calibrated range to see a sample refused) [m]."""
        c = self._channel(bar)
        if not 0.1 < length_m < 1.0:
            raise TwinError(f'length_m must be between 0.1 and 1 m, got {length_m}')
        with self._lock:
            self._move(c, f'length:{float(length_m)!r}')

    def remove(self, bar: str) -> None:
        """The operator takes ``bar`` off and lays it in its case."""
        c = self._channel(bar)
        with self._lock:
            self._move(c, 'off')

    def mount(self) -> None:
        """The six measuring bars go between the plates (the machine's motion starts if it had
        not yet); reference bars go back to their resting pairs."""
        with self._lock:
            if self._stream is None:
                self._start_stream(self._next)
            for c in self._measuring:
                self._move(c, 'mounted')
            for c, pair in self._resting.items():
                if self._state.get(c, 'off').partition('@')[0] != pair:  # one already there stays
                    self._move(c, pair)

    def disturb(self, bar: str, seconds: float = 3.0, amplitude_m: float = 20e-6) -> None:
        """Something moves ``bar`` for ``seconds``: its reading oscillates by ``amplitude_m``."""
        c = self._channel(bar)
        if not seconds > 0:
            raise TwinError(f'seconds must be > 0, got {seconds}')
        with self._lock:
            self._disturb[c] = _Disturbance(self._next, self._next + int(seconds * self.rate),
                                            amplitude_m / self.device.encoder_resolution_m)

    def where(self) -> dict[str, str]:
        """Where each bar is: 'mounted', 'off', a pair name or 'length:<m>'."""
        with self._lock:
            return {self.names[c]: s for c, s in self._state.items()}

    @property
    def samples_taken(self) -> int:
        return self._next

    def note_counter_reset(self) -> None:
        """The terminal restarts its clock at its next read (call with the terminal's lock held,
        so that this and :meth:`SimTerminal.reset_counters` are one step)."""
        with self._lock:
            self._reset_pending = True

    def reference_at(self, device_time_ns: ArrayLike) -> NDArray[np.float64]:
        """The reference instrument's reading (x y z roll pitch yaw [m, rad]) at samples of the
        given device times, shape (N, 6); NaN where unknown (bars not all mounted, or older
        than ``history_s``)."""
        t = np.asarray(device_time_ns, dtype=np.int64)
        with self._lock:
            k = np.round(t * (self.rate / NS_PER_S)).astype(np.int64) + self._epoch_k
            slot = k % self._ref_k.size
            hit = self._ref_k[slot] == k
            out = np.full((t.size, 6), np.nan)
            out[hit] = self._ref[slot[hit]]
            return out

    # -- the simulation ------------------------------------------------------------------------
    def _start_stream(self, k: int, *, keep: bool = False) -> None:
        """Start the scenario at sample k (``keep``: the samples of the previous run that are
        already computed stay in the buffer)."""
        start = float(self.twin_time(k))
        self._stream = self.twin.stream(self.scenario, self.ambient, start_s=start,
                                        reference='pose6', chunk_samples=self.block)
        self._stream_k0 = k
        if not keep:
            self._stream_buf = []
        self._stream_at = k

    def _stream_rows(self, k0: int, k1: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Counts (n, 8) and reference (n, 6) of the machine's motion at samples k0..k1-1,
        restarting the scenario when it ends."""
        assert self._stream is not None
        while self._stream_at < k1:
            try:
                chunk = next(self._stream)
            except StopIteration:
                self.restarts += 1
                self._start_stream(self._stream_at, keep=True)
                continue
            self._stream_buf.append((self._stream_at, chunk))
            self._stream_at += chunk.n_samples
        while self._stream_buf and self._stream_buf[0][0] + self._stream_buf[0][1].n_samples <= k0:
            self._stream_buf.pop(0)
        counts, reference = [], []
        for start, chunk in self._stream_buf:
            a = max(k0, start) - start
            b = min(k1, start + chunk.n_samples) - start
            if b > a:
                counts.append(chunk.counts[a:b])
                reference.append(chunk.reference[a:b])
        return np.concatenate(counts), np.concatenate(reference)

    def _base(self, c: int, k0: int, k1: int) -> NDArray[np.float64]:
        """Counts of channel c in its current state at samples k0..k1-1 (cached ahead)."""
        state = self._state.get(c, 'off')
        if state == 'off' or c not in self._bars:
            value = self._case.get(c, 0.0)
            return np.full(k1 - k0, value)
        cached = self._cache.get(c)
        if cached is not None and cached[0] <= k0 and cached[0] + cached[1].size >= k1:
            a = k0 - cached[0]
            return cached[1][a:a + k1 - k0]
        n = max(self.block, k1 - k0)
        times = self.twin_time(np.arange(k0, k0 + n))
        if state.startswith('length:'):
            length = float(state.split(':', 1)[1])
            values = self.twin.counts_for_lengths(c, np.full(n, length), times,
                                                  self.ambient).astype(np.float64)
        else:
            pair, _, approach = state.partition('@')
            values = self.twin.counts_on_pair(c, pair, times, self.ambient,
                                              approach=APPROACH_STATES[approach],
                                              seat=self._seat.get(c, 0)).astype(np.float64)
        self._cache[c] = (k0, values)
        return values[:k1 - k0]

    def _compose(self, k0: int, k1: int, *, commit: bool) -> NDArray[np.float64]:
        n = k1 - k0
        k = np.arange(k0, k1)
        out = np.zeros((n, 8))
        stream_counts = reference = None
        if self._stream is not None and any(self._state[c] == 'mounted' for c in self._measuring):
            stream_counts, reference = self._stream_rows(k0, k1)
        elif self._stream is not None and commit:
            self._stream_rows(k0, k1)  # the machine keeps moving while no bar is mounted
        seated = np.ones(n, dtype=bool)
        for c in range(8):
            state = self._state.get(c, 'off')
            if state == 'mounted':
                base = stream_counts[:, c].astype(np.float64)
            else:
                base = self._base(c, k0, k1)
                if c in self._measuring:
                    seated[:] = False
            tr = self._transitions.get(c)
            if tr is not None:
                if k0 >= tr.end:
                    if commit:
                        del self._transitions[c]
                else:
                    tau = np.clip((k - tr.start) / max(tr.end - tr.start, 1), 0.0, 1.0)
                    s = tau * tau * (3.0 - 2.0 * tau)
                    wobble = (SEAT_WOBBLE_M / self.device.encoder_resolution_m) * (1.0 - tau) * \
                        np.sin(2 * math.pi * SEAT_WOBBLE_HZ * (k - tr.start) / self.rate)
                    moving = k < tr.end
                    base = np.where(moving, tr.origin + (base - tr.origin) * s + wobble, base)
                    if c in self._measuring:
                        seated &= ~moving
            dis = self._disturb.get(c)
            if dis is not None:
                if k0 >= dis.end:
                    if commit:
                        del self._disturb[c]
                else:
                    active = (k >= dis.start) & (k < dis.end)
                    base = base + active * dis.amplitude * np.sin(
                        2 * math.pi * DISTURB_HZ * (k - dis.start) / self.rate)
                    if c in self._measuring:
                        seated &= ~active
            out[:, c] = base
        if commit:
            slot = k % self._ref_k.size
            self._ref_k[slot] = k
            if reference is not None:
                ref = reference.copy()
                ref[~seated] = np.nan
                self._ref[slot] = ref
            else:
                self._ref[slot] = np.nan
        return out

    # -- a factory calibration -----------------------------------------------------------------
    def factory_calibration(self, at_s: float | None = None) -> Calibration:
        """The twin's own calibration routine (section 3.2) run before power-on, in the counts
        this terminal reports (its counter offset included)."""
        at = self.start_s - 300.0 if at_s is None else float(at_s)
        cal = self.twin.calibrate(at, self.ambient)
        bars = {}
        for name, bar in cal.bars.items():
            off = float(self.count_offset[self.names.index(name)])
            bars[name] = BarCalibration(bar.channel, bar.pairs, tuple(c + off for c in bar.counts),
                                        bar.distances_m)
        return Calibration(device=cal.device, bars=bars, thermal_zero_m=dict(cal.thermal_zero_m),
                           ambient_c=cal.ambient_c, created=cal.created, valid=True,
                           uncertainty=cal.uncertainty,
                           quality={'source': f'factory calibration of the digital twin '
                                              f'(seed {self.twin.seed}) at t = {at:.0f} s'})
