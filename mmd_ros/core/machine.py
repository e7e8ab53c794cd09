"""Machine description: the YAML file that says how a machine tool's axes are stacked.

The twin's machine (:mod:`mmd_ros.twin.machine`) and the machine analysis
(:mod:`mmd_ros.machine`) read the same description, as both read the device description;
each computes its own kinematics from it.

Conventions (``msg_docs/machine.md``):

- **Machine coordinates** are the workpiece (table) frame with every axis at its reference
  position. An axis value moves the *tool relative to the workpiece* (ISO 841): increasing X
  moves the tool towards +``direction`` whether the spindle or the table carries X; a rotary
  axis turns the tool about its ``direction`` by the right-hand rule relative to the workpiece.
  A table-carried axis therefore moves the table the opposite way.
- **Chains** list the axes from the machine bed outwards: ``tool`` (bed to spindle) and
  ``workpiece`` (bed to table); each axis carries the ones after it.
- The **controlled tool point** at an axis position is ``sum(q_k d_k)`` over the linear axes in
  machine coordinates. The MMD's functional point is the origin of its upper plate {U}:
  ``mmd.upper_offset_mm`` from the controlled tool point, in the spindle's frame.
- A rotary axis line passes through ``pivot_mm`` (machine coordinates at the reference
  position) along ``direction``; its location errors are given at that point.

The file keeps lengths in mm and angles in degrees and says so in every key;
:class:`MachineDescription` holds SI values (m, rad).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from mmd_ros.core import validate
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.units import M_PER_MM, M_PER_UM
from mmd_ros.core.yamlio import read_yaml

__all__ = ['AXIS_LETTERS', 'MachineAxis', 'MachineDescription', 'load_machine', 'parse_machine']

FloatArray = NDArray[np.float64]

#: Axis names the description accepts: linear X Y Z (U V W), rotary A B C.
AXIS_LETTERS = {'X': 'linear', 'Y': 'linear', 'Z': 'linear', 'U': 'linear', 'V': 'linear',
                'W': 'linear', 'A': 'rotary', 'B': 'rotary', 'C': 'rotary'}
SIDES = ('tool', 'workpiece')
#: The keys of a machine description, of its axes (linear and rotary) and of its ``mmd``
#: section; anything else is refused as a typo.
MACHINE_KEYS = ('format_version', 'name', 'description', 'axes', 'chains', 'mmd')
AXIS_KEYS = {'linear': ('name', 'type', 'carried_by', 'direction', 'reference_mm', 'travel_mm'),
             'rotary': ('name', 'type', 'carried_by', 'direction', 'pivot_mm', 'reference_deg',
                        'travel_deg')}
MMD_KEYS = ('lower_position_mm', 'lower_rpy_deg', 'upper_offset_mm', 'upper_offset_uncertainty_um')


@dataclass(frozen=True)
class MachineAxis:
    """One numerically controlled axis.

    name : 'X', 'Y', 'Z', 'A', 'B' or 'C'
    kind : 'linear' or 'rotary'
    side : 'tool' (the spindle carries it) or 'workpiece' (the table carries it)
    direction : ndarray, shape (3,) — unit vector of the motion of the tool relative to the
        workpiece for an increasing value (ISO 841), in machine coordinates
    pivot : ndarray, shape (3,) — a point on a rotary axis line at the reference position [m];
        zeros for a linear axis
    reference : float — axis value of the session's reference position [m or rad]
    travel : (low, high) — the axis travel [m or rad]
    """

    name: str
    kind: str
    side: str
    direction: FloatArray
    pivot: FloatArray
    reference: float
    travel: tuple[float, float]

    @property
    def rotary(self) -> bool:
        return self.kind == 'rotary'

    @property
    def component(self) -> int:
        """Index 0, 1, 2 of the machine coordinate axis (x, y, z) the axis runs along or about."""
        return int(np.argmax(np.abs(self.direction)))


@dataclass(frozen=True)
class MachineDescription:
    """A machine tool: axes, how they are stacked, and where the MMD sits on it (SI units).

    axes : the axes in the order of the file (and of the joint-state names)
    tool_chain, workpiece_chain : axis names from the bed outwards
    lower_position : ndarray, shape (3,) — nominal origin of {L} in machine coordinates [m]
    lower_rotation : ndarray, shape (3,) — nominal roll, pitch, yaw of {L} in machine
        coordinates (Eq. 3 convention) [rad]
    upper_offset : ndarray, shape (3,) — origin of {U} relative to the controlled tool point,
        in the spindle's frame at the reference position [m]
    upper_offset_uncertainty : float — standard uncertainty of each component of
        ``upper_offset`` (how well the plate's position on the spindle is known) [m]
    """

    name: str
    source: str
    description: str
    axes: tuple[MachineAxis, ...]
    tool_chain: tuple[str, ...]
    workpiece_chain: tuple[str, ...]
    lower_position: FloatArray
    lower_rotation: FloatArray
    upper_offset: FloatArray
    upper_offset_uncertainty: float
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def axis_names(self) -> list[str]:
        return [a.name for a in self.axes]

    def axis(self, name: str) -> MachineAxis:
        for a in self.axes:
            if a.name == name.upper():
                return a
        raise ConfigError(self.source, 'axes', f'has no axis {name!r}; axes are {self.axis_names}')

    def index(self, name: str) -> int:
        return self.axis_names.index(self.axis(name).name)

    @property
    def linear_axes(self) -> list[MachineAxis]:
        return [a for a in self.axes if not a.rotary]

    @property
    def rotary_axes(self) -> list[MachineAxis]:
        return [a for a in self.axes if a.rotary]

    @property
    def reference(self) -> FloatArray:
        """Axis values of the reference position, shape (n_axes,) [m, rad]."""
        return np.array([a.reference for a in self.axes])

    def tool_point(self, q: Any) -> FloatArray:
        """Controlled tool point in machine coordinates, sum of q_k d_k over linear axes.

        q : array_like, shape (..., n_axes) [m, rad]
        returns : ndarray, shape (..., 3) [m]
        """
        q = np.asarray(q, dtype=np.float64)
        out = np.zeros(q.shape[:-1] + (3,))
        for k, a in enumerate(self.axes):
            if not a.rotary:
                out = out + q[..., k, None] * a.direction
        return out

    @property
    def functional_point(self) -> FloatArray:
        """Nominal origin of {U} at the reference position, machine coordinates [m]."""
        return self.tool_point(self.reference) + self.upper_offset

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.raw, sort_keys=False)


class _Reader:
    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(self.source, key, problem)

    def vector(self, mapping: dict[str, Any], key: str, path: str, scale: float,
               default: Any = None) -> FloatArray:
        value = mapping.get(key, default)
        try:
            arr = np.asarray(value, dtype=np.float64) * scale
        except (TypeError, ValueError):
            raise self.fail(f'{path}{key}', f'must be three numbers, got {value!r}') from None
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise self.fail(f'{path}{key}', f'must be three finite numbers, got {value!r}')
        return arr

    def number(self, mapping: dict[str, Any], key: str, path: str, default: float | None = None,
               low: float | None = None) -> float:
        value = mapping.get(key, default)
        if value is None:
            raise self.fail(f'{path}{key}', 'required, not given')
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(f'{path}{key}', f'must be a finite number, got {value!r}')
        if low is not None and value < low:
            raise self.fail(f'{path}{key}', f'must be >= {low}, got {value}')
        return float(value)


def load_machine(path: str | os.PathLike[str]) -> MachineDescription:
    """Read a machine description file (a path, or a file name in the package's ``config/``)."""
    from mmd_ros.core.device import find_config
    found = find_config(str(path))
    data = read_yaml(found)
    return parse_machine(data, str(found))


def parse_machine(data: Any, source: str = '<machine>') -> MachineDescription:
    """A :class:`MachineDescription` from the file's mapping; malformed input raises
    :class:`ConfigError` naming the key."""
    r = _Reader(source)
    if not isinstance(data, dict):
        raise r.fail('(file)', 'must hold a YAML mapping')
    if data.get('format_version', 1) != 1:
        raise r.fail('format_version', f'must be 1, got {data.get("format_version")!r}')
    validate.known_keys(data, MACHINE_KEYS, source)
    raw_axes = data.get('axes')
    if not isinstance(raw_axes, list) or not raw_axes:
        raise r.fail('axes', 'must be a list of axes, e.g. {name: X, type: linear, ...}')
    axes: list[MachineAxis] = []
    for i, item in enumerate(raw_axes):
        path = f'axes[{i}].'
        if not isinstance(item, dict):
            raise r.fail(f'axes[{i}]', 'must be a mapping')
        name = str(item.get('name', '')).upper()
        if name not in AXIS_LETTERS:
            raise r.fail(f'{path}name', f'must be one of {" ".join(AXIS_LETTERS)}, got {item.get("name")!r}')
        if name in [a.name for a in axes]:
            raise r.fail(f'{path}name', f'axis {name} is listed twice')
        kind = str(item.get('type', AXIS_LETTERS[name]))
        if kind not in ('linear', 'rotary'):
            raise r.fail(f'{path}type', f'must be linear or rotary, got {kind!r}')
        validate.known_keys(item, AXIS_KEYS[kind], source, path)
        side = str(item.get('carried_by', ''))
        if side not in SIDES:
            raise r.fail(f'{path}carried_by', f'must be tool or workpiece, got {item.get("carried_by")!r}')
        direction = r.vector(item, 'direction', path, 1.0)
        norm = float(np.linalg.norm(direction))
        if not abs(norm - 1.0) < 1e-6 or np.count_nonzero(np.abs(direction) > 1e-9) != 1:
            raise r.fail(f'{path}direction', 'must be a unit vector along x, y or z (e.g. '
                         f'[0, 0, 1] or [-1, 0, 0]), got {item.get("direction")!r}')
        if kind == 'linear':
            reference = r.number(item, 'reference_mm', path, 0.0) * M_PER_MM
            key, scale = 'travel_mm', M_PER_MM
            pivot = np.zeros(3)
        else:
            reference = math.radians(r.number(item, 'reference_deg', path, 0.0))
            key, scale = 'travel_deg', math.pi / 180.0
            pivot = r.vector(item, 'pivot_mm', path, M_PER_MM)
        travel = item.get(key, [-1e6, 1e6])
        if not isinstance(travel, (list, tuple)) or len(travel) != 2 \
                or any(validate.number_problem(v) for v in travel):
            raise r.fail(f'{path}{key}', f'must be two numbers [low, high], got {travel!r}')
        lo, hi = (float(v) * scale for v in travel)
        if not lo < hi or not lo <= reference <= hi:
            raise r.fail(f'{path}{key}', 'must be [low, high] with low < high around the reference')
        axes.append(MachineAxis(name, kind, side, direction, pivot, reference, (lo, hi)))
    names = [a.name for a in axes]
    chains = data.get('chains')
    if not isinstance(chains, dict):
        raise r.fail('chains', 'must map tool and workpiece to lists of axis names')
    validate.known_keys(chains, SIDES, source, 'chains.')
    parsed: dict[str, tuple[str, ...]] = {}
    for side in SIDES:
        items = chains.get(side, [])
        if not isinstance(items, list):
            raise r.fail(f'chains.{side}', f'must be a list of axis names, got {items!r}')
        parsed[side] = tuple(str(v).upper() for v in items)
        for v in parsed[side]:
            if v not in names:
                raise r.fail(f'chains.{side}', f'names {v!r}, which is not an axis ({names})')
            if next(a for a in axes if a.name == v).side != side:
                raise r.fail(f'chains.{side}', f'lists {v}, which is carried_by the other side')
    listed = parsed['tool'] + parsed['workpiece']
    if sorted(listed) != sorted(names):
        raise r.fail('chains', f'must list every axis exactly once, got {list(listed)} for {names}')
    linear = [a for a in axes if not a.rotary]
    comps = sorted(a.component for a in linear)
    if comps != [0, 1, 2]:
        raise r.fail('axes', 'needs three linear axes along x, y and z')
    mmd = data.get('mmd', {}) or {}
    if not isinstance(mmd, dict):
        raise r.fail('mmd', 'must be a mapping')
    validate.known_keys(mmd, MMD_KEYS, source, 'mmd.')
    return MachineDescription(
        name=str(data.get('name', 'machine')), source=source,
        description=str(data.get('description', '')), axes=tuple(axes),
        tool_chain=parsed['tool'], workpiece_chain=parsed['workpiece'],
        lower_position=r.vector(mmd, 'lower_position_mm', 'mmd.', M_PER_MM, [0, 0, 0]),
        lower_rotation=r.vector(mmd, 'lower_rpy_deg', 'mmd.', math.pi / 180.0, [0, 0, 0]),
        upper_offset=r.vector(mmd, 'upper_offset_mm', 'mmd.', M_PER_MM, [0, 0, 0]),
        upper_offset_uncertainty=r.number(mmd, 'upper_offset_uncertainty_um', 'mmd.', 1.0, 0.0) * M_PER_UM,
        raw=data)
