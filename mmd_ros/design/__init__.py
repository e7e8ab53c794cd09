"""Design tools of the MMD, ROS-free: the Monte Carlo error budget of the kinematic parameters
(section 2.2 of Lei & Chen, 2024) and the reachable workspace (section 2.3, Fig. 8).

Figures live in :mod:`mmd_ros.design.plots`, imported on demand (it needs matplotlib).
"""

from __future__ import annotations

from mmd_ros.design.error_budget import (
    DEFAULT_READING, PAPER_DESIGN_POINT_M, PAPER_EQ9_UM, PAPER_POSITIONS_M, READINGS, Accuracy,
    ErrorBudget, FrontierPoint, PoseErrors, Study, Surface, TopEdgeCylinder, fit_eq9, run_study,
    sample_unit_errors, tolerance_frontier)
from mmd_ros.design.errors import DesignError
from mmd_ros.design.workspace import (
    CONSTRAINTS, PAPER_CYLINDER_M, PAPER_RANGES_M, PAPER_ROTATION_LEVELS_DEG, PAPER_SPHERE_M,
    Workspace, WorkspaceLimits, WorkspaceStudy, largest_rotation_range, orientation_set,
    run_workspace_study)

__all__ = [
    'Accuracy', 'CONSTRAINTS', 'DEFAULT_READING', 'DesignError', 'ErrorBudget',
    'FrontierPoint', 'PAPER_CYLINDER_M', 'PAPER_DESIGN_POINT_M', 'PAPER_EQ9_UM',
    'PAPER_POSITIONS_M', 'PAPER_RANGES_M', 'PAPER_ROTATION_LEVELS_DEG', 'PAPER_SPHERE_M',
    'PoseErrors', 'READINGS', 'Study', 'Surface', 'TopEdgeCylinder', 'Workspace',
    'WorkspaceLimits', 'WorkspaceStudy', 'fit_eq9', 'largest_rotation_range',
    'orientation_set', 'run_study', 'run_workspace_study', 'sample_unit_errors',
    'tolerance_frontier',
]
