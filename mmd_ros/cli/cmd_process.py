"""``mmd process LOG.mcap``: counts → CDF → thermal → FK for every sample of a log."""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.cli.progress import Progress
from mmd_ros.core.accuracy import error_stats, format_stats, length_error, pose_error
from mmd_ros.core.calibration import load_calibration
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.model import Model, load_model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.logs.layout import (
    BAR_NAMES, FRAME_LOWER, TOPIC_BAR_LENGTHS, TOPIC_CALIBRATION, TOPIC_DEVICE, TOPIC_FK_STATUS,
    TOPIC_MODEL, TOPIC_POSE, TOPIC_POSE_COV, TOPIC_THERMAL, RunLog, read_run,
)
from mmd_ros.logs.writer import LogWriter

__all__ = ['ProcessedRun', 'process_run', 'register']

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
        cat(lambda p: p.covariance) if with_covariance else None)


def write_processed(path: Path, run: RunLog, model: Model, result: ProcessedRun,
                    calibration_text: str) -> None:
    """Write bar lengths, poses, thermal state and FK status in the live pipeline's topics."""
    stamps = result.stamps_ns
    t0 = int(stamps[0])
    ref_names = [c.name + '_error' for c in run.device.reference_channels][:result.reference_error_m.shape[1]]
    status = np.column_stack([result.converged, result.valid, result.iterations,
                              result.residual_m, np.full(stamps.size, np.nan)]).astype(np.float64)
    with LogWriter(path) as log:
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
        if result.covariance is not None:
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
    with open(path, 'w', encoding='utf-8') as handle:
        handle.write(header + '\n')
        for stamp, row in zip(result.stamps_ns.tolist(), data):
            handle.write(f'{stamp},' + ','.join(f'{v:.12g}' for v in row) + '\n')


def summarize(run: RunLog, result: ProcessedRun) -> dict[str, Any]:
    """Counts of samples and, with a reference in the log, the error statistics."""
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
        summary['log_problem'] = run.problem
    if run.reference_pose is not None:
        stats = error_stats(pose_error(result.poses, run.reference_pose), result.valid)
        summary['pose_error'] = [s.as_dict() for s in stats]
    if run.reference_lengths is not None:
        stats = error_stats(length_error(result.lengths_m, run.reference_lengths), result.valid,
                            kind='lengths')
        summary['length_error'] = [s.as_dict() for s in stats]
    return summary


def run_command(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    quiet = args.json or args.quiet
    if not quiet:
        print(f'reading {args.log}', file=sys.stderr)
    run = read_run(args.log)
    if run.problem:
        print(f'warning: {run.problem}', file=sys.stderr)
    model = load_model(args.model) if args.model else (run.model or Model())
    progress = Progress('processing', run.counts.shape[0], enabled=not quiet)
    result = process_run(run, model, calibration_path=args.calibration,
                         with_covariance=args.covariance, progress=progress)
    progress.close()
    out = Path(args.out) if args.out else Path(args.log).with_suffix('.processed.mcap')
    cal = run.calibration if not args.calibration else load_calibration(args.calibration)
    write_processed(out, run, model, result, cal.to_yaml())
    if args.csv:
        write_csv(Path(args.csv), result)
    elapsed = time.perf_counter() - started
    summary = summarize(run, result)
    summary.update(output=str(out), csv=args.csv, seconds=elapsed,
                   samples_per_s=summary['samples'] / elapsed if elapsed > 0 else None,
                   model=model.to_dict())
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write('\n')
        return 0
    print(f'{summary["samples"]} samples over {summary["duration_s"]:.1f} s: '
          f'{summary["valid"]} valid poses, {summary["not_converged"]} not converged, '
          f'{summary["out_of_range"]} with a bar out of its calibrated range')
    print(f'wrote {out}' + (f' and {args.csv}' if args.csv else '')
          + f' in {elapsed:.2f} s ({summary["samples_per_s"]:.0f} samples/s)')
    if 'pose_error' in summary:
        from mmd_ros.core.accuracy import ComponentStats
        print(format_stats([ComponentStats(**s) for s in summary['pose_error']],
                           'pose error against the reference (MMD - reference):'))
    if 'length_error' in summary:
        from mmd_ros.core.accuracy import ComponentStats
        print(format_stats([ComponentStats(**s) for s in summary['length_error']],
                           'bar length error against the reference:'))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser('process', help='compute bar lengths and poses for every sample of a log',
                       description='Run the model over every sample of a log (counts → CDF, Eq. 10 → '
                       'thermal, Eqs. 11–13 → model terms → forward kinematics) and write the bar '
                       'lengths and poses as MCAP (CSV on request). With a reference in the log, '
                       'print the error statistics in µm and arc-seconds.')
    p.add_argument('log', help='MCAP log with raw counts (from mmd simulate, the recorder, a user)')
    p.add_argument('--model', help='model file (YAML); default: the log\'s model, else CDF + thermal')
    p.add_argument('--calibration', help='calibration file to use instead of the one in the log')
    p.add_argument('--out', help='output MCAP (default: LOG.processed.mcap)')
    p.add_argument('--csv', help='also write the poses and lengths as CSV to this file')
    p.add_argument('--covariance', action='store_true',
                   help='also write /mmd/pose_with_covariance (propagated uncertainty)')
    p.add_argument('--json', action='store_true', help='print a machine-readable summary on stdout')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run_command)
