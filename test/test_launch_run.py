"""The launch description, started from another directory with ``package://`` paths, runs a working graph.

launch / launch_ros have no wheel on PyPI for Jazzy (``pip install launch_ros`` / ``ros-jazzy-launch-ros``: no
distribution), so :mod:`launch_helpers` evaluates launch/ppoe.launch.py with recording stand-ins and the real
ament_index_python over an ament prefix of this checkout, and starts each described node with the command line
launch_ros would run, in a directory that holds neither the model nor the URDF.  The kinematics node must load
the model through ``package://`` (a model with perturbations gives a non-zero covariance; a missing one would be
a start-up error), publish in the launch namespace and log at the launch's level; the fusion node must fuse its
priors there.  A node started with a parameter file whose ``model_file`` is relative to that file loads it too.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from launch_helpers import launch_context, load_launch, node_command  # noqa: E402
from ros_helpers import REPO, NodeProcess, Probe, ros_env  # noqa: E402

pytestmark = pytest.mark.ros

ARM = [f"joint_{i}" for i in range(1, 8)]


def _joint_state(k: int):
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import ns_to_stamp

    msg = JointState(name=ARM, position=[0.3, 0.6, 0.0, -1.2, 0.0, 0.9 + 0.01 * k, 0.0])
    msg.header.stamp = ns_to_stamp(10**9 + k * 10**7)
    return msg


def _publish_until(probe: Probe, js, done, *procs: NodeProcess, timeout: float = 60.0) -> None:
    """Joint states every 0.1 s until ``done()`` (a best-effort subscriber may drop the first ones)."""
    end = time.monotonic() + timeout
    k = 0
    while not done():
        for proc in procs:
            assert proc.alive(), proc.output()[-3000:]
        assert time.monotonic() < end, "\n".join(p.output()[-2000:] for p in procs)
        js.publish(_joint_state(k))
        k += 1
        probe.spin_for(0.1)


def test_launch_description_runs_from_another_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import JointState

    module = load_launch(monkeypatch, tmp_path / "install")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mine.yaml").write_text("kinematics_node:\n  ros__parameters:\n    diagnostics_period: 0.3\n")
    monkeypatch.chdir(elsewhere)
    ctx = launch_context(module, model="package://ppoe_ros/config/robots/arm7_model.yaml",
                         urdf="package://ppoe_ros/config/robots/arm7.urdf", params_file="mine.yaml",
                         namespace="r1", log_level="debug", tag_bearing="false", contact="false")
    kin, fusion = module.launch_nodes(ctx)
    env = ros_env(tmp_path)
    env["AMENT_PREFIX_PATH"] = str(tmp_path / "install")
    with Probe(env) as probe:
        poses = probe.collect("/r1/ppoe/pose", PoseWithCovarianceStamped)
        fused = probe.collect("/r1/ppoe/fused_pose", PoseWithCovarianceStamped)
        js = probe.publisher("/r1/joint_states", JointState, 100)
        with NodeProcess(node_command(kin, tmp_path), env, tmp_path / "kin.log", cwd=elsewhere) as kin_proc, \
                NodeProcess(node_command(fusion, tmp_path), env, tmp_path / "fusion.log", cwd=elsewhere) as fus_proc:
            probe.wait_for_subscribers(js, kin_proc)
            probe.wait_for_publishers("/r1/ppoe/fused_pose", fus_proc)
            _publish_until(probe, js, lambda: len(fused) >= 3, kin_proc, fus_proc)
            kin_log, fus_log = kin_proc.output(), fus_proc.output()
    assert "[FATAL]" not in kin_log + fus_log
    assert "[DEBUG]" in kin_log, "log_level:=debug did not reach the node"
    cov = np.array(poses[-1].pose.covariance).reshape(6, 6)
    assert np.all(np.diag(cov) > 0), "the model (package://) was not loaded: zero covariance"
    assert fused[-1].header.frame_id == poses[-1].header.frame_id


def test_parameter_file_relative_model_from_any_directory(tmp_path: Path) -> None:
    """``model_file: ../robots/m.yaml`` in a parameter file is taken relative to that file (the issue's
    ``[FATAL] config/robots/rover_model.yaml: cannot read model file`` when started elsewhere)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from ppoe_ros.common import LATCHED_QOS

    (tmp_path / "robots").mkdir()
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cwd").mkdir()
    shutil.copy(REPO / "config" / "robots" / "arm7_model.yaml", tmp_path / "robots" / "m.yaml")
    (tmp_path / "cfg" / "kin.yaml").write_text("/**:\n  ros__parameters:\n    model_file: ../robots/m.yaml\n")
    env = ros_env(tmp_path)
    with Probe(env) as probe:
        probe.publisher("/robot_description", String, LATCHED_QOS).publish(
            String(data=(REPO / "config" / "robots" / "arm7.urdf").read_text()))
        poses = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        js = probe.publisher("/joint_states", JointState, 100)
        cmd = [sys.executable, "-m", "ppoe_ros.nodes.kinematics_node", "--ros-args", "--params-file",
               str(tmp_path / "cfg" / "kin.yaml")]
        with NodeProcess(cmd, env, tmp_path / "kin.log", cwd=tmp_path / "cwd") as proc:
            probe.wait_for_subscribers(js, proc)
            probe.spin_until(lambda: "model from topic" in proc.output(), 30, proc, "the model")
            _publish_until(probe, js, lambda: len(poses) >= 1, proc, proc)
    assert np.all(np.diag(np.array(poses[-1].pose.covariance).reshape(6, 6)) > 0)


def test_lifecycle_launch_brings_the_nodes_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """lifecycle:=true: the described managed kinematics node, started with launch_ros' command line, is driven
    through the transitions the launch's events describe (configure, then activate once inactive) and then
    publishes poses; before activate it subscribes nothing."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from sensor_msgs.msg import JointState

    module = load_launch(monkeypatch, tmp_path / "install")
    ctx = launch_context(module, model="package://ppoe_ros/config/robots/arm7_model.yaml",
                         urdf="package://ppoe_ros/config/robots/arm7.urdf", tag_bearing="false", contact="false",
                         fusion="false", lifecycle="true")
    node_action, handler, configure = module.launch_nodes(ctx)
    env = ros_env(tmp_path)
    env["AMENT_PREFIX_PATH"] = str(tmp_path / "install")
    with Probe(env) as probe, NodeProcess(node_command(node_action, tmp_path), env, tmp_path / "managed.log") as proc:
        poses = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        js = probe.publisher("/joint_states", JointState, 100)
        client = probe.node.create_client(ChangeState, "/kinematics_node/change_state")
        probe.spin_until(client.service_is_ready, 60, proc, "the lifecycle services")
        probe.spin_for(1.0)  # the server's answer writer matches after the client sees it (ros_helpers' Probe.call)
        for event in (configure.kwargs["event"], handler.args[0].kwargs["entities"][0].kwargs["event"]):
            if event.kwargs["transition_id"] == Transition.TRANSITION_ACTIVATE:
                assert js.get_subscription_count() == 0
            future = client.call_async(ChangeState.Request(transition=Transition(id=event.kwargs["transition_id"])))
            probe.spin_until(future.done, 60, proc, f"transition {event.kwargs['transition_id']}")
            assert future.result().success, proc.output()[-2000:]
        probe.wait_for_subscribers(js, proc)
        _publish_until(probe, js, lambda: len(poses) >= 3, proc)
    cov = np.array(poses[-1].pose.covariance).reshape(6, 6)
    assert np.all(np.diag(cov) > 0)
