"""A simulated encoder terminal behind the real pyusb API, with fault injection.

No virtual USB device can be made in this kernel, so the simulation sits at pyusb's backend
layer: :class:`SimUsbBackend` is a :class:`usb.backend.IBackend` and ``usb.core.find(...,
backend=SimUsbBackend(...))`` returns a real :class:`usb.core.Device` whose descriptors, string
descriptors, ``set_configuration``, interface claims and bulk transfers are served by
:class:`SimTerminal`, a model of the terminal's firmware (``msg_docs/usb_protocol.md``).

The terminal is self-powered (24 V supply): its sample clock, sequence numbers and counters run
from power-on, whether or not it streams or is plugged in. Samples come from a pluggable
:class:`~mmd_ros.hardware.source.SampleSource`.

Two timings:

- ``paced=True``: the sample clock follows the wall clock at the sample rate; a transfer is sent
  when ``frames_per_transfer`` frames are queued (8 ms at 1 kHz by default). Samples taken while
  not streaming are not sent; a full FIFO discards new samples and flags FIFO_OVERFLOW.
- ``paced=False``: "as fast as possible" for tests; every bulk read of the sample endpoint takes
  as many new samples as fit in the host's buffer, immediately.

Faults (thread-safe; may be called while another thread reads): :meth:`SimTerminal.unplug` /
:meth:`~SimTerminal.plug`, :meth:`~SimTerminal.corrupt_frames`, :meth:`~SimTerminal.drop_frames`,
:meth:`~SimTerminal.preset_counters` / :meth:`~SimTerminal.start_near_wrap`,
:meth:`~SimTerminal.reset_counters`, :meth:`~SimTerminal.stall` / :meth:`~SimTerminal.resume`,
:meth:`~SimTerminal.set_signal_lost`, :meth:`~SimTerminal.set_quadrature_error`.
"""

from __future__ import annotations

import array
import errno
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import usb.backend
import usb.core
from numpy.typing import ArrayLike, NDArray

from mmd_ros.hardware.errors import ProtocolError
from mmd_ros.hardware.protocol import (
    EP_COMMAND_OUT, EP_REPLY_IN, EP_SAMPLES_IN, FLAG_COUNTER_RESET, FLAG_FIFO_OVERFLOW,
    FRAME_DTYPE, FRAME_SIZE, INTERFACE_NUMBER, MAX_FRAMES_PER_TRANSFER, MAX_SAMPLE_RATE_HZ,
    N_CHANNELS, PRODUCT_ID, VENDOR_ID, DeviceInfo, Opcode, Status,
    decode_command, encode_frames, encode_info, encode_reply,
)
from mmd_ros.hardware.source import SampleSource, SyntheticSource

__all__ = ['SimTerminal', 'SimUsbBackend']

# libusb error codes and the errno pyusb's libusb1 backend gives with them
_LIBUSB_ERRORS = {
    'NO_DEVICE': (-4, errno.ENODEV, 'No such device (it may have been disconnected)'),
    'TIMEOUT': (-7, errno.ETIMEDOUT, 'Operation timed out'),
    'PIPE': (-9, errno.EPIPE, 'Pipe error'),
    'BUSY': (-6, errno.EBUSY, 'Resource busy'),
    'NOT_FOUND': (-5, errno.ENOENT, 'Entity not found'),
    'INVALID_PARAM': (-2, errno.EINVAL, 'Invalid parameter'),
    'OVERFLOW': (-8, errno.EOVERFLOW, 'Overflow'),
}


def _usb_error(kind: str) -> usb.core.USBError:
    code, err, text = _LIBUSB_ERRORS[kind]
    cls = usb.core.USBTimeoutError if kind == 'TIMEOUT' else usb.core.USBError
    return cls(text, code, err)


class _Descriptor:
    """A USB descriptor as pyusb's backends return it: fields as attributes."""

    def __init__(self, **fields: Any) -> None:
        self.__dict__.update(fields)


# Descriptor layout (one configuration, one vendor-specific interface, three bulk endpoints)
_STRINGS = {1: 'manufacturer', 2: 'product', 3: 'serial', 4: 'interface'}
_ENDPOINTS = (EP_SAMPLES_IN, EP_COMMAND_OUT, EP_REPLY_IN)
_BULK_PACKET = 512  # high-speed bulk
_CONFIG_TOTAL_LENGTH = 9 + 9 + 7 * len(_ENDPOINTS)


@dataclass
class _Handle:
    """An open device handle: dead once its terminal was unplugged (other generation)."""

    terminal: SimTerminal
    generation: int
    closed: bool = False


@dataclass(frozen=True)
class _DeviceId:
    """The backend's opaque device identification (libusb_device)."""

    terminal: SimTerminal
    generation: int


class SimTerminal:
    """Model of the 8-channel encoder terminal's firmware, USB side included.

    source : SampleSource | None — samples to send (a :class:`SyntheticSource` when omitted)
    serial : str — USB serial number string and GET_INFO serial (<= 16 ASCII characters)
    paced : bool — follow the wall clock (True) or produce as fast as the host reads (False)
    sample_rate_hz : int | None — initial rate [Hz] (the source's rate when omitted)
    frames_per_transfer : int — frames the terminal collects before it sends a transfer
    fifo_frames : int — capacity of the terminal's frame FIFO
    power_on_reset : bool — frames carry COUNTER_RESET from power-on until CLEAR_RESET_FLAG
    counter_offset : array_like, shape (8,) or scalar — added to the source's counts before
        they are truncated to 32 bits [counts]
    record : bool — keep the sequence numbers of all frames put on the wire (``delivered_seqs``)
    clock : callable — monotonic clock [s] (tests may pass a fake)
    """

    def __init__(self, source: SampleSource | None = None, *, serial: str = 'MMD-SIM-0001',
                 paced: bool = True, sample_rate_hz: int | None = None,
                 frames_per_transfer: int = 8, fifo_frames: int = 4096,
                 power_on_reset: bool = True, counter_offset: ArrayLike = 0,
                 vendor: str = 'MMD Lab', model: str = 'MMD-ET8', firmware: str = '1.0.0-sim',
                 vendor_id: int = VENDOR_ID, product_id: int = PRODUCT_ID, bus: int = 1,
                 port: int = 1, record: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.source: SampleSource = source if source is not None else SyntheticSource()
        for key, text in (('serial', serial), ('vendor', vendor), ('model', model),
                          ('firmware', firmware)):
            if len(text.encode('ascii')) > 16:
                raise ValueError(f'{key} "{text}" is longer than 16 ASCII characters')
        if not 1 <= frames_per_transfer <= MAX_FRAMES_PER_TRANSFER:
            raise ValueError(f'frames_per_transfer must be 1..{MAX_FRAMES_PER_TRANSFER}, '
                             f'got {frames_per_transfer}')
        rate = sample_rate_hz if sample_rate_hz is not None else self.source.info.sample_rate_hz
        if not 1 <= rate <= MAX_SAMPLE_RATE_HZ or rate != int(rate):
            raise ValueError(f'sample rate must be an integer 1..{MAX_SAMPLE_RATE_HZ} Hz, got {rate}')
        if sample_rate_hz is not None and rate != self.source.info.sample_rate_hz:
            self._source_set_rate(int(rate))
        self.serial, self.vendor, self.model, self.firmware = serial, vendor, model, firmware
        self.vendor_id, self.product_id = int(vendor_id), int(product_id)
        self.bus, self.port = int(bus), int(port)
        self.paced = bool(paced)
        self.fifo_frames = int(fifo_frames)
        self._clock = clock
        self._cond = threading.Condition()
        # USB state
        self._plugged = True
        self._generation = 0
        self.address = 2
        self._configuration = 0
        self._claimed_by: _Handle | None = None
        self._replies: deque[bytes] = deque(maxlen=16)
        # firmware state
        self._rate = int(rate)
        self._fpt = int(frames_per_transfer)
        self._streaming = False
        self._fifo = bytearray()
        self._seq_next = 0
        self._count_offset = np.broadcast_to(np.asarray(counter_offset, np.int64), (N_CHANNELS,)).copy()
        self._time_offset = 0
        self._reset_flag = bool(power_on_reset)
        self._pending_reset = False
        self._pending_preset: NDArray[np.int64] | None = None
        self._overflow_pending = False
        self._drop_remaining = 0
        self._corrupt_remaining = 0
        self._corrupt_offset = 20
        self._stalled = False
        self._signal_lost = 0
        self._quadrature = 0
        self._origin = clock()
        self._taken_at_origin = 0
        self._taken = 0
        # observation
        self.record = bool(record)
        self.delivered_seqs: list[int] = []
        self.frames_sent = 0
        self.frames_dropped_by_fault = 0
        self.frames_corrupted = 0
        self.frames_lost_to_overflow = 0
        self.commands: list[tuple[int, int, int]] = []  # (opcode, arg, status)

    # ------------------------------------------------------------------ observation
    @property
    def plugged(self) -> bool:
        return self._plugged

    @property
    def streaming(self) -> bool:
        return self._streaming

    @property
    def sample_rate_hz(self) -> int:
        return self._rate

    @property
    def frames_per_transfer(self) -> int:
        return self._fpt

    @property
    def reset_flag(self) -> bool:
        """The sticky COUNTER_RESET flag (set at power-on and by a counter reset)."""
        return self._reset_flag

    @property
    def next_seq(self) -> int:
        """Sequence number the next sample will get."""
        return self._seq_next

    @property
    def samples_taken(self) -> int:
        """Samples read from the source so far (sent or not)."""
        return self._taken

    def info(self) -> DeviceInfo:
        """The terminal's GET_INFO answer."""
        return DeviceInfo(vendor=self.vendor, model=self.model, serial=self.serial,
                          firmware=self.firmware, frames_per_transfer=self._fpt,
                          sample_rate_hz=self._rate)

    # ------------------------------------------------------------------ faults
    def unplug(self) -> None:
        """Pull the cable: the device leaves the bus.

        Every transfer on an open handle now fails with ``usb.core.USBError`` errno ENODEV
        (libusb's LIBUSB_ERROR_NO_DEVICE), a blocked read wakes up with it, and
        ``usb.core.find`` no longer lists the device. Frames still queued in the terminal are
        lost. The terminal keeps sampling (it is self-powered).
        """
        with self._cond:
            self._advance()
            self._plugged = False
            self._generation += 1
            self._usb_reset()
            self._cond.notify_all()

    def plug(self) -> None:
        """Plug the cable back in: the device enumerates again, with a new address, unconfigured
        and not streaming (as after any USB reset). Counters and sequence numbers have run on."""
        with self._cond:
            if self._plugged:
                return
            self._advance()
            self._plugged = True
            self.address = self.address % 126 + 2
            self._cond.notify_all()

    def corrupt_frames(self, count: int = 1, byte_offset: int = 20) -> None:
        """Flip one byte (XOR 0xFF, at ``byte_offset`` in the frame) of each of the next
        ``count`` frames put on the wire: their CRC no longer matches."""
        if not 0 <= byte_offset < FRAME_SIZE:
            raise ValueError(f'byte_offset must be 0..{FRAME_SIZE - 1}, got {byte_offset}')
        with self._cond:
            self._corrupt_remaining += int(count)
            self._corrupt_offset = int(byte_offset)

    def drop_frames(self, count: int = 1) -> None:
        """The next ``count`` samples taken while streaming are never sent: a sequence gap."""
        with self._cond:
            self._drop_remaining += int(count)

    def preset_counters(self, counts: ArrayLike) -> None:
        """Preset the hardware counters: the next sample reads ``counts`` (before wrapping) and
        later samples move from there as the source moves."""
        with self._cond:
            self._advance()
            self._pending_preset = np.broadcast_to(np.asarray(counts, np.int64), (N_CHANNELS,)).copy()

    def start_near_wrap(self, margin: int = 1000) -> None:
        """Preset every counter to 2^31 - ``margin``, just below the 32-bit wrap."""
        self.preset_counters((1 << 31) - int(margin))

    def reset_counters(self) -> None:
        """Counter reset (the counter section lost power or its watchdog fired): from the next
        sample on, counters restart from 0, sequence numbers from 0, device time from 0, and
        frames carry COUNTER_RESET until the host sends CLEAR_RESET_FLAG."""
        with self._cond:
            self._advance()
            self._pending_reset = True

    def stall(self) -> None:
        """Hang the firmware's USB side: reads time out (``usb.core.USBTimeoutError``), commands
        are not accepted. Sampling goes on into the FIFO, which overflows if the stall lasts."""
        with self._cond:
            self._advance()
            self._stalled = True
            self._cond.notify_all()

    def resume(self) -> None:
        """End a :meth:`stall`."""
        with self._cond:
            self._advance()
            self._stalled = False
            self._cond.notify_all()

    def set_signal_lost(self, channel: int, lost: bool = True) -> None:
        """Set or clear channel ``channel``'s signal-lost status bit (encoder unplugged)."""
        self._set_bit('_signal_lost', channel, lost)

    def set_quadrature_error(self, channel: int, error: bool = True) -> None:
        """Set or clear channel ``channel``'s quadrature-error status bit."""
        self._set_bit('_quadrature', channel, error)

    def _set_bit(self, name: str, channel: int, value: bool) -> None:
        if not 0 <= channel < N_CHANNELS:
            raise ValueError(f'channel must be 0..{N_CHANNELS - 1}, got {channel}')
        with self._cond:
            self._advance()
            bits = getattr(self, name)
            setattr(self, name, bits | (1 << channel) if value else bits & ~(1 << channel))

    # ------------------------------------------------------------------ firmware model
    def _source_set_rate(self, rate: int) -> bool:
        setter = getattr(self.source, 'set_sample_rate', None)
        if setter is None:
            return False
        setter(float(rate))
        return True

    def _usb_reset(self) -> None:
        """What a USB reset / re-enumeration does to the firmware state (lock held)."""
        self._configuration = 0
        self._claimed_by = None
        self._streaming = False
        self._fifo.clear()
        self._replies.clear()

    def _advance(self) -> None:
        """Take the samples the paced sample clock has ticked since the last call (lock held)."""
        if not self.paced:
            return
        due = self._taken_at_origin + math.floor((self._clock() - self._origin) * self._rate)
        if due > self._taken:
            self._take(due - self._taken)

    def _take(self, n: int) -> None:
        """Read n samples from the source and frame them into the FIFO if streaming (lock held)."""
        while n > 0:
            m = min(n, 65536)
            n -= m
            t_ns, counts = self.source.read(m)
            t_ns = np.asarray(t_ns, np.int64)
            counts = np.asarray(counts, np.int64)
            if t_ns.shape != (m,) or counts.shape != (m, N_CHANNELS):
                raise ValueError(f'sample source returned shapes {t_ns.shape} and {counts.shape} '
                                 f'for read({m}); expected ({m},) and ({m}, {N_CHANNELS})')
            self._taken += m
            if self._pending_reset:
                self._pending_reset = False
                self._pending_preset = None
                self._count_offset = -counts[0]
                self._time_offset = int(t_ns[0])
                self._seq_next = 0
                self._reset_flag = True
            if self._pending_preset is not None:
                self._count_offset = self._pending_preset - counts[0]
                self._pending_preset = None
            seq0 = self._seq_next
            self._seq_next = (self._seq_next + m) % (1 << 32)
            if not (self._streaming and self._plugged):
                continue
            keep = np.ones(m, bool)
            if self._drop_remaining:
                k = min(self._drop_remaining, m)
                keep[:k] = False
                self._drop_remaining -= k
                self.frames_dropped_by_fault += k
            idx = np.flatnonzero(keep)
            space = self.fifo_frames - len(self._fifo) // FRAME_SIZE
            if idx.size > space:
                self.frames_lost_to_overflow += idx.size - space
                idx = idx[:space]
                lost = True
            else:
                lost = False
            if idx.size:
                flags = np.full(idx.size, FLAG_COUNTER_RESET if self._reset_flag else 0, np.uint16)
                if self._overflow_pending:
                    flags[0] |= FLAG_FIFO_OVERFLOW
                    self._overflow_pending = False
                level = len(self._fifo) // FRAME_SIZE + 1 + np.arange(idx.size)
                self._fifo += encode_frames(
                    seq0 + idx, t_ns[idx] - self._time_offset, counts[idx] + self._count_offset,
                    channel_status=self._signal_lost | (self._quadrature << 8), flags=flags,
                    fifo_level=np.minimum(level, 0xFFFF))
            if lost:
                self._overflow_pending = True

    def _deliver(self, max_frames: int) -> bytes:
        """Pop up to max_frames frames from the FIFO as one transfer (lock held)."""
        k = min(len(self._fifo) // FRAME_SIZE, max_frames)
        data = bytearray(self._fifo[:k * FRAME_SIZE])
        del self._fifo[:k * FRAME_SIZE]
        if self.record:
            self.delivered_seqs.extend(np.frombuffer(bytes(data), FRAME_DTYPE)['seq'].tolist())
        c = min(self._corrupt_remaining, k)
        for i in range(c):
            data[i * FRAME_SIZE + self._corrupt_offset] ^= 0xFF
        self._corrupt_remaining -= c
        self.frames_corrupted += c
        self.frames_sent += k
        return bytes(data)

    def _command(self, data: bytes) -> bytes:
        """Execute one command and return its reply (lock held)."""
        try:
            cmd = decode_command(data)
        except ProtocolError:
            tag = int.from_bytes(data[6:8], 'little') if len(data) >= 8 else 0
            op = data[4] if len(data) >= 5 else 0
            self.commands.append((op, 0, Status.BAD_COMMAND))
            return encode_reply(op, tag, Status.BAD_COMMAND)
        status, payload = Status.OK, b''
        op, arg = cmd.opcode, cmd.arg
        if op == Opcode.GET_INFO:
            payload = encode_info(self.info())
        elif op == Opcode.START_STREAM:
            self._advance()
            self._fifo.clear()
            self._overflow_pending = False
            self._streaming = True
        elif op == Opcode.STOP_STREAM:
            self._advance()
            self._streaming = False
            self._fifo.clear()
        elif op == Opcode.SET_SAMPLE_RATE:
            if self._streaming:
                status = Status.BUSY
            elif not 1 <= arg <= MAX_SAMPLE_RATE_HZ:
                status = Status.BAD_ARGUMENT
            else:
                self._advance()
                if arg != self._rate and not self._source_set_rate(arg):
                    status = Status.BAD_ARGUMENT
                else:
                    self._rate = int(arg)
                    self._origin, self._taken_at_origin = self._clock(), self._taken
        elif op == Opcode.SET_FRAMES_PER_TRANSFER:
            if 1 <= arg <= MAX_FRAMES_PER_TRANSFER:
                self._fpt = int(arg)
            else:
                status = Status.BAD_ARGUMENT
        elif op == Opcode.CLEAR_RESET_FLAG:
            self._advance()
            self._reset_flag = False
        else:
            status = Status.UNKNOWN_OPCODE
        self.commands.append((op, arg, int(status)))
        return encode_reply(op, cmd.tag, status, payload)

    # ------------------------------------------------------------------ USB side (backend calls)
    def _check(self, handle: _Handle) -> None:
        if handle.closed:
            raise _usb_error('INVALID_PARAM')
        if not self._plugged or handle.generation != self._generation:
            raise _usb_error('NO_DEVICE')

    def _deadline(self, timeout_ms: int) -> float | None:
        return None if not timeout_ms else self._clock() + timeout_ms / 1000.0

    def _wait(self, deadline: float | None, until: float | None = None) -> None:
        """Wait on the condition until notified, ``until`` or the deadline (lock held)."""
        now = self._clock()
        if deadline is not None and now >= deadline:
            raise _usb_error('TIMEOUT')
        ends = [t for t in (deadline, until) if t is not None]
        self._cond.wait(max(0.0, min(ends) - now) if ends else None)

    def read_samples(self, handle: _Handle, buff: array.array, timeout_ms: int) -> int:
        max_frames = len(buff) * buff.itemsize // FRAME_SIZE
        if max_frames == 0:
            raise _usb_error('OVERFLOW')  # a frame does not fit the host's buffer
        deadline = self._deadline(timeout_ms)
        with self._cond:
            while True:
                self._check(handle)
                if not self._stalled and self._streaming:
                    self._advance()
                    have = len(self._fifo) // FRAME_SIZE
                    if not self.paced:
                        for _ in range(4):  # dropped frames may leave the FIFO short
                            if have >= max_frames:
                                break
                            self._take(max_frames - have)
                            have = len(self._fifo) // FRAME_SIZE
                    want = min(self._fpt, max_frames) if self.paced else 1
                    if have >= want:
                        data = self._deliver(max_frames)
                        memoryview(buff).cast('B')[:len(data)] = data
                        return len(data)
                    if self.paced:
                        # when will the want-th frame be taken?
                        k = self._taken + (want - have) - self._taken_at_origin
                        until = self._origin + k / self._rate + 1e-5
                        self._wait(deadline, until)
                        continue
                self._wait(deadline)

    def read_reply(self, handle: _Handle, buff: array.array, timeout_ms: int) -> int:
        deadline = self._deadline(timeout_ms)
        with self._cond:
            while True:
                self._check(handle)
                if not self._stalled and self._replies:
                    reply = self._replies[0]
                    if len(reply) > len(buff) * buff.itemsize:
                        raise _usb_error('OVERFLOW')
                    self._replies.popleft()
                    memoryview(buff).cast('B')[:len(reply)] = reply
                    return len(reply)
                self._wait(deadline)

    def write_command(self, handle: _Handle, data: array.array, timeout_ms: int) -> int:
        deadline = self._deadline(timeout_ms)
        payload = bytes(data)
        with self._cond:
            while True:
                self._check(handle)
                if not self._stalled:
                    self._replies.append(self._command(payload))
                    self._cond.notify_all()
                    return len(payload)
                self._wait(deadline)

    # descriptors ------------------------------------------------------------------
    def device_descriptor(self) -> _Descriptor:
        return _Descriptor(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=self.vendor_id, idProduct=self.product_id,
            bcdDevice=0x0100, iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
            address=self.address, bus=self.bus, port_number=self.port, port_numbers=(self.port,),
            speed=3)  # usb.util.SPEED_HIGH

    @staticmethod
    def configuration_descriptor() -> _Descriptor:
        return _Descriptor(
            bLength=9, bDescriptorType=2, wTotalLength=_CONFIG_TOTAL_LENGTH, bNumInterfaces=1,
            bConfigurationValue=1, iConfiguration=0, bmAttributes=0xC0,  # self-powered
            bMaxPower=50, extra_descriptors=[])

    @staticmethod
    def interface_descriptor() -> _Descriptor:
        return _Descriptor(
            bLength=9, bDescriptorType=4, bInterfaceNumber=INTERFACE_NUMBER, bAlternateSetting=0,
            bNumEndpoints=len(_ENDPOINTS), bInterfaceClass=0xFF, bInterfaceSubClass=0,
            bInterfaceProtocol=0, iInterface=4, extra_descriptors=[])

    @staticmethod
    def endpoint_descriptor(index: int) -> _Descriptor:
        return _Descriptor(
            bLength=7, bDescriptorType=5, bEndpointAddress=_ENDPOINTS[index], bmAttributes=0x02,
            wMaxPacketSize=_BULK_PACKET, bInterval=0, bRefresh=0, bSynchAddress=0,
            extra_descriptors=[])

    def string(self, index: int) -> str | None:
        return {1: self.vendor, 2: self.model, 3: self.serial,
                4: 'MMD encoder stream'}.get(index)

    def raw_descriptor(self, dtype: int, index: int) -> bytes | None:
        """GET_DESCRIPTOR bytes: device (1), configuration (2, whole set) or string (3)."""
        if dtype == 1:
            d = self.device_descriptor()
            return (bytes([18, 1]) + d.bcdUSB.to_bytes(2, 'little') + bytes([0, 0, 0, 64])
                    + self.vendor_id.to_bytes(2, 'little') + self.product_id.to_bytes(2, 'little')
                    + (0x0100).to_bytes(2, 'little') + bytes([1, 2, 3, 1]))
        if dtype == 2:
            out = bytes([9, 2]) + _CONFIG_TOTAL_LENGTH.to_bytes(2, 'little') + bytes([1, 1, 0, 0xC0, 50])
            out += bytes([9, 4, INTERFACE_NUMBER, 0, len(_ENDPOINTS), 0xFF, 0, 0, 4])
            for ep in _ENDPOINTS:
                out += bytes([7, 5, ep, 0x02]) + _BULK_PACKET.to_bytes(2, 'little') + bytes([0])
            return out
        if dtype == 3:
            if index == 0:
                return bytes([4, 3, 0x09, 0x04])  # LANGID en-US
            text = self.string(index)
            if text is None:
                return None
            body = text.encode('utf-16-le')
            return bytes([2 + len(body), 3]) + body
        return None


class SimUsbBackend(usb.backend.IBackend):
    """pyusb backend serving one or more :class:`SimTerminal` s (one by default).

    terminals : SimTerminal | sequence of SimTerminal | None
    """

    def __init__(self, terminals: SimTerminal | Sequence[SimTerminal] | None = None) -> None:
        if terminals is None:
            terminals = [SimTerminal()]
        elif isinstance(terminals, SimTerminal):
            terminals = [terminals]
        self.terminals: list[SimTerminal] = list(terminals)
        if not self.terminals:
            raise ValueError('SimUsbBackend needs at least one SimTerminal')

    @property
    def terminal(self) -> SimTerminal:
        """The first (usually the only) terminal."""
        return self.terminals[0]

    # enumeration and descriptors
    def enumerate_devices(self) -> Iterator[_DeviceId]:
        for t in self.terminals:
            if t.plugged:
                yield _DeviceId(t, t._generation)

    def get_parent(self, dev: _DeviceId) -> None:
        return None

    def get_device_descriptor(self, dev: _DeviceId) -> _Descriptor:
        return dev.terminal.device_descriptor()

    def get_configuration_descriptor(self, dev: _DeviceId, config: int) -> _Descriptor:
        if config != 0:
            raise IndexError(f'configuration index {config} out of range')
        return dev.terminal.configuration_descriptor()

    def get_interface_descriptor(self, dev: _DeviceId, intf: int, alt: int, config: int) -> _Descriptor:
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError(f'interface ({intf}, {alt}) of configuration {config} out of range')
        return dev.terminal.interface_descriptor()

    def get_endpoint_descriptor(self, dev: _DeviceId, ep: int, intf: int, alt: int,
                                config: int) -> _Descriptor:
        if config != 0 or intf != 0 or alt != 0 or not 0 <= ep < len(_ENDPOINTS):
            raise IndexError(f'endpoint {ep} of interface ({intf}, {alt}) out of range')
        return dev.terminal.endpoint_descriptor(ep)

    # handles
    def open_device(self, dev: _DeviceId) -> _Handle:
        t = dev.terminal
        with t._cond:
            if not t.plugged or dev.generation != t._generation:
                raise _usb_error('NO_DEVICE')
            return _Handle(t, t._generation)

    def close_device(self, dev_handle: _Handle) -> None:
        t = dev_handle.terminal
        with t._cond:
            if t._claimed_by is dev_handle:
                t._claimed_by = None
            dev_handle.closed = True

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            if config_value not in (0, 1):
                raise _usb_error('NOT_FOUND')
            owner = t._claimed_by
            if owner is not None and owner is not dev_handle and not owner.closed:
                raise _usb_error('BUSY')  # Linux refuses while another handle holds the interface
            # (re)configuring resets the firmware's USB state, like a SET_CONFIGURATION request
            t._advance()
            claimed = t._claimed_by
            t._usb_reset()
            t._claimed_by = claimed
            t._configuration = int(config_value)
            t._cond.notify_all()

    def get_configuration(self, dev_handle: _Handle) -> int:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            return t._configuration

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        dev_handle.terminal._check(dev_handle)
        if intf != INTERFACE_NUMBER or altsetting != 0:
            raise _usb_error('NOT_FOUND')

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            if intf != INTERFACE_NUMBER:
                raise _usb_error('NOT_FOUND')
            if t._claimed_by is not None and t._claimed_by is not dev_handle and not t._claimed_by.closed:
                raise _usb_error('BUSY')
            t._claimed_by = dev_handle

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            if t._claimed_by is dev_handle:
                t._claimed_by = None

    # transfers
    def _require_claim(self, dev_handle: _Handle) -> SimTerminal:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            if t._configuration == 0:
                raise _usb_error('NOT_FOUND')
            if t._claimed_by is not dev_handle:
                raise _usb_error('NOT_FOUND')
        return t

    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: array.array, timeout: int) -> int:
        t = self._require_claim(dev_handle)
        if ep != EP_COMMAND_OUT:
            raise _usb_error('PIPE')
        return t.write_command(dev_handle, data, timeout)

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        t = self._require_claim(dev_handle)
        if ep == EP_SAMPLES_IN:
            return t.read_samples(dev_handle, buff, timeout)
        if ep == EP_REPLY_IN:
            return t.read_reply(dev_handle, buff, timeout)
        raise _usb_error('PIPE')

    def ctrl_transfer(self, dev_handle: _Handle, bmRequestType: int, bRequest: int, wValue: int,
                      wIndex: int, data: array.array, timeout: int) -> int:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            answer: bytes | None = None
            if bmRequestType == 0x80 and bRequest == 0x06:  # GET_DESCRIPTOR
                answer = t.raw_descriptor(wValue >> 8, wValue & 0xFF)
            elif bmRequestType == 0x80 and bRequest == 0x00:  # GET_STATUS: self-powered
                answer = bytes([1, 0])
            elif bmRequestType == 0x80 and bRequest == 0x08:  # GET_CONFIGURATION
                answer = bytes([t._configuration])
            if answer is None:
                raise _usb_error('PIPE')  # the device stalls requests it does not know
            n = min(len(answer), len(data) * data.itemsize)
            memoryview(data).cast('B')[:n] = answer[:n]
            return n

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        dev_handle.terminal._check(dev_handle)

    def reset_device(self, dev_handle: _Handle) -> None:
        t = dev_handle.terminal
        with t._cond:
            t._check(dev_handle)
            t._advance()
            t._usb_reset()
            t._cond.notify_all()

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        dev_handle.terminal._check(dev_handle)
        return False

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        dev_handle.terminal._check(dev_handle)

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        dev_handle.terminal._check(dev_handle)
