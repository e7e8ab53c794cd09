"""Where a model was validated, and whether the live state is still there (ROS-free).

``mmd analyze`` writes a ``validity`` record into the model file: the runs it fitted the model
on (by the hash of their raw counts), their references, the range of each bar's length and of
the temperature they covered. A term fitted over 300–340 mm of a bar says nothing about 360 mm;
a thermal term fitted between 21 and 24 °C says nothing about 28 °C. The compensation and pose
nodes use :class:`Validity` to warn in their diagnostics when the live state leaves that range
(the correction is still applied: it is the best the model has, but it is not validated there).

    validity:
      runs: [{log: x.mcap, ident: 3f2a..., reference: [x], ...}, ...]
      bar_range_mm: [[301.2, 344.0], ...]     # per bar, CDF lengths covered
      temperature_c: [22.1, 24.2]             # room temperature estimated from the reference bar
      temperature_is_absolute: true           # false: relative to the thermal zero
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.calibration import Calibration
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.model import Model
from mmd_ros.core.uncertainty import CalibrationUncertainty
from mmd_ros.core.units import M_PER_MM

__all__ = ['BAR_MARGIN_M', 'CALIBRATION_TERMS', 'TEMP_MARGIN_C', 'Validity',
           'fitted_calibration_figures', 'other_calibration', 'other_device']

FloatArray = NDArray[np.float64]

#: A bar this far outside the lengths the model was validated on counts as outside [m].
BAR_MARGIN_M = 1e-3
#: A temperature this far outside the validated span counts as outside [°C].
TEMP_MARGIN_C = 0.5
#: Term types whose parameters belong to the calibration they were fitted with: the errors of
#: its CDF points, and an encoder cyclic error as its points read it (the analysis' effects of
#: scope ``calibration``).
CALIBRATION_TERMS = ('cdf_offsets', 'cyclic_error')


def _last_analysis(model: Model) -> dict[str, Any]:
    """The last ``analysis`` entry of a model file ({} when it has none)."""
    analysis: Any = model.extra.get('analysis')
    if isinstance(analysis, list):
        analysis = analysis[-1] if analysis else None
    return analysis if isinstance(analysis, dict) else {}


def fitted_calibration_figures(model: Model) -> CalibrationUncertainty | None:
    """What the routine of the calibration a model's per-calibration parameters were fitted
    with measured of its own points (``per_calibration_uncertainty`` of its last ``analysis``
    entry: approaches, seating, the routine's drift), or None when the model does not say
    (written before it was recorded, not by ``mmd analyze``, or malformed)."""
    data = _last_analysis(model).get('per_calibration_uncertainty')
    if not isinstance(data, dict):
        return None
    try:
        return CalibrationUncertainty.from_dict(data, '<model analysis record>')
    except ConfigError:
        return None


def other_device(model: Model, calibration: Calibration) -> str | None:
    """Why ``model`` belongs to another device than ``calibration``, or None: a model ``mmd
    analyze`` wrote names the terminal its logs' calibrations were made with
    (``per_calibration_terminal`` of its last ``analysis`` entry); a calibration made by the
    nodes names its own (``terminal.serial``). When both do and they differ, the model's terms
    (the channels' delays are the terminal's; each bar's friction and points are the bars')
    are another MMD's, and its uncertainty that MMD's. None when either does not say."""
    fitted = _last_analysis(model).get('per_calibration_terminal')
    mine = calibration.terminal.serial if calibration.terminal is not None else ''
    if not isinstance(fitted, str) or not fitted or not mine or fitted == mine:
        return None
    return (f'the model was fitted on logs of terminal {fitted} and this calibration was made '
            f'with terminal {mine}: its terms (the channels\' delays, each bar\'s friction and '
            'points) and its uncertainty are another device\'s; use the model of this device, or '
            'run mmd analyze on its logs')


def other_calibration(model: Model, calibration: Calibration) -> str | None:
    """Why ``model`` does not fit ``calibration``, or None: a model ``mmd analyze`` wrote
    names the calibration its per-calibration parameters were fitted with
    (``per_calibration_parameters_of`` of its last ``analysis`` entry). Its terms of
    :data:`CALIBRATION_TERMS` correct that calibration's points, and the residual it
    measured stands for that calibration's errors: applied with another calibration (the
    device calibrated again, another device of the same description) the first are wrong and
    the second is not this calibration's (a model of one twin on another twin's log: its
    95 % ellipsoid held none of the samples). None for a model without that record."""
    fitted = _last_analysis(model).get('per_calibration_parameters_of')
    if not isinstance(fitted, str) or not fitted:
        return None
    mine = calibration.key()
    if mine == fitted:
        return None
    terms = sorted({t.type_name for t in model.terms if t.type_name in CALIBRATION_TERMS})
    what = (f'its {", ".join(terms)} term(s) correct that calibration\'s points, not this '
            'one\'s, and ' if terms else '')
    return (f'the model was fitted with calibration {fitted} and this calibration is {mine}: '
            f'{what}the uncertainty it measured stands for that calibration\'s errors; run mmd '
            'analyze on a log of this calibration')


@dataclass(frozen=True)
class Validity:
    """The validated range of a model.

    bar_range_m : ndarray, shape (6, 2) — lowest and highest CDF length of each bar [m]
    temperature_c : (low, high) [°C], absolute or relative to the thermal zero, or None
    absolute : True when ``temperature_c`` is the room temperature (the calibration knew it)
    runs : content hashes of the runs the model was fitted on
    """

    bar_range_m: FloatArray
    temperature_c: tuple[float, float] | None
    absolute: bool
    runs: tuple[str, ...]

    @classmethod
    def from_model(cls, model: Model) -> Validity | None:
        """The model's ``validity`` record, or None when it has none (or a malformed one: a
        model file from elsewhere is not refused for lacking it)."""
        record: Any = model.extra.get('validity')
        if not isinstance(record, dict):
            return None
        try:
            bars = np.array(record.get('bar_range_mm'), dtype=np.float64) * M_PER_MM
            temp = record.get('temperature_c')
            span = None
            if isinstance(temp, (list, tuple)) and len(temp) == 2 and all(
                    isinstance(v, (int, float)) and math.isfinite(v) for v in temp):
                span = (float(temp[0]), float(temp[1]))
        except (TypeError, ValueError):
            return None
        if bars.shape != (6, 2) or not np.all(np.isfinite(bars)):
            return None
        runs = tuple(str(r.get('ident')) for r in record.get('runs') or [] if isinstance(r, dict))
        return cls(bars, span, bool(record.get('temperature_is_absolute', False)), runs)

    def outside(self, lengths_m: FloatArray, temperature_c: FloatArray | None
                ) -> tuple[NDArray[np.int64], int]:
        """Samples outside the validated range: per bar (6,), and for the temperature.

        lengths_m : ndarray, shape (N, 6) — CDF lengths [m] (NaN ignored)
        temperature_c : ndarray, shape (N,) — on the scale of ``temperature_c`` [°C], or None
        """
        lo = self.bar_range_m[:, 0] - BAR_MARGIN_M
        hi = self.bar_range_m[:, 1] + BAR_MARGIN_M
        x = np.asarray(lengths_m, dtype=np.float64)
        with np.errstate(invalid='ignore'):
            bars = np.sum((x < lo) | (x > hi), axis=0).astype(np.int64)
        temp = 0
        if self.temperature_c is not None and temperature_c is not None:
            t = np.asarray(temperature_c, dtype=np.float64)
            with np.errstate(invalid='ignore'):
                temp = int(np.sum((t < self.temperature_c[0] - TEMP_MARGIN_C)
                                  | (t > self.temperature_c[1] + TEMP_MARGIN_C)))
        return bars, temp

    def describe(self, bars_out: NDArray[np.int64], temp_out: int) -> str:
        """A diagnostics message for samples found outside ('' when none)."""
        parts = []
        for i in np.flatnonzero(bars_out):
            lo, hi = self.bar_range_m[i] / M_PER_MM
            parts.append(f'bar{i + 1} outside {lo:.1f}–{hi:.1f} mm ({int(bars_out[i])} samples)')
        if temp_out and self.temperature_c is not None:
            lo, hi = self.temperature_c
            what = 'temperature' if self.absolute else 'temperature change'
            parts.append(f'{what} outside {lo:.2f}–{hi:.2f} °C ({temp_out} samples)')
        if not parts:
            return ''
        return ('the model\'s terms were validated on other conditions: ' + '; '.join(parts)
                + ': their corrections are extrapolated (re-run mmd analyze with a run that covers them)')
