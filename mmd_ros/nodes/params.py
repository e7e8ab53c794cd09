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
import sys
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

__all__ = ['Param', 'ParameterError', 'check', 'declare', 'every_param_name', 'on_set_checker',
           'unknown_overrides']


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


#: Parameters rclpy itself reads, and prefixes of its own (QoS overrides).
ROS_PARAMS = ('use_sim_time', 'start_type_description_service')
ROS_PARAM_PREFIXES = ('qos_overrides.',)


def every_param_name() -> list[str]:
    """The parameters some mmd_ros node declares (a parameters file under ``/**`` gives every
    node all of them: each takes its own and leaves the others)."""
    from mmd_ros.nodes import compensation_node, fk_node, pose_node, recorder_node, replay_node
    from mmd_ros.nodes.calibration_stage import CALIBRATION_PARAMS
    from mmd_ros.nodes.common import COMMON_PARAMS, MODEL_PARAMS
    from mmd_ros.nodes.recorder_stage import RECORDER_PARAMS
    from mmd_ros.nodes.terminal import TERMINAL_PARAMS
    groups = (COMMON_PARAMS, MODEL_PARAMS, TERMINAL_PARAMS, CALIBRATION_PARAMS, RECORDER_PARAMS,
              compensation_node.PARAMS, fk_node.PARAMS, recorder_node.PARAMS, replay_node.PARAMS,
              pose_node.POSE_PARAMS)
    return sorted({p.name for group in groups for p in group})


def _params_files(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == '--params-file']


def unknown_overrides(names: Iterable[str], argv: list[str] | None = None) -> str | None:
    """Why one of the parameter ``names`` given to a node (``-p``, ``--params-file``) is no
    parameter of any mmd_ros node, naming the one it resembles and the files, or None.

    A typo in a parameters file (``sim_efects:``) would otherwise leave the default in force,
    silently: the same rule as for every other file (:func:`mmd_ros.core.validate.known_keys`).
    """
    known = every_param_name()
    given = [n for n in names if n not in ROS_PARAMS and not n.startswith(ROS_PARAM_PREFIXES)]
    found = validate.unknown_key(given, known, 'parameter', ' of the mmd_ros nodes')
    if found is None:
        return None
    files = _params_files(sys.argv if argv is None else argv)
    where = f' (from {", ".join(files)} or -p)' if files else ''
    problem = found[1].split('; known')[0]
    return f'parameter {found[0]}{where}: {problem}; msg_docs/nodes.md lists them'


def declare(node: Node, params: Iterable[Param]) -> dict[str, Any]:
    """Declare ``params`` on ``node`` and return their checked values by name.

    Raises :class:`ParameterError` for the first invalid value, and for a parameter given to
    the node that no mmd_ros node knows (:func:`unknown_overrides`).
    """
    why = unknown_overrides(getattr(node, '_parameter_overrides', {}))
    if why:
        raise ParameterError(why)
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
