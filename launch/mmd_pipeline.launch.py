"""Launch the separate-process pipeline of mmd_ros.

encoder_node (the terminal: simulated by default, ``device:=usb`` for hardware),
calibration_node, compensation_node, fk_node and recorder_node, each in its own process, all
with the parameters file ``config/mmd_nodes.yaml`` of the installed package (or
``params_file:=...``) and in the namespace ``namespace`` (default ``mmd``)::

    ros2 launch mmd_ros mmd_pipeline.launch.py
    ros2 launch mmd_ros mmd_pipeline.launch.py device:=usb namespace:=/cell3/mmd

Topics, parameters and what each node does: ``msg_docs/nodes.md``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

#: The executables of the pipeline, upstream first.
EXECUTABLES = ['encoder_node', 'calibration_node', 'compensation_node', 'fk_node', 'recorder_node']


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('mmd_ros'), 'config', 'mmd_nodes.yaml')
    params_file = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    nodes = []
    for executable in EXECUTABLES:
        parameters = [params_file]
        if executable == 'encoder_node':
            parameters.append({'device': LaunchConfiguration('device')})
        nodes.append(Node(package='mmd_ros', executable=executable, name=executable,
                          namespace=namespace, parameters=parameters, output='screen'))
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='parameters file of the nodes'),
        DeclareLaunchArgument('namespace', default_value='mmd',
                              description='namespace of the device (topics, services, nodes)'),
        DeclareLaunchArgument('device', default_value='sim',
                              description='encoder terminal: sim (the digital twin) or usb'),
        *nodes,
    ])
