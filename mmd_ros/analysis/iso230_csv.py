"""ISO 230-2 from a table of readings: the CSV exports of laser interferometers and rotary
calibrators, evaluated exactly as a log (:mod:`mmd_ros.analysis.iso230`) and reported the same
way (:class:`~mmd_ros.analysis.iso230_report.Iso230Report`). Documented for users in
``msg_docs/analysis.md`` ("Laser and calibrator data").

Three layouts, told apart by their header:

- **long**: one row per approach — ``target``, ``direction``, ``deviation`` (or ``position``,
  the instrument's reading, from which deviation = position - target), optionally ``run`` (the
  cycle j; else numbered in the order of the rows) and ``instrument`` (several instruments in
  one table, as Tables 3–4 compare an MMD with a laser);
- **wide**: one row per target, one column per run and direction — the layout of the paper's
  Tables 3–4 evaluation and of most calibration reports: ``target``, ``+1 … +n``, ``-1 … -n``
  (or ``up1``, ``fwd1``, ``↑1`` …, ``down1``, ``bwd1``, ``↓1`` …);
- **series**: a time series — ``time`` and one or more columns of the axis position read by
  each instrument; the dwells at the targets are found as in a log.

Units go in the header as ``name [unit]``, ``name (unit)`` or ``name_unit``; without them
positions are in mm and deviations in µm on a linear axis, degrees and arc-seconds on a rotary
one. Columns may be separated by commas, semicolons or tabs; with semicolons or tabs a decimal
comma is read too. Lines starting with ``#`` are comments.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.iso230 import AXIS_NAMES, IsoResult, axis_index, evaluate, evaluate_run
from mmd_ros.analysis.iso230_report import Iso230Report, parse_targets
from mmd_ros.core.units import ARCSEC_PER_RAD, M_PER_MM, M_PER_UM

__all__ = ['LAYOUTS', 'IsoTable', 'iso230_of_csv', 'read_iso230_table', 'source_kind']

FloatArray = NDArray[np.float64]

#: The table layouts :func:`read_iso230_table` accepts.
LAYOUTS = ('long', 'wide', 'series')

#: The first bytes of every MCAP file.
MCAP_MAGIC = b'\x89MCAP0\r\n'

#: Length units [m per unit] and angle units [rad per unit] a header may name.
_LENGTH = {'m': 1.0, 'mm': M_PER_MM, 'um': M_PER_UM, 'µm': M_PER_UM, 'μm': M_PER_UM,
           'nm': 1e-9}
_ANGLE = {'rad': 1.0, 'mrad': 1e-3, 'urad': 1e-6, 'µrad': 1e-6, 'μrad': 1e-6,
          'deg': math.pi / 180, '°': math.pi / 180, 'arcsec': 1.0 / ARCSEC_PER_RAD,
          '″': 1.0 / ARCSEC_PER_RAD, '"': 1.0 / ARCSEC_PER_RAD}
_TIME = {'s': 1.0, 'ms': 1e-3}
_UNITS = sorted({**_LENGTH, **_ANGLE, **_TIME}, key=len, reverse=True)
_UNIT_RE = re.compile(r'^(?P<name>.*?)\s*(?:\[(?P<b>[^\]]+)\]|\((?P<p>[^)]+)\)|_(?P<u>'
                      + '|'.join(re.escape(u) for u in _UNITS) + r'))$')

_UP = {'+', 'up', '↑', 'forward', 'fwd', 'f', 'pos', 'positive', '1', '+1', 'plus'}
_DOWN = {'-', 'down', '↓', 'backward', 'reverse', 'rev', 'bwd', 'b', 'neg', 'negative', '-1',
         'minus', '−'}
_RUN_RE = re.compile(r'^(?P<dir>\+|-|−|↑|↓|up|down|fwd|bwd|forward|backward|reverse|pos|neg)'
                     r'\s*_?\s*(?:run\s*_?\s*)?(?P<run>\d+)$')
_DEVIATION = ('deviation', 'error', 'dev')
_POSITION = ('position', 'actual', 'reading', 'measured')
_TIME_NAMES = ('time', 't', 'timestamp')


def source_kind(path: str | Path) -> str:
    """``'mcap'`` or ``'csv'``, from the file's content (not its name): an MCAP file starts with
    its magic bytes, a table is text. Anything else is refused with the reason."""
    p = Path(path)
    try:
        with open(p, 'rb') as handle:
            head = handle.read(65536)
    except FileNotFoundError:
        raise AnalysisError(f'{p}: no such file') from None
    except OSError as exc:
        raise AnalysisError(f'{p}: cannot be read ({exc.strerror})') from None
    if head.startswith(MCAP_MAGIC):
        return 'mcap'
    if not head.strip():
        raise AnalysisError(f'{p} is empty: expected an MCAP log or a CSV table')
    if b'\x00' in head or head.startswith(b'\x89MCAP'):
        raise AnalysisError(f'{p} is neither an MCAP log (its first bytes are not the MCAP magic) '
                            'nor a CSV table (it is binary)')
    return 'csv'


@dataclass(frozen=True)
class _Column:
    """A header cell: its position, lower-case name, unit (as written) and scale to SI."""

    index: int
    name: str
    unit: str | None
    scale: float | None


@dataclass
class IsoTable:
    """An ISO 230-2 table as read: per instrument the targets and deviations (long and wide
    layouts) or the time series of readings (series layout). SI units (m or rad, s).

    targets : instrument -> (m,) target positions
    up, down : instrument -> (m, n) deviations per approach, NaN where missing
    times_s : (N,) sample times and readings : instrument -> (N,) positions (series)
    """

    path: Path
    layout: str
    axis: str
    targets: dict[str, FloatArray]
    up: dict[str, FloatArray]
    down: dict[str, FloatArray]
    times_s: FloatArray | None = None
    readings: dict[str, FloatArray] | None = None


class _Reader:
    """Parses one table, keeping the file name and line numbers for the error messages."""

    def __init__(self, path: Path) -> None:
        self.path = path
        raw = path.read_bytes()
        try:
            text = raw.decode('utf-8-sig')
        except UnicodeDecodeError:
            text = raw.decode('latin-1')      # Windows exports: µ and ° are single bytes there
        rows = [(k + 1, line) for k, line in enumerate(text.splitlines())]
        self.lines = [(n, line) for n, line in rows if line.strip() and not line.lstrip().startswith('#')]
        if not self.lines:
            raise self.error('holds no table (only blank or comment lines)')
        header = self.lines[0][1]
        counts = {d: header.count(d) for d in (',', ';', '\t')}
        self.delimiter = max(counts, key=lambda d: counts[d])
        if counts[self.delimiter] == 0:
            raise self.error(f'line {self.lines[0][0]}: the header has one column only; columns '
                             'must be separated by commas, semicolons or tabs')
        parsed = list(csv.reader([line for _, line in self.lines], delimiter=self.delimiter))
        self.header = [cell.strip() for cell in parsed[0]]
        self.rows = [(n, [c.strip() for c in cells]) for (n, _), cells in zip(self.lines[1:], parsed[1:])]
        if not self.rows:
            raise self.error('has a header but no data rows')
        for n, cells in self.rows:
            if len(cells) != len(self.header):
                raise self.error(f'line {n} has {len(cells)} cells, the header {len(self.header)}')
        self.columns = [self._column(k, cell) for k, cell in enumerate(self.header)]

    def error(self, problem: str) -> AnalysisError:
        return AnalysisError(f'{self.path}: {problem}')

    def _column(self, index: int, cell: str) -> _Column:
        text = cell.strip().strip('"').strip()
        m = _UNIT_RE.match(text)
        if m and m.group('name').strip():
            unit = (m.group('b') or m.group('p') or m.group('u')).strip()
            key = unit.lower() if unit.lower() in _LENGTH or unit.lower() in _ANGLE or unit.lower() in _TIME else unit
            scale = _LENGTH.get(key, _ANGLE.get(key, _TIME.get(key)))
            if scale is None:
                raise self.error(f'column {text!r}: unknown unit {unit!r}; use one of '
                                 f'{", ".join(sorted(set(_LENGTH) | set(_ANGLE) | set(_TIME)))}')
            return _Column(index, m.group('name').strip().lower(), key, scale)
        return _Column(index, text.lower(), None, None)

    def find(self, names: Sequence[str]) -> _Column | None:
        hits = [c for c in self.columns if c.name in names]
        if len(hits) > 1:
            raise self.error(f'more than one column of {"/".join(names)}: '
                             f'{[self.header[c.index] for c in hits]}')
        return hits[0] if hits else None

    def number(self, line: int, column: _Column, text: str, *, empty_ok: bool = False) -> float:
        cell = text.strip()
        if not cell:
            if empty_ok:
                return math.nan
            raise self.error(f'line {line}, column {self.header[column.index]!r}: empty cell')
        if self.delimiter != ',' and re.fullmatch(r'[+-]?\d+,\d+(?:[eE][+-]?\d+)?', cell):
            cell = cell.replace(',', '.')
        try:
            value = float(cell.replace('−', '-'))
        except ValueError:
            raise self.error(f'line {line}, column {self.header[column.index]!r}: {text!r} is not '
                             'a number') from None
        if not math.isfinite(value):
            raise self.error(f'line {line}, column {self.header[column.index]!r}: {text!r} is not '
                             'a finite number')
        return value


def _unit_kind(columns: Sequence[_Column]) -> str | None:
    """'angle', 'length' or None from the units named in the header (refusing a mixture)."""
    kinds = {('angle' if c.unit in _ANGLE else 'length') for c in columns
             if c.unit is not None and c.unit not in _TIME}
    if len(kinds) > 1:
        raise AnalysisError('the header mixes length and angle units: '
                            + ', '.join(f'{c.name} [{c.unit}]' for c in columns if c.unit))
    return kinds.pop() if kinds else None


def _resolve_axis(reader: _Reader, axis: str | None, columns: Sequence[_Column]) -> str:
    kind = _unit_kind(columns)
    if axis is None:
        if kind == 'angle':
            raise reader.error('the table is in angles: pass --axis phi, theta or psi (A, B, C)')
        return 'x'
    name = AXIS_NAMES[axis_index(axis)]
    rotary = axis_index(axis) >= 3
    if kind == 'angle' and not rotary or kind == 'length' and rotary:
        raise reader.error(f'axis {name} is {"rotary" if rotary else "linear"} but the header '
                           f'gives {kind} units')
    return name


def _scales(column: _Column, rotary: bool, kind: str) -> float:
    """SI per unit of a position ('position') or deviation ('deviation') column."""
    if column.scale is not None:
        return column.scale
    if kind == 'position':
        return math.pi / 180 if rotary else M_PER_MM
    return 1.0 / ARCSEC_PER_RAD if rotary else M_PER_UM


def _direction(reader: _Reader, line: int, text: str) -> int:
    key = text.strip().lower()
    if key in _UP:
        return 1
    if key in _DOWN:
        return -1
    raise reader.error(f'line {line}: direction {text!r} is neither up (+, up, ↑, forward) nor '
                       'down (-, down, ↓, backward)')


def _group_targets(values: Sequence[float]) -> tuple[FloatArray, list[int]]:
    """Distinct target positions (sorted) and each value's index among them."""
    keys = np.round(np.asarray(values, dtype=np.float64), 9)
    targets, index = np.unique(keys, return_inverse=True)
    return targets, index.tolist()


def _arrays(reader: _Reader, instrument: str, targets: FloatArray,
            entries: list[tuple[int, int, int, float, int]], rotary: bool
            ) -> tuple[FloatArray, FloatArray]:
    """(m, n) deviation arrays from (target index, direction, run, value, line) entries;
    targets [m or rad]."""
    unit_label, scale_pos = ('deg', math.pi / 180) if rotary else ('mm', M_PER_MM)
    m = targets.size
    if m < 2:
        raise reader.error(f'ISO 230-2 needs at least two targets; {instrument or "the table"} '
                           f'has {m}')
    seen: dict[tuple[int, int, int], int] = {}
    for i, d, j, _, line in entries:
        if (i, d, j) in seen:
            raise reader.error(f'line {line} repeats run {j} {"up" if d > 0 else "down"} at target '
                               f'{targets[i] / scale_pos:g} {unit_label} (first on line '
                               f'{seen[(i, d, j)]})')
        seen[(i, d, j)] = line
    n_up = max([j for _, d, j, _, _ in entries if d > 0] or [0])
    n_dn = max([j for _, d, j, _, _ in entries if d < 0] or [0])
    up, dn = np.full((m, max(n_up, 1)), np.nan), np.full((m, max(n_dn, 1)), np.nan)
    for i, d, j, v, _ in entries:
        (up if d > 0 else dn)[i, j - 1] = v
    for k in range(m):
        for arr, word in ((up, 'up (+)'), (dn, 'down (-)')):
            if not np.any(np.isfinite(arr[k])):
                raise reader.error(f'target {targets[k] / scale_pos:g} {unit_label}'
                                   f'{" of " + instrument if instrument else ""} has no runs in '
                                   f'the {word} direction')
    return up, dn


def _read_long(reader: _Reader, axis: str | None) -> IsoTable:
    target = reader.find(('target', 'target_position', 'nominal', 'position_target'))
    direction = reader.find(('direction', 'dir'))
    value = reader.find(_DEVIATION)
    reading = reader.find(_POSITION)
    run = reader.find(('run', 'cycle', 'j'))
    inst = reader.find(('instrument', 'system', 'device'))
    if value is None and reading is None:
        raise reader.error('a table with target and direction columns needs a deviation (or '
                           f'error) or a position column; the header is {reader.header}')
    if value is not None and reading is not None:
        raise reader.error('give either deviation or position, not both')
    assert target is not None and direction is not None
    name = _resolve_axis(reader, axis, [target, value or reading])
    rotary = axis_index(name) >= 3
    sp = _scales(target, rotary, 'position')
    sv = _scales(value, rotary, 'deviation') if value is not None else _scales(reading, rotary, 'position')  # type: ignore[arg-type]
    raw: dict[str, list[tuple[float, int, int | None, float, int]]] = {}
    for line, cells in reader.rows:
        t = reader.number(line, target, cells[target.index]) * sp
        d = _direction(reader, line, cells[direction.index])
        j = None
        if run is not None:
            r = reader.number(line, run, cells[run.index])
            if r < 1 or r != int(r):
                raise reader.error(f'line {line}: run {cells[run.index]!r} must be a whole number >= 1')
            j = int(r)
        col = value if value is not None else reading
        v = reader.number(line, col, cells[col.index]) * sv  # type: ignore[union-attr]
        if reading is not None:
            v -= t
            if rotary:
                v = (v + math.pi) % (2 * math.pi) - math.pi
        key = cells[inst.index] if inst is not None else ''
        if inst is not None and not key:
            raise reader.error(f'line {line}: empty instrument name')
        raw.setdefault(key, []).append((t, d, j, v, line))
    out = IsoTable(reader.path, 'long', name, {}, {}, {})
    for key, items in raw.items():
        targets, index = _group_targets([t for t, *_ in items])
        counters: dict[tuple[int, int], int] = {}
        entries = []
        for (t, d, j, v, line), i in zip(items, index):
            if j is None:
                j = counters.get((i, d), 0) + 1
                counters[(i, d)] = j
            entries.append((i, d, j, v, line))
        up, dn = _arrays(reader, key, targets, entries, rotary)
        label_key = key or reader.path.stem
        out.targets[label_key], out.up[label_key], out.down[label_key] = targets, up, dn
    return out


def _read_wide(reader: _Reader, axis: str | None, runs: list[tuple[_Column, int, int]]) -> IsoTable:
    target = reader.find(('target', 'target_position', 'nominal', 'position_target'))
    assert target is not None
    units = {c.unit for c, _, _ in runs}
    if len(units) > 1:
        raise reader.error(f'the run columns have different units: {sorted(map(str, units))}')
    name = _resolve_axis(reader, axis, [target] + [c for c, _, _ in runs])
    rotary = axis_index(name) >= 3
    sp = _scales(target, rotary, 'position')
    sv = _scales(runs[0][0], rotary, 'deviation')
    extra = [reader.header[c.index] for c in reader.columns
             if c is not target and all(c is not r for r, _, _ in runs)]
    if extra:
        raise reader.error(f'unexpected columns {extra} in a table of runs (target, +1 … +n, '
                           '-1 … -n)')
    values, entries = [], []
    for line, cells in reader.rows:
        values.append(reader.number(line, target, cells[target.index]) * sp)
    targets, index = _group_targets(values)
    if len(set(index)) != len(index):
        dup = next(v for v in values if values.count(v) > 1)
        raise reader.error(f'target {dup / sp:g} appears on more than one row')
    for (line, cells), i in zip(reader.rows, index):
        for col, d, j in runs:
            v = reader.number(line, col, cells[col.index], empty_ok=True)
            if math.isfinite(v):
                entries.append((i, d, j, v * sv, line))
    up, dn = _arrays(reader, '', targets, entries, rotary)
    key = reader.path.stem
    return IsoTable(reader.path, 'wide', name, {key: targets}, {key: up}, {key: dn})


def _read_series(reader: _Reader, axis: str | None, time: _Column) -> IsoTable:
    others = [c for c in reader.columns if c is not time]
    if not others:
        raise reader.error('a time series needs at least one column of positions besides time')
    name = _resolve_axis(reader, axis, others)
    rotary = axis_index(name) >= 3
    st = time.scale if time.unit in _TIME else 1.0
    if time.unit is not None and time.unit not in _TIME:
        raise reader.error(f'column {reader.header[time.index]!r}: time in {time.unit}? use s or ms')
    times = np.array([reader.number(n, time, cells[time.index]) * st for n, cells in reader.rows])
    if times.size < 10:
        raise reader.error(f'a time series needs at least 10 rows, found {times.size}')
    bad = np.flatnonzero(np.diff(times) <= 0)
    if bad.size:
        n = reader.rows[int(bad[0]) + 1][0]
        raise reader.error(f'line {n}: time does not increase ({times[bad[0] + 1]:g} s after '
                           f'{times[bad[0]]:g} s)')
    readings = {}
    for col in others:
        scale = _scales(col, rotary, 'position')
        readings[reader.header[col.index] if col.unit is None else col.name] = np.array(
            [reader.number(n, col, cells[col.index], empty_ok=True) * scale for n, cells in reader.rows])
    return IsoTable(reader.path, 'series', name, {}, {}, {}, times - times[0], readings)


def read_iso230_table(path: str | Path, *, axis: str | None = None) -> IsoTable:
    """Read an ISO 230-2 table (module docstring) into SI units.

    axis : the axis tested (x, y, z, phi/A, theta/B, psi/C); default x, or refused for a table
        in angles; it decides the default units (mm and µm, or degrees and arc-seconds)
    raises AnalysisError naming the file, line and column of anything malformed
    """
    reader = _Reader(Path(path))
    time = reader.find(_TIME_NAMES)
    if time is not None:
        return _read_series(reader, axis, time)
    target = reader.find(('target', 'target_position', 'nominal', 'position_target'))
    if target is not None and reader.find(('direction', 'dir')) is not None:
        return _read_long(reader, axis)
    runs = []
    for c in reader.columns:
        m = _RUN_RE.match(c.name)
        if m:
            d = 1 if m.group('dir') in ('+', '↑', 'up', 'fwd', 'forward', 'pos') else -1
            runs.append((c, d, int(m.group('run'))))
    if target is not None and runs:
        if not any(d > 0 for _, d, _ in runs) or not any(d < 0 for _, d, _ in runs):
            raise reader.error('a table of runs needs columns of both directions (+1 … and -1 …)')
        return _read_wide(reader, axis, runs)
    raise reader.error(
        f'unrecognised columns {reader.header}: expected target, direction, deviation [, run, '
        'instrument] (one row per approach); or target, +1 … +n, -1 … -n (one row per target); '
        'or time and positions (a time series) — see msg_docs/analysis.md')


def iso230_of_csv(path: str | Path, *, axis: str | None = None, targets: str | None = None,
                  min_dwell_s: float = 0.15) -> Iso230Report:
    """ISO 230-2 of a table of readings (:func:`read_iso230_table`), as :func:`iso230_of_run`
    gives for a log: one :class:`IsoResult` per instrument, and the Tables 3–4 rows; an
    instrument named ``reference`` (or ``laser``) is the one the others are compared with.

    targets : comma-separated target positions in the table's position unit (series layout
        only; else the table's own)
    min_dwell_s : shortest dwell at a target (series layout) [s]
    """
    table = read_iso230_table(path, axis=axis)
    results: dict[str, IsoResult] = {}
    if table.layout == 'series':
        assert table.readings is not None and table.times_s is not None
        given = None
        if targets:
            given = parse_targets(targets, table.axis)
        names = list(table.readings)
        ref = next((n for n in names if n.lower() in ('reference', 'laser')), names[0])
        results = evaluate_run(table.times_s, table.axis, table.readings, table.readings[ref],
                               given, min_dwell_s=min_dwell_s)
    else:
        if targets:
            raise AnalysisError(f'--targets applies to a time series only: {table.path} names '
                                'its targets')
        for name in table.targets:
            results[name] = evaluate(table.targets[name], table.up[name], table.down[name],
                                     axis=table.axis, instrument=name)
    names = list(results)
    reference = next((n for n in names if n.lower() in ('reference', 'laser')), None)
    if reference is not None and reference != 'reference':
        results = {('reference' if n == reference else n): r for n, r in results.items()}
    described = {n: f'{table.layout} table, {r.n} run(s) per direction at {r.positions.size} targets'
                 for n, r in results.items() if n != 'reference'}
    return Iso230Report(str(table.path), table.axis, results, described, source=f'csv ({table.layout} layout)')
