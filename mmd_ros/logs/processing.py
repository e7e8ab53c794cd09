"""Every sample of a log through the pipeline (counts → CDF → thermal → model terms → FK), and
the processed log written back in the live pipeline's topics. Used by ``mmd process``, the demo
and the live demo.

A run is processed in blocks of :data:`BLOCK` samples, in time order, with one
:class:`Pipeline` (terms that carry state see every sample once, as live). :func:`process_log`
never holds more than a few blocks: it reads the next block, computes one and writes the one
before at the same time (three threads; the compiled helpers, zstd and numpy's copies release
the GIL), so a log of any length is processed in bounded memory. :func:`process_run` gives the
whole run's arrays, for callers that want them in memory.
"""

from __future__ import annotations

import contextlib
import itertools
import queue
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import IO, Any, Iterable, Iterator, Protocol

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.accuracy import (
    POSE_NAMES, CoverageAccumulator, ErrorAccumulator, ReferenceNoise, ReferenceScale,
    length_error, pose_error, read_datum,
)
from mmd_ros.core.calibration import Calibration, calibration_for, load_calibration
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.kinematics import FkStatus
from mmd_ros.core.lag import (
    LAG_WINDOW, LagAccumulator, ReferenceLag, aligned_reference, is_reference_lag,
)
from mmd_ros.core.model import Model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.progress import Progress
from mmd_ros.core.validity import other_calibration
from mmd_ros.logs.layout import (
    BAR_NAMES, FK_STATUS_NAMES, FRAME_LOWER, TOPIC_BAR_LENGTHS, TOPIC_CALIBRATION, TOPIC_DEVICE,
    TOPIC_FK_STATUS, TOPIC_MODEL, TOPIC_POSE, TOPIC_POSE_COV, TOPIC_THERMAL, RunBlock, RunLog,
    stated_absolute,
)
from mmd_ros.logs.outputs import check_outputs, replacing
from mmd_ros.logs.writer import FAST_ZSTD_LEVEL, LogWriter

__all__ = [
    'BLOCK', 'LagAligner', 'ProcessedLogWriter', 'ProcessedRun', 'RunSummary', 'process_blocks',
    'process_log', 'process_run', 'summarize', 'write_csv', 'write_processed',
]

#: Samples per block: bounds memory, keeps the working arrays small, paces the progress.
BLOCK = 65536
#: Chunk size of processed logs [bytes]: fewer per-chunk costs than the 1 MiB of a live
#: recording, which keeps chunks small so that a crash loses little.
PROCESSED_CHUNK_BYTES = 4 << 20
CSV_HEADER = ('stamp_ns,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad,valid,converged,iterations,'
              'residual_m,' + ','.join(f'bar{i}_m' for i in range(1, 7)) + ',temp_change_c')


class RunSource(Protocol):
    """What :func:`process_log` reads: a :class:`RunLog`, or a log read block by block."""

    path: Path
    device: DeviceDescription
    calibration: Calibration | None
    problem: str | None

    metadata: dict[str, Any]

    @property
    def n_samples(self) -> int: ...

    @property
    def has_reference_pose(self) -> bool: ...

    @property
    def has_reference_lengths(self) -> bool: ...

    def blocks(self, size: int) -> Iterator[RunBlock]: ...


@dataclass
class ProcessedRun:
    """Samples of a run (or of a block of it) through the pipeline, arrays of N samples."""

    stamps_ns: NDArray[np.int64]
    lengths_m: NDArray[np.float64]
    poses: NDArray[np.float64]
    converged: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    status: NDArray[np.int8]
    out_of_range: NDArray[np.bool_]
    iterations: NDArray[np.int64]
    residual_m: NDArray[np.float64]
    condition: NDArray[np.float64]
    reference_error_m: NDArray[np.float64]
    temp_change_c: NDArray[np.float64]
    covariance: NDArray[np.float64] | None
    #: the uncertainty budget's numbers and notes after these samples (with the covariance)
    budget: dict[str, Any] | None = None
    #: (N,) samples the terminal flagged (encoder signal lost on a channel they need): no pose
    no_signal: NDArray[np.bool_] | None = None
    #: (N, 6, 7) where the covariance's error is lighter-tailed than a Gaussian (``tails_every``)
    tails: NDArray[np.float64] | None = None
    #: (N, 6, 6) the bars' length covariance [m^2] (with the covariance, a block with reference
    #: bar lengths: what they judge)
    length_covariance: NDArray[np.float64] | None = None

    @classmethod
    def concatenate(cls, parts: list[ProcessedRun]) -> ProcessedRun:
        values: dict[str, Any] = {}
        for f in fields(cls):
            items = [getattr(p, f.name) for p in parts]
            if f.name == 'budget':
                values[f.name] = items[-1]      # the budget as it stood after the last sample
            else:
                values[f.name] = None if items[0] is None else np.concatenate(items)
        return cls(**values)

    def __getitem__(self, part: slice) -> ProcessedRun:
        """The samples ``part`` (the budget as it is)."""
        return ProcessedRun(**{f.name: getattr(self, f.name) if f.name == 'budget'
                               or getattr(self, f.name) is None else getattr(self, f.name)[part]
                               for f in fields(self)})


def _resolve_calibration(source: RunSource, calibration: Calibration | str | None) -> Calibration:
    if isinstance(calibration, str):
        calibration = load_calibration(calibration)
    return calibration_for(source.calibration, calibration, str(source.path))


def process_blocks(source: RunSource, model: Model, *, calibration: Calibration | str | None = None,
                   with_covariance: bool = False, covariance_every: int = 1, block: int = BLOCK,
                   compiled: bool | None = None, tails_every: int = 0
                   ) -> Iterator[tuple[RunBlock, ProcessedRun]]:
    """The run block by block through one pipeline: (samples, their results), in time order.
    The next block is read in a background thread while one is computed.

    calibration : a calibration or a calibration file to use instead of the log's
    compiled : the compiled helpers (default: when they are in use); False: the numpy path
    tails_every : with the covariance, its light-tailed directions at every k-th sample
        (:meth:`Pipeline.process`), for the size of its coverage region; 0: none
    """
    parts = _prefetched(source.blocks(block))
    first = next(parts, None)   # what is wrong with the samples is said before the calibration
    if first is None:
        return
    pipeline = Pipeline(source.device, _resolve_calibration(source, calibration), model)
    t0 = int(first.stamps_ns[0])
    for part in itertools.chain([first], parts):
        times = (part.stamps_ns - t0).astype(np.float64) * 1e-9
        res = pipeline.process(times, part.counts, with_covariance=with_covariance,
                               covariance_every=covariance_every, compiled=compiled,
                               status=part.status, tails_every=tails_every,
                               with_length_covariance=part.reference_lengths is not None,
                               epoch_s=t0 * 1e-9)
        comp = res.compensated
        yield part, ProcessedRun(
            part.stamps_ns, comp.lengths_m, res.poses, res.converged, res.valid, res.status,
            comp.out_of_range, res.iterations, res.residual_m, res.condition,
            comp.thermal.reference_error_m, comp.thermal.temp_change_c, res.covariance,
            pipeline.budget.summary() if with_covariance else None,
            res.no_signal if res.no_signal is not None else np.zeros(part.stamps_ns.size, bool),
            res.tails, res.length_covariance)


def process_run(run: RunLog, model: Model, *, calibration_path: str | None = None,
                with_covariance: bool = False, progress: Progress | None = None,
                compiled: bool | None = None, block: int = BLOCK) -> ProcessedRun:
    """Run the pipeline over a whole log held in memory; the whole run's arrays."""
    parts = []
    for part, result in process_blocks(run, model, calibration=calibration_path,
                                       with_covariance=with_covariance, compiled=compiled,
                                       block=block):
        parts.append(result)
        if progress:
            progress.update(sum(p.stamps_ns.size for p in parts))
    if not parts:
        raise CalibrationError(f'{run.path} has no samples')
    return ProcessedRun.concatenate(parts)


class RunSummary:
    """Counts of samples, FK outcomes and, with a reference, the error statistics, gathered
    block by block (:meth:`add`) and given as ``mmd process --json`` prints them.

    covariance_every : the blocks carry the covariance of every k-th sample only
    """

    def __init__(self, covariance_every: int = 1) -> None:
        self.samples = 0
        self.valid = 0
        self.not_converged = 0
        self.out_of_range = 0
        self.no_signal = 0
        self.max_iterations = 0
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.status = np.zeros(len(FkStatus), dtype=np.int64)
        self.pose_error: ErrorAccumulator | None = None
        #: how the reference pose scales against the MMD's (units, sign: :class:`ReferenceScale`)
        self.reference_scale: ReferenceScale | None = None
        self.length_error: ErrorAccumulator | None = None
        self.coverage: CoverageAccumulator | None = None
        self.reference_noise: ReferenceNoise | None = None
        self.length_coverage: CoverageAccumulator | None = None
        self.length_noise: ReferenceNoise | None = None
        self.covariance_every = covariance_every
        self.budget: dict[str, Any] | None = None
        #: the reference pose where the log's first measurement has one (6,) [m, rad]
        self.reference_start: NDArray[np.float64] | None = None
        #: what reads the delay between a reference pose and the MMD (:meth:`reference_lag`),
        #: when the log does not say that its reference was sampled at the MMD's instants
        self.lag: LagAccumulator | None = None
        #: the reference's lag as read, and whether the comparison has it taken out
        self.lag_read: tuple[ReferenceLag, bool] | None = None

    def add(self, part: RunBlock, result: ProcessedRun) -> None:
        n = int(result.stamps_ns.size)
        if n == 0:
            return
        self.samples += n
        self.valid += int(result.valid.sum())
        self.not_converged += int((~result.converged).sum())
        self.out_of_range += int(result.out_of_range.any(axis=1).sum())
        if result.no_signal is not None:
            self.no_signal += int(result.no_signal.sum())
        self.max_iterations = max(self.max_iterations, int(result.iterations.max()))
        self.status += np.bincount(result.status, minlength=len(FkStatus))
        if self.first_ns is None:
            self.first_ns = int(result.stamps_ns[0])
        self.last_ns = int(result.stamps_ns[-1])
        if part.reference_pose is not None:
            self.pose_error = self.pose_error or ErrorAccumulator('pose')
            errors = pose_error(result.poses, part.reference_pose)
            self.pose_error.add(errors, result.valid)
            self.reference_scale = self.reference_scale or ReferenceScale()
            self.reference_scale.add(result.poses, part.reference_pose, result.valid)
            if self.lag is not None:
                times = (result.stamps_ns - self.first_ns).astype(np.float64) * 1e-9
                self.lag.add(times, result.poses, errors, result.valid)
            if self.reference_start is None:
                has = result.valid & np.any(np.isfinite(part.reference_pose), axis=1)
                if has.any():
                    self.reference_start = part.reference_pose[np.argmax(has)].copy()
            if result.covariance is not None:
                self.coverage = self.coverage or CoverageAccumulator()
                self.coverage.add(errors, result.covariance, result.valid, result.tails)
                self.reference_noise = self.reference_noise or ReferenceNoise()
                self.reference_noise.add(errors, result.poses, result.valid)
        if result.budget is not None:
            self.budget = result.budget
        if part.reference_lengths is not None:
            self.length_error = self.length_error or ErrorAccumulator('lengths')
            errors = length_error(result.lengths_m, part.reference_lengths)
            self.length_error.add(errors, result.valid)
            if result.length_covariance is not None:
                # a bar's length is a measurement wherever the sample has one (FK need not agree)
                measured = np.all(np.isfinite(result.lengths_m), axis=1)
                self.length_coverage = self.length_coverage or CoverageAccumulator()
                self.length_coverage.add(errors, result.length_covariance, measured)
                self.length_noise = self.length_noise or ReferenceNoise()
                self.length_noise.add(errors, result.lengths_m, measured)

    def as_dict(self, source: RunSource, *, absolute_reference: bool | None = None
                ) -> dict[str, Any]:
        """The summary; with a reference pose and the covariance, how well the covariance
        covers the error (:func:`~mmd_ros.core.accuracy.coverage`).

        absolute_reference : the reference pose is absolute in {L} (no offset removed); None
            takes what the log's metadata says (``reference_absolute``), else what the
            reference's offsets from the MMD say (:func:`~mmd_ros.core.accuracy.read_datum`,
            as ``mmd analyze`` reads them), else False (zeroed: its offset is removed)
        """
        summary: dict[str, Any] = {
            'log': str(source.path),
            'samples': self.samples,
            'duration_s': (self.last_ns - self.first_ns) * 1e-9 if self.samples else 0.0,
            'valid': self.valid,
            'not_converged': self.not_converged,
            'fk_status': {s.name.lower(): int(c) for s, c in zip(FkStatus, self.status) if c},
            'out_of_range': self.out_of_range,
            'no_signal': self.no_signal,
            'max_fk_iterations': self.max_iterations,
        }
        if source.problem:
            summary['log_problem'] = source.problem.as_dict()
        if self.lag_read is not None:
            summary['reference_lag'] = {**self.lag_read[0].as_dict(),
                                        'taken_out': self.lag_read[1]}
        if getattr(source, 'metadata_as_text', ()):
            summary['metadata_as_text'] = list(source.metadata_as_text)
        segment = getattr(source, 'segment', (1, 1))
        if segment[1] > 1:
            summary['segment'] = {'index': segment[0], 'of': segment[1]}
        if self.pose_error is not None:
            summary['pose_error'] = [s.as_dict() for s in self.pose_error.stats()]
            blunder = self.reference_scale.text() if self.reference_scale else ''
            if blunder:
                summary['reference_scale_note'] = blunder
            if not summary['pose_error']:
                summary['pose_error_note'] = (
                    'the log has a reference pose, but no sample with a valid pose has a value '
                    'of it: its stamps match none of the raw counts\' and no raw sample lies '
                    'between two of its readings near enough to interpolate (the reader pairs '
                    'them by stamp, msg_docs/topics.md), or all its values are NaN')
        if self.coverage is not None:
            metadata = getattr(source, 'metadata', {}) or {}
            sigma = metadata.get('reference_sigma')
            ref_sigma = (np.array([np.nan if v is None else float(v) for v in sigma])
                         if isinstance(sigma, list) and len(sigma) == 6 else np.full(6, np.nan))
            # what the log does not state of its reference's noise, read from the data
            estimated = ~np.isfinite(ref_sigma)
            if self.reference_noise is not None:
                ref_sigma = np.where(estimated, self.reference_noise.sigma(), ref_sigma)
            absolute, datum = absolute_reference, 'option'
            if absolute is None and stated_absolute(metadata) is not None:
                absolute, datum = stated_absolute(metadata), 'stated'
            if absolute is None:
                absolute, datum = self._read_datum(ref_sigma), 'found'
            summary['reference_datum'] = {'zeroed': not absolute, 'source': datum}
            report = self.coverage.report(absolute=absolute, reference_sigma=ref_sigma)
            if report is not None:
                report['reference_sigma_estimated'] = [
                    r['name'] for r in report['per_component']
                    if estimated[POSE_NAMES.index(r['name'])]]
                report['every'] *= self.covariance_every
                summary['uncertainty_coverage'] = report
        if self.budget is not None:
            summary['uncertainty_budget'] = self.budget
        if self.length_error is not None:
            summary['length_error'] = [s.as_dict() for s in self.length_error.stats()]
        if self.length_coverage is not None:
            # reference bar lengths are absolute (a bar resting on a known pair); their own
            # noise is not stated in a log: read from the data as for a pose
            sigma = (self.length_noise.sigma() if self.length_noise is not None
                     else np.full(6, np.nan))
            report = self.length_coverage.report(absolute=True, reference_sigma=sigma,
                                                 kind='lengths')
            if report is not None:
                report['reference_sigma_estimated'] = [r['name'] for r in report['per_component']]
                report['every'] *= self.covariance_every
                summary['length_uncertainty_coverage'] = report
        return summary

    def reference_lag(self, clock: str | None) -> ReferenceLag | None:
        """The delay between the reference pose and the MMD as the samples added show it
        (:class:`~mmd_ros.core.lag.LagAccumulator`), kept in :attr:`lag_read`, and returned
        when it is the reference's (:func:`~mmd_ros.core.lag.is_reference_lag`; ``clock`` as
        the log's ``reference_clock`` says): None when it is not, or not read."""
        found = self.lag.estimate() if self.lag is not None else None
        if found is None or not np.isfinite(found[1]):
            return None
        lag = ReferenceLag(found[0], found[1], clock == 'own')
        taken = is_reference_lag(found[0], found[1], clock)
        self.lag_read = (lag, taken)
        return lag if taken else None

    def _read_datum(self, reference_sigma: NDArray[np.float64]) -> bool:
        """Whether the reference pose, its log not saying, reads as absolute."""
        found = self.coverage.offsets() if self.coverage is not None else None
        if found is None or self.reference_start is None:
            return False
        known, median, predicted = found
        own = np.nan_to_num(reference_sigma[known])
        return read_datum(-median, np.hypot(predicted, own), self.reference_start[known],
                          known).absolute


def summarize(run: RunLog, result: ProcessedRun, *, absolute_reference: bool | None = None,
              reference_clock: str | None = None) -> dict[str, Any]:
    """Counts of samples and, with a reference in the log, the error statistics and, with the
    covariance computed, its coverage (:meth:`RunSummary.as_dict`); a reference pose that lags
    the MMD compared at the MMD's instants (``reference_clock`` as for :func:`process_log`)."""
    block = RunBlock(run.stamps_ns, run.counts, run.reference_pose, run.reference_lengths)
    summary = _summary(run, 1, reference_clock)
    summary.add(block, result)
    lag = summary.reference_lag(_clock(run, reference_clock))
    if lag is not None:
        summary = _compared_again(summary, lag, [(block, result)], 1)
    return summary.as_dict(run, absolute_reference=absolute_reference)


def _clock(source: RunSource, reference_clock: str | None) -> str | None:
    """Whose clock a log's reference pose runs on: ``reference_clock`` if given, else what
    the log says (metadata ``reference_clock``: 'own' or 'shared'), else None."""
    said = reference_clock or (getattr(source, 'metadata', None) or {}).get('reference_clock')
    return said if said in ('own', 'shared') else None


def _summary(source: RunSource, covariance_every: int, reference_clock: str | None
             ) -> RunSummary:
    """A summary that reads the reference's lag unless the log's reference has none."""
    summary = RunSummary(covariance_every=covariance_every)
    if source.has_reference_pose and _clock(source, reference_clock) != 'shared':
        summary.lag = LagAccumulator(source.n_samples)
    return summary


def _compared_again(first: RunSummary, lag: ReferenceLag,
                    blocks: Iterable[tuple[RunBlock, ProcessedRun]], covariance_every: int
                    ) -> RunSummary:
    """A summary of ``blocks`` (the run once more) with the reference's ``lag`` taken out
    (:class:`LagAligner`), saying what ``first`` read of it."""
    summary = RunSummary(covariance_every=covariance_every)
    summary.lag_read = first.lag_read
    aligner = LagAligner(lag, first.lag.period or 1.0)     # (read: ``first`` has a lag)
    for part, result in blocks:
        for given in aligner.push(part, result):
            summary.add(*given)
    for given in aligner.finish():
        summary.add(*given)
    return summary


class LagAligner:
    """Blocks of a run whose reference pose reads ``lag`` late, given out with the reference
    as it read at each MMD sample's instant (:func:`~mmd_ros.core.lag.aligned_reference`):
    the reading a whole number of periods later, moved on by the rest of the delay along the
    MMD's smoothed motion. A block is given out once the samples after it that this needs
    have come (the last ones at :meth:`finish`), in bounded memory.

    period : the run's sample period [s]
    """

    def __init__(self, lag: ReferenceLag, period: float) -> None:
        self.period = period
        self.shift = int(round(lag.delay_s / period))
        self.remainder_s = lag.delay_s - self.shift * period
        #: samples either side a block's alignment reads
        self.margin = LAG_WINDOW + abs(self.shift)
        self._held: list[tuple[RunBlock, ProcessedRun]] = []
        #: the last samples given out, (stamps, reference, poses)
        self._before: tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]] | None
        self._before = None

    def push(self, part: RunBlock, result: ProcessedRun) -> list[tuple[RunBlock, ProcessedRun]]:
        """The blocks that can be given out now that ``part`` has come."""
        self._held.append((part, result))
        out = []
        while len(self._held) > 1 and sum(
                p.stamps_ns.size for p, _ in self._held[1:]) >= self.margin:
            out.append(self._give())
        return out

    def finish(self) -> list[tuple[RunBlock, ProcessedRun]]:
        """The blocks still held."""
        return [self._give() for _ in range(len(self._held))]

    def _give(self) -> tuple[RunBlock, ProcessedRun]:
        part, result = self._held.pop(0)
        own = [] if self._before is None else [self._before]
        own.append(_samples(part, result))
        after, left = [], self.margin
        for p, r in self._held:
            if left <= 0:
                break
            after.append(tuple(a[:left] for a in _samples(p, r)))
            left -= p.stamps_ns.size
        stamps, reference, poses = (np.concatenate(a) for a in zip(*own, *after))
        times = (stamps - stamps[0]).astype(np.float64) * 1e-9
        aligned = aligned_reference(times, reference, poses, self.shift, self.remainder_s,
                                    self.period)
        start = 0 if self._before is None else self._before[0].shape[0]
        self._before = tuple(np.concatenate(a)[-self.margin:] for a in zip(*own))
        n = part.stamps_ns.size
        return replace(part, reference_pose=aligned[start:start + n]), result


def _samples(part: RunBlock, result: ProcessedRun
             ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """A block's stamps, reference pose (NaN where it has none) and the MMD's poses (NaN
    where a sample is not a measurement)."""
    reference = (part.reference_pose if part.reference_pose is not None
                 else np.full((part.stamps_ns.size, 6), np.nan))
    return part.stamps_ns, reference, _masked(result.poses, result.valid)


class ProcessedLogWriter:
    """A processed log being written block by block: bar lengths, poses (NaN where not a
    measurement), thermal state, FK status and, with covariance, poses with covariance, in the
    live pipeline's topics; the device, calibration and model first, as latched strings.

    with_covariance : write the poses with their covariance when a block has them (a
        covariance computed only to report its coverage is not written)
    """

    def __init__(self, path: Path, device: DeviceDescription, model: Model,
                 calibration_text: str, stamp_ns: int, *, with_covariance: bool = True) -> None:
        self.device = device
        self.with_covariance = with_covariance
        self._log = LogWriter(path, level=FAST_ZSTD_LEVEL, chunk_size=PROCESSED_CHUNK_BYTES)
        try:
            self._log.write_string(TOPIC_DEVICE, stamp_ns, device.to_yaml())
            self._log.write_string(TOPIC_CALIBRATION, stamp_ns, calibration_text)
            self._log.write_string(TOPIC_MODEL, stamp_ns, model.to_yaml())
        except BaseException:
            self._log.close()
            raise

    def write(self, result: ProcessedRun) -> None:
        log = self._log
        stamps = result.stamps_ns
        k = result.reference_error_m.shape[1]
        ref_names = [c.name + '_error' for c in self.device.reference_channels][:k]
        status = np.column_stack([result.converged, result.valid, result.iterations,
                                  result.residual_m, result.condition,
                                  result.status]).astype(np.float64)
        poses = _masked(result.poses, result.valid)
        streams = [
            (TOPIC_BAR_LENGTHS, 'sensor_msgs/msg/JointState',
             log.joint_state_rows(BAR_NAMES, stamps, result.lengths_m)),
            (TOPIC_POSE, 'geometry_msgs/msg/PoseStamped', log.pose_rows(FRAME_LOWER, stamps, poses)),
            (TOPIC_THERMAL, 'sensor_msgs/msg/JointState',
             log.joint_state_rows(ref_names + ['temp_change'], stamps,
                                  np.column_stack([result.reference_error_m, result.temp_change_c]))),
            (TOPIC_FK_STATUS, 'sensor_msgs/msg/JointState',
             log.joint_state_rows(FK_STATUS_NAMES, stamps, status)),
        ]
        if result.covariance is not None and self.with_covariance:
            streams.append((TOPIC_POSE_COV, 'geometry_msgs/msg/PoseWithCovarianceStamped',
                            log.pose_rows(FRAME_LOWER, stamps, poses, result.covariance)))
        log.write_rows(streams, stamps)
        # the disk writes of this block overlap the next one's compute (else the final fsync
        # waits for them all: 0.05 s of a 10-minute log's ~1.2 s)
        log.sync_written()

    def close(self) -> None:
        self._log.close()

    def __enter__(self) -> ProcessedLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_processed(path: Path, run: RunLog, model: Model, result: ProcessedRun,
                    calibration_text: str, *, with_covariance: bool = True) -> None:
    """Write a processed run held in memory (:class:`ProcessedLogWriter`), under a temporary
    name renamed to ``path`` once complete."""
    with replacing(path) as tmp, ProcessedLogWriter(tmp, run.device, model, calibration_text,
                                                    int(result.stamps_ns[0]),
                                                    with_covariance=with_covariance) as out:
        for start in range(0, result.stamps_ns.size, BLOCK):
            out.write(result[start:start + BLOCK])


def process_log(source: RunSource, out: Path, model: Model, *,
                calibration: Calibration | str | None = None, with_covariance: bool = False,
                csv: Path | None = None, progress: Progress | None = None,
                compiled: bool | None = None, block: int = BLOCK,
                absolute_reference: bool | None = None, coverage: bool = True,
                reference_clock: str | None = None) -> dict[str, Any]:
    """``mmd process``: every sample of ``source`` through the pipeline into the processed log
    ``out`` (and ``csv``), block by block in bounded memory; returns the summary
    (:class:`RunSummary`). Reading, computing and writing overlap (module docstring). The
    outputs are written under temporary names and renamed when complete
    (:func:`~mmd_ros.logs.outputs.replacing`): a failure leaves none. An output that is the
    log being read is refused.

    with_covariance : write the poses with their covariance. With a reference pose or
        reference bar lengths in the log the covariance is computed anyway, to report how well
        it covers the error (of about :attr:`CoverageAccumulator.MAX_SAMPLES` samples spread
        over the run).
    absolute_reference : see :meth:`RunSummary.as_dict`
    coverage : False: no covariance for the coverage report (with a reference and without
        ``with_covariance``, the budget's covariance costs a few µs per sample)
    reference_clock : whose clock the reference pose runs on, 'own' or 'shared' (the MMD's
        instants); None: what the log says (metadata ``reference_clock``), else not known.
        Unless shared, the delay between the two is read (:meth:`RunSummary.reference_lag`);
        when it is the reference's the run is computed once more, the poses compared with the
        reference's readings of their instants (:class:`LagAligner`; the processed log is
        written by the first pass only)
    """
    check_outputs([('out', out), ('csv', csv)], [source.path], force=True)
    if isinstance(calibration, str):
        calibration = load_calibration(calibration)
    # a covariance wanted only for its coverage is computed for the samples the summary keeps
    referenced = source.has_reference_pose or source.has_reference_lengths
    coverage_only = coverage and referenced and not with_covariance
    every = max(1, source.n_samples // CoverageAccumulator.MAX_SAMPLES) if coverage_only else 1
    # and the size of its coverage region, from where the budget's error is light-tailed
    tails_every = (max(1, source.n_samples // CoverageAccumulator.MAX_SAMPLES)
                   if coverage and source.has_reference_pose else 0)
    summary = _summary(source, every, reference_clock)
    writer: ProcessedLogWriter | None = None
    handle: IO[str] | None = None
    pending: Future[None] | None = None

    def write(part: RunBlock, result: ProcessedRun) -> None:
        writer.write(result)  # type: ignore[union-attr]
        if handle is not None:
            _write_csv_rows(handle, result)
        summary.add(part, result)
        if progress:
            progress.update(summary.samples)

    # the pool exits first: a block being written is finished before the files are closed
    with contextlib.ExitStack() as files, ThreadPoolExecutor(1, thread_name_prefix='mmd-write') as pool:
        for part, result in process_blocks(source, model, calibration=calibration,
                                           with_covariance=with_covariance or coverage_only,
                                           covariance_every=every,
                                           compiled=compiled, block=block,
                                           tails_every=tails_every):
            if writer is None:
                cal = _resolve_calibration(source, calibration)
                writer = files.enter_context(ProcessedLogWriter(
                    files.enter_context(replacing(out)), source.device, model, cal.to_yaml(),
                    int(part.stamps_ns[0]), with_covariance=with_covariance))
                if csv is not None:
                    handle = files.enter_context(open(files.enter_context(replacing(csv)), 'w',
                                                      encoding='utf-8'))
                    handle.write(CSV_HEADER + '\n')
            if pending is not None:
                pending.result()      # at most one block waits to be written
            pending = pool.submit(write, part, result)
        if pending is not None:
            pending.result()
    if summary.samples == 0:
        raise CalibrationError(f'{source.path} has no samples')
    lag = summary.reference_lag(_clock(source, reference_clock))
    if lag is not None:
        again = Progress('comparing with the reference, its lag taken out', source.n_samples,
                         enabled=progress.enabled) if progress else None
        if progress:
            progress.close()
        blocks = process_blocks(source, model, calibration=calibration,
                                with_covariance=with_covariance or coverage_only,
                                covariance_every=every, compiled=compiled, block=block,
                                tails_every=tails_every)
        if again:
            blocks = _counted(blocks, again)
        summary = _compared_again(summary, lag, blocks, every)
        if again:
            again.close()
    out_summary = summary.as_dict(source, absolute_reference=absolute_reference)
    mismatch = other_calibration(model, _resolve_calibration(source, calibration))
    if mismatch:
        out_summary['model_calibration'] = mismatch
    return out_summary


def _counted(blocks: Iterator[tuple[RunBlock, ProcessedRun]], progress: Progress
             ) -> Iterator[tuple[RunBlock, ProcessedRun]]:
    done = 0
    for part, result in blocks:
        yield part, result
        done += part.stamps_ns.size
        progress.update(done)


def _masked(poses: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Poses with NaN where the sample is not a measurement (never a wrong number)."""
    out = poses.copy()
    out[~valid] = np.nan
    return out


def _write_csv_rows(handle: IO[str], result: ProcessedRun) -> None:
    data = np.column_stack([result.poses, result.valid, result.converged, result.iterations,
                            result.residual_m, result.lengths_m, result.temp_change_c])
    for stamp, row in zip(result.stamps_ns.tolist(), data):
        handle.write(f'{stamp},' + ','.join(f'{v:.12g}' for v in row) + '\n')


def write_csv(path: Path, result: ProcessedRun) -> None:
    with replacing(path) as tmp, open(tmp, 'w', encoding='utf-8') as handle:
        handle.write(CSV_HEADER + '\n')
        _write_csv_rows(handle, result)


_DONE = object()


def _prefetched(items: Iterable[Any], depth: int = 2) -> Iterator[Any]:
    """``items`` produced in a background thread, up to ``depth`` ahead; an exception there is
    raised here. Stops the producer when the consumer stops early."""
    q: queue.Queue[Any] = queue.Queue(depth)
    stop = threading.Event()

    def offer(item: Any) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not offer(item):
                    return
            offer(_DONE)
        except BaseException as exc:  # handed to the consumer
            offer(exc)

    thread = threading.Thread(target=produce, name='mmd-read', daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=5)
