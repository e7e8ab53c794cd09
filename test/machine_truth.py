"""Test-side truth of a simulated machine session, by the definitions of msg_docs/machine.md,
computed from the twin's own kinematics (never from mmd_ros.machine), and helpers that turn a
twin machine into exact approaches (no MMD in between) for known-answer tests."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from mmd_ros.machine.session import Approach, AxisRun
from mmd_ros.twin.machine import (
    Harmonics, LinearAxisTruth, MachineTruth, RotaryAxisTruth, SmoothError, TwinMachine,
)

UM = 1e-6
ARCSEC = math.radians(1 / 3600)


def zero_truth(machine) -> MachineTruth:
    """A machine without errors (reversal take-up kept tiny)."""
    lin = {a.name: LinearAxisTruth((SmoothError.zero(),) * 3, (SmoothError.zero(),) * 3, 0.0, 0.0, 1e-9)
           for a in machine.linear_axes}
    rot = {a.name: RotaryAxisTruth(np.zeros(3), np.zeros(3), SmoothError.zero(), 0.0, 0.0, 1e-9,
                                   (Harmonics(),) * 3, (Harmonics(),) * 3) for a in machine.rotary_axes}
    names = {a.component: a.name for a in machine.linear_axes}
    return MachineTruth(lin, rot, {f'EC0{names[1]}': 0.0, f'EB0{names[2]}': 0.0, f'EA0{names[2]}': 0.0})


def exact_runs(twin: TwinMachine, plans, cycles: int = 2, sigma: float = 0.0,
               rng: np.random.Generator | None = None,
               resting: dict[str, dict[str, float]] | None = None,
               known_rest: bool = False) -> list[AxisRun]:
    """The approaches of the ISO cycles of ``plans`` with the twin's true poses of {U} in {L}
    (optionally with pose noise ``sigma`` [m, rad] and that covariance). ``resting``: per run
    axis, the play state (-1 … 1) of axes that stand still during it (default 0); with
    ``known_rest`` their last direction of motion is the sign of that state (as joint states
    would say; else it is not known)."""
    m = twin.machine
    out = []
    for plan in plans:
        still = (resting or {}).get(plan.axis, {})
        k = m.index(plan.axis)
        n = plan.targets.size
        q = np.tile(m.reference, (n, 1))
        q[:, k] = plan.targets
        slope = np.zeros_like(q)
        if plan.follow:   # followers move with the sign of their slope against the rotary axis
            q = twin.follow(q)
            ahead = q.copy()
            ahead[:, k] += 1e-4
            slope = twin.follow(ahead) - q
        apps = []
        for d in (1, -1):
            last = np.where(np.abs(slope) > 1e-12, np.sign(slope) * d, 0).astype(np.int64)
            last[:, k] = d
            play = last.astype(float)
            for other, state in still.items():
                play[:, m.index(other)] = state
                if known_rest:   # the joint states say which side it was last moved to
                    last[:, m.index(other)] = int(np.sign(state))
            poses = twin.mmd_poses(q, play)
            for c in range(cycles):
                for i in range(n):
                    pose = poses[i] if sigma == 0 else poses[i] + rng.normal(0.0, sigma, 6)
                    cov = np.eye(6) * max(sigma, 1e-9) ** 2
                    apps.append(Approach(plan.axis, i, d, c, q[i].copy(), last[i].copy(), pose, cov,
                                         10, (0.0, 0.0)))
        out.append(AxisRun(plan.axis, m.axis(plan.axis).rotary, 'twin', plan.targets, apps))
    return out


def _plays(machine, k: int, d: int, n: int) -> np.ndarray:
    play = np.zeros((n, len(machine.axes)))
    play[:, k] = d
    return play


def _slope(x, y):
    xc = x - x.mean()
    return (xc @ (y - y.mean(0))) / (xc @ xc)


def session_truth(twin: TwinMachine, plans) -> dict:
    """The ISO quantities of the twin's true machine for a session's runs, by definition:
    linear error motions (machine frame from the X and Y lines, relative to each run's
    reference), squareness (slopes), location errors (the twin's axis lines), rotary component
    errors (a twin with only that axis' component and positioning errors, at the axis point,
    relative to the reference angle). Arrays are (targets, 2 directions, 6)."""
    m = twin.machine
    plans = {p.axis: p for p in plans}
    out: dict = {'linear': {}, 'rotary': {}, 'location': {}, 'squareness': {}}
    raw = {}
    for name, plan in plans.items():
        a = m.axis(name)
        if a.rotary:
            continue
        k = m.index(name)
        q = np.tile(m.reference, (plan.targets.size, 1))
        q[:, k] = plan.targets
        e = np.stack([twin.error_screw(q, _plays(m, k, d, len(q))) for d in (1, -1)], axis=1)
        dq = plan.targets - a.reference
        bm = e.mean(axis=1)
        i = np.flatnonzero(np.abs(dq) < 1e-9)
        if i.size:
            ref = bm[i[0]]
        else:
            j = int(np.searchsorted(dq, 0.0)) - 1
            t = -dq[j] / (dq[j + 1] - dq[j])
            ref = (1 - t) * bm[j] + t * bm[j + 1]
        raw[name] = (dq, e - ref, a)
    lin = {a.component: a.name for a in m.linear_axes}
    slopes = {n: _slope(dq, dq[:, None] * a.direction + e.mean(axis=1)[:, :3]) for n, (dq, e, a) in raw.items()}
    x = slopes[lin[0]] / np.linalg.norm(slopes[lin[0]]) * np.sign(m.axis(lin[0]).direction[0])
    y = slopes[lin[1]] * np.sign(m.axis(lin[1]).direction[1])
    y = y - (y @ x) * x
    y /= np.linalg.norm(y)
    frame = np.vstack([x, y, np.cross(x, y)])
    out['frame'] = frame
    for name, (dq, e, a) in raw.items():
        et = (dq[:, None, None] * a.direction + e[..., :3]) @ frame.T - dq[:, None, None] * a.direction
        out['linear'][name] = np.concatenate([et, e[..., 3:] @ frame.T], axis=-1)
    sm = {n: _slope(raw[n][0], out['linear'][n].mean(axis=1)[:, :3]) for n in raw}
    ya, za = m.axis(lin[1]), m.axis(lin[2])
    ex, ey, ez = np.eye(3)
    if ya.name in sm:
        out['squareness'][f'EC0{ya.name}'] = sm[ya.name][0] / np.cross(ez, ya.direction)[0]
    if za.name in sm:
        out['squareness'][f'EB0{za.name}'] = sm[za.name][0] / np.cross(ey, za.direction)[0]
        out['squareness'][f'EA0{za.name}'] = sm[za.name][1] / np.cross(ex, za.direction)[1]
    for name, plan in plans.items():
        a = m.axis(name)
        if not a.rotary:
            continue
        k = m.index(name)
        t = twin.truth.rotary[name]
        perp = [j for j in range(3) if j != a.component]
        # the twin's line in the machine frame of the definition (the X and Y lines), which is
        # turned against the twin's coordinates by the straightness errors' residual slopes
        # over the targets; the analysis places the motion there about the functional point
        fp = m.functional_point
        d = a.direction
        c = fp + frame @ (a.pivot + t.position - fp)
        d_f = frame @ (d + np.cross(t.orientation, d))
        d_f /= np.linalg.norm(d_f)
        at_pivot = c - np.dot(c - a.pivot, d) / np.dot(d_f, d) * d_f
        tilt = np.cross(d, d_f)
        for j in perp:
            out['location'][f'E{"XYZ"[j]}0{name}'] = (at_pivot - a.pivot)[j]
        for j in perp:
            out['location'][f'E{"ABC"[j]}0{name}'] = tilt[j]
        only = zero_truth(m)
        only.rotary[name] = replace(t, position=np.zeros(3), orientation=np.zeros(3))
        single = TwinMachine(m, only, twin.setup)
        q = np.tile(m.reference, (plan.targets.size, 1))
        q[:, k] = plan.targets
        q = twin.follow(q)
        point = a.pivot + np.dot(m.functional_point - a.pivot, a.direction) * a.direction
        kw = {'at_workpiece': point} if a.side == 'workpiece' else {'at': point}
        e = np.stack([single.error_screw(q, _plays(m, k, d, len(q)), **kw) for d in (1, -1)], axis=1)
        iref = int(np.argmin(np.abs(plan.targets - a.reference)))
        e = e - e[iref].mean(axis=0)
        out['rotary'][name] = np.concatenate([e[..., :3] @ frame.T, e[..., 3:] @ frame.T], axis=-1)
    return out


def comparisons(result, truth: dict) -> list[tuple[str, float, float, float, str]]:
    """(name, identified, truth, U, unit) for every identified error: squareness, location
    errors, and every error motion at every target in each direction."""
    rows = []
    for v in result.squareness:
        if v.name in truth['squareness']:
            rows.append((v.name, v.value, truth['squareness'][v.name], v.expanded, v.unit))
    for name, a in result.axes.items():
        for v in a.location:
            rows.append((v.name, v.value, truth['location'][v.name], v.expanded, v.unit))
        table = truth['rotary'][name] if a.rotary else truth['linear'][name]
        for j, mo in enumerate(a.motions):
            for i in range(a.targets.size):
                rows.append((f'{mo.name}[{i}]↑', mo.up[i], table[i, 0, j], mo.U_up[i], mo.unit))
                rows.append((f'{mo.name}[{i}]↓', mo.down[i], table[i, 1, j], mo.U_down[i], mo.unit))
    return rows
