"""Contact node: force/torque (or a contact flag) -> the contact plane while in contact.

Subscriptions
    ``wrench`` (``geometry_msgs/WrenchStamped``, sensor-data QoS), or, when
    ``contact_flag_topic`` is set, that ``std_msgs/Bool`` topic instead.
Publications
    ``contact/plane`` (``geometry_msgs/PoseWithCovarianceStamped``), one per input
    message while in contact: the configured plane pose ``T_frame_plane`` (normal =
    plane z axis) with ``header.frame_id`` = ``frame_prefix`` + the plane's frame, and its Sigma_v
    (paper sec. V, given in the plane frame, i.e. local / right perturbation)
    converted to the ROS convention of docs/conventions.md sec. 2.  Stamp = the wrench
    stamp (a ``Bool`` has no header: the node clock, so ``use_sim_time`` applies).
    Topics are relative (they follow the node's namespace, :mod:`ppoe_ros.common.frame_prefix`).
    ``/diagnostics``: ``received``, ``published``, ``bad``, ``contacts`` (number of
    contact onsets), ``in_contact`` (0/1).

Contact detection (:class:`ppoe_core.sensing.contact.ContactDetector`, the same code ``ppoe evaluate``
replays a bag's ``/wrench`` through) with hysteresis: contact begins when the force measure
(``force_component``: the force norm, or one signed axis of the sensor frame)
reaches ``force_threshold`` and ends when it falls below ``release_threshold``
(< ``force_threshold``).  A wrench with NaN/inf values or a stamp older than the
previous one is logged (throttled), counted as ``bad`` and ignored.

The plane, its Sigma_v and the thresholds come from the model YAML ``contact``
section (:func:`ppoe_core.sensing.contact.plane_from_config`); parameters override them (see
``config/nodes/contact_node.yaml``).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped, WrenchStamped
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from std_msgs.msg import Bool

from ppoe_core.errors import ModelConfigError
from ppoe_core.robot.config import load_contact_config
from ppoe_core.robot.yaml_io import read_yaml_mapping
from ppoe_core.model.stamp_policy import BACKWARD, NEW_TIMELINE, StampRefused, StampResetPolicy
from ppoe_core.sensing.contact import (
    DEFAULT_FORCE_THRESHOLD, DEFAULT_RELEASE_THRESHOLD, FORCE_COMPONENTS, ContactDetector, force_measure,
    plane_from_config,
)
from ppoe_ros.common.conversions import pose_cov_stamped_msg, stamp_to_ns, wrench_to_numpy
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_length, check_nonempty, declare_parameters, mapping_get
from ppoe_ros.common.qos import reliable_qos, sensor_qos
from ppoe_ros.common.frame_prefix import FRAME_PREFIX_PARAM, prefixed, resolve_topics

__all__ = ["ContactNode", "PARAMS", "main"]

_DOUBLE_ARRAY = ParameterType.PARAMETER_DOUBLE_ARRAY
_COMPONENTS = FORCE_COMPONENTS

#: Parameters of the node (defaults; documented in config/nodes/contact_node.yaml).
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("model_file", "", "model YAML whose 'contact' section gives plane, Sigma_v and thresholds"),
    ParamSpec("wrench_topic", "wrench", "geometry_msgs/WrenchStamped input", check=check_nonempty),
    ParamSpec("contact_flag_topic", "", "std_msgs/Bool contact flag used instead of the wrench when set"),
    ParamSpec("plane_topic", "contact/plane", "output topic", check=check_nonempty),
    ParamSpec("plane_frame", "", "frame of the plane pose; empty = model YAML contact.plane.frame, else "
              "frames.base"),
    ParamSpec("plane_xyz", [], "plane origin in plane_frame; empty = model YAML", unit="m",
              ptype=_DOUBLE_ARRAY, check=check_length(0, 3)),
    ParamSpec("plane_rpy", [], "plane orientation (roll, pitch, yaw) in plane_frame; empty = model YAML", unit="rad",
              ptype=_DOUBLE_ARRAY, check=check_length(0, 3)),
    ParamSpec("plane_sigma", [], "1-sigma of the plane pose [rho; theta] in the plane frame (Sigma_v "
              "diagonal); empty = model YAML", unit="m, rad", ptype=_DOUBLE_ARRAY, check=check_length(0, 6)),
    ParamSpec("force_threshold", 0.0, "force that starts a contact; 0 = model YAML contact.force_threshold "
              "(else 5 N)", unit="N", min_value=0.0, read_only=False),
    ParamSpec("release_threshold", 0.0, "force below which the contact ends; 0 = model YAML "
              "contact.release_threshold (else 2 N)", unit="N", min_value=0.0, read_only=False),
    ParamSpec("force_component", "norm", "force measure: norm, or signed axis x, y, z, -x, -y, -z of the "
              "wrench frame", check=lambda v: None if v in _COMPONENTS else f"must be one of {_COMPONENTS}"),
    ParamSpec("qos_depth", 100, "history depth of the input subscription (sensor-data QoS)",
              min_value=1, max_value=100000),
    ParamSpec("stamp_reset_threshold", 1.0, "a wrench stamp this much older than the last one starts a new "
              "timeline (bag loop, simulator restart): counted, the contact state reset", unit="s", min_value=0.0),
    ParamSpec("input_timeout", 1.0, "/diagnostics says WARN when no wrench (or contact flag) arrived for this "
              "long; 0 = off",
              unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
    FRAME_PREFIX_PARAM,
    ParamSpec("log_throttle", 2.0, "at most one log line per kind of bad message per this period", unit="s",
              min_value=0.0),
)


class ContactNode(Node):
    """Publishes the configured contact plane while the wrench (or flag) says "in contact"."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("contact_node", **kwargs)
        p = declare_parameters(self, PARAMS, on_change=self._on_change)
        resolve_topics(self, p, ("wrench_topic", "contact_flag_topic", "plane_topic"))
        self.params = p
        self.stats = NodeStats(self, ("received", "published", "bad", "contacts", "in_contact"), p["log_throttle"])
        where = f"node {self.get_name()}" + (f", model file {p['model_file']}" if p["model_file"] else "")
        # the contact section validated as everywhere else (file:line errors); no URDF needed here
        contact = load_contact_config(p["model_file"]) if p["model_file"] else None
        frames_base = mapping_get(read_yaml_mapping(p["model_file"], "model file"), "frames", "base")
        self.plane = plane_from_config(contact, frames_base, p, where)
        enter = p["force_threshold"] or (contact.force_threshold if contact is not None else DEFAULT_FORCE_THRESHOLD)
        release = p["release_threshold"] or (contact.release_threshold if contact is not None
                                             else DEFAULT_RELEASE_THRESHOLD)
        try:
            self.detector = ContactDetector(enter, release)
        except ModelConfigError as exc:
            raise ModelConfigError(f"{where}: {exc}") from None
        self._component = p["force_component"]
        self._last_ns: int | None = None
        self.policy = StampResetPolicy(p["stamp_reset_threshold"])
        self._out = pose_cov_stamped_msg(self.plane.T_frame_plane, self.plane.cov_ros, 0,
                                         prefixed(p["frame_prefix"], self.plane.frame))
        self._pub = self.create_publisher(PoseWithCovarianceStamped, p["plane_topic"], reliable_qos(100))
        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])
        self.diagnostics.watch_input(p["contact_flag_topic"] or p["wrench_topic"], "received", p["input_timeout"])
        qos = sensor_qos(p["qos_depth"])
        if p["contact_flag_topic"]:
            t = p["contact_flag_topic"]
            counted_subscription(self, self.stats, Bool, t, self._flag, qos)
        else:
            t = p["wrench_topic"]
            counted_subscription(self, self.stats, WrenchStamped, t, self._wrench, qos)
        self.get_logger().info(
            f"plane in {prefixed(p['frame_prefix'], self.plane.frame)} at {self.plane.T_frame_plane[:3, 3].tolist()}, "
            f"contact on {t} "
            f"(enter {self.detector.enter} N, release {self.detector.release} N) -> {p['plane_topic']}")

    def _on_change(self, changed: dict[str, Any]) -> None:
        enter = changed.get("force_threshold", self.detector.enter) or self.detector.enter
        release = changed.get("release_threshold", self.detector.release) or self.detector.release
        ContactDetector.check_thresholds(enter, release)
        self.detector.enter, self.detector.release = float(enter), float(release)

    def _set_state(self, in_contact: bool, was: bool, stamp_s: float) -> None:
        if in_contact and not was:
            self.stats.inc("contacts")
            self.get_logger().info(f"contact begins at t = {stamp_s:.3f} s")
        elif was and not in_contact:
            self.get_logger().info(f"contact ends at t = {stamp_s:.3f} s")
        self.stats.counts["in_contact"] = int(in_contact)

    def _publish(self, stamp: Any) -> None:
        self._out.header.stamp = stamp
        self._pub.publish(self._out)
        self.stats.counts["published"] += 1

    def _wrench(self, msg: WrenchStamped) -> None:
        self.stats.counts["received"] += 1
        w = wrench_to_numpy(msg)
        if not np.all(np.isfinite(w)):
            raise ValueError(f"non-finite wrench {w.tolist()}")
        stamp_ns = stamp_to_ns(msg.header.stamp)
        check = self.policy.check(stamp_ns, self._last_ns)
        if check.verdict == BACKWARD:
            raise StampRefused(check.why, check.verdict)
        if check.verdict == NEW_TIMELINE:
            self.stats.bad(self.params["wrench_topic"], f"{check.why}, contact state reset")
            self.detector.in_contact = False
        self._last_ns = stamp_ns
        force = float(force_measure(w[:3], self._component))
        was = self.detector.in_contact
        now = self.detector.update(force)
        if now != was:
            self._set_state(now, was, stamp_ns * 1e-9)
        if now:
            self._publish(msg.header.stamp)

    def _flag(self, msg: Bool) -> None:
        self.stats.counts["received"] += 1
        was = self.detector.in_contact
        now = bool(msg.data)
        self.detector.in_contact = now
        stamp = self.get_clock().now()
        if now != was:
            self._set_state(now, was, stamp.nanoseconds * 1e-9)
        if now:
            self._publish(stamp.to_msg())


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``contact_node`` (``--ros-args`` accepted)."""
    from ppoe_ros.common.runner import run_node

    return run_node(ContactNode, args, executor="events", kernels=("contact_node",))


if __name__ == "__main__":
    sys.exit(main())
