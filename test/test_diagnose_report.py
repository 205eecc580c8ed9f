"""The diagnose report (ppoe_core/analysis/diagnose/report.py, report_apply.py, report_plot.py) and what the
calibrated URDF applies (calibrated_urdf.plan_calibration): only significant static components are folded, the
others are listed with the reason; "How to apply" names the files, commands and parameters; one word for a share;
the figure has a panel per measurement kind with its before / after; corrected camera_info files load as the
camera_calibration_parsers format.  Results are built by hand (no fit), so every number checked is known;
the last test runs the command line on a shipped bag."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from conftest import CONFIG, REPO

from ppoe_core.analysis.diagnose.calibrated_urdf import calibrated_urdf, plan_calibration
from ppoe_core.analysis.diagnose.report import SHARE, write_model_yaml, write_report
from ppoe_core.analysis.diagnose.report_apply import camera_info_yaml
from ppoe_core.analysis.diagnose.report_plot import block_figure
from ppoe_core.analysis.diagnose.results import BlockReport, DiagnoseResult, EffectReport, StructureTest
from ppoe_core.model.effects import make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

URDF = CONFIG / "robots" / "arm7.urdf"


def _report(e, ci: dict[str, tuple[float, float]], share: float, **kw) -> EffectReport:
    return EffectReport(name=e.name, location=e.location,
                        parameters={p: float(v) for p, v in zip(e.param_names, e.params)},
                        ci={p: list(ci[p]) for p in e.param_names},
                        sigma={p: (ci[p][1] - ci[p][0]) / 3.92 for p in e.param_names}, share=share, **kw)


def _block(kind: str, unit: str, before: float, after: float, sensors=(), structure=()) -> BlockReport:
    per = {s: {"rms_before": before * (1 + k), "rms_after": after * (1 + k), "rms_before_insample": before,
               "rms_after_insample": after} for k, s in enumerate(sensors)}
    return BlockReport(kind=kind, unit=unit, n=40, rms_before=before, rms_after=after, rms_before_insample=before,
                       rms_after_insample=after, sensor_scale=1.0, prior_scale=1.1, noise_floor=0.9 * after,
                       unexplained=0.4 * after, nees_before=3.0, nees_after=1.1, per_sensor=per,
                       structure=list(structure))


@pytest.fixture(scope="module")
def case():
    """arm7 with a camera mount error (x, rz significant; y, z, rx, ry not), a joint offset whose interval
    contains zero, a gravity compliance (configuration-dependent) and corrected intrinsics; five blocks."""
    robot = parse_urdf(URDF)
    tree = KinematicTree(robot)
    cam = make_effect("camera_extrinsics", "camera_joint", tree, [0.021, 0.0004, -0.0003, 0.0002, 0.0001, 0.019])
    ci_cam = {"x": (0.015, 0.027), "y": (-0.002, 0.0028), "z": (-0.003, 0.0024), "rx": (-0.001, 0.0014),
              "ry": (-0.0011, 0.0013), "rz": (0.013, 0.025)}
    off = make_effect("joint_offset", "joint_2", tree, [0.0003])
    grav = make_effect("gravity_compliance", "joint_2", tree, [2.9e-4])
    intr = make_effect("camera_intrinsics", "camera_optical_frame", tree, [3.0, 2.0, 4.0, -1.0], components=(
        "fx", "fy", "cx", "cy"))
    K = [703.0, 0.0, 324.0, 0.0, 702.0, 239.0, 0.0, 0.0, 1.0]
    reports = [_report(cam, ci_cam, 0.62, measurement="pixels", frame="camera_optical_frame"),
               _report(off, {"offset": (-0.0004, 0.001)}, 0.004, measurement="tracker"),
               _report(grav, {"compliance": (2.6e-4, 3.2e-4)}, 0.21, measurement="tracker"),
               _report(intr, {p: (v - 1.0, v + 1.0) for p, v in zip(intr.param_names, intr.params)}, 0.05,
                       measurement="pixels", camera_info={"K": K, "D": [-0.05, 0.02, 0.0, 0.0, 0.0],
                                                          "distortion_model": "plumb_bob"})]
    blocks = {b.kind: b for b in [
        _block("pixels", "px", 21.6, 2.1, sensors=("cam_a", "cam_b")),
        _block("tracker", "m", 0.0175, 0.0139, structure=[StructureTest("time", 0.12, 4.5, True)]),
        _block("imu", "rad", 0.008, 0.0079), _block("contact", "m", 0.004, 0.003), _block("pose", "m", 0.01, 0.008)]}
    result = DiagnoseResult(effects=reports, found=[cam, off, grav, intr], blocks=blocks,
                            steps=[{"action": "add", "move": "camera_extrinsics@camera_joint", "heldout_gain": 272.8,
                                    "delta_L": -258.0, "t": 8.5, "z": 4.9}],
                            rejected=[], cv="stops", n_stops=40, n_sessions=1, n_poses=40)
    return robot, tree, result


def test_only_significant_static_components_are_folded(case):
    """plan_calibration folds the declared static effects in full and, of the found ones, only the components
    whose interval excludes zero; the URDF's FK equals that correction (not the full one) to 1e-9 m."""
    robot, tree, result = case
    declared = [make_effect("link_error", "joint_5", tree, [0.001, 0.0, 0.0, 0.0, 0.0, 0.002])]
    plan = plan_calibration(result, declared)
    assert plan.applied == {"camera_extrinsics@camera_joint": ["x", "rz"]}
    assert [(n.effect, n.parameter) for n in plan.not_applied] == [
        ("camera_extrinsics@camera_joint", p) for p in ("y", "z", "rx", "ry")] + [("joint_offset@joint_2", "offset")]
    assert all("contains 0" in n.reason for n in plan.not_applied)
    assert plan.in_model == ["gravity_compliance@joint_2", "camera_intrinsics@camera_optical_frame[fx,fy,cx,cy]"]
    text, rest = calibrated_urdf(URDF.read_text(), robot, plan.folded)
    assert rest == []
    folded_cam = next(e for e in plan.folded if e.name == "camera_extrinsics")
    np.testing.assert_allclose(folded_cam.params, [0.021, 0, 0, 0, 0, 0.019])
    rng = np.random.default_rng(3)
    q = {j: rng.uniform(-2, 2, 25) for j in robot.independent_joints}
    expect = tree.link_poses(q, *sum_effect_corrections(plan.folded, q, {}))
    full = tree.link_poses(q, *sum_effect_corrections([*declared, *result.found[:2]], q, {}))
    got = KinematicTree(parse_urdf(text)).link_poses(q)
    assert max(float(np.abs(expect[k] - got[k]).max()) for k in got) < 1e-9
    assert float(np.abs(full["camera_optical_frame"] - got["camera_optical_frame"]).max()) > 1e-4
    assert "camera_extrinsics@camera_joint[x,rz]" in text and "link_error@joint_5" in text


def test_report_says_how_to_apply_and_what_was_left_out(case, tmp_path):
    """diagnose.md: the three files with the commands and parameter names of this repo, the components not
    applied with their intervals, the refit command, and the camera_info file for the corrected intrinsics."""
    robot, tree, result = case
    paths = write_report(result, tmp_path, "t")
    md = paths["md"].read_text()
    apply = md[md.index("## How to apply"):md.index("## Selection steps")]
    for needle in ("robot_calibrated.urdf", "model_calibrated.yaml", "model_diagnosed.yaml",
                   "ros2 run robot_state_publisher robot_state_publisher --ros-args -p robot_description:=",
                   "ros2 run ppoe_ros kinematics_node --ros-args -p model_file:=",
                   "ros2 launch ppoe_ros ppoe.launch.py urdf:=", "ppoe evaluate OTHER_BAG --urdf", "camera_info_topic",
                   "camera_info_url:=file://", "tf_camera_suffix",
                   "| camera_extrinsics@camera_joint | y | 0.0004 | [-0.002, 0.0028] | "
                   "95 % CI [-0.002, 0.0028] contains 0",
                   "| joint_offset@joint_2 | offset |",
                   "--effects 'camera_extrinsics@camera_joint[x,rz]' 'gravity_compliance@joint_2' "
                   "'camera_intrinsics@camera_optical_frame[fx,fy,cx,cy]'"):
        assert needle in apply, needle
    assert "`camera_extrinsics@camera_joint` (x, rz)" in apply
    # every parameter name the section tells users to set exists in this repo's node / launch files
    launch = (REPO / "launch" / "ppoe.launch.py").read_text()
    nodes = "".join(p.read_text() for p in (CONFIG / "nodes").glob("*.yaml"))
    for name in re.findall(r"-p (\w+):=", apply):
        assert name == "robot_description" or f"{name}:" in nodes, name
    for name in re.findall(r" (\w+):=", apply.split("ros2 launch")[1].split("\n")[0]):
        assert f'"{name}"' in launch, name
    cam = yaml.safe_load((tmp_path / "camera_info_camera_optical_frame.yaml").read_text())
    assert cam["camera_matrix"]["data"] == result.effects[3].camera_info["K"]
    assert cam["projection_matrix"]["data"][:3] == [703.0, 0.0, 324.0] and cam["distortion_model"] == "plumb_bob"


def test_one_word_for_a_share(case, tmp_path):
    """"share" appears in the report and in docs/diagnose_report.md (prose) only as "share of the residual"; the effects
    table's column has that name, the predictable part and a step's held-out drop of -2 log L have their own words,
    and no "gain" (a word other pages use for relative gains) is left in the report."""
    _, _, result = case
    md = write_report(result, tmp_path, "t")["md"].read_text()
    doc = (REPO / "docs" / "diagnose_report.md").read_text()
    for text in (md, re.sub(r"`[^`]*`", "", doc)):  # the JSON key `share` aside
        words = re.findall(r"shares?\b(?: of the residual)?", text, flags=re.IGNORECASE)
        assert words and all(w.lower().endswith("of the residual") for w in words), set(words) - {SHARE}
    assert f"| {SHARE} |" in md and "62.0 %" in md
    assert "predictable part" in md and "time 12.0 %, t 4.5 **structure left**" in md
    assert "held-out drop of -2 log L |" in md and "| 272.8 |" in md and "gain" not in md.replace("heldout_gain", "")


def test_plot_shows_every_measurement_kind_before_and_after(case):
    """One panel per block (tracker, pose, pixels, imu, contact), bars = held-out RMS before / after in the
    display unit, one pair per sensor when a block has several."""
    _, _, result = case
    fig = block_figure(result, "t")
    try:
        titles = [ax.get_title().split(" ")[0] for ax in fig.axes]
        assert titles == ["tracker", "pose", "pixels", "imu", "contact"]
        heights = {ax.get_title().split(" ")[0]: [p.get_height() for p in ax.patches] for ax in fig.axes}
        np.testing.assert_allclose(heights["tracker"], [17.5, 13.9])  # mm
        np.testing.assert_allclose(heights["imu"], [8.0, 7.9])  # mrad
        np.testing.assert_allclose(heights["pixels"], [21.6, 21.6, 43.2, 2.1, 2.1, 4.2])  # all, cam_a, cam_b
        assert "structure left" in fig.axes[0].get_title() and "17.5 -> 13.9 mm" in fig.axes[0].get_title()
    finally:
        import matplotlib.pyplot as plt
        plt.close(fig)


def test_calibrated_model_drops_static_effects_and_camera_info_without_size(case, tmp_path):
    """model_calibrated.yaml keeps the configuration-dependent effects only; a camera file without a known image
    size says so and writes 0 x 0."""
    _, _, result = case
    out = write_model_yaml(CONFIG / "robots" / "arm7_model.yaml", result, tmp_path / "m.yaml",
                           drop=("joint_offset", "link_error", "camera_extrinsics"))
    doc = yaml.safe_load(out.read_text())
    assert [e["name"] for e in doc["effects"]] == ["gravity_compliance", "camera_intrinsics"]
    text = camera_info_yaml("cam", result.effects[3].camera_info, None)
    assert "image size unknown" in text and yaml.safe_load(text)["image_width"] == 0


def test_cli_report_on_the_camera_bag(tmp_path):
    """``ppoe diagnose bags/effect_camera_extrinsics --out``: the report has the sections, the figure, the camera
    file sized from the bag's camera_info, and the calibrated URDF parses with the original links."""
    from ppoe_ros.cli import main

    out = tmp_path / "d"
    assert main(["diagnose", str(REPO / "bags" / "effect_camera_extrinsics"), "--model",
                 str(CONFIG / "robots" / "arm7_model.yaml"), "--out", str(out), "--quiet"]) == 0
    md = (out / "diagnose.md").read_text()
    for section in ("## Effects found", "## Measurements", "## How to apply", "## Terms"):
        assert section in md
    assert (out / "diagnose.png").stat().st_size < 150_000
    robot = parse_urdf(out / "robot_calibrated.urdf")
    assert set(robot.links) == set(parse_urdf(URDF).links)
    for cam in out.glob("camera_info_*.yaml"):
        assert (yaml.safe_load(cam.read_text())["image_width"], yaml.safe_load(cam.read_text())["image_height"]) \
            == (640, 480)


def test_cli_folds_only_the_camera_components_whose_interval_excludes_zero(tmp_path):
    """The issue's case: all six camera_extrinsics components fitted on bags/effect_camera_extrinsics (truth x and
    rz): robot_calibrated.urdf carries exactly the components whose interval excludes zero (FK to 1e-9 m), the
    others are listed as not applied, and the calibrated model has no static effect left."""
    from ppoe_core.model.effects import effect_from_config
    from ppoe_ros.cli import main

    out = tmp_path / "d"
    assert main(["diagnose", str(REPO / "bags" / "effect_camera_extrinsics"), "--model",
                 str(CONFIG / "robots" / "arm7_model.yaml"), "--effects", "camera_extrinsics@camera_joint",
                 "--pixels", "on", "--out", str(out), "--quiet"]) == 0
    doc = yaml.safe_load((out / "diagnose.json").read_text())
    (entry,) = doc["effects"]
    keep = [p for p, (lo, hi) in entry["ci"].items() if lo > 0 or hi < 0]
    left = [p for p in entry["ci"] if p not in keep]
    assert keep and left  # this bag: x and rz are significant, the rest is not
    robot0 = parse_urdf(URDF)
    eff = effect_from_config(entry, robot0)
    folded = eff.with_params([v if p in keep else 0.0 for p, v in zip(eff.param_names, eff.params)])
    q = {j: np.random.default_rng(4).uniform(-2, 2, 20) for j in robot0.independent_joints}
    expect = KinematicTree(robot0).link_poses(q, *sum_effect_corrections([folded], q, {}))
    got = KinematicTree(parse_urdf(out / "robot_calibrated.urdf")).link_poses(q)
    assert max(float(np.abs(expect[k] - got[k]).max()) for k in got) < 1e-9
    md = (out / "diagnose.md").read_text()
    for p in left:
        assert f"| camera_extrinsics@camera_joint | {p} |" in md
    assert f"--effects 'camera_extrinsics@camera_joint[{','.join(keep)}]'" in md
    cal = yaml.safe_load((out / "model_calibrated.yaml").read_text())
    assert not [e for e in cal.get("effects") or [] if e["name"] == "camera_extrinsics"]
