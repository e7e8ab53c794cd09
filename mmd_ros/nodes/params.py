"""Node parameters: declared once with descriptors, validated into plain values.

Each node lists its parameters as :class:`Param` entries (name, default, unit and meaning,
allowed range or choices, whether it may change at run time). :func:`declare` declares them
with a ``ParameterDescriptor`` (so ``ros2 param describe`` shows the description and range),
reads the values and checks every one; an invalid value raises :class:`ParameterError` naming
the parameter, the value and what is allowed, and the node refuses to start. Parameters marked
``dynamic`` may be changed with ``ros2 param set``; their new values go through the same check
(:func:`check`) in the node's on-set callback.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult,
)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from mmd_ros.core import validate
from mmd_ros.core.errors import MmdError

__all__ = ['Param', 'ParameterError', 'check', 'declare', 'on_set_checker']


class ParameterError(MmdError):
    """A parameter has a value the node cannot use."""


@dataclass(frozen=True)
class Param:
    """One parameter.

    name : parameter name
    default : default value; its Python type (bool, int, float, str) is the parameter's type
    description : meaning and unit
    low, high : allowed range (inclusive) for numbers; None for no bound
    choices : allowed values for strings
    dynamic : may be changed at run time
    allow_zero : 0 is allowed besides the range (0 meaning "off" or "keep")
    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    dynamic: bool = False
    allow_zero: bool = False

    def allowed(self) -> str:
        if self.choices is not None:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        parts = []
        if self.low is not None or self.high is not None:
            lo = '-inf' if self.low is None else f'{self.low:g}'
            hi = 'inf' if self.high is None else f'{self.high:g}'
            parts.append(f'in [{lo}, {hi}]')
        if self.allow_zero:
            parts.append('0')
        if isinstance(self.default, float) and math.isnan(self.default):
            parts.append('NaN (unset)')
        kind = {'bool': 'true or false', 'int': 'an integer', 'float': 'a number',
                'str': 'a string'}[type(self.default).__name__]
        return kind + (' ' + ' or '.join(parts) if parts else '')

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(name=self.name, description=self.description,
                                read_only=not self.dynamic,
                                additional_constraints=f'must be {self.allowed()}')
        if isinstance(self.default, bool):
            return d
        if isinstance(self.default, int) and self.low is not None and self.high is not None \
                and not self.allow_zero:
            d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=1)]
        elif isinstance(self.default, float) and self.low is not None and self.high is not None \
                and not self.allow_zero and not math.isnan(self.default):
            d.floating_point_range = [FloatingPointRange(from_value=float(self.low),
                                                         to_value=float(self.high), step=0.0)]
        return d


def check(param: Param, value: Any) -> str | None:
    """Why ``value`` is not acceptable for ``param``, or None (the range through
    :func:`mmd_ros.core.validate.number_problem`, as for files and command-line options)."""
    want = type(param.default)
    bad = f'parameter {param.name}: must be {param.allowed()}, got {value!r}'
    if want is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if want in (int, float):
        if want is float and isinstance(value, float) and math.isnan(value):
            if math.isnan(param.default):
                return None
            return f'parameter {param.name}: must be {param.allowed()}, got NaN'
        if param.allow_zero and value == 0 and not isinstance(value, bool):
            return None
        if validate.number_problem(value, low=param.low, high=param.high, integer=want is int):
            return bad
    elif not isinstance(value, want):
        return bad
    if param.choices is not None and value not in param.choices:
        return bad
    return None


def declare(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """Declare ``params`` on ``node`` and return their checked values by name.

    Raises :class:`ParameterError` for the first invalid value.
    """
    out: dict[str, Any] = {}
    for p in params:
        try:
            value = node.declare_parameter(p.name, p.default, p.descriptor()).value
        except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
            given = getattr(exc, 'value', None)
            raise ParameterError(f'parameter {p.name}: must be {p.allowed()}'
                                 + (f', got {given!r}' if given is not None else f' ({exc})')) from None
        if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        why = check(p, value)
        if why:
            raise ParameterError(why)
        out[p.name] = value
    return out


def on_set_checker(params: Iterable[Param]):
    """An on-set-parameters callback that refuses invalid values of the given parameters
    (read-only ones are refused by rclpy itself)."""
    by_name = {p.name: p for p in params}

    def callback(changes: list[Parameter]) -> SetParametersResult:
        for change in changes:
            p = by_name.get(change.name)
            if p is None:
                continue
            why = check(p, change.value)
            if why:
                return SetParametersResult(successful=False, reason=why)
        return SetParametersResult(successful=True)

    return callback
