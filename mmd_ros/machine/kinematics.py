"""The kinematic model of a machine tool with its identified errors (ISO 230-1 rigid-body model).

Each side of the machine (tool: bed → spindle; workpiece: bed → table) is a chain of carriage
transforms in the order of the description's chains. Relative to the reference position:

- a linear axis k at value q moves its carriage by ``s (q - q_ref) d_k`` (s = +1 on the tool
  side, -1 on the workpiece side: a table moves opposite to the tool's relative motion, ISO
  841), then by its error motion ``e_k(q)`` = [v, w]: the rotation w about the functional point
  as the axis' run saw it (fixed to the carriage on the tool side; on the workpiece side the
  point of the table under the tool, which moves with q) and the translation v of that point.
  On the workpiece side the carriage moves by the inverse, so that e_k is always the error of the
  tool relative to the workpiece (``msg_docs/machine.md``);
- a rotary axis k at angle θ turns its carriage by ``s (θ - θ_ref)`` about its actual line
  (the nominal line through ``pivot`` along ``d``, moved by the location errors: a position
  offset at the pivot and a tilt), then moves it by its component error motion c_k(θ): rotation
  w about the axis point (the point of the nominal line nearest the functional point) and
  translation v of that point, in fixed machine axes.

The relative pose of the tool frame in the workpiece frame is T_W_T = T_M_W⁻¹ T_M_T; with no
errors it is the nominal kinematics, and at the reference position it is the identity.
Error tables are interpolated with cubic splines between targets (linear with fewer than four)
and held at their end values outside the measured range (:meth:`ErrorTable.outside` says where).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline

from mmd_ros.core.machine import MachineAxis, MachineDescription
from mmd_ros.machine.geometry import apply, compose_screw, inverse, rotation_from_rotvec, transform

__all__ = ['ErrorTable', 'MachineModel', 'axis_point']

FloatArray = NDArray[np.float64]


def axis_point(axis: MachineAxis, point: ArrayLike) -> FloatArray:
    """The point of a rotary axis' nominal line nearest ``point`` (machine coordinates) [m]."""
    p = np.asarray(point, dtype=np.float64)
    d = axis.direction
    return axis.pivot + np.dot(p - axis.pivot, d) * d


@dataclass
class ErrorTable:
    """Error motion of one axis against its value, for each approach direction.

    positions : ndarray, shape (m,) — axis values of the targets, increasing [m or rad]
    up, down : ndarray, shape (m, 6) — [v, w] of the tool relative to the workpiece in machine
        axes [m, rad], approached in the positive / negative direction
    """

    axis: str
    positions: FloatArray
    up: FloatArray
    down: FloatArray
    bumps: FloatArray | None = None   # (m - 1, 6): amplitudes of sin(pi t) between targets
    _splines: list = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        self._splines = [self._interpolant(self.up), self._interpolant(self.down)]

    def with_bumps(self, amplitudes: FloatArray) -> ErrorTable:
        """The same table plus sin(pi t) between each pair of targets (t from 0 to 1 across the
        interval) with the given amplitudes (m - 1, 6): an interpolation error that vanishes at
        the targets (Monte Carlo draws of the interpolation's uncertainty)."""
        return ErrorTable(self.axis, self.positions, self.up, self.down, np.asarray(amplitudes))

    def _interpolant(self, values: FloatArray):
        if self.positions.size >= 4:
            return CubicSpline(self.positions, values, axis=0, bc_type='not-a-knot')
        pos = self.positions

        def linear(q: FloatArray) -> FloatArray:
            return np.stack([np.interp(q, pos, values[:, j]) for j in range(values.shape[1])], axis=-1)
        return linear

    def at(self, q: ArrayLike, direction: ArrayLike | None = None) -> FloatArray:
        """Error [v, w] at values q (N,) after a motion in ``direction`` (N,) (+1, -1; 0 or None:
        the mean of both), shape (N, 6); held at the end values outside the table."""
        q = np.clip(np.asarray(q, dtype=np.float64), self.positions[0], self.positions[-1])
        up = self._splines[0](q)
        down = self._splines[1](q)
        if self.bumps is not None:
            i = np.clip(np.searchsorted(self.positions, q, side='right') - 1, 0, self.positions.size - 2)
            t = (q - self.positions[i]) / (self.positions[i + 1] - self.positions[i])
            extra = np.sin(np.pi * np.clip(t, 0.0, 1.0))[..., None] * self.bumps[i]
            up, down = up + extra, down + extra
        if direction is None:
            return 0.5 * (up + down)
        d = np.asarray(direction, dtype=np.float64)[..., None]
        return np.where(d > 0, up, np.where(d < 0, down, 0.5 * (up + down)))

    def outside(self, q: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """Where q lies outside the measured range (by more than ``margin``)."""
        q = np.asarray(q, dtype=np.float64)
        return (q < self.positions[0] - margin) | (q > self.positions[-1] + margin)


@dataclass
class RotaryLocation:
    """Location errors of a rotary axis line: position offset at the pivot [m] and tilt (a
    rotation vector applied to the nominal direction) [rad], both in machine axes."""

    position: FloatArray
    tilt: FloatArray


class MachineModel:
    """Forward kinematics of the machine with the errors known so far.

    machine : the description
    tables : axis name -> :class:`ErrorTable` (linear error motions, including the squareness
        slope; rotary component errors, including the angular positioning error)
    locations : rotary axis name -> :class:`RotaryLocation`
    """

    def __init__(self, machine: MachineDescription, tables: dict[str, ErrorTable] | None = None,
                 locations: dict[str, RotaryLocation] | None = None) -> None:
        self.machine = machine
        self.tables = dict(tables or {})
        self.locations = dict(locations or {})
        self.names = machine.axis_names
        self.fp = machine.functional_point

    def _axis(self, k: int, q: FloatArray, direction: FloatArray | None) -> FloatArray:
        axis = self.machine.axes[k]
        s = 1.0 if axis.side == 'tool' else -1.0
        n = q.size
        dq = q - axis.reference
        table = self.tables.get(axis.name)
        e = table.at(q, direction) if table is not None else None
        if not axis.rotary:
            move = transform(np.broadcast_to(np.eye(3), (n, 3, 3)), s * dq[:, None] * axis.direction)
            if e is None:
                return move
            centre = self.fp if s > 0 else self.fp + dq[:, None] * axis.direction
            err = compose_screw(e[:, 3:], centre, e[:, :3])
            return move @ (err if s > 0 else inverse(err))
        loc = self.locations.get(axis.name)
        c = axis.pivot if loc is None else axis.pivot + loc.position
        d = axis.direction if loc is None else rotation_from_rotvec(loc.tilt) @ axis.direction
        turn = compose_screw(s * dq[:, None] * d, c, np.zeros((n, 3)))
        if e is None:
            return turn
        err = compose_screw(e[:, 3:], axis_point(axis, self.fp), e[:, :3])
        return (err if s > 0 else inverse(err)) @ turn

    def _chain(self, side: tuple[str, ...], q: FloatArray, dirs: FloatArray | None) -> FloatArray:
        out = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4)).copy()
        for name in side:
            k = self.names.index(name)
            out = out @ self._axis(k, q[:, k], None if dirs is None else dirs[:, k])
        return out

    def relative(self, q: ArrayLike, directions: ArrayLike | None = None) -> FloatArray:
        """T_W_T: the tool frame in the workpiece frame (machine coordinates), (N, 4, 4).

        q : array_like, shape (N, n_axes) — axis values [m, rad]
        directions : array_like, shape (N, n_axes) — direction of each axis' last motion (+1 /
            -1; 0 or None: the mean of both directions' errors)
        """
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        dirs = None if directions is None else np.atleast_2d(np.asarray(directions, dtype=np.float64))
        tool = self._chain(self.machine.tool_chain, q, dirs)
        work = self._chain(self.machine.workpiece_chain, q, dirs)
        return inverse(work) @ tool

    def parts(self, q: ArrayLike, directions: ArrayLike | None, axis: str
              ) -> tuple[FloatArray, FloatArray, bool]:
        """The relative pose split around one axis' carriage transform A (N, 4, 4):
        T_W_T = left @ A @ right on the tool side, left @ A⁻¹ @ right on the workpiece side.
        Returns (left, right, workpiece_side); A itself is :meth:`axis_transform`."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        dirs = None if directions is None else np.atleast_2d(np.asarray(directions, dtype=np.float64))
        a = self.machine.axis(axis)
        chain = self.machine.tool_chain if a.side == 'tool' else self.machine.workpiece_chain
        i = chain.index(a.name)
        before = self._chain(chain[:i], q, dirs)
        after = self._chain(chain[i + 1:], q, dirs)
        if a.side == 'tool':
            work = self._chain(self.machine.workpiece_chain, q, dirs)
            return inverse(work) @ before, after, False
        tool = self._chain(self.machine.tool_chain, q, dirs)
        return inverse(after), inverse(before) @ tool, True

    def axis_transform(self, axis: str, q: ArrayLike, directions: ArrayLike | None = None) -> FloatArray:
        """Carriage transform of one axis at its values q (N,), (N, 4, 4)."""
        k = self.names.index(self.machine.axis(axis).name)
        q = np.asarray(q, dtype=np.float64)
        return self._axis(k, q, None if directions is None else np.asarray(directions, dtype=np.float64))

    def workpiece_rotation(self, q: ArrayLike) -> FloatArray:
        """Nominal rotation of the workpiece frame in the machine axes at q, (N, 3, 3)."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        return MachineModel(self.machine)._chain(self.machine.workpiece_chain, q, None)[:, :3, :3]

    def tool_point_error(self, q: ArrayLike, directions: ArrayLike | None = None,
                         offset: ArrayLike | None = None) -> FloatArray:
        """Volumetric error: actual minus nominal position of the tool tip relative to the
        workpiece, in machine axes (the workpiece frame turned back by its nominal rotation),
        shape (N, 3) [m].

        offset : the tool tip relative to the functional point, in the spindle frame [m]
        """
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        tip = self.fp + (np.zeros(3) if offset is None else np.asarray(offset, dtype=np.float64))
        actual = apply(self.relative(q, directions), tip)
        nominal = apply(MachineModel(self.machine).relative(q), tip)
        return np.einsum('nij,nj->ni', self.workpiece_rotation(q), actual - nominal)

    def nominal_follow(self, q: ArrayLike) -> FloatArray:
        """Axis values with the linear axes set so that the nominal functional point stays on
        the workpiece point it touches at the reference (the R-test style following of a
        rotary run), (N, n_axes)."""
        nominal = MachineModel(self.machine)
        q = np.atleast_2d(np.array(q, dtype=np.float64))
        lin = [self.names.index(a.name) for a in self.machine.linear_axes]
        for k in lin:
            q[:, k] = self.machine.axes[k].reference
        base = apply(nominal.relative(q), self.fp)
        jac = np.zeros((q.shape[0], 3, len(lin)))
        for col, k in enumerate(lin):
            dq = q.copy()
            dq[:, k] += 1e-3
            jac[:, :, col] = (apply(nominal.relative(dq), self.fp) - base) / 1e-3
        q[:, lin] += np.linalg.solve(jac, (self.fp - base)[:, :, None])[:, :, 0]
        return q
