"""``ppoe urdf from-dh``: a URDF from a DH table, checked against an independent product of DH matrices and a
published zero pose; and a robot of our own built this way, with two reflectors on two links, diagnosed in
one fit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import CONFIG  # noqa: F401  (test path set-up)

from ppoe_core.errors import ModelConfigError
from ppoe_core.robot.dh import dh_to_urdf
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

HALF_PI = np.pi / 2
#: UR5 in standard DH (Universal Robots' published parameters) [m, rad]
UR5 = [(0.0, HALF_PI, 0.089159), (-0.425, 0.0, 0.0), (-0.39225, 0.0, 0.0), (0.0, HALF_PI, 0.10915),
       (0.0, -HALF_PI, 0.09465), (0.0, 0.0, 0.0823)]


def _table(tmp: Path, rows, convention="standard", extra=None, name="t.yaml") -> Path:
    doc = {"name": "t", "convention": convention,
           "joints": [dict({"name": f"j{i + 1}", "a": a, "alpha": al, "d": d, "lower": -3.0, "upper": 3.0},
                           **(extra[i] if extra else {})) for i, (a, al, d) in enumerate(rows)],
           "tool": {"name": "tool0"}}
    (tmp / name).write_text(yaml.safe_dump(doc, sort_keys=False))
    return tmp / name


def _rz(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _rx(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _tr(x, z):
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def test_ur5_zero_pose_and_random_poses_match_the_dh_product(tmp_path):
    robot = parse_urdf(dh_to_urdf(_table(tmp_path, UR5)))
    tree = KinematicTree(robot)
    names = [f"j{i}" for i in range(1, 7)]
    T0 = tree.link_poses({n: np.array(0.0) for n in names}, links=["tool0"])["tool0"]
    np.testing.assert_allclose(T0[:3, 3], [-0.81725, -0.19145, 0.089159 - 0.09465], atol=1e-12)  # published
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(-3, 3, 6)
        T = np.eye(4)
        for (a, al, d), qi in zip(UR5, q):
            T = T @ _rz(qi) @ _tr(0.0, d) @ _tr(a, 0.0) @ _rx(al)
        got = tree.link_poses({n: np.array(v) for n, v in zip(names, q)}, links=["tool0"])["tool0"]
        np.testing.assert_allclose(got, T, atol=1e-12)


def test_modified_convention_and_prismatic_rows_match_their_product(tmp_path):
    rows = [(0.0, 0.0, 0.3), (0.1, -HALF_PI, 0.0), (0.4, 0.0, 0.05), (0.0, HALF_PI, 0.2)]
    extra = [{}, {"theta": 0.3}, {"type": "prismatic", "lower": 0.0, "upper": 0.5}, {"type": "continuous"}]
    robot = parse_urdf(dh_to_urdf(_table(tmp_path, rows, "modified", extra)))
    tree = KinematicTree(robot)
    assert robot.joints["j3"].type == "prismatic" and robot.joints["j4"].type == "continuous"
    rng = np.random.default_rng(4)
    for _ in range(10):
        q = rng.uniform(0.0, 0.5, 4)
        T = np.eye(4)
        for (a, al, d), e, qi in zip(rows, extra, q):
            th = e.get("theta", 0.0)
            T = T @ _rx(al) @ _tr(a, 0.0) @ (_rz(th) @ _tr(0.0, d + qi) if e.get("type") == "prismatic"
                                              else _rz(th + qi) @ _tr(0.0, d))
        got = tree.link_poses({f"j{i + 1}": np.array(v) for i, v in enumerate(q)}, links=["tool0"])["tool0"]
        np.testing.assert_allclose(got, T, atol=1e-12)


@pytest.mark.parametrize("change,needle", [
    ({"type": "spherical"}, "joints[1].type: must be revolute, continuous or prismatic"),
    ({"lower": None}, "joints[1].lower: must be a number"),
    ({"colour": 1}, "joints[1]: unknown key 'colour'"),
    ({"mass": -1.0}, "joints[1].mass: must be > 0"),
])
def test_bad_rows_name_the_file_line_and_row(tmp_path, change, needle):
    path = _table(tmp_path, UR5[:3], extra=[{}, change, {}])
    with pytest.raises(ModelConfigError) as err:
        dh_to_urdf(path)
    assert needle in str(err.value) and f"{path}:" in str(err.value)


def test_cli_from_dh_writes_a_urdf_and_refuses_to_overwrite(tmp_path, capsys):
    from ppoe_ros.cli import main

    table, out = _table(tmp_path, UR5), tmp_path / "ur5.urdf"
    assert main(["urdf", "from-dh", str(table), "--out", str(out)]) == 0
    assert "6 movable joints" in capsys.readouterr().err
    assert parse_urdf(out).joints["j6"].type == "revolute"
    assert main(["urdf", "from-dh", str(table), "--out", str(out)]) == 2
    assert "exists (pass --force" in capsys.readouterr().err


def test_a_dh_robot_of_our_own_with_two_reflectors_is_diagnosed_in_one_fit(tmp_path, capsys):
    """A 5-joint arm of our own from a DH table (masses on the links), reflectors on the forearm and on the
    tool, one undeclared encoder offset at the elbow: named at the right joint with the truth in its CI."""
    from ppoe_core.sim.simulate import simulate
    from ppoe_ros.cli import main

    rows = [(0.0, HALF_PI, 0.4), (0.55, 0.0, 0.0), (0.45, 0.0, 0.0), (0.0, HALF_PI, 0.0), (0.0, 0.0, 0.12)]
    extra = [{"mass": 6.0, "com": [0, 0, -0.1]}, {"mass": 4.0, "com": [-0.27, 0, 0]},
             {"mass": 2.5, "com": [-0.2, 0, 0]}, {"mass": 1.0}, {"mass": 0.5}]
    urdf = tmp_path / "arm5.urdf"
    assert main(["urdf", "from-dh", str(_table(tmp_path, rows, extra=extra)), "--out", str(urdf)]) == 0
    names = [f"j{i}" for i in range(1, 6)]
    model = {"perturbations": {n: {"sigma": [1e-4, 1e-4, 1e-4, 2e-4, 2e-4, 2e-4]} for n in names},
             "joint_noise": {n: 2e-4 for n in names}, "frames": {"base": "base_link", "tool": "tool0"},
             "trackers": [{"topic": "/ground_truth/point/forearm", "link": "link_3", "xyz": [-0.1, 0.0, 0.05],
                           "sigma": 2e-4},
                          {"topic": "/ground_truth/point/tool", "link": "tool0", "xyz": [0.0, 0.0, 0.03],
                           "sigma": 2e-4}]}
    (tmp_path / "arm5_model.yaml").write_text(yaml.safe_dump(model))
    T = {"xyz": [2.0, 1.0, 0.0], "rpy": [0.0, 0.0, 0.5]}
    sc = {"robot": {"urdf": str(urdf), "model": str(tmp_path / "arm5_model.yaml")}, "seed": 12,
          "truth": {"perturbations": "per_stop", "joint_noise": True,
                    "effects": [{"name": "joint_offset", "location": "j3", "parameters": {"offset": 0.015}}]},
          "trajectory": {"joint_rate": 100.0, "dwell": 0.3, "settle": 0.1, "move_time": 0.4,
                         "random_stops": {"count": 40, "around": {n: 0.0 for n in names},
                                          "spread": {n: 1.2 for n in names}}},
          "ground_truth": {"point": [{"topic": "/ground_truth/point/forearm", "frame": "tracker",
                                      "T_tracker_base": T},
                                     {"topic": "/ground_truth/point/tool", "frame": "tracker", "T_tracker_base": T}]}}
    (tmp_path / "sc.yaml").write_text(yaml.safe_dump(sc))
    simulate(tmp_path / "sc.yaml", tmp_path / "bag")
    assert main(["diagnose", str(tmp_path / "bag"), "--model", str(tmp_path / "arm5_model.yaml"), "--json",
                 "--pixels", "off"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(e["name"], e["location"]) for e in doc["effects"]] == [("joint_offset", "j3")], doc["summary"]
    lo, hi = doc["effects"][0]["ci"]["offset"]
    assert lo <= 0.015 <= hi
    assert doc["n_stops"] == 80 and doc["n_sessions"] == 1


# ----------------------------------------------------------------------------- trees of chains

HUMANOID = CONFIG / "robots" / "humanoid19_dh.yaml"


def _fixed_T(xyz, rpy):
    """Independent of ppoe_core.lie: URDF rpy = Rz(yaw) Ry(pitch) Rx(roll), then the translation."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                  [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                  [-sp, cp * sr, cp * cr]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, xyz
    return T


def _chain_product(rows, q):
    """Standard DH: prod Rz(theta_i + q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)."""
    T = np.eye(4)
    for r, qi in zip(rows, q):
        T = T @ _rz(r.get("theta", 0.0) + qi) @ _tr(0.0, r.get("d", 0.0)) @ _tr(r.get("a", 0.0), 0.0) \
            @ _rx(r.get("alpha", 0.0))
    return T


def test_a_tree_of_chains_matches_the_product_of_its_dh_matrices():
    """humanoid19 (torso, two arms on the chest, a head): every hand / head frame = mount transforms times the
    DH products of the chains from the root, at random joint values; 19 movable joints, masses and inertias
    as written."""
    table = yaml.safe_load(HUMANOID.read_text())
    robot = parse_urdf(dh_to_urdf(HUMANOID))
    tree = KinematicTree(robot)
    assert len(robot.independent_joints) == 19 and robot.root == "pelvis"
    torso, left, right, head = table["chains"]
    rng = np.random.default_rng(7)
    for _ in range(10):
        qv = {j: rng.uniform(-1.5, 1.5) for j in robot.independent_joints}
        P = tree.link_poses({j: np.array(v) for j, v in qv.items()})
        T_chest = _chain_product(torso["joints"], [qv[r["name"]] for r in torso["joints"]])
        np.testing.assert_allclose(P["chest_flange"], T_chest, atol=1e-12)
        for arm in (left, right):
            m, tool = arm["mount"], arm["tool"]
            # the arm's mount hangs on `chest` (the last torso row's frame BEFORE its a/alpha)
            r3 = torso["joints"][2]
            T_chest_link = T_chest @ np.linalg.inv(_tr(r3["a"], 0.0) @ _rx(r3["alpha"]))
            T = T_chest_link @ _fixed_T(m["xyz"], m["rpy"]) @ _chain_product(
                arm["joints"], [qv[r["name"]] for r in arm["joints"]]) @ _fixed_T(tool["xyz"], [0, 0, 0])
            np.testing.assert_allclose(P[tool["name"]], T, atol=1e-12)
        T_head = T_chest_link @ _fixed_T(head["mount"]["xyz"], head["mount"]["rpy"]) @ _chain_product(
            head["joints"], [qv[r["name"]] for r in head["joints"]])
        np.testing.assert_allclose(P["head_link_2_flange"], T_head, atol=1e-12)
    chest = robot.links["chest"].inertial
    assert chest is not None and chest.mass == 14.0
    np.testing.assert_allclose(np.diag(chest.inertia), [0.1008, 0.1933, 0.1933])
    hand = robot.links["l_hand"].inertial
    assert hand is not None and hand.mass == 0.3 and robot.joints["l_hand_joint"].type == "fixed"


def test_mounts_frames_and_payloads_of_the_industrial_arms():
    """ind6 / cobot6: the arm on a named mount joint (mount_bending needs it), a camera on a named fixed joint,
    a payload on the tool; the tool = mount times the chain's DH product."""
    for name, mount, first in (("ind6", "mount_joint", "joint_1"), ("cobot6", "mount_joint", "shoulder_pan")):
        path = CONFIG / "robots" / f"{name}_dh.yaml"
        table = yaml.safe_load(path.read_text())
        robot = parse_urdf(dh_to_urdf(path))
        assert robot.root == "world" and robot.joints[mount].type == "fixed"
        assert robot.joints["camera_joint"].parent == "world" and "camera_optical_frame" in robot.links
        assert robot.joints[first].parent == "base_link" and robot.links["tool0"].inertial is not None
        arm = table["chains"][0]
        q = np.random.default_rng(3).uniform(-2, 2, 6)
        P = KinematicTree(robot).link_poses({r["name"]: np.array(v) for r, v in zip(arm["joints"], q)})
        T = _fixed_T(arm["mount"]["xyz"], arm["mount"].get("rpy", [0, 0, 0])) @ _chain_product(arm["joints"], q) \
            @ _fixed_T(arm["tool"]["xyz"], [0, 0, 0])
        np.testing.assert_allclose(P["tool0"], T, atol=1e-12)


def _tree_table(tmp: Path, **over) -> Path:
    doc = {"name": "t", "base_link": "base",
           "chains": [{"name": "a", "joints": [{"name": "a1", "a": 0.3, "lower": -1, "upper": 1}]},
                      {"name": "b", "parent": "a_link_1", "mount": {"name": "b_mount", "xyz": [0, 0.1, 0]},
                       "joints": [{"name": "b1", "d": 0.2, "lower": -1, "upper": 1}],
                       "tool": {"name": "b_tool", "mass": 1.0, "inertia": [0.01, 0.01, 0.02]}}],
           "frames": [{"name": "cam", "parent": "base", "joint": "cam_joint", "xyz": [1, 0, 0]}]}
    doc.update(over)
    (tmp / "tree.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return tmp / "tree.yaml"


def test_tree_default_names_and_parents(tmp_path):
    robot = parse_urdf(dh_to_urdf(_tree_table(tmp_path)))
    assert robot.joints["a1"].child == "a_link_1" and robot.joints["a_flange_joint"].child == "a_link_1_flange"
    assert robot.joints["b_mount_joint"].parent == "a_link_1" and robot.joints["b1"].parent == "b_mount"
    assert robot.joints["cam_joint"].parent == "base"
    assert robot.links["b_tool"].inertial.mass == 1.0


@pytest.mark.parametrize("change,needle", [
    ({"chains": [{"name": "a", "parent": "nowhere", "joints": [{"name": "a1", "type": "continuous"}]}]},
     "chains[0].parent: unknown parent link 'nowhere'"),
    ({"frames": [{"name": "base", "parent": "base"}]}, "frames[0]: link name 'base' is used twice"),
    ({"chains": [{"name": "a", "joints": [{"name": "a1", "type": "continuous"},
                                          {"name": "a1", "type": "continuous"}]}]},
     "chains[0].joints[1]: joint name 'a1' is used twice"),
    ({"chains": [{"name": "a", "joints": [{"name": "a1", "type": "continuous", "mass": 1.0, "inertia": [1, 2]}]}]},
     "chains[0].joints[0].inertia: must be a list of 3 numbers"),
    ({"chains": [{"name": "a", "joints": [{"name": "a1", "type": "hinge"}]}]},
     "chains[0].joints[0].type: must be revolute, continuous or prismatic"),
    ({"chains": [{"name": "a", "joints": [{"name": "a1", "type": "continuous"}], "colour": 1}]},
     "chains[0]: unknown key 'colour'"),
    ({"frames": [{"name": "cam"}]}, "frames[0]: missing required key 'parent'"),
])
def test_bad_tree_entries_name_the_file_line_and_entry(tmp_path, change, needle):
    path = _tree_table(tmp_path, **change)
    with pytest.raises(ModelConfigError) as err:
        dh_to_urdf(path)
    assert needle in str(err.value) and f"{path}:" in str(err.value), str(err.value)
