"""Driver of the 8-channel encoder terminal over USB (pyusb), real or simulated.

:class:`TerminalDriver` finds the terminal by vendor/product id (and serial number), claims its
interface, reads its :class:`~mmd_ros.hardware.protocol.DeviceInfo`, starts streaming and
returns :class:`~mmd_ros.hardware.stream.SampleBatch` es of unwrapped counts from
:meth:`TerminalDriver.read_batch`. It implements :class:`~mmd_ros.hardware.transport.Transport`.

Link loss: when the terminal leaves the bus, the ``read_batch`` call that notices raises
:class:`TerminalDisconnectedError` (every frame that arrived before was already returned: a
batch is one USB transfer, handed over as soon as it is read). With ``auto_reconnect`` (the
default), each later ``read_batch`` tries to find the same terminal (same serial number) again,
with exponential backoff, and raises :class:`TerminalDisconnectedError` while it is away; once
it is back, the driver reconfigures it, restarts the stream and returns an empty batch with
``reconnected=True``. Samples the terminal took while off the bus were never delivered: they
show up as a gap (``missing_before``) in the next batch. Counts stay unwrapped across the
disconnect. Without ``auto_reconnect``, call :meth:`TerminalDriver.reconnect`.

Typical use, from a reader thread (never an rclpy timer)::

    with TerminalDriver(serial='MMD-0042') as drv:
        while running:
            try:
                batch = drv.read_batch(timeout=0.5)
            except (TerminalTimeoutError, TerminalDisconnectedError) as exc:
                report(exc); continue
            publish(batch)
"""

from __future__ import annotations

import array
import collections
import errno
import logging
import random
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import usb.backend
import usb.core
import usb.util

from mmd_ros.hardware.errors import (
    AmbiguousTerminalError, CommandError, HardwareError, IncompatibleTerminalError, ProtocolError,
    TerminalAccessError, TerminalBusyError, TerminalClosedError, TerminalDisconnectedError,
    TerminalNotFoundError, TerminalTimeoutError,
)
from mmd_ros.hardware.protocol import (
    COUNTER_BITS, EP_COMMAND_OUT, EP_REPLY_IN, EP_SAMPLES_IN, FRAME_SIZE, INTERFACE_NUMBER,
    MAX_FRAMES_PER_TRANSFER, MAX_REPLY_SIZE, MAX_SAMPLE_RATE_HZ, N_CHANNELS, PRODUCT_ID,
    PROTOCOL_VERSION, VENDOR_ID, DeviceInfo, Opcode, Status, decode_info, decode_reply,
    encode_command,
)
from mmd_ros.hardware.stream import DriverStats, FrameStream, SampleBatch

__all__ = ['Backoff', 'TerminalDriver', 'default_backend']

_log = logging.getLogger(__name__)

#: errno values of a USB error that mean the link is gone (unplug, hub reset, EMI reset)
_LINK_LOSS_ERRNOS = {errno.ENODEV, errno.EIO, errno.ESHUTDOWN, errno.ENXIO}
_UDEV_HINT = ('install config/99-mmd-terminal.rules into /etc/udev/rules.d/, run '
              '"sudo udevadm control --reload && sudo udevadm trigger", make sure you are in the '
              'plugdev group, and plug the terminal in again')

_STATUS_HINTS = {
    Status.BAD_COMMAND: 'the command was damaged in transit or the firmware speaks another protocol; '
                        'check the cable, then update the firmware',
    Status.UNKNOWN_OPCODE: 'the firmware is too old for this command; update it',
    Status.BAD_ARGUMENT: 'the value is outside what the terminal supports (see msg_docs/usb_protocol.md)',
    Status.BUSY: 'stop streaming first',
}


def default_backend() -> usb.backend.IBackend | None:
    """The libusb-1.0 backend of the ``libusb-package`` wheel, or None for pyusb's own choice
    (the system's libusb-1.0, then OpenUSB, then libusb-0.1)."""
    try:
        import libusb_package
    except ImportError:
        return None
    try:
        return libusb_package.get_libusb1_backend()
    except Exception:  # noqa: BLE001 - a broken wheel must not hide the system libusb
        return None


@dataclass(frozen=True)
class Backoff:
    """Reconnect schedule: wait ``initial_s``, then ``factor`` times longer, at most ``max_s``."""

    initial_s: float = 0.05
    factor: float = 2.0
    max_s: float = 1.0


def _is_link_loss(exc: usb.core.USBError) -> bool:
    return exc.errno in _LINK_LOSS_ERRNOS or getattr(exc, 'backend_error_code', None) == -4


class TerminalDriver:
    """The encoder terminal over USB: open, read batches of samples, close.

    serial : str | None — serial number of the terminal to use; None accepts the only one present
    backend : usb.backend.IBackend | None — pyusb backend; None uses :func:`default_backend`
        (real libusb). Tests pass a :class:`~mmd_ros.hardware.sim_backend.SimUsbBackend`.
    vendor_id, product_id : int — USB ids (protocol defaults)
    sample_rate_hz : int | None — rate to set at open [Hz]; None keeps the terminal's
    frames_per_transfer : int | None — frames per USB transfer to set at open; None keeps it
    read_timeout_s : float — default ``read_timeout`` of :meth:`read_batch` [s]
    command_timeout_s : float — limit for one command and its reply [s]
    auto_reconnect : bool — reconnect inside :meth:`read_batch` after a link loss
    backoff : Backoff — reconnect schedule
    max_transfer_frames : int — size of the read buffer, in frames (one transfer at most)
    """

    def __init__(self, serial: str | None = None, *, backend: usb.backend.IBackend | None = None,
                 vendor_id: int = VENDOR_ID, product_id: int = PRODUCT_ID,
                 sample_rate_hz: int | None = None, frames_per_transfer: int | None = None,
                 read_timeout_s: float = 1.0, command_timeout_s: float = 1.0,
                 auto_reconnect: bool = True, backoff: Backoff = Backoff(),
                 max_transfer_frames: int = 256) -> None:
        if sample_rate_hz is not None and not 1 <= sample_rate_hz <= MAX_SAMPLE_RATE_HZ:
            raise ValueError(f'sample_rate_hz must be 1..{MAX_SAMPLE_RATE_HZ}, got {sample_rate_hz}')
        if frames_per_transfer is not None and not 1 <= frames_per_transfer <= MAX_FRAMES_PER_TRANSFER:
            raise ValueError(f'frames_per_transfer must be 1..{MAX_FRAMES_PER_TRANSFER}, '
                             f'got {frames_per_transfer}')
        if not read_timeout_s > 0 or not command_timeout_s > 0:
            raise ValueError('read_timeout_s and command_timeout_s must be positive [s]')
        self.serial = serial
        self.vendor_id, self.product_id = int(vendor_id), int(product_id)
        self.sample_rate_hz = sample_rate_hz
        self.frames_per_transfer = frames_per_transfer
        self.read_timeout_s = float(read_timeout_s)
        self.command_timeout_s = float(command_timeout_s)
        self.auto_reconnect = bool(auto_reconnect)
        self.backoff = backoff
        self._backend = backend if backend is not None else default_backend()
        self._buf = array.array('B', bytes(max(1, int(max_transfer_frames)) * FRAME_SIZE))
        self._reply_buf = array.array('B', bytes(MAX_REPLY_SIZE))
        self._lock = threading.RLock()
        self._cmd_lock = threading.Lock()
        self._dev: usb.core.Device | None = None
        self._open = False
        self._info: DeviceInfo | None = None
        self._locked_serial: str | None = serial
        self._stats = DriverStats()
        self._stream = FrameStream(self._stats)
        self._tag = random.getrandbits(16)  # unlikely to match a stale reply of another session
        self._reference_valid = True
        self._next_attempt = 0.0
        self._backoff_s = backoff.initial_s
        self._down_since: float | None = None
        self._last_error: BaseException | None = None
        self._rate_window: collections.deque[tuple[float, int]] = collections.deque()

    # ------------------------------------------------------------------ public API
    def __enter__(self) -> TerminalDriver:
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def info(self) -> DeviceInfo | None:
        """The terminal's GET_INFO answer of the last (re)connection."""
        return self._info

    @property
    def connected(self) -> bool:
        return self._dev is not None

    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def stats(self) -> DriverStats:
        """Snapshot of the stream and link counters (safe to read from another thread)."""
        s = self._stats.copy()
        s.sample_rate_hz = self._measured_rate()
        return s

    @property
    def reference_valid(self) -> bool:
        """False from a counter reset until :meth:`mark_referenced`: counts lost their zero, so a
        calibration made against them is invalid until the bars are re-referenced."""
        return self._reference_valid

    def mark_referenced(self) -> None:
        """Say the bars were re-referenced (calibrated) after the last counter reset."""
        self._reference_valid = True

    @property
    def last_error(self) -> BaseException | None:
        """The last link error (why the terminal is or was disconnected)."""
        return self._last_error

    @property
    def usb_location(self) -> str:
        dev = self._dev
        if dev is None:
            return 'not connected'
        return f'USB {dev.idVendor:04x}:{dev.idProduct:04x} bus {dev.bus} address {dev.address}'

    def open(self) -> DeviceInfo:
        """Find, claim and configure the terminal, read its info and start streaming.

        Raises :class:`TerminalNotFoundError`, :class:`AmbiguousTerminalError`,
        :class:`TerminalAccessError`, :class:`TerminalBusyError`,
        :class:`IncompatibleTerminalError`, :class:`CommandError` or :class:`TerminalTimeoutError`.
        """
        with self._lock:
            if self._open:
                assert self._info is not None
                return self._info
            self._stats = DriverStats()
            self._stream = FrameStream(self._stats)
            self._rate_window.clear()
            self._reference_valid = True
            self._locked_serial = self.serial
            info = self._connect()
            self._locked_serial = info.serial
            self._open = True
            return info

    def close(self) -> None:
        """Stop streaming, release the interface and the device. Safe to call twice."""
        with self._lock:
            self._open = False
            dev = self._dev
            if dev is not None:
                try:
                    self._command(Opcode.STOP_STREAM, timeout_s=min(self.command_timeout_s, 0.2))
                except HardwareError:
                    pass
                self._dispose()

    def read_batch(self, timeout: float | None = None) -> SampleBatch:
        """Read one USB transfer and return its samples (blocking for at most ``timeout`` s).

        timeout : float | None — [s]; ``read_timeout_s`` when None. Keep it well above
            frames_per_transfer / sample rate (8 ms by default), the time a transfer takes to fill.

        Returns a :class:`SampleBatch` (empty when every frame of the transfer was bad, or right
        after a reconnect, with ``reconnected=True``). Raises :class:`TerminalTimeoutError` when
        no transfer arrived in time (the terminal is stalled) and
        :class:`TerminalDisconnectedError` when the terminal is off the bus.
        """
        if not self._open:
            raise TerminalClosedError('the driver is not open: call open() first (or use it as a '
                                      'context manager)')
        limit = self.read_timeout_s if timeout is None else max(0.0, float(timeout))
        deadline = time.monotonic() + limit
        if self._dev is None:
            if not self.auto_reconnect:
                raise TerminalDisconnectedError(
                    f'terminal {self._locked_serial} is disconnected ({self._last_error}); '
                    'call reconnect() once it is plugged in again')
            self._reconnect_until(deadline)
            return SampleBatch.empty(time.time_ns()).with_reconnected()
        dev = self._dev
        ms = max(1, int(round((deadline - time.monotonic()) * 1000)))
        try:
            n = dev.read(EP_SAMPLES_IN, self._buf, ms)
        except usb.core.USBTimeoutError as exc:
            self._stats.timeouts += 1
            raise TerminalTimeoutError(
                f'terminal {self._locked_serial} sent no sample frame for {limit:.3g} s while '
                'streaming: it is stalled or its firmware hung; if this persists, power-cycle it '
                '(its counters then restart and the calibration must be re-referenced)') from exc
        except usb.core.USBError as exc:
            if _is_link_loss(exc):
                self._link_lost(exc)
                raise TerminalDisconnectedError(
                    f'terminal {self._locked_serial} left the bus ({exc}); '
                    + ('the driver reconnects when it is back' if self.auto_reconnect
                       else 'call reconnect() once it is plugged in again')) from exc
            if exc.errno == errno.EPIPE:  # the terminal halted its sample endpoint
                try:
                    dev.clear_halt(EP_SAMPLES_IN)
                except usb.core.USBError:
                    pass
                raise HardwareError(
                    f'terminal {self._locked_serial} halted its sample endpoint ({exc}); the halt '
                    'was cleared and reading again may work; if it repeats, power-cycle the '
                    'terminal') from exc
            raise HardwareError(f'USB read from terminal {self._locked_serial} failed: {exc}; '
                                'check the cable and the hub') from exc
        batch = self._stream.feed(memoryview(self._buf)[:n], time.time_ns())
        self._note_rate()
        if batch.counter_reset:
            self._on_counter_reset()
        if batch.crc_errors:
            _log.warning('terminal %s: %d frame(s) with a bad CRC dropped', self._locked_serial,
                         batch.crc_errors)
        return batch

    def batches(self, stop: threading.Event | None = None,
                timeout: float | None = None) -> Iterator[SampleBatch]:
        """Yield non-empty batches until ``stop`` is set; errors propagate."""
        while stop is None or not stop.is_set():
            batch = self.read_batch(timeout)
            if batch.n:
                yield batch

    def reconnect(self, timeout: float | None = None) -> DeviceInfo:
        """Wait (with backoff) until the same terminal is back, then restart its stream.

        timeout : float | None — [s]; None waits for ever. A no-op when connected.
        Raises :class:`TerminalDisconnectedError` when it did not come back in time.
        """
        if not self._open:
            raise TerminalClosedError('the driver is not open: call open() first')
        if self._dev is None:
            self._reconnect_until(None if timeout is None else time.monotonic() + timeout)
        assert self._info is not None
        return self._info

    def set_sample_rate(self, rate_hz: int) -> DeviceInfo:
        """Change the terminal's sample rate [Hz] (stops and restarts the stream; the samples
        not taken during the switch are not a gap: the sequence continues)."""
        if not 1 <= rate_hz <= MAX_SAMPLE_RATE_HZ:
            raise ValueError(f'rate_hz must be 1..{MAX_SAMPLE_RATE_HZ}, got {rate_hz}')
        with self._lock:
            self._require_connected()
            self._command(Opcode.STOP_STREAM)
            self._command(Opcode.SET_SAMPLE_RATE, int(rate_hz))
            self.sample_rate_hz = int(rate_hz)
            self._info = decode_info(self._command(Opcode.GET_INFO))
            self._command(Opcode.START_STREAM)
            self._rate_window.clear()
            return self._info

    # ------------------------------------------------------------------ connection
    def _require_connected(self) -> None:
        if not self._open:
            raise TerminalClosedError('the driver is not open: call open() first')
        if self._dev is None:
            raise TerminalDisconnectedError(f'terminal {self._locked_serial} is disconnected')

    def _find(self) -> usb.core.Device:
        ids = f'{self.vendor_id:04x}:{self.product_id:04x}'
        try:
            found = list(usb.core.find(find_all=True, idVendor=self.vendor_id,
                                       idProduct=self.product_id, backend=self._backend))
        except usb.core.NoBackendError as exc:
            raise HardwareError('no libusb found for pyusb: pip install libusb-package, or '
                                'apt-get install libusb-1.0-0') from exc
        if not found:
            raise TerminalNotFoundError(
                f'no encoder terminal (USB {ids}) on the bus: check its cable and power; '
                f'"lsusb -d {ids}" should list it')
        serials: list[str | None] = []
        unreadable = 0
        for dev in found:
            try:
                serials.append(dev.serial_number)
            except (usb.core.USBError, ValueError):
                serials.append(None)
                unreadable += 1
        want = self._locked_serial
        if want is not None:
            match = [d for d, s in zip(found, serials) if s == want]
            if not match:
                extra = (f'; {unreadable} could not be read (permissions: {_UDEV_HINT})'
                         if unreadable else '')
                raise TerminalNotFoundError(
                    f'no encoder terminal with serial "{want}" (USB {ids}); present: '
                    f'{[s for s in serials if s is not None]}{extra}')
            return match[0]
        if len(found) > 1:
            raise AmbiguousTerminalError(
                f'{len(found)} encoder terminals (USB {ids}) are present, serials {serials}: '
                'pass serial= to choose one')
        return found[0]

    def _connect(self) -> DeviceInfo:
        """Find, configure, claim; STOP, GET_INFO, optional settings, START."""
        dev = self._find()
        try:
            dev.set_configuration()
            usb.util.claim_interface(dev, INTERFACE_NUMBER)
        except usb.core.USBError as exc:
            usb.util.dispose_resources(dev)
            raise self._translate_open_error(exc, dev) from exc
        self._dev = dev
        try:
            self._command(Opcode.STOP_STREAM)
            info = decode_info(self._command(Opcode.GET_INFO))
            self._check_compatible(info)
            if self._locked_serial is not None and info.serial != self._locked_serial:
                raise TerminalNotFoundError(
                    f'the terminal at {self.usb_location} says its serial is "{info.serial}", '
                    f'not "{self._locked_serial}"')
            if self.sample_rate_hz is not None and info.sample_rate_hz != self.sample_rate_hz:
                self._command(Opcode.SET_SAMPLE_RATE, int(self.sample_rate_hz))
            if self.frames_per_transfer is not None and info.frames_per_transfer != self.frames_per_transfer:
                self._command(Opcode.SET_FRAMES_PER_TRANSFER, int(self.frames_per_transfer))
            if self.sample_rate_hz is not None or self.frames_per_transfer is not None:
                info = decode_info(self._command(Opcode.GET_INFO))
            self._command(Opcode.START_STREAM)
        except BaseException:
            self._dispose()
            raise
        self._info = info
        self._down_since = None
        _log.info('terminal %s (%s %s, firmware %s) at %s, %d Hz, streaming', info.serial,
                  info.vendor, info.model, info.firmware, self.usb_location, info.sample_rate_hz)
        return info

    def _check_compatible(self, info: DeviceInfo) -> None:
        wrong = []
        if info.protocol_version != PROTOCOL_VERSION:
            wrong.append(f'protocol version {info.protocol_version} (need {PROTOCOL_VERSION})')
        if info.n_channels != N_CHANNELS:
            wrong.append(f'{info.n_channels} channels (need {N_CHANNELS})')
        if info.counter_bits != COUNTER_BITS:
            wrong.append(f'{info.counter_bits}-bit counters (need {COUNTER_BITS})')
        if info.frame_size != FRAME_SIZE:
            wrong.append(f'{info.frame_size}-byte frames (need {FRAME_SIZE})')
        if wrong:
            raise IncompatibleTerminalError(
                f'terminal {info.serial} (firmware {info.firmware}) has ' + ', '.join(wrong)
                + ': update its firmware or this driver')

    def _translate_open_error(self, exc: usb.core.USBError, dev: usb.core.Device) -> HardwareError:
        where = f'USB {dev.idVendor:04x}:{dev.idProduct:04x} bus {dev.bus} address {dev.address}'
        if exc.errno == errno.EACCES:
            return TerminalAccessError(f'permission denied opening the terminal at {where}: {_UDEV_HINT}')
        if exc.errno == errno.EBUSY:
            return TerminalBusyError(
                f'the terminal at {where} is claimed by another process (another mmd driver node?): '
                'stop it, then open again')
        if _is_link_loss(exc):
            return TerminalDisconnectedError(f'the terminal at {where} left the bus while opening: {exc}')
        return HardwareError(f'cannot configure the terminal at {where}: {exc}')

    def _dispose(self) -> None:
        dev, self._dev = self._dev, None
        if dev is None:
            return
        try:
            usb.util.release_interface(dev, INTERFACE_NUMBER)
        except usb.core.USBError:
            pass
        try:
            usb.util.dispose_resources(dev)
        except usb.core.USBError:
            pass

    def _link_lost(self, exc: BaseException) -> None:
        with self._lock:
            self._last_error = exc
            self._stats.disconnects += 1
            self._dispose()
            self._stream.expect_reset()
            self._down_since = time.monotonic()
            self._next_attempt = time.monotonic()
            self._backoff_s = self.backoff.initial_s
        _log.warning('terminal %s disconnected: %s', self._locked_serial, exc)

    def _reconnect_until(self, deadline: float | None) -> None:
        while True:
            now = time.monotonic()
            if now >= self._next_attempt:
                try:
                    with self._lock:
                        self._connect()
                except HardwareError as exc:
                    self._last_error = exc
                    now = time.monotonic()
                    self._next_attempt = now + self._backoff_s
                    self._backoff_s = min(self._backoff_s * self.backoff.factor, self.backoff.max_s)
                else:
                    self._stats.reconnects += 1
                    self._backoff_s = self.backoff.initial_s
                    self._rate_window.clear()
                    _log.info('terminal %s reconnected', self._locked_serial)
                    return
            if deadline is not None and now >= deadline:
                away = now - (self._down_since if self._down_since is not None else now)
                raise TerminalDisconnectedError(
                    f'terminal {self._locked_serial} has been off the bus for {away:.1f} s '
                    f'(last error: {self._last_error}); retrying every {self._backoff_s:.2g} s '
                    'at most: plug it in again')
            wake = self._next_attempt if deadline is None else min(self._next_attempt, deadline)
            time.sleep(max(0.0, wake - time.monotonic()))

    # ------------------------------------------------------------------ commands
    def _command(self, opcode: Opcode, arg: int = 0, timeout_s: float | None = None) -> bytes:
        """Send one command and return its reply payload."""
        dev = self._dev
        if dev is None:
            raise TerminalDisconnectedError(f'terminal {self._locked_serial} is disconnected')
        limit = self.command_timeout_s if timeout_s is None else timeout_s
        name = opcode.name
        with self._cmd_lock:
            self._tag = (self._tag + 1) & 0xFFFF
            tag = self._tag
            deadline = time.monotonic() + limit
            try:
                dev.write(EP_COMMAND_OUT, encode_command(opcode, tag, arg), max(1, int(limit * 1000)))
                while True:
                    ms = max(1, int(round((deadline - time.monotonic()) * 1000)))
                    n = dev.read(EP_REPLY_IN, self._reply_buf, ms)
                    reply = decode_reply(self._reply_buf[:n].tobytes())
                    if reply.tag == tag and reply.opcode == opcode:
                        break
                    if time.monotonic() >= deadline:  # only stale replies: treat as silence
                        raise usb.core.USBTimeoutError('stale replies only', -7, errno.ETIMEDOUT)
            except usb.core.USBTimeoutError as exc:
                raise TerminalTimeoutError(
                    f'terminal {self._locked_serial} did not answer {name} within {limit:.3g} s: it '
                    'is stalled or its firmware hung; power-cycle it') from exc
            except usb.core.USBError as exc:
                if _is_link_loss(exc):
                    raise TerminalDisconnectedError(
                        f'terminal {self._locked_serial} left the bus during {name}: {exc}') from exc
                raise HardwareError(f'USB error during {name} to terminal {self._locked_serial}: '
                                    f'{exc}') from exc
            except ProtocolError as exc:
                raise ProtocolError(
                    f'bad reply to {name} from terminal {self._locked_serial}: {exc}') from exc
        if reply.status != Status.OK:
            known = reply.status in {int(v) for v in Status}
            status = Status(reply.status).name if known else f'status {reply.status}'
            hint = _STATUS_HINTS.get(reply.status, 'see msg_docs/usb_protocol.md')
            raise CommandError(f'{name}({arg})' if arg else name, status, hint)
        return reply.payload

    def _on_counter_reset(self) -> None:
        self._reference_valid = False
        _log.warning('terminal %s: counter reset (power loss or watchdog); the calibration is '
                     'invalid until the bars are re-referenced', self._locked_serial)
        try:
            self._command(Opcode.CLEAR_RESET_FLAG)
        except HardwareError as exc:  # the flag stays set; the stream logic copes
            _log.warning('could not acknowledge the counter reset: %s', exc)

    # ------------------------------------------------------------------ measured rate
    def _note_rate(self) -> None:
        now = time.monotonic()
        w = self._rate_window
        w.append((now, self._stats.frames_ok))
        while len(w) > 2 and now - w[1][0] >= 1.0:
            w.popleft()

    def _measured_rate(self) -> float:
        w = list(self._rate_window)
        if len(w) < 2 or w[-1][0] - w[0][0] < 0.2:
            return 0.0
        return (w[-1][1] - w[0][1]) / (w[-1][0] - w[0][0])
