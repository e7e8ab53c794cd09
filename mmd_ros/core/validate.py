"""Input checks, in one layer.

Every value a user can hand the software — a command-line option, a node parameter, a field of a
model, device, calibration or ambient file, a string read back from a log — goes through these
typed checkers, so that a bad value is refused the same way everywhere: one line naming where
it came from, the field, what is allowed and what was given. Nothing here converts silently:
``true`` is not the number 1, ``"abc"`` is not a number, NaN and infinities are not numbers a
file may ask for (``.nan`` in YAML, ``nan`` on the command line), and a mapping may be checked
for keys it does not know (a typo such as ``thermall:`` is refused, with the key it resembles).

- :func:`number_problem` and :func:`describe` phrase the rule ("an integer in [1, 1000]");
  :func:`number`, :func:`integer`, :func:`boolean`, :func:`choice`, :func:`floats`,
  :func:`mapping` and :func:`known_keys` (:func:`unknown_key` says why) raise :class:`~mmd_ros.core.errors.ConfigError`
  naming the source (a file, a log topic) and the key.
- :func:`arg_number` makes an argparse ``type=`` that applies the same rule to an option
  (argparse then prints ``argument --blocks: must be an integer >= 1, got '0'`` and exits 2).
- :class:`Fields` is the same checks bound to one source, for loaders that read nested keys.
"""

from __future__ import annotations

import argparse
import difflib
import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.core.errors import ConfigError

__all__ = [
    'Fields', 'arg_number', 'arg_numbers', 'boolean', 'choice', 'describe', 'floats', 'integer',
    'known_keys', 'mapping', 'number', 'number_problem', 'unknown_key',
]

_MISSING = object()


def _fmt(v: float) -> str:
    text = f'{v:g}'
    # an integer bound that %g would round (2^64 - 1 for a seed) is written out
    return str(v) if isinstance(v, int) and float(text) != v else text


def describe(*, low: float | None = None, high: float | None = None, low_open: bool = False,
             high_open: bool = False, integer: bool = False) -> str:
    """The rule in words: 'a finite number', 'an integer >= 1', 'a number in (0, 10000]'."""
    kind = 'an integer' if integer else 'a finite number' if low is None and high is None else 'a number'
    if low is None and high is None:
        return kind
    if high is None:
        return f'{kind} {">" if low_open else ">="} {_fmt(low)}'
    if low is None:
        return f'{kind} {"<" if high_open else "<="} {_fmt(high)}'
    return f'{kind} in {"(" if low_open else "["}{_fmt(low)}, {_fmt(high)}{")" if high_open else "]"}'


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def number_problem(value: Any, *, low: float | None = None, high: float | None = None,
                   low_open: bool = False, high_open: bool = False, integer: bool = False) -> str | None:
    """Why ``value`` is not a number of the rule ('must be ..., got ...'), or None if it is.

    A bool, a string, NaN or an infinity is never a number here; with ``integer`` a float is
    refused too (1.0 included: a count written as a float is a mistake worth seeing).
    """
    rule = describe(low=low, high=high, low_open=low_open, high_open=high_open, integer=integer)
    bad = f'must be {rule}, got {value!r}'
    if not _is_number(value):
        return bad
    if integer and not isinstance(value, (int, np.integer)):
        return bad
    if not integer and not math.isfinite(float(value)):
        return bad
    if low is not None and (value <= low if low_open else value < low):
        return bad
    if high is not None and (value >= high if high_open else value > high):
        return bad
    return None


def number(value: Any, source: str, key: str, *, low: float | None = None,
           high: float | None = None, low_open: bool = False, high_open: bool = False) -> float:
    """``value`` as a float, or :class:`ConfigError` naming ``source`` and ``key``."""
    why = number_problem(value, low=low, high=high, low_open=low_open, high_open=high_open)
    if why:
        raise ConfigError(source, key, why)
    return float(value)


def integer(value: Any, source: str, key: str, *, low: int | None = None,
            high: int | None = None) -> int:
    """``value`` as an int (a YAML integer, not a float nor a bool)."""
    why = number_problem(value, low=low, high=high, integer=True)
    if why:
        raise ConfigError(source, key, why)
    return int(value)


def boolean(value: Any, source: str, key: str) -> bool:
    """A YAML ``true``/``false`` (not 0/1, not a string)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(source, key, f'must be true or false, got {value!r}')
    return bool(value)


def choice(value: Any, source: str, key: str, options: Iterable[Any]) -> Any:
    """One of ``options``."""
    opts = list(options)
    if isinstance(value, bool) or value not in opts:
        raise ConfigError(source, key, f'must be one of {", ".join(map(str, opts))}, got {value!r}')
    return value


def mapping(value: Any, source: str, key: str) -> dict[str, Any]:
    """A YAML mapping."""
    if not isinstance(value, dict):
        raise ConfigError(source, key, f'must be a mapping of names to values, got {value!r}')
    return value


def _all_numbers(value: Any, depth: int = 0) -> bool:
    if isinstance(value, (list, tuple)):
        return depth < 8 and all(_all_numbers(v, depth + 1) for v in value)
    return _is_number(value)


def floats(value: Any, source: str, key: str, shape: tuple[int, ...] | None = None, *,
           what: str | None = None) -> NDArray[np.float64]:
    """Finite numbers (nested lists) as an array, of ``shape`` when given (-1: any length).

    Strings and bools inside are refused (numpy would read ``true`` as 1 and fail on ``"abc"``
    with a traceback)."""
    want = what or ('numbers' if shape is None else f'finite numbers of shape {list(shape)}')
    bad = ConfigError(source, key, f'must be {want}, got {_short(value)}')
    if not _all_numbers(value):
        raise bad
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):  # ragged lists
        raise bad from None
    if not np.all(np.isfinite(arr)):
        raise ConfigError(source, key, f'must be {want}: finite, got {_short(value)}')
    if shape is not None and (arr.ndim != len(shape) or any(
            s != -1 and s != n for s, n in zip(shape, arr.shape))):
        raise bad
    return arr


def _short(value: Any, limit: int = 80) -> str:
    text_ = repr(value)
    return text_ if len(text_) <= limit else text_[:limit - 3] + '...'


def unknown_key(keys: Iterable[Any], allowed: Iterable[str], what: str = 'key',
                of: str = '') -> tuple[str, str] | None:
    """The first of ``keys`` outside ``allowed`` and why, with the known key it resembles
    (``('thermall', 'is not a known key (did you mean thermal?); known keys: ...')``), or None.
    ``what`` names a key ('parameter'), ``of`` what it would belong to (' of Ramp')."""
    allowed = [str(a) for a in allowed]
    for key in keys:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f' (did you mean {close[0]}?)' if close else ''
            return str(key), f'is not a known {what}{of}{hint}; known {what}s: {", ".join(allowed)}'
    return None


def known_keys(data: dict[str, Any], allowed: Iterable[str], source: str, prefix: str = '') -> None:
    """Refuse a key of ``data`` outside ``allowed``, naming it and the known key it resembles."""
    found = unknown_key(data, allowed)
    if found:
        raise ConfigError(source, f'{prefix}{found[0]}', found[1])


class Fields:
    """The checks above bound to one source, for nested mappings: errors name the full key
    (``terminal.channels[3].bar``)."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(self.source, key, problem)

    @staticmethod
    def full(path: str, key: str) -> str:
        return f'{path}.{key}' if path else key

    def get(self, data: Any, key: str, path: str = '', default: Any = _MISSING) -> Any:
        if not isinstance(data, dict):
            raise self.fail(path or '(file)', 'must be a mapping')
        if key not in data:
            if default is _MISSING:
                raise self.fail(self.full(path, key), 'is missing')
            return default
        return data[key]

    def number(self, data: Any, key: str, path: str = '', *, default: Any = _MISSING,
               low: float | None = None, high: float | None = None, low_open: bool = False,
               high_open: bool = False, positive: bool = False) -> float:
        if positive:  # > 0
            low, low_open = 0.0, True
        return number(self.get(data, key, path, default), self.source, self.full(path, key),
                      low=low, high=high, low_open=low_open, high_open=high_open)

    def integer(self, data: Any, key: str, path: str = '', *, default: Any = _MISSING,
                low: int | None = None, high: int | None = None) -> int:
        return integer(self.get(data, key, path, default), self.source, self.full(path, key),
                       low=low, high=high)

    def boolean(self, data: Any, key: str, path: str = '', *, default: Any = _MISSING) -> bool:
        return boolean(self.get(data, key, path, default), self.source, self.full(path, key))

    def choice(self, data: Any, key: str, path: str, options: Iterable[Any], *,
               default: Any = _MISSING) -> Any:
        return choice(self.get(data, key, path, default), self.source, self.full(path, key), options)

    def mapping(self, data: Any, key: str, path: str = '', *, default: Any = _MISSING) -> dict[str, Any]:
        return mapping(self.get(data, key, path, default), self.source, self.full(path, key))

    def floats(self, data: Any, key: str, path: str = '', shape: tuple[int, ...] | None = None, *,
               default: Any = _MISSING, what: str | None = None) -> NDArray[np.float64]:
        return floats(self.get(data, key, path, default), self.source, self.full(path, key), shape,
                      what=what)

    def known_keys(self, data: dict[str, Any], allowed: Iterable[str], path: str = '') -> None:
        known_keys(data, allowed, self.source, f'{path}.' if path else '')


def arg_number(*, low: float | None = None, high: float | None = None, low_open: bool = False,
               high_open: bool = False, integer: bool = False) -> Callable[[str], Any]:
    """An argparse ``type=`` for a number of the rule (``nan``, ``inf`` and out-of-range
    values are refused with the rule)."""
    rule = describe(low=low, high=high, low_open=low_open, high_open=high_open, integer=integer)

    def parse(text_: str) -> float | int:
        try:
            value: float | int = int(text_, 10) if integer else float(text_)
        except ValueError:
            raise argparse.ArgumentTypeError(f'must be {rule}, got {text_!r}') from None
        if number_problem(value, low=low, high=high, low_open=low_open, high_open=high_open,
                          integer=integer):
            raise argparse.ArgumentTypeError(f'must be {rule}, got {text_!r}')
        return value

    parse.__name__ = 'integer' if integer else 'number'
    return parse


def arg_numbers(*, low: float | None = None, high: float | None = None, low_open: bool = False,
                high_open: bool = False) -> Callable[[str], list[float]]:
    """An argparse ``type=`` for comma-separated numbers, each of the rule (at least one)."""
    one = arg_number(low=low, high=high, low_open=low_open, high_open=high_open)
    rule = describe(low=low, high=high, low_open=low_open, high_open=high_open)

    def parse(text_: str) -> list[float]:
        items = [v.strip() for v in text_.split(',') if v.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f'must be {rule}, or several separated by commas, got {text_!r}')
        try:
            return [float(one(v)) for v in items]
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f'each value must be {rule}, got {text_!r}') from None

    parse.__name__ = 'numbers'
    return parse
