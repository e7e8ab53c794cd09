"""Message definitions of the standard interfaces our logs use, as rosbag2 writes them in MCAP.

The schema of a channel (encoding ``ros2msg``) is the type's ``.msg`` text followed by each
dependency, depth first, after a line of 80 ``=`` and ``MSG: package/Type`` (no ``/msg/``).
The definitions are the field lines of the ROS 2 Jazzy interfaces (comments left out).
"""

from __future__ import annotations

__all__ = ['DEFINITIONS', 'schema_text']

#: Field lines of each type, by ``package/msg/Type``.
DEFINITIONS: dict[str, str] = {
    'builtin_interfaces/msg/Time': 'int32 sec\nuint32 nanosec\n',
    'std_msgs/msg/Header': 'builtin_interfaces/Time stamp\nstring frame_id\n',
    'std_msgs/msg/String': 'string data\n',
    'sensor_msgs/msg/JointState': ('std_msgs/Header header\nstring[] name\nfloat64[] position\n'
                                   'float64[] velocity\nfloat64[] effort\n'),
    'geometry_msgs/msg/Point': 'float64 x\nfloat64 y\nfloat64 z\n',
    'geometry_msgs/msg/Quaternion': 'float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n',
    'geometry_msgs/msg/Pose': 'Point position\nQuaternion orientation\n',
    'geometry_msgs/msg/PoseStamped': 'std_msgs/Header header\nPose pose\n',
    'geometry_msgs/msg/PoseWithCovariance': 'Pose pose\nfloat64[36] covariance\n',
    'geometry_msgs/msg/PoseWithCovarianceStamped': 'std_msgs/Header header\nPoseWithCovariance pose\n',
    'diagnostic_msgs/msg/KeyValue': 'string key\nstring value\n',
    'diagnostic_msgs/msg/DiagnosticStatus': (
        'byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\n'
        'string message\nstring hardware_id\nKeyValue[] values\n'),
    'diagnostic_msgs/msg/DiagnosticArray': 'std_msgs/Header header\nDiagnosticStatus[] status\n',
}

_PRIMITIVES = {'bool', 'byte', 'char', 'int8', 'uint8', 'int16', 'uint16', 'int32', 'uint32',
               'int64', 'uint64', 'float32', 'float64', 'string', 'wstring'}


def _dependencies(msg_type: str) -> list[str]:
    package = msg_type.split('/')[0]
    deps = []
    for line in DEFINITIONS[msg_type].splitlines():
        field_type = line.split()[0].split('[')[0]
        if field_type in _PRIMITIVES or '=' in line.split()[1]:
            continue
        if '/' in field_type:
            pkg, name = field_type.split('/')
        else:
            pkg, name = package, field_type
        deps.append(f'{pkg}/msg/{name}')
    return deps


def schema_text(msg_type: str) -> str:
    """The ``ros2msg`` schema of ``msg_type`` (``package/msg/Type``) with its dependencies."""
    if msg_type not in DEFINITIONS:
        raise KeyError(f'no definition of {msg_type!r}; known: {sorted(DEFINITIONS)}')
    seen: list[str] = []

    def visit(t: str) -> None:
        for dep in _dependencies(t):
            if dep not in seen:
                seen.append(dep)
                visit(dep)

    visit(msg_type)
    parts = [DEFINITIONS[msg_type]]
    for dep in seen:
        pkg, _, name = dep.split('/')
        parts.append('=' * 80 + f'\nMSG: {pkg}/{name}\n' + DEFINITIONS[dep])
    return ''.join(parts)
