"""Exceptions of the digital twin. Each message says what was wrong and what to do."""

from __future__ import annotations

from mmd_ros.core.errors import MmdError

__all__ = ['TwinError', 'TwinParameterError', 'WorkspaceError']


class TwinError(MmdError):
    """A twin parameter, scenario or request is invalid."""


class WorkspaceError(TwinError):
    """A scenario takes a bar out of its range or a joint beyond its tilt limit."""


class TwinParameterError(TwinError):
    """A twin parameter (of effects, a scenario, an ambient profile) is unknown or has a value
    of the wrong kind: ``key`` names it (``ramps[0].end_c``), ``problem`` says what is wrong."""

    def __init__(self, key: str, problem: str) -> None:
        self.key = key
        self.problem = problem
        super().__init__(f'{key}: {problem}')
