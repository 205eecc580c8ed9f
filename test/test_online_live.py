"""Online effects live through topics: ``ppoe play`` of a drift bag into the online effects hook (run alone as
``python -m ppoe_ros.common.online_effects``); the published estimates equal ``ppoe evaluate --online``'s, the
model YAML written back at shutdown holds the last estimate, and a bad tracker or IMU message is counted while the
node keeps running."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
import yaml
from conftest import REPO
from ros_helpers import random_domain_id

pytest.importorskip("rclpy")

from ppoe_core.analysis.evaluate.online import evaluate_online, load_online_config  # noqa: E402
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402
from ppoe_core.sim.simulate import simulate  # noqa: E402

ONLINE = REPO / "bags" / "online"
MODEL = ONLINE / "arm7_drift_model.yaml"


def test_live_estimates_equal_offline(tmp_path):
    from geometry_msgs.msg import PointStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from sensor_msgs.msg import Imu
    from std_msgs.msg import Float64MultiArray

    from ppoe_ros.common.online_effects import estimates_from_msg

    raw = yaml.safe_load((ONLINE / "tilt.yaml").read_text())
    raw["robot"] = {"urdf": str(REPO / "config" / "robots" / "arm7.urdf"), "model": str(MODEL)}
    raw["trajectory"]["random_stops"]["count"] = 40
    raw["truth"]["effects"][0]["parameters"]["tilt_x"]["step"]["at"] = 16.0
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    bag = tmp_path / "tilt"
    simulate(tmp_path / "s.yaml", bag)
    cfg, jump = load_online_config(ONLINE / "online_effects.yaml")
    offline = evaluate_online(bag, MODEL, cfg, jump)
    model_out = tmp_path / "online_model.yaml"
    env = ros_env(tmp_path)
    # the URDF as a parameter: the model exists before the first message (from /robot_description it would come
    # after the player started, and points before it are dropped, counted as online_no_model)
    pf = write_params_file(tmp_path / "online.yaml", {
        "model_file": str(MODEL), "robot_description": (REPO / "config" / "robots" / "arm7.urdf").read_text(),
        "online_effects": ["base_tilt:base_link", "gravity_compliance:joint_2"],
        "online_process_noise": [1.0e-5, 1.0e-6], "online_initial_sigma": [0.005, 5.0e-4],
        "online_model_out": str(model_out)})
    cmd = [sys.executable, "-m", "ppoe_ros.common.online_effects", "--ros-args", "--params-file", str(pf)]
    node = NodeProcess(cmd, env, tmp_path / "online.log")
    try:
        with Probe(env) as probe:
            got = probe.collect("/ppoe/online_effects", Float64MultiArray)
            probe.wait_for_publishers("/ppoe/online_effects", node, timeout=60)
            play = NodeProcess.ppoe(["play", str(bag), "--rate", "4", "--wait-for-subscribers", "30", "--topics",
                                     "/joint_states", "/ground_truth/point"], env, tmp_path,
                                    "play")
            assert play.wait(timeout=120) == 0, play.output()[-2000:]
            probe.spin_until(lambda: len(got) >= len(offline.stamps), 60, node, "all estimates")
            # bad input: a tracker frame the model has no registration for -> counted, the node keeps running
            pub = probe.publisher("/ground_truth/point", PointStamped)
            probe.wait_for_subscribers(pub, node)
            bad = PointStamped()
            bad.header.frame_id = "laser"
            bad.header.stamp.sec = int(offline.stamps[-1])
            pub.publish(bad)
            imu_pub = probe.publisher("/imu/forearm", Imu)
            probe.wait_for_subscribers(imu_pub, node)
            bad_imu = Imu()
            bad_imu.header.frame_id = "gripper_link"
            bad_imu.header.stamp = bad.header.stamp
            imu_pub.publish(bad_imu)
            deadline = time.monotonic() + 20
            for text in ("no tracker_registration effect for tracker frame 'laser'",
                         "header.frame_id 'gripper_link' is not the IMU's link 'arm_link_4'"):
                while text not in node.output():
                    assert time.monotonic() < deadline, node.output()[-3000:]
                    probe.spin_for(0.2)
            assert node.alive()
        node.stop(timeout=10)  # SIGINT: the node writes online_model_out on its way down
    finally:
        node.stop()
    assert len(got) == len(offline.stamps)
    for k, msg in enumerate(got):
        stamp, labels, theta, P = estimates_from_msg(msg)
        assert labels == offline.labels
        assert stamp == pytest.approx(offline.stamps[k], abs=1e-6)
        np.testing.assert_allclose(theta, offline.theta[k], rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(np.sqrt(np.diag(P)), offline.sigma[k], rtol=1e-6)
    # the live tool pose: the same core function of the live estimate (the newest one before each ground truth)
    # gives the offline "online" tool error
    from ppoe_core.estimation.online_effects import OnlineEffects, parse_online_config
    from ppoe_core.io.bagio import read_bag

    model = PPOEModel.from_files(REPO / "config" / "robots" / "arm7.urdf", MODEL)
    filt = OnlineEffects(model, parse_online_config(cfg, model), jump)
    live = [estimates_from_msg(m) for m in got]
    data = read_bag(bag, load_images=False)
    js, gt = data.joint_states, data.ground_truth_pose
    err = []
    for t, T_gt in zip(gt.stamps, gt.T):
        before = [e for e in live if e[0] < t - 1e-9]
        if before:
            filt.theta, filt.P = before[-1][2], before[-1][3]
        q = js.as_dict(int(np.searchsorted(js.stamps, t, side="right")) - 1)
        err.append(np.linalg.norm(filt.tool_pose(q, "base_link", "tool0")[0][:3, 3] - T_gt[:3, 3]))
    np.testing.assert_allclose(err, offline.position_error["online"], rtol=1e-6, atol=1e-9)
    # write-back at shutdown: the model YAML with the last estimate, loadable as a model
    written = PPOEModel.from_files(REPO / "config" / "robots" / "arm7.urdf", model_out)
    tilt = next(e for e in written.effects if e.name == "base_tilt")
    np.testing.assert_allclose(tilt.params, offline.theta[-1][:2], rtol=1e-6)
    assert yaml.safe_load(model_out.read_text())["effects"][-1]["ci"]["compliance"] > 0


def test_correct_prior_moves_the_static_pose_to_the_estimate():
    """The fusion node's call: a static-model prior becomes the online pose (mean and added covariance)."""
    import rclpy
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import ns_to_stamp
    from ppoe_ros.common.online_effects import OnlineEffectsNode

    urdf = (REPO / "config" / "robots" / "arm7.urdf").read_text()
    rclpy.init(domain_id=random_domain_id())
    try:
        node = OnlineEffectsNode(parameter_overrides=[Parameter("model_file", value=str(MODEL)),
                                                      Parameter("robot_description", value=urdf)])
        hook = node.hook
        q = {"joint_1": 0.3, "joint_2": 0.6, "joint_3": -0.2, "joint_4": -1.2, "joint_5": 0.4, "joint_6": 0.9,
             "joint_7": 0.1, "finger_left_joint": 0.02}
        T0, C0 = np.eye(4), np.eye(6) * 1e-8
        assert hook.correct_prior(5, T0, C0, "base_link", "tool0")[0] is T0  # no joint state yet: unchanged
        msg = JointState()
        msg.header.stamp = ns_to_stamp(1_000_000_000)
        msg.name, msg.position = list(q), list(q.values())
        hook._joint_state(msg)
        filt = hook.filter
        filt.theta = filt.theta + np.array([0.004, -0.002, 1e-4])
        T_static, C_static = filt.static_model.fk(q, "base_link", "tool0")
        T, C = hook.correct_prior(1_000_000_000, T_static, C_static, "base_link", "tool0")
        T_on, C_on = filt.tool_pose(q, "base_link", "tool0")
        np.testing.assert_allclose(T, T_on, atol=1e-12)
        np.testing.assert_allclose(C, C_on, rtol=1e-9, atol=1e-15)
        assert np.linalg.norm(T[:3, 3] - T_static[:3, 3]) > 1e-3
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_fusion_node_moves_its_priors_to_the_online_estimate(tmp_path):
    """The fusion node with ``online_enable``: ``ppoe play`` of a drift bag feeds the hook inside the node; a prior of
    the static model published afterwards comes out as the online tool pose of the last published estimate."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from std_msgs.msg import Float64MultiArray

    from ppoe_core import lie
    from ppoe_core.estimation.online_effects import OnlineEffects, parse_online_config
    from ppoe_core.io.bagio import read_bag
    from ppoe_ros.common import matrix_from_pose_msg, ns_to_stamp, pose_cov_stamped_msg
    from ppoe_ros.common.online_effects import estimates_from_msg

    raw = yaml.safe_load((ONLINE / "tilt.yaml").read_text())
    raw["robot"] = {"urdf": str(REPO / "config" / "robots" / "arm7.urdf"), "model": str(MODEL)}
    raw["trajectory"]["random_stops"]["count"] = 12
    raw["truth"]["effects"][0]["parameters"]["tilt_x"]["step"]["at"] = 5.0
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    bag = tmp_path / "tilt"
    simulate(tmp_path / "s.yaml", bag)
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(MODEL), "robot_description": (REPO / "config" / "robots" / "arm7.urdf").read_text(),
        "observations_topic": "", "contact_topic": "", "online_enable": True,
        "online_effects": ["base_tilt:base_link"], "online_process_noise": [1.0e-5], "online_initial_sigma": [0.005],
        "online_model_out": str(tmp_path / "online_model.yaml")})
    node = NodeProcess.node("fusion_node", env, tmp_path, params_file=pf)
    model = PPOEModel.from_files(REPO / "config" / "robots" / "arm7.urdf", MODEL)
    data = read_bag(bag, load_images=False)
    js = data.joint_states
    q = js.as_dict(len(js.stamps) - 1)
    stamp_ns = int(round(js.stamps[-1] * 1e9))
    T_static, C_static = model.fk(q, "base_link", "tool0")
    try:
        with Probe(env) as probe:
            got = probe.collect("/ppoe/online_effects", Float64MultiArray)
            fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
            probe.wait_for_publishers("/ppoe/online_effects", node, timeout=60)
            play = NodeProcess.ppoe(["play", str(bag), "--rate", "4", "--wait-for-subscribers", "30", "--topics",
                                     "/joint_states", "/ground_truth/point"], env, tmp_path, "play")
            assert play.wait(timeout=120) == 0, play.output()[-2000:]
            n_points = len(data.ground_truth_point.stamps)
            probe.spin_until(lambda: len(got) >= n_points, 60, node, "an estimate per tracker point")
            pub = probe.publisher("/ppoe/pose", PoseWithCovarianceStamped)
            probe.wait_for_subscribers(pub, node)
            pub.publish(pose_cov_stamped_msg(T_static, lie.cov_local_to_ros(T_static, C_static),
                                             ns_to_stamp(stamp_ns), "base_link"))
            probe.spin_until(lambda: len(fused) >= 1, 30, node, "the fused pose")
            assert node.alive()
        node.stop(timeout=10)
    finally:
        node.stop()
    _, labels, theta, P = estimates_from_msg(got[-1])
    filt = OnlineEffects(model, parse_online_config(
        [{"name": "base_tilt", "location": "base_link", "process_noise": 1.0e-5, "initial_sigma": 0.005}], model))
    assert labels == filt.labels
    filt.theta, filt.P = theta, P
    T_online = filt.tool_pose(q, "base_link", "tool0")[0]
    T_fused = matrix_from_pose_msg(fused[-1].pose.pose)
    np.testing.assert_allclose(T_fused, T_online, atol=1e-9)
    assert np.linalg.norm(T_fused[:3, 3] - T_static[:3, 3]) > 1e-3  # the 3 mrad tilt moved the tool
    assert (tmp_path / "online_model.yaml").exists()  # written at shutdown
