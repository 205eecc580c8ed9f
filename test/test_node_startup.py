"""Every node with a missing or broken ``--params-file``: one line naming the file (and the YAML line), exit 2,
no RCLError traceback (issue 13 item 12)."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("rclpy")

from ros_helpers import ros_env  # noqa: E402

pytestmark = pytest.mark.ros
NODES = ["kinematics_node", "tag_bearing_node", "contact_node", "fusion_node"]


@pytest.mark.parametrize("node", NODES)
def test_missing_or_broken_params_file_is_one_clear_line(tmp_path, node):
    broken = tmp_path / "broken.yaml"
    broken.write_text("/**:\n  ros__parameters: [1, 2\n")
    cases = [(tmp_path / "missing.yaml", f"{tmp_path / 'missing.yaml'}: cannot read parameter file"),
             (broken, f"{broken}:3: parameter file does not parse")]
    for path, expected in cases:
        res = subprocess.run([sys.executable, "-m", f"ppoe_ros.nodes.{node}", "--ros-args", "--params-file", str(path)],
                             env=ros_env(tmp_path), capture_output=True, text=True, timeout=60)
        assert res.returncode == 2, res.stderr
        assert expected in res.stderr and "Traceback" not in res.stderr and "RCLError" not in res.stderr, res.stderr


@pytest.mark.parametrize("node,typo,meant", [("kinematics_node", "joint_max_agee", "joint_max_age"),
                                             ("fusion_node", "gate_probabilty", "gate_probability"),
                                             ("contact_node", "force_treshold", "force_threshold"),
                                             ("tag_bearing_node", "zzz_unrelated", None)])
def test_unknown_parameter_key_is_reported_with_the_closest_name(tmp_path, node, typo, meant):
    """A misspelled key in a node's parameter file is reported at start-up with the closest valid name (or the
    valid names), and the node keeps running."""
    import time

    import yaml
    from ros_helpers import REPO, NodeProcess

    params = yaml.safe_load((REPO / "config" / "nodes" / f"{node}.yaml").read_text())
    params[next(iter(params))]["ros__parameters"][typo] = 1.0
    if node == "contact_node":  # its shipped file leaves the plane to a model YAML
        params[next(iter(params))]["ros__parameters"].update(plane_frame="base_link", plane_xyz=[0.0, 0.0, 0.0],
                                                            plane_rpy=[0.0, 0.0, 0.0], plane_sigma=[0.001] * 6)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    proc = NodeProcess.node(node, ros_env(tmp_path), tmp_path, params_file=path)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and f"unknown parameter '{typo}'" not in proc.output():
            assert proc.alive(), proc.output()
            time.sleep(0.2)
        out = proc.output()
        assert f"unknown parameter '{typo}' ignored" in out, out
        assert (f"(did you mean '{meant}'?)" in out) if meant else ("(valid: " in out)
        time.sleep(0.5)
        assert proc.alive(), out
    finally:
        proc.stop()
