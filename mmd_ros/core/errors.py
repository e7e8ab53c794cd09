"""Exceptions of the metrology core. Each message says what was wrong and what to do."""

from __future__ import annotations

__all__ = ['CalibrationError', 'ConfigError', 'KinematicsError', 'MmdError', 'ModelError']


class MmdError(Exception):
    """Base class of every error raised by mmd_ros."""


class ConfigError(MmdError):
    """A device description, calibration or model file is malformed or inconsistent."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__(f'{source}: key "{key}": {problem}')


class CalibrationError(MmdError):
    """Calibration points cannot define a centre distance function."""


class KinematicsError(MmdError):
    """Forward kinematics was asked something it cannot answer."""


class ModelError(MmdError):
    """A model term is unknown or its parameters do not fit the device."""
