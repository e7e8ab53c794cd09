"""Options the commands that read a log share."""

from __future__ import annotations

import argparse
import sys

from mmd_ros.core import validate
from mmd_ros.core.device import DeviceDescription, find_config, load_device

__all__ = ['add_device_argument', 'add_segment_argument', 'log_device', 'print_read_notes']


def add_segment_argument(p: argparse.ArgumentParser) -> None:
    """``--segment N``: read one stretch of increasing stamps of a log whose clock stepped back
    (:func:`mmd_ros.logs.layout.read_run`)."""
    p.add_argument('--segment', type=validate.arg_number(low=1, integer=True), default=None,
                   help='for a log whose stamps go backwards somewhere: use only its N-th '
                   'stretch of increasing stamps (the error message lists them)')


def add_device_argument(p: argparse.ArgumentParser) -> None:
    """``--device FILE``: the device description to read the logs with instead of their own
    (:func:`mmd_ros.logs.layout.read_run`)."""
    p.add_argument('--device', default=None,
                   help='device description (a path, or a file name in config/) to use instead '
                   'of the one in the log: for a log written without one, or whose start was '
                   'lost (default: the log\'s own)')


def log_device(args: argparse.Namespace) -> DeviceDescription | None:
    """The device description ``--device`` names, or None (each log's own)."""
    return load_device(find_config(args.device)) if args.device else None


def print_read_notes(run: object) -> None:
    """Warn on stderr when a device description given replaced a log's own, which differs, and
    when a reference on stamps of its own was interpolated to the raw samples."""
    for note in (getattr(run, 'device_note', ''), getattr(run, 'reference_note', '')):
        if note:
            print(f'warning: {note}', file=sys.stderr)
