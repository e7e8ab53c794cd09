"""Exceptions of the design tools."""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = ['DesignError']


class DesignError(MmdError):
    """A design-tool request cannot be answered as asked (unknown option, unreachable pose)."""
