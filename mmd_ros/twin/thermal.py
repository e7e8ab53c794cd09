"""Room temperature and the first-order thermal lag of bars and plates (section 4.1).

The ambient temperature is a chain of smooth ramps, each an exponential approach that reaches
its end temperature exactly at the end of the ramp:

    T_a(s) = T_start + (T_end - T_start) (1 - exp(-s / tau_a)) / (1 - exp(-D / tau_a))

for 0 <= s <= D, held at the last end temperature afterwards and at the initial temperature
before time 0, where everything is in equilibrium. A bar or plate follows the room with a
first-order lag, dT/dt = (T_a - T) / tau. Within a ramp the input has the form A + B exp(-s/tau_a),
so the lagged temperature has the closed form

    T(s) = A + B' exp(-s / tau_a) + (T_0 - A - B') exp(-s / tau),   B' = B tau_a / (tau_a - tau)

(and A + (T_0 - A) exp(-s/tau) + B (s/tau) exp(-s/tau) when tau = tau_a). Temperatures are
therefore exact at any time, in any order, which keeps chunked simulations identical to
one-shot ones. Times are seconds on the profile's own clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.calibration import AMBIENT_RANGE_C
from mmd_ros.twin.codec import from_plain, to_plain
from mmd_ros.twin.errors import TwinError

__all__ = ['REFERENCE_TEMP_C', 'AmbientProfile', 'Ramp', 'check_room']

FloatArray = NDArray[np.float64]

#: Temperature at which the CMM measured joints and reference distances, and at which a bar's
#: scale and rods have their nominal lengths [°C].
REFERENCE_TEMP_C = 20.0

#: Relative difference of two time constants below which the degenerate lag formula is used.
_SAME_TAU = 1e-6


def check_room(name: str, temp_c: float) -> None:
    """A room temperature of a profile: within what a calibration may state (the twin's
    calibration records the room's temperature; a log whose calibration says -300 °C is
    refused by every command that reads it). The profile never leaves the range of its
    temperatures: each ramp approaches its end exponentially."""
    low, high = AMBIENT_RANGE_C
    if not low <= temp_c <= high:       # False for NaN too
        raise TwinError(f'{name} must be in [{low:g}, {high:g}] °C (a room temperature a '
                        f'calibration may state), got {temp_c}')


@dataclass(frozen=True)
class Ramp:
    """One smooth change of the room temperature.

    duration_s : float — length of the ramp [s]
    end_c : float — temperature reached at the end [°C]
    time_constant_s : float — time constant of the exponential approach [s]
    """

    duration_s: float
    end_c: float
    time_constant_s: float

    def __post_init__(self) -> None:
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise TwinError(f'ramp duration_s must be > 0, got {self.duration_s}')
        if not (self.time_constant_s > 0 and math.isfinite(self.time_constant_s)):
            raise TwinError(f'ramp time_constant_s must be > 0, got {self.time_constant_s}')
        check_room('ramp end_c', self.end_c)


@dataclass(frozen=True)
class AmbientProfile:
    """Room temperature against time: ``initial_c`` until 0, then ``ramps`` one after the other.

    initial_c : float — temperature before and at time 0 [°C]
    ramps : tuple of Ramp
    """

    initial_c: float
    ramps: tuple[Ramp, ...] = ()

    def __post_init__(self) -> None:
        check_room('initial_c', self.initial_c)
        object.__setattr__(self, 'ramps', tuple(self.ramps))
        knots = [0.0]
        starts = [self.initial_c]
        for ramp in self.ramps:
            knots.append(knots[-1] + ramp.duration_s)
            starts.append(ramp.end_c)
        # Segment k (k < number of ramps) carries the input A_k + B_k exp(-(t - knot_k)/tau_k);
        # the last segment holds the final temperature (B = 0).
        a_coef, b_coef, taus = [], [], []
        for ramp, start in zip(self.ramps, starts):
            c = -math.expm1(-ramp.duration_s / ramp.time_constant_s)
            a_coef.append(start + (ramp.end_c - start) / c)
            b_coef.append(-(ramp.end_c - start) / c)
            taus.append(ramp.time_constant_s)
        a_coef.append(starts[-1])
        b_coef.append(0.0)
        taus.append(1.0)
        object.__setattr__(self, '_knots', np.array(knots))
        object.__setattr__(self, '_a', np.array(a_coef))
        object.__setattr__(self, '_b', np.array(b_coef))
        object.__setattr__(self, '_tau', np.array(taus))

    # -- presets -------------------------------------------------------------------------------
    @classmethod
    def constant(cls, temp_c: float) -> AmbientProfile:
        """A room held at ``temp_c`` [°C]."""
        return cls(float(temp_c))

    @classmethod
    def section_4_1(cls) -> AmbientProfile:
        """The 20 h test of section 4.1 (Fig. 11a): air conditioner on for 8 h, 24.2 -> 18.4 °C,
        then off, the room warming slowly to 22.1 °C at 20 h."""
        return cls(24.2, (Ramp(8 * 3600.0, 18.4, 2.5 * 3600.0),
                          Ramp(12 * 3600.0, 22.1, 5.0 * 3600.0)))

    @property
    def duration_s(self) -> float:
        """End of the last ramp [s]."""
        return float(self._knots[-1])

    # -- evaluation ----------------------------------------------------------------------------
    def __call__(self, times_s: ArrayLike) -> FloatArray:
        """Room temperature [°C] at ``times_s`` [s] (any shape)."""
        t = np.asarray(times_s, dtype=np.float64)
        k, s = self._segment(t)
        return np.where(t < 0, self.initial_c,
                        self._a[k] + self._b[k] * np.exp(-s / self._tau[k]))

    def lagged(self, times_s: ArrayLike, time_constant_s: ArrayLike) -> FloatArray:
        """Temperature [°C] of a body following the room with a first-order lag.

        times_s : array_like, shape (N,) [s]
        time_constant_s : float or array_like, shape (M,) — lag of each body [s]; 0 follows
            the room without lag
        returns : ndarray, shape (N,) for a scalar time constant, else (N, M)
        """
        t = np.asarray(times_s, dtype=np.float64)
        taus = np.asarray(time_constant_s, dtype=np.float64)
        out = np.stack([self._lag_one(t, float(tau)) for tau in taus.ravel()], axis=-1)
        return out[..., 0] if taus.ndim == 0 else out

    def _segment(self, t: FloatArray) -> tuple[NDArray[np.intp], FloatArray]:
        k = np.clip(np.searchsorted(self._knots, t, side='right') - 1, 0, self._a.size - 1)
        return k, np.maximum(t - self._knots[k], 0.0)

    def _lag_one(self, t: FloatArray, tau: float) -> FloatArray:
        if tau < 0 or not math.isfinite(tau):
            raise TwinError(f'a thermal time constant must be finite and >= 0, got {tau}')
        if tau == 0.0:
            return self(t)
        b_lag = np.empty_like(self._b)
        same = np.abs(self._tau - tau) <= _SAME_TAU * tau
        b_lag[~same] = self._b[~same] * self._tau[~same] / (self._tau[~same] - tau)
        b_lag[same] = 0.0
        # Lagged temperature at each knot, from equilibrium at time 0.
        start = np.empty_like(self._a)
        start[0] = self.initial_c
        for k in range(self._a.size - 1):
            start[k + 1] = self._lag_formula(self._knots[k + 1] - self._knots[k], k, tau, start[k],
                                             b_lag[k], bool(same[k]))
        k, s = self._segment(t)
        out = np.empty_like(s)
        for seg in np.unique(k):
            sel = k == seg
            out[sel] = self._lag_formula(s[sel], int(seg), tau, start[seg], b_lag[seg], bool(same[seg]))
        return np.where(t < 0, self.initial_c, out)

    def _lag_formula(self, s: Any, k: int, tau: float, t0: float, b_lag: float, same: bool) -> Any:
        a, b, tau_a = self._a[k], self._b[k], self._tau[k]
        decay = np.exp(-s / tau)
        if same:
            return a + (t0 - a) * decay + b * (s / tau) * decay
        return a + b_lag * np.exp(-s / tau_a) + (t0 - a - b_lag) * decay

    # -- serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return to_plain(self)

    @classmethod
    def from_dict(cls, data: Any) -> AmbientProfile:
        return from_plain(cls, data)
