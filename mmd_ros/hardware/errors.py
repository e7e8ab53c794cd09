"""Exceptions of the hardware layer. Each message says what was wrong and what to do.

All derive from :class:`HardwareError`, itself an :class:`mmd_ros.core.errors.MmdError`, so a
caller can catch the whole area at once. USB errors from pyusb never leave the driver raw: they
are translated here, with the original kept as ``__cause__``.
"""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = [
    'AmbiguousTerminalError', 'CommandError', 'HardwareError', 'IncompatibleTerminalError',
    'ProtocolError', 'TerminalAccessError', 'TerminalBusyError', 'TerminalClosedError',
    'TerminalDisconnectedError', 'TerminalNotFoundError', 'TerminalTimeoutError',
]


class HardwareError(MmdError):
    """Base class of every error raised by :mod:`mmd_ros.hardware`."""


class ProtocolError(HardwareError):
    """Bytes that do not follow the terminal protocol (``msg_docs/usb_protocol.md``).

    Raised for a malformed command or reply. Sample frames are never raised about: a bad frame
    is dropped and counted (see :class:`mmd_ros.hardware.stream.DriverStats`).
    """


class CommandError(HardwareError):
    """The terminal received a command and refused it (reply status other than OK)."""

    def __init__(self, command: str, status: str, hint: str) -> None:
        self.command = command
        self.status = status
        super().__init__(f'terminal refused {command}: {status}; {hint}')


class TerminalNotFoundError(HardwareError):
    """No terminal with the requested USB ids (and serial number) is on the bus."""


class AmbiguousTerminalError(HardwareError):
    """Several terminals match and no serial number says which one to use."""


class TerminalAccessError(HardwareError):
    """The terminal is present but the operating system refuses to open it (permissions)."""


class TerminalBusyError(HardwareError):
    """Another process holds the terminal's interface."""


class IncompatibleTerminalError(HardwareError):
    """The terminal speaks another protocol version or has another channel layout."""


class TerminalDisconnectedError(HardwareError):
    """The terminal left the bus (cable pulled, hub reset, power lost) or has not come back yet."""


class TerminalTimeoutError(HardwareError):
    """The terminal sent nothing within the time limit (stalled or hung firmware)."""


class TerminalClosedError(HardwareError):
    """The driver is not open: a read or command was attempted before ``open()`` or after ``close()``."""
