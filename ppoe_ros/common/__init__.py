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
from typing import Any

#: module of the package -> the names taken from it
_NAMES: dict[str, tuple[str, ...]] = {
    "conversions": ("matrix_from_pose_msg", "message_class", "ns_to_stamp",
                    "pose_cov_from_msg", "pose_cov_stamped_msg", "pose_msg_from_matrix", "stamp_to_ns",
                    "wrench_to_numpy"),
    "diagnostics": ("DiagnosticsPublisher", "NodeStats", "guarded"),
    "losses": ("SequenceGaps", "counted_subscription"),
    "params": ("ParamSpec", "check_length", "check_nonempty",
               "declare_parameters", "mapping_get"),
    "qos": ("LATCHED_QOS", "reliable_qos", "sensor_qos"),
    "runner": ("run_node", "take_robot_description"),
}
_WHERE = {name: f"ppoe_ros.common.{module}" for module, names in _NAMES.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """The name ``name`` from its module (imported now), e.g. ``ppoe_ros.common.NodeStats``."""
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'ppoe_ros.common' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value
