"""``fk_node``: compensated bar lengths → the pose of {U} in {L}.

Pairs each ``bar_lengths`` sample with the ``thermal`` sample of the same stamp (for the
plates' scale factor), solves the forward kinematics warm-started from the previous poses and
publishes ``pose`` (``geometry_msgs/PoseStamped``, frame ``mmd_lower``, SI units, quaternion
x y z w), ``pose_batch`` (``nav_msgs/Path``: the poses solved together, each with its own stamp,
one message per batch), ``pose_with_covariance`` (the covariance propagated from the model's bar-length
uncertainty) and ``fk_status`` for every sample. A sample that does not converge, or has a bar
out of its calibrated range (NaN length), gets no pose and is counted in the diagnostics.
Topics, parameters: ``msg_docs/nodes.md``.
"""

from __future__ import annotations

import sys
from collections import OrderedDict

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from mmd_ros.core.errors import MmdError
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import BAR_NAMES
from mmd_ros.nodes.common import COMMON_PARAMS, NAMESPACE, load_device_param, run
from mmd_ros.core.streaming import Kinematics
from mmd_ros.nodes.convert import DIAGNOSTIC_ARRAY, JS, PATH, POSE, POSE_COV, RawBatch, Rows
from mmd_ros.nodes.diagnostics import Diagnostics
from mmd_ros.nodes.outlets import Outlet
from mmd_ros.nodes.params import Param, declare
from mmd_ros.nodes.progress import CountedInputs, ProgressPublisher
from mmd_ros.nodes.qos import DIAGNOSTICS, LATCHED, data_qos
from mmd_ros.nodes.reports import kinematics_report

__all__ = ['FkNode', 'main']

PARAMS = [
    Param('publish_covariance', True, 'publish pose_with_covariance'),
    Param('length_sigma_um', 0.0, '1-sigma bar-length uncertainty for the covariance [µm]; 0 '
          'takes length_sigma_um of the model on the model topic', low=1e-6, high=1e6,
          allow_zero=True),
]
#: Samples waiting for their partner (lengths or thermal) before they are given up.
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
        self.fixed_sigma = v['length_sigma_um'] * 1e-6
        sigma = self.fixed_sigma or Model().length_sigma_m
        self.kinematics = Kinematics(device, sigma, with_covariance=v['publish_covariance'])
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
        self._lengths: OrderedDict[int, np.ndarray] = OrderedDict()
        self._scales: OrderedDict[int, float] = OrderedDict()
        self.unpaired = 0
        self.inputs = CountedInputs(self)
        self.inputs.subscribe(JointState, 'bar_lengths', self._on_lengths, qos)
        self.inputs.subscribe(JointState, 'thermal', self._on_thermal, qos)
        self.create_subscription(String, 'model', self._on_model, LATCHED)
        self.create_timer(FLUSH_PERIOD_S, self._flush)
        self.diagnostics = Diagnostics(self, self.out_diag, [self._report], v['diagnostics_period_s'])
        self.progress = ProgressPublisher(self, self.inputs, [self.out_pose, self.out_pose_cov,
                                                              self.out_status], v['qos_depth'])

    def _on_model(self, msg: String) -> None:
        if self.fixed_sigma:
            return
        try:
            model = Model.from_yaml(msg.data, 'the model topic')
        except MmdError as exc:
            self.get_logger().error(f'model message refused: {exc}')
            return
        self.kinematics.sigma_m = model.length_sigma_m

    def _on_lengths(self, payload: bytes) -> None:
        if self.in_lengths.add(payload) >= BATCH and len(self.in_thermal) >= BATCH:
            self._flush()

    def _on_thermal(self, payload: bytes) -> None:
        if self.in_thermal.add(payload) >= BATCH and len(self.in_lengths) >= BATCH:
            self._flush()

    def _flush(self) -> None:
        if len(self.in_lengths):
            for stamp, row in zip(*self.in_lengths.take()):
                self._lengths[int(stamp)] = row
        if len(self.in_thermal):
            for stamp, row in zip(*self.in_thermal.take()):
                self._scales[int(stamp)] = float(row[self.scale_column])
        if not self._lengths or not self._scales:
            self._trim()
            return
        both = sorted(s for s in self._lengths if s in self._scales)
        if both:
            stamps = np.array(both, dtype=np.int64)
            lengths = np.array([self._lengths.pop(s) for s in both])
            scales = np.array([self._scales.pop(s) for s in both])
            self._solve(stamps, lengths, scales)
        self._trim()

    def _trim(self) -> None:
        for pending in (self._lengths, self._scales):
            while len(pending) > PENDING:
                pending.popitem(last=False)
                self.unpaired += 1

    def _solve(self, stamps: np.ndarray, lengths: np.ndarray, scales: np.ndarray) -> None:
        kin = self.kinematics.solve(lengths, scales)
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
        r.values['unpaired_samples'] = self.unpaired
        r.values['foreign_messages'] = self.in_lengths.foreign + self.in_thermal.foreign
        self.inputs.report(r)
        return [r]


def main(args: list[str] | None = None) -> int:
    return run(FkNode, args)


if __name__ == '__main__':
    sys.exit(main())
