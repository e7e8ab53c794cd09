"""Hardware layer: the 8-channel encoder terminal behind a small transport interface.

- :mod:`~mmd_ros.hardware.protocol`: the terminal's USB protocol (frames, commands, CRC-32),
  vectorised with numpy; documented in ``msg_docs/usb_protocol.md``.
- :mod:`~mmd_ros.hardware.stream`: received bytes to checked batches of unwrapped counts.
- :mod:`~mmd_ros.hardware.driver`: :class:`TerminalDriver`, the terminal over pyusb.
- :mod:`~mmd_ros.hardware.sim_backend`: a simulated terminal as a pyusb backend, with faults.
- :mod:`~mmd_ros.hardware.source`: what a simulated terminal samples (:class:`SampleSource`).
- :mod:`~mmd_ros.hardware.transport`: :class:`Transport`, what consumers are written against.

Nothing here imports rclpy or takes a ROS node.
"""

from __future__ import annotations

from mmd_ros.hardware.driver import Backoff, TerminalDriver, default_backend
from mmd_ros.hardware.errors import (
    AmbiguousTerminalError, CommandError, HardwareError, IncompatibleTerminalError, ProtocolError,
    TerminalAccessError, TerminalBusyError, TerminalClosedError, TerminalDisconnectedError,
    TerminalNotFoundError, TerminalTimeoutError,
)
from mmd_ros.hardware.protocol import (
    PRODUCT_ID, VENDOR_ID, DecodedFrames, DeviceInfo, decode_frames, encode_frames,
)
from mmd_ros.hardware.sim_backend import SimTerminal, SimUsbBackend
from mmd_ros.hardware.source import SampleSource, SourceInfo, SyntheticSource
from mmd_ros.hardware.stream import DriverStats, FrameStream, SampleBatch
from mmd_ros.hardware.transport import Transport

__all__ = [
    'AmbiguousTerminalError', 'Backoff', 'CommandError', 'DecodedFrames', 'DeviceInfo',
    'DriverStats', 'FrameStream', 'HardwareError', 'IncompatibleTerminalError', 'PRODUCT_ID',
    'ProtocolError', 'SampleBatch', 'SampleSource', 'SimTerminal', 'SimUsbBackend',
    'SourceInfo', 'SyntheticSource', 'TerminalAccessError', 'TerminalBusyError',
    'TerminalClosedError', 'TerminalDisconnectedError', 'TerminalDriver',
    'TerminalNotFoundError', 'TerminalTimeoutError', 'Transport', 'VENDOR_ID', 'decode_frames',
    'default_backend', 'encode_frames',
]
