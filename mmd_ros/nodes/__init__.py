"""The ROS 2 nodes of mmd_ros (documented in ``msg_docs/nodes.md``).

One ``Node`` subclass per executable, each with ``main(args=None)``: ``encoder_node``,
``compensation_node``, ``fk_node``, ``calibration_node``, ``recorder_node``, ``replay_node`` and
``pose_node`` (all of them in one process). They are thin: parameters are declared and checked
once (:mod:`.params`), messages are converted to arrays and back (:mod:`.convert`), and the work
is done by the ROS-free core (``mmd_ros.core``, ``mmd_ros.hardware``, ``mmd_ros.logs``) through
small stages shared by the separate nodes and ``pose_node``: :mod:`.terminal`,
:mod:`.calibration_stage`, :mod:`.recorder_stage`, and :mod:`.progress` (inputs that count what
was lost on the way, and the progress a replay paces itself by). :mod:`.client` is an rclpy
client of a running device (demo, benchmark, tests).
"""
