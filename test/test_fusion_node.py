"""Fusion node through live topics: prior + simulated tag observations -> fused pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from conftest import CONFIG, REPO  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo, JointState, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from ppoe_core import PPOEModel, lie  # noqa: E402
from ppoe_core.estimation import measurements as mm  # noqa: E402
from ppoe_ros.common import matrix_from_pose_msg, ns_to_stamp, pose_cov_stamped_msg  # noqa: E402
from ppoe_ros.common.tag_cloud import cloud_from_observations  # noqa: E402

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

    model = PPOEModel.from_files(CONFIG / "robots" / "rover.urdf", CONFIG / "robots" / "rover_model.yaml")
    T_prior, P_prior = model.fk(ROVER_Q, "base_link", "tool_link")
    cov_ros = lie.cov_local_to_ros(T_prior, P_prior)
    rng = np.random.default_rng(2024)
    T_true = model.sample(ROVER_Q, "base_link", "tool_link", n=1, rng=rng)[0]
    err_prior = np.linalg.norm(T_prior[:3, 3] - T_true[:3, 3])
    assert err_prior > 0.01  # the seed gives a kinematics error worth correcting
    rows = _observation_rows(model, T_true, rng)

    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(CONFIG / "robots" / "rover_model.yaml"),
        "robot_description": (CONFIG / "robots" / "rover.urdf").read_text(),
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
        # before any measurement the fused pose is the prior, and /diagnostics says so (issue 13 item 15)
        np.testing.assert_allclose(matrix_from_pose_msg(fused[-1].pose.pose), T_prior, atol=1e-9)
        probe.spin_until(lambda: counts().get("converging") == "True", 10, proc, "diagnostics: converging")
        assert diags[-1].status[0].level == b"\x01" and "uncorrected prior" in diags[-1].status[0].message

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
        assert counts().get("converging") == "False"
        # issue 13 item 5: a prior 1.5 s late, one 0.1 s back in time, an image listing a corner twice
        pub_prior.publish(pose_cov_stamped_msg(T_prior, cov_ros, ns_to_stamp(t0 + 35 * dt - 1_500_000_000),
                                               "base_link"))
        pub_prior.publish(pose_cov_stamped_msg(T_prior, cov_ros, ns_to_stamp(t0 + 35 * dt - 100_000_000),
                                               "base_link"))
        hdr30 = Header(frame_id="camera_optical_frame", stamp=ns_to_stamp(t0 + 30 * dt))
        pub_obs.publish(cloud_from_observations(np.vstack([rows, rows[:1]]), hdr30))
        probe.spin_until(lambda: counts().get("priors_late") == "1" and counts().get("priors_out_of_order") == "1"
                         and counts().get("bad") == "3", 20, proc, "late 1, out of order 1, bad 3")
        assert proc.alive()
        log = proc.output()

    # every fused pose carries a prior's exact stamp, the update's output too (the newest prior's, published again;
    # it went through float seconds and was off by up to ~0.1 us)
    sent = {t0 + k * dt for k in range(36)} | {t0 + 35 * dt - 100_000_000}
    stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in fused]
    assert set(stamps) <= sent, sorted(set(stamps) - sent)[:3]
    assert len(stamps) > len(set(stamps)), "no update output repeating its prior's stamp"
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
    assert "is older than the prior buffer" in log and "out of order" in log
    assert f"duplicated observation rows (tag {int(rows[0, 0])} corner {int(rows[0, 1])} x2)" in log
    print(f"fusion node: prior position error {err_prior * 1000:.1f} mm, fused {err_fused * 1000:.1f} mm")


# ----------------------------------------------------------------------------- end to end
# ppoe play BAG -> kinematics_node + tag_bearing_node / contact_node + fusion_node
# -> ppoe record -> compare /ppoe/pose and /ppoe/fused_pose with /ground_truth/pose


#: fusion node settings for a machine so loaded that the nodes lag seconds behind the player:
#: keep 20 s of priors, deep input queues, and wait 5 s of prior silence before giving up on a
#: pending measurement (the defaults are for a node that keeps up: 1 s, 1000, 1 s)
_LAG_TOLERANT = {"buffer_duration": 20.0, "qos_depth": 5000, "pending_timeout": 5.0}


def _run_chain(tmp_path, bag: Path, nodes, play_topics, rate: float):
    """Play ``bag`` through ``nodes`` (list of (module, params)) and ``ppoe record`` the outputs.

    Readiness comes from the recorder's log and ``ppoe play --wait-for-subscribers``.  The
    recorder runs on wall time: with ``--use-sim-time`` its topic discovery timer would not
    fire before ``/clock`` starts.  Comparisons use the message stamps only.
    """
    import time

    from ros_helpers import NodeProcess, ros_env

    env = ros_env(tmp_path)
    out = tmp_path / "recorded"
    procs = []
    try:
        for module, params in nodes:
            procs.append(NodeProcess.node(module, env, tmp_path, params={"use_sim_time": True, **params}))
        rec = NodeProcess.ppoe(["record", "--out", str(out), "/ppoe/pose", "/ppoe/fused_pose",
                                "/diagnostics"], env, tmp_path, "record")
        procs.append(rec)
        deadline = time.monotonic() + 60
        while not all(f"recording {t} " in rec.output() for t in ("/ppoe/pose", "/ppoe/fused_pose")):
            if time.monotonic() > deadline or not all(p.alive() for p in procs):
                raise AssertionError("recorder did not see the nodes' publishers:\n"
                                     + "\n".join(p.output()[-1500:] for p in procs))
            time.sleep(0.2)
        play = NodeProcess.ppoe(["play", str(bag), "--clock", "--rate", str(rate), "--wait-for-subscribers", "30",
                                 "--topics", *play_topics], env, tmp_path, "play")
        procs.append(play)
        assert play.wait(timeout=120) == 0, play.output()[-3000:]
        _wait_until_fusion_idle(env, procs)
        for p in procs[:-2]:
            assert p.alive(), f"{p.cmd} died:\n{p.output()[-3000:]}"
        rec.stop(timeout=10)
        logs = {p.log_path.stem: p.output() for p in procs}
    finally:
        for p in procs:
            p.stop()
    return out, logs


def _wait_until_fusion_idle(env, procs, quiet: float = 2.0, timeout: float = 60.0) -> None:
    """Wait until the fusion node's ``received`` counter on /diagnostics has not changed for
    ``quiet`` s and nothing is pending (a loaded machine makes the nodes lag behind the player)."""
    import time

    from ros_helpers import Probe

    with Probe(env, name="idle_probe") as probe:
        diags = probe.collect("/diagnostics", DiagnosticArray)
        state = {"value": None, "since": time.monotonic()}

        def idle() -> bool:
            for d in reversed(diags):
                st = {s.name: s for s in d.status}.get("/fusion_node: health")
                if st is not None:
                    kv = {k.key: k.value for k in st.values}
                    break
            else:
                return False
            if kv.get("received") != state["value"]:
                state["value"], state["since"] = kv.get("received"), time.monotonic()
            return kv.get("pending") == "0" and time.monotonic() - state["since"] > quiet

        probe.spin_until(idle, timeout, procs[0], "the fusion node to finish the bag")


def _errors_at_ground_truth(bag: Path, recorded: Path, window: float = 0.8):
    """Per ground-truth pose: position error vector [m] of the prior and of the fused pose, both at
    the newest fused stamp within ``window`` s after the ground-truth stamp (same stop: the
    joints are checked to be unchanged)."""
    from ppoe_core.io.bagio import read_bag

    src, rec = read_bag(bag), read_bag(recorded)
    prior = rec.poses_with_covariance["/ppoe/pose"]
    fused = rec.poses_with_covariance["/ppoe/fused_pose"]
    js = src.joint_states
    e_prior, e_fused = [], []
    for t_gt, T_gt in zip(src.ground_truth_pose.stamps, src.ground_truth_pose.T):
        sel = np.flatnonzero((fused.stamps >= t_gt - 1e-6) & (fused.stamps <= t_gt + window))
        if sel.size == 0:
            continue
        t_best = fused.stamps[sel].max()
        i_f = sel[fused.stamps[sel] == t_best][-1]  # last published for that stamp
        i_p = np.flatnonzero(np.abs(prior.stamps - t_best) < 1e-6)
        assert i_p.size, f"no prior at {t_best}"
        q0 = js.positions[np.argmin(np.abs(js.stamps - t_gt))]
        q1 = js.positions[np.argmin(np.abs(js.stamps - t_best))]
        assert np.nanmax(np.abs(q0 - q1)) < 1e-9, "arm moved inside the comparison window"
        e_prior.append(prior.T[i_p[-1]][:3, 3] - T_gt[:3, 3])
        e_fused.append(fused.T[i_f][:3, 3] - T_gt[:3, 3])
    return np.array(e_prior).reshape(-1, 3), np.array(e_fused).reshape(-1, 3), len(src.ground_truth_pose.stamps)


def _diag(logs_bag: Path, node: str) -> dict[str, str]:
    from ppoe_core.io.bagio import deserialize, iter_raw

    last = {}
    for raw in iter_raw(logs_bag, ["/diagnostics"]):
        msg = deserialize(raw.data, raw.msgtype, topic=raw.topic)
        for st in msg.status:
            if st.name == node:
                last = {kv.key: kv.value for kv in st.values}
    return last


@pytest.mark.ros
@pytest.mark.timeout(150)
def test_end_to_end_bag_with_tags(tmp_path):
    bag = REPO / "bags" / "table1_exp1"
    model = str(CONFIG / "robots" / "rover_model.yaml")
    nodes = [
        ("kinematics_node", {"model_file": model, "qos_depth": 5000}),
        ("tag_bearing_node", {"model_file": model, "qos_depth": 50}),  # tag family and ids from the model
        ("fusion_node", {"model_file": model, "diagnostics_period": 0.5, **_LAG_TOLERANT}),
    ]
    recorded, logs = _run_chain(tmp_path, bag, nodes,
                                ["/robot_description", "/joint_states", "/camera/camera_info",
                                 "/camera/image_raw/compressed"], rate=2.0)
    v_prior, v_fused, n_gt = _errors_at_ground_truth(bag, recorded)
    e_prior, e_fused = np.linalg.norm(v_prior, axis=1), np.linalg.norm(v_fused, axis=1)
    diag = _diag(recorded, "/fusion_node: health")
    print(f"\ntable1_exp1 end to end: {len(e_fused)}/{n_gt} stops, position error mean prior "
          f"{e_prior.mean() * 1000:.2f} mm, fused {e_fused.mean() * 1000:.2f} mm; fusion diagnostics {diag}")
    assert len(e_fused) >= n_gt - 2  # a stop may lack fused poses when the machine is loaded
    assert e_fused.mean() < 0.5 * e_prior.mean()
    assert int(diag["accepted"]) >= n_gt


@pytest.mark.ros
@pytest.mark.timeout(150)
def test_end_to_end_bag_with_contact(tmp_path):
    bag = REPO / "bags" / "contact"
    model = str(CONFIG / "robots" / "humanoid_model.yaml")
    nodes = [
        ("kinematics_node", {"model_file": model, "qos_depth": 5000}),
        ("contact_node", {"model_file": model}),
        ("fusion_node", {"model_file": model, "diagnostics_period": 0.5, **_LAG_TOLERANT}),
    ]
    recorded, logs = _run_chain(tmp_path, bag, nodes, ["/robot_description", "/joint_states", "/wrench"], rate=2.0)
    v_prior, v_fused, n_gt = _errors_at_ground_truth(bag, recorded)
    e_prior, e_fused = np.linalg.norm(v_prior, axis=1), np.linalg.norm(v_fused, axis=1)
    # error along the table normal (the direction a contact observes), on the stops where the
    # fusion changed the pose (the contact stops; free stops pass the prior unchanged)
    robots = CONFIG / "robots"
    plane = PPOEModel.from_files(robots / "humanoid.urdf", robots / "humanoid_model.yaml").config.contact
    normal = plane.T_frame_plane[:3, 2]
    touched = np.linalg.norm(v_fused - v_prior, axis=1) > 1e-9
    n_prior, n_fused = np.abs(v_prior[touched] @ normal), np.abs(v_fused[touched] @ normal)
    diag = _diag(recorded, "/fusion_node: health")
    print(
        f"\ncontact end to end: {len(e_fused)}/{n_gt} stops, position error mean prior "
        f"{e_prior.mean() * 1000:.2f} mm, fused {e_fused.mean() * 1000:.2f} mm; along the table normal on the "
        f"{touched.sum()} corrected stops: prior {n_prior.mean() * 1000:.2f} mm, fused {n_fused.mean() * 1000:.2f} mm;"
        f" fusion diagnostics {diag}"
    )
    assert len(e_fused) >= n_gt // 2
    assert e_fused.mean() < e_prior.mean()
    assert touched.sum() >= 4 and n_fused.mean() < 0.1 * n_prior.mean()
    assert int(diag["accepted"]) >= 8


@pytest.mark.parametrize("node", ["fusion_node", "tag_bearing_node"])
def test_config_file_documents_every_parameter(node):
    """config/<node>.yaml: every parameter of PARAMS, each with a comment above it, defaults as
    in the code (except the example values listed here)."""
    import importlib

    import yaml

    params = importlib.import_module(f"ppoe_ros.nodes.{node}").PARAMS
    path = CONFIG / "nodes" / f"{node}.yaml"
    values = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]  # any name and namespace
    assert set(values) == {p.name for p in params}
    examples = {"fusion_node": {"model_file"}, "tag_bearing_node": set()}[node]
    for p in params:
        if p.name not in examples:
            assert values[p.name] == p.default, p.name
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        key = line.strip().split(":")[0]
        if line.startswith("    ") and not line.strip().startswith("#") and key in values:
            assert lines[i - 1].strip().startswith("#"), f"{path.name}: '{key}' has no comment"
            assert "Default" in " ".join(lines[max(0, i - 4) : i]), f"{path.name}: '{key}' comment names no default"


def test_fusion_node_joints_are_the_one_joint_history():
    """The fusion node looks the prior's joints up in a JointHistory of every model joint (split messages merged per
    joint, NaN = unknown; the bounded hold of JointHistory.at), as evaluate's joint matrix merges them."""
    from ppoe_core.model.joint_history import JointHistory

    jb = JointHistory(["a", "b", "c"], known=["a", "b", "c"], max_age_ns=500_000_000, keep_ns=2_000_000_000)
    assert jb.at(5) is None
    jb.update(["a"], [1.0], 100)
    jb.update(["b"], [2.0], 200)  # a partial message keeps the last known values of the others
    np.testing.assert_array_equal(jb.at(150), [1.0, np.nan, np.nan])
    np.testing.assert_array_equal(jb.at(250), [1.0, 2.0, np.nan])
    np.testing.assert_array_equal(jb.at(50), [1.0, np.nan, np.nan])  # prior just older than all: the oldest
    Q, held = JointHistory(["a", "b", "c"], max_age_ns=500_000_000).merge_rows(
        np.array([100e-9, 200e-9]), np.array([[1.0, np.nan, np.nan], [np.nan, 2.0, np.nan]]))
    np.testing.assert_array_equal(Q, [jb.at(100), jb.at(200)])
    assert held == 1


def test_evaluate_refuses_what_the_node_refuses(tmp_path, capsys):
    """Issue 13: ``ppoe evaluate --set max_iterations=0`` is refused like the node's parameter; the
    ranges of ``FUSION_RANGES`` are the node's ParamSpec ranges."""
    from ppoe_core.estimation.updater import FUSION_RANGES
    from ppoe_ros.cli import main
    from ppoe_ros.nodes.fusion_node import PARAMS

    spec = {p.name: p for p in PARAMS}
    for key, (lo, hi) in FUSION_RANGES.items():
        assert (spec[key].min_value, spec[key].max_value) == (lo, hi), key
    bag = REPO / "bags" / "table1_exp1"
    for setting in ("max_iterations=0", "gate_probability=1.5", "max_gap=-1"):
        rc = main(["evaluate", str(bag), "--model", str(CONFIG / "robots" / "rover_model.yaml"), "--set", setting])
        err = capsys.readouterr().err
        assert rc == 2 and f"fusion setting {setting.replace('=', ' = ')} is outside" in err, err


def test_diagnostics_error_until_the_model_arrives_and_warn_when_inputs_stop(tmp_path):
    """Without a URDF the fusion node says ERROR 'no model' on /diagnostics; once the URDF arrives on the topic
    and no input follows for input_timeout, it says WARN 'no input ... for X s'."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from std_msgs.msg import String

    from ppoe_ros.common import LATCHED_QOS

    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(CONFIG / "robots" / "rover_model.yaml"), "diagnostics_period": 0.2, "input_timeout": 0.5})
    with Probe(env) as probe, NodeProcess.node("fusion_node", env, tmp_path, params_file=pf) as proc:
        diags = probe.collect("/diagnostics", DiagnosticArray)

        def last():
            return diags[-1].status[0] if diags else None

        probe.spin_until(lambda: last() is not None, 15, proc, "/diagnostics")
        assert last().level == DiagnosticStatus.ERROR and "no model" in last().message
        desc = probe.publisher("/robot_description", String, LATCHED_QOS)
        desc.publish(String(data=(CONFIG / "robots" / "rover.urdf").read_text()))
        probe.spin_until(lambda: last().level == DiagnosticStatus.WARN and "no input" in last().message, 15, proc,
                         "WARN: no input")
        assert proc.alive()


def test_pose_message_fast_build_equals_the_constructors_and_round_trips(monkeypatch):
    """``pose_cov_stamped_msg`` builds the message without the generated constructors: equal (``==`` and CDR bytes)
    to the constructors' message, for int and ``Time`` stamps; ``pose_cov_from_msg`` gives the pose back."""
    from rclpy.serialization import serialize_message

    from ppoe_ros.common import conversions, pose_cov_from_msg

    assert conversions._FAST_MSG  # the default environment takes the fast build
    rng = np.random.default_rng(3)
    for k in range(50):
        T = lie.exp(rng.normal(size=6) * (0.1 if k % 2 else 3.0))
        A = rng.normal(size=(6, 6))
        cov = A @ A.T
        stamp = 1_700_000_000_123_456_789 + k if k % 3 else ns_to_stamp(k * 1_000_003)
        fast = pose_cov_stamped_msg(T, cov, stamp, "base_link")
        monkeypatch.setattr(conversions, "_FAST_MSG", False)
        slow = pose_cov_stamped_msg(T, cov, stamp, "base_link")
        monkeypatch.setattr(conversions, "_FAST_MSG", True)
        assert fast == slow and repr(fast) == repr(slow)
        assert serialize_message(fast) == serialize_message(slow)
        assert ns_to_stamp(12_345_678_901) == conversions.TimeMsg(sec=12, nanosec=345_678_901)
        T_back, cov_back, ns, frame = pose_cov_from_msg(fast)
        monkeypatch.setattr(conversions, "_FAST_MSG", False)  # the reading through the properties: the same floats
        T_slow, cov_slow, ns_slow, frame_slow = pose_cov_from_msg(fast)
        monkeypatch.setattr(conversions, "_FAST_MSG", True)
        assert np.array_equal(T_back, T_slow) and np.array_equal(cov_back, cov_slow)
        assert (ns, frame) == (ns_slow, frame_slow)
        np.testing.assert_allclose(T_back, T, atol=1e-12)
        assert np.array_equal(cov_back, cov) and frame == "base_link"
        assert ns == (stamp if isinstance(stamp, int) else k * 1_000_003)


def test_prior_parse_of_the_writers_layout_equals_the_cdr_reader():
    """``PoseCovarianceCdr.parse`` (the fusion node's prior input): for messages laid out as its writer's, the same
    pose, covariance, stamp and frame as :func:`pose_cov_from_cdr` (bit for bit); another frame, non-zero padding,
    trailing bytes, a big-endian header or truncated bytes go through :func:`pose_cov_from_cdr` (its values or its
    error)."""
    from rclpy.serialization import serialize_message

    from ppoe_core.errors import MeasurementError
    from ppoe_ros.common.conversions import PoseCovarianceCdr, pose_cov_from_cdr

    rng = np.random.default_rng(11)
    for frame in ("base_link", "ab", "robot_1/base_link"):
        codec = PoseCovarianceCdr(frame)
        for k in range(20):
            T = lie.exp(rng.normal(size=6) * (0.1 if k % 2 else 3.0))
            A = rng.normal(size=(6, 6))
            stamp = 1_700_000_000_123_456_789 + 1_000_003 * k - (2_000_000_000_000_000_000 if k == 7 else 0)
            raw = codec.serialize(T, A @ A.T, stamp)
            typed = serialize_message(pose_cov_stamped_msg(T, A @ A.T, stamp, frame))
            for data in (raw, typed, raw + bytes(4)):
                got, ref = codec.parse(data), pose_cov_from_cdr(data)
                assert all(np.array_equal(a, b) for a, b in zip(got[:2], ref[:2])) and got[2:] == ref[2:]
                assert got[2:] == (stamp, frame) and got[1].flags.writeable
                T_l, cov_l, *rest = codec.parse_local(data)  # the compiled path: cov_ros_to_local's floats
                assert np.array_equal(T_l, ref[0]) and np.array_equal(cov_l, lie.cov_ros_to_local(*ref[:2]))
                assert tuple(rest) == (stamp, frame)
            cov_tool = lie.cov_ros_to_local(T, A @ A.T)
            assert codec.serialize_local(T, cov_tool, stamp) == codec.serialize(T, lie.cov_local_to_ros(T, cov_tool),
                                                                                stamp)
            assert np.array_equal(codec.fields[:3], T[:3, 3]) and np.array_equal(codec.fields[3:7],
                                                                                 lie.quat_from_matrix(T[:3, :3]))
            other = PoseCovarianceCdr(frame + "_x").serialize(T, A @ A.T, stamp)
            assert codec.parse(other)[3] == frame + "_x"
    padded = bytearray(PoseCovarianceCdr("ab").serialize(np.eye(4), np.eye(6), 5))
    assert len(padded) % 8 == 4 and padded[19] == 0  # "ab\0" at 16..18 and one byte of padding before the pose
    padded[19] = 7
    assert PoseCovarianceCdr("ab").parse(bytes(padded))[3] == "ab"  # padding is not read (rclpy leaves it unset)
    for bad in (raw[:-8], b"\x00\x00\x00\x00" + raw[4:]):
        for read in (codec.parse, codec.parse_local):
            with pytest.raises(MeasurementError):
                read(bad)
    no_rotation = codec.serialize(np.eye(4), np.eye(6), 5)
    no_rotation = no_rotation[:-8 * 40] + bytes(8 * 4) + no_rotation[-8 * 36:]  # quaternion 0 0 0 0
    with pytest.raises(ValueError, match="not a rotation"):
        codec.parse_local(no_rotation)


def test_joint_state_reader_equals_parse_joint_state():
    """``JointStateReader.parse`` (the fusion node's joint-state input, which remembers the last layout) gives what
    ``parse_joint_state`` gives for a stream of messages with garbage padding (rclpy leaves it unset: bytes no field
    is read from), a name changed in place, another frame, more joints, no positions, and raises its errors for bad
    bytes."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from ppoe_core.io.cdr import SCHEMAS, CdrError, JointStateReader, parse_joint_state, read

    def fields(raw: bytes) -> list:
        return [np.asarray(v).tolist() for v in read(SCHEMAS["sensor_msgs/msg/JointState"], raw)[0]]

    rng = np.random.default_rng(4)
    reader = JointStateReader()
    layouts = [(["j1", "joint_22", "abc"], "base"), (["j1", "joint_23", "abc"], "base"),
               (["j1", "joint_22", "abc"], "odom"), (["j1", "joint_22", "abc", "x"], "base"), ([], "")]
    hits = 0
    for k in range(200):
        names, frame = layouts[(k // 7) % len(layouts)]
        msg = JointState(name=names, position=list(rng.normal(size=len(names))), velocity=[0.5] * (k // 35 % 2))
        msg.header.frame_id = frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000 + k, 999_999 * k
        raw = bytearray(serialize_message(msg))
        for at in range(len(raw)):  # garbage in every padding byte: the bytes the parser does not read
            if at >= 4 and raw[at] == 0 and rng.random() < 0.5:
                probe = bytes(raw[:at]) + b"\x5a" + bytes(raw[at + 1:])
                try:
                    if fields(probe) == fields(bytes(raw)):
                        raw[at] = 0x5A
                except CdrError:
                    continue
        data = bytes(raw)
        hits += reader.layout is not None and reader.layout.matches(data)
        got, ref = reader.parse(data), parse_joint_state(data)
        assert (got.stamp_ns, got.frame_id, got.names) == (ref.stamp_ns, ref.frame_id, ref.names), k
        assert np.array_equal(got.positions, ref.positions) and got.positions.dtype == ref.positions.dtype, k
    assert hits > 100
    for bad in (data[:3], b"\x00\x00\x00\x00" + data[4:], data[:20]):
        with pytest.raises(CdrError):
            reader.parse(bad)
