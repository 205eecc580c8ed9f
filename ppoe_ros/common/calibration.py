"""Live calibration collector (node ``ppoe_calibration``), easy_handeye2 style: ``~/take_sample``, ``~/compute``.

Move the robot to a stop, let the tracker measure, call ``~/take_sample`` (``std_srvs/Trigger``): the newest
measurement (``point_topic``, ``geometry_msgs/PointStamped`` of the reflector in the tracker's frame, or with
``measurement: pose`` ``pose_topic``, ``geometry_msgs/PoseStamped`` of the tool in the base frame) is paired with
the joint state nearest its stamp (at most ``max_age`` away; a measurement is used once).  ``~/compute`` runs
``ppoe diagnose`` on the samples (:class:`ppoe_core.cli.live_calibration.CalibrationSession`) and writes into
``calibration_out``: the samples as a bag (``samples/``), ``diagnose.md/.json/.png``, ``model_diagnosed.yaml``,
``robot_calibrated.urdf`` and ``model_calibrated.yaml``; its response says the effects found and the held-out
residual before and after.  ``~/clear`` forgets the samples.  Every response names what went wrong (no
measurement yet, no joint state near it, too few samples ...); the node keeps running.

``python -m ppoe_ros.common.calibration --ros-args -p model_file:=MODEL.yaml`` (console script
``ppoe_calibration``); the URDF comes from ``robot_description`` (parameter or latched topic).
"""

from __future__ import annotations

import bisect
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped, PoseStamped
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ppoe_core.errors import PpoeError
from ppoe_core.model.joint_history import JointHistory
from ppoe_ros.common.conversions import matrix_from_pose_msg, stamp_to_ns
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats, guarded
from ppoe_ros.common.params import ParamSpec, check_nonempty, declare_parameters
from ppoe_ros.common.qos import reliable_qos, sensor_qos
from ppoe_ros.common.runner import run_node, take_robot_description

__all__ = ["CALIBRATION_PARAMS", "CalibrationNode", "main"]

#: joint states kept for pairing with a measurement [s]
_JOINT_HISTORY_S = 10.0

CALIBRATION_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("model_file", "", "model YAML of the robot (perturbations, trackers, frames); required",
              check=check_nonempty),
    ParamSpec("robot_description", "", "URDF XML; empty = take it from robot_description_topic"),
    ParamSpec("robot_description_topic", "robot_description", "latched std_msgs/String with the URDF",
              check=check_nonempty),
    ParamSpec("joint_states_topic", "joint_states", "sensor_msgs/JointState input", check=check_nonempty),
    ParamSpec("measurement", "point", "point (tracker reflector, PointStamped) or pose (tool, PoseStamped)",
              check=lambda v: None if v in ("point", "pose") else "must be 'point' or 'pose'"),
    ParamSpec("point_topic", "ground_truth/point", "geometry_msgs/PointStamped of the reflector (tracker frame)"),
    ParamSpec("pose_topic", "ground_truth/pose", "geometry_msgs/PoseStamped of the tool (base frame)"),
    ParamSpec("max_age", 0.1, "the joint state paired with a measurement is at most this far from its stamp",
              unit="s", min_value=0.0),
    ParamSpec("calibration_out", "calibration", "directory of the results (created; files replaced)"),
    ParamSpec("diagnose_args", [], "further ppoe diagnose options, e.g. ['--min-t', '3']; [] = none",
              ptype=ParameterType.PARAMETER_STRING_ARRAY),
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
)


class CalibrationNode(Node):
    """Samples (measurement + nearest joint state) on ``~/take_sample``, ``ppoe diagnose`` on ``~/compute``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("ppoe_calibration", **kwargs)
        self.p = p = declare_parameters(self, CALIBRATION_PARAMS)
        self.stats = NodeStats(self, ("received", "samples", "computed", "bad"))
        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])
        self.session: Any = None
        self.joints = JointHistory([])
        self.latest: Any = None  # (stamp_ns, frame, value) of the newest measurement
        self._used: int | None = None  # stamp of the measurement the last sample used
        self._urdf: str | None = None
        topic = p["point_topic"] if p["measurement"] == "point" else p["pose_topic"]
        msg_type = PointStamped if p["measurement"] == "point" else PoseStamped
        self.create_subscription(msg_type, topic, guarded(self.stats, topic)(self._measurement), reliable_qos(100))
        self.create_subscription(JointState, p["joint_states_topic"],
                                 guarded(self.stats, p["joint_states_topic"])(self._joint_state), sensor_qos(1000))
        self.create_service(Trigger, "~/take_sample", self._take_sample)
        self.create_service(Trigger, "~/compute", self._compute)
        self.create_service(Trigger, "~/clear", self._clear)
        take_robot_description(self, p, self.stats, self._set_model, self._robot_description)

    def _set_model(self, urdf_xml: str, where: str) -> None:
        from ppoe_core.cli.live_calibration import CalibrationSession
        from ppoe_core.robot.urdf import parse_urdf

        robot = parse_urdf(urdf_xml, text_source=where)
        names = robot.independent_joints
        self.joints = JointHistory(names, needed=[], known=robot.joints, keep_ns=int(_JOINT_HISTORY_S * 1e9))
        self.session = CalibrationSession(urdf_xml, self.p["model_file"])
        self._urdf = urdf_xml
        self.get_logger().info(f"model from {where}: {len(names)} joints; call ~/take_sample at each stop")

    def _robot_description(self, msg: String) -> None:
        if msg.data != self._urdf:
            self._set_model(msg.data, f"topic {self.p['robot_description_topic']}")

    def _joint_state(self, msg: JointState) -> None:
        if self.session is not None:
            self.joints.update(msg.name, msg.position, stamp_to_ns(msg.header.stamp))

    def _measurement(self, msg: Any) -> None:
        self.stats.inc("received")
        if isinstance(msg, PointStamped):
            value = np.array([msg.point.x, msg.point.y, msg.point.z], dtype=float)
        else:
            value = matrix_from_pose_msg(msg.pose)
        if not np.all(np.isfinite(value)):
            raise PpoeError("NaN or inf in the measurement")
        self.latest = (stamp_to_ns(msg.header.stamp), msg.header.frame_id, value)

    def _paired_joints(self, stamp_ns: int) -> tuple[tuple[str, ...], np.ndarray]:
        """Names and positions of the joints known at the joint state nearest ``stamp_ns`` (PpoeError naming the
        gap when none is within max_age); a joint never received is left out (``ppoe diagnose`` names it if the
        measured chain needs it)."""
        stamps = self.joints.history.stamps
        if not stamps:
            raise PpoeError("no joint state received yet")
        i = bisect.bisect_left(stamps, stamp_ns)
        near = min((k for k in (i - 1, i) if 0 <= k < len(stamps)), key=lambda k: abs(stamps[k] - stamp_ns))
        gap = abs(stamps[near] - stamp_ns) * 1e-9
        if gap > self.p["max_age"]:
            raise PpoeError(f"the joint state nearest the measurement is {gap:.3f} s away (max_age "
                            f"{self.p['max_age']:g} s)")
        q = self.joints.history.values[near]
        known = ~np.isnan(q)
        if not known.any():
            raise PpoeError("no joint value of the URDF received yet")
        return tuple(n for n, k in zip(self.joints.joints, known) if k), q[known].copy()

    def _take_sample(self, request: Any, response: Any) -> Any:
        from ppoe_core.cli.live_calibration import CalibrationSample

        try:
            if self.session is None:
                raise PpoeError("no URDF yet (waiting for robot_description)")
            if self.latest is None or self.latest[0] == self._used:
                raise PpoeError(f"no new {self.p['measurement']} measurement since the last sample")
            stamp_ns, frame, value = self.latest
            names, q = self._paired_joints(stamp_ns)
            n = self.session.add(CalibrationSample(stamp_ns * 1e-9, names, q, frame, value))
        except PpoeError as exc:
            return _answer(response, False, f"sample not taken: {exc}")
        self._used = stamp_ns
        self.stats.counts["samples"] = n
        return _answer(response, True, f"sample {n} at {stamp_ns * 1e-9:.3f} s ({frame})")

    def _compute(self, request: Any, response: Any) -> Any:
        if self.session is None or not self.session.samples:
            return _answer(response, False, "no sample taken yet")
        extra = [a for a in self.p["diagnose_args"] if a]
        try:
            result = self.session.compute(self.p["calibration_out"], extra)
        except (PpoeError, SystemExit) as exc:  # argparse exits on a bad diagnose_args entry
            return _answer(response, False, f"{len(self.session.samples)} samples: {exc}")
        self.stats.inc("computed")
        return _answer(response, True, f"{len(self.session.samples)} samples: {result.summary()}")

    def _clear(self, request: Any, response: Any) -> Any:
        n = len(self.session.samples) if self.session is not None else 0
        if self.session is not None:
            self.session.samples.clear()
        self.stats.counts["samples"] = 0
        return _answer(response, True, f"forgot {n} samples")


def _answer(response: Any, success: bool, message: str) -> Any:
    response.success, response.message = bool(success), str(message)
    return response


def main(args: Any = None) -> int:
    """``ppoe_calibration --ros-args -p model_file:=MODEL.yaml`` (``python -m ppoe_ros.common.calibration``)."""
    return run_node(CalibrationNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
