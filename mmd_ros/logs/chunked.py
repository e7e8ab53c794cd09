"""Read a log a chunk at a time, in bounded memory (``mmd process`` on logs of any length).

:class:`ChunkedReader` is a :class:`LogReader` that does not take the whole file in at once:

1. a first pass walks the file's top-level records without decompressing anything: schemas,
   channels, metadata, and after each chunk its message index records, which say which channels
   the chunk holds and how many messages;
2. the chunks holding the small topics asked for (the device description, the calibration, the
   model) are read then, and only those topics are kept;
3. :meth:`ChunkedReader.chunks` then reads the chunks in file order and yields, per chunk, the
   messages of the streamed topics (raw counts, reference), keeping nothing of a chunk once it
   is handed on.

A chunk with no message index (allowed by MCAP, not written by us or rosbag2) is read in both
passes. Damage is handled as :class:`LogReader` handles it, chunk by chunk.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Iterator

from mmd_ros.logs.cdr import JointStateLayout
from mmd_ros.logs.errors import LogError
from mmd_ros.logs.reader import (
    MAGIC, OP_CHUNK, OP_DATA_END, OP_FOOTER, OP_HEADER, JointStates, LogReader, _Channel, _string,
)

__all__ = ['ChunkedReader']

OP_MESSAGE_INDEX = 0x07


class ChunkedReader(LogReader):
    """A log read in two passes, its streamed topics a chunk at a time (module docstring).

    path : the MCAP file
    small : topics read whole in the first pass (strings: device, calibration, model)
    streamed : topics handed out chunk by chunk by :meth:`chunks`
    Everything else in the log is skipped. Close with :meth:`close` (or use ``with``).
    """

    def __init__(self, path: str | os.PathLike[str], small: set[str], streamed: set[str]) -> None:
        self.path = Path(path)
        self.truncated = False
        self.problem: str | None = None
        self.profile = ''
        self.metadata: dict[str, dict[str, str]] = {}
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._channels: dict[int, _Channel] = {}
        self._small = set(small)
        self._streamed = set(streamed)
        self._layouts: dict[str, JointStateLayout] = {}
        #: (offset, record start, record end, channel ids or None when no index follows)
        self._chunk_list: list[tuple[int, int, int, set[int] | None]] = []
        self._counts: dict[int, int] = {}
        try:
            self._file = open(self.path, 'rb')  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise LogError(f'cannot read log {self.path}: {exc.strerror}') from None
        try:
            size = os.fstat(self._file.fileno()).st_size
            if size < len(MAGIC):
                raise LogError(f'{self.path} is empty or not an MCAP file')
            self._size = size
            self._contents()
            self._read_small()
        except BaseException:
            self.close()
            raise

    def _pread(self, offset: int, size: int) -> bytes:
        """Bytes of the file. Read with ``pread``, not through a map: pages of a mapped file
        stay in the process's resident set once touched (and the kernel maps 64 KiB around
        each), so a 2-hour log would add most of its size to it."""
        return os.pread(self._file.fileno(), size, offset)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> ChunkedReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the first pass ----------------------------------------------------------------------------
    def _contents(self) -> None:
        """Top-level records: schemas, channels, metadata, and which channels each chunk holds."""
        size = self._size
        if self._pread(0, 8) != MAGIC:
            raise LogError(f'{self.path} is not an MCAP file (bad magic bytes)')
        off = 8
        while off < size:
            if off + 9 > size:
                self._damage(f'file ends inside a record header at byte {off}')
                return
            head = self._pread(off, 15)
            op = head[0]
            (length,) = struct.unpack_from('<Q', head, 1)
            start, end = off + 9, off + 9 + length
            if end > size:
                self._damage(f'file ends inside a record (opcode {op}) at byte {off} of {size}')
                return
            if op in (OP_FOOTER, OP_DATA_END):
                return
            if op == OP_CHUNK:
                self._chunk_list.append((off, start, end, None))
            elif op == OP_MESSAGE_INDEX and self._chunk_list and length >= 6:
                cid, n = struct.unpack_from('<HI', head, 9)
                first, s, e, ids = self._chunk_list[-1]
                self._chunk_list[-1] = (first, s, e, (ids or set()) | {cid})
                self._counts[cid] = self._counts.get(cid, 0) + n // 16
            elif op == OP_HEADER:
                self.profile, _ = _string(self._pread(start, length), 0)
            elif op != OP_MESSAGE_INDEX:
                self._parse_record(op, self._pread(start, length), 0, length)
            off = end

    def _ids(self, topics: set[str]) -> set[int]:
        return {cid for cid, ch in self._channels.items() if ch.topic in topics}

    def _needs(self, ids: set[int] | None, topics: set[str]) -> bool:
        """Whether a chunk holding channels ``ids`` may hold messages of ``topics``."""
        return ids is None or bool(ids & self._ids(topics)) or any(c not in self._channels for c in ids)

    def _read_chunk(self, start: int, end: int, keep: set[str]) -> bool:
        """Parse one chunk, keeping the messages of ``keep`` only; False (and the reader's
        problem set) when the chunk is damaged."""
        try:
            self._parse_chunk(self._pread(start, end - start), 0, end - start)
        except LogError as exc:
            self._damage(str(exc))
            return False
        finally:
            for cid, ch in list(self._channels.items()):
                if ch.topic not in keep:
                    self._channels[cid] = _Channel(ch.topic, ch.schema_id, ch.encoding, ch.metadata)
        return True

    def _read_small(self) -> None:
        for _, start, end, ids in self._chunk_list:
            if self._needs(ids, self._small) and not self._read_chunk(start, end, self._small):
                return

    # -- the second pass ---------------------------------------------------------------------------
    def message_count(self, topic: str) -> int | None:
        """Messages of ``topic`` according to the message indexes (None if some are missing)."""
        if any(ids is None for *_, ids in self._chunk_list):
            return None
        return sum(self._counts.get(cid, 0) for cid in self._ids({topic}))

    def chunks(self) -> Iterator[dict[str, JointStates]]:
        """Per chunk holding a streamed topic, in file order: its messages of each streamed
        (JointState) topic. Stops at damage (:attr:`problem` says where)."""
        if self.truncated and not self._chunk_list:
            return
        keep = self._small | self._streamed
        for _, start, end, ids in self._chunk_list:
            if not self._needs(ids, self._streamed):
                continue
            if not self._read_chunk(start, end, keep):
                return
            out = {}
            for topic in self._streamed:
                if self.has_topic(topic) and any(ch.count for ch in self._channels.values()
                                                 if ch.topic == topic):
                    out[topic] = self._take(topic)
            if out:
                yield out

    def _take(self, topic: str) -> JointStates:
        """The messages of ``topic`` read so far, decoded; forgotten here."""
        stamps, payloads, _, _ = self._collect(topic)
        layout = self._layouts.get(topic)
        rows = self._rows(payloads)
        decoded = layout.decode(rows) if layout is not None and rows is not None else None
        if decoded is None:
            states = self.joint_states(topic)   # the first chunk, or messages of another layout
            if rows is not None and states.names:
                first = self.decode_one(topic, bytes(rows[0]))
                self._layouts[topic] = JointStateLayout(states.names, first.header.frame_id)
        else:
            states = JointStates(decoded[0], layout.names, decoded[1])
        for cid, ch in list(self._channels.items()):
            if ch.topic == topic:
                self._channels[cid] = _Channel(ch.topic, ch.schema_id, ch.encoding, ch.metadata)
        return states
