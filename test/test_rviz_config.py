"""config/rviz/ppoe.rviz shows what the nodes publish: the topics, their QoS and the marker namespaces."""

from __future__ import annotations

import importlib

import pytest
import yaml
from conftest import REPO

RVIZ = REPO / "config" / "rviz" / "ppoe.rviz"

#: rviz_default_plugins display classes of RViz 2 Jazzy used here (message type each one reads)
KNOWN = {"rviz_default_plugins/Grid": None, "rviz_default_plugins/RobotModel": "std_msgs/msg/String",
         "rviz_default_plugins/TF": None, "rviz_default_plugins/PoseWithCovariance":
         "geometry_msgs/msg/PoseWithCovarianceStamped", "rviz_default_plugins/MarkerArray":
         "visualization_msgs/msg/MarkerArray"}


def _displays() -> list[dict]:
    return yaml.safe_load(RVIZ.read_text())["Visualization Manager"]["Displays"]


def _default(module: str, name: str) -> str:
    params = importlib.import_module(module)
    specs = getattr(params, "PARAMS", None) or params.MARKER_PARAMS
    return "/" + next(s.default for s in specs if s.name == name)


def test_displays_are_known_and_read_the_nodes_topics() -> None:
    pytest.importorskip("rclpy")
    displays = _displays()
    assert all(d["Class"] in KNOWN for d in displays), [d["Class"] for d in displays]
    topics = {d["Topic"]["Value"]: d for d in displays if "Topic" in d}
    assert set(topics) == {_default("ppoe_ros.nodes.kinematics_node", "pose_topic"),
                           _default("ppoe_ros.nodes.fusion_node", "fused_topic"),
                           _default("ppoe_ros.common.markers", "markers_topic")}
    for d in topics.values():
        assert d["Topic"]["Reliability Policy"] == "Reliable" and d["Topic"]["Durability Policy"] == "Volatile"
    (robot,) = [d for d in displays if d["Class"] == "rviz_default_plugins/RobotModel"]
    assert robot["Description Source"] == "Topic"
    assert robot["Description Topic"]["Value"] == "/robot_description"
    assert robot["Description Topic"]["Durability Policy"] == "Transient Local"  # the nodes' latched URDF
    (markers,) = [d for d in displays if d["Class"] == "rviz_default_plugins/MarkerArray"]
    source = (REPO / "ppoe_ros" / "common" / "markers.py").read_text()
    for ns in markers["Namespaces"]:
        assert f'"{ns}"' in source, f"marker namespace {ns} is not published"
    assert yaml.safe_load(RVIZ.read_text())["Visualization Manager"]["Global Options"]["Fixed Frame"] == "base_link"


def test_rviz_config_is_installed() -> None:
    text = (REPO / "setup.py").read_text()
    assert '"share/" + PACKAGE + "/config/rviz", sorted(glob("config/rviz/*.rviz"))' in text
