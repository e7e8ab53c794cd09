"""From logs to the approaches of a machine session: which axis run, which target, which
direction, the machine's axis values and the MMD's mean pose (with its covariance) at each
dwell.

Where the axis values come from:

- **joint states** (``/mmd/machine/joint_states`` in the log, names = the machine's axes, in m
  and rad, commanded or measured): interpolated to the MMD's samples; a dwell is a stretch in
  which every axis stands still (each axis' stillness found by
  :func:`mmd_ros.analysis.iso230.detect_dwells`); runs are the stretches in which one axis
  steps (a rotary axis with any linear axes following it); approaches are assigned to targets
  and cycles by :func:`mmd_ros.analysis.iso230.approaches`;
- else a **test program** (:class:`Program`: per run the axis, its targets and whether the
  linear axes follow), one log per run in program order: the dwells are found on the MMD's own
  pose coordinate along (or about) the axis and matched to the program's targets in order.

Each approach keeps the mean pose over the middle 60 % of its dwell and the mean of the
samples' pose covariance there (both from one pass of the pipeline over the whole log in time
order, with the model in use: :func:`log_poses`), converted to [dp, dw] screw coordinates, not
divided by the number of samples: the covariance stands for the MMD's error at that pose, which
averaging in one place does not reduce.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.analysis.iso230 import Dwell, approaches, detect_dwells
from mmd_ros.core import validate
from mmd_ros.core.machine import MachineDescription
from mmd_ros.core.model import Model
from mmd_ros.core.progress import Progress
from mmd_ros.core.rotation import rotation_angle, rotation_matrix
from mmd_ros.core.units import M_PER_MM
from mmd_ros.core.yamlio import read_yaml
from mmd_ros.logs.layout import RunLog
from mmd_ros.logs.processing import process_blocks
from mmd_ros.machine.errors import MachineAnalysisError
from mmd_ros.machine.geometry import pose_covariance_to_screw
from mmd_ros.machine.kinematics import MachineModel

__all__ = ['Approach', 'AxisRun', 'Program', 'ProgramRun', 'extract_runs', 'load_program']

FloatArray = NDArray[np.float64]

#: An axis moved between two dwells when its value changed by more than this [m], [rad].
MOVED_M, MOVED_RAD = 5e-6, 5e-6
#: Shortest stillness counted as a dwell [s].
MIN_DWELL_S = 0.15
#: A run's travel between its targets against what the MMD measured between the same dwells:
#: beyond this factor the axis positions are in other units than m and rad (the machine's own
#: errors are parts in 10^4 at most); checked on runs the MMD saw move at least this far.
UNIT_RATIO = 1.25
UNIT_MIN_M, UNIT_MIN_RAD = 5e-3, math.radians(2.0)


@dataclass
class Approach:
    """One approach to a target: a dwell of the machine.

    q : ndarray, shape (n_axes,) — the machine's axis values in the dwell [m, rad]
    last_direction : ndarray of int, shape (n_axes,) — sign of each axis' last motion
    pose : ndarray, shape (6,) — mean pose of {U} in {L} over the dwell's middle [m, rad]
    covariance : ndarray, shape (6, 6) — the MMD's covariance of that pose in [dp, dw]
    n : samples averaged; span_s : (start, stop) since the log's first sample [s]
    """

    run: str
    target: int
    direction: int
    cycle: int
    q: FloatArray
    last_direction: NDArray[np.int64]
    pose: FloatArray
    covariance: FloatArray
    n: int
    span_s: tuple[float, float]


@dataclass
class AxisRun:
    """The approaches of one axis run: targets [m or rad] and where they come from."""

    axis: str
    rotary: bool
    log: str
    targets: FloatArray
    approaches: list[Approach]
    following: list[str] = field(default_factory=list)
    source: str = 'joint states'


@dataclass(frozen=True)
class ProgramRun:
    """One run of a test program: axis, targets [m or rad], linear axes following."""

    axis: str
    targets: FloatArray
    follow: bool


@dataclass(frozen=True)
class Program:
    """A test program (targets and dwell of each run), matched to the dwells of the logs."""

    runs: tuple[ProgramRun, ...]
    min_dwell_s: float = MIN_DWELL_S


#: The keys of a test program file (each run: axis, targets_mm or targets_deg, follow).
PROGRAM_KEYS = ('runs', 'min_dwell_s')


def load_program(path: str | Path, machine: MachineDescription) -> Program:
    """Read a test program: YAML ``runs: [{axis: X, targets_mm: [...]}, {axis: C, targets_deg:
    [...], follow: true}]`` (optional ``min_dwell_s``), or CSV lines ``axis,target`` (mm or
    degrees) in run order."""
    p = Path(path)
    source = str(p)
    if p.suffix.lower() == '.csv':
        runs: list[dict[str, Any]] = []
        try:
            lines = p.read_text(encoding='utf-8').splitlines()
        except OSError as exc:
            raise MachineAnalysisError(f'{source}: cannot be read: {exc.strerror}') from None
        for n, line in enumerate(lines, start=1):
            text = line.split('#')[0].strip()
            if not text or text.lower().startswith('axis'):
                continue
            parts = [v.strip() for v in text.split(',')]
            if len(parts) < 2:
                raise MachineAnalysisError(f'{source}:{n}: expected "axis,target", got {line!r}')
            axis = parts[0].upper()
            if not runs or runs[-1]['axis'] != axis:
                runs.append({'axis': axis, 'targets': []})
            try:
                runs[-1]['targets'].append(float(parts[1]))
            except ValueError:
                raise MachineAnalysisError(f'{source}:{n}: target {parts[1]!r} is not a number') from None
        data = {'runs': [{'axis': r['axis'], ('targets_deg' if machine.axis(r['axis']).rotary
                                              else 'targets_mm'): r['targets']} for r in runs]}
    else:
        data = read_yaml(p)
    if not isinstance(data, dict) or not isinstance(data.get('runs'), list) or not data['runs']:
        raise MachineAnalysisError(f'{source}: a test program needs "runs:", a list of '
                                   '{axis: X, targets_mm: [...]} entries')
    validate.known_keys(data, PROGRAM_KEYS, source)
    out = []
    for i, item in enumerate(data['runs']):
        where = f'{source}: runs[{i}]'
        if not isinstance(item, dict) or 'axis' not in item:
            raise MachineAnalysisError(f'{where}: needs axis and targets_mm (or targets_deg)')
        try:
            axis = machine.axis(str(item['axis']))
        except Exception as exc:
            raise MachineAnalysisError(f'{where}: {exc}') from None
        key = 'targets_deg' if axis.rotary else 'targets_mm'
        validate.known_keys(item, ('axis', key, 'follow'), source, f'runs[{i}].')
        values = item.get(key)
        if not isinstance(values, list) or len(values) < 3:
            raise MachineAnalysisError(f'{where}: {key} must list at least three targets')
        try:
            t = np.array([float(v) for v in values])
        except (TypeError, ValueError):
            raise MachineAnalysisError(f'{where}: {key} must be numbers, got {values!r}') from None
        t = np.radians(t) if axis.rotary else t * M_PER_MM
        if np.any(np.diff(t) <= 0):
            raise MachineAnalysisError(f'{where}: {key} must increase')
        out.append(ProgramRun(axis.name, t, validate.boolean(item.get('follow', axis.rotary), source,
                                                               f'runs[{i}].follow')))
    return Program(tuple(out), validate.number(data.get('min_dwell_s', MIN_DWELL_S), source,
                                               'min_dwell_s', low=0.0, low_open=True))


# -- poses of a log ---------------------------------------------------------------------------
@dataclass
class LogPoses:
    """Poses of every sample of one log, and the MMD's pose covariance [m, rad]^2 of a regular
    subset of them (every ``stride``-th sample of the one pass over the whole log; None for a
    reference instrument: no covariance).

    cov_index : ndarray of int, shape (K,) — the samples whose covariance is kept
    cov : ndarray, shape (K, 6, 6) — their covariance in [x, y, z, phi, theta, psi], NaN where
        the pipeline gave none
    """

    path: str
    times_s: FloatArray
    poses: FloatArray
    valid: NDArray[np.bool_]
    cov_index: NDArray[np.int64] | None = None
    cov: FloatArray | None = None

    def covariance(self, sl: slice, at: FloatArray) -> FloatArray:
        """Mean covariance (6, 6) in [dp, dw] of the samples in ``sl`` (a dwell's middle) whose
        covariance was kept, at the mean pose ``at``; zero without a covariance (a reference
        instrument), NaN when none of them has one."""
        if self.cov is None or self.cov_index is None:
            return np.zeros((6, 6))
        lo, hi = (int(i) for i in np.searchsorted(self.cov_index, [sl.start, sl.stop]))
        rows = np.arange(lo, hi)
        if not self._usable(rows).any():
            # none kept inside (a stretch shorter than the stride, or its kept samples flagged):
            # the kept samples just outside it, a stride away, still in the dwell
            rows = np.array([i for i in (lo - 1, hi) if 0 <= i < self.cov_index.size], dtype=np.int64)
        ok = self._usable(rows)
        if not ok.any():
            return np.full((6, 6), np.nan)
        return pose_covariance_to_screw(at, self.cov[rows[ok]].mean(axis=0))

    def _usable(self, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which kept covariances (their rows in ``cov``) belong to a valid pose."""
        return self.valid[self.cov_index[rows]] & np.all(np.isfinite(self.cov[rows]), axis=(1, 2))


#: Pose covariances kept per second of a log (every k-th sample, k from the sample rate): a
#: dwell's covariance changes slowly, so a few dozen a second describe it.
COVARIANCE_RATE_HZ = 50.0


def log_poses(run: RunLog, model: Model | None, *, instrument: str = 'mmd',
              calibration_path: str | None = None, progress: bool = False) -> LogPoses:
    """The MMD's poses of a log, with the pose covariance of every k-th sample (about
    :data:`COVARIANCE_RATE_HZ` a second): one pass of the pipeline over the whole log in time
    order, so that the uncertainty budget sees the run as the live pipeline does (the stream's
    read noise, each bar's friction state and speed, what the model's terms know after the
    bars have moved). Or the log's reference instrument's poses (``instrument='reference'``: a
    6-D reference such as the twin's pose6, no covariance)."""
    times = run.times_s
    if instrument == 'reference':
        ref = run.reference_pose
        if ref is None or not np.isfinite(ref).all(axis=1).mean() > 0.5:
            raise MachineAnalysisError(f'{run.path}: no six-dimensional reference pose to evaluate')
        return LogPoses(str(run.path), times, ref, np.isfinite(ref).all(axis=1))
    model = run.model or Model() if model is None else model
    span = float(times[-1] - times[0]) if times.size > 1 else 0.0
    rate = (times.size - 1) / span if span > 0 else COVARIANCE_RATE_HZ
    every = max(1, int(round(rate / COVARIANCE_RATE_HZ)))
    bar = Progress(f'poses of {Path(run.path).name}', times.size, enabled=progress)
    poses, valid, index, cov = [], [], [], []
    start = 0
    for part, res in process_blocks(run, model, calibration=calibration_path, with_covariance=True,
                                    covariance_every=every):
        n = part.stamps_ns.size
        poses.append(res.poses)
        valid.append(res.valid)
        index.append(start + np.arange(0, n, every))
        cov.append(res.covariance[::every])
        start += n
        bar.update(start)
    bar.close()
    if not poses:
        raise MachineAnalysisError(f'{run.path} has no samples')
    return LogPoses(str(run.path), times, np.concatenate(poses), np.concatenate(valid),
                    np.concatenate(index), np.concatenate(cov))


# -- dwells -----------------------------------------------------------------------------------
def _check_times(times: FloatArray, log: str) -> None:
    """Refuse time stamps that repeat or go back: a dwell is timed by them (detect_dwells takes
    its window from the median time step, which repeated stamps make zero)."""
    step = np.diff(np.asarray(times, dtype=np.float64))
    bad = np.flatnonzero(~(step > 0))
    if bad.size:
        i = int(bad[0]) + 1
        raise MachineAnalysisError(
            f'{log}: time stamps must increase, but {bad.size} of {step.size} steps repeat or go '
            f'back (first at sample {i}, t = {float(times[i]):.6f} s after the first): '
            'record with one stamp per sample, or drop the repeated samples')


def _still(times: FloatArray, values: FloatArray, min_dwell_s: float, log: str = 'the log'
           ) -> NDArray[np.bool_]:
    """Samples where ``values`` stands still (detect_dwells' stretches)."""
    _check_times(times, log)
    mask = np.zeros(values.size, dtype=bool)
    for d in detect_dwells(times, values, min_dwell_s=min_dwell_s):
        mask[d.start:d.stop] = True
    return mask


def _segments(mask: NDArray[np.bool_], times: FloatArray, min_dwell_s: float) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])
            if times[b - 1] - times[a] >= min_dwell_s]


def _middle(start: int, stop: int) -> slice:
    n = stop - start
    return slice(start + n // 5, stop - n // 5) if n >= 5 else slice(start, stop)


def _cluster(values: FloatArray, directions: NDArray[np.int64] | None = None,
             tolerance: float = 1e-9) -> FloatArray:
    """Distinct target values: medians of groups separated by more than ``tolerance`` (the
    joint states' standstill scatter); with ``directions``, only groups reached from both sides
    (an ISO target, not a home position visited on the way between runs)."""
    order = np.argsort(values)
    v = values[order]
    if v.size == 0:
        return v
    gap = max(tolerance, 1e-9)
    cuts = np.flatnonzero(np.diff(v) > gap) + 1
    groups = np.split(v, cuts)
    if directions is None:
        return np.array([float(np.median(g)) for g in groups])
    dirs = np.split(np.asarray(directions)[order], cuts)
    return np.array([float(np.median(g)) for g, d in zip(groups, dirs) if (d > 0).any() and (d < 0).any()])


def _mean_pose(poses: LogPoses, sl: slice) -> tuple[FloatArray, FloatArray, int] | None:
    ok = poses.valid[sl]
    if ok.sum() < 2:
        return None
    mean = poses.poses[sl][ok].mean(axis=0)
    cov = poses.covariance(sl, mean)
    if not np.all(np.isfinite(cov)):
        return None
    return mean, cov, int(ok.sum())


def _label(moved: list[int], machine: MachineDescription) -> str | None:
    """The run a move belongs to: a rotary axis (with any followers), or one linear axis."""
    rotary = [k for k in moved if machine.axes[k].rotary]
    if len(rotary) == 1:
        return machine.axes[rotary[0]].name
    if not rotary and len(moved) == 1:
        return machine.axes[moved[0]].name
    return None


def _joint_values(run: RunLog, machine: MachineDescription, times: FloatArray) -> FloatArray:
    js = run.machine_joints
    if js is None:
        raise MachineAnalysisError(
            f'{run.path} has no machine axis positions (/mmd/machine/joint_states); record the '
            'controller\'s joint states beside /mmd/pose, or give a test program (--program)')
    names = [n.strip().upper() for n in js.names]
    missing = [a for a in machine.axis_names if a not in names]
    if missing:
        raise MachineAnalysisError(f'{run.path}: /mmd/machine/joint_states names {js.names}, '
                                   f'missing the machine axes {missing}')
    t_js = (js.stamps_ns - run.stamps_ns[0]).astype(np.float64) * 1e-9
    order = np.argsort(t_js, kind='stable')
    out = np.empty((times.size, len(machine.axis_names)))
    for k, name in enumerate(machine.axis_names):
        col = js.positions[order, names.index(name)]
        out[:, k] = np.interp(times, t_js[order], col)
    return out


def _runs_from_joints(run: RunLog, machine: MachineDescription, poses: LogPoses,
                      min_dwell_s: float) -> list[AxisRun]:
    times = poses.times_s
    q = _joint_values(run, machine, times)
    still = np.ones(times.size, dtype=bool)
    for k in range(q.shape[1]):
        still &= _still(times, q[:, k], min_dwell_s, str(run.path))
    segments = _segments(still, times, min_dwell_s)
    if len(segments) < 3:
        raise MachineAnalysisError(f'{run.path}: the machine stood still only {len(segments)} '
                                   'time(s): not an ISO test cycle')
    tol = np.array([MOVED_RAD if a.rotary else MOVED_M for a in machine.axes])
    values = np.array([q[_middle(a, b)].mean(axis=0) for a, b in segments])
    last = np.zeros(values.shape, dtype=np.int64)
    labels: list[str | None] = []
    moved_sets: list[list[int]] = []
    for i in range(1, len(segments)):
        # the motion between the two dwells: an axis that overran and came back moved too, and
        # its last direction is that of its last motion into the dwell
        between = q[segments[i - 1][1] - 1:segments[i][0] + 1]
        far = np.abs(between - values[i]) > tol
        moved = [k for k in range(q.shape[1]) if far[:, k].any()]
        last[i] = last[i - 1]
        for k in moved:
            j = np.flatnonzero(far[:, k])[-1]
            last[i, k] = int(np.sign(values[i, k] - between[j, k]))
        labels.append(_label(moved, machine))
        moved_sets.append(moved)
    # runs: maximal stretches of moves with the same label
    out: list[AxisRun] = []
    i = 0
    while i < len(labels):
        label = labels[i]
        j = i
        while j + 1 < len(labels) and labels[j + 1] == label:
            j += 1
        if label is not None:
            idx = list(range(i, j + 2))  # dwells joined by moves i..j
            k = machine.axis_names.index(label)
            axis = machine.axes[k]
            followers = sorted({machine.axes[m].name for s in moved_sets[i:j + 1] for m in s
                                if m != k})
            dwells = [Dwell(segments[n][0], segments[n][1], float(values[n, k]), int(last[n, k]))
                      for n in idx]
            moving = [d for d in dwells if d.direction != 0]
            targets = _cluster(np.array([d.value for d in moving]), np.array([d.direction for d in moving]),
                               tol[k])
            if targets.size >= 3:
                tg, found = approaches(dwells, targets)
                _check_one_run(str(run.path), axis.rotary, axis.name, dwells, tg, found, times)
                out.append(_axis_run(run, axis.name, axis.rotary, tg, found, poses,
                                     {d.start: n for n, d in zip(idx, dwells)}, values, last,
                                     followers, 'joint states'))
        i = j + 1
    return [r for r in out if r.approaches]


def _check_one_run(log: str, rotary: bool, name: str, dwells: list[Dwell], targets: FloatArray,
                   found: list, times: FloatArray) -> None:
    """Refuse a stretch of one axis' moves that is not one ISO 230-2 run: runs of an axis one
    after the other (no other axis moving between them) make one stretch; with the same targets
    they are one run with their cycles added, with different targets the passes of one of them
    skip targets of the other and :func:`approaches` drops them (or leaves targets without an
    approach). Such a pass: two dwells in a row at targets, in one direction, neither kept."""
    kept = {a.dwell.start for a in found}
    tol = 0.25 * float(np.min(np.diff(targets)))

    def stray(d: Dwell) -> bool:
        return d.direction != 0 and d.start not in kept and \
            float(np.min(np.abs(targets - d.value))) <= tol
    approached = {(a.target, a.direction) for a in found}
    skipped = any(stray(a) and stray(b) and a.direction == b.direction
                  for a, b in zip(dwells, dwells[1:]))
    if not skipped and len(approached) == 2 * targets.size:
        return
    scale, unit = (180.0 / math.pi, '°') if rotary else (1e3, ' mm')
    shown = ', '.join(f'{v * scale:g}' for v in targets)
    raise MachineAnalysisError(
        f'{log}: the {name} moves from {times[dwells[0].start]:.1f} s to '
        f'{times[dwells[-1].stop - 1]:.1f} s are not one ISO 230-2 run: passes through the targets '
        f'found there ({shown}{unit}) skip some of them. Two runs of {name} one after the other '
        'with different targets? Give one run per axis (runs with the same targets one after the '
        'other count as one, their cycles added)')


def _axis_run(run: RunLog, name: str, rotary: bool, targets: FloatArray, found: list,
              poses: LogPoses, index_of: dict[int, int], values: FloatArray,
              last: NDArray[np.int64], followers: list[str], source: str) -> AxisRun:
    times = poses.times_s
    out = []
    for a in found:
        sl = _middle(a.dwell.start, a.dwell.stop)
        mean = _mean_pose(poses, sl)
        if mean is None:
            continue
        n = index_of[a.dwell.start]
        out.append(Approach(name, a.target, a.direction, a.cycle, values[n].copy(), last[n].copy(),
                            mean[0], mean[1], mean[2],
                            (float(times[a.dwell.start]), float(times[a.dwell.stop - 1]))))
    return AxisRun(name, rotary, str(run.path), targets, out, followers, source)


def _runs_from_program(run: RunLog, machine: MachineDescription, poses: LogPoses,
                       plan: ProgramRun, min_dwell_s: float) -> AxisRun:
    """Dwells on the MMD's own coordinate along / about the axis, matched to the program."""
    axis = machine.axis(plan.axis)
    k = machine.index(plan.axis)
    comp = axis.component + (3 if axis.rotary else 0)
    coord = np.where(poses.valid, poses.poses[:, comp], np.nan)
    _check_times(poses.times_s, str(run.path))
    dwells = detect_dwells(poses.times_s, coord, min_dwell_s=min_dwell_s)
    moving = [d for d in dwells if d.direction != 0]
    found_values = _cluster(np.array([d.value for d in moving]),
                            tolerance=1e-3 * float(np.ptp([d.value for d in moving] or [0.0])))
    if found_values.size != plan.targets.size:
        raise MachineAnalysisError(
            f'{run.path}: found dwells at {found_values.size} positions of the '
            f'{plan.axis} axis, the program lists {plan.targets.size} targets; check the program '
            'or record the machine\'s joint states')
    sign = 1.0 if axis.direction[axis.component] > 0 else -1.0
    if sign < 0:
        found_values = found_values[::-1]
    # each dwell at its program target; direction of motion in axis values
    mapped = []
    for d in dwells:
        i = int(np.argmin(np.abs(found_values - d.value)))
        spacing = np.min(np.abs(np.diff(found_values)))
        if abs(found_values[i] - d.value) > 0.25 * spacing:
            mapped.append(Dwell(d.start, d.stop, math.nan, 0))
            continue
        mapped.append(Dwell(d.start, d.stop, float(plan.targets[i]), int(sign * d.direction)))
    mapped = [d for d in mapped if math.isfinite(d.value)]
    tg, found = approaches(mapped, plan.targets)
    model = MachineModel(machine)
    values = np.tile(machine.reference, (len(mapped), 1))
    values[:, k] = [d.value for d in mapped]
    if plan.follow and axis.rotary:
        values = model.nominal_follow(values)
    last = np.zeros(values.shape, dtype=np.int64)
    for n, d in enumerate(mapped):
        last[n, k] = d.direction
        if plan.follow and axis.rotary:  # followers move with the sign of their slope
            dq = np.zeros(len(machine.axes))
            dq[k] = 1e-4
            ahead = model.nominal_follow((values[n] + dq)[None])[0]
            for m, a in enumerate(machine.axes):
                if not a.rotary:
                    last[n, m] = int(np.sign(ahead[m] - values[n, m])) * d.direction
    followers = [a.name for m, a in enumerate(machine.axes)
                 if not a.rotary and np.ptp(values[:, m]) > MOVED_M] if len(mapped) else []
    return _axis_run(run, axis.name, axis.rotary, tg, found, poses,
                     {d.start: n for n, d in enumerate(mapped)}, values, last, followers,
                     'test program')


def extract_runs(run: RunLog, machine: MachineDescription, poses: LogPoses, *,
                 program_run: ProgramRun | None = None,
                 min_dwell_s: float = MIN_DWELL_S) -> list[AxisRun]:
    """The axis runs in one log: from its joint states, or from one run of a test program."""
    if run.times_s.size < 10:
        raise MachineAnalysisError(f'{run.path} has too few samples')
    if program_run is not None:
        runs = [_runs_from_program(run, machine, poses, program_run, min_dwell_s)]
    else:
        runs = _runs_from_joints(run, machine, poses, min_dwell_s)
    check_units(runs, machine)
    return runs


def check_units(runs: list[AxisRun], machine: MachineDescription) -> None:
    """Refuse axis positions in units other than the SI ones of REP 103 (m, rad): each run's
    travel between two of its dwells against the travel the MMD measured between them (a
    controller that publishes mm or degrees gives 1000 or 57.3 times the MMD's)."""
    for r in runs:
        if len(r.approaches) < 2:
            continue
        k = machine.axis_names.index(r.axis)
        first = r.approaches[0]
        travel = measured = 0.0
        for a in r.approaches[1:]:
            if r.rotary:
                seen = float(rotation_angle(rotation_matrix(first.pose[3:]).T
                                            @ rotation_matrix(a.pose[3:])))
            else:
                seen = float(np.linalg.norm(a.pose[:3] - first.pose[:3]))
            if seen > measured:
                travel, measured = abs(float(a.q[k] - first.q[k])), seen
        if measured < (UNIT_MIN_RAD if r.rotary else UNIT_MIN_M):
            continue
        ratio = travel / measured
        if 1.0 / UNIT_RATIO <= ratio <= UNIT_RATIO:
            continue
        unit = 'rad' if r.rotary else 'm'
        likely = [name for factor, name in ((1e3, 'mm'), (180.0 / math.pi, 'degrees'), (1e6, 'µm'))
                  if abs(ratio / factor - 1.0) < 0.25]
        raise MachineAnalysisError(
            f'{r.log}: axis {r.axis} moved {travel:.6g} {unit} by its {r.source} where the MMD '
            f'measured {measured:.6g} {unit}, {ratio:.4g} times as much'
            + (f' (in {likely[0]}?)' if likely else '')
            + ': machine axis positions must be in m and rad (REP 103)')
