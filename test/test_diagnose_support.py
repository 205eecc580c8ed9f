"""Diagnose: a robot rocking on its support (the tilt a root accelerometer measures at each stop, ``base_tilt``
with ``variable: measured``) and a telescopic stage whose bending compliance grows with its extension
(``mount_bending`` with ``extension_x`` / ``extension_y`` at a prismatic joint).  Synthetic data made here."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG

from ppoe_core import lie
from ppoe_core.analysis.diagnose import DiagnoseOptions, Stops, diagnose
from ppoe_core.analysis.diagnose.stops import base_tilt_context
from ppoe_core.analysis.diagnose.testing import score_stops
from ppoe_core.model.effects import effect_from_config, make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

SIGMA = 1e-4  # tracker noise [m]


def _points(robot, link, q, ctx, true_effects, session, rng, point=(0.0, 0.0, 0.0)):
    """Tracker points of ``link`` with the true effects, noise SIGMA, a random registration per session."""
    tree = KinematicTree(robot)
    dq, dxi = sum_effect_corrections(list(true_effects), q, ctx)
    x = (tree.link_poses(q, dq, dxi)[link] @ np.append(point, 1.0))[:, :3]
    p = np.empty_like(x)
    for s in np.unique(session):
        T = lie.from_xyz_rpy(rng.uniform(-3, 3, 3), [0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        p[session == s] = x[session == s] @ T[:3, :3].T + T[:3, 3]
    return p + rng.normal(0.0, SIGMA, p.shape)


def _stops(robot, link, q, p, ctx, session, name="synthetic", point=(0.0, 0.0, 0.0)):
    n = len(session)
    return Stops(q=q, p_meas=p, kind="point", link=link, point=np.asarray(point), sigma=SIGMA,
                 session=session, session_names=[f"{name}:{i}" for i in range(int(session.max()) + 1)],
                 group=np.zeros(n, dtype=int), group_names=[name], reg_mask=np.ones(n, dtype=bool),
                 score_mask=np.ones(n, dtype=bool), context=ctx, base=robot.root)


@pytest.fixture(scope="module")
def arm7():
    return parse_urdf(CONFIG / "robots" / "arm7.urdf")


def _rocking(robot, gain, seed, n=160, sessions=4, rock=1e-3):
    """arm7 tool0 points; the root tilts by a constant per session plus ``rock`` [rad] 1-sigma per stop, as a
    root accelerometer measures it (context ``gravity``); the chain is rotated by ``gain`` times the rocking."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(robot)
    q = {j: rng.uniform(-1.2, 1.2, n) for j in tree.joint_names if robot.joints[j].type != "prismatic"}
    q.update({j: np.full(n, 0.01) for j in tree.joint_names if robot.joints[j].type == "prismatic"})
    session = np.arange(n) % sessions
    w = rng.normal(0.0, 5e-3, (sessions, 2))[session] + rng.normal(0.0, rock, (n, 2))
    g = np.column_stack([w[:, 1], -w[:, 0], -np.ones(n)])
    g /= np.linalg.norm(g, axis=1)[:, None]
    ctx = {"gravity": g, "base_tilt": base_tilt_context(g, session)}
    truth = [make_effect("base_tilt", robot.root, robot, [gain], variable="measured")] if gain else []
    p = _points(robot, "tool0", q, ctx, truth, session, rng, point=(0.0, 0.0, 0.02))
    return _stops(robot, "tool0", q, p, ctx, session, point=(0.0, 0.0, 0.02))


def test_base_tilt_context_is_the_tilt_minus_its_session_mean():
    w = np.array([[1e-3, -2e-3], [3e-3, 0.0], [5e-3, 1e-3]])
    g = np.column_stack([w[:, 1], -w[:, 0], -np.ones(3)])
    g /= np.linalg.norm(g, axis=1)[:, None]
    got = base_tilt_context(g, np.array([0, 0, 1]))
    assert got == pytest.approx(np.array([[-1e-3, -1e-3], [1e-3, 1e-3], [0.0, 0.0]]), abs=1e-8)


def test_rocking_base_is_named_with_gain_one_in_ci_and_transfers(arm7):
    stops = _rocking(arm7, 1.0, seed=41)
    res = diagnose(arm7, stops, options=DiagnoseOptions())
    assert [(e["name"], e["location"]) for e in res.to_json()["effects"]] == [("base_tilt", arm7.root)], res.summary
    entry = res.to_json()["effects"][0]
    assert entry["variable"] == "measured"
    lo, hi = entry["ci"]["gain"]
    assert lo <= 1.0 <= hi and hi - lo < 0.1
    assert res.residual_after < 0.3 * res.residual_before
    # the JSON entry loads back, and the fitted model scores other stops of the robot with their own tilts
    assert effect_from_config(entry, arm7).params == pytest.approx([entry["parameters"]["gain"]])
    other = _rocking(arm7, 1.0, seed=42)
    scored = score_stops(arm7, other, [], res.chosen)
    assert scored["rms"] < 0.3 * scored["before"]["rms"]


def test_no_rocking_finds_nothing(arm7):
    res = diagnose(arm7, _rocking(arm7, 0.0, seed=43), options=DiagnoseOptions())
    assert not res.effects, res.summary


LIFT_URDF = """<robot name="lift">
  <link name="base"><inertial><mass value="50"/><origin xyz="0 0 0.1"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="lift" type="prismatic"><parent link="base"/><child link="column"/><origin xyz="0 0 0.5"/>
    <axis xyz="0 0 1"/><limit lower="0" upper="1.5" effort="1000" velocity="1"/></joint>
  <link name="column"><inertial><mass value="10"/><origin xyz="0 0 0.2"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
  <joint name="yaw" type="revolute"><parent link="column"/><child link="arm"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="100" velocity="1"/></joint>
  <link name="arm"><inertial><mass value="15"/><origin xyz="0.4 0 0"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
  <joint name="elbow" type="revolute"><parent link="arm"/><child link="fore"/><origin xyz="0.8 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="100" velocity="1"/></joint>
  <link name="fore"><inertial><mass value="5"/><origin xyz="0.3 0 0"/>
    <inertia ixx="0.05" ixy="0" ixz="0" iyy="0.05" iyz="0" izz="0.05"/></inertial></link>
  <joint name="tool_joint" type="fixed"><parent link="fore"/><child link="tool"/><origin xyz="0.6 0 0"/></joint>
  <link name="tool"/>
</robot>"""


def _telescope(robot, truth, seed, per_height=40, heights=(0.1, 0.5, 0.9, 1.3)):
    """Tool points of a lifting column with an arm; one registration session per column height (as the
    stations of a construction robot)."""
    rng = np.random.default_rng(seed)
    n = per_height * len(heights)
    session = np.repeat(np.arange(len(heights)), per_height)
    q = {"lift": np.asarray(heights)[session], "yaw": rng.uniform(-3, 3, n), "elbow": rng.uniform(-1.2, 1.2, n)}
    p = _points(robot, "tool", q, {}, truth, session, rng)
    return _stops(robot, "tool", q, p, {}, session)


def test_telescopic_bending_growing_with_extension_is_named_with_truth_in_ci():
    robot = parse_urdf(LIFT_URDF)
    truth = {"compliance_x": 1e-5, "compliance_y": 2e-5, "extension_x": 3e-5, "extension_y": 2e-5}
    eff = make_effect("mount_bending", "lift", robot, list(truth.values()), components=tuple(truth))
    res = diagnose(robot, _telescope(robot, [eff], seed=44), options=DiagnoseOptions())
    assert [(e["name"], e["location"]) for e in res.to_json()["effects"]] == [("mount_bending", "lift")], res.summary
    entry = res.to_json()["effects"][0]
    assert set(entry["parameters"]) == set(truth)
    assert all(entry["ci"][k][0] <= v <= entry["ci"][k][1] for k, v in truth.items()), entry
    assert res.residual_after < 1.5 * res.noise_floor


def test_constant_bending_at_a_telescopic_stage_keeps_two_parameters():
    """Parsimony: a compliance that does not change with the extension is the two-parameter effect."""
    robot = parse_urdf(LIFT_URDF)
    eff = make_effect("mount_bending", "lift", robot, [2e-5, 3e-5])
    res = diagnose(robot, _telescope(robot, [eff], seed=45), options=DiagnoseOptions())
    assert [(e["name"], e["location"]) for e in res.to_json()["effects"]] == [("mount_bending", "lift")], res.summary
    assert set(res.to_json()["effects"][0]["parameters"]) == {"compliance_x", "compliance_y"}
    ci = res.to_json()["effects"][0]["ci"]["compliance_x"]
    assert ci[0] <= 2e-5 <= ci[1]


def test_measured_base_tilt_without_a_measurement_changes_nothing(arm7):
    """fk and the nodes have no per-stop accelerometer context: the effect then corrects nothing."""
    from ppoe_core.model.ppoe import PPOEModel

    eff = effect_from_config({"name": "base_tilt", "location": arm7.root, "parameters": {"gain": 1.0},
                              "variable": "measured"}, arm7)
    assert eff.corrections({"joint_1": np.zeros(3)}, {}) == ({}, {})
    q = {j: 0.3 for j in KinematicTree(arm7).joint_names}
    plain = PPOEModel(arm7)
    model = PPOEModel(arm7, effects=[eff])
    assert model.fk_mean(q, arm7.root, "tool0") == pytest.approx(plain.fk_mean(q, arm7.root, "tool0"), abs=1e-15)
