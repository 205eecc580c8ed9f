"""Covariance of the PPOE model against seeded Monte-Carlo (paper eq. 9).

MC covariance = mean of ``Log(Tbar^-1 T) Log(Tbar^-1 T)^T`` over samples ``T`` of the model.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA

from ppoe_core import PPOEModel, lie, load_model_config, parse_urdf

EDGE = DATA / "ppoe_edge.urdf"
PLANAR = DATA / "planar3.urdf"
N_MC = 200_000


def _mc_cov(T_mean, samples):
    xi = lie.log(lie.inverse(T_mean) @ samples)
    return xi.T @ xi / len(xi)


def _rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def _uniform_model(path, sigma_rho, sigma_theta, joints=None):
    robot = parse_urdf(path)
    joints = joints if joints is not None else list(robot.joints)
    pert = {j: {"sigma": [sigma_rho] * 3 + [sigma_theta] * 3} for j in joints}
    return PPOEModel(robot, load_model_config({"perturbations": pert}, robot))


def _naive_samples(model, q, frm, to, n, rng):
    """Independent sampler: eq. 16 written out, up-branch links inverted (Exp(-xi))."""
    robot, cfg = model.robot, model.config
    qd = dict(zip(model.joint_names, q))
    up, down = robot.chain(frm, to)

    def link(jn):
        j = robot.joints[jn]
        T = np.broadcast_to(j.origin, (n, 4, 4))
        if jn in cfg.perturbations:
            C = cfg.perturbations[jn].covariance
            xi = rng.multivariate_normal(np.zeros(6), C, size=n, method="eigh")
            T = T @ lie.exp(xi)
        if j.movable:
            v = qd[jn] if j.mimic_root is None else j.mimic_root[1] * qd[j.mimic_root[0]] + j.mimic_root[2]
            T = T @ lie.exp(j.twist * v)
        return T

    out = np.broadcast_to(np.eye(4), (n, 4, 4))
    for jn in up:
        out = out @ lie.inverse(link(jn))
    for jn in down:
        out = out @ link(jn)
    return out


@pytest.mark.parametrize(
    "frm, to, q",
    [("base_link", "tool0", [0.3, -0.7, 0.12, 1.1]),
     ("finger", "camera_optical_frame", [0.5, 1.2, 0.05, 0.8])],
)
def test_second_order_within_5_percent_at_small_sigmas(frm, to, q):
    """1 mm / 1 deg on all six components of every joint (fixed joints included)."""
    model = _uniform_model(EDGE, 0.001, np.deg2rad(1.0))
    q = np.array(q)
    T, cov2 = model.fk(q, frm, to, order=2)
    S = model.sample(q, frm, to, n=100_000, rng=np.random.default_rng(10))
    cov_mc = _mc_cov(T, S)
    assert _rel(cov2, cov_mc) < 0.05
    _, cov4 = model.fk(q, frm, to, order=4)
    assert _rel(cov4, cov_mc) < 0.05


def test_sampler_matches_independent_sampler():
    """model.sample draws the same distribution as eq. 16-17 written out by hand."""
    model = _uniform_model(EDGE, 0.002, np.deg2rad(3.0))
    q = np.array([0.4, -0.3, 0.1, 0.7])
    frm, to = "camera_optical_frame", "finger"
    T = model.fk_mean(q, frm, to)
    c_model = _mc_cov(T, model.sample(q, frm, to, n=60_000, rng=np.random.default_rng(11)))
    c_naive = _mc_cov(T, _naive_samples(model, q, frm, to, 60_000, np.random.default_rng(12)))
    assert _rel(c_model, c_naive) < 0.03
    # and the mean of the samples' twists is ~0 (zero-mean perturbations, small sigmas)
    xi = lie.log(lie.inverse(T) @ model.sample(q, frm, to, n=20_000, rng=np.random.default_rng(13)))
    assert np.all(np.abs(xi.mean(axis=0)) < 4 * np.sqrt(np.diag(c_model) / 20_000) + 1e-4)


@pytest.mark.parametrize("q", [[0.0, 0.0, 0.0], [0.6, 1.4, -0.9]])
def test_fourth_order_closer_than_second_at_10_degrees_planar(q):
    """Fig. 3 set-up: 10 deg rotational sigmas on all three joint axes (z).

    (In strongly bent configurations the two orders differ by less than the MC noise of
    200k samples, so those would not test anything.)
    """
    robot = parse_urdf(PLANAR)
    s = np.deg2rad(10.0)
    pert = {j: {"sigma": [0, 0, 0, 0, 0, s]} for j in ("joint1", "joint2", "joint3")}
    model = PPOEModel(robot, load_model_config({"perturbations": pert}, robot))
    q = np.array(q)
    T, cov2 = model.fk(q, "base_link", "tool0", order=2)
    _, cov4 = model.fk(q, "base_link", "tool0", order=4)
    cov_mc = _mc_cov(T, model.sample(q, "base_link", "tool0", n=N_MC, rng=np.random.default_rng(20)))
    assert _rel(cov4, cov_mc) < _rel(cov2, cov_mc)


@pytest.mark.parametrize("frm, to", [("base_link", "tool0"), ("camera_optical_frame", "tool0")])
def test_fourth_order_closer_than_second_at_10_degrees_3d(frm, to):
    """All three rotation axes perturbed by 10 deg at every joint of the 3-D test robot."""
    model = _uniform_model(EDGE, 0.0, np.deg2rad(10.0), joints=["j1", "j2", "j3", "j4"])
    q = np.array([0.3, -0.7, 0.12, 1.1])
    T, cov2 = model.fk(q, frm, to, order=2)
    _, cov4 = model.fk(q, frm, to, order=4)
    cov_mc = _mc_cov(T, model.sample(q, frm, to, n=N_MC, rng=np.random.default_rng(21)))
    e2, e4 = _rel(cov2, cov_mc), _rel(cov4, cov_mc)
    assert e4 < e2, (e2, e4)
