"""``compensation_node``: raw counts → compensated centre distances and the thermal state.

Applies each bar's CDF (Eq. 10), the reference-bar thermal offset (Eq. 11, Eq. 13 with one
reference bar, Eq. 12 with two) and the model's active terms to every ``raw_counts`` sample and
publishes ``bar_lengths`` (d_i* [m]; NaN for a bar outside its calibrated span) and ``thermal``
(Eq. 11 error per reference bar [m], temperature change since the thermal zero [°C], the
plates' scale factor). The calibration comes from the latched ``calibration`` topic (the
calibration node, a replay) and, with ``calibration_file`` set, from that file, reloaded when
it changes; either way without a restart. A calibration made with another terminal than the one
``terminal/info`` names (or on the simulator, for hardware) is refused unless
``calibration_any_terminal`` is set; either way the diagnostics say ERROR. A
``terminal/counter_reset`` event stops the output until a calibration made after it arrives.
Topics, parameters: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String

from mmd_ros.core.calibration import (
    Calibration, TerminalBinding, binding_problem, load_calibration,
)
from mmd_ros.core.errors import MmdError
from mmd_ros.nodes.common import (
    COMMON_PARAMS, MODEL_PARAMS, NAMESPACE, load_device_param, load_model_param, run,
)
from mmd_ros.core.streaming import Compensator
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, JS, STRING, RawBatch, Rows, from_time, string_bytes
from mmd_ros.nodes.calibration_stage import ANY_TERMINAL
from mmd_ros.nodes.diagnostics import ERROR, Diagnostics, Events
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, declare
from mmd_ros.nodes.progress import CountedInputs, ProgressPublisher
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos
from mmd_ros.nodes.reports import compensation_report

__all__ = ['CompensationNode', 'main']

#: Samples computed together (a transfer of the terminal), and the longest wait for the rest [s].
BATCH = 8
FLUSH_PERIOD_S = 0.005

PARAMS = [
    Param('calibration_file', '', 'also read the calibration from this file and reload it when it '
          'changes ("" only the calibration topic)'),
    Param('thermal_warn_c', 2.0, 'warn when the temperature has changed more than this since the '
          'thermal zero with one reference bar (Eq. 13 territory) [°C]', low=0.0, high=100.0),
    ANY_TERMINAL,
]


class CompensationNode(Node):
    """Counts → bar lengths and thermal state, for every sample."""

    def __init__(self) -> None:
        super().__init__('compensation_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + MODEL_PARAMS + PARAMS)
        self.device = load_device_param(v['device_file'])
        self.model = load_model_param(v['model_file'])
        self.names = self.device.channel_names
        self.rows = Rows(self.names, [c.name for c in self.device.reference_channels])
        self.thermal_warn_c = v['thermal_warn_c']
        self.compensator = Compensator(self.device, self.model)
        self.events = Events()
        self.any_terminal = v['calibration_any_terminal']
        self.terminal: TerminalBinding | None = None
        self._offered: tuple[Calibration, str] | None = None
        self.binding_problem = ''
        qos = data_qos(v['qos'], v['qos_depth'])
        kind = 'sensor' if v['qos'] == 'sensor' else 'reliable'
        self.out_lengths = Outlet(self, 'bar_lengths', JointState, JS, qos, kind)
        self.out_thermal = Outlet(self, 'thermal', JointState, JS, qos, kind)
        self.out_model = Outlet(self, 'model', String, STRING, LATCHED, 'latched')
        self.out_diag = Outlet(self, '/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        self.file = Path(v['calibration_file']).expanduser() if v['calibration_file'] else None
        self._file_sig = None
        if self.file is not None:
            self._poll_file()
            self.create_timer(1.0, self._poll_file)
        self.pending = RawBatch(self.names)
        self.inputs = CountedInputs(self)
        self.inputs.subscribe(JointState, 'raw_counts', self._on_raw, qos)
        self.create_timer(FLUSH_PERIOD_S, self._flush)
        self.progress = ProgressPublisher(self, self.inputs, [self.out_lengths, self.out_thermal],
                                          v['qos_depth'], on_run=self._new_run)
        self.create_subscription(String, 'calibration', self._on_calibration, LATCHED)
        self.create_subscription(Header, 'terminal/counter_reset', self._on_reset, LATCHED)
        self.create_subscription(String, 'terminal/info', self._on_terminal, LATCHED)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self.out_model.payload(string_bytes(self.model.to_yaml()), self.get_clock().now().nanoseconds)

    def _use(self, cal: Calibration, source: str) -> None:
        self._offered = (cal, source)
        self.binding_problem = ''
        refusal = binding_problem(cal, self.terminal) if self.terminal is not None else None
        if refusal is not None:
            if not self.any_terminal:
                self.binding_problem = (f'calibration from {source} refused: {refusal}; calibrate '
                                        'this terminal, or set calibration_any_terminal:=true')
                self.get_logger().error(self.binding_problem)
                self.compensator.set_calibration(None, source)
                return
            self.binding_problem = f'calibration from {source} used by override: {refusal}'
            self.get_logger().error(self.binding_problem)
        problem = self.compensator.set_calibration(cal, source)
        if problem:
            self.get_logger().warn(problem)
        else:
            self.get_logger().info(f'calibration from {source} in use (created {cal.created or "?"})')

    def _on_calibration(self, msg: String) -> None:
        try:
            cal = Calibration.from_yaml(msg.data, 'the calibration topic')
        except MmdError as exc:
            self.events.note('topic', f'calibration message refused: {exc}', ERROR)
            self.get_logger().error(f'calibration message refused: {exc}')
            return
        self._use(cal, 'the calibration topic')

    def _poll_file(self) -> None:
        assert self.file is not None
        try:
            st = self.file.stat()
            sig = (st.st_mtime, st.st_size)
        except OSError:
            return
        if sig == self._file_sig:
            return
        self._file_sig = sig
        try:
            cal = load_calibration(self.file)
        except MmdError as exc:
            self.events.note('file', f'calibration file refused, keeping the one in use: {exc}', ERROR)
            self.get_logger().error(f'calibration file refused, keeping the one in use: {exc}')
            return
        self._use(cal, str(self.file))

    def _on_terminal(self, msg: String) -> None:
        """The encoder node says which terminal it reads: check the calibration against it."""
        try:
            self.terminal = TerminalBinding.from_yaml(msg.data, 'terminal/info')
        except MmdError as exc:
            self.get_logger().error(f'terminal/info message refused: {exc}')
            return
        if self._offered is not None:
            self._use(*self._offered)

    def _on_reset(self, msg: Header) -> None:
        self.compensator.hold(from_time(msg.stamp))

    def _on_raw(self, payload: bytes) -> None:
        # a transfer's samples arrive together: compute them together (the timer flushes the rest)
        if self.pending.add(payload) >= BATCH:
            self._flush()

    def _flush(self) -> None:
        if not len(self.pending):
            return
        stamps, counts, status = self.pending.take_all()
        hold = self.compensator.hold_from_ns
        if hold is not None:
            keep = stamps < hold
            self.compensator.stats.held += int((~keep).sum())
            stamps, counts = stamps[keep], counts[keep]
            status = status[keep] if status is not None else None
            if not stamps.size:
                return
        comp = self.compensator.process(stamps, counts, status)
        if comp is None:
            return
        self.out_lengths.rows(self.rows.lengths.encode(stamps, comp.lengths_m), stamps)
        self.out_thermal.rows(self.rows.thermal.encode(stamps, comp.thermal_values()), stamps)

    def _new_run(self) -> None:
        """A replay begins: finish what came before it, then start the terms' states and the
        run's clock afresh, as ``mmd process`` does."""
        self._flush()
        self.compensator.new_run()

    def _report(self) -> list:
        r = compensation_report(self.compensator, self.thermal_warn_c, self.model.source)
        if self.binding_problem:
            r.worse(ERROR, self.binding_problem)
        self.events.apply(r)
        self.inputs.report(r)
        return [r]


def main(args: list[str] | None = None) -> int:
    return run(CompensationNode, args)


if __name__ == '__main__':
    sys.exit(main())
