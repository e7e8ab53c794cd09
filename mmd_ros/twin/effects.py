"""What the twin's bars get wrong: every error source as a switchable physical parameter.

:meth:`Effects.ideal` keeps only what the compensation model of the paper accounts for
(quantisation, a small read noise, unknown count offsets, identical bars following the room
with one time constant, plates expanding in step with them); :meth:`Effects.none` takes the
read noise and the count offsets away as well, and with a room held at 20 °C (the ambient
:data:`PRESET_AMBIENT` gives it) nothing is left but the quantisation to one count;
:meth:`Effects.realistic` switches everything on at plausible sizes. Where each effect enters
the reading is described in :mod:`mmd_ros.twin.physics`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields
from typing import Any

from mmd_ros.twin.codec import assign, from_plain, to_plain
from mmd_ros.twin.errors import TwinError

__all__ = ['Bump', 'Effects', 'PRESETS', 'PRESET_AMBIENT']

#: Names of the effect presets (:meth:`Effects.preset`), in the order the CLI lists them.
PRESETS = ('none', 'ideal', 'realistic')

#: The room temperature each preset runs in unless another is asked for (``--ambient``):
#: ``none`` holds the room at the CMM's 20 °C, so that the bars and plates keep their 20 °C
#: lengths; the others follow the 20 h profile of section 4.1.
PRESET_AMBIENT = {'none': 'constant:20', 'ideal': 'section_4_1', 'realistic': 'section_4_1'}


@dataclass(frozen=True)
class Bump:
    """A localised error in one bar's scale, outside any catalogue of effects.

    channel : int — terminal channel of the bar (0..7)
    centre_m : float — centre distance at which the bump sits (at 20 °C) [m]
    width_m : float — standard deviation of its Gaussian shape [m]
    height_m : float — reading error at its centre [m]
    """

    channel: int
    centre_m: float
    width_m: float
    height_m: float

    def __post_init__(self) -> None:
        if not 0 <= self.channel <= 7:
            raise TwinError(f'bump.channel must be a terminal channel 0..7, got {self.channel}')
        if not (self.width_m > 0 and math.isfinite(self.width_m)):
            raise TwinError(f'bump.width_m must be > 0, got {self.width_m}')
        if not (math.isfinite(self.centre_m) and math.isfinite(self.height_m)):
            raise TwinError('bump.centre_m and bump.height_m must be finite')


@dataclass(frozen=True)
class Effects:
    """Error sources of the simulated bars and plates. Amplitudes are peak values.

    read_noise_m : Gaussian read noise (standard deviation) before quantisation [m]
    count_offsets : unknown power-on count offset of each channel (uniform +-1e6 counts on a
        per-channel base); off gives zero offsets, handy when debugging
    scale_nonlinearity_m : peak of a smooth per-bar scale error, harmonics 1 and 2 over the bar's
        stroke with random phases [m]
    rod_cte_per_c : effective CTE of the rod assemblies (l_L + l_S + l_R of Fig. 10) [1/°C];
        None takes the device's INVAR value
    thermal_mismatch : relative standard deviation of each bar's rod CTE and time constant
    bar_time_constant_s : first-order lag of a bar's temperature behind the room [s]
    plate_expansion : upper, lower and reference plates expand with their CTEs from 20 °C
    plate_time_constant_s : first-order lag of the plates behind the room [s]
    hysteresis_m : amplitude of the friction hysteresis of a bar's reading [m] (each bar gets
        0.5..1.5 times it); the reading lags the motion
    hysteresis_travel_m : travel over which the friction state turns (Dahl model) [m]
    cyclic_error_m : amplitude of the encoder's sub-division error [m]
    cyclic_period_m : its period, the scale's signal period [m]
    sampling_skew_s : largest latch delay of a channel; each channel reads at t + skew_k with
        skew_k uniform in [0, sampling_skew_s] [s]
    gravity_sag_m : reading error of a horizontal bar from its gravity sag [m]; a bar with axis
        z-component n_z reads gravity_sag_m * (1 - n_z^2) long
    gravity_sag_spread : relative standard deviation of this twin's sag about gravity_sag_m,
        one draw per twin, alike for its bars (a characterisation states the figure of the bar
        type, these bars have their own); the twin's description states gravity_sag_m and this
        spread times it as the figure's uncertainty (0: the figure is exact)
    drift_m_per_s : largest slow drift of a bar's reading (each bar a uniform fraction in
        [-1, 1]), counted from the twin's time 0 [m/s]
    placement_repeatability_m : standard deviation of a bar's seating offset on a socket pair
        (fixed per bar and pair) [m]
    bump : optional localised scale error of one bar
    """

    read_noise_m: float = 5e-9
    count_offsets: bool = True
    scale_nonlinearity_m: float = 0.0
    rod_cte_per_c: float | None = None
    thermal_mismatch: float = 0.0
    bar_time_constant_s: float = 1200.0
    plate_expansion: bool = True
    plate_time_constant_s: float = 1200.0
    hysteresis_m: float = 0.0
    hysteresis_travel_m: float = 5e-6
    cyclic_error_m: float = 0.0
    cyclic_period_m: float = 20e-6
    sampling_skew_s: float = 0.0
    gravity_sag_m: float = 0.0
    gravity_sag_spread: float = 0.0
    drift_m_per_s: float = 0.0
    placement_repeatability_m: float = 0.0
    bump: Bump | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or value is None or isinstance(value, Bump):
                continue
            if not math.isfinite(value):
                raise TwinError(f'effect {f.name} must be finite, got {value}')
            if f.name != 'drift_m_per_s' and value < 0:
                raise TwinError(f'effect {f.name} must be >= 0, got {value}')
        for name in ('hysteresis_travel_m', 'cyclic_period_m'):
            if getattr(self, name) <= 0:
                raise TwinError(f'effect {name} must be > 0, got {getattr(self, name)}')
        if self.thermal_mismatch > 0.3:
            raise TwinError(f'effect thermal_mismatch is a relative spread, at most 0.3, '
                            f'got {self.thermal_mismatch}')
        if self.gravity_sag_spread > 0.5:
            raise TwinError(f'effect gravity_sag_spread is a relative spread, at most 0.5, '
                            f'got {self.gravity_sag_spread}')
        if self.sampling_skew_s > 1e-3:
            raise TwinError(f'effect sampling_skew_s must stay below one 1 kHz sample period, '
                            f'got {self.sampling_skew_s} s')

    def rod_cte(self, described_per_c: float) -> float:
        """The bars' effective rod CTE: ``rod_cte_per_c``, else the one the device description
        states, ``described_per_c`` [1/°C]."""
        return described_per_c if self.rod_cte_per_c is None else self.rod_cte_per_c

    @classmethod
    def ideal(cls) -> Effects:
        """Only what the model compensates: 50 nm quantisation, 5 nm read noise, count offsets,
        identical bars following the room with a 1200 s lag, plates expanding with the same lag
        (so that the reference bar tells their temperature too)."""
        return cls()

    @classmethod
    def none(cls) -> Effects:
        """No error source at all: no read noise, no count offsets (a count is the scale
        position since the readhead's index, 50 nm each); the bars and plates are the ideal
        set's, so in a room at 20 °C (:data:`PRESET_AMBIENT`) they keep their calibrated
        lengths and the counts are the true lengths quantised to one count. In another room
        they still expand with the device's CTEs, as the default model expects."""
        return cls(read_noise_m=0.0, count_offsets=False)

    @classmethod
    def realistic(cls) -> Effects:
        """Every effect on at a plausible size, sized on the paper where it reports one: the
        effective rod CTE of 3.5 ppm/°C gives the up to 6 µm thermal error of section 4.1 over
        its 5.8 °C swing; a 5 % spread between bars and 0.02 µm/h of drift leave about the
        0.6 µm it saw after compensation; 0.3 µm of hysteresis gives a psi reversal of about
        4.5 arc-seconds, the MMD's share in Table 4; 2 µm of scale nonlinearity leaves about
        0.5 µm between calibration points (the +-0.8 µm of Fig. 13)."""
        return cls(
            read_noise_m=10e-9,
            scale_nonlinearity_m=2e-6,
            rod_cte_per_c=3.5e-6,
            thermal_mismatch=0.05,
            plate_time_constant_s=2400.0,
            hysteresis_m=0.3e-6,
            cyclic_error_m=20e-9,
            sampling_skew_s=50e-6,
            gravity_sag_m=0.1e-6,
            drift_m_per_s=0.02e-6 / 3600.0,
            placement_repeatability_m=30e-9,
        )

    @classmethod
    def preset(cls, name: str) -> Effects:
        """``'none'``, ``'ideal'`` or ``'realistic'`` (:data:`PRESETS`)."""
        presets = {'none': cls.none, 'ideal': cls.ideal, 'realistic': cls.realistic}
        if name not in presets:
            raise TwinError(f'unknown effects preset {name!r}; choose one of {sorted(presets)}')
        return presets[name]()

    # -- serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return to_plain(self)

    @classmethod
    def from_dict(cls, data: Any) -> Effects:
        return from_plain(cls, data)

    def with_assignments(self, assignments: Iterable[str]) -> Effects:
        """A copy with ``name=value`` assignments applied (e.g. from ``--effect``)."""
        return assign(self, assignments)

