"""The compiled helpers of the 1 kHz path (``_fast.c``), when they were built.

``setup.py`` builds them as an optional extension: without a C compiler the package installs
and every caller does the same work in Python (slower: a transfer of 8 samples then spends most
of its time in interpreter and numpy call overhead). Which path runs is :data:`AVAILABLE`; the
tests check the two paths against each other. Setting the environment variable
``MMD_PURE_PYTHON=1`` makes a process use the Python paths even when the helpers were built
(to compare the two, or to rule them out when chasing a problem).
"""

from __future__ import annotations

import os
from types import ModuleType

from mmd_ros.core.errors import MmdError

__all__ = ['AVAILABLE', 'NOT_IN_USE', 'CompiledUnavailable', 'fast', 'use_compiled']

fast: ModuleType | None
if os.environ.get('MMD_PURE_PYTHON', '') not in ('', '0'):
    fast = None
else:
    try:
        from mmd_ros.core import _fast as fast
    except ImportError:  # installed without a C compiler
        fast = None

#: The compiled helpers are used by this process.
AVAILABLE = fast is not None

#: What to tell someone who asked for the compiled path when it is not there.
NOT_IN_USE = ('the compiled helpers are not in use: MMD_PURE_PYTHON is set, or '
              'mmd_ros/core/_fast.c was not built (no C compiler or Python headers when mmd_ros '
              'was installed)')


class CompiledUnavailable(MmdError):
    """The compiled path was asked for and is not in use."""


def use_compiled(compiled: bool | None) -> bool:
    """Whether a caller takes the compiled path: ``compiled`` as asked, or (None) whenever it is
    in use. Raises :class:`CompiledUnavailable` when it is asked for and not there."""
    if compiled is None:
        return AVAILABLE
    if compiled and not AVAILABLE:
        raise CompiledUnavailable(NOT_IN_USE)
    return bool(compiled)
