"""Device description: the YAML file in ``config/`` that says what an MMD is made of.

The file keeps the paper's units and says them in every key (``*_mm``, ``*_ppm_per_c``,
``*_deg``); :class:`DeviceDescription` holds SI values. A malformed or inconsistent file is
refused with a :class:`ConfigError` naming the key and the problem.
"""

from __future__ import annotations

import copy
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from mmd_ros.core import validate
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.kinematics import Geometry
from mmd_ros.core.units import M_PER_MM, M_PER_NM, M_PER_UM, PPM
from mmd_ros.core.yamlio import read_yaml

__all__ = [
    'Channel', 'DeviceDescription', 'ReferencePair', 'find_config', 'load_device',
    'parse_device',
]

ROLES = ('measuring', 'reference', 'unused')
#: The keys a device description may hold, per section (``inherit`` is resolved before);
#: anything else is refused as a typo (:func:`mmd_ros.core.validate.known_keys`).
DEVICE_KEYS = ('format_version', 'name', 'joints', 'reference_plate', 'bars', 'plates', 'limits',
               'terminal')
SECTION_KEYS = {
    'joints': ('use', 'upper_design_mm', 'upper_measured_mm', 'lower_design_mm', 'lower_measured_mm'),
    'reference_plate': ('use', 'cte_ppm_per_c', 'distance_uncertainty_um',
                        'seating_repeatability_nm', 'pairs'),
    'bars': ('range_mm', 'encoder_resolution_nm', 'scale_cte_ppm_per_c', 'rod_cte_ppm_per_c',
             'fixed_length_mm', 'thermal_mismatch_fraction', 'subdivision_error_nm',
             'signal_period_um', 'friction_hysteresis_nm', 'gravity_sag_nm',
             'gravity_sag_uncertainty_nm', 'drift_nm_per_h', 'rod_cte_uncertainty_ppm_per_c'),
    'plates': ('position_layer_cte_ppm_per_c', 'vertical'),
    'limits': ('upper_tilt_deg', 'lower_tilt_deg', 'min_bar_separation_mm'),
    'terminal': ('sample_rate_hz', 'counter_bits', 'latch_skew_us', 'channels'),
}
PAIR_KEYS = ('name', 'sockets', 'design_mm', 'measured_mm', 'uncertainty_um')
CHANNEL_KEYS = ('name', 'role', 'bar', 'pair')
N_CHANNELS = 8
#: How far a reference distance may lie outside the nominal bar range [m].
RANGE_SLACK_M = 1e-3


@dataclass(frozen=True)
class ReferencePair:
    """A reference centre distance d_r^j on the reference plate (Table 2)."""

    name: str
    sockets: tuple[str, str]
    design_m: float
    measured_m: float
    distance_m: float  # the one in use
    sigma_m: float = 0.0  # standard uncertainty of distance_m (the CMM's), 0 when not stated


@dataclass(frozen=True)
class Channel:
    """One of the terminal's eight encoder channels."""

    index: int
    name: str
    role: str  # measuring | reference | unused
    bar: int | None = None  # 1..6 for a measuring bar
    pair: str | None = None  # reference pair a reference bar rests on


@dataclass(frozen=True)
class DeviceDescription:
    """An MMD: joints, reference plate, bars, limits and terminal channel map, in SI units."""

    name: str
    source: str
    geometry: Geometry
    design_geometry: Geometry
    measured_geometry: Geometry
    pairs: tuple[ReferencePair, ...]
    bar_range_m: tuple[float, float]
    encoder_resolution_m: float
    scale_cte_per_c: float
    rod_cte_per_c: float
    plate_cte_per_c: float
    reference_plate_cte_per_c: float
    fixed_length_m: float
    upper_tilt_rad: float
    lower_tilt_rad: float
    min_bar_separation_m: float
    sample_rate_hz: float
    counter_bits: int
    channels: tuple[Channel, ...]
    raw: dict[str, Any] = field(repr=False, compare=False)
    #: sigma of a bar's thermal error left after Eqs. (12)/(13), as a fraction of the error
    #: subtracted (bars do not behave exactly alike); None when the description does not say
    thermal_mismatch_fraction: float | None = None
    #: the terminal's latch skew: every channel latches its counter at an unknown, fixed delay
    #: between 0 and this after the sample tick that stamps it (its datasheet) [s]; None when
    #: the description does not say
    latch_skew_s: float | None = None
    #: the encoders' sub-divisional (cyclic) error: the datasheet's bound a on the error the
    #: interpolation of the scale's sine signals makes within each signal period [m], and that
    #: period (the scale's grating signal period) [m]; None when the description does not say
    subdivision_error_m: float | None = None
    signal_period_m: float | None = None
    #: the bars' friction hysteresis, as the bars' characterisation states it: the amplitude h
    #: by which a bar that last lengthened reads short (half its reversal difference), RMS over
    #: bars of the type [m]; None when the description does not say (a two-sided calibration
    #: measures each bar's own)
    friction_hysteresis_m: float | None = None
    #: the bars' gravity sag, as the bars' characterisation states it: how much longer a bar
    #: reads lying horizontally than standing vertically, g (a bar whose axis has the vertical
    #: component n_z reads g (1 - n_z^2) long) [m]; None when the description does not say
    gravity_sag_m: float | None = None
    #: the standard uncertainty of that figure for these bars (how far their sag may lie from
    #: the one stated, one sigma, as the characterisation states it) [m]; None when the
    #: description does not say (then nothing is known of the figure beyond it)
    gravity_sag_sigma_m: float | None = None
    #: the upward vertical as the MMD is mounted, a unit vector in {L} (the lower plate's frame);
    #: None when the description does not say (the lower plate is then taken level: +z). The
    #: bars' gravity sag goes with their axes' component along it (:attr:`up`)
    vertical: tuple[float, float, float] | None = None
    #: how repeatably a bar seats in a socket pair of the reference plate, as the plate's
    #: characterisation states it: the standard deviation of a placement's centre distance [m];
    #: None when the description does not say (a two-sided calibration measures it)
    seating_repeatability_m: float | None = None
    #: the bound on how fast a bar's reading drifts at constant length and temperature (its
    #: encoder's and its assembly's long-term stability, as their characterisation states it):
    #: each channel's rate lies anywhere within +-this [m/s]; None when the description does not
    #: say (the drift of the readings since calibration is then not claimed)
    drift_m_per_s: float | None = None
    #: the standard uncertainty of the bars' effective rod CTE (``bars.rod_cte_ppm_per_c``: its
    #: rods, joints and holders together, as their characterisation states it) [1/°C]: what
    #: turns the reference bar's Eq. (11) error into the temperature change the plates'
    #: expansion is estimated from; None when the description does not say (the plates' scale
    #: is then claimed from the bars' thermal mismatch only)
    rod_cte_sigma_per_c: float | None = None

    @property
    def up(self) -> NDArray[np.float64]:
        """The upward vertical in {L}, (3,): the stated ``plates.vertical``, else +z (the lower
        plate level)."""
        return np.array(self.vertical if self.vertical is not None else (0.0, 0.0, 1.0))

    @property
    def reference_distances_m(self) -> NDArray[np.float64]:
        """d_r^1..d_r^7 in use, shape (7,) [m]."""
        return np.array([p.distance_m for p in self.pairs])

    def pair(self, name: str) -> ReferencePair:
        for p in self.pairs:
            if p.name == name:
                return p
        raise KeyError(f'no reference pair {name!r}; pairs are {[p.name for p in self.pairs]}')

    @property
    def measuring_channels(self) -> list[int]:
        """Channel index of bar 1..6, in bar order."""
        by_bar = {c.bar: c.index for c in self.channels if c.role == 'measuring'}
        return [by_bar[i] for i in range(1, 7)]

    @property
    def reference_channels(self) -> list[Channel]:
        """Reference-bar channels, shortest reference distance first."""
        refs = [c for c in self.channels if c.role == 'reference']
        return sorted(refs, key=lambda c: self.pair(c.pair).distance_m)

    @property
    def channel_names(self) -> list[str]:
        return [c.name for c in self.channels]

    def to_yaml(self) -> str:
        """The description as YAML (the mapping it was read from, inheritance resolved)."""
        return yaml.safe_dump(self.raw, sort_keys=False)

    def with_latch_skew(self, skew_s: float) -> DeviceDescription:
        """A copy that states the terminal's latch skew (``terminal.latch_skew_us``) [s]."""
        return self._stating('terminal', latch_skew_us=round(float(skew_s) * 1e6, 6))

    def with_subdivision_error(self, amplitude_m: float, period_m: float) -> DeviceDescription:
        """A copy that states the encoders' sub-divisional error bound and signal period
        (``bars.subdivision_error_nm``, ``bars.signal_period_um``) [m]."""
        return self._stating('bars', subdivision_error_nm=round(float(amplitude_m) * 1e9, 6),
                             signal_period_um=round(float(period_m) * 1e6, 9))

    def with_friction_hysteresis(self, amplitude_m: float) -> DeviceDescription:
        """A copy that states the bars' friction hysteresis (``bars.friction_hysteresis_nm``)
        [m]."""
        return self._stating('bars', friction_hysteresis_nm=round(float(amplitude_m) * 1e9, 6))

    def with_gravity_sag(self, sag_m: float, sigma_m: float | None = None) -> DeviceDescription:
        """A copy that states the bars' gravity sag (``bars.gravity_sag_nm``) and, unless None,
        its standard uncertainty (``bars.gravity_sag_uncertainty_nm``) [m]."""
        values = {'gravity_sag_nm': round(float(sag_m) * 1e9, 6)}
        if sigma_m is not None:
            values['gravity_sag_uncertainty_nm'] = round(float(sigma_m) * 1e9, 6)
        return self._stating('bars', **values)

    def with_reading_drift(self, rate_m_per_s: float) -> DeviceDescription:
        """A copy that states the bound on the bars' reading drift rate (``bars.drift_nm_per_h``)
        [m/s]."""
        return self._stating('bars', drift_nm_per_h=round(float(rate_m_per_s) * 1e9 * 3600.0, 6))

    def with_rod_cte_uncertainty(self, sigma_per_c: float) -> DeviceDescription:
        """A copy that states the standard uncertainty of the bars' effective rod CTE
        (``bars.rod_cte_uncertainty_ppm_per_c``) [1/°C]."""
        return self._stating('bars', rod_cte_uncertainty_ppm_per_c=round(
            float(sigma_per_c) / PPM, 6))

    def with_vertical(self, up: Any) -> DeviceDescription:
        """A copy that states the upward vertical in {L} as mounted (``plates.vertical``)."""
        return self._stating('plates', vertical=[float(v) for v in np.asarray(up, dtype=float)])

    def with_seating_repeatability(self, sigma_m: float) -> DeviceDescription:
        """A copy that states the reference plate's seating repeatability
        (``reference_plate.seating_repeatability_nm``) [m]."""
        return self._stating('reference_plate',
                             seating_repeatability_nm=round(float(sigma_m) * 1e9, 6))

    def _stating(self, section: str, **values: Any) -> DeviceDescription:
        data = copy.deepcopy(self.raw)
        data[section].update(values)
        return parse_device(data, self.source)


# -- parsing -----------------------------------------------------------------------------------
class _Reader(validate.Fields):
    """Typed access to a device description that names the full key in every error."""

    def joints(self, mapping: Any, key: str, path: str) -> NDArray[np.float64]:
        arr = self.floats(mapping, key, path, (6, 3), what='six rows of [x, y, z] numbers')
        if np.max(np.abs(arr)) > 2000.0:
            raise self.fail(f'{path}.{key}', 'has a coordinate beyond 2 m: is it in mm?')
        return arr * M_PER_MM


def _merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _load_mapping(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    source = str(path)
    if path in seen:
        raise ConfigError(source, 'inherit', 'inheritance loops back to this file')
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(source, '(file)', 'must hold a YAML mapping')
    parent = data.pop('inherit', None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ConfigError(source, 'inherit', 'must be a file name')
        base = _load_mapping((path.parent / parent).resolve(), seen + (path,))
        data = _merge(base, data)
    return data


def load_device(path: str | os.PathLike[str]) -> DeviceDescription:
    """Read and validate a device description file (``inherit:`` resolved relative to it)."""
    p = Path(path).resolve()
    return parse_device(_load_mapping(p), str(p))


def parse_device(data: dict[str, Any], source: str = '<device>') -> DeviceDescription:
    """Validate a device description mapping (as loaded from YAML)."""
    r = _Reader(source)
    if data.get('format_version') != 1:
        raise r.fail('format_version', f'must be 1, got {data.get("format_version")!r}')
    r.known_keys(data, DEVICE_KEYS)
    for section, keys in SECTION_KEYS.items():
        r.known_keys(r.mapping(data, section), keys, section)
    name = r.get(data, 'name', '')
    if not isinstance(name, str) or not name:
        raise r.fail('name', 'must be a non-empty string')

    joints = r.get(data, 'joints', '')
    use_joints = r.choice(joints, 'use', 'joints', ('measured', 'design'))
    design = Geometry(r.joints(joints, 'upper_design_mm', 'joints'),
                      r.joints(joints, 'lower_design_mm', 'joints'))
    measured = Geometry(r.joints(joints, 'upper_measured_mm', 'joints'),
                        r.joints(joints, 'lower_measured_mm', 'joints'))
    for tag, geo in (('design', design), ('measured', measured)):
        if np.max(np.abs(geo.upper - design.upper)) > 1e-3 or \
                np.max(np.abs(geo.lower - design.lower)) > 1e-3:
            raise r.fail(f'joints.{tag}', 'differs from the design joints by more than 1 mm')

    bars = r.get(data, 'bars', '')
    rule = '[shortest, longest] with 0 < shortest < longest'
    rng = r.floats(bars, 'range_mm', 'bars', (2,), what=rule)
    if not 0 < rng[0] < rng[1]:
        raise r.fail('bars.range_mm', f'must be {rule}, got {rng.tolist()!r}')
    bar_range = (float(rng[0]) * M_PER_MM, float(rng[1]) * M_PER_MM)
    resolution = r.number(bars, 'encoder_resolution_nm', 'bars', positive=True) * M_PER_NM

    plate = r.get(data, 'reference_plate', '')
    use_pairs = r.choice(plate, 'use', 'reference_plate', ('measured', 'design'))
    raw_pairs = r.get(plate, 'pairs', 'reference_plate')
    if not isinstance(raw_pairs, list) or len(raw_pairs) != 7:
        raise r.fail('reference_plate.pairs', 'must list the seven reference pairs (Table 2)')
    pairs = []
    for j, item in enumerate(raw_pairs):
        path = f'reference_plate.pairs[{j}]'
        r.known_keys(validate.mapping(item, source, path), PAIR_KEYS, path)
        pname = r.get(item, 'name', path)
        sockets = r.get(item, 'sockets', path)
        if not (isinstance(sockets, list) and len(sockets) == 2 and sockets[0] != sockets[1]):
            raise r.fail(f'{path}.sockets', 'must name two different sockets')
        dm = r.number(item, 'design_mm', path, positive=True) * M_PER_MM
        mm = r.number(item, 'measured_mm', path, positive=True) * M_PER_MM
        if abs(dm - mm) > 1e-3:
            raise r.fail(f'{path}.measured_mm', 'differs from design_mm by more than 1 mm')
        dist = mm if use_pairs == 'measured' else dm
        sigma = 0.0
        if use_pairs == 'measured':
            if isinstance(item, dict) and 'uncertainty_um' in item:
                sigma = r.number(item, 'uncertainty_um', path, low=0.0, high=1000.0) * M_PER_UM
            elif isinstance(plate, dict) and 'distance_uncertainty_um' in plate:
                sigma = r.number(plate, 'distance_uncertainty_um', 'reference_plate', low=0.0,
                                 high=1000.0) * M_PER_UM
        if not (bar_range[0] - RANGE_SLACK_M <= dist <= bar_range[1] + RANGE_SLACK_M):
            raise r.fail(f'{path}', f'distance {dist / M_PER_MM:.4f} mm lies outside bars.range_mm')
        pairs.append(ReferencePair(str(pname), (str(sockets[0]), str(sockets[1])), dm, mm, dist, sigma))
    names = [p.name for p in pairs]
    if len(set(names)) != 7:
        raise r.fail('reference_plate.pairs', f'pair names must be unique, got {names}')
    if any(b.distance_m <= a.distance_m for a, b in zip(pairs, pairs[1:])):
        raise r.fail('reference_plate.pairs', 'distances must increase strictly from dr1 to dr7')

    plates = r.get(data, 'plates', '')
    limits = r.get(data, 'limits', '')
    terminal = r.get(data, 'terminal', '')
    raw_channels = r.get(terminal, 'channels', 'terminal')
    if not isinstance(raw_channels, list) or len(raw_channels) != N_CHANNELS:
        raise r.fail('terminal.channels', f'must list all {N_CHANNELS} terminal channels')
    channels = []
    for k, item in enumerate(raw_channels):
        path = f'terminal.channels[{k}]'
        r.known_keys(validate.mapping(item, source, path), CHANNEL_KEYS, path)
        cname = r.get(item, 'name', path)
        role = r.choice(item, 'role', path, ROLES)
        bar = pair = None
        if role == 'measuring':
            bar = r.integer(item, 'bar', path, low=1, high=6)
        elif role == 'reference':
            pair = r.get(item, 'pair', path)
            if pair not in names:
                raise r.fail(f'{path}.pair', f'must be one of {names}, got {pair!r}')
        channels.append(Channel(k, str(cname), role, bar, pair))
    cnames = [c.name for c in channels]
    if len(set(cnames)) != N_CHANNELS:
        raise r.fail('terminal.channels', f'channel names must be unique, got {cnames}')
    bar_numbers = sorted(c.bar for c in channels if c.bar is not None)
    if bar_numbers != [1, 2, 3, 4, 5, 6]:
        raise r.fail('terminal.channels', f'must map bars 1..6 once each, got {bar_numbers}')
    refs = [c for c in channels if c.role == 'reference']
    if not 1 <= len(refs) <= 2:
        raise r.fail('terminal.channels', f'needs one or two reference bars, got {len(refs)}')
    if len(refs) == 2 and refs[0].pair == refs[1].pair:
        raise r.fail('terminal.channels', 'the two reference bars must rest on different pairs')

    bits = r.get(terminal, 'counter_bits', 'terminal')
    if bits not in (16, 24, 32, 48, 64):
        raise r.fail('terminal.counter_bits', f'must be 16, 24, 32, 48 or 64, got {bits!r}')

    return DeviceDescription(
        name=name,
        source=source,
        geometry=measured if use_joints == 'measured' else design,
        design_geometry=design,
        measured_geometry=measured,
        pairs=tuple(pairs),
        bar_range_m=bar_range,
        encoder_resolution_m=resolution,
        scale_cte_per_c=r.number(bars, 'scale_cte_ppm_per_c', 'bars', low=-50, high=50) * PPM,
        rod_cte_per_c=r.number(bars, 'rod_cte_ppm_per_c', 'bars', low=-50, high=50) * PPM,
        plate_cte_per_c=r.number(plates, 'position_layer_cte_ppm_per_c', 'plates', low=-50, high=50) * PPM,
        reference_plate_cte_per_c=r.number(plate, 'cte_ppm_per_c', 'reference_plate', low=-50, high=50) * PPM,
        fixed_length_m=r.number(bars, 'fixed_length_mm', 'bars', positive=True) * M_PER_MM,
        upper_tilt_rad=math.radians(r.number(limits, 'upper_tilt_deg', 'limits', low=0, high=90)),
        lower_tilt_rad=math.radians(r.number(limits, 'lower_tilt_deg', 'limits', low=0, high=90)),
        min_bar_separation_m=r.number(limits, 'min_bar_separation_mm', 'limits', low=0) * M_PER_MM,
        sample_rate_hz=r.number(terminal, 'sample_rate_hz', 'terminal', positive=True),
        counter_bits=int(bits),
        channels=tuple(channels),
        raw=data,
        thermal_mismatch_fraction=_stated(r, bars, 'thermal_mismatch_fraction', 'bars', 1.0, 1.0),
        latch_skew_s=_stated(r, terminal, 'latch_skew_us', 'terminal', 1e-6, 1000.0),
        friction_hysteresis_m=_stated(r, bars, 'friction_hysteresis_nm', 'bars', M_PER_NM, 1e5),
        gravity_sag_m=_stated(r, bars, 'gravity_sag_nm', 'bars', M_PER_NM, 1e5),
        gravity_sag_sigma_m=_sag_sigma(r, bars),
        seating_repeatability_m=_stated(r, plate, 'seating_repeatability_nm', 'reference_plate',
                                        M_PER_NM, 1e5),
        vertical=_vertical(r, plates),
        drift_m_per_s=_stated(r, bars, 'drift_nm_per_h', 'bars', M_PER_NM / 3600.0, 1e6),
        rod_cte_sigma_per_c=_stated(r, bars, 'rod_cte_uncertainty_ppm_per_c', 'bars', PPM, 50.0),
        **_subdivision(r, bars, resolution),
    )


def _stated(r: _Reader, section: Any, key: str, path: str, unit: float, high: float
            ) -> float | None:
    """A figure the description may state (a datasheet's, a characterisation's): the number at
    ``key`` in 0 … ``high``, times ``unit``; None when the description does not say."""
    if not isinstance(section, dict) or key not in section:
        return None
    return r.number(section, key, path, low=0.0, high=high) * unit


def _sag_sigma(r: _Reader, bars: Any) -> float | None:
    """``bars.gravity_sag_uncertainty_nm``, the stated sag's standard uncertainty [m]: only
    with the figure it qualifies."""
    sigma = _stated(r, bars, 'gravity_sag_uncertainty_nm', 'bars', M_PER_NM, 1e5)
    if sigma is not None and 'gravity_sag_nm' not in bars:
        raise r.fail('bars.gravity_sag_uncertainty_nm', 'qualifies bars.gravity_sag_nm, which '
                     'the description does not state')
    return sigma


def _vertical(r: _Reader, plates: Any) -> tuple[float, float, float] | None:
    """``plates.vertical``, the upward vertical in {L} as the MMD is mounted, normalised; None
    when the description does not say."""
    if not isinstance(plates, dict) or 'vertical' not in plates:
        return None
    v = r.floats(plates, 'vertical', 'plates', (3,), what='[x, y, z], the upward direction in {L}')
    norm = float(np.linalg.norm(v))
    if not norm > 0.0:
        raise r.fail('plates.vertical', 'must not be the zero vector (it is the upward direction '
                     'in {L}; [0, 0, 1] when the lower plate lies level)')
    u = v / norm
    return (float(u[0]), float(u[1]), float(u[2]))


def _subdivision(r: _Reader, bars: dict[str, Any], resolution_m: float) -> dict[str, float | None]:
    """The encoders' sub-divisional error bound and signal period, stated together or not at
    all: a bound without its period cannot say how the error changes with the count."""
    out: dict[str, float | None] = {'subdivision_error_m': None, 'signal_period_m': None}
    if 'subdivision_error_nm' in bars:
        out['subdivision_error_m'] = r.number(bars, 'subdivision_error_nm', 'bars', low=0.0,
                                              high=10000.0) * M_PER_NM
    if 'signal_period_um' in bars:
        period = r.number(bars, 'signal_period_um', 'bars', positive=True, high=10000.0) * M_PER_UM
        if period < 2.0 * resolution_m:
            raise r.fail('bars.signal_period_um', f'{period / M_PER_UM:g} um is shorter than two '
                         f'counts of {resolution_m / M_PER_NM:g} nm: is it in um?')
        out['signal_period_m'] = period
    missing = [k for k, v in (('subdivision_error_nm', out['subdivision_error_m']),
                              ('signal_period_um', out['signal_period_m'])) if v is None]
    if len(missing) == 1:
        other = 'signal_period_um' if missing[0] == 'subdivision_error_nm' else 'subdivision_error_nm'
        raise r.fail(f'bars.{missing[0]}', f'must be given with bars.{other} (the encoder '
                     'datasheet states both)')
    return out


def find_config(name: str) -> Path:
    """Locate a file shipped in ``config/``: next to the source tree (a checkout or an editable
    install), or under ``share/mmd_ros/config`` of a colcon/ament prefix or of this Python's
    prefix. ``MMD_CONFIG_DIR`` is searched first. A path that exists is returned as is."""
    direct = Path(name)
    if direct.exists():
        return direct
    candidates = []
    if os.environ.get('MMD_CONFIG_DIR'):
        candidates.append(Path(os.environ['MMD_CONFIG_DIR']))
    candidates.append(Path(__file__).resolve().parents[2] / 'config')
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) + [sys.prefix]:
        if prefix:
            candidates.append(Path(prefix) / 'share' / 'mmd_ros' / 'config')
    for folder in candidates:
        if (folder / name).is_file():
            return folder / name
    raise FileNotFoundError(
        f'config file {name!r} not found; looked in {[str(c) for c in candidates]}')
