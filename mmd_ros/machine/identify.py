"""Identification of a machine's geometric errors from the approaches of a session (ISO 230-1,
ISO 230-2, ISO 230-7), with Monte Carlo uncertainty.

Definitions (``msg_docs/machine.md`` states them with their signs):

- **Machine frame.** X is the reference: x is the direction of the X run's least-squares line
  (through the bidirectional means at its targets), y completes the plane of the X and Y lines,
  z = x × y. {L}'s setup misalignment on the table drops out this way (ISO 230-1: the slope of
  a straightness run is setup; the difference of two axes' slopes in one setup is squareness).
- **Linear error motions** of axis k at target i: the displacement of the functional point
  (origin of {U}) relative to {L} in machine axes, minus the commanded motion, and the rotation
  of {U} relative to {L}: the tool relative to the workpiece, relative to the run's reference
  position (the bidirectional mean there is zero). Per direction of approach; the bidirectional
  mean and reversal (↑ − ↓) follow. Straightness deviations are from the least-squares
  reference line of the bidirectional means; the line's slope in machine axes gives the
  squareness: EC0Y (Y about z), EB0Z and EA0Z (Z about y and x), the rotation of the axis' line
  by the right-hand rule.
- **Rotary axes.** The measured motion relative to the run's reference (the pose at the
  reference angle), placed in machine coordinates by the machine frame and the functional
  point, is compared with the kinematic model (:mod:`mmd_ros.machine.kinematics`: nominal
  motion, the linear axes' identified error motions where they follow, and the axis' location
  errors). The location errors (position of the axis line at its pivot in the two directions
  across it, its tilt about those two directions) are fitted by least squares over all
  approaches; what remains, at the axis point nearest the functional point in fixed machine
  axes and relative to the reference angle, are the component error motions: radial, axial,
  tilt and angular positioning.

Uncertainty: the approaches' mean poses are drawn ``draws`` times from their covariance (the
MMD's pose covariance, systematic at a pose, plus the scatter between cycles over their number)
and the functional point from the stated uncertainty of the upper plate's position; the whole
identification is repeated on each draw. The MMD's error at a pose is drawn from its
covariance independently between targets and, once more, as a linear trend along the run: its
errors follow the bar lengths, which change smoothly along a run, and a trend is what turns into
a false slope (squareness) or a false location. A second set of draws with the MMD's covariance alone
gives the MMD's part. The other table axes' play during a rotary run (within ± their reversal)
is drawn too, and each target's cycle scatter is floored by the run's pooled scatter. Component
errors that a partial turn cannot tell from the location (harmonics 2–4 of the angle, of the
stated size, scaled per component by the fit's residual) add their projection onto the location
(:meth:`_Session._leak`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from scipy.stats import t as student_t

from mmd_ros.analysis.iso230 import evaluate
from mmd_ros.core.machine import MachineAxis, MachineDescription
from mmd_ros.core.rotation import rotation_matrix
from mmd_ros.machine.errors import MachineAnalysisError
from mmd_ros.machine.geometry import (
    apply, inverse, pose_to_transform, rotation_from_rotvec, rotvec, transform,
)
from mmd_ros.machine.kinematics import ErrorTable, MachineModel, RotaryLocation, axis_point
from mmd_ros.machine.results import COVERAGE_K, AxisResult, ErrorMotion, MachineResult, Value
from mmd_ros.machine.session import AxisRun

__all__ = ['IdentifyOptions', 'identify']

FloatArray = NDArray[np.float64]
_XYZ, _ABC = 'XYZ', 'ABC'


@dataclass(frozen=True)
class IdentifyOptions:
    """draws : Monte Carlo draws per uncertainty estimate; seed : their random seed
    limit_m, limit_rad : an error whose standard uncertainty exceeds these is reported as not
        determined by the session (the value is still given)
    mmd_bound_m, mmd_bound_rad : a stated accuracy of the MMD's pose (± bound of each position
        and rotation component, e.g. from its data sheet or its own validation), added to its
        covariance as a uniform distribution (u = bound / sqrt 3) at every approach; 0: the
        pose covariance alone
    component_m, component_rad : the size (RMS over a full turn) of the rotary axes' radial
        and axial, and of their tilt and positioning, component error motions that are not
        the location (harmonics 2–4 of the angle), as the table's acceptance test or data sheet
        states them. Over a partial turn such errors can pass for location errors; their
        possible effect is part of every location error's uncertainty (scaled up where the
        fit's residual shows more). The default, 1 µm and 1″, is a good rotary table's.
    """

    draws: int = 200
    seed: int = 0
    limit_m: float = 2e-6
    limit_rad: float = math.radians(2.0 / 3600.0)
    mmd_bound_m: float = 0.0
    mmd_bound_rad: float = 0.0
    component_m: float = 1e-6
    component_rad: float = math.radians(1.0 / 3600.0)


@dataclass
class RunMeans:
    """The approaches of one run averaged per target and direction (index 0 up, 1 down)."""

    run: AxisRun
    axis: MachineAxis
    k: int
    targets: FloatArray
    p: FloatArray          # (m, 2, 3) mean position of {U} in {L}
    r: FloatArray          # (m, 2, 3, 3) mean rotation
    cov_mmd: FloatArray    # (m, 2, 6, 6) the MMD's covariance of the mean [dp, dw] in {L}
    cov_stat: FloatArray   # (m, 2, 6, 6) scatter between cycles / n
    n: NDArray[np.int64]   # (m, 2)
    q: FloatArray          # (m, 2, n_axes)
    dirs: FloatArray       # (m, 2, n_axes)
    ref: int | None
    ref_interp: tuple[int, float] | None
    cycles_p: FloatArray   # (m, 2, c, 3) per approach, NaN where missing
    cycles_r: FloatArray   # (m, 2, c, 3, 3)


def _mean_rotation(rs: FloatArray) -> FloatArray:
    """Mean of nearby rotations (k, 3, 3) about the first."""
    w = rotvec(rs @ np.swapaxes(rs[0], -1, -2)[None])
    return rotation_from_rotvec(w.mean(axis=0)) @ rs[0]


def aggregate(run: AxisRun, machine: MachineDescription) -> RunMeans:
    """Per target and direction: mean pose, the MMD's covariance, the scatter of the means."""
    axis = machine.axis(run.axis)
    k = machine.index(run.axis)
    m = run.targets.size
    cycles = max(a.cycle for a in run.approaches) + 1
    p = np.full((m, 2, 3), np.nan)
    r = np.full((m, 2, 3, 3), np.nan)
    cov_mmd = np.zeros((m, 2, 6, 6))
    cov_stat = np.zeros((m, 2, 6, 6))
    n = np.zeros((m, 2), dtype=np.int64)
    q = np.full((m, 2, len(machine.axes)), np.nan)
    dirs = np.zeros((m, 2, len(machine.axes)))
    cp = np.full((m, 2, cycles, 3), np.nan)
    cr = np.full((m, 2, cycles, 3, 3), np.nan)
    for i in range(m):
        for j, direction in enumerate((1, -1)):
            group = [a for a in run.approaches if a.target == i and a.direction == direction]
            if not group:
                continue
            t = pose_to_transform(np.array([a.pose for a in group]))
            pm = t[:, :3, 3].mean(axis=0)
            rm = _mean_rotation(t[:, :3, :3])
            p[i, j], r[i, j] = pm, rm
            dev = np.column_stack([t[:, :3, 3] - pm, rotvec(t[:, :3, :3] @ rm.T[None])])
            if len(group) > 1:
                cov_stat[i, j] = np.cov(dev.T, ddof=1) / len(group)
            cov_mmd[i, j] = np.mean([a.covariance for a in group], axis=0)
            n[i, j] = len(group)
            q[i, j] = np.mean([a.q for a in group], axis=0)
            dirs[i, j] = group[-1].last_direction
            for a, tt in zip(group, t):
                cp[i, j, a.cycle] = tt[:3, 3]
                cr[i, j, a.cycle] = tt[:3, :3]
    _floor_scatter(cov_stat, n)
    missing = [f'{v:g}' for v, c in zip(run.targets, n) if c.min() == 0]
    if missing:
        raise MachineAnalysisError(
            f'{run.log}: {run.axis} run: targets {missing} were not approached from both '
            'directions; run the ISO 230-2 standard test cycle (bidirectional)')
    scale = 1.0
    close = np.flatnonzero(np.abs(run.targets - axis.reference) < 1e-9 + 1e-6 * scale)
    ref = int(close[0]) if close.size else None
    interp = None
    if ref is None:
        if axis.rotary or not run.targets[0] < axis.reference < run.targets[-1]:
            unit = '°' if axis.rotary else ' mm'
            value = math.degrees(axis.reference) if axis.rotary else axis.reference * 1e3
            raise MachineAnalysisError(
                f'{run.log}: the {run.axis} run has no target at the reference position '
                f'{value:g}{unit} (machine description): add one, or set the reference there')
        i = int(np.searchsorted(run.targets, axis.reference)) - 1
        interp = (i, float((axis.reference - run.targets[i]) / (run.targets[i + 1] - run.targets[i])))
    return RunMeans(run, axis, k, run.targets, p, r, cov_mmd, cov_stat, n, q, dirs, ref, interp, cp, cr)


def _floor_scatter(cov_stat: FloatArray, n: NDArray[np.int64]) -> None:
    """Floor each approach group's scatter covariance (m, 2, 6, 6), in place, by the run's
    pooled one: the machine's repeatability does not change much along an axis, and a few
    cycles at one target can show far less scatter than there is by chance (with 3 cycles, 1
    in 20 targets shows under a quarter of the variance). The translation and rotation blocks
    are floored separately (by their traces)."""
    use = n > 1
    if not np.any(use):
        return
    pooled = np.sum(cov_stat[use] * (n[use] - 1)[:, None, None] * n[use][:, None, None], axis=0) \
        / max(float(np.sum(n[use] - 1)), 1.0)   # per-approach covariance, pooled over the run
    for block in (slice(0, 3), slice(3, 6)):
        p_tr = float(np.trace(pooled[block, block]))
        for i, j in zip(*np.nonzero(use)):
            mine = float(np.trace(cov_stat[i, j][block, block]))
            floor = p_tr / n[i, j]
            if mine < floor:
                cov_stat[i, j][block, block] = pooled[block, block] / n[i, j]


# -- the identification (one evaluation; repeated on Monte Carlo draws) ------------------------
def _bidirectional(p: FloatArray, r: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean of the up and down poses at each target: (m, 3), (m, 3, 3)."""
    w = rotvec(r[:, 1] @ np.swapaxes(r[:, 0], -1, -2))
    return 0.5 * (p[:, 0] + p[:, 1]), rotation_from_rotvec(0.5 * w) @ r[:, 0]


def _reference(mean: RunMeans, p: FloatArray, r: FloatArray) -> tuple[FloatArray, FloatArray]:
    pb, rb = _bidirectional(p, r)
    if mean.ref is not None:
        return pb[mean.ref], rb[mean.ref]
    i, t = mean.ref_interp
    w = rotvec(rb[i + 1] @ rb[i].T)
    return (1 - t) * pb[i] + t * pb[i + 1], rotation_from_rotvec(t * w) @ rb[i]


def _slope(x: FloatArray, y: FloatArray) -> FloatArray:
    """Least-squares slope of y (m, ...) against x (m,)."""
    xc = x - x.mean()
    return np.tensordot(xc, y - y.mean(axis=0), axes=(0, 0)) / np.dot(xc, xc)


def _detrend(x: FloatArray, y: FloatArray) -> FloatArray:
    """Deviations of y (m, ...) from its least-squares line against x."""
    b = _slope(x, y)
    return y - y.mean(axis=0) - np.multiply.outer(x - x.mean(), b)


class _Session:
    """The inputs of the identification and one evaluation of it."""

    def __init__(self, machine: MachineDescription, means: dict[str, RunMeans],
                 component_prior: tuple[float, float] = (1e-6, math.radians(1.0 / 3600.0))) -> None:
        self.machine = machine
        self.means = means
        self.linear = [n for n, m in means.items() if not m.axis.rotary]
        self.rotary = [n for n, m in means.items() if m.axis.rotary]
        lin = {a.component: a.name for a in machine.linear_axes}
        self.frame_axes = (lin[0], lin[1])
        self.frame_measured = lin[0] in means and lin[1] in means
        #: machine direction (0 x, 1 y, 2 z) -> the run that would fix the frame's rotation about
        #: it, for the rotations this session leaves open: the X line fixes the rotation about y
        #: and z, the Y line (in the plane with X's) the rotation about x
        self.frame_open = {j: need for j, need in ((0, lin[1]), (1, lin[0]), (2, lin[0]))
                           if need not in means}
        self.nominal_ml = rotation_matrix(machine.lower_rotation)
        self.component_prior = component_prior
        #: rotary axis -> (location, normalised Jacobian, its pseudo-inverse) of the nominal fit;
        #: set after the nominal evaluation so that Monte Carlo draws take one linear step
        self.linearised: dict[str, tuple[FloatArray, FloatArray, FloatArray]] = {}
        #: rotary axis -> (rows, 6) uncertainty of the following axes' interpolated errors
        self.interp_u: dict[str, FloatArray] = {}
        self.loo: dict[str, FloatArray] = {}
        self.rng = np.random.default_rng(0)
        self.draw_interpolation = False
        #: workpiece-side rotary axis -> its reversal B at the reference (ISO 230-2, the
        #: positioning error approached from + minus from -) [rad] and its standard
        #: uncertainty (set after the nominal evaluation): where it stands during another
        #: rotary run depends on the side it was last approached from, which need not be the
        #: side of the linear runs
        self.play: dict[str, tuple[float, float]] = {}
        #: (run, other rotary axis) -> the side of its play the other axis rests at during the
        #: run (+1, -1; 0: not known), from the joint states' or the program's last directions
        self.rest = {(n, a.name): _rest_side([means[n]], machine.index(a.name))
                     for n in self.rotary for a in machine.rotary_axes if a.name != n}
        #: other rotary axis -> its side during the runs that define the frame (0: not known)
        self.rest_frame = {a.name: _rest_side([means[f] for f in self.frame_axes if f in means],
                                              machine.index(a.name)) for a in machine.rotary_axes}

    # -- frame and linear axes -------------------------------------------------------------------
    def _frame(self, slopes_l: dict[str, FloatArray]) -> FloatArray:
        """R_ML from the X and Y slopes in {L} (nominal where a run is missing)."""
        xa, ya = (self.machine.axis(n) for n in self.frame_axes)
        x = slopes_l.get(xa.name)
        y = slopes_l.get(ya.name)
        x = self.nominal_ml[0] if x is None else np.sign(xa.direction[0]) * x / np.linalg.norm(x)
        y = self.nominal_ml[1] if y is None else np.sign(ya.direction[1]) * y
        y = y - np.dot(y, x) * x
        y /= np.linalg.norm(y)
        return np.vstack([x, y, np.cross(x, y)])

    def evaluate(self, p: dict[str, FloatArray], r: dict[str, FloatArray], shift: FloatArray
                 ) -> dict[str, Any]:
        out: dict[str, Any] = {}
        dl: dict[str, tuple[FloatArray, FloatArray, FloatArray]] = {}
        slopes_l = {}
        for name in self.linear:
            mean = self.means[name]
            p0, r0 = _reference(mean, p[name], r[name])
            dp = p[name] - p0
            dw = rotvec(r[name] @ r0.T)
            dq = mean.targets - mean.axis.reference
            pb = 0.5 * (dp[:, 0] + dp[:, 1])
            slopes_l[name] = _slope(dq, pb)
            dl[name] = (dp, dw, dq)
        frame = self._frame(slopes_l)
        out['frame'] = frame
        tables: dict[str, ErrorTable] = {}
        slopes_m = {}
        for name in self.linear:
            mean = self.means[name]
            dp, dw, dq = dl[name]
            et = dp @ frame.T - dq[:, None, None] * mean.axis.direction
            er = dw @ frame.T
            e = np.concatenate([et, er], axis=-1)          # (m, 2, 6)
            out[f'{name}/up'], out[f'{name}/down'] = e[:, 0], e[:, 1]
            emean = 0.5 * (e[:, 0] + e[:, 1])
            out[f'{name}/mean'] = emean
            out[f'{name}/reversal'] = e[:, 0] - e[:, 1]
            out[f'{name}/deviation'] = _detrend(dq, emean[:, :3])
            slopes_m[name] = _slope(dq, emean[:, :3])
            c = mean.axis.component
            fig = np.zeros(6)
            for j in range(3):
                if j == c:
                    fig[j] = max(e[:, 0, j].max(), e[:, 1, j].max()) - min(e[:, 0, j].min(), e[:, 1, j].min())
                else:
                    fig[j] = np.ptp(out[f'{name}/deviation'][:, j])
                fig[3 + j] = np.ptp(emean[:, 3 + j])
            out[f'{name}/figure'] = fig
            tables[name] = ErrorTable(name, mean.targets, e[:, 0], e[:, 1])
        out['squareness'] = self._squareness(slopes_m)
        for name in self.rotary:
            self._rotary(name, p[name], r[name], frame, tables, shift, out)
        return out

    def _squareness(self, slopes: dict[str, FloatArray]) -> FloatArray:
        """EC0 of the y axis, EB0 and EA0 of the z axis (NaN where a run is missing)."""
        lin = {a.component: a for a in self.machine.linear_axes}
        out = np.full(3, np.nan)
        ex, ey, ez = np.eye(3)
        ya, za = lin[1], lin[2]
        if ya.name in slopes and self.frame_measured:
            out[0] = slopes[ya.name][0] / np.cross(ez, ya.direction)[0]
        if za.name in slopes and self.frame_measured:
            out[1] = slopes[za.name][0] / np.cross(ey, za.direction)[0]
            out[2] = slopes[za.name][1] / np.cross(ex, za.direction)[1]
        return out

    # -- rotary axes ---------------------------------------------------------------------------
    def _rotary(self, name: str, p: FloatArray, r: FloatArray, frame: FloatArray,
                tables: dict[str, ErrorTable], shift: FloatArray, out: dict[str, Any]) -> None:
        mean = self.means[name]
        axis = mean.axis
        m = mean.targets.size
        fp = self.machine.functional_point
        g = transform(r, p)                                   # (m, 2, 4, 4)
        g_ref = transform(*reversed(_reference(mean, p, r)))
        t_wl = transform(frame, fp + shift - frame @ _reference(mean, p, r)[0])
        meas = t_wl @ g @ inverse(g_ref) @ inverse(t_wl)
        meas = self._other_play(name, meas)
        q = mean.q.reshape(-1, mean.q.shape[-1])
        dirs = mean.dirs.reshape(-1, mean.dirs.shape[-1])
        ref = mean.ref
        point = axis_point(axis, fp)
        r_mw = MachineModel(self.machine).workpiece_rotation(q)
        perp = [j for j in range(3) if j != axis.component]
        meas = meas.reshape(-1, 4, 4)
        if not self.loo:
            self.loo = {n: _loo_rms(t) for n, t in tables.items()}
        if name not in self.interp_u:
            self.interp_u[name] = _interpolation_u(tables, self.loo, q, self.machine)
        u_interp = self.interp_u[name]
        if self.draw_interpolation:   # a Monte Carlo draw: tables bent between their targets
            tables = {n: t.with_bumps(self.rng.standard_normal((t.positions.size - 1, 6))
                                      * (np.sqrt(2.0) * self.loo[n])) for n, t in tables.items()}
        known = MachineModel(self.machine, tables)
        left, right, work_side = known.parts(q, dirs, name)
        rows = q.shape[0]
        ref_rows = [2 * ref, 2 * ref + 1]

        def residual(lam: FloatArray) -> FloatArray:
            pos, tilt = np.zeros(3), np.zeros(3)
            pos[perp], tilt[perp] = lam[:2], lam[2:]
            model = MachineModel(self.machine, {}, {name: RotaryLocation(pos, tilt)})
            a = model.axis_transform(name, q[:, mean.k])
            pred = left @ (inverse(a) if work_side else a) @ right
            pr = pred[ref_rows]
            w = rotvec(pr[1, :3, :3] @ pr[0, :3, :3].T)
            pred_ref = transform(rotation_from_rotvec(0.5 * w) @ pr[0, :3, :3],
                                 0.5 * (pr[0, :3, 3] + pr[1, :3, 3]))
            pred = pred @ inverse(pred_ref)[None]
            e = meas @ inverse(pred)
            at = np.broadcast_to(point, (rows, 3)) if work_side else apply(pred, point)
            v = apply(e, at) - at
            dw = rotvec(e[:, :3, :3])
            return np.concatenate([np.einsum('nij,nj->ni', r_mw, v),
                                   np.einsum('nij,nj->ni', r_mw, dw)], axis=1)

        sigma = np.sqrt(self._rotary_sigma(mean)[None, :] ** 2 + u_interp ** 2)
        linear = self.linearised.get(name)
        if linear is not None:
            # a Monte Carlo draw: one Gauss-Newton step from the nominal fit with its Jacobian,
            # the following axes' interpolation error drawn too
            lam0, jac, pinv = linear
            res0 = residual(lam0)
            lam = lam0 - pinv @ (res0 / sigma).ravel()
            res = res0 + (jac @ (lam - lam0)).reshape(res0.shape) * sigma
        else:
            lam = np.zeros(4)
            step = 1e-6
            jac = np.zeros((rows * 6, 4))
            for _ in range(3):
                flat = (residual(lam) / sigma).ravel()
                for col in range(4):
                    d = lam.copy()
                    d[col] += step
                    jac[:, col] = ((residual(d) / sigma).ravel() - flat) / step
                delta = np.linalg.lstsq(jac, -flat, rcond=None)[0]
                lam = lam + delta
                if np.max(np.abs(delta)) < 1e-11:
                    break
            res = residual(lam)
            out[f'{name}/leak'] = self._leak(jac, (res / sigma).ravel(), mean.targets, sigma)
            out[f'{name}/jacobian'] = jac * sigma.reshape(-1, 1)
            out[f'{name}/linear'] = (lam.copy(), jac.copy(), np.linalg.pinv(jac))
        out[f'{name}/chi2'] = float(np.sum((res / sigma) ** 2) / max(res.size - 4, 1))
        res = res.reshape(m, 2, 6)
        res = res - 0.5 * (res[ref, 0] + res[ref, 1])
        out[f'{name}/location'] = lam
        out[f'{name}/up'], out[f'{name}/down'] = res[:, 0], res[:, 1]
        emean = 0.5 * (res[:, 0] + res[:, 1])
        out[f'{name}/mean'] = emean
        out[f'{name}/reversal'] = res[:, 0] - res[:, 1]
        out[f'{name}/deviation'] = np.full((m, 3), np.nan)
        c = axis.component
        fig = np.array([np.ptp(emean[:, j]) for j in range(6)])
        fig[3 + c] = max(res[:, 0, 3 + c].max(), res[:, 1, 3 + c].max()) - \
            min(res[:, 0, 3 + c].min(), res[:, 1, 3 + c].min())
        out[f'{name}/figure'] = fig

    def play_turn(self, name: str, other: str) -> tuple[float, float]:
        """How far the other workpiece-side rotary axis ``other`` stands turned during the run
        of ``name`` against where it stood while the frame was measured: (known part, half
        width of what is not known) [rad]. An axis rests on the side of its play it was last
        approached from, B / 2 from the middle (B its signed reversal, ISO 230-2): known where
        the joint states (or the program) give its last direction during both; where only the
        run's side is known, the frame's side is anywhere within the play (centre B s / 2, ±
        B / 2); where neither is, ± B."""
        reversal = self.play[other][0]
        s_run = self.rest.get((name, other), 0)
        s_frame = self.rest_frame.get(other, 0)
        if s_run and s_frame:
            return 0.5 * reversal * (s_run - s_frame), 0.0
        if s_run:
            return 0.5 * reversal * s_run, 0.5 * abs(reversal)
        return 0.0, abs(reversal)

    def _other_play(self, name: str, meas: FloatArray) -> FloatArray:
        """The measured motion (..., 4, 4) with each other workpiece-side rotary axis' play
        taken out (:meth:`play_turn`): the table turned about that axis' line by the known part
        (its reversal B drawn within its uncertainty on a Monte Carlo draw) and, on a draw, a
        uniform part of the rest. Tool-side axes carried after the linear axes cancel in the
        relative motion."""
        for other, (reversal, u_reversal) in self.play.items():
            if other == name:
                continue
            known, width = self.play_turn(name, other)
            angle = known
            if self.draw_interpolation:
                if known and reversal:
                    angle *= 1.0 + u_reversal / abs(reversal) * self.rng.standard_normal()
                angle += self.rng.uniform(-1.0, 1.0) * width
            if angle == 0.0:
                continue
            a = self.machine.axis(other)
            turn = transform(rotation_from_rotvec(-angle * a.direction), np.zeros(3))
            about = transform(np.eye(3), a.pivot)
            t = about @ turn @ inverse(about)
            meas = t @ meas @ inverse(t)
        return meas

    def _leak(self, jac: FloatArray, res: FloatArray, targets: FloatArray, sigma: FloatArray
              ) -> FloatArray:
        """Covariance (4, 4) of the location errors from component errors that the fit cannot
        tell from them over the tested span. Component errors are modelled as harmonics 2..4
        of the angle in each of the six components, each of a full-turn RMS of the prior size
        (``component_prior``). Each component's prior is scaled up where the fit's residual in
        that component shows more than the noise and the prior explain: the residual measures
        the size of the component errors in each direction, and only the radial and tilt ones
        can pass for location (a large angular positioning error says nothing about them).

        jac : (rows*6, 4) Jacobian of the normalised residual; res : (rows*6,) normalised
        residual; targets : (m,) angles [rad]; sigma : (rows, 6) the normalisation [m, rad]
        """
        rows = res.size // 6
        theta = np.repeat(targets, 2)                     # row order: target, direction
        prior = self.component_prior
        basis, var, group = [], [], []
        for j in range(6):
            for order in (2, 3, 4):
                for f in (np.cos, np.sin):
                    b = np.zeros((rows, 6))
                    b[:, j] = f(order * theta) / sigma[:, j]
                    basis.append(b.ravel())
                    var.append(prior[0 if j < 3 else 1] ** 2 / 3.0)
                    group.append(j)
        b = np.array(basis).T                             # (rows*6, n_basis), normalised units
        var = np.array(var)
        group = np.array(group)
        try:
            inv = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            return np.full((4, 4), np.inf)
        leak = inv @ jac.T @ b                            # (4, n_basis): location per coefficient
        visible = b - jac @ leak
        # the residual's share of the noise in each component: its dof spread evenly
        dof = max(res.size - 4, 1) / 6.0
        r2 = np.sum(res.reshape(rows, 6) ** 2, axis=0)
        scale = np.ones(var.size)
        for j in range(6):
            mine = group == j
            expected = float(np.sum(var[mine] * np.sum(visible[:, mine] ** 2, axis=0)))
            excess = max(float(r2[j]) - dof, 0.0)
            scale[mine] = max(1.0, excess / max(expected, 1e-300))
        return (leak * (scale * var)) @ leak.T

    @staticmethod
    def _rotary_sigma(mean: RunMeans) -> FloatArray:
        """Typical standard deviation of a residual's translation and rotation components."""
        cov = mean.cov_mmd + mean.cov_stat
        ref = cov[mean.ref].mean(axis=0)
        t = float(np.sqrt(np.mean([np.trace(c[:3, :3]) + np.trace(ref[:3, :3]) for c in cov.reshape(-1, 6, 6)]) / 3))
        w = float(np.sqrt(np.mean([np.trace(c[3:, 3:]) + np.trace(ref[3:, 3:]) for c in cov.reshape(-1, 6, 6)]) / 3))
        return np.array([max(t, 1e-9)] * 3 + [max(w, 1e-9)] * 3)


def _loo_rms(table: ErrorTable) -> FloatArray:
    """RMS (6,) of a table's leave-one-out prediction errors at its interior targets: how far
    its interpolation between targets may be off (estimated at twice the target spacing, so on
    the safe side)."""
    pos = table.positions
    if pos.size < 4:
        return np.zeros(6)
    mean = 0.5 * (table.up + table.down)
    errors = []
    for i in range(1, pos.size - 1):
        keep = np.arange(pos.size) != i
        loo = ErrorTable(table.axis, pos[keep], mean[keep], mean[keep])
        errors.append(loo.at(pos[i:i + 1])[0] - mean[i])
    return np.sqrt(np.mean(np.square(errors), axis=0))


def _interpolation_u(tables: dict[str, ErrorTable], loo: dict[str, FloatArray], q: FloatArray,
                     machine: MachineDescription) -> FloatArray:
    """Uncertainty (rows, 6) of the linear axes' errors interpolated between their targets at
    the axis values q (rows, n_axes) of a rotary run: zero at a target, rising as sin(pi t)
    across an interval (t from 0 to 1) to sqrt 2 times the leave-one-out RMS halfway (the
    shape and size the Monte Carlo draws bend the tables by), added in quadrature over the
    axes."""
    out = np.zeros((q.shape[0], 6))
    for name, table in tables.items():
        pos = table.positions
        if pos.size < 2:
            continue
        x = np.clip(q[:, machine.index(name)], pos[0], pos[-1])
        i = np.clip(np.searchsorted(pos, x, side='right') - 1, 0, pos.size - 2)
        t = (x - pos[i]) / (pos[i + 1] - pos[i])
        bump = np.sin(np.pi * t)[:, None] * (math.sqrt(2.0) * loo[name])[None, :]
        out = np.sqrt(out ** 2 + bump ** 2)
    return out


def _rest_side(means: list[RunMeans], k: int) -> int:
    """The side of its play axis ``k`` rests at through the runs ``means`` (+1, -1: the
    direction of its last move, the same at every approach; 0: not known or not the same)."""
    sides = {int(v) for m in means for v in np.ravel(m.dirs[..., k])}
    return sides.pop() if len(sides) == 1 and 0 not in sides else 0


def _reversal_at_reference(mean: RunMeans, base: dict[str, Any]) -> tuple[float, float]:
    """A rotary axis' signed reversal B at its reference angle (its angular positioning error
    approached from + minus from -, in the machine frame) [rad], and its standard uncertainty
    from the covariance of the two mean poses (the MMD's and the cycles' scatter)."""
    c = mean.axis.component
    value = float(base[f'{mean.axis.name}/reversal'][mean.ref, 3 + c])
    d = mean.axis.direction
    var = sum(float(d @ (mean.cov_mmd[mean.ref, j] + mean.cov_stat[mean.ref, j])[3:, 3:] @ d)
              for j in range(2))
    return value, math.sqrt(max(var, 0.0))


# -- Monte Carlo -------------------------------------------------------------------------------
def _draws(session: _Session, base: dict[str, Any], draws: int, rng: np.random.Generator,
           shift_sigma: float, progress: Callable[[int], None] | None
           ) -> tuple[dict[str, FloatArray], dict[str, FloatArray], dict[str, FloatArray]]:
    """Standard deviation of every numeric output over perturbed inputs: (everything, the MMD's
    part, the part of the scatter between cycles). Each draw evaluates three times with shared
    random numbers: all perturbations (the MMD's covariance, the scatter between cycles, the
    functional point's uncertainty, the interpolation between targets), the MMD's alone, the
    scatter alone."""
    keys = [k for k, v in base.items() if isinstance(v, np.ndarray) and k != 'frame'
            and not k.endswith(('/jacobian', '/leak'))]
    acc = [{k: [] for k in keys} for _ in range(3)]
    roots = {}
    for name, mean in session.means.items():
        roots[name] = tuple(_sqrtm(c) for c in (mean.cov_mmd, mean.cov_stat))
    for d in range(draws):
        parts = {}
        for name, mean in session.means.items():
            shape = mean.p.shape[:2] + (6,)
            # the MMD's error at a pose: independent between targets, plus a trend along the run
            # (it follows the bar lengths, which change smoothly along the run)
            trend = _trend(mean.targets)[:, None, None] * rng.standard_normal(6)[None, None, :]
            xi = MMD_INDEPENDENT * rng.standard_normal(shape) + MMD_TREND * trend
            z_mmd = np.einsum('mdij,mdj->mdi', roots[name][0], xi)
            z_stat = np.einsum('mdij,mdj->mdi', roots[name][1], rng.standard_normal(shape))
            parts[name] = (z_mmd + z_stat, z_mmd, z_stat)
        shift = rng.normal(0.0, shift_sigma, 3) if shift_sigma > 0 else np.zeros(3)
        for which in range(3):
            session.draw_interpolation = which == 0
            p = {n: m.p + parts[n][which][..., :3] for n, m in session.means.items()}
            r = {n: rotation_from_rotvec(parts[n][which][..., 3:]) @ m.r for n, m in session.means.items()}
            out = session.evaluate(p, r, shift if which == 0 else np.zeros(3))
            for k in keys:
                acc[which][k].append(np.asarray(out[k], dtype=np.float64))
        if progress:
            progress(d + 1)
    session.draw_interpolation = False
    std = lambda a: {k: np.std(np.array(v), axis=0, ddof=1) for k, v in a.items()}  # noqa: E731
    return std(acc[0]), std(acc[1]), std(acc[2])


#: The MMD's pose covariance is drawn twice: independent between targets, and again as a
#: linear trend along the run (the covariance of one pose says nothing about how the errors of
#: neighbouring poses go together; both extremes are taken, on the safe side)
MMD_INDEPENDENT = 1.0
MMD_TREND = 1.0


def _trend(targets: FloatArray) -> FloatArray:
    """-1 … +1 along a run's targets."""
    span = float(targets[-1] - targets[0])
    return (2.0 * (targets - targets[0]) / span - 1.0) if span > 0 else np.zeros_like(targets)


def _sqrtm(cov: FloatArray) -> FloatArray:
    """The symmetric square root of stacked covariance matrices (..., 6, 6) (positive
    semi-definite). Symmetric, so that one standard normal vector drawn for several poses
    (the trend along a run) moves each of them the same way where their covariances agree: an
    eigenvector root's column order and signs are arbitrary per pose, and would turn a
    correlated draw into an independent one."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    return (vecs * np.sqrt(np.clip(vals, 0.0, None))[..., None, :]) @ np.swapaxes(vecs, -1, -2)


# -- results -----------------------------------------------------------------------------------
KINDS_LINEAR = {True: 'positioning', False: 'straightness'}


def _motion_kind(axis: MachineAxis, j: int) -> str:
    if not axis.rotary:
        return KINDS_LINEAR[j == axis.component] if j < 3 else 'angular'
    if j < 3:
        return 'axial' if j == axis.component else 'radial'
    return 'positioning' if j - 3 == axis.component else 'tilt'


def _iso230(mean: RunMeans, frame: FloatArray, out: dict[str, Any], session: _Session) -> Any:
    """ISO 230-2 of the positioning component from every approach (linear axes)."""
    axis = mean.axis
    p0, _ = _reference(mean, mean.p, mean.r)
    dq = mean.targets - axis.reference
    dev = (mean.cycles_p - p0) @ frame.T - dq[:, None, None, None] * axis.direction
    sign = np.sign(axis.direction[axis.component])
    d = dev[..., axis.component] * sign
    return evaluate(mean.targets, d[:, 0], d[:, 1], axis='x', instrument=f'{axis.name} positioning')


def identify(runs: list[AxisRun], machine: MachineDescription, *,
             options: IdentifyOptions = IdentifyOptions(), instrument: str = 'mmd',
             model_text: str = '', logs: list[str] | None = None,
             progress: Callable[[str, int, int], None] | None = None) -> MachineResult:
    """All errors a session determines, with their uncertainty (module docstring)."""
    started = time.perf_counter()
    _check_options(options)
    if not runs:
        raise MachineAnalysisError('no axis runs found in the logs')
    seen: dict[str, AxisRun] = {}

    def where(r: AxisRun) -> str:
        spans = [a.span_s for a in r.approaches] or [(math.nan, math.nan)]
        return f'{r.log} {min(s[0] for s in spans):.1f}–{max(s[1] for s in spans):.1f} s'
    for run in runs:
        if run.axis in seen:
            raise MachineAnalysisError(
                f'the {run.axis} axis was run twice ({where(seen[run.axis])} and {where(run)}): '
                'give one run per axis (runs with the same targets one after the other, no other '
                'axis moving between them, count as one, their cycles added)')
        seen[run.axis] = run
    means = {run.axis: aggregate(run, machine) for run in runs}
    if options.mmd_bound_m > 0 or options.mmd_bound_rad > 0:
        bound = np.diag([options.mmd_bound_m ** 2 / 3.0] * 3 + [options.mmd_bound_rad ** 2 / 3.0] * 3)
        for mean in means.values():
            mean.cov_mmd = mean.cov_mmd + bound
    session = _Session(machine, means, (options.component_m, options.component_rad))
    zero = np.zeros(3)
    p0, r0 = {n: m.p for n, m in means.items()}, {n: m.r for n, m in means.items()}
    base = session.evaluate(p0, r0, zero)
    for n in session.rotary:
        a = session.means[n]
        if a.axis.side == 'workpiece' and a.ref is not None:
            session.play[n] = _reversal_at_reference(a, base)
    if any(session.play_turn(n, o)[0] for n in session.rotary for o in session.play if o != n):
        base = session.evaluate(p0, r0, zero)     # with the other axes' known play taken out
        for n in session.play:
            session.play[n] = _reversal_at_reference(session.means[n], base)
    session.linearised = {n: base[f'{n}/linear'] for n in session.rotary}
    rng = np.random.default_rng(options.seed)
    sigma_shift = machine.upper_offset_uncertainty

    def tick(label: str) -> Callable[[int], None] | None:
        return None if progress is None else (lambda done: progress(label, done, options.draws))

    t1 = time.perf_counter()
    u_total, u_mmd, u_stat = _draws(session, base, options.draws, rng, sigma_shift, tick('uncertainty'))
    t2 = time.perf_counter()
    result = _build(machine, session, base, u_total, u_mmd, u_stat, options, instrument, model_text,
                    logs or sorted({r.log for r in runs}))
    result.seconds = {'evaluate': t1 - started, 'monte_carlo': t2 - t1,
                      'total': time.perf_counter() - started}
    return result


def _check_options(options: IdentifyOptions) -> None:
    """Refuse options the identification cannot use, naming the option and its value."""
    if not (isinstance(options.draws, (int, np.integer)) and options.draws >= 2):
        raise MachineAnalysisError(
            f'draws must be an integer >= 2, got {options.draws!r}: every uncertainty is the '
            'spread (standard deviation) of the Monte Carlo draws, which needs at least two')
    checks = (('limit_m', 'm', False), ('limit_rad', 'rad', False),
              ('mmd_bound_m', 'm', True), ('mmd_bound_rad', 'rad', True),
              ('component_m', 'm', True), ('component_rad', 'rad', True))
    for key, unit, zero in checks:
        v = float(getattr(options, key))
        if not (math.isfinite(v) and (v >= 0 if zero else v > 0)):
            raise MachineAnalysisError(f'{key} must be a finite number {">=" if zero else ">"} 0, '
                                       f'got {v:g} {unit}')


def _coverage(u: Any, u_stat: Any, n: int) -> FloatArray:
    """Coverage factor(s) for about 95 %: Student's t for the Welch-Satterthwaite degrees of
    freedom of u, its part from the scatter between n cycles (``u_stat``) having n - 1 and the
    rest (the MMD's covariance and the other type-B parts) infinitely many; at least 2."""
    u = np.asarray(u, dtype=np.float64)
    u_stat2 = np.minimum(np.asarray(u_stat, dtype=np.float64) ** 2, u ** 2)
    if n < 2:
        return np.full(u.shape, COVERAGE_K)
    with np.errstate(divide='ignore', invalid='ignore'):
        nu = np.where(u_stat2 > 0, u ** 4 / (u_stat2 ** 2 / (n - 1)), np.inf)
    nu = np.where(np.isfinite(nu), np.maximum(nu, n - 1), 1e9)
    return np.maximum(COVERAGE_K, student_t.ppf(0.975, nu))


def _value(name: str, v: float, u: float, um: float, unit: str, options: IdentifyOptions,
           note_missing: str | None = None, n: int = 0, ustat: float = 0.0) -> Value:
    if note_missing is not None or not math.isfinite(v):
        return Value(name, math.nan, math.nan, math.nan, unit, False, note_missing or 'not measured')
    limit = options.limit_m if unit == 'm' else options.limit_rad
    ok = bool(u <= limit)
    note = '' if ok else (f'uncertainty {u / (1e-6 if unit == "m" else math.radians(1 / 3600)):.2g}'
                          f'{" µm" if unit == "m" else "″"} exceeds the limit: the run does not fix it')
    return Value(name, float(v), float(u), float(um), unit, ok, note, float(_coverage(u, ustat, n)))


def _build(machine: MachineDescription, session: _Session, base: dict[str, Any],
           u: dict[str, FloatArray], um: dict[str, FloatArray], us: dict[str, FloatArray],
           options: IdentifyOptions, instrument: str, model_text: str, logs: list[str]) -> MachineResult:
    notes: list[str] = []
    us_ = us
    lin = {a.component: a for a in machine.linear_axes}
    names = [f'EC0{lin[1].name}', f'EB0{lin[2].name}', f'EA0{lin[2].name}']
    squareness = []
    for i, name in enumerate(names):
        missing = None
        if not session.frame_measured:
            missing = f'needs the {lin[0].name} and {lin[1].name} runs in one setup'
        elif i > 0 and lin[2].name not in session.means:
            missing = f'needs the {lin[2].name} run in the same setup as {lin[0].name} and {lin[1].name}'
        cycles = min([int(m.n.min()) for m in session.means.values() if not m.axis.rotary] or [0])
        squareness.append(_value(name, base['squareness'][i], u['squareness'][i], um['squareness'][i],
                                 'rad', options, missing, cycles, us['squareness'][i]))
    if not session.frame_measured:
        notes.append(f'machine frame: the {lin[0].name} or {lin[1].name} run is missing, so the '
                     'frame is {L} as described (its setup misalignment on the table remains '
                     'in every direction-dependent result)')
    axes: dict[str, AxisResult] = {}
    for name, mean in session.means.items():
        axis = mean.axis
        motions = []
        extra = np.zeros((mean.targets.size, 2, 6))
        leak = np.zeros((4, 4))
        if axis.rotary:
            # component errors the location fit took for location over a partial turn
            leak = base[f'{name}/leak']
            jac = base[f'{name}/jacobian']
            extra = np.sqrt(np.einsum('ij,jk,ik->i', jac, leak, jac)).reshape(mean.targets.size, 2, 6)
        for j in range(6):
            unit = 'm' if j < 3 else 'rad'
            tname = f'E{_XYZ[j % 3] if j < 3 else _ABC[j % 3]}{name}'
            kind = _motion_kind(axis, j)

            def col(key: str) -> FloatArray:
                return np.asarray(base[f'{name}/{key}'])[:, j]

            def ucol(key: str, add: FloatArray | None = None) -> FloatArray:
                val = np.asarray(u[f'{name}/{key}'])[:, j]
                return val if add is None else np.sqrt(val ** 2 + add ** 2)
            ex_up, ex_down = extra[:, 0, j], extra[:, 1, j]
            ex_mean = 0.5 * (ex_up + ex_down)
            n_cyc = int(mean.n.min())
            fig = _value(f'{tname} figure', base[f'{name}/figure'][j], u[f'{name}/figure'][j],
                         um[f'{name}/figure'][j], unit, options, None, n_cyc, us_[f'{name}/figure'][j])
            fig.determined = True
            fig.note = ''
            deviation = u_dev = None
            if kind == 'straightness':
                deviation = col('deviation')
                u_dev = ucol('deviation')
            iso = None
            if kind == 'positioning' and not axis.rotary:
                iso = _iso230(mean, base['frame'], base, session)
            elif kind == 'positioning':
                sign = np.sign(axis.direction[axis.component])
                up_dev, down_dev = _rotary_cycles(mean, j, base, session, sign)
                iso = evaluate(mean.targets, up_dev, down_dev, axis='psi',
                               instrument=f'{axis.name} positioning')
            unc = {'up': ucol('up', ex_up), 'down': ucol('down', ex_down), 'mean': ucol('mean', ex_mean),
                   'reversal': ucol('reversal', np.hypot(ex_up, ex_down))}
            ks = {key: _coverage(val, np.asarray(us_[f'{name}/{key}'])[:, j], n_cyc) for key, val in unc.items()}
            motions.append(ErrorMotion(
                tname, name, kind, unit, mean.targets, col('up'), col('down'), col('mean'),
                col('reversal'), unc['up'], unc['down'], unc['mean'], unc['reversal'],
                np.asarray(um[f'{name}/mean'])[:, j], fig, deviation, u_dev, iso, True,
                ks['up'], ks['down'], ks['mean'], ks['reversal'],
                *(np.asarray(um[f'{name}/{key}'])[:, j] for key in ('up', 'down', 'reversal'))))
        location = []
        if axis.rotary:
            perp = [j for j in range(3) if j != axis.component]
            lam, uml = base[f'{name}/location'], um[f'{name}/location']
            ul = np.sqrt(u[f'{name}/location'] ** 2 + np.diag(leak))
            n_cyc = int(mean.n.min())
            usl = us_[f'{name}/location']
            for i, j in enumerate(perp):
                location.append(_value(f'E{_XYZ[j]}0{name}', lam[i], ul[i], uml[i], 'm', options, None,
                                       n_cyc, usl[i]))
            for i, j in enumerate(perp):
                location.append(_value(f'E{_ABC[j]}0{name}', lam[2 + i], ul[2 + i], uml[2 + i], 'rad',
                                       options, None, n_cyc, usl[2 + i]))
            for i, v in enumerate(location):
                v.u_turn = float(math.sqrt(leak[i, i]))
            _flag_open_frame(location, axis, perp, session)
        axes[name] = AxisResult(name, axis.rotary, mean.run.log, mean.run.source, mean.targets,
                                int(mean.n.min()), mean.run.following, motions, location,
                                base[f'{name}/chi2'] if axis.rotary else 1.0)
    for a in machine.axes:
        if a.name not in axes:
            notes.append(f'{a.name}: no run in this session: none of its errors is determined')
    return MachineResult(machine, axes, squareness, base['frame'],
                         'measured (X run and Y run)' if session.frame_measured else 'nominal',
                         instrument, model_text, logs, options.draws, notes, play=_play_notes(session))


#: A pivot at least this far [m] off the functional point across an open rotation of the frame
#: moves with that rotation (a setup misalignment of a few degrees moves it by a few % of this)
LEVER_M = 1e-6


def _flag_open_frame(location: list[Value], axis: MachineAxis, perp: list[int],
                     session: _Session) -> None:
    """Flag, as not determined, the location errors (EX0C, EY0C, EA0C, EB0C order) of a rotary
    axis that depend on a rotation of the machine frame the session does not fix
    (:attr:`_Session.frame_open`; it is then {L}'s setup misalignment, not the machine's): the
    tilt about that direction, and the position across it. The frame turns {L} into machine axes
    about the functional point, where the motion is measured; turned by ε about e, it moves the
    axis line at its pivot by ε e × (pivot − functional point): with the X run alone, the C
    table's EY0C moves with EA0C, 300 mm below the functional point."""
    arm = axis.pivot - session.machine.functional_point
    for a, need in session.frame_open.items():
        shift = np.cross(np.eye(3)[a], arm)
        for i, j in enumerate(perp):
            if j == a:
                notes = [(location[2 + i], 'orientation relative to {L}, not to the machine\'s '
                          f'axes (no frame: needs the {need} run)')]
            else:
                notes = []
            if abs(shift[j]) >= LEVER_M:
                notes.append((location[i], f'moves {abs(shift[j]) * 1e3:.3g} µm per mrad of the '
                              f'frame\'s rotation about {"xyz"[a]} (no frame: needs the {need} '
                              f'run), {abs(shift[j]) * 1e3:.3g} mm from the functional point'))
            for v, note in notes:
                v.note = note if v.determined else f'{v.note}; {note}'
                v.determined = False


def _play_notes(session: _Session) -> list[str]:
    """What the report says of the other table axes' play during each rotary run."""
    sec = math.radians(1.0 / 3600.0)
    side = {1: '+', -1: '-', 0: 'unknown'}
    out = []
    for name in session.rotary:
        for other, (reversal, u_rev) in session.play.items():
            if other == name:
                continue
            known, width = session.play_turn(name, other)
            out.append(
                f'{name} run: {other} rested on the {side[session.rest.get((name, other), 0)]} side of its '
                f'play, on the {side[session.rest_frame.get(other, 0)]} side during the frame\'s runs '
                f'({other}\'s reversal B {reversal / sec:.2f}″ ± {u_rev / sec:.2f}″ at its reference): '
                f'{known / sec:.2f}″ about its line taken out, ±{width / sec:.2f}″ not known '
                '(in the uncertainty)')
    return out


def _rotary_cycles(mean: RunMeans, j: int, base: dict[str, Any], session: _Session,
                   sign: float) -> tuple[FloatArray, FloatArray]:
    """Per-approach angular positioning deviations of a rotary run: the fitted positioning
    error of the means plus each approach's rotation about the axis relative to its mean."""
    c = mean.axis.component
    w = rotvec(mean.cycles_r @ np.swapaxes(mean.r, -1, -2)[:, :, None])   # (m, 2, c, 3) in {L}
    about = (w @ base['frame'].T)[..., c] * sign
    centre = np.stack([base[f'{mean.axis.name}/up'][:, 3 + c], base[f'{mean.axis.name}/down'][:, 3 + c]], axis=1)
    dev = centre[..., None] * sign + about
    return dev[:, 0], dev[:, 1]
