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
from mmd_ros.logs.cdr import JointStateLayout, PoseLayout, encode_string
from mmd_ros.logs.errors import LogError, LogFormatError
from mmd_ros.logs.mcap_records import MESSAGE_HEADER, McapWriter
from mmd_ros.logs.schemas import schema_text

__all__ = ['LogWriter', 'qos_yaml']

QOS_KINDS = ('reliable', 'sensor', 'latched')


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


class LogWriter:
    """An MCAP log being written.

    Chunks are written to disk as they fill (``chunk_size`` bytes); after a crash everything up
    to the last complete chunk can be read back (:class:`mmd_ros.logs.reader.LogReader`).
    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: str | os.PathLike[str], *, chunk_size: int = 1 << 20,
                 compression: str = 'zstd') -> None:
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
                                  chunk_size=chunk_size, compression=comp[compression])
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
                         values: NDArray[np.float64], frame_id: str = '') -> NDArray[np.uint8]:
        key = ('js', tuple(names), frame_id)
        layout = self._layouts.setdefault(key, JointStateLayout(list(names), frame_id))
        return layout.encode(stamps_ns, values)

    def pose_rows(self, frame_id: str, stamps_ns: NDArray[np.int64], poses: NDArray[np.float64],
                  covariance: NDArray[np.float64] | None = None) -> NDArray[np.uint8]:
        key = ('pose', frame_id, covariance is not None)
        layout = self._layouts.setdefault(key, PoseLayout(frame_id, covariance is not None))
        return layout.encode(stamps_ns, PoseLayout.values_from_poses(poses, covariance))

    def write_rows(self, streams: list[tuple[str, str, NDArray[np.uint8]]],
                   stamps_ns: NDArray[np.int64], qos: str = 'reliable') -> None:
        """Several topics of N samples each, interleaved sample by sample in time order.

        streams : list of (topic, msg_type, rows (N, size) bytes from ``*_rows``)
        stamps_ns : ndarray, shape (N,) — log time of sample k on every topic
        """
        ids = [self.channel(topic, msg_type, qos) for topic, msg_type, _ in streams]
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        for cid, (topic, _, rows) in zip(ids, streams):
            if rows.shape[0] != stamps.shape[0]:
                raise LogFormatError(f'{topic}: {rows.shape[0]} messages for {stamps.shape[0]} stamps')
        n = stamps.shape[0]
        widths = [MESSAGE_HEADER + rows.shape[1] for _, _, rows in streams]
        offsets = np.cumsum([0] + widths[:-1]).astype(np.int64)
        heads = [np.frombuffer(struct.pack('<BQHI', 0x05, width - 9, cid, 0), dtype=np.uint8)
                 for cid, width in zip(ids, widths)]
        # Build the message records a chunk at a time: small blocks stay in the CPU cache.
        step = max(1, self._chunk_size // sum(widths))
        for start in range(0, n, step):
            stop = min(start + step, n)
            k = stop - start
            block = np.empty((k, sum(widths)), dtype=np.uint8)
            times = stamps[start:stop].astype('<u8').view(np.uint8).reshape(k, 8)
            for head, (_, _, rows), off, width in zip(heads, streams, offsets, widths):
                block[:, off:off + 15] = head
                block[:, off + 15:off + 23] = times
                block[:, off + 23:off + 31] = times
                block[:, off + 31:off + width] = rows[start:stop]
            self._writer.add_records(block, np.array(ids, dtype=np.int64), stamps[start:stop], offsets)
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
