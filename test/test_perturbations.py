"""Learned PPOE perturbation covariances (``ppoe_core.analysis.diagnose.perturbations``) on a simulated 5-joint
arm whose true covariances differ per joint and per axis class (``test/perturbation_sim.py``): components within
their CIs of the truth, ellipsoid coverage at 68/95/99 % on held-out poses, the global scale missing coverage in
some direction where the learned covariances do not, and the CIs' coverage by Monte-Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from perturbation_sim import DECLARED, TRUTH, sigma_matrices, simulate_poses, soft5
from ppoe_core.analysis.diagnose.block_pose import PoseBlock
from ppoe_core.analysis.diagnose.covariance_check import compare_choices
from ppoe_core.analysis.diagnose.noise import estimate_scales
from ppoe_core.analysis.diagnose.perturbations import (
    axis_projectors,
    component_matrices,
    fit_components,
    joint_axes,
    learn_perturbations,
)
from ppoe_core.robot.tree import KinematicTree


@pytest.fixture(scope="module")
def learned():
    robot = soft5()
    tree = KinematicTree(robot)
    truth = sigma_matrices(robot, TRUTH)
    train = PoseBlock(tree, simulate_poses(robot, truth, 1000, seed=11))
    lin = train.linearise([], (), {}, {})
    axes = joint_axes(tree)
    fit = learn_perturbations(lin.r, lin.S, component_matrices(train, [], axes))
    return robot, tree, truth, axes, fit, train


def test_components_contain_the_truth(learned):
    robot, tree, truth, axes, fit, _ = learned
    assert fit.components, "nothing learned"
    names = {c.name: c for c in fit.components}
    # the two softened classes are found as components of their own
    assert "j2/lateral" in names and "j3/axial" in names, list(names)
    for c in fit.components:
        true = {TRUTH[j][cls] for j, cls in c.members}
        assert len(true) == 1, f"{c.name} merged joints whose true sigmas differ: {true}"
        lo, hi = c.ci
        assert lo <= next(iter(true)) ** 2 <= hi, (c.name, c.sigma, np.sqrt(c.ci), true)
    # the learned 6x6 of the softened joint has its large variance perpendicular to the axis
    S2 = fit.covariances(axes)["j2"]
    P = axis_projectors(robot.joints["j2"].axis)
    assert np.trace(P["lateral"] @ S2) / 2 == pytest.approx(5e-3 ** 2, rel=0.15)


def test_coverage_learned_vs_global_vs_user(learned):
    robot, tree, truth, axes, fit, train = learned
    test = PoseBlock(tree, simulate_poses(robot, truth, 5000, seed=12))
    declared = sigma_matrices(robot, DECLARED)
    lin_tr = train.linearise([], (), declared, {})
    g = estimate_scales(lin_tr.r, lin_tr.S, lin_tr.Q)  # the one global scale (and the sensor's), on the same rows
    lin_user = test.linearise([], (), declared, {})
    lin_learned = test.linearise([], (), fit.covariances(axes), {})
    choices = {"user": lin_user.S + lin_user.Q,
               "global": g.a ** 2 * lin_user.S + g.k ** 2 * lin_user.Q,
               "learned": fit.sensor_scale ** 2 * lin_learned.S + lin_learned.Q}
    checks = compare_choices(lin_user.r, choices)
    L = checks["learned"]
    # 1000 training poses estimate the sigmas to a few %: the 6-D ellipsoid's coverage within 3 % of nominal, along
    # each principal axis within 4 % (the true covariance itself is within 2.3 % on these 5000 rows;
    # bench/study_perturbations.py shows 2 % with more training poses)
    for lvl, cov in L.coverage.items():
        assert abs(cov - float(lvl)) <= 0.03, (lvl, cov)
    assert L.worst_coverage_error() <= 0.04, L.to_json()
    # one global scale fixes the mean NEES but not the shape: some principal direction misses its coverage
    assert checks["global"].worst_coverage_error() > 0.05, checks["global"].to_json()
    assert checks["user"].worst_coverage_error() > 0.05
    assert L.loglik > checks["global"].loglik > checks["user"].loglik


def test_fisher_intervals_cover_by_monte_carlo(learned):
    """The 95 % intervals of a fixed structure, refitted on rows drawn from the first-order model with known
    variances: the truth falls inside about 95 % of the time."""
    robot, tree, truth, axes, fit, train = learned
    parts = component_matrices(train, [], axes)
    groups = [[("j2", "lateral")], [("j3", "axial")],
              [(j, c) for j in ("j1", "j2", "j4", "j5") for c in ("axial",)] + [("j1", "lateral")]]
    D = [np.sum([parts[m] for m in g], axis=0) for g in groups]
    lam_true = np.array([1.0, 5e-3 ** 2, 3e-3 ** 2, 1e-3 ** 2])
    n = 200
    S, D = train.linearise([], (), {}, {}).S[:n], [x[:n] for x in D]
    L = np.linalg.cholesky(np.tensordot(lam_true, np.stack([S, *D]), axes=1))
    rng = np.random.default_rng(5)
    hits, total = 0, 0
    for _ in range(120):
        r = np.einsum("nij,nj->ni", L, rng.standard_normal((n, 6)))
        f = fit_components(r, S, D)
        sd = np.sqrt(np.diag(np.linalg.inv(f.fisher)))
        inside = np.abs(np.log(f.lam) - np.log(lam_true)) <= 1.96 * sd
        hits += int(inside.sum())
        total += inside.size
    assert 0.91 <= hits / total <= 0.985, hits / total
