"""Write MCAP logs in rosbag2's layout: profile ``ros2``, ``ros2msg`` schemas, CDR messages and
``offered_qos_profiles`` channel metadata (Jazzy's format), so rosbag2, Foxglove and rosbags
open them. Topics, types, units and frames: ``msg_docs/topics.md``.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

import mmd_ros
from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.logs.cdr import JointStateLayout, PendingRows, PoseLayout, encode_string, split_stamps
from mmd_ros.logs.errors import LogError, LogFormatError
from mmd_ros.logs.mcap_records import MESSAGE_HEADER, McapWriter
from mmd_ros.logs.schemas import schema_text

__all__ = ['FAST_ZSTD_LEVEL', 'LogWriter', 'qos_yaml']

QOS_KINDS = ('reliable', 'sensor', 'latched')
#: zstd level of processed logs. On their message records (templated rows) level -4
#: compressed 1.0–1.2 GB/s against 0.5–0.8 GB/s at level 1 with files 4 % larger; on a raw log
#: 20 % larger, so raw logs keep level 1 (measured on the 10-minute benchmark logs).
FAST_ZSTD_LEVEL = -4


def qos_yaml(kind: str, depth: int = 1000) -> str:
    """``offered_qos_profiles`` as rosbag2 (Jazzy) writes it.

    kind : 'reliable' (reliable, volatile, keep last ``depth``), 'sensor' (best effort,
        volatile, keep last 5) or 'latched' (reliable, transient local, keep last 1)
    """
    if kind not in QOS_KINDS:
        raise LogError(f'qos kind must be one of {QOS_KINDS}, got {kind!r}')
    reliability = 'best_effort' if kind == 'sensor' else 'reliable'
    durability = 'transient_local' if kind == 'latched' else 'volatile'
    depth = {'sensor': 5, 'latched': 1}.get(kind, depth)
    zero = '\n    sec: 0\n    nsec: 0'
    return (f'- history: keep_last\n  depth: {depth}\n  reliability: {reliability}\n'
            f'  durability: {durability}\n  deadline:{zero}\n  lifespan:{zero}\n'
            f'  liveliness: automatic\n  liveliness_lease_duration:{zero}\n'
            '  avoid_ros_namespace_conventions: false')


class _RecordRow:
    """One sample's message records of several topics side by side, as a numpy structured
    dtype over the row's bytes: per record its log and publish time, and either its whole
    payload (serialised rows) or, for :class:`PendingRows`, the header stamp and the float64
    block; every other byte comes from a template row."""

    def __init__(self, channel_ids: list[int], streams: list[NDArray[np.uint8] | PendingRows]) -> None:
        self.streams = streams
        self.channel_ids = np.array(channel_ids, dtype=np.int64)
        names: list[str] = []
        formats: list[Any] = []
        offsets: list[int] = []
        template = bytearray()
        starts = []
        for k, (cid, rows) in enumerate(zip(channel_ids, streams)):
            off = len(template)
            starts.append(off)
            size = rows.shape[1]
            template += struct.pack('<BQHI', 0x05, MESSAGE_HEADER - 9 + size, cid, 0) + bytes(16)
            names += [f'log{k}', f'pub{k}']
            formats += ['<i8', '<i8']
            offsets += [off + 15, off + 23]
            if isinstance(rows, PendingRows):
                template += rows.layout.template.tobytes()
                names += [f'sec{k}', f'nsec{k}', f'val{k}']
                formats += ['<i4', '<u4', ('<f8', (rows.layout.n_float,))]
                offsets += [off + MESSAGE_HEADER + 4, off + MESSAGE_HEADER + 8,
                            off + MESSAGE_HEADER + rows.layout.float_offset]
            else:
                template += bytes(size)
                names.append(f'raw{k}')
                formats.append(('u1', (size,)))
                offsets.append(off + MESSAGE_HEADER)
        self.width = len(template)
        self.offsets = np.array(starts, dtype=np.int64)
        self.template = np.frombuffer(bytes(template), dtype=np.uint8)
        self.dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                               'itemsize': self.width})

    def fill(self, log_times: NDArray[np.int64], part: slice, *,
             compiled: bool | None = None) -> NDArray[np.uint8]:
        """The records of samples ``part``: (k, width) bytes. Compiled: one pass over the
        rows without the GIL (``fast.fill_rows``); else numpy field by field."""
        k = len(log_times)
        block = np.empty((k, self.width), dtype=np.uint8)
        stamps: dict[int, tuple[NDArray[np.int32], NDArray[np.uint32]]] = {}
        columns: list[tuple[str, NDArray[Any]]] = []
        for i, rows in enumerate(self.streams):
            columns += [(f'log{i}', log_times), (f'pub{i}', log_times)]
            if isinstance(rows, PendingRows):
                key = id(rows.stamps_ns)   # the streams of a sample share their stamps
                if key not in stamps:
                    stamps[key] = split_stamps(rows.stamps_ns[part])
                sec, nsec = stamps[key]
                columns += [(f'sec{i}', sec), (f'nsec{i}', nsec), (f'val{i}', rows.values[part])]
            else:
                columns.append((f'raw{i}', rows[part]))
        if use_compiled(compiled):
            fields = self.dtype.fields
            fast.fill_rows(block, self.template,
                           [(fields[name][1], np.ascontiguousarray(col, dtype=fields[name][0].base))
                            for name, col in columns])
            return block
        block[:] = self.template
        rec = block.view(self.dtype)[:, 0]
        for name, col in columns:
            rec[name] = col
        return block


class LogWriter:
    """An MCAP log being written.

    Chunks are written to disk as they fill (``chunk_size`` bytes); after a crash everything up
    to the last complete chunk can be read back (:class:`mmd_ros.logs.reader.LogReader`).
    ``level``: the zstd level (1: raw logs, small; :data:`FAST_ZSTD_LEVEL`: processed logs).
    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: str | os.PathLike[str], *, chunk_size: int = 1 << 20,
                 compression: str = 'zstd', level: int = 1) -> None:
        self.path = Path(path)
        comp = {'zstd': 'zstd', 'lz4': 'lz4', 'none': ''}
        if compression not in comp:
            raise LogError(f'compression must be zstd, lz4 or none, got {compression!r}')
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._file = open(self.path, 'wb')  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise LogError(f'cannot create log {self.path}: {exc.strerror}') from None
        self._chunk_size = int(chunk_size)
        self._writer = McapWriter(self._file, profile='ros2', library=f'mmd_ros {mmd_ros.__version__}',
                                  chunk_size=chunk_size, compression=comp[compression],
                                  level=level)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._layouts: dict[tuple[Any, ...], Any] = {}
        self.closed = False
        self.messages_written = 0

    # -- channels ------------------------------------------------------------------------------
    def channel(self, topic: str, msg_type: str, qos: str = 'reliable') -> int:
        """The channel id of ``topic``, registered on first use with ``msg_type`` and QoS."""
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msg_type:
                raise LogFormatError(f'topic {topic} has type {known[1]}, not {msg_type}')
            return known[0]
        if msg_type not in self._schemas:
            self._schemas[msg_type] = self._writer.register_schema(
                name=msg_type, encoding='ros2msg', data=schema_text(msg_type).encode())
        cid = self._writer.register_channel(
            topic=topic, message_encoding='cdr', schema_id=self._schemas[msg_type],
            metadata={'offered_qos_profiles': qos_yaml(qos)})
        self._channels[topic] = (cid, msg_type)
        return cid

    # -- messages ------------------------------------------------------------------------------
    def write_raw(self, topic: str, msg_type: str, stamp_ns: int, payload: bytes,
                  qos: str = 'reliable') -> None:
        """One serialised message; log and publish time are ``stamp_ns``."""
        cid = self.channel(topic, msg_type, qos)
        self._writer.add_message(cid, int(stamp_ns), payload, int(stamp_ns))
        self.messages_written += 1

    def write_string(self, topic: str, stamp_ns: int, text: str, *, latched: bool = True) -> None:
        """A std_msgs/msg/String (latched, like /robot_description, by default)."""
        self.write_raw(topic, 'std_msgs/msg/String', stamp_ns, encode_string(text),
                       'latched' if latched else 'reliable')

    def joint_state_rows(self, names: list[str], stamps_ns: NDArray[np.int64],
                         values: NDArray[np.float64], frame_id: str = '') -> PendingRows:
        """N sensor_msgs/msg/JointState for :meth:`write_rows` (``.encode()``: their bytes)."""
        key = ('js', tuple(names), frame_id)
        layout = self._layouts.setdefault(key, JointStateLayout(list(names), frame_id))
        return PendingRows(layout, stamps_ns, values)

    def pose_rows(self, frame_id: str, stamps_ns: NDArray[np.int64], poses: NDArray[np.float64],
                  covariance: NDArray[np.float64] | None = None) -> PendingRows:
        """N PoseStamped (PoseWithCovarianceStamped with ``covariance``) for :meth:`write_rows`."""
        key = ('pose', frame_id, covariance is not None)
        layout = self._layouts.setdefault(key, PoseLayout(frame_id, covariance is not None))
        return PendingRows(layout, stamps_ns, PoseLayout.values_from_poses(poses, covariance))

    def write_rows(self, streams: list[tuple[str, str, NDArray[np.uint8] | PendingRows]],
                   stamps_ns: NDArray[np.int64], qos: str = 'reliable') -> None:
        """Several topics of N samples each, interleaved sample by sample in time order.

        streams : list of (topic, msg_type, rows): serialised messages (N, size) bytes, or
            :class:`PendingRows` from ``*_rows``, whose stamps and values are written straight
            into the message records (the layout's fixed bytes come from one template row)
        stamps_ns : ndarray, shape (N,) — log time of sample k on every topic
        """
        ids = [self.channel(topic, msg_type, qos) for topic, msg_type, _ in streams]
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        for cid, (topic, _, rows) in zip(ids, streams):
            if rows.shape[0] != stamps.shape[0]:
                raise LogFormatError(f'{topic}: {rows.shape[0]} messages for {stamps.shape[0]} stamps')
        n = stamps.shape[0]
        layout = _RecordRow(ids, [rows for _, _, rows in streams])
        # Build the message records a chunk at a time: small blocks stay in the CPU cache.
        step = max(1, self._chunk_size // layout.width)
        for start in range(0, n, step):
            part = slice(start, min(start + step, n))
            self._writer.add_records(layout.fill(stamps[part], part), layout.channel_ids,
                                     stamps[part], layout.offsets)
        self.messages_written += n * len(streams)

    def write_joint_states(self, topic: str, stamps_ns: NDArray[np.int64], names: list[str],
                           values: NDArray[np.float64], *, frame_id: str = '',
                           qos: str = 'reliable') -> None:
        """N sensor_msgs/msg/JointState with ``name`` = names and ``position`` = values (N, k)."""
        rows = self.joint_state_rows(names, stamps_ns, values, frame_id)
        self.write_rows([(topic, 'sensor_msgs/msg/JointState', rows)], stamps_ns, qos)

    def write_metadata(self, name: str, values: dict[str, str]) -> None:
        """An MCAP metadata record (string key/value pairs); rosbag2 ignores names it does
        not know."""
        self._writer.add_metadata(name, {str(k): str(v) for k, v in values.items()})

    def flush(self) -> None:
        """Close the open chunk and push everything to the disk (fsync): after a crash the log
        reads back up to here."""
        self._writer.flush_chunk()
        self._file.flush()
        os.fsync(self._file.fileno())

    def sync_written(self) -> None:
        """Push what has been written so far to the disk (fdatasync), leaving the open chunk
        open: a long log written in pieces then does its disk writes while it is being made,
        not all in the final fsync of :meth:`close`."""
        self._file.flush()
        os.fdatasync(self._file.fileno())

    def close(self) -> None:
        """Write the summary and close; a closed log is a complete, indexed MCAP file."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
