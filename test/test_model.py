"""PPOEModel against an independent, literal implementation of eq. 15-18 (no shortcuts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import DATA
from jacobian_check import SE3_MINUS, check_jacobian

from ppoe_core import PPOEModel, lie, load_model_config, parse_urdf
from ppoe_core.errors import JointValueError, ModelConfigError, UnknownFrameError, UnknownJointError
from ppoe_core.model.fourth_order import compound_fourth_order

EDGE = DATA / "ppoe_edge.urdf"
EDGE_YAML = DATA / "ppoe_edge_model.yaml"
PLANAR = DATA / "planar3.urdf"


@pytest.fixture(scope="module")
def edge():
    return PPOEModel.from_files(EDGE, EDGE_YAML)


# ----------------------------------------------------------------------------
# Literal reference: the chain as a list of 4x4 factors and perturbation covariances
# ----------------------------------------------------------------------------


def _qval(robot, qd, jn, dq):
    j = robot.joints[jn]
    if j.mimic_root is not None:
        m, mult, off = j.mimic_root
        v = mult * qd[m] + off
    else:
        v = qd[jn]
    return v + dq.get(jn, 0.0)


def _link_items(robot, config, qd, jn, dq, dxi):
    """eq. 16: Exp(p) Exp(dxi) Exp(xi) Exp(zeta q) Exp(zeta n) as [('M', T) | ('P', Sigma)]."""
    j = robot.joints[jn]
    items = [("M", j.origin)]
    if jn in dxi:
        items.append(("M", lie.exp(dxi[jn])))
    if jn in config.perturbations:
        items.append(("P", config.perturbations[jn].covariance, "xi:" + jn, 1.0))
    if j.movable:
        items.append(("M", lie.exp(j.twist * _qval(robot, qd, jn, dq))))
        s = config.joint_noise.get(jn, 0.0)
        if s > 0:
            items.append(("P", s**2 * np.outer(j.twist, j.twist), "noise:" + jn, 1.0))
    return items


def reference_chain(model, qd, frm, to, dq=None, dxi=None):
    """Items of T_frm_to: up-branch links inverted (Exp(-xi) has the same covariance)."""
    dq, dxi = dq or {}, dxi or {}
    robot, config = model.robot, model.config
    up, down = robot.chain(frm, to)
    items = []
    for jn in up:
        for item in reversed(_link_items(robot, config, qd, jn, dq, dxi)):
            # inverted link: (X Exp(xi))^-1 = Exp(-xi) X^-1
            items.append(("M", lie.inverse(item[1])) if item[0] == "M" else ("P", item[1], item[2], -1.0))
    for jn in down:
        items.extend(_link_items(robot, config, qd, jn, dq, dxi))
    return items


def reference_fk(items):
    """Mean and second-order covariance, eq. 15/18, with explicit adjoints of B_k^-1."""
    T = np.eye(4)
    for item in items:
        if item[0] == "M":
            T = T @ item[1]
    cov = np.zeros((6, 6))
    for J, S in reference_transport(items).values():
        cov += J @ S @ J.T
    return T, cov


def reference_transport(items):
    """source -> (J, Sigma): the target's local twist is ``sum_s J_s xi_s`` (first order)."""
    out = {}
    for k, item in enumerate(items):
        if item[0] != "P":
            continue
        B = np.eye(4)
        for item2 in items[k + 1:]:
            if item2[0] == "M":
                B = B @ item2[1]
        out[item[2]] = (item[3] * lie.adjoint(lie.inverse(B)), item[1])
    return out


def _random_q(model, rng, shape=()):
    return rng.uniform(-1.2, 1.2, size=shape + (len(model.joint_names),))


# ----------------------------------------------------------------------------
# Mean pose
# ----------------------------------------------------------------------------


def test_joint_names_are_independent_movable_in_urdf_order(edge):
    assert edge.joint_names == ["j1", "j2", "j3", "j4"]


def test_mean_between_all_link_pairs(edge):
    rng = np.random.default_rng(1)
    q = _random_q(edge, rng)
    qd = dict(zip(edge.joint_names, q))
    links = list(edge.robot.links)
    for frm in links:
        for to in links:
            T_ref, _ = reference_fk(reference_chain(edge, qd, frm, to))
            np.testing.assert_allclose(edge.fk_mean(q, frm, to), T_ref, atol=1e-12, err_msg=f"{frm}->{to}")


def test_inverted_chain_camera_to_tool(edge):
    q = np.array([0.3, -0.7, 0.12, 1.1])
    T_ct, cov_ct = edge.fk(q, "camera_optical_frame", "tool0")
    T_tc, cov_tc = edge.fk(q, "tool0", "camera_optical_frame")
    np.testing.assert_allclose(T_ct, lie.inverse(T_tc), atol=1e-13)
    T_bc = edge.fk_mean(q, "base_link", "camera_optical_frame")
    T_bt = edge.fk_mean(q, "base_link", "tool0")
    np.testing.assert_allclose(T_ct, lie.inverse(T_bc) @ T_bt, atol=1e-13)
    # second order is linear transport: inverse pose covariance = Ad_T cov Ad_T^T
    Ad = lie.adjoint(T_tc)
    np.testing.assert_allclose(cov_ct, Ad @ cov_tc @ Ad.T, atol=1e-15)
    assert np.trace(cov_ct) > 0


def test_same_frame_is_identity(edge):
    T, cov = edge.fk(np.zeros(4), "link3", "link3")
    np.testing.assert_array_equal(T, np.eye(4))
    np.testing.assert_array_equal(cov, np.zeros((6, 6)))


def test_mimic_joint_follows_master(edge):
    q = np.array([0.0, 0.0, 0.0, 0.8])
    T = edge.fk_mean(q, "link4", "finger")
    expected = edge.robot.joints["finger_joint"].origin @ lie.exp(np.array([0, 0, 0, 0, 1.0, 0]) * (-0.5 * 0.8 + 0.1))
    np.testing.assert_allclose(T, expected, atol=1e-14)
    # a value given for the mimic joint itself is ignored: the master rules
    qd = {"j1": 0.0, "j2": 0.0, "j3": 0.0, "j4": 0.8, "finger_joint": 5.0, "not_in_urdf": 1.0}
    np.testing.assert_allclose(edge.fk_mean(qd, "link4", "finger"), expected, atol=1e-14)


# ----------------------------------------------------------------------------
# Covariance (second order) against the literal reference
# ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "frm, to",
    [("base_link", "tool0"), ("camera_optical_frame", "tool0"), ("finger", "camera_optical_frame"),
     ("tool0", "base_link"), ("link2", "finger")],
)
def test_covariance_matches_eq15_reference(edge, frm, to):
    rng = np.random.default_rng(2)
    for _ in range(3):
        q = _random_q(edge, rng)
        T_ref, cov_ref = reference_fk(reference_chain(edge, dict(zip(edge.joint_names, q)), frm, to))
        T, cov = edge.fk(q, frm, to)
        np.testing.assert_allclose(T, T_ref, atol=1e-12)
        np.testing.assert_allclose(cov, cov_ref, rtol=1e-9, atol=1e-18)
        # batched path (N > 1) gives the same
        Tb, covb = edge.fk(np.stack([q, q]), frm, to)
        np.testing.assert_allclose(covb[1], cov_ref, rtol=1e-9, atol=1e-18)


def test_fig3a_first_joint_only_gives_rank1_position_covariance():
    model = PPOEModel.from_files(PLANAR, None)
    model = PPOEModel(model.robot, load_model_config(
        {"perturbations": {"joint1": {"sigma": [0, 0, 0, 0, 0, np.deg2rad(10)]}}}, model.robot))
    for q in ([0.0, 0.0, 0.0], [0.4, 0.9, -0.6], [1.0, -1.5, 0.7]):
        T, cov = model.fk(np.array(q), "base_link", "tool0")
        cov_pos = lie.cov_local_to_ros(T, cov)[:3, :3]  # position covariance in base axes
        ev, V = np.linalg.eigh(cov_pos)
        assert ev[-1] > 1e-3
        assert abs(ev[0]) < 1e-12 * ev[-1] and abs(ev[1]) < 1e-12 * ev[-1]
        # the one direction is the arc tangent at the tool: e_z x p_tool
        d = np.cross([0, 0, 1], T[:3, 3])
        assert abs(abs(V[:, -1] @ d) / np.linalg.norm(d) - 1) < 1e-10
        # and the tool rotation varies only about z
        cov_rot = cov[3:, 3:]
        np.testing.assert_allclose(cov_rot[2, 2], np.deg2rad(10) ** 2)
        assert np.linalg.matrix_rank(cov, tol=1e-12) == 1


def test_no_perturbations_zero_covariance():
    model = PPOEModel.from_files(EDGE)
    T, cov = model.fk(np.array([0.1, 0.2, 0.0, -0.3]), "base_link", "tool0")
    np.testing.assert_array_equal(cov, np.zeros((6, 6)))
    _, covb = model.fk(np.zeros((3, 4)), "base_link", "tool0", order=4)
    np.testing.assert_array_equal(covb, np.zeros((3, 6, 6)))


def test_joint_noise_equals_axis_perturbation():
    """xi = zeta (paper IV-D): noise along the axis after the motion == axis perturbation before it."""
    robot = parse_urdf(EDGE)
    a4 = robot.joints["j4"].axis
    m_noise = PPOEModel(robot, load_model_config({"joint_noise": {"j4": 0.01, "j3": 0.002}}, robot))
    m_pert = PPOEModel(robot, load_model_config({"perturbations": {
        "j4": {"covariance": (1e-4 * np.outer(np.r_[0, 0, 0, a4], np.r_[0, 0, 0, a4])).tolist()},
        "j3": {"sigma": [0, 0.002, 0, 0, 0, 0]},
    }}, robot))
    q = np.array([0.2, -0.4, 0.1, 0.9])
    for frm, to in (("base_link", "tool0"), ("tool0", "camera_optical_frame")):
        _, c1 = m_noise.fk(q, frm, to)
        _, c2 = m_pert.fk(q, frm, to)
        np.testing.assert_allclose(c1, c2, rtol=1e-9, atol=1e-20)


# ----------------------------------------------------------------------------
# Batching
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("order", [2, 4])
def test_batched_equals_looped_single(edge, order):
    rng = np.random.default_rng(3)
    Q = _random_q(edge, rng, (2, 3))
    T, cov = edge.fk(Q, "camera_optical_frame", "tool0", order=order)
    assert T.shape == (2, 3, 4, 4) and cov.shape == (2, 3, 6, 6)
    for i in range(2):
        for k in range(3):
            Ti, ci = edge.fk(Q[i, k], "camera_optical_frame", "tool0", order=order)
            np.testing.assert_allclose(T[i, k], Ti, atol=1e-13)
            np.testing.assert_allclose(ci, cov[i, k], rtol=1e-9, atol=1e-20)


def test_batched_over_chunks_and_dict_broadcast(edge):
    rng = np.random.default_rng(4)
    from ppoe_core.model.chain_kernel import CHUNK

    n = 3 * CHUNK + 5  # several chunks of the compiled kernel, the last one partial
    Q = _random_q(edge, rng, (n,))
    T, cov = edge.fk(Q, "base_link", "tool0")
    for i in (0, CHUNK - 1, CHUNK, 2 * CHUNK + 1, n - 1):
        Ti, ci = edge.fk(Q[i], "base_link", "tool0")
        np.testing.assert_allclose(T[i], Ti, atol=1e-13)
        np.testing.assert_allclose(cov[i], ci, rtol=1e-9, atol=1e-20)
    # mapping: scalars broadcast against arrays
    qd = {"j1": Q[:5, 0], "j2": 0.3, "j3": Q[:5, 2], "j4": -0.2}
    Td = edge.fk_mean(qd, "base_link", "tool0")
    assert Td.shape == (5, 4, 4)
    ref = np.stack([edge.fk_mean(np.array([Q[i, 0], 0.3, Q[i, 2], -0.2]), "base_link", "tool0") for i in range(5)])
    np.testing.assert_allclose(Td, ref, atol=1e-13)


def test_default_frames_from_config(edge):
    q = np.array([0.1, 0.2, 0.05, 0.3])
    np.testing.assert_array_equal(edge.fk(q)[0], edge.fk(q, "base_link", "tool0")[0])


# ----------------------------------------------------------------------------
# Jacobian
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("frm, to", [("base_link", "tool0"), ("camera_optical_frame", "finger"), ("tool0", "link1")])
def test_jacobian_joints_central_differences(edge, frm, to):
    rng = np.random.default_rng(5)
    q = _random_q(edge, rng)
    J = edge.jacobian_joints(q, frm, to)
    assert J.shape == (6, 4)
    T0 = edge.fk_mean(q, frm, to)
    check_jacobian(lambda x: edge.fk_mean(x, frm, to), q, J, minus=SE3_MINUS, atol=1e-8, err_msg=f"{frm}->{to}")
    assert np.all(np.isfinite(T0))
    Jb = edge.jacobian_joints(np.stack([q, q, q]), frm, to)
    np.testing.assert_allclose(Jb[2], J, atol=1e-14)


def test_jacobian_zero_for_joints_off_the_chain(edge):
    J = edge.jacobian_joints(np.array([0.3, 0.2, 0.1, 0.4]), "link1", "camera_optical_frame")
    np.testing.assert_array_equal(J, np.zeros((6, 4)))


# ----------------------------------------------------------------------------
# Fourth order: port check against pytransform3d
# ----------------------------------------------------------------------------


def test_fourth_order_terms_match_pytransform3d():
    from pytransform3d.uncertainty._composition import _compound_cov_fourth_order_terms

    rng = np.random.default_rng(6)
    A = rng.normal(size=(6, 6)) * 0.1
    B = rng.normal(size=(6, 6)) * 0.1
    c1, c2 = A @ A.T, B @ B.T
    swap = np.r_[3, 4, 5, 0, 1, 2]  # [rho; theta] <-> [omega; v]
    ref = _compound_cov_fourth_order_terms(c1[np.ix_(swap, swap)], c2[np.ix_(swap, swap)])[np.ix_(swap, swap)]
    ours = compound_fourth_order(c1, c2) - c1 - c2
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-15)
    # batched
    out = compound_fourth_order(np.stack([c1, c2]), np.stack([c2, c1]))
    np.testing.assert_allclose(out[0], compound_fourth_order(c1, c2), atol=1e-15)


# ----------------------------------------------------------------------------
# Effects hook
# ----------------------------------------------------------------------------


class _FakeEffect:
    """dq on j2 proportional to the context temperature, a constant twist at j3."""

    def __init__(self):
        self.calls = []

    def corrections(self, q, context):
        self.calls.append((sorted(q), dict(context)))
        shape = np.shape(q["j1"])
        dq = {"j2": np.full(shape, 0.01 * context.get("temperature", 0.0))}
        dxi = {"j3": np.broadcast_to(np.array([0.001, 0.0, 0.002, 0.01, -0.02, 0.005]), shape + (6,))}
        return dq, dxi


def test_effect_hook_mean_and_covariance(edge):
    fake = _FakeEffect()
    model = edge.with_effects([fake])
    q = np.array([0.3, -0.2, 0.1, 0.5])
    qd = dict(zip(edge.joint_names, q))
    dq = {"j2": 0.01 * 25.0}
    dxi = {"j3": np.array([0.001, 0.0, 0.002, 0.01, -0.02, 0.005])}
    for frm, to in (("base_link", "tool0"), ("tool0", "camera_optical_frame")):
        T, cov = model.fk(q, frm, to, context={"temperature": 25.0})
        T_ref, cov_ref = reference_fk(reference_chain(edge, qd, frm, to, dq, dxi))
        np.testing.assert_allclose(T, T_ref, atol=1e-12)
        np.testing.assert_allclose(cov, cov_ref, rtol=1e-9, atol=1e-18)
        T0 = edge.fk_mean(q, frm, to)
        assert np.abs(T - T0).max() > 1e-3  # the effect really moved the pose
    assert fake.calls[-1][1] == {"temperature": 25.0}
    assert "finger_joint" in fake.calls[-1][0]  # mimic values are passed to effects too
    # batched path with effects
    Tb, covb = model.fk(np.stack([q, q]), "base_link", "tool0", context={"temperature": 25.0})
    T1, cov1 = model.fk(q, "base_link", "tool0", context={"temperature": 25.0})
    np.testing.assert_allclose(Tb[1], T1, atol=1e-13)
    np.testing.assert_allclose(covb[1], cov1, rtol=1e-9, atol=1e-20)


class _MasterOffset:
    """A joint offset on j4, the master of the mimic finger_joint, and one on the mimic itself."""

    def corrections(self, q, context):
        shape = np.shape(q["j1"])
        return {"j4": np.full(shape, 0.05), "finger_joint": np.full(shape, 0.01)}, {}


def test_joint_offset_on_a_mimic_master_moves_the_mimic_as_the_kinematic_tree(edge):
    from ppoe_core.robot.tree import KinematicTree

    model = edge.with_effects([_MasterOffset()])
    q = np.array([0.3, -0.2, 0.1, 0.8])
    T = model.fk_mean(q, "link4", "finger")
    mimic = -0.5 * (0.8 + 0.05) + 0.1 + 0.01  # the master's true value, then the mimic's own offset
    expected = edge.robot.joints["finger_joint"].origin @ lie.exp(np.array([0, 0, 0, 0, 1.0, 0]) * mimic)
    np.testing.assert_allclose(T, expected, atol=1e-14)
    poses = KinematicTree(edge.robot).link_poses(dict(zip(edge.joint_names, q)), {"j4": 0.05, "finger_joint": 0.01})
    np.testing.assert_allclose(model.fk_mean(q, "base_link", "finger"), poses["finger"], atol=1e-13)
    Tb = model.fk_mean(np.stack([q, q]), "base_link", "finger")  # batched path
    np.testing.assert_allclose(Tb[1], poses["finger"], atol=1e-13)


def test_effects_from_config_are_built_lazily(monkeypatch):
    """config.effects -> ppoe_core.model.effects.effect_from_config(entry, robot, where=...)."""
    import sys
    import types

    built = []

    def effect_from_config(entry, robot, where="effects"):
        built.append((entry["name"], where))
        return _FakeEffect()

    fake = types.SimpleNamespace(effect_from_config=effect_from_config)
    monkeypatch.setitem(sys.modules, "ppoe_core.model.effects", fake)
    import ppoe_core
    import ppoe_core.model

    monkeypatch.setattr(ppoe_core.model, "effects", sys.modules["ppoe_core.model.effects"], raising=False)
    text = EDGE_YAML.read_text() + "effects:\n  - {name: joint_offset, location: j2, parameters: {offset: 0.01}}\n"
    model = PPOEModel.from_strings(EDGE.read_text(), text)
    assert built == []  # nothing imported or built before the first use
    T = model.fk_mean(np.zeros(4), "base_link", "tool0", context={"temperature": 10.0})
    assert built == [("joint_offset", f"<string>:{text.count(chr(10))}: effects[0]")]
    edge = PPOEModel.from_files(EDGE, EDGE_YAML)
    dxi = {"j3": np.array([0.001, 0.0, 0.002, 0.01, -0.02, 0.005])}
    T_ref, _ = reference_fk(
        reference_chain(edge, dict.fromkeys(edge.joint_names, 0.0), "base_link", "tool0", {"j2": 0.1}, dxi)
    )
    np.testing.assert_allclose(T, T_ref, atol=1e-12)


# ----------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------


def test_missing_joint_value_names_joint(edge):
    with pytest.raises(JointValueError, match="'j3'"):
        edge.fk({"j1": 0.0, "j2": 0.0, "j4": 0.0}, "base_link", "tool0")
    # a joint the chain does not need may be missing
    T = edge.fk_mean({"j1": 0.2}, "base_link", "camera_optical_frame")
    assert T.shape == (4, 4)


def test_nan_joint_value_names_joint(edge):
    with pytest.raises(JointValueError, match="'j4'"):
        edge.fk(np.array([0.0, 0.0, 0.0, np.nan]), "base_link", "tool0")
    with pytest.raises(JointValueError, match="'j2'"):
        edge.fk({"j1": 0.0, "j2": [0.0, np.inf], "j3": 0.0, "j4": 0.0}, "base_link", "tool0")
    # NaN in a joint the chain does not use is fine
    edge.fk(np.array([0.1, np.nan, np.nan, np.nan]), "base_link", "camera_optical_frame")


def test_unknown_frame_and_bad_shapes(edge):
    with pytest.raises(UnknownFrameError, match="tool_9"):
        edge.fk(np.zeros(4), "base_link", "tool_9")
    with pytest.raises(JointValueError, match=r"shape \(\.\.\., 4\)"):
        edge.fk(np.zeros(3), "base_link", "tool0")
    with pytest.raises(JointValueError, match="not numeric"):
        edge.fk({"j1": "a", "j2": 0, "j3": 0, "j4": 0}, "base_link", "tool0")
    with pytest.raises(ModelConfigError, match="order"):
        edge.fk(np.zeros(4), "base_link", "tool0", order=3)


def test_from_strings_matches_from_files(edge):
    m = PPOEModel.from_strings(EDGE.read_text(), EDGE_YAML.read_text())
    q = np.array([0.3, 0.1, 0.2, -0.5])
    for a, b in zip(m.fk(q), edge.fk(q)):
        np.testing.assert_array_equal(a, b)


def test_sample_shapes_and_exact_model():
    model = PPOEModel.from_files(EDGE)  # no perturbations: every sample is the mean
    q = np.zeros((2, 4))
    S = model.sample(q, "base_link", "tool0", n=5, rng=np.random.default_rng(0))
    assert S.shape == (5, 2, 4, 4)
    np.testing.assert_allclose(S, np.broadcast_to(model.fk_mean(q, "base_link", "tool0"), S.shape), atol=1e-14)


# ----------------------------------------------------------------------------
# Properties over random link pairs and joint values (hypothesis)
# ----------------------------------------------------------------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_EDGE_MODEL = PPOEModel.from_files(EDGE, EDGE_YAML)
_LINKS = list(_EDGE_MODEL.robot.links)


@settings(max_examples=40, deadline=None)
@given(
    frm=st.sampled_from(_LINKS),
    to=st.sampled_from(_LINKS),
    mid=st.sampled_from(_LINKS),
    q=st.lists(st.floats(-3.0, 3.0), min_size=4, max_size=4),
)
def test_chain_properties(frm, to, mid, q):
    """Inverse chain, composition through any third link, and covariance transport."""
    m = _EDGE_MODEL
    q = np.array(q)
    T_ft, cov_ft = m.fk(q, frm, to)
    T_tf, cov_tf = m.fk(q, to, frm)
    np.testing.assert_allclose(T_ft @ T_tf, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(m.fk_mean(q, frm, mid) @ m.fk_mean(q, mid, to), T_ft, atol=1e-12)
    Ad = lie.adjoint(T_tf)
    np.testing.assert_allclose(cov_ft, Ad @ cov_tf @ Ad.T, rtol=1e-8, atol=1e-16)
    # symmetric PSD, and order 4 too
    for cov in (cov_ft, m.fk(q, frm, to, order=4)[1]):
        np.testing.assert_allclose(cov, cov.T, atol=1e-18)
        assert np.linalg.eigvalsh(cov).min() > -1e-15


def test_from_strings_empty_and_one_line_yaml():
    text = EDGE.read_text()
    assert PPOEModel.from_strings(text, "").config.perturbations == {}
    assert PPOEModel.from_strings(text, "{}").config.perturbations == {}
    m = PPOEModel.from_strings(text, "perturbations: {j1: {sigma: [0, 0, 0, 0, 0, 0.01]}}")
    assert list(m.config.perturbations) == ["j1"]


# ----------------------------------------------------------------------------
# Joint covariance of several targets
# ----------------------------------------------------------------------------


def test_fk_multi_joint_covariance_matches_reference(edge):
    q = np.array([0.4, -0.6, 0.15, 0.9])
    qd = dict(zip(edge.joint_names, q))
    frm, tos = "link1", ["tool0", "camera_optical_frame", "finger", "base_link"]
    T, cov = edge.fk_multi(q, frm, tos)
    assert T.shape == (4, 4, 4) and cov.shape == (24, 24)
    refs = [reference_transport(reference_chain(edge, qd, frm, to)) for to in tos]
    for i, to in enumerate(tos):
        Ti, ci = edge.fk(q, frm, to)
        np.testing.assert_allclose(T[i], Ti, atol=1e-13)
        np.testing.assert_allclose(cov[6 * i : 6 * i + 6, 6 * i : 6 * i + 6], ci, rtol=1e-9, atol=1e-20)
        for j in range(len(tos)):
            cross = np.zeros((6, 6))
            for key, (Ji, S) in refs[i].items():
                if key in refs[j]:
                    cross += Ji @ S @ refs[j][key][0].T
            np.testing.assert_allclose(cov[6 * i : 6 * i + 6, 6 * j : 6 * j + 6], cross, rtol=1e-9, atol=1e-18)
    # the up-branch (link1 -> base_link) shares mount/j1 perturbations with nothing else here,
    # but tool0 and finger share j2, j3, j4: a clearly non-zero cross block
    assert np.abs(cov[0:6, 12:18]).max() > 1e-6
    # batched
    Tb, covb = edge.fk_multi(np.stack([q, q, q]), frm, tos)
    assert covb.shape == (3, 24, 24)
    np.testing.assert_allclose(covb[2], cov, rtol=1e-9, atol=1e-20)


# ----------------------------------------------------------------------------
# Random kinematic trees (hypothesis): parser + compiled chains vs the literal reference
# ----------------------------------------------------------------------------

_AXES = [(0, 0, 1), (0, 0, -1), (1, 0, 0), (0, -2, 0), (0.3, -0.5, 0.8), (-1e-3, 0, -1)]


@st.composite
def _random_tree(draw):
    n = draw(st.integers(1, 6))
    f = st.floats(-1.0, 1.0)
    joints, pert, noise = [], {}, {}
    for i in range(n):
        parent = draw(st.integers(0, i))
        jtype = draw(st.sampled_from(["revolute", "continuous", "prismatic", "fixed"]))
        axis = draw(st.sampled_from(_AXES))
        xyz = [draw(f) for _ in range(3)]
        rpy = [3 * draw(f) for _ in range(3)]
        joints.append(
            f'<joint name="j{i}" type="{jtype}"><parent link="l{parent}"/><child link="l{i + 1}"/>'
            f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="{rpy[0]} {rpy[1]} {rpy[2]}"/>'
            f'<axis xyz="{axis[0]} {axis[1]} {axis[2]}"/></joint>'
        )
        if draw(st.booleans()):
            pert[f"j{i}"] = {"sigma": [draw(st.floats(0.0, 0.01)) for _ in range(6)]}
        if jtype != "fixed" and draw(st.booleans()):
            noise[f"j{i}"] = draw(st.floats(0.0, 0.01))
    links = "".join(f'<link name="l{i}"/>' for i in range(n + 1))
    urdf = f'<robot name="r">{links}{"".join(joints)}</robot>'
    return urdf, {"perturbations": pert, "joint_noise": noise}, n


@settings(max_examples=30, deadline=None)
@given(tree=_random_tree(), data=st.data())
def test_random_trees_against_reference(tree, data):
    urdf, cfg, n = tree
    model = PPOEModel.from_strings(urdf, cfg)
    frm = f"l{data.draw(st.integers(0, n))}"
    to = f"l{data.draw(st.integers(0, n))}"
    q = np.array([data.draw(st.floats(-3.0, 3.0)) for _ in model.joint_names])
    T, cov = model.fk(q, frm, to)
    T_ref, cov_ref = reference_fk(reference_chain(model, dict(zip(model.joint_names, q)), frm, to))
    np.testing.assert_allclose(T, T_ref, atol=1e-11)
    np.testing.assert_allclose(cov, cov_ref, rtol=1e-8, atol=1e-17)
    Tb, covb = model.fk(np.stack([q, q]), frm, to)
    np.testing.assert_allclose(Tb[0], T_ref, atol=1e-11)
    np.testing.assert_allclose(covb[0], cov_ref, rtol=1e-8, atol=1e-17)


def test_fourth_order_compounding_over_chunks_equals_one_by_one():
    from ppoe_core.model.fourth_order import CHUNK

    rng = np.random.default_rng(7)
    n = 2 * CHUNK + 3  # the compiled compounding runs in chunks; the last one partial
    A = rng.normal(size=(n, 6, 6)) * 0.1
    B = rng.normal(size=(n, 6, 6)) * 0.1
    c1, c2 = A @ A.transpose(0, 2, 1), B @ B.transpose(0, 2, 1)
    out = compound_fourth_order(c1, c2)
    for i in (0, CHUNK - 1, CHUNK, n - 1):
        np.testing.assert_allclose(out[i], compound_fourth_order(c1[i], c2[i]), rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(out, out.transpose(0, 2, 1), rtol=1e-13, atol=1e-18)


@pytest.mark.parametrize("frm, to", [("base_link", "tool0"), ("tool0", "base_link"),
                                     ("finger", "camera_optical_frame")])
def test_fourth_order_chain_matches_sequential_reference(edge, frm, to):
    """Order 4 = the local site covariances (explicit adjoints) compounded in chain order."""
    rng = np.random.default_rng(8)
    for q in _random_q(edge, rng, (2,)):
        items = reference_chain(edge, dict(zip(edge.joint_names, q)), frm, to)
        cov_ref = np.zeros((6, 6))
        for J, S in reference_transport(items).values():
            cov_ref = compound_fourth_order(cov_ref, J @ S @ J.T)
        T, cov = edge.fk(q, frm, to, order=4)
        np.testing.assert_allclose(cov, cov_ref, rtol=1e-9, atol=1e-18)
        _, cov2 = edge.fk(q, frm, to, order=2)
        assert np.linalg.norm(cov - cov2) > 1e-6 * np.linalg.norm(cov2)  # the fourth-order terms are there


def test_core_never_imports_ros() -> None:
    """Every ppoe_core module (and the ``ppoe`` dispatcher) imports without rclpy or ROS message packages.

    Run in a fresh interpreter: other tests of the session import rclpy themselves."""
    import subprocess
    import sys

    code = (
        "import importlib, pkgutil, sys, ppoe_core, ppoe_ros.cli\n"
        "names = [m.name for m in pkgutil.walk_packages(ppoe_core.__path__, 'ppoe_core.')]\n"
        "assert len(names) > 15, names\n"
        "for n in names: importlib.import_module(n)\n"
        "ros = ('rclpy', 'rcl_interfaces', 'geometry_msgs', 'sensor_msgs', 'std_msgs', 'diagnostic_msgs',\n"
        "       'rosgraph_msgs', 'builtin_interfaces')\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ros)\n"
        "print(len(names), bad)\n"
        "sys.exit(1 if bad else 0)\n"
    )
    repo = Path(__file__).resolve().parents[1]
    res = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def test_from_strings_names_the_yaml_file_and_the_urdf_source(tmp_path) -> None:
    """A model YAML given as a Path to from_strings is read from the file: errors name file and line."""
    urdf_xml = EDGE.read_text()
    bad = tmp_path / "bad_model.yaml"
    bad.write_text("perturbations:\n  j1: {sigma: [0, 0, 0, 0, 0, 1]}\n  nope: {sigma: [0, 0, 0, 0, 0, 1]}\n")
    with pytest.raises(
        UnknownJointError,
        match=r"bad_model.yaml:3: perturbations.nope: unknown joint 'nope' "
        r"\(not in URDF bag b1 /robot_description\)",
    ):
        PPOEModel.from_strings(urdf_xml, bad, urdf_source="bag b1 /robot_description")
    m = PPOEModel.from_strings(urdf_xml, EDGE_YAML, urdf_source="bag b1 /robot_description")
    ref = PPOEModel.from_files(EDGE, EDGE_YAML)
    q = np.linspace(-0.5, 0.5, len(ref.joint_names))
    frm, to = ref.robot.root, list(ref.robot.links)[-1]
    np.testing.assert_array_equal(m.fk(q, frm, to)[1], ref.fk(q, frm, to)[1])
    assert m.robot.source == "bag b1 /robot_description"
