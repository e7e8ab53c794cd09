"""Every sample of a log through the pipeline (counts → CDF → thermal → model terms → FK), and
the processed log written back in the live pipeline's topics. Used by ``mmd process``, the demo
and the live demo."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.accuracy import coverage, error_stats, length_error, pose_error
from mmd_ros.core.calibration import load_calibration
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.model import Model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.progress import Progress
from mmd_ros.logs.layout import (
    BAR_NAMES, FRAME_LOWER, TOPIC_BAR_LENGTHS, TOPIC_CALIBRATION, TOPIC_DEVICE, TOPIC_FK_STATUS,
    TOPIC_MODEL, TOPIC_POSE, TOPIC_POSE_COV, TOPIC_THERMAL, RunLog,
)
from mmd_ros.logs.outputs import replacing
from mmd_ros.logs.writer import LogWriter

__all__ = ['ProcessedRun', 'process_run', 'summarize', 'write_csv', 'write_processed']

#: Samples per block: bounds memory and lets progress be shown on long logs.
BLOCK = 65536
FK_STATUS_NAMES = ['converged', 'valid', 'iterations', 'residual', 'condition']


@dataclass
class ProcessedRun:
    """Every sample of a run through the pipeline (arrays of N samples)."""

    stamps_ns: NDArray[np.int64]
    lengths_m: NDArray[np.float64]
    poses: NDArray[np.float64]
    converged: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    out_of_range: NDArray[np.bool_]
    iterations: NDArray[np.int64]
    residual_m: NDArray[np.float64]
    reference_error_m: NDArray[np.float64]
    temp_change_c: NDArray[np.float64]
    covariance: NDArray[np.float64] | None
    budget: dict[str, Any] | None = None  # the uncertainty budget's numbers and notes


def process_run(run: RunLog, model: Model, *, calibration_path: str | None = None,
                with_covariance: bool = False, progress: Progress | None = None) -> ProcessedRun:
    """Run the pipeline over a whole log, block by block, in time order."""
    calibration = load_calibration(calibration_path) if calibration_path else run.calibration
    if calibration is None:
        raise CalibrationError(f'{run.path} carries no calibration; pass --calibration FILE')
    pipeline = Pipeline(run.device, calibration, model)
    times = run.times_s
    parts = []
    for start in range(0, times.size, BLOCK):
        stop = start + BLOCK
        parts.append(pipeline.process(times[start:stop], run.counts[start:stop],
                                      with_covariance=with_covariance))
        if progress:
            progress.update(min(stop, times.size))
    if not parts:
        raise CalibrationError(f'{run.path} has no samples')

    def cat(get):
        return np.concatenate([get(p) for p in parts])

    return ProcessedRun(
        run.stamps_ns, cat(lambda p: p.compensated.lengths_m), cat(lambda p: p.poses),
        cat(lambda p: p.converged), cat(lambda p: p.valid),
        cat(lambda p: p.compensated.out_of_range), cat(lambda p: p.iterations),
        cat(lambda p: p.residual_m), cat(lambda p: p.compensated.thermal.reference_error_m),
        cat(lambda p: p.compensated.thermal.temp_change_c),
        cat(lambda p: p.covariance) if with_covariance else None,
        pipeline.budget.summary() if with_covariance else None)


def write_processed(path: Path, run: RunLog, model: Model, result: ProcessedRun,
                    calibration_text: str, *, with_covariance: bool = True) -> None:
    """Write bar lengths, poses, thermal state and FK status in the live pipeline's topics (and
    the poses with their covariance when computed and ``with_covariance``), under a temporary
    name, renamed to ``path`` once complete."""
    stamps = result.stamps_ns
    t0 = int(stamps[0])
    ref_names = [c.name + '_error' for c in run.device.reference_channels][:result.reference_error_m.shape[1]]
    status = np.column_stack([result.converged, result.valid, result.iterations,
                              result.residual_m, np.full(stamps.size, np.nan)]).astype(np.float64)
    with replacing(path) as tmp, LogWriter(tmp) as log:
        log.write_string(TOPIC_DEVICE, t0, run.device.to_yaml())
        log.write_string(TOPIC_CALIBRATION, t0, calibration_text)
        log.write_string(TOPIC_MODEL, t0, model.to_yaml())
        streams = [
            (TOPIC_BAR_LENGTHS, 'sensor_msgs/msg/JointState',
             log.joint_state_rows(BAR_NAMES, stamps, result.lengths_m)),
            (TOPIC_POSE, 'geometry_msgs/msg/PoseStamped',
             log.pose_rows(FRAME_LOWER, stamps, _masked(result.poses, result.valid))),
            (TOPIC_THERMAL, 'sensor_msgs/msg/JointState',
             log.joint_state_rows(ref_names + ['temp_change'], stamps,
                                  np.column_stack([result.reference_error_m, result.temp_change_c]))),
            (TOPIC_FK_STATUS, 'sensor_msgs/msg/JointState',
             log.joint_state_rows(FK_STATUS_NAMES, stamps, status)),
        ]
        if result.covariance is not None and with_covariance:
            streams.append((TOPIC_POSE_COV, 'geometry_msgs/msg/PoseWithCovarianceStamped',
                            log.pose_rows(FRAME_LOWER, stamps, _masked(result.poses, result.valid),
                                          result.covariance)))
        log.write_rows(streams, stamps)


def _masked(poses: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Poses with NaN where the sample is not a measurement (never a wrong number)."""
    out = poses.copy()
    out[~valid] = np.nan
    return out


def write_csv(path: Path, result: ProcessedRun) -> None:
    header = ('stamp_ns,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad,valid,converged,iterations,'
              'residual_m,' + ','.join(f'bar{i}_m' for i in range(1, 7)) + ',temp_change_c')
    data = np.column_stack([result.poses, result.valid, result.converged, result.iterations,
                            result.residual_m, result.lengths_m, result.temp_change_c])
    with replacing(path) as tmp, open(tmp, 'w', encoding='utf-8') as handle:
        handle.write(header + '\n')
        for stamp, row in zip(result.stamps_ns.tolist(), data):
            handle.write(f'{stamp},' + ','.join(f'{v:.12g}' for v in row) + '\n')


def summarize(run: RunLog, result: ProcessedRun, *, absolute_reference: bool | None = None
              ) -> dict[str, Any]:
    """Counts of samples and, with a reference in the log, the error statistics and, with the
    covariance computed, how well it covers the error (:func:`~mmd_ros.core.accuracy.coverage`).

    absolute_reference : the reference pose is absolute in {L} (no offset removed); None takes
        what the log's metadata says (``reference_absolute``), else False (zeroed at the start)
    """
    n = int(result.stamps_ns.size)
    summary: dict[str, Any] = {
        'log': str(run.path),
        'samples': n,
        'duration_s': float(run.times_s[-1]) if n else 0.0,
        'valid': int(result.valid.sum()),
        'not_converged': int((~result.converged).sum()),
        'out_of_range': int(result.out_of_range.any(axis=1).sum()),
        'max_fk_iterations': int(result.iterations.max()) if n else 0,
    }
    if run.problem:
        summary['log_problem'] = run.problem.as_dict()
    if run.segment[1] > 1:
        summary['segment'] = {'index': run.segment[0], 'of': run.segment[1]}
    if run.reference_pose is not None:
        errors = pose_error(result.poses, run.reference_pose)
        stats = error_stats(errors, result.valid)
        summary['pose_error'] = [s.as_dict() for s in stats]
        if result.covariance is not None:
            absolute = absolute_reference
            if absolute is None:
                absolute = bool(run.metadata.get('reference_absolute', False))
            sigma = run.metadata.get('reference_sigma')
            ref_sigma = (np.array([np.nan if v is None else float(v) for v in sigma])
                         if isinstance(sigma, list) and len(sigma) == 6 else None)
            report = coverage(errors, result.covariance, result.valid, absolute=absolute,
                              reference_sigma=ref_sigma)
            if report is not None:
                summary['uncertainty_coverage'] = report
    if result.budget is not None:
        summary['uncertainty_budget'] = result.budget
    if run.reference_lengths is not None:
        stats = error_stats(length_error(result.lengths_m, run.reference_lengths), result.valid,
                            kind='lengths')
        summary['length_error'] = [s.as_dict() for s in stats]
    return summary
