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

from ppoe_ros.nodes.container import NODES, parse_node_specs  # noqa: E402

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
@pytest.mark.parametrize("module", NODE_TEST_MODULES)
def test_node_tests_pass_with_the_nodes_in_the_container(module: str) -> None:
    """Every live test of a node module passes with the node running inside ``ppoe_container``
    (``PPOE_TEST_CONTAINER=1``: ``ros_helpers.NodeProcess.node`` starts ``ppoe_container NODE --ros-args ...``)."""
    env = dict(os.environ, PPOE_TEST_CONTAINER="1")
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", f"test/{module}"],
                         env=env, cwd=REPO, capture_output=True, text=True, timeout=880)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert " passed" in res.stdout


@pytest.mark.ros
@pytest.mark.timeout(180)
def test_kinematics_and_fusion_nodes_in_one_process(tmp_path: Path) -> None:
    """Joint states in -> the kinematics node's prior -> the fusion node's fused pose, both nodes on one executor in
    one process, each with its own parameter file; both report on /diagnostics under their own names."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from sensor_msgs.msg import JointState

    from ppoe_core import PPOEModel
    from ppoe_ros.common import ns_to_stamp

    urdf = (CONFIG / "robots" / "arm7.urdf").read_text()
    model_file = str(CONFIG / "robots" / "arm7_model.yaml")
    kin = write_params_file(tmp_path / "kin.yaml", {"robot_description": urdf, "model_file": model_file,
                                                    "diagnostics_period": 0.2})
    fus = write_params_file(tmp_path / "fus.yaml", {"robot_description": urdf, "model_file": model_file,
                                                    "diagnostics_period": 0.2, "publish_tf": False})
    env = ros_env(tmp_path)
    cmd = [sys.executable, "-m", "ppoe_ros.nodes.container", f"kinematics_node:{kin}", f"fusion_node:{fus}",
           "--ros-args", "--log-level", "info"]
    model = PPOEModel.from_files(CONFIG / "robots" / "arm7.urdf", model_file)
    names = list(model.joint_names)
    with Probe(env) as probe, NodeProcess(cmd, env, tmp_path / "container.log") as proc:
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        priors = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        pub = probe.publisher("/joint_states", JointState)
        probe.wait_for_subscribers(pub, proc, n=2)  # both nodes take the joint states
        t0 = probe.node.get_clock().now().nanoseconds
        for k in range(20):
            msg = JointState(name=names, position=[0.1 * np.sin(0.1 * k + i) for i in range(len(names))])
            msg.header.stamp = ns_to_stamp(t0 + k * 10_000_000)
            pub.publish(msg)
            probe.spin_for(0.01)
        probe.spin_until(lambda: len(fused) >= 20, 30, proc, "20 fused poses")
        probe.spin_until(lambda: {s.name for d in diags for s in d.status} >= {
            "/kinematics_node: health", "/fusion_node: health"}, 10, proc, "both nodes' diagnostics")
        assert proc.alive()
        out = proc.output()
    assert len(priors) >= 20
    # no measurement: the fused pose is the prior, stamp for stamp
    by_stamp = {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in priors}
    for m in fused[:20]:
        p = by_stamp[(m.header.stamp.sec, m.header.stamp.nanosec)]
        cov_p = np.array(p.pose.covariance)
        np.testing.assert_allclose(np.array(m.pose.covariance), cov_p, rtol=1e-9, atol=1e-9 * np.abs(cov_p).max())
        assert (m.pose.pose.position.x, m.pose.pose.position.y) == (p.pose.pose.position.x, p.pose.pose.position.y)
    assert "compiled kernels" in out
