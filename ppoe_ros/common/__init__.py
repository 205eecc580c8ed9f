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

Importing this package imports nothing heavy (no rclpy, no message packages): each name is taken from its module
on first use (``from ppoe_ros.common import NodeStats`` imports :mod:`ppoe_ros.common.diagnostics` then); the nodes
import from the modules themselves.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: where each name of the package lives
_WHERE: dict[str, str] = {
    "cov_ros_to_msg_array": "ppoe_ros.common.conversions",
    "matrix_from_pose_msg": "ppoe_ros.common.conversions",
    "message_class": "ppoe_ros.common.conversions",
    "ns_to_stamp": "ppoe_ros.common.conversions",
    "pose_cov_from_msg": "ppoe_ros.common.conversions",
    "pose_cov_stamped_msg": "ppoe_ros.common.conversions",
    "pose_msg_from_matrix": "ppoe_ros.common.conversions",
    "stamp_to_ns": "ppoe_ros.common.conversions",
    "wrench_to_numpy": "ppoe_ros.common.conversions",
    "DiagnosticsPublisher": "ppoe_ros.common.diagnostics",
    "NodeStats": "ppoe_ros.common.diagnostics",
    "guarded": "ppoe_ros.common.diagnostics",
    "SequenceGaps": "ppoe_ros.common.losses",
    "counted_subscription": "ppoe_ros.common.losses",
    "ParamSpec": "ppoe_ros.common.params",
    "check_length": "ppoe_ros.common.params",
    "check_nonempty": "ppoe_ros.common.params",
    "check_nonnegative": "ppoe_ros.common.params",
    "check_positive": "ppoe_ros.common.params",
    "declare_parameters": "ppoe_ros.common.params",
    "mapping_get": "ppoe_ros.common.params",
    "LATCHED_QOS": "ppoe_ros.common.qos",
    "reliable_qos": "ppoe_ros.common.qos",
    "sensor_qos": "ppoe_ros.common.qos",
    "run_node": "ppoe_ros.common.runner",
    "take_robot_description": "ppoe_ros.common.runner",
}

if TYPE_CHECKING:  # the names for type checkers; at run time they are imported on first use
    from ppoe_ros.common.conversions import cov_ros_to_msg_array  # noqa: F401
    from ppoe_ros.common.conversions import matrix_from_pose_msg  # noqa: F401
    from ppoe_ros.common.conversions import message_class  # noqa: F401
    from ppoe_ros.common.conversions import ns_to_stamp  # noqa: F401
    from ppoe_ros.common.conversions import pose_cov_from_msg  # noqa: F401
    from ppoe_ros.common.conversions import pose_cov_stamped_msg  # noqa: F401
    from ppoe_ros.common.conversions import pose_msg_from_matrix  # noqa: F401
    from ppoe_ros.common.conversions import stamp_to_ns  # noqa: F401
    from ppoe_ros.common.conversions import wrench_to_numpy  # noqa: F401
    from ppoe_ros.common.diagnostics import DiagnosticsPublisher  # noqa: F401
    from ppoe_ros.common.diagnostics import NodeStats  # noqa: F401
    from ppoe_ros.common.diagnostics import guarded  # noqa: F401
    from ppoe_ros.common.losses import SequenceGaps  # noqa: F401
    from ppoe_ros.common.losses import counted_subscription  # noqa: F401
    from ppoe_ros.common.params import ParamSpec  # noqa: F401
    from ppoe_ros.common.params import check_length  # noqa: F401
    from ppoe_ros.common.params import check_nonempty  # noqa: F401
    from ppoe_ros.common.params import check_nonnegative  # noqa: F401
    from ppoe_ros.common.params import check_positive  # noqa: F401
    from ppoe_ros.common.params import declare_parameters  # noqa: F401
    from ppoe_ros.common.params import mapping_get  # noqa: F401
    from ppoe_ros.common.qos import LATCHED_QOS  # noqa: F401
    from ppoe_ros.common.qos import reliable_qos  # noqa: F401
    from ppoe_ros.common.qos import sensor_qos  # noqa: F401
    from ppoe_ros.common.runner import run_node  # noqa: F401
    from ppoe_ros.common.runner import take_robot_description  # noqa: F401


def __getattr__(name: str) -> Any:
    """The name ``name`` from its module (imported now), e.g. ``ppoe_ros.common.NodeStats``."""
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'ppoe_ros.common' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value


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
    "run_node",
    "check_positive",
    "check_nonnegative",
    "check_nonempty",
    "check_length",
    "mapping_get",
    "message_class",
]
