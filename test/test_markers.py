"""RViz covariance markers (ppoe_ros/common/markers.py): the message geometry, and the node through live topics."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from ros_helpers import NodeProcess, Probe, ros_env  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from ppoe_core import lie  # noqa: E402
from ppoe_core.lie.ellipsoid import sigma_scale  # noqa: E402
from ppoe_ros.common import ns_to_stamp, pose_cov_stamped_msg  # noqa: E402
from ppoe_ros.common.markers import MIN_SCALE, correction_marker, ellipsoid_marker  # noqa: E402

pytestmark = pytest.mark.ros


def _pose_msg(seed: int, frame: str = "base_link") -> tuple[PoseWithCovarianceStamped, np.ndarray]:
    rng = np.random.default_rng(seed)
    T = lie.exp(rng.normal(size=6) * [0.3, 0.3, 0.3, 1, 1, 1])
    A = rng.normal(size=(6, 6)) * 1e-3
    cov_ros = A @ A.T
    return pose_cov_stamped_msg(T, cov_ros, ns_to_stamp(1_500_000_000), frame), cov_ros


def marker_covariance(m: Marker, k: float) -> np.ndarray:
    """The position covariance a SPHERE marker draws: ``R diag((scale / 2k)^2) R^T`` from its pose and scale."""
    q = m.pose.orientation
    R = lie.matrix_from_quat(np.array([q.x, q.y, q.z, q.w]))
    s = np.array([m.scale.x, m.scale.y, m.scale.z]) / (2.0 * k)
    return R @ np.diag(s**2) @ R.T


def test_sphere_marker_draws_the_position_covariance() -> None:
    msg, cov_ros = _pose_msg(2)
    k = sigma_scale(0.95)
    m = ellipsoid_marker(msg, "raw", k, (1.0, 0.5, 0.0, 0.3))
    assert (m.type, m.action, m.ns, m.header.frame_id) == (Marker.SPHERE, Marker.ADD, "raw", "base_link")
    assert m.header.stamp == msg.header.stamp
    np.testing.assert_allclose(marker_covariance(m, k), cov_ros[:3, :3], rtol=1e-7, atol=1e-16)
    assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == (
        msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z)
    exact = pose_cov_stamped_msg(np.eye(4), np.zeros((6, 6)), ns_to_stamp(0), "base_link")
    z = ellipsoid_marker(exact, "raw", k, (1, 1, 1, 1))
    assert (z.scale.x, z.scale.y, z.scale.z) == (MIN_SCALE, MIN_SCALE, MIN_SCALE)


def test_correction_arrow_goes_from_raw_to_fused() -> None:
    raw, _ = _pose_msg(3)
    fused, _ = _pose_msg(4)
    m = correction_marker(raw, fused)
    assert m.type == Marker.ARROW and len(m.points) == 2
    assert m.points[0].x == raw.pose.pose.position.x and m.points[1].z == fused.pose.pose.position.z


def test_markers_node_publishes_raw_fused_and_correction(tmp_path: Path) -> None:
    """The standalone node in a namespace: one array per pose (rate-limited), geometry of each pose's covariance;
    a non-symmetric covariance is counted as bad and the node keeps running."""
    env = ros_env(tmp_path)
    cmd = [sys.executable, "-m", "ppoe_ros.common.markers", "--ros-args", "-r", "__ns:=/r1",
           "-p", "marker_probability:=0.99", "-p", "marker_rate:=1000.0"]
    with Probe(env) as probe, NodeProcess(cmd, env, tmp_path / "markers.log") as proc:
        arrays = probe.collect("/r1/ppoe/markers", MarkerArray)
        raw_pub = probe.publisher("/r1/ppoe/pose", PoseWithCovarianceStamped)
        fused_pub = probe.publisher("/r1/ppoe/fused_pose", PoseWithCovarianceStamped)
        probe.wait_for_subscribers(raw_pub, proc)
        probe.wait_for_subscribers(fused_pub, proc)
        raw, raw_cov = _pose_msg(5)
        raw_pub.publish(raw)
        probe.spin_until(lambda: len(arrays) >= 1, 20, proc, "the raw marker")
        fused, fused_cov = _pose_msg(6)
        fused_pub.publish(fused)
        probe.spin_until(lambda: len(arrays) >= 2, 20, proc, "the fused markers")
        bad, _ = _pose_msg(7)
        cov = np.array(bad.pose.covariance)
        cov[1] += 1.0  # not symmetric
        bad.pose.covariance = cov.tolist()
        raw_pub.publish(bad)
        probe.spin_for(1.0)
        raw_pub.publish(raw)
        probe.spin_until(lambda: len(arrays) >= 3, 20, proc, "markers after a bad message")
        # the node's log reaches its file late under load: wait for the line instead of reading once
        probe.spin_until(lambda: "bad message on ppoe/pose" in proc.output(), 20, proc, "the bad-message log line")
        log = proc.output()
    k = sigma_scale(0.99)
    (only_raw,) = arrays[0].markers
    np.testing.assert_allclose(marker_covariance(only_raw, k), raw_cov[:3, :3], rtol=1e-7, atol=1e-16)
    by_ns = {m.ns: m for m in arrays[1].markers}
    assert set(by_ns) == {"raw", "fused", "correction"}
    np.testing.assert_allclose(marker_covariance(by_ns["fused"], k), fused_cov[:3, :3], rtol=1e-7, atol=1e-16)
    assert "bad message on ppoe/pose" in log and "symmetric" in log
