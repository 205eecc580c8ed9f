"""The standalone online effects node's measurement subscriptions (the fusion node feeds the hook from its own):
tag observations with the focal lengths of ``camera_info``, contact planes, and the ``sources`` blocks, each handed
to :meth:`~ppoe_ros.common.online_effects.OnlineEffectsHook.measure` as the fusion node would hand it its
:class:`~ppoe_core.estimation.corrections.Measurement`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from sensor_msgs.msg import CameraInfo, PointCloud2

from ppoe_core import lie
from ppoe_core.estimation.pipeline import ContactMeasurement, Measurement, TagMeasurement, source_key
from ppoe_core.estimation.sources import parse_sources
from ppoe_ros.common.conversions import pose_cov_from_msg, stamp_to_ns
from ppoe_ros.common.diagnostics import NodeStats
from ppoe_ros.common.fusion_sources import LiveSources
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.qos import reliable_qos, sensor_qos
from ppoe_ros.common.tag_cloud import observations_from_cloud

__all__ = ["OnlineSubscriptions", "subscribe_measurements"]


class OnlineSubscriptions:
    """Tag observations, camera_info, contact planes and ``sources`` of the standalone node -> the hook."""

    def __init__(self, node: Any, p: Mapping[str, Any], names: list[str], stats: NodeStats, hook: Any) -> None:
        self.node, self.p, self.stats, self.hook = node, p, stats, hook
        self.focal: dict[str, tuple[float, float]] = {}
        self.obs_topic = node.resolve_topic_name(p["observations_topic"]) if p["observations_topic"] else ""
        self.contact_topic = node.resolve_topic_name(p["contact_topic"]) if p["contact_topic"] else ""
        qos = reliable_qos(1000)
        if self.obs_topic:
            counted_subscription(node, stats, PointCloud2, self.obs_topic, self._observations, qos)
        if p["camera_info_topic"]:
            counted_subscription(node, stats, CameraInfo, p["camera_info_topic"], self._camera_info, sensor_qos(100))
        if self.contact_topic:
            counted_subscription(node, stats, PoseWithCovarianceStamped, self.contact_topic, self._contact, qos)
        self.sources = LiveSources(node, parse_sources(p, names, f"node {node.get_fully_qualified_name()}"),
                                   stats, "", hook.measure)
        self.sources.subscribe(qos)

    def set_model(self, model: Any) -> None:
        """Complete and check the sources against the model (a source that cannot work is off, logged)."""
        for line in self.sources.set_model(model):
            self.node.get_logger().error(f"{line} (the node keeps running)")

    def _camera_info(self, msg: CameraInfo) -> None:
        K = np.asarray(msg.k, dtype=float).reshape(3, 3)
        self.focal[msg.header.frame_id] = (float(K[0, 0]), float(K[1, 1]))
        self.hook.camera_info(msg.header.frame_id, K, np.asarray(msg.d, dtype=float))

    def _observations(self, msg: PointCloud2) -> None:
        d = observations_from_cloud(msg)
        if d["id"].size == 0:
            return
        frame = msg.header.frame_id
        fx, fy = self.focal.get(frame, (None, None))
        payload = TagMeasurement(frame, d["id"].astype(int), d["corner"].astype(int), np.column_stack([d["x"], d["y"]]),
                                 np.column_stack([d["u"], d["v"]]), fx, fy)
        self.hook.measure(Measurement(stamp_to_ns(msg.header.stamp) * 1e-9, source_key(self.obs_topic, frame),
                                      payload))

    def _contact(self, msg: PoseWithCovarianceStamped) -> None:
        T, cov_ros, stamp_ns, frame = pose_cov_from_msg(msg)
        cov = lie.check_covariance(lie.cov_ros_to_local(T, cov_ros), name=f"{self.contact_topic} covariance", size=6)
        self.hook.measure(Measurement(stamp_ns * 1e-9, source_key(self.contact_topic, frame),
                                      ContactMeasurement(frame, T, cov)))


def subscribe_measurements(node: Any, p: Mapping[str, Any], names: list[str], stats: NodeStats,
                           hook: Any) -> OnlineSubscriptions:
    """:class:`OnlineSubscriptions` of ``node``."""
    return OnlineSubscriptions(node, p, names, stats, hook)
