"""From raw counts to poses: CDF (Eq. 10) → thermal (Eqs. 11–13) → model terms → FK.

:class:`Pipeline` is the one implementation used by ``mmd process`` (batch) and by the ROS
nodes (stream, :meth:`Pipeline.process_sample`). Plate expansion scales both plates' joints by
``s``; since |R s a + t - s b| = s |R a + t/s - b|, FK runs on d/s with the nominal geometry and
the translation is multiplied by s. The pose covariance is Sigma_p = J^-1 Sigma_d J^-T with the
bar lengths' covariance Sigma_d of :class:`~mmd_ros.core.budget.LengthBudget`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.budget import KNOWN_ERROR_SHAPE, LengthBudget, Observed
from mmd_ros.core.calibration import Calibration, CdfBank
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import CalibrationError, ModelError
from mmd_ros.core.kinematics import FkStatus, ForwardKinematics
from mmd_ros.core.model import Model, TermContext
from mmd_ros.core.thermal import (
    ReferenceBar, ThermalCompensation, ThermalState, reference_plate_growth,
)
from mmd_ros.core.uncertainty import pose_covariance, tail_columns
from mmd_ros.core.validity import other_device

__all__ = ['Compensated', 'Pipeline', 'ProcessResult', 'SampleResult', 'bars_without_signal']

FloatArray = NDArray[np.float64]


def bars_without_signal(device: DeviceDescription, status: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """Which bars of N samples have no length because the terminal flagged a channel (its
    status code not 0: encoder signal lost, quadrature error): the bar's own channel, or any
    reference bar's (its thermal correction, Eq. 11, is then unknown for every bar).

    status : ndarray, shape (N, 8) — the terminal's channel status codes
    returns : ndarray of bool, shape (N, 6)
    """
    bad = np.asarray(status) != 0
    refs = [c.index for c in device.reference_channels]
    return bad[:, device.measuring_channels] | bad[:, refs].any(axis=1)[:, None]


@dataclass(frozen=True)
class Compensated:
    """Bar lengths of N samples.

    cdf_lengths_m : ndarray, shape (N, 6) — f_i(q_i), Eq. (10) [m]
    lengths_m : ndarray, shape (N, 6) — after thermal compensation and model terms [m]
    out_of_range : ndarray, shape (N, 6) — count outside the calibrated span (extrapolated)
    thermal : :class:`ThermalState`
    fit_columns_m : ndarray, shape (N, 6, r), or None — corrections of the one-sigma
        perturbations of the model's fitted terms (their share of Sigma_d is C C^T)
    """

    cdf_lengths_m: FloatArray
    lengths_m: FloatArray
    out_of_range: NDArray[np.bool_]
    thermal: ThermalState
    fit_columns_m: FloatArray | None = None


@dataclass(frozen=True)
class ProcessResult:
    """Poses of N samples.

    poses : ndarray, shape (N, 6) — [x, y, z, phi, theta, psi] of {U} in {L} [m, rad]; NaN
        where FK gave no plausible pose
    valid : ndarray, shape (N,) — converged and no bar out of range; only these are measurements
    status : ndarray of int8, shape (N,) — :class:`FkStatus`; OUT_OF_SPAN wherever a bar is out
        of its calibrated span (as live, where such samples are not solved)
    covariance : ndarray, shape (N, 6, 6), or None — pose covariance [m, rad]^2
    no_signal : ndarray, shape (N,) — the terminal flagged a channel the sample needs
        (:func:`bars_without_signal`): no length, no pose, status OUT_OF_SPAN (as live)
    tails : ndarray, shape (N, 6, 7), or None — with ``tails_every``, where the covariance's
        error is lighter-tailed than a Gaussian (:func:`~mmd_ros.core.uncertainty.tail_columns`:
        the size of its coverage regions)
    length_covariance : ndarray, shape (N, 6, 6), or None — with ``with_length_covariance``,
        the six measuring bars' length covariance Sigma_d the pose covariance propagates [m^2]
    """

    times_s: FloatArray
    compensated: Compensated
    poses: FloatArray
    converged: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    status: NDArray[np.int8]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    condition: FloatArray
    covariance: FloatArray | None
    no_signal: NDArray[np.bool_] | None = None
    tails: FloatArray | None = None
    length_covariance: FloatArray | None = None


@dataclass(frozen=True)
class SampleResult:
    """One streamed sample: lengths (6,), pose (6,), flags and FK diagnostics."""

    lengths_m: FloatArray
    out_of_range: NDArray[np.bool_]
    reference_error_m: FloatArray
    temp_change_c: float
    pose: FloatArray
    converged: bool
    valid: bool
    status: FkStatus
    iterations: int
    residual_m: float
    covariance: FloatArray | None


class Pipeline:
    """The compensation and kinematics of one calibrated device under one model.

    The pipeline owns a copy of the model: terms that carry state between calls (play
    operators, filters, the previous sample) carry it for this pipeline's stream only, so two
    pipelines built from one :class:`Model` (two runs, a calibration swapped live) never see
    each other's state.
    """

    def __init__(self, device: DeviceDescription, calibration: Calibration,
                 model: Model | None = None) -> None:
        self.device = device
        self.calibration = calibration
        if model is not None and (problem := other_device(model, calibration)) is not None:
            raise ModelError(f'model refused: {problem}')
        self.model = copy.deepcopy(model) if model is not None else Model()
        self.model.reset()
        names = device.channel_names
        measuring = [names[k] for k in device.measuring_channels]
        # the reference distances at the temperature the bars were calibrated at
        growth = reference_plate_growth(device, calibration.ambient_c)
        self.cdfs = CdfBank(calibration.cdfs(measuring, growth))
        self.channels = np.array(device.measuring_channels)
        references = []
        if self.model.thermal_mode != 'off':
            for ch in device.reference_channels:
                if ch.name not in calibration.bars:
                    raise CalibrationError(
                        f'reference bar {ch.name!r} has no calibration points; calibrate it or '
                        'set thermal.mode: off in the model')
                references.append(ReferenceBar(ch.index, device.pair(ch.pair).distance_m * growth,
                                               calibration.bars[ch.name].cdf(growth),
                                               calibration.thermal_zero_m.get(ch.name, 0.0)))
        self.thermal = ThermalCompensation(
            device, references, mode=self.model.thermal_mode,
            plate_expansion=self.model.plate_expansion, ambient_at_zero_c=calibration.ambient_c)
        self.fk = ForwardKinematics.for_device(device)
        self._pose_terms = [t for t in self.model.terms if t.needs_pose]
        self._length_terms = [t for t in self.model.terms if not t.needs_pose]
        fit = self.model.uncertainty.fit
        groups = fit.directions if fit is not None else []
        self._n_fit = len(groups)
        self._fit_pose_terms = [(g, t) for g, group in enumerate(groups) for t in group if t.needs_pose]
        self._fit_length_terms = [(g, t) for g, group in enumerate(groups) for t in group
                                  if not t.needs_pose]
        self._budget: LengthBudget | None = None

    @property
    def budget(self) -> LengthBudget:
        """The bar lengths' uncertainty budget (made when first asked for: it fits the
        interpolation error to the calibration points)."""
        if self._budget is None:
            self._budget = LengthBudget(self.device, self.calibration, self.model)
        return self._budget

    def reset(self) -> None:
        """Start a new run: forget FK warm starts, term states and the read-noise estimate."""
        self.fk.reset()
        self.model.reset()
        if self._budget is not None:
            self._budget.reset()

    # -- lengths -------------------------------------------------------------------------------
    def compensate(self, times_s: FloatArray, counts: FloatArray, *,
                   compiled: bool | None = None) -> Compensated:
        """Compensated bar lengths of N consecutive samples, with the terms that need no pose.

        times_s : ndarray, shape (N,) [s]
        counts : ndarray, shape (N, 8) — raw counts of all channels
        compiled : CDFs with the compiled helper (default: when it is in use)
        """
        counts = np.asarray(counts, dtype=np.float64)
        cdf_lengths, out = self.cdfs(counts[:, self.channels], compiled=compiled)
        thermal = self.thermal.state(counts, cdf_lengths)
        lengths = cdf_lengths - thermal.bar_error_m
        columns = None
        if self._length_terms or self._fit_length_terms:
            ctx = TermContext(np.asarray(times_s, dtype=np.float64), counts, lengths.copy(),
                              cdf_lengths, thermal.reference_error_m, thermal.temp_change_c)
            for term in self._length_terms:
                lengths = lengths + term.correction(ctx)
            columns = self._columns(self._fit_length_terms, ctx, None)
        return Compensated(cdf_lengths, lengths, out, thermal, columns)

    def add_pose_terms(self, comp: Compensated, times_s: FloatArray, counts: FloatArray,
                        poses: FloatArray) -> Compensated:
        """Add the pose-dependent terms, given first-pass poses. Each term sees every sample
        once, so terms that carry state give the same result streamed or in a batch."""
        ctx = TermContext(np.asarray(times_s, dtype=np.float64), np.asarray(counts, dtype=np.float64),
                          comp.cdf_lengths_m - comp.thermal.bar_error_m, comp.cdf_lengths_m,
                          comp.thermal.reference_error_m, comp.thermal.temp_change_c, poses)
        lengths = comp.lengths_m
        for term in self._pose_terms:
            lengths = lengths + term.correction(ctx)
        columns = comp.fit_columns_m
        if self._fit_pose_terms:
            columns = self._columns(self._fit_pose_terms, ctx, columns)
        return Compensated(comp.cdf_lengths_m, lengths, comp.out_of_range, comp.thermal, columns)

    def _columns(self, terms: list[tuple[int, Any]], ctx: TermContext,
                 columns: FloatArray | None) -> FloatArray | None:
        """Add the corrections of the fitted terms' perturbations to their direction's column,
        (N, 6, directions); None when the model has none."""
        if not self._n_fit:
            return None
        if columns is None:
            columns = np.zeros(ctx.lengths_m.shape + (self._n_fit,))
        for g, term in terms:
            columns[:, :, g] += term.correction(ctx)
        return columns

    @property
    def needs_pose(self) -> bool:
        """The model (or its fitted terms' uncertainty) has terms that need a first-pass pose."""
        return bool(self._pose_terms or self._fit_pose_terms)

    # -- batch ---------------------------------------------------------------------------------
    def process(self, times_s: FloatArray, counts: FloatArray, *,
                with_covariance: bool = False, covariance_every: int = 1,
                compiled: bool | None = None,
                status: NDArray[np.uint8] | None = None, tails_every: int = 0,
                with_length_covariance: bool = False, epoch_s: float | None = None
                ) -> ProcessResult:
        """Poses of N consecutive samples (one run, in time order).

        covariance_every : with the covariance, that of every k-th sample only (the others NaN):
            enough to judge how it covers a long run's error at a fraction of the cost (the
            budget still observes every sample)
        compiled : FK and covariance with the compiled helpers (default: when they are in
            use); False: numpy, the reference (the same results, bit for bit)
        status : (N, 8) the terminal's channel status codes (a log's ``RunLog.status``), or
            None when every sample is good. A bar without signal (:func:`bars_without_signal`)
            gets no length (NaN after the model's terms, which still see the sample, as the
            live compensation does), so its sample no pose: FK leaves it unsolved, status
            OUT_OF_SPAN, valid False.
        tails_every : with the covariance, where its error is lighter-tailed than a Gaussian
            (``ProcessResult.tails``, for the size of its coverage regions) at every k-th
            sample (k a multiple of ``covariance_every``; NaN elsewhere); 0: none
        with_length_covariance : with the covariance, also the bars' length covariance it
            propagates (``ProcessResult.length_covariance``, at the same samples): what a
            reference of bar lengths judges
        epoch_s : the Unix time [s] of ``times_s`` = 0 (a log's first stamp): with it the
            covariance claims the readings' drift since the calibration was made
            (:meth:`LengthBudget.observe`); None: that time is not known
        """
        times_s = np.asarray(times_s, dtype=np.float64)
        lost = None if status is None else bars_without_signal(self.device, status)
        no_signal = None if lost is None else lost.any(axis=1)
        comp = self.compensate(times_s, counts, compiled=compiled)
        sol = self._solve_batch(comp, with_covariance, compiled)
        if self.needs_pose:
            comp = self.add_pose_terms(comp, times_s, counts, sol.poses)
        measured = comp   # what the budget sees: every bar's length, before the signal mask
        if no_signal is not None and no_signal.any():   # (after the terms, as live)
            comp = Compensated(comp.cdf_lengths_m, np.where(lost, np.nan, comp.lengths_m),
                               comp.out_of_range, comp.thermal, comp.fit_columns_m)
        if self._pose_terms or (no_signal is not None and no_signal.any()):
            sol = self._solve_batch(comp, with_covariance, compiled)
        out_of_range = np.any(comp.out_of_range, axis=1)
        unsolved = out_of_range if no_signal is None else out_of_range | no_signal
        valid = sol.converged & ~unsolved
        fk_status = np.where(unsolved, np.int8(FkStatus.OUT_OF_SPAN), sol.status)
        cov = tails = sigma_d = None
        if with_covariance and sol.jacobian_inverse is not None:
            observed = self.budget.observe(comp.cdf_lengths_m, comp.thermal.reference_error_m,
                                           times_s, sol.poses, epoch_s)
            rows = slice(None, None, covariance_every)
            cov = np.full((times_s.size, 6, 6), np.nan)
            lengths = self.length_covariance(measured, observed, rows=rows)
            cov[rows] = pose_covariance(sol.jacobian_inverse[rows], lengths,
                                        measured.thermal.plate_scale[rows], compiled=compiled)
            if with_length_covariance:
                sigma_d = np.full((times_s.size, 6, 6), np.nan)
                sigma_d[rows] = lengths
            if tails_every:
                rows = slice(None, None, tails_every)
                tails = np.full((times_s.size, 6, 7), np.nan)
                tails[rows] = self.tails(sol.jacobian_inverse, measured, observed, rows=rows)
        return ProcessResult(times_s, comp, sol.poses, sol.converged, valid, fk_status,
                             sol.iterations, sol.residual_m, sol.condition, cov, no_signal, tails,
                             sigma_d)

    def _solve_batch(self, comp: Compensated, with_inverse: bool, compiled: bool | None):
        """FK of d / s with the nominal joints, translations times s (the module docstring)."""
        scale = comp.thermal.plate_scale
        sol = self.fk.solve_series(comp.lengths_m / scale[:, None], with_inverse=with_inverse,
                                   compiled=compiled)
        sol.poses[:, :3] *= scale[:, None]
        return sol

    def covariance(self, jinv: FloatArray, comp: Compensated, observed: Observed | None = None,
                   *, rows: slice | None = None, compiled: bool | None = None) -> FloatArray:
        """Pose covariance of N samples, (N, 6, 6) [m, rad]^2: J^-1 Sigma_d J^-T with Sigma_d of
        the budget, the translation rows and columns scaled by the plates' expansion.

        jinv : ndarray, shape (N, 6, 6) — inverse Jacobians at the solutions (on d / s)
        observed : what :meth:`LengthBudget.observe` returned for these samples, or None
        rows : only these samples (default all)
        """
        r = slice(None) if rows is None else rows
        return pose_covariance(jinv[r], self.length_covariance(comp, observed, rows=rows),
                               comp.thermal.plate_scale[r], compiled=compiled)

    def length_covariance(self, comp: Compensated, observed: Observed | None = None,
                          *, rows: slice | None = None) -> FloatArray:
        """Sigma_d of N samples, (N, 6, 6) [m^2]: the budget's covariance of the six measuring
        bars' lengths (what :meth:`covariance` propagates); arguments as there."""
        r = slice(None) if rows is None else rows
        th = comp.thermal
        return self.budget.covariance(
            comp.lengths_m[r], th.reference_error_m[r], th.temp_change_c[r], th.bar_error_m[r],
            None if comp.fit_columns_m is None else comp.fit_columns_m[r],
            None if observed is None else observed[r])

    def tails(self, jinv: FloatArray, comp: Compensated, observed: Observed | None = None,
              *, rows: slice | None = None) -> FloatArray:
        """Where the pose covariance's error is lighter-tailed than a Gaussian, (N, 6, 7)
        [m, rad] (:func:`~mmd_ros.core.uncertainty.tail_columns` of the budget's
        :meth:`~mmd_ros.core.budget.LengthBudget.light_tails`); arguments as :meth:`covariance`.
        """
        r = slice(None) if rows is None else rows
        th = comp.thermal
        cumulant, known = self.budget.light_tails(
            comp.lengths_m[r], th.reference_error_m[r], th.temp_change_c[r], th.bar_error_m[r],
            None if comp.fit_columns_m is None else comp.fit_columns_m[r],
            None if observed is None else observed[r])
        return tail_columns(jinv[r], cumulant, known, th.plate_scale[r], KNOWN_ERROR_SHAPE)

    # -- stream --------------------------------------------------------------------------------
    def process_sample(self, time_s: float, counts: FloatArray, *,
                       with_covariance: bool = False) -> SampleResult:
        """One sample of a stream; call in time order. FK warm-starts from the previous poses."""
        c = np.asarray(counts, dtype=np.float64).reshape(1, -1)
        t = np.array([time_s], dtype=np.float64)
        comp = self.compensate(t, c)
        scale = float(comp.thermal.plate_scale[0])
        sol = self.fk.solve(comp.lengths_m[0] / scale)
        pose = sol.pose.copy()
        if self.needs_pose:
            first = pose.copy()
            first[:3] *= scale
            if not sol.converged:  # the terms still see the sample, so their state stays in step
                first[:] = np.nan
            comp = self.add_pose_terms(comp, t, c, first[None])
            if self._pose_terms:
                sol = self.fk.solve(comp.lengths_m[0] / scale)
                pose = sol.pose.copy()
        pose[:3] *= scale
        out = comp.out_of_range[0]
        cov = None
        if with_covariance:
            observed = self.budget.observe(comp.cdf_lengths_m, comp.thermal.reference_error_m, t,
                                           pose[None])
            if sol.converged:
                jinv = np.linalg.inv(sol.jacobian)
                cov = self.covariance(jinv[None], comp, observed)[0]
        status = FkStatus.OUT_OF_SPAN if out.any() else sol.status
        return SampleResult(comp.lengths_m[0], out, comp.thermal.reference_error_m[0],
                            float(comp.thermal.temp_change_c[0]), pose, sol.converged,
                            bool(sol.converged and not out.any()), status, sol.iterations,
                            sol.residual_m if math.isfinite(sol.residual_m) else math.nan, cov)
