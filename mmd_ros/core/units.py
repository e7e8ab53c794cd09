"""Unit conversions, in one place.

Core APIs and topics are SI (REP-103): metres, radians, seconds, degrees Celsius. Reports,
plots and CLI tables use mm, µm and arc-seconds; they convert here and nowhere else.
"""

from __future__ import annotations

import math

__all__ = [
    'ARCSEC_PER_RAD', 'M_PER_MM', 'M_PER_NM', 'M_PER_UM', 'NS_PER_S', 'PPM',
    'arcsec', 'deg', 'mm', 'um',
]

M_PER_MM = 1e-3
M_PER_UM = 1e-6
M_PER_NM = 1e-9
PPM = 1e-6
NS_PER_S = 1_000_000_000
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0


def mm(value_m):
    """Metres to millimetres."""
    return value_m / M_PER_MM


def um(value_m):
    """Metres to micrometres."""
    return value_m / M_PER_UM


def arcsec(value_rad):
    """Radians to arc-seconds."""
    return value_rad * ARCSEC_PER_RAD


def deg(value_rad):
    """Radians to degrees."""
    return value_rad * (180.0 / math.pi)
