"""The encoder terminal stage: driver, reader thread, time mapping, raw counts, simulation.

Used by ``encoder_node`` and ``pose_node``. A reader thread blocks on
:meth:`TerminalDriver.read_batch` (never an rclpy timer), maps the terminal's sample clock to ROS
time (:class:`~mmd_ros.nodes.clock.StampMapper`), publishes one ``/mmd/raw_counts`` JointState per
sample and hands every transfer to the stages that follow (``on_batch``) by direct call. With
``device:=sim`` the terminal is a :class:`SimTerminal` behind the real pyusb API, streaming the
digital twin (:class:`~mmd_ros.hardware.twin_source.TwinSource`); the twin's reference reading
goes to ``/mmd/reference/pose``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.calibration import TerminalBinding, channel_roles
from mmd_ros.core.device import DeviceDescription
from mmd_ros.hardware import (
    DeviceInfo, HardwareError, SampleBatch, SimTerminal, SimUsbBackend, TerminalDisconnectedError,
    TerminalDriver, TerminalTimeoutError,
)
from mmd_ros.hardware.protocol import PRODUCT_ID, VENDOR_ID
from mmd_ros.hardware.twin_source import TwinSource
from mmd_ros.nodes.clock import StampMapper
from mmd_ros.nodes.convert import Rows
from mmd_ros.nodes.diagnostics import ERROR, OK, Events, Report
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param
from mmd_ros.nodes.sim_commands import SimCommandError, run_commands
from mmd_ros.twin import SCENARIOS, simulated_serial
from mmd_ros.twin.effects import PRESETS as EFFECT_PRESETS

__all__ = ['TERMINAL_PARAMS', 'TerminalConfig', 'TerminalStage', 'sim_serial_of']

TERMINAL_PARAMS = [
    Param('device', 'sim', 'encoder terminal: "sim" (a simulated terminal streaming the digital '
          'twin, behind the real pyusb API) or "usb" (a real terminal through libusb)',
          choices=('sim', 'usb')),
    Param('vendor_id', VENDOR_ID, 'USB vendor id of the terminal', low=0, high=0xFFFF),
    Param('product_id', PRODUCT_ID, 'USB product id of the terminal', low=0, high=0xFFFF),
    Param('serial', '', 'USB serial number of the terminal; "" accepts the only one present'),
    Param('sample_rate_hz', 0, 'sample rate to set at open [Hz]; 0 keeps the terminal\'s',
          low=1, high=10000, allow_zero=True),
    Param('frames_per_transfer', 0, 'frames per USB transfer to set at open; 0 keeps the '
          'terminal\'s (8)', low=1, high=64, allow_zero=True),
    Param('read_timeout_s', 0.5, 'no transfer within this time while streaming means the '
          'terminal stalled [s]', low=0.05, high=10.0),
    Param('publish_reference', True, 'simulation: publish the twin\'s reference instrument '
          '(true pose + 1 nm noise) on reference/pose'),
    Param('timing_log', '', 'benchmark aid: append (stamp_ns, arrival_ns) of every sample, as '
          'int64 pairs, to this file ("" off)'),
    Param('sim_scenario', 'random_motion', 'simulation: what the machine does while the bars '
          'are mounted (restarted when it ends)', choices=tuple(sorted(SCENARIOS))),
    Param('sim_scenario_params', 'duration_s=300.0', 'simulation: scenario parameters, '
          'space-separated name=value (see msg_docs/simulation.md)'),
    Param('sim_effects', 'realistic', 'simulation: physical effects preset (msg_docs/'
          'simulation.md): none (no error source at all), ideal or realistic',
          choices=EFFECT_PRESETS),
    Param('sim_effect_params', '', 'simulation: effect parameters, space-separated name=value'),
    Param('sim_seed', 1, 'simulation: seed of the simulated device', low=0, high=2**31 - 1),
    Param('sim_ambient', 'constant:20.0', 'simulation: room temperature: section_4_1, '
          'constant:T [°C] or a profile .yaml'),
    Param('sim_start_s', 600.0, 'simulation: the twin\'s clock at power-on [s]',
          low=-1e9, high=1e9),
    Param('sim_mounted', True, 'simulation: the measuring bars start mounted between the plates '
          '(else in their case)'),
    Param('sim_transition_s', 0.5, 'simulation: time the operator takes to move and seat a '
          'bar [s]', low=0.0, high=10.0),
    Param('sim_near_wrap_margin', 0, 'simulation: start every counter this many counts below '
          'the 32-bit wrap; 0 off', low=1, high=2**30, allow_zero=True),
    Param('sim_serial', '', 'simulation: serial number of the simulated terminal; "" the '
          'twin\'s, MMD-SIM-<sim_seed> (as mmd simulate\'s calibrations name it)'),
    Param('sim_command', '', 'simulation only: operator and fault commands, e.g. "place bar3 '
          'dr5", "mount", "move bar2 3", "unplug", "corrupt 5" (msg_docs/nodes.md)',
          dynamic=True),
]


@dataclass(frozen=True)
class TerminalConfig:
    device: str
    vendor_id: int
    product_id: int
    serial: str
    sample_rate_hz: int
    frames_per_transfer: int
    read_timeout_s: float
    publish_reference: bool
    timing_log: str
    sim_scenario: str
    sim_scenario_params: str
    sim_effects: str
    sim_effect_params: str
    sim_seed: int
    sim_ambient: str
    sim_start_s: float
    sim_mounted: bool
    sim_transition_s: float
    sim_near_wrap_margin: int
    sim_serial: str

    @classmethod
    def from_values(cls, v: dict[str, Any]) -> TerminalConfig:
        return cls(**{k: v[k] for k in cls.__dataclass_fields__
                      if k != 'sim_serial'}, sim_serial=sim_serial_of(v))


def sim_serial_of(v: dict[str, Any]) -> str:
    """The simulated terminal's serial number: the ``sim_serial`` parameter, or when it is
    empty the twin's (:func:`~mmd_ros.twin.simulated_serial` of ``sim_seed``)."""
    return str(v['sim_serial']) or simulated_serial(int(v['sim_seed']))


#: (stamps_ns (N,), counts (N, 8), channel status codes (N, 8) or None when all are good)
BatchCallback = Callable[[NDArray[np.int64], NDArray[np.float64], NDArray[np.uint8] | None], None]


class TerminalStage:
    """Driver + reader thread + raw counts (see the module docstring).

    raw, reference : outlets of /mmd/raw_counts and /mmd/reference/pose
    alive : False once the node's context is shut down (the reader thread then ends)
    raw_last : publish raw counts and reference after ``on_batch`` (pose_node: the poses go
        out first, which shortens their latency)
    on_batch : called from the reader thread with (stamps_ns, counts (N, 8), status) for every
        run of samples of one counter epoch, in order; status (N, 8) the channel status codes
        (:meth:`SampleBatch.status_codes`: 1 signal lost, 2 quadrature error), None when good
    on_reset : called from the reader thread with the stamp of the first sample after a
        terminal counter reset, before that sample goes to ``on_batch``
    on_open : called from the reader thread with the terminal's :class:`TerminalBinding`
        each time it has been opened, before its first sample goes to ``on_batch``
    """

    def __init__(self, cfg: TerminalConfig, device: DeviceDescription, rows: Rows, raw: Outlet,
                 reference: Outlet | None, logger: Any,
                 alive: Callable[[], bool] = lambda: True, raw_last: bool = False) -> None:
        self.cfg = cfg
        self.alive = alive
        self.raw_last = raw_last
        self.device = device
        self.rows = rows
        self.raw = raw
        self.reference = reference
        self.log = logger
        self.on_batch: list[BatchCallback] = []
        self.on_reset: list[Callable[[int], None]] = []
        self.on_open: list[Callable[[TerminalBinding], None]] = []
        self.source: TwinSource | None = None
        self.terminal: SimTerminal | None = None
        backend = None
        if cfg.device == 'sim':
            backend = self._make_sim()
        self.driver = TerminalDriver(
            cfg.serial or (cfg.sim_serial if cfg.device == 'sim' else None), backend=backend,
            vendor_id=cfg.vendor_id, product_id=cfg.product_id,
            sample_rate_hz=cfg.sample_rate_hz or None,
            frames_per_transfer=cfg.frames_per_transfer or None,
            read_timeout_s=cfg.read_timeout_s)
        self.mapper = StampMapper(int(round(1e9 / device.sample_rate_hz)))
        self.events = Events()
        self.state = 'starting'
        self.state_text = 'opening the terminal'
        self.samples = 0
        self.flagged_samples = 0
        self.resets_seen = 0
        self.last_stamp_ns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._timing = open(cfg.timing_log, 'ab') if cfg.timing_log else None  # noqa: SIM115
        self._last_stats = self.driver.stats

    # -- simulation ----------------------------------------------------------------------------
    def _make_sim(self) -> SimUsbBackend:
        from mmd_ros.twin.recording import ambient_profile
        from mmd_ros.twin import Effects, TwinDevice, make_scenario
        cfg = self.cfg
        effects = Effects.preset(cfg.sim_effects).with_assignments(cfg.sim_effect_params.split())
        twin = TwinDevice(self.device, effects, seed=cfg.sim_seed)
        scenario = make_scenario(cfg.sim_scenario, cfg.sim_scenario_params.split())
        self.source = TwinSource(twin, ambient_profile(cfg.sim_ambient), scenario,
                                 start_s=cfg.sim_start_s, mounted=cfg.sim_mounted,
                                 transition_s=cfg.sim_transition_s,
                                 near_wrap_margin=cfg.sim_near_wrap_margin)
        self.terminal = SimTerminal(self.source, serial=cfg.sim_serial, paced=True,
                                    power_on_reset=False)
        return SimUsbBackend(self.terminal)

    def sim_command(self, text: str) -> tuple[bool, str]:
        """Carry out a ``sim_command``; (success, what was done or why not)."""
        if not text.strip():
            return True, 'nothing to do'
        if self.source is None or self.terminal is None:
            return False, 'sim_command needs device:=sim (this node reads a real terminal)'
        try:
            done = run_commands(text, self.source, self.terminal)
        except SimCommandError as exc:
            return False, f'sim_command: {exc}'
        self.log.info(f'simulation: {done}')
        return True, done

    # -- thread --------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name='mmd-terminal-reader', daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        try:
            self.driver.close()
        except HardwareError:
            pass
        if self._timing is not None:
            self._timing.close()

    def _run(self) -> None:
        while not self._stop.is_set() and self.alive():
            try:
                self._read_loop()
            except Exception as exc:  # noqa: BLE001 - the reader must survive anything
                if not self.alive():
                    return
                self.log.error(f'terminal reader: {exc!r}; restarting it')
                self._stop.wait(0.5)

    def _read_loop(self) -> None:
        backoff = 0.1
        while not self._stop.is_set() and self.alive():
            if not self.driver.is_open:
                try:
                    info = self.driver.open()
                except HardwareError as exc:
                    self._set_state('not found', f'cannot open the terminal: {exc}', ERROR)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, 2.0)
                    continue
                backoff = 0.1
                self._set_state('streaming', f'streaming from {info.serial} '
                                f'({info.model}, firmware {info.firmware}) at {info.sample_rate_hz} Hz')
                for cb in self.on_open:
                    cb(self.binding(info))
            try:
                batch = self.driver.read_batch(self.cfg.read_timeout_s)
            except TerminalTimeoutError as exc:
                self._set_state('stalled', str(exc), ERROR)
                continue
            except TerminalDisconnectedError as exc:
                self._set_state('disconnected', str(exc), ERROR)
                continue
            except HardwareError as exc:
                self._set_state('error', str(exc), ERROR)
                self._stop.wait(0.1)
                continue
            if batch.reconnected:
                self.events.note('reconnected', 'terminal reconnected after a link loss')
            if self.state != 'streaming':
                self._set_state('streaming', 'streaming')
            if batch.n:
                try:
                    self._handle(batch)
                except Exception as exc:  # noqa: BLE001 - keep reading; say what broke
                    if not self.alive():
                        return  # shutting down: the publishers are gone
                    self.log.error(f'processing a transfer failed: {exc!r}')
                    self.events.note('processing', f'processing failed: {exc!r}', ERROR)

    def _set_state(self, state: str, text: str, level: int = OK) -> None:
        if state != self.state:
            if level:
                self.log.warn(f'terminal: {text}')
            else:
                self.log.info(f'terminal: {text}')
        self.state, self.state_text = state, text

    def _handle(self, batch: SampleBatch) -> None:
        dev_t = batch.device_time_ns
        counts = batch.counts.astype(np.float64)
        status = batch.status_codes()
        n = batch.n
        if batch.counter_reset:
            ri = max(0, batch.reset_index)
            parts = [(0, ri, False), (ri, n, True)] if ri > 0 else [(0, n, True)]
        else:
            parts = [(0, n, False)]
        stamps = np.empty(n, dtype=np.int64)
        for a, b, reset in parts:
            if reset:
                self.mapper.new_epoch()
            stamps[a:b] = self.mapper.map(dev_t[a:b], batch.host_time_ns)
        if not self.raw_last:
            self._publish_raw(stamps, counts, dev_t, status)
        for a, b, reset in parts:
            if reset:
                self.resets_seen += 1
                self.events.note('reset', 'terminal counter reset (power loss or watchdog): '
                                 'the calibration is invalid until the bars are re-referenced', ERROR)
                for cb in self.on_reset:
                    cb(int(stamps[a]))
            for cb in self.on_batch:
                cb(stamps[a:b], counts[a:b], status[a:b] if status is not None else None)
        if self.raw_last:
            self._publish_raw(stamps, counts, dev_t, status)
        if self._timing is not None:
            np.column_stack([stamps, np.full(n, batch.host_time_ns, dtype=np.int64)]).tofile(self._timing)
        self.samples += n
        if status is not None:
            self.flagged_samples += int(np.count_nonzero(status.any(axis=1)))
        self.last_stamp_ns = int(stamps[-1])

    def _publish_raw(self, stamps: NDArray[np.int64], counts: NDArray[np.float64],
                     dev_t: NDArray[np.int64], status: NDArray[np.uint8] | None) -> None:
        # a sample whose channel status is not good carries it in ``effort``
        for rows, part in self.rows.raw_parts(stamps, counts, status):
            self.raw.rows(rows, part)
        if self.source is not None and self.reference is not None and self.cfg.publish_reference:
            ref = self.source.reference_at(dev_t)
            known = np.isfinite(ref).any(axis=1)
            if known.any():
                self.reference.rows(self.rows.reference.encode(stamps[known], ref[known]), stamps[known])

    # -- status --------------------------------------------------------------------------------
    def binding(self, info: DeviceInfo | None = None) -> TerminalBinding:
        """The terminal as a calibration records it: its serial number ('' while a real
        terminal without a ``serial`` parameter has not been opened yet), simulated or not,
        the bar on each channel."""
        sim = self.cfg.device == 'sim'
        serial = info.serial if info is not None else (self.cfg.serial or (self.cfg.sim_serial if sim else ''))
        return TerminalBinding(serial, sim, channel_roles(self.device.channels))

    @property
    def serial(self) -> str:
        info = self.driver.info
        return info.serial if info is not None else (self.cfg.serial or self.cfg.sim_serial)

    def mark_referenced(self) -> None:
        self.driver.mark_referenced()

    def report(self) -> Report:
        st = self.driver.stats
        prev, self._last_stats = self._last_stats, st
        level = ERROR if self.state in ('stalled', 'disconnected', 'not found', 'error') else OK
        r = Report('terminal', level, self.state_text)
        if st.crc_errors > prev.crc_errors:
            self.events.note('crc', f'{st.crc_errors - prev.crc_errors} frame(s) with a bad checksum '
                             'dropped (never turned into a pose)')
        if st.missing_samples > prev.missing_samples:
            self.events.note('gap', f'{st.missing_samples - prev.missing_samples} sample(s) missing '
                             f'in {st.gaps - prev.gaps} gap(s) of the sequence')
        if st.disconnects > prev.disconnects:
            self.events.note('unplug', 'terminal left the bus (cable pulled?)', ERROR)
        if st.overflows > prev.overflows:
            self.events.note('overflow', 'the terminal\'s FIFO overflowed: the host fell behind')
        if st.signal_errors > prev.signal_errors:
            self.events.note('signal', f'encoder signal lost or quadrature error on a channel in '
                             f'{st.signal_errors - prev.signal_errors} sample(s): they are not '
                             'measurements (no pose)')
        if st.timeouts > prev.timeouts:
            self.events.note('stall', 'the terminal sent nothing within the read timeout', ERROR)
        self.events.apply(r)
        if not self.driver.reference_valid:
            r.worse(ERROR, 'counters were reset: the calibration is invalid until the bars are '
                    're-referenced (call calibrate_bar)')
        r.values.update({
            'state': self.state,
            'device': self.cfg.device,
            'serial': self.serial,
            'usb': self.driver.usb_location,
            'sample_rate_hz': round(st.sample_rate_hz, 1),
            'samples_published': self.samples,
            'frames_ok': st.frames_ok,
            'gaps': st.gaps,
            'missing_samples': st.missing_samples,
            'crc_errors': st.crc_errors,
            'sequence_errors': st.sequence_errors,
            'framing_errors': st.framing_errors,
            'counter_resets': st.resets,
            'fifo_overflows': st.overflows,
            'signal_errors': st.signal_errors,
            'samples_flagged': self.flagged_samples,
            'disconnects': st.disconnects,
            'reconnects': st.reconnects,
            'timeouts': st.timeouts,
            'reference_valid': self.driver.reference_valid,
            'time_offset_ns': self.mapper.offset_ns if self.mapper.offset_ns is not None else 0,
        })
        if self.source is not None:
            where = self.source.where()
            r.values['sim_bars'] = ' '.join(f'{k}={v}' for k, v in where.items())
            r.values['sim_twin_time_s'] = round(float(self.source.twin_time(self.source.samples_taken)), 3)
        return r
