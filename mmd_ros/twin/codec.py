"""Plain-dict round trips of the twin's parameter dataclasses.

The twin's parameters (:class:`~mmd_ros.twin.effects.Effects`, scenarios, ambient profiles)
go into a log's metadata as plain JSON/YAML values and come back from there or from the
command line as ``name=value`` assignments (``hysteresis_m=5e-7``, ``limits.speed_m_per_s=0.1``,
``bump=6,0.3,0.005,1e-6``). Values are coerced to the field's declared type; an unknown name or
a value of the wrong kind is refused with a :class:`TwinParameterError` naming the parameter
(unknown names through :func:`mmd_ros.core.validate.unknown_key`, with the name they resemble).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Iterable
from typing import Any, TypeVar

import numpy as np

from mmd_ros.core import validate
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.yamlio import parse_yaml
from mmd_ros.twin.errors import TwinParameterError

__all__ = ['assign', 'from_plain', 'to_plain']

T = TypeVar('T')

_TRUE = {'true', 'on', 'yes', '1'}
_FALSE = {'false', 'off', 'no', '0'}


def to_plain(obj: Any) -> Any:
    """A dataclass (possibly nested) as dicts, lists and Python scalars."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list, np.ndarray)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def from_plain(cls: type[T], data: Any, path: str = '') -> T:
    """Build dataclass ``cls`` from a mapping; missing fields keep their defaults."""
    if isinstance(data, cls):
        return data
    names = [f.name for f in dataclasses.fields(cls)]
    if isinstance(data, str):
        data = [item.strip() for item in data.split(',')]
    if isinstance(data, (list, tuple)):
        if len(data) != len(names):
            raise TwinParameterError(path or cls.__name__, f'expected {len(names)} values '
                            f'({", ".join(names)}), got {len(data)}')
        data = dict(zip(names, data))
    if not isinstance(data, dict):
        raise TwinParameterError(path or cls.__name__, f'expected a mapping of {names}, got {data!r}')
    unknown = validate.unknown_key(sorted(set(data) - set(names), key=str), names, 'parameter',
                                   f' of {cls.__name__}')
    if unknown:
        raise TwinParameterError(f'{path}{unknown[0]}', unknown[1])
    missing = [f.name for f in dataclasses.fields(cls) if f.name not in data
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise TwinParameterError(f'{path or cls.__name__ + "."}{missing[0]}', 'required, not given')
    hints = typing.get_type_hints(cls)
    kwargs = {k: _coerce(hints[k], v, f'{path}{k}') for k, v in data.items()}
    return cls(**kwargs)


def assign(obj: T, assignments: Iterable[str]) -> T:
    """A copy of dataclass ``obj`` with ``name=value`` assignments applied (dots reach into
    nested parameters); values are read as YAML scalars or lists."""
    plain = to_plain(obj)
    for item in assignments:
        name, sep, text = item.partition('=')
        name = name.strip()
        if not sep or not name:
            raise TwinParameterError(repr(item), 'expected name=value')
        try:
            value = parse_yaml(text, name)
        except ConfigError as exc:
            if not exc.problem.startswith('is not valid YAML'):
                raise TwinParameterError(name, f'the value {exc.problem}') from None
            value = text
        node = plain
        keys = name.split('.')
        for key in keys[:-1]:
            if node.get(key) is None:
                node[key] = {}
            if not isinstance(node[key], dict):
                raise TwinParameterError(name, f'{key} is not a group of parameters')
            node = node[key]
        node[keys[-1]] = value
        plain = to_plain(from_plain(type(obj), plain))  # validate now, and normalise text values
    return from_plain(type(obj), plain)


def _coerce(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None or (isinstance(value, str) and value.lower() in ('none', 'null', '')):
            if type(None) in args:
                return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], value, path)
    if dataclasses.is_dataclass(tp):
        return from_plain(tp, value, f'{path}.')
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.strip('[]() ').split(',') if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise TwinParameterError(path, f'expected a list, got {value!r}')
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f'{path}[{i}]') for i, v in enumerate(value))
        if len(args) != len(value):
            raise TwinParameterError(path, f'expected {len(args)} values, got {len(value)}')
        return tuple(_coerce(a, v, f'{path}[{i}]') for i, (a, v) in enumerate(zip(args, value)))
    if tp is bool:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        text = str(value).strip().lower()
        if text in _TRUE | _FALSE:
            return text in _TRUE
        raise TwinParameterError(path, f'expected on/off (true/false), got {value!r}')
    if tp in (int, float):
        if isinstance(value, bool):
            raise TwinParameterError(path, f'expected a number, got {value!r}')
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            raise TwinParameterError(path, f'expected a number, got {value!r}') from None
        if not math.isfinite(number):
            raise TwinParameterError(path, f'expected a finite number, got {value!r}')
        if tp is int:
            if not number.is_integer():
                raise TwinParameterError(path, f'expected an integer, got {value!r}')
            return int(number)
        return number
    if tp is str:
        return str(value)
    raise TwinParameterError(path, f'cannot read a value of type {tp}')  # pragma: no cover
