"""``ppoe evaluate`` replays the fusion node's sensor blocks (tracker points, 6D poses, accelerometers) exactly as
the node fuses them (issue 21 item 4): offline, a bag of the arm7 robot with all three kinds and bad messages is
fused and counted as the node counts; live, ``ppoe play`` of the same bag through the kinematics and fusion nodes
gives the same fused poses at every ground-truth stamp (1e-6).

The bag is made here (not a shipped one): static stops of the arm7 robot, joint states at 100 Hz, per stop one
tracker point (``/ground_truth/point``, frame ``tracker`` placed by the block's ``sensor_pose``), one 6D pose of the
tool (``/mocap/tool``, covariance in the message), one accelerometer reading on ``arm_link_4`` (``/imu/forearm``,
the model YAML's ``imus`` entry gives its noise) and the ground-truth tool pose; plus an IMU message on a link the
URDF lacks and one that is not at rest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import CONFIG

from ppoe_core import PPOEModel, lie
from ppoe_core.analysis.evaluate import EvaluateOptions, evaluate_bag, load_fusion_params, load_sources
from ppoe_core.errors import BagError, ModelConfigError
from ppoe_core.estimation.source_updater import pose_from_xyz_rpy
from ppoe_core.io.bagio import BagWriter
from ppoe_core.robot.tree import GRAVITY

URDF = CONFIG / "robots" / "arm7.urdf"
MODEL = CONFIG / "robots" / "arm7_model.yaml"
ARM = [f"joint_{i}" for i in range(1, 8)] + ["finger_left_joint"]
TRACKER_POSE = [1.4, -0.3, 0.2, 0.0, 0.0, 0.7]  # [x, y, z, roll, pitch, yaw] of the tracker in base_link
REFLECTOR = [0.0, 0.0, 0.02]
STOP = 0.6  # s per static stop
N_STOPS = 6


def _params(path: Path) -> Path:
    """The fusion node's parameter file with the three sensor blocks (shared by the node and evaluate)."""
    import yaml

    params = {
        "model_file": str(MODEL), "robot_description": URDF.read_text(), "correction_timeout": 0.0,
        "diagnostics_period": 0.5, "publish_tf": False,
        "sources": ["tracker", "mocap", "forearm"],
        "tracker": {"type": "point", "topic": "ground_truth/point", "link": "tool0", "xyz": REFLECTOR,
                    "sigma": [0.0005], "frame": "tracker", "sensor_pose": TRACKER_POSE},
        "mocap": {"type": "pose", "topic": "mocap/tool", "link": "tool0", "frame": "base_link"},
        "forearm": {"type": "imu", "topic": "imu/forearm", "link": "arm_link_4"},
    }
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    return path


def _make_bag(path: Path, seed: int = 5) -> Path:
    """The bag of the module docstring; returns its directory."""
    model = PPOEModel.from_files(URDF, MODEL)
    rng = np.random.default_rng(seed)
    T_base_tracker = pose_from_xyz_rpy(TRACKER_POSE)
    t = 100.0
    with BagWriter(path) as w:
        w.write_robot_description(URDF.read_text(), 0.0)
        q0 = [0.0] * len(ARM)
        for j in range(150):  # 1.5 s of joint states first: the live nodes' subscriptions settle before the stops
            w.write_joint_state(t - 1.7 + 0.01 * j, ARM, q0)
        for k in range(N_STOPS):
            q = {n: float(v) for n, v in zip(ARM, rng.uniform(-0.8, 0.8, len(ARM)))}
            q["finger_left_joint"] = 0.01
            q["joint_4"] = -1.2 + 0.2 * k / N_STOPS
            T_true = model.sample(q, "base_link", "tool0", n=1, rng=rng)[0]
            T_arm = model.fk_mean(q, "base_link", "arm_link_4")
            t0 = t
            for j in range(int(STOP * 100)):
                w.write_joint_state(t0 + 0.01 * j, list(q), list(q.values()))
            p = lie.inverse(T_base_tracker) @ (T_true @ np.array([*REFLECTOR, 1.0]))
            w.write_ground_truth_point(t0 + 0.105, "tracker", p[:3] + rng.normal(0.0, 0.0005, 3))
            cov = np.diag([2e-4, 2e-4, 2e-4, 2e-3, 2e-3, 2e-3]) ** 2
            T_meas = T_true @ lie.exp(rng.multivariate_normal(np.zeros(6), cov))
            w.write_pose_with_covariance("/mocap/tool", t0 + 0.155, "base_link", T_meas,
                                         lie.cov_local_to_ros(T_meas, cov))
            a = GRAVITY * (T_arm[:3, :3].T @ np.array([0.0, 0.0, 1.0])) + rng.normal(0.0, 0.0004, 3)
            w.write_imu("forearm", t0 + 0.205, "arm_link_4", a, accel_sigma=0.0004)
            if k == 1:
                w.write_imu("forearm", t0 + 0.225, "ghost_link", a)  # a link the URDF lacks: unknown_link
                w.write_imu("forearm", t0 + 0.245, "arm_link_4", 1.3 * a)  # |a| = 1.3 g: not at rest
            w.write_ground_truth_pose(t0 + 0.305, "base_link", T_true)
            t = t0 + STOP + 0.2  # a gap between stops: a new configuration
    return path


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("sources")
    return _make_bag(tmp / "sources_bag"), _params(tmp / "fusion.yaml")


def test_evaluate_fuses_points_poses_and_accelerations_as_the_node_counts(bag):
    bag_dir, params = bag
    sources = load_sources(params)
    assert [s.name for s in sources] == ["tracker", "mocap", "forearm"]
    ev = evaluate_bag(bag_dir, MODEL, EvaluateOptions(fusion=load_fusion_params(params), sources=sources))
    counts = ev.summary["measurements"]["sources"]
    assert counts["tracker"]["measurements"] == counts["mocap"]["measurements"] == N_STOPS
    assert counts["forearm"]["measurements"] == N_STOPS
    assert counts["forearm"]["unknown_link"] == 1 and counts["forearm"]["not_at_rest"] == 1
    assert ev.summary["measurements"]["total"] == 3 * N_STOPS
    outcomes = ev.summary["methods"]["ppoe"]["measurements"]["outcomes"]
    assert outcomes.get("accepted", 0) + outcomes.get("rejected", 0) == 3 * N_STOPS, outcomes
    assert outcomes.get("accepted", 0) >= 2 * N_STOPS, outcomes  # the gate may refuse a few (as live)
    fk = ev.summary["methods"]["fk"]["position_3d"]["mean"]
    ppoe = ev.summary["methods"]["ppoe"]["position_3d"]["mean"]
    assert ppoe < 0.5 * fk, (fk, ppoe)
    assert ev.summary["methods"]["ppoe"]["nis"]["n"] == 3 * N_STOPS


def test_a_source_the_node_would_switch_off_or_a_topic_without_messages_is_an_error(bag, tmp_path):
    import yaml

    bag_dir, params = bag
    doc = yaml.safe_load(params.read_text())
    doc["/**"]["ros__parameters"]["mocap"]["link"] = "no_such_link"
    broken = tmp_path / "broken.yaml"
    broken.write_text(yaml.safe_dump(doc))
    with pytest.raises(ModelConfigError, match="source 'mocap' on /mocap/tool: link 'no_such_link' is not a link"):
        evaluate_bag(bag_dir, MODEL, EvaluateOptions(sources=load_sources(broken)))
    doc["/**"]["ros__parameters"]["mocap"].update(link="tool0", topic="mocap/elsewhere")
    broken.write_text(yaml.safe_dump(doc))
    with pytest.raises(BagError, match="source 'mocap' \\(pose\\): no messages on /mocap/elsewhere"):
        evaluate_bag(bag_dir, MODEL, EvaluateOptions(sources=load_sources(broken)))
    doc["/**"]["ros__parameters"]["mocap"]["type"] = "laser"
    broken.write_text(yaml.safe_dump(doc))
    with pytest.raises(ModelConfigError, match="broken.yaml: parameter 'mocap.type' = 'laser': must be one of"):
        load_sources(broken)


@pytest.mark.ros
@pytest.mark.timeout(300)
def test_evaluate_equals_the_live_fusion_node_for_points_poses_and_accelerations(bag, tmp_path):
    """``ppoe play`` of the bag through the live kinematics and fusion nodes (the same parameter file): the newest
    fused pose after each stop's ground-truth stamp and before the stop ends equals ``ppoe evaluate``'s PPOE
    estimate at that stamp, to 1e-6 (correction timeout off: within a static stop every fused pose is the same)."""
    pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file

    from ppoe_core.io.bagio import read_bag
    from ppoe_ros.common.conversions import matrix_from_pose_msg

    bag_dir, params = bag
    env = ros_env(tmp_path)
    pf_kin = write_params_file(tmp_path / "kin.yaml", {"model_file": str(MODEL), "robot_description":
                                                       URDF.read_text()})
    topics = ["/joint_states", "/ground_truth/point", "/mocap/tool", "/imu/forearm"]
    with (
        Probe(env) as probe,
        NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf_kin) as kin,
        NodeProcess.node("fusion_node", env, tmp_path, params_file=params) as fus,
    ):
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        probe.wait_for_publishers("/ppoe/fused_pose", fus)
        for p in (kin, fus):
            probe.spin_until(lambda p=p: "model from parameter" in p.output(), timeout=60.0, proc=p, what="the model")
        play = NodeProcess.ppoe(["play", str(bag_dir), "--rate", "0.5", "--topics", *topics,
                                 "--wait-for-subscribers", "30"], env, tmp_path, "play")
        with play:
            probe.spin_until(lambda: not play.alive(), timeout=120.0)
            rc = play.wait(10)
        assert rc == 0, play.output()[-2000:]
        probe.spin_for(2.0)
        for p in (kin, fus):
            assert p.alive(), p.output()[-2000:]
        log = fus.output()
    assert "source 'tracker'" not in log or "is off" not in log, log[-2000:]
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in fused])
    T_live = np.stack([matrix_from_pose_msg(m.pose.pose) for m in fused])
    ev = evaluate_bag(bag_dir, MODEL, EvaluateOptions(fusion=load_fusion_params(params), sources=load_sources(params)))
    gt = read_bag(bag_dir).ground_truth_pose
    err_live = np.full((len(gt), 3), np.nan)
    for i, (t, T_gt) in enumerate(zip(gt.stamps, gt.T)):
        sel = np.flatnonzero((stamps > t + 1e-6) & (stamps < t + STOP - 0.31))
        if sel.size:
            err_live[i] = T_live[sel[np.argmax(stamps[sel])]][:3, 3] - T_gt[:3, 3]
    ok = np.all(np.isfinite(err_live), axis=1)
    # Under load a sensor-QoS message may be lost (a stop without a live pose in its window), or a stop's
    # measurements may reach the node only after its window (its newest pose there is the FK prior, as in
    # test_evaluate.py::test_evaluate_matches_live_node_pipeline): one of each is tolerated, every other stop
    # must agree.
    fk = ev.samples["fk_position_error"]
    late = ok & (np.linalg.norm(err_live - fk, axis=1) < 1e-9)
    assert ok.sum() >= N_STOPS - 1 and late.sum() <= 1, (ok, late)
    cmp = ok & ~late
    print(f"stops compared: {int(cmp.sum())} of {N_STOPS}, max |live - evaluate| = "
          f"{np.abs(err_live[cmp] - ev.samples['ppoe_position_error'][cmp]).max():.3g} m")
    np.testing.assert_allclose(err_live[cmp], ev.samples["ppoe_position_error"][cmp], rtol=0, atol=1e-6)
    assert np.linalg.norm(err_live[cmp], axis=1).mean() < 0.5 * np.linalg.norm(fk[cmp], axis=1).mean()
