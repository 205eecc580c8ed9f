"""Tests of ppoe_core.model.effects: analytic Jacobians vs central finite differences, config round trip."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG
from jacobian_check import SE3_MINUS, check_jacobian

from ppoe_core.errors import ModelConfigError, UnknownJointError
from ppoe_core.model.effects import EFFECT_NAMES, effect_from_config, make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf


@pytest.fixture(scope="module")
def tree() -> KinematicTree:
    return KinematicTree(parse_urdf(CONFIG / "robots" / "arm7.urdf"))


def _random_q(tree: KinematicTree, rng: np.random.Generator, n: int = 4) -> dict[str, np.ndarray]:
    return {j: rng.uniform(-1.5, 1.5, n) if tree.robot.joints[j].type != "prismatic"
            else rng.uniform(0.0, 0.02, n) for j in tree.joint_names}


def _context(tree: KinematicTree, rng: np.random.Generator, n: int) -> dict:
    return {"motion_sign": {j: rng.choice([-1.0, 1.0], n) for j in tree.joint_names},
            "temperature": rng.uniform(15, 30, n), "time": rng.uniform(0, 600, n),
            "joint_velocity": {j: rng.normal(0, 0.5, n) for j in tree.joint_names}}


def _point(tree, q, effects, ctx, link="tool0", p=(0.01, -0.02, 0.05)):
    dq, dxi = sum_effect_corrections(effects, q, ctx)
    T = tree.link_poses(q, dq, dxi)[link]
    return (T @ np.append(p, 1.0))[..., :3]


def test_chain_jacobians_match_finite_differences(tree):
    rng = np.random.default_rng(0)
    q = _random_q(tree, rng)
    link, p = "gripper_link", np.array([0.02, 0.01, 0.07])
    Jq, Jx = tree.point_jacobian(q, link, p)
    Fq, Fx = tree.frame_jacobian(q, link)
    p_h = np.append(p, 1.0)
    for jn, J in Jx.items():
        check_jacobian(lambda e, jn=jn: (tree.link_poses(q, dxi={jn: e})[link] @ p_h)[..., :3], np.zeros(6), J,
                       err_msg=f"point wrt dxi {jn}")
        check_jacobian(lambda e, jn=jn: tree.link_poses(q, dxi={jn: e})[link], np.zeros(6), Fx[jn],
                       minus=SE3_MINUS, err_msg=f"frame wrt dxi {jn}")
    for jn, J in Jq.items():
        check_jacobian(lambda d, jn=jn: (tree.link_poses(q, dq={jn: d[0]})[link] @ p_h)[..., :3], np.zeros(1),
                       J[..., None], err_msg=f"point wrt q {jn}")


def test_mimic_offsets_propagate():
    robot = parse_urdf("""<robot name="m"><link name="a"/><link name="b"/><link name="c"/>
      <joint name="j1" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/></joint>
      <joint name="j2" type="prismatic"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
        <mimic joint="j1" multiplier="0.5" offset="-0.1"/></joint></robot>""")
    tree = KinematicTree(robot)
    T = tree.link_poses({"j1": np.array(1.0)}, dq={"j1": 0.2})["c"]
    assert T[2, 3] == pytest.approx(1.2 + 0.5 * 1.2 - 0.1)
    Jq, _ = tree.point_jacobian({"j1": np.array(1.0)}, "c", np.zeros(3))
    np.testing.assert_allclose(Jq["j1"], [0, 0, 1.5])


CASES = [
    ("joint_offset", "joint_2", {}),
    ("link_error", "joint_3", {}),
    ("gravity_compliance", "joint_2", {}),
    ("gravity_compliance", "joint_4", {}),
    ("mount_bending", "mount_joint", {}),
    ("lateral_compliance", "joint_2", {}),
    ("lateral_compliance", "joint_5", {}),
    ("base_tilt", "base_link", {}),
    ("backlash", "joint_1", {}),
    ("thermal_growth", "joint_4", {"variable": "temperature", "reference": 20.0}),
    ("time_offset", "/ground_truth/point", {}),
    ("camera_extrinsics", "camera_optical_frame", {}),
]


@pytest.mark.parametrize("name,location,opts", CASES)
def test_effect_point_jacobian_matches_finite_differences(tree, name, location, opts):
    rng = np.random.default_rng(1)
    q = _random_q(tree, rng, 3)
    ctx = _context(tree, rng, 3)
    eff = make_effect(name, location, tree, **opts)
    link = "camera_optical_frame" if name == "camera_extrinsics" else "tool0"
    p = np.array([0.01, -0.02, 0.05])
    scale = {"gravity_compliance": 1e-4, "mount_bending": 1e-4, "lateral_compliance": 1e-4, "thermal_growth": 1e-4,
             "time_offset": 1e-2}.get(name, 1e-3)
    theta = rng.normal(0.0, scale, eff.n_params)
    J = eff.with_params(theta).point_jacobian(q, link, p, ctx)
    h = scale * 1e-3
    for k in range(eff.n_params):
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        fd = (_point(tree, q, [eff.with_params(tp)], ctx, link, p)
              - _point(tree, q, [eff.with_params(tm)], ctx, link, p)) / (2 * h)
        np.testing.assert_allclose(J[..., k], fd, rtol=1e-4, atol=1e-9 * max(1.0, np.abs(fd).max()))
    # the effect does move the point (not a silent no-op)
    assert np.abs(J).max() > 0.0


def test_gravity_torque_matches_virtual_work(tree):
    """tau_j = -dV/dq_j with V the potential energy of the links the joint carries."""
    rng = np.random.default_rng(2)
    q = _random_q(tree, rng, 2)
    eff = make_effect("gravity_compliance", "joint_2", tree)

    def potential(qq):
        poses = tree.link_poses(qq)
        V = 0.0
        for ln in tree.subtree_links("joint_2"):
            inert = tree.robot.links[ln].inertial
            if inert is not None:
                V = V + inert.mass * 9.80665 * (poses[ln] @ inert.origin)[..., 2, 3]
        return V

    h = 1e-6
    qp = dict(q, joint_2=q["joint_2"] + h)
    qm = dict(q, joint_2=q["joint_2"] - h)
    np.testing.assert_allclose(eff.torque(q), -(potential(qp) - potential(qm)) / (2 * h), rtol=1e-6)
    assert np.all(np.abs(eff.torque(q)) > 0.1)


def test_lateral_compliance_bends_perpendicular_to_the_axis_along_the_moment(tree):
    """The rotation of lateral_compliance (in the child frame) is perpendicular to the joint axis and, with
    positive compliances, has a non-negative projection on the gravity moment (the link yields along the
    load); each axis is its own parameter, and a subset of them is an effect of its own."""
    from ppoe_core.model.effects import perpendicular_axes

    for axis in ([0, 0, 1], [0, 1, 0], [0.6, 0.0, 0.8], [1, 1, 1]):
        uv = perpendicular_axes(np.array(axis, float))
        a = np.array(axis, float) / np.linalg.norm(axis)
        np.testing.assert_allclose(uv @ uv.T, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(np.cross(uv[0], uv[1]), a, atol=1e-12)
    rng = np.random.default_rng(4)
    q = _random_q(tree, rng, 5)
    eff = make_effect("lateral_compliance", "joint_2", tree).with_params([1e-4, 3e-4])
    poses = tree.link_poses(q)
    theta_a = eff.corrections(q, {}, poses)[1]["joint_2"][..., 3:]
    T_a, T_c = tree.joint_frames(poses, "joint_2")
    R_ac = np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_c[..., :3, :3]
    theta_c = np.einsum("nji,nj->ni", R_ac, theta_a)
    axis = tree.robot.joints["joint_2"].axis
    np.testing.assert_allclose(theta_c @ axis, 0.0, atol=1e-15)
    M_c = tree.gravity_wrench(poses, "joint_2", about="c")[1]
    assert np.all(np.einsum("ni,ni->n", theta_c, M_c) >= 0.0) and np.abs(theta_c).max() > 1e-5
    only_v = make_effect("lateral_compliance", "joint_2", tree, components=["compliance_v"]).with_params([3e-4])
    uv = perpendicular_axes(axis)
    np.testing.assert_allclose(only_v.corrections(q, {}, poses)[1]["joint_2"][..., 3:],
                               np.einsum("nij,j->ni", R_ac, uv[1]) * (M_c @ uv[1])[:, None] * 3e-4, atol=1e-15)


def test_mount_bending_is_zero_without_lever(tree):
    """Arm straight up above the mount: no horizontal moment from joint 2-7 links' COMs only if
    they lie on the axis; at least check the moment flips sign with the arm's lean."""
    eff = make_effect("mount_bending", "mount_joint", tree)
    q = {j: np.array([0.0, 0.0]) for j in tree.joint_names}
    q["joint_2"] = np.array([0.5, -0.5])
    M = eff.moment(q)
    assert np.sign(M[0, 0] * M[1, 0]) < 0 or np.sign(M[0, 1] * M[1, 1]) < 0


def test_config_round_trip(tree):
    for name, loc, opts in CASES:
        eff = make_effect(name, loc, tree, **opts)
        eff = eff.with_params(np.arange(1, eff.n_params + 1) * 1e-4)
        back = effect_from_config(eff.to_config(ci=[1e-5] * eff.n_params), tree.robot)
        assert back.name == name
        np.testing.assert_allclose(back.params, eff.params)
    sub = effect_from_config({"name": "link_error", "location": "joint_3",
                              "parameters": {"x": 0.001, "rz": 0.002}}, tree.robot)
    assert sub.param_names == ("x", "rz")
    assert set(EFFECT_NAMES) == {c[0] for c in CASES} | {"tracker_registration"} | set(SENSOR_CASES)
    for name, (loc, params) in SENSOR_CASES.items():  # sensor effects: the components listed, no chain change
        eff = effect_from_config({"name": name, "location": loc, "parameters": params}, tree.robot)
        assert eff.param_names == tuple(params) and eff.sensor
        assert effect_from_config(eff.to_config(), tree.robot).key == eff.key
        q = _random_q(tree, np.random.default_rng(4), 2)
        assert sum_effect_corrections([eff], q, {}) == ({}, {})


#: sensor effects: location and a parameter subset (corrections of camera_info; a tag's pose on its link)
SENSOR_CASES = {"camera_intrinsics": ("camera_optical_frame", {"cx": 2.0, "cy": -1.5}),
                "tag_offset": ("tag_10", {"x": 0.002, "rz": 0.01})}


def test_sensor_effects_correct_their_sensor(tree):
    """camera_intrinsics adds to K and D; tag_offset composes Exp(delta) on the right of T_link_tag; a tag
    location that is neither tag_<id> nor an id is refused, naming it."""
    from ppoe_core import lie

    K = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])
    eff = make_effect("camera_intrinsics", "camera_optical_frame", tree, np.arange(1.0, 10.0))
    K2, D2 = eff.corrected(K, np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(K2, [[501.0, 0.0, 323.0], [0.0, 512.0, 244.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(D2, [5.1, 6.0, 7.0, 8.0, 9.0])
    T = lie.from_xyz_rpy([0.1, 0.0, 0.2], [0.0, 1.0, 0.0])
    tag = make_effect("tag_offset", "12", tree, [0.01, 0.0, 0.0, 0.0, 0.0, 0.1])
    assert tag.location == "tag_12"
    np.testing.assert_allclose(tag.corrected(T), T @ lie.exp(np.array([0.01, 0, 0, 0, 0, 0.1])))
    with pytest.raises(ModelConfigError, match="tag_offset: location 'gripper'"):
        make_effect("tag_offset", "gripper", tree)
    with pytest.raises(ModelConfigError, match="not a link"):
        make_effect("camera_intrinsics", "no_camera", tree)


@pytest.mark.parametrize("entry,err,word", [
    ({"name": "warp_drive", "location": "joint_1", "parameters": {}}, ModelConfigError, "warp_drive"),
    ({"name": "joint_offset", "location": "nope", "parameters": {"offset": 0.1}}, UnknownJointError, "nope"),
    ({"name": "joint_offset", "location": "mount_joint", "parameters": {"offset": 0.1}}, ModelConfigError,
     "mount_joint"),
    ({"name": "joint_offset", "location": "joint_1", "parameters": {"ofset": 0.1}}, ModelConfigError, "ofset"),
    ({"name": "joint_offset", "location": "joint_1"}, ModelConfigError, "parameters"),
    ({"name": "joint_offset", "location": "joint_1", "parameters": {"offset": "x"}}, ModelConfigError,
     "numbers"),
])
def test_config_errors_name_the_entry(tree, entry, err, word):
    with pytest.raises(err) as exc:
        effect_from_config(entry, tree.robot, where="model.yaml effects[0]")
    assert word in str(exc.value) and "effects[0]" in str(exc.value)


def test_context_effects_require_their_context(tree):
    q = _random_q(tree, np.random.default_rng(3), 2)
    with pytest.raises(ModelConfigError, match="motion_sign"):
        make_effect("backlash", "joint_1", tree, [0.001]).corrections(q, {})


def test_ppoe_model_applies_effects_like_the_tree():
    """PPOEModel (model.py) builds the model YAML's effects with effect_from_config and must
    place them exactly as KinematicTree does (eq. 16 hooks), mimic joints included."""
    from ppoe_core.model.ppoe import PPOEModel

    urdf = (CONFIG / "robots" / "arm7.urdf").read_text()
    entries = [
        {"name": "gravity_compliance", "location": "joint_2", "parameters": {"compliance": 3e-4}},
        {"name": "mount_bending", "location": "mount_joint",
         "parameters": {"compliance_x": 2e-4, "compliance_y": 1e-4}},
        {"name": "link_error", "location": "joint_5", "parameters": {"x": 0.002, "rz": 0.01}},
        {"name": "joint_offset", "location": "joint_6", "parameters": {"offset": 0.02}},
    ]
    model = PPOEModel.from_strings(urdf, {"effects": entries})
    tree = KinematicTree(parse_urdf(urdf))
    rng = np.random.default_rng(10)
    q = _random_q(tree, rng, 5)
    effects = [effect_from_config(e, tree.robot) for e in entries]
    dq, dxi = sum_effect_corrections(effects, q, {})
    T_tree = tree.link_poses(q, dq, dxi)["tool0"]
    T_model = model.fk_mean(q, "base_link", "tool0")
    np.testing.assert_allclose(T_model, T_tree, atol=1e-12)
    assert np.abs(T_tree - tree.link_poses(q)["tool0"]).max() > 1e-3  # the effects do act


def test_intrinsics_jacobian_matches_finite_differences():
    """d uv / d (fx, fy, cx, cy, k1, k2, p1, p2, k3) and d uv / d P of the intrinsics Jacobian module against
    central differences of the one projection (ppoe_core.estimation.camera.project_points), skew kept."""
    from ppoe_core.estimation.camera import project_points
    from ppoe_core.estimation.camera_intrinsics import project_with_intrinsics_jacobian

    rng = np.random.default_rng(5)
    P = np.column_stack([rng.uniform(-0.4, 0.4, (6, 2)), rng.uniform(0.8, 2.0, 6)])
    K = np.array([[800.0, 1.5, 330.0], [0.0, 790.0, 250.0], [0.0, 0.0, 1.0]])
    D = np.array([-0.2, 0.05, 0.001, -0.002, 0.01])
    uv, J_point, J_k = project_with_intrinsics_jacobian(P, K, D)
    np.testing.assert_allclose(uv, project_points(P, K, D), atol=1e-12)

    def with_k(k):
        K2 = K.copy()
        K2[0, 0], K2[1, 1], K2[0, 2], K2[1, 2] = K[0, 0] + k[0], K[1, 1] + k[1], K[0, 2] + k[2], K[1, 2] + k[3]
        return project_points(P, K2, D + k[4:])

    check_jacobian(with_k, np.zeros(9), J_k, atol=1e-6, rtol=1e-7, err_msg="intrinsics")
    for i in range(len(P)):
        check_jacobian(lambda p: project_points(p, K, D), P[i], J_point[i], atol=1e-5, err_msg=f"point {i}")
