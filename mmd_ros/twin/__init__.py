"""The digital twin of the MMD (ROS-free): a simulated device that produces encoder counts.

It simulates the physical device of Lei & Chen (2024) independently of the compensation and
kinematics code in :mod:`mmd_ros.core`: its own inverse kinematics (Eqs. 2-6), the thermal
model of a ball bar (Fig. 10, section 3.3), switchable error effects, the calibration routine
on the reference plate (section 3.2) and the experiments of sections 4.1 and 5.

    twin = TwinDevice(load_device(find_config('mmd_prototype.yaml')), Effects.realistic(), seed=1)
    room = AmbientProfile.constant(20.0)
    calibration = twin.calibrate(0.0, room)
    run = twin.simulate(IsoLinear(axis='x'), room, start_s=600.0)
"""

from mmd_ros.twin.effects import Bump, Effects
from mmd_ros.twin.errors import TwinError, TwinParameterError, WorkspaceError
from mmd_ros.twin.mechanism import bar_legs, rotation_matrices
from mmd_ros.twin.reference import REFERENCE_KINDS
from mmd_ros.twin.scenarios import (
    HOME_POSE, SCENARIOS, Hold, IsoLinear, IsoRotary, RandomMotion, Scenario, ThermalSoak,
    make_scenario, scenario_from_dict,
)
from mmd_ros.twin.thermal import REFERENCE_TEMP_C, AmbientProfile, Ramp
from mmd_ros.twin.trajectories import MachineErrors, MotionLimits, Trajectory
from mmd_ros.twin.twin import IsoTargets, Placement, SimulatedRun, TwinDevice, simulated_serial

__all__ = [
    'AmbientProfile', 'Bump', 'Effects', 'HOME_POSE', 'Hold', 'IsoLinear', 'IsoRotary',
    'IsoTargets', 'MachineErrors', 'MotionLimits', 'Placement', 'REFERENCE_KINDS',
    'REFERENCE_TEMP_C', 'Ramp', 'RandomMotion', 'SCENARIOS', 'Scenario', 'SimulatedRun',
    'ThermalSoak', 'Trajectory', 'TwinDevice', 'TwinError', 'TwinParameterError', 'WorkspaceError',
    'bar_legs', 'make_scenario', 'rotation_matrices', 'scenario_from_dict', 'simulated_serial',
]
