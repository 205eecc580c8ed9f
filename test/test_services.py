"""Services of the nodes through live topics: fusion ``~/reset`` and ``~/set_pose``, online ``~/save_model``."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from ros_helpers import REPO, NodeProcess, Probe, ros_env, write_params_file  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from ppoe_core import lie  # noqa: E402
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402
from ppoe_ros.common import matrix_from_pose_msg, ns_to_stamp, pose_cov_stamped_msg  # noqa: E402

pytestmark = pytest.mark.ros

ROBOTS = REPO / "config" / "robots"


def _call(probe: Probe, client, proc: NodeProcess, resend_after: float | None = None):
    return probe.call(client, Trigger.Request(), proc, resend_after=resend_after)


def test_fusion_reset_and_set_pose(tmp_path: Path) -> None:
    """set_pose pins the fused pose to the given pose (its covariance far below the prior's) and the correction is
    carried to later priors; reset forgets it (fused = prior again) and says what it forgot; a set_pose in the
    wrong frame is named and the node keeps running."""
    model = PPOEModel.from_files(ROBOTS / "rover.urdf", ROBOTS / "rover_model.yaml")
    q = {n: 0.2 for n in model.joint_names}
    T_prior, P_prior = model.fk(q, "base_link", "tool_link")
    cov_ros = lie.cov_local_to_ros(T_prior, P_prior)
    T_set = T_prior @ lie.exp(np.array([0.004, -0.003, 0.002, 0.0, 0.0, 0.002]))
    cov_set = lie.cov_local_to_ros(T_set, np.diag([1e-10] * 3 + [1e-10] * 3))
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(ROBOTS / "rover_model.yaml"), "robot_description": (ROBOTS / "rover.urdf").read_text(),
        "buffer_duration": 2.0, "log_throttle": 0.0, "publish_tf": False})
    with Probe(env) as probe, NodeProcess.node("fusion_node", env, tmp_path, params_file=pf) as proc:
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        pub_prior = probe.publisher("/ppoe/pose", PoseWithCovarianceStamped)
        pub_js = probe.publisher("/joint_states", JointState)
        pub_set = probe.publisher("/fusion_node/set_pose", PoseWithCovarianceStamped)
        reset = probe.node.create_client(Trigger, "/fusion_node/reset")
        for pub in (pub_prior, pub_js, pub_set):
            probe.wait_for_subscribers(pub, proc)
        t0 = probe.node.get_clock().now().nanoseconds

        def priors(ks: range) -> None:
            for k in ks:
                stamp = ns_to_stamp(t0 + k * 20_000_000)
                pub_js.publish(JointState(header=Header(stamp=stamp), name=list(q), position=list(q.values())))
                pub_prior.publish(pose_cov_stamped_msg(T_prior, cov_ros, stamp, "base_link"))
                probe.spin_for(0.01)
            probe.spin_until(lambda: len(fused) >= n_before + len(ks), 20, proc, f"fused poses of priors {ks}")

        n_before = 0
        priors(range(10))
        np.testing.assert_allclose(matrix_from_pose_msg(fused[-1].pose.pose), T_prior, atol=1e-9)
        pub_set.publish(pose_cov_stamped_msg(T_set, cov_set, ns_to_stamp(t0 + 9 * 20_000_000), "base_link"))
        probe.spin_for(0.5)
        n_before = len(fused)
        priors(range(10, 20))
        d_prior = np.linalg.norm(T_prior[:3, 3] - T_set[:3, 3])
        d_fused = np.linalg.norm(matrix_from_pose_msg(fused[-1].pose.pose)[:3, 3] - T_set[:3, 3])
        assert d_fused < 0.02 * d_prior, (d_fused, d_prior)
        answer = _call(probe, reset, proc)
        assert answer.success and "1 carried corrections" in answer.message, answer.message
        n_before = len(fused)
        priors(range(20, 30))
        np.testing.assert_allclose(matrix_from_pose_msg(fused[-1].pose.pose), T_prior, atol=1e-9)
        pub_set.publish(pose_cov_stamped_msg(T_set, cov_set, ns_to_stamp(t0 + 29 * 20_000_000), "odom"))
        probe.spin_until(lambda: "set_pose frame 'odom' is not base_frame 'base_link'" in proc.output(), 20, proc,
                         "the bad set_pose named")
        assert proc.alive()


def test_online_save_model(tmp_path: Path) -> None:
    """~/save_model writes the estimate to online_model_out now; without online_model_out it says why not."""
    model = REPO / "bags" / "online" / "arm7_drift_model.yaml"
    out = tmp_path / "saved.yaml"
    env = ros_env(tmp_path)
    params = {"model_file": str(model), "robot_description": (ROBOTS / "arm7.urdf").read_text(),
              "online_effects": ["base_tilt:base_link"], "online_process_noise": [1.0e-5],
              "online_initial_sigma": [0.005]}
    with_out = write_params_file(tmp_path / "a.yaml", {**params, "online_model_out": str(out)})
    without = write_params_file(tmp_path / "b.yaml", params)
    cmd = [sys.executable, "-m", "ppoe_ros.common.online_effects", "--ros-args", "-r", "__ns:=/r1"]
    with Probe(env) as probe, NodeProcess([*cmd, "--params-file", str(with_out)], env, tmp_path / "a.log") as a, \
            NodeProcess([*cmd, "-r", "__node:=other", "--params-file", str(without)], env, tmp_path / "b.log") as b:
        saved = _call(probe, probe.node.create_client(Trigger, "/r1/online_effects_node/save_model"), a, 10.0)
        refused = _call(probe, probe.node.create_client(Trigger, "/r1/other/save_model"), b, 10.0)
    assert saved.success and saved.message == f"wrote {out}", saved.message
    assert "written by the online effects of /r1/online_effects_node" in out.read_text()
    assert "base_tilt" in out.read_text()
    assert not refused.success and "online_model_out is empty" in refused.message
