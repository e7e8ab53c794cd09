"""JSON for ``--json`` and the reports, always valid: NaN and infinities become ``null``.

Python's :mod:`json` writes a NaN as the bare word ``NaN``, which no JSON parser accepts; a
quantity that is not known (a pose that did not converge, a figure of an axis without a
reference) is written as ``null`` instead, and :func:`dumps` refuses anything else that is not
JSON (``allow_nan=False``), so a forgotten case fails loudly in the tests, not in a user's
parser.
"""

from __future__ import annotations

import json
import math
from typing import IO, Any

import numpy as np

__all__ = ['dump', 'dumps', 'finite_json']


def finite_json(value: Any) -> Any:
    """``value`` with NaN and infinities as None, numpy scalars and arrays as Python values,
    tuples as lists (dicts and lists are copied, not changed in place)."""
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return finite_json(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def _default(value: Any) -> Any:
    if hasattr(value, 'as_dict'):
        return finite_json(value.as_dict())
    if hasattr(value, 'tolist'):
        return finite_json(value.tolist())
    return str(value)


def dumps(data: Any, *, indent: int | None = 2) -> str:
    """``data`` as JSON text (see the module docstring)."""
    return json.dumps(finite_json(data), indent=indent, allow_nan=False, default=_default)


def dump(data: Any, stream: IO[str], *, indent: int | None = 2) -> None:
    """``data`` as JSON on ``stream``, with a final newline."""
    stream.write(dumps(data, indent=indent) + '\n')
