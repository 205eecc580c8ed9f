"""Fusion node: kinematics prior + tag / contact / tracker / pose / accelerometer measurements -> corrected tool pose.

Thin ROS wrapper around :class:`ppoe_core.estimation.pipeline.FusionPipeline` (the same code
``ppoe evaluate`` replays offline); the design (prior buffer, how a correction is carried
while the arm moves on and when it is dropped) is in ``docs/fusion_node.md``.

Subscriptions
    Topics are relative (they follow the node's namespace; in the root namespace ``prior_topic`` is
    ``/ppoe/pose``), ``frame_prefix`` goes in front of every frame of the robot published or expected
    (:mod:`ppoe_ros.common.frame_prefix`).
    ``prior_topic`` (default ``ppoe/pose``, ``PoseWithCovarianceStamped`` from the
    kinematics node: ``T_base_tool``, ROS-convention covariance); ``header.frame_id`` must be
    ``frame_prefix + base_frame``.
    ``observations_topic`` (default ``tag_bearing/observations``, ``PointCloud2``, fields
    ``id``, ``corner``, ``u``, ``v``, ``x``, ``y``; ``header.frame_id`` = camera optical frame).
    ``contact_topic`` (default ``contact/plane``, ``PoseWithCovarianceStamped``: plane pose
    and ``Sigma_v`` in the ROS convention, while in contact).
    ``camera_info_topic`` (default ``camera/camera_info``): focal lengths that turn the pixel
    noise into normalised units (without it they are fitted from ``u, v`` vs ``x, y``).
    ``joint_states_topic`` (default ``joint_states``): joint positions at the prior stamps
    (camera on a pan-tilt mast, tag mounts behind joints, the joint-motion limit).
    ``robot_description`` (transient local) unless the ``robot_description`` parameter is set.
    The sensor blocks of ``sources`` (robot_localization style, :mod:`ppoe_ros.common.fusion_sources`): tracker
    points (``PointStamped``), 6D poses of a link (``PoseWithCovarianceStamped``), accelerometers (``Imu``).
Publications
    ``fused_topic`` (default ``ppoe/fused_pose``, ``PoseWithCovarianceStamped``): for every
    prior, the prior with the carried correction applied (the prior itself when there is
    none), same stamp and frame; after each accepted measurement once more for the newest
    prior (``publish_on_update``).
    ``/tf`` (``publish_tf``): the fused pose as the transform ``base_frame`` -> ``tf_child_frame`` (default
    ``<tool>_corrected``) at the fused pose's stamp, each time one is published; ``/tf_static``: the
    calibrated camera frame(s) of the model YAML (``<camera frame><tf_camera_suffix>``) relative to the
    link their fixed mount hangs on (:mod:`ppoe_ros.common.tf_broadcast`).
    ``/diagnostics``: counters ``priors``, ``measurements``, ``accepted``, ``rejected``,
    ``dropped`` (= ``dropped_stale`` + ``dropped_no_prior``), ``corrections_dropped``,
    ``bad``, ``published`` ...

A bad message (NaN pose, non-PSD covariance, wrong frame, unknown tag ids or camera frame,
corrupt point cloud, a tracker or IMU frame the URDF lacks) is logged (throttled), counted and dropped; the node
keeps running.  Every measurement enters the pipeline in one place, :meth:`FusionNode._measure`.

Parameters: :data:`PARAMS`, documented in ``config/nodes/fusion_node.yaml``.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, JointState, PointCloud2
from std_msgs.msg import String

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, ModelConfigError, PpoeError
from ppoe_core.io.cdr import JointStateReader
from ppoe_core.estimation.pipeline import (
    FUSION_SETTINGS, ContactMeasurement, Measurement, MeasurementOutcome, ModelUpdater, PriorSample, TagMeasurement,
    ToolUpdate, make_pipeline, make_updater, source_key,
)
from ppoe_core.model.joint_history import JointHistory
from ppoe_core.estimation.source_updater import SourceUpdater
from ppoe_core.robot.yaml_io import read_yaml_mapping
from ppoe_ros.common.conversions import (
    PoseCovarianceCdr,
    pose_cov_from_msg,
    stamp_to_ns,
)
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats, guarded
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_nonempty, declare_parameters, mapping_get
from ppoe_ros.common.qos import reliable_qos, sensor_qos
from ppoe_ros.common.runner import take_robot_description
from ppoe_ros.common.frame_prefix import FRAME_PREFIX_PARAM, resolve_topics, unprefixed
from ppoe_core.estimation.sources import parse_sources
from ppoe_ros.common.fusion_sources import SOURCES_PARAM, LiveSources, source_names, source_specs
from ppoe_ros.common.tag_cloud import observations_from_cloud
from ppoe_ros.common.online_effects import ONLINE_PARAMS, OnlineEffectsHook
from ppoe_ros.common.services import FusionServices
from ppoe_ros.common.tf_broadcast import FusionTf

__all__ = ["FusionNode", "PARAMS", "main"]

#: defaults shared with ``ppoe evaluate`` (ppoe_core.estimation.pipeline.FUSION_SETTINGS)
_D = FUSION_SETTINGS

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("model_file", "", "model YAML: tags, camera, contact, perturbations (required)", check=check_nonempty),
    ParamSpec("robot_description", "", "URDF XML; empty = take it from robot_description_topic"),
    ParamSpec("robot_description_topic", "robot_description", "latched std_msgs/String topic carrying the URDF",
              check=check_nonempty),
    ParamSpec("base_frame", "", "frame of the prior (its header.frame_id); empty = model YAML frames.base"),
    ParamSpec("tool_frame", "", "frame whose pose the prior is; empty = model YAML frames.tool"),
    ParamSpec("prior_topic", "ppoe/pose", "kinematics prior (PoseWithCovarianceStamped)", check=check_nonempty),
    ParamSpec("observations_topic", "tag_bearing/observations", "tag observations (PointCloud2); empty = off"),
    ParamSpec("contact_topic", "contact/plane", "contact plane (PoseWithCovarianceStamped); empty = off"),
    ParamSpec("camera_info_topic", "camera/camera_info", "CameraInfo for the focal lengths; empty = fit from u,v"),
    ParamSpec("joint_states_topic", "joint_states", "JointState for joint positions at the prior stamps; empty = off"),
    ParamSpec("joint_max_age", 0.5, "a joint value a split joint-state message lacks is held this long (as the "
              "kinematics node's joint_max_age); 0 = no limit", unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("fused_topic", "ppoe/fused_pose", "output topic (PoseWithCovarianceStamped)", check=check_nonempty),
    ParamSpec("buffer_duration", _D["buffer_duration"], "history of priors kept; older measurements are dropped",
              unit="s", min_value=1e-3, max_value=3600.0),
    ParamSpec("max_gap", _D["max_gap"], "neighbouring priors further apart are not interpolated between", unit="s",
              min_value=1e-6, max_value=3600.0),
    ParamSpec("max_hold", _D["max_hold"], "max distance to the nearest prior when interpolation is impossible",
              unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("max_pending", _D["max_pending"], "measurements newer than the newest prior kept waiting", min_value=0,
              max_value=100000),
    ParamSpec("min_interval", _D["min_interval"], "per source (topic + frame_id): a measurement less than this after "
              "the last one processed is skipped (counted as throttled); 0 = process all", unit="s", min_value=0.0,
              max_value=3600.0),
    ParamSpec("pending_timeout", 1.0, "when no prior arrived for this long (steady clock), pending measurements "
              "are processed with the newest prior (hold) or dropped", unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("correction_timeout", _D["correction_timeout"],
              "a carried correction fades over / is dropped after this; <= 0 = off", unit="s", max_value=1e6),
    ParamSpec("correction_joint_motion", _D["correction_joint_motion"],
              "... after this max-abs joint motion; <= 0 = off", unit="rad or m", max_value=1e6),
    ParamSpec("correction_tool_translation", _D["correction_tool_translation"],
              "... after this tool translation; <= 0 = off", unit="m", max_value=1e6),
    ParamSpec("correction_tool_rotation", _D["correction_tool_rotation"], "... after this tool rotation; <= 0 = off",
              unit="rad", max_value=1e6),
    ParamSpec("correction_decay", _D["correction_decay"], "linear: weight 1 - ratio; step: full weight until dropped",
              check=lambda v: None if v in ("linear", "step") else f"must be 'linear' or 'step', got {v!r}"),
    ParamSpec("max_iterations", _D["max_iterations"],
              "relinearisations of the iterated LG-EKF update (1 = plain LG-EKF)", min_value=1, max_value=100),
    ParamSpec("gate_probability", _D["gate_probability"], "chi-square gate probability; 1.0 = no gating", min_value=0.5,
              max_value=1.0),
    ParamSpec("gating", _D["gating"], "posterior: cost of the iterated solution; prior: NIS at the prior",
              check=lambda v: None if v in ("posterior", "prior") else f"must be 'posterior' or 'prior', got {v!r}"),
    ParamSpec("pixel_sigma", _D["pixel_sigma"], "1-sigma pixel noise; <= 0 = model YAML camera.pixel_sigma", unit="px",
              max_value=1e6),
    ParamSpec("use_tag_centre", _D["use_tag_centre"], "use the tag centres (corner 0)"),
    ParamSpec("use_tag_corners", _D["use_tag_corners"], "use the tag corners 1..4"),
    ParamSpec("camera_covariance", _D["camera_covariance"],
              "let the PPOE covariance of the camera chain enter the tag model"),
    ParamSpec("contact_distance_sigma", _D["contact_distance_sigma"], "extra 1-sigma noise of the contact distance",
              unit="m", min_value=0.0, max_value=1e3),
    SOURCES_PARAM,
    FRAME_PREFIX_PARAM,
    ParamSpec("publish_tf", True, "publish the fused pose on /tf and the calibrated cameras on /tf_static"),
    ParamSpec("tf_child_frame", "", "child frame of the fused pose on /tf; empty = '<tool_frame>_corrected'; "
              "a URDF link is refused (TF of the tool off, the node keeps running)"),
    ParamSpec("tf_camera_suffix", "_calibrated", "the calibrated camera frame on /tf_static is the model YAML's "
              "camera frame + this suffix", check=check_nonempty),
    ParamSpec("publish_on_update", True, "publish the newest fused pose right after an accepted measurement"),
    ParamSpec(
        "qos_depth",
        1000,
        "history depth of the input subscriptions (a node that falls behind a "
        "1 kHz prior stream catches up instead of losing priors)",
        min_value=1,
        max_value=100000,
    ),
    ParamSpec("output_qos_depth", 1000, "history depth of the fused-pose publisher (reliable): a subscriber "
              "that falls behind by more loses poses; 1000 = 1 s at 1 kHz", min_value=1, max_value=100000),
    ParamSpec("input_timeout", 1.0, "/diagnostics says WARN when no input (prior or measurement) arrived for "
              "this long; 0 = off",
              unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
    ParamSpec(
        "log_throttle", 2.0, "at most one log line per kind of bad message per this period", unit="s", min_value=0.0
    ),
) + ONLINE_PARAMS  # online effects (docs/online.md)

_STAT_KEYS = (
    "received", "published", "bad", "priors", "measurements", "accepted", "rejected", "dropped", "dropped_stale",
    "dropped_no_prior", "dropped_no_model", "throttled", "corrections_dropped", "pending", "empty_observations",
    "resets", "priors_late", "priors_out_of_order",
)


class FusionNode(Node):
    """Kinematics prior + measurements -> ``/ppoe/fused_pose`` through :class:`FusionPipeline`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("fusion_node", **kwargs)
        names = source_names(self)
        p = declare_parameters(self, PARAMS + source_specs(names))
        resolve_topics(self, p, ("robot_description_topic", "prior_topic", "observations_topic", "contact_topic",
                                 "camera_info_topic", "joint_states_topic", "fused_topic"))
        self.params = p
        self.prefix = p["frame_prefix"]
        self.stats = NodeStats(self, _STAT_KEYS, p["log_throttle"])
        self.stats.warn_keys |= {"priors_late", "priors_out_of_order"}
        self._converging: bool | None = None  # no measurement fused since start / the last reset
        self._accepted_base = (0, 0)  # (resets, accepted) when the filter last started over
        self.model_yaml = read_yaml_mapping(p["model_file"], "model file")
        frames = mapping_get(self.model_yaml, "frames", default={}) or {}
        self.base_frame = p["base_frame"] or frames.get("base") or "base_link"
        self.tool_frame = p["tool_frame"] or frames.get("tool") or "tool0"
        self.settings = {k: p[k] for k in FUSION_SETTINGS}
        try:
            self.pipeline = make_pipeline(None, self.base_frame, self.tool_frame, self.settings, updater=self._update)
        except PpoeError as exc:
            raise ModelConfigError(f"node {self.get_name()}: {exc}") from None
        self.updater: ModelUpdater | None = None
        self.model: Any = None
        self._urdf: str | None = None
        self.joints = JointHistory([])
        self.focal: dict[str, tuple[float, float]] = {}

        self.pub = self.create_publisher(PoseWithCovarianceStamped, p["fused_topic"],
                                          reliable_qos(p["output_qos_depth"]))
        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])
        self.diagnostics.watch_input("input (prior or measurement)", "received", p["input_timeout"])
        self.tf = FusionTf(self, p, self.diagnostics)
        self.online = (OnlineEffectsHook(self, p, self.stats, p["model_file"], self.diagnostics)
                       if p["online_enable"] else None)
        qos = sensor_qos(p["qos_depth"])
        rel = reliable_qos(p["qos_depth"])

        def sub(msg_type: Any, topic: str, cb: Any, q: Any, raw: bool = False) -> None:
            if topic:
                counted_subscription(self, self.stats, msg_type, topic, cb, q, raw=raw)

        self._out = PoseCovarianceCdr(self.prefix + self.base_frame)  # the output as bytes, the 1 kHz inputs too
        self._js_reader = JointStateReader()
        sub(PoseWithCovarianceStamped, p["prior_topic"], self._prior, qos, raw=True)
        sub(PointCloud2, p["observations_topic"], self._observations, rel)
        sub(PoseWithCovarianceStamped, p["contact_topic"], self._contact, rel)
        sub(CameraInfo, p["camera_info_topic"], self._camera_info, qos)
        sub(JointState, p["joint_states_topic"], self._joint_state, qos, raw=True)
        self.sources = LiveSources(self, parse_sources(p, names, f"node {self.get_fully_qualified_name()}"),
                                   self.stats, self.prefix, self._measure)
        self.sources.subscribe(qos)
        self.commands = FusionServices(self, self.pipeline, self._measure, self.prefix, self.stats)
        self._last_prior_wall = time.monotonic()
        self._newest_stamp = (math.nan, 0)  # the newest prior's stamp: (seconds as the pipeline keeps it, exact ns)
        self.create_timer(0.1, guarded(self.stats, "pending measurements")(self._expire_pending),
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

        take_robot_description(self, p, self.stats, self._set_model, self._robot_description)
        if self.model is None:
            self.diagnostics.set_status(DiagnosticStatus.ERROR, "no model: waiting for robot_description")

    # ------------------------------------------------------------------ model
    def _set_model(self, urdf_xml: str, where: str) -> None:
        from ppoe_core.model.ppoe import PPOEModel

        try:
            model = PPOEModel.from_strings(urdf_xml, Path(self.params["model_file"]), urdf_source=where)
            model.robot.check_link(self.base_frame)
            model.robot.check_link(self.tool_frame)
            updater = make_updater(model, self.base_frame, self.tool_frame, self.settings, cls=SourceUpdater)
        except PpoeError as exc:
            raise type(exc)(f"{where}: {exc}") from None
        # import the update code now (scipy.stats ...), not while the first measurement waits
        import ppoe_core.estimation.fusion  # noqa: F401
        import ppoe_core.estimation.measurements  # noqa: F401

        self.model, self.updater, self._urdf = model, updater, urdf_xml
        p = self.params
        self.joints = JointHistory(model.joint_names, known=model.robot.joints,
                                   max_age_ns=int(round(p["joint_max_age"] * 1e9)),
                                   keep_ns=int((p["buffer_duration"] + 1.0) * 1e9),
                                   policy=self.pipeline.stamp_policy)
        self.tf.set_model(model, self.base_frame, self.tool_frame)
        if self.online is not None:
            self.online.set_model(model)
        problems = self.sources.set_model(model)
        for line in problems:
            self.get_logger().error(f"{line} (the node keeps running)")
        self.diagnostics.set_problem("sources", "; ".join(problems) if problems else None)
        self.get_logger().info(
            f"model from {where}: fusing into {self.base_frame} -> {self.tool_frame}; tags "
            f"{sorted(updater.tags)}; contact {'yes' if updater.contact is not None else 'no'}; sources "
            + (", ".join(f"{s.name} ({s.kind} on {s.topic})" for s in self.sources.sources if not s.off) or "none")
        )

    def _robot_description(self, msg: String) -> None:
        if msg.data == self._urdf:
            return
        self._set_model(msg.data, f"topic {self.params['robot_description_topic']}")
        self.diagnostics.set_status(None, "")
        self._converging = None  # re-announced at the next prior

    def _update(self, T: np.ndarray, cov: np.ndarray, m: Measurement, prior: PriorSample) -> ToolUpdate:
        if self.updater is None:
            raise MeasurementError("no robot model yet (waiting for robot_description)")
        return self.updater(T, cov, m, prior)

    # -------------------------------------------------------------- callbacks
    def _camera_info(self, msg: CameraInfo) -> None:
        fx, fy = float(msg.k[0]), float(msg.k[4])
        if not (math.isfinite(fx) and math.isfinite(fy) and fx > 0 and fy > 0):
            raise MeasurementError(f"camera_info K has fx = {fx}, fy = {fy}")
        self.focal[msg.header.frame_id] = (fx, fy)
        if self.online is not None:  # a change of the intrinsics mid-run is counted and logged by the hook
            self.online.camera_info(unprefixed(self.prefix, msg.header.frame_id, self.params["camera_info_topic"]),
                                    np.asarray(msg.k, float).reshape(3, 3), np.asarray(msg.d, float))

    def _joint_state(self, data: bytes) -> None:
        if self.model is None:
            return
        msg = self._js_reader.parse(data)  # MeasurementError naming the field of a malformed message: counted bad
        self.joints.update(msg.names, msg.positions, msg.stamp_ns)  # a refused one: counted bad

    def _prior(self, data: bytes) -> None:
        self.stats.counts["received"] += 1
        T, cov_tool, stamp_ns, frame = self._out.parse_local(data)
        if frame != self.prefix + self.base_frame:
            raise MeasurementError(f"prior frame '{frame}' is not base_frame '{self.prefix}{self.base_frame}'")
        if self.online is not None:  # the static model's prior moved to the online effect estimate
            T, cov_tool = self.online.correct_prior(stamp_ns, T, cov_tool, self.base_frame, self.tool_frame)
        newest, topic = self.pipeline.buffer.newest, self.params["prior_topic"]
        est, outcomes = self.pipeline.add_prior(stamp_ns * 1e-9, T, cov_tool, self.joints.at(stamp_ns))
        if est is not None and (newest is None or stamp_ns * 1e-9 >= newest):
            self._newest_stamp = (stamp_ns * 1e-9, stamp_ns)
        if est is None:
            self.stats.bad(topic, f"prior at {stamp_ns * 1e-9:.6f} s is older than the prior buffer "
                                  f"(newest {newest:.6f} s, {self.params['buffer_duration']:g} s kept): dropped",
                           kind="priors_late")
        elif newest is not None and not self.pipeline.stamp_policy.new_timeline_s(stamp_ns * 1e-9, newest) \
                and stamp_ns * 1e-9 <= newest:
            self.stats.bad(topic, f"prior at {stamp_ns * 1e-9:.6f} s is not newer than the last one "
                                  f"({newest:.6f} s): used, out of order", kind="priors_out_of_order")
        self._last_prior_wall = time.monotonic()
        for o in outcomes:
            self._report(o)
        if est is not None:
            self._publish(est.T_base_tool, est.cov_tool, stamp_ns)
        self._sync_counts()

    def _observations(self, msg: PointCloud2) -> None:
        self.stats.counts["received"] += 1
        d = observations_from_cloud(msg)
        if d["id"].size == 0:
            self.stats.counts["empty_observations"] += 1
            return
        frame = msg.header.frame_id
        fx, fy = self.focal.get(frame, (None, None))
        payload = TagMeasurement(unprefixed(self.prefix, frame, self.params["observations_topic"]), d["id"].astype(int),
                                 d["corner"].astype(int), np.column_stack([d["x"], d["y"]]),
                                 np.column_stack([d["u"], d["v"]]), fx, fy)
        source = source_key(self.params["observations_topic"], frame)
        self._measure(Measurement(stamp_to_ns(msg.header.stamp) * 1e-9, source, payload))

    def _contact(self, msg: PoseWithCovarianceStamped) -> None:
        self.stats.counts["received"] += 1
        T, cov_ros, stamp_ns, frame = pose_cov_from_msg(msg)
        cov_plane = lie.check_covariance(
            lie.cov_ros_to_local(T, cov_ros), name=f"{self.params['contact_topic']} covariance", size=6
        )
        source = source_key(self.params["contact_topic"], frame)
        plane_frame = unprefixed(self.prefix, frame, self.params["contact_topic"])
        self._measure(Measurement(stamp_ns * 1e-9, source, ContactMeasurement(plane_frame, T, cov_plane)))

    def _measure(self, m: Measurement) -> None:
        """The one place where a measurement (any kind, any source) is handed to the pipeline."""
        if self.updater is None:
            self.stats.bad(m.source, "no robot model yet (waiting for robot_description)", kind="dropped_no_model")
            return
        if self.online is not None:  # every measurement kind also updates the online effects
            self.online.measure(m)
        self._report(self.pipeline.add_measurement(m))
        self._sync_counts()

    def _expire_pending(self) -> None:
        # measurements newer than the newest prior wait for it; only when the prior stream
        # has gone quiet are they taken with the newest prior (hold) or dropped
        if not self.pipeline.pending or time.monotonic() - self._last_prior_wall < self.params["pending_timeout"]:
            return
        for o in self.pipeline.flush():
            self._report(o)
        self._sync_counts()

    # ---------------------------------------------------------------- output
    def _report(self, o: MeasurementOutcome) -> None:
        src = o.measurement.source
        if o.status == "bad":
            self.stats.bad(src, o.error)
        elif o.status in ("stale", "no_prior"):
            self.stats.bad(
                src,
                f"measurement at {o.measurement.stamp:.6f} s: {o.status} (prior buffer "
                f"{self.pipeline.buffer.oldest} .. {self.pipeline.buffer.newest} s)",
                kind="dropped",
            )
        elif o.status == "rejected":
            self.stats.bad(src, f"rejected by the gate (cost {o.nis:.3g})", kind="rejected")
        elif o.status == "accepted" and self.params["publish_on_update"]:
            est = self.pipeline.latest()
            if est is not None:  # the newest prior's exact stamp (seconds as float lose up to ~0.1 us at 2026 epochs)
                s, ns = self._newest_stamp
                self._publish(est.T_base_tool, est.cov_tool, ns if est.stamp == s else int(round(est.stamp * 1e9)))

    def _publish(self, T: np.ndarray, cov_tool: np.ndarray, stamp_ns: int) -> None:
        out = self._out
        self.pub.publish(out.serialize_local(T, cov_tool, stamp_ns))
        self.tf.publish_pose(out.fields[:7], stamp_ns)  # the message's position and quaternion
        self.stats.counts["published"] += 1

    def _sync_counts(self) -> None:
        c, s = self.pipeline.counts, self.stats.counts
        for k in ("priors", "measurements", "accepted", "rejected", "dropped_stale", "dropped_no_prior",
                  "corrections_dropped", "resets", "throttled"):
            s[k] = c[k]
        s["dropped"] = c["dropped_stale"] + c["dropped_no_prior"]
        s["pending"] = len(self.pipeline.pending)
        if c["resets"] != self._accepted_base[0]:
            self._accepted_base = (c["resets"], c["accepted"])
        self._set_converging(c["accepted"] == self._accepted_base[1])

    def _set_converging(self, converging: bool) -> None:
        """``/diagnostics`` WARN "converging" until a measurement is fused after start or a clock reset."""
        if converging == self._converging or self.model is None:
            return
        self._converging = converging
        if converging:
            self.diagnostics.set_status(
                DiagnosticStatus.WARN, "converging: no measurement fused since start or the last clock reset; "
                "the output is the uncorrected prior", converging=True)
        else:
            self.diagnostics.set_status(None, "", converging=False)

    def destroy_node(self) -> None:
        """Write the online effect estimate as a model YAML (``online_model_out``) before the node goes."""
        if self.online is not None:
            self.online.write_model()
        super().destroy_node()


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``fusion_node`` (``--ros-args`` accepted)."""
    from ppoe_ros.common.runner import run_node

    return run_node(FusionNode, args, executor="events", kernels=("fusion_node",))


if __name__ == "__main__":
    sys.exit(main())
