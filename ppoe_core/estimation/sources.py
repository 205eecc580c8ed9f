"""Sensor blocks of the fusion node, in the style of robot_localization: tracker points, 6D poses, accelerometers
(docs/fusion_node.md, "Sources").  The rules live here, without ROS, so that the fusion node
(``ppoe_ros.common.fusion_sources``: declaration, subscriptions, message fields) and ``ppoe evaluate`` (a bag's
series) turn a message into the same measurement.

The node YAML lists the blocks by name in ``sources`` and gives each a block of keys (``<name>.<key>``)::

    sources: [tracker, hand_imu]
    tracker:
      type: point                  # point | pose | imu
      topic: ground_truth/point    # relative: follows the node's namespace
      link: ""                     # "" = the model YAML trackers entry of this topic
      ...

* :data:`SOURCE_KEYS`: every key of a block with its default, meaning and unit (the node declares them from here);
* :func:`parse_sources`: the blocks checked (:class:`SourceConfig`);
* :func:`complete_source`: ``link`` / ``xyz`` / ``sigma`` from the model YAML (``trackers``), the links checked
  against the URDF;
* :func:`point_payload`, :func:`pose_payload`, :func:`imu_payload`: one message's fields -> the payload of
  :mod:`ppoe_core.estimation.source_updater` (frame checks, the at-rest gate of an accelerometer, the noise choice).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.estimation.source_updater import (
    GravityMeasurement, PointMeasurement, PoseMeasurement, pose_from_xyz_rpy,
)
from ppoe_core.robot.tree import GRAVITY

__all__ = ["SOURCE_TYPES", "SourceKey", "SOURCE_KEYS", "SourceConfig", "UnknownFrame", "parse_sources",
           "check_source_names", "complete_source", "point_payload", "pose_payload", "imu_payload", "unprefixed"]

SOURCE_TYPES = ("point", "pose", "imu")
_COMPONENTS = {"point": 3, "pose": 6, "imu": 3}
_SIGMA_LENGTHS = {"point": (0, 1, 3), "pose": (0, 6), "imu": (0, 1, 3)}


@dataclass(frozen=True)
class SourceKey:
    """One key of a sensor block: name, default, meaning, unit; ``items`` the element type of a list key
    (``"double"`` / ``"bool"``, None for a scalar), ``lengths`` its allowed lengths, ``choices`` the allowed values,
    ``low`` / ``high`` the inclusive range of a number."""

    key: str
    default: Any
    description: str
    unit: str = ""
    items: str | None = None
    lengths: tuple[int, ...] = ()
    choices: tuple[str, ...] = ()
    low: float | None = None
    high: float | None = None
    required: bool = False


#: every key of a block (config/nodes/fusion_node.yaml documents the same)
SOURCE_KEYS: tuple[SourceKey, ...] = (
    SourceKey("type", "", "point (PointStamped of a reflector), pose (PoseWithCovarianceStamped of a link) or imu "
              "(sensor_msgs/Imu: gravity direction)", choices=SOURCE_TYPES),
    SourceKey("topic", "", "input topic (relative: follows the namespace)", required=True),
    SourceKey("link", "", "point: link carrying the reflector ('' = the model YAML trackers entry of this topic); "
              "pose: the link measured; imu: the expected header.frame_id ('' = any)"),
    SourceKey("xyz", [], "point: reflector in link; empty = model YAML trackers entry", "m", "double", (0, 3)),
    SourceKey("frame", "", "point/pose: expected header.frame_id; '' = any frame of the URDF"),
    SourceKey("sensor_pose", [], "point/pose: pose [x, y, z, roll, pitch, yaw] of 'frame' (not a URDF frame, e.g. a "
              "tracker) in base_frame; empty = 'frame' is a URDF frame", "m, rad", "double", (0, 6)),
    SourceKey("components", [], "which components are fused (point/imu: x y z; pose: x y z roll pitch yaw of the "
              "tangent); empty = all", "", "bool", (0, 3, 6)),
    SourceKey("sigma", [], "1-sigma noise: point 1 or 3 numbers [m] (empty = model YAML trackers), pose 6 [m, rad] "
              "(empty = message covariance), imu 1 or 3 [m/s^2] (empty = model YAML imus, else message covariance)",
              "", "double", (0, 1, 3, 6)),
    SourceKey("gate_probability", 0.0, "chi-square gate of this source; 0 = the node's gate_probability, 1 = no "
              "gating", low=0.0, high=1.0),
    SourceKey("up", [], "imu: up direction in base_frame; empty = [0, 0, 1]", "", "double", (0, 3)),
    SourceKey("rest_tolerance", 0.5, "imu: a message whose |acceleration| differs from g by more is skipped (the "
              "link accelerates; counted not_at_rest); 0 = off", "m/s^2", low=0.0, high=100.0),
)


@dataclass
class SourceConfig:
    """One sensor block, checked (:func:`parse_sources`); ``link``/``xyz``/``sigma`` may be completed from the model
    YAML by :func:`complete_source`."""

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


def _block(params: Mapping[str, Any], name: str, where: str) -> dict[str, Any]:
    """The keys of block ``name`` (defaults for missing ones), each checked against :data:`SOURCE_KEYS`."""
    out = {}
    for k in SOURCE_KEYS:
        v = params.get(f"{name}.{k.key}", k.default)
        bad = None
        if k.items is not None:
            if not isinstance(v, (list, tuple)) or len(v) not in k.lengths:
                bad = f"needs a list of {' or '.join(map(str, k.lengths))} values"
            elif k.items == "bool" and not all(isinstance(x, bool) for x in v):
                bad = "needs booleans"
            elif k.items == "double" and not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
                bad = "needs numbers"
        elif k.choices and v not in k.choices:
            bad = f"must be one of {list(k.choices)}"
        elif k.required and not v:
            bad = "must not be empty"
        elif k.low is not None and not (isinstance(v, (int, float)) and k.low <= v <= (k.high or math.inf)):
            bad = f"must be a number in [{k.low:g}, {k.high:g}]"
        if bad:
            raise ModelConfigError(f"{where}: parameter '{name}.{k.key}' = {v!r}: {bad}")
        out[k.key] = list(v) if k.items is not None else v
    return out


def check_source_names(names: Sequence[str], where: str) -> None:
    """The ``sources`` list: unique names of letters, digits and ``_`` (each names a block of keys).

    Raises
    ------
    ModelConfigError
        Naming ``where`` and the list.
    """
    bad = [n for n in names if not n or not str(n).replace("_", "").isalnum()]
    if bad or len(set(names)) != len(names):
        raise ModelConfigError(f"{where}: parameter 'sources' = {list(names)}: names must be unique, letters, digits "
                               "and '_'")


def parse_sources(params: Mapping[str, Any], names: Sequence[str], where: str) -> list[SourceConfig]:
    """The blocks ``names`` from ``params`` (``"<name>.<key>"`` -> value; missing keys take their defaults).

    Raises
    ------
    ModelConfigError
        A name that is not letters, digits and ``_`` (or repeats), a block whose keys do not fit its type; names
        ``where`` (the node or the parameter file), the block and the key.
    """
    check_source_names(names, where)
    out = []
    for n in names:
        b = _block(params, n, where)
        kind = b["type"]

        def fail(key: str, why: str, n: str = n, kind: str = kind) -> ModelConfigError:
            return ModelConfigError(f"{where}: parameter '{n}.{key}' ({kind} source): {why}")

        comp, sigma = b["components"], b["sigma"]
        if comp and (len(comp) != _COMPONENTS[kind] or not any(comp)):
            raise fail("components", f"needs {_COMPONENTS[kind]} booleans, at least one true, got {comp}")
        if len(sigma) not in _SIGMA_LENGTHS[kind] or any(not (math.isfinite(s) and s > 0) for s in sigma):
            raise fail("sigma", f"needs {' or '.join(map(str, _SIGMA_LENGTHS[kind]))} positive numbers, got {sigma}")
        if kind == "pose" and not b["link"]:
            raise fail("link", "the link whose pose is measured is required")
        pose = b["sensor_pose"]
        if pose and (kind == "imu" or not b["frame"]):
            raise fail("sensor_pose", "needs a point or pose source with 'frame' set (the frame it places)")
        up = np.asarray(b["up"] or [0.0, 0.0, 1.0], dtype=float)
        if not np.linalg.norm(up) > 0:
            raise fail("up", "must be a non-zero vector")
        gate = float(b["gate_probability"])
        if 0.0 < gate < 0.5:
            raise fail("gate_probability", f"must be 0 (node's), or in [0.5, 1], got {gate}")
        xyz = b["xyz"]
        out.append(SourceConfig(
            n, kind, b["topic"], b["link"], np.asarray(xyz, float) if xyz else None, b["frame"],
            pose_from_xyz_rpy(pose) if pose else None, np.asarray(comp, dtype=bool) if comp else None,
            np.asarray(sigma, dtype=float), gate or None, up / np.linalg.norm(up), float(b["rest_tolerance"])))
    return out


def complete_source(src: SourceConfig, model: Any) -> str:
    """Complete ``src`` from the model YAML (``trackers`` entry of its topic) and check its links against the URDF;
    returns why the source cannot work ("" when it can)."""
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


# ------------------------------------------------------------------------------------ messages
class UnknownFrame(MeasurementError):
    """A message names a frame the URDF does not have (the node counts it as ``unknown_link``)."""


def unprefixed(prefix: str, frame: str, topic: str) -> str:
    """The URDF name of a received ``header.frame_id``: ``frame`` without the node's ``frame_prefix``.

    Raises
    ------
    MeasurementError
        ``frame`` does not start with ``prefix`` (a message of another robot); names the topic.
    """
    if not prefix:
        return frame
    if not frame.startswith(prefix):
        raise MeasurementError(f"{topic}: header.frame_id '{frame}' lacks the frame_prefix '{prefix}' of this robot")
    return frame[len(prefix):]


def _frame(src: SourceConfig, model: Any, frame_id: str, prefix: str) -> str:
    """The URDF (or external) frame of a point/pose message; :class:`UnknownFrame` when the URDF lacks it."""
    if src.T_base_frame is not None:
        frame = frame_id
    else:
        frame = unprefixed(prefix, frame_id, src.topic)
        if frame not in model.robot.links:
            raise UnknownFrame(f"header.frame_id '{frame_id}': '{frame}' is not a frame of the URDF")
    if src.frame and frame != src.frame:
        raise MeasurementError(f"{src.topic}: header.frame_id '{frame_id}' is not the source's frame '{src.frame}'")
    return frame


def _diag_cov(sigma: np.ndarray, n: int) -> np.ndarray:
    """Diagonal covariance of 1 (isotropic) or ``n`` sigmas."""
    s = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)) if sigma.size == 1 else np.asarray(sigma, float)
    return np.diag(s**2)


def point_payload(src: SourceConfig, model: Any, frame_id: str, point: Any, prefix: str = "") -> PointMeasurement:
    """A ``PointStamped``'s ``header.frame_id`` and point -> :class:`PointMeasurement` (noise: the source's
    sigma, completed from the model YAML)."""
    frame = _frame(src, model, frame_id, prefix)
    p = np.asarray(point, dtype=float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise MeasurementError(f"{src.topic}: NaN/inf in the point")
    assert src.xyz is not None  # complete_source completed it, else the source is off
    return PointMeasurement(src.link, src.xyz, frame, p, _diag_cov(src.sigma, 3), src.T_base_frame, src.mask,
                            src.gate)


def pose_payload(src: SourceConfig, model: Any, frame_id: str, T: np.ndarray, cov_ros: np.ndarray,
                 prefix: str = "") -> PoseMeasurement:
    """A ``PoseWithCovarianceStamped``'s frame, pose and ROS-convention covariance -> :class:`PoseMeasurement`
    (noise: the source's sigma, else the message's covariance moved to the tangent space at the pose)."""
    frame = _frame(src, model, frame_id, prefix)
    if src.sigma.size:
        cov = _diag_cov(src.sigma, 6)
    else:
        if not np.any(cov_ros):
            raise MeasurementError(f"{src.topic}: the message's covariance is zero; set {src.name}.sigma")
        cov = lie.cov_ros_to_local(T, cov_ros)
    return PoseMeasurement(src.link, frame, T, cov, src.T_base_frame, src.mask, src.gate)


def imu_payload(src: SourceConfig, model: Any, frame_id: str, accel: Any, cov_msg: Any,
                prefix: str = "") -> GravityMeasurement | str:
    """An ``Imu``'s frame, ``linear_acceleration`` and its covariance (3, 3) -> :class:`GravityMeasurement`, or,
    for a link that is not at rest (``| |a| - g | > rest_tolerance``), the reason it is skipped (the caller counts
    ``not_at_rest``).  Noise: the source's sigma, else the model YAML ``imus`` entry of the link, else the
    message's covariance."""
    link = unprefixed(prefix, frame_id, src.topic)
    if link not in model.robot.links:
        raise UnknownFrame(f"IMU header.frame_id '{frame_id}': '{link}' is not a link of the URDF")
    if src.link and link != src.link:
        raise MeasurementError(f"{src.topic}: IMU header.frame_id '{frame_id}' is not the source's link '{src.link}'")
    a = np.asarray(accel, dtype=float).reshape(3)
    if not np.all(np.isfinite(a)):
        raise MeasurementError(f"{src.topic}: NaN/inf in linear_acceleration")
    norm = float(np.linalg.norm(a))
    if src.rest_tolerance > 0 and abs(norm - GRAVITY) > src.rest_tolerance:
        return (f"|acceleration| = {norm:.3f} m/s^2 differs from g by more than rest_tolerance "
                f"{src.rest_tolerance:g}: not at rest, skipped")
    imu = next((i for i in (getattr(model.config, "imus", {}) or {}).values() if i.link == link), None)
    if src.sigma.size:
        cov = _diag_cov(src.sigma, 3)
    elif imu is not None:
        cov = _diag_cov(np.array([imu.sigma]), 3)
    else:
        cov = np.asarray(cov_msg, dtype=float).reshape(3, 3)
        if cov[0, 0] < 0 or not np.any(cov):
            raise MeasurementError(f"{src.topic}: no linear_acceleration_covariance in the message and no sigma "
                                   f"({src.name}.sigma or the model YAML imus entry of '{link}')")
    return GravityMeasurement(link, a, cov, src.up, src.mask, src.gate)
