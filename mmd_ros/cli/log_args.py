"""Options the commands that read a log share."""

from __future__ import annotations

import argparse

from mmd_ros.core import validate

__all__ = ['add_segment_argument']


def add_segment_argument(p: argparse.ArgumentParser) -> None:
    """``--segment N``: read one stretch of increasing stamps of a log whose clock stepped back
    (:func:`mmd_ros.logs.layout.read_run`)."""
    p.add_argument('--segment', type=validate.arg_number(low=1, integer=True), default=None,
                   help='for a log whose stamps go backwards somewhere: use only its N-th '
                   'stretch of increasing stamps (the error message lists them)')
