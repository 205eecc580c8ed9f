"""Tests of the joint tracker + pixel fit (ppoe_core.analysis.diagnose.joint_fit / joint_cv): synthetic arm7
data made here (tracker reflector on tool0, tags on two links seen by the external camera, a camera error and
arm errors), robust loss, analytic Jacobian, seeded Monte-Carlo coverage, and the Motoman dataset."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG, DATASETS
from jacobian_check import check_jacobian

from ppoe_core import lie
from ppoe_core.analysis.diagnose import predict_pixels
from ppoe_core.analysis.diagnose.joint_cv import joint_heldout, joint_pose_ids
from ppoe_core.analysis.diagnose.joint_fit import JointProblem, joint_fit
from ppoe_core.analysis.diagnose.joint_synthetic import TAGS_SYN, arm7_joint_data, arm7_truth
from ppoe_core.model.effects import make_effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

SIGMA_T = 1e-4  # tracker noise [m] (arm7_joint_data default)


@pytest.fixture(scope="module")
def robot():
    return parse_urdf(CONFIG / "robots" / "arm7.urdf")


def _zero(effects):
    return [e.with_params(np.zeros(e.n_params)) for e in effects]


def _z(fit, truth):
    """(estimate - truth) / sigma of every parameter, effect by effect."""
    return np.concatenate([[(e["parameters"][k] - v) / e["sigma"][k] for k, v in zip(e["parameters"], t.params)]
                           for e, t in zip(fit.effects, truth)])


def test_two_tag_links_predicted_per_row(robot):
    """A PixelObs with tags on two links predicts each row on its own link (= the single-link obs of that link)."""
    tree = KinematicTree(robot)
    _, obs = arm7_joint_data(robot, (), n=5, seed=1)
    uv = predict_pixels(tree, obs)
    for ln in TAGS_SYN:
        m = obs.row_links() == ln
        one = obs.subset(m)
        one.links, one.link = None, ln
        np.testing.assert_allclose(uv[m], predict_pixels(tree, one), atol=1e-9)
    assert set(obs.tag_links()) == set(TAGS_SYN)


def test_joint_fit_separates_camera_from_arm(robot):
    """Truths inside the joint 95 % CIs (10 parameters); the staged pixel fit (cameras only) blames the camera."""
    from ppoe_core.analysis.diagnose import diagnose_pixels, pixel_candidates

    tree = KinematicTree(robot)
    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth)
    assert len(set(obs.row_links().tolist())) == 2 and len(obs) > 200
    pose_t, _ = joint_pose_ids(stops, obs)
    fit = joint_fit(tree, _zero(truth), stops, obs, pose_t=pose_t)
    for e, t in zip(fit.effects, truth):  # every truth inside its 95 % CI (this seed: |z| <= 1.51)
        assert all(e["ci"][k][0] <= v <= e["ci"][k][1] for k, v in zip(e["parameters"], t.params)), e
    assert fit.pixel_rms["camera_optical_frame"] < 0.8  # noise: 0.71 px (2D RMS of N(0, 0.5) per axis)
    assert fit.tracker_rms < 2.2 * SIGMA_T  # noise: sqrt(3) sigma
    # staged: the pixel stage with its default candidates (cameras) absorbs the arm errors into the camera
    staged = diagnose_pixels(robot, obs, candidates=pixel_candidates(robot, obs))
    cam = staged.effects[0]
    assert (cam["name"], cam["location"]) == ("camera_extrinsics", "camera_joint")
    z_staged = [(cam["parameters"][k] - v) / cam["sigma"][k] for k, v in zip(cam["parameters"], truth[0].params)]
    assert np.max(np.abs(z_staged)) > 4.0, z_staged  # truth far outside the staged 95 % CI (measured 6.7)
    # and its camera error is larger than the joint fit's by far
    err_joint = np.abs(fit.fitted[0].params - truth[0].params)
    err_staged = np.abs(np.array(list(cam["parameters"].values())) - truth[0].params)
    assert err_staged.max() > 5.0 * err_joint.max()


def test_robust_loss_ignores_gross_pixel_outliers(robot):
    """Six pixels moved by 60-120 px: every estimate stays within its CI half-width of the clean one; without
    the robust loss at least one leaves it (so the test can fail)."""
    tree = KinematicTree(robot)
    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth, seed=2)
    pose_t, _ = joint_pose_ids(stops, obs)
    clean = joint_fit(tree, _zero(truth), stops, obs, pose_t=pose_t)
    bad = obs.subset(np.arange(len(obs)))
    rows = np.random.default_rng(7).choice(len(obs), 6, replace=False)
    bad.uv[rows] += np.random.default_rng(8).uniform(60.0, 120.0, (6, 2)) * np.array([1.0, -1.0])
    theta = np.concatenate([e.params for e in clean.fitted])
    half = 1.96 * np.sqrt(np.diag(clean.cov)[:theta.size])
    robust = joint_fit(tree, _zero(truth), stops, bad, pose_t=pose_t)
    assert np.all(np.abs(np.concatenate([e.params for e in robust.fitted]) - theta) < half)
    plain = joint_fit(tree, _zero(truth), stops, bad, pose_t=pose_t, loss="linear", rescale=False)
    assert np.any(np.abs(np.concatenate([e.params for e in plain.fitted]) - theta) > half)


def test_joint_jacobian_matches_finite_differences(robot):
    """Analytic Jacobian of the whitened joint residual (effects, registration) vs central differences, at
    non-zero effect parameters and registration perturbation."""
    tree = KinematicTree(robot)
    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth, n=6, seed=3)
    effs = _zero(truth) + [make_effect("link_error", "joint_6", robot), make_effect("joint_offset", "joint_7", robot)]
    prob = JointProblem(tree, effs, stops, obs)
    x = prob.x0() + np.random.default_rng(4).normal(0.0, 0.01, prob.x0().size)
    J = prob.jacobian(x)
    fd = check_jacobian(prob.residuals, x, J, eps=1e-6, atol=1e-3, rtol=1e-5)
    assert J.shape == (3 * len(stops) + 2 * len(obs), prob.P + 6)
    assert np.abs(fd[:3 * len(stops), prob.P:]).min(axis=0).max() > 0.0  # registration columns act


def test_joint_ci_coverage_monte_carlo(robot):
    """Seeded Monte-Carlo: 30 data sets x 10 parameters, 95 % CIs (pose-clustered sandwich, robust weights; one
    solve with the declared noise, which is right here: the noise re-estimation and pre-fits only set weights)."""
    tree = KinematicTree(robot)
    truth = arm7_truth(robot)
    hits = []
    for s in range(30):
        stops, obs = arm7_joint_data(robot, truth, n=25, seed=100 + s)
        pose_t, _ = joint_pose_ids(stops, obs)
        fit = joint_fit(tree, _zero(truth), stops, obs, pose_t=pose_t, presolve=False, rescale=0)
        hits.append(np.abs(_z(fit, truth)) < 1.96)
    cover = float(np.mean(hits))
    print(f"joint CI coverage {cover:.3f}")
    # 300 intervals (correlated within a data set): 0.95 expected; clustered sandwich with 30 clusters runs low
    assert 0.85 <= cover <= 0.99, cover


def test_heldout_folds_keep_poses_together(robot):
    """Held-out scoring: every row scored once, the pixel error at the noise with the true effect set and well
    above it with the camera alone (the arm errors are not in that set)."""
    tree = KinematicTree(robot)
    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth, n=30, seed=5)
    full = joint_heldout(tree, _zero(truth), stops, obs, folds=3)
    assert np.all(np.isfinite(full["pixel_error"])) and np.all(np.isfinite(full["tracker_error"]))
    assert full["pixel_rms"]["camera_optical_frame"] < 0.9 and full["tracker_rms"] < 2.5 * SIGMA_T
    cam_only = joint_heldout(tree, _zero(truth[:1]), None, obs, folds=3)
    assert cam_only["pixel_rms"]["camera_optical_frame"] > 1.2 * full["pixel_rms"]["camera_optical_frame"]
    assert full["protocol"] == "cross-validated over poses"


@pytest.mark.skipif(not (DATASETS / "motoman_leica").exists(), reason="Motoman dataset not present")
def test_motoman_joint_fit_beats_cameras_only():
    """Right arm, 6x6x6: tracker + both cameras' marker pixels, effects = link_error@U1_dh + cameras; held-out
    pixel RMS per camera below the cameras-only fit under the same protocol (measured here)."""
    from ppoe_core.analysis.diagnose import pixel_candidates
    from ppoe_core.cli.datasets import pixels_from_motoman, stops_from_motoman

    d = DATASETS / "motoman_leica"
    robot = parse_urdf(d / "motoman_right.urdf")
    tree = KinematicTree(robot)
    stops = stops_from_motoman(d / "leica_right_hand_6x6x6_dataset.mat", robot)
    obs = pixels_from_motoman(d / "leica_right_hand_6x6x6_dataset.mat", robot, d / "model.yaml")
    cams = [e for e in pixel_candidates(robot, obs) if e.name == "camera_extrinsics"]
    # 3 folds and no noise re-estimation round (the per-sensor pre-fits set the weights) keep it short
    cam_only = joint_heldout(tree, cams, None, obs, folds=3, rescale=0)
    joint = joint_heldout(tree, [make_effect("link_error", "U1_dh", tree), *cams], stops, obs, folds=3, rescale=0)
    print(cam_only["pixel_rms"], joint["pixel_rms"], joint["tracker_rms"])
    for f, v in cam_only["pixel_rms"].items():
        assert joint["pixel_rms"][f] < v, (joint["pixel_rms"], cam_only["pixel_rms"])
    assert joint["tracker_rms"] < 0.2e-3


def test_gtsam_tangent_conversion():
    """Ours [rho; theta] <-> GTSAM Pose3 [omega; v]: the same right perturbation, Jacobian columns swapped."""
    gtsam = pytest.importorskip("gtsam")
    from ppoe_core.analysis.diagnose.joint_gtsam import from_gtsam_tangent, to_gtsam_tangent

    rng = np.random.default_rng(9)
    T = lie.exp(rng.normal(0.0, 0.5, 6))
    xi = rng.normal(0.0, 0.3, 6)  # ours: [rho; theta]
    got = gtsam.Pose3(T).compose(gtsam.Pose3.Expmap(to_gtsam_tangent(xi))).matrix()
    np.testing.assert_allclose(got, T @ lie.exp(xi), atol=1e-12)
    np.testing.assert_allclose(from_gtsam_tangent(gtsam.Pose3.Logmap(gtsam.Pose3(lie.exp(xi)))), xi, atol=1e-12)
    assert not np.allclose(to_gtsam_tangent(xi), xi)


def test_gtsam_and_scipy_agree(robot):
    """The factor graph (LM, Marginals) and scipy least_squares reach the same solution and marginal sigmas."""
    pytest.importorskip("gtsam")
    from scipy.optimize import least_squares

    from ppoe_core.analysis.diagnose.joint_gtsam import solve_gtsam

    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth, n=15, seed=11)
    prob = JointProblem(KinematicTree(robot), _zero(truth), stops, obs)
    sol = least_squares(prob.residuals, prob.x0(), jac=prob.jacobian, method="trf", x_scale=1.0, xtol=1e-12,
                        ftol=1e-12, gtol=1e-12)
    g = solve_gtsam(prob)
    J = prob.jacobian(sol.x)
    sig = np.sqrt(np.diag(np.linalg.pinv(J.T @ J))[:prob.P])
    assert g["cost"] == pytest.approx(sol.cost, rel=1e-6)
    np.testing.assert_allclose(g["x"][:prob.P], sol.x[:prob.P], atol=1e-3 * sig.min())
    np.testing.assert_allclose(np.sqrt(np.diag(g["cov_theta"])), sig, rtol=1e-4)


def test_concat_pixel_obs_of_two_tag_links(robot):
    """concat_pixel_obs of single-link observations on different links gives a per-row link array (it raised
    before) and predicts every row as its source did."""
    from ppoe_core.analysis.diagnose import concat_pixel_obs

    tree = KinematicTree(robot)
    _, obs = arm7_joint_data(robot, (), n=4, seed=12)
    parts = []
    for ln in TAGS_SYN:
        part = obs.subset(obs.row_links() == ln)
        part.links, part.link = None, ln
        parts.append(part)
    both = concat_pixel_obs(parts)
    assert list(both.row_links()) == [p.link for p in parts for _ in range(len(p))]
    np.testing.assert_allclose(predict_pixels(tree, both), np.concatenate([predict_pixels(tree, p) for p in parts]),
                               atol=1e-9)
    single = concat_pixel_obs(parts[:1])
    assert single.links is None and single.link == parts[0].link
