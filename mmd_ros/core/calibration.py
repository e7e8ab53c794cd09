"""Bar calibration on the reference plate (section 3.2) and the centre distance function, Eq. (10).

A :class:`Calibration` holds, for every bar channel (measuring and reference bars), the seven
calibration points (q_i^j, d_r^j): the averaged encoder count with the bar on socket pair j and
that pair's reference distance. It is saved as YAML, atomically, with the previous file kept as
a backup; a corrupt file is refused with its name.

Counts mean something only on the terminal and the bars they were read from: a calibration
records the terminal it was made with (:class:`TerminalBinding`: serial number, simulated or
not, what is on each channel), and :func:`binding_problem` says why it must not be used with
another one.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core import validate
from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.errors import CalibrationError, ConfigError
from mmd_ros.core.uncertainty import CalibrationUncertainty
from mmd_ros.core.units import M_PER_MM
from mmd_ros.core.yamlio import (
    atomic_write_text, interrupted_saves, parse_yaml, read_text_file, read_yaml,
)

__all__ = ['AMBIENT_RANGE_C', 'BarCalibration', 'Calibration', 'CdfBank', 'CentreDistanceFunction',
           'RecoveredCalibration', 'TerminalBinding', 'binding_problem', 'calibration_for',
           'channel_roles', 'iso_utc', 'load_calibration', 'recover_interrupted_save',
           'replacement_problem', 'unix_seconds']

FloatArray = NDArray[np.float64]
#: The keys of a calibration file, of one bar's points and of the terminal it was made with;
#: anything else is refused as a typo (``quality`` is free-form: the routine's notes).
CALIBRATION_KEYS = ('format_version', 'device', 'created', 'valid', 'ambient_c', 'thermal_zero_um',
                    'bars', 'quality', 'terminal', 'uncertainty')
BAR_KEYS = ('pairs', 'counts', 'distances_mm')
#: Room temperatures a calibration may state (``ambient_c``) [°C].
AMBIENT_RANGE_C = (-100.0, 200.0)
TERMINAL_KEYS = ('serial', 'simulated', 'channels')


class CentreDistanceFunction:
    """Eq. (10): piecewise-linear map from encoder counts to centre distance.

    Built from calibration points (q^j, d_r^j), j = 1..n (n = 7 on the prototype); between two
    adjacent points the distance is interpolated linearly. Counts must be strictly monotonic
    in the distance (increasing or decreasing: a bar may count down as it lengthens), or the
    points are refused.

    Outside the calibrated span Eq. (10) clamps to d_r^1 or d_r^7. We extrapolate with the end
    segment instead, which keeps the measurement continuous and usable a little beyond the
    span, and flag the sample as out of range so that it is never taken for a calibrated one.
    """

    def __init__(self, counts: ArrayLike, distances_m: ArrayLike) -> None:
        q = np.asarray(counts, dtype=np.float64).ravel()
        d = np.asarray(distances_m, dtype=np.float64).ravel()
        if q.shape != d.shape or q.size < 2:
            raise CalibrationError(
                f'need at least two (count, distance) points of equal number, got {q.size} and {d.size}')
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(d))):
            raise CalibrationError('calibration points must be finite')
        order = np.argsort(d)
        q, d = q[order], d[order]
        if np.any(np.diff(d) <= 0):
            raise CalibrationError(f'reference distances must be distinct, got {d.tolist()}')
        dq = np.diff(q)
        if not (np.all(dq > 0) or np.all(dq < 0)):
            raise CalibrationError(
                'counts are not strictly monotonic in the reference distance '
                f'(counts {q.astype(np.int64).tolist()} for distances {np.round(d / M_PER_MM, 4).tolist()} mm): '
                'a bar was misplaced or moved during a capture; repeat those placements')
        if dq[0] < 0:
            q, d = q[::-1], d[::-1]
        self.counts = q
        self.distances_m = d
        self._slope = np.diff(d) / np.diff(q)

    @property
    def span_counts(self) -> tuple[float, float]:
        return float(self.counts[0]), float(self.counts[-1])

    def __call__(self, counts: ArrayLike) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Centre distances [m] and an out-of-range flag for each count.

        counts : array_like, any shape — encoder counts
        returns : (distances_m, out_of_range), both of the shape of ``counts``
        """
        c = np.asarray(counts, dtype=np.float64)
        idx = np.clip(np.searchsorted(self.counts, c, side='right') - 1, 0, self.counts.size - 2)
        dist = self.distances_m[idx] + self._slope[idx] * (c - self.counts[idx])
        out = (c < self.counts[0]) | (c > self.counts[-1])
        return dist, out

    def inverse(self, distances_m: ArrayLike) -> FloatArray:
        """Counts (real-valued) that map to the given distances; the inverse of ``__call__``."""
        x = np.asarray(distances_m, dtype=np.float64)
        d, q = self.distances_m, self.counts
        if d[0] > d[-1]:  # a bar that counts down as it lengthens
            d, q = d[::-1], q[::-1]
        idx = np.clip(np.searchsorted(d, x, side='right') - 1, 0, q.size - 2)
        return q[idx] + (x - d[idx]) * (q[idx + 1] - q[idx]) / (d[idx + 1] - d[idx])


@dataclass(frozen=True)
class BarCalibration:
    """Calibration points of one bar channel: ``counts[j]`` read on ``pairs[j]`` at ``distances_m[j]``."""

    channel: str
    pairs: tuple[str, ...]
    counts: tuple[float, ...]
    distances_m: tuple[float, ...]

    def cdf(self, growth: float = 1.0) -> CentreDistanceFunction:
        """Eq. (10) of this bar; ``growth`` scales the reference distances (the reference plate's
        expansion from the CMM's 20 °C to the temperature of the calibration, see
        :func:`mmd_ros.core.thermal.reference_plate_growth`)."""
        return CentreDistanceFunction(self.counts, np.asarray(self.distances_m) * growth)


def channel_roles(channels: Any) -> dict[str, str]:
    """What is on each channel of a device (:class:`~mmd_ros.core.device.Channel` list):
    ``{'bar1': 'measuring bar 1', 'ref1': 'reference bar on dr4', 'ch8': 'unused'}``."""
    out = {}
    for c in channels:
        if c.role == 'measuring':
            out[c.name] = f'measuring bar {c.bar}'
        elif c.role == 'reference':
            out[c.name] = f'reference bar on {c.pair}'
        else:
            out[c.name] = str(c.role)
    return out


@dataclass(frozen=True)
class TerminalBinding:
    """The encoder terminal and channel map a calibration was made with.

    serial : the terminal's serial number ('' unknown)
    simulated : a simulated terminal (the digital twin), not hardware
    channels : what was on each channel (:func:`channel_roles`)
    """

    serial: str
    simulated: bool
    channels: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {'serial': self.serial, 'simulated': self.simulated, 'channels': dict(self.channels)}

    @classmethod
    def from_dict(cls, data: Any, source: str) -> TerminalBinding:
        if not isinstance(data, dict):
            raise ConfigError(source, 'terminal', 'must map serial, simulated and channels')
        validate.known_keys(data, TERMINAL_KEYS, source, 'terminal.')
        serial, simulated = data.get('serial', ''), data.get('simulated')
        channels = data.get('channels') or {}
        if not isinstance(serial, str):
            raise ConfigError(source, 'terminal.serial', f'must be a string, got {serial!r}')
        if not isinstance(simulated, bool):
            raise ConfigError(source, 'terminal.simulated', f'must be true or false, got {simulated!r}')
        if not isinstance(channels, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                     for k, v in channels.items()):
            raise ConfigError(source, 'terminal.channels', 'must map channel names to what is on them')
        return cls(serial, simulated, dict(channels))

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def from_yaml(cls, text: str, source: str) -> TerminalBinding:
        return cls.from_dict(parse_yaml(text, source), source)

    def describe(self) -> str:
        return ('the simulated terminal ' if self.simulated else 'terminal ') + (self.serial or '(serial unknown)')


def binding_problem(calibration: Calibration, terminal: TerminalBinding) -> str | None:
    """Why ``calibration`` must not be used with ``terminal``, or None.

    Refused: a calibration made on a simulated terminal (recorded, or its ``quality.source``
    says it came from the digital twin) used with hardware; one made with another terminal
    (serial numbers differ, when both are known); one whose calibrated channels carried other
    bars. A calibration that records no terminal (older files) is judged by its source only.
    """
    b = calibration.terminal
    source = str(calibration.quality.get('source', '')) if calibration.quality else ''
    simulated = b.simulated if b is not None else 'digital twin' in source
    if simulated and not terminal.simulated:
        return (f'it was made on a simulated terminal ({source or (b.describe() if b else "")}), '
                f'and this is real hardware ({terminal.describe()})')
    if b is None:
        return None
    if b.serial and terminal.serial and b.serial != terminal.serial:
        return f'it was made with {b.describe()}, and this is {terminal.describe()}'
    if not b.simulated and terminal.simulated:
        return f'it was made with real hardware ({b.describe()}), and this is {terminal.describe()}'
    moved = [f'{name} ({b.channels[name]} then, {terminal.channels.get(name, "absent")} now)'
             for name in calibration.bars
             if name in b.channels and b.channels[name] != terminal.channels.get(name)]
    if moved:
        return 'its channels carried other bars: ' + ', '.join(moved)
    return None


def replacement_problem(recorded: Calibration | None, given: Calibration) -> str | None:
    """Why ``given`` must not read the counts of a log recorded under the calibration
    ``recorded`` (the log's own), or None: the log's calibration names the terminal its counts
    came from, and ``given`` was made with another (:func:`binding_problem`). None when the
    log's calibration is missing or names no terminal."""
    if recorded is None or recorded.terminal is None:
        return None
    problem = binding_problem(given, recorded.terminal)
    if problem is None:
        return None
    return (f'the log\'s counts came from {recorded.terminal.describe()} (its own calibration '
            f'says so), and the calibration given cannot read them: {problem}')


def calibration_for(recorded: Calibration | None, given: Calibration | None, where: str
                    ) -> Calibration:
    """The calibration to read a log's counts with: ``given`` (a file passed for the log) or
    the log's own, ``recorded``. Raises :class:`CalibrationError` naming ``where`` when there
    is neither, or when ``given`` cannot read counts of the terminal the log's own names
    (:func:`replacement_problem`)."""
    if given is not None:
        problem = replacement_problem(recorded, given)
        if problem is not None:
            raise CalibrationError(f'{where}: calibration refused: {problem}')
        return given
    if recorded is None:
        raise CalibrationError(f'{where} carries no calibration; pass --calibration FILE')
    return recorded


def unix_seconds(when: str) -> float | None:
    """An ISO 8601 time as a Unix time [s] (one without a zone taken as UTC), or None when
    the text is not one."""
    try:
        stamp = datetime.fromisoformat(when)
    except (TypeError, ValueError):
        return None
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    return stamp.timestamp()


def iso_utc(unix_s: float) -> str:
    """A Unix time [s] as ISO 8601 text in UTC, to the millisecond (what ``created`` holds)."""
    return datetime.fromtimestamp(unix_s, timezone.utc).isoformat(timespec='milliseconds')


@dataclass(frozen=True)
class Calibration:
    """The calibration of a whole device.

    bars : per channel name (measuring and reference bars)
    thermal_zero_m : per reference channel, the offset of Eq. (11) at the thermal zero,
        f_ref(q_ref) - d_r when the zero was set; Eq. (11) subtracts it
    ambient_c : ambient temperature when calibrated [°C] (entered by the user; the plates'
        expansion is counted from the CMM's 20 °C), or None when not known
    created : free text time stamp (ISO 8601)
    valid : False after a terminal counter reset until the bars are re-referenced
    terminal : the terminal and channel map it was made with, or None (not recorded)
    uncertainty : what the routine measured about its own points (read noise, friction
        hysteresis and seating repeatability of two-sided captures); empty for old files
    """

    device: str
    bars: dict[str, BarCalibration]
    thermal_zero_m: dict[str, float] = field(default_factory=dict)
    ambient_c: float | None = None
    created: str = ''
    valid: bool = True
    quality: dict[str, Any] = field(default_factory=dict)
    terminal: TerminalBinding | None = None
    uncertainty: CalibrationUncertainty = field(default_factory=CalibrationUncertainty)

    @property
    def created_s(self) -> float | None:
        """When the calibration was made (``created``) as a Unix time [s], or None when it
        does not say (:func:`unix_seconds`)."""
        return unix_seconds(self.created)

    def cdfs(self, channels: list[str], growth: float = 1.0) -> list[CentreDistanceFunction]:
        missing = [c for c in channels if c not in self.bars]
        if missing:
            raise CalibrationError(f'calibration of {self.device!r} has no points for {missing}')
        return [self.bars[c].cdf(growth) for c in channels]

    # -- files ---------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            'format_version': 1,
            'device': self.device,
            'created': self.created,
            'valid': self.valid,
            'ambient_c': self.ambient_c,
            'thermal_zero_um': {k: v / 1e-6 for k, v in self.thermal_zero_m.items()},
            'bars': {
                name: {
                    'pairs': list(b.pairs),
                    'counts': [int(c) if float(c).is_integer() else float(c) for c in b.counts],
                    'distances_mm': [d / M_PER_MM for d in b.distances_m],
                } for name, b in self.bars.items()
            },
            'quality': self.quality,
            **({'terminal': self.terminal.to_dict()} if self.terminal is not None else {}),
            'uncertainty': self.uncertainty.to_dict(),
        }

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def key(self) -> str:
        """Identity of the calibration: a hash of its file contents (12 hex digits), as a
        model file names the calibration its per-calibration parameters were fitted with."""
        return hashlib.sha256(self.to_yaml().encode()).hexdigest()[:12]

    @classmethod
    def from_dict(cls, data: Any, source: str = '<calibration>') -> Calibration:
        """Validate a calibration mapping (as loaded from YAML); every field is checked and a
        bad one raises :class:`ConfigError` naming it."""
        f = validate.Fields(source)
        if not isinstance(data, dict) or data.get('format_version') != 1:
            raise f.fail('format_version', 'not a calibration file of format 1')
        f.known_keys(data, CALIBRATION_KEYS)
        bars_raw = f.get(data, 'bars')
        if not isinstance(bars_raw, dict) or not bars_raw:
            raise f.fail('bars', 'must map channel names to calibration points')
        bars = {}
        for name, item in bars_raw.items():
            path = f'bars.{name}'
            f.known_keys(validate.mapping(item, source, path), BAR_KEYS, path)
            pairs = f.get(item, 'pairs', path)
            if not isinstance(pairs, list) or not all(isinstance(p, str) for p in pairs):
                raise f.fail(f'{path}.pairs', f'must be a list of reference pair names, got {pairs!r}')
            counts = tuple(f.floats(item, 'counts', path, (-1,)).tolist())
            dist = tuple(d * M_PER_MM for d in f.floats(item, 'distances_mm', path, (-1,)).tolist())
            if not (len(pairs) == len(counts) == len(dist)):
                raise f.fail(path, 'pairs, counts and distances_mm must be of equal length')
            bar = BarCalibration(str(name), tuple(pairs), counts, dist)
            try:
                bar.cdf()
            except CalibrationError as exc:
                raise f.fail(path, str(exc)) from None
            bars[str(name)] = bar
        zero = f.mapping(data, 'thermal_zero_um') if data.get('thermal_zero_um') is not None else {}
        ambient = data.get('ambient_c')
        ambient_low, ambient_high = AMBIENT_RANGE_C
        quality = data.get('quality') or {}
        return cls(
            device=str(data.get('device', '')),
            bars=bars,
            thermal_zero_m={str(k): f.number(zero, k, 'thermal_zero_um') * 1e-6 for k in zero},
            ambient_c=None if ambient is None else f.number(data, 'ambient_c', low=ambient_low,
                                                            high=ambient_high),
            created=str(data.get('created', '')),
            valid=f.boolean(data, 'valid', default=True),
            quality=dict(f.mapping(data, 'quality') if quality else {}),
            terminal=(TerminalBinding.from_dict(data['terminal'], source)
                      if data.get('terminal') is not None else None),
            uncertainty=CalibrationUncertainty.from_dict(data.get('uncertainty'), source),
        )

    @classmethod
    def from_yaml(cls, text: str, source: str = '<calibration>') -> Calibration:
        return cls.from_dict(parse_yaml(text, source), source)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write atomically; an existing file is kept as ``.bak``."""
        return atomic_write_text(path, self.to_yaml(), backup=True)


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file; a missing or corrupt one raises :class:`ConfigError` naming it."""
    return Calibration.from_dict(read_yaml(path), str(path))


@dataclass(frozen=True)
class RecoveredCalibration:
    """What :func:`recover_interrupted_save` did.

    calibration : the calibration restored to the file (None when nothing could be restored)
    source : the file it came from (``<file>.bak``), or None
    ignored : what else the interrupted save left (temporaries), not used
    problem : why the backup could not be used ('' when it was)
    """

    calibration: Calibration | None
    source: Path | None
    ignored: tuple[Path, ...]
    problem: str = ''

    def describe(self, path: str | os.PathLike[str]) -> str:
        """One line for the log and the diagnostics."""
        names = ', '.join(q.name for q in self.ignored)
        rest = (f'; not used: {names} (a temporary file may be incomplete: check it)'
                if self.ignored else '')
        if self.source is None:
            return (f'calibration file {path} is missing; an interrupted save left only {names}, '
                    f'not used (a temporary file may be incomplete): check it and copy it to '
                    f'{Path(path).name} to use it')
        if self.calibration is None:
            return (f'calibration file {path} is missing; an interrupted save left '
                    f'{self.source.name}, which cannot be used: {self.problem}{rest}')
        return (f'calibration file {path} was missing (an interrupted save): restored the complete '
                f'earlier calibration from {self.source.name} (created {self.calibration.created or "?"})'
                + rest)


def recover_interrupted_save(path: str | os.PathLike[str]) -> RecoveredCalibration | None:
    """Restore a calibration file that a save killed mid-way left missing.

    The writer of older versions moved the file to ``<file>.bak`` and then renamed the new one
    in; killed between the two, only the backup and a temporary remain. When ``path`` does not
    exist and ``<file>.bak`` does, the backup — a file that was complete and in use — is
    validated (every field, :meth:`Calibration.from_dict`) and written back to ``path``
    atomically; the backup stays. A temporary is never used: it may have been cut short, and a
    YAML file cut after a complete entry still parses. Returns None when ``path`` exists or
    nothing was left beside it; otherwise what was done (``calibration`` None when the backup
    is not a usable calibration, and then nothing is written).
    """
    p = Path(path)
    if p.exists():
        return None
    left = interrupted_saves(p)
    backup = p.with_name(p.name + '.bak')
    others = tuple(q for q in left if q != backup)
    if backup not in left:
        return RecoveredCalibration(None, None, others, 'no backup') if others else None
    try:
        text = read_text_file(backup, 'calibration')
        cal = Calibration.from_yaml(text, str(backup))
    except ConfigError as exc:
        return RecoveredCalibration(None, backup, others, str(exc))
    atomic_write_text(p, text)
    return RecoveredCalibration(cal, backup, others)


class CdfBank:
    """Several CDFs evaluated together: column k of the input through ``cdfs[k]``.

    Equivalent to calling each :class:`CentreDistanceFunction` on its column, but one pass of
    numpy for all bars, which matters for a single streaming sample as much as for a batch.
    Every CDF must have the same number of points.
    """

    def __init__(self, cdfs: list[CentreDistanceFunction]) -> None:
        sizes = {c.counts.size for c in cdfs}
        if len(sizes) != 1:
            raise CalibrationError(f'all bars need the same number of calibration points, got {sorted(sizes)}')
        self.counts = np.stack([c.counts for c in cdfs])          # (k, n)
        self.distances_m = np.stack([c.distances_m for c in cdfs])  # (k, n)
        self.slopes = np.diff(self.distances_m, axis=1) / np.diff(self.counts, axis=1)
        self._rows = np.arange(len(cdfs))

    def __call__(self, counts: ArrayLike, *, compiled: bool | None = None
                 ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """counts : array_like, shape (..., k) → (distances_m, out_of_range), shape (..., k).

        compiled : evaluate with :mod:`mmd_ros.core.compiled` (default: when it is in use)
        """
        c = np.asarray(counts, dtype=np.float64)
        if use_compiled(compiled) and c.ndim == 2 and c.shape[1] == len(self._rows):
            c = np.ascontiguousarray(c)
            dist = np.empty_like(c)
            out = np.empty(c.shape, dtype=bool)
            fast.cdf_eval(c, self.counts, self.distances_m, self.slopes, dist, out)
            return dist, out
        n = self.counts.shape[1]
        idx = np.clip(np.sum(c[..., None] >= self.counts, axis=-1) - 1, 0, n - 2)
        q0 = self.counts[self._rows, idx]
        dist = self.distances_m[self._rows, idx] + self.slopes[self._rows, idx] * (c - q0)
        out = (c < self.counts[:, 0]) | (c > self.counts[:, -1])
        return dist, out
