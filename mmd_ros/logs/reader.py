"""Read MCAP logs, fast and forgiving.

The reader walks the file's records itself (the MCAP format is a flat sequence of
``opcode u8, length u64, content``; chunks hold compressed records of the same form) instead of
going through an indexed reader: it needs no summary section, so a log cut short by a crash or a
full disk is read up to its last complete chunk, and it groups payloads per topic without
building a Python object per message. What was lost is said in :attr:`LogReader.problem`.
Messages of our fixed layouts decode in one numpy pass (:mod:`mmd_ros.logs.cdr`); others go
through mcap-ros2-support's generic decoder.
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

__all__ = ['JointStates', 'LogReader', 'Topic']

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_METADATA, OP_DATA_END = 0x0C, 0x0F
#: Longest repeating record pattern, and attempts per chunk, of the fast path.
MAX_PATTERN = 32
MAX_PATTERN_TRIES = 3


@dataclass
class Topic:
    """A topic of the log: its type, offered QoS (YAML) and message count."""

    name: str
    msg_type: str
    qos: str
    count: int = 0


@dataclass(frozen=True)
class JointStates:
    """Messages of one JointState topic: stamps (N,) [ns], names (k), values (N, k)."""

    stamps_ns: NDArray[np.int64]
    names: list[str]
    values: NDArray[np.float64]

    @property
    def times_s(self) -> NDArray[np.float64]:
        return self.stamps_ns.astype(np.float64) * 1e-9


@dataclass
class _Channel:
    """Messages of one channel, as loose payloads and/or blocks of equal-size rows."""

    topic: str
    schema_id: int
    encoding: str
    metadata: dict[str, str]
    log_times: list[int] = field(default_factory=list)
    payloads: list[bytes] = field(default_factory=list)
    block_times: list[NDArray[np.int64]] = field(default_factory=list)
    blocks: list[NDArray[np.uint8]] = field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.payloads) + sum(len(b) for b in self.blocks)


def _string(buf: Any, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from('<I', buf, off)
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


class LogReader:
    """All messages of an MCAP log, grouped by topic.

    truncated : the file ended inside a record, or a chunk was damaged; every message before
        the damage was kept
    problem : what was wrong, in words, or None
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.truncated = False
        self.problem: str | None = None
        self.profile = ''
        self.metadata: dict[str, dict[str, str]] = {}
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._channels: dict[int, _Channel] = {}
        try:
            with open(self.path, 'rb') as handle:
                size = os.fstat(handle.fileno()).st_size
                if size < len(MAGIC):
                    raise LogError(f'{self.path} is empty or not an MCAP file')
                with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
                    self._parse(data, size)
        except OSError as exc:
            raise LogError(f'cannot read log {self.path}: {exc.strerror}') from None

    # -- parsing -------------------------------------------------------------------------------
    def _damage(self, problem: str) -> None:
        self.truncated = True
        self.problem = f'{self.path}: {problem}; kept everything before it'

    def _parse(self, data: Any, size: int) -> None:
        if data[:8] != MAGIC:
            raise LogError(f'{self.path} is not an MCAP file (bad magic bytes)')
        off = 8
        while off < size:
            if off + 9 > size:
                self._damage(f'file ends inside a record header at byte {off}')
                return
            op = data[off]
            (length,) = struct.unpack_from('<Q', data, off + 1)
            start, end = off + 9, off + 9 + length
            if end > size:
                self._damage(f'file ends inside a record (opcode {op}) at byte {off} of {size}')
                return
            if op == OP_FOOTER:
                return
            if op == OP_DATA_END:
                # The summary repeats schemas and channels we already have; nothing new follows.
                return
            if op == OP_CHUNK:
                try:
                    self._parse_chunk(data, start, end)
                except LogError as exc:
                    self._damage(str(exc))
                    return
            elif op == OP_HEADER:
                self.profile, _ = _string(data, start)
            else:
                self._parse_record(op, data, start, end)
            off = end

    def _parse_chunk(self, data: Any, start: int, end: int) -> None:
        uncompressed_size, crc = struct.unpack_from('<QI', data, start + 16)
        compression, off = _string(data, start + 28)
        (n,) = struct.unpack_from('<Q', data, off)
        raw = data[off + 8:off + 8 + n]
        try:
            if compression == '':
                records = bytes(raw)
            elif compression == 'zstd':
                import zstandard
                records = zstandard.ZstdDecompressor().decompress(raw, max_output_size=uncompressed_size)
            elif compression == 'lz4':
                import lz4.frame
                records = lz4.frame.decompress(raw)
            else:
                raise LogError(f'chunk compression {compression!r} is not supported')
        except LogError:
            raise
        except Exception as exc:  # a damaged compressed block: keep what came before
            raise LogError(f'a chunk does not decompress ({exc})') from None
        if crc and zlib.crc32(records) != crc:
            raise LogError('a chunk fails its CRC check (the file is corrupt there)')
        pos, stop = 0, len(records)
        unpack = struct.unpack_from
        channels = self._channels
        tries = 0  # the fast path is tried on the first few messages only: no quadratic cost
        while pos + 9 <= stop:
            if records[pos] == OP_MESSAGE and tries < MAX_PATTERN_TRIES:
                tries += 1
                if self._periodic(records, pos):
                    return
            op = records[pos]
            (length,) = unpack('<Q', records, pos + 1)
            rs, re_ = pos + 9, pos + 9 + length
            if op == OP_MESSAGE:
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
            ch.block_times.append(rows[:, off + 15:off + 23].copy().view('<u8')[:, 0].astype(np.int64))
            ch.blocks.append(rows[:, off + 31:off + 9 + length])
        return True

    def _parse_record(self, op: int, buf: Any, start: int, end: int) -> None:
        if op == OP_SCHEMA:
            (sid,) = struct.unpack_from('<H', buf, start)
            name, off = _string(buf, start + 2)
            encoding, off = _string(buf, off)
            (n,) = struct.unpack_from('<I', buf, off)
            self._schemas[sid] = (name, encoding, bytes(buf[off + 4:off + 4 + n]))
        elif op == OP_CHANNEL:
            cid, sid = struct.unpack_from('<HH', buf, start)
            if cid in self._channels:
                return
            topic, off = _string(buf, start + 4)
            encoding, off = _string(buf, off)
            meta, _ = _map(buf, off)
            self._channels[cid] = _Channel(topic, sid, encoding, meta)
        elif op == OP_MESSAGE:
            cid, _seq, log_time = struct.unpack_from('<HIQ', buf, start)
            ch = self._channels.get(cid)
            if ch is not None:
                ch.log_times.append(log_time)
                ch.payloads.append(bytes(buf[start + 22:end]))
        elif op == OP_METADATA:
            name, off = _string(buf, start)
            self.metadata[name], _ = _map(buf, off)

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
        """Stamps (log times) and payloads of ``topic`` in time order: an (N, size) byte array
        when every message has the same size, else a list of bytes."""
        chans = [ch for ch in self._channels.values() if ch.topic == topic]
        if not chans:
            raise LogFormatError(f'{self.path} has no topic {topic}; topics: {sorted(self.topics)}')
        times = [np.array(ch.log_times, dtype=np.int64) for ch in chans]
        times += [t for ch in chans for t in ch.block_times]
        stamps = np.concatenate(times) if times else np.zeros(0, dtype=np.int64)
        loose = [p for ch in chans for p in ch.payloads]
        blocks = [b for ch in chans for b in ch.blocks]
        widths = {b.shape[1] for b in blocks} | {len(p) for p in loose}
        payloads: list[bytes] | NDArray[np.uint8]
        if len(widths) == 1 and stamps.size:
            width = widths.pop()
            parts = [np.frombuffer(b''.join(loose), np.uint8).reshape(-1, width)] if loose else []
            payloads = np.concatenate(parts + blocks) if len(parts + blocks) > 1 else (parts + blocks)[0]
        else:
            payloads = loose + [r.tobytes() for b in blocks for r in b]
        if np.any(np.diff(stamps) < 0):
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

    def decode(self, topic: str) -> list[Any]:
        """Every message of ``topic`` decoded by the generic ROS 2 decoder (slow; small topics)."""
        from mcap.records import Schema
        from mcap_ros2.decoder import DecoderFactory
        _, payloads, schema_name, sid = self._collect(topic)
        name, encoding, data = self._schemas[sid]
        decoder = DecoderFactory().decoder_for('cdr', Schema(id=sid, name=name, encoding=encoding, data=data))
        if decoder is None:
            raise LogFormatError(f'{topic}: cannot decode schema {schema_name} ({encoding})')
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
        rows = self._rows(payloads)
        if rows is not None:
            decoded = JointStateLayout(names, first.header.frame_id).decode(rows)
            if decoded is not None:
                return JointStates(decoded[0], names, decoded[1])
        msgs = self.decode(topic)
        if any(list(m.name) != names for m in msgs):
            raise LogFormatError(f'{topic}: the joint names change within the log')
        values = np.array([list(m.position) for m in msgs], dtype=np.float64).reshape(len(msgs), len(names))
        stamps = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs],
                          dtype=np.int64)
        return JointStates(stamps, names, values)

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
        from mcap.records import Schema
        from mcap_ros2.decoder import DecoderFactory
        cid, ch = next((c, ch) for c, ch in self._channels.items() if ch.topic == topic)
        name, encoding, data = self._schemas[ch.schema_id]
        decoder = DecoderFactory().decoder_for('cdr', Schema(id=ch.schema_id, name=name, encoding=encoding, data=data))
        return decoder(payload)

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
