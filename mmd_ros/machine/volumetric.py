"""Volumetric error of the machine from its kinematic model: the tool tip against the workpiece
anywhere in the working volume (within the ranges the session measured).

:func:`linear_map` evaluates a grid over the linear axes with the rotary axes at their reference;
:func:`rotary_map` sweeps the rotary axes over their measured spans with the linear axes
following (the tool tip stays on the workpiece point it touches at the reference, as in five-axis
machining with tool-centre-point control). Errors are in machine axes (the workpiece frame turned
back by its nominal rotation) [m]; the mean of both approach directions is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mmd_ros.machine.results import MachineResult

__all__ = ['VolumetricMap', 'linear_map', 'rotary_map']

FloatArray = NDArray[np.float64]


@dataclass
class VolumetricMap:
    """Axis values (N, n_axes) and the tool tip's error (N, 3) [m] at each."""

    names: list[str]
    q: FloatArray
    error: FloatArray
    tool_offset: FloatArray

    @property
    def magnitude(self) -> FloatArray:
        return np.linalg.norm(self.error, axis=1)

    def csv(self) -> str:
        head = ','.join(f'{n}_{"deg" if n in "ABC" else "mm"}' for n in self.names)
        rows = [head + ',ex_um,ey_um,ez_um,e_um']
        scale = np.array([180 / np.pi if n in 'ABC' else 1e3 for n in self.names])
        for q, e, mag in zip(self.q, self.error, self.magnitude):
            rows.append(','.join(f'{v:.4f}' for v in q * scale) + ',' +
                        ','.join(f'{v * 1e6:.4f}' for v in e) + f',{mag * 1e6:.4f}')
        return '\n'.join(rows) + '\n'


def _range(result: MachineResult, name: str) -> tuple[float, float]:
    a = result.axes.get(name)
    axis = result.machine.axis(name)
    if a is None:
        return axis.reference, axis.reference
    return float(a.targets[0]), float(a.targets[-1])


def linear_map(result: MachineResult, *, points: int = 9, z_levels: int = 3,
               tool_offset: FloatArray | None = None) -> VolumetricMap:
    """The tool tip's error on a grid over the measured ranges of the linear axes (``points``
    per horizontal axis, ``z_levels`` along the vertical one), rotary axes at their reference."""
    machine = result.machine
    model = result.model()
    lin = {a.component: a.name for a in machine.linear_axes}
    axes = [np.linspace(*_range(result, lin[j]), points if j < 2 else z_levels) for j in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, 3)
    q = np.tile(machine.reference, (grid.shape[0], 1))
    for j in range(3):
        q[:, machine.index(lin[j])] = grid[:, j]
    offset = np.zeros(3) if tool_offset is None else np.asarray(tool_offset, dtype=np.float64)
    return VolumetricMap(machine.axis_names, q, model.tool_point_error(q, None, offset), offset)


def rotary_map(result: MachineResult, *, points: int = 9,
               tool_offset: FloatArray | None = None) -> VolumetricMap:
    """The tool tip's error over the measured spans of the rotary axes (a grid of all rotary
    axes), the linear axes following the workpiece point of the reference."""
    machine = result.machine
    model = result.model()
    rot = [a.name for a in machine.rotary_axes]
    axes = [np.linspace(*_range(result, n), points) for n in rot]
    grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, len(rot))
    q = np.tile(machine.reference, (grid.shape[0], 1))
    for j, n in enumerate(rot):
        q[:, machine.index(n)] = grid[:, j]
    q = model.nominal_follow(q)
    offset = np.zeros(3) if tool_offset is None else np.asarray(tool_offset, dtype=np.float64)
    return VolumetricMap(machine.axis_names, q, model.tool_point_error(q, None, offset), offset)
