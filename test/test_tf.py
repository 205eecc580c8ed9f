"""TF output (issue 11 item 3): the fusion node's corrected tool on /tf and calibrated camera on /tf_static,
the kinematics node's model frames like robot_state_publisher, a colliding child frame, and a node without
tf2_msgs.  Live tests run the node as a separate process in an isolated DDS domain (ros_helpers) and receive
/tf and /tf_static in the test process; they need tf2_msgs (built by scripts/build_tf2_msgs.py, as .ci/run
does) and skip only when it does not import.  The frame math is checked without DDS too.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")

from conftest import CONFIG  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo, JointState, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from ppoe_core import PPOEModel, lie  # noqa: E402
from ppoe_ros.common import matrix_from_pose_msg, ns_to_stamp, pose_cov_stamped_msg, stamp_to_ns  # noqa: E402
from ppoe_core.model.tf_frames import JointFrames, calibrated_camera_frames, urdf_collision  # noqa: E402

HAVE_TF2_MSGS = importlib.util.find_spec("tf2_msgs") is not None
needs_tf2_msgs = pytest.mark.skipif(not HAVE_TF2_MSGS, reason="tf2_msgs not importable: run "
                                    "`.venv/bin/python scripts/build_tf2_msgs.py` (.ci/run does)")

ROVER_URDF = CONFIG / "robots" / "rover.urdf"
ARM7_URDF = CONFIG / "robots" / "arm7.urdf"
#: a calibrated camera as `ppoe diagnose` writes it: camera_extrinsics at the camera's mount joint
CAMERA_EFFECT = {"name": "camera_extrinsics", "location": "camera_joint",
                 "parameters": {"x": 0.02, "y": -0.01, "rz": 0.02}}
#: static effects and a configuration-dependent one (gravity compliance moves joint_3 with every joint)
ARM7_EFFECTS = [
    {"name": "joint_offset", "location": "joint_2", "parameters": {"offset": 0.01}},
    {"name": "link_error", "location": "joint_4", "parameters": {"x": 0.002, "rz": 0.01}},
    dict(CAMERA_EFFECT),
    {"name": "gravity_compliance", "location": "joint_3", "parameters": {"compliance": 3e-4}},
]


def _model_file(tmp_path, base_yaml: str, effects: list[dict]):
    """A copy of a shipped model YAML with ``effects`` set (as `ppoe diagnose` leaves it)."""
    data = yaml.safe_load((CONFIG / "robots" / base_yaml).read_text())
    data["effects"] = effects
    path = tmp_path / f"calibrated_{base_yaml}"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _T(tr) -> np.ndarray:
    """``geometry_msgs/TransformStamped`` -> (4, 4)."""
    t, r = tr.transform.translation, tr.transform.rotation
    T = np.eye(4)
    T[:3, :3] = lie.matrix_from_quat(np.array([r.x, r.y, r.z, r.w]))
    T[:3, 3] = (t.x, t.y, t.z)
    return T


def _compose(tree: dict, root: str, link: str) -> np.ndarray:
    """``T_root_link`` from a {child: (parent, T_parent_child)} TF tree."""
    T = np.eye(4)
    while link != root:
        parent, T_parent_link = tree[link]
        T, link = T_parent_link @ T, parent
    return T


# ----------------------------------------------------------------------------------- frame math, no DDS


def test_joint_frames_compose_to_the_model_fk_with_effects_and_split_messages():
    model = PPOEModel.from_strings(ARM7_URDF.read_text(), {**yaml.safe_load(
        (CONFIG / "robots" / "arm7_model.yaml").read_text()), "effects": ARM7_EFFECTS})
    jf = JointFrames(model)
    assert jf.dynamic_joints == {"joint_3"}
    tree = {f.child: (f.parent, f.T_parent_child) for f in jf.static_frames()}
    assert set(tree) == {"mount_plate", "tool0", "gripper_link", "camera_link", "camera_optical_frame"}
    rng = np.random.default_rng(3)
    q = {n: rng.uniform(-1.0, 1.0) * (0.02 if "finger" in n else 1.0) for n in model.joint_names}
    arm = [n for n in q if n.startswith("joint_")]
    # arm first: joint_3 (moved by the gravity compliance) waits until the finger is known too
    first = jf.frames(arm, [q[n] for n in arm])
    assert {f.child for f in first} == {f"arm_link_{i}" for i in (1, 2, 4, 5, 6, 7)}
    second = jf.frames(["finger_left_joint"], [q["finger_left_joint"]])
    assert {f.child for f in second} == {"finger_left", "finger_right", "arm_link_3"}  # mimic follower too
    for f in first + second:
        tree[f.child] = (f.parent, f.T_parent_child)
    for link in model.robot.links:
        np.testing.assert_allclose(_compose(tree, "base_link", link), model.fk_mean(q, "base_link", link),
                                   atol=1e-12, err_msg=link)
    # unknown joints and non-finite values are left out, not raised (joint_3 follows the full configuration)
    assert {f.child for f in jf.frames(["nope", "joint_1", "joint_2"], [1.0, float("nan"), 0.1])} == \
        {"arm_link_2", "arm_link_3"}


def test_calibrated_camera_frame_carries_the_diagnosed_extrinsic():
    nominal = PPOEModel.from_files(ROVER_URDF, CONFIG / "robots" / "rover_model.yaml")
    calibrated = PPOEModel.from_strings(ROVER_URDF.read_text(), {**yaml.safe_load(
        (CONFIG / "robots" / "rover_model.yaml").read_text()), "effects": [CAMERA_EFFECT]})
    frames, notes = calibrated_camera_frames(calibrated, "_calibrated")
    assert notes == [] and len(frames) == 1
    f = frames[0]
    assert (f.parent, f.child) == ("tilt_link", "camera_optical_frame_calibrated")
    q = {n: 0.3 for n in calibrated.joint_names}
    np.testing.assert_allclose(f.T_parent_child, calibrated.fk_mean(q, "tilt_link", "camera_optical_frame"), atol=1e-12)
    joints = calibrated.robot.joints  # paper eq. 16: the extrinsic right after camera_joint's origin
    T_expected = joints["camera_joint"].origin @ lie.exp([0.02, -0.01, 0, 0, 0, 0.02]) @ \
        joints["camera_optical_joint"].origin
    np.testing.assert_allclose(f.T_parent_child, T_expected, atol=1e-12)
    assert np.linalg.norm(f.T_parent_child[:3, 3] - nominal.fk_mean(q, "tilt_link", "camera_optical_frame")[:3, 3]) \
        > 0.02
    # a suffix that makes a URDF link, a camera on a movable joint, no camera: no frame, a note
    frames, notes = calibrated_camera_frames(calibrated, "_link")  # camera_optical_frame_link is not a link
    assert len(frames) == 1
    on_joint = PPOEModel.from_strings(ARM7_URDF.read_text(), {"camera": {"frame": "arm_link_7"}})
    frames, notes = calibrated_camera_frames(on_joint, "_calibrated")
    assert frames == [] and "camera frame 'arm_link_7' is not on a fixed mount" in notes[0]
    assert calibrated_camera_frames(PPOEModel.from_strings(ARM7_URDF.read_text(), {}), "_c") == ([], [])
    assert "is a link of the URDF" in urdf_collision(calibrated.robot, "tool_link")
    assert urdf_collision(calibrated.robot, "tool_link_corrected") is None


@needs_tf2_msgs
def test_tf_message_cdr_equals_rclpy_serialisation():
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message

    from ppoe_ros.common.tf_broadcast import tf_message_cdr, tf_message_class, transform_msg
    from ppoe_core.model.tf_frames import TfFrame

    TFMessage = tf_message_class()
    rng = np.random.default_rng(7)
    for names in ([], [("base_link", "a")], [("base_link", "tool_link_corrected"), ("ab", "c_d"), ("xyz", "w")]):
        frames = [TfFrame(p, c, lie.exp(rng.normal(size=6))) for p, c in names]
        stamp_ns = 1_700_000_123_456_789_012
        ref = TFMessage(transforms=[transform_msg(f, Time(sec=1_700_000_123, nanosec=456_789_012)) for f in frames])
        data = tf_message_cdr(frames, stamp_ns)
        assert len(data) == len(serialize_message(ref)), names  # same layout (rclpy leaves padding unset)
        back = deserialize_message(data, TFMessage)
        assert back == ref, names
        for f, tr in zip(frames, back.transforms):
            np.testing.assert_allclose(_T(tr), f.T_parent_child, atol=1e-12)



@needs_tf2_msgs
def test_one_frame_tf_writer_equals_tf_message_cdr():
    """The fusion node's /tf writer (one frame, stamp and pose rewritten in place) gives tf_message_cdr's bytes, for
    the pose as the node computes it (``pose_fields_one``: ``lie.quat_from_matrix``'s floats)."""
    from ppoe_core.lie.compiled import lie_kernels
    from ppoe_core.model.tf_frames import TfFrame
    from ppoe_ros.common.tf_broadcast import OneFrameTfCdr, tf_message_cdr

    rng = np.random.default_rng(5)
    for parent, child in (("base_link", "tool0_corrected"), ("b", "c"), ("r1/base_link", "r1/tool_link_corrected")):
        writer = OneFrameTfCdr(parent, child)
        for k in range(30):
            T = lie.exp(rng.normal(size=6) * (0.1 if k % 2 else 3.0))
            stamp_ns = 1_700_000_000_123_456_789 + 999_999_937 * k - (1_800_000_000_000_000_000 if k == 3 else 0)
            fields = np.empty(7)
            lie_kernels().pose_fields_one(T, fields)
            assert np.array_equal(fields[0:4], lie.quat_from_matrix(T[:3, :3]))
            data = writer.serialize(np.concatenate([fields[4:7], fields[0:4]]), stamp_ns)
            assert data == tf_message_cdr([TfFrame(parent, child, T)], stamp_ns), (parent, k)

def test_kinematics_node_hot_path_untouched_without_publish_tf(tmp_path):
    """publish_tf false (the default): no TF object and no /tf publisher, the per-message path is the compiled one;
    true: TF is published from the Python path (the compiled one is off)."""
    from rclpy.parameter import Parameter
    from ros_helpers import Probe, ros_env

    from ppoe_ros.nodes.kinematics_node import KinematicsNode

    urdf = Parameter("robot_description", value=ARM7_URDF.read_text())
    with Probe(ros_env(tmp_path)) as probe:
        node = KinematicsNode(context=probe.context, parameter_overrides=[urdf])
        try:
            assert node._tf is None and node._fast is not None
            assert not any(p.topic_name in ("/tf", "/tf_static") for p in node.publishers)
        finally:
            node.destroy_node()
        if not HAVE_TF2_MSGS:
            return
        node = KinematicsNode(context=probe.context, parameter_overrides=[urdf, Parameter("publish_tf", value=True)])
        try:
            assert node._tf is not None and node._fast is None
            assert {"/tf", "/tf_static"} <= {p.topic_name for p in node.publishers}
        finally:
            node.destroy_node()


# ---------------------------------------------------------------------------------------- live: fusion


def _fusion_run(tmp_path, params: dict, n_priors: int = 30):
    """Run the fusion node on the rover with a calibrated camera; priors, one tag image, more priors.

    Returns (fused poses, /tf messages, /tf_static messages, diagnostics, node log, alive, prior pose, model).
    """
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from test_fusion_node import K, ROVER_Q, _observation_rows

    from ppoe_ros.common.tag_cloud import cloud_from_observations
    from ppoe_ros.common.tf_broadcast import TF_STATIC_QOS, tf_message_class

    TFMessage = tf_message_class()
    model_file = _model_file(tmp_path, "rover_model.yaml", [CAMERA_EFFECT])
    model = PPOEModel.from_strings(ROVER_URDF.read_text(), model_file)
    T_prior, P_prior = model.fk(ROVER_Q, "base_link", "tool_link")
    cov_ros = lie.cov_local_to_ros(T_prior, P_prior)
    rng = np.random.default_rng(2024)
    rows = _observation_rows(model, model.sample(ROVER_Q, "base_link", "tool_link", n=1, rng=rng)[0], rng)
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(model_file), "robot_description": ROVER_URDF.read_text(),
        "diagnostics_period": 0.2, "log_throttle": 0.0, **params})
    names = list(ROVER_Q)
    with Probe(env) as probe, NodeProcess.node("fusion_node", env, tmp_path, params_file=pf) as proc:
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        tf = probe.collect("/tf", TFMessage) if TFMessage is not None else []
        diags = probe.collect("/diagnostics", DiagnosticArray)
        pubs = [probe.publisher(t, c) for t, c in (("/ppoe/pose", PoseWithCovarianceStamped),
                                                    ("/joint_states", JointState),
                                                    ("/tag_bearing/observations", PointCloud2),
                                                    ("/camera/camera_info", CameraInfo))]
        for pub in pubs:
            probe.wait_for_subscribers(pub, proc)
        # a late subscriber of /tf_static: transient local gives it what was published at start-up
        static = probe.collect("/tf_static", TFMessage, TF_STATIC_QOS) if TFMessage is not None else []
        pubs[3].publish(CameraInfo(header=Header(frame_id="camera_optical_frame"), k=K.ravel().tolist(),
                                   d=[0.0] * 5, distortion_model="plumb_bob", width=640, height=480))
        t0 = probe.node.get_clock().now().nanoseconds
        for k in range(n_priors):
            stamp = ns_to_stamp(t0 + k * 20_000_000)
            pubs[1].publish(JointState(header=Header(stamp=stamp), name=names, position=list(ROVER_Q.values())))
            pubs[0].publish(pose_cov_stamped_msg(T_prior, cov_ros, stamp, "base_link"))
            if k == n_priors // 2:
                probe.spin_for(0.3)
                pubs[2].publish(cloud_from_observations(rows, Header(frame_id="camera_optical_frame", stamp=stamp)))
            probe.spin_for(0.02)
        probe.spin_until(lambda: len(fused) >= n_priors + 1, 30, proc, "every prior fused, and one update")
        probe.spin_for(1.0)
        alive = proc.alive()
        log = proc.output()
    return fused, tf, static, diags, log, alive, T_prior, model


@needs_tf2_msgs
@pytest.mark.ros
@pytest.mark.timeout(120)
def test_fusion_node_tf_carries_the_fused_pose_and_the_calibrated_camera(tmp_path):
    fused, tf, static, diags, log, alive, T_prior, model = _fusion_run(tmp_path, {})
    assert alive, log
    # one /tf message per fused pose, same stamp, frame and value
    assert len(tf) == len(fused), (len(tf), len(fused))
    for pose_msg, tf_msg in zip(fused, tf):
        (tr,) = tf_msg.transforms
        assert (tr.header.frame_id, tr.child_frame_id) == ("base_link", "tool_link_corrected")
        assert stamp_to_ns(tr.header.stamp) == stamp_to_ns(pose_msg.header.stamp)
        np.testing.assert_allclose(_T(tr), matrix_from_pose_msg(pose_msg.pose.pose), atol=1e-12)
    moved = max(np.linalg.norm(_T(m.transforms[0])[:3, 3] - T_prior[:3, 3]) for m in tf)
    assert moved > 0.005, f"the tag update should correct the tool by more than 5 mm, got {moved * 1e3:.2f} mm"
    # /tf_static: the calibrated camera (mount link tilt_link), with the diagnosed extrinsic
    (tr,) = static[-1].transforms
    assert (tr.header.frame_id, tr.child_frame_id) == ("tilt_link", "camera_optical_frame_calibrated")
    q = {n: 0.0 for n in model.joint_names}
    np.testing.assert_allclose(_T(tr), model.fk_mean(q, "tilt_link", "camera_optical_frame"), atol=1e-9)
    nominal = PPOEModel.from_files(ROVER_URDF, CONFIG / "robots" / "rover_model.yaml")
    assert np.linalg.norm(_T(tr)[:3, 3] - nominal.fk_mean(q, "tilt_link", "camera_optical_frame")[:3, 3]) > 0.02
    assert "TF: base_link -> tool_link_corrected on /tf" in log
    assert all(kv.key != "tf" for kv in diags[-1].status[0].values)


@needs_tf2_msgs
@pytest.mark.ros
@pytest.mark.timeout(120)
def test_fusion_node_tf_child_frame_that_is_a_urdf_link_is_refused_node_keeps_running(tmp_path):
    fused, tf, static, diags, log, alive, _, _ = _fusion_run(tmp_path, {"tf_child_frame": "tool_link"})
    assert alive, log
    assert "parameter tf_child_frame = 'tool_link': 'tool_link' is a link of the URDF" in log
    assert "/tf of the corrected tool is off" in log and "[ERROR]" in log
    assert len(fused) >= 31 and tf == []  # fused poses go on; nothing on /tf
    (tr,) = static[-1].transforms  # the calibrated camera is still published
    assert tr.child_frame_id == "camera_optical_frame_calibrated"
    status = diags[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert "tf_child_frame = 'tool_link'" in values["tf"] and "tf_child_frame" in status.message
    assert status.level >= b"\x01"


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_fusion_node_without_tf2_msgs_runs_with_tf_off_and_says_how_to_build_it(tmp_path, monkeypatch):
    fake = tmp_path / "no_tf2_msgs" / "tf2_msgs"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('tf2_msgs hidden by the test')\n")
    monkeypatch.setenv("PYTHONPATH", str(fake.parent))  # ros_env puts the repo in front of it
    monkeypatch.setattr("ppoe_ros.common.tf_broadcast.tf_message_class", lambda: None)
    fused, tf, static, diags, log, alive, _, _ = _fusion_run(tmp_path, {})
    assert alive, log
    assert "tf2_msgs is not importable: /tf and /tf_static are off" in log
    assert "scripts/build_tf2_msgs.py" in log
    assert len(fused) >= 31
    values = {kv.key: kv.value for kv in diags[-1].status[0].values}
    assert "tf2_msgs not importable" in values["tf"]


# ------------------------------------------------------------------------------------ live: kinematics


@needs_tf2_msgs
@pytest.mark.ros
@pytest.mark.timeout(120)
def test_kinematics_node_tf_equals_model_fk_with_split_joint_states(tmp_path):
    """Arm and gripper on separate /joint_states publishers: /tf carries each message's joints at its stamp,
    /tf_static the fixed joints; composed, they equal the model FK and the node's /ppoe/pose."""
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file

    from ppoe_ros.common.tf_broadcast import TF_STATIC_QOS, tf_message_class

    TFMessage = tf_message_class()
    model_file = _model_file(tmp_path, "arm7_model.yaml", ARM7_EFFECTS)
    model = PPOEModel.from_strings(ARM7_URDF.read_text(), model_file)
    env = ros_env(tmp_path)
    rng = np.random.default_rng(11)
    arm = [n for n in model.joint_names if n.startswith("joint_")]
    pf = write_params_file(tmp_path / "kin.yaml", {
        "robot_description": ARM7_URDF.read_text(), "model_file": str(model_file), "publish_tf": True,
        "joint_max_age": 0.0, "log_throttle": 0.0})
    with Probe(env) as probe, NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf) as proc:
        tf = probe.collect("/tf", TFMessage)
        poses = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        pub_arm = probe.publisher("/joint_states", JointState)
        pub_grip = probe.publisher("/joint_states", JointState)
        probe.wait_for_subscribers(pub_arm, proc)
        probe.wait_for_subscribers(pub_grip, proc)
        static = probe.collect("/tf_static", TFMessage, TF_STATIC_QOS)
        t0 = probe.node.get_clock().now().nanoseconds
        sent = []
        for k in range(6):
            stamp_ns = t0 + k * 10_000_000
            if k % 2 == 0:
                names, values = arm, rng.uniform(-1.0, 1.0, len(arm))
                pub = pub_arm
            else:
                names, values = ["finger_left_joint"], rng.uniform(0.0, 0.04, 1)
                pub = pub_grip
            pub.publish(JointState(header=Header(stamp=ns_to_stamp(stamp_ns)), name=names, position=list(values)))
            sent.append((stamp_ns, dict(zip(names, values))))
            probe.spin_for(0.1)
        probe.spin_until(lambda: len(tf) >= 6 and len(static) >= 1, 20, proc, "6 /tf messages and /tf_static")
        probe.spin_for(0.5)
        assert proc.alive()
        log = proc.output()
    assert len(tf) == 6, log
    children = [{tr.child_frame_id for tr in m.transforms} for m in tf]
    assert children[0] == {f"arm_link_{i}" for i in (1, 2, 4, 5, 6, 7)}  # joint_3 waits for the gripper
    assert children[1] == {"finger_left", "finger_right", "arm_link_3"}
    assert children[2] == {f"arm_link_{i}" for i in range(1, 8)}
    for (stamp_ns, _), m in zip(sent, tf):
        assert {stamp_to_ns(tr.header.stamp) for tr in m.transforms} == {stamp_ns}
    tree = {tr.child_frame_id: (tr.header.frame_id, _T(tr)) for tr in static[-1].transforms}
    assert set(tree) == {"mount_plate", "tool0", "gripper_link", "camera_link", "camera_optical_frame"}
    for m in tf:
        tree.update({tr.child_frame_id: (tr.header.frame_id, _T(tr)) for tr in m.transforms})
    q: dict[str, float] = {}
    for _, values in sent:
        q.update(values)
    for link in model.robot.links:
        np.testing.assert_allclose(_compose(tree, "base_link", link), model.fk_mean(q, "base_link", link),
                                   atol=1e-9, err_msg=link)
    assert len(poses) >= 3  # the pose output goes on beside TF
