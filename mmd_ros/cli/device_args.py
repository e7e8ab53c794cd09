"""The device options the design tools share (``--device``, ``--joints``)."""

from __future__ import annotations

import argparse

from mmd_ros.core.device import DeviceDescription, find_config, load_device
from mmd_ros.core.kinematics import Geometry

__all__ = ['add_device_arguments', 'device_geometry']


def add_device_arguments(p: argparse.ArgumentParser, joints_help: str) -> None:
    """Add ``--device`` (a path or a file name in config/) and ``--joints`` (design/measured)."""
    p.add_argument('--device', default='mmd_prototype.yaml',
                   help='device description (a path, or a file name in config/)')
    p.add_argument('--joints', choices=('design', 'measured'), default='design', help=joints_help)


def device_geometry(args: argparse.Namespace) -> tuple[DeviceDescription, Geometry]:
    """The device description the options name and its design or measured joint geometry."""
    device = load_device(find_config(args.device))
    return device, device.design_geometry if args.joints == 'design' else device.measured_geometry
