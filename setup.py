"""ament_python build of mmd_ros: ``colcon build`` installs executables into lib/mmd_ros."""
from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = 'mmd_ros'

# Console scripts: the ``mmd`` offline tool and one executable per ROS node.
CONSOLE_SCRIPTS = [
    'mmd = mmd_ros.cli.main:main',
    'encoder_node = mmd_ros.nodes.encoder_node:main',
    'compensation_node = mmd_ros.nodes.compensation_node:main',
    'fk_node = mmd_ros.nodes.fk_node:main',
    'calibration_node = mmd_ros.nodes.calibration_node:main',
    'recorder_node = mmd_ros.nodes.recorder_node:main',
    'replay_node = mmd_ros.nodes.replay_node:main',
    'pose_node = mmd_ros.nodes.pose_node:main',
]

# The compiled helpers of the 1 kHz path (mmd_ros.core.compiled: streaming FK, CDFs, frame
# decoding; plain C, no numpy headers). Optional: without a C compiler the package installs and
# runs the same algorithms in Python.
EXTENSIONS = [
    Extension('mmd_ros.core._fast', ['mmd_ros/core/_fast.c'],
              extra_compile_args=['-O2'], optional=True),
]

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', sorted(glob('config/*'))),
        ('share/' + PACKAGE + '/launch', sorted(glob('launch/*.launch.py'))),
        ('share/' + PACKAGE + '/msg_docs', sorted(glob('msg_docs/*'))),
    ],
    install_requires=['setuptools'],
    zip_safe=False,  # a compiled extension
    maintainer='mmd_ros developers',
    maintainer_email='dev@mmd.example',
    description='Six-dimensional Motion Measuring Device: driver, compensation, kinematics, tools.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={'console_scripts': CONSOLE_SCRIPTS},
    ext_modules=EXTENSIONS,
)
