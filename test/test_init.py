"""``ppoe init`` (ppoe_core.robot.model_init, ppoe_core.io.bag_facts, ppoe_core.cli.init) on robots of three shapes
and on a measured dataset's URDF: the YAML loads, the guesses are right or marked ``# GUESS: confirm``, and
``ppoe diagnose`` runs on it without edits.

Robots: ``ind6`` (config/robots/ind6_dh.yaml: a 6-axis arm on a mount plate, a camera at the side), a mobile
manipulator (test/data/init/mobile_dh.yaml: a mast with lift, pan, tilt and a camera, an arm, an IMU on the deck)
and a dual-arm torso (test/data/init/torso_dh.yaml).  Bags: short simulated recordings (test/data/init/*scenario*,
different from the tutorial's), and the Motoman dataset imported (``PPOE_DATASETS``, marker ``datasets``).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import CONFIG_ROBOTS, DATASETS, REPO

from ppoe_core.robot.config import load_model_config
from ppoe_core.robot.dh import dh_to_urdf
from ppoe_core.robot.model_init import GUESS, guess_frames
from ppoe_core.robot.urdf import parse_urdf
from ppoe_ros.cli import main

DATA = REPO / "test" / "data" / "init"
#: robot -> (DH table, expected base, expected tool)
ROBOTS = {
    "ind6": (CONFIG_ROBOTS / "ind6_dh.yaml", "world", "tool0"),
    "mobile": (DATA / "mobile_dh.yaml", "base_link", "gripper_tcp"),
    "torso": (DATA / "torso_dh.yaml", "pelvis", "left_tcp"),
}


def _urdf(tmp: Path, name: str) -> Path:
    path = tmp / f"{name}.urdf"
    if not path.exists():
        path.write_text(dh_to_urdf(ROBOTS[name][0]), encoding="utf-8")
    return path


def _line(text: str, key: str) -> str:
    return next(ln for ln in text.splitlines() if ln.strip().startswith(key))


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_init_from_urdf_loads_and_marks_its_guesses(tmp_path, name, capsys):
    urdf = _urdf(tmp_path, name)
    out = tmp_path / "model.yaml"
    assert main(["init", "--urdf", str(urdf), "--out", str(out)]) == 0
    robot = parse_urdf(urdf)
    cfg = load_model_config(out, robot)
    _, base, tool = ROBOTS[name]
    assert (cfg.frames.base, cfg.frames.tool) == (base, tool)
    chain = robot.path_from_root(tool)
    assert list(cfg.perturbations) == chain          # every joint base -> tool, fixed ones included
    movable = [j for j in chain if robot.joints[j].movable]
    assert list(cfg.joint_noise) == movable
    for jn in chain:                                  # the default prior, as documented
        sigma = np.sqrt(np.diag(cfg.perturbations[jn].covariance))
        assert sigma[3] == pytest.approx(0.004 if robot.joints[jn].movable else 0.003)
    text = out.read_text()
    assert GUESS in _line(text, "tool:")
    assert "wrote" in capsys.readouterr().err


def test_guess_frames_on_the_shipped_robots():
    """The shipped models name these tools: the leaf of the longest chain, or the link its tags / fingers hang on."""
    expected = {"arm7": "tool0", "rover": "tool_link", "planar3": "tool0", "humanoid": "fingertip"}
    for name, tool in expected.items():
        robot = parse_urdf(CONFIG_ROBOTS / f"{name}.urdf")
        base, guessed, others = guess_frames(robot)
        assert (base, guessed) == (robot.root, tool), name
        assert tool not in others


def test_dual_arm_lists_the_other_hand(tmp_path):
    robot = parse_urdf(_urdf(tmp_path, "torso"))
    assert guess_frames(robot) == ("pelvis", "left_tcp", ["right_tcp"])


def _simulate(tmp: Path, scenario: str) -> Path:
    bag = tmp / Path(scenario).stem
    assert main(["simulate", str(DATA / scenario), "--out", str(bag), "--truth", "none"]) == 0   # DATA / abs = abs
    return bag


def _diagnose_runs(bag: Path, model: Path, capsys) -> dict:
    capsys.readouterr()
    assert main(["diagnose", str(bag), "--model", str(model), "--json", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "check:" not in captured.err               # ppoe check has no failure to print first
    return json.loads(captured.out)


def test_mobile_manipulator_bag_guesses(tmp_path, capsys):
    bag = _simulate(tmp_path, "mobile_scenario.yaml")
    urdf = _urdf(tmp_path, "mobile")
    out = tmp_path / "model.yaml"
    assert main(["init", "--urdf", str(urdf), "--bag", str(bag), "--out", str(out)]) == 0
    cfg = load_model_config(out, parse_urdf(urdf))
    # truth (test/data/init/mobile_sim_model.yaml): reflector on gripper_tcp at [0.03, 0, -0.02]
    (tracker,) = cfg.trackers
    assert (tracker.topic, tracker.link) == ("/ground_truth/point", "gripper_tcp")
    np.testing.assert_allclose(tracker.xyz, [0.03, 0.0, -0.02], atol=0.002)
    assert cfg.camera is not None and cfg.camera.frame == "mast_camera_optical"
    assert {n: i.link for n, i in cfg.imus.items()} == {"deck": "deck_imu"}
    text = out.read_text()
    assert "mast_camera_joint" in cfg.perturbations and GUESS in _line(text, "mast_camera_joint:")
    # the mast moves the camera: its joints get a prior too, marked
    assert {"mast_lift", "mast_pan", "mast_tilt"} <= set(cfg.perturbations) and GUESS in _line(text, "mast_pan:")
    # the tag seen (truth: id 6 on gripper_tcp at [-0.03, 0, -0.05], 4 cm), commented out: its rpy is the user's
    tag = re.search(r"#     - \{id: 6, link: gripper_tcp, size: ([0-9.]+), xyz: \[([^\]]+)\]", text)
    assert tag is not None, text
    np.testing.assert_allclose([float(v) for v in tag.group(2).split(",")], [-0.03, 0.0, -0.05], atol=0.003)
    for key in ("link: gripper_tcp", "xyz:", "pixel_sigma:"):
        assert GUESS in _line(text, key), key
    res = _diagnose_runs(bag, out, capsys)
    assert res["residual_after"] <= res["residual_before"]


def test_tag_links_from_images(tmp_path, capsys):
    """Without tag observations the tags are detected in the images: link, centre and size as in the truth."""
    import yaml

    sc = yaml.safe_load((DATA / "mobile_scenario.yaml").read_text())
    sc["robot"] = {"dh": str(DATA / "mobile_dh.yaml"), "model": str(DATA / "mobile_sim_model.yaml")}
    sc["camera"] = {"format": "png", "rate": 2.0}
    sc["trajectory"]["random_stops"]["count"] = 8
    (tmp_path / "png.yaml").write_text(yaml.safe_dump(sc))
    bag = _simulate(tmp_path, str(tmp_path / "png.yaml"))
    out = tmp_path / "model.yaml"
    assert main(["init", "--urdf", str(_urdf(tmp_path, "mobile")), "--bag", str(bag), "--out", str(out)]) == 0
    tag = re.search(r"#     - \{id: 6, link: gripper_tcp, size: ([0-9.]+), xyz: \[([^\]]+)\]", out.read_text())
    assert tag is not None, out.read_text()
    np.testing.assert_allclose([float(v) for v in tag.group(2).split(",")], [-0.03, 0.0, -0.05], atol=0.003)
    assert float(tag.group(1)) == pytest.approx(0.04, abs=0.005)
    assert "tag36h11 detections in 8 of 8 images" in out.read_text()


def test_dual_arm_torso_bag_guesses_both_hands(tmp_path, capsys):
    bag = _simulate(tmp_path, "torso_scenario.yaml")
    urdf = _urdf(tmp_path, "torso")
    out = tmp_path / "model.yaml"
    assert main(["init", "--urdf", str(urdf), "--bag", str(bag), "--out", str(out)]) == 0
    robot = parse_urdf(urdf)
    cfg = load_model_config(out, robot)
    got = {t.topic: (t.link, t.xyz) for t in cfg.trackers}
    assert {k: v[0] for k, v in got.items()} == {"/ground_truth/point/left": "left_tcp",
                                                 "/ground_truth/point/right": "right_tcp"}
    np.testing.assert_allclose(got["/ground_truth/point/left"][1], [0.0, 0.02, -0.03], atol=0.002)
    np.testing.assert_allclose(got["/ground_truth/point/right"][1], [0.0, -0.02, -0.03], atol=0.002)
    # the right arm's joints get a prior too (the chain of the second reflector), marked as a guess
    assert set(robot.path_from_root("right_tcp")) <= set(cfg.perturbations)
    assert GUESS in _line(out.read_text(), "right_3:")
    _diagnose_runs(bag, out, capsys)


def test_six_axis_arm_bag_and_diagnose(tmp_path, capsys):
    """ind6 recorded with the YAML init wrote for it (the scenario uses that model), then init --bag and diagnose."""
    urdf = _urdf(tmp_path, "ind6")
    first = tmp_path / "first.yaml"
    assert main(["init", "--urdf", str(urdf), "--out", str(first)]) == 0
    scenario = tmp_path / "ind6_scenario.yaml"
    scenario.write_text(f"""robot: {{urdf: {urdf}, model: {first}}}
seed: 5
truth: {{perturbations: none, joint_noise: false}}
trajectory:
  joint_rate: 60.0
  dwell: 0.3
  move_time: 0.3
  random_stops: {{count: 10, around: {{joint_2: -0.5, joint_3: 0.5, joint_5: 0.6}},
                 spread: {{joint_1: 1.0, joint_2: 0.4, joint_3: 0.4, joint_4: 1.0, joint_5: 0.6, joint_6: 1.0}}}}
ground_truth:
  point: {{link: tool0, xyz: [0.0, 0.04, 0.0], sigma: 0.0002, frame: laser_tracker,
          T_tracker_base: {{xyz: [3.0, 0.5, 0.0], rpy: [0.0, 0.0, 2.0]}}}}
""")
    bag = tmp_path / "ind6_bag"
    assert main(["simulate", str(scenario), "--out", str(bag), "--truth", "none"]) == 0
    out = tmp_path / "model.yaml"
    assert main(["init", "--urdf", str(urdf), "--bag", str(bag), "--out", str(out)]) == 0
    (tracker,) = load_model_config(out, parse_urdf(urdf)).trackers
    assert tracker.link == "tool0"
    np.testing.assert_allclose(tracker.xyz, [0.0, 0.04, 0.0], atol=0.002)
    _diagnose_runs(bag, out, capsys)


def test_init_refuses_what_it_did_not_write_and_bad_input(tmp_path, capsys):
    urdf = _urdf(tmp_path, "ind6")
    mine = tmp_path / "mine.yaml"
    mine.write_text("perturbations: {}\n")
    assert main(["init", "--urdf", str(urdf), "--out", str(mine)]) == 2
    assert main(["init", "--urdf", str(urdf), "--out", str(mine), "--force"]) == 2   # not written by ppoe init
    assert mine.read_text() == "perturbations: {}\n"
    assert main(["init", "--out", str(tmp_path / "x.yaml")]) == 2
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'><parent link='a'/>"
                   "<child link='nope'/></joint></robot>")
    assert main(["init", "--urdf", str(bad), "--out", str(tmp_path / "y.yaml")]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "ppoe init needs --urdf" in err and "bad.urdf" in err
    assert "Traceback" not in err
    again = tmp_path / "again.yaml"
    assert main(["init", "--urdf", str(urdf), "--out", str(again)]) == 0
    assert main(["init", "--urdf", str(urdf), "--out", str(again), "--force"]) == 0   # its own file: replaced


@pytest.mark.datasets
def test_motoman_dataset_urdf(tmp_path, capsys):
    d = DATASETS / "motoman_leica"
    if not (d / "leica_right_hand_6x6x6_dataset.mat").exists():
        pytest.fail(f"Motoman dataset not found in {d} (set PPOE_DATASETS)")
    bag = tmp_path / "motoman"
    assert main(["import", "motoman", str(d / "leica_right_hand_6x6x6_dataset.mat"), "--model-yaml",
                 str(d / "model.yaml"), "--out", str(bag), "--ppoe-model", str(tmp_path / "imported.yaml")]) == 0
    out = tmp_path / "model.yaml"
    assert main(["init", "--bag", str(bag), "--out", str(out)]) == 0    # the URDF from /robot_description
    from ppoe_core.io.bag_facts import bag_urdf

    robot = parse_urdf(bag_urdf(bag), text_source="motoman")
    cfg = load_model_config(out, robot)
    (tracker,) = cfg.trackers
    # the Leica reflector LR1 hangs on the flange T1 by a fixed joint; the dataset's grid hardly turns the tool, so
    # a link rigidly fixed to the flange (T1, LR1, EE1, the markers) is all the points can tell
    rigid = {"T1"} | {robot.joints[j].child for j in robot.joints if robot.joints[j].parent == "T1"
                      and not robot.joints[j].movable}
    rigid |= {robot.joints[j].child for j in robot.joints if robot.joints[j].parent in rigid
              and not robot.joints[j].movable}
    assert "LR1" in rigid and tracker.link in rigid, tracker.link
    assert cfg.camera is not None and GUESS in _line(out.read_text(), "tool:")
    from ppoe_core.io.bag_check import check_bags

    report = check_bags([str(bag)], str(out))
    assert report.exit_code < 2 and any(r.item == "/dataset/stop" for r in report.rows), report.markdown()
    capsys.readouterr()
    assert main(["diagnose", str(bag), "--model", str(out), "--json", "--quiet"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["residual_after"] < res["residual_before"]


@pytest.mark.datasets
def test_hilti_dataset_urdf(tmp_path):
    """The Hilti stationing robot: 15 total-station set-ups (one registration each), two tilt sensors."""
    d = DATASETS / "hilti_stationing"
    if not (d / "pallet.yaml").exists():
        pytest.fail(f"Hilti dataset not found in {d} (set PPOE_DATASETS)")
    bag = tmp_path / "pallet"
    assert main(["import", "hilti", str(d / "pallet.yaml"), "--out", str(bag)]) == 0
    out = tmp_path / "model.yaml"
    assert main(["init", "--bag", str(bag), "--out", str(out)]) == 0
    from ppoe_core.io.bag_check import check_bags
    from ppoe_core.io.bag_facts import bag_urdf

    robot = parse_urdf(bag_urdf(bag), text_source="hilti")
    cfg = load_model_config(out, robot)
    assert [t.link for t in cfg.trackers] == ["prism"]     # the dataset's own model: tracker.link prism
    np.testing.assert_allclose(cfg.trackers[0].xyz, 0.0, atol=0.005)
    assert {n: i.link for n, i in cfg.imus.items()} == {"base": "tilt_sensor_base",
                                                         "column_tip": "tilt_sensor_column_tip"}
    assert check_bags([str(bag)], str(out)).exit_code < 2


def test_shipped_arm7_bag_reflector_not_on_a_resting_finger(tmp_path):
    """bags/effect_joint_offset (arm7): the reflector rides on tool0 ([0, 0, 0.02]); the gripper fingers rest, so
    they move with it too -- a finger that happened to rest is not named. /ground_truth/pose gives the base."""
    out = tmp_path / "model.yaml"
    assert main(["init", "--bag", str(REPO / "bags" / "effect_joint_offset"), "--out", str(out)]) == 0
    cfg = load_model_config(out, parse_urdf(CONFIG_ROBOTS / "arm7.urdf"))
    (tracker,) = cfg.trackers
    assert tracker.link == "tool0"
    np.testing.assert_allclose(tracker.xyz, [0.0, 0.0, 0.02], atol=0.01)   # the hidden 0.02 rad offset blurs it
    assert (cfg.frames.base, cfg.frames.tool) == ("base_link", "tool0")
    assert "/ground_truth/pose's frame_id" in _line(out.read_text(), "base:")
