"""``ppoe check`` (ppoe_core.io.bag_check, ppoe_core.cli.check): each kind of mismatch between a bag and a model
gives the right line and exit code, never a traceback; ``ppoe diagnose`` / ``evaluate`` print the failures first.

The bags are written here (BagWriter) for ind6 (config/robots/ind6_dh.yaml): static stops of random poses, a
laser-tracker reflector on tool0 measured in the tracker's own frame; each case changes one thing.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import CONFIG_ROBOTS

from ppoe_core import lie
from ppoe_core.io.bag_check import MIN_RANGE_DEG, check_bags, offset_identifiability, static_rows
from ppoe_core.io.bagio import BagWriter, read_bag
from ppoe_core.robot.dh import dh_to_urdf
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf
from ppoe_ros.cli import main

URDF = dh_to_urdf(CONFIG_ROBOTS / "ind6_dh.yaml")
ROBOT = parse_urdf(URDF)
JOINTS = ROBOT.independent_joints
XYZ = np.array([0.0, 0.04, 0.0])                      # reflector on tool0 [m]
T_TRACKER_BASE = lie.from_xyz_rpy([2.0, -1.0, 0.3], [0.0, 0.0, 2.4])
MODEL = """trackers:
  - {topic: /ground_truth/point, link: tool0, xyz: [0.0, 0.04, 0.0], sigma: 0.0002}
"""


def write_bag(path: Path, *, n: int = 12, rename: dict[str, str] | None = None, camera_frame: str | None = None,
              moving: bool = False, frozen: tuple[str, ...] = (), description: bool = True, seed: int = 3,
              encoder_noise: float = 0.0) -> Path:
    """A contract bag of ind6: per stop 0.3 s of joint states at 100 Hz, then one tracker point (and camera_info).

    ``moving``: the joints never rest (a sinusoid; points every 0.5 s); ``frozen``: these joints stay at 0.2 rad;
    ``rename``: joint names as the bag publishes them; ``encoder_noise``: white noise on every joint-state sample
    [rad], also at rest."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(ROBOT)
    names = [(rename or {}).get(j, j) for j in JOINTS]
    with BagWriter(path) as bag:
        if description:
            bag.write_robot_description(URDF, stamp=0.5)
        for k in range(n):
            q0 = rng.uniform(-0.8, 0.8, len(JOINTS))
            q0[[JOINTS.index(j) for j in frozen]] = 0.2
            t0 = 1.0 + k
            for i in range(30 if not moving else 50):
                t = t0 + 0.01 * i * (1 if not moving else 2)
                q = q0 if not moving else 0.5 * np.sin(0.7 * t + np.arange(len(JOINTS)))
                bag.write_joint_state(t, names, q + encoder_noise * rng.standard_normal(len(JOINTS)))
            t_meas = t0 + 0.25
            q = q0 if not moving else 0.5 * np.sin(0.7 * t_meas + np.arange(len(JOINTS)))
            T = tree.link_poses(dict(zip(JOINTS, q)), links=["tool0"])["tool0"]
            p = (T_TRACKER_BASE @ T @ np.r_[XYZ, 1.0])[:3]
            bag.write_ground_truth_point(t_meas, "tracker", p)
            if camera_frame:
                bag.write_camera_info(t_meas, camera_frame, 640, 480, np.array([[600, 0, 320], [0, 600, 240],
                                                                                 [0, 0, 1.0]]), np.zeros(5))
    return path


@pytest.fixture
def model(tmp_path) -> Path:
    path = tmp_path / "model.yaml"
    path.write_text(MODEL)
    return path


def rows_of(report, verdict: str | None = None) -> dict[str, str]:
    return {r.item: r.holds for r in report.rows if verdict is None or r.verdict == verdict}


def test_a_good_bag_passes(tmp_path, model, capsys):
    bag = write_bag(tmp_path / "good")
    report = check_bags([str(bag)], str(model))
    assert report.exit_code == 0, report.markdown()
    rows = rows_of(report)
    assert rows["stops"].startswith("12 stops at rest (12 of 12")
    assert rows["/ground_truth/point"] == "12 points"
    # the first joint's offset is a rigid turn of every point: the registration absorbs it, and check says so
    assert "first joint that moves" in rows["joint_offset@joint_1"]
    assert main(["check", str(bag), "--model", str(model)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "| bag | check | the bag holds | the model needs | verdict |"
    assert out.strip().splitlines()[-1] == "ppoe check: OK: 0 failure(s), 0 warning(s) in 1 bag(s)"


def test_missing_topic(tmp_path, capsys):
    bag = write_bag(tmp_path / "one_reflector")
    model = tmp_path / "two.yaml"
    model.write_text(MODEL + "  - {topic: /ground_truth/point/left, link: tool0, xyz: [0.0, 0.0, 0.0]}\n")
    report = check_bags([str(bag)], str(model))
    assert rows_of(report, "FAIL") == {"/ground_truth/point/left": "absent"}
    assert main(["check", str(bag), "--model", str(model)]) == 2
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("ppoe check: FAIL: 1 failure(s)") and "/ground_truth/point/left: absent" in last


def test_renamed_joint(tmp_path, model, capsys):
    bag = write_bag(tmp_path / "renamed", rename={"joint_3": "joint3"})
    report = check_bags([str(bag)], str(model))
    fails = rows_of(report, "FAIL")
    assert fails == {"joint joint_3": "absent from /joint_states; the bag has 'joint3', not in the URDF: renamed?"}
    assert rows_of(report)["joints not in the URDF"] == "joint3"
    # diagnose prints the same failure first, then stops with its own error: no traceback
    assert main(["diagnose", str(bag), "--model", str(model), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ppoe diagnose: check: renamed: joint joint_3: absent from /joint_states")
    assert "Traceback" not in err


def test_camera_frame_not_in_the_urdf(tmp_path, model, capsys):
    bag = write_bag(tmp_path / "camera", camera_frame="usb_cam_optical")
    report = check_bags([str(bag)], str(model))
    assert rows_of(report, "FAIL") == {"frame usb_cam_optical": "camera_info frame_id, not a link of the URDF"}
    assert main(["evaluate", str(bag), "--model", str(model), "--quiet"]) in (0, 2)
    err = capsys.readouterr().err
    assert err.startswith("ppoe evaluate: check: camera: frame usb_cam_optical") and "Traceback" not in err


def test_stop_free_recording(tmp_path, model):
    bag = write_bag(tmp_path / "moving", moving=True)
    report = check_bags([str(bag)], str(model))
    assert rows_of(report, "FAIL") == {"stops": "0 stops at rest (0 of 12 measurements)"}
    assert report.exit_code == 2


def test_effect_not_identifiable(tmp_path, model):
    bag = write_bag(tmp_path / "frozen", frozen=("joint_2",))
    report = check_bags([str(bag)], str(model))
    warns = rows_of(report, "warn")
    assert set(warns) == {"joint_offset@joint_2"}, report.markdown()
    assert warns["joint_offset@joint_2"] == (f"joint_2's zero offset cannot be told from a link_error at joint_2: "
                                             f"joint_2 never moves more than {MIN_RANGE_DEG:g}° (range 0.0°)")
    assert report.exit_code == 1
    assert report.summary().startswith("ppoe check: WARN: 0 failure(s), 1 warning(s) in 1 bag(s); first: frozen: "
                                       "joint_offset@joint_2")


def test_unreadable_bag_model_errors_and_json(tmp_path, model, capsys):
    (tmp_path / "empty").mkdir()
    nodesc = write_bag(tmp_path / "nodesc", description=False)
    bad_model = tmp_path / "bad.yaml"
    bad_model.write_text("perturbations:\n  joint_9: {sigma: [0, 0, 0, 0.001, 0.001, 0.001]}\n")
    good = write_bag(tmp_path / "good")
    report = check_bags([str(tmp_path / "empty"), str(nodesc)], str(model))
    fails = rows_of(report, "FAIL")
    assert fails["bag"].startswith("unreadable") and fails["/robot_description"] == "absent"
    bad = check_bags([str(good)], str(bad_model))
    assert "joint_9" in rows_of(bad, "FAIL")["model"] and "bad.yaml" in rows_of(bad, "FAIL")["model"]
    assert main(["check", str(good), str(nodesc), "--model", str(model), "--json"]) == 2
    doc = json.loads(capsys.readouterr().out)
    assert doc["exit_code"] == 2 and {r["bag"] for r in doc["rows"]} == {"good", "nodesc"}
    assert doc["summary"].startswith("ppoe check: FAIL: 1 failure(s), 0 warning(s) in 2 bag(s)")


def test_identifiability_against_a_direct_count(tmp_path):
    """The first joint's share is 0 (a rigid turn), an elbow's is large; a frozen joint is found at rest."""
    bag = write_bag(tmp_path / "good", n=10)
    data = read_bag(bag, load_images=False)
    stamps = data.ground_truth_point.stamps
    assert static_rows(data, JOINTS, stamps).all()
    moving = read_bag(write_bag(tmp_path / "moving", n=10, moving=True), load_images=False)
    assert not static_rows(moving, JOINTS, moving.ground_truth_point.stamps).any()
    # a noisy encoder at rest (0.1 mrad white noise on every sample: 2-4 mrad/s of apparent spread over 0.1-0.2 s)
    # is still at rest; the same noise on a moving robot is still motion
    noisy = read_bag(write_bag(tmp_path / "noisy", n=10, encoder_noise=1e-4), load_images=False)
    assert static_rows(noisy, JOINTS, noisy.ground_truth_point.stamps).all()
    noisy_moving = read_bag(write_bag(tmp_path / "noisy_moving", n=10, moving=True, encoder_noise=1e-4),
                            load_images=False)
    assert not static_rows(noisy_moving, JOINTS, noisy_moving.ground_truth_point.stamps).any()
    # diagnose's stops carry the same rest test: its accelerometer rows are not all dropped on a noisy encoder
    # (they were, by the raw joint velocity's noise: 0.1 mrad at 100 Hz is about 7 mrad/s in a central difference)
    from ppoe_core.analysis.diagnose.block_imu import at_rest
    from ppoe_core.analysis.diagnose.load_stops import stops_from_bag

    stops = stops_from_bag(tmp_path / "noisy", ROBOT, tracker_link="tool0", tracker_xyz=XYZ)
    assert at_rest(stops).all() and stops.subset(np.arange(3)).context["at_rest"].all()
    moving_stops = stops_from_bag(tmp_path / "noisy_moving", ROBOT, tracker_link="tool0", tracker_xyz=XYZ)
    assert not at_rest(moving_stops).any()
    from ppoe_core.io.bag_joints import joints_at

    q = joints_at(data, ROBOT, stamps)
    share = offset_identifiability(ROBOT, q, ["tool0"], [XYZ])
    assert share["joint_1"] < 1e-6 and share["joint_3"] > 0.2


def test_a_model_without_tool_or_trackers_still_counts_stops(tmp_path):
    """ind6 has two leaves (tool0, the camera): no default tool; the stops are counted over every joint."""
    bag = write_bag(tmp_path / "bare", n=8)
    model = tmp_path / "bare.yaml"
    model.write_text("effects: []\n")
    report = check_bags([str(bag)], str(model))
    rows = rows_of(report)
    assert rows["stops"].startswith("8 stops at rest (8 of 8")
    assert rows_of(report, "warn") == {"/ground_truth/point": "8 points"}    # diagnose then needs --tool
    assert report.exit_code == 1
