"""The calibration stage: the guided routine behind ``/mmd/calibrate_bar`` and the calibration file.

Used by ``calibration_node`` and ``pose_node``. It keeps the last seconds of raw counts (fed by
direct call or by a subscription), runs :class:`~mmd_ros.core.calibration_routine.CalibrationRoutine`
on each service call, and owns the calibration file: loaded at start (a corrupt file is refused
with its name and the reason, and diagnostics say so; a file that an interrupted save left
missing is restored from its ``.bak``, the complete earlier calibration, and the log and the
diagnostics say so), watched for changes made by hand
(reloaded, refused if corrupt), written atomically after every change (``Calibration.save``:
temporary file, fsync, rename; the previous file is kept as ``<file>.bak``; a corrupt file that
is replaced is kept as ``<file>.corrupt``), and published on the latched ``/mmd/calibration``
topic whenever it changes. A terminal counter reset marks it invalid until every bar is
re-referenced.

A calibration is bound to the terminal it was made with (serial number, simulated or not, the
bar on each channel: :class:`~mmd_ros.core.calibration.TerminalBinding`), recorded in the file
when it is saved. A file made for another terminal, or on the simulator when this is hardware,
is refused (ERROR in the diagnostics; with ``calibration_any_terminal`` it is used, still with
an ERROR); a refused file that a new calibration replaces is kept as ``<file>.foreign``. When
the calibration cannot be written (a read-only or full file system, a path under a file) the
node still runs with what it could load, and the diagnostics say ERROR until a save succeeds.
"""

from __future__ import annotations

import math
import os
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from mmd_ros.core.calibration import (
    Calibration, TerminalBinding, binding_problem, iso_utc, load_calibration,
    recover_interrupted_save,
)
from mmd_ros.core.calibration_routine import CalibrationRoutine, RoutineSettings, Window
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import CalibrationError, ConfigError, MmdError
from mmd_ros.nodes.diagnostics import ERROR, OK, WARN, Events, Report
from mmd_ros.nodes.params import Param, check
from mmd_ros.nodes.reports import calibration_age_s

__all__ = ['ANY_TERMINAL', 'CALIBRATION_PARAMS', 'CalibrationConfig', 'CalibrationService', 'CalibrationStage', 'SampleBuffer',
           'default_calibration_file', 'now_iso']


def ros_home() -> Path:
    return Path(os.environ.get('ROS_HOME') or Path.home() / '.ros')


def default_calibration_file(device_name: str = 'mmd_prototype', terminal: str = '') -> str:
    """``$ROS_HOME/mmd/<device>_calibration.yaml``, or ``<device>_<terminal>_calibration.yaml``
    for a named terminal (the simulated one has its own serial number, so a simulation never
    writes the file a real terminal reads)."""
    name = f'{device_name}_{terminal}' if terminal else device_name
    return str(ros_home() / 'mmd' / f'{name}_calibration.yaml')


def why_not(exc: OSError) -> str:
    """What an OSError of a write means, in words (a path under a file says "File exists")."""
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        return f'{exc.filename or "a part of the path"} is a file, not a folder'
    return exc.strerror or str(exc)


def now_iso() -> str:
    return iso_utc(time.time())


#: Parameter of the nodes that check a calibration against the terminal.
ANY_TERMINAL = Param('calibration_any_terminal', False, 'use a calibration made for another '
                     'terminal, other bars or on the simulator anyway (diagnostics stay at ERROR)')


def calibration_params(device_name: str = 'mmd_prototype', terminal: str = '') -> list[Param]:
    return [
        Param('calibration_file', default_calibration_file(device_name, terminal),
              'calibration file (YAML): read at start, reloaded when it changes, written '
              'atomically after every change (previous one kept as <file>.bak)'),
        ANY_TERMINAL,
        Param('bar', '', 'the bar to calibrate next ("" follows the routine: bar1..bar6, then '
              'the reference bar)', dynamic=True),
        Param('pair', '', 'the socket pair of the next capture ("" follows the routine); '
              'cleared after an accepted capture', dynamic=True),
        Param('mode', 'auto', 'auto: re-reference after a counter reset, else calibrate; full: '
              'calibrate on all seven pairs; re_reference: one placement restores a bar\'s offset',
              choices=('auto', 'full', 're_reference'), dynamic=True),
        Param('settle_window_s', 2.0, 'a capture averages the counts of the last ... [s]',
              low=0.05, high=60.0),
        Param('settle_std_um', 0.25, 'largest standard deviation of a bar\'s reading over the '
              'window for it to count as settled [µm]', low=0.001, high=1000.0),
        Param('settle_drift_um', 0.25, 'largest drift of a bar\'s reading across the window '
              '[µm]', low=0.001, high=1000.0),
        Param('plausibility_mm', 0.2, 'largest disagreement between a reading and what the '
              'bar\'s other points predict for that pair [mm]', low=0.001, high=50.0),
        Param('re_reference_pair', '', 'pair on which measuring bars are re-referenced; "" the '
              'middle pair (dr4)'),
        Param('ambient_c', math.nan, 'room temperature recorded with the thermal zero [°C]; NaN '
              'unknown (the plates\' expansion is then counted from the CMM\'s 20 °C)',
              low=-50.0, high=100.0),
        Param('approaches', 1, '1: each bar once on each pair (the paper\'s routine); 2: twice, '
              'seated from short and from long, and a reference bar read first on its resting '
              'pair (measures hysteresis, seating repeatability and the routine\'s drift for the '
              'uncertainty budget, msg_docs/frames.md)', low=1, high=2),
    ]


CALIBRATION_PARAMS = calibration_params()


@dataclass(frozen=True)
class CalibrationConfig:
    calibration_file: str
    calibration_any_terminal: bool
    settle_window_s: float
    settle_std_um: float
    settle_drift_um: float
    plausibility_mm: float
    re_reference_pair: str
    ambient_c: float
    approaches: int = 1

    @classmethod
    def from_values(cls, v: dict[str, Any]) -> CalibrationConfig:
        return cls(**{k: v[k] for k in cls.__dataclass_fields__ if k in v})


class SampleBuffer:
    """The last ``seconds`` of samples (stamps and counts), fed from any thread."""

    def __init__(self, seconds: float, rate_hz: float) -> None:
        self.capacity = max(16, int(seconds * rate_hz))
        self._stamps = np.zeros(self.capacity, dtype=np.int64)
        self._counts = np.zeros((self.capacity, 8))
        self._n = 0  # total appended
        self._resets: list[int] = []
        self._lock = threading.Lock()

    def append(self, stamps: NDArray[np.int64], counts: NDArray[np.float64]) -> None:
        m = len(stamps)
        if m == 0:
            return
        with self._lock:
            if m >= self.capacity:
                stamps, counts, m = stamps[-self.capacity:], counts[-self.capacity:], self.capacity
            slot = (self._n + np.arange(m)) % self.capacity
            self._stamps[slot] = stamps
            self._counts[slot] = counts
            self._n += m

    def note_reset(self, stamp_ns: int) -> None:
        with self._lock:
            self._resets = (self._resets + [int(stamp_ns)])[-16:]

    @property
    def last_stamp_ns(self) -> int | None:
        with self._lock:
            return int(self._stamps[(self._n - 1) % self.capacity]) if self._n else None

    def window(self, seconds: float) -> Window:
        """The samples of the last ``seconds`` (by stamp), in time order."""
        with self._lock:
            k = min(self._n, self.capacity)
            if k == 0:
                return Window.of(np.zeros((0, 8)), 0.0)
            idx = (self._n - k + np.arange(k)) % self.capacity
            stamps = self._stamps[idx]
            counts = self._counts[idx]
            resets = list(self._resets)
        start = stamps[-1] - int(seconds * 1e9)
        keep = stamps > start
        s = stamps[keep]
        reset = any(start < r <= s[-1] for r in resets)
        duration = (s[-1] - s[0]) * 1e-9 if s.size > 1 else 0.0
        return Window.of(counts[keep], duration, reset)


class CalibrationStage:
    """The guided calibration and the calibration file (see the module docstring).

    publish : called with every new calibration (to publish it on /mmd/calibration)
    on_valid : called when the calibration becomes valid again after a counter reset
    on_refused : called when the calibration in use is refused (the terminal turned out to be
        another one): nothing may be computed with it any more
    factory : simulation: makes a calibration when the file does not exist yet
    terminal : the terminal the samples come from, as far as known at start (its serial may
        be '' until it is opened: :meth:`set_terminal`); None: not known (calibration_node
        before the encoder node said which terminal it reads)
    """

    def __init__(self, cfg: CalibrationConfig, device: DeviceDescription, *, thermal_mode: str,
                 publish: Callable[[Calibration], None], logger: Any,
                 on_valid: Callable[[], None] | None = None,
                 on_refused: Callable[[], None] | None = None,
                 factory: Callable[[], Calibration] | None = None,
                 terminal: TerminalBinding | None = None) -> None:
        self.cfg = cfg
        self.device = device
        self.path = Path(cfg.calibration_file).expanduser()
        self._publish = publish
        self.log = logger
        self.on_valid = on_valid
        self.on_refused = on_refused
        self.terminal = terminal
        self.settings = RoutineSettings(
            settle_std_m=cfg.settle_std_um * 1e-6, settle_drift_m=cfg.settle_drift_um * 1e-6,
            min_samples=max(2, int(0.5 * cfg.settle_window_s * device.sample_rate_hz)),
            plausibility_m=cfg.plausibility_mm * 1e-3, thermal_mode=thermal_mode,
            re_reference_pair=cfg.re_reference_pair or None, approaches=int(cfg.approaches))
        self.routine = CalibrationRoutine(device, None, self.settings)
        self.buffer = SampleBuffer(max(2 * cfg.settle_window_s, cfg.settle_window_s + 2.0),
                                   device.sample_rate_hz)
        self.events = Events(hold_s=10.0)
        self.file_problem = ''
        self.binding_note = ''  # the calibration in use is foreign, used by override
        self.save_problem = ''
        self.recovery = ''  # what was restored after an interrupted save (until the next save)
        self.foreign = False  # the file holds a calibration refused for its terminal
        self.last_message = ''
        self.captures = self.refused = 0
        self._lock = threading.RLock()
        self._file_sig: tuple[float, int] | None = None
        self._probe_writable()
        self._load(initial=True)
        if self.routine.calibration is None and factory is not None and self._signature() is None \
                and not self.foreign:
            cal = factory()
            cal = Calibration(cal.device, cal.bars, cal.thermal_zero_m, cal.ambient_c, now_iso(),
                              True, cal.quality, uncertainty=cal.uncertainty)
            self.routine.set_calibration(cal)
            note = self._save(cal)
            self.log.info('simulation: factory calibration of the twin in use.' + note)

    # -- the terminal --------------------------------------------------------------------------
    def bind(self, cal: Calibration) -> Calibration:
        """``cal`` bound to the terminal in use (when known)."""
        t = self.terminal
        if t is None:
            return cal
        if cal.terminal is not None and (not t.serial or self.binding_note):
            # the terminal's serial is not known yet (the calibration's is), or a foreign
            # calibration is used by override: it keeps saying where it is from
            return cal
        return replace(cal, terminal=t)

    def publish(self, cal: Calibration) -> None:
        self._publish(self.bind(cal))

    def _refusal(self, cal: Calibration) -> str | None:
        """Why ``cal`` must not be used with this terminal (None: it may, perhaps by override;
        then :attr:`binding_note` says so)."""
        self.binding_note = ''
        if self.terminal is None:
            return None
        problem = binding_problem(cal, self.terminal)
        if problem is None:
            return None
        if self.cfg.calibration_any_terminal:
            self.binding_note = (f'calibration of {self.path} used by override '
                                 f'(calibration_any_terminal): {problem}')
            return None
        return (f'calibration file refused: {self.path}: {problem}; calibrate this terminal '
                '(calibrate_bar), or set calibration_any_terminal:=true to use it anyway')

    def set_terminal(self, terminal: TerminalBinding) -> None:
        """The terminal is known now (opened, or announced by the encoder node): check the
        calibration in use against it; a refused one is withdrawn (``on_refused``)."""
        with self._lock:
            if terminal == self.terminal:
                return
            self.terminal = terminal
            cal = self.routine.calibration
            if cal is None:
                if self.foreign or self._signature() is not None:
                    self._file_sig = None  # the file may suit this terminal: read it again
                    if self._load():
                        self.publish(self.routine.calibration)
                return
            problem = self._refusal(cal)
            if problem is None:
                if self.binding_note:
                    self.log.error(self.binding_note)
                return
            self.routine.set_calibration(None)
            self.file_problem, self.foreign = problem, True
        self.log.error(problem)
        self.events.note('file', problem, ERROR)
        if self.on_refused is not None:
            self.on_refused()

    def _probe_writable(self) -> None:
        """Say now, not after the 49th capture, when the calibration cannot be written."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(prefix=f'.{self.path.name}.', suffix='.probe',
                                         dir=self.path.parent)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            self._cannot_save(exc)

    def _cannot_save(self, exc: OSError) -> None:
        self.save_problem = (f'calibrations cannot be saved to {self.path}: {why_not(exc)}; the '
                             'calibration in use is not on disk (fix the folder or set '
                             'calibration_file)')
        self.log.error(self.save_problem)

    # -- the file ------------------------------------------------------------------------------
    def _signature(self) -> tuple[float, int] | None:
        try:
            st = self.path.stat()
        except OSError:
            return None
        return st.st_mtime, st.st_size

    def _load(self, initial: bool = False) -> bool:
        sig = self._signature()
        self._file_sig = sig
        if sig is None and initial and self._recover():
            sig = self._file_sig = self._signature()
        if sig is None:
            if initial:
                self.file_problem = ''
                if not self.recovery:
                    self.log.info(f'no calibration file {self.path} yet: run the calibration '
                                  '(ros2 service call .../calibrate_bar std_srvs/srv/Trigger)')
            return False
        try:
            cal = load_calibration(self.path)
        except ConfigError as exc:
            self.file_problem = f'calibration file refused: {exc}'
            self.log.error(self.file_problem + ('' if initial else '; keeping the calibration in use'))
            self.events.note('file', self.file_problem, ERROR)
            return False
        if cal.device and cal.device != self.device.name:
            self.file_problem = (f'calibration file refused: {self.path} is for device '
                                 f'{cal.device!r}, not {self.device.name!r}')
            self.log.error(self.file_problem)
            self.foreign = True
            return False
        problem = self._refusal(cal)
        if problem is not None:
            self.file_problem, self.foreign = problem, True
            self.log.error(problem)
            self.events.note('file', problem, ERROR)
            return False
        self.file_problem, self.foreign = '', False
        with self._lock:
            self.routine.set_calibration(cal)
        if self.binding_note:
            self.log.error(self.binding_note)
        self.log.info(f'calibration loaded from {self.path} (created {cal.created or "?"}, '
                      f'{"valid" if cal.valid else "INVALID: re-reference the bars"}'
                      + (f', made with {cal.terminal.describe()}' if cal.terminal else '') + ')')
        return True

    def _recover(self) -> bool:
        """The file is missing: restore what an interrupted save left (its ``.bak``, the
        complete earlier calibration; :func:`recover_interrupted_save`), saying so in the log
        and, until the next save, in the diagnostics (WARN; ERROR when it cannot be used).
        True when the file is back."""
        try:
            done = recover_interrupted_save(self.path)
        except OSError as exc:  # the backup is fine, but the file cannot be written back
            self._cannot_save(exc)
            return False
        if done is None:
            return False
        self.recovery = done.describe(self.path)
        if done.calibration is None:
            self.log.error(self.recovery)
            return False
        self.log.warn(self.recovery)
        return True

    def start(self) -> None:
        """Publish the calibration in use (call once the publisher exists)."""
        if self.routine.calibration is not None:
            self.publish(self.routine.calibration)

    def poll_file(self) -> None:
        """Reload the file when someone else changed it (call about once a second)."""
        sig = self._signature()
        if sig == self._file_sig or sig is None:
            return
        if self._load() and self.routine.calibration is not None:
            self.publish(self.routine.calibration)

    def _persist(self, cal: Calibration) -> str:
        """Save atomically, bound to the terminal; a corrupt file in the way is kept as
        ``.corrupt``, one refused for its terminal or device as ``.foreign``. Returns a note;
        raises OSError when it cannot be written."""
        note = ''
        if self.path.exists():
            keep = ''
            try:
                load_calibration(self.path)
                keep = 'foreign' if self.foreign else ''
            except ConfigError:
                keep = 'corrupt'
            if keep:
                kept = self.path.with_name(f'{self.path.name}.{keep}')
                os.replace(self.path, kept)
                note = f' (the {keep} file was kept as {kept.name})'
        existed = self.path.exists()
        self.bind(cal).save(self.path)
        self._file_sig = self._signature()
        self.file_problem, self.foreign, self.save_problem, self.recovery = '', False, '', ''
        return (f' Saved to {self.path}' + (f' (previous kept as {self.path.name}.bak)' if existed else '')
                + note + '.')

    def _save(self, cal: Calibration) -> str:
        """:meth:`_persist`, saying (note, log, diagnostics) when the file cannot be written."""
        try:
            return self._persist(cal)
        except OSError as exc:
            self._cannot_save(exc)
            return (f' COULD NOT SAVE to {self.path}: {why_not(exc)}; the calibration is in use '
                    'but not on disk: fix the folder and capture again.')

    # -- samples and events --------------------------------------------------------------------
    def feed(self, stamps: NDArray[np.int64], counts: NDArray[np.float64]) -> None:
        self.buffer.append(stamps, counts)
        if len(counts):
            self._check_alignment(counts[-1])

    def _check_alignment(self, counts: NDArray[np.float64]) -> None:
        """Keep the calibration's counts in this driver session's 2^32 window (see
        :meth:`CalibrationRoutine.align`); publish (not save) a moved calibration."""
        cal = self.routine.calibration
        if cal is None or not cal.valid:
            return
        half = float(1 << (self.device.counter_bits - 1))
        for name, bar in cal.bars.items():
            k = self.device.channel_names.index(name)
            if abs(counts[k] - bar.counts[0]) > half:
                break
        else:
            return
        with self._lock:
            moved = self.routine.align(counts)
        if moved is not None:
            self.log.info('calibration counts of ' + ', '.join(moved.quality['aligned_to_session'])
                          + ' moved by whole turns of the 32-bit counters to this driver session '
                          '(the counters were near their wrap when the session started)')
            self.publish(moved)

    def on_counter_reset(self, stamp_ns: int) -> None:
        """The terminal's counters restarted: the calibration is invalid until re-referenced."""
        self.buffer.note_reset(stamp_ns)
        with self._lock:
            cal = self.routine.invalidate('terminal counter reset (power loss or watchdog)', now_iso())
            if cal is None:
                return
            self._save(cal)
        self.events.note('reset', 'terminal counter reset: calibration invalid until every bar is '
                         're-referenced', ERROR)
        self.log.warn('terminal counter reset: the calibration is invalid until the bars are '
                      're-referenced (call calibrate_bar; mode auto re-references)')
        self.publish(cal)

    # -- the service ---------------------------------------------------------------------------
    def trigger(self, bar: str, pair: str, mode: str) -> tuple[bool, str]:
        """One call of /mmd/calibrate_bar: (success, message)."""
        with self._lock:
            was_valid = self.routine.calibration is not None and self.routine.calibration.valid
            try:
                step = self.routine.next_step(bar, pair, mode)
            except CalibrationError as exc:
                return self._answer(False, f'refused: {exc}')
            if step is None:
                cal = self.routine.calibration
                missing = self.routine.missing_bars()
                if cal is not None and cal.valid and not missing:
                    return self._answer(False, 'nothing to capture: the calibration is complete '
                                        'and valid. To calibrate again set mode:=full (or bar:=<bar>) '
                                        'and call again; call reset_session to start over.')
                return self._answer(False, 'nothing to capture in this mode; set mode:=full')
            window = self.buffer.window(self.cfg.settle_window_s)
            ambient = None if math.isnan(self.cfg.ambient_c) else self.cfg.ambient_c
            res = self.routine.capture(step, window, now_iso(), ambient_c=ambient, bar=bar,
                                       pair=pair, mode=mode)
            message = res.message
            if res.calibration is not None:
                note = self._save(res.calibration)
                head, sep, tail = message.partition(' Next: ')
                message = head + note + (sep + tail if sep else '')
                self.publish(res.calibration)
                if res.calibration.valid and not was_valid and self.on_valid is not None:
                    self.on_valid()
            return self._answer(res.accepted, message)

    def _answer(self, ok: bool, message: str) -> tuple[bool, str]:
        if ok:
            self.captures += 1
            self.log.info(f'calibrate_bar: {message}')
        else:
            self.refused += 1
            self.log.warn(f'calibrate_bar: {message}')
        self.last_message = message
        return ok, message

    def reset_session(self) -> tuple[bool, str]:
        with self._lock:
            self.routine.reset_session()
        return True, 'session points forgotten; the calibration file is unchanged'

    def next_text(self, bar: str = '', pair: str = '', mode: str = 'auto') -> str:
        try:
            step = self.routine.next_step(bar, pair, mode)
        except CalibrationError as exc:
            return str(exc)
        return step.describe(self.device) if step is not None else 'nothing (calibration complete)'

    # -- status --------------------------------------------------------------------------------
    def report(self, bar: str = '', pair: str = '', mode: str = 'auto') -> Report:
        cal = self.routine.calibration
        r = Report('calibration', OK, 'calibration valid')
        if self.file_problem:
            r.worse(ERROR, self.file_problem)
        if self.binding_note:
            r.worse(ERROR, self.binding_note)
        if self.save_problem:
            r.worse(ERROR, self.save_problem)
        if self.recovery:
            r.worse(WARN if cal is not None else ERROR, self.recovery)
        if cal is None:
            r.worse(WARN, 'no calibration: run the calibration routine (calibrate_bar)')
        else:
            missing = self.routine.missing_bars()
            if not cal.valid:
                r.worse(ERROR, 'calibration invalid after a terminal counter reset: re-reference '
                        + ', '.join(self.routine.pending) + ' (calibrate_bar)')
            elif missing:
                r.worse(WARN, f'calibration incomplete: no CDF for {", ".join(missing)}')
        self.events.apply(r)
        made_with = cal.terminal if cal is not None else None
        r.values.update({
            'file': str(self.path),
            'saved': not self.save_problem,
            'recovered': self.recovery,
            'terminal': self.terminal.describe() if self.terminal is not None else 'unknown',
            'made_with': made_with.describe() if made_with is not None else 'not recorded',
            'valid': bool(cal is not None and cal.valid and not self.routine.missing_bars()),
            'created': cal.created if cal is not None else '',
            'age_s': round(calibration_age_s(cal), 1),
            'bars': ' '.join(cal.bars) if cal is not None else '',
            'pending_re_reference': ' '.join(self.routine.pending),
            'next_step': self.next_text(bar, pair, mode),
            'captures': self.captures,
            'refused': self.refused,
            'last_message': self.last_message,
        })
        if cal is not None:
            for name, zero in cal.thermal_zero_m.items():
                r.values[f'thermal_zero_{name}_um'] = round(zero * 1e6, 4)
        return r


class CalibrationService:
    """``calibrate_bar`` and ``calibration/reset_session`` (std_srvs/Trigger) and the ``bar`` /
    ``pair`` / ``mode`` parameters, for the nodes that own a :class:`CalibrationStage`
    (``calibration_node`` and ``pose_node``). The node sets ``self.calibration`` and
    ``self._params`` and calls :meth:`_create_calibration_service`."""

    calibration: CalibrationStage
    _params: dict[str, Param]

    def _create_calibration_service(self) -> None:
        self.create_service(Trigger, 'calibrate_bar', self._calibrate_bar)
        self.create_service(Trigger, 'calibration/reset_session', self._reset_session)

    def _before_capture(self) -> None:
        """Hook: make sure every sample received so far is in the capture window."""

    def _selection(self) -> tuple[str, str, str]:
        return (self.get_parameter('bar').value, self.get_parameter('pair').value,
                self.get_parameter('mode').value)

    def _calibrate_bar(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._before_capture()
        bar, pair, mode = self._selection()
        response.success, response.message = self.calibration.trigger(bar, pair, mode)
        if response.success and pair:
            self.set_parameters([Parameter('pair', Parameter.Type.STRING, '')])
        return response

    def _reset_session(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.calibration.reset_session()
        return response

    def _refuse_parameter(self, name: str, value: Any) -> str | None:
        """Why a new parameter value is refused (named, with what is allowed), or None."""
        p = self._params.get(name)
        if p is None:
            return None
        why = check(p, value)
        if why:
            return why
        if name in ('bar', 'pair') and value:
            try:
                self.calibration.routine.next_step(value if name == 'bar' else '',
                                                   value if name == 'pair' else '', 'full')
            except MmdError as exc:
                return f'parameter {name}: {exc}'
        return None
