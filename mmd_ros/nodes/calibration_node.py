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
from std_srvs.srv import Trigger

from mmd_ros.core.calibration import Calibration
from mmd_ros.core.errors import MmdError
from mmd_ros.nodes.calibration_stage import (
    CalibrationConfig, CalibrationStage, calibration_params,
)
from mmd_ros.nodes.common import (
    COMMON_PARAMS, MODEL_PARAMS, NAMESPACE, load_device_param, load_model_param, run,
)
from mmd_ros.nodes.compute import calibration_created_ns
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, STRING, RawBatch, from_time, string_bytes
from mmd_ros.nodes.diagnostics import Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import check, declare
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos

__all__ = ['CalibrationNode', 'main']


class CalibrationNode(Node):
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
        self.stage = CalibrationStage(CalibrationConfig.from_values(v), self.device,
                                      thermal_mode=model.thermal_mode, publish=self._publish,
                                      logger=self.get_logger())
        qos = data_qos(v['qos'], v['qos_depth'])
        self.pending = RawBatch(self.names)
        self.create_subscription(JointState, 'raw_counts', self._on_raw, qos, raw=True)
        self.create_timer(0.02, self._flush)
        self.create_subscription(Header, 'terminal/counter_reset', self._on_reset, LATCHED)
        self.create_service(Trigger, 'calibrate_bar', self._calibrate_bar)
        self.create_service(Trigger, 'calibration/reset_session', self._reset_session)
        self.add_on_set_parameters_callback(self._on_set)
        self.create_timer(1.0, self.stage.poll_file)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self.stage.start()

    def _publish(self, cal: Calibration) -> None:
        self.out_calibration.payload(string_bytes(cal.to_yaml()), self.get_clock().now().nanoseconds)

    def _on_raw(self, payload: bytes) -> None:
        if self.pending.add(payload) >= 64:
            self._flush()

    def _flush(self) -> None:
        if len(self.pending):
            self.stage.feed(*self.pending.take())

    def _on_reset(self, msg: Header) -> None:
        stamp = from_time(msg.stamp)
        cal = self.stage.routine.calibration
        if cal is None or not cal.valid:
            self.stage.buffer.note_reset(stamp)
            return
        created = calibration_created_ns(cal)
        if created is not None and created >= stamp:
            return  # an old event: this calibration was made after that reset
        self.stage.on_counter_reset(stamp)

    def _selection(self) -> tuple[str, str, str]:
        return (self.get_parameter('bar').value, self.get_parameter('pair').value,
                self.get_parameter('mode').value)

    def _calibrate_bar(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._flush()
        bar, pair, mode = self._selection()
        response.success, response.message = self.stage.trigger(bar, pair, mode)
        if response.success and pair:
            self.set_parameters([Parameter('pair', Parameter.Type.STRING, '')])
        return response

    def _reset_session(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.stage.reset_session()
        return response

    def _on_set(self, changes: list[Parameter]) -> SetParametersResult:
        for change in changes:
            p = self._params.get(change.name)
            if p is None:
                continue
            why = check(p, change.value)
            if why:
                return SetParametersResult(successful=False, reason=why)
            if change.name in ('bar', 'pair') and change.value:
                try:
                    self.stage.routine.next_step(change.value if change.name == 'bar' else '',
                                                 change.value if change.name == 'pair' else '', 'full')
                except MmdError as exc:
                    return SetParametersResult(successful=False, reason=f'parameter {change.name}: {exc}')
        return SetParametersResult(successful=True)

    def _report(self) -> list:
        return [self.stage.report(*self._selection())]


def main(args: list[str] | None = None) -> int:
    return run(CalibrationNode, args)


if __name__ == '__main__':
    sys.exit(main())
