"""Errors of the log layer."""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = ['LogError', 'LogFormatError', 'StampsNotIncreasing']


class LogError(MmdError):
    """A log cannot be written or read."""


class LogFormatError(LogError):
    """A log holds something our layout does not allow (a wrong type on a topic, for example)."""


class StampsNotIncreasing(LogFormatError):
    """The samples' stamps go backwards or repeat (a log read block by block cannot sort them)."""
