"""Lifecycle (managed) nodes: ``ppoe_managed kinematics_node`` brought up through its lifecycle services.

Unconfigured: no parameter, no subscription.  ``configure`` declares the parameters and builds the model (the
URDF parameter), but subscribes no input: a joint-state publisher sees no subscriber and no pose comes.
``activate``: the subscription appears and poses come.  ``deactivate``: it is gone again.  A bad model file
fails ``configure`` with the reason, and the node stays unconfigured.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from ros_helpers import REPO, NodeProcess, Probe, ros_env, write_params_file  # noqa: E402

pytestmark = pytest.mark.ros

ROBOTS = REPO / "config" / "robots"


def _transition(probe: Probe, node: NodeProcess, name: str, transition_id: int) -> bool:
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    client = probe.node.create_client(ChangeState, f"/{name}/change_state")
    return bool(probe.call(client, ChangeState.Request(transition=Transition(id=transition_id)), node).success)


def _state(probe: Probe, node: NodeProcess, name: str) -> str:
    from lifecycle_msgs.srv import GetState

    client = probe.node.create_client(GetState, f"/{name}/get_state")
    return str(probe.call(client, GetState.Request(), node, resend_after=10.0).current_state.label)


def _managed(env: dict, tmp: Path, params: dict, log: str) -> NodeProcess:
    pf = write_params_file(tmp / f"{log}.yaml", params)
    cmd = [sys.executable, "-m", "ppoe_ros.common.lifecycle", "kinematics_node", "--ros-args", "--params-file", str(pf)]
    return NodeProcess(cmd, env, tmp / f"{log}.log")


def test_managed_kinematics_node_bring_up(tmp_path: Path) -> None:
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from lifecycle_msgs.msg import Transition
    from sensor_msgs.msg import JointState

    env = ros_env(tmp_path)
    params = {"model_file": str(ROBOTS / "arm7_model.yaml"), "robot_description": (ROBOTS / "arm7.urdf").read_text()}
    with Probe(env) as probe, _managed(env, tmp_path, params, "kin") as node:
        poses = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        js = probe.publisher("/joint_states", JointState)
        msg = JointState(name=[f"joint_{i}" for i in range(1, 8)], position=[0.1] * 7)
        assert _state(probe, node, "kinematics_node") == "unconfigured"
        assert _transition(probe, node, "kinematics_node", Transition.TRANSITION_CONFIGURE)
        assert _state(probe, node, "kinematics_node") == "inactive"
        probe.spin_for(1.5)
        assert js.get_subscription_count() == 0, "an inactive node subscribed its input"
        assert "model from parameter robot_description" in node.output()  # configure built the model
        assert _transition(probe, node, "kinematics_node", Transition.TRANSITION_ACTIVATE)
        probe.wait_for_subscribers(js, node)
        k = 0
        while not poses:
            msg.header.stamp.sec = 1 + k
            js.publish(msg)
            k += 1
            probe.spin_for(0.1)
            assert k < 300, node.output()[-2000:]
        assert _transition(probe, node, "kinematics_node", Transition.TRANSITION_DEACTIVATE)
        probe.spin_until(lambda: js.get_subscription_count() == 0, 20, node, "the subscription to go")
        assert _state(probe, node, "kinematics_node") == "inactive"


def test_configure_fails_on_a_bad_model_file(tmp_path: Path) -> None:
    from lifecycle_msgs.msg import Transition

    env = ros_env(tmp_path)
    with Probe(env) as probe, _managed(env, tmp_path, {"model_file": str(tmp_path / "missing.yaml")}, "bad") as node:
        assert not _transition(probe, node, "kinematics_node", Transition.TRANSITION_CONFIGURE)
        assert _state(probe, node, "kinematics_node") == "unconfigured"
        assert "configure failed" in node.output() and "missing.yaml" in node.output()
        assert node.alive()


def test_unknown_node_kind_is_named(tmp_path: Path) -> None:
    env = ros_env(tmp_path)
    proc = NodeProcess([sys.executable, "-m", "ppoe_ros.common.lifecycle", "no_such_node"], env, tmp_path / "x.log")
    assert proc.wait(60) == 2
    assert "no managed node 'no_such_node'" in proc.output() and "kinematics_node" in proc.output()


KINDS = {
    "kinematics_node": ("/joint_states", {"model_file": str(ROBOTS / "arm7_model.yaml"),
                                          "robot_description": (ROBOTS / "arm7.urdf").read_text()}),
    "tag_bearing_node": ("/camera/image_raw/compressed", {"model_file": str(ROBOTS / "rover_model.yaml")}),
    "contact_node": ("/wrench", {"plane_frame": "base_link", "plane_xyz": [0.0, 0.0, 0.0],
                                 "plane_rpy": [0.0, 0.0, 0.0], "plane_sigma": [0.0, 0.0, 0.001, 0.01, 0.01, 0.0]}),
    "fusion_node": ("/ppoe/pose", {"model_file": str(ROBOTS / "rover_model.yaml"),
                                   "robot_description": (ROBOTS / "rover.urdf").read_text(), "publish_tf": False}),
}


@pytest.mark.parametrize("kind", list(KINDS))
def test_every_managed_node_subscribes_only_while_active(tmp_path: Path, kind: str) -> None:
    from lifecycle_msgs.msg import Transition

    topic, params = KINDS[kind]
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "p.yaml", params)
    cmd = [sys.executable, "-m", "ppoe_ros.common.lifecycle", kind, "--ros-args", "--params-file", str(pf)]
    with Probe(env) as probe, NodeProcess(cmd, env, tmp_path / f"{kind}.log") as node:
        for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE,
                           Transition.TRANSITION_DEACTIVATE):
            if transition != Transition.TRANSITION_CONFIGURE:
                want = 1 if transition == Transition.TRANSITION_DEACTIVATE else 0
                probe.spin_until(lambda w=want: probe.node.count_subscribers(topic) == w, 20, node,
                                 f"{want} subscriber(s) of {topic}")
            assert _transition(probe, node, kind, transition), node.output()[-2000:]
        probe.spin_until(lambda: probe.node.count_subscribers(topic) == 0, 20, node, f"{topic} unsubscribed")
        assert "[ERROR]" not in node.output() and node.alive()
