"""``ppoe plan`` (issue 26): the information from the engine's blocks, the design, the constraints on every planned
pose, the outputs and the errors.  The simulate/diagnose round trip is ``test_plan_roundtrip.py``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import CONFIG, DATA

from ppoe_core.analysis.plan.constraints import Constraints, collision_capsules, segment_distance, violations
from ppoe_core.analysis.plan.design import (
    MIN_D_EFFICIENCY,
    SOFT_MAX_POWER,
    design,
    information_of,
    log_det,
    minimax,
    observability_indices,
    relative_variance,
)
from ppoe_core.analysis.plan.information import pose_information, reduced_information, target_effects
from ppoe_core.analysis.plan.outputs import trajectory_message
from ppoe_core.analysis.plan.planner import information_bound, predict
from ppoe_core.cli.fk import read_batch_csv
from ppoe_core.errors import ScenarioError
from ppoe_core.robot.config import load_model_config
from ppoe_core.robot.dh import dh_to_urdf
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf
from ppoe_ros.cli import main

PLAN = DATA / "plan"
COBOT_CAMERA = {"image_width": 1920, "image_height": 1200,   # the declared camera of test/data/engine/_cobot6_camera
                "camera_matrix": {"rows": 3, "cols": 3, "data": [1650.0, 0, 960.0, 0, 1650.0, 600.0, 0, 0, 1]},
                "distortion_coefficients": {"rows": 1, "cols": 5, "data": [-0.02, 0.01, 0, 0, 0]}}


@pytest.fixture(scope="module")
def cobot(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, KinematicTree, object]:
    d = tmp_path_factory.mktemp("cobot")
    urdf = d / "cobot6.urdf"
    urdf.write_text(dh_to_urdf(CONFIG / "robots" / "cobot6_dh.yaml"))
    robot = parse_urdf(str(urdf))
    return urdf, KinematicTree(robot), load_model_config(str(CONFIG / "robots" / "cobot6_model.yaml"), robot)


@pytest.fixture(scope="module")
def info(cobot):
    _, tree, model = cobot
    from ppoe_core.analysis.plan.constraints import sample_candidates
    targets = target_effects(tree, [("joint_offset", "shoulder_lift", []), ("joint_offset", "elbow", []),
                                    ("gravity_compliance", "elbow", [])])
    q, _ = sample_candidates(tree, Constraints(points=[(t.link, t.xyz) for t in model.trackers]), 300,
                             np.random.default_rng(3))
    return pose_information(tree, model.trackers, q, targets)


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


# -- information and design -----------------------------------------------------------------------------------------

def test_reduced_information_is_the_projection_onto_what_the_registration_cannot_explain(info) -> None:
    """Schur complement of the summed blocks == G^T (I - N N^+) G of the stacked rows of those poses."""
    idx = np.arange(0, 40, 3)
    G = info.G[idx].reshape(-1, info.G.shape[2])
    N = info.N[idx].reshape(-1, info.N.shape[2])
    P = np.eye(G.shape[0]) - N @ np.linalg.pinv(N)
    H_ref = G.T @ P @ G
    H = information_of(info, idx)
    np.testing.assert_allclose(H, H_ref, rtol=1e-6, atol=1e-9 * np.abs(H_ref).max())


def test_predicted_covariance_montecarlo(info) -> None:
    """Seeded Monte-Carlo: least-squares fits of (theta, registration) on whitened rows with unit noise scatter as
    the predicted covariance of theta (diagonal within 10 %, 2000 draws)."""
    rng = np.random.default_rng(11)
    idx = np.arange(12)
    G = info.G[idx].reshape(-1, info.G.shape[2])
    N = info.N[idx].reshape(-1, info.N.shape[2])
    X = np.concatenate([G, N], axis=1)
    E = rng.standard_normal((X.shape[0], 2000))
    est = np.linalg.lstsq(X, E, rcond=None)[0][:G.shape[1]]
    pred = predict(info, idx)
    np.testing.assert_allclose(np.cov(est), pred.cov, rtol=0.1, atol=0.1 * np.sqrt(np.outer(np.diag(pred.cov),
                                                                                             np.diag(pred.cov))).max())
    np.testing.assert_allclose(pred.ci95, 1.96 * np.sqrt(np.diag(np.cov(est))), rtol=0.06)


def test_design_beats_every_random_subset_and_exchange_never_lowers_it(info) -> None:
    n = 8
    d = design(info, n)
    assert len(set(d.chosen.tolist())) == n
    greedy = design(info, n, max_passes=0)
    assert d.log_det >= greedy.log_det - 1e-9
    rng = np.random.default_rng(5)
    rand = [float(log_det(information_of(info, rng.choice(info.A.shape[0], n, replace=False)), info.scale))
            for _ in range(200)]
    assert d.log_det > max(rand)
    assert d.log_det == pytest.approx(float(log_det(information_of(info, d.chosen), info.scale)), abs=1e-9)


def test_minimax_stage_lowers_the_worst_relative_variance_and_keeps_the_d_efficiency(info) -> None:
    """Reference: the median variances of 32 random poses; the second stage from the D-optimal 8 poses lowers the
    soft maximum of var_k / ref_k, keeps log det within P log(MIN_D_EFFICIENCY) of the D-optimum, and the soft
    maximum (mean r^p)^(1/p) lies between P^(-1/p) times the largest ratio and the largest ratio."""
    n, P = 8, info.A.shape[1]
    rng = np.random.default_rng(8)
    ref = np.median([np.diag(predict(info, rng.choice(info.A.shape[0], 4 * n, replace=False)).cov)
                     for _ in range(20)], axis=0)
    d = design(info, n)
    m = minimax(info, d.chosen, ref)
    assert len(set(m.chosen.tolist())) == n
    before = float(relative_variance(information_of(info, d.chosen), info.scale, ref))
    after = float(relative_variance(information_of(info, m.chosen), info.scale, ref))
    assert m.exchanges > 0 and after < before
    assert m.log_det >= d.log_det + P * np.log(MIN_D_EFFICIENCY) - 1e-9
    r = np.diag(predict(info, m.chosen).cov) / ref
    assert r.max() * P ** (-1 / SOFT_MAX_POWER) * (1 - 1e-6) <= after <= r.max() * (1 + 1e-6)


def test_information_bound_holds_for_every_pose_set(info) -> None:
    """No n poses of the pool give a parameter a half-width below information_bound: checked on the D-optimal, the
    minimax and 200 random sets; and it is attained for one parameter measured alone by one row per pose."""
    n = 8
    bound = information_bound(info, n)
    rng = np.random.default_rng(9)
    sets = [design(info, n).chosen] + [rng.choice(info.A.shape[0], n, replace=False) for _ in range(200)]
    for idx in sets:
        assert np.all(predict(info, idx).ci95 >= bound * (1 - 1e-9))
    a = np.diagonal(info.A, axis1=1, axis2=2)[:, 0]
    best = np.argsort(a)[::-1][:n]
    assert bound[0] == pytest.approx(1.96 / np.sqrt(a[best].sum()))


def test_observability_indices_of_known_singular_values() -> None:
    s = np.array([4.0, 2.0, 1.0])
    ind = observability_indices(np.diag(s ** 2), np.ones(3), 4)
    assert ind["O1"] == pytest.approx(2.0 / 2.0)
    assert ind["O2"] == pytest.approx(0.25)
    assert ind["O3"] == pytest.approx(1.0)
    assert ind["O4"] == pytest.approx(0.25)
    assert ind["O5"] == pytest.approx(1.0 / 1.75)
    assert ind["condition_number"] == pytest.approx(4.0)


def test_reduced_information_batched_shapes() -> None:
    rng = np.random.default_rng(0)
    G, N = rng.standard_normal((5, 9, 3)), rng.standard_normal((5, 9, 2))
    H = reduced_information(np.einsum("uki,ukj->uij", G, G), np.einsum("uki,ukj->uij", G, N),
                            np.einsum("uki,ukj->uij", N, N), ridge=0.0)
    for u in range(5):
        P = np.eye(9) - N[u] @ np.linalg.pinv(N[u])
        np.testing.assert_allclose(H[u], G[u].T @ P @ G[u], atol=1e-10)


# -- constraints ----------------------------------------------------------------------------------------------------

def test_segment_distance_against_dense_sampling() -> None:
    rng = np.random.default_rng(2)
    a0, a1, b0, b1 = (rng.standard_normal((50, 3)) for _ in range(4))
    t = np.linspace(0, 1, 201)
    A = a0[:, None, :] + t[None, :, None] * (a1 - a0)[:, None, :]
    B = b0[:, None, :] + t[None, :, None] * (b1 - b0)[:, None, :]
    dense = np.linalg.norm(A[:, :, None, :] - B[:, None, :, :], axis=-1).min(axis=(1, 2))
    d = segment_distance(a0, a1, b0, b1)
    assert np.all(d <= dense + 1e-12)
    np.testing.assert_allclose(d, dense, atol=1e-2)


def test_collision_and_line_of_sight_flag_known_configurations() -> None:
    tree = KinematicTree(parse_urdf(str(PLAN / "fold3.urdf")))
    caps, meshes = collision_capsules((PLAN / "fold3.urdf").read_text())
    assert len(caps) == 5 and meshes == 0
    pts = [("tool0", np.array([0.0, 0.0, 0.03]))]
    q = {"j1": np.array([0.0, 0.0, 1.4, 0.0]), "j2": np.array([0.0, 2.8, 0.0, 0.0]),
         "j3": np.array([0.0, 2.8, 0.0, 3.0])}
    v = violations(tree, q, Constraints(capsules=caps, points=pts, tracker_at=np.array([-2.0, 0.0, 0.2])))
    # straight arm: free, but the base column hides the reflector from a tracker behind it
    assert v["self_collision"].tolist() == [False, True, True, False]
    assert v["line_of_sight"][0]
    assert v["joint_limits"].tolist() == [False, False, False, True]   # j3 = 3.0 > 2.9 - margin
    v2 = violations(tree, q, Constraints(capsules=caps, points=pts, tracker_at=np.array([2.0, 0.0, 0.5])))
    assert not v2["line_of_sight"][0]


def test_every_planned_pose_passes_every_constraint(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """fold3 (URDF collision capsules), joint margin, workspace box, tracker line of sight: the planned poses pass
    each check, and the checks did reject draws (so they were active)."""
    out = tmp_path / "p"
    code, stdout, err = _run(["plan", "--urdf", str(PLAN / "fold3.urdf"), "--model", str(PLAN / "fold3_model.yaml"),
                              "--effects", "joint_offset@j2", "joint_offset@j3", "gravity_compliance@j2",
                              "--n", "6", "--out", str(out), "--candidates", "300", "--margin", "0.1",
                              "--box", "-2", "-2", "0.1", "2", "2", "2", "--tracker-at", "-2", "0", "0.2",
                              "--json"], capsys)
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["rejected_draws"]["self_collision"] > 0 and doc["rejected_draws"]["line_of_sight"] > 0
    assert doc["rejected_draws"]["workspace_box"] > 0
    tree = KinematicTree(parse_urdf(str(PLAN / "fold3.urdf")))
    q = read_batch_csv(str(out / "poses.csv"), tree.robot.independent_joints)
    caps, _ = collision_capsules((PLAN / "fold3.urdf").read_text())
    c = Constraints(margin=0.1, box=(np.array([-2, -2, 0.1]), np.array([2, 2, 2.0])), capsules=caps,
                    clearance=0.01, tracker_at=np.array([-2.0, 0.0, 0.2]), points=[("tool0", np.array([0, 0, 0.03]))])
    for name, bad in violations(tree, q, c).items():
        assert not bad.any(), name


def test_tags_in_view_on_every_planned_pose(cobot, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    urdf, tree, model = cobot
    info_yaml = tmp_path / "camera_info.yaml"
    info_yaml.write_text(yaml.safe_dump(COBOT_CAMERA))
    out = tmp_path / "p"
    code, stdout, err = _run(["plan", "--urdf", str(urdf), "--model", str(CONFIG / "robots" / "cobot6_model.yaml"),
                              "--effects", "joint_offset@elbow", "gravity_compliance@elbow", "--n", "5",
                              "--candidates", "200", "--camera-info", str(info_yaml), "--max-view-angle", "50",
                              "--region", "shoulder_pan=-1.9:-0.5", "--out", str(out), "--json"], capsys)
    assert code == 0, err
    assert json.loads(stdout)["rejected_draws"]["tags_in_view"] > 0
    from ppoe_core.cli.plan import _camera
    cam = _camera(str(info_yaml), model)
    q = read_batch_csv(str(out / "poses.csv"), tree.robot.independent_joints)
    c = Constraints(camera=cam, tags=model.tags.items, min_tags=1, max_view_angle=50.0)
    assert not violations(tree, q, c)["tags_in_view"].any()
    strict = Constraints(camera=cam, tags=model.tags.items, min_tags=1, max_view_angle=1.0)
    assert violations(tree, q, strict)["tags_in_view"].all()   # facing within 1 deg: none of them


# -- errors ---------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("extra, needle", [
    (["--effects", "joint_offset@no_such_link", "--n", "5"], "'no_such_link' is neither a joint nor a link"),
    (["--effects", "link_error@j3", "--n", "4"], "--n 4 poses is fewer than the 6 target parameters"),
    (["--effects", "joint_offset@j2", "--n", "4", "--box", "5", "5", "5", "6", "6", "6"], "empty feasible set"),
    (["--effects", "backlash@j2", "--n", "4"], "a pose design cannot plan it"),
    (["--effects", "joint_offset@j1", "--n", "4"], "cannot be told apart from the tracker registration"),
    (["--effects", "joint_offset@j2", "--n", "4", "--region", "j9=0:1"], "['j9'], not independent joints"),
])
def test_bad_input_is_a_clear_error(extra: list[str], needle: str, tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(["plan", "--urdf", str(PLAN / "fold3.urdf"), "--model", str(PLAN / "fold3_model.yaml"),
                         "--out", str(tmp_path / "p"), "--candidates", "50", *extra], capsys)
    assert code == 2
    assert needle in err and "Traceback" not in err


# -- outputs --------------------------------------------------------------------------------------------------------

def test_outputs_csv_trajectory_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "p"
    code, _, err = _run(["plan", "--urdf", str(PLAN / "fold3.urdf"), "--model", str(PLAN / "fold3_model.yaml"),
                         "--effects", "joint_offset@j2", "gravity_compliance@j2", "--n", "5", "--out", str(out),
                         "--candidates", "100", "--dwell", "2.0", "--max-speed", "0.5", "--min-move", "1.0"], capsys)
    assert code == 0, err
    with open(out / "poses.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["j1", "j2", "j3"] and len(rows) == 6
    q = read_batch_csv(str(out / "poses.csv"), ["j1", "j2", "j3"])
    traj = yaml.safe_load((out / "trajectory.yaml").read_text())
    assert traj["joint_names"] == ["j1", "j2", "j3"] and len(traj["points"]) == 10
    t = [p["time_from_start"]["sec"] + 1e-9 * p["time_from_start"]["nanosec"] for p in traj["points"]]
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.diff(t)[0::2], 2.0, atol=1e-9)                      # dwell at each pose
    Q = np.stack([q[j] for j in ("j1", "j2", "j3")], axis=1)
    moves = np.maximum(1.0, np.abs(np.diff(Q, axis=0)).max(axis=1) / 0.5)
    np.testing.assert_allclose(np.diff(t)[1::2], moves, atol=1e-9)
    for p, row in zip(traj["points"][0::2], Q):
        np.testing.assert_allclose(p["positions"], row)
        assert p["velocities"] == [0.0, 0.0, 0.0]
    doc = json.loads((out / "plan.json").read_text())
    assert set(doc["planned"]["ci95"]) == {"joint_offset@j2:offset", "gravity_compliance@j2:compliance"}
    assert doc["planned"]["heldout_rms"] > 5e-5 * np.sqrt(3) * 0.99      # never below the sensor noise
    assert {"O1", "O2", "O3", "O4", "O5", "condition_number"} <= set(doc["planned"]["indices"])
    assert doc["planned"]["indices"]["O1"] > doc["random_n"]["indices"]["O1"]
    assert (out / "plan.png").is_file()


def test_trajectory_message_single_pose() -> None:
    msg = trajectory_message({"a": np.array([0.5])}, 1.5, 1.0, 1.0)
    assert [p["time_from_start"] for p in msg["points"]] == [{"sec": 0, "nanosec": 0}, {"sec": 1, "nanosec": 500000000}]


def test_given_data_counts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--given``: the given bag's information is part of the prediction (tighter than the same plan alone)."""
    urdf = str(PLAN / "fold3.urdf")
    common = ["--urdf", urdf, "--model", str(PLAN / "fold3_model.yaml"), "--effects", "joint_offset@j2",
              "gravity_compliance@j2", "--candidates", "100", "--json"]
    code, out1, err = _run(["plan", *common, "--n", "8", "--out", str(tmp_path / "a")], capsys)
    assert code == 0, err
    scen = tmp_path / "s.yaml"
    scen.write_text(yaml.safe_dump({
        "robot": {"urdf": urdf, "model": str(PLAN / "fold3_model.yaml")}, "seed": 1,
        "truth": {"perturbations": "none", "joint_noise": False},
        "trajectory": {"joint_rate": 50.0, "dwell": 0.3, "settle": 0.1, "move_time": 0.4,
                       "stops_csv": str(tmp_path / "a" / "poses.csv")},
        "ground_truth": {"point": {"frame": "tracker", "rate": 0.0}}}))
    code, _, err = _run(["simulate", str(scen), "--out", str(tmp_path / "bag")], capsys)
    assert code == 0, err
    code, out2, err = _run(["plan", *common, "--n", "4", "--out", str(tmp_path / "b"), "--given",
                            str(tmp_path / "bag")], capsys)
    assert code == 0, err
    alone, given = json.loads(out1)["planned"]["ci95"], json.loads(out2)["planned"]["ci95"]
    assert all(given[k] < alone[k] for k in alone)


def test_simulate_stops_csv_errors(tmp_path: Path) -> None:
    from ppoe_core.sim.simulate import simulate
    bad = tmp_path / "bad.csv"
    bad.write_text("j1,j9\n0,0\n")
    scen = tmp_path / "s.yaml"
    scen.write_text(yaml.safe_dump({
        "robot": {"urdf": str(PLAN / "fold3.urdf"), "model": str(PLAN / "fold3_model.yaml")},
        "trajectory": {"stops_csv": "bad.csv"}, "ground_truth": {"point": {"frame": "tracker"}}}))
    with pytest.raises(ScenarioError, match=r"bad.csv: line 1: \['j9'\] are not independent joints"):
        simulate(scen, tmp_path / "bag")
    bad.write_text("j1,j2\n0,x\n")
    with pytest.raises(ScenarioError, match="line 2: not a number"):
        simulate(scen, tmp_path / "bag")


def test_refinement_never_lowers_log_det_and_stays_feasible(cobot, info) -> None:
    from ppoe_core.analysis.plan.refine import refine
    _, tree, model = cobot
    targets = target_effects(tree, [("joint_offset", "shoulder_lift", []), ("joint_offset", "elbow", []),
                                    ("gravity_compliance", "elbow", [])])
    c = Constraints(margin=0.2, points=[(t.link, t.xyz) for t in model.trackers],
                    box=(np.array([-2.0, -2.0, 0.9]), np.array([2.0, 2.0, 3.0])))
    d = design(info, 6)
    joints = tree.robot.independent_joints
    from ppoe_core.analysis.plan.constraints import sample_candidates
    q, _ = sample_candidates(tree, c, 6, np.random.default_rng(4))
    Q = np.stack([q[j] for j in joints], axis=1)
    start = float(log_det(information_of(pose_information(tree, model.trackers, q, targets, (), info.scale),
                                         np.arange(6)), info.scale))
    ref = refine(tree, model.trackers, targets, (), c, Q, info.scale, None, np.random.default_rng(0))
    assert ref.moved > 0 and ref.log_det > start
    assert ref.log_det == pytest.approx(float(log_det(information_of(ref.info, np.arange(6)), info.scale)))
    v = violations(tree, {j: ref.Q[:, i] for i, j in enumerate(ref.joints)}, c)
    assert not any(m.any() for m in v.values())
    assert d.chosen.size == 6


def test_trajectory_yaml_builds_a_joint_trajectory_message(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``trajectory.yaml``'s fields are those of ``trajectory_msgs/JointTrajectory`` (the message builds from it)."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    out = tmp_path / "p"
    code, _, err = _run(["plan", "--urdf", str(PLAN / "fold3.urdf"), "--model", str(PLAN / "fold3_model.yaml"),
                         "--effects", "joint_offset@j2", "--n", "3", "--out", str(out), "--candidates", "50"], capsys)
    assert code == 0, err
    doc = yaml.safe_load((out / "trajectory.yaml").read_text())
    assert set(doc) == set(JointTrajectory.get_fields_and_field_types())
    msg = JointTrajectory(joint_names=doc["joint_names"], points=[
        JointTrajectoryPoint(**{k: (Duration(**v) if k == "time_from_start" else v) for k, v in p.items()})
        for p in doc["points"]])
    assert len(msg.points) == 6 and msg.points[-1].time_from_start.sec >= 3


def test_tag_pixels_add_information_with_the_camera_pose_eliminated(cobot) -> None:
    """The same poses with the camera's tag pixels in the design: every predicted half-width tighter or equal (more
    rows; the camera pose, a nuisance, only touches the pixel rows), the pixel rows zero where no tag is usable."""
    from ppoe_core.analysis.plan.constraints import CameraView, sample_candidates
    from ppoe_core.analysis.plan.information import PixelDesign
    _, tree, model = cobot
    cam_doc = yaml.safe_load((PLAN / "camera_info.yaml").read_text())
    cam = CameraView(model.camera.frame, np.array(cam_doc["camera_matrix"]["data"]).reshape(3, 3),
                     np.array(cam_doc["distortion_coefficients"]["data"]), 1920, 1200)
    c = Constraints(camera=cam, tags=model.tags.items, region={"shoulder_pan": (-1.9, -0.5)},
                    points=[(t.link, t.xyz) for t in model.trackers])
    targets = target_effects(tree, [("joint_offset", "shoulder_lift", []), ("joint_offset", "elbow", []),
                                    ("gravity_compliance", "elbow", [])])
    q, _ = sample_candidates(tree, c, 40, np.random.default_rng(8))
    plain = pose_information(tree, model.trackers, q, targets)
    both = pose_information(tree, model.trackers, q, targets, (), plain.scale, PixelDesign(c, 0.25))
    assert both.G.shape[1] == plain.G.shape[1] + 10 * len(model.tags.items) and both.N.shape[2] == 12
    idx = np.arange(20)
    a, b = predict(plain, idx), predict(both, idx)
    assert np.all(b.ci95 <= a.ci95 * (1 + 1e-9)) and np.all(b.ci95 < 0.99 * a.ci95)
    assert b.heldout_rms == pytest.approx(a.heldout_rms, rel=0.5)      # tracker components only
    from ppoe_core.analysis.plan.constraints import tags_visible
    vis = tags_visible(tree.link_poses(q), c, 40)
    px = both.G[:, plain.G.shape[1]:].reshape(40, len(model.tags.items), 10, -1)
    assert np.all((np.abs(px).sum(axis=(2, 3)) > 0) == vis)
