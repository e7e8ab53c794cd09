"""The encoder terminal's vendor-specific USB protocol, version 1 (``msg_docs/usb_protocol.md``).

The terminal (paper, section 5.1) counts the A/B quadrature signals of eight ball bars with
32-bit hardware counters, samples them at 1 kHz and sends each sample to the PC as one 64-byte
**sample frame** on bulk IN endpoint 0x81, several frames per USB transfer. The host sends
16-byte **commands** on bulk OUT endpoint 0x01 and reads each **reply** on bulk IN endpoint 0x82,
so a reply never has to be fished out of the sample stream. Everything is little-endian and
protected by CRC-32 (IEEE 802.3, the polynomial of zlib and Ethernet).

Encoding and decoding of frames work on whole batches with numpy (no Python loop per frame), so
the same decoder serves the live driver at 1 kHz and the replay of long logs. (The live stream's
common case, valid frames that continue it, is also decoded by compiled code:
:class:`~mmd_ros.hardware.stream.FrameStream`.)

Sample frame, 64 bytes (offsets in bytes)::

    0  u16  magic 0x444D ("MD")        16  i32[8] counts (hardware counters, wrap at 2^31)
    2  u8   protocol version (1)       48  u16   channel status (bits 0-7 signal lost,
    3  u8   frame type 'S' (0x53)                 bits 8-15 quadrature error, bit i = channel i)
    4  u32  sequence number (wraps)    50  u16   flags (bit 0 counter reset, bit 1 FIFO overflow)
    8  u64  device time [ns]           52  u16   FIFO level [frames] after this frame was queued
                                       54  u8[6] reserved, zero
                                       60  u32   CRC-32 of bytes 0-59
"""

from __future__ import annotations

import enum
import functools
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.hardware.errors import ProtocolError

__all__ = [
    'CHANNEL_STATUS_QUADRATURE_ERROR_SHIFT', 'CHANNEL_STATUS_SIGNAL_LOST_SHIFT', 'COMMAND_DTYPE',
    'COMMAND_SIZE', 'COUNTER_BITS', 'Command', 'DecodedFrames', 'DeviceInfo', 'EP_COMMAND_OUT',
    'EP_REPLY_IN', 'EP_SAMPLES_IN', 'FLAG_COUNTER_RESET', 'FLAG_FIFO_OVERFLOW', 'FRAME_DTYPE',
    'FRAME_SIZE', 'INFO_DTYPE', 'INTERFACE_NUMBER', 'MAGIC', 'MAX_FRAMES_PER_TRANSFER',
    'MAX_REPLY_SIZE', 'MAX_SAMPLE_RATE_HZ', 'N_CHANNELS', 'Opcode', 'PRODUCT_ID',
    'PROTOCOL_VERSION', 'REPLY_HEADER_DTYPE', 'Reply', 'Status', 'TYPE_COMMAND', 'TYPE_REPLY',
    'TYPE_SAMPLE', 'VENDOR_ID', 'crc32_rows', 'decode_command', 'decode_frames', 'decode_info',
    'decode_reply', 'encode_command', 'encode_frames', 'encode_info', 'encode_reply',
    'wrap_counts',
]

# --- USB identity -------------------------------------------------------------------------
#: pid.codes' vendor id for open hardware.
VENDOR_ID = 0x1209
#: Product id in pid.codes' range for testing (0x0000-0x0FFF); a registered PID replaces it
#: before terminals leave the lab (change it here and in config/99-mmd-terminal.rules).
PRODUCT_ID = 0x0001
INTERFACE_NUMBER = 0
EP_COMMAND_OUT = 0x01
EP_SAMPLES_IN = 0x81
EP_REPLY_IN = 0x82

# --- frames -------------------------------------------------------------------------------
MAGIC = 0x444D  # b'MD' little-endian
PROTOCOL_VERSION = 1
TYPE_SAMPLE = 0x53  # 'S'
TYPE_COMMAND = 0x43  # 'C'
TYPE_REPLY = 0x52  # 'R'
N_CHANNELS = 8
COUNTER_BITS = 32
FRAME_SIZE = 64
#: Bytes covered by a frame's CRC (everything before the CRC field).
FRAME_CRC_SPAN = 60
MAX_FRAMES_PER_TRANSFER = 64
MAX_SAMPLE_RATE_HZ = 10_000

FLAG_COUNTER_RESET = 0x0001
FLAG_FIFO_OVERFLOW = 0x0002
CHANNEL_STATUS_SIGNAL_LOST_SHIFT = 0
CHANNEL_STATUS_QUADRATURE_ERROR_SHIFT = 8

FRAME_DTYPE = np.dtype({
    'names': ['magic', 'version', 'type', 'seq', 'time_ns', 'counts', 'channel_status', 'flags',
              'fifo_level', 'reserved', 'crc'],
    'formats': ['<u2', 'u1', 'u1', '<u4', '<u8', ('<i4', (N_CHANNELS,)), '<u2', '<u2', '<u2',
                ('u1', (6,)), '<u4'],
    'offsets': [0, 2, 3, 4, 8, 16, 48, 50, 52, 54, 60],
    'itemsize': FRAME_SIZE,
})

_COUNTER_MOD = 1 << COUNTER_BITS
_COUNTER_HALF = 1 << (COUNTER_BITS - 1)


# --- CRC-32, vectorised ---------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _crc_tables(length: int) -> tuple[NDArray[np.uint32], int]:
    """Per-position CRC-32 tables for messages of a fixed length.

    CRC-32 is affine over GF(2): for messages of one length, crc(m) = crc(0) XOR the XOR over
    byte positions i of T[i, m_i], where T[i, b] = crc(b at position i, zeros elsewhere) XOR
    crc(0). A batch of frames is then one table gather and one XOR-reduction.
    """
    n = length * 256
    msgs = np.zeros((n, length), np.uint8)
    k = np.arange(n)
    msgs[k, k // 256] = k % 256
    zero = zlib.crc32(bytes(length))
    table = np.fromiter((zlib.crc32(m) for m in msgs), dtype=np.uint32, count=n) ^ np.uint32(zero)
    return table, zero


#: Up to this many rows, :func:`crc32_rows` calls zlib per row (measured faster than the tables).
_CRC_LOOP_ROWS = 32


def crc32_rows(rows: NDArray[np.uint8]) -> NDArray[np.uint32]:
    """CRC-32 (IEEE 802.3, as ``zlib.crc32``) of each row of a byte matrix.

    rows : ndarray, shape (N, L), uint8 — N messages of L bytes each
    returns : ndarray, shape (N,), uint32
    """
    rows = np.asarray(rows, dtype=np.uint8)
    n, length = rows.shape
    if n <= _CRC_LOOP_ROWS:
        # a live transfer (8 frames): zlib row by row beats the table's fixed cost
        return np.fromiter((zlib.crc32(r) for r in np.ascontiguousarray(rows)), np.uint32, n)
    table, zero = _crc_tables(length)
    offsets = (np.arange(length, dtype=np.intp) * 256)[None, :]
    out = np.empty(n, np.uint32)
    chunk = 4096  # keeps the gathered block (chunk x L x 4 bytes) in cache
    for s in range(0, n, chunk):
        block = table[rows[s:s + chunk].astype(np.intp) + offsets]
        out[s:s + chunk] = np.bitwise_xor.reduce(block, axis=1) if length else 0
    return out ^ np.uint32(zero)


def wrap_counts(counts: ArrayLike) -> NDArray[np.int32]:
    """Truncate counts to the terminal's signed 32-bit wrapping counters.

    counts : array_like of int — unwrapped counts [counts]
    returns : ndarray of int32, same shape — ((c + 2^31) mod 2^32) - 2^31
    """
    c = np.asarray(counts, dtype=np.int64)
    return ((c + _COUNTER_HALF) % _COUNTER_MOD - _COUNTER_HALF).astype(np.int32)


# --- sample frames --------------------------------------------------------------------------
def encode_frames(seq: ArrayLike, time_ns: ArrayLike, counts: ArrayLike,
                  channel_status: ArrayLike = 0, flags: ArrayLike = 0,
                  fifo_level: ArrayLike = 0) -> bytes:
    """Encode N samples as N consecutive sample frames.

    seq : array_like, shape (N,) — sequence numbers (taken modulo 2^32)
    time_ns : array_like, shape (N,) — device time [ns], 0 <= t < 2^64
    counts : array_like, shape (N, 8) — counts [counts]; any int64, truncated to the 32-bit
        wrapping hardware counter (:func:`wrap_counts`)
    channel_status, flags, fifo_level : array_like, shape (N,) or scalar — see module docstring
    returns : bytes of length 64 N
    """
    c = np.asarray(counts, dtype=np.int64)
    if c.ndim != 2 or c.shape[1] != N_CHANNELS:
        raise ValueError(f'counts must have shape (N, {N_CHANNELS}), got {c.shape}')
    n = c.shape[0]
    f = np.zeros(n, FRAME_DTYPE)
    f['magic'] = MAGIC
    f['version'] = PROTOCOL_VERSION
    f['type'] = TYPE_SAMPLE
    f['seq'] = np.asarray(seq, dtype=np.int64) % (1 << 32)
    f['time_ns'] = np.asarray(time_ns, dtype=np.uint64)
    f['counts'] = wrap_counts(c)
    f['channel_status'] = channel_status
    f['flags'] = flags
    f['fifo_level'] = fifo_level
    raw = f.view(np.uint8).reshape(n, FRAME_SIZE)
    f['crc'] = crc32_rows(raw[:, :FRAME_CRC_SPAN])
    return f.tobytes()


@dataclass(frozen=True)
class DecodedFrames:
    """Fields of N received frames, as arrays; ``valid`` says which frames may be used.

    seq : ndarray, shape (N,), uint32 — sequence numbers
    time_ns : ndarray, shape (N,), int64 — device time [ns]
    counts : ndarray, shape (N, 8), int32 — raw 32-bit counter values [counts]
    channel_status, flags, fifo_level : ndarray, shape (N,), uint16
    valid : ndarray, shape (N,), bool — magic, version, type and CRC all correct
    trailing_bytes : bytes after the last whole frame (a framing error when non-zero)
    """

    seq: NDArray[np.uint32]
    time_ns: NDArray[np.int64]
    counts: NDArray[np.int32]
    channel_status: NDArray[np.uint16]
    flags: NDArray[np.uint16]
    fifo_level: NDArray[np.uint16]
    valid: NDArray[np.bool_]
    trailing_bytes: int = 0

    @property
    def n(self) -> int:
        return int(self.seq.shape[0])

    @property
    def n_invalid(self) -> int:
        return int(self.n - np.count_nonzero(self.valid))

    def select(self, mask: NDArray[np.bool_]) -> DecodedFrames:
        """The frames where ``mask`` is true."""
        return DecodedFrames(self.seq[mask], self.time_ns[mask], self.counts[mask],
                             self.channel_status[mask], self.flags[mask], self.fifo_level[mask],
                             self.valid[mask], 0)


def decode_frames(data: bytes | bytearray | memoryview | NDArray[np.uint8]) -> DecodedFrames:
    """Decode a buffer of consecutive sample frames (one or many USB transfers).

    Frames with a wrong magic, version, type or CRC are kept in the result with
    ``valid == False`` so that the caller can count them; their fields are meaningless.

    data : bytes-like — 64 N bytes (+ trailing bytes, reported, ignored)
    returns : :class:`DecodedFrames`
    """
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.ravel()
    n = buf.size // FRAME_SIZE
    trailing = buf.size - n * FRAME_SIZE
    raw = buf[:n * FRAME_SIZE]
    f = raw.view(FRAME_DTYPE)
    rows = raw.reshape(n, FRAME_SIZE)
    valid = ((f['magic'] == MAGIC) & (f['version'] == PROTOCOL_VERSION) & (f['type'] == TYPE_SAMPLE)
             & (crc32_rows(rows[:, :FRAME_CRC_SPAN]) == f['crc']))
    return DecodedFrames(
        seq=f['seq'].astype(np.uint32),
        time_ns=f['time_ns'].astype(np.int64),
        counts=f['counts'].astype(np.int32),
        channel_status=f['channel_status'].astype(np.uint16),
        flags=f['flags'].astype(np.uint16),
        fifo_level=f['fifo_level'].astype(np.uint16),
        valid=valid,
        trailing_bytes=int(trailing),
    )


# --- commands and replies ---------------------------------------------------------------------
class Opcode(enum.IntEnum):
    """Command opcodes (byte 4 of a command, echoed in the reply)."""

    GET_INFO = 0x01
    START_STREAM = 0x02
    STOP_STREAM = 0x03
    SET_SAMPLE_RATE = 0x04  # arg: rate [Hz], 1..MAX_SAMPLE_RATE_HZ; only while stopped
    SET_FRAMES_PER_TRANSFER = 0x05  # arg: 1..MAX_FRAMES_PER_TRANSFER
    CLEAR_RESET_FLAG = 0x06  # acknowledge a counter reset: the flag clears in later frames


class Status(enum.IntEnum):
    """Reply status codes (byte 5 of a reply)."""

    OK = 0
    BAD_COMMAND = 1  # wrong magic, version, type, length or CRC
    UNKNOWN_OPCODE = 2
    BAD_ARGUMENT = 3
    BUSY = 4  # not allowed while streaming


COMMAND_SIZE = 16
COMMAND_DTYPE = np.dtype({
    'names': ['magic', 'version', 'type', 'opcode', 'reserved', 'tag', 'arg', 'crc'],
    'formats': ['<u2', 'u1', 'u1', 'u1', 'u1', '<u2', '<u4', '<u4'],
    'offsets': [0, 2, 3, 4, 5, 6, 8, 12],
    'itemsize': COMMAND_SIZE,
})
REPLY_HEADER_DTYPE = np.dtype({
    'names': ['magic', 'version', 'type', 'opcode', 'status', 'tag', 'payload_len', 'reserved'],
    'formats': ['<u2', 'u1', 'u1', 'u1', 'u1', '<u2', '<u2', '<u2'],
    'offsets': [0, 2, 3, 4, 5, 6, 8, 10],
    'itemsize': 12,
})
MAX_REPLY_SIZE = 128


@dataclass(frozen=True)
class Command:
    """A decoded command: opcode, host-chosen tag (echoed in the reply), argument."""

    opcode: int
    tag: int
    arg: int


@dataclass(frozen=True)
class Reply:
    """A decoded reply: the command's opcode and tag, a status and a payload."""

    opcode: int
    tag: int
    status: int
    payload: bytes


def _crc(data: bytes) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


def encode_command(opcode: int, tag: int, arg: int = 0) -> bytes:
    """One 16-byte command: opcode, tag (0..65535), argument (0..2^32-1), CRC-32 of bytes 0-11."""
    c = np.zeros(1, COMMAND_DTYPE)
    c['magic'], c['version'], c['type'] = MAGIC, PROTOCOL_VERSION, TYPE_COMMAND
    c['opcode'], c['tag'], c['arg'] = int(opcode), int(tag) & 0xFFFF, int(arg) & 0xFFFFFFFF
    b = c.tobytes()
    return b[:12] + _crc(b[:12]).to_bytes(4, 'little')


def decode_command(data: bytes) -> Command:
    """Parse a command; raise :class:`ProtocolError` naming the first thing that is wrong."""
    if len(data) != COMMAND_SIZE:
        raise ProtocolError(f'a command is {COMMAND_SIZE} bytes, got {len(data)}')
    c = np.frombuffer(bytes(data), COMMAND_DTYPE)[0]
    if int(c['magic']) != MAGIC or int(c['version']) != PROTOCOL_VERSION or int(c['type']) != TYPE_COMMAND:
        raise ProtocolError(
            f'not a version-{PROTOCOL_VERSION} command: magic 0x{int(c["magic"]):04x}, '
            f'version {int(c["version"])}, type 0x{int(c["type"]):02x}')
    if _crc(bytes(data[:12])) != int(c['crc']):
        raise ProtocolError('command CRC mismatch: the command was damaged in transit; send it again')
    return Command(int(c['opcode']), int(c['tag']), int(c['arg']))


def encode_reply(opcode: int, tag: int, status: int, payload: bytes = b'') -> bytes:
    """One reply: 12-byte header, payload, CRC-32 of everything before it."""
    if len(payload) > MAX_REPLY_SIZE - 16:
        raise ValueError(f'reply payload of {len(payload)} bytes exceeds {MAX_REPLY_SIZE - 16}')
    h = np.zeros(1, REPLY_HEADER_DTYPE)
    h['magic'], h['version'], h['type'] = MAGIC, PROTOCOL_VERSION, TYPE_REPLY
    h['opcode'], h['status'], h['tag'] = int(opcode), int(status), int(tag) & 0xFFFF
    h['payload_len'] = len(payload)
    body = h.tobytes() + bytes(payload)
    return body + _crc(body).to_bytes(4, 'little')


def decode_reply(data: bytes) -> Reply:
    """Parse a reply; raise :class:`ProtocolError` naming the first thing that is wrong."""
    data = bytes(data)
    if len(data) < 16:
        raise ProtocolError(f'a reply is at least 16 bytes, got {len(data)}')
    h = np.frombuffer(data[:12], REPLY_HEADER_DTYPE)[0]
    if int(h['magic']) != MAGIC or int(h['version']) != PROTOCOL_VERSION or int(h['type']) != TYPE_REPLY:
        raise ProtocolError(
            f'not a version-{PROTOCOL_VERSION} reply: magic 0x{int(h["magic"]):04x}, '
            f'version {int(h["version"])}, type 0x{int(h["type"]):02x}')
    size = 16 + int(h['payload_len'])
    if len(data) != size:
        raise ProtocolError(f'reply announces {size} bytes but {len(data)} arrived')
    if _crc(data[:-4]) != int.from_bytes(data[-4:], 'little'):
        raise ProtocolError('reply CRC mismatch: the reply was damaged in transit')
    return Reply(int(h['opcode']), int(h['tag']), int(h['status']), data[12:-4])


# --- device information -------------------------------------------------------------------------
INFO_DTYPE = np.dtype({
    'names': ['vendor', 'model', 'serial', 'firmware', 'n_channels', 'counter_bits',
              'protocol_version', 'frames_per_transfer', 'sample_rate_hz', 'max_sample_rate_hz',
              'frame_size', 'reserved'],
    'formats': ['S16', 'S16', 'S16', 'S16', 'u1', 'u1', 'u1', 'u1', '<u4', '<u4', '<u2', '<u2'],
    'offsets': [0, 16, 32, 48, 64, 65, 66, 67, 68, 72, 76, 78],
    'itemsize': 80,
})


@dataclass(frozen=True)
class DeviceInfo:
    """What the terminal says about itself (GET_INFO reply, 80-byte payload).

    Strings are ASCII, at most 16 bytes. ``sample_rate_hz`` is the current rate [Hz],
    ``counter_bits`` the width of the wrapping hardware counters (32).
    """

    vendor: str
    model: str
    serial: str
    firmware: str
    n_channels: int = N_CHANNELS
    counter_bits: int = COUNTER_BITS
    protocol_version: int = PROTOCOL_VERSION
    frames_per_transfer: int = 8
    sample_rate_hz: int = 1000
    max_sample_rate_hz: int = MAX_SAMPLE_RATE_HZ
    frame_size: int = FRAME_SIZE

    def as_dict(self) -> dict[str, str | int]:
        return dict(self.__dict__)


def encode_info(info: DeviceInfo) -> bytes:
    """The 80-byte GET_INFO payload of ``info``."""
    r = np.zeros(1, INFO_DTYPE)
    for key in ('vendor', 'model', 'serial', 'firmware'):
        text = getattr(info, key).encode('ascii')
        if len(text) > 16:
            raise ValueError(f'{key} "{getattr(info, key)}" is longer than 16 ASCII characters')
        r[key] = text
    for key in ('n_channels', 'counter_bits', 'protocol_version', 'frames_per_transfer',
                'sample_rate_hz', 'max_sample_rate_hz', 'frame_size'):
        r[key] = getattr(info, key)
    return r.tobytes()


def decode_info(payload: bytes) -> DeviceInfo:
    """Parse a GET_INFO payload."""
    if len(payload) != INFO_DTYPE.itemsize:
        raise ProtocolError(f'GET_INFO payload must be {INFO_DTYPE.itemsize} bytes, got {len(payload)}')
    r = np.frombuffer(bytes(payload), INFO_DTYPE)[0]
    text = {k: bytes(r[k]).rstrip(b'\0').decode('ascii', 'replace')
            for k in ('vendor', 'model', 'serial', 'firmware')}
    return DeviceInfo(**text, **{k: int(r[k]) for k in (
        'n_channels', 'counter_bits', 'protocol_version', 'frames_per_transfer', 'sample_rate_hz',
        'max_sample_rate_hz', 'frame_size')})
