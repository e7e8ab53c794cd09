"""``calibration_node``: the reference-plate calibration routine as a service (section 3.2).

Each call of ``calibrate_bar`` (``std_srvs/srv/Trigger``) captures one calibration point of the
bar and socket pair that come next, averaging the last ``settle_window_s`` of ``raw_counts``; it
refuses, saying why, when the bar is still moving or the reading is implausible for that pair.
The answer says what was captured and what to place next; after a bar's seventh point it
builds the CDF (Eq. 10), reports its quality and saves the calibration atomically (previous
file kept as ``.bak``). The reference bar ends on its resting pair, where its last point also
sets the thermal zero (Eq. 11). After a terminal counter reset (``terminal/counter_reset``) the
calibration is invalid until every bar is re-referenced: one placement on one pair each
(``mode`` auto does that). Parameters ``bar``, ``pair`` and ``mode`` select or override the
next step (``ros2 param set``). The calibration is published on the latched ``calibration``
topic whenever it changes. Topics, parameters: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String

from mmd_ros.core.calibration import Calibration, TerminalBinding
from mmd_ros.core.errors import MmdError
from mmd_ros.nodes.calibration_stage import (
    CalibrationConfig, CalibrationService, CalibrationStage, calibration_params,
)
from mmd_ros.nodes.common import (
    COMMON_PARAMS, MODEL_PARAMS, NAMESPACE, load_device_param, load_model_param, run,
)
from mmd_ros.core.streaming import calibration_created_ns
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, STRING, RawBatch, from_time, string_bytes
from mmd_ros.nodes.diagnostics import Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import declare
from mmd_ros.nodes.progress import CountedInputs, ProgressPublisher
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos

__all__ = ['CalibrationNode', 'main']


class CalibrationNode(CalibrationService, Node):
    """``calibrate_bar`` and the calibration file."""

    def __init__(self) -> None:
        super().__init__('calibration_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + MODEL_PARAMS)
        self.device = load_device_param(v['device_file'])
        model = load_model_param(v['model_file'])
        params = calibration_params(self.device.name)
        v.update(declare(self, params))
        self._params = {p.name: p for p in params}
        self.names = self.device.channel_names
        self.out_calibration = Outlet(self, 'calibration', String, STRING, LATCHED, 'latched')
        self.out_diag = Outlet(self, '/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        self.calibration = CalibrationStage(CalibrationConfig.from_values(v), self.device,
                                      thermal_mode=model.thermal_mode, publish=self._publish,
                                      logger=self.get_logger())
        qos = data_qos(v['qos'], v['qos_depth'])
        self.pending = RawBatch(self.names)
        self.inputs = CountedInputs(self)
        self.inputs.subscribe(JointState, 'raw_counts', self._on_raw, qos)
        self.create_timer(0.02, self._flush)
        self.progress = ProgressPublisher(self, self.inputs, [], v['qos_depth'])
        self.create_subscription(Header, 'terminal/counter_reset', self._on_reset, LATCHED)
        self.create_subscription(String, 'terminal/info', self._on_terminal, LATCHED)
        self._create_calibration_service()
        self.add_on_set_parameters_callback(self._on_set)
        self.create_timer(1.0, self.calibration.poll_file)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self.calibration.start()

    def _publish(self, cal: Calibration) -> None:
        self.out_calibration.payload(string_bytes(cal.to_yaml()), self.get_clock().now().nanoseconds)

    def _on_raw(self, payload: bytes) -> None:
        if self.pending.add(payload) >= 64:
            self._flush()

    def _flush(self) -> None:
        if len(self.pending):
            stamps, counts, status = self.pending.take_all()
            if status is not None:  # samples without encoder signal are no calibration points
                good = ~status.any(axis=1)
                stamps, counts = stamps[good], counts[good]
            self.calibration.feed(stamps, counts)

    def _on_terminal(self, msg: String) -> None:
        """The encoder node says which terminal it reads: bind and check the calibration."""
        try:
            binding = TerminalBinding.from_yaml(msg.data, 'terminal/info')
        except MmdError as exc:
            self.get_logger().error(f'terminal/info message refused: {exc}')
            return
        self.calibration.set_terminal(binding)

    def _on_reset(self, msg: Header) -> None:
        stamp = from_time(msg.stamp)
        cal = self.calibration.routine.calibration
        if cal is None or not cal.valid:
            self.calibration.buffer.note_reset(stamp)
            return
        created = calibration_created_ns(cal)
        if created is not None and created >= stamp:
            return  # an old event: this calibration was made after that reset
        self.calibration.on_counter_reset(stamp)

    def _before_capture(self) -> None:
        self._flush()

    def _on_set(self, changes: list[Parameter]) -> SetParametersResult:
        for change in changes:
            why = self._refuse_parameter(change.name, change.value)
            if why:
                return SetParametersResult(successful=False, reason=why)
        return SetParametersResult(successful=True)

    def _report(self) -> list:
        r = self.calibration.report(*self._selection())
        self.inputs.report(r)
        return [r]


def main(args: list[str] | None = None) -> int:
    return run(CalibrationNode, args)


if __name__ == '__main__':
    sys.exit(main())
