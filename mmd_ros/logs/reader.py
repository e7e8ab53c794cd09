"""Read MCAP logs, fast and forgiving.

The reader walks the file's records itself (the MCAP format is a flat sequence of
``opcode u8, length u64, content``; chunks hold compressed records of the same form) instead of
going through an indexed reader, and groups payloads per topic without building a Python object
per message. Messages of our fixed layouts decode in one numpy pass (:mod:`mmd_ros.logs.cdr`);
others go through mcap-ros2-support's generic decoder. Messages come back in the order they
were written (per topic), which is the order they were recorded.

A damaged file loses only its damaged part:

- a chunk that fails its CRC, does not decompress or holds a malformed record is skipped as a
  whole, and reading goes on after it: at its end when its header is consistent, else at the
  next chunk — found from the summary's chunk index when the file has one, by scanning for the
  next well-formed chunk record when it has not;
- a log cut by a crash (no summary and footer) is read to its last complete chunk;
- what was skipped is said in :attr:`LogReader.problem`, a :class:`LogProblem`: its kind, a
  message, and for each skipped stretch the bytes, the reason, the time span and the messages
  lost per topic (exactly, from the message indexes, when they survived; else the span between
  the last message read before and the first after).
"""

from __future__ import annotations

import mmap
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.logs.cdr import JointStateLayout, PoseLayout, decode_string, rows_match
from mmd_ros.logs.errors import LogError, LogFormatError
from mmd_ros.logs.mcap_records import crc32

__all__ = ['JointStates', 'LogProblem', 'LogReader', 'SkippedSpan', 'Topic', 'status_codes']

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_MESSAGE_INDEX, OP_CHUNK_INDEX = 7, 8
OP_METADATA, OP_DATA_END = 0x0C, 0x0F
RECORD_NAMES = {OP_SCHEMA: 'schema', OP_CHANNEL: 'channel', OP_METADATA: 'metadata'}
#: Opcode, record length, summary start, summary offset start, CRC.
FOOTER = struct.Struct('<BQQQI')
#: Longest repeating record pattern, and attempts per chunk, of the fast path.
MAX_PATTERN = 32
MAX_PATTERN_TRIES = 3
#: Largest decompressed chunk accepted [bytes]: writers use 1–100 MiB; a larger size in a
#: chunk's header is damage, not an allocation to attempt.
MAX_CHUNK_BYTES = 1 << 30
COMPRESSIONS = (b'', b'zstd', b'lz4')
#: What goes wrong when parsing damaged bytes.
_DAMAGE = (LogError, struct.error, ValueError, IndexError, OverflowError, UnicodeDecodeError,
           MemoryError)


@dataclass
class Topic:
    """A topic of the log: its type, offered QoS (YAML) and message count."""

    name: str
    msg_type: str
    qos: str
    count: int = 0


def status_codes(effort: Any) -> NDArray[np.uint8]:
    """Channel status codes from the ``effort`` of a ``/mmd/raw_counts`` message: 0 good, any
    other value (NaN included) not good, kept as a code 1..255."""
    e = np.asarray(effort, dtype=np.float64)
    return np.where(e == 0, 0, np.clip(np.nan_to_num(e, nan=255.0), 1, 255)).astype(np.uint8)


@dataclass(frozen=True)
class JointStates:
    """Messages of one JointState topic: stamps (N,) [ns], names (k), values (N, k) (the
    ``position`` fields), and status (N, k) uint8 — the ``effort`` codes of the messages that
    carry one per name (``/mmd/raw_counts`` of a sample the terminal flagged: 1 encoder signal
    lost, 2 quadrature error, 3 both; 0 good), 0 elsewhere — or None when no message does."""

    stamps_ns: NDArray[np.int64]
    names: list[str]
    values: NDArray[np.float64]
    status: NDArray[np.uint8] | None = None

    @property
    def times_s(self) -> NDArray[np.float64]:
        return self.stamps_ns.astype(np.float64) * 1e-9


@dataclass(frozen=True)
class SkippedSpan:
    """A stretch of a log that could not be read.

    offset, size : where it lies in the file [bytes]
    reason : what was wrong there
    start_ns, end_ns : log times of the first and last message lost when ``exact``; else the
        last message read before the stretch and the first read after it (None: none there)
    exact : the times (and ``messages``) come from the message index of the lost chunk
    messages : messages lost per topic, or None when no index survived to say
    at_end : the stretch is the end of the file (a record cut short by a crash)
    """

    offset: int
    size: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    exact: bool = False
    messages: dict[str, int] | None = None
    at_end: bool = False

    def describe(self, t0_ns: int | None) -> str:
        """In words, times in seconds from ``t0_ns`` (the log's first message)."""

        def t(ns: int | None) -> str:
            if ns is None:
                return '?'
            return f'{(ns - t0_ns) * 1e-9:.3f} s' if t0_ns is not None else f'{ns} ns'

        where = f'bytes {self.offset}–{self.offset + self.size} ({self.reason})'
        if self.messages is not None:
            n = sum(self.messages.values())
            per = ', '.join(f'{k} {v}' for k, v in sorted(self.messages.items()))
            lost = f'{n} messages lost ({per})'
        else:
            lost = 'messages lost: not known'
        if self.exact:
            span = f'stamped {t(self.start_ns)} to {t(self.end_ns)}'
        elif self.at_end:
            span = f'after {t(self.start_ns)}'
        else:
            span = f'none read between {t(self.start_ns)} and {t(self.end_ns)}'
        return f'{where}: {lost}, {span}'

    def as_dict(self, t0_ns: int | None = None) -> dict[str, Any]:
        out: dict[str, Any] = {
            'offset': self.offset, 'size': self.size, 'reason': self.reason,
            'start_ns': self.start_ns, 'end_ns': self.end_ns, 'exact': self.exact,
            'messages': self.messages, 'at_end': self.at_end}
        if t0_ns is not None:
            out['start_s'] = None if self.start_ns is None else (self.start_ns - t0_ns) * 1e-9
            out['end_s'] = None if self.end_ns is None else (self.end_ns - t0_ns) * 1e-9
        return out


@dataclass(frozen=True)
class LogProblem:
    """What is wrong with a log that was read anyway.

    kind : 'damaged' (parts were skipped, see ``skipped``) or 'unclean_end' (the recording did
        not end cleanly: no summary and footer; read to its last complete chunk)
    message : the whole story in one paragraph (also ``str(problem)``)
    skipped : the stretches not read, in file order
    clean_end : the file ends with its summary and footer, as a finished recording does
    t0_ns : log time of the first message read (times in the message count from it)
    """

    kind: str
    message: str
    skipped: tuple[SkippedSpan, ...] = ()
    clean_end: bool = True
    t0_ns: int | None = None

    def __str__(self) -> str:
        return self.message

    @property
    def lost_messages(self) -> dict[str, int] | None:
        """Messages lost per topic, summed over the stretches; None if any count is unknown."""
        total: dict[str, int] = {}
        for span in self.skipped:
            if span.messages is None:
                return None
            for k, v in span.messages.items():
                total[k] = total.get(k, 0) + v
        return total

    def as_dict(self) -> dict[str, Any]:
        """For ``--json`` and reports: plain values only."""
        return {'kind': self.kind, 'message': self.message, 'clean_end': self.clean_end,
                'lost_messages': self.lost_messages,
                'skipped': [s.as_dict(self.t0_ns) for s in self.skipped]}


@dataclass
class _Channel:
    """Messages of one channel, in file order: pieces (stamps, payloads), where payloads are a
    list of bytes or a block of equal-size rows; loose messages collect until sealed."""

    topic: str
    schema_id: int
    encoding: str
    metadata: dict[str, str]
    log_times: list[int] = field(default_factory=list)
    payloads: list[bytes] = field(default_factory=list)
    pieces: list[tuple[NDArray[np.int64], list[bytes] | NDArray[np.uint8]]] = field(default_factory=list)

    def seal(self) -> None:
        if self.log_times:
            self.pieces.append((np.array(self.log_times, dtype=np.int64), self.payloads))
            self.log_times, self.payloads = [], []

    @property
    def count(self) -> int:
        return len(self.payloads) + sum(len(t) for t, _ in self.pieces)


@dataclass(frozen=True)
class _ChunkIndex:
    offset: int
    length: int
    start_ns: int
    end_ns: int
    message_index_offsets: dict[int, int]


@dataclass
class _Summary:
    """What a finished log's summary section says (None fields: not present)."""

    chunks: dict[int, _ChunkIndex] = field(default_factory=dict)
    data_end: int | None = None
    schemas: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)
    channels: dict[int, tuple[str, int, str, dict[str, str]]] = field(default_factory=dict)


@dataclass
class _Span:
    """A stretch being skipped while parsing (becomes a :class:`SkippedSpan`)."""

    offset: int
    size: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    messages: dict[int, int] | None = None  # per channel id
    at_end: bool = False
    from_summary: bool = False  # messages and times already taken from the summary's index

    def add_index(self, cid: int, times: NDArray[np.int64]) -> None:
        if times.size == 0:
            return
        self.messages = self.messages or {}
        self.messages[cid] = self.messages.get(cid, 0) + int(times.size)
        lo, hi = int(times.min()), int(times.max())
        self.start_ns = lo if self.start_ns is None else min(self.start_ns, lo)
        self.end_ns = hi if self.end_ns is None else max(self.end_ns, hi)


def _string(buf: Any, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from('<I', buf, off)
    if off + 4 + n > len(buf):
        raise LogError('a string runs past its record')
    return bytes(buf[off + 4:off + 4 + n]).decode('utf-8'), off + 4 + n


def _map(buf: Any, off: int) -> tuple[dict[str, str], int]:
    (n,) = struct.unpack_from('<I', buf, off)
    end = off + 4 + n
    off += 4
    out = {}
    while off < end:
        key, off = _string(buf, off)
        value, off = _string(buf, off)
        out[key] = value
    return out, end


def _schema_record(buf: Any, start: int) -> tuple[int, tuple[str, str, bytes]]:
    """A schema record's id and (name, encoding, data)."""
    (sid,) = struct.unpack_from('<H', buf, start)
    name, off = _string(buf, start + 2)
    encoding, off = _string(buf, off)
    (n,) = struct.unpack_from('<I', buf, off)
    return sid, (name, encoding, bytes(buf[off + 4:off + 4 + n]))


def _channel_record(buf: Any, start: int) -> tuple[int, tuple[str, int, str, dict[str, str]]]:
    """A channel record's id and (topic, schema id, message encoding, metadata)."""
    cid, sid = struct.unpack_from('<HH', buf, start)
    topic, off = _string(buf, start + 4)
    encoding, off = _string(buf, off)
    meta, _ = _map(buf, off)
    return cid, (topic, sid, encoding, meta)


def _index_times(buf: Any, start: int, end: int) -> tuple[int, NDArray[np.int64]]:
    """A message index record's channel and log times."""
    cid, n = struct.unpack_from('<HI', buf, start)
    if n % 16 or start + 6 + n > end:
        raise LogError('a malformed message index')
    entries = np.frombuffer(buf, dtype='<u8', count=n // 8, offset=start + 6).reshape(-1, 2)
    return cid, entries[:, 0].astype(np.int64)


class LogReader:
    """All messages of an MCAP log, grouped by topic, in the order they were written.

    problem : a :class:`LogProblem` when parts were skipped or the recording did not end
        cleanly, else None
    truncated : ``problem is not None`` (kept for older callers)
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.problem: LogProblem | None = None
        self.profile = ''
        self.metadata: dict[str, dict[str, str]] = {}
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._channels: dict[int, _Channel] = {}
        self._spans: list[_Span] = []
        self._read: list[tuple[int, int, int]] = []  # (offset, first, last log time) of chunks read
        self._summary: _Summary | None = None
        try:
            with open(self.path, 'rb') as handle:
                size = os.fstat(handle.fileno()).st_size
                if size < len(MAGIC):
                    raise LogError(f'{self.path} is empty or not an MCAP file')
                with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
                    clean = self._parse(data, size)
        except OSError as exc:
            raise LogError(f'cannot read log {self.path}: {exc.strerror}') from None
        for ch in self._channels.values():
            ch.seal()
        self.problem = self._make_problem(clean)

    @property
    def truncated(self) -> bool:
        return self.problem is not None

    # -- parsing -------------------------------------------------------------------------------
    def _parse(self, data: Any, size: int) -> bool:
        """Walk the records; returns whether the file ends cleanly (summary and footer)."""
        if data[:8] != MAGIC:
            raise LogError(f'{self.path} is not an MCAP file (bad magic bytes)')
        footer = self._read_summary(data, size)
        pending: _Span | None = None  # a skipped chunk whose message indexes may follow
        off = 8
        while off < size:
            if off + 9 > size:
                self._spans.append(_Span(off, size - off, 'the file ends inside a record header',
                                          at_end=True))
                break
            op = data[off]
            (length,) = struct.unpack_from('<Q', data, off + 1)
            start, end = off + 9, off + 9 + length
            if op == 0 or end > size:
                reason = (f'the file ends inside a record (opcode {op})' if end > size
                          else 'a record with opcode 0 (not MCAP)')
                if self._summary is not None and off in self._summary.chunks:
                    reason = 'a chunk whose opcode or length is damaged'
                    pending = self._skip_chunk(data, off, end, size, reason)
                    off = None if pending is None else pending.offset + pending.size
                else:
                    off, pending = self._skip_to_next(data, off, size, reason), None
                if off is None:
                    break
                continue
            if op in (OP_FOOTER, OP_DATA_END):
                break
            if op == OP_CHUNK:
                nxt, pending = self._walk_chunk(data, off, start, end, size)
                if nxt is None:
                    break
                off = nxt
                continue
            elif op == OP_MESSAGE_INDEX:
                if pending is not None and not pending.from_summary:
                    try:  # the index of the chunk just skipped: what it held
                        pending.add_index(*_index_times(data, start, end))
                    except _DAMAGE:
                        pass
            elif op == OP_HEADER:
                try:
                    self.profile, _ = _string(data, start)
                except _DAMAGE:
                    pass
            else:
                try:
                    self._parse_record(op, data, start, end)
                except _DAMAGE as exc:
                    self._spans.append(_Span(off, end - off, f'a damaged {RECORD_NAMES.get(op, "")} '
                                             f'record ({exc})'))
            off = end
        return footer

    def _walk_chunk(self, data: Any, off: int, start: int, end: int, size: int
                    ) -> tuple[int | None, _Span | None]:
        """The chunk record at ``off``, met walking the file: parsed, or skipped when damaged.
        Returns where the walk goes on (None: nowhere) and the span skipped (whose message
        indexes may follow), or None."""
        try:
            self._parse_chunk(data, off, start, end)
            return end, None
        except _DAMAGE as exc:
            reason = str(exc) if isinstance(exc, LogError) else f'a malformed chunk ({exc})'
            span = self._skip_chunk(data, off, end, size, reason)
            return (None, None) if span is None else (span.offset + span.size, span)

    def _read_summary(self, data: Any, size: int) -> bool:
        """Read the footer and summary section, if the file has them; returns whether the
        footer is there (the recording ended cleanly)."""
        foot = size - len(MAGIC) - FOOTER.size
        if foot < len(MAGIC) or data[size - len(MAGIC):] != MAGIC:
            return False
        op, length, summary_start, _, crc = FOOTER.unpack_from(data, foot)
        if op != OP_FOOTER or length != FOOTER.size - 9:
            return False
        if not summary_start or not len(MAGIC) <= summary_start < foot:
            return True
        if crc and zlib.crc32(data[summary_start:foot + FOOTER.size - 4]) != crc:
            return True  # a damaged summary is not used; the data section is read on its own
        summary = _Summary()
        try:
            off = summary_start
            while off + 9 <= foot:
                op = data[off]
                (length,) = struct.unpack_from('<Q', data, off + 1)
                start, end = off + 9, off + 9 + length
                if end > foot:
                    return True
                if op == OP_SCHEMA:
                    sid, schema = _schema_record(data, start)
                    summary.schemas[sid] = schema
                elif op == OP_CHANNEL:
                    cid, channel = _channel_record(data, start)
                    summary.channels[cid] = channel
                elif op == OP_CHUNK_INDEX:
                    t0, t1, offset, clen = struct.unpack_from('<QQQQ', data, start)
                    (n,) = struct.unpack_from('<I', data, start + 32)
                    offsets = {}
                    for k in range(n // 10):
                        cid, moff = struct.unpack_from('<HQ', data, start + 36 + 10 * k)
                        offsets[cid] = moff
                    summary.chunks[offset] = _ChunkIndex(offset, clen, t0, t1, offsets)
                off = end
        except _DAMAGE:
            return True
        if summary_start >= 13 and data[summary_start - 13] == OP_DATA_END:
            summary.data_end = summary_start - 13
        self._summary = summary
        for sid, schema in summary.schemas.items():
            self._schemas.setdefault(sid, schema)
        for cid, (topic, sid, encoding, meta) in summary.channels.items():
            self._channels.setdefault(cid, _Channel(topic, sid, encoding, meta))
        return True

    def _next_record(self, data: Any, after: int, size: int) -> int | None:
        """Offset of the next record to read after damage at ``after``: the next chunk (or the
        end of the data section) from the summary when there is one, else the next
        well-formed chunk or message index record found by scanning."""
        if self._summary is not None:
            later = [o for o in self._summary.chunks if o > after]
            if later:
                return min(later)
            end = self._summary.data_end
            return end if end is not None and end > after else None
        pos = after + 1
        while True:
            chunk = data.find(b'\x06', pos)
            index = data.find(b'\x07', pos)
            hits = [h for h in (chunk, index) if h >= 0]
            if not hits:
                return None
            pos = min(hits)
            if self._looks_like_record(data, pos, size):
                return pos
            pos += 1

    def _looks_like_record(self, data: Any, pos: int, size: int) -> bool:
        """Whether a well-formed chunk, or message index of a known channel, starts at ``pos``."""
        if pos + 9 > size:
            return False
        op = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        end = pos + 9 + length
        if end > size:
            return False
        try:
            if op == OP_CHUNK:
                return self._chunk_header(data, pos, end) is not None
            if op == OP_MESSAGE_INDEX and length >= 6:
                cid, n = struct.unpack_from('<HI', data, pos + 9)
                return cid in self._channels and n % 16 == 0 and length == 6 + n
        except struct.error:
            return False
        return False

    @staticmethod
    def _chunk_header(data: Any, off: int, end: int) -> tuple[int, int, int, bytes, int, int] | None:
        """(start time, end time, uncompressed size, compression, CRC, offset of the records)
        of a chunk whose header is consistent with its record length, else None."""
        start = off + 9
        if end - start < 40:
            return None
        t0, t1, usize, crc, n = struct.unpack_from('<QQQII', data, start)
        if n > 4:
            return None
        compression = bytes(data[start + 32:start + 32 + n])
        (records,) = struct.unpack_from('<Q', data, start + 32 + n)
        body = start + 32 + n + 8
        if compression not in COMPRESSIONS or t0 > t1 or body + records != end:
            return None
        return t0, t1, usize, compression, crc, body

    def _skip_chunk(self, data: Any, off: int, end: int, size: int, reason: str) -> _Span | None:
        """Skip the damaged chunk at ``off``: to its end if its header holds, else to the next
        record; the span is recorded (and returned, for its message indexes to follow)."""
        index = self._summary.chunks.get(off) if self._summary is not None else None
        if index is not None:
            nxt = off + index.length
        elif self._chunk_header(data, off, end) is not None:
            nxt = end
        else:
            nxt = self._next_record(data, off, size)
        span = _Span(off, (size if nxt is None else nxt) - off, reason, at_end=nxt is None)
        if index is not None:
            span.start_ns, span.end_ns = index.start_ns, index.end_ns
            for cid, moff in index.message_index_offsets.items():
                try:
                    if data[moff] != OP_MESSAGE_INDEX:
                        raise LogError('not a message index')
                    (length,) = struct.unpack_from('<Q', data, moff + 1)
                    span.add_index(*_index_times(data, moff + 9, moff + 9 + length))
                except _DAMAGE:
                    span.messages = None
                    break
            span.from_summary = span.messages is not None
        self._spans.append(span)
        return None if nxt is None else span

    def _skip_to_next(self, data: Any, off: int, size: int, reason: str) -> int | None:
        """Damage outside a chunk at ``off``: go on at the next record (recorded as skipped)."""
        nxt = self._next_record(data, off, size)
        self._spans.append(_Span(off, (size if nxt is None else nxt) - off, reason, at_end=nxt is None))
        return nxt

    def _parse_chunk(self, data: Any, off: int, start: int, end: int) -> None:
        """Every message of the chunk at ``off``, or none (a damaged chunk raises and leaves
        nothing of itself behind)."""
        header = self._chunk_header(data, off, end)
        if header is None:
            raise LogError('a chunk header is inconsistent (a damaged length or compression field)')
        _, _, usize, compression, crc, body = header
        raw = data[body:end]
        try:
            if compression == b'':
                records = bytes(raw)
            elif compression == b'zstd':
                import zstandard
                declared = zstandard.frame_content_size(raw)
                if declared > MAX_CHUNK_BYTES or usize > MAX_CHUNK_BYTES:
                    raise LogError('a chunk header declares an impossible size')
                records = zstandard.ZstdDecompressor().decompress(raw, max_output_size=usize)
            else:
                import lz4.frame
                if usize > MAX_CHUNK_BYTES:
                    raise LogError('a chunk header declares an impossible size')
                records = lz4.frame.LZ4FrameDecompressor().decompress(raw, max_length=usize)
        except LogError:
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of the decompressor is damage
            raise LogError(f'a chunk does not decompress ({exc})') from None
        if crc and crc32(records) != crc:
            raise LogError('a chunk fails its CRC check')
        for ch in self._channels.values():
            ch.seal()
        before = {cid: len(ch.pieces) for cid, ch in self._channels.items()}
        try:
            self._parse_records(records)
        except _DAMAGE as exc:
            for cid, ch in self._channels.items():  # leave nothing of a damaged chunk behind
                del ch.pieces[before.get(cid, 0):]
                ch.log_times, ch.payloads = [], []
            raise LogError(f'a chunk holds a malformed record ({exc})') from None
        lo, hi = None, None
        for cid, ch in self._channels.items():
            ch.seal()
            for times, _ in ch.pieces[before.get(cid, 0):]:
                if times.size:
                    lo = int(times.min()) if lo is None else min(lo, int(times.min()))
                    hi = int(times.max()) if hi is None else max(hi, int(times.max()))
        if lo is not None:
            self._read.append((off, lo, hi))

    def _parse_records(self, records: bytes) -> None:
        pos, stop = 0, len(records)
        unpack = struct.unpack_from
        channels = self._channels
        tries = 0  # the fast path is tried on the first few messages only: no quadratic cost
        while pos < stop:
            if pos + 9 > stop:
                raise LogError('a record runs past the end of its chunk')
            if records[pos] == OP_MESSAGE and tries < MAX_PATTERN_TRIES:
                tries += 1
                if self._periodic(records, pos):
                    return
            op = records[pos]
            (length,) = unpack('<Q', records, pos + 1)
            rs, re_ = pos + 9, pos + 9 + length
            if re_ > stop:
                raise LogError('a record runs past the end of its chunk')
            if op == OP_MESSAGE:
                if length < 22:
                    raise LogError('a message record is too short')
                cid, _seq, log_time = unpack('<HIQ', records, rs)
                ch = channels.get(cid)
                if ch is not None:
                    ch.log_times.append(log_time)
                    ch.payloads.append(records[rs + 22:re_])
            else:
                self._parse_record(op, records, rs, re_)
            pos = re_

    def _periodic(self, records: bytes, start: int) -> bool:
        """Fast path for chunks whose messages repeat one pattern of fixed-size records (one
        record per topic per sample, as our writer lays them out): check the pattern across the
        whole rest of the chunk with numpy and slice out times and payloads in one pass.
        Returns False, having taken nothing, when the chunk does not follow a pattern."""
        pattern: list[tuple[int, int, int]] = []  # (offset in period, channel, record length)
        pos, stop = start, len(records)
        while pos + 31 <= stop and records[pos] == OP_MESSAGE and len(pattern) < MAX_PATTERN:
            (length,) = struct.unpack_from('<Q', records, pos + 1)
            (cid,) = struct.unpack_from('<H', records, pos + 9)
            if pattern and cid == pattern[0][1] or cid not in self._channels or length < 22:
                break
            pattern.append((pos - start, cid, length))
            pos += 9 + length
        period = pos - start
        if not pattern or period == 0 or (stop - start) % period or (stop - start) // period < 2:
            return False
        rows = np.frombuffer(records, dtype=np.uint8, offset=start).reshape(-1, period)
        template = np.frombuffer(records, dtype=np.uint8, offset=start, count=period)
        # opcode, length and channel of every record must repeat
        if not rows_match(rows, template, np.array([(off, 11) for off, _, _ in pattern], dtype=np.int64)):
            return False
        for off, cid, length in pattern:
            ch = self._channels[cid]
            ch.seal()
            ch.pieces.append((rows[:, off + 15:off + 23].copy().view('<u8')[:, 0].astype(np.int64),
                              rows[:, off + 31:off + 9 + length]))
        return True

    def _parse_record(self, op: int, buf: Any, start: int, end: int) -> None:
        if op == OP_SCHEMA:
            sid, schema = _schema_record(buf, start)
            self._schemas[sid] = schema
        elif op == OP_CHANNEL:
            cid, (topic, sid, encoding, meta) = _channel_record(buf, start)
            self._channels.setdefault(cid, _Channel(topic, sid, encoding, meta))
        elif op == OP_MESSAGE:
            cid, _seq, log_time = struct.unpack_from('<HIQ', buf, start)
            ch = self._channels.get(cid)
            if ch is not None:
                ch.log_times.append(log_time)
                ch.payloads.append(bytes(buf[start + 22:end]))
        elif op == OP_METADATA:
            name, off = _string(buf, start)
            self.metadata[name], _ = _map(buf, off)

    # -- what was lost -------------------------------------------------------------------------
    def _make_problem(self, clean_end: bool) -> LogProblem | None:
        if clean_end and not self._spans:
            return None
        firsts = [lo for _, lo, _ in self._read]
        t0 = min(firsts) if firsts else None
        spans = []
        for s in self._spans:
            exact = s.messages is not None
            start_ns, end_ns = s.start_ns, s.end_ns
            if not exact:
                before = [hi for off, _, hi in self._read if off < s.offset]
                after = [lo for off, lo, _ in self._read if off > s.offset]
                start_ns = max(before) if before else None
                end_ns = min(after) if after else None
            messages = None
            if s.messages is not None:
                messages = {}
                for cid, n in s.messages.items():
                    topic = self._channels[cid].topic if cid in self._channels else f'channel {cid}'
                    messages[topic] = messages.get(topic, 0) + n
            spans.append(SkippedSpan(s.offset, s.size, s.reason, start_ns, end_ns, exact, messages,
                                     s.at_end))
        parts = []
        inner = [s for s in spans if not s.at_end]
        if inner:
            parts.append(f'{len(inner)} damaged part{"s" if len(inner) > 1 else ""} skipped, '
                         'read on after each: ' + '; '.join(s.describe(t0) for s in inner))
        tail = [s for s in spans if s.at_end]
        if not clean_end:
            parts.append('the recording ended uncleanly (no summary and footer: the writer was '
                         'killed, lost power or ran out of disk space); read to its last complete '
                         'chunk' + ''.join(f'; {s.describe(t0)}' for s in tail))
        elif tail:
            parts.append('; '.join(s.describe(t0) for s in tail))
        kind = 'damaged' if inner else 'unclean_end' if not clean_end else 'damaged'
        return LogProblem(kind, f'{self.path}: ' + '; '.join(parts), tuple(spans), clean_end, t0)

    # -- access --------------------------------------------------------------------------------
    @property
    def topics(self) -> dict[str, Topic]:
        out = {}
        for ch in self._channels.values():
            schema = self._schemas.get(ch.schema_id, ('', '', b''))
            if ch.topic in out:
                out[ch.topic].count += ch.count
            else:
                out[ch.topic] = Topic(ch.topic, schema[0], ch.metadata.get('offered_qos_profiles', ''),
                                      ch.count)
        return out

    def _collect(self, topic: str) -> tuple[NDArray[np.int64], list[bytes] | NDArray[np.uint8], str, int]:
        """Stamps (log times) and payloads of ``topic`` in the order written: an (N, size) byte
        array when every message has the same size, else a list of bytes. (A topic on several
        channels is merged in log-time order.)"""
        chans = [ch for ch in self._channels.values() if ch.topic == topic]
        if not chans:
            raise LogFormatError(f'{self.path} has no topic {topic}; topics: {sorted(self.topics)}')
        pieces = [p for ch in chans for p in ch.pieces]
        stamps = np.concatenate([t for t, _ in pieces]) if pieces else np.zeros(0, dtype=np.int64)
        widths = {p.shape[1] if isinstance(p, np.ndarray) else len(x) for _, p in pieces
                  for x in ([b''] if isinstance(p, np.ndarray) else p)}
        payloads: list[bytes] | NDArray[np.uint8]
        if len(widths) == 1 and stamps.size:
            width = widths.pop()
            parts = [p if isinstance(p, np.ndarray)
                     else np.frombuffer(b''.join(p), np.uint8).reshape(-1, width) for _, p in pieces]
            payloads = np.concatenate(parts) if len(parts) > 1 else parts[0]
        else:
            payloads = [r.tobytes() if isinstance(p, np.ndarray) else r for _, p in pieces for r in p]
        if len(chans) > 1 and np.any(np.diff(stamps) < 0):
            order = np.argsort(stamps, kind='stable')
            stamps = stamps[order]
            payloads = payloads[order] if isinstance(payloads, np.ndarray) else [payloads[k] for k in order]
        schema_name = self._schemas.get(chans[0].schema_id, ('',))[0]
        return stamps, payloads, schema_name, chans[0].schema_id

    def has_topic(self, topic: str) -> bool:
        return any(ch.topic == topic for ch in self._channels.values())

    @staticmethod
    def _rows(payloads: list[bytes] | NDArray[np.uint8]) -> NDArray[np.uint8] | None:
        if isinstance(payloads, np.ndarray):
            return payloads
        if not payloads:
            return None
        size = len(payloads[0])
        if any(len(p) != size for p in payloads):
            return None
        return np.frombuffer(b''.join(payloads), dtype=np.uint8).reshape(len(payloads), size)

    def _decoder(self, topic: str) -> Any:
        """The generic CDR decoder of ``topic``'s schema; a message it cannot decode raises
        :class:`LogFormatError` naming the topic."""
        from mcap.records import Schema
        from mcap_ros2.decoder import DecoderFactory
        ch = next((ch for ch in self._channels.values() if ch.topic == topic), None)
        if ch is None:
            raise LogFormatError(f'{self.path} has no topic {topic}; topics: {sorted(self.topics)}')
        if ch.schema_id not in self._schemas:
            raise LogFormatError(f'{self.path}: {topic} refers to schema {ch.schema_id}, which the log lacks')
        name, encoding, data = self._schemas[ch.schema_id]
        try:
            decoder = DecoderFactory().decoder_for('cdr', Schema(id=ch.schema_id, name=name,
                                                                 encoding=encoding, data=data))
        except Exception as exc:  # noqa: BLE001 - a malformed schema text in the log
            raise LogFormatError(f'{self.path}: {topic}: cannot read its schema {name} ({exc})') from None
        if decoder is None:
            raise LogFormatError(f'{self.path}: {topic}: cannot decode schema {name} ({encoding})')

        def decode(payload: bytes) -> Any:
            try:
                return decoder(payload)
            except Exception as exc:  # noqa: BLE001 - whatever a malformed payload raises
                raise LogFormatError(f'{self.path}: {topic}: a message does not decode as {name} '
                                     f'({type(exc).__name__}: {exc})') from None

        return decode

    def decode(self, topic: str) -> list[Any]:
        """Every message of ``topic`` decoded by the generic ROS 2 decoder (slow; small topics)."""
        _, payloads, _, _ = self._collect(topic)
        decoder = self._decoder(topic)
        return [decoder(bytes(p)) for p in payloads]

    def joint_states(self, topic: str) -> JointStates:
        """A sensor_msgs/msg/JointState topic with the same names in every message."""
        stamps, payloads, schema_name, _ = self._collect(topic)
        if schema_name != 'sensor_msgs/msg/JointState':
            raise LogFormatError(f'{topic} has type {schema_name}, not sensor_msgs/msg/JointState')
        if len(payloads) == 0:
            return JointStates(stamps, [], np.zeros((0, 0)))
        first = self.decode_one(topic, bytes(payloads[0]))
        names = list(first.name)
        layout = JointStateLayout(names, first.header.frame_id)
        rows = self._rows(payloads)
        if rows is not None:
            decoded = layout.decode(rows)
            if decoded is not None:
                return JointStates(decoded[0], names, decoded[1])
        return self._mixed_joint_states(topic, payloads, names, layout)

    def _mixed_joint_states(self, topic: str, payloads: list[bytes] | NDArray[np.uint8],
                            names: list[str], layout: JointStateLayout) -> JointStates:
        """Messages of which some do not fit ``layout`` (flagged samples with an ``effort``,
        another tool's messages): those that fit are decoded together, the others one by one
        with the generic decoder."""
        n, k = len(payloads), len(names)
        fits = np.array([len(p) == layout.size for p in payloads], dtype=bool)
        stamps = np.zeros(n, dtype=np.int64)
        values = np.zeros((n, k))
        status = np.zeros((n, k), dtype=np.uint8)
        idx = np.flatnonzero(fits)
        if idx.size:
            block = np.frombuffer(b''.join(bytes(payloads[i]) for i in idx), np.uint8).reshape(idx.size, -1)
            decoded = layout.decode(block)
            if decoded is None:
                fits[:] = False
            else:
                stamps[idx], values[idx] = decoded
        decode = self._decoder(topic)
        for i in np.flatnonzero(~fits):
            m = decode(bytes(payloads[i]))
            if list(m.name) != names:
                raise LogFormatError(f'{topic}: the joint names change within the log')
            if len(m.position) != k:
                raise LogFormatError(f'{topic}: a message has {len(m.position)} positions for '
                                     f'{k} names')
            stamps[i] = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            values[i] = m.position
            if len(m.effort) == k:
                status[i] = status_codes(m.effort)
        return JointStates(stamps, names, values, status if status.any() else None)

    def pose_values(self, topic: str) -> tuple[NDArray[np.int64], NDArray[np.float64], str]:
        """A PoseStamped or PoseWithCovarianceStamped topic: stamps (N,) [ns], values (N, 7 or
        43: position, quaternion x y z w, covariance) and the frame id."""
        stamps, payloads, schema_name, _ = self._collect(topic)
        cov = schema_name == 'geometry_msgs/msg/PoseWithCovarianceStamped'
        if schema_name != 'geometry_msgs/msg/PoseStamped' and not cov:
            raise LogFormatError(f'{topic} has type {schema_name}, not a stamped pose')
        if len(payloads) == 0:
            return stamps, np.zeros((0, 43 if cov else 7)), ''
        first = self.decode_one(topic, bytes(payloads[0]))
        rows = self._rows(payloads)
        if rows is not None:
            decoded = PoseLayout(first.header.frame_id, cov).decode(rows)
            if decoded is not None:
                return decoded[0], decoded[1], first.header.frame_id
        values, out_stamps = [], []
        for m in self.decode(topic):
            pose = m.pose.pose if cov else m.pose
            v = [pose.position.x, pose.position.y, pose.position.z, pose.orientation.x,
                 pose.orientation.y, pose.orientation.z, pose.orientation.w]
            values.append(v + (list(m.pose.covariance) if cov else []))
            out_stamps.append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
        return np.array(out_stamps, dtype=np.int64), np.array(values), first.header.frame_id

    def decode_one(self, topic: str, payload: bytes) -> Any:
        return self._decoder(topic)(payload)

    def strings(self, topic: str) -> list[tuple[int, str]]:
        """Every std_msgs/msg/String of ``topic``: (stamp [ns], text)."""
        stamps, payloads, schema_name, _ = self._collect(topic)
        if schema_name != 'std_msgs/msg/String':
            raise LogFormatError(f'{topic} has type {schema_name}, not std_msgs/msg/String')
        out = []
        for t, p in zip(stamps.tolist(), payloads):
            try:
                out.append((t, decode_string(bytes(p))))
            except ValueError as exc:
                raise LogFormatError(f'{topic}: a String message is malformed ({exc})') from None
        return out

    def latest_string(self, topic: str, at_ns: int | None = None) -> str | None:
        """The last String on ``topic`` (at or before ``at_ns``), or None if it has none."""
        if not self.has_topic(topic):
            return None
        items = [(t, s) for t, s in self.strings(topic) if at_ns is None or t <= at_ns]
        return items[-1][1] if items else None
