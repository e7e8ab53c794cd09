"""Thermal compensation with the reference ball bar(s), section 3.3.

The reference bar rests on a ZERODUR socket pair whose distance d_r^j does not change with
temperature, so whatever its CDF reads beyond d_r^j is the bar's thermal error, Eq. (11):

    eps_j(t) = f_ref(q_ref(t)) - d_r^j

With one reference bar (the prototype: R3R6, d_r^4 = 323 mm) every measuring bar is corrected by
that error, Eq. (13): d_i* = f_i(q_i) - eps_4. With two reference bars on d_r^j < d_r^k the error
is interpolated linearly in the bar's length, Eq. (12).

Fig. 10's bar model gives the sensitivity that links the reference error to a temperature change:
a bar of fixed part L (= l_L + l_S + l_R = d_min) with rod CTE a_r and scale CTE a_s reads, at a
true centre distance d, an apparent change of -(a_r L + a_s (d - L)) dT. The plates' expansion
(end of section 3.3) is estimated from that temperature change.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.calibration import CdfBank, CentreDistanceFunction
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import ModelError

__all__ = ['CMM_TEMP_C', 'ReferenceBar', 'ThermalCompensation', 'ThermalState',
           'reference_plate_growth', 'thermal_sensitivity']

FloatArray = NDArray[np.float64]

#: Temperature at which the joint positions of Table 1 were measured on the CMM [°C].
CMM_TEMP_C = 20.0

MODES = ('auto', 'single', 'interpolate', 'off')


def reference_plate_growth(device: DeviceDescription, ambient_c: float | None) -> float:
    """1 + a_ref (T_cal - 20 °C): how much longer the reference pairs are at the calibration's
    temperature than the CMM distances d_r^j of Table 2, measured at 20 °C.

    The bars are calibrated at the room's temperature (section 3.2), so each CDF point is
    (q^j, d_r^j at T_cal), not d_r^j. ZERODUR expands little (0.02 ppm/°C) but not nothing: at
    24.2 °C every pair is 0.084 ppm longer, which a CDF through the 20 °C distances turns into
    bars reading 21–32 nm short, an error of the pose that follows the bars' lengths. 1 when the
    calibration does not say its temperature.
    """
    if ambient_c is None:
        return 1.0
    return 1.0 + device.reference_plate_cte_per_c * (ambient_c - CMM_TEMP_C)


def thermal_sensitivity(device: DeviceDescription, distance_m: Any) -> Any:
    """d eps / dT of a bar at the centre distance ``distance_m`` (Fig. 10): its fixed part L
    with the rods' CTE, the rest with the scale's, -(a_r L + a_s (d - L)) [m/°C] (negative: a
    warm bar reads short); a float or an array, as ``distance_m``."""
    fixed = device.fixed_length_m
    return -(device.rod_cte_per_c * fixed + device.scale_cte_per_c * (distance_m - fixed))


@dataclass(frozen=True)
class ReferenceBar:
    """A reference bar: its channel, the pair distance it rests on, its CDF and thermal zero."""

    channel: int
    distance_m: float
    cdf: CentreDistanceFunction
    zero_m: float = 0.0


@dataclass(frozen=True)
class ThermalState:
    """Thermal quantities of N samples.

    reference_error_m : ndarray, shape (N, k) — Eq. (11) per reference bar [m]
    bar_error_m : ndarray, shape (N, 6) — thermal error subtracted from each bar [m]
    temp_change_c : ndarray, shape (N,) — temperature change since the thermal zero, estimated
        from the reference bar(s) [°C]
    plate_scale : ndarray, shape (N,) — 1 + a_plate * dT_plate applied to the joint positions
    """

    reference_error_m: FloatArray
    bar_error_m: FloatArray
    temp_change_c: FloatArray
    plate_scale: FloatArray


class ThermalCompensation:
    """Eqs. (11)–(13) and the plate expansion for one device.

    mode : 'auto' (Eq. 12 with two reference bars, Eq. 13 with one), 'single' (Eq. 13 with the
        first reference bar), 'interpolate' (Eq. 12; needs two), 'off' (no thermal correction)
    plate_expansion : scale the joint positions by the plates' estimated expansion
    ambient_at_zero_c : ambient temperature when the thermal zero was set; the plates' expansion
        is counted from the CMM's 20 °C, so this adds (ambient_at_zero_c - 20) to dT
    """

    def __init__(self, device: DeviceDescription, references: list[ReferenceBar], *,
                 mode: str = 'auto', plate_expansion: bool = True,
                 ambient_at_zero_c: float | None = None) -> None:
        if mode not in MODES:
            raise ModelError(f'thermal mode must be one of {MODES}, got {mode!r}')
        if mode != 'off' and not references:
            raise ModelError('thermal compensation needs a reference bar; set thermal.mode: off')
        if mode == 'interpolate' and len(references) < 2:
            raise ModelError('thermal.mode interpolate (Eq. 12) needs two reference bars; '
                             f'the device has {len(references)}')
        self.references = sorted(references, key=lambda r: r.distance_m)
        self.mode = ('interpolate' if len(references) >= 2 else 'single') if mode == 'auto' else mode
        self.plate_expansion = plate_expansion
        self.plate_cte = device.plate_cte_per_c
        self.offset_c = 0.0 if ambient_at_zero_c is None else ambient_at_zero_c - CMM_TEMP_C
        self._sensitivity = np.array([thermal_sensitivity(device, r.distance_m)
                                      for r in self.references])
        # The pair under a reference bar grows with the reference plate: f_ref - d_r reads the
        # bar's error eps plus d_r a_ref dT, and dT = eps / sensitivity, so
        # eps = (f_ref - d_r) / (1 + d_r a_ref / sensitivity).
        self._pair_factor = 1.0 + np.array([r.distance_m * device.reference_plate_cte_per_c
                                            for r in self.references]) / self._sensitivity
        # Eq. (11) of every reference bar in one pass of their CDFs (when they have as many
        # points each, as the calibration routine makes them)
        self._channels = [r.channel for r in self.references]
        self._offsets_m = np.array([r.distance_m + r.zero_m for r in self.references])
        self._bank = (CdfBank([r.cdf for r in self.references])
                      if len({r.cdf.counts.size for r in self.references}) == 1 else None)

    def sensitivity_m_per_c(self) -> FloatArray:
        """d eps / dT of each reference bar, shape (k,) [m/°C] (negative: a warm bar reads short)."""
        return self._sensitivity.copy()

    def reference_errors(self, counts: FloatArray) -> FloatArray:
        """Eq. (11) for every reference bar.

        counts : ndarray, shape (N, 8) — raw counts of all channels
        returns : ndarray, shape (N, k) [m]
        """
        if self._bank is not None:
            return (self._bank(counts[:, self._channels])[0] - self._offsets_m) / self._pair_factor
        cols = [r.cdf(counts[:, r.channel])[0] - r.distance_m - r.zero_m for r in self.references]
        return np.stack(cols, axis=1) / self._pair_factor if cols else np.zeros((counts.shape[0], 0))

    def state(self, counts: FloatArray, lengths_m: FloatArray) -> ThermalState:
        """Thermal state of N samples.

        counts : ndarray, shape (N, 8) — raw counts
        lengths_m : ndarray, shape (N, 6) — CDF lengths f_i(q_i) of the measuring bars [m]
        """
        n = lengths_m.shape[0]
        if self.mode == 'off':
            zeros = np.zeros(n)
            return ThermalState(np.zeros((n, 0)), np.zeros((n, 6)), zeros, np.ones(n))
        eps = self.reference_errors(counts)
        if self.mode == 'single':
            bar_error = np.repeat(eps[:, :1], 6, axis=1)  # Eq. (13)
            temp_change = eps[:, 0] / self._sensitivity[0]
        else:
            lo, hi = self.references[0], self.references[-1]
            frac = (lengths_m - lo.distance_m) / (hi.distance_m - lo.distance_m)
            bar_error = eps[:, :1] + frac * (eps[:, -1:] - eps[:, :1])  # Eq. (12)
            temp_change = np.mean(eps / self._sensitivity, axis=1)
        if self.plate_expansion:
            scale = 1.0 + self.plate_cte * (temp_change + self.offset_c)
        else:
            scale = np.ones(n)
        return ThermalState(eps, bar_error, temp_change, scale)
