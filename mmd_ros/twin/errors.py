"""Exceptions of the digital twin. Each message says what was wrong and what to do."""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = ['TwinError', 'WorkspaceError']


class TwinError(MmdError):
    """A twin parameter, scenario or request is invalid."""


class WorkspaceError(TwinError):
    """A scenario takes a bar out of its range or a joint beyond its tilt limit."""
