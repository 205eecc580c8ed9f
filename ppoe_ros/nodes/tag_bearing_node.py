"""Tag bearing node: camera images -> tag centre and corner observations.

Subscriptions
    ``image_topic`` (default ``camera/image_raw/compressed``, ``sensor_msgs/CompressedImage``
    when ``compressed`` is true, else ``sensor_msgs/Image``; sensor-data QoS).
    ``camera_info_topic`` (default ``camera/camera_info``, ``sensor_msgs/CameraInfo``): ``K``
    and ``D`` (``plumb_bob`` or ``rational_polynomial``) of the latest valid message are used.
Publications
    ``tag_bearing/observations`` (``sensor_msgs/PointCloud2``), one message per image, as in
    the topic table of ``docs/ARCHITECTURE.md``: header = image header (stamp, camera optical
    frame); one point per observed tag point with FLOAT64 fields ``id``, ``corner`` (0 =
    centre, 1..4 = corners in the order of :mod:`ppoe_core.sensing.tags`), ``u``, ``v`` (raw distorted
    pixels) and ``x``, ``y`` (undistorted normalised coordinates ``X/Z``, ``Y/Z`` from ``K``,
    ``D``).  An image without configured tags gives a message with zero points.
    ``tag_bearing/debug_image`` (``sensor_msgs/Image``, bgr8) with the detections drawn,
    when ``publish_debug_image`` is true.
    Topics are relative (they follow the node's namespace, :mod:`ppoe_ros.common.frame_prefix`); the
    observations keep the image's ``header.frame_id`` (the camera driver's, prefixed by it if at all).
    ``/diagnostics``: counters ``received``, ``published``, ``bad``, ``dropped``,
    ``detections``, ``camera_info``.

The rows come from :func:`ppoe_core.sensing.tag_rows.observe_tags` (ROS-free, the same
function ``ppoe evaluate`` runs on a bag's images): the centre is the intersection of the
diagonals of the four *undistorted* corners (the exact image of the tag centre for the pinhole
model), distorted back for ``u``, ``v``.

Bad input never stops the node: an empty or undecodable image, an unsupported encoding, a
``camera_info`` with a zero / non-finite ``K`` or an unsupported distortion model is logged
(throttled), counted as ``bad`` and dropped; an image before any valid ``camera_info`` is
counted as ``dropped``.  A bad ``camera_info`` does not replace the last good one.

Parameters: :data:`PARAMS`, documented in ``config/nodes/tag_bearing_node.yaml``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.io.images import DEFAULT_MAX_PIXELS, camera_from_info, check_image_size, decode_image, draw_detections
from ppoe_core.sensing import tags as tagmod
from ppoe_core.sensing.tag_rows import DEFAULT_CORNER_REFINEMENT, OBSERVATION_FIELDS, observe_tags
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats, guarded
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_nonempty, declare_parameters, mapping_get
from ppoe_ros.common.qos import reliable_qos, sensor_qos
from ppoe_ros.common.frame_prefix import resolve_topics
from ppoe_ros.common.tag_cloud import cloud_from_observations

__all__ = ["TagBearingNode", "PARAMS", "OBSERVATION_FIELDS", "main"]


_REFINE = ("edges", "subpix", "contour", "apriltag", "none")

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("image_topic", "camera/image_raw/compressed", "image input topic", check=check_nonempty),
    ParamSpec("compressed", True, "true: image_topic is sensor_msgs/CompressedImage (png/jpeg); "
              "false: sensor_msgs/Image"),
    ParamSpec("camera_info_topic", "camera/camera_info", "sensor_msgs/CameraInfo of the camera", check=check_nonempty),
    ParamSpec("model_file", "", "model YAML whose 'tags' section gives the family and ids; empty = none"),
    ParamSpec("dictionary", "", "tag family: tag36h11, tag36h10, tag25h9, tag16h5, aruco_original, "
              "4x4_50 ... 7x7_1000; empty = model YAML tags.family, else tag36h11"),
    ParamSpec("tag_ids", [], "tag ids to publish; empty = the model YAML's tag ids, else every detected tag",
              ptype=ParameterType.PARAMETER_INTEGER_ARRAY),
    ParamSpec("corner_refinement", DEFAULT_CORNER_REFINEMENT, "corner refinement: edges (subpix, then the outer "
              "edges fitted), subpix, contour, apriltag or none",
              check=lambda v: None if v in _REFINE else f"must be one of {_REFINE}, got {v!r}"),
    ParamSpec("observations_topic", "tag_bearing/observations", "output PointCloud2 topic", check=check_nonempty),
    ParamSpec("publish_debug_image", False, "publish an image with the detections drawn"),
    ParamSpec("debug_image_topic", "tag_bearing/debug_image", "debug image topic (sensor_msgs/Image bgr8)",
              check=check_nonempty),
    ParamSpec("max_image_pixels", DEFAULT_MAX_PIXELS, "images with more pixels (read from the PNG/JPEG header before "
              "decoding) are refused", min_value=1),
    ParamSpec("qos_depth", 10, "history depth of the image and camera_info subscriptions", min_value=1,
              max_value=1000),
    ParamSpec("input_timeout", 5.0, "/diagnostics says WARN when no image arrived for this long; 0 = off",
              unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
    ParamSpec("log_throttle", 2.0, "at most one log line per kind of bad message per this period", unit="s",
              min_value=0.0),
)

# ---------------------------------------------------------------------------- node


class TagBearingNode(Node):
    """Detects tags in each image and publishes their centre and corner observations."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("tag_bearing_node", **kwargs)
        p = declare_parameters(self, PARAMS)
        resolve_topics(self, p, ("image_topic", "camera_info_topic", "observations_topic", "debug_image_topic"))
        self.params = p
        self.stats = NodeStats(self, ("received", "published", "bad", "dropped", "detections", "camera_info"),
                               p["log_throttle"])
        from ppoe_core.robot.yaml_io import read_yaml_mapping

        tags_cfg = mapping_get(read_yaml_mapping(p["model_file"], "model file"), "tags", default={}) or {}
        self.dictionary = p["dictionary"] or str(tags_cfg.get("family") or "tag36h11")
        try:
            tagmod.aruco_dictionary(self.dictionary)
        except MeasurementError as exc:
            raise ModelConfigError(f"node {self.get_name()}: parameter 'dictionary': {exc}") from None
        self.tag_ids = [int(i) for i in p["tag_ids"]]
        if not self.tag_ids:
            try:
                self.tag_ids = [int(item["id"]) for item in tags_cfg.get("items") or []]
            except (KeyError, TypeError, ValueError) as exc:
                raise ModelConfigError(f"model file {p['model_file']}: tags.items: every item needs an integer "
                                       f"'id' ({exc})") from None
        self.K: np.ndarray | None = None
        self.D: np.ndarray | None = None
        self.info_frame = ""
        self.info_size: tuple[int, int] | None = None
        self.pub = self.create_publisher(PointCloud2, p["observations_topic"], reliable_qos(50))
        self.debug_pub = (self.create_publisher(Image, p["debug_image_topic"], reliable_qos(5))
                          if p["publish_debug_image"] else None)
        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])
        self.diagnostics.watch_input(p["image_topic"], "received", p["input_timeout"])
        qos = sensor_qos(p["qos_depth"])
        it, ct = p["image_topic"], p["camera_info_topic"]
        self.create_subscription(CameraInfo, ct, guarded(self.stats, ct)(self._camera_info), qos)
        counted_subscription(self, self.stats, CompressedImage if p["compressed"] else Image, it, self._image, qos)
        self.get_logger().info(
            f"detecting {self.dictionary} tags {self.tag_ids or 'all'} in {it} "
            f"({'compressed' if p['compressed'] else 'raw'}), publishing {p['observations_topic']}")

    def _camera_info(self, msg: CameraInfo) -> None:
        self.K, self.D = camera_from_info(msg)  # raises (counted as bad) before replacing
        self.info_frame = msg.header.frame_id
        self.info_size = (int(msg.width), int(msg.height))
        self.stats.counts["camera_info"] += 1

    def _image(self, msg: Any) -> None:
        st = self.stats
        st.counts["received"] += 1
        if self.K is None or self.D is None:
            st.bad(self.params["image_topic"], "no valid camera_info yet: image dropped", kind="dropped")
            return
        image = decode_image(msg, self.params["compressed"], self.params["max_image_pixels"])
        check_image_size(image, self.info_size)
        rows, dets = observe_tags(image, self.K, self.D, self.dictionary, self.tag_ids,
                                  self.params["corner_refinement"])
        header = msg.header
        if not header.frame_id:
            header.frame_id = self.info_frame
        self.pub.publish(cloud_from_observations(rows, header))
        st.counts["published"] += 1
        st.counts["detections"] += len(dets)
        if self.debug_pub is not None:
            img = draw_detections(image, rows, dets)
            out = Image()
            out.header = header
            out.height, out.width = img.shape[:2]
            out.encoding = "bgr8"
            out.is_bigendian = 0
            out.step = 3 * img.shape[1]
            out.data = img.tobytes()
            self.debug_pub.publish(out)


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``tag_bearing_node`` (``--ros-args`` accepted)."""
    from ppoe_ros.common.runner import run_node

    return run_node(TagBearingNode, args, executor="events", kernels=("tag_bearing_node",))


if __name__ == "__main__":
    sys.exit(main())
