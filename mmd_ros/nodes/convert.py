"""Messages ↔ arrays, for every topic of the mmd nodes (units in ``msg_docs/nodes.md``).

Per-sample topics are built for a whole transfer at once as CDR bytes, with the fixed layouts
of :mod:`mmd_ros.logs.cdr` (one numpy pass per topic instead of one Python message object per
sample); the bytes are published as they are (``Publisher.publish(bytes)``) and written as they
are into logs, so a log holds exactly what was published. Subscribers get ordinary message
objects, turned into arrays here.
"""

from __future__ import annotations

import struct

import numpy as np
from builtin_interfaces.msg import Time
from numpy.typing import NDArray
from std_msgs.msg import Header, String

from mmd_ros.core.rotation import angles_to_quaternion, quaternion_to_angles
from mmd_ros.logs.cdr import ENCAPSULATION, JointStateLayout, PoseLayout, encode_string, split_stamps
from mmd_ros.logs.layout import BAR_NAMES, FK_STATUS_NAMES, FRAME_LOWER, REFERENCE_POSE_NAMES, flag_runs

__all__ = [
    'DIAGNOSTIC_ARRAY', 'FK_STATUS_NAMES', 'HEADER', 'JS', 'PATH', 'POSE', 'POSE_COV', 'PathLayout',
    'RawBatch', 'Rows',
    'STRING', 'from_time', 'header', 'joint_state_values', 'pose_from_msg', 'string_bytes',
    'stamp_of_serialized', 'string_msg', 'thermal_names', 'to_time',
]

JS = 'sensor_msgs/msg/JointState'
PATH = 'nav_msgs/msg/Path'
POSE = 'geometry_msgs/msg/PoseStamped'
POSE_COV = 'geometry_msgs/msg/PoseWithCovarianceStamped'
STRING = 'std_msgs/msg/String'
HEADER = 'std_msgs/msg/Header'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'


def thermal_names(reference_channels: list[str]) -> list[str]:
    """Names of /mmd/thermal: Eq. (11) error per reference bar [m], the temperature change
    since the thermal zero [°C], the plates' scale factor (1 + alpha dT) [1]."""
    return [f'{name}_error' for name in reference_channels] + ['temp_change', 'plate_scale']


def to_time(stamp_ns: int) -> Time:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def from_time(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def stamp_of_serialized(data: bytes) -> int:
    """``header.stamp`` [ns] of a serialised message whose first field is a std_msgs/Header
    (PoseStamped, JointState, ...), read without deserialising it: after the 4-byte CDR
    encapsulation header (byte 1 = 1: little-endian), int32 sec and uint32 nanosec."""
    sec, nanosec = struct.unpack_from('<iI' if data[1] == 1 else '>iI', data, 4)
    return sec * 1_000_000_000 + nanosec


def header(stamp_ns: int, frame_id: str = '') -> Header:
    return Header(stamp=to_time(stamp_ns), frame_id=frame_id)


def string_msg(text: str) -> String:
    return String(data=text)


def string_bytes(text: str) -> bytes:
    """A std_msgs/msg/String as CDR bytes."""
    return encode_string(text)


def joint_state_values(msg, names: list[str] | None = None) -> NDArray[np.float64]:
    """``position`` of a JointState as an array, in the order of ``names`` (checked)."""
    values = np.asarray(msg.position, dtype=np.float64)
    if names is not None and list(msg.name) != names:
        index = {n: k for k, n in enumerate(msg.name)}
        missing = [n for n in names if n not in index]
        if missing:
            raise ValueError(f'joint state lacks {missing} (has {list(msg.name)})')
        values = values[[index[n] for n in names]]
    return values


def pose_from_msg(pose) -> NDArray[np.float64]:
    """[x, y, z, roll, pitch, yaw] [m, rad] (Eq. 3) of a geometry_msgs/Pose."""
    q = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
    ang = quaternion_to_angles(np.array(q))
    return np.array([pose.position.x, pose.position.y, pose.position.z, *ang])


class PathLayout:
    """``nav_msgs/msg/Path`` as CDR bytes: the poses of one transfer in one message.

    ``header.stamp`` is the last pose's stamp, each ``poses[k]`` a ``PoseStamped`` with its
    sample's own stamp; every header has ``frame_id`` ``frame_id``. The byte layout for n poses
    (alignment differs from one element to the next) is built once and cached.
    """

    def __init__(self, frame_id: str) -> None:
        self.frame = frame_id.encode('utf-8') + b'\x00'
        self._templates: dict[int, tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64]]] = {}

    def _template(self, n: int) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64]]:
        if n in self._templates:
            return self._templates[n]
        buf = bytearray()

        def align(k: int) -> None:
            buf.extend(b'\x00' * (-len(buf) % k))

        def header() -> int:
            align(4)
            at = len(buf)
            buf.extend(b'\x00' * 8)
            buf.extend(struct.pack('<I', len(self.frame)) + self.frame)
            return at

        stamps = [header()]
        align(4)
        buf.extend(struct.pack('<I', n))
        values = []
        for _ in range(n):
            stamps.append(header())
            align(8)
            values.append(len(buf))
            buf.extend(b'\x00' * 56)
        four = len(ENCAPSULATION)
        out = (np.frombuffer(ENCAPSULATION + bytes(buf), np.uint8).copy(),
               np.asarray(stamps, np.int64) + four, np.asarray(values, np.int64) + four)
        if len(self._templates) < 256:
            self._templates[n] = out
        return out

    def encode(self, stamps_ns: NDArray[np.int64], values: NDArray[np.float64]) -> bytes:
        """One Path of n poses: stamps (n,) [ns], values (n, 7) [x y z qx qy qz qw]."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        n = int(stamps_ns.size)
        template, stamp_at, value_at = self._template(n)
        data = template.copy()
        all_stamps = np.concatenate([stamps_ns[-1:] if n else np.zeros(1, np.int64), stamps_ns])
        sec, nsec = split_stamps(all_stamps)
        words = np.column_stack([sec.astype('<i4').view('<u4'), nsec.astype('<u4')]).view(np.uint8)
        data[stamp_at[:, None] + np.arange(8)] = words.reshape(-1, 8)
        if n:
            block = np.ascontiguousarray(values, dtype='<f8').reshape(n, 7).view(np.uint8)
            data[value_at[:, None] + np.arange(56)] = block
        return data.tobytes()


class _StatusLayout:
    """A ``sensor_msgs/JointState`` with fixed names, ``position`` and ``effort`` of that length
    and an empty ``velocity``, as CDR rows: rclpy serialises a template once, the offsets of
    the stamp and of both blocks are found in it, and N messages are filled in with numpy."""

    def __init__(self, names: list[str]) -> None:
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import JointState
        k = len(names)
        marks = [float(1000 + i) for i in range(k)], [float(2000 + i) for i in range(k)]
        data = serialize_message(JointState(header=header(0), name=list(names), position=marks[0],
                                            effort=marks[1]))
        self.template = np.frombuffer(data, np.uint8).copy()
        self.k = k
        self.position_at = data.index(struct.pack('<d', marks[0][0]))
        self.effort_at = data.index(struct.pack('<d', marks[1][0]))
        self.template[self.position_at:self.position_at + 8 * k] = 0
        self.template[self.effort_at:self.effort_at + 8 * k] = 0

    def encode(self, stamps_ns: NDArray[np.int64], position: NDArray[np.float64],
               effort: NDArray[np.uint8]) -> NDArray[np.uint8]:
        n = len(stamps_ns)
        rows = np.empty((n, self.template.size), np.uint8)
        rows[:] = self.template
        sec, nsec = split_stamps(np.asarray(stamps_ns, dtype=np.int64))
        rows[:, 4:8] = sec.astype('<i4').view(np.uint8).reshape(n, 4)
        rows[:, 8:12] = nsec.astype('<u4').view(np.uint8).reshape(n, 4)
        for at, values in ((self.position_at, position), (self.effort_at, effort)):
            block = np.ascontiguousarray(values, dtype='<f8').reshape(n, self.k)
            rows[:, at:at + 8 * self.k] = block.view(np.uint8)
        return rows


class Rows:
    """CDR bytes of N samples of each per-sample topic (fixed layouts, built once).

    channel_names : the terminal's 8 channel names (/mmd/raw_counts)
    reference_channels : names of the reference-bar channels (/mmd/thermal)
    """

    def __init__(self, channel_names: list[str], reference_channels: list[str]) -> None:
        self.raw = JointStateLayout(list(channel_names))
        self.lengths = JointStateLayout(list(BAR_NAMES))
        self.thermal_names = thermal_names(reference_channels)
        self.thermal = JointStateLayout(self.thermal_names)
        self.fk_status = JointStateLayout(FK_STATUS_NAMES)
        self.reference = JointStateLayout(REFERENCE_POSE_NAMES, FRAME_LOWER)
        self.pose = PoseLayout(FRAME_LOWER)
        self.pose_cov = PoseLayout(FRAME_LOWER, covariance=True)
        self.path = PathLayout(FRAME_LOWER)
        self._status_layout: _StatusLayout | None = None

    def pose_batch(self, stamps_ns: NDArray[np.int64], poses: NDArray[np.float64]) -> bytes:
        """A Path of poses (n, 6) [m, rad] stamped ``stamps_ns``, frame mmd_lower."""
        return self.path.encode(stamps_ns, PoseLayout.values_from_poses(poses))

    def raw_with_status(self, stamps_ns: NDArray[np.int64], counts: NDArray[np.float64],
                        status: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """``raw_counts`` rows (N, size) whose ``effort`` holds the channel status codes (1
        signal lost, 2 quadrature error, 3 both; 0 good) of samples the terminal flagged."""
        if self._status_layout is None:
            self._status_layout = _StatusLayout(self.raw.names)
        return self._status_layout.encode(stamps_ns, counts, status)

    def raw_parts(self, stamps_ns: NDArray[np.int64], counts: NDArray[np.float64],
                  status: NDArray[np.uint8] | None) -> list[tuple[NDArray[np.uint8], NDArray[np.int64]]]:
        """``raw_counts`` of N samples as (rows, stamps) runs in order: the flagged samples
        (a status code not 0 on some channel) with their codes in ``effort``, the others
        without (``status`` None: none flagged)."""
        if status is None or not np.any(status):
            return [(self.raw.encode(stamps_ns, counts), stamps_ns)]
        flagged = np.any(status != 0, axis=1)
        out = []
        for a, b in flag_runs(flagged):
            part = slice(a, b)
            rows = (self.raw_with_status(stamps_ns[part], counts[part], status[part]) if flagged[a]
                    else self.raw.encode(stamps_ns[part], counts[part]))
            out.append((rows, stamps_ns[part]))
        return out

    def poses(self, stamps_ns: NDArray[np.int64], poses: NDArray[np.float64],
              covariance: NDArray[np.float64] | None = None) -> NDArray[np.uint8]:
        """PoseStamped (or PoseWithCovarianceStamped with ``covariance``) rows, frame mmd_lower."""
        p = np.asarray(poses, dtype=np.float64)
        parts = [p[:, :3], angles_to_quaternion(p[:, 3:])]
        if covariance is None:
            return self.pose.encode(stamps_ns, np.concatenate(parts, axis=1))
        parts.append(np.asarray(covariance, dtype=np.float64).reshape(len(p), 36))
        return self.pose_cov.encode(stamps_ns, np.concatenate(parts, axis=1))


class RawBatch:
    """Serialised messages of a fixed-layout JointState topic, collected from a ``raw=True``
    subscription and decoded together (one numpy pass instead of one Python message object per
    sample). Messages that do not match the layout (another publisher's padding, other names)
    are decoded one by one with rclpy and reordered by name.

    names : the joint names expected, in order; frame_id : their frame
    """

    def __init__(self, names: list[str], frame_id: str = '') -> None:
        self.names = list(names)
        self.layout = JointStateLayout(self.names, frame_id)
        self.items: list[bytes] = []
        self.foreign = 0

    def add(self, payload: bytes) -> int:
        self.items.append(payload)
        return len(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def take(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Stamps (N,) [ns] and values (N, k) of the collected messages, in arrival order."""
        stamps, values, _ = self.take_all()
        return stamps, values

    def take_all(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.uint8] | None]:
        """Stamps (N,) [ns], values (N, k) and the status codes (N, k) that messages with an
        ``effort`` of k values carry (``raw_counts`` of a sample the terminal flagged; 0 for
        the others), or None when no message carries any."""
        items, self.items = self.items, []
        if not items:
            return np.zeros(0, np.int64), np.zeros((0, len(self.names))), None
        size = self.layout.size
        if all(len(p) == size for p in items):
            rows = np.frombuffer(b''.join(items), dtype=np.uint8).reshape(len(items), size)
            decoded = self.layout.decode(rows)
            if decoded is not None:
                return decoded[0], decoded[1], None
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState
        stamps = np.empty(len(items), np.int64)
        values = np.empty((len(items), len(self.names)))
        status = np.zeros((len(items), len(self.names)), np.uint8)
        for i, payload in enumerate(items):
            if len(payload) == size:
                decoded = self.layout.decode(np.frombuffer(payload, np.uint8).reshape(1, size))
                if decoded is not None:
                    stamps[i], values[i] = decoded[0][0], decoded[1][0]
                    continue
            msg = deserialize_message(payload, JointState)
            stamps[i] = from_time(msg.header.stamp)
            values[i] = joint_state_values(msg, self.names)
            if len(msg.effort) == len(self.names):
                status[i] = np.asarray(msg.effort, dtype=np.float64).astype(np.uint8)
            else:
                self.foreign += 1
        return stamps, values, status if status.any() else None
