"""Exceptions of the machine analysis. Each message says what was wrong and what to do."""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = ['MachineAnalysisError']


class MachineAnalysisError(MmdError):
    """A session cannot be analysed as asked (no axis positions, missing runs, bad program)."""
