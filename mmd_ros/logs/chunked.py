"""Read a log a chunk at a time, in bounded memory (``mmd process`` on logs of any length).

:class:`ChunkedReader` is a :class:`LogReader` that does not take the whole file in at once:

1. a first pass walks the file's records as :class:`LogReader` does (summary, schemas,
   channels, metadata, damage outside chunks), but only notes where each chunk lies;
2. the chunks holding the small topics asked for (the device description, the calibration, the
   model) are read then, and only those topics are kept;
3. :meth:`ChunkedReader.chunks` reads the chunks in file order and yields, per chunk, the
   messages of the streamed topics (raw counts, reference), keeping nothing of a chunk once it
   is handed on. A damaged chunk is skipped and reported exactly as :class:`LogReader` does
   (:attr:`problem`, complete once :meth:`chunks` has run).

Which channels a chunk holds comes from the summary's chunk index; a log without one (a
recording cut short) has each chunk read in both passes. The file is mapped, and the pages of
what has been read are given back (``madvise``): a mapped file's pages otherwise stay in the
process's resident set, and a 2-hour log would add most of its size to it.
"""

from __future__ import annotations

import mmap
import os
import struct
from pathlib import Path
from typing import Any, Iterator

from mmd_ros.logs.cdr import JointStateLayout
from mmd_ros.logs.errors import LogError
from mmd_ros.logs.reader import (
    _DAMAGE, MAGIC, OP_MESSAGE_INDEX, JointStates, LogReader, _Channel, _index_times, _Span,
)

__all__ = ['ChunkedReader']

#: Bytes the kernel may map around a page fault (``fault_around_bytes``, 64 KiB by default),
#: kept mapped behind the reading position until passed.
FAULT_AROUND = 1 << 16


class ChunkedReader(LogReader):
    """A log read in two passes, its streamed topics a chunk at a time (module docstring).

    path : the MCAP file
    small : topics read whole in the first pass (strings: device, calibration, model)
    streamed : topics handed out chunk by chunk by :meth:`chunks`
    Everything else in the log is skipped. Close with :meth:`close` (or use ``with``).
    """

    def __init__(self, path: str | os.PathLike[str], small: set[str], streamed: set[str]) -> None:
        # the state LogReader.__init__ sets up, without reading the chunks
        self.path = Path(path)
        self.problem = None
        self.profile = ''
        self.metadata: dict[str, dict[str, str]] = {}
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._channels: dict[int, _Channel] = {}
        self._spans: list[_Span] = []
        self._read: list[tuple[int, int, int]] = []
        self._summary = None
        self._small = set(small)
        self._streamed = set(streamed)
        self._layouts: dict[str, JointStateLayout] = {}
        self._deferred: list[tuple[int, int, int]] = []   # (offset, content start, end)
        self._walking = True
        self._released = 0   # pages before this offset have been given back
        self._data: Any = None
        try:
            self._file = open(self.path, 'rb')  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise LogError(f'cannot read log {self.path}: {exc.strerror}') from None
        try:
            self._size = os.fstat(self._file.fileno()).st_size
            if self._size < len(MAGIC):
                raise LogError(f'{self.path} is empty or not an MCAP file')
            self._data = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
            self._clean = self._parse(self._data, self._size)
            self._walking = False
            self._read_small()
            self._give_back(0, self._size)
        except OSError as exc:
            self.close()
            raise LogError(f'cannot read log {self.path}: {exc.strerror}') from None
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self._data is not None:
            self._data.close()
            self._data = None
        self._file.close()

    def __enter__(self) -> ChunkedReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _release_before(self, off: int) -> None:
        """Give back what lies well before ``off`` (the kernel maps up to 64 KiB around each
        page touched, on both sides), once: reading goes forward."""
        stop = off - FAULT_AROUND
        if stop > self._released:
            self._give_back(self._released, stop)
            self._released = stop

    def _give_back(self, start: int, stop: int) -> None:
        """Drop the mapped pages of bytes [start, stop) from the resident set (they stay in
        the page cache)."""
        first = start - start % mmap.PAGESIZE
        if stop > first and hasattr(self._data, 'madvise'):
            self._data.madvise(mmap.MADV_DONTNEED, first, stop - first)

    # -- the first pass ----------------------------------------------------------------------------
    def _walk_chunk(self, data: Any, off: int, start: int, end: int, size: int
                    ) -> tuple[int | None, _Span | None]:
        """While walking: a chunk whose header holds is noted for later; one whose header is
        damaged is skipped now, as LogReader skips it."""
        if self._walking and self._chunk_header(data, off, end) is not None:
            self._deferred.append((off, start, end))
            self._release_before(off)
            return end, None
        return super()._walk_chunk(data, off, start, end, size)

    def _holds(self, off: int, topics: set[str]) -> bool:
        """Whether the chunk at ``off`` may hold messages of ``topics`` (the summary's chunk
        index says which channels it holds; without it, any chunk may)."""
        index = self._summary.chunks.get(off) if self._summary is not None else None
        if index is None:
            return True
        return any(cid not in self._channels or self._channels[cid].topic in topics
                   for cid in index.message_index_offsets)

    def _keep_only(self, topics: set[str]) -> None:
        for cid, ch in list(self._channels.items()):
            if ch.topic not in topics:
                self._channels[cid] = _Channel(ch.topic, ch.schema_id, ch.encoding, ch.metadata)

    def _read_small(self) -> None:
        """The small topics, from the chunks that hold them (damage is reported by the second
        pass, which reads those chunks again)."""
        for off, start, end in self._deferred:
            if self._holds(off, self._small):
                try:
                    self._parse_chunk(self._data, off, start, end)
                except _DAMAGE:
                    pass
                self._keep_only(self._small)
        for ch in self._channels.values():
            ch.seal()

    def message_count(self, topic: str) -> int | None:
        """Messages of ``topic`` according to the summary's message indexes, or None."""
        if self._summary is None or not self._summary.chunks:
            return None
        ids = {cid for cid, ch in self._channels.items() if ch.topic == topic}
        total = 0
        self._released = 0
        for off in sorted(self._summary.chunks):
            for cid, moff in self._summary.chunks[off].message_index_offsets.items():
                if cid in ids and moff + 15 <= self._size:
                    total += struct.unpack_from('<I', self._data, moff + 11)[0] // 16
            self._release_before(off)
        self._give_back(0, self._size)
        return total

    # -- the second pass ---------------------------------------------------------------------------
    def chunks(self) -> Iterator[dict[str, JointStates]]:
        """Per chunk holding a streamed topic, in file order: its messages of each streamed
        (JointState) topic. A damaged chunk is skipped and reported in :attr:`problem`."""
        needed = self._small | self._streamed
        nexts = [off for off, _, _ in self._deferred[1:]] + [self._size + FAULT_AROUND]
        self._released = 0
        for (off, start, end), nxt in zip(self._deferred, nexts):
            if not self._holds(off, needed):
                continue
            _, span = super()._walk_chunk(self._data, off, start, end, self._size)
            if span is not None and not span.from_summary:
                self._index_after(end, span)
            self._keep_only(self._streamed)
            self._release_before(nxt)
            out = {topic: self._take(topic) for topic in self._streamed
                   if any(ch.count for ch in self._channels.values() if ch.topic == topic)}
            if out:
                yield out
        self._spans.sort(key=lambda span: span.offset)   # in file order, as both passes found them
        self.problem = self._make_problem(self._clean)

    def _index_after(self, off: int, span: _Span) -> None:
        """The message index records that follow a skipped chunk: what it held."""
        while off + 9 <= self._size and self._data[off] == OP_MESSAGE_INDEX:
            (length,) = struct.unpack_from('<Q', self._data, off + 1)
            try:
                span.add_index(*_index_times(self._data, off + 9, off + 9 + length))
            except _DAMAGE:
                return
            off += 9 + length

    def _take(self, topic: str) -> JointStates:
        """The messages of ``topic`` read so far, decoded; forgotten here."""
        for ch in self._channels.values():
            ch.seal()
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
        self._keep_only(self._streamed - {topic})
        return states
