"""Fusion node through live topics: prior + simulated tag observations -> fused pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo, JointState, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from ppoe_core import PPOEModel, lie  # noqa: E402
from ppoe_core import measurements as mm  # noqa: E402
from ppoe_ros.ros_common import matrix_from_pose_msg, ns_to_stamp, pose_cov_stamped_msg  # noqa: E402
from ppoe_ros.tag_bearing_node import cloud_from_observations  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config"
ROVER_Q = {"pan_joint": -0.378, "tilt_joint": 1.477, "arm_joint_1": -0.247, "arm_joint_2": 1.532,
           "arm_joint_3": 0.302, "arm_joint_4": -0.302, "arm_joint_5": -0.991, "arm_joint_6": 1.294}
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])


def _observation_rows(model, T_base_tool_true, rng, pixel_sigma=0.5):
    """[id, corner, u, v, x, y] of the tags the mast camera sees (no distortion, 0.5 px noise)."""
    T_cam_tool = lie.inverse(model.fk_mean(ROVER_Q, "base_link", "camera_optical_frame")) @ T_base_tool_true
    rows = []
    for tid, item in model.config.tags.by_id().items():
        T_tool_tag = model.fk_mean(ROVER_Q, "tool_link", item.link) @ item.T_link_tag
        P = mm.tag_points(item.size, T_tool_tag) @ T_cam_tool[:3, :3].T + T_cam_tool[:3, 3]
        if np.any(P[:, 2] < 0.1) or (T_cam_tool @ T_tool_tag)[:3, 2] @ P[0] > 0:
            continue
        uv = P[:, :2] / P[:, 2:] * 600.0 + [320.0, 240.0] + rng.normal(size=(5, 2)) * pixel_sigma
        xy = (uv - [320.0, 240.0]) / 600.0
        rows += [[tid, c, *uv[c], *xy[c]] for c in range(5)]
    assert rows
    return np.array(rows)


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_fusion_node_live_corrects_prior_drops_stale_and_survives_bad_input(tmp_path):
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file

    model = PPOEModel.from_files(CONFIG / "rover.urdf", CONFIG / "rover_model.yaml")
    T_prior, P_prior = model.fk(ROVER_Q, "base_link", "tool_link")
    cov_ros = lie.cov_local_to_ros(T_prior, P_prior)
    rng = np.random.default_rng(2024)
    T_true = model.sample(ROVER_Q, "base_link", "tool_link", n=1, rng=rng)[0]
    err_prior = np.linalg.norm(T_prior[:3, 3] - T_true[:3, 3])
    assert err_prior > 0.01  # the seed gives a kinematics error worth correcting
    rows = _observation_rows(model, T_true, rng)

    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(CONFIG / "rover_model.yaml"),
        "robot_description": (CONFIG / "rover.urdf").read_text(),
        "diagnostics_period": 0.2, "log_throttle": 0.0, "buffer_duration": 1.0,
    })
    names = list(ROVER_Q)
    with Probe(env) as probe, NodeProcess.node("fusion_node", env, tmp_path, params_file=pf) as proc:
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        pub_prior = probe.publisher("/ppoe/pose", PoseWithCovarianceStamped)
        pub_js = probe.publisher("/joint_states", JointState)
        pub_obs = probe.publisher("/tag_bearing/observations", PointCloud2)
        pub_info = probe.publisher("/camera/camera_info", CameraInfo)
        for pub in (pub_prior, pub_js, pub_obs, pub_info):
            probe.wait_for_subscribers(pub, proc)
        probe.spin_for(0.5)

        def counts():
            return {kv.key: kv.value for kv in diags[-1].status[0].values} if diags else {}

        t0 = probe.node.get_clock().now().nanoseconds
        dt = 20_000_000  # 50 Hz

        def send_prior(k, T=T_prior, cov=cov_ros):
            stamp = ns_to_stamp(t0 + k * dt)
            pub_js.publish(JointState(header=Header(stamp=stamp), name=names, position=list(ROVER_Q.values())))
            pub_prior.publish(pose_cov_stamped_msg(T, cov, stamp, "base_link"))

        pub_info.publish(CameraInfo(header=Header(frame_id="camera_optical_frame"), k=K.ravel().tolist(),
                                    d=[0.0] * 5, distortion_model="plumb_bob", width=640, height=480))
        for k in range(25):
            send_prior(k)
            probe.spin_for(0.01)
        probe.spin_until(lambda: len(fused) >= 25, 20, proc, "25 fused poses (no correction yet)")
        # before any measurement the fused pose is the prior
        np.testing.assert_allclose(matrix_from_pose_msg(fused[-1].pose.pose), T_prior, atol=1e-9)

        # tag observation at prior 12.5 (interpolated), a stale one 5 s old, a bad one
        hdr = Header(frame_id="camera_optical_frame", stamp=ns_to_stamp(t0 + 12 * dt + dt // 2))
        pub_obs.publish(cloud_from_observations(rows, hdr))
        stale = Header(frame_id="camera_optical_frame", stamp=ns_to_stamp(t0 - 5_000_000_000))
        pub_obs.publish(cloud_from_observations(rows, stale))
        unknown = rows.copy()
        unknown[:, 0] += 50
        pub_obs.publish(cloud_from_observations(unknown, hdr))
        probe.spin_until(lambda: counts().get("accepted") == "1" and counts().get("dropped_stale") == "1"
                         and counts().get("bad") == "1", 20, proc, "accepted 1, stale 1, bad 1")
        # a prior with NaN: bad, and the node keeps publishing
        bad_T = T_prior.copy()
        bad_T[0, 3] = np.nan
        pub_prior.publish(pose_cov_stamped_msg(bad_T, cov_ros, ns_to_stamp(t0 + 25 * dt), "base_link"))
        n_before = len(fused)
        for k in range(26, 36):
            send_prior(k)
            probe.spin_for(0.01)
        probe.spin_until(lambda: len(fused) >= n_before + 10 and counts().get("bad") == "2", 20, proc,
                         "fused poses after the update")
        assert proc.alive()
        log = proc.output()

    last = fused[-1]
    T_last = matrix_from_pose_msg(last.pose.pose)
    err_fused = np.linalg.norm(T_last[:3, 3] - T_true[:3, 3])
    assert err_fused < 0.3 * err_prior, (err_fused, err_prior)
    cov_last = np.array(last.pose.covariance).reshape(6, 6)
    assert np.trace(cov_last[:3, :3]) < 0.2 * np.trace(cov_ros[:3, :3])
    assert last.header.frame_id == "base_link"
    c = {kv.key: kv.value for kv in diags[-1].status[0].values}
    assert c["dropped"] == "1" and c["rejected"] == "0"
    assert "stale" in log and "no point of a tag configured" in log
    print(f"fusion node: prior position error {err_prior * 1000:.1f} mm, fused {err_fused * 1000:.1f} mm")
