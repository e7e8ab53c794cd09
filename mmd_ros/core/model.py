"""The compensation model: which terms are active and their parameters.

A model file (YAML) is read by the offline tools (``mmd process --model``) and by the ROS
compensation node (parameter ``model_file``), so that both compute the same lengths::

    format_version: 1
    thermal:
      mode: auto              # auto | single (Eq. 13) | interpolate (Eq. 12) | off
      plate_expansion: true   # joint positions scaled by the estimated plate expansion
    terms:                    # optional corrections added to the compensated lengths
      - type: hysteresis      # section 5.3: direction-dependent mean correction
        amplitude_um: [0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
        travel_um: 5.0
    uncertainty:              # optional: the bar-length uncertainty (msg_docs/frames.md)
      thermal_mismatch_fraction: 0.058   # default: the device description's
      read_noise_nm: 5.0                 # default: estimated from the stream
      fit: {...}                         # written by mmd analyze (see ModelUncertainty)

Without an ``uncertainty`` section every source takes its documented default, computed from the
device description and the calibration (:mod:`mmd_ros.core.budget`). ``length_sigma_um`` (a
fixed bar-length sigma of model files before the uncertainty budget) is read and ignored.

Every term is a :class:`ModelTerm`: given the samples of a run (consecutive, in time order),
it returns a length correction per sample and bar, and carries whatever state it needs from
one call to the next so that a stream processed piecewise gives the batch result. Terms
register themselves in :data:`TERM_TYPES` by name.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml
from numpy.typing import NDArray

from mmd_ros.core import validate
from mmd_ros.core.compiled import fast, use_compiled
from mmd_ros.core.errors import ConfigError, ModelError
from mmd_ros.core.units import M_PER_UM
from mmd_ros.core.yamlio import atomic_write_text, parse_yaml, read_yaml

__all__ = [
    'FIT_REPLACEABLE', 'FitUncertainty', 'HysteresisTerm', 'LengthProfile', 'Model', 'ModelTerm',
    'ModelUncertainty', 'TERM_TYPES', 'TermContext', 'load_model', 'play_operator',
    'register_term', 'six_values', 'term_from_dict',
]

FloatArray = NDArray[np.float64]

#: Keys of a model file. ``analysis`` is the history ``mmd analyze`` appends (free-form);
#: ``validity`` is what it was fitted and validated on (read by :mod:`mmd_ros.core.validity`).
RECORD_KEYS = ('analysis', 'validity')
MODEL_KEYS = ('format_version', 'thermal', 'length_sigma_um', 'terms', 'uncertainty', *RECORD_KEYS)
THERMAL_KEYS = ('mode', 'plate_expansion')
THERMAL_MODES = ('auto', 'single', 'interpolate', 'off')
#: Largest 1-sigma bar-length uncertainty a model may state [µm] (a bar that uncertain measures
#: nothing), and largest hysteresis play half-width [µm] (the bars' whole range).
MAX_LENGTH_SIGMA_UM = 1000.0
MAX_TRAVEL_UM = 1_000_000.0


@dataclass
class TermContext:
    """What a term may look at, for N consecutive samples.

    times_s : ndarray, shape (N,) [s]
    counts : ndarray, shape (N, 8) — raw counts
    lengths_m : ndarray, shape (N, 6) — lengths after CDF and thermal compensation [m]
    cdf_lengths_m : ndarray, shape (N, 6) — CDF lengths f_i(q_i) before thermal [m]
    reference_error_m : ndarray, shape (N, k) — Eq. (11) per reference bar [m]
    temp_change_c : ndarray, shape (N,) — estimated temperature change [°C]
    poses : ndarray, shape (N, 6), or None — a first-pass pose (for pose-dependent terms)
    """

    times_s: FloatArray
    counts: FloatArray
    lengths_m: FloatArray
    cdf_lengths_m: FloatArray
    reference_error_m: FloatArray
    temp_change_c: FloatArray
    poses: FloatArray | None = None


class ModelTerm:
    """A correction of the bar lengths. Subclasses set ``type_name`` and implement
    :meth:`correction`, :meth:`from_params` and :meth:`params`."""

    type_name: ClassVar[str] = ''
    #: True when the term needs a first-pass pose (``TermContext.poses``).
    needs_pose: ClassVar[bool] = False

    def reset(self) -> None:
        """Forget the state carried between calls (start of a new run)."""

    def correction(self, ctx: TermContext) -> FloatArray:
        """Length correction to add, shape (N, 6) [m]."""
        raise NotImplementedError

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> ModelTerm:
        raise NotImplementedError

    def params(self) -> dict[str, Any]:
        raise NotImplementedError


TERM_TYPES: dict[str, type[ModelTerm]] = {}


def register_term(cls: type[ModelTerm]) -> type[ModelTerm]:
    """Class decorator: make a term type available to model files by its ``type_name``."""
    if not cls.type_name:
        raise ModelError(f'{cls.__name__} has no type_name')
    TERM_TYPES[cls.type_name] = cls
    return cls


def six_values(params: dict[str, Any], key: str, source: str) -> FloatArray:
    """A per-bar parameter: one number for all bars or a list of six (finite numbers; a bool or
    a string is refused)."""
    what = 'a number or a list of six numbers'
    if key not in params:
        raise ConfigError(source, key, f'is missing; must be {what}')
    arr = validate.floats(params[key], source, key, what=what)
    if arr.shape not in ((), (6,)):
        raise ConfigError(source, key, f'must be {what}, got {params[key]!r}')
    return np.broadcast_to(arr, (6,)).copy()


def play_operator(lengths_m: FloatArray, deadband_m: float, play: FloatArray,
                  direction: FloatArray | None = None, *, positions: FloatArray | None = None,
                  directions: FloatArray | None = None, compiled: bool | None = None) -> None:
    """The play (backlash) operator of half-width ``deadband_m`` on each column of lengths
    (N, k): it follows the input only when the input is more than ``deadband_m`` away.

    play : ndarray, shape (k,) float64 — its position before the first sample, updated in place
    direction : ndarray, shape (k,) float64, or None — the direction (-1, 0, +1) of its last move,
        updated in place
    positions, directions : ndarray, shape (N, k) float64, or None — filled with its output and
        the direction of its last move at every sample
    compiled : the compiled loop (default: when it is in use); False: Python (the same numbers)
    """
    x = np.ascontiguousarray(lengths_m, dtype=np.float64)
    w = float(deadband_m)
    if use_compiled(compiled):
        fast.play(x, w, play, direction, positions, directions)
        return
    n = x.shape[0]
    for j in range(x.shape[1]):  # a sequential recurrence: plain floats beat numpy rows here
        p = float(play[j])
        d = 0.0 if direction is None else float(direction[j])
        pos, dirs = [0.0] * n, [0.0] * n
        for k, v in enumerate(x[:, j].tolist()):
            if p < v - w:
                p, d = v - w, 1.0
            elif p > v + w:
                p, d = v + w, -1.0
            pos[k], dirs[k] = p, d
        if positions is not None:
            positions[:, j] = pos
        if directions is not None:
            directions[:, j] = dirs
        play[j] = p
        if direction is not None:
            direction[j] = d


@register_term
class HysteresisTerm(ModelTerm):
    """Direction-dependent mean hysteresis correction (section 5.3).

    Friction in the ball joints and guides makes a bar read differently when it lengthens and
    when it shortens. The direction of each bar is tracked with a play (backlash) operator of
    half-width ``travel``: it flips only after the bar has moved ``2 * travel`` against the
    current direction, so noise and dwell do not flip it. The correction is
    ``-amplitude * direction`` (direction +1 lengthening, -1 shortening, 0 before the first
    move). A positive amplitude means the bar reads long when lengthening.
    """

    type_name = 'hysteresis'

    def __init__(self, amplitude_m: FloatArray, travel_m: float) -> None:
        self.amplitude_m = np.asarray(amplitude_m, dtype=np.float64)
        self.travel_m = float(travel_m)
        self.reset()

    def reset(self) -> None:
        self._play: FloatArray | None = None
        self._direction = np.zeros(6)

    def directions(self, lengths_m: FloatArray, *, compiled: bool | None = None) -> FloatArray:
        """Motion direction of each bar at each sample, shape (N, 6), values -1, 0, +1.

        compiled : the compiled play operator (default: when in use); False: Python
        """
        out = np.empty(np.shape(lengths_m))
        if out.shape[0] == 0:
            return out
        play = np.array(lengths_m[0], dtype=np.float64) if self._play is None else self._play.copy()
        direction = self._direction.copy()
        play_operator(lengths_m, self.travel_m, play, direction, directions=out, compiled=compiled)
        self._play, self._direction = play, direction
        return out

    def correction(self, ctx: TermContext) -> FloatArray:
        return -self.amplitude_m * self.directions(ctx.lengths_m)

    @classmethod
    def from_params(cls, params: dict[str, Any], source: str) -> HysteresisTerm:
        amp = six_values(params, 'amplitude_um', source) * M_PER_UM
        travel = validate.number(params.get('travel_um', 5.0), source, 'travel_um', low=0.0,
                                 low_open=True, high=MAX_TRAVEL_UM)
        return cls(amp, travel * M_PER_UM)

    def params(self) -> dict[str, Any]:
        return {'amplitude_um': (self.amplitude_m / M_PER_UM).tolist(),
                'travel_um': self.travel_m / M_PER_UM}


#: Sources of the uncertainty budget that a fit's measured residual may stand in for: the
#: systematic errors derived from the calibration (msg_docs/frames.md), and what the readings
#: had drifted since it by the time the residual was measured (they drift on from there).
FIT_REPLACEABLE = ('calibration_points', 'calibration_drift', 'reference_distances', 'interpolation',
                   'subdivision', 'hysteresis', 'gravity_sag', 'reading_drift')
#: Keys of a model file's ``uncertainty.fit`` section.
FIT_KEYS = ('residual_nm2', 'replaces', 'systematic_scale', 'mean_terms_nm2', 'directions', 'from',
            'read_noise_nm', 'flank_nm2', 'rest_terms_nm2', 'profile', 'measured_unix_s',
            'thermal_state_nm', 'thermal_state_c')
#: Most lengths per bar of a residual's length profile in a model file.
PROFILE_POINTS = 1000


def _matrix6(value: Any, source: str, key: str) -> FloatArray:
    """A symmetric positive semi-definite 6 x 6 matrix (nested lists)."""
    what = 'a symmetric positive semi-definite 6 x 6 matrix'
    arr = validate.floats(value, source, key, (6, 6), what=what)
    size = max(float(np.max(np.abs(arr))), 1e-12)
    # (a written matrix may have lost a little to rounding: nearly singular ones then dip below 0)
    if np.max(np.abs(arr - arr.T)) > 1e-6 * size or np.min(np.linalg.eigvalsh(0.5 * (arr + arr.T))) < -1e-4 * size:
        raise ConfigError(source, key, f'must be {what}, got {value!r}')
    return 0.5 * (arr + arr.T)


@dataclass
class LengthProfile:
    """Where along each bar's length the residual a fit measured lay: the part of that
    residual it redistributes and, per bar, a factor over lengths.

    excess_m2 : (6, 6) — the part of ``FitUncertainty.residual_m2`` the factors redistribute
        (what the references showed beyond the budget's per-sample sources) [m^2]
    lengths_m : per bar, increasing CDF lengths (G_b,) [m], empty where the bar's residual
        showed no dependence on its length
    factor : per bar, the factor f_b >= 0 at those lengths (G_b,) [1]: its mean over the fit's
        samples 1 where the residual was read as a function of the length, else 1 but where
        the residual stood out; 1 beyond the first and the last length and without lengths

    At a sample, the residual claims ``residual_m2 + E * (sqrt(f f^T) - 1)``, E ``excess_m2``
    and f each bar's factor at its CDF length (linear between the lengths): E is claimed where
    along each bar it was seen.
    """

    excess_m2: FloatArray
    lengths_m: list[FloatArray]
    factor: list[FloatArray]

    def factors(self, cdf_lengths_m: FloatArray) -> FloatArray:
        """Each bar's factor at CDF lengths (N, 6), (N, 6) [1]."""
        x = np.asarray(cdf_lengths_m, dtype=np.float64)
        out = np.ones(x.shape)
        for b in range(6):
            if self.lengths_m[b].size:
                out[:, b] = np.interp(x[:, b], self.lengths_m[b], self.factor[b],
                                      left=1.0, right=1.0)
        return np.where(np.isfinite(out), out, 1.0)

    def added(self, cdf_lengths_m: FloatArray) -> FloatArray:
        """What the profile adds to the residual at CDF lengths (N, 6), (N, 6, 6) [m^2]
        (negative where a bar's factor is below 1)."""
        root = np.sqrt(self.factors(cdf_lengths_m))
        return self.excess_m2 * (root[:, :, None] * root[:, None, :] - 1.0)

    def to_dict(self) -> dict[str, Any]:
        return {'excess_nm2': (self.excess_m2 * 1e18).tolist(),
                'lengths_mm': [[round(float(v) * 1e3, 4) for v in x] for x in self.lengths_m],
                'factor': [[round(float(v), 4) for v in f] for f in self.factor]}

    @classmethod
    def from_dict(cls, data: Any, source: str, path: str) -> LengthProfile:
        data = validate.mapping(data, source, path)
        validate.known_keys(data, ('excess_nm2', 'lengths_mm', 'factor'), source, f'{path}.')
        excess = _matrix6(data.get('excess_nm2'), source, f'{path}.excess_nm2') * 1e-18
        lengths, factor = data.get('lengths_mm'), data.get('factor')
        what = 'six lists, one per measuring bar'
        for key, value in (('lengths_mm', lengths), ('factor', factor)):
            if not isinstance(value, list) or len(value) != 6:
                raise ConfigError(source, f'{path}.{key}', f'must be {what}, got {value!r}')
        xs, fs = [], []
        for b in range(6):
            x = validate.floats(lengths[b], source, f'{path}.lengths_mm[{b}]', (-1,),
                                what='increasing lengths in mm')
            f = validate.floats(factor[b], source, f'{path}.factor[{b}]', (-1,),
                                what='factors >= 0')
            if (x.size != f.size or x.size > PROFILE_POINTS or np.any(np.diff(x) <= 0)
                    or np.any((f < 0) | (f > 1e6))):
                raise ConfigError(source, f'{path}.factor[{b}]',
                                  f'must be at most {PROFILE_POINTS} factors in 0 … 1e6, one per '
                                  f'length of lengths_mm[{b}] (increasing), got {f.size} for '
                                  f'{x.size} lengths')
            xs.append(x * 1e-3)
            fs.append(f)
        return cls(excess, xs, fs)


@dataclass
class FitUncertainty:
    """What ``mmd analyze`` measured about the uncertainty of the model it wrote.

    residual_m2 : (6, 6) — covariance of the bar-length residual the fit left, beyond the
        per-sample sources the budget keeps (read noise, quantisation, reference bar, thermal)
        [m^2]; added to every sample
    replaces : budget sources (of :data:`FIT_REPLACEABLE`) the residual stands in for: it
        measured them, so they are not added again
    systematic_scale : factor on the variance of the replaceable sources that are kept (a
        reference that sees only some pose components sizes them in those components only)
    directions : one sigma of the fitted correction along each principal direction of the
        fitted parameters' covariance, each as the model term(s) that apply it (the sum of a
        direction's corrections is c_k(t); sum_k c_k c_k^T per sample)
    mean_terms_m2 : (6, 6) — the mean of sum_k c_k c_k^T over the fit's samples, for a stage
        that cannot evaluate the terms (fk_node sees no counts) [m^2]
    record : where the figures come from (log, reference, samples)
    read_noise_m : (6 + k,) — the read noise of each channel (six measuring bars, then the
        reference bars) measured where the analysed logs' bars stood still [m], or None: what a
        stream claims until it has stood still long enough to show its own (the larger of this
        and the calibration's figure)
    flank_m2 : (6,) — per bar, what the residual held beyond the model's claim where the bar
        lay within the lengths the fit saw but in a CDF segment whose middle it did not see
        (:meth:`~mmd_ros.core.budget.LengthBudget.flank`) [m^2]; added there
    rest_terms_m2 : (6, 6) — the mean of c_k c_k^T over the fit's samples of the principal
        directions not written in ``directions`` (a stage evaluates a few per sample): added to
        every sample whose directions are evaluated, so that the fitted terms' whole covariance
        is claimed [m^2]
    profile : where along each bar's length the residual lay (:class:`LengthProfile`), or None:
        the residual claimed alike at every length
    measured_unix_s : when the residual was measured: the mean Unix time of the samples it
        was measured on [s], or None (not known). It holds what the readings had drifted by
        then; the budget counts their drift from there (the later of it and the calibration)
    thermal_state_m : (6 + k,) — the thermal correction of each measuring bar (Eq. 13), then
        each reference bar's error (Eq. 11), averaged over the samples of the absolute
        references that saw every bar [m], or None: the fit measured the bars' thermal
        mismatch as it was there (its terms of free constants took it up, or its residual
        holds it), and the budget claims the mismatch of the change since
    thermal_state_c : the mean temperature change since the thermal zero of the samples of
        absolute pose references that saw every component [°C], or None: Eq. (13)'s
        approximation and the plates' scale are claimed of the change since
    """

    residual_m2: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))
    replaces: tuple[str, ...] = ()
    systematic_scale: float = 1.0
    directions: list[list[ModelTerm]] = field(default_factory=list)
    mean_terms_m2: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))
    record: dict[str, Any] = field(default_factory=dict)
    read_noise_m: FloatArray | None = None
    flank_m2: FloatArray = field(default_factory=lambda: np.zeros(6))
    rest_terms_m2: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))
    profile: LengthProfile | None = None
    measured_unix_s: float | None = None
    thermal_state_m: FloatArray | None = None
    thermal_state_c: float | None = None

    def reset(self) -> None:
        for group in self.directions:
            for term in group:
                term.reset()

    def to_dict(self) -> dict[str, Any]:
        nm2 = 1e18
        return {
            'residual_nm2': (self.residual_m2 * nm2).tolist(),
            'replaces': list(self.replaces),
            'systematic_scale': float(self.systematic_scale),
            'mean_terms_nm2': (self.mean_terms_m2 * nm2).tolist(),
            'directions': [[{'type': t.type_name, **t.params()} for t in group]
                           for group in self.directions],
            'from': self.record,
            **({} if self.read_noise_m is None else
               {'read_noise_nm': [round(float(v) * 1e9, 4) for v in self.read_noise_m]}),
            **({} if not np.any(self.flank_m2) else
               {'flank_nm2': [round(float(v) * 1e18, 3) for v in self.flank_m2]}),
            **({} if not np.any(self.rest_terms_m2) else
               {'rest_terms_nm2': (self.rest_terms_m2 * nm2).tolist()}),
            **({} if self.profile is None else {'profile': self.profile.to_dict()}),
            **({} if self.measured_unix_s is None else
               {'measured_unix_s': round(float(self.measured_unix_s), 3)}),
            **({} if self.thermal_state_m is None else
               {'thermal_state_nm': [round(float(v) * 1e9, 3) for v in self.thermal_state_m]}),
            **({} if self.thermal_state_c is None else
               {'thermal_state_c': round(float(self.thermal_state_c), 5)}),
        }

    @classmethod
    def from_dict(cls, data: Any, source: str) -> FitUncertainty:
        f = validate.Fields(source)
        data = validate.mapping(data, source, 'uncertainty.fit')
        path = 'uncertainty.fit'
        f.known_keys(data, FIT_KEYS, path)
        residual = _matrix6(data.get('residual_nm2', np.zeros((6, 6)).tolist()), source,
                            f'{path}.residual_nm2') * 1e-18
        mean_terms = _matrix6(data.get('mean_terms_nm2', np.zeros((6, 6)).tolist()), source,
                              f'{path}.mean_terms_nm2') * 1e-18
        replaces = f.get(data, 'replaces', path, default=None) or []
        if not isinstance(replaces, list) or any(r not in FIT_REPLACEABLE for r in replaces):
            raise ConfigError(source, f'{path}.replaces',
                              f'must list some of {", ".join(FIT_REPLACEABLE)}, got {replaces!r}')
        scale = f.number(data, 'systematic_scale', path, default=1.0, low=0.0, high=1e6)
        groups = f.get(data, 'directions', path, default=None) or []
        if not isinstance(groups, list) or not all(isinstance(g, list) for g in groups):
            raise ConfigError(source, f'{path}.directions', 'must be a list of lists of terms')
        directions = [[term_from_dict(item, source, f'{path}.directions[{k}][{j}]')
                       for j, item in enumerate(g)] for k, g in enumerate(groups)]
        record = data.get('from') or {}
        noise = None
        if data.get('read_noise_nm') is not None:
            what = '6 to 8 read noises in nm (measuring bars, then reference bars), each 0 … 1e4'
            noise = f.floats(data, 'read_noise_nm', path, (-1,), what=what)
            if not 6 <= noise.size <= 8 or np.any((noise < 0) | (noise >= 1e4)):
                raise ConfigError(source, f'{path}.read_noise_nm', f'must be {what}, got {noise.tolist()}')
            noise = noise * 1e-9
        flank = np.zeros(6)
        if data.get('flank_nm2') is not None:
            what = '6 variances in nm^2, one per measuring bar, each 0 … 1e8'
            flank = f.floats(data, 'flank_nm2', path, (-1,), what=what)
            if flank.size != 6 or np.any((flank < 0) | (flank > 1e8)):
                raise ConfigError(source, f'{path}.flank_nm2', f'must be {what}, got {flank.tolist()}')
            flank = flank * 1e-18
        rest = _matrix6(data.get('rest_terms_nm2', np.zeros((6, 6)).tolist()), source,
                        f'{path}.rest_terms_nm2') * 1e-18
        profile = (None if data.get('profile') is None
                   else LengthProfile.from_dict(data['profile'], source, f'{path}.profile'))
        measured = (None if data.get('measured_unix_s') is None
                    else f.number(data, 'measured_unix_s', path, low=0.0, high=1e11))
        state = None
        if data.get('thermal_state_nm') is not None:
            what = ('7 or 8 thermal corrections in nm (measuring bars, then reference bars), '
                    'each within ±1e6')
            state = f.floats(data, 'thermal_state_nm', path, (-1,), what=what)
            if not 7 <= state.size <= 8 or np.any(np.abs(state) > 1e6):
                raise ConfigError(source, f'{path}.thermal_state_nm',
                                  f'must be {what}, got {state.tolist()}')
            state = state * 1e-9
        state_c = (None if data.get('thermal_state_c') is None
                   else f.number(data, 'thermal_state_c', path, low=-100.0, high=100.0))
        return cls(residual, tuple(replaces), scale, directions, mean_terms,
                   dict(record) if isinstance(record, dict) else {}, noise, flank, rest, profile,
                   measured, state, state_c)


@dataclass
class ModelUncertainty:
    """The model file's ``uncertainty`` section: numbers that override the budget's defaults
    (the device description's, the calibration's, the stream's) and what a fit measured.

    thermal_mismatch_fraction : sigma of a bar's thermal error left after Eqs. (12)/(13), as a
        fraction of the error subtracted; None takes the device description's
    read_noise_m : read noise of every channel [m]; None estimates it from the stream (the
        calibration's figure until the stream has shown enough)
    fit : what ``mmd analyze`` measured, or None
    """

    thermal_mismatch_fraction: float | None = None
    read_noise_m: float | None = None
    fit: FitUncertainty | None = None

    def reset(self) -> None:
        if self.fit is not None:
            self.fit.reset()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.thermal_mismatch_fraction is not None:
            out['thermal_mismatch_fraction'] = float(self.thermal_mismatch_fraction)
        if self.read_noise_m is not None:
            out['read_noise_nm'] = float(self.read_noise_m / 1e-9)
        if self.fit is not None:
            out['fit'] = self.fit.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: Any, source: str) -> ModelUncertainty:
        if data is None:
            return cls()
        f = validate.Fields(source)
        data = validate.mapping(data, source, 'uncertainty')
        f.known_keys(data, ('thermal_mismatch_fraction', 'read_noise_nm', 'fit'), 'uncertainty')
        frac = (f.number(data, 'thermal_mismatch_fraction', 'uncertainty', low=0.0, high=1.0)
                if data.get('thermal_mismatch_fraction') is not None else None)
        noise = (f.number(data, 'read_noise_nm', 'uncertainty', low=0.0, high=1e4)
                 if data.get('read_noise_nm') is not None else None)
        fit = FitUncertainty.from_dict(data['fit'], source) if data.get('fit') is not None else None
        return cls(frac, None if noise is None else noise * 1e-9, fit)


@dataclass
class Model:
    """Which compensation terms are active, and their parameters.

    length_sigma_m : a fixed bar-length sigma of old model files; read, not used, not written
    uncertainty : the model file's ``uncertainty`` section (defaults when absent)
    """

    thermal_mode: str = 'auto'
    plate_expansion: bool = True
    length_sigma_m: float | None = None
    terms: list[ModelTerm] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    source: str = '<default model>'
    uncertainty: ModelUncertainty = field(default_factory=ModelUncertainty)

    def reset(self) -> None:
        for term in self.terms:
            term.reset()
        self.uncertainty.reset()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            'format_version': 1,
            'thermal': {'mode': self.thermal_mode, 'plate_expansion': self.plate_expansion},
            'terms': [{'type': t.type_name, **t.params()} for t in self.terms],
        }
        unc = self.uncertainty.to_dict()
        if unc:
            out['uncertainty'] = unc
        out.update(self.extra)
        return out

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write atomically."""
        return atomic_write_text(path, self.to_yaml())

    @classmethod
    def from_dict(cls, data: Any, source: str = '<model>') -> Model:
        """Validate a model mapping (as loaded from YAML): every field is checked, unknown keys
        (a typo such as ``thermall``) are refused, in the terms too."""
        f = validate.Fields(source)
        if not isinstance(data, dict) or data.get('format_version') != 1:
            raise ConfigError(source, 'format_version', 'not a model file of format 1')
        f.known_keys(data, MODEL_KEYS)
        thermal = f.mapping(data, 'thermal', default={})
        f.known_keys(thermal, THERMAL_KEYS, 'thermal')
        mode = f.choice(thermal, 'mode', 'thermal', THERMAL_MODES, default='auto')
        plate = f.boolean(thermal, 'plate_expansion', 'thermal', default=True)
        # the fixed bar-length sigma of older files: read (and checked), not used, not written
        sigma = (f.number(data, 'length_sigma_um', low=0.0, low_open=True, high=MAX_LENGTH_SIGMA_UM)
                 if 'length_sigma_um' in data else None)
        raw_terms = f.get(data, 'terms', default=None) or []
        if not isinstance(raw_terms, list):
            raise ConfigError(source, 'terms', f'must be a list of terms, got {raw_terms!r}')
        terms = [term_from_dict(item, source, f'terms[{k}]') for k, item in enumerate(raw_terms)]
        uncertainty = ModelUncertainty.from_dict(data.get('uncertainty'), source)
        extra = {k: data[k] for k in RECORD_KEYS if k in data}
        if extra.get('validity') is not None:
            _check_validity(extra['validity'], source)
        return cls(mode, plate, None if sigma is None else sigma * M_PER_UM, terms, extra, source,
                   uncertainty)

    @classmethod
    def from_yaml(cls, text: str, source: str = '<model>') -> Model:
        return cls.from_dict(parse_yaml(text, source), source)


def _check_validity(record: Any, source: str) -> None:
    """The ranges of a model's ``validity`` record (:mod:`mmd_ros.core.validity`), which the
    uncertainty budget and the nodes' warnings use: each bar's lowest and highest CDF length
    and the temperature span, finite and in order (a reversed range changed the pose's claimed
    sigma without a word). The rest of the record is free-form."""
    record = validate.mapping(record, source, 'validity')
    if 'bar_range_mm' in record:
        bars = validate.floats(record['bar_range_mm'], source, 'validity.bar_range_mm', (6, 2),
                               what='six [lowest, highest] CDF lengths in mm')
        if np.any(bars[:, 0] > bars[:, 1]):
            raise ConfigError(source, 'validity.bar_range_mm',
                              f'each bar\'s lowest length must not exceed its highest, got '
                              f'{bars.tolist()}')
    if record.get('temperature_c') is not None:
        temp = validate.floats(record['temperature_c'], source, 'validity.temperature_c', (2,),
                               what='[lowest, highest] temperature in °C')
        if temp[0] > temp[1]:
            raise ConfigError(source, 'validity.temperature_c',
                              f'the lowest must not exceed the highest, got {temp.tolist()}')


def term_from_dict(item: Any, source: str, where: str = 'term') -> ModelTerm:
    """One term of a model file (``where``, e.g. ``terms[2]``, in ``source``): ``type`` and its
    parameters, none unknown to the term."""
    if not isinstance(item, dict) or item.get('type') not in TERM_TYPES:
        given = item.get('type') if isinstance(item, dict) else item
        raise ConfigError(source, f'{where}.type',
                          f'must be one of {", ".join(sorted(TERM_TYPES))}, got {given!r}')
    params = {key: v for key, v in item.items() if key != 'type'}
    term = TERM_TYPES[item['type']].from_params(params, f'{source}: {where}')
    # A term writes every parameter it reads (params()), so its keys are the known ones.
    validate.known_keys(params, ['type', *term.params()], f'{source}: {where}')
    return term


def load_model(path: str | os.PathLike[str] | None) -> Model:
    """Read a model file; None gives the default model (CDF + thermal, no extra terms)."""
    if path is None:
        return Model()
    return Model.from_dict(read_yaml(path), str(path))


import mmd_ros.core.terms  # noqa: F401,E402  (registers the catalogue's terms)
