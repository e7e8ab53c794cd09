"""``pose_node``: the whole pipeline in one process.

Terminal → compensation → forward kinematics, with the calibration service and the recorder,
passing each transfer's samples between the stages by direct calls (no serialisation between
them) and still publishing every topic of the separate nodes, plus ``pose_batch`` (a transfer's
poses in one ``nav_msgs/Path``, for subscribers that cannot take 1 kHz). Samples the terminal
flagged (encoder signal lost) are no measurements: no length, no pose. The calibration is bound
to the terminal it was made with (``calibration_stage``). Defaults: the simulated terminal
streaming the digital twin in a demonstration scenario (random 6-DOF motion), a factory
calibration of the twin when there is no calibration file yet, and recording on, so that
``ros2 run mmd_ros pose_node`` works on a machine without hardware.

Topics, parameters and services: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from mmd_ros.core.calibration import Calibration, TerminalBinding
from mmd_ros.core.errors import MmdError
from mmd_ros.nodes.calibration_stage import (
    CalibrationConfig, CalibrationService, CalibrationStage, calibration_params,
)
from mmd_ros.nodes.common import (
    COMMON_PARAMS, MODEL_PARAMS, NAMESPACE, load_device_param, load_model_param, run,
)
from mmd_ros.core.streaming import Compensator, Kinematics
from mmd_ros.nodes.convert import (
    DIAGNOSTIC_ARRAY, JS, PATH, POSE, POSE_COV, STRING, Rows, string_bytes,
)
from mmd_ros.nodes.diagnostics import Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, declare
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos
from mmd_ros.nodes.recorder_stage import RECORDER_PARAMS, RecorderConfig, RecorderStage, raw_writer
from mmd_ros.nodes.reports import compensation_report, kinematics_report
from mmd_ros.nodes.terminal import TERMINAL_PARAMS, TerminalConfig, TerminalStage, sim_serial_of

__all__ = ['PoseNode', 'main']

POSE_PARAMS = [
    Param('record', True, 'record every topic of this node into an MCAP log'),
    Param('publish_covariance', True, 'publish pose_with_covariance'),
    Param('thermal_warn_c', 2.0, 'warn when the temperature has changed more than this since the '
          'thermal zero with one reference bar (Eq. 13 territory) [°C]', low=0.0, high=100.0),
    Param('sim_factory_calibration', True, 'simulation: when the calibration file does not exist, '
          'write the twin\'s own calibration (made before power-on) into it'),
]


class PoseNode(CalibrationService, Node):
    """Terminal, compensation, kinematics, calibration service and recorder in one node."""

    def __init__(self) -> None:
        super().__init__('pose_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + MODEL_PARAMS + TERMINAL_PARAMS + POSE_PARAMS)
        device = load_device_param(v['device_file'])
        # the simulated terminal has its own default calibration file: a simulation never
        # writes the file a real terminal reads
        cal_params = calibration_params(device.name,
                                        sim_serial_of(v) if v['device'] == 'sim' else '')
        v.update(declare(self, cal_params))
        record = v['record']
        if record:
            v.update(declare(self, RECORDER_PARAMS))
        self._params = {p.name: p for p in TERMINAL_PARAMS + cal_params}
        self.device = device
        self.model = load_model_param(v['model_file'])
        self.rows = Rows(device.channel_names, [c.name for c in device.reference_channels])
        self.recorder = RecorderStage(RecorderConfig.from_values(v), self.get_fully_qualified_name(),
                                      self.get_logger()) if record else None
        rec = self.recorder.queue if self.recorder is not None else None
        qos = data_qos(v['qos'], v['qos_depth'])
        log_qos = 'sensor' if v['qos'] == 'sensor' else 'reliable'

        def outlet(topic: str, cls: Any, type_name: str, profile=qos, kind=log_qos) -> Outlet:
            return Outlet(self, topic, cls, type_name, profile, kind, rec)

        self.out_device = outlet('device_description', String, STRING, LATCHED, 'latched')
        self.out_calibration = outlet('calibration', String, STRING, LATCHED, 'latched')
        self.out_model = outlet('model', String, STRING, LATCHED, 'latched')
        self.out_info = outlet('terminal/info', String, STRING, LATCHED, 'latched')
        self.out_raw = outlet('raw_counts', JointState, JS)
        self.out_reference = outlet('reference/pose', JointState, JS)
        self.out_lengths = outlet('bar_lengths', JointState, JS)
        self.out_thermal = outlet('thermal', JointState, JS)
        self.out_status = outlet('fk_status', JointState, JS)
        self.out_pose = outlet('pose', PoseStamped, POSE)
        self.out_pose_cov = outlet('pose_with_covariance', PoseWithCovarianceStamped, POSE_COV)
        # the poses of a transfer in one message, for subscribers that cannot take 1 kHz (not
        # recorded: the same poses are in pose)
        self.out_pose_batch = Outlet(self, 'pose_batch', Path, PATH, qos, log_qos)
        self.out_diag = outlet('/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS, 'reliable')
        if rec is not None:
            # the machine tool's axis positions beside the poses (mmd machine), when a controller
            # publishes them: recorded as received
            self.create_subscription(
                JointState, 'machine/joint_states',
                raw_writer(rec, self.get_clock(), self.resolve_topic_name('machine/joint_states'),
                           JS, log_qos, True), qos, raw=True)
        self.publish_covariance = v['publish_covariance']
        self.thermal_warn_c = v['thermal_warn_c']

        self.compensator = Compensator(device, self.model)
        self.kinematics = Kinematics(device, None, with_covariance=self.publish_covariance)
        tcfg = TerminalConfig.from_values(v)
        self.terminal = TerminalStage(tcfg, device, self.rows, self.out_raw, self.out_reference,
                                      self.get_logger(), alive=self.context.ok, raw_last=True)
        factory = None
        if tcfg.device == 'sim' and v['sim_factory_calibration'] and self.terminal.source is not None:
            factory = self.terminal.source.factory_calibration
        self.calibration = CalibrationStage(
            CalibrationConfig.from_values(v), device, thermal_mode=self.model.thermal_mode,
            publish=self._publish_calibration, logger=self.get_logger(),
            on_valid=self.terminal.mark_referenced, on_refused=self._calibration_refused,
            factory=factory, terminal=self.terminal.binding())
        self.terminal.on_open.append(self._on_open)
        self.terminal.on_reset.append(self._on_reset)
        self.terminal.on_batch.append(self._on_batch)

        self._create_calibration_service()
        self.add_on_set_parameters_callback(self._on_set)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._reports], v['diagnostics_period_s'],
                                       hardware_id=lambda: self.terminal.serial)
        self.create_timer(1.0, self.calibration.poll_file)
        stamp = self.get_clock().now().nanoseconds
        self.out_device.payload(string_bytes(device.to_yaml()), stamp)
        self.out_model.payload(string_bytes(self.model.to_yaml()), stamp)
        self.calibration.start()
        self.terminal.start()
        self.get_logger().info(
            f'pose_node: {tcfg.device} terminal, calibration {self.calibration.path}, '
            + (f'recording into {self.recorder.path}' if self.recorder else 'not recording'))

    # -- stages --------------------------------------------------------------------------------
    def _publish_calibration(self, cal: Calibration) -> None:
        self.compensator.set_calibration(cal, str(self.calibration.path)
                                         if hasattr(self, 'calibration') else 'calibration file')
        if self.publish_covariance:
            # the uncertainty budget of this calibration (it fits the interpolation error)
            try:
                self.kinematics.budget = self.compensator.budget
            except MmdError as exc:
                self.kinematics.budget = None
                self.get_logger().error(f'no covariance with this calibration: {exc}')
        self.out_calibration.payload(string_bytes(cal.to_yaml()), self.get_clock().now().nanoseconds)

    def _on_open(self, binding: TerminalBinding) -> None:
        self.out_info.payload(string_bytes(binding.to_yaml()), self.get_clock().now().nanoseconds)
        self.calibration.set_terminal(binding)

    def _calibration_refused(self) -> None:
        self.compensator.set_calibration(None, 'refused: made with another terminal')

    def _on_reset(self, stamp_ns: int) -> None:
        self.compensator.hold(stamp_ns)
        self.calibration.on_counter_reset(stamp_ns)

    def _on_batch(self, stamps, counts, status) -> None:
        # poses first (what CNC tooling waits for), then the calibration routine's capture, the
        # covariance (computed only now) and the rest of the transfer's topics
        comp = self.compensator.process(stamps, counts, status)
        if comp is not None:
            kin = self.kinematics.solve(comp.lengths_m, comp.plate_scale, comp.reference_error_m,
                                        comp.temp_change_c, comp.bar_error_m, comp.fit_columns_m,
                                        stamps_ns=stamps)
            valid = kin.valid if kin.valid.any() else None
            if valid is not None:
                s = stamps[valid]
                poses = kin.poses[valid]
                self.out_pose.rows(self.rows.poses(s, poses), s)
                self.out_pose_batch.payload(self.rows.pose_batch(s, poses), int(s[-1]))
        if status is None:
            self.calibration.feed(stamps, counts)
        else:  # samples without encoder signal are no calibration points
            good = ~status.any(axis=1)
            self.calibration.feed(stamps[good], counts[good])
        if comp is None:
            return
        if valid is not None and kin.covariance is not None:
            self.out_pose_cov.rows(self.rows.poses(s, poses, kin.covariance), s)
        self.out_lengths.rows(self.rows.lengths.encode(stamps, comp.lengths_m), stamps)
        self.out_thermal.rows(self.rows.thermal.encode(stamps, comp.thermal_values()), stamps)
        self.out_status.rows(self.rows.fk_status.encode(stamps, kin.status_values()), stamps)

    # -- service and parameters ----------------------------------------------------------------
    def _on_set(self, changes: list[Parameter]) -> SetParametersResult:
        for change in changes:
            why = self._refuse_parameter(change.name, change.value)
            if why:
                return SetParametersResult(successful=False, reason=why)
            if change.name == 'sim_command':
                ok, text = self.terminal.sim_command(change.value)
                return SetParametersResult(successful=ok, reason=text)
        return SetParametersResult(successful=True)

    def _reports(self) -> list:
        bar, pair, mode = self._selection()
        out = [self.terminal.report(),
               compensation_report(self.compensator, self.thermal_warn_c, self.model.source),
               kinematics_report(self.kinematics),
               self.calibration.report(bar, pair, mode)]
        if self.recorder is not None:
            out.append(self.recorder.report())
        return out

    def destroy_node(self) -> None:
        self.terminal.stop()
        if self.recorder is not None:
            # the last diagnostics say how the recording ended
            self.recorder.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(PoseNode, args)


if __name__ == '__main__':
    sys.exit(main())
