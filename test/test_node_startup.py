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
