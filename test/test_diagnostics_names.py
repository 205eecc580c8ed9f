"""``/diagnostics`` of two namespaced robots: statuses named ``<namespace>/<node>: health``, ``hardware_id`` = robot.

Two kinematics nodes (robot ``arm7`` in /r1 with the URDF from its topic, robot ``planar3`` in /r2 with the URDF as
a parameter) and a contact node in /r1 (no URDF of its own: the robot_description topic of its namespace names
the robot) publish on the one global ``/diagnostics``; every status must say which node and which robot it is.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from ros_helpers import REPO, NodeProcess, Probe, ros_env, write_params_file  # noqa: E402

from ppoe_ros.common.diagnostics import status_name, urdf_robot_name  # noqa: E402

pytestmark = pytest.mark.ros

ARM7 = REPO / "config" / "robots" / "arm7.urdf"
PLANAR3 = REPO / "config" / "robots" / "planar3.urdf"
CONTACT_PLANE = ["-p", "plane_frame:=base_link", "-p", "plane_xyz:=[0.0, 0.0, 0.0]", "-p", "plane_rpy:=[0.0, 0.0, 0.0]",
                 "-p", "plane_sigma:=[0.0, 0.0, 0.001, 0.01, 0.01, 0.0]"]


def test_status_name_and_robot_name_helpers() -> None:
    assert status_name("/r1/kinematics_node") == "/r1/kinematics_node: health"
    assert urdf_robot_name(ARM7.read_text()) == "arm7"
    assert urdf_robot_name("<?xml version='1.0'?>\n<robot  xmlns:xacro='x' name = 'a b'>") == "a b"
    assert urdf_robot_name("<robots name='no'/>") == ""


def _node(module: str, env: dict, tmp: Path, name: str, ros_args: list[str]) -> NodeProcess:
    cmd = [sys.executable, "-m", f"ppoe_ros.nodes.{module}", "--ros-args", *ros_args, "-p", "diagnostics_period:=0.2"]
    return NodeProcess(cmd, env, tmp / f"{name}.log")


def test_two_robots_statuses_do_not_collide(tmp_path: Path) -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import String

    from ppoe_ros.common import LATCHED_QOS

    env = ros_env(tmp_path)
    params = write_params_file(tmp_path / "r2.yaml", {"robot_description": PLANAR3.read_text()})
    want = {"/r1/kinematics_node: health": "arm7", "/r2/kinematics_node: health": "planar3",
            "/r1/contact_node: health": "arm7"}
    with Probe(env) as probe:
        probe.publisher("/r1/robot_description", String, LATCHED_QOS).publish(String(data=ARM7.read_text()))
        diags = probe.collect("/diagnostics", DiagnosticArray)
        seen: dict[str, str] = {}

        def collect() -> bool:
            for d in diags:
                for st in d.status:
                    seen[st.name] = st.hardware_id
            return all(seen.get(k) == v for k, v in want.items())

        with _node("kinematics_node", env, tmp_path, "kin_r1", ["-r", "__ns:=/r1"]) as a, \
                _node("kinematics_node", env, tmp_path, "kin_r2",
                      ["-r", "__ns:=/r2", "--params-file", str(params)]) as b, \
                _node("contact_node", env, tmp_path, "contact_r1", ["-r", "__ns:=/r1", *CONTACT_PLANE]) as c:
            try:
                probe.spin_until(collect, 60, None, "the three statuses with their robots")
            except AssertionError:
                raise AssertionError(f"seen {seen}\n{a.output()[-1500:]}\n{b.output()[-1500:]}\n"
                                     f"{c.output()[-1500:]}") from None
    assert "kinematics_node" not in seen, "a status still carries the bare node name"
