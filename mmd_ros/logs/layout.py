"""The layout of an MMD log: topic names, types, frames, and reading/writing a whole run.

Documented for users in ``msg_docs/topics.md``. A log is self-contained: it carries the device
description and the calibration (latched ``std_msgs/String`` topics holding YAML, as
``/robot_description`` does), the raw counts of every channel at every sample and, when there is
one, the reference instrument's reading.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core import validate
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import DeviceDescription, parse_device
from mmd_ros.core.model import Model
from mmd_ros.core.yamlio import parse_yaml
from mmd_ros.logs.errors import LogFormatError
from mmd_ros.logs.reader import JointStates, LogProblem, LogReader
from mmd_ros.logs.writer import LogWriter

__all__ = [
    'FRAME_LOWER', 'FRAME_UPPER', 'REFERENCE_POSE_NAMES', 'RunLog', 'TOPIC_BAR_LENGTHS',
    'TOPIC_CALIBRATION', 'TOPIC_DEVICE', 'TOPIC_DIAGNOSTICS', 'TOPIC_FK_STATUS', 'TOPIC_MODEL',
    'TOPIC_POSE', 'TOPIC_POSE_COV', 'TOPIC_RAW', 'TOPIC_REF_LENGTHS', 'TOPIC_REF_POSE',
    'TOPIC_THERMAL', 'monotonic_runs', 'read_run', 'write_run',
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

FRAME_LOWER = 'mmd_lower'
FRAME_UPPER = 'mmd_upper'
#: Names of the reference pose components [m, m, m, rad, rad, rad]; unknown ones are NaN.
REFERENCE_POSE_NAMES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
BAR_NAMES = [f'bar{i}' for i in range(1, 7)]
RUN_METADATA = 'mmd_run'


@dataclass
class RunLog:
    """A recorded run, as read from a log.

    stamps_ns : ndarray, shape (N,) — sample times [ns since the epoch]
    counts : ndarray, shape (N, 8) — raw counts of the terminal's channels
    reference_pose : (N, 6) [m, rad] with NaN for components the reference does not give, or None
    reference_lengths : (N, 6) [m] bar lengths known from the set-up, or None
    metadata : the run's description (scenario, effects, seed...) if the log has one
    problem : what was lost reading the log (damage, an unclean end), or None
    segment : (k, n) — the k-th of the log's n segments of increasing stamps
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
    problem: LogProblem | None = None
    segment: tuple[int, int] = (1, 1)

    def content_hash(self) -> str:
        """Identity of the run: a hash of its raw counts and their stamps (16 hex digits).

        Two logs of the same run (a copy, a renamed file, the log re-written by ``mmd process``)
        have the same hash; a model file names the runs it was fitted on by it."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.stamps_ns, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(self.counts, dtype=np.float64).tobytes())
        return h.hexdigest()[:16]

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


def monotonic_runs(stamps_ns: NDArray[np.int64]) -> list[tuple[int, int]]:
    """Index ranges [a, b) of the longest stretches of non-decreasing stamps, in order: one
    range for a well-formed log, more where a clock stepped back while recording."""
    back = np.flatnonzero(np.diff(stamps_ns) < 0) + 1
    edges = [0, *back.tolist(), int(stamps_ns.size)]
    return list(zip(edges[:-1], edges[1:]))


def _runs_text(stamps_ns: NDArray[np.int64], runs: list[tuple[int, int]]) -> str:
    return ', '.join(f'{k}: samples {a}–{b - 1} ({(stamps_ns[b - 1] - stamps_ns[a]) * 1e-9:.1f} s)'
                     for k, (a, b) in enumerate(runs, 1))


def read_run(path: str | os.PathLike[str], *, segment: int | None = None) -> RunLog:
    """Read a run log: device description, calibration (the last one before the data ends),
    raw counts and the reference if there is one. A damaged or truncated log is read around the
    damage and :attr:`RunLog.problem` says what was lost (a
    :class:`~mmd_ros.logs.reader.LogProblem`).

    Stamps that go backwards (a clock stepped back while recording) are refused: the samples
    are searched by time everywhere downstream, so such a log would give errors of metres
    without a word. The message lists the stretches of increasing stamps ("segments");
    ``segment`` (1, 2, ...) reads one of them alone.
    """
    reader = LogReader(path)
    source = str(path)
    text = reader.latest_string(TOPIC_DEVICE)
    if text is None:
        raise LogFormatError(f'{source} has no {TOPIC_DEVICE}: it is not an MMD log, or the '
                             'recording lost its start' + (f' ({reader.problem})' if reader.problem else ''))
    where = f'{source}:{TOPIC_DEVICE}'
    device = parse_device(validate.mapping(parse_yaml(text, where), where, '(message)'), where)
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
    runs = monotonic_runs(raw.stamps_ns)
    if segment is None and len(runs) > 1:
        k = runs[1][0]
        step = (raw.stamps_ns[k - 1] - raw.stamps_ns[k]) * 1e-9
        raise LogFormatError(
            f'{source}: the stamps of {TOPIC_RAW} go backwards {len(runs) - 1} time(s), first by '
            f'{step:.6g} s after sample {k - 1} (a clock stepped back while recording?); samples '
            f'out of time order cannot be processed as one run. The log holds {len(runs)} segments '
            f'of increasing stamps: {_runs_text(raw.stamps_ns, runs)}. Read one with --segment N')
    if segment is not None and not 1 <= segment <= len(runs):
        raise LogFormatError(f'{source}: --segment must be in [1, {len(runs)}] (the log has '
                             f'{len(runs)} segment(s) of increasing stamps), got {segment}')
    a, b = runs[segment - 1] if segment is not None else (0, raw.stamps_ns.size)
    values = raw.values if raw.values.size else np.zeros((0, 8))
    sel = JointStates(raw.stamps_ns[a:b], raw.names, values[a:b])
    run = RunLog(Path(path), device, calibration, model, sel.stamps_ns, sel.values,
                 device.channel_names, problem=reader.problem, segment=(segment or 1, len(runs)))
    for topic, names, attr in ((TOPIC_REF_POSE, REFERENCE_POSE_NAMES, 'reference_pose'),
                               (TOPIC_REF_LENGTHS, BAR_NAMES, 'reference_lengths')):
        if reader.has_topic(topic):
            ref = _segment_of(reader.joint_states(topic), len(runs), segment or 1, topic, source)
            setattr(run, attr, _aligned(ref, sel, names, source))
    meta = reader.metadata.get(RUN_METADATA, {})
    try:
        run.metadata = {k: json.loads(v) for k, v in meta.items()}
    except ValueError as exc:
        raise LogFormatError(f'{source}: the run description (MCAP metadata {RUN_METADATA}) is not '
                             f'valid JSON ({exc})') from None
    return run


def _segment_of(ref: JointStates, n_runs: int, segment: int, topic: str, source: str) -> JointStates:
    """The reference samples of the raw counts' segment: its own segment of the same number
    (its clock stepped back with the terminal's), or all of it when its stamps only increase."""
    runs = monotonic_runs(ref.stamps_ns)
    if len(runs) == 1:
        return ref
    if len(runs) != n_runs:
        raise LogFormatError(f'{source}: the stamps of {topic} go backwards {len(runs) - 1} '
                             f'time(s), those of {TOPIC_RAW} {n_runs - 1} time(s): the reference '
                             'cannot be matched to the samples')
    a, b = runs[segment - 1]
    return JointStates(ref.stamps_ns[a:b], ref.names, ref.values[a:b])


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
