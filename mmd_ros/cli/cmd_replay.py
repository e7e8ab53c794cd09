"""``mmd replay LOG``: republish a recorded log's raw counts (and calibration) on ROS topics.

The same code as the ``replay_node`` executable, run in this process: the compensation and
kinematics nodes (or a ``pose_node``-free pipeline) recompute the poses from the log. rclpy is
imported only when the command runs, so the rest of ``mmd`` works without ROS.
"""

from __future__ import annotations

import argparse

from mmd_ros.core import validate

__all__ = ['register']


def ros_arguments(args: argparse.Namespace) -> list[str]:
    """The node's ``--ros-args`` for the command-line options."""
    rate = 0.0 if args.fast else args.rate
    out = ['mmd_replay', '--ros-args', '-p', f'log:={args.log}', '-p', f'rate:={rate!r}',
           '-p', f'wait_for_subscribers:={args.wait_for_subscribers}',
           '-p', f'publish_reference:={"false" if args.no_reference else "true"}']
    if args.ns:
        out += ['-r', f'__ns:={args.ns}']
    return out


def run_command(args: argparse.Namespace) -> int:
    from mmd_ros.nodes.replay_node import main as replay_main  # needs rclpy
    return replay_main(ros_arguments(args))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser('replay', help='republish a log\'s raw counts and calibration on ROS topics',
                       description='Publish the device description, the calibration (the last one '
                       'in the log) and the model on the latched topics, then every raw_counts '
                       'sample (and reference/pose) with its recorded stamp, at the original timing '
                       'times --rate or as fast as possible. Needs ROS 2 (rclpy).')
    p.add_argument('log', help='MCAP log (from the recorder, mmd simulate or mmd process input)')
    p.add_argument('--rate', type=validate.arg_number(low=0.001, high=1000.0), default=1.0,
                   help='speed factor, in [0.001, 1000] (default 1: original timing)')
    p.add_argument('--fast', action='store_true', help='as fast as possible')
    p.add_argument('--ns', default='', help='namespace of the device (default /mmd)')
    p.add_argument('--wait-for-subscribers', type=validate.arg_number(low=0, high=100, integer=True),
                   default=1, dest='wait_for_subscribers',
                   help='wait for this many raw_counts subscribers first (default 1, up to 30 s)')
    p.add_argument('--no-reference', action='store_true', dest='no_reference',
                   help='do not publish reference/pose')
    p.set_defaults(func=run_command)
