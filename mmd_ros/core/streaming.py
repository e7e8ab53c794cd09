"""Compensation and forward kinematics of a sample stream, one transfer at a time (ROS-free).

:class:`Compensator` (``compensation_node``, ``pose_node``) turns raw counts into compensated
bar lengths with :meth:`Pipeline.compensate` (CDF Eq. 10, thermal Eqs. 11–13, model terms); for
model terms that need a pose it solves a first-pass pose as :meth:`Pipeline.process` does.
:class:`Kinematics` (``fk_node``, ``pose_node``) solves the pose of every sample whose six bars
are within their calibrated span, warm-started from the previous poses, with the propagated
covariance J^-1 Sigma_d J^-T (Sigma_d of :class:`~mmd_ros.core.budget.LengthBudget`, from the
lengths and the thermal state of each sample). Both keep the figures their diagnostics report.

A bar out of its calibrated span gives NaN in the published lengths (the extrapolated value is
not a measurement) and no pose; live, such samples are not solved. So does a bar whose encoder
signal the terminal reported lost (or a quadrature error: a count may be missing) in that
sample, and every bar of a sample whose reference bar's signal was lost (its thermal
compensation, Eq. 11, is then unknown).
"""

from __future__ import annotations

import functools
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.budget import LengthBudget, Observed
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import MmdError, ModelError
from mmd_ros.core.kinematics import FkStatus, ForwardKinematics
from mmd_ros.core.model import Model
from mmd_ros.core.pipeline import Pipeline, bars_without_signal
from mmd_ros.core.uncertainty import pose_covariance
from mmd_ros.core.validity import Validity, other_calibration

__all__ = ['CompensationOut', 'Compensator', 'Kinematics', 'KinematicsOut', 'calibration_created_ns']

FloatArray = NDArray[np.float64]


def calibration_created_ns(calibration: Calibration) -> int | None:
    """When the calibration was made [ns since the epoch], or None when it does not say."""
    when = calibration.created_s
    return None if when is None else int(when * 1e9)


@dataclass(frozen=True)
class CompensationOut:
    """Compensated lengths of N samples.

    lengths_m : (N, 6) — d_i* [m], NaN where the bar is out of its calibrated span or has no
        encoder signal
    out_of_range : (N, 6)
    no_signal : (N, 6) — no length because an encoder signal was lost (the bar's, or a
        reference bar's)
    reference_error_m : (N, k) — Eq. (11) per reference bar [m]
    temp_change_c : (N,) — temperature change since the thermal zero [°C]
    plate_scale : (N,) — the plates' expansion factor applied to the joints
    bar_error_m : (N, 6) — thermal error subtracted from each bar [m]
    fit_columns_m : (N, 6, r) or None — the model's fitted terms' one-sigma perturbations
    """

    lengths_m: FloatArray
    out_of_range: NDArray[np.bool_]
    reference_error_m: FloatArray
    temp_change_c: FloatArray
    plate_scale: FloatArray
    no_signal: NDArray[np.bool_] | None = None
    bar_error_m: FloatArray | None = None
    fit_columns_m: FloatArray | None = None

    def thermal_values(self) -> FloatArray:
        """Values of /mmd/thermal: reference errors [m], temp_change [°C], plate_scale [1]."""
        return np.column_stack([self.reference_error_m, self.temp_change_c, self.plate_scale])


@dataclass
class _CompStats:
    samples: int = 0
    out_of_range: NDArray[np.int64] = field(default_factory=lambda: np.zeros(6, np.int64))
    period_out: NDArray[np.int64] = field(default_factory=lambda: np.zeros(6, np.int64))
    last_ref_error_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    last_temp_change_c: float = math.nan
    held: int = 0
    no_signal: int = 0
    period_no_signal: NDArray[np.int64] = field(default_factory=lambda: np.zeros(6, np.int64))
    #: samples outside the model's validated range since the last report: per bar, temperature
    period_outside_bars: NDArray[np.int64] = field(default_factory=lambda: np.zeros(6, np.int64))
    period_outside_temp: int = 0


class Compensator:
    """Counts → compensated lengths with the current calibration and model (thread-safe swap).

    device, model : the device description and the model in use
    """

    def __init__(self, device: DeviceDescription, model: Model) -> None:
        self.device = device
        self.model = model
        self.validity = Validity.from_model(model)
        fit = model.uncertainty.fit
        fit_terms = [t for group in fit.directions for t in group] if fit is not None else []
        self.needs_pose = any(getattr(t, 'needs_pose', False) for t in model.terms + fit_terms)
        self.reference_names = [c.name for c in device.reference_channels]
        self._lock = threading.Lock()
        self._pipeline: Pipeline | None = None
        self._fk: ForwardKinematics | None = None
        self._t0: int | None = None
        self.calibration: Calibration | None = None
        self.calibration_source = ''
        self.problem = 'no calibration yet'
        #: why the model does not fit the calibration in use, or None (:func:`other_calibration`)
        self.model_mismatch: str | None = None
        self.hold_from_ns: int | None = None
        self.stats = _CompStats()

    def set_calibration(self, calibration: Calibration | None, source: str) -> str | None:
        """Use ``calibration`` from now on. Returns why it cannot be used (and keeps computing
        nothing), or None. An invalid calibration (counter reset) stops the output."""
        problem = None
        pipeline = None
        if calibration is None:
            problem = 'no calibration'
        elif not calibration.valid:
            pending = calibration.quality.get('pending_re_reference') if calibration.quality else None
            problem = ('calibration invalid: the terminal\'s counters were reset; re-reference '
                       + (', '.join(pending) if pending else 'the bars') + ' (calibrate_bar)')
        elif self.hold_from_ns is not None and calibration_created_ns(calibration) is not None and \
                calibration_created_ns(calibration) < self.hold_from_ns - 1_000_000_000:
            problem = ('the terminal\'s counters were reset after this calibration was made: '
                       'waiting for the bars to be re-referenced (calibrate_bar)')
        else:
            try:
                pipeline = Pipeline(self.device, calibration, self.model)
            except ModelError as exc:      # (the model, not the calibration: another device's)
                problem = f'{exc} (calibration from {source})'
            except MmdError as exc:
                problem = f'calibration from {source} cannot be used: {exc}'
        mismatch = other_calibration(self.model, calibration) if calibration is not None else None
        with self._lock:
            self.calibration = calibration
            self.calibration_source = source
            self.problem = problem
            self.model_mismatch = mismatch
            self._pipeline = pipeline
            self._fk = ForwardKinematics.for_device(self.device) if pipeline is not None else None
            self._t0 = None
            if pipeline is not None:
                self.hold_from_ns = None
        return problem

    def hold(self, from_stamp_ns: int) -> None:
        """A counter reset happened at ``from_stamp_ns``: compute nothing from there until a
        calibration made after it arrives."""
        cal = self.calibration
        if cal is not None and cal.valid and calibration_created_ns(cal) is not None and \
                calibration_created_ns(cal) >= from_stamp_ns and self._pipeline is not None:
            return  # an old reset event: this calibration was made (re-referenced) after it
        with self._lock:
            self.hold_from_ns = int(from_stamp_ns)
            self._pipeline = None
            self.problem = ('the terminal\'s counters were reset: waiting for the bars to be '
                            're-referenced (calibrate_bar)')

    def new_run(self) -> None:
        """A new run begins (a replay): its stamps restart, and nothing of the samples before
        it (term states, the read-noise estimate, FK warm starts) carries into it, so that it is
        computed as ``mmd process`` computes the log."""
        with self._lock:
            self._t0 = None
            if self._pipeline is not None:
                self._pipeline.reset()
            if self._fk is not None:
                self._fk.reset()

    @property
    def ready(self) -> bool:
        return self._pipeline is not None

    @property
    def budget(self) -> LengthBudget | None:
        """The uncertainty budget of the calibration in use, or None."""
        pipeline = self._pipeline
        return pipeline.budget if pipeline is not None else None

    def process(self, stamps_ns: NDArray[np.int64], counts: FloatArray,
                status: NDArray[np.uint8] | None = None) -> CompensationOut | None:
        """Lengths of the samples of one transfer, or None when there is no usable calibration.

        status : (N, 8) channel status codes of the terminal (0 good; see
            :meth:`~mmd_ros.hardware.stream.SampleBatch.status_codes`), or None when all good
        """
        with self._lock:
            pipeline, fk = self._pipeline, self._fk
            if pipeline is None:
                self.stats.held += len(stamps_ns)
                return None
            if self._t0 is None:
                self._t0 = int(stamps_ns[0])
            t0 = self._t0
        times = (np.asarray(stamps_ns, dtype=np.int64) - t0).astype(np.float64) * 1e-9
        comp = pipeline.compensate(times, counts)
        if self.needs_pose and fk is not None:
            first = _solve(fk, comp.lengths_m, comp.thermal.plate_scale).poses
            comp = pipeline.add_pose_terms(comp, times, counts, first)
        out = comp.out_of_range
        lengths = np.where(out, np.nan, comp.lengths_m)
        no_signal = None
        if status is not None:
            no_signal = bars_without_signal(self.device, status)
            lengths[no_signal] = np.nan
        result = CompensationOut(lengths, out, comp.thermal.reference_error_m,
                                 comp.thermal.temp_change_c, comp.thermal.plate_scale, no_signal,
                                 comp.thermal.bar_error_m, comp.fit_columns_m)
        st = self.stats
        if no_signal is not None:
            st.no_signal += int(np.count_nonzero(no_signal.any(axis=1)))
            st.period_no_signal += no_signal.sum(axis=0)
        st.samples += len(stamps_ns)
        bad = out.sum(axis=0)
        st.out_of_range += bad
        st.period_out += bad
        if result.reference_error_m.size:
            st.last_ref_error_m = result.reference_error_m[-1].copy()
        st.last_temp_change_c = float(result.temp_change_c[-1])
        if self.validity is not None:
            temp = result.temp_change_c
            if self.validity.absolute:
                ambient = self.calibration.ambient_c if self.calibration is not None else None
                temp = None if ambient is None else temp + ambient
            bars, t_out = self.validity.outside(comp.cdf_lengths_m, temp)
            st.period_outside_bars += bars
            st.period_outside_temp += t_out
        return result


@dataclass(frozen=True)
class KinematicsOut:
    """Poses of N samples: poses (N, 6) [m, rad]; valid (N,): published as a measurement;
    converged, status (:class:`FkStatus`), iterations, residual_m and condition (NaN when not
    solved); jacobians (N, 6, 6) and plate_scale (N,) of the solutions; what the covariance
    needs (``uncertainty``: the budget and each sample's lengths and thermal state, or a fixed
    bar-length sigma [m]), or None when no covariance is wanted."""

    poses: FloatArray
    valid: NDArray[np.bool_]
    converged: NDArray[np.bool_]
    status: NDArray[np.int8]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    condition: FloatArray
    jacobians: FloatArray
    plate_scale: FloatArray
    uncertainty: _CovarianceInputs | float | None

    @functools.cached_property
    def covariance(self) -> FloatArray | None:
        """Covariance (M, 6, 6) [m, rad]^2 of the M valid samples, or None.

        J^-1 Sigma_d J^-T, translation rows and columns times the plates' scale (as
        :class:`Pipeline` does). Computed when first asked for, so that a node can publish the
        poses before it spends time on the inverses.
        """
        unc = self.uncertainty
        if unc is None or not self.valid.any():
            return None
        v = self.valid
        jinv = np.linalg.inv(self.jacobians[v])
        if isinstance(unc, float):
            sigma_d = np.broadcast_to(unc * unc * np.eye(6), (jinv.shape[0], 6, 6))
        else:
            observed = unc.observe()
            sigma_d = unc.budget.covariance(
                unc.lengths_m[v], unc.reference_error_m[v], unc.temp_change_c[v],
                unc.bar_error_m[v], None if unc.fit_columns_m is None else unc.fit_columns_m[v],
                observed[v])
        return pose_covariance(jinv, sigma_d, self.plate_scale[v])

    def status_values(self) -> FloatArray:
        """Values of /mmd/fk_status: converged, valid, iterations, residual [m], condition,
        status (:class:`FkStatus`)."""
        return np.column_stack([self.converged, self.valid, self.iterations, self.residual_m,
                                self.condition, self.status]).astype(np.float64)


def _solve(fk: ForwardKinematics, lengths: FloatArray, scale: FloatArray,
           dt_s: FloatArray | None = None):
    """Streaming FK of N samples as :meth:`Pipeline.process_sample` does it: FK on d / s with the
    nominal geometry, translation times s. Samples with a NaN length are not solved.
    Returns the :class:`StreamSolution` with the translations scaled."""
    scale = np.asarray(scale, dtype=np.float64)[:, None]
    sol = fk.solve_stream(lengths / scale, dt_s=dt_s)
    sol.poses[:, :3] *= scale
    return sol


@dataclass
class _KinStats:
    samples: int = 0
    poses: int = 0
    not_converged: int = 0
    out_of_range: int = 0
    by_status: NDArray[np.int64] = field(default_factory=lambda: np.zeros(len(FkStatus), np.int64))
    period_by_status: NDArray[np.int64] = field(
        default_factory=lambda: np.zeros(len(FkStatus), np.int64))
    period_samples: int = 0
    period_not_converged: int = 0
    period_out_of_range: int = 0
    period_solved: int = 0
    period_iterations_sum: int = 0
    period_iterations_max: int = 0
    period_residual_max_m: float = 0.0
    period_t0: float = field(default_factory=time.monotonic)


@dataclass
class _CovarianceInputs:
    """What the budget needs of N samples (see :meth:`LengthBudget.covariance`). The budget
    observes them (read noise, motion directions) once, in the order of the transfers: when
    their covariance is first asked for, or at the latest before the next transfer is solved,
    so that the poses go out first."""

    budget: LengthBudget
    lengths_m: FloatArray
    reference_error_m: FloatArray
    temp_change_c: FloatArray
    bar_error_m: FloatArray
    fit_columns_m: FloatArray | None
    times_s: FloatArray | None = None
    poses: FloatArray | None = None
    observed: Observed | None = None

    def observe(self) -> Observed:
        if self.observed is None:
            # (the stamps' times are Unix times: the drift since the calibration is claimed)
            self.observed = self.budget.observe(self.lengths_m + self.bar_error_m,
                                                self.reference_error_m, self.times_s, self.poses,
                                                None if self.times_s is None else 0.0)
        return self.observed


class Kinematics:
    """Forward kinematics of compensated lengths (see the module docstring).

    uncertainty : the bar lengths' uncertainty budget (:class:`LengthBudget` of the calibration
        and model in use; set :attr:`budget` when they change), a fixed 1-sigma bar-length
        uncertainty [m] for every bar (``fk_node``'s ``length_sigma_um``), or None: no
        covariance until a budget is set
    with_covariance : compute covariances at all
    """

    def __init__(self, device: DeviceDescription, uncertainty: LengthBudget | float | None = None,
                 *, with_covariance: bool = True) -> None:
        self.fk = ForwardKinematics.for_device(device)
        self.budget: LengthBudget | None = uncertainty if isinstance(uncertainty, LengthBudget) else None
        self.fixed_sigma_m: float | None = (float(uncertainty) if isinstance(uncertainty, (int, float))
                                            and uncertainty else None)
        self.with_covariance = with_covariance
        self.stats = _KinStats()
        self._last: _CovarianceInputs | None = None
        self._last_stamp_ns: int | None = None

    def new_run(self) -> None:
        """A new run begins (a replay): forget the warm starts, the last stamp and the budget's
        read-noise estimate, as a fresh :class:`Kinematics` (or ``mmd process``) would start."""
        self.fk.reset()
        self._last_stamp_ns = None
        self._last = None
        if self.budget is not None:
            self.budget.reset()

    def solve(self, lengths_m: FloatArray, plate_scale: FloatArray,
              reference_error_m: FloatArray | None = None, temp_change_c: FloatArray | None = None,
              bar_error_m: FloatArray | None = None, fit_columns_m: FloatArray | None = None, *,
              stamps_ns: NDArray[np.int64] | None = None) -> KinematicsOut:
        """Poses of N consecutive samples.

        lengths_m : (N, 6) compensated lengths, NaN where out of range [m]
        plate_scale : (N,)
        reference_error_m, temp_change_c : (N, k) and (N,), the thermal state of the samples
            (for the budget; zeros when not given)
        bar_error_m : (N, 6) thermal error subtracted from each bar; None computes it from the
            reference errors as the compensation did
        fit_columns_m : (N, 6, r) the fitted terms' perturbations, or None (their mean is used)
        stamps_ns : (N,) the samples' stamps, for the continuity test at the measured rate
            (default: the device's sample period between samples)
        """
        plate_scale = np.asarray(plate_scale, dtype=np.float64)
        if self._last is not None:      # the previous transfer, if its covariance was not asked for
            if self._last.budget is self.budget:
                self._last.observe()
            self._last = None
        dt = None
        if stamps_ns is not None and len(stamps_ns):
            stamps = np.asarray(stamps_ns, dtype=np.int64)
            last = self._last_stamp_ns
            dt = np.diff(stamps, prepend=stamps[0] if last is None else last) * 1e-9
            if last is None:
                dt[0] = self.fk.limits.sample_period_s
            self._last_stamp_ns = int(stamps[-1])
        sol = _solve(self.fk, lengths_m, plate_scale, dt)
        poses, converged, iterations, residual = sol.poses, sol.converged, sol.iterations, sol.residual_m
        in_range = np.isfinite(lengths_m).all(axis=1)
        valid = converged & in_range
        # (a transfer's figures with few numpy calls: this runs at 1 kHz / 8; samples not
        # solved have 0 iterations and a NaN residual)
        st = self.stats
        n = len(valid)
        n_valid = int(np.count_nonzero(valid))
        n_solved = int(np.count_nonzero(in_range))
        st.samples += n
        st.period_samples += n
        st.poses += n_valid
        st.not_converged += n_solved - n_valid
        st.period_not_converged += n_solved - n_valid
        st.out_of_range += n - n_solved
        st.period_out_of_range += n - n_solved
        counts = np.bincount(sol.status, minlength=len(FkStatus))
        st.by_status += counts
        st.period_by_status += counts
        if n_solved:
            st.period_solved += n_solved
            st.period_iterations_sum += int(iterations.sum())
            st.period_iterations_max = max(st.period_iterations_max, int(iterations.max()))
            r = float(np.fmax.reduce(residual))
            if r > st.period_residual_max_m:
                st.period_residual_max_m = r
        unc: _CovarianceInputs | float | None = None
        if self.with_covariance:
            if self.fixed_sigma_m is not None:
                unc = self.fixed_sigma_m
            elif self.budget is not None:
                b = self.budget
                eps = (np.zeros((n, 0)) if reference_error_m is None
                       else np.asarray(reference_error_m, dtype=np.float64).reshape(n, -1))
                dtemp = (np.zeros(n) if temp_change_c is None
                         else np.asarray(temp_change_c, dtype=np.float64))
                if bar_error_m is None:
                    bar_error_m = b.bar_error(lengths_m, eps)
                times = (None if stamps_ns is None or not len(stamps_ns)
                         else np.asarray(stamps_ns, dtype=np.int64) * 1e-9)
                unc = self._last = _CovarianceInputs(b, lengths_m, eps, dtemp, bar_error_m,
                                                     fit_columns_m, times, poses)
        return KinematicsOut(poses, valid, converged, sol.status, iterations, residual,
                             sol.condition, sol.jacobians, plate_scale, unc)
