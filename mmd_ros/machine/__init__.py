"""Machine-tool geometric errors from an MMD session (ROS-free): ISO 230-1 error motions and
squareness of the linear axes, ISO 230-7 component and location errors of the rotary axes, a
kinematic model with the volumetric error, and compensation files.

    machine = load_machine('machine_xyzac.yaml')
    result = analyze_session(['session.mcap'], machine)          # every error with its uncertainty
    write_outputs(result, Path('out/machine'))                   # report, figures, comp files

``msg_docs/machine.md`` states the definitions, signs and file formats.
"""

from mmd_ros.machine.analyze import SessionOptions, analyze_session, separation_text, write_outputs
from mmd_ros.machine.compensation import (
    linuxcnc_table, write_compensation, write_csv, write_location_yaml,
)
from mmd_ros.machine.errors import MachineAnalysisError
from mmd_ros.machine.identify import IdentifyOptions, identify
from mmd_ros.machine.kinematics import ErrorTable, MachineModel, RotaryLocation
from mmd_ros.machine.report import error_rows, error_table, markdown_report
from mmd_ros.machine.results import AxisResult, ErrorMotion, MachineResult, Value, load_result
from mmd_ros.machine.session import (
    Approach, AxisRun, Program, ProgramRun, extract_runs, load_program, log_poses,
)
from mmd_ros.machine.volumetric import VolumetricMap, linear_map, rotary_map

__all__ = [
    'Approach', 'AxisResult', 'AxisRun', 'ErrorMotion', 'ErrorTable', 'IdentifyOptions',
    'MachineAnalysisError', 'MachineModel', 'MachineResult', 'Program', 'ProgramRun',
    'RotaryLocation', 'SessionOptions', 'Value', 'VolumetricMap', 'analyze_session', 'error_rows',
    'error_table', 'extract_runs', 'identify', 'linear_map', 'linuxcnc_table', 'load_program',
    'load_result', 'log_poses', 'markdown_report', 'rotary_map', 'separation_text',
    'write_compensation', 'write_csv', 'write_location_yaml', 'write_outputs',
]
