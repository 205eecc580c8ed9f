"""Two robots in one ROS graph (issue 11 item 5): namespaces and ``frame_prefix``.

Two kinematics nodes and two fusion nodes, started as separate processes in the namespaces /robot1 and /robot2
(``--ros-args -r __ns:=...``) of one DDS domain, with ``frame_prefix`` robot1/ and robot2/; each robot is fed its
own joint states.  Asserted from the test process: every output stays in its namespace with its robot's frames
and values (nothing on the root topics, nothing crossing), and /tf carries both robots' frames, prefixed.
Plus the relative topic defaults and the prefix helpers without DDS.
"""

from __future__ import annotations

import importlib
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")

from conftest import CONFIG  # noqa: E402

from ppoe_core import PPOEModel, lie  # noqa: E402
from ppoe_core.errors import MeasurementError  # noqa: E402

ARM7_URDF = CONFIG / "robots" / "arm7.urdf"
ARM7_MODEL = CONFIG / "robots" / "arm7_model.yaml"
JOINTS = ["joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6", "joint_7", "finger_left_joint",
          "finger_right_joint"]
Q = {"robot1": [0.3, -0.6, 0.2, 1.1, -0.4, 0.9, 0.1, 0.01, 0.01],
     "robot2": [-0.8, 0.4, -0.3, 0.7, 0.6, -0.5, 1.2, 0.02, 0.02]}

#: contract topics a bag carries: node defaults must not be absolute versions of them (they would not follow
#: the namespace), except the absolute ROS conventions
_ABSOLUTE_OK = {"/tf", "/tf_static", "/diagnostics"}


@pytest.mark.parametrize("node", ["kinematics_node", "fusion_node", "contact_node", "tag_bearing_node"])
def test_default_topics_are_relative(node):
    params = importlib.import_module(f"ppoe_ros.nodes.{node}").PARAMS
    topics = {p.name: p.default for p in params if p.name.endswith("_topic")}
    assert topics, node
    absolute = {k: v for k, v in topics.items() if v.startswith("/") and v not in _ABSOLUTE_OK}
    assert not absolute, f"{node}: absolute default topics do not follow the namespace: {absolute}"
    names = {p.name for p in params}
    if node != "tag_bearing_node":  # it publishes no frame of its own (the image's frame passes through)
        assert "frame_prefix" in names


def test_prefix_helpers():
    from ppoe_ros.common.frame_prefix import prefixed, unprefixed

    assert prefixed("robot1/", "base_link") == "robot1/base_link" and prefixed("robot1/", "") == ""
    assert unprefixed("robot1/", "robot1/tool0", "/robot1/imu") == "tool0"
    assert unprefixed("", "tool0", "/imu") == "tool0"
    with pytest.raises(MeasurementError, match="/robot1/imu: header.frame_id 'robot2/tool0' lacks the frame_prefix"):
        unprefixed("robot1/", "robot2/tool0", "/robot1/imu")


def _start(module: str, robot: str, env, tmp_path, params: dict):
    from ros_helpers import NodeProcess, write_params_file

    pf = write_params_file(tmp_path / f"{robot}_{module}.yaml", params)
    cmd = [sys.executable, "-m", f"ppoe_ros.nodes.{module}", "--ros-args", "-r", f"__ns:=/{robot}",
           "--params-file", str(pf)]
    return NodeProcess(cmd, env, tmp_path / f"{robot}_{module}.log")


def _T_tf(tr) -> np.ndarray:
    t, r = tr.transform.translation, tr.transform.rotation
    T = np.eye(4)
    T[:3, :3] = lie.matrix_from_quat(np.array([r.x, r.y, r.z, r.w]))
    T[:3, 3] = (t.x, t.y, t.z)
    return T


@pytest.mark.ros
@pytest.mark.timeout(240)
def test_two_robots_in_one_graph_outputs_do_not_cross(tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import Probe, ros_env
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header

    from ppoe_ros.common import matrix_from_pose_msg, ns_to_stamp
    from ppoe_ros.common.tf_broadcast import tf_message_class
    from ppoe_core.model.tf_frames import JointFrames

    TFMessage = tf_message_class()
    model = PPOEModel.from_files(ARM7_URDF, ARM7_MODEL)
    fk = {r: model.fk(dict(zip(JOINTS, q)), "base_link", "tool0") for r, q in Q.items()}
    assert np.linalg.norm(fk["robot1"][0][:3, 3] - fk["robot2"][0][:3, 3]) > 0.1  # the robots are told apart
    env = ros_env(tmp_path)  # one domain for both robots
    common = {"model_file": str(ARM7_MODEL), "robot_description": ARM7_URDF.read_text(), "log_throttle": 0.0}
    procs = []
    n = 20
    try:
        for robot in Q:
            procs.append(_start("kinematics_node", robot, env, tmp_path,
                                {**common, "frame_prefix": f"{robot}/", "publish_tf": TFMessage is not None}))
            procs.append(_start("fusion_node", robot, env, tmp_path, {**common, "frame_prefix": f"{robot}/"}))
        with Probe(env) as probe:
            box = {(r, kind): probe.collect(f"/{r}/ppoe/{kind}", PoseWithCovarianceStamped)
                   for r in Q for kind in ("pose", "fused_pose")}
            root = [probe.collect("/ppoe/pose", PoseWithCovarianceStamped),
                    probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)]
            tf = probe.collect("/tf", TFMessage) if TFMessage is not None else []
            pubs = {r: probe.publisher(f"/{r}/joint_states", JointState) for r in Q}
            for pub in pubs.values():
                probe.wait_for_subscribers(pub, procs[0], n=2, timeout=60)  # kinematics + fusion of that robot
            for r in Q:  # the fusion node's prior subscription matched too
                probe.spin_until(lambda r=r: probe.node.count_subscribers(f"/{r}/ppoe/pose") >= 2, 60, procs[1],
                                 f"the {r} fusion node on /{r}/ppoe/pose")
            probe.spin_for(0.5)
            # joint states until every output has n messages (a best-effort input may lose one under load)
            t0, sent, end = probe.node.get_clock().now().nanoseconds, 0, time.monotonic() + 90
            while not all(len(b) >= n for b in box.values()):
                assert time.monotonic() < end, f"outputs so far: { {k: len(b) for k, b in box.items()} }"
                for r, pub in pubs.items():
                    pub.publish(JointState(header=Header(stamp=ns_to_stamp(t0 + sent * 10_000_000)), name=JOINTS,
                                           position=Q[r]))
                sent += 1
                probe.spin_for(0.03)
            probe.spin_for(0.5)
        logs = [p.output() for p in procs]
        alive = [p.alive() for p in procs]
    finally:
        for p in procs:
            p.stop()
    assert all(alive), "\n".join(log[-2000:] for log in logs)
    assert root == [[], []], "an output leaked onto the root namespace"
    for (r, kind), msgs in box.items():
        assert n <= len(msgs) <= sent, (r, kind, len(msgs), sent)  # at most one per joint state of that robot
        T_fk = fk[r][0]
        for m in msgs:
            assert m.header.frame_id == f"{r}/base_link", (r, kind, m.header.frame_id)
            np.testing.assert_allclose(matrix_from_pose_msg(m.pose.pose), T_fk, atol=1e-9, err_msg=f"{r} {kind}")
    if TFMessage is None:
        return
    frames = JointFrames(model)
    for r, q in Q.items():
        expected = {f.child: f for f in frames.frames(JOINTS, q)}
        got = {tr.child_frame_id: tr for m in tf for tr in m.transforms if tr.child_frame_id.startswith(f"{r}/")}
        assert {f"{r}/{c}" for c in expected} <= set(got), (r, sorted(got))
        for child, f in expected.items():
            tr = got[f"{r}/{child}"]
            assert tr.header.frame_id == f"{r}/{f.parent}"
            np.testing.assert_allclose(_T_tf(tr), f.T_parent_child, atol=1e-9)
        corrected = got[f"{r}/tool0_corrected"]  # the fusion node's corrected tool, prefixed too
        assert corrected.header.frame_id == f"{r}/base_link"
        np.testing.assert_allclose(_T_tf(corrected), fk[r][0], atol=1e-9)
    unprefixed = [tr.child_frame_id for m in tf for tr in m.transforms if not tr.child_frame_id.startswith("robot")]
    assert not unprefixed, unprefixed


def test_in_process_nodes_follow_namespace_and_prefix(tmp_path):
    """Contact and fusion node built in /robot1 with frame_prefix robot1/: resolved topics, prefixed output frames,
    inputs of another robot (or without the prefix) refused, sensor-block frames checked with the prefix."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import Probe, ros_env
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Imu
    from std_msgs.msg import Header

    from ppoe_ros.common import pose_cov_stamped_msg
    from ppoe_ros.nodes.contact_node import ContactNode
    from ppoe_ros.nodes.fusion_node import FusionNode

    model = PPOEModel.from_files(ARM7_URDF, ARM7_MODEL)
    T, P = model.fk(dict(zip(JOINTS, Q["robot1"])), "base_link", "tool0")
    with Probe(ros_env(tmp_path)) as probe:
        contact = ContactNode(context=probe.context, namespace="/robot1", parameter_overrides=[
            Parameter("frame_prefix", value="robot1/"), Parameter("plane_frame", value="base_link"),
            Parameter("plane_xyz", value=[0.0, 0.0, 0.1]), Parameter("plane_rpy", value=[0.0, 0.0, 0.0]),
            Parameter("plane_sigma", value=[0.1, 0.1, 0.001, 0.01, 0.01, 0.1])])
        try:
            assert contact._pub.topic_name == "/robot1/contact/plane"
            assert contact._out.header.frame_id == "robot1/base_link"
        finally:
            contact.destroy_node()
        fusion = FusionNode(context=probe.context, namespace="/robot1", parameter_overrides=[
            Parameter("model_file", value=str(ARM7_MODEL)), Parameter("robot_description", value=ARM7_URDF.read_text()),
            Parameter("frame_prefix", value="robot1/"), Parameter("publish_tf", value=False),
            Parameter("sources", value=["tool_imu"]), Parameter("tool_imu.type", value="imu"),
            Parameter("tool_imu.topic", value="imu/tool")])
        try:
            sent = []
            fusion.pub.publish = sent.append
            assert fusion.pub.topic_name == "/robot1/ppoe/fused_pose"
            topics = {s.topic_name for s in fusion.subscriptions}
            assert {"/robot1/ppoe/pose", "/robot1/joint_states", "/robot1/imu/tool", "/robot1/contact/plane",
                    "/robot1/tag_bearing/observations", "/robot1/camera/camera_info"} <= topics
            cov_ros = lie.cov_local_to_ros(T, P)
            # the node takes its priors as bytes and publishes bytes (raw subscription and publisher)
            with pytest.raises(MeasurementError, match="prior frame 'base_link' is not base_frame 'robot1/base_link'"):
                fusion._prior(serialize_message(pose_cov_stamped_msg(T, cov_ros, 0, "base_link")))
            fusion._prior(serialize_message(pose_cov_stamped_msg(T, cov_ros, 1_000_000_000, "robot1/base_link")))
            assert [deserialize_message(m, PoseWithCovarianceStamped).header.frame_id for m in sent] == [
                "robot1/base_link"]
            src = fusion.sources.sources[0]
            assert src.topic == "/robot1/imu/tool"

            def imu(frame: str, accel) -> Imu:
                msg = Imu(header=Header(frame_id=frame))
                msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = accel
                msg.linear_acceleration_covariance = [1e-6, 0, 0, 0, 1e-6, 0, 0, 0, 1e-6]
                return msg

            with pytest.raises(MeasurementError, match="'robot2/tool0' lacks the frame_prefix 'robot1/'"):
                fusion.sources._on_message(src, imu("robot2/tool0", (0.0, 0.0, 9.8)))
            counts = fusion.stats.counts
            fusion.sources._on_message(src, imu("robot1/ghost", (0.0, 0.0, 9.8)))
            fusion.sources._on_message(src, imu("robot1/tool0", (0.0, 0.0, 5.0)))  # accelerating: skipped
            assert (counts["unknown_link"], counts["not_at_rest"], counts["measurements"]) == (1, 1, 0)
            fusion.sources._on_message(src, imu("robot1/tool0", (0.0, 0.0, 9.8)))
            assert fusion.pipeline.counts["measurements"] == 1  # the prefixed one reached the pipeline
        finally:
            fusion.destroy_node()
