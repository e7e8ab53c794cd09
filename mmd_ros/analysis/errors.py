"""Exceptions of the analysis tools. Each message says what was wrong and what to do."""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = ['AnalysisError']


class AnalysisError(MmdError):
    """A log cannot be analysed as asked (no reference, too few samples, no targets...)."""
