"""A shipped bag played the way ``ros2 bag play`` plays it reaches our nodes; ``ppoe play --ros-args`` namespaces.

``ros2 bag`` is not installable here (no rosbag2_py wheel), so :func:`_rosbag2_like_publishers` plays a bag as
rosbag2's player does: each topic offered with its recorded profile by rosbag2's rule
(:func:`ppoe_core.io.bag_qos.playback_qos` without a fallback: reliable *volatile* when the metadata holds no
profile).  With the shipped metadata a kinematics node started *after* the URDF was published (as a user
starts nodes on a playing bag) gets it and publishes poses; with the metadata the bags had before
(``offered_qos_profiles: []``) it never does, and rclpy names the incompatible QoS.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from ros_helpers import REPO, NodeProcess, Probe, ros_env  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402

from ppoe_core.io.bag_qos import playback_qos, recorded_qos  # noqa: E402

pytestmark = pytest.mark.ros

BAG = REPO / "bags" / "no_effect"


def _rosbag2_like_publishers(probe: Probe, bag: Path, topics: list[str], metadata_of: Path) -> dict[str, tuple]:
    """Publishers as rosbag2's player makes them and the bag's messages (the first 300 per topic).

    rosbag2 takes the profiles from ``metadata.yaml`` (here: that of ``metadata_of``) and offers the recorded
    one, else reliable volatile."""
    from ppoe_ros.common import message_class
    from ppoe_ros.common.bag_qos import qos_to_rclpy

    recorded = recorded_qos(metadata_of)
    out: dict[str, tuple] = {}
    with Reader(bag) as reader:
        conns = {c.topic: c for c in reader.connections if c.topic in topics}
        msgs: dict[str, list[bytes]] = {t: [] for t in conns}
        for conn, _, data in reader.messages(connections=list(conns.values())):
            if len(msgs[conn.topic]) < 300:
                msgs[conn.topic].append(bytes(data))
    for topic, conn in conns.items():
        qos = qos_to_rclpy(playback_qos(recorded[topic]), depth=10)
        out[topic] = (probe.node.create_publisher(message_class(conn.msgtype), topic, qos), msgs[topic])
    return out


def _kinematics(env: dict, tmp: Path, name: str, ros_args: list[str] = ()) -> NodeProcess:
    cmd = [sys.executable, "-m", "ppoe_ros.nodes.kinematics_node", "--ros-args", *ros_args,
           "-p", "diagnostics_period:=0.5"]
    return NodeProcess(cmd, env, tmp / f"{name}.log")


def _play_then_start_node(tmp: Path, metadata_of: Path, wait_for_poses: float) -> tuple[int, str]:
    """URDF published first, node started after, then joint states: how many poses came, and the node's log."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    env = ros_env(tmp)
    with Probe(env) as probe:
        pubs = _rosbag2_like_publishers(probe, BAG, ["/robot_description", "/joint_states"], metadata_of)
        desc_pub, (urdf,) = pubs["/robot_description"]
        desc_pub.publish(urdf)
        probe.spin_for(0.5)
        poses = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        js_pub, joint_states = pubs["/joint_states"]
        with _kinematics(env, tmp, metadata_of.name) as node:
            probe.wait_for_subscribers(js_pub, node)
            for data in joint_states:
                js_pub.publish(data)
                probe.spin_for(0.005)
            end = time.monotonic() + wait_for_poses
            while time.monotonic() < end and len(poses) < 50:
                probe.spin_for(0.1)
            return len(poses), node.output()


def test_rosbag2_like_player_latches_the_shipped_urdf(tmp_path: Path) -> None:
    n_poses, log = _play_then_start_node(tmp_path, BAG, 30.0)
    assert n_poses >= 50, f"the node got no URDF from the played bag ({n_poses} poses)\n{log[-3000:]}"


def test_without_recorded_qos_the_urdf_never_arrives(tmp_path: Path) -> None:
    """The control: the same bag with the metadata the shipped bags had before (no profiles) is played volatile
    by rosbag2's rule, and the node's transient-local subscription never matches it."""
    import yaml

    bag = tmp_path / "no_qos"
    bag.mkdir()
    shutil.copy2(BAG / "metadata.yaml", bag)
    meta = bag / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    for entry in doc["rosbag2_bagfile_information"]["topics_with_message_count"]:
        entry["topic_metadata"]["offered_qos_profiles"] = []
    meta.write_text(yaml.safe_dump(doc))
    n_poses, log = _play_then_start_node(tmp_path, bag, 5.0)
    assert n_poses == 0
    assert "offering incompatible QoS" in log and "DURABILITY" in log, log[-3000:]


def test_ppoe_play_ros_args_namespace_drives_a_namespaced_graph(tmp_path: Path) -> None:
    """``ppoe play BAG --ros-args -r __ns:=/r1``: the bag's topics appear under /r1 (the URDF latched, as
    recorded), a kinematics node in /r1 publishes /r1/ppoe/pose, nothing reaches the root namespace."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    env = ros_env(tmp_path)
    with Probe(env) as probe:
        namespaced = probe.collect("/r1/ppoe/pose", PoseWithCovarianceStamped)
        root = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        with _kinematics(env, tmp_path, "kin_r1", ["-r", "__ns:=/r1"]) as node:
            probe.wait_for_publishers("/r1/ppoe/pose", node)
            player = NodeProcess.ppoe(["play", str(BAG), "--topics", "/robot_description", "/joint_states",
                                       "--rate", "4", "--wait-for-subscribers", "30", "--ros-args",
                                       "-r", "__ns:=/r1", "-r", "__node:=player_r1"], env, tmp_path, "play_r1")
            try:
                probe.spin_until(lambda: len(namespaced) >= 50, 60, player, "50 poses on /r1/ppoe/pose")
            finally:
                player.stop()
            log = player.output()
            assert node.alive(), node.output()[-3000:]
    assert not root, "a pose reached the root namespace"
    assert "/r1/joint_states" in log and "/r1/robot_description" in log, log
    assert "r1.player_r1" in log, "the node name and namespace from --ros-args are not used"
    assert namespaced[-1].header.frame_id == "base_link"
