"""A minimal MCAP writer (format version 0, https://mcap.dev/spec) built for batches.

Why not ``mcap.writer.Writer``: it builds a Python object per message (about 5 µs each), and
``mmd process`` writes several messages per sample at 100,000 samples/s. Here a batch of
fixed-size messages becomes one numpy byte array of message records, cut into chunks; message
indexes are computed with numpy. Everything else (schemas, channels, metadata, chunk indexes,
statistics, summary offsets, CRCs) follows the specification, so the ``mcap`` library's indexed
reader, rosbag2 and Foxglove read the files (tested against ``mcap`` and ``rosbags``).
"""

from __future__ import annotations

import struct
import zlib
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.compiled import fast, use_compiled

__all__ = ['McapWriter']

MAGIC = b'\x89MCAP0\r\n'
OP = {'header': 0x01, 'footer': 0x02, 'schema': 0x03, 'channel': 0x04, 'message': 0x05,
      'chunk': 0x06, 'message_index': 0x07, 'chunk_index': 0x08, 'statistics': 0x0B,
      'metadata': 0x0C, 'metadata_index': 0x0D, 'summary_offset': 0x0E, 'data_end': 0x0F}
MESSAGE_HEADER = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log and publish time


def _str(text: str) -> bytes:
    raw = text.encode('utf-8')
    return struct.pack('<I', len(raw)) + raw


def _map(items: dict[str, str]) -> bytes:
    body = b''.join(_str(k) + _str(v) for k, v in items.items())
    return struct.pack('<I', len(body)) + body


def crc32(data: bytes | NDArray[np.uint8], *, compiled: bool | None = None) -> int:
    """zlib.crc32: compiled (folded with carry-less multiplication, about 10 GB/s against
    zlib's 1.7 here, without the GIL) where the CPU has it."""
    if use_compiled(compiled) and fast.CLMUL:
        return fast.crc32(data)
    return zlib.crc32(data)


def _record(op: str, body: bytes) -> bytes:
    return struct.pack('<BQ', OP[op], len(body)) + body


class McapWriter:
    """Writes an MCAP stream: ``register_schema``/``register_channel``, then messages with
    :meth:`add_message` (one) or :meth:`add_records` (a prepared batch), then :meth:`finish`."""

    def __init__(self, stream: BinaryIO, *, profile: str, library: str,
                 chunk_size: int = 1 << 20, compression: str = 'zstd', level: int = 1) -> None:
        if compression not in ('zstd', 'lz4', ''):
            raise ValueError(f'compression must be zstd, lz4 or empty, got {compression!r}')
        self._out = stream
        self._pos = 0
        self.chunk_size = int(chunk_size)
        self.compression = compression
        if compression == 'zstd':
            import zstandard
            self._compress = zstandard.ZstdCompressor(level=level).compress
        elif compression == 'lz4':
            import lz4.frame
            self._compress = lz4.frame.compress
        else:
            self._compress = bytes
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self._channel_ids: list[int] = []
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self._counts: dict[int, int] = {}
        self._metadata_count = 0
        self._start_time: int | None = None
        self._end_time = 0
        self._new_chunk()
        self._write(MAGIC + _record('header', _str(profile) + _str(library)))

    # -- low level -------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        self._out.write(data)
        self._pos += len(data)

    def _new_chunk(self) -> None:
        self._parts: list[bytes | NDArray[np.uint8]] = []
        self._size = 0
        # per channel, in time order: log times and offsets in the chunk of its messages
        self._index: dict[int, tuple[list[NDArray[np.int64]], list[NDArray[np.int64]]]] = {}

    # -- registration ----------------------------------------------------------------------------
    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self._schemas) + 1
        rec = _record('schema', struct.pack('<H', sid) + _str(name) + _str(encoding)
                      + struct.pack('<I', len(data)) + data)
        self._schemas.append(rec)
        self._write(rec)
        return sid

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str]) -> int:
        cid = len(self._channels) + 1
        rec = _record('channel', struct.pack('<HH', cid, schema_id) + _str(topic)
                      + _str(message_encoding) + _map(metadata))
        self._channels.append(rec)
        self._channel_ids.append(cid)
        self._write(rec)
        return cid

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        self.flush_chunk()
        rec = _record('metadata', _str(name) + _map(values))
        self._metadata_indexes.append(_record(
            'metadata_index', struct.pack('<QQ', self._pos, len(rec)) + _str(name)))
        self._write(rec)
        self._metadata_count += 1

    # -- messages --------------------------------------------------------------------------------
    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        """One message record."""
        rec = struct.pack('<BQHIQQ', OP['message'], 22 + len(data), channel_id, 0, log_time,
                          publish_time) + data
        self._append(rec, [(channel_id, np.array([log_time]), np.array([0]))])

    def add_records(self, block: NDArray[np.uint8], channel_ids: NDArray[np.int64],
                    log_times: NDArray[np.int64], offsets: NDArray[np.int64]) -> None:
        """A batch of N samples, each a row of ``block`` holding M message records.

        block : ndarray, shape (N, B) uint8 — complete message records, laid out per sample
        channel_ids, offsets : ndarray, shape (M,) — channel and byte offset within a row of
            each of the M records
        log_times : ndarray, shape (N,) — log time of the sample's records [ns]
        """
        n, width = block.shape
        per_chunk = max(1, self.chunk_size // max(width, 1))
        for start in range(0, n, per_chunk):
            part = block[start:start + per_chunk]
            k = part.shape[0]
            times = np.asarray(log_times[start:start + k], dtype=np.int64)
            rows = np.arange(k, dtype=np.int64) * width
            self._append(np.ascontiguousarray(part).reshape(-1),
                         [(int(cid), times, rows + int(off)) for cid, off in zip(channel_ids, offsets)])
            if self._size + width > self.chunk_size:   # no room for another sample
                self.flush_chunk()

    def _append(self, data: bytes | NDArray[np.uint8],
                entries: list[tuple[int, NDArray[np.int64], NDArray[np.int64]]]) -> None:
        """Records (bytes, or a contiguous uint8 array kept as it is until the chunk is
        written) and, per channel, the log times and offsets in ``data`` of its messages."""
        for cid, times, offsets in entries:
            lists = self._index.setdefault(cid, ([], []))
            lists[0].append(times)
            lists[1].append(offsets + self._size)
        self._parts.append(data)
        self._size += len(data)
        if self._size >= self.chunk_size:
            self.flush_chunk()

    def flush_chunk(self) -> None:
        """Close the open chunk and write it, with its message indexes."""
        if not self._parts:
            return
        # one block of records (the usual case) is compressed where it lies, without a copy
        records = self._parts[0] if len(self._parts) == 1 else b''.join(self._parts)
        index = {cid: (np.concatenate(t), np.concatenate(o)) for cid, (t, o) in self._index.items()}
        self._new_chunk()
        start = min(int(t.min()) for t, _ in index.values())
        end = max(int(t.max()) for t, _ in index.values())
        self._start_time = start if self._start_time is None else min(self._start_time, start)
        self._end_time = max(self._end_time, end)
        compressed = self._compress(records)
        body = (struct.pack('<QQQI', start, end, len(records), crc32(records))
                + _str(self.compression) + struct.pack('<Q', len(compressed)) + compressed)
        chunk_start = self._pos
        chunk = _record('chunk', body)
        self._write(chunk)
        index_start = self._pos
        index_offsets = {}
        for cid in sorted(index):
            times, offsets = index[cid]
            entries = np.empty((times.size, 2), dtype='<u8')
            entries[:, 0] = times
            entries[:, 1] = offsets
            index_offsets[cid] = self._pos
            self._write(_record('message_index', struct.pack('<HI', cid, entries.nbytes)
                                + entries.tobytes()))
            self._counts[cid] = self._counts.get(cid, 0) + times.size
        offsets_map = b''.join(struct.pack('<HQ', c, o) for c, o in index_offsets.items())
        self._chunk_indexes.append(_record(
            'chunk_index', struct.pack('<QQQQ', start, end, chunk_start, len(chunk))
            + struct.pack('<I', len(offsets_map)) + offsets_map
            + struct.pack('<Q', self._pos - index_start) + _str(self.compression)
            + struct.pack('<QQ', len(compressed), len(records))))

    # -- end -------------------------------------------------------------------------------------
    def finish(self) -> None:
        """Write the last chunk, the summary section and the footer."""
        self.flush_chunk()
        self._write(_record('data_end', struct.pack('<I', 0)))
        summary_start = self._pos
        groups: list[tuple[str, bytes]] = []
        counts_map = b''.join(struct.pack('<HQ', c, n) for c, n in sorted(self._counts.items()))
        stats = _record('statistics', struct.pack(
            '<QHIIIIQQ', sum(self._counts.values()), len(self._schemas), len(self._channels), 0,
            self._metadata_count, len(self._chunk_indexes), self._start_time or 0, self._end_time)
            + struct.pack('<I', len(counts_map)) + counts_map)
        for op, records in (('schema', self._schemas), ('channel', self._channels),
                            ('statistics', [stats]), ('chunk_index', self._chunk_indexes),
                            ('metadata_index', self._metadata_indexes)):
            if records:
                groups.append((op, b''.join(records)))
        summary = bytearray()
        offsets = bytearray()
        for op, data in groups:
            offsets += _record('summary_offset', struct.pack('<BQQ', OP[op], summary_start + len(summary), len(data)))
            summary += data
        summary_offset_start = summary_start + len(summary)
        footer_head = struct.pack('<BQQQ', OP['footer'], 20, summary_start, summary_offset_start)
        crc = zlib.crc32(bytes(summary) + bytes(offsets) + footer_head)
        self._write(bytes(summary) + bytes(offsets) + footer_head + struct.pack('<I', crc) + MAGIC)
