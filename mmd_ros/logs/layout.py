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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core import validate
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import DeviceDescription, parse_device
from mmd_ros.core.model import Model
from mmd_ros.core.yamlio import parse_yaml
from mmd_ros.logs.cdr import encode_joint_state
from mmd_ros.logs.chunked import ChunkedReader
from mmd_ros.logs.errors import LogFormatError, StampsNotIncreasing
from mmd_ros.logs.reader import JointStates, LogProblem, LogReader
from mmd_ros.logs.writer import LogWriter

__all__ = [
    'FK_STATUS_NAMES', 'FRAME_LOWER', 'FRAME_UPPER', 'REFERENCE_POSE_NAMES', 'RunBlock', 'RunLog',
    'TOPIC_BAR_LENGTHS',
    'TOPIC_CALIBRATION', 'TOPIC_DEVICE', 'TOPIC_DIAGNOSTICS', 'TOPIC_FK_STATUS', 'TOPIC_MODEL',
    'TOPIC_POSE', 'TOPIC_POSE_COV', 'TOPIC_RAW', 'TOPIC_REF_LENGTHS', 'TOPIC_REF_POSE',
    'TOPIC_MACHINE_JOINTS', 'TOPIC_THERMAL', 'MachineJoints', 'RunStream', 'flag_runs',
    'metadata_note', 'monotonic_runs', 'open_run', 'read_run', 'stated_absolute', 'write_run',
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
#: Names of /mmd/fk_status, live and in processed logs (msg_docs/topics.md).
FK_STATUS_NAMES = ['converged', 'valid', 'iterations', 'residual', 'condition', 'status']
TOPIC_DIAGNOSTICS = '/diagnostics'
#: The machine tool's axis values beside the MMD (sensor_msgs/JointState: names X Y Z A C...,
#: positions in m and rad), from its controller or the twin's machine session.
TOPIC_MACHINE_JOINTS = '/mmd/machine/joint_states'

FRAME_LOWER = 'mmd_lower'
FRAME_UPPER = 'mmd_upper'
#: Names of the reference pose components [m, m, m, rad, rad, rad]; unknown ones are NaN.
REFERENCE_POSE_NAMES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']
BAR_NAMES = [f'bar{i}' for i in range(1, 7)]
#: A reference whose stamps are its own (fewer than this share of them at raw samples' stamps)
#: is read at the raw samples by interpolation between its readings ...
OWN_STAMPS_SHARE = 0.5
#: ... at most this many of its median periods apart (a longer gap is a dropout: not bridged)
INTERPOLATION_GAP_PERIODS = 1.5
RUN_METADATA = 'mmd_run'


@dataclass(frozen=True)
class RunBlock:
    """Consecutive samples of a run: stamps_ns (N,) [ns], counts (N, 8), and the reference
    pose (N, 6) [m, rad] and bar lengths (N, 6) [m] at those stamps, or None when the log has
    none; status (N, 8) the terminal's channel status codes (:attr:`RunLog.status`) or None."""

    stamps_ns: NDArray[np.int64]
    counts: NDArray[np.float64]
    reference_pose: NDArray[np.float64] | None = None
    reference_lengths: NDArray[np.float64] | None = None
    status: NDArray[np.uint8] | None = None


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
    metadata_as_text : the keys of ``metadata`` whose values were not JSON, kept as their text
    problem : what was lost reading the log (damage, an unclean end), or None
    segment : (k, n) — the k-th of the log's n segments of increasing stamps
    machine_joints : the machine tool's axis values (``/mmd/machine/joint_states``), or None
    status : (N, 8) uint8 — the terminal's channel status codes of the samples it flagged (the
        ``effort`` of ``/mmd/raw_counts``: 1 encoder signal lost, 2 quadrature error, 3 both;
        0 good), or None when no sample was flagged. A flagged sample is not a measurement:
        the pipeline gives it no pose (``Pipeline.process(status=...)``), as live.
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
    metadata_as_text: tuple[str, ...] = ()
    problem: LogProblem | None = None
    segment: tuple[int, int] = (1, 1)
    machine_joints: MachineJoints | None = None
    status: NDArray[np.uint8] | None = None
    #: the hash of the run as recorded, when this holds only part of its samples
    recorded_hash: str | None = None
    #: what a command says when a device description given replaced the log's own, or ''
    device_note: str = ''
    #: what a command says when a reference on stamps of its own was interpolated, or ''
    reference_note: str = ''

    @property
    def no_signal(self) -> NDArray[np.bool_]:
        """(N,) — samples the terminal flagged on some channel (not measurements)."""
        if self.status is None:
            return np.zeros(self.n_samples, dtype=bool)
        return np.any(self.status != 0, axis=1)

    def content_hash(self) -> str:
        """Identity of the run: a hash of its raw counts and their stamps (16 hex digits).

        Two logs of the same run (a copy, a renamed file, the log re-written by ``mmd process``)
        have the same hash; a model file names the runs it was fitted on by it. A run
        without its flagged samples (:meth:`without_flagged`) keeps the recorded run's hash."""
        if self.recorded_hash is not None:
            return self.recorded_hash
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.stamps_ns, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(self.counts, dtype=np.float64).tobytes())
        return h.hexdigest()[:16]

    @property
    def unreadable(self) -> NDArray[np.bool_]:
        """(N,) — samples with a count that is not a finite number (a log written by other
        software that marks a missing reading so): not measurements either."""
        return ~np.all(np.isfinite(self.counts), axis=1)

    def every(self, k: int) -> RunLog:
        """Every k-th sample of the run, the first kept (a lower sample rate), as one log of
        it; the run itself when k is 1. It keeps the recorded run's hash (a model fitted on it
        names the run as recorded). The machine's axis values, stamped on their own, stay
        whole."""
        if k < 1:
            raise ValueError(f'k must be a positive integer, got {k!r}')
        if k == 1:
            return self
        rows = slice(None, None, int(k))
        return self._taking(rows, None if self.status is None else self.status[rows])

    def _taking(self, rows: Any, status: NDArray[np.uint8] | None) -> RunLog:
        """The samples ``rows`` of the run (a mask or a slice), with ``status``; the recorded
        run's hash kept."""
        return replace(
            self, stamps_ns=self.stamps_ns[rows], counts=self.counts[rows],
            reference_pose=None if self.reference_pose is None else self.reference_pose[rows],
            reference_lengths=(None if self.reference_lengths is None
                               else self.reference_lengths[rows]),
            status=status, recorded_hash=self.content_hash())

    def without_flagged(self) -> tuple[RunLog, int]:
        """The run without the samples the terminal flagged (:attr:`no_signal`) or with a
        count that is not a number (:attr:`unreadable`): not measurements, and how many were
        left out; the run itself when there are none. For the analyses that take whole arrays
        of counts (``mmd analyze``): such a sample is then a gap in the record, as a lost
        message would be."""
        drop = self.no_signal | self.unreadable
        n = int(drop.sum())
        if n == 0:
            return self, 0
        return self._taking(~drop, None), n

    @property
    def times_s(self) -> NDArray[np.float64]:
        """Seconds since the first sample."""
        if self.stamps_ns.size == 0:
            return np.zeros(0)
        return (self.stamps_ns - self.stamps_ns[0]).astype(np.float64) * 1e-9

    @property
    def epoch_s(self) -> float | None:
        """The Unix time of the first sample [s] (:attr:`times_s` = 0), None without one."""
        return float(self.stamps_ns[0]) * 1e-9 if self.stamps_ns.size else None

    @property
    def n_samples(self) -> int:
        return int(self.stamps_ns.size)

    @property
    def has_reference_pose(self) -> bool:
        return self.reference_pose is not None

    @property
    def has_reference_lengths(self) -> bool:
        return self.reference_lengths is not None

    def blocks(self, size: int) -> Iterator[RunBlock]:
        """The run in blocks of ``size`` samples, in time order."""
        for start in range(0, self.n_samples, size):
            part = slice(start, start + size)
            yield RunBlock(self.stamps_ns[part], self.counts[part],
                           None if self.reference_pose is None else self.reference_pose[part],
                           None if self.reference_lengths is None else self.reference_lengths[part],
                           None if self.status is None else self.status[part])


def write_run(path: str | os.PathLike[str], device: DeviceDescription,
              calibration: Calibration | None, stamps_ns: NDArray[np.int64],
              counts: NDArray[np.float64], *, reference_pose: NDArray[np.float64] | None = None,
              reference_lengths: NDArray[np.float64] | None = None,
              metadata: dict[str, Any] | None = None, model: Model | None = None,
              chunk_size: int = 1 << 20, status: NDArray[np.uint8] | None = None) -> Path:
    """Write a run log (device, calibration, raw counts, reference) in our layout.

    status : (N, 8) channel status codes; a sample with a code other than 0 is written with
        them in its ``effort``, as the live terminal stage publishes a flagged sample
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    t0 = int(stamps[0]) if stamps.size else 0
    flagged = (np.zeros(stamps.size, dtype=bool) if status is None
               else np.any(np.asarray(status) != 0, axis=1))
    with LogWriter(path, chunk_size=chunk_size) as log:
        log.write_string(TOPIC_DEVICE, t0, device.to_yaml())
        if calibration is not None:
            log.write_string(TOPIC_CALIBRATION, t0, calibration.to_yaml())
        if model is not None:
            log.write_string(TOPIC_MODEL, t0, model.to_yaml())
        if metadata:
            log.write_metadata(RUN_METADATA, {k: json.dumps(v) for k, v in metadata.items()})
        for a, b in flag_runs(flagged):
            part = slice(a, b)
            streams = []
            if flagged[a]:
                for i in range(a, b):
                    log.write_raw(TOPIC_RAW, 'sensor_msgs/msg/JointState', int(stamps[i]),
                                  encode_joint_state(device.channel_names, int(stamps[i]), counts[i],
                                                     effort=np.asarray(status[i], dtype=np.float64)))
            else:
                streams.append((TOPIC_RAW, 'sensor_msgs/msg/JointState',
                                log.joint_state_rows(device.channel_names, stamps[part], counts[part])))
            if reference_pose is not None:
                streams.append((TOPIC_REF_POSE, 'sensor_msgs/msg/JointState',
                                log.joint_state_rows(REFERENCE_POSE_NAMES, stamps[part],
                                                     reference_pose[part], FRAME_LOWER)))
            if reference_lengths is not None:
                streams.append((TOPIC_REF_LENGTHS, 'sensor_msgs/msg/JointState',
                                log.joint_state_rows(BAR_NAMES, stamps[part], reference_lengths[part])))
            if streams:
                log.write_rows(streams, stamps[part])
    return Path(path)


def flag_runs(flags: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """[a, b) ranges of equal values of ``flags``, in order (flagged and good samples)."""
    edges = np.flatnonzero(np.diff(np.asarray(flags).astype(np.int8))) + 1
    bounds = np.r_[0, edges, np.size(flags)]
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def monotonic_runs(stamps_ns: NDArray[np.int64]) -> list[tuple[int, int]]:
    """Index ranges [a, b) of the longest stretches of non-decreasing stamps, in order: one
    range for a well-formed log, more where a clock stepped back while recording."""
    back = np.flatnonzero(np.diff(stamps_ns) < 0) + 1
    edges = [0, *back.tolist(), int(stamps_ns.size)]
    return list(zip(edges[:-1], edges[1:]))


def repeated_stamps(stamps_ns: NDArray[np.int64]) -> NDArray[np.intp]:
    """Indices of the samples whose stamp is that of the sample before them."""
    return np.flatnonzero(np.diff(stamps_ns) == 0) + 1


def _refuse_repeated(stamps_ns: NDArray[np.int64], topic: str, source: str, first: int = 0) -> None:
    """Raise when samples of ``topic`` repeat the stamp of the one before them: samples are
    found by stamp downstream (the reference by the raw counts' stamps, dwells and speeds by
    time), so two at one time would be paired with the wrong samples or divide by a zero step.
    ``first`` is the index in the log of ``stamps_ns[0]``."""
    rep = repeated_stamps(stamps_ns)
    if rep.size == 0:
        return
    k = int(rep[0])
    raise LogFormatError(
        f'{source}: {rep.size} of the {stamps_ns.size} samples of {topic} repeat the stamp of '
        f'the sample before them, first sample {first + k} at {int(stamps_ns[k])} ns '
        f'({(stamps_ns[k] - stamps_ns[0]) * 1e-9:.6g} s into the run); samples at the same time '
        'cannot be told apart or matched by stamp (a clock too coarse for the sample rate, or a '
        'recorder that stamped on arrival?)')


def _runs_text(stamps_ns: NDArray[np.int64], runs: list[tuple[int, int]]) -> str:
    return ', '.join(f'{k}: samples {a}–{b - 1} ({(stamps_ns[b - 1] - stamps_ns[a]) * 1e-9:.1f} s)'
                     for k, (a, b) in enumerate(runs, 1))


def read_run(path: str | os.PathLike[str], *, segment: int | None = None,
             device: DeviceDescription | None = None) -> RunLog:
    """Read a run log: device description, calibration (the last one before the data ends),
    raw counts and the reference if there is one. A damaged or truncated log is read around the
    damage and :attr:`RunLog.problem` says what was lost (a
    :class:`~mmd_ros.logs.reader.LogProblem`).

    Stamps that go backwards (a clock stepped back while recording) are refused: the samples
    are searched by time everywhere downstream, so such a log would give errors of metres
    without a word. The message lists the stretches of increasing stamps ("segments");
    ``segment`` (1, 2, ...) reads one of them alone. Samples that repeat the stamp of the one
    before them (of the raw counts in the segment read, or of the reference) are refused too.

    ``device``: the device description to use instead of the log's own (a log recorded by a
    program that did not write one, or whose start was lost; :attr:`RunLog.device_note` says
    when it differs from the log's).
    """
    reader = LogReader(path)
    source = str(path)
    device, calibration, model, device_note = _run_header(reader, source, device)
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
    _refuse_repeated(raw.stamps_ns[a:b], TOPIC_RAW, source, a)
    values = raw.values if raw.values.size else np.zeros((0, 8))
    status = raw.status[a:b] if raw.status is not None and raw.status[a:b].any() else None
    sel = JointStates(raw.stamps_ns[a:b], raw.names, values[a:b], status)
    run = RunLog(Path(path), device, calibration, model, sel.stamps_ns, sel.values,
                 device.channel_names, problem=reader.problem, segment=(segment or 1, len(runs)),
                 status=status, device_note=device_note)
    notes = []
    for topic, names, attr in ((TOPIC_REF_POSE, REFERENCE_POSE_NAMES, 'reference_pose'),
                               (TOPIC_REF_LENGTHS, BAR_NAMES, 'reference_lengths')):
        if reader.has_topic(topic):
            ref = _segment_of(reader.joint_states(topic), len(runs), segment or 1, topic, source)
            values, read = _aligned(ref, sel, names, topic, source)
            setattr(run, attr, values)
            notes.append(read.note(source, topic))
    run.reference_note = '; '.join(n for n in notes if n)
    if reader.has_topic(TOPIC_MACHINE_JOINTS) and sel.stamps_ns.size:
        # all of them for a run of one segment (a recorder may hear the controller before the
        # terminal, seconds apart on a busy machine); of one segment, those within its span
        js = reader.joint_states(TOPIC_MACHINE_JOINTS)
        keep = np.ones(js.stamps_ns.size, dtype=bool) if len(runs) == 1 else \
            (js.stamps_ns >= sel.stamps_ns[0] - 10**9) & (js.stamps_ns <= sel.stamps_ns[-1] + 10**9)
        if keep.any():
            run.machine_joints = MachineJoints(js.stamps_ns[keep], list(js.names), js.values[keep])
    run.metadata, run.metadata_as_text = _run_metadata(reader)
    return run


def _run_metadata(reader: LogReader) -> tuple[dict[str, Any], tuple[str, ...]]:
    """The run description (MCAP metadata ``mmd_run``, JSON values), or {}; and the keys whose
    value is not JSON, kept as its text (another program may write plain strings: the samples
    do not depend on them, and a log whose description an MCAP map of strings holds otherwise
    is read whole, :func:`metadata_note` saying so)."""
    meta = reader.metadata.get(RUN_METADATA, {})
    out, text = {}, []
    for key, value in meta.items():
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
            text.append(key)
    return out, tuple(text)


def stated_absolute(metadata: dict[str, Any]) -> bool | None:
    """What a run description says of its reference pose's zero (``reference_absolute``):
    True absolute in {L}, False zeroed, None not said (also a value that is neither a boolean
    nor its text, true or false)."""
    value = metadata.get('reference_absolute')
    if isinstance(value, str):
        value = {'true': True, 'false': False}.get(value.strip().lower())
    return value if isinstance(value, bool) else None


def metadata_note(source: Any) -> str | None:
    """What a command says of a log whose run description holds values that are not JSON
    (``metadata_as_text``), or None."""
    keys = getattr(source, 'metadata_as_text', ())
    if not keys:
        return None
    return (f'{source.path}: the run description (MCAP metadata {RUN_METADATA}) holds values that '
            f'are not JSON, kept as their text: {", ".join(keys)} (a statement such as '
            'reference_absolute needs true or false, reference_sigma a list of six numbers; '
            'msg_docs/topics.md)')


class RunStream:
    """A run log read block by block in bounded memory (:func:`open_run`): what
    :class:`RunLog` has, except the samples, which come from :meth:`blocks`.

    n_samples : the raw samples the log's message indexes count (0 when they are missing)
    problem : what was wrong with the file (known once :meth:`blocks` has run), or None
    """

    #: Raw samples held back at most while the reference catches up: this many blocks, and at
    #: least HOLD_SAMPLES (a recorder writes each topic as it comes, some transfers apart).
    HOLD_BLOCKS = 4
    HOLD_SAMPLES = 1 << 16

    def __init__(self, path: str | os.PathLike[str],
                 device: DeviceDescription | None = None) -> None:
        self.path = Path(path)
        source = str(path)
        self._reader = ChunkedReader(path, {TOPIC_DEVICE, TOPIC_CALIBRATION, TOPIC_MODEL},
                                     {TOPIC_RAW, TOPIC_REF_POSE, TOPIC_REF_LENGTHS})
        try:
            self.device, self.calibration, self.model, self.device_note = _run_header(
                self._reader, source, device)
            self.metadata, self.metadata_as_text = _run_metadata(self._reader)
            self.n_samples = self._reader.message_count(TOPIC_RAW) or 0
            self.channel_names = self.device.channel_names
            # how each reference topic was read at the raw samples, block by block
            self._reads: dict[str, _Interpolated] = {}
        except BaseException:
            self._reader.close()
            raise

    @property
    def problem(self) -> LogProblem | None:
        return self._reader.problem

    @property
    def reference_note(self) -> str:
        """As :attr:`RunLog.reference_note`, over the blocks read so far."""
        source = str(self.path)
        return '; '.join(n for n in (self._reads[t].note(source, t) for t in sorted(self._reads))
                         if n)

    @property
    def has_reference_pose(self) -> bool:
        """The log has a reference pose (its blocks carry one)."""
        return self._reader.has_topic(TOPIC_REF_POSE)

    @property
    def has_reference_lengths(self) -> bool:
        """The log has reference bar lengths (its blocks carry them)."""
        return self._reader.has_topic(TOPIC_REF_LENGTHS)

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> RunStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def blocks(self, size: int) -> Iterator[RunBlock]:
        """The run in blocks of ``size`` samples (the last may be shorter), in time order, with
        the reference aligned by stamp as :func:`read_run` aligns it. A raw sample is handed on
        once the reference has reached its stamp (or is too far behind: ``HOLD_*``).
        Raises :class:`StampsNotIncreasing` when the stamps go back or repeat
        (:func:`read_run` says where)."""
        source = str(self.path)
        raw: list[JointStates] = []
        refs: dict[str, list[JointStates]] = {TOPIC_REF_POSE: [], TOPIC_REF_LENGTHS: []}
        has_ref = {t for t in refs if self._reader.has_topic(t)}
        self._reads = reads = {t: _Interpolated() for t in has_ref}
        last_ref: dict[str, int] = {}
        last_raw: int | None = None
        pending = 0

        def take(n: int) -> RunBlock:
            nonlocal raw, pending
            stamps = np.concatenate([r.stamps_ns for r in raw])
            values = np.concatenate([r.values for r in raw])
            status = (np.concatenate([np.zeros(r.values.shape, np.uint8) if r.status is None
                                      else r.status for r in raw])
                      if any(r.status is not None for r in raw) else None)
            out_s, out_v = stamps[:n], values[:n]
            out_status = status[:n] if status is not None and status[:n].any() else None
            raw = [JointStates(stamps[n:], raw[0].names, values[n:],
                               None if status is None else status[n:])] if n < stamps.size else []
            pending -= n
            aligned = {}
            for topic, names in ((TOPIC_REF_POSE, REFERENCE_POSE_NAMES), (TOPIC_REF_LENGTHS, BAR_NAMES)):
                if topic not in has_ref:
                    continue
                parts = refs[topic]
                ref = JointStates(np.concatenate([p.stamps_ns for p in parts]) if parts else np.zeros(0, np.int64),
                                  parts[0].names if parts else names,
                                  np.concatenate([p.values for p in parts]) if parts else np.zeros((0, len(names))))
                aligned[topic], read = _aligned(ref, JointStates(out_s, [], out_v), names, topic,
                                                source)
                reads[topic].add(read)
                # (the last reading at or before the block's end stays: it brackets the next)
                keep = max(int(np.searchsorted(ref.stamps_ns, out_s[-1], side='right')) - 1, 0)
                refs[topic] = [JointStates(ref.stamps_ns[keep:], ref.names, ref.values[keep:])]
            return RunBlock(out_s, out_v, aligned.get(TOPIC_REF_POSE), aligned.get(TOPIC_REF_LENGTHS),
                            out_status)

        for chunk in self._reader.chunks():
            for topic in has_ref & chunk.keys():
                refs[topic].append(chunk[topic])
                if chunk[topic].stamps_ns.size:
                    last_ref[topic] = int(chunk[topic].stamps_ns[-1])
            got = chunk.get(TOPIC_RAW)
            if got is None or got.stamps_ns.size == 0:
                continue
            if got.names != self.device.channel_names:
                raise LogFormatError(f'{source}: {TOPIC_RAW} names {got.names} do not match the '
                                     f'device channels {self.device.channel_names}')
            if not _increasing(got.stamps_ns, last_raw):
                raise StampsNotIncreasing(f'{source}: the {TOPIC_RAW} stamps go backwards or '
                                          'repeat')
            last_raw = int(got.stamps_ns[-1])
            raw.append(got)
            pending += got.stamps_ns.size
            while pending >= size:
                stamps = raw[0].stamps_ns if len(raw) == 1 else np.concatenate([r.stamps_ns for r in raw])
                reach = min((last_ref.get(t, -1) for t in has_ref), default=None)
                hold = max(self.HOLD_BLOCKS * size, self.HOLD_SAMPLES)
                if reach is not None and stamps[size - 1] > reach and pending < hold:
                    break   # the reference has not reached these stamps yet
                yield take(size)
        while pending > 0:
            yield take(min(size, pending))


def open_run(path: str | os.PathLike[str], device: DeviceDescription | None = None) -> RunStream:
    """A run log to read block by block (:class:`RunStream`); close it when done. ``device``
    as in :func:`read_run`."""
    return RunStream(path, device)


def _increasing(stamps: NDArray[np.int64], last: int | None) -> bool:
    """Whether ``stamps`` increase (never go back nor repeat), from ``last`` on."""
    if stamps.size == 0:
        return True
    if last is not None and stamps[0] <= last:
        return False
    return bool(np.all(np.diff(stamps) > 0))


def _run_header(reader: LogReader, source: str, given: DeviceDescription | None = None
                ) -> tuple[DeviceDescription, Calibration | None, Model | None, str]:
    """The device description (``given``, else the log's), the calibration (the last in the
    log) and the model of a run log, and what to say when ``given`` differs from the log's own
    description ('' otherwise); raises when it has neither description or no raw counts."""
    text = reader.latest_string(TOPIC_DEVICE)
    if text is None and given is None:
        raise LogFormatError(f'{source} has no {TOPIC_DEVICE}: it is not an MMD log, or the '
                             'recording lost its start'
                             + (f' ({reader.problem})' if reader.problem else '')
                             + '. Give the description of the device it was recorded with: '
                             '--device FILE (and its calibration: --calibration FILE)')
    own = None
    if text is not None:
        where = f'{source}:{TOPIC_DEVICE}'
        own = parse_device(validate.mapping(parse_yaml(text, where), where, '(message)'), where)
    device = given if given is not None else own
    note = ''
    if given is not None and own is not None:
        differ = [k for k in dict.fromkeys([*own.raw, *given.raw])
                  if own.raw.get(k) != given.raw.get(k)]
        if differ:
            note = (f'{source}: the device description given ({given.name}) replaces the '
                    f'log\'s own ({own.name}), which differs from it in {", ".join(differ)}')
    cal_text = reader.latest_string(TOPIC_CALIBRATION)
    calibration = (Calibration.from_yaml(cal_text, f'{source}:{TOPIC_CALIBRATION}')
                   if cal_text is not None else None)
    model_text = reader.latest_string(TOPIC_MODEL)
    model = Model.from_yaml(model_text, f'{source}:{TOPIC_MODEL}') if model_text else None
    if not reader.has_topic(TOPIC_RAW):
        raise LogFormatError(f'{source} has no {TOPIC_RAW}: nothing to process')
    return device, calibration, model, note


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


@dataclass
class _Interpolated:
    """How a reference was read at the raw samples: samples read by interpolation (its stamps
    its own), its median period over the blocks that had one [ns], the samples given a value,
    and the first and last stamps of the reference and of the raw samples seen [ns]."""

    samples: int = 0
    periods: list[float] = field(default_factory=list)
    given: int = 0
    spans: dict[str, tuple[int, int]] = field(default_factory=dict)

    def add(self, other: _Interpolated) -> None:
        self.samples += other.samples
        self.periods += other.periods
        self.given += other.given
        for key, (lo, hi) in other.spans.items():
            a, b = self.spans.get(key, (lo, hi))
            self.spans[key] = (min(a, lo), max(b, hi))

    def note(self, source: str, topic: str) -> str:
        ref, raw = self.spans.get('reference'), self.spans.get('raw')
        where = ''
        if not self.given and ref is not None and raw is not None:
            if ref[1] < raw[0]:
                where = f'its stamps end {(raw[0] - ref[1]) * 1e-9:.6g} s before theirs begin'
            elif ref[0] > raw[1]:
                where = f'its stamps begin {(ref[0] - raw[1]) * 1e-9:.6g} s after theirs end'
        if where:
            return (f'{source}: {topic} never meets the raw samples: {where} (stamped on '
                    'another clock or from another epoch? Stamp it on the MMD\'s clock, '
                    'topics.md)')
        if not self.samples:
            return ''
        period_s = float(np.median(self.periods)) * 1e-9
        return (f'{source}: {topic} is stamped on instants of its own, not at the raw samples\' '
                f'({1.0 / period_s:.4g} Hz): read at {self.samples} raw samples by linear '
                'interpolation between its readings (not across a gap of more than '
                f'{INTERPOLATION_GAP_PERIODS:g} of its periods); between readings T apart, a '
                'motion accelerating at a is read up to a T^2/8 off, which the pose '
                'uncertainty does not claim')


def _aligned(ref: JointStates, raw: JointStates, names: list[str], topic: str,
             source: str) -> tuple[NDArray[np.float64], _Interpolated]:
    """Reference values at the raw samples' stamps (NaN where the reference has none), and how
    many were interpolated; raises when reference samples repeat a stamp (which of them goes
    with that sample?). A reference stamped at the raw samples' instants (a reading of the
    MMD's sample tick) is taken where its stamps are; one whose stamps are its own (fewer than
    :data:`OWN_STAMPS_SHARE` of those within the raw samples' span fall on one: an instrument
    logged on its own clock by another program) is interpolated linearly between its
    readings, angles unwrapped, not across a dropout (:data:`INTERPOLATION_GAP_PERIODS`)."""
    _refuse_repeated(ref.stamps_ns, topic, source)
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
    read = _Interpolated()
    if raw.stamps_ns.size and ref.stamps_ns.size:
        read.spans = {'reference': (int(ref.stamps_ns[0]), int(ref.stamps_ns[-1])),
                      'raw': (int(raw.stamps_ns[0]), int(raw.stamps_ns[-1]))}
    read.given = int(np.sum(np.any(np.isfinite(out), axis=1)))
    if ref.stamps_ns.size < 2 or raw.stamps_ns.size == 0:
        return out, read
    span = (ref.stamps_ns >= raw.stamps_ns[0]) & (ref.stamps_ns <= raw.stamps_ns[-1])
    if not span.any() or np.mean(np.isin(ref.stamps_ns[span], raw.stamps_ns)) >= OWN_STAMPS_SHARE:
        return out, read
    period = float(np.median(np.diff(ref.stamps_ns)))
    left = np.searchsorted(ref.stamps_ns, raw.stamps_ns, side='right') - 1
    between = ~match & (left >= 0) & (left + 1 < ref.stamps_ns.size)
    a = np.clip(left, 0, ref.stamps_ns.size - 2)
    gap = (ref.stamps_ns[a + 1] - ref.stamps_ns[a]).astype(np.float64)
    between &= gap <= INTERPOLATION_GAP_PERIODS * period
    w = (raw.stamps_ns - ref.stamps_ns[a]).astype(np.float64) / gap
    angles = set(REFERENCE_POSE_NAMES[3:]) if names == REFERENCE_POSE_NAMES else set()
    for j, c in enumerate(cols):
        if c < 0:
            continue
        v = ref.values[:, c].copy()
        if names[j] in angles:          # (a turn past +-pi is not a jump of 2 pi)
            fin = np.isfinite(v)
            v[fin] = np.unwrap(v[fin])
        got = v[a] * (1.0 - w) + v[a + 1] * w       # (NaN where either reading is)
        if names[j] in angles:
            got = np.angle(np.exp(1j * got))          # back into (-pi, pi]
        out[between, j] = got[between]
    read.samples = int(between.sum())
    read.given = int(np.sum(np.any(np.isfinite(out), axis=1)))
    read.periods.append(period)
    return out, read
