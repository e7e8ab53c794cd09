"""Diagnostic reports of the compensation and kinematics stages (shared by the nodes)."""

from __future__ import annotations

import math
import time

import numpy as np

from mmd_ros.core.calibration import Calibration
from mmd_ros.core.kinematics import FkStatus
from mmd_ros.core.streaming import Compensator, Kinematics
from mmd_ros.nodes.diagnostics import ERROR, OK, WARN, Report

__all__ = ['calibration_age_s', 'compensation_report', 'kinematics_report']


def calibration_age_s(calibration: Calibration | None) -> float:
    """Seconds since the calibration was made (``created``), NaN when unknown."""
    when = None if calibration is None else calibration.created_s
    return math.nan if when is None else time.time() - when


def _reading_drift_um(comp: Compensator) -> float:
    """One sigma of each channel's reading drift since the calibration now, as the budget
    claims it [um] (NaN when it claims none)."""
    budget = comp.budget
    return math.nan if budget is None else round(budget.reading_drift_sigma_m(time.time()) * 1e6, 4)


def _plate_scale_ppm(comp: Compensator, temp_change_c: float) -> float:
    """One sigma of the plates' scale at the thermal drift now, as the budget claims it
    [ppm] (0 when it claims none, NaN when the drift or the budget is not known)."""
    budget = comp.budget
    return math.nan if budget is None else round(budget.plate_scale_sigma(temp_change_c) * 1e6, 4)


def compensation_report(comp: Compensator, thermal_warn_c: float, model_source: str) -> Report:
    """Calibration in use, thermal drift since the thermal zero (Eq. 11), bars out of range."""
    st = comp.stats
    r = Report('compensation', OK, 'compensating')
    if comp.problem:
        r.worse(ERROR if comp.calibration is not None or comp.hold_from_ns else WARN, comp.problem)
    cal = comp.calibration
    n_refs = len(comp.reference_names)
    dt = st.last_temp_change_c
    if math.isfinite(dt) and abs(dt) > thermal_warn_c:
        if n_refs == 1:
            r.worse(WARN, f'thermal drift {dt:+.2f} °C since the thermal zero with one reference '
                    f'bar: past {thermal_warn_c:g} °C Eq. (13) neglects how the thermal error grows '
                    'with bar length (Eq. 12); fit a second reference bar or set a new thermal zero')
        else:
            r.worse(OK, f'thermal drift {dt:+.2f} °C since the thermal zero (Eq. 12)')
    if comp.model_mismatch:
        r.worse(WARN, comp.model_mismatch)
    if comp.validity is not None:
        text = comp.validity.describe(st.period_outside_bars, st.period_outside_temp)
        if text:
            r.worse(WARN, text)
        r.values['model_validated_runs'] = len(comp.validity.runs)
        r.values['outside_validated_range'] = int(st.period_outside_bars.sum() + st.period_outside_temp)
        st.period_outside_bars = np.zeros(6, np.int64)
        st.period_outside_temp = 0
    out = st.period_out
    if out.any():
        bars = [f'bar{i + 1} ({int(v)})' for i, v in enumerate(out) if v]
        r.worse(WARN, 'out of the calibrated range: ' + ', '.join(bars)
                + ' samples: no pose for them')
    lost = st.period_no_signal
    if lost.any():
        bars = [f'bar{i + 1} ({int(v)})' for i, v in enumerate(lost) if v]
        r.worse(WARN, 'encoder signal lost (terminal channel status): ' + ', '.join(bars)
                + ' samples: not measurements, no length and no pose for them')
    r.values.update({
        'calibration': comp.calibration_source,
        'calibration_valid': bool(cal is not None and cal.valid and comp.ready),
        'calibration_created': cal.created if cal is not None else '',
        'calibration_age_s': round(calibration_age_s(cal), 1),
        'reading_drift_um': _reading_drift_um(comp),
        'plate_scale_ppm': _plate_scale_ppm(comp, dt),
        'model': model_source,
        'thermal_mode': comp.model.thermal_mode,
        'reference_bars': n_refs,
        'temp_change_c': round(dt, 4) if math.isfinite(dt) else math.nan,
        'samples': st.samples,
        'samples_without_calibration': st.held,
        'samples_without_signal': st.no_signal,
    })
    for name, err in zip(comp.reference_names, st.last_ref_error_m):
        r.values[f'{name}_error_um'] = round(float(err) * 1e6, 4)
    for i in range(6):
        r.values[f'bar{i + 1}_out_of_range'] = int(st.out_of_range[i])
    st.period_out = np.zeros(6, np.int64)
    st.period_no_signal = np.zeros(6, np.int64)
    return r


def kinematics_report(kin: Kinematics) -> Report:
    """FK iterations and residual, samples without a pose (and why) and out-of-range samples
    since the last one; the counts of each :class:`FkStatus` since the start."""
    st = kin.stats
    r = Report('kinematics', OK, 'solving')
    if st.period_samples == 0:
        r.message = 'no compensated lengths received'
    if st.period_not_converged:
        why = ', '.join(f'{int(st.period_by_status[s])} {s.name.lower()}' for s in FkStatus
                        if s > FkStatus.OUT_OF_SPAN and st.period_by_status[s])
        r.worse(WARN, f'{st.period_not_converged} sample(s) without a pose ({why}): not '
                'measurements')
    if st.period_out_of_range:
        r.worse(WARN, f'{st.period_out_of_range} sample(s) with a bar out of its calibrated range '
                'or without encoder signal (no length): no pose for them')
    solved = st.period_solved
    now = time.monotonic()
    elapsed = now - st.period_t0
    r.values.update({
        'samples': st.samples,
        'poses_published': st.poses,
        'not_converged': st.not_converged,
        'out_of_range': st.out_of_range,
        **{f'fk_{s.name.lower()}': int(st.by_status[s]) for s in FkStatus
           if s not in (FkStatus.OK, FkStatus.OUT_OF_SPAN)},
        'iterations_mean': round(st.period_iterations_sum / solved, 3) if solved else math.nan,
        'iterations_max': st.period_iterations_max,
        'residual_max_m': st.period_residual_max_m if solved else math.nan,
        'rate_hz': round(st.period_samples / elapsed, 1) if elapsed > 0 else math.nan,
    })
    st.period_t0 = now
    st.period_samples = st.period_not_converged = st.period_out_of_range = 0
    st.period_solved = st.period_iterations_sum = st.period_iterations_max = 0
    st.period_residual_max_m = 0.0
    st.period_by_status[:] = 0
    return r
