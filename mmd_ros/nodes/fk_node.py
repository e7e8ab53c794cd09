"""``fk_node``: compensated bar lengths → the pose of {U} in {L}.

Pairs each ``bar_lengths`` sample with the ``thermal`` sample of the same stamp (the plates'
scale factor, and the Eq. 11 errors and temperature change the uncertainty budget needs),
solves the forward kinematics warm-started from the previous poses and publishes ``pose``
(``geometry_msgs/PoseStamped``, frame ``mmd_lower``, SI units, quaternion x y z w),
``pose_batch`` (``nav_msgs/Path``: the poses solved together, each with its own stamp, one
message per batch), ``pose_with_covariance`` and ``fk_status`` for every sample. The covariance
is J^-1 Sigma_d J^-T with the bar lengths' uncertainty budget of the calibration (latched
``calibration`` topic) and the model (latched ``model`` topic): until both have arrived no
covariance is published. A sample whose forward kinematics gives no plausible pose
(``fk_status`` ``status`` says why), or has a bar out of its calibrated range (NaN length), gets
no pose and is counted in the diagnostics. Topics, parameters: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from mmd_ros.core.budget import LengthBudget
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.errors import MmdError
from mmd_ros.core.flow import StampPairing
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import BAR_NAMES
from mmd_ros.nodes.common import COMMON_PARAMS, NAMESPACE, load_device_param, run
from mmd_ros.core.streaming import Kinematics
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, JS, PATH, POSE, POSE_COV, RawBatch, Rows
from mmd_ros.nodes.diagnostics import WARN, Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, declare
from mmd_ros.nodes.progress import CountedInputs, ProgressPublisher
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos
from mmd_ros.nodes.reports import kinematics_report

__all__ = ['FkNode', 'main']

PARAMS = [
    Param('publish_covariance', True, 'publish pose_with_covariance'),
    Param('length_sigma_um', 0.0, 'a fixed 1-sigma bar-length uncertainty for the covariance, the '
          'same for every bar [µm]; 0 takes the uncertainty budget of the calibration and model '
          '(msg_docs/frames.md)', low=1e-6, high=1e6, allow_zero=True),
]
#: Samples of one topic (lengths or thermal) that may wait for their partner, at least; the
#: subscriptions' queue depth when larger (one topic may arrive that far ahead of the other).
PENDING = 2000
#: Samples solved together (a transfer of the terminal), and the longest wait for the rest [s].
BATCH = 8
FLUSH_PERIOD_S = 0.005


class FkNode(Node):
    """Bar lengths → poses."""

    def __init__(self) -> None:
        super().__init__('fk_node', namespace=NAMESPACE)
        v = declare(self, COMMON_PARAMS + PARAMS)
        device = load_device_param(v['device_file'])
        refs = [c.name for c in device.reference_channels]
        self.rows = Rows(device.channel_names, refs)
        self.device = device
        self.fixed_sigma = v['length_sigma_um'] * 1e-6
        self.model: Model | None = None
        self.calibration: Calibration | None = None
        self.budget_problem = 'waiting for the model and calibration topics'
        self.kinematics = Kinematics(device, self.fixed_sigma or None,
                                     with_covariance=v['publish_covariance'])
        qos = data_qos(v['qos'], v['qos_depth'])
        kind = 'sensor' if v['qos'] == 'sensor' else 'reliable'
        self.out_pose = Outlet(self, 'pose', PoseStamped, POSE, qos, kind)
        self.out_pose_cov = Outlet(self, 'pose_with_covariance', PoseWithCovarianceStamped,
                                   POSE_COV, qos, kind)
        self.out_status = Outlet(self, 'fk_status', JointState, JS, qos, kind)
        self.out_pose_batch = Outlet(self, 'pose_batch', Path, PATH, qos, kind)
        self.out_diag = Outlet(self, '/diagnostics', DiagnosticArray, DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        self.in_lengths = RawBatch(BAR_NAMES)
        self.in_thermal = RawBatch(self.rows.thermal_names)
        self.scale_column = self.rows.thermal_names.index('plate_scale')
        self.temp_column = self.rows.thermal_names.index('temp_change')
        self.n_refs = len(refs)
        self.pairing = StampPairing(max(PENDING, v['qos_depth']))
        self.inputs = CountedInputs(self)
        self.inputs.subscribe(JointState, 'bar_lengths', self._on_lengths, qos)
        self.inputs.subscribe(JointState, 'thermal', self._on_thermal, qos)
        self.create_subscription(String, 'model', self._on_model, LATCHED)
        self.create_subscription(String, 'calibration', self._on_calibration, LATCHED)
        self.create_timer(FLUSH_PERIOD_S, self._flush)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self.progress = ProgressPublisher(self, self.inputs, [self.out_pose, self.out_pose_cov,
                                                              self.out_status], v['qos_depth'],
                                          on_run=self._new_run)

    def _on_model(self, msg: String) -> None:
        try:
            self.model = Model.from_yaml(msg.data, 'the model topic')
        except MmdError as exc:
            self.get_logger().error(f'model message refused: {exc}')
            return
        self._update_budget()

    def _on_calibration(self, msg: String) -> None:
        try:
            self.calibration = Calibration.from_yaml(msg.data, 'the calibration topic')
        except MmdError as exc:
            self.get_logger().error(f'calibration message refused: {exc}')
            return
        self._update_budget()

    def _update_budget(self) -> None:
        """The uncertainty budget of the calibration and model now in use."""
        if self.fixed_sigma or self.model is None or self.calibration is None:
            return
        try:
            self.kinematics.budget = LengthBudget(self.device, self.calibration, self.model)
            self.budget_problem = ''
        except (MmdError, ValueError) as exc:
            self.kinematics.budget = None
            self.budget_problem = f'no covariance: the calibration and model give no budget ({exc})'
            self.get_logger().error(self.budget_problem)

    def _on_lengths(self, payload: bytes) -> None:
        if self.in_lengths.add(payload) >= BATCH and (len(self.in_thermal) >= BATCH or len(self.pairing)):
            self._flush()

    def _on_thermal(self, payload: bytes) -> None:
        if self.in_thermal.add(payload) >= BATCH and (len(self.in_lengths) >= BATCH or len(self.pairing)):
            self._flush()

    def _flush(self) -> None:
        if len(self.in_lengths):
            self.pairing.add(0, *self.in_lengths.take())
        if len(self.in_thermal):
            self.pairing.add(1, *self.in_thermal.take())
        paired = self.pairing.take()
        if paired is not None:
            self._solve(*paired)

    def _new_run(self) -> None:
        """A replay begins: finish what came before it, then start as ``mmd process`` does. A
        sample still waiting for its partner is given up (its stamp may come again in the run)."""
        self._flush()
        self.pairing.clear()
        self.kinematics.new_run()

    def _solve(self, stamps: np.ndarray, lengths: np.ndarray, thermal: np.ndarray) -> None:
        kin = self.kinematics.solve(lengths, thermal[:, self.scale_column],
                                    thermal[:, :self.n_refs], thermal[:, self.temp_column],
                                    stamps_ns=stamps)
        # poses first (what CNC tooling waits for); the covariance is computed after them
        if kin.valid.any():
            s = stamps[kin.valid]
            poses = kin.poses[kin.valid]
            self.out_pose.rows(self.rows.poses(s, poses), s)
            self.out_pose_batch.payload(self.rows.pose_batch(s, poses), int(s[-1]))
            if kin.covariance is not None:
                self.out_pose_cov.rows(self.rows.poses(s, poses, kin.covariance), s)
        self.out_status.rows(self.rows.fk_status.encode(stamps, kin.status_values()), stamps)

    def _report(self) -> list:
        r = kinematics_report(self.kinematics)
        if self.kinematics.with_covariance and not self.fixed_sigma and self.budget_problem:
            r.worse(WARN, self.budget_problem)
        r.values['unpaired_samples'] = self.pairing.unpaired
        r.values['foreign_messages'] = self.in_lengths.foreign + self.in_thermal.foreign
        self.inputs.report(r)
        return [r]


def main(args: list[str] | None = None) -> int:
    return run(FkNode, args)


if __name__ == '__main__':
    sys.exit(main())
