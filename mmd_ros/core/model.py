"""The compensation model: which terms are active and their parameters.

A model file (YAML) is read by the offline tools (``mmd process --model``) and by the ROS
compensation node (parameter ``model_file``), so that both compute the same lengths::

    format_version: 1
    thermal:
      mode: auto              # auto | single (Eq. 13) | interpolate (Eq. 12) | off
      plate_expansion: true   # joint positions scaled by the estimated plate expansion
    length_sigma_um: 0.4      # 1-sigma bar-length uncertainty for pose covariance
    terms:                    # optional corrections added to the compensated lengths
      - type: hysteresis      # section 5.3: direction-dependent mean correction
        amplitude_um: [0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
        travel_um: 5.0

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
from mmd_ros.core.errors import ConfigError, ModelError
from mmd_ros.core.units import M_PER_UM
from mmd_ros.core.yamlio import atomic_write_text, parse_yaml, read_yaml

__all__ = [
    'HysteresisTerm', 'Model', 'ModelTerm', 'TERM_TYPES', 'TermContext', 'load_model',
    'register_term', 'six_values', 'term_from_dict',
]

FloatArray = NDArray[np.float64]

#: Keys of a model file. ``analysis`` is the history ``mmd analyze`` appends (free-form).
MODEL_KEYS = ('format_version', 'thermal', 'length_sigma_um', 'terms', 'analysis', 'validity')
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

    def directions(self, lengths_m: FloatArray) -> FloatArray:
        """Motion direction of each bar at each sample, shape (N, 6), values -1, 0, +1."""
        out = np.empty_like(lengths_m)
        if lengths_m.shape[0] == 0:
            return out
        play = lengths_m[0].copy() if self._play is None else self._play.copy()
        direction = self._direction.copy()
        w = self.travel_m
        for bar in range(6):  # a sequential recurrence: plain floats beat numpy rows here
            p, d = float(play[bar]), float(direction[bar])
            column = lengths_m[:, bar].tolist()
            dirs = [0.0] * len(column)
            for k, x in enumerate(column):
                if p < x - w:
                    p, d = x - w, 1.0
                elif p > x + w:
                    p, d = x + w, -1.0
                dirs[k] = d
            out[:, bar] = dirs
            play[bar], direction[bar] = p, d
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


@dataclass
class Model:
    """Which compensation terms are active, and their parameters."""

    thermal_mode: str = 'auto'
    plate_expansion: bool = True
    length_sigma_m: float = 0.4e-6
    terms: list[ModelTerm] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    source: str = '<default model>'

    def reset(self) -> None:
        for term in self.terms:
            term.reset()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            'format_version': 1,
            'thermal': {'mode': self.thermal_mode, 'plate_expansion': self.plate_expansion},
            'length_sigma_um': self.length_sigma_m / M_PER_UM,
            'terms': [{'type': t.type_name, **t.params()} for t in self.terms],
        }
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
        sigma = f.number(data, 'length_sigma_um', default=0.4, low=0.0, low_open=True,
                         high=MAX_LENGTH_SIGMA_UM)
        raw_terms = f.get(data, 'terms', default=None) or []
        if not isinstance(raw_terms, list):
            raise ConfigError(source, 'terms', f'must be a list of terms, got {raw_terms!r}')
        terms = [term_from_dict(item, source, f'terms[{k}]') for k, item in enumerate(raw_terms)]
        extra = {key: data[key] for key in ('analysis', 'validity') if key in data}
        return cls(mode, plate, sigma * M_PER_UM, terms, extra, source)

    @classmethod
    def from_yaml(cls, text: str, source: str = '<model>') -> Model:
        return cls.from_dict(parse_yaml(text, source), source)


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


import mmd_ros.core.terms  # noqa: F401  (registers the catalogue's terms)
