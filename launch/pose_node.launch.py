"""Launch ``pose_node``: the whole mmd_ros pipeline in one process.

Terminal (simulated by default, ``device:=usb`` for hardware), compensation, kinematics, the
calibration service and the recorder, with the parameters file ``config/mmd_nodes.yaml`` of the
installed package (or ``params_file:=...``) in the namespace ``namespace`` (default ``mmd``)::

    ros2 launch mmd_ros pose_node.launch.py
    ros2 launch mmd_ros pose_node.launch.py device:=usb

Topics, parameters and services: ``msg_docs/nodes.md``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('mmd_ros'), 'config', 'mmd_nodes.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='parameters file of the node'),
        DeclareLaunchArgument('namespace', default_value='mmd',
                              description='namespace of the device (topics, services, node)'),
        DeclareLaunchArgument('device', default_value='sim',
                              description='encoder terminal: sim (the digital twin) or usb'),
        Node(package='mmd_ros', executable='pose_node', name='pose_node',
             namespace=LaunchConfiguration('namespace'),
             parameters=[LaunchConfiguration('params_file'), {'device': LaunchConfiguration('device')}],
             output='screen'),
    ])
