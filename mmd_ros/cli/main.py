"""The ``mmd`` command-line tool for offline work.

Each subcommand lives in its own module under :mod:`mmd_ros.cli` with
``register(subparsers)``, which adds an argparse parser whose ``func(args)`` returns the exit
status. Errors of the metrology core (:class:`~mmd_ros.core.errors.MmdError`) and of the file
system (``OSError``: a missing file, a full disk) are printed as one line, without a traceback,
and exit with status 2, as argparse does for a bad option; an interrupt exits with 130.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from mmd_ros.core.errors import MmdError

__all__ = ['build_parser', 'main']

#: Subcommand modules, in the order ``mmd --help`` lists them.
COMMAND_MODULES = [
    'mmd_ros.cli.cmd_simulate',
    'mmd_ros.cli.cmd_process',
    'mmd_ros.cli.cmd_replay',
    'mmd_ros.cli.cmd_error_budget',
    'mmd_ros.cli.cmd_workspace',
    'mmd_ros.cli.cmd_analyze',
    'mmd_ros.cli.cmd_iso230',
    'mmd_ros.cli.cmd_machine',
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='mmd',
        description='Offline tools of the six-dimensional Motion Measuring Device (MMD).')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except MmdError as exc:
        print(f'mmd {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:  # a file that cannot be read or written (missing, full disk...)
        print(f'mmd {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'mmd {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
