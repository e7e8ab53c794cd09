"""From raw counts to poses: CDF (Eq. 10) → thermal (Eqs. 11–13) → model terms → FK.

:class:`Pipeline` is the one implementation used by ``mmd process`` (batch) and by the ROS
nodes (stream, :meth:`Pipeline.process_sample`). Plate expansion scales both plates' joints by
``s``; since |R s a + t - s b| = s |R a + t/s - b|, FK runs on d/s with the nominal geometry and
the translation is multiplied by s.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.calibration import Calibration, CdfBank
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.kinematics import ForwardKinematics
from mmd_ros.core.model import Model, TermContext
from mmd_ros.core.thermal import (
    ReferenceBar, ThermalCompensation, ThermalState, reference_plate_growth,
)

__all__ = ['Compensated', 'Pipeline', 'ProcessResult', 'SampleResult']

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Compensated:
    """Bar lengths of N samples.

    cdf_lengths_m : ndarray, shape (N, 6) — f_i(q_i), Eq. (10) [m]
    lengths_m : ndarray, shape (N, 6) — after thermal compensation and model terms [m]
    out_of_range : ndarray, shape (N, 6) — count outside the calibrated span (extrapolated)
    thermal : :class:`ThermalState`
    """

    cdf_lengths_m: FloatArray
    lengths_m: FloatArray
    out_of_range: NDArray[np.bool_]
    thermal: ThermalState


@dataclass(frozen=True)
class ProcessResult:
    """Poses of N samples.

    poses : ndarray, shape (N, 6) — [x, y, z, phi, theta, psi] of {U} in {L} [m, rad]
    valid : ndarray, shape (N,) — converged and no bar out of range; only these are measurements
    covariance : ndarray, shape (N, 6, 6), or None — pose covariance [m, rad]^2
    """

    times_s: FloatArray
    compensated: Compensated
    poses: FloatArray
    converged: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    iterations: NDArray[np.int64]
    residual_m: FloatArray
    condition: FloatArray
    covariance: FloatArray | None


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
        self.fk = ForwardKinematics(device.geometry)
        self._pose_terms = [t for t in self.model.terms if t.needs_pose]
        self._length_terms = [t for t in self.model.terms if not t.needs_pose]

    def reset(self) -> None:
        """Start a new run: forget FK warm starts and term states."""
        self.fk.reset()
        self.model.reset()

    # -- lengths -------------------------------------------------------------------------------
    def compensate(self, times_s: FloatArray, counts: FloatArray) -> Compensated:
        """Compensated bar lengths of N consecutive samples, with the terms that need no pose.

        times_s : ndarray, shape (N,) [s]
        counts : ndarray, shape (N, 8) — raw counts of all channels
        """
        counts = np.asarray(counts, dtype=np.float64)
        cdf_lengths, out = self.cdfs(counts[:, self.channels])
        thermal = self.thermal.state(counts, cdf_lengths)
        lengths = cdf_lengths - thermal.bar_error_m
        if self._length_terms:
            ctx = TermContext(np.asarray(times_s, dtype=np.float64), counts, lengths.copy(),
                              cdf_lengths, thermal.reference_error_m, thermal.temp_change_c)
            for term in self._length_terms:
                lengths = lengths + term.correction(ctx)
        return Compensated(cdf_lengths, lengths, out, thermal)

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
        return Compensated(comp.cdf_lengths_m, lengths, comp.out_of_range, comp.thermal)

    # -- batch ---------------------------------------------------------------------------------
    def process(self, times_s: FloatArray, counts: FloatArray, *,
                with_covariance: bool = False, with_condition: bool = False) -> ProcessResult:
        """Poses of N consecutive samples (one run, in time order)."""
        times_s = np.asarray(times_s, dtype=np.float64)
        comp = self.compensate(times_s, counts)
        sol = self._solve_batch(comp, with_covariance or with_condition, with_condition)
        if self._pose_terms:
            comp = self.add_pose_terms(comp, times_s, counts, sol[0])
            sol = self._solve_batch(comp, with_covariance or with_condition, with_condition)
        poses, converged, iterations, residual, condition, jinv = sol
        valid = converged & ~np.any(comp.out_of_range, axis=1)
        cov = None
        if with_covariance and jinv is not None:
            cov = self._covariance(jinv, comp.thermal.plate_scale)
        return ProcessResult(times_s, comp, poses, converged, valid, iterations, residual,
                             condition, cov)

    def _solve_batch(self, comp: Compensated, with_inverse: bool, with_condition: bool):
        scale = comp.thermal.plate_scale
        sol = self.fk.solve_series(comp.lengths_m / scale[:, None], with_inverse=with_inverse,
                                   with_condition=with_condition)
        poses = sol.poses.copy()
        poses[:, :3] *= scale[:, None]
        return poses, sol.converged, sol.iterations, sol.residual_m, sol.condition, sol.jacobian_inverse

    def _covariance(self, jinv: FloatArray, scale: FloatArray) -> FloatArray:
        """J^-1 (sigma^2 I) J^-T with the translation rows scaled back by the plate expansion."""
        sigma = self.model.length_sigma_m
        cov = sigma * sigma * (jinv @ np.swapaxes(jinv, -1, -2))
        s = np.ones(jinv.shape[:1] + (6,))
        s[:, :3] = scale[:, None]
        return cov * s[:, :, None] * s[:, None, :]

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
        if self._pose_terms:
            first = pose.copy()
            first[:3] *= scale
            if not sol.converged:  # the terms still see the sample, so their state stays in step
                first[:] = np.nan
            comp = self.add_pose_terms(comp, t, c, first[None])
            sol = self.fk.solve(comp.lengths_m[0] / scale)
            pose = sol.pose.copy()
        pose[:3] *= scale
        out = comp.out_of_range[0]
        cov = None
        if with_covariance and sol.converged:
            jinv = np.linalg.inv(sol.jacobian)
            cov = self._covariance(jinv[None], comp.thermal.plate_scale)[0]
        return SampleResult(comp.lengths_m[0], out, comp.thermal.reference_error_m[0],
                            float(comp.thermal.temp_change_c[0]), pose, sol.converged,
                            bool(sol.converged and not out.any()), sol.iterations,
                            sol.residual_m if math.isfinite(sol.residual_m) else math.nan, cov)
