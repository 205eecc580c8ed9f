"""Tests of ``ppoe evaluate`` (ppoe_core.analysis.evaluate, ppoe_core.cli.evaluate).

* metric helpers: Kabsch, lateral / rotation errors, the reflector covariance against
  Monte-Carlo (seeded), NEES statistics;
* a small simulated Table I bag (``ppoe simulate``, generated into a tmp dir): forward
  kinematics is worse than the PPOE-fused estimate where tags are seen;
* the measured datasets (``PPOE_DATASETS``, marker ``datasets``): the Hilti nominal baseline
  of its README is reproduced through the whole evaluate pipeline (import -> bag -> replay ->
  per-station registration), and on the Motoman marker data the PPOE-fused reflector error
  stays at the FK level while the naive-fused one does not;
* bad bags raise BagError naming the topic; CLI ``--json`` / ``--out``.
"""

from __future__ import annotations

import argparse
import io
import json

import numpy as np
import pytest
import yaml
from conftest import DATASETS, REPO
from conftest import random_pose as _random_pose
from hypothesis import given, settings
from hypothesis import strategies as st

from ppoe_core import lie
from ppoe_core.analysis.evaluate import (
    REPLAY_SETTINGS,
    EvaluateOptions,
    ProgressBar,
    error_stats,
    evaluate_bag,
    load_fusion_params,
    markdown_report,
    nees_stats,
    point_covariance,
    position_errors,
    registration_split,
    rotation_errors,
    write_report,
)
from ppoe_core.errors import BagError, ModelConfigError, PpoeError
from ppoe_core.estimation import camera
from ppoe_core.io.bagio import BagWriter
from ppoe_core.sensing import tags
from ppoe_core.sensing.tag_rows import centre_from_corners, observe_tags

needs_data = pytest.mark.skipif(not DATASETS.is_dir(), reason=f"datasets folder {DATASETS} not present")


# ----------------------------------------------------------------------------- metrics


def test_registration_split_follows_the_stop_roles():
    """A bag with stop roles is scored by its protocol: per station, fitted on its stationing stops
    of the chosen point set, scored on its evaluation stops; a station with fewer than 3 fit points
    is not scored (counted); without roles, one registration on even samples, scored on odd."""
    roles = ([{"station": "A", "role": "stationing", "point_sets": ["cross"]}] * 3
             + [{"station": "A", "role": "stationing", "point_sets": ["square"]}]
             + [{"station": "A", "role": "evaluation"}] * 2
             + [{"station": "B", "role": "stationing", "point_sets": ["cross"]}] * 2
             + [{"station": "B", "role": "evaluation"}] * 3)
    groups, desc, unscored = registration_split(roles, len(roles), "cross")
    assert [g[0] for g in groups] == ["A"] and unscored == 3
    np.testing.assert_array_equal(groups[0][1], [0, 1, 2])
    np.testing.assert_array_equal(groups[0][2], [4, 5])
    assert "per station" in desc
    groups_all, _, _ = registration_split(roles, len(roles), "all")
    np.testing.assert_array_equal(groups_all[0][1], [0, 1, 2, 3])
    groups_none, desc_none, unscored_none = registration_split([None] * 5, 5, "cross")
    np.testing.assert_array_equal(groups_none[0][1], [0, 2, 4])
    np.testing.assert_array_equal(groups_none[0][2], [1, 3])
    assert unscored_none == 0 and "even" in desc_none
    with pytest.raises(PpoeError, match="--fit-set"):
        registration_split(roles, len(roles), "diagonal")


def test_position_and_rotation_errors():
    z = np.tile([0.0, 0.0, 1.0], (3, 1))
    p_gt = np.zeros((3, 3))
    p_est = np.array([[0.0, 0.0, 0.05], [0.03, 0.04, 0.0], [0.03, 0.04, 1.0]])
    e3, el = position_errors(p_est, p_gt, z)
    np.testing.assert_allclose(e3, [0.05, 0.05, np.sqrt(1.0 + 0.05**2)])
    np.testing.assert_allclose(el, [0.0, 0.05, 0.05])  # the z component never counts as lateral
    T0 = np.eye(4)
    T1 = lie.exp(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.3]))
    np.testing.assert_allclose(rotation_errors(T0[None], T1[None]), [0.3])
    st = error_stats(np.array([1.0, 2.0, np.nan, 3.0]))
    assert st["n"] == 3 and st["mean"] == 2.0 and st["max"] == 3.0
    np.testing.assert_allclose(st["rms"], np.sqrt(14 / 3))


def test_point_covariance_matches_monte_carlo():
    rng = np.random.default_rng(7)
    T = _random_pose(rng)
    A = rng.normal(size=(6, 6)) * np.array([0.002, 0.002, 0.002, 0.01, 0.01, 0.01])
    cov = A @ A.T
    r = np.array([0.1, -0.2, 0.3])
    xi = rng.multivariate_normal(np.zeros(6), cov, size=200000)
    Ts = T @ lie.exp(xi)
    p = Ts[:, :3, :3] @ r + Ts[:, :3, 3]
    mc = np.cov(p.T)
    pred = point_covariance(T[None], cov[None], r[None])[0]
    assert np.linalg.norm(pred - mc) / np.linalg.norm(mc) < 0.03


def test_nees_stats_consistent_chi2():
    rng = np.random.default_rng(3)
    v = rng.chisquare(3, size=4000)
    st = nees_stats(v, 3)
    assert st["bounds95"][0] < st["mean"] < st["bounds95"][1]
    assert abs(st["fraction_inside"] - 0.95) < 0.02
    assert nees_stats(np.array([np.nan]), 6)["n"] == 0


def test_json_document_is_strict():
    from ppoe_core.analysis.evaluate import Evaluation

    ev = Evaluation({"a": float("nan"), "b": [np.float64(1.5), np.inf], "c": {"n": np.int64(3)}})
    assert json.dumps(ev.to_dict(), allow_nan=False) == '{"a": null, "b": [1.5, null], "c": {"n": 3}}'


def test_progress_bar_only_when_enabled():
    s = io.StringIO()
    bar = ProgressBar(10, enabled=True, stream=s)
    bar.update(5)
    bar.close()
    assert "100.0%" in s.getvalue() and s.getvalue().endswith("\n")
    s2 = io.StringIO()
    bar = ProgressBar(10, enabled=False, stream=s2)
    bar.update(5)
    bar.close()
    assert s2.getvalue() == ""


# ----------------------------------------------------------------------------- simulated bag


@pytest.fixture(scope="module")
def small_table1_bag(tmp_path_factory):
    """Experiment I of Table I with 5 stops (the shipped scenario, shortened), in a tmp dir."""
    from ppoe_core.sim.simulate import simulate

    sc = yaml.safe_load((REPO / "bags" / "table1_exp1.yaml").read_text())
    sc["robot"]["urdf"] = str(REPO / "config" / "robots" / "rover.urdf")
    sc["robot"]["model"] = str(REPO / "config" / "robots" / "rover_model.yaml")
    sc["trajectory"]["random_stops"]["count"] = 5
    d = tmp_path_factory.mktemp("sim")
    (d / "scenario.yaml").write_text(yaml.safe_dump(sc))
    simulate(d / "scenario.yaml", d / "bag")
    return d / "bag"


def test_evaluate_simulated_tags_improve_on_fk(small_table1_bag):
    ev = evaluate_bag(small_table1_bag, REPO / "config" / "robots" / "rover_model.yaml")
    s = ev.summary
    assert s["ground_truth"]["kind"] == "pose" and s["ground_truth"]["samples"] == 5
    fk, ppoe = s["methods"]["fk"], s["methods"]["ppoe"]
    assert ppoe["measurements"]["counts"]["accepted"] > 0
    assert fk["lateral"]["mean"] > ppoe["lateral"]["mean"]
    assert fk["position_3d"]["mean"] > ppoe["position_3d"]["mean"]
    assert set(s["methods"]) == {"fk", "ppoe", "naive"}
    # the markdown table has one row per method and the JSON round-trips
    md = markdown_report(ev)
    assert md.count("| forward kinematics |") == 1 and md.count("| fused, PPOE covariance |") == 2
    assert json.loads(json.dumps(s))["methods"]["fk"]["lateral"]["n"] == 5


def test_cli_evaluate_json_and_out(small_table1_bag, tmp_path, capsys):
    from ppoe_ros.cli import main

    out = tmp_path / "report"
    rc = main(["evaluate", str(small_table1_bag), "--model", str(REPO / "config" / "robots" / "rover_model.yaml"),
               "--out", str(out), "--json", "--no-progress"])
    assert rc == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)  # exactly one JSON document on stdout
    assert doc["methods"]["ppoe"]["lateral"]["n"] == 5
    assert captured.err == ""
    for name in ("evaluation.md", "evaluation.json", "errors.png"):
        assert (out / name).stat().st_size > 0
    assert json.loads((out / "evaluation.json").read_text())["base"] == "base_link"
    # TUM trajectories for evo: the ground truth and each method at the scored samples; their position
    # differences are the reported errors
    gt = np.loadtxt(out / "trajectory_ground_truth.tum")
    fk = np.loadtxt(out / "trajectory_fk.tum")
    assert gt.shape == fk.shape == (5, 8) and np.allclose(gt[:, 0], fk[:, 0])
    np.testing.assert_allclose(np.linalg.norm(gt[:, 4:], axis=1), 1.0, atol=1e-6)
    rms = np.sqrt(np.mean(np.sum((fk[:, 1:4] - gt[:, 1:4]) ** 2, axis=1)))
    assert rms == pytest.approx(doc["methods"]["fk"]["position_3d"]["rms"], rel=1e-6)


# ----------------------------------------------------------------------------- bad bags


def _tiny_bag(path, *, gt=True, joint="j1", gt_frame="base", axis="0 0 1"):
    urdf = f"""<robot name="r"><link name="base"/><link name="l1"/>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="{axis}"/>
      <origin xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint></robot>"""
    with BagWriter(path) as w:
        w.write_robot_description(urdf, 0.0)
        for k in range(10):
            w.write_joint_state(0.01 * (k + 1), [joint], [0.1])
        if gt:
            w.write_ground_truth_pose(0.05, gt_frame, np.eye(4))


def _tiny_model(tmp_path):
    p = tmp_path / "m.yaml"
    p.write_text("frames: {base: base, tool: l1}\njoint_noise: {j1: 0.01}\n")
    return p


def test_bad_bags_name_the_topic(tmp_path):
    model = _tiny_model(tmp_path)
    _tiny_bag(tmp_path / "nogt", gt=False)
    with pytest.raises(BagError, match="/ground_truth/pose"):
        evaluate_bag(tmp_path / "nogt", model)
    _tiny_bag(tmp_path / "wrongjoint", joint="other")
    with pytest.raises(BagError, match=r"/joint_states.*'j1'"):
        evaluate_bag(tmp_path / "wrongjoint", model)
    _tiny_bag(tmp_path / "frame", gt_frame="world")
    with pytest.raises(BagError, match=r"/ground_truth/pose has frame_id 'world'"):
        evaluate_bag(tmp_path / "frame", model)
    with pytest.raises(BagError, match="does not exist"):
        evaluate_bag(tmp_path / "missing", model)
    _tiny_bag(tmp_path / "posegt")
    with pytest.raises(BagError, match="no /ground_truth/point"):
        evaluate_bag(tmp_path / "posegt", model, EvaluateOptions(ground_truth="point"))
    _tiny_bag(tmp_path / "ok")
    with pytest.raises(ModelConfigError, match="cannot read"):
        evaluate_bag(tmp_path / "ok", tmp_path / "nomodel.yaml")


def test_errors_name_the_bags_urdf_and_the_model_file_line(tmp_path, capsys):
    """Issue 13: an error in a bag's URDF names the bag and topic, not ``<string>``; a model YAML
    error names its file and line; both through the CLI as one line with exit 2."""
    from ppoe_ros.cli import main

    _tiny_bag(tmp_path / "zeroaxis", axis="0 0 0")
    model = _tiny_model(tmp_path)
    for cmd in ("evaluate", "diagnose"):
        assert main([cmd, str(tmp_path / "zeroaxis"), "--model", str(model)]) == 2
        err = capsys.readouterr().err
        assert f"bag {tmp_path / 'zeroaxis'} /robot_description" in err and "<string>" not in err, err
        assert "j1" in err and len(err.strip().splitlines()) == 1, err
    _tiny_bag(tmp_path / "ok")
    bad = tmp_path / "bad.yaml"
    bad.write_text("frames: {base: base, tool: l1}\njoint_noise:\n  j1: 0.01\n  nope: 0.02\n")
    assert main(["evaluate", str(tmp_path / "ok"), "--model", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:4:" in err and "nope" in err and "<string>" not in err, err


def test_tiny_bag_fk_error_is_exact(tmp_path):
    """FK of the 1-joint arm at q = 0.1 against an identity ground truth: error = |(1 + 0) origin|."""
    _tiny_bag(tmp_path / "ok")
    ev = evaluate_bag(tmp_path / "ok", _tiny_model(tmp_path))
    fk = ev.summary["methods"]["fk"]
    np.testing.assert_allclose(fk["position_3d"]["mean"], 1.0, atol=1e-12)
    np.testing.assert_allclose(fk["rotation"]["mean"], 0.1, atol=1e-12)
    # no measurement in the bag: only forward kinematics is scored, and the report says so
    assert set(ev.summary["methods"]) == {"fk"} and "only forward kinematics" in ev.summary["fusion"]
    assert "only forward kinematics" in markdown_report(ev)
    paths = write_report(ev, tmp_path / "r")
    assert all(p.is_file() for p in paths)
    # strict JSON: the NaN of an empty statistic is written as null
    doc = json.loads(paths[1].read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert doc["methods"]["fk"]["position_3d"]["n"] == 1


# ----------------------------------------------------------------------------- measured data


@pytest.mark.datasets
@needs_data
def test_evaluate_hilti_reproduces_readme_baseline(tmp_path):
    """flat.yaml through import + evaluate: cross-set per-station registration, RMS 3D 8.64 mm."""
    from ppoe_core.io.importers.hilti import import_hilti

    res = import_hilti(DATASETS / "hilti_stationing" / "flat.yaml", tmp_path / "flat")
    ev = evaluate_bag(tmp_path / "flat", res["model"], EvaluateOptions(fit_set="cross"))
    fk = ev.summary["methods"]["fk"]["position_3d"]
    reg = ev.summary["ground_truth"]["registration"]
    assert len(reg["groups"]) == 10 and fk["n"] == 321 and reg["unscored"] == 45  # 5 upside-down stations
    assert set(ev.summary["methods"]) == {"fk"}
    assert abs(fk["rms"] - 8.64e-3) < 0.1e-3 and abs(fk["max"] - 24.66e-3) < 0.1e-3
    sq = evaluate_bag(tmp_path / "flat", res["model"], EvaluateOptions(fit_set="square"))
    assert abs(sq.summary["methods"]["fk"]["position_3d"]["rms"] - 8.74e-3) < 0.1e-3


@pytest.mark.datasets
@needs_data
def test_evaluate_motoman_marker_fusion(tmp_path):
    """Right-arm marker pixels vs Leica: registration on even poses, scored on odd ones."""
    from ppoe_core.io.importers.motoman import import_motoman

    d = DATASETS / "motoman_leica"
    # the wall set (25 poses, 311 marker points) keeps the test short; docs/results.md has all four
    res = import_motoman(d / "leica_wall_table1_5x5_dataset.mat", d / "model.yaml", tmp_path / "wall")
    # both cameras' observations of a pose share topic and stamp; the source is topic + frame_id,
    # so the default min_interval (0.05 s) throttles neither: one update per camera and pose
    ev = evaluate_bag(tmp_path / "wall", res["model"], EvaluateOptions())
    m = ev.summary["methods"]
    for method in ("ppoe", "naive"):
        c = m[method]["measurements"]["counts"]
        assert c["throttled"] == 0, (method, c)
        assert c["accepted"] + c["rejected"] == c["measurements"] == 50, (method, c)
    reg = ev.summary["ground_truth"]["registration"]
    assert reg["groups"][0]["fit"] == 13 and reg["groups"][0]["scored"] == 12
    assert m["fk"]["position_3d"]["rms"] < 0.6e-3  # README: 0.47 mm with all 25 poses in the fit
    assert m["ppoe"]["measurements"]["counts"]["accepted"] > 0
    # the PPOE covariance knows the camera chains are the weak part: fusion keeps FK accuracy,
    # the naive covariance trusts the ~24 px off markers and is pulled away
    assert m["ppoe"]["position_3d"]["rms"] < 1.5 * m["fk"]["position_3d"]["rms"]
    assert m["naive"]["position_3d"]["rms"] > 3 * m["ppoe"]["position_3d"]["rms"]


def test_fusion_settings_from_node_params_file(tmp_path, small_table1_bag):
    """A fusion-node parameter file sets the replay's pipeline; bad keys/values are refused."""
    from ppoe_core.estimation.pipeline import FUSION_SETTINGS

    pf = tmp_path / "fusion.yaml"
    pf.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {
        "use_tag_corners": False, "max_iterations": 2, "prior_topic": "/ppoe/pose"}}}))
    fusion = load_fusion_params(pf)
    assert fusion == {"use_tag_corners": False, "max_iterations": 2}  # node-only keys ignored
    opts = EvaluateOptions(fusion=fusion)
    assert opts.fusion_settings()["gate_probability"] == FUSION_SETTINGS["gate_probability"]
    ev_c = evaluate_bag(small_table1_bag, REPO / "config" / "robots" / "rover_model.yaml", opts)
    ev_d = evaluate_bag(small_table1_bag, REPO / "config" / "robots" / "rover_model.yaml")
    assert ev_c.summary["fusion_settings"]["use_tag_corners"] is False
    # centres only: fewer measured coordinates, so a different (here: not identical) estimate
    assert ev_c.summary["methods"]["ppoe"]["lateral"]["mean"] != ev_d.summary["methods"]["ppoe"]["lateral"]["mean"]
    with pytest.raises(ModelConfigError, match="unknown fusion setting"):
        EvaluateOptions(fusion={"gate": 0.9}).fusion_settings()
    with pytest.raises(ModelConfigError, match="force_component"):
        EvaluateOptions(fusion={"force_component": "sideways"}).fusion_settings()
    pf.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {"max_iterations": "many"}}}))
    with pytest.raises(ModelConfigError, match="max_iterations"):
        load_fusion_params(pf)
    pf.write_text("just: text\n")
    with pytest.raises(ModelConfigError, match="ros__parameters"):
        load_fusion_params(pf)


def test_default_settings_are_the_fusion_nodes(small_table1_bag):
    """Without overrides the replay runs the fusion node's defaults (ppoe_core.estimation.pipeline
    FUSION_SETTINGS, which the node declares), e.g. max_pending 200 and the per-source
    min_interval; a bad value is refused by make_pipeline naming the setting."""
    from ppoe_core.estimation.pipeline import FUSION_SETTINGS

    fs = EvaluateOptions().fusion_settings()
    assert {k: fs[k] for k in FUSION_SETTINGS} == FUSION_SETTINGS
    assert set(fs) - set(FUSION_SETTINGS) == set(REPLAY_SETTINGS)
    with pytest.raises(PpoeError, match="min_interval"):
        evaluate_bag(small_table1_bag, REPO / "config" / "robots" / "rover_model.yaml",
                     EvaluateOptions(fusion={"min_interval": -1.0}))


# ----------------------------------------------------------------------------- tag observations
# ppoe_core.sensing.tag_rows.observe_tags is what the tag bearing node publishes and what
# evaluate fuses from a bag's images (one function, imported by both).

_K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])
_D = np.array([-0.08, 0.02, 0.001, -0.0005, 0.0])


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6), st.floats(0.02, 0.2))
def test_tag_centre_from_corners_is_the_projected_centre(xi, size):
    """The diagonals' intersection of exactly projected (pinhole) corners is the projection of
    the tag centre, for any tag pose in front of the camera; the corners' mean is not."""
    T_cam_tag = lie.from_xyz_rpy([0.3 * xi[0], 0.3 * xi[1], 0.6 + 0.3 * xi[2]], [np.pi + 0.6 * xi[3], 0.6 * xi[4],
                                                                             3.0 * xi[5]])
    P = tags.tag_points_local(size) @ T_cam_tag[:3, :3].T + T_cam_tag[:3, 3]  # centre, 4 corners
    xy = P[:, :2] / P[:, 2:]
    np.testing.assert_allclose(centre_from_corners(xy[1:]), xy[0], atol=1e-12)
    # broadcasting over leading axes
    np.testing.assert_allclose(centre_from_corners(np.stack([xy[1:], xy[1:]])), [xy[0], xy[0]], atol=1e-12)


def test_observe_tags_against_known_projection():
    """Rendered tags (distorted camera, strongly tilted tag) against their true projection."""
    size = 0.06
    T_list = [lie.from_xyz_rpy([-0.07, 0.02, 0.35], [np.pi + 0.7, -0.2, 0.1]),
              lie.from_xyz_rpy([0.09, -0.03, 0.45], [np.pi - 0.15, 0.6, -0.4])]
    img, drawn = tags.render_tags((640, 480), _K, _D, T_list, [3, 7], size, supersample=4)
    assert sorted(drawn) == [3, 7]
    rows, dets = observe_tags(img, _K, _D, "tag36h11")
    truth = {}
    for tid, T in zip([3, 7], T_list):
        P = tags.tag_points_local(size) @ T[:3, :3].T + T[:3, 3]
        truth[tid] = (camera.project_points(P, _K, _D), P[:, :2] / P[:, 2:])
    assert rows.shape == (10, 6)
    for r in rows:
        uv, xy = truth[int(r[0])]
        c = int(r[1])
        assert np.linalg.norm(r[2:4] - uv[c]) < 0.3  # px
        assert np.linalg.norm(r[4:6] - xy[c]) < 0.3 / 600
    # x, y are the undistorted u, v (the centre is distorted back from its x, y)
    np.testing.assert_allclose(camera.undistort_pixels(rows[:, 2:4], _K, _D), rows[:, 4:6], atol=1e-9)
    # the perspective is strong enough that the corners' mean would be wrong by > 1 px
    centres = rows[rows[:, 1] == 0]
    for r in centres:
        uv, _ = truth[int(r[0])]
        assert np.linalg.norm(uv[1:].mean(axis=0) - uv[0]) > 1.0
    # id filter and an image without tags
    assert set(observe_tags(img, _K, _D, tag_ids=[7])[0][:, 0]) == {7.0}
    assert observe_tags(np.full((480, 640), 128, np.uint8), _K, _D)[0].shape == (0, 6)


# ----------------------------------------------------------------------------- contact


def test_evaluate_contact_bag_replays_wrench_through_the_contact_detector():
    """``ppoe evaluate bags/contact``: /wrench -> ContactDetector -> the model YAML's table plane
    -> fusion: the fused fingertip is closer to ground truth than FK, and along the table normal
    (what a contact observes) the error almost vanishes on the contact stops."""
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.config import load_contact_config
    from ppoe_core.sensing.contact import ContactDetector, contact_stamps

    bag, model = REPO / "bags" / "contact", REPO / "config" / "robots" / "humanoid_model.yaml"
    ev = evaluate_bag(bag, model)
    meas = ev.summary["measurements"]
    contact = load_contact_config(model)
    wr = read_bag(bag, topics=["/wrench"]).wrench
    on, _ = contact_stamps(wr.stamps, wr.force, ContactDetector(contact.force_threshold, contact.release_threshold))
    assert meas["contact_source"] == "/wrench" and meas["contact_planes"] == len(on) == meas["total"] > 0
    assert meas["wrench"]["contacts"] == 8 and meas["wrench"]["bad"] == 0  # 8 touches in bags/contact.yaml
    m = ev.summary["methods"]
    c = m["ppoe"]["measurements"]["counts"]
    assert c["accepted"] >= 8 and c["rejected"] == 0 and c["bad"] == 0
    # throttled by the fusion node's min_interval (0.05 s per source) as live: 100 Hz -> <= 20 Hz
    assert c["throttled"] > 0 and c["accepted"] + c["throttled"] == len(on)
    assert m["ppoe"]["position_3d"]["mean"] < 0.9 * m["fk"]["position_3d"]["mean"]
    e_fk, e_fused = ev.samples["fk_position_error"], ev.samples["ppoe_position_error"]
    normal = contact.T_frame_plane[:3, 2]  # plane frame = the state's base (camera_optical_frame)
    touched = np.linalg.norm(e_fused - e_fk, axis=1) > 1e-9
    assert touched.sum() == 8
    n_fk, n_fused = np.abs(e_fk[touched] @ normal), np.abs(e_fused[touched] @ normal)
    assert n_fused.mean() < 0.1 * n_fk.mean(), (n_fused, n_fk)


def test_cli_contact_thresholds_and_settings(capsys):
    """``--set force_threshold=...`` reaches the replayed contact detector: above the 8-15 N
    presses nothing is in contact and only FK is scored."""
    from ppoe_core.cli import evaluate as cli_evaluate

    parser = argparse.ArgumentParser()
    cli_evaluate.add_arguments(parser)
    args = parser.parse_args(
        [
            str(REPO / "bags" / "contact"),
            "--model",
            str(REPO / "config" / "robots" / "humanoid_model.yaml"),
            "--set",
            "force_threshold=100.0",
            "--set",
            "release_threshold=50",
            "--json",
            "--no-progress",
        ]
    )
    assert cli_evaluate.run(args) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["measurements"]["contact_planes"] == 0 and doc["measurements"]["wrench"]["contacts"] == 0
    assert list(doc["methods"]) == ["fk"]
    args = parser.parse_args(
        [
            str(REPO / "bags" / "contact"),
            "--model",
            str(REPO / "config" / "robots" / "humanoid_model.yaml"),
            "--set",
            "release_threshold=6.0",
            "--no-progress",
        ]
    )
    with pytest.raises(ModelConfigError, match="humanoid_model.yaml: contact: release_threshold .* must be below"):
        cli_evaluate.run(args)
    args = parser.parse_args(
        [
            str(REPO / "bags" / "contact"),
            "--model",
            str(REPO / "config" / "robots" / "humanoid_model.yaml"),
            "--set",
            "no_such_key=1",
            "--no-progress",
        ]
    )
    with pytest.raises(ModelConfigError, match="unknown fusion setting"):
        cli_evaluate.run(args)


@pytest.mark.ros
@pytest.mark.timeout(240)
def test_evaluate_matches_live_node_pipeline(tmp_path):
    """``ppoe play`` of a shipped bag through the live kinematics, tag bearing and fusion nodes
    gives the same PPOE-fused errors as ``ppoe evaluate`` of that bag with the same node
    parameters.

    The correction timeout is off (``correction_timeout: 0``), so within a static stop a correction
    keeps weight 1 and every fused pose the fusion node publishes after the stop's first
    observation is processed and before the stop's second image equals the evaluate estimate at
    the ground-truth stamp (the first image's stamp), whatever the live message timing.
    """
    pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file

    from ppoe_core.io.bagio import read_bag
    from ppoe_ros.common import matrix_from_pose_msg

    bag = REPO / "bags" / "table1_exp1"
    model = REPO / "config" / "robots" / "rover_model.yaml"
    env = ros_env(tmp_path)
    common = {"model_file": str(model), "diagnostics_period": 1.0}
    pf_fusion = write_params_file(tmp_path / "fusion.yaml", {**common, "correction_timeout": 0.0})
    pf_kin = write_params_file(tmp_path / "kin.yaml", common)
    pf_tag = write_params_file(tmp_path / "tag.yaml", common)
    topics = ["/robot_description", "/joint_states", "/camera/camera_info", "/camera/image_raw/compressed"]
    with (
        Probe(env) as probe,
        NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf_kin) as kin,
        NodeProcess.node("tag_bearing_node", env, tmp_path, params_file=pf_tag) as tag,
        NodeProcess.node("fusion_node", env, tmp_path, params_file=pf_fusion) as fus,
    ):
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        probe.wait_for_publishers("/ppoe/fused_pose", fus)
        # the bag's URDF first (latched, from the probe), the data only once both nodes built their model
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from std_msgs.msg import String

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub = probe.publisher("/robot_description", String, qos=latched)
        pub.publish(String(data=read_bag(bag, topics=["/robot_description"]).robot_description))
        for p in (kin, fus):
            probe.spin_until(lambda p=p: "model from topic" in p.output(), timeout=60.0, proc=p, what="the model")
        # half speed: on a loaded 2-core machine the nodes otherwise lag and drop sensor-QoS messages
        play = NodeProcess.ppoe(
            ["play", str(bag), "--rate", "0.5", "--topics", *topics[1:], "--wait-for-subscribers", "30"],
            env,
            tmp_path,
            "play",
        )
        with play:
            probe.spin_until(lambda: not play.alive(), timeout=120.0)  # keep receiving while playing
            rc = play.wait(10)
        assert rc == 0, play.output()[-2000:]
        probe.spin_for(2.0)
        for p in (kin, tag, fus):
            assert p.alive(), p.output()[-2000:]
    assert fused, fus.output()[-2000:]
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in fused])
    T_live = np.stack([matrix_from_pose_msg(m.pose.pose) for m in fused])

    ev = evaluate_bag(bag, model, EvaluateOptions(fusion=load_fusion_params(pf_fusion)))
    data = read_bag(bag)
    gt_t, gt_T = data.ground_truth_pose.stamps, data.ground_truth_pose.T
    img_t = np.sort(data.images.stamps)
    live_e3 = np.full(len(gt_t), np.nan)
    for i, (t, T_gt) in enumerate(zip(gt_t, gt_T)):
        nxt = img_t[img_t > t + 1e-6]
        t_end = min(nxt[0] if nxt.size else t + 0.5, t + 0.5) - 1e-6
        sel = np.flatnonzero((stamps > t + 1e-6) & (stamps < t_end))
        if sel.size:
            k = sel[np.argmax(stamps[sel])]  # the newest: the stop's first image is processed by then
            live_e3[i] = np.linalg.norm(T_live[k][:3, 3] - T_gt[:3, 3])
    # Under heavy load a sensor-QoS message may be lost, leaving one stop's window without a live
    # pose; at most one such stop is tolerated, every other stop is compared.
    ok = np.isfinite(live_e3)
    assert ok.sum() >= len(gt_t) - 1, f"live fused poses for only {ok.sum()} of {len(gt_t)} stops"
    # A stop whose first observation reached the fusion node only after the second image's
    # stamp (the tag node's first detection is slow: it builds its detector) has no corrected
    # pose in the window: its newest pose there is the FK prior. All others must agree exactly.
    fk_e3 = ev.samples["fk_position_3d"]
    late = ok & (np.abs(live_e3 - fk_e3) < 1e-9)
    assert late.sum() <= 1, f"stops without a correction in time: {np.flatnonzero(late)}"
    cmp = ok & ~late
    assert cmp.sum() >= len(gt_t) - 2
    np.testing.assert_allclose(live_e3[cmp], ev.samples["ppoe_position_3d"][cmp], atol=1e-6)
    # and the fusion did something: the errors are well below FK's
    assert live_e3[cmp].mean() < 0.5 * fk_e3[cmp].mean()


@pytest.mark.parametrize("command", ["evaluate", "diagnose"])
def test_out_path_checked_before_the_run(tmp_path, capsys, monkeypatch, command):
    """``--out`` on an existing file or an unwritable place: one clear line naming it, exit 2, and the bag is
    never read (checked before the run, not after it)."""
    import ppoe_core.analysis.evaluate
    import ppoe_core.io.bagio
    from ppoe_ros.cli import main

    def never(*args, **kwargs):
        raise AssertionError("the run started although --out is unusable")

    monkeypatch.setattr(ppoe_core.analysis.evaluate, "evaluate_bag", never)
    monkeypatch.setattr(ppoe_core.io.bagio, "read_bag", never)
    existing = tmp_path / "report.txt"
    existing.write_text("keep me")
    bag, model = (("no_effect", "arm7_model.yaml") if command == "diagnose" else ("contact", "humanoid_model.yaml"))
    argv = [command, str(REPO / "bags" / bag), "--model", str(REPO / "config" / "robots" / model)]
    assert main([*argv, "--out", str(existing)]) == 2
    err = capsys.readouterr().err
    assert f"--out {existing}: is an existing file, not a directory" in err and "Traceback" not in err
    assert existing.read_text() == "keep me"
    assert main([*argv, "--out", "/proc/ppoe_cannot_create_this"]) == 2
    err = capsys.readouterr().err
    assert "--out /proc/ppoe_cannot_create_this: cannot write there" in err


def test_split_joint_states_are_merged_like_the_kinematics_node(small_table1_bag, tmp_path):
    """The same bag with every joint-state message split in two (the first joints, then the rest 1 ms later, as
    two publishers would): evaluate merges per joint (values at most 0.5 s old), skips only what cannot be
    completed (the very first message) and scores as on the original bag."""
    from ppoe_core.io.bagio import BagWriter, iter_raw, read_bag

    data = read_bag(small_table1_bag)
    js = data.joint_states
    split = tmp_path / "split"
    k = len(js.names) // 2
    with BagWriter(split) as w:
        for m in iter_raw(small_table1_bag):
            if m.topic != "/joint_states":
                w.write_raw(m.topic, m.msgtype, m.stamp_ns, m.data)
        for i in range(len(js)):
            w.write_joint_state(float(js.stamps[i]), js.names[:k], js.positions[i, :k])
            w.write_joint_state(float(js.stamps[i]) + 0.001, js.names[k:], js.positions[i, k:])
    model = REPO / "config" / "robots" / "rover_model.yaml"
    a = evaluate_bag(small_table1_bag, model).summary
    b = evaluate_bag(split, model).summary
    assert a["joint_states_incomplete"] == 0 and b["joint_states_incomplete"] == 1
    assert b["joint_states"] == 2 * a["joint_states"] and b["joint_values_held"] > 0
    for method in ("fk", "ppoe"):
        ra, rb = a["methods"][method]["position_3d"]["rms"], b["methods"][method]["position_3d"]["rms"]
        assert rb == pytest.approx(ra, rel=0.05), (method, ra, rb)


def test_error_stats_give_median_and_p95_beside_mean_and_rms():
    from ppoe_core.analysis.evaluate.metrics import error_stats

    v = np.arange(1.0, 101.0)  # 1..100
    st = error_stats(np.append(v, np.nan))
    assert st["n"] == 100 and st["median"] == 50.5 and st["p95"] == pytest.approx(95.05)
    assert st["mean"] == 50.5 and st["max"] == 100.0 and st["rms"] == pytest.approx(np.sqrt(np.mean(v ** 2)))
    assert np.isnan(error_stats(np.array([np.nan]))["p95"])


def test_a_recorded_estimate_topic_is_scored_beside_the_replay(small_table1_bag, tmp_path, capsys):
    """``--estimate TOPIC`` scores a recorded PoseWithCovarianceStamped topic (e.g. /ppoe/fused_pose of a live run):
    here the ground truth shifted by 1 mm in x, stamped with it, so its 3D error is 1 mm at every sample."""
    from ppoe_core.io.bagio import BagWriter, iter_raw, read_bag
    from ppoe_ros.cli import main

    gt = read_bag(small_table1_bag).ground_truth_pose
    bag = tmp_path / "with_estimate"
    with BagWriter(bag) as w:
        for m in iter_raw(small_table1_bag):
            w.write_raw(m.topic, m.msgtype, m.stamp_ns, m.data)
        for i in range(len(gt)):
            T = gt.T[i].copy()
            T[0, 3] += 1e-3
            w.write_pose_with_covariance("/ppoe/fused_pose", float(gt.stamps[i]), "base_link", T, 1e-6 * np.eye(6))
    model = str(REPO / "config" / "robots" / "rover_model.yaml")
    assert main(["evaluate", str(bag), "--model", model, "--estimate", "/ppoe/fused_pose", "--json",
                 "--no-progress"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rec = doc["methods"]["recorded"]["position_3d"]
    assert rec["n"] == 5 and rec["rms"] == pytest.approx(1e-3, rel=1e-6) and rec["p95"] == pytest.approx(1e-3)
    assert doc["recorded_estimate"] == "/ppoe/fused_pose"
    assert main(["evaluate", str(bag), "--model", model, "--estimate", "/nope", "--no-progress"]) == 2
    assert "--estimate /nope: no PoseWithCovarianceStamped messages on it" in capsys.readouterr().err
