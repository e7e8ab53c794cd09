"""``encoder_node``: the 8-channel encoder terminal on ROS.

Reads the terminal through pyusb (``device:=usb``) or the simulated terminal streaming the
digital twin (``device:=sim``), from a reader thread blocking on the transport, and publishes
every sample's raw counts on ``raw_counts`` (one ``sensor_msgs/JointState`` per sample, stamped
with the terminal's sample time mapped to ROS time). A terminal counter reset is published on
the latched ``terminal/counter_reset`` (``std_msgs/Header``: stamp of the first sample after it,
``frame_id`` the terminal's serial) so that the calibration and compensation nodes stop using
the lost count offsets. Which terminal it reads (serial number, simulated or not, the bar on each
channel) goes to the latched ``terminal/info`` each time it is opened: the calibration and
compensation nodes check a calibration against it. Topics, parameters: ``msg_docs/nodes.md``.
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
from mmd_ros.nodes.common import COMMON_PARAMS, NAMESPACE, load_device_param, run
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, HEADER, JS, STRING, Rows, header, string_bytes
from mmd_ros.nodes.diagnostics import Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import check, declare
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos
from mmd_ros.nodes.terminal import TERMINAL_PARAMS, TerminalConfig, TerminalStage

__all__ = ['EncoderNode', 'main']


class EncoderNode(Node):
    """The terminal's samples on ``raw_counts`` (and the twin's reference, simulated)."""

    def __init__(self) -> None:
        super().__init__('encoder_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + TERMINAL_PARAMS)
        self._params = {p.name: p for p in TERMINAL_PARAMS}
        device = load_device_param(v['device_file'])
        qos = data_qos(v['qos'], v['qos_depth'])
        kind = 'sensor' if v['qos'] == 'sensor' else 'reliable'
        rows = Rows(device.channel_names, [c.name for c in device.reference_channels])
        self.out_raw = Outlet(self, 'raw_counts', JointState, JS, qos, kind)
        self.out_reference = Outlet(self, 'reference/pose', JointState, JS, qos, kind)
        self.out_device = Outlet(self, 'device_description', String, STRING, LATCHED, 'latched')
        self.out_reset = Outlet(self, 'terminal/counter_reset', Header, HEADER, LATCHED, 'latched')
        self.out_info = Outlet(self, 'terminal/info', String, STRING, LATCHED, 'latched')
        self.out_diag = Outlet(self, '/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        self.terminal = TerminalStage(TerminalConfig.from_values(v), device, rows, self.out_raw,
                                      self.out_reference, self.get_logger(), alive=self.context.ok)
        self.terminal.on_reset.append(self._on_reset)
        self.terminal.on_open.append(self._on_open)
        self._reset_at_ns: int | None = None
        self.create_subscription(String, 'calibration', self._on_calibration, LATCHED)
        self.add_on_set_parameters_callback(self._on_set)
        self.diagnostics = Diagnostics(self, self.out_diag, [lambda: [self.terminal.report()]],
                                       v['diagnostics_period_s'], hardware_id=lambda: self.terminal.serial)
        self.out_device.payload(string_bytes(device.to_yaml()), self.get_clock().now().nanoseconds)
        self.terminal.start()

    def _on_open(self, binding: TerminalBinding) -> None:
        self.out_info.payload(string_bytes(binding.to_yaml()), self.get_clock().now().nanoseconds)

    def _on_reset(self, stamp_ns: int) -> None:
        # called from the reader thread before the first sample after the reset is published
        self._reset_at_ns = stamp_ns
        self.out_reset.message(header(stamp_ns, self.terminal.serial), stamp_ns)

    def _on_calibration(self, msg: String) -> None:
        """A calibration made after the last counter reset and valid: the bars are re-referenced."""
        if self._reset_at_ns is None or self.terminal.driver.reference_valid:
            return
        try:
            cal = Calibration.from_yaml(msg.data, 'calibration topic')
        except MmdError:
            return
        if cal.valid and not cal.quality.get('pending_re_reference'):
            self.terminal.mark_referenced()
            self.get_logger().info('the bars were re-referenced: the counter reset is resolved')

    def _on_set(self, changes: list[Parameter]) -> SetParametersResult:
        for change in changes:
            p = self._params.get(change.name)
            if p is None:
                continue
            why = check(p, change.value)
            if why:
                return SetParametersResult(successful=False, reason=why)
            if change.name == 'sim_command':
                ok, text = self.terminal.sim_command(change.value)
                return SetParametersResult(successful=ok, reason=text)
        return SetParametersResult(successful=True)

    def destroy_node(self) -> None:
        self.terminal.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(EncoderNode, args)


if __name__ == '__main__':
    sys.exit(main())
