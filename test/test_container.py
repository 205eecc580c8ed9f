"""``ppoe_container``: the nodes in one process pass the same live tests as the separate nodes, and several nodes in
one process work together (one executor)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from conftest import CONFIG, REPO  # noqa: E402

from ppoe_core import PPOEModel, lie  # noqa: E402

from ppoe_ros.nodes.container import NODES, parse_node_specs  # noqa: E402

#: environment variable: "1" runs the live tests of the nodes again with every node inside ``ppoe_container``
FULL_ENV = "PPOE_TEST_CONTAINER_FULL"
#: tag ids and camera matrix of the container test's rendered image
TAG_IDS = [3, 7]
K_CAM = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])
#: the live tests of the nodes, run again with every node started inside ``ppoe_container`` (ros_helpers)
NODE_TEST_MODULES = ("test_kinematics_node.py", "test_fusion_node.py", "test_tag_bearing_node.py",
                     "test_contact_node.py", "test_fusion_sources.py", "test_tf.py", "test_node_startup.py")


def test_node_specs_parsed_and_refused() -> None:
    nodes, rest = parse_node_specs(["ppoe_container", "kinematics_node:a.yaml,b.yaml", "fusion_node",
                                    "--ros-args", "-p", "x:=1"])
    assert nodes == [("kinematics_node", ["a.yaml", "b.yaml"]), ("fusion_node", [])]
    assert rest == ["ppoe_container", "--ros-args", "-p", "x:=1"]
    assert [n for n, _ in parse_node_specs(["ppoe_container"])[0]] == list(NODES)
    with pytest.raises(ValueError, match="unknown node 'kinematic_node'"):
        parse_node_specs(["ppoe_container", "kinematic_node"])
    with pytest.raises(ValueError, match="given twice"):
        parse_node_specs(["ppoe_container", "fusion_node", "fusion_node"])


def test_unknown_node_and_bad_params_file_exit_2(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    res = subprocess.run([sys.executable, "-m", "ppoe_ros.nodes.container", "kinematic_node"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "unknown node 'kinematic_node'" in res.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("- not a mapping\n")
    res = subprocess.run([sys.executable, "-m", "ppoe_ros.nodes.container", f"fusion_node:{bad}"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "bad.yaml" in res.stderr and "mapping" in res.stderr


@pytest.mark.ros
@pytest.mark.timeout(900)
@pytest.mark.skipif(os.environ.get(FULL_ENV) != "1", reason=f"the full re-run is opt-in: {FULL_ENV}=1 "
                    "(about 7 min; docs/performance.md 'CI time')")
@pytest.mark.parametrize("module", NODE_TEST_MODULES)
def test_node_tests_pass_with_the_nodes_in_the_container(module: str) -> None:
    """Every live test of a node module passes with the node running inside ``ppoe_container``
    (``PPOE_TEST_CONTAINER=1``: ``ros_helpers.NodeProcess.node`` starts ``ppoe_container NODE --ros-args ...``).
    Opt-in (``PPOE_TEST_CONTAINER_FULL=1``): it runs the node tests a second time; the default suite has
    :func:`test_four_nodes_in_one_container_live`."""
    env = dict(os.environ, PPOE_TEST_CONTAINER="1")
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", f"test/{module}"],
                         env=env, cwd=REPO, capture_output=True, text=True, timeout=880)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert " passed" in res.stdout


def _four_node_params(tmp_path: Path) -> tuple[list[str], PPOEModel]:
    """The container's node specs (each node with its own parameter file) and the arm7 model."""
    from ros_helpers import write_params_file

    urdf = (CONFIG / "robots" / "arm7.urdf").read_text()
    model_file = str(CONFIG / "robots" / "arm7_model.yaml")
    common = {"diagnostics_period": 0.2, "log_throttle": 0.0}
    files = {
        "kinematics_node": {"robot_description": urdf, "model_file": model_file, **common},
        "fusion_node": {"robot_description": urdf, "model_file": model_file, "publish_tf": False, **common},
        "tag_bearing_node": {"tag_ids": TAG_IDS, **common},
        "contact_node": {"model_file": str(CONFIG / "robots" / "humanoid_model.yaml"), **common},
    }
    specs = [f"{name}:{write_params_file(tmp_path / f'{name}.yaml', params)}" for name, params in files.items()]
    return specs, PPOEModel.from_files(CONFIG / "robots" / "arm7.urdf", model_file)


def _tag_image() -> bytes:
    """PNG of two tags (ids :data:`TAG_IDS`) rendered 0.5 m in front of the camera :data:`K_CAM`."""
    import cv2

    from ppoe_core.sensing import tags

    T1 = lie.from_xyz_rpy([-0.07, 0.02, 0.5], [np.pi + 0.25, -0.2, 0.1])
    T2 = lie.from_xyz_rpy([0.08, -0.03, 0.55], [np.pi - 0.15, 0.3, -0.4])
    img, drawn = tags.render_tags((640, 480), K_CAM, np.zeros(5), [T1, T2], TAG_IDS, 0.06, supersample=2)
    assert sorted(drawn) == TAG_IDS
    return bytes(cv2.imencode(".png", img)[1].tobytes())


@pytest.mark.ros
@pytest.mark.timeout(180)
def test_four_nodes_in_one_container_live(tmp_path: Path) -> None:
    """The kinematics, fusion, tag and contact nodes in ONE ``ppoe_container`` process (one executor, each node with
    its own parameter file), each driven through live topics: a message in, the expected message out; a bad message
    to each, logged with the reason, and each node still answers after it; all four report on /diagnostics."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped, WrenchStamped
    from ros_helpers import NodeProcess, Probe, ros_env
    from sensor_msgs.msg import CameraInfo, CompressedImage, JointState, PointCloud2

    from ppoe_ros.common import ns_to_stamp, stamp_to_ns
    from ppoe_ros.common.tag_cloud import observations_from_cloud

    specs, model = _four_node_params(tmp_path)
    names = list(model.joint_names)
    env = ros_env(tmp_path)
    cmd = [sys.executable, "-m", "ppoe_ros.nodes.container", *specs, "--ros-args", "--log-level", "info"]
    with Probe(env) as probe, NodeProcess(cmd, env, tmp_path / "container.log") as proc:
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        priors = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        planes = probe.collect("/contact/plane", PoseWithCovarianceStamped)
        obs = probe.collect("/tag_bearing/observations", PointCloud2)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        pub_js = probe.publisher("/joint_states", JointState)
        pub_wrench = probe.publisher("/wrench", WrenchStamped)
        pub_img = probe.publisher("/camera/image_raw/compressed", CompressedImage)
        pub_info = probe.publisher("/camera/camera_info", CameraInfo)
        probe.wait_for_subscribers(pub_js, proc, n=2)  # the kinematics and the fusion node
        for pub in (pub_wrench, pub_img, pub_info):
            probe.wait_for_subscribers(pub, proc)
        t0 = probe.node.get_clock().now().nanoseconds

        def joints(k: int, bad: bool = False) -> JointState:
            q = [0.1 * np.sin(0.1 * k + i) for i in range(len(names))]
            msg = JointState(name=names, position=[float("nan")] + q[1:] if bad else q)
            msg.header.stamp = ns_to_stamp(t0 + k * 10_000_000)
            return msg

        # kinematics -> fusion: 10 joint states, a NaN one, 10 more: 20 priors and 20 fused poses
        for k in range(21):
            pub_js.publish(joints(k, bad=k == 10))
            probe.spin_for(0.01)
        probe.spin_until(lambda: len(fused) >= 20 and len(priors) >= 20, 30, proc, "20 priors and 20 fused poses")
        # contact: in contact, a NaN wrench, in contact again: two planes
        for k, force in enumerate([(0.0, 0.0, -6.0), (float("nan"), 0.0, 0.0), (0.0, 0.0, -7.0)]):
            w = WrenchStamped()
            w.header.stamp = ns_to_stamp(t0 + k * 10_000_000)
            w.header.frame_id = "fingertip"
            w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = force
            pub_wrench.publish(w)
        probe.spin_until(lambda: len(planes) >= 2, 10, proc, "two contact planes")
        # tag node: camera_info, an image, an empty image, the image again: two observation clouds
        info = CameraInfo(width=640, height=480, k=K_CAM.ravel().tolist(), d=[0.0] * 5, distortion_model="plumb_bob")
        info.header.frame_id = "camera_optical_frame"
        png = _tag_image()
        for k, data in enumerate([png, b"", png]):
            pub_info.publish(info)
            probe.spin_for(0.2)
            img = CompressedImage(format="png", data=data)
            img.header.frame_id = "camera_optical_frame"
            img.header.stamp.sec = k + 1
            pub_img.publish(img)
            probe.spin_for(0.2)
        probe.spin_until(lambda: len(obs) >= 2, 20, proc, "two tag observation clouds")
        probe.spin_until(lambda: {s.name for d in diags for s in d.status} >= {
            "/kinematics_node: health", "/fusion_node: health", "/tag_bearing_node: health",
            "/contact_node: health"}, 10, proc, "the four nodes' diagnostics")
        assert proc.alive()
        out = proc.output()
    assert "NaN or infinite value for joint(s) 'joint_1'" in out
    assert "bad message on /wrench: non-finite wrench" in out and "empty image" in out
    assert "compiled kernels" in out
    # fused = prior, stamp for stamp (no measurement before the tag images)
    by_stamp = {stamp_to_ns(m.header.stamp): m for m in priors}
    assert sorted(by_stamp) == [t0 + k * 10_000_000 for k in range(21) if k != 10]
    for m in fused[:20]:
        p = by_stamp[stamp_to_ns(m.header.stamp)]
        cov_p = np.array(p.pose.covariance)
        np.testing.assert_allclose(np.array(m.pose.covariance), cov_p, rtol=1e-9, atol=1e-9 * np.abs(cov_p).max())
        assert (m.pose.pose.position.x, m.pose.pose.position.y) == (p.pose.pose.position.x, p.pose.pose.position.y)
    T_q = model.fk(dict(zip(names, joints(20).position)))[0]
    last = by_stamp[t0 + 20 * 10_000_000].pose.pose.position
    np.testing.assert_allclose([last.x, last.y, last.z], T_q[:3, 3], atol=1e-12)
    assert [stamp_to_ns(m.header.stamp) for m in planes] == [t0, t0 + 20_000_000]
    assert [m.header.stamp.sec for m in obs] == [1, 3]
    ids = observations_from_cloud(obs[-1])["id"]
    assert sorted(set(ids.tolist())) == TAG_IDS and len(ids) == 10
