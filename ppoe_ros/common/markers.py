"""RViz markers of the pose covariances: the raw (kinematics prior) and the fused pose's position ellipsoids.

``visualization_msgs/MarkerArray`` on ``markers_topic`` (default ``ppoe/markers``, relative: it follows the
namespace): a ``SPHERE`` per pose scaled to its confidence ellipsoid (geometry from
:func:`ppoe_core.lie.ellipsoid.position_ellipsoid`: axes = eigenvectors of the position covariance in the
parent frame, scale = ``2 k sqrt(lambda)`` with ``k`` from ``marker_probability``), namespace ``raw`` (orange)
and ``fused`` (blue), plus an ``ARROW`` (namespace ``correction``) from the raw to the fused position.  Each
marker carries the header (frame, stamp) of its pose; the markers of a new pose replace the old ones (same
namespace and id).  At most ``marker_rate`` arrays per second are published (RViz needs no 1 kHz).

:class:`CovarianceMarkers` attaches to any node (its own subscriptions); ``python -m ppoe_ros.common.markers``
(console script ``ppoe_markers``) runs it alone beside the kinematics / fusion nodes; config/rviz/ppoe.rviz
shows the array.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from rclpy.node import Node
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from ppoe_core.lie.ellipsoid import position_ellipsoid, sigma_scale
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats, guarded
from ppoe_ros.common.params import ParamSpec, check_nonempty, declare_parameters
from ppoe_ros.common.qos import reliable_qos
from ppoe_ros.common.runner import run_node

__all__ = ["MARKER_PARAMS", "RAW_RGBA", "FUSED_RGBA", "MIN_SCALE", "ellipsoid_marker", "correction_marker",
           "CovarianceMarkers", "MarkersNode", "main"]

#: colours (r, g, b, alpha) of the raw (kinematics prior) and the fused ellipsoid
RAW_RGBA = (1.0, 0.55, 0.0, 0.35)
FUSED_RGBA = (0.1, 0.55, 1.0, 0.55)
_ARROW_RGBA = (0.9, 0.9, 0.9, 0.9)

#: smallest marker scale [m]: RViz refuses a zero scale (an exact pose has a zero covariance)
MIN_SCALE = 1e-5

#: Parameters of the markers (a node that has them publishes the array; documented in the console script's node)
MARKER_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("markers_topic", "ppoe/markers", "visualization_msgs/MarkerArray out: the position ellipsoids"),
    ParamSpec("raw_topic", "ppoe/pose", "raw pose (PoseWithCovarianceStamped): the kinematics prior",
              check=check_nonempty),
    ParamSpec("fused_topic", "ppoe/fused_pose", "fused pose (PoseWithCovarianceStamped); empty = raw only"),
    ParamSpec("marker_probability", 0.95, "probability inside the drawn ellipsoid (3-D Gaussian)",
              min_value=1e-3, max_value=0.999999),
    ParamSpec("marker_rate", 30.0, "at most this many MarkerArray messages per second", unit="Hz",
              min_value=0.1, max_value=10000.0),
)


def _color(rgba: tuple[float, float, float, float]) -> ColorRGBA:
    return ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))


def ellipsoid_marker(msg: PoseWithCovarianceStamped, ns: str, k: float,
                     rgba: tuple[float, float, float, float], marker_id: int = 0) -> Marker:
    """A ``SPHERE`` marker of the ``k``-sigma position ellipsoid of ``msg`` (covariance in the ROS convention:
    the position block is in the axes of ``header.frame_id``).

    Raises
    ------
    CovarianceError
        The position covariance is not symmetric positive semi-definite.
    """
    p = msg.pose.pose.position
    P = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3]
    e = position_ellipsoid(np.array([p.x, p.y, p.z]), P, k)
    m = Marker(header=msg.header, ns=ns, id=int(marker_id), type=Marker.SPHERE, action=Marker.ADD)
    m.pose.position = p
    q = e.quat_xyzw
    m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = (float(v) for v in q)
    m.scale.x, m.scale.y, m.scale.z = (float(max(s, MIN_SCALE)) for s in e.scale)
    m.color = _color(rgba)
    return m


def correction_marker(raw: PoseWithCovarianceStamped, fused: PoseWithCovarianceStamped, ns: str = "correction",
                      marker_id: int = 0) -> Marker:
    """An ``ARROW`` from the raw to the fused position (shaft diameter 10 % of its length, at least 0.1 mm)."""
    a, b = raw.pose.pose.position, fused.pose.pose.position
    length = float(np.linalg.norm([b.x - a.x, b.y - a.y, b.z - a.z]))
    m = Marker(header=fused.header, ns=ns, id=int(marker_id), type=Marker.ARROW, action=Marker.ADD)
    m.pose.orientation.w = 1.0
    m.points = [Point(x=a.x, y=a.y, z=a.z), Point(x=b.x, y=b.y, z=b.z)]
    shaft = max(0.1 * length, 1e-4)
    m.scale.x, m.scale.y, m.scale.z = shaft, 2.0 * shaft, 0.3 * max(length, 1e-4)
    m.color = _color(_ARROW_RGBA)
    return m


class CovarianceMarkers:
    """Subscribes ``raw_topic`` / ``fused_topic`` of ``node`` and publishes the MarkerArray (see the module)."""

    def __init__(self, node: Node, params: dict[str, Any], stats: NodeStats) -> None:
        self.node, self.stats = node, stats
        self.k = sigma_scale(float(params["marker_probability"]))
        self.period = 1.0 / float(params["marker_rate"])
        self.pub = node.create_publisher(MarkerArray, params["markers_topic"], reliable_qos(10))
        self.raw: PoseWithCovarianceStamped | None = None
        self.fused: PoseWithCovarianceStamped | None = None
        self._last = -np.inf
        node.create_subscription(PoseWithCovarianceStamped, params["raw_topic"],
                                 guarded(stats, params["raw_topic"])(self._on_raw), reliable_qos(100))
        if params["fused_topic"]:
            node.create_subscription(PoseWithCovarianceStamped, params["fused_topic"],
                                     guarded(stats, params["fused_topic"])(self._on_fused), reliable_qos(100))

    def _on_raw(self, msg: PoseWithCovarianceStamped) -> None:
        self.stats.inc("received")
        self.raw = msg
        self.publish()

    def _on_fused(self, msg: PoseWithCovarianceStamped) -> None:
        self.stats.inc("received")
        self.fused = msg
        self.publish(force=True)

    def markers(self) -> MarkerArray:
        """The array of the newest raw and fused pose (and the correction between them)."""
        out = MarkerArray()
        if self.raw is not None:
            out.markers.append(ellipsoid_marker(self.raw, "raw", self.k, RAW_RGBA))
        if self.fused is not None:
            out.markers.append(ellipsoid_marker(self.fused, "fused", self.k, FUSED_RGBA))
            if self.raw is not None and self.raw.header.frame_id == self.fused.header.frame_id:
                out.markers.append(correction_marker(self.raw, self.fused))
        return out

    def publish(self, force: bool = False) -> None:
        """Publish :meth:`markers` unless one went out less than ``1 / marker_rate`` ago (``force``: always)."""
        now = time.monotonic()
        if not force and now - self._last < self.period:
            return
        self._last = now
        self.pub.publish(self.markers())
        self.stats.inc("published")


_NODE_PARAMS: tuple[ParamSpec, ...] = MARKER_PARAMS + (
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
)


class MarkersNode(Node):
    """The markers alone in a node (``ppoe_markers``): raw + fused pose -> MarkerArray."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("ppoe_markers", **kwargs)
        p = declare_parameters(self, _NODE_PARAMS)
        self.stats = NodeStats(self, ("received", "published", "bad"))
        self.markers = CovarianceMarkers(self, p, self.stats)
        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])


def main(args: Any = None) -> int:
    """``ppoe_markers --ros-args [-r __ns:=/robot1] [-p fused_topic:=...]`` (``python -m ppoe_ros.common.markers``)."""
    return run_node(MarkersNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
