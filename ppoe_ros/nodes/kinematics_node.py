"""Kinematics node: joint states -> PPOE pose with covariance (``/ppoe/pose``).

Subscriptions
    ``joint_states`` (``sensor_msgs/JointState``, sensor-data QoS; reliable with ``joint_states_reliable``):
    one output per message.
    ``robot_description`` (``std_msgs/String``, transient local) unless the
    ``robot_description`` parameter holds the URDF.
Publications
    ``ppoe/pose`` (``geometry_msgs/PoseWithCovarianceStamped``): ``T_reference_target``
    with ``header.frame_id = frame_prefix + reference_frame`` and ``header.stamp`` = the joint-state
    stamp; the covariance is ``cov_target`` (local, right perturbation, paper
    eq. 8-9/18) converted to the ROS convention of docs/conventions.md sec. 2.
    ``ppoe/<frame>/pose`` (same type) for each of ``extra_target_frames``.
    Topics are relative (robot_state_publisher's convention): in the root namespace they are ``/joint_states``,
    ``/ppoe/pose`` ..., under ``--ros-args -r __ns:=/robot1`` ``/robot1/joint_states`` ...; ``/tf``, ``/tf_static``
    and ``/diagnostics`` stay absolute, and ``frame_prefix`` goes in front of every frame published
    (:mod:`ppoe_ros.common.frame_prefix`).
    ``/diagnostics``: counters ``received``, ``published``, ``bad``, ``dropped``.
    ``/tf`` and ``/tf_static`` (``publish_tf``, off by default): the model's frames like
    robot_state_publisher, each movable joint's child link in its parent link at the joint-state
    stamp, the fixed joints once (:class:`~ppoe_ros.common.tf_broadcast.KinematicsTf`).  With
    ``publish_tf: false`` nothing of it is on the per-message path.

Split joint states (arm, mast and gripper on separate publishers, as with ros2_control) are merged per
joint: each output uses the latest value of every chain joint, at most ``joint_max_age`` old; a message
carrying none of the chain's joints is counted as ``ignored``, one arriving while a chain joint is not
yet known or too old as ``incomplete`` (both logged, throttled, no output).

Bad input never stops the node: a NaN/inf position, mismatched ``name``/``position`` lengths, a joint named
twice, a chain joint missing while the message carries a name the URDF lacks (a misspelt joint: its held value is
not used), a stamp older than the previous one or more than ``stamp_future_tolerance`` ahead of the node's clock
is logged (throttled), counted as ``bad`` and dropped (:class:`ppoe_core.model.joint_history.JointHistory`,
:class:`~ppoe_core.model.joint_history.StampResetPolicy`).  A backward jump larger than
``stamp_reset_threshold`` (a replayed bag looping, a simulator reset) is logged and counted too, but taken as the
start of a new timeline (held joint values forgotten): that message is published.  Joint states that arrive
before the URDF are counted as ``dropped``.  Joints the chain does not use are ignored.
A model whose effects read a context (``thermal_growth`` against time or temperature, ``backlash``) gets it from
the joint states so far (:class:`ppoe_core.model.context.LiveContext`: time since the first one, each joint's last
motion sign); for a temperature the node subscribes to ``temperature`` (``sensor_msgs/Temperature``) and counts
joint states as bad until the first arrives.

Throughput (``bench/bench_nodes.py``, docs/performance.md): the node spins rclpy's ``EventsExecutor``
(:func:`~ppoe_ros.common.runner.run_node`), takes ``/joint_states`` as raw CDR bytes and publishes the pose as
bytes: no typed ROS message is built on the hot path.  A usual joint state (a name layout seen before, finite
values, stamp not going back, the chain's joints known and fresh) takes ONE compiled call from its bytes to the
pose message's bytes (:mod:`ppoe_core.io.joint_pose`: parse, joint merge, one-configuration FK, quaternion,
ROS covariance, serialisation); anything else takes the Python path (:mod:`ppoe_core.io.cdr`, the joint merger,
``model.fk``), which gives the same bytes and all the diagnostics (with ``publish_tf``, ``max_batch`` > 1 or
model effects only the Python path runs).  ``max_batch`` > 1
moves the FK to a worker thread that takes whatever queued up as one vectorised batch (``model.fk``
broadcasts over a batch axis); ``drain_max`` takes waiting messages in one callback, which also picks up
messages the events executor was not told about after a history overflow.

Parameters: see ``config/nodes/kinematics_node.yaml`` (every key documented there) and
:data:`PARAMS`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from sensor_msgs.msg import JointState, Temperature
from std_msgs.msg import String

from ppoe_core import lie
from ppoe_core.errors import ModelConfigError, PpoeError
from ppoe_core.estimation.batch_worker import BatchWorker
from ppoe_core.model.joint_history import JointHistory
from ppoe_core.model.stamp_policy import StampResetPolicy
from ppoe_core.io.cdr import PoseCovarianceWriter, parse_joint_state
from ppoe_core.io.joint_pose import NO_LIMIT, JointPoseFastPath
from ppoe_core.model.context import LiveContext
from ppoe_core.model.ppoe import PPOEModel
from ppoe_core.robot.yaml_io import read_yaml_mapping
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats, guarded
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_nonempty, declare_parameters, mapping_get
from ppoe_ros.common.qos import reliable_qos, sensor_qos
from ppoe_ros.common.runner import take_robot_description
from ppoe_ros.common.frame_prefix import FRAME_PREFIX_PARAM, resolve_topics
from ppoe_ros.common.tf_broadcast import KinematicsTf

__all__ = ["KinematicsNode", "PARAMS", "main", "output_topic"]

_STRING_ARRAY = ParameterType.PARAMETER_STRING_ARRAY

#: Parameters of the node (defaults; documented in config/nodes/kinematics_node.yaml).
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("model_file", "", "model YAML (perturbations, frames, ...); empty = exact URDF, zero covariance"),
    ParamSpec("robot_description", "", "URDF XML; empty = take it from the robot_description topic"),
    ParamSpec("robot_description_topic", "robot_description", "latched std_msgs/String topic carrying the URDF",
              check=check_nonempty),
    ParamSpec("joint_states_topic", "joint_states", "sensor_msgs/JointState input (relative: follows the node's "
              "namespace)", check=check_nonempty),
    ParamSpec("reference_frame", "", "frame the pose is expressed in; empty = model YAML frames.base, "
              "else the URDF root link"),
    ParamSpec("target_frame", "", "frame whose pose is published; empty = model YAML frames.tool, else tool0"),
    ParamSpec("pose_topic", "ppoe/pose", "output topic of the target frame", check=check_nonempty),
    ParamSpec("extra_target_frames", [], "more target frames, published on ppoe/<frame>/pose",
              ptype=_STRING_ARRAY),
    ParamSpec("order", 2, "covariance propagation order (paper eq. 15/18: 2; 4 = fourth order)",
              check=lambda v: None if v in (2, 4) else f"must be 2 or 4, got {v}"),
    ParamSpec("max_batch", 1, "largest batch of queued joint states per FK call; 1 = compute in the "
              "subscription callback (no worker thread)", min_value=1, max_value=100000),
    ParamSpec("max_queue", 2000, "joint states waiting for the FK worker beyond this are dropped (oldest first)",
              min_value=1, max_value=1000000),
    ParamSpec("drain_max", 200, "after each joint-state callback, take up to this many already waiting "
              "joint states at once (one executor wake-up per burst); 0 = one per wake-up",
              min_value=0, max_value=100000),
    ParamSpec("qos_depth", 100, "history depth of the joint-state subscription (sensor-data QoS)",
              min_value=1, max_value=100000),
    ParamSpec("joint_states_reliable", False, "subscribe the joint states with reliable QoS (nothing lost between a "
              "reliable publisher and the node, which may slow the publisher) instead of best effort (sensor data)"),
    ParamSpec("output_qos_depth", 1000, "history depth of the pose publishers (reliable): a subscriber "
              "that falls behind by more loses poses; 1000 = 1 s at 1 kHz", min_value=1, max_value=100000),
    ParamSpec("input_timeout", 1.0, "/diagnostics says WARN when no joint state arrived for this long; 0 = off",
              unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("joint_max_age", 0.5, "joint states may come split over several publishers (arm, mast, gripper): a "
              "needed joint's latest value is used while at most this old; 0 = no limit", unit="s", min_value=0.0,
              max_value=3600.0),
    ParamSpec("stamp_reset_threshold", 1.0, "a stamp this much older than the last one starts a new timeline",
              unit="s", min_value=0.0),
    ParamSpec("stamp_future_tolerance", 0.5, "a stamp more than this ahead of the node's clock is refused (counted "
              "as bad, not published); 0 = off", unit="s", min_value=0.0, max_value=3600.0),
    FRAME_PREFIX_PARAM,
    ParamSpec("publish_tf", False, "publish the model's frames on /tf (movable joints, at each joint state) and "
              "/tf_static (fixed joints) like robot_state_publisher"),
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
    ParamSpec("log_throttle", 2.0, "at most one log line per kind of bad message per this period", unit="s",
              min_value=0.0),
)


def output_topic(frame: str) -> str:
    """Topic of an extra target frame: ``ppoe/<frame>/pose`` (relative, in the node's namespace)."""
    return f"ppoe/{frame.strip('/')}/pose"


class _Target:
    """One output: a target frame, its publisher and the serialiser of its messages (raw CDR)."""

    __slots__ = ("frame", "pub", "writer")

    def __init__(self, frame: str, pub: Any) -> None:
        self.frame = frame
        self.pub = pub
        self.writer = PoseCovarianceWriter("")


class KinematicsNode(Node):
    """Publishes ``T_reference_target`` and its ROS-convention covariance for every joint state."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("kinematics_node", **kwargs)
        p = declare_parameters(self, PARAMS)
        resolve_topics(self, p, ("robot_description_topic", "joint_states_topic", "pose_topic"))
        self.params = p
        self.stats = NodeStats(self, ("received", "published", "bad", "dropped"), p["log_throttle"])
        self.model_yaml = read_yaml_mapping(p["model_file"], "model file")
        frames = self._frames = mapping_get(self.model_yaml, "frames", default={}) or {}
        # "" = the URDF root link, resolved when the URDF arrives
        self.reference = p["reference_frame"] or frames.get("base") or ""
        target = p["target_frame"] or frames.get("tool") or "tool0"
        self.order = int(p["order"])
        self.policy = StampResetPolicy(p["stamp_reset_threshold"], p["stamp_future_tolerance"])
        self._future_ns = self.policy.future_ns
        self._sim_time = bool(self.get_parameter("use_sim_time").value)
        self.model: Any = None
        self._urdf: str | None = None
        self._fast: JointPoseFastPath | None = None
        self._history = JointHistory([], policy=self.policy)
        self._model_joints: list[str] = []
        self._dst = np.zeros(0, dtype=np.intp)
        self._worker: BatchWorker | None = None
        self._live: LiveContext | None = None  # context of effects that read time, motion or temperature
        self._temperature_sub: Any = None

        out_qos = reliable_qos(p["output_qos_depth"])
        self.targets = [_Target(target, self.create_publisher(PoseWithCovarianceStamped, p["pose_topic"],
                                                              out_qos))]
        for frame in p["extra_target_frames"]:
            if frame == target or frame in (t.frame for t in self.targets):
                raise ModelConfigError(
                    f"node {self.get_name()}: parameter 'extra_target_frames' repeats '{frame}'")
            self.targets.append(_Target(frame, self.create_publisher(
                PoseWithCovarianceStamped, output_topic(frame), out_qos)))

        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])
        self._tf = (KinematicsTf.create(self, self.stats, self.diagnostics, p["frame_prefix"]) if p["publish_tf"]
                    else None)
        js_topic = p["joint_states_topic"]
        js_qos = reliable_qos(p["qos_depth"]) if p["joint_states_reliable"] else sensor_qos(p["qos_depth"])
        self._on_joint_state = guarded(self.stats, js_topic)(self._joint_state)
        self._drain_max = int(p["drain_max"])
        take_robot_description(self, p, self.stats, self._set_model, self._robot_description)
        # after the model (its kernels take 1-30 s to load or compile): a subscription that exists while the node
        # does not spin yet loses what overflows its history, and the node could not count it (losses.py)
        self._js_sub, self._js_gaps = counted_subscription(self, self.stats, JointState, js_topic,
                                                           self._on_joint_state_burst, js_qos,
                                                           raw=True)
        self.diagnostics.watch_input(js_topic, "received", p["input_timeout"])
        self.diagnostics.set_status(None if self.model else DiagnosticStatus.ERROR,
                                    "" if self.model else "no model: waiting for robot_description")
        if p["max_batch"] > 1:  # last: nothing after it can fail and leave the thread behind
            self._worker = BatchWorker(self._process, p["max_batch"], p["max_queue"],
                                       on_dropped=lambda why: self.stats.bad(js_topic, why, kind="dropped"),
                                       on_error=lambda exc: self.stats.error(js_topic, exc))

    # ------------------------------------------------------------------ model
    def _set_model(self, urdf_xml: str, where: str) -> None:
        try:
            # the model YAML from its file (a Path), so that errors name file and line (a dict would not)
            model_file = self.params["model_file"]
            model = PPOEModel.from_strings(urdf_xml, Path(model_file) if model_file else None, urdf_source=where)
            reference = self.params["reference_frame"] or self._frames.get("base") or model.robot.root
            model.robot.check_link(reference)  # check the frames now, not at the first joint state
            live = LiveContext(model.effects, model.joint_names)  # effects that read time, motion, temperature
            for t in self.targets:
                model.robot.check_link(t.frame)
                # compile (or load from numba's cache) the kernels now, not at the first joint state
                T, cov = model.fk(np.zeros(len(model.joint_names)), reference, t.frame, order=self.order,
                                  context=live.neutral() if live else None)
                lie.cov_local_to_ros(T, cov)
                lie.quat_from_matrix(T[:3, :3])
                t.writer = PoseCovarianceWriter(self.params["frame_prefix"] + reference)
        except PpoeError as exc:
            raise type(exc)(f"{where}: {exc}") from None
        needed: list[str] = []
        for t in self.targets:
            needed += [n for n in model.chain_joints(reference, t.frame) if n not in needed]
        self._model_joints = list(model.joint_names)
        self._dst = np.array([self._model_joints.index(n) for n in needed], dtype=np.intp)
        self._history = JointHistory(needed, known=model.robot.joints, policy=self.policy,
                                     max_age_ns=int(round(self.params["joint_max_age"] * 1e9)))
        self._live = live if live else None
        if self._live is not None and "temperature" in live.needed and self._temperature_sub is None:
            self._temperature_sub = counted_subscription(self, self.stats, Temperature, "temperature",
                                                         self._temperature, sensor_qos(10))
        self.reference = reference
        self.model = model
        self._urdf = urdf_xml
        if self._tf is not None:
            self._tf.set_model(model)
        self._fast = self._fast_path(model)
        self.get_logger().info(
            f"model from {where}: {len(model.joint_names)} joints; publishing "
            + ", ".join(f"{self.params['frame_prefix']}{self.reference}->{t.frame} on {t.pub.topic_name}"
                        for t in self.targets))

    def _fast_path(self, model: Any) -> JointPoseFastPath | None:
        """The whole per-message path as one compiled call (:mod:`ppoe_core.io.joint_pose`), for the default
        configuration: FK in the callback, no TF, a model without effects; None otherwise."""
        if self._tf is not None or self.params["max_batch"] > 1:
            return None
        leans = [model.lean_program(self.reference, t.frame) for t in self.targets]
        if any(lean is None for lean in leans):
            return None
        fast = JointPoseFastPath(self._history, self._dst, len(self._model_joints),
                                 [(lean, t.writer) for lean, t in zip(leans, self.targets)], self.order)
        fast.warm()
        return fast

    def _now_ns(self) -> int | None:
        """The node's clock [ns] for the future-stamp check (None: off, or no /clock yet with use_sim_time); the
        system clock without use_sim_time (what rclpy's clock reads, at a fraction of its cost)."""
        if not self._future_ns:
            return None
        if not self._sim_time:
            return time.time_ns()
        return self.get_clock().now().nanoseconds or None

    def _robot_description(self, msg: String) -> None:
        if msg.data == self._urdf:
            return
        self._set_model(msg.data, f"topic {self.params['robot_description_topic']}")
        self.diagnostics.set_status(None, "")

    # --------------------------------------------------------------- callback
    def _on_joint_state_burst(self, msg: bytes) -> None:
        """Subscription callback: this message, then up to ``drain_max`` more that already wait (one callback
        per burst; with the events executor also the messages it was not told about after a history overflow,
        which would otherwise wait uncounted until the next message)."""
        self._on_joint_state(msg)
        handle = self._js_sub.handle
        for _ in range(self._drain_max):
            try:
                with handle:
                    taken = handle.take_message(JointState, True)
            except Exception as exc:  # noqa: BLE001 - rclpy internals changed: fall back to the executor
                self._drain_max = 0
                self.get_logger().warning(f"draining /joint_states disabled: {type(exc).__name__}: {exc}")
                return
            if taken is None:
                return
            self._js_gaps.observe(taken[1])
            self._on_joint_state(taken[0])

    def _joint_state(self, data: bytes) -> None:
        """Validate one serialised joint state (in arrival order) and process it, or queue it for the worker."""
        stats = self.stats
        stats.counts["received"] += 1
        fast = self._fast
        now = self._now_ns()
        limit = NO_LIMIT if now is None else now + self._future_ns
        if fast is not None and type(data) is bytes and fast.run(data, limit):
            for t in self.targets:  # the usual message: one compiled call
                t.pub.publish(t.writer.message())
            stats.counts["published"] += 1
            return
        model = self.model
        topic = self.params["joint_states_topic"]
        if model is None:
            stats.bad(topic, "no URDF yet (waiting for robot_description)", kind="dropped")
            return
        msg = parse_joint_state(data)  # MeasurementError naming the field of a malformed message
        # StampRefused / JointValueError / ValueError naming the stamp or the joint: counted as bad by the guard
        upd = self._history.update(msg.names, msg.positions, msg.stamp_ns, now)
        if upd.new_timeline:
            stats.bad(topic, upd.new_timeline)
        if self._tf is not None:
            self._tf.publish(msg.stamp_ns, msg.names, msg.positions)
        if fast is not None:
            fast.learn(data, msg.names)
        if upd.values is None:
            stats.bad(topic, upd.why, kind=upd.kind)
            return
        q = np.zeros(len(self._model_joints))
        q[self._dst] = upd.values
        if self._worker is None:
            self._publish_one(msg.stamp_ns, q, model)
        else:
            self._worker.put((msg.stamp_ns, q, model))

    def _process(self, items: list[tuple[Any, np.ndarray, Any]]) -> None:
        """FK of a batch of validated joint states (one model call per target) and publish each."""
        model = items[0][2]
        if any(it[2] is not model for it in items):  # URDF changed inside the batch: split it
            cut = next(i for i, it in enumerate(items) if it[2] is not model)
            self._process(items[:cut])
            self._process(items[cut:])
            return
        if len(items) == 1:
            self._publish_one(*items[0])
            return
        q = np.stack([it[1] for it in items])
        try:
            ctx = self._live.update_many([it[0] * 1e-9 for it in items], q) if self._live is not None else None
            results = []
            for t in self.targets:
                T, cov_local = model.fk(q, self.reference, t.frame, order=self.order, context=ctx)
                results.append((t, T[:, :3, 3], lie.quat_from_matrix(T[:, :3, :3]), lie.cov_local_to_ros(T, cov_local)))
        except PpoeError as exc:
            for _ in items:
                self.stats.bad(self.params["joint_states_topic"], str(exc))
            return
        for k, (stamp_ns, _, _) in enumerate(items):
            for t, xyz, quat, cov in results:
                t.pub.publish(t.writer.serialize(stamp_ns, xyz[k], quat[k], cov[k]))
            self.stats.counts["published"] += 1

    def _publish_one(self, stamp_ns: int, q: np.ndarray, model: Any) -> None:
        """FK of one validated joint state (the lean one-configuration path of ``model.fk``) and publish it;
        a :class:`PpoeError` is counted as a bad message by the caller's guard."""
        ctx = self._live.update(stamp_ns * 1e-9, q) if self._live is not None else None
        for t in self.targets:
            T, cov_local = model.fk(q, self.reference, t.frame, order=self.order, context=ctx)
            t.pub.publish(t.writer.serialize(stamp_ns, T[:3, 3], lie.quat_from_matrix(T[:3, :3]),
                                             lie.cov_local_to_ros(T, cov_local)))
        self.stats.counts["published"] += 1

    def _temperature(self, msg: Temperature) -> None:
        """Latest ``temperature`` for a thermal_growth against temperature (subscribed only for such a model)."""
        if not np.isfinite(msg.temperature):
            raise ValueError(f"temperature {msg.temperature!r} is not finite")
        if self._live is not None:
            self._live.temperature = float(msg.temperature)

    def destroy_node(self) -> None:
        """Stop the worker thread, then destroy the node."""
        if self._worker is not None:
            self._worker.stop()
        super().destroy_node()


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``kinematics_node`` (``--ros-args`` accepted)."""
    from ppoe_core import aot
    from ppoe_ros.common.runner import run_node

    aot.load()  # the ahead-of-time kernels when `ppoe warmup` built them for this install: numba is not loaded
    return run_node(KinematicsNode, args, executor="events")


if __name__ == "__main__":
    sys.exit(main())
