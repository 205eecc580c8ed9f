"""Shared helpers of the ``ppoe_ros`` nodes: parameters, counters, diagnostics, QoS, conversions.

Every node of the package is thin (parse, call :mod:`ppoe_core`, publish) and uses
the same pieces from here:

* :class:`ParamSpec` + :func:`declare_parameters`: ROS parameters declared with a
  descriptor (description, unit, range, read-only) and validated; a bad value is
  refused with the reason, both at start-up (:class:`~ppoe_core.errors.ModelConfigError`
  naming node and parameter) and on a later ``set_parameters`` call.
* :class:`NodeStats`: counters (``received``, ``published``, ``bad``, ...) and
  throttled logging of bad messages, naming the topic and the reason.
* :class:`DiagnosticsPublisher`: the counters on ``/diagnostics`` once per period
  (steady-clock timer, so it also runs while a replayed ``/clock`` is paused).
* :func:`guarded`: wraps a subscription callback so that a bad message is logged,
  counted and dropped while the node keeps running.
* QoS profiles (:func:`sensor_qos`, :data:`LATCHED_QOS`, :func:`reliable_qos`) and
  message <-> numpy conversions, among them :func:`pose_cov_stamped_msg` which fills
  a ``PoseWithCovarianceStamped`` with a covariance already in the ROS convention
  (docs/conventions.md section 2, ``cov_ros``).
* :func:`counted_subscription`: a guarded subscription that also counts the messages lost
  before the callback (publisher sequence gaps, the middleware's message-lost events).
* :func:`run_node`: the standard ``main()`` of a node.

This module imports rclpy and ROS message packages: it is ``ppoe_ros`` only,
never imported by :mod:`ppoe_core`.
"""

from __future__ import annotations

from ppoe_ros.common.conversions import (
    cov_ros_to_msg_array,
    joint_positions,
    matrix_from_pose_msg,
    message_class,
    ns_to_stamp,
    pose_cov_from_msg,
    pose_cov_stamped_msg,
    pose_msg_from_matrix,
    stamp_to_ns,
    wrench_to_numpy,
)
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats, guarded
from ppoe_ros.common.losses import SequenceGaps, counted_subscription
from ppoe_ros.common.params import (
    ParamSpec,
    check_length,
    check_nonempty,
    check_nonnegative,
    check_positive,
    declare_parameters,
    mapping_get,
)
from ppoe_ros.common.qos import LATCHED_QOS, reliable_qos, sensor_qos
from ppoe_ros.common.runner import run_node, take_robot_description

__all__ = [
    "ParamSpec",
    "declare_parameters",
    "NodeStats",
    "DiagnosticsPublisher",
    "guarded",
    "counted_subscription",
    "SequenceGaps",
    "take_robot_description",
    "sensor_qos",
    "reliable_qos",
    "LATCHED_QOS",
    "stamp_to_ns",
    "ns_to_stamp",
    "pose_msg_from_matrix",
    "matrix_from_pose_msg",
    "pose_cov_stamped_msg",
    "pose_cov_from_msg",
    "cov_ros_to_msg_array",
    "wrench_to_numpy",
    "joint_positions",
    "run_node",
    "check_positive",
    "check_nonnegative",
    "check_nonempty",
    "check_length",
    "mapping_get",
    "message_class",
]
