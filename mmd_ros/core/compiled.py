"""The compiled helpers of the 1 kHz path (``_fast.c``), when they were built.

``setup.py`` builds them as an optional extension: without a C compiler the package installs
and every caller does the same work in Python (slower: a transfer of 8 samples then spends most
of its time in interpreter and numpy call overhead). Which path runs is :data:`AVAILABLE`; the
tests check the two paths against each other.
"""

from __future__ import annotations

from types import ModuleType

__all__ = ['AVAILABLE', 'fast']

fast: ModuleType | None
try:
    from mmd_ros.core import _fast as fast
except ImportError:  # installed without a C compiler
    fast = None

#: The compiled helpers were built and are used.
AVAILABLE = fast is not None
