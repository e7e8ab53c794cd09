"""Vectorised CDR (little-endian, XCDR1 as ROS 2 uses it) for the fixed-layout messages of our logs.

A log has hundreds of thousands of messages of one layout per topic (a JointState with the same
eight names, a PoseStamped with the same frame). Their bytes differ only in the stamp and the
numbers, so a batch is built as one (N, L) byte array from a template, and read back the same
way after checking that every message matches the template. Anything that does not match (a
message written by another tool, a different frame id) is decoded by the generic decoder of
mcap-ros2-support instead; see :mod:`mmd_ros.logs.reader`.

Alignment in CDR is relative to the first byte after the 4-byte encapsulation header.
"""

from __future__ import annotations

import struct

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.rotation import angles_to_quaternion

__all__ = [
    'JointStateLayout', 'PendingRows', 'PoseLayout', 'decode_string', 'encode_joint_state',
    'encode_string',
    'fixed_runs', 'rows_match', 'split_stamps',
]

ENCAPSULATION = b'\x00\x01\x00\x00'  # CDR_LE


class _Buffer:
    """Appends CDR fields with alignment, counting offsets from after the encapsulation."""

    def __init__(self) -> None:
        self.data = bytearray()

    def align(self, n: int) -> None:
        self.data.extend(b'\x00' * (-len(self.data) % n))

    def u32(self, value: int) -> None:
        self.align(4)
        self.data.extend(struct.pack('<I', value))

    def string(self, text: str) -> None:
        raw = text.encode('utf-8')
        self.u32(len(raw) + 1)
        self.data.extend(raw + b'\x00')


def split_stamps(stamps_ns: NDArray[np.int64]) -> tuple[NDArray[np.int32], NDArray[np.uint32]]:
    """Nanoseconds since the epoch to builtin_interfaces/Time (sec, nanosec)."""
    s = np.asarray(stamps_ns, dtype=np.int64)
    sec = np.floor_divide(s, 1_000_000_000)
    return sec.astype(np.int32), (s - sec * 1_000_000_000).astype(np.uint32)


def fixed_runs(fixed: NDArray[np.bool_]) -> NDArray[np.int64]:
    """The runs of True in a mask, shape (M, 2) int64: (start, length)."""
    edges = np.diff(np.concatenate([[0], fixed.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    return np.column_stack([starts, np.flatnonzero(edges == -1) - starts]).astype(np.int64)


def rows_match(rows: NDArray[np.uint8], template: NDArray[np.uint8], runs: NDArray[np.int64], *,
               compiled: bool | None = None) -> bool:
    """Whether every row of ``rows`` (N, W) holds ``template``'s bytes in ``runs``
    (:func:`fixed_runs`): a whole chunk's messages checked against their layout at memcmp speed
    (compiled), or one numpy comparison per run."""
    if rows.shape[0] == 0:
        return True
    if use_compiled(compiled) and rows.strides[1] == 1:
        return fast.match_rows(rows, template, runs)
    return all(np.array_equal(rows[:, a:a + n], np.broadcast_to(template[a:a + n], (rows.shape[0], n)))
               for a, n in runs.tolist())


def _stamps_from(rows: NDArray[np.uint8]) -> NDArray[np.int64]:
    sec = rows[:, 4:8].copy().view('<i4')[:, 0].astype(np.int64)
    nsec = rows[:, 8:12].copy().view('<u4')[:, 0].astype(np.int64)
    return sec * 1_000_000_000 + nsec


class _Layout:
    """A fixed message layout: template bytes, where the float64 block starts, how many."""

    def __init__(self, body_before: bytes, n_float: int, body_after: bytes) -> None:
        # body_before: everything after the stamp up to (and including padding before) floats
        self.prefix = ENCAPSULATION + b'\x00' * 8 + body_before
        self.float_offset = len(self.prefix)
        self.n_float = n_float
        self.suffix = body_after
        self.size = self.float_offset + 8 * n_float + len(body_after)
        template = np.frombuffer(self.prefix + b'\x00' * (8 * n_float) + body_after, np.uint8)
        self.template = template
        # a message's stamp and numbers as fields of a structured view of its bytes
        self._dtype = np.dtype({'names': ['sec', 'nsec', 'values'],
                                'formats': ['<i4', '<u4', ('<f8', (n_float,))],
                                'offsets': [4, 8, self.float_offset], 'itemsize': self.size})
        fixed = np.ones(self.size, dtype=bool)
        fixed[4:12] = False  # stamp
        fixed[self.float_offset:self.float_offset + 8 * n_float] = False
        self._runs = fixed_runs(fixed)

    def encode(self, stamps_ns: NDArray[np.int64], values: NDArray[np.float64]) -> NDArray[np.uint8]:
        """(N, size) bytes of N messages. values : shape (N, n_float)."""
        n = len(stamps_ns)
        rows = np.empty((n, self.size), dtype=np.uint8)
        rows[:] = self.template
        sec, nsec = split_stamps(stamps_ns)
        rows[:, 4:8] = sec.astype('<i4').view(np.uint8).reshape(n, 4)
        rows[:, 8:12] = nsec.astype('<u4').view(np.uint8).reshape(n, 4)
        block = np.ascontiguousarray(values, dtype='<f8').reshape(n, self.n_float)
        rows[:, self.float_offset:self.float_offset + 8 * self.n_float] = block.view(np.uint8)
        return rows

    def decode(self, rows: NDArray[np.uint8]) -> tuple[NDArray[np.int64], NDArray[np.float64]] | None:
        """Stamps (N,) and values (N, n_float) if every row matches this layout, else None."""
        if rows.ndim != 2 or rows.shape[1] != self.size:
            return None
        if not rows_match(rows, self.template, self._runs):
            return None
        view = rows.view(self._dtype)[:, 0] if rows.strides[1] == 1 and rows.shape[0] else None
        if view is None:
            block = rows[:, self.float_offset:self.float_offset + 8 * self.n_float].copy()
            return _stamps_from(rows), block.view('<f8').reshape(rows.shape[0], self.n_float)
        stamps = view['sec'].astype(np.int64) * 1_000_000_000 + view['nsec']
        return stamps, view['values'].copy()


class PendingRows:
    """N messages of one fixed layout, not yet encoded: a writer fills their stamps and values
    straight into its message records (:meth:`mmd_ros.logs.writer.LogWriter.write_rows`), which
    saves building the (N, size) byte array first. :meth:`encode` gives that array.

    layout : the :class:`_Layout`; stamps_ns : (N,) [ns]; values : (N, layout.n_float)
    """

    def __init__(self, layout: _Layout, stamps_ns: NDArray[np.int64], values: NDArray[np.float64]) -> None:
        self.layout = layout
        self.stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        self.values = np.asarray(values, dtype=np.float64).reshape(len(self.stamps_ns), layout.n_float)

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.stamps_ns), self.layout.size)

    def encode(self) -> NDArray[np.uint8]:
        return self.layout.encode(self.stamps_ns, self.values)


class JointStateLayout(_Layout):
    """sensor_msgs/msg/JointState with fixed ``name`` list, ``position`` of that length, empty
    ``velocity`` and ``effort``."""

    def __init__(self, names: list[str], frame_id: str = '') -> None:
        buf = _Buffer()
        buf.data.extend(b'\x00' * 8)  # stamp placeholder
        buf.string(frame_id)
        buf.u32(len(names))
        for name in names:
            buf.string(name)
        buf.u32(len(names))
        buf.align(8)
        before = bytes(buf.data[8:])
        after = _Buffer()
        after.data.extend(b'\x00' * (len(buf.data) + 8 * len(names)))
        after.u32(0)  # velocity
        after.u32(0)  # effort
        tail = bytes(after.data[len(buf.data) + 8 * len(names):])
        super().__init__(before, len(names), tail)
        self.names = list(names)
        self.frame_id = frame_id


class PoseLayout(_Layout):
    """geometry_msgs/msg/PoseStamped, or PoseWithCovarianceStamped with ``covariance`` True.

    Values are ``[px, py, pz, qx, qy, qz, qw]`` (+ 36 covariance entries, row-major, in the
    message's x, y, z, rotation-about-x, -y, -z order).
    """

    def __init__(self, frame_id: str, covariance: bool = False) -> None:
        buf = _Buffer()
        buf.data.extend(b'\x00' * 8)
        buf.string(frame_id)
        buf.align(8)
        super().__init__(bytes(buf.data[8:]), 7 + (36 if covariance else 0), b'')
        self.frame_id = frame_id
        self.covariance = covariance

    @staticmethod
    def values_from_poses(poses: NDArray[np.float64],
                          covariance: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """Pose vectors [x, y, z, phi, theta, psi] (N, 6) to message values (N, 7 or 43)."""
        p = np.asarray(poses, dtype=np.float64)
        parts = [p[:, :3], angles_to_quaternion(p[:, 3:])]
        if covariance is not None:
            parts.append(np.asarray(covariance, dtype=np.float64).reshape(len(p), 36))
        return np.concatenate(parts, axis=1)


def encode_joint_state(names: list[str], stamp_ns: int, position: NDArray[np.float64], *,
                       effort: NDArray[np.float64] | None = None, frame_id: str = '') -> bytes:
    """One sensor_msgs/msg/JointState with ``position`` (and ``effort``, e.g. the terminal's
    channel status codes of a flagged ``/mmd/raw_counts`` sample) of ``len(names)`` values and
    an empty ``velocity``; for the messages that do not fit a batch's layout."""
    sec, nsec = split_stamps(np.array([stamp_ns], dtype=np.int64))
    buf = _Buffer()
    buf.data.extend(struct.pack('<iI', int(sec[0]), int(nsec[0])))
    buf.string(frame_id)
    buf.u32(len(names))
    for name in names:
        buf.string(name)
    for values in (position, (), () if effort is None else effort):
        values = np.asarray(values, dtype='<f8').ravel()
        buf.u32(values.size)
        if values.size:
            buf.align(8)
            buf.data.extend(values.tobytes())
    return ENCAPSULATION + bytes(buf.data)


def encode_string(text: str) -> bytes:
    """std_msgs/msg/String."""
    buf = _Buffer()
    buf.string(text)
    return ENCAPSULATION + bytes(buf.data)


def decode_string(payload: bytes) -> str:
    """std_msgs/msg/String; raises ValueError on a malformed payload."""
    if len(payload) < 8 or payload[:2] != b'\x00\x01':
        raise ValueError('not a little-endian CDR std_msgs/String')
    (length,) = struct.unpack_from('<I', payload, 4)
    if length == 0 or 8 + length > len(payload):
        raise ValueError('std_msgs/String length runs past the message')
    return payload[8:8 + length - 1].decode('utf-8')
