"""mmd_ros: software of a six-dimensional Motion Measuring Device (Lei & Chen, MMT 191, 2024).

Sub-packages:
- ``mmd_ros.core``: ROS-free metrology (kinematics, calibration, thermal, model, pipeline).
- ``mmd_ros.twin``: the digital twin of the physical device (ROS-free).
- ``mmd_ros.logs``: MCAP logs in rosbag2's layout (ROS-free).
- ``mmd_ros.cli``: the ``mmd`` command-line tool.
"""

__version__ = '0.1.0'
