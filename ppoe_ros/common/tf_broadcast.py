"""TF output of the nodes: ``/tf`` and ``/tf_static`` (``tf2_msgs/msg/TFMessage``, docs/conventions.md sec. 4).

Published as tf2_ros' broadcasters do (no tf2_ros needed): ``/tf`` reliable, volatile, keep last 100;
``/tf_static`` reliable, transient local, keep last 1, every static transform of the node in one message
(a late subscriber gets them all).

* :class:`FusionTf`: the fusion node's corrected tool frame on ``/tf`` (parent = base frame, child =
  ``tf_child_frame``, default ``<tool>_corrected``) at every fused pose, and the calibrated camera frames
  on ``/tf_static`` (:func:`~ppoe_core.model.tf_frames.calibrated_camera_frames`).
* :class:`KinematicsTf`: the kinematics node's model frames like robot_state_publisher
  (:class:`~ppoe_core.model.tf_frames.JointFrames`).

A child frame that is a URDF link is refused with an error naming the frame and the parameter; that
frame's TF is off, the node keeps running, and ``/diagnostics`` says so.  Without ``tf2_msgs`` (a pip
install where ``scripts/build_tf2_msgs.py`` was not run) TF is off with one log line saying how to build it.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ppoe_core import lie
from ppoe_core.io.cdr import tf_message
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats
from ppoe_core.model.tf_frames import JointFrames, TfFrame, calibrated_camera_frames, urdf_collision

__all__ = [
    "TF_TOPIC", "TF_STATIC_TOPIC", "TF2_MSGS_HINT", "tf_message_class", "transform_msg", "tf_message_cdr",
    "OneFrameTfCdr", "TfBroadcaster", "FusionTf", "KinematicsTf",
]

TF_TOPIC = "/tf"
#: ``header.stamp`` (int32 sec, uint32 nanosec)
_STAMP = struct.Struct("<iI")
TF_STATIC_TOPIC = "/tf_static"

#: the log line when TF is asked for but tf2_msgs does not import
TF2_MSGS_HINT = ("tf2_msgs is not importable: /tf and /tf_static are off. With a pip install, build it into the "
                 "venv once: `.venv/bin/python scripts/build_tf2_msgs.py` (needs cmake, a C/C++ compiler and the "
                 "Python headers; README, section TF); with ROS 2 Jazzy from apt: source /opt/ros/jazzy/setup.bash")

#: tf2_ros' DynamicBroadcasterQoS
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
#: tf2_ros' StaticBroadcasterQoS
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


def tf_message_class() -> Any:
    """``tf2_msgs.msg.TFMessage``, or None when tf2_msgs does not import."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


def transform_msg(frame: TfFrame, stamp: TimeMsg) -> TransformStamped:
    """``TransformStamped``: ``frame.child`` in ``frame.parent`` (``header.frame_id`` = parent) at ``stamp``."""
    T = np.asarray(frame.T_parent_child, dtype=float)
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame.parent
    msg.child_frame_id = frame.child
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    rot.x, rot.y, rot.z, rot.w = (float(v) for v in lie.quat_from_matrix(T[:3, :3]))
    return msg


def tf_message_cdr(frames: Sequence[TfFrame], stamp_ns: int) -> bytes:
    """``tf2_msgs/TFMessage`` of ``frames``, all at ``stamp_ns``, as CDR bytes (:func:`ppoe_core.io.cdr.tf_message`,
    what rclpy's ``serialize_message`` gives; ``test/test_tf.py`` checks it): the per-joint-state path of the
    kinematics node builds no typed message."""
    if len(frames) == 1:  # the fusion node's corrected tool, at every prior: no stacking
        T1 = np.asarray(frames[0].T_parent_child, dtype=float)
        poses = np.concatenate([T1[:3, 3], lie.quat_from_matrix(T1[:3, :3])])[None]
    else:
        T = np.stack([f.T_parent_child for f in frames]) if frames else np.zeros((0, 4, 4))
        poses = np.concatenate([T[:, :3, 3], lie.quat_from_matrix(T[:, :3, :3])], axis=1)
    return tf_message([(f.parent, f.child, p) for f, p in zip(frames, poses)], stamp_ns)


class OneFrameTfCdr:
    """:func:`tf_message_cdr` of one frame with fixed names (the fusion node's corrected tool at every prior): the
    message written once, then only its stamp and its 7 doubles (translation, rotation x y z w: the message's last
    56 bytes) rewritten; the same bytes (``test/test_tf.py``)."""

    def __init__(self, parent: str, child: str) -> None:
        self._buf = bytearray(tf_message([(parent, child, np.zeros(7))], 0))
        self._pose = np.frombuffer(self._buf, dtype="<f8", count=7, offset=len(self._buf) - 56)

    def serialize(self, pose: np.ndarray, stamp_ns: int) -> bytes:
        """The message bytes at ``stamp_ns`` [ns]: ``pose`` (7,) = position x y z, quaternion x y z w."""
        _STAMP.pack_into(self._buf, 8, *divmod(int(stamp_ns), 1_000_000_000))  # after the sequence's length
        self._pose[:] = pose
        return bytes(self._buf)


class TfBroadcaster:
    """The ``/tf`` and ``/tf_static`` publishers of a node (tf2_ros' QoS, see the module docstring).

    Build it with :meth:`create`, which gives None (and logs :data:`TF2_MSGS_HINT`) without tf2_msgs.
    """

    def __init__(self, node: Node, msg_class: Any, prefix: str = "") -> None:
        self.node = node
        self.msg_class = msg_class
        self.prefix = prefix  # frame_prefix, prepended to every parent and child (ppoe_ros.common.frame_prefix)
        self.pub = node.create_publisher(msg_class, TF_TOPIC, TF_QOS)
        self.static_pub = node.create_publisher(msg_class, TF_STATIC_TOPIC, TF_STATIC_QOS)
        self.static: list[TransformStamped] = []

    @classmethod
    def create(cls, node: Node, diagnostics: DiagnosticsPublisher | None = None,
               prefix: str = "") -> TfBroadcaster | None:
        """The broadcaster (``prefix``: the node's ``frame_prefix``); None with :data:`TF2_MSGS_HINT` logged (and on
        ``/diagnostics``) without tf2_msgs."""
        msg_class = tf_message_class()
        if msg_class is None:
            node.get_logger().warning(TF2_MSGS_HINT)
            if diagnostics is not None:
                diagnostics.set_problem("tf", "TF off: tf2_msgs not importable (build it: scripts/build_tf2_msgs.py)")
            return None
        return cls(node, msg_class, prefix)

    def _prefixed(self, frames: Iterable[TfFrame]) -> list[TfFrame]:
        p = self.prefix
        return [TfFrame(p + f.parent, p + f.child, f.T_parent_child) for f in frames]

    def send(self, frames: Sequence[TfFrame], stamp_ns: int) -> None:
        """Publish ``frames`` on ``/tf``, all at ``stamp_ns`` [ns], in one message (serialised here)."""
        self.pub.publish(tf_message_cdr(self._prefixed(frames) if self.prefix else frames, stamp_ns))

    def set_static(self, frames: Iterable[TfFrame]) -> None:
        """Replace the node's static transforms by ``frames`` (stamped now) and publish them all on ``/tf_static``
        (nothing while there are none)."""
        stamp = self.node.get_clock().now().to_msg()
        static = [transform_msg(f, stamp) for f in self._prefixed(frames)]
        if not static and not self.static:
            return
        self.static = static
        self.static_pub.publish(self.msg_class(transforms=self.static))


class FusionTf:
    """TF of the fusion node (module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
    params : mapping
        The node's parameters ``publish_tf``, ``tf_child_frame``, ``tf_camera_suffix``, ``frame_prefix``.
    diagnostics : DiagnosticsPublisher
        Where a frame that is off is reported (value ``tf``, level WARN).
    """

    def __init__(self, node: Node, params: Mapping[str, Any], diagnostics: DiagnosticsPublisher) -> None:
        self.node = node
        self.diagnostics = diagnostics
        self.child_param = str(params["tf_child_frame"])
        self.camera_suffix = str(params["tf_camera_suffix"])
        prefix = str(params.get("frame_prefix", ""))
        self.broadcaster = TfBroadcaster.create(node, diagnostics, prefix) if params["publish_tf"] else None
        self.base = ""
        self.child: str | None = None  # None: no /tf for the corrected tool
        self._writer: OneFrameTfCdr | None = None

    def set_model(self, model: Any, base: str, tool: str) -> None:
        """Check the child frames against ``model``'s URDF and publish the calibrated cameras on ``/tf_static``."""
        if self.broadcaster is None:
            return
        log = self.node.get_logger()
        child = self.child_param or f"{tool}_corrected"
        problems = []
        why = urdf_collision(model.robot, child)
        if why:
            problems.append(f"parameter tf_child_frame = '{child}': {why}; /tf of the corrected tool is off")
            log.error(f"{problems[-1]} (the node keeps running; set tf_child_frame to a name that is not a URDF "
                      f"link, e.g. the default '{tool}_corrected')")
        self.base, self.child = base, None if why else child
        p = self.broadcaster.prefix
        self._writer = None if self.child is None else OneFrameTfCdr(p + base, p + self.child)
        cameras, notes = calibrated_camera_frames(model, self.camera_suffix)
        for note in notes:
            log.warning(note)
        problems += notes
        self.broadcaster.set_static(cameras)
        self.diagnostics.set_problem("tf", "; ".join(problems) if problems else None)
        p = self.broadcaster.prefix
        log.info("TF: " + (", ".join(
            ([f"{p}{base} -> {p}{child} on {TF_TOPIC} (corrected tool)"] if self.child else [])
            + [f"{p}{c.parent} -> {p}{c.child} on {TF_STATIC_TOPIC} (calibrated camera)" for c in cameras]) or "none"))

    def publish(self, T_base_tool: np.ndarray, stamp_ns: int) -> None:
        """The corrected tool frame on ``/tf`` at ``stamp_ns`` [ns] (the fused pose's), unless it is off."""
        if self._writer is not None:
            T = np.asarray(T_base_tool, dtype=float)
            self.publish_pose(np.concatenate([T[:3, 3], lie.quat_from_matrix(T[:3, :3])]), stamp_ns)

    def publish_pose(self, pose: np.ndarray, stamp_ns: int) -> None:
        """:meth:`publish` of the pose as ``pose`` (7,): position x y z, quaternion x y z w
        (``lie.quat_from_matrix``'s)."""
        if self._writer is not None and self.broadcaster is not None:
            self.broadcaster.pub.publish(self._writer.serialize(pose, stamp_ns))


class KinematicsTf:
    """TF of the kinematics node: the model's frames like robot_state_publisher (module docstring).

    Parameters
    ----------
    broadcaster : TfBroadcaster
    stats : NodeStats
        An error while computing or publishing TF is counted (``errors``) and logged; the pose output goes on.
    """

    def __init__(self, broadcaster: TfBroadcaster, stats: NodeStats) -> None:
        self.broadcaster = broadcaster
        self.stats = stats
        self.frames: JointFrames | None = None

    @classmethod
    def create(cls, node: Node, stats: NodeStats, diagnostics: DiagnosticsPublisher,
               prefix: str = "") -> KinematicsTf | None:
        """None (logged, on ``/diagnostics``) when tf2_msgs is missing; ``prefix``: the node's ``frame_prefix``."""
        broadcaster = TfBroadcaster.create(node, diagnostics, prefix)
        return None if broadcaster is None else cls(broadcaster, stats)

    def set_model(self, model: Any) -> None:
        """New model: its fixed joints on ``/tf_static`` (once), its movable joints from now on."""
        self.frames = JointFrames(model)
        static = self.frames.static_frames()
        self.broadcaster.set_static(static)
        n_dyn = len(self.frames.dynamic_joints)
        self.broadcaster.node.get_logger().info(
            f"TF: {len(self.frames.movable)} movable joints on {TF_TOPIC} at each joint state, {len(static)} fixed "
            f"joints on {TF_STATIC_TOPIC}" + (f"; {n_dyn} joints moved by configuration-dependent effects on "
                                               f"{TF_TOPIC} once every joint has a value" if n_dyn else ""))

    def publish(self, stamp_ns: int, names: Sequence[str], positions: Sequence[float]) -> None:
        """The transforms one joint state changes, on ``/tf`` at its stamp."""
        if self.frames is None:
            return
        try:
            frames = self.frames.frames(names, positions, stamp_ns)
            if frames:
                self.broadcaster.send(frames, stamp_ns)
        except Exception as exc:  # noqa: BLE001 - TF must not stop the pose output
            self.stats.error(TF_TOPIC, exc)
