"""The example robots in config/: every URDF parses, every model YAML loads, the frames they
name exist, and the geometry does what config/README.md says (hand-computed FK of planar3,
Fig. 3a rank-1 property, rover tags visible from the mast camera, humanoid fingertip on the table).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import CONFIG_ROBOTS as CONFIG

from ppoe_core.model.ppoe import PPOEModel
from ppoe_core.robot.config import load_model_config
from ppoe_core.robot.dh import dh_to_urdf
from ppoe_core.robot.urdf import parse_urdf

MODEL_YAMLS = sorted(CONFIG.glob("*_model.yaml"))
URDFS = sorted(CONFIG.glob("*.urdf"))
DEG = math.pi / 180.0


def _urdf_for(yaml_path: Path) -> str:
    """The robot's URDF file, or the URDF of its DH table ``<robot>_dh.yaml`` (``ppoe urdf from-dh``)."""
    urdf = CONFIG / (yaml_path.name.split("_")[0] + ".urdf")
    return str(urdf) if urdf.is_file() else dh_to_urdf(CONFIG / (yaml_path.name.split("_")[0] + "_dh.yaml"))


def _model(name: str, yaml_name: str | None = None) -> PPOEModel:
    return PPOEModel.from_files(str(CONFIG / f"{name}.urdf"), str(CONFIG / (yaml_name or f"{name}_model.yaml")))


def test_all_expected_robots_present() -> None:
    names = {p.stem for p in URDFS}
    assert {"planar3", "rover", "humanoid", "arm7"} <= names
    assert (CONFIG / "planar3_joint1_model.yaml").is_file()


@pytest.mark.parametrize("urdf", URDFS, ids=lambda p: p.stem)
def test_urdf_parses_and_optical_frames_follow_convention(urdf: Path) -> None:
    robot = parse_urdf(str(urdf))
    assert robot.root == "base_link"
    assert robot.independent_joints, "every example robot has movable joints"
    for joint in robot.joints.values():
        if joint.child.endswith("optical_frame"):
            R = joint.origin[:3, :3]  # optical axes in the camera_link (x forward, y left, z up)
            np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-6)  # z forward
            np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-6)  # x right
            np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-6)  # y down
            np.testing.assert_allclose(joint.origin[:3, 3], 0.0)


@pytest.mark.parametrize("model_yaml", MODEL_YAMLS, ids=lambda p: p.stem)
def test_model_yaml_loads_and_names_existing_frames(model_yaml: Path) -> None:
    robot = parse_urdf(_urdf_for(model_yaml))
    cfg = load_model_config(str(model_yaml), robot)
    assert cfg.perturbations, "every example model perturbs something"
    links = set(robot.links)
    assert cfg.frames is not None and cfg.frames.base in links and cfg.frames.tool in links
    for name in list(cfg.perturbations) + list(cfg.joint_noise):
        assert name in robot.joints
    if cfg.camera is not None:
        assert cfg.camera.frame in links and cfg.camera.frame.endswith("optical_frame")
    if cfg.tags is not None:
        assert cfg.tags.family == "tag36h11"
        ids = [t.id for t in cfg.tags.items]
        assert len(ids) == len(set(ids)) and 2 <= len(ids) <= 4
        for tag in cfg.tags.items:
            assert tag.link in links and 0.03 <= tag.size <= 0.07
    if cfg.contact is not None:
        assert cfg.contact.plane_frame in links and cfg.contact.tool_link in links


@pytest.mark.parametrize("model_yaml", MODEL_YAMLS, ids=lambda p: p.stem)
def test_every_yaml_key_has_a_comment(model_yaml: Path) -> None:
    """Every line that opens a key (or a list entry) has a comment on it or on the line above."""
    lines = model_yaml.read_text().splitlines()
    for i, line in enumerate(lines):
        if not re.match(r"^\s*(- )?[\w{]", line) or line.strip().startswith("- ["):
            continue  # blank, comment, or a matrix row of a commented covariance
        above = lines[i - 1].strip() if i else ""
        assert "#" in line or above.startswith("#"), f"{model_yaml.name}:{i + 1}: {line.strip()!r} has no comment"


@pytest.mark.parametrize("name", ["rover", "arm7", "humanoid"])
def test_arm_links_carry_masses(name: str) -> None:
    robot = parse_urdf(str(CONFIG / f"{name}.urdf"))
    for joint in robot.joints.values():
        if joint.movable:
            inertial = robot.links[joint.child].inertial
            assert inertial is not None and inertial.mass > 0, f"{name}: link {joint.child} has no mass"


# --------------------------------------------------------------------------- planar3


def test_planar3_fk_matches_hand_computation() -> None:
    model = _model("planar3")
    q = np.array([0.3, -0.5, 0.9])
    T = model.fk_mean(dict(zip(["joint1", "joint2", "joint3"], q)), "base_link", "tool0")
    c = np.cumsum(q)
    np.testing.assert_allclose(T[:3, 3], [np.cos(c).sum(), np.sin(c).sum(), 0.0], atol=1e-12)
    np.testing.assert_allclose(
        T[:3, :3], [[np.cos(c[-1]), -np.sin(c[-1]), 0], [np.sin(c[-1]), np.cos(c[-1]), 0], [0, 0, 1]], atol=1e-12
    )


def test_planar3_perturbations_are_10_deg_about_the_joint_axes() -> None:
    cfg = _model("planar3").config
    for jn in ("joint1", "joint2", "joint3"):
        expected = np.zeros((6, 6))
        expected[5, 5] = (10 * DEG) ** 2
        np.testing.assert_allclose(cfg.perturbations[jn].covariance, expected, rtol=1e-6)
    assert list(_model("planar3", "planar3_joint1_model.yaml").config.perturbations) == ["joint1"]


def test_planar3_joint1_only_gives_rank1_tool_position_covariance() -> None:
    """Paper Fig. 3a: a perturbation on joint 1 only moves the tool on a circle: rank-1 position cov."""
    model = _model("planar3", "planar3_joint1_model.yaml")
    T, cov = model.fk({"joint1": 0.25, "joint2": 0.8, "joint3": 0.9}, "base_link", "tool0")
    cov_pos_base = T[:3, :3] @ cov[:3, :3] @ T[:3, :3].T
    w = np.linalg.eigvalsh(cov_pos_base)
    assert w[-1] > 1e-3 and w[-2] < 1e-12 * w[-1]
    # and the direction is tangent to the circle about the base origin
    v = np.linalg.eigh(cov_pos_base)[1][:, -1]
    assert abs(v @ T[:3, 3]) < 1e-9 * np.linalg.norm(T[:3, 3])


# --------------------------------------------------------------------------- rover

ROVER_STRETCHED = dict(
    pan_joint=2.53,
    tilt_joint=0.45,
    arm_joint_1=1.83,
    arm_joint_2=1.5,
    arm_joint_3=-0.1,
    arm_joint_4=-1.28,
    arm_joint_5=0.29,
    arm_joint_6=0.0,
)
ROVER_CLOSE = dict(
    pan_joint=-2.97,
    tilt_joint=0.65,
    arm_joint_1=0.37,
    arm_joint_2=-0.54,
    arm_joint_3=1.93,
    arm_joint_4=-0.72,
    arm_joint_5=1.39,
    arm_joint_6=0.0,
)


@pytest.mark.parametrize(
    ("q", "facing_ids"), [(ROVER_STRETCHED, {0, 3}), (ROVER_CLOSE, {1})], ids=["stretched", "close"]
)
def test_rover_example_configurations_show_tags_to_the_camera(q: dict, facing_ids: set) -> None:
    """config/README.md: at the example configurations these tags face the mast camera and are in the image."""
    model = _model("rover")
    cam = model.config.camera.frame
    f, w, h = 600.0, 1280, 960
    for tag in model.config.tags.items:
        T_cam_tag = model.fk_mean(q, cam, tag.link) @ tag.T_link_tag
        p, normal = T_cam_tag[:3, 3], T_cam_tag[:3, 2]
        facing = -normal @ p / np.linalg.norm(p)
        if tag.id in facing_ids:
            assert facing > 0.3, f"tag {tag.id} does not face the camera ({facing:.2f})"
            assert p[2] > 0.5
            u, v = f * p[0] / p[2] + w / 2, f * p[1] / p[2] + h / 2
            assert 0 < u < w and 0 < v < h


def test_rover_sigmas_are_the_papers() -> None:
    cfg = _model("rover").config
    np.testing.assert_allclose(
        np.sqrt(np.diag(cfg.perturbations["mount_joint"].covariance)), [0, 0, 0, 1 * DEG, 1 * DEG, 5 * DEG], rtol=1e-6
    )
    for i in range(1, 7):
        np.testing.assert_allclose(
            np.sqrt(np.diag(cfg.perturbations[f"arm_joint_{i}"].covariance))[3:], 0.5 * DEG, rtol=1e-5
        )
    np.testing.assert_allclose(
        np.sqrt(np.diag(cfg.naive.covariance)), [0.07, 0.07, 0.03, 5 * DEG, 5 * DEG, 15 * DEG], rtol=1e-6
    )
    assert cfg.camera.pixel_sigma == 0.5
    # reach of the arm from the shoulder (arm_joint_2) to the tool tip: about 0.9 m
    robot = model_robot = _model("rover").robot
    reach = sum(
        np.linalg.norm(robot.joints[j].origin[:3, 3])
        for j in ["arm_joint_3", "arm_joint_4", "arm_joint_5", "arm_joint_6", "tool_joint"]
    )
    assert 0.8 < reach < 1.0, model_robot.name


# --------------------------------------------------------------------------- humanoid

HUMANOID_TOUCH = dict(
    shoulder_pitch_joint=-0.5,
    shoulder_roll_joint=0.0,
    shoulder_yaw_joint=0.0,
    elbow_joint=-1.2,
    wrist_flex_joint=0.6,
    wrist_abduct_joint=0.0,
    index_mcp_joint=0.3,
    index_pip_joint=-0.2,
    index_dip_joint=-0.1,
)


def test_humanoid_table_plane_touches_fingertip_at_example_configuration() -> None:
    model = _model("humanoid")
    contact = model.config.contact
    T_base_plane = model.fk_mean(HUMANOID_TOUCH, "base_link", contact.plane_frame) @ contact.T_frame_plane
    T_base_tip = model.fk_mean(HUMANOID_TOUCH, "base_link", contact.tool_link)
    np.testing.assert_allclose(T_base_plane[:3, 2], [0, 0, 1], atol=1e-6)  # table normal = torso z
    np.testing.assert_allclose(T_base_plane[:3, 3], T_base_tip[:3, 3], atol=1e-5)
    assert T_base_tip[0, 3] > 0.3  # table in front of the torso
    # the head camera sees the contact point
    p = model.fk_mean(HUMANOID_TOUCH, model.config.camera.frame, contact.tool_link)[:3, 3]
    assert p[2] > 0.3 and abs(p[0] / p[2]) < 0.6 and abs(p[1] / p[2]) < 0.5


def test_humanoid_sigma_v_read_as_sigmas() -> None:
    cov = _model("humanoid").config.contact.covariance
    np.testing.assert_allclose(cov, np.diag(np.square([0.5, 0.5, 0.001, 0.017, 0.017, 0.17])))


def test_humanoid_chain_from_camera_runs_through_the_perturbed_neck() -> None:
    model = _model("humanoid")
    up, down = model.robot.chain("camera_optical_frame", "fingertip")
    assert "neck_joint" in up and "wrist_flex_joint" in down and "index_dip_joint" in down
    raw = yaml.safe_load((CONFIG / "humanoid_model.yaml").read_text())
    assert set(raw["joint_noise"]) == {"index_mcp_joint", "index_pip_joint", "index_dip_joint"}


# --------------------------------------------------------------------------- arm7


def test_arm7_is_a_7dof_chain_with_camera_and_mimic_gripper() -> None:
    model = _model("arm7")
    up, down = model.robot.chain("base_link", "tool0")
    movable = [j for j in down if model.robot.joints[j].movable]
    assert up == [] and len(movable) == 7 and "mount_joint" in down
    assert model.robot.joints["finger_right_joint"].mimic is not None
    T = model.fk_mean({f"joint_{i}": 0.0 for i in range(1, 8)}, "base_link", "tool0")
    np.testing.assert_allclose(T[:3, 3], [0, 0, 1.326], atol=1e-9)
    # README example: tool0 in front of the camera
    q = dict(joint_1=0.3, joint_2=0.6, joint_3=0.0, joint_4=-1.2, joint_5=0.0, joint_6=0.9, joint_7=0.0)
    p = model.fk_mean(q, "camera_optical_frame", "tool0")[:3, 3]
    assert p[2] > 0.5 and abs(p[0] / p[2]) < 0.5 and abs(p[1] / p[2]) < 0.4


@pytest.mark.parametrize("name", ["planar3", "rover", "humanoid", "arm7"])
def test_compiled_chains_equal_the_kinematic_tree(name: str) -> None:
    """PPOEModel's compiled chain programs give the nominal poses of robot.tree.KinematicTree (the one tree),
    for every link relative to the root and for an up/down chain between two leaves."""
    from ppoe_core.robot.tree import KinematicTree

    model = _model(name)
    tree = KinematicTree(model.robot)
    rng = np.random.default_rng(11)
    q = {j: rng.uniform(-1.0, 1.0, 5) for j in model.joint_names}
    poses = tree.link_poses(q)
    links = sorted(model.robot.links)
    for ln in links:
        T = np.broadcast_to(model.fk_mean(q, model.robot.root, ln), poses[ln].shape)
        np.testing.assert_allclose(T, poses[ln], atol=1e-12, err_msg=ln)
    a, b = links[0], links[-1]
    T_ab = np.linalg.inv(poses[a]) @ poses[b]
    np.testing.assert_allclose(model.fk_mean(q, a, b), T_ab, atol=1e-12)
