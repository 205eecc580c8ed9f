"""Accelerometer tilts and contacts as residual blocks of the diagnosis (ppoe_core.analysis.diagnose.block_imu,
block_contact): Jacobians against finite differences, the prior covariance against Monte Carlo, a tilted base and
a bending mount found from the accelerometers, a contact-only diagnosis.  Synthetic data made here."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG
from jacobian_check import check_jacobian, numerical_jacobian
from test_diagnose import _synthetic

from ppoe_core import lie
from ppoe_core.analysis.diagnose import ContactBlock, Contacts, ImuBlock, Measurements, Stops, diagnose
from ppoe_core.model.effects import make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf


@pytest.fixture(scope="module")
def robot():
    return parse_urdf(CONFIG / "robots" / "arm7.urdf")


def _tilted(robot, tilts, bending=None, n=80, seed=30):
    """One group (placement) per entry of ``tilts`` (tilt_x, tilt_y) [rad] of the base, forearm IMU, optional
    mount bending; the tracker sees the same chain."""
    tree = KinematicTree(robot)
    parts = []
    for g, tilt in enumerate(tilts):
        effs = [make_effect("base_tilt", tree.root, tree, list(tilt))] if tilt is not None else []
        if bending is not None:
            effs.append(make_effect("mount_bending", "mount_joint", tree, list(bending)))
        s = _synthetic(robot, effs, n=n, seed=seed + g)
        s.group_names = [f"placement{g}"]
        s.session_names = [f"placement{g}:{k}" for k in range(len(s.session_names))]
        parts.append(s)
    return Stops.concat(parts)


def _named(res):
    return [(e["name"], e["location"]) for e in res.to_json()["effects"]]


def test_imu_columns_match_finite_differences(robot):
    """d tilt / d effect parameters (chain through the frame Jacobian's rotation rows) and d tilt / d nuisance
    (placement tilt of the second session, mounting of the second accelerometer) against central differences."""
    tree = KinematicTree(robot)
    stops = _tilted(robot, [None, None], n=6)
    acc = stops.imus["forearm"][1]
    stops.imus = {"forearm": ("arm_link_4", acc), "hand": ("arm_link_6", acc * 1.0)}
    block = ImuBlock(tree, stops)
    block.nu = np.random.default_rng(2).normal(0, 0.01, block.nu.shape)
    effs = [make_effect("base_tilt", tree.root, tree, [0.01, -0.02]),
            make_effect("mount_bending", "mount_joint", tree, [3e-4, 2e-4]),
            make_effect("joint_offset", "joint_2", tree, [0.02])]
    lin = block.linearise(effs, effs, {}, {})
    for k, e in enumerate(effs):
        def predict(th, k=k):
            cur = list(effs)
            cur[k] = effs[k].with_params(th)
            return -block.linearise(cur, (), {}, {}).r
        check_jacobian(predict, e.params, lin.J[k], atol=1e-7, rtol=1e-5, eps=1e-7, err_msg=e.name)
    nu0 = block.nu.copy()

    def predict_nu(step):
        block.nu = nu0.copy()
        block.apply_nuisance(step.reshape(nu0.shape))
        return -block.linearise(effs, (), {}, {}).r

    num = numerical_jacobian(predict_nu, np.zeros(nu0.size))
    for g in range(block.n_segments):  # one placement per session
        rows = block.segment == g
        cols = slice(4 * g, 4 * g + 4)
        want = num[rows][:, :, cols].copy()
        if g == 0:  # the first placement's tilt is the base_tilt effect, not a nuisance: its columns are zero
            want[:, :, :2] = 0.0
        np.testing.assert_allclose(lin.N[rows], want, atol=1e-6, rtol=1e-5)
    block.nu = nu0


def test_imu_prior_covariance_matches_monte_carlo(robot):
    """Tilt residuals of an accelerometer on arm_link_4 under a declared perturbation of joint_2 and joint noise,
    against the block's first-order Q (seeded Monte Carlo)."""
    tree = KinematicTree(robot)
    stops = _tilted(robot, [None], n=3, seed=40)
    pert = {"joint_2": np.diag([1e-6, 1e-6, 1e-6, 4e-6, 1e-6, 9e-6])}
    jn = {"joint_3": 2e-3}
    Q = ImuBlock(tree, stops).linearise([], [], pert, jn).Q
    rng = np.random.default_rng(41)
    M = 3000
    samples = np.empty((M, len(stops), 2))
    for m in range(M):
        dxi = {"joint_2": rng.multivariate_normal(np.zeros(6), pert["joint_2"], len(stops))}
        dq = {"joint_3": rng.normal(0.0, jn["joint_3"], len(stops))}
        R = tree.link_poses(stops.q, dq, dxi)["arm_link_4"][:, :3, :3]
        s = Stops.concat([stops])
        s.imus = {"forearm": ("arm_link_4", 9.81 * R[:, 2, :])}
        samples[m] = ImuBlock(tree, s).linearise([], [], {}, {}).r
    emp = np.einsum("mni,mnj->nij", samples, samples) / M
    np.testing.assert_allclose(emp, Q, rtol=0.1, atol=0.05 * np.abs(Q).max())


def test_a_tilted_base_and_a_bending_mount_are_named_from_the_accelerometer(robot):
    """One placement tilted by (1.5, -0.8) mrad with a bending mount: base_tilt (which only the accelerometer sees:
    the tracker's registration takes any rigid rotation) and mount_bending, truths in their CIs; a second placement
    tilted otherwise is a nuisance of the accelerometer block (its tilt relative to the first)."""
    tilts = [(1.5e-3, -0.8e-3), (-0.5e-3, 1.0e-3)]
    bending = (3e-5, 2e-5)
    res = diagnose(robot, _tilted(robot, tilts, bending), options=_opts())
    assert sorted(_named(res)) == [("base_tilt", robot.root), ("mount_bending", "mount_joint")], res.summary
    e = {x["name"]: x for x in res.to_json()["effects"]}
    for k, v in zip(("tilt_x", "tilt_y"), tilts[0]):
        assert e["base_tilt"]["ci"][k][0] <= v <= e["base_tilt"]["ci"][k][1], e["base_tilt"]
    for k, v in zip(("compliance_x", "compliance_y"), bending):
        assert e["mount_bending"]["ci"][k][0] <= v <= e["mount_bending"]["ci"][k][1], e["mount_bending"]
    assert res.blocks["imu"].rms_after < 6e-5 < res.blocks["imu"].rms_before


def _opts():
    from ppoe_core.analysis.diagnose import DiagnoseOptions

    return DiagnoseOptions(cv="stops")


def test_imu_without_tilt_finds_nothing(robot):
    res = diagnose(robot, _tilted(robot, [None, None]), options=_opts())
    assert res.effects == [] and not res.unexplained_significant, res.summary


def test_imu_rows_in_motion_are_left_out(robot):
    """An accelerometer in motion measures the motion's acceleration too: rows where a joint moves are not fitted
    (counted as dropped)."""
    stops = _tilted(robot, [None], n=40)
    stops.context["joint_velocity"] = {j: np.where(np.arange(40) < 10, 0.5, 0.0) for j in stops.q}
    block = ImuBlock(KinematicTree(robot), stops)
    assert len(block) == 30 and block.dropped == 10


def _contacts(robot, true_effects, n=60, seed=50, height=0.3):
    """Contacts of a point 2 cm out of tool0 with a table ``height`` above the root: random poses, joint_2 solved
    (Newton) so that the TRUE point touches; the contact residual of a model without the effects is their
    normal displacement."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(robot)
    names = tree.joint_names
    q = {j: rng.uniform(-0.8, 0.8, n) for j in names if robot.joints[j].type != "prismatic"}
    q.update({j: np.full(n, 0.01) for j in names if j not in q})
    q["joint_2"] = np.full(n, 0.6)
    point = np.array([0.0, 0.0, 0.02, 1.0])

    def z_true(qq):
        dq, dxi = sum_effect_corrections(list(true_effects), qq, {})
        return (tree.link_poses(qq, dq, dxi)["tool0"] @ point)[:, 2]

    for _ in range(30):
        z = z_true(q) - height
        h = 1e-6
        dz = (z_true({**q, "joint_2": q["joint_2"] + h}) - height - z) / h
        q["joint_2"] = q["joint_2"] - z / np.where(np.abs(dz) > 1e-6, dz, 1e-6)
    keep = np.abs(z_true(q) - height) < 1e-9
    # encoders read the touching configuration with 1e-5 rad noise (a contact of noise-free data would make the
    # CI a rounding error wide)
    rec = {j: v[keep] + (rng.normal(0.0, 1e-5, int(keep.sum())) if j in q and robot.joints[j].type != "prismatic"
                         else 0.0) for j, v in q.items()}
    return Contacts(q=rec, link="tool0", point=point[:3], plane_frame=robot.root,
                    T_frame_plane=lie.from_xyz_rpy([0.0, 0.0, height], [0.0, 0.0, 0.0]), sigma=2e-5,
                    group=np.zeros(int(keep.sum()), dtype=int), group_names=["contacts"])


def test_contact_columns_match_finite_differences(robot):
    tree = KinematicTree(robot)
    block = ContactBlock(tree, _contacts(robot, [], n=5))
    effs = [make_effect("joint_offset", "joint_2", tree, [0.01]), make_effect("link_error", "joint_6", tree,
                                                                              [0.01, -0.01, 0.02, 0.01, 0.0, -0.02])]
    lin = block.linearise(effs, effs, {}, {})
    for k, e in enumerate(effs):
        def predict(th, k=k):
            cur = list(effs)
            cur[k] = effs[k].with_params(th)
            return -block.linearise(cur, (), {}, {}).r
        check_jacobian(predict, e.params, lin.J[k], atol=1e-8, rtol=1e-6, err_msg=e.name)


def test_contacts_alone_name_a_joint_offset(robot):
    """The contact block is a measurement of its own: touches of a known table, nothing else measured, name an
    encoder offset of joint_4 with the truth in its CI; a model without error finds nothing."""
    truth = make_effect("joint_offset", "joint_4", robot, [0.004])
    contacts = _contacts(robot, [truth])
    assert len(contacts) > 40
    res = diagnose(robot, Measurements(contacts=contacts))
    assert _named(res) == [("joint_offset", "joint_4")], res.summary
    ci = res.to_json()["effects"][0]["ci"]["offset"]
    assert ci[0] <= 0.004 <= ci[1]
    assert diagnose(robot, Measurements(contacts=_contacts(robot, [], seed=51))).effects == []


def test_concatenated_stops_name_their_joints_in_sorted_order(robot):
    """``Stops.concat`` once built its joint and motion-context dicts in the iteration order of a set of joint names
    (the strings' hashes, another order in every process): the Motoman diagnosis then differed from run to run in
    the last digits (the sums over joints in that order), up to the order of rejected candidates."""
    s = _tilted(robot, [None, None], n=4, seed=50)
    assert len(s.q) > 3
    assert list(s.q) == sorted(s.q)
    for key in ("motion_sign", "joint_velocity"):
        if key in s.context:
            assert list(s.context[key]) == sorted(s.context[key])
