"""Sensor blocks of the fusion node, in the style of robot_localization: tracker points, 6D poses, accelerometers.

The node YAML lists the blocks by name in ``sources`` and gives each a block of keys (``<name>.<key>``)::

    sources: [tracker, hand_imu]
    tracker:
      type: point                  # point | pose | imu
      topic: ground_truth/point    # relative: follows the node's namespace
      link: ""                     # "" = the model YAML trackers entry of this topic
      ...

:func:`source_specs` declares the keys of every named block (so a misspelled key is reported with the closest
name like any other parameter), :func:`parse_sources` checks them, :class:`LiveSources` subscribes, checks the
links against the URDF when the model arrives (:meth:`LiveSources.set_model`) and turns each message into a
:class:`~ppoe_core.estimation.corrections.Measurement` with a payload of
:mod:`ppoe_core.estimation.source_updater`, handed to the node's measurement hook.

A source whose link is not in the URDF is switched off with one error naming topic and link (the node keeps
running, ``/diagnostics`` says so); a message for a frame the URDF does not have (an IMU's ``header.frame_id``,
a tracker frame) is logged, counted as ``unknown_link`` and dropped.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import ParameterType
from sensor_msgs.msg import Imu

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.estimation.corrections import Measurement
from ppoe_core.estimation.pipeline import source_key
from ppoe_core.estimation.source_updater import (
    GravityMeasurement,
    PointMeasurement,
    PoseMeasurement,
    pose_from_xyz_rpy,
)
from ppoe_core.robot.tree import GRAVITY
from ppoe_ros.common.conversions import pose_cov_from_msg, stamp_to_ns
from ppoe_ros.common.diagnostics import NodeStats
from ppoe_ros.common.frame_prefix import unprefixed
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_length, check_nonempty

__all__ = ["SOURCE_TYPES", "SOURCES_PARAM", "source_names", "source_specs", "SourceConfig", "parse_sources",
           "LiveSources"]

SOURCE_TYPES = ("point", "pose", "imu")
_MESSAGE = {"point": PointStamped, "pose": PoseWithCovarianceStamped, "imu": Imu}
_COMPONENTS = {"point": 3, "pose": 6, "imu": 3}
_SIGMA_LENGTHS = {"point": (0, 1, 3), "pose": (0, 6), "imu": (0, 1, 3)}
_DOUBLES = ParameterType.PARAMETER_DOUBLE_ARRAY

SOURCES_PARAM = ParamSpec("sources", [], "names of the sensor blocks (tracker points, 6D poses, accelerometers); "
                          "each name is a block of keys <name>.type, .topic, ... (docs/fusion_node.md)",
                          ptype=ParameterType.PARAMETER_STRING_ARRAY)


def source_names(node: Any) -> list[str]:
    """The ``sources`` the node was started with (read from its overrides before the parameters are declared, so
    that the blocks' keys are declared with the others)."""
    override = (getattr(node, "_parameter_overrides", {}) or {}).get("sources")
    names = list(override.value or []) if override is not None else []
    bad = [n for n in names if not n or not n.replace("_", "").isalnum()]
    if bad or len(set(names)) != len(names):
        raise ModelConfigError(f"node {node.get_fully_qualified_name()}: parameter 'sources' = {names}: names "
                               "must be unique, letters, digits and '_'")
    return names


def _choice(options: Sequence[str]) -> Callable[[Any], str | None]:
    return lambda v: None if v in options else f"must be one of {list(options)}, got {v!r}"


def source_specs(names: Sequence[str]) -> tuple[ParamSpec, ...]:
    """The parameters of the blocks ``names`` (meaning, unit and default of each: config/nodes/fusion_node.yaml)."""
    out: list[ParamSpec] = []
    for n in names:
        out += [
            ParamSpec(f"{n}.type", "", "point (PointStamped of a reflector), pose (PoseWithCovarianceStamped of a "
                      "link) or imu (sensor_msgs/Imu: gravity direction)", check=_choice(SOURCE_TYPES)),
            ParamSpec(f"{n}.topic", "", "input topic (relative: follows the namespace)", check=check_nonempty),
            ParamSpec(f"{n}.link", "", "point: link carrying the reflector ('' = the model YAML trackers entry of "
                      "this topic); pose: the link measured; imu: the expected header.frame_id ('' = any)"),
            ParamSpec(f"{n}.xyz", [], "point: reflector in link; empty = model YAML trackers entry", unit="m",
                      ptype=_DOUBLES, check=check_length(0, 3)),
            ParamSpec(f"{n}.frame", "", "point/pose: expected header.frame_id; '' = any frame of the URDF"),
            ParamSpec(f"{n}.sensor_pose", [], "point/pose: pose [x, y, z, roll, pitch, yaw] of 'frame' (not a URDF "
                      "frame, e.g. a tracker) in base_frame; empty = 'frame' is a URDF frame", unit="m, rad",
                      ptype=_DOUBLES, check=check_length(0, 6)),
            ParamSpec(f"{n}.components", [], "which components are fused (point/imu: x y z; pose: x y z roll pitch "
                      "yaw of the tangent); empty = all", ptype=ParameterType.PARAMETER_BOOL_ARRAY,
                      check=check_length(0, 3, 6)),
            ParamSpec(f"{n}.sigma", [], "1-sigma noise: point 1 or 3 numbers [m] (empty = model YAML trackers), pose "
                      "6 [m, rad] (empty = message covariance), imu 1 or 3 [m/s^2] (empty = model YAML imus, else "
                      "message covariance)", ptype=_DOUBLES, check=check_length(0, 1, 3, 6)),
            ParamSpec(f"{n}.gate_probability", 0.0, "chi-square gate of this source; 0 = the node's "
                      "gate_probability, 1 = no gating", min_value=0.0, max_value=1.0),
            ParamSpec(f"{n}.up", [], "imu: up direction in base_frame; empty = [0, 0, 1]", ptype=_DOUBLES,
                      check=check_length(0, 3)),
            ParamSpec(f"{n}.rest_tolerance", 0.5, "imu: a message whose |acceleration| differs from g by more is "
                      "skipped (the link accelerates; counted not_at_rest); 0 = off", unit="m/s^2",
                      min_value=0.0, max_value=100.0),
        ]
    return tuple(out)


@dataclass
class SourceConfig:
    """One sensor block, checked (:func:`parse_sources`); ``link``/``xyz``/``sigma`` may be completed from the model
    YAML by :meth:`LiveSources.set_model`."""

    name: str
    kind: str
    topic: str
    link: str
    xyz: np.ndarray | None
    frame: str
    T_base_frame: np.ndarray | None
    mask: np.ndarray | None
    sigma: np.ndarray
    gate: float | None
    up: np.ndarray
    rest_tolerance: float
    off: str = ""  # why the source is off ("" = on)


def parse_sources(params: Mapping[str, Any], names: Sequence[str], node_name: str) -> list[SourceConfig]:
    """The blocks ``names`` from the declared ``params``.

    Raises
    ------
    ModelConfigError
        A block whose keys do not fit its type; names node, block and key.
    """
    out = []
    for n in names:
        kind = params[f"{n}.type"]

        def fail(key: str, why: str, n: str = n, kind: str = kind) -> ModelConfigError:
            return ModelConfigError(f"node {node_name}: parameter '{n}.{key}' ({kind} source): {why}")

        comp, sigma = list(params[f"{n}.components"]), list(params[f"{n}.sigma"])
        if comp and (len(comp) != _COMPONENTS[kind] or not any(comp)):
            raise fail("components", f"needs {_COMPONENTS[kind]} booleans, at least one true, got {comp}")
        if len(sigma) not in _SIGMA_LENGTHS[kind] or any(not (math.isfinite(s) and s > 0) for s in sigma):
            raise fail("sigma", f"needs {' or '.join(map(str, _SIGMA_LENGTHS[kind]))} positive numbers, got {sigma}")
        if kind == "pose" and not params[f"{n}.link"]:
            raise fail("link", "the link whose pose is measured is required")
        pose = list(params[f"{n}.sensor_pose"])
        if pose and (kind == "imu" or not params[f"{n}.frame"]):
            raise fail("sensor_pose", "needs a point or pose source with 'frame' set (the frame it places)")
        up = np.asarray(list(params[f"{n}.up"]) or [0.0, 0.0, 1.0], dtype=float)
        if not np.linalg.norm(up) > 0:
            raise fail("up", "must be a non-zero vector")
        xyz = list(params[f"{n}.xyz"])
        gate = float(params[f"{n}.gate_probability"])
        if 0.0 < gate < 0.5:
            raise fail("gate_probability", f"must be 0 (node's), or in [0.5, 1], got {gate}")
        out.append(SourceConfig(
            n, kind, params[f"{n}.topic"], params[f"{n}.link"], np.asarray(xyz, float) if xyz else None,
            params[f"{n}.frame"], pose_from_xyz_rpy(pose) if pose else None,
            np.asarray(comp, dtype=bool) if comp else None, np.asarray(sigma, dtype=float), gate or None,
            up / np.linalg.norm(up), float(params[f"{n}.rest_tolerance"])))
    return out


class LiveSources:
    """Subscriptions of the sensor blocks and message -> :class:`Measurement` (module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
    sources : list of SourceConfig
    stats : NodeStats
        ``received`` per message; ``unknown_link``, ``not_at_rest`` and bad messages counted per topic.
    prefix : str
        The node's ``frame_prefix``.
    measure : callable
        The node's measurement hook, ``measure(Measurement)``.
    """

    def __init__(self, node: Any, sources: list[SourceConfig], stats: NodeStats, prefix: str,
                 measure: Callable[[Measurement], None]) -> None:
        self.node = node
        self.sources = sources
        self.stats = stats
        self.prefix = prefix
        self.measure = measure
        self.model: Any = None
        for key in ("unknown_link", "not_at_rest"):
            stats.counts.setdefault(key, 0)
        stats.warn_keys.add("unknown_link")

    def subscribe(self, qos: Any) -> None:
        """One guarded, loss-counted subscription per source (topic resolved in the node's namespace)."""
        for src in self.sources:
            src.topic = self.node.resolve_topic_name(src.topic)
            counted_subscription(self.node, self.stats, _MESSAGE[src.kind], src.topic,
                                 lambda msg, src=src: self._on_message(src, msg), qos)

    def set_model(self, model: Any) -> list[str]:
        """Complete the sources from the model YAML (trackers, imus) and check their links against the URDF; a source
        that cannot work is switched off.  Returns one line per source that is off (naming topic and link)."""
        self.model = model
        problems = []
        for src in self.sources:
            src.off = self._complete(src, model)
            if src.off:
                problems.append(f"source '{src.name}' on {src.topic} is off: {src.off}")
        return problems

    def _complete(self, src: SourceConfig, model: Any) -> str:
        cfg, links = model.config, model.robot.links
        if src.kind == "point" and (not src.link or src.xyz is None or src.sigma.size == 0):
            entry = next((t for t in getattr(cfg, "trackers", ()) or ()
                          if ("/" + src.topic.strip("/")).endswith("/" + t.topic.strip("/"))), None)
            if entry is None:
                return "no link/xyz/sigma given and no model YAML trackers entry for this topic"
            src.link = src.link or entry.link
            src.xyz = entry.xyz if src.xyz is None else src.xyz
            src.sigma = src.sigma if src.sigma.size else np.array([entry.sigma])
        if src.link and src.link not in links:
            return f"link '{src.link}' is not a link of the URDF ({model.robot.source})"
        if src.frame and src.T_base_frame is None and src.frame not in links:
            return f"frame '{src.frame}' is not a frame of the URDF: give sensor_pose for an external frame"
        return ""

    # ------------------------------------------------------------------ messages
    def _on_message(self, src: SourceConfig, msg: Any) -> None:
        self.stats.counts["received"] += 1
        if self.model is None:
            self.stats.bad(src.topic, "no robot model yet (waiting for robot_description)", kind="dropped_no_model")
            return
        if src.off:
            self.stats.bad(src.topic, f"source '{src.name}' is off: {src.off}", kind="unknown_link")
            return
        frame_id = msg.header.frame_id
        try:
            payload = getattr(self, f"_{src.kind}")(src, msg)
        except _UnknownLink as exc:
            self.stats.bad(src.topic, str(exc), kind="unknown_link")
            return
        if payload is None:
            return
        self.measure(Measurement(stamp_to_ns(msg.header.stamp) * 1e-9, source_key(src.topic, frame_id), payload))

    def _frame(self, src: SourceConfig, frame_id: str) -> str:
        """The URDF (or external) frame of a point/pose message; :class:`_UnknownLink` when the URDF lacks it."""
        if src.T_base_frame is not None:
            frame = frame_id
        else:
            frame = unprefixed(self.prefix, frame_id, src.topic)
            if frame not in self.model.robot.links:
                raise _UnknownLink(f"header.frame_id '{frame_id}': '{frame}' is not a frame of the URDF")
        if src.frame and frame != src.frame:
            raise MeasurementError(f"{src.topic}: header.frame_id '{frame_id}' is not the source's frame "
                                   f"'{src.frame}'")
        return frame

    def _point(self, src: SourceConfig, msg: PointStamped) -> PointMeasurement:
        frame = self._frame(src, msg.header.frame_id)
        p = np.array([msg.point.x, msg.point.y, msg.point.z], dtype=float)
        if not np.all(np.isfinite(p)):
            raise MeasurementError(f"{src.topic}: NaN/inf in the point")
        assert src.xyz is not None  # set_model completed it, else the source is off
        return PointMeasurement(src.link, src.xyz, frame, p, _diag_cov(src.sigma, 3), src.T_base_frame, src.mask,
                                src.gate)

    def _pose(self, src: SourceConfig, msg: PoseWithCovarianceStamped) -> PoseMeasurement:
        frame = self._frame(src, msg.header.frame_id)
        T, cov_ros, _, _ = pose_cov_from_msg(msg)
        if src.sigma.size:
            cov = _diag_cov(src.sigma, 6)
        else:
            if not np.any(cov_ros):
                raise MeasurementError(f"{src.topic}: the message's covariance is zero; set {src.name}.sigma")
            cov = lie.cov_ros_to_local(T, cov_ros)
        return PoseMeasurement(src.link, frame, T, cov, src.T_base_frame, src.mask, src.gate)

    def _imu(self, src: SourceConfig, msg: Imu) -> GravityMeasurement | None:
        frame_id = msg.header.frame_id
        link = unprefixed(self.prefix, frame_id, src.topic)
        if link not in self.model.robot.links:
            raise _UnknownLink(f"IMU header.frame_id '{frame_id}': '{link}' is not a link of the URDF")
        if src.link and link != src.link:
            raise MeasurementError(f"{src.topic}: IMU header.frame_id '{frame_id}' is not the source's link "
                                   f"'{src.link}'")
        a = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z], float)
        if not np.all(np.isfinite(a)):
            raise MeasurementError(f"{src.topic}: NaN/inf in linear_acceleration")
        norm = float(np.linalg.norm(a))
        if src.rest_tolerance > 0 and abs(norm - GRAVITY) > src.rest_tolerance:
            self.stats.bad(src.topic, f"|acceleration| = {norm:.3f} m/s^2 differs from g by more than "
                                      f"rest_tolerance {src.rest_tolerance:g}: not at rest, skipped",
                           kind="not_at_rest")
            return None
        imu = next((i for i in (getattr(self.model.config, "imus", {}) or {}).values() if i.link == link), None)
        if src.sigma.size or imu is not None:
            cov = _diag_cov(src.sigma if src.sigma.size else np.array([imu.sigma]), 3)
        else:
            cov = np.asarray(msg.linear_acceleration_covariance, dtype=float).reshape(3, 3)
            if cov[0, 0] < 0 or not np.any(cov):
                raise MeasurementError(f"{src.topic}: no linear_acceleration_covariance in the message and no "
                                       f"sigma ({src.name}.sigma or the model YAML imus entry of '{link}')")
        return GravityMeasurement(link, a, cov, src.up, src.mask, src.gate)


class _UnknownLink(MeasurementError):
    """A message names a frame the URDF does not have (counted as ``unknown_link``)."""


def _diag_cov(sigma: np.ndarray, n: int) -> np.ndarray:
    """Diagonal covariance of 1 (isotropic) or ``n`` sigmas."""
    s = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)) if sigma.size == 1 else np.asarray(sigma, float)
    return np.diag(s**2)
