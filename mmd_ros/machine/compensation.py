"""Compensation files a controller can load, written from a :class:`MachineResult`.

- **LinuxCNC axis compensation** (``comp_<axis>.txt``): one file per joint, for the INI's
  ``[JOINT_n]`` ``COMP_FILE`` with ``COMP_FILE_TYPE = 0``: each line ``nominal forward
  reverse`` in machine units (mm or inch; degrees for an angular joint), ascending nominal;
  forward/reverse are the positions the axis actually reaches moving in the positive / negative
  direction (LinuxCNC's ``docs/src/config/ini-config.adoc``, ``[JOINT_<num>]`` section; its
  loader ``usrmotLoadComp`` stores ``nominal - actual`` as the trim and stops at the first
  line that is not three numbers, so the files carry no comments). At most 256 lines.
- **CSV** of every error motion against position (``error_motions.csv``).
- **YAML** of the location errors: rotary axis lines and squareness (``location_errors.yaml``),
  with the actual pivot points and directions a kinematics configuration can take.

Formats: ``msg_docs/machine.md``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from mmd_ros.core.units import ARCSEC_PER_RAD, M_PER_MM, M_PER_UM
from mmd_ros.core.yamlio import atomic_write_text
from mmd_ros.machine.errors import MachineAnalysisError
from mmd_ros.machine.results import MachineResult

__all__ = ['LINUXCNC_MAX_LINES', 'linuxcnc_table', 'write_compensation', 'write_csv',
           'write_location_yaml']

#: LinuxCNC keeps at most this many triplets per joint.
LINUXCNC_MAX_LINES = 256
INCH_M = 0.0254


def linuxcnc_table(result: MachineResult, axis: str, units: str = 'mm') -> str:
    """The ``COMP_FILE_TYPE = 0`` file of one axis: ``nominal forward reverse`` per line."""
    a = result.axes.get(axis)
    if a is None:
        raise MachineAnalysisError(f'no {axis} run in this session: no compensation table for it')
    desc = result.machine.axis(axis)
    c = desc.component
    motion = a.motions[3 + c] if a.rotary else a.motions[c]
    sign = float(np.sign(desc.direction[c]))
    if a.targets.size > LINUXCNC_MAX_LINES:
        raise MachineAnalysisError(f'{axis}: {a.targets.size} targets, LinuxCNC takes at most '
                                   f'{LINUXCNC_MAX_LINES} lines per joint')
    if a.rotary:
        scale, digits = 180.0 / math.pi, 7
    elif units == 'inch':
        scale, digits = 1.0 / INCH_M, 8
    else:
        scale, digits = 1.0 / M_PER_MM, 6
    lines = []
    for q, up, down in zip(a.targets, motion.up * sign, motion.down * sign):
        lines.append(f'{q * scale:.{digits}f} {(q + up) * scale:.{digits}f} {(q + down) * scale:.{digits}f}')
    return '\n'.join(lines) + '\n'


def write_compensation(result: MachineResult, out: Path, units: str = 'mm') -> list[Path]:
    """LinuxCNC compensation files of every measured axis and an INI snippet naming them."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    ini = ['# Add to the [JOINT_n] section of each axis (n: the joint of that axis in your',
           '# kinematics). Files: nominal, position reached moving +, position reached moving -,',
           f'# in {units} (degrees for rotary axes), from mmd machine (msg_docs/machine.md).']
    for name in result.machine.axis_names:
        if name not in result.axes:
            continue
        path = out / f'comp_{name}.txt'
        atomic_write_text(path, linuxcnc_table(result, name, units))
        written.append(path)
        ini += [f'# axis {name}', 'COMP_FILE = ' + path.name, 'COMP_FILE_TYPE = 0', '']
    snippet = out / 'linuxcnc_comp.ini'
    atomic_write_text(snippet, '\n'.join(ini) + '\n')
    return written + [snippet]


def write_csv(result: MachineResult, path: Path) -> Path:
    """Every error motion at every target: one row per axis, error, target and direction;
    u_mmd (the MMD's part of u, not expanded) empty where not known (a machine.json written
    before it was kept for up, down and reversal)."""
    rows = ['axis,error,kind,position,position_unit,direction,value,U95,u_mmd,unit,determined']
    for a in result.axes.values():
        ps, punit = a.position_scale
        for m in a.motions:
            scale = 1.0 / M_PER_UM if m.unit == 'm' else ARCSEC_PER_RAD
            unit = 'um' if m.unit == 'm' else 'arcsec'
            for i, q in enumerate(a.targets):
                for label, v, big_u in (('up', m.up, m.U_up), ('down', m.down, m.U_down),
                                        ('mean', m.mean, m.U_mean), ('reversal', m.reversal, m.U_reversal)):
                    um = m.u_mmd(label)
                    um = '' if um is None or not math.isfinite(um[i]) else f'{um[i] * scale:.5f}'
                    rows.append(f'{a.axis},{m.name},{m.kind},{q * ps:.6f},{punit},{label},'
                                f'{v[i] * scale:.5f},{big_u[i] * scale:.5f},'
                                f'{um},{unit},{int(m.determined)}')
    return atomic_write_text(path, '\n'.join(rows) + '\n')


def write_location_yaml(result: MachineResult, path: Path) -> Path:
    """Rotary axis lines (nominal and actual pivot and direction, location errors) and the
    squareness of the linear axes, for a kinematics configuration."""
    def entry(v) -> dict:
        scale = 1.0 / M_PER_UM if v.unit == 'm' else ARCSEC_PER_RAD
        unit = 'um' if v.unit == 'm' else 'arcsec'
        if not v.determined and not math.isfinite(v.value):
            return {'determined': False, 'note': v.note}
        out = {f'value_{unit}': round(v.value * scale, 4), f'U_{unit}': round(v.expanded * scale, 4),
               'determined': bool(v.determined)}
        if v.note:
            out['note'] = v.note
        return out

    data: dict = {
        'format_version': 1,
        'machine': result.machine.name,
        'conventions': 'machine coordinates = workpiece frame at the reference position; '
                       'positions in mm at the nominal pivot, directions as unit vectors; '
                       'location errors of the axis line (ISO 230-7), squareness as the rotation '
                       'of the axis line by the right-hand rule (ISO 230-1), X the reference; '
                       'U is the expanded uncertainty (about 95 %)',
        'rotary_axes': {}, 'squareness': {v.name: entry(v) for v in result.squareness}}
    model = result.model()
    for name, a in result.axes.items():
        if not a.rotary:
            continue
        desc = result.machine.axis(name)
        loc = model.locations[name]
        from mmd_ros.machine.geometry import rotation_from_rotvec
        actual_dir = rotation_from_rotvec(loc.tilt) @ desc.direction
        data['rotary_axes'][name] = {
            'nominal_pivot_mm': [round(float(v) / M_PER_MM, 6) for v in desc.pivot],
            'nominal_direction': [float(v) for v in desc.direction],
            'actual_pivot_mm': [round(float(v) / M_PER_MM, 6) for v in desc.pivot + loc.position],
            'actual_direction': [round(float(v), 9) for v in actual_dir / np.linalg.norm(actual_dir)],
            'location_errors': {v.name: entry(v) for v in a.location},
        }
    return atomic_write_text(path, yaml.safe_dump(data, sort_keys=False))
