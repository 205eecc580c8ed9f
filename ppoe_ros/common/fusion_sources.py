"""Sensor blocks of the fusion node (robot_localization style): their ROS side.

The rules are :mod:`ppoe_core.estimation.sources` (the keys of a block, their checks, how a message becomes a
measurement: frame checks, the at-rest gate, the noise choice), shared with ``ppoe evaluate``.  Here:
:func:`source_names` reads the ``sources`` override before the parameters are declared, :func:`source_specs`
declares every key of the named blocks (so a misspelled key is reported with the closest name like any other
parameter), and :class:`LiveSources` subscribes, hands each message's fields to the core rules and the resulting
:class:`~ppoe_core.estimation.corrections.Measurement` to the node's measurement hook.

A source whose link is not in the URDF is switched off with one error naming topic and link (the node keeps
running, ``/diagnostics`` says so); a message for a frame the URDF does not have (an IMU's ``header.frame_id``,
a tracker frame) is logged, counted as ``unknown_link`` and dropped.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import ParameterType
from sensor_msgs.msg import Imu

from ppoe_core.estimation.corrections import Measurement
from ppoe_core.estimation.pipeline import source_key
from ppoe_core.estimation.sources import (
    SOURCE_KEYS, SourceConfig, UnknownFrame, check_source_names, complete_source, imu_payload, point_payload,
    pose_payload,
)
from ppoe_ros.common.conversions import pose_cov_from_msg, stamp_to_ns
from ppoe_ros.common.diagnostics import NodeStats
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_length

__all__ = ["SOURCES_PARAM", "source_names", "source_specs", "LiveSources"]

_MESSAGE = {"point": PointStamped, "pose": PoseWithCovarianceStamped, "imu": Imu}
_ARRAY = {"double": ParameterType.PARAMETER_DOUBLE_ARRAY, "bool": ParameterType.PARAMETER_BOOL_ARRAY}

SOURCES_PARAM = ParamSpec("sources", [], "names of the sensor blocks (tracker points, 6D poses, accelerometers); "
                          "each name is a block of keys <name>.type, .topic, ... (docs/fusion_node.md)",
                          ptype=ParameterType.PARAMETER_STRING_ARRAY)


def source_names(node: Any) -> list[str]:
    """The ``sources`` the node was started with (read from its overrides before the parameters are declared, so
    that the blocks' keys are declared with the others)."""
    override = (getattr(node, "_parameter_overrides", {}) or {}).get("sources")
    names = list(override.value or []) if override is not None else []
    check_source_names(names, f"node {node.get_fully_qualified_name()}")
    return names


def _check(k: Any) -> Callable[[Any], str | None] | None:
    if k.items is not None:
        return check_length(*k.lengths)
    if k.choices:
        return lambda v: None if v in k.choices else f"must be one of {list(k.choices)}, got {v!r}"
    if k.required:
        return lambda v: None if v else "must not be empty"
    return None


def source_specs(names: Sequence[str]) -> tuple[ParamSpec, ...]:
    """The parameters of the blocks ``names`` (:data:`~ppoe_core.estimation.sources.SOURCE_KEYS`; meaning, unit and
    default of each also in config/nodes/fusion_node.yaml)."""
    return tuple(ParamSpec(f"{n}.{k.key}", k.default, k.description, unit=k.unit,
                           ptype=_ARRAY.get(k.items or ""), check=_check(k), min_value=k.low, max_value=k.high)
                 for n in names for k in SOURCE_KEYS)


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
        """Complete the sources from the model YAML and check them against the URDF
        (:func:`~ppoe_core.estimation.sources.complete_source`); a source that cannot work is switched off.  Returns
        one line per source that is off (naming topic and link)."""
        self.model = model
        problems = []
        for src in self.sources:
            src.off = complete_source(src, model)
            if src.off:
                problems.append(f"source '{src.name}' on {src.topic} is off: {src.off}")
        return problems

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
            if src.kind == "point":
                payload: Any = point_payload(src, self.model, frame_id, [msg.point.x, msg.point.y, msg.point.z],
                                             self.prefix)
            elif src.kind == "pose":
                T, cov_ros, _, _ = pose_cov_from_msg(msg)
                payload = pose_payload(src, self.model, frame_id, T, cov_ros, self.prefix)
            else:
                a = msg.linear_acceleration
                payload = imu_payload(src, self.model, frame_id, [a.x, a.y, a.z], msg.linear_acceleration_covariance,
                                      self.prefix)
        except UnknownFrame as exc:
            self.stats.bad(src.topic, str(exc), kind="unknown_link")
            return
        if isinstance(payload, str):
            self.stats.bad(src.topic, payload, kind="not_at_rest")
            return
        self.measure(Measurement(stamp_to_ns(msg.header.stamp) * 1e-9, source_key(src.topic, frame_id), payload))
