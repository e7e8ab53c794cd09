"""The layout of an MMD log: topic names, types, frames, and reading/writing a whole run.

Documented for users in ``msg_docs/topics.md``. A log is self-contained: it carries the device
description and the calibration (latched ``std_msgs/String`` topics holding YAML, as
``/robot_description`` does), the raw counts of every channel at every sample and, when there is
one, the reference instrument's reading.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import DeviceDescription, parse_device
from mmd_ros.core.model import Model
from mmd_ros.core.yamlio import parse_yaml
from mmd_ros.logs.errors import LogFormatError
from mmd_ros.logs.reader import JointStates, LogReader
from mmd_ros.logs.writer import LogWriter

__all__ = [
    'FRAME_LOWER', 'FRAME_UPPER', 'REFERENCE_POSE_NAMES', 'RunLog', 'TOPIC_BAR_LENGTHS',
    'TOPIC_CALIBRATION', 'TOPIC_DEVICE', 'TOPIC_DIAGNOSTICS', 'TOPIC_FK_STATUS', 'TOPIC_MODEL',
    'TOPIC_POSE', 'TOPIC_POSE_COV', 'TOPIC_RAW', 'TOPIC_REF_LENGTHS', 'TOPIC_REF_POSE',
    'TOPIC_MACHINE_JOINTS', 'TOPIC_THERMAL', 'MachineJoints', 'read_run', 'write_run',
]

TOPIC_DEVICE = '/mmd/device_description'
TOPIC_CALIBRATION = '/mmd/calibration'
TOPIC_MODEL = '/mmd/model'
TOPIC_RAW = '/mmd/raw_counts'
TOPIC_REF_POSE = '/mmd/reference/pose'
TOPIC_REF_LENGTHS = '/mmd/reference/bar_lengths'
TOPIC_BAR_LENGTHS = '/mmd/bar_lengths'
TOPIC_THERMAL = '/mmd/thermal'
TOPIC_POSE = '/mmd/pose'
TOPIC_POSE_COV = '/mmd/pose_with_covariance'
TOPIC_FK_STATUS = '/mmd/fk_status'
TOPIC_DIAGNOSTICS = '/diagnostics'
#: The machine tool's axis values beside the MMD (sensor_msgs/JointState: names X Y Z A C...,
#: positions in m and rad), from its controller or the twin's machine session.
TOPIC_MACHINE_JOINTS = '/mmd/machine/joint_states'

FRAME_LOWER = 'mmd_lower'
FRAME_UPPER = 'mmd_upper'
#: Names of the reference pose components [m, m, m, rad, rad, rad]; unknown ones are NaN.
REFERENCE_POSE_NAMES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
BAR_NAMES = [f'bar{i}' for i in range(1, 7)]
RUN_METADATA = 'mmd_run'


@dataclass
class MachineJoints:
    """Axis values of the machine tool carrying the MMD, on their own time stamps.

    stamps_ns : ndarray, shape (M,) [ns since the epoch]; names : axis names
    positions : ndarray, shape (M, n_axes) [m, rad]
    """

    stamps_ns: NDArray[np.int64]
    names: list[str]
    positions: NDArray[np.float64]


@dataclass
class RunLog:
    """A recorded run, as read from a log.

    stamps_ns : ndarray, shape (N,) — sample times [ns since the epoch]
    counts : ndarray, shape (N, 8) — raw counts of the terminal's channels
    reference_pose : (N, 6) [m, rad] with NaN for components the reference does not give, or None
    reference_lengths : (N, 6) [m] bar lengths known from the set-up, or None
    metadata : the run's description (scenario, effects, seed...) if the log has one
    machine_joints : the machine tool's axis values (``/mmd/machine/joint_states``), or None
    """

    path: Path
    device: DeviceDescription
    calibration: Calibration | None
    model: Model | None
    stamps_ns: NDArray[np.int64]
    counts: NDArray[np.float64]
    channel_names: list[str]
    reference_pose: NDArray[np.float64] | None = None
    reference_lengths: NDArray[np.float64] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    problem: str | None = None
    machine_joints: MachineJoints | None = None

    @property
    def times_s(self) -> NDArray[np.float64]:
        """Seconds since the first sample."""
        if self.stamps_ns.size == 0:
            return np.zeros(0)
        return (self.stamps_ns - self.stamps_ns[0]).astype(np.float64) * 1e-9


def write_run(path: str | os.PathLike[str], device: DeviceDescription,
              calibration: Calibration | None, stamps_ns: NDArray[np.int64],
              counts: NDArray[np.float64], *, reference_pose: NDArray[np.float64] | None = None,
              reference_lengths: NDArray[np.float64] | None = None,
              metadata: dict[str, Any] | None = None, model: Model | None = None,
              chunk_size: int = 1 << 20) -> Path:
    """Write a run log (device, calibration, raw counts, reference) in our layout."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    t0 = int(stamps[0]) if stamps.size else 0
    with LogWriter(path, chunk_size=chunk_size) as log:
        log.write_string(TOPIC_DEVICE, t0, device.to_yaml())
        if calibration is not None:
            log.write_string(TOPIC_CALIBRATION, t0, calibration.to_yaml())
        if model is not None:
            log.write_string(TOPIC_MODEL, t0, model.to_yaml())
        if metadata:
            log.write_metadata(RUN_METADATA, {k: json.dumps(v) for k, v in metadata.items()})
        streams = [(TOPIC_RAW, 'sensor_msgs/msg/JointState',
                    log.joint_state_rows(device.channel_names, stamps, counts))]
        if reference_pose is not None:
            streams.append((TOPIC_REF_POSE, 'sensor_msgs/msg/JointState',
                            log.joint_state_rows(REFERENCE_POSE_NAMES, stamps, reference_pose, FRAME_LOWER)))
        if reference_lengths is not None:
            streams.append((TOPIC_REF_LENGTHS, 'sensor_msgs/msg/JointState',
                            log.joint_state_rows(BAR_NAMES, stamps, reference_lengths)))
        log.write_rows(streams, stamps)
    return Path(path)


def read_run(path: str | os.PathLike[str]) -> RunLog:
    """Read a run log: device description, calibration (the last one before the data ends),
    raw counts and the reference if there is one. A truncated log is read up to the damage and
    :attr:`RunLog.problem` says so."""
    reader = LogReader(path)
    source = str(path)
    text = reader.latest_string(TOPIC_DEVICE)
    if text is None:
        raise LogFormatError(f'{source} has no {TOPIC_DEVICE}: it is not an MMD log, or the '
                             'recording lost its start')
    where = f'{source}:{TOPIC_DEVICE}'
    device = parse_device(parse_yaml(text, where), where)
    cal_text = reader.latest_string(TOPIC_CALIBRATION)
    calibration = (Calibration.from_yaml(cal_text, f'{source}:{TOPIC_CALIBRATION}')
                   if cal_text is not None else None)
    model_text = reader.latest_string(TOPIC_MODEL)
    model = Model.from_yaml(model_text, f'{source}:{TOPIC_MODEL}') if model_text else None
    if not reader.has_topic(TOPIC_RAW):
        raise LogFormatError(f'{source} has no {TOPIC_RAW}: nothing to process')
    raw = reader.joint_states(TOPIC_RAW)
    if raw.names and raw.names != device.channel_names:
        raise LogFormatError(f'{source}: {TOPIC_RAW} names {raw.names} do not match the device '
                             f'channels {device.channel_names}')
    run = RunLog(Path(path), device, calibration, model, raw.stamps_ns,
                 raw.values if raw.values.size else np.zeros((0, 8)), device.channel_names,
                 problem=reader.problem)
    if reader.has_topic(TOPIC_REF_POSE):
        run.reference_pose = _aligned(reader.joint_states(TOPIC_REF_POSE), raw, REFERENCE_POSE_NAMES, source)
    if reader.has_topic(TOPIC_REF_LENGTHS):
        run.reference_lengths = _aligned(reader.joint_states(TOPIC_REF_LENGTHS), raw, BAR_NAMES, source)
    if reader.has_topic(TOPIC_MACHINE_JOINTS):
        js = reader.joint_states(TOPIC_MACHINE_JOINTS)
        if js.stamps_ns.size:
            run.machine_joints = MachineJoints(js.stamps_ns, list(js.names), js.values)
    meta = reader.metadata.get(RUN_METADATA, {})
    run.metadata = {k: json.loads(v) for k, v in meta.items()}
    return run


def _aligned(ref: JointStates, raw: JointStates, names: list[str], source: str) -> NDArray[np.float64]:
    """Reference values at the raw samples' stamps (NaN where the reference has none)."""
    out = np.full((raw.stamps_ns.size, len(names)), np.nan)
    cols = [ref.names.index(n) if n in ref.names else -1 for n in names]
    if not any(c >= 0 for c in cols):
        raise LogFormatError(f'{source}: reference names {ref.names} include none of {names}')
    idx = np.searchsorted(ref.stamps_ns, raw.stamps_ns)
    idx = np.clip(idx, 0, max(ref.stamps_ns.size - 1, 0))
    hit = ref.stamps_ns.size > 0
    match = (ref.stamps_ns[idx] == raw.stamps_ns) if hit else np.zeros(raw.stamps_ns.size, bool)
    for j, c in enumerate(cols):
        if c >= 0:
            out[match, j] = ref.values[idx[match], c]
    return out
