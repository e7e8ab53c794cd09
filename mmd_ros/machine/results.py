"""What a machine session identified: values with their uncertainty, per axis and for the
machine, and the kinematic model they make.

Every number is SI (m, rad) here; reports convert to µm and arc-seconds. ``u`` is the
standard uncertainty (everything: the MMD's pose covariance, the repeatability between
approaches, the setup and the fit), ``u_mmd`` the part that comes from the MMD alone; the
expanded uncertainty is ``U = k u`` for about 95 % coverage: k is Student's t for the
Welch-Satterthwaite degrees of freedom of u (the scatter between n cycles has n - 1; the MMD's
covariance and the other type-B parts count as exactly known), and at least 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.analysis.iso230 import IsoResult
from mmd_ros.core.machine import MachineDescription
from mmd_ros.core.units import ARCSEC_PER_RAD, M_PER_UM
from mmd_ros.machine.kinematics import ErrorTable, MachineModel, RotaryLocation

__all__ = ['AxisResult', 'COVERAGE_K', 'ErrorMotion', 'MachineResult', 'Value', 'load_result',
           'report_scale']

FloatArray = NDArray[np.float64]

#: Smallest coverage factor of the expanded uncertainty U = k u (about 95 %).
COVERAGE_K = 2.0


def report_scale(unit: str) -> tuple[float, str]:
    """SI to report units: m -> µm, rad -> arc-seconds."""
    return (1.0 / M_PER_UM, 'µm') if unit == 'm' else (ARCSEC_PER_RAD, '″')


def _num(v: float, scale: float = 1.0) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v * scale)


def _arr(a: FloatArray | None, scale: float = 1.0) -> list[float | None] | None:
    return None if a is None else [_num(float(v), scale) for v in np.asarray(a, dtype=float)]


@dataclass
class Value:
    """A scalar error with its uncertainty [m or rad]; ``determined`` is False when the session
    does not fix it (``note`` says why)."""

    name: str
    value: float
    u: float
    u_mmd: float
    unit: str
    determined: bool = True
    note: str = ''
    k: float = COVERAGE_K
    #: rotary location errors: the part of u from component errors that the tested span cannot
    #: tell from the location (NaN elsewhere) [m or rad]
    u_turn: float = math.nan

    @property
    def expanded(self) -> float:
        """U = k u [m or rad]."""
        return self.k * self.u

    def as_dict(self) -> dict[str, Any]:
        scale, unit = report_scale(self.unit)
        out = {'name': self.name, 'value': _num(self.value, scale), 'u': _num(self.u, scale),
               'U': _num(self.expanded, scale), 'u_mmd': _num(self.u_mmd, scale), 'unit': unit,
               'determined': bool(self.determined), 'note': self.note}
        if math.isfinite(self.u_turn):
            out['u_turn'] = _num(self.u_turn, scale)
        return out


@dataclass
class ErrorMotion:
    """One error motion of one axis against its position, per approach direction.

    kind : 'positioning', 'straightness', 'angular' (linear axes); 'radial', 'axial', 'tilt',
        'positioning' (rotary axes)
    up, down, mean, reversal : (m,) values relative to the reference position [m or rad]
    deviation : (m,) straightness deviations from the least-squares reference line, or None
    figure : straightness error (max - min of ``deviation``), angular deviation (max - min of
        ``mean``), or the positioning's bidirectional systematic deviation E
    iso230 : the ISO 230-2 evaluation (positioning error motions)
    """

    name: str
    axis: str
    kind: str
    unit: str
    positions: FloatArray
    up: FloatArray
    down: FloatArray
    mean: FloatArray
    reversal: FloatArray
    u_up: FloatArray
    u_down: FloatArray
    u_mean: FloatArray
    u_reversal: FloatArray
    u_mmd_mean: FloatArray
    figure: Value
    deviation: FloatArray | None = None
    u_deviation: FloatArray | None = None
    iso230: IsoResult | None = None
    determined: bool = True
    k_up: FloatArray | None = None
    k_down: FloatArray | None = None
    k_mean: FloatArray | None = None
    k_reversal: FloatArray | None = None
    #: the MMD's part of u_up, u_down, u_reversal (None: not known, a result written before)
    u_mmd_up: FloatArray | None = None
    u_mmd_down: FloatArray | None = None
    u_mmd_reversal: FloatArray | None = None

    def u_mmd(self, direction: str) -> FloatArray | None:
        """The MMD's part of the uncertainty of ``direction`` ('up', 'down', 'mean',
        'reversal'), or None where it is not known."""
        return getattr(self, f'u_mmd_{direction}')

    def _k(self, k: FloatArray | None) -> FloatArray:
        return np.full(self.positions.shape, COVERAGE_K) if k is None else k

    @property
    def U_up(self) -> FloatArray:
        return self._k(self.k_up) * self.u_up

    @property
    def U_down(self) -> FloatArray:
        return self._k(self.k_down) * self.u_down

    @property
    def U_mean(self) -> FloatArray:
        return self._k(self.k_mean) * self.u_mean

    @property
    def U_reversal(self) -> FloatArray:
        return self._k(self.k_reversal) * self.u_reversal

    def as_dict(self, position_scale: float) -> dict[str, Any]:
        scale, unit = report_scale(self.unit)
        out = {'name': self.name, 'axis': self.axis, 'kind': self.kind, 'unit': unit,
               'positions': _arr(self.positions, position_scale), 'up': _arr(self.up, scale),
               'down': _arr(self.down, scale), 'mean': _arr(self.mean, scale),
               'reversal': _arr(self.reversal, scale), 'u_up': _arr(self.u_up, scale),
               'u_down': _arr(self.u_down, scale), 'u_mean': _arr(self.u_mean, scale),
               'u_reversal': _arr(self.u_reversal, scale), 'u_mmd_mean': _arr(self.u_mmd_mean, scale),
               'U_up': _arr(self.U_up, scale), 'U_down': _arr(self.U_down, scale),
               'U_mean': _arr(self.U_mean, scale), 'U_reversal': _arr(self.U_reversal, scale),
               'figure': self.figure.as_dict(), 'determined': bool(self.determined)}
        for key in ('up', 'down', 'reversal'):
            if self.u_mmd(key) is not None:
                out[f'u_mmd_{key}'] = _arr(self.u_mmd(key), scale)
        if self.deviation is not None:
            out['deviation'] = _arr(self.deviation, scale)
            out['u_deviation'] = _arr(self.u_deviation, scale)
        if self.iso230 is not None:
            out['iso230_figures'] = {k: _num(v, scale) for k, v in self.iso230.figures.items()}
        return out


@dataclass
class AxisResult:
    """Everything one axis run gave: six error motions and (rotary) four location errors."""

    axis: str
    rotary: bool
    log: str
    source: str
    targets: FloatArray
    n_cycles: int
    following: list[str]
    motions: list[ErrorMotion]
    location: list[Value] = field(default_factory=list)
    fit_ratio: float = 1.0   # rotary: residual / its expected size (Birge ratio) of the location fit

    @property
    def position_scale(self) -> tuple[float, str]:
        return (180.0 / math.pi, '°') if self.rotary else (1e3, 'mm')

    def motion(self, name: str) -> ErrorMotion:
        for m in self.motions:
            if m.name == name:
                return m
        raise KeyError(name)

    def table(self) -> ErrorTable:
        """The error motions as an :class:`ErrorTable` for the kinematic model."""
        up = np.column_stack([m.up for m in self.motions])
        down = np.column_stack([m.down for m in self.motions])
        return ErrorTable(self.axis, self.targets, up, down)

    def as_dict(self) -> dict[str, Any]:
        ps, punit = self.position_scale
        return {'axis': self.axis, 'rotary': self.rotary, 'log': self.log, 'source': self.source,
                'targets': _arr(self.targets, ps), 'position_unit': punit, 'n_cycles': self.n_cycles,
                'following': self.following, 'fit_ratio': _num(self.fit_ratio),
                'location': [v.as_dict() for v in self.location],
                'motions': [m.as_dict(ps) for m in self.motions]}


@dataclass
class MachineResult:
    """A machine session's errors.

    frame : ndarray, shape (3, 3) — R_ML, machine axes in {L}'s coordinates as rows (X is the
        reference; Y lies in the xy plane)
    """

    machine: MachineDescription
    axes: dict[str, AxisResult]
    squareness: list[Value]
    frame: FloatArray
    frame_source: str
    instrument: str
    model_text: str
    logs: list[str]
    draws: int
    notes: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    #: per rotary run, where the other table axes' play stood and what was taken out of it
    play: list[str] = field(default_factory=list)

    def values(self) -> list[Value]:
        """Every scalar error: squareness, location errors."""
        out = list(self.squareness)
        for a in self.axes.values():
            out.extend(a.location)
        return out

    def value(self, name: str) -> Value:
        for v in self.values():
            if v.name == name:
                return v
        raise KeyError(name)

    def not_determined(self) -> list[str]:
        """Errors this session could not determine, with the reason."""
        out = [f'{v.name}: {v.note}' for v in self.values() if not v.determined]
        for a in self.axes.values():
            out += [f'{m.name}: {m.figure.note}' for m in a.motions if not m.determined]
        return out + list(self.notes)

    def model(self) -> MachineModel:
        """The kinematic model with every identified error."""
        tables = {name: a.table() for name, a in self.axes.items()}
        locations = {}
        for name, a in self.axes.items():
            if a.rotary:
                pos, tilt = np.zeros(3), np.zeros(3)
                for v in a.location:   # the estimates, also where the session does not fix them
                    value = v.value if math.isfinite(v.value) else 0.0
                    if v.name[1] in 'XYZ':
                        pos['XYZ'.index(v.name[1])] = value
                    else:
                        tilt['ABC'.index(v.name[1])] = value
                locations[name] = RotaryLocation(pos, tilt)
        return MachineModel(self.machine, tables, locations)

    def as_dict(self) -> dict[str, Any]:
        return {'machine': self.machine.name, 'machine_file': self.machine.source,
                'instrument': self.instrument, 'model': self.model_text, 'logs': self.logs,
                'monte_carlo_draws': self.draws, 'coverage': '95 % (k >= 2)',
                'frame_source': self.frame_source,
                'squareness': [v.as_dict() for v in self.squareness],
                'axes': {k: a.as_dict() for k, a in self.axes.items()},
                'not_determined': self.not_determined(),
                'other_axes_play': list(self.play),
                'seconds': {k: round(v, 3) for k, v in self.seconds.items()}}


def load_result(data: dict[str, Any], machine: MachineDescription) -> MachineResult:
    """A :class:`MachineResult` back from its :meth:`MachineResult.as_dict` (``machine.json``):
    values, uncertainties and error tables, enough for compensation files and volumetric maps
    (not the per-approach ISO 230-2 data)."""
    from mmd_ros.machine.errors import MachineAnalysisError
    try:
        def value(d: dict[str, Any], unit: str) -> Value:
            scale, _ = report_scale(unit)

            def f(key: str) -> float:
                v = d.get(key)
                return math.nan if v is None else float(v) / scale
            u = f('u')
            big_u = f('U')
            k = big_u / u if u and math.isfinite(u) and math.isfinite(big_u) else COVERAGE_K
            return Value(d['name'], f('value'), u, f('u_mmd'), unit, bool(d['determined']),
                         d.get('note', ''), k, f('u_turn'))

        axes = {}
        for name, a in data['axes'].items():
            ps = 180.0 / math.pi if a['rotary'] else 1e3
            targets = np.array(a['targets'], dtype=float) / ps
            motions = []
            for m in a['motions']:
                unit = 'm' if m['unit'] == 'µm' else 'rad'
                scale, _ = report_scale(unit)

                def arr(key: str) -> FloatArray:
                    return np.array([math.nan if v is None else v for v in m[key]], dtype=float) / scale
                with np.errstate(divide='ignore', invalid='ignore'):
                    ks = {key: np.nan_to_num(arr('U_' + key) / arr('u_' + key), nan=COVERAGE_K)
                          for key in ('up', 'down', 'mean', 'reversal')}
                motions.append(ErrorMotion(
                    m['name'], name, m['kind'], unit, targets, arr('up'), arr('down'), arr('mean'),
                    arr('reversal'), arr('u_up'), arr('u_down'), arr('u_mean'), arr('u_reversal'),
                    arr('u_mmd_mean'), value(m['figure'], unit),
                    arr('deviation') if 'deviation' in m else None,
                    arr('u_deviation') if 'deviation' in m else None, None, bool(m['determined']),
                    ks['up'], ks['down'], ks['mean'], ks['reversal'],
                    *(arr(f'u_mmd_{key}') if f'u_mmd_{key}' in m else None
                      for key in ('up', 'down', 'reversal'))))
            location = [value(v, 'm' if v['unit'] == 'µm' else 'rad') for v in a['location']]
            axes[name] = AxisResult(name, bool(a['rotary']), a['log'], a['source'], targets,
                                    int(a['n_cycles']), list(a['following']), motions, location,
                                    float(a['fit_ratio'] or 1.0))
        squareness = [value(v, 'rad') for v in data['squareness']]
    except (KeyError, TypeError, ValueError) as exc:
        raise MachineAnalysisError(f'not a machine result (machine.json of mmd machine analyze): '
                                   f'{exc.__class__.__name__} {exc}') from None
    return MachineResult(machine, axes, squareness, np.eye(3), str(data.get('frame_source', '')),
                         str(data.get('instrument', '')), str(data.get('model', '')),
                         list(data.get('logs', [])), int(data.get('monte_carlo_draws', 0)),
                         play=[str(n) for n in data.get('other_axes_play', [])])
