"""Test-session settings shared by every test module.

``make test`` runs the suite on two pytest-xdist workers (``--dist loadgroup``). The tests
marked ``needs_ros`` start real executables or rclpy clients that talk over DDS in real time;
they go to one worker, in one group, so that at most one set of nodes runs at a time (each test
in its own ``ROS_DOMAIN_ID``, test_nodes_support.py) while the other worker's analyses share the
machine with it, as a machine controller's would.
"""

from __future__ import annotations

import pytest

from test_nodes_support import NO_ROS


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if any(mark.kwargs.get('reason') == NO_ROS for mark in item.iter_markers('skipif')):
            item.add_marker(pytest.mark.xdist_group('dds'))
