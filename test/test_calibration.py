"""Live calibration collector: the session (ppoe_core/cli/live_calibration.py) and the node's services.

The session's samples are taken from a shipped bag with a known effect (``effect_joint_offset``: joint_2 zero
offset +0.02 rad): one sample per ``/ground_truth/point`` with the joint state nearest it.  ``compute`` must find
the effect as ``ppoe diagnose`` finds it on the bag itself.  Live, ``ppoe play`` drives the node and the test
calls ``~/take_sample`` at each stop, then ``~/compute``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

from ppoe_core.cli.live_calibration import CalibrationSample, CalibrationSession
from ppoe_core.errors import PpoeError
from ppoe_core.io.bagio import read_bag

BAG = REPO / "bags" / "effect_joint_offset"
MODEL = REPO / "config" / "robots" / "arm7_model.yaml"


def _samples_from_bag() -> tuple[str, list[CalibrationSample]]:
    data = read_bag(BAG, load_images=False)
    js, gt = data.joint_states, data.ground_truth_point
    out = []
    for k in range(len(gt)):
        i = int(np.argmin(np.abs(js.stamps - gt.stamps[k])))
        out.append(CalibrationSample(float(gt.stamps[k]), tuple(js.names), js.positions[i].copy(), gt.frame_ids[k],
                                     np.asarray(gt.p[k], dtype=float)))
    return data.robot_description, out


def test_session_finds_the_joint_offset_and_writes_the_files(tmp_path: Path) -> None:
    urdf, samples = _samples_from_bag()
    session = CalibrationSession(urdf, MODEL)
    for s in samples:
        session.add(s)
    result = session.compute(tmp_path / "out")
    effects = {(e["name"], e["location"]): e for e in result.document["effects"]}
    assert ("joint_offset", "joint_2") in effects
    assert effects[("joint_offset", "joint_2")]["parameters"]["offset"] == pytest.approx(0.02, abs=0.002)
    assert result.document["residual_after"] < result.document["residual_before"]
    for name in ("diagnose.md", "diagnose.json", "model_diagnosed.yaml", "robot_calibrated.urdf",
                 "model_calibrated.yaml"):
        assert (tmp_path / "out" / name).is_file(), name
    assert json.loads((tmp_path / "out" / "diagnose.json").read_text())["effects"] == result.document["effects"]
    assert len(read_bag(result.bag, load_images=False).ground_truth_point) == len(samples)
    assert "joint_offset@joint_2" in result.summary() and "mm" in result.summary()


def test_session_refuses_bad_samples() -> None:
    urdf, samples = _samples_from_bag()
    session = CalibrationSession(urdf, MODEL)
    session.add(samples[0])
    with pytest.raises(PpoeError, match="not after the previous one"):
        session.add(samples[0])
    other = CalibrationSample(samples[1].stamp, samples[1].joint_names, samples[1].positions, "other_tracker",
                              samples[1].value)
    with pytest.raises(PpoeError, match="frame 'other_tracker'"):
        session.add(other)
    nan = CalibrationSample(samples[1].stamp, samples[1].joint_names, samples[1].positions * np.nan,
                            samples[1].frame, samples[1].value)
    with pytest.raises(PpoeError, match="NaN"):
        session.add(nan)
    with pytest.raises(PpoeError, match="no sample taken yet"):
        CalibrationSession(urdf, MODEL).write_bag(Path("/nonexistent/never"))


@pytest.mark.ros
def test_take_sample_and_compute_services_live(tmp_path: Path) -> None:
    """``ppoe play`` of the bag drives the node; ``~/take_sample`` after every point, then ``~/compute``."""
    pytest.importorskip("rclpy")
    import sys

    from geometry_msgs.msg import PointStamped
    from ros_helpers import NodeProcess, Probe, ros_env
    from std_srvs.srv import Trigger

    env = ros_env(tmp_path)
    out = tmp_path / "calib"
    cmd = [sys.executable, "-m", "ppoe_ros.common.calibration", "--ros-args", "-p", f"model_file:={MODEL}",
           "-p", f"calibration_out:={out}"]
    with Probe(env) as probe, NodeProcess(cmd, env, tmp_path / "calibration.log") as node:
        points = probe.collect("/ground_truth/point", PointStamped)
        take = probe.node.create_client(Trigger, "/ppoe_calibration/take_sample")
        compute = probe.node.create_client(Trigger, "/ppoe_calibration/compute")

        def call(client, timeout: float = 120.0):
            settle = 0.0 if client.service_is_ready() else 1.0  # a new client: see Probe.call
            return probe.call(client, Trigger.Request(), node, timeout, settle=settle)

        early = call(compute)
        assert not early.success and "no sample" in early.message
        player = NodeProcess.ppoe(["play", str(BAG), "--rate", "2", "--wait-for-subscribers", "30", "--topics",
                                   "/robot_description", "/joint_states", "/ground_truth/point"], env, tmp_path, "play")
        answers = []
        try:
            seen = 0
            while player.alive() or seen < len(points):
                probe.spin_for(0.01)
                if len(points) > seen:
                    seen = len(points)
                    answers.append(call(take, 30))
            again = call(take, 30)
        finally:
            player.stop()
        result = call(compute, 300)
        log = node.output()
    taken = [a for a in answers if a.success]
    assert len(taken) >= 50, [a.message for a in answers if not a.success][:5]
    assert not again.success and "no new point measurement" in again.message
    assert result.success, result.message + "\n" + log[-2000:]
    assert "joint_offset@joint_2" in result.message and f"{len(taken)} samples" in result.message
    assert (out / "robot_calibrated.urdf").is_file() and (out / "model_diagnosed.yaml").is_file()
