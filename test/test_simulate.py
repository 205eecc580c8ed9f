"""ppoe simulate: determinism, truth vs. the effects catalogue, sensors at the true pose, shipped bags."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import BAGS, CONFIG

from ppoe_core import lie
from ppoe_core.errors import ScenarioError
from ppoe_core.estimation import camera
from ppoe_core.io import bagio
from ppoe_core.model import effects
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf
from ppoe_core.sensing import tags
from ppoe_core.sim.simulate import TrueRobot, load_scenario, simulate

ARM7_START = {"joint_1": 0.3, "joint_2": 0.6, "joint_3": 0.0, "joint_4": -1.2, "joint_5": 0.0, "joint_6": 0.9,
              "joint_7": 0.0, "finger_left_joint": 0.02}


def _scenario(tmp_path: Path, name: str = "s.yaml", **over: object) -> Path:
    sc: dict = {
        "robot": {"urdf": str(CONFIG / "robots" / "arm7.urdf"), "model": str(CONFIG / "robots" / "arm7_model.yaml")},
        "seed": 5,
        "truth": {"perturbations": "once", "joint_noise": True, "effects": []},
        "trajectory": {"joint_rate": 100.0, "dwell": 0.3, "move_time": 0.3, "start": dict(ARM7_START),
                       "stops": [{"joints": {}}, {"joints": {"joint_1": 0.5, "joint_4": -1.0}},
                                 {"joints": {"joint_2": 0.4, "joint_6": 1.1}}]},
        "ground_truth": {"pose": {"sigma_xyz": 0.0001, "sigma_rot": 0.0002},
                         "point": {"T_tracker_base": {"xyz": [2.0, 1.0, 0.3], "rpy": [0.0, 0.0, 1.0]}}},
        "imus": {"rate": 0.0},
    }
    sc.update(over)
    p = tmp_path / name
    p.write_text(yaml.safe_dump(sc))
    return p


def _md5(bag: Path) -> str:
    return hashlib.md5(next(bag.glob("*.mcap")).read_bytes()).hexdigest()


def test_deterministic_for_a_seed(tmp_path: Path) -> None:
    sc = _scenario(tmp_path)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    simulate(sc, tmp_path / "a" / "bag")
    simulate(sc, tmp_path / "b" / "bag")
    assert _md5(tmp_path / "a" / "bag") == _md5(tmp_path / "b" / "bag")
    simulate(sc, tmp_path / "c", seed=6)
    a = bagio.read_bag(tmp_path / "a" / "bag")
    c = bagio.read_bag(tmp_path / "c")
    np.testing.assert_array_equal(a.joint_states.positions, c.joint_states.positions)  # same trajectory
    assert np.abs(a.ground_truth_pose.T - c.ground_truth_pose.T).max() > 1e-4          # other draws


def test_ground_truth_equals_nominal_fk_without_errors(tmp_path: Path) -> None:
    sc = _scenario(tmp_path, truth={"perturbations": "none", "joint_noise": False, "effects": []},
                   ground_truth={"pose": {"sigma_xyz": 0.0, "sigma_rot": 0.0},
                                 "point": {"sigma": 0.0, "frame": "laser",
                                           "T_tracker_base": {"xyz": [2.0, 1.0, 0.3], "rpy": [0.1, 0.0, 1.0]}}},
                   imus={"rate": 0.0, "sigma": 0.0})
    res = simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    assert res.n_stops == 3 and len(d.ground_truth_pose) == 3
    assert d.robot_description == (CONFIG / "robots" / "arm7.urdf").read_text()
    tree = KinematicTree(parse_urdf(d.robot_description))
    js = d.joint_states
    idx = np.searchsorted(js.stamps, d.ground_truth_pose.stamps, side="right") - 1
    q = {n: js.positions[idx, i] for i, n in enumerate(js.names)}
    poses = tree.link_poses(q)
    np.testing.assert_allclose(d.ground_truth_pose.T, poses["tool0"], atol=1e-9)
    assert d.ground_truth_pose.frame_ids == ["base_link"] * 3
    T_tb = lie.from_xyz_rpy([2.0, 1.0, 0.3], [0.1, 0.0, 1.0])
    p = (T_tb @ poses["tool0"] @ np.array([0, 0, 0.02, 1.0]))[:, :3]
    np.testing.assert_allclose(d.ground_truth_point.p, p, atol=1e-9)
    assert d.ground_truth_point.frame_ids == ["laser"] * 3
    # accelerometer at rest: +g along the root z, in the IMU link axes
    R = poses["arm_link_4"][:, :3, :3]
    np.testing.assert_allclose(d.imus["forearm"].linear_acceleration,
                               np.einsum("nji,j->ni", R, [0, 0, 9.80665]), atol=1e-9)
    # joint states: every stop inside a burst, >= 50 Hz
    assert d.rate("/joint_states") == pytest.approx(100.0)
    assert d.joint_states.names[:7] == [f"joint_{i}" for i in range(1, 8)]


ARM7 = parse_urdf(str(CONFIG / "robots" / "arm7.urdf"))


def test_recorded_draws_reproduce_the_ground_truth(tmp_path: Path) -> None:
    """With record_draws, the truth file's per-stop xi and joint errors give the ground truth exactly."""
    sc = _scenario(tmp_path, truth={"perturbations": "per_stop", "joint_noise": True, "record_draws": True,
                                    "effects": [{"name": "joint_offset", "location": "joint_2",
                                                 "parameters": {"offset": 0.01}}]},
                   ground_truth={"pose": {"sigma_xyz": 0.0, "sigma_rot": 0.0}}, imus=None)
    res = simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    draws = res.truth["stop_draws"]
    assert len(draws) == 3
    true = TrueRobot(ARM7, res.truth["effects"])
    js = d.joint_states
    for k, st in enumerate(draws):
        t = d.ground_truth_pose.stamps[k]
        assert st["start"] <= t <= st["end"]
        i = int(np.searchsorted(js.stamps, t, side="right") - 1)
        q = {n: js.positions[i:i + 1, j] for j, n in enumerate(js.names)}
        xi = {j: np.array([v]) for j, v in st["xi"].items()}
        noise = {j: np.array([v]) for j, v in st["joint_noise"].items()}
        P = true.poses(q, xi, noise, {}, np.zeros(1), 1)
        np.testing.assert_allclose(P["tool0"][0], d.ground_truth_pose.T[k], atol=1e-9)
    assert draws[0]["xi"]["mount_joint"] != draws[1]["xi"]["mount_joint"]


@pytest.mark.parametrize("entry", [
    {"name": "joint_offset", "location": "joint_2", "parameters": {"offset": 0.02}},
    {"name": "gravity_compliance", "location": "joint_2", "parameters": {"compliance": 3e-4}},
    {"name": "gravity_compliance", "location": "joint_4", "parameters": {"compliance": 5e-4}},
    {"name": "mount_bending", "location": "mount_joint", "parameters": {"compliance_x": 2e-4, "compliance_y": 1e-4}},
    {"name": "link_error", "location": "joint_3", "parameters": {"x": 0.002, "rz": 0.004}},
    {"name": "camera_extrinsics", "location": "camera_joint", "parameters": {"y": 0.01, "rx": 0.01}},
    {"name": "base_tilt", "location": "base_link", "parameters": {"tilt_x": 0.01, "tilt_y": -0.02}},
])
def test_true_effects_match_the_catalogue(entry: dict) -> None:
    """The simulator's physics (own code) agrees with ppoe_core.model.effects' parametrisation."""
    rng = np.random.default_rng(2)
    n = 7
    q = {j: rng.uniform(-1.2, 1.2, n) for j in ARM7.independent_joints}
    true = TrueRobot(ARM7, [entry])
    P_true = true.poses(q, {}, {}, {}, np.zeros(n), n)
    tree = KinematicTree(ARM7)
    eff = effects.effect_from_config(entry, tree)
    dq, dxi = eff.corrections(q, {})
    P_cat = tree.link_poses(q, dq, dxi)
    for link in ("tool0", "camera_optical_frame", "arm_link_4"):
        np.testing.assert_allclose(P_true[link], P_cat[link], atol=1e-12)
    # and the effect is not nothing
    P0 = tree.link_poses(q)
    cam = "camera_optical_frame"
    moved = np.abs(P_true["tool0"] - P0["tool0"]).max() + np.abs(P_true[cam] - P0[cam]).max()
    assert moved > 1e-3


def test_backlash_and_thermal_growth_match_the_catalogue() -> None:
    n = 4
    q = {j: np.linspace(-0.5, 0.5, n) for j in ARM7.independent_joints}
    sign = {"joint_3": np.array([1.0, -1.0, 1.0, 0.0])}
    t = np.array([0.0, 10.0, 100.0, 1000.0])
    entries = [
        {"name": "backlash", "location": "joint_3", "parameters": {"play": 0.003}},
        {"name": "thermal_growth", "location": "joint_4", "parameters": {"alpha": 2e-5}},
    ]
    P_true = TrueRobot(ARM7, entries).poses(q, {}, {}, sign, t, n)
    tree = KinematicTree(ARM7)
    effs = [
        effects.effect_from_config(entries[0], tree),
        effects.effect_from_config({**entries[1], "variable": "time", "reference": 0.0}, tree),
    ]
    dq, dxi = effects.sum_effect_corrections(effs, q, {"motion_sign": sign, "time": t})
    np.testing.assert_allclose(P_true["tool0"], tree.link_poses(q, dq, dxi)["tool0"], atol=1e-12)


def test_tags_rendered_at_true_pose_with_camera_error(tmp_path: Path) -> None:
    cam_err = {"name": "camera_extrinsics", "location": "camera_joint", "parameters": {"x": 0.01, "ry": 0.01}}
    sc = _scenario(
        tmp_path,
        truth={"perturbations": "none", "joint_noise": False, "effects": [cam_err]},
        camera={
            "width": 640,
            "height": 480,
            "intrinsics": [700, 700, 320, 240],
            "D": [-0.05, 0.02, 0, 0, 0],
            "rate": 1.0,
            "noise_sigma": 1.0,
        },
        ground_truth=None,
        imus=None,
    )
    sc_text = yaml.safe_load(sc.read_text())
    sc_text["trajectory"]["stops"] = [{"joints": {}}, {"joints": {"joint_1": 0.35}}]
    sc.write_text(yaml.safe_dump(sc_text))
    res = simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    assert len(d.images) == 2 and len(d.camera_info) == 2
    np.testing.assert_array_equal(d.images.stamps, d.camera_info.stamps)
    scen = load_scenario(sc)
    model = scen.model
    js = d.joint_states
    true = TrueRobot(scen.robot, [cam_err])
    tree = KinematicTree(scen.robot)
    errs_true, errs_nominal, n_det = [], [], 0
    for i in range(len(d.images)):
        k = int(np.searchsorted(js.stamps, d.images.stamps[i], side="right") - 1)
        q = {n: js.positions[k : k + 1, j] for j, n in enumerate(js.names)}
        det = {t.id: t for t in tags.detect_tags(d.images.decode(i))}
        n_det += len(det)
        for P, errs in ((true.poses(q, {}, {}, {}, np.zeros(1), 1), errs_true), (tree.link_poses(q), errs_nominal)):
            T_cam = lie.inverse(P["camera_optical_frame"][0])
            for item in model.tags.items:
                if item.id in det:
                    T = T_cam @ P[item.link][0] @ item.T_link_tag
                    pts = tags.tag_points_local(item.size) @ T[:3, :3].T + T[:3, 3]
                    uv = camera.project_points(pts, d.camera_info.K[i], d.camera_info.D[i])
                    errs.append(np.abs(det[item.id].corners - uv[1:]).max())
    assert n_det >= 2 and res.visible_tags
    # tags drawn at the true pose (corners of ~20 px tags found to a fraction of a pixel)
    assert max(errs_true) < 0.5
    assert min(errs_nominal) > 3.0  # and the camera error is visible against the nominal one


def test_raw_blurred_images_with_camera_time_offset(tmp_path: Path) -> None:
    sc = _scenario(
        tmp_path,
        truth={"perturbations": "none", "joint_noise": False, "effects": []},
        camera={
            "width": 640,
            "height": 480,
            "intrinsics": [700, 700, 320, 240],
            "rate": 1.0,
            "format": "raw",
            "blur_sigma": 0.7,
            "noise_sigma": 0.0,
            "time_offset": 0.004,
        },
        ground_truth={"pose": {"sigma_xyz": 0.0, "sigma_rot": 0.0}},
        imus=None,
    )
    simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    assert d.images.topic == "/camera/image_raw" and set(d.images.formats) == {"mono8"}
    img = d.images.decode(0)
    assert img.shape == (480, 640)
    assert tags.detect_tags(img)  # still detectable when blurred
    # blur: no pixel jumps by more than the blurred edge allows (sharp renders jump by ~200)
    assert np.abs(np.diff(img.astype(int), axis=1)).max() < 140
    # images stamped 4 ms after the ground truth taken at the same instant
    np.testing.assert_allclose(d.images.stamps - d.ground_truth_pose.stamps, 0.004, atol=1e-9)


def test_time_offset_and_smooth_motion(tmp_path: Path) -> None:
    dt = 0.05
    sc = _scenario(
        tmp_path,
        truth={
            "perturbations": "none",
            "joint_noise": False,
            "effects": [{"name": "time_offset", "location": "/joint_states", "parameters": {"dt": dt}}],
        },
        trajectory={
            "joint_rate": 200.0,
            "start": dict(ARM7_START),
            "smooth": {"duration": 2.0, "amplitude": {"joint_1": 0.4}, "period": {"joint_1": 2.0}},
        },
        ground_truth={"pose": {"sigma_xyz": 0.0, "sigma_rot": 0.0, "rate": 50.0}},
        imus=None,
    )
    simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    js = d.joint_states
    assert d.rate("/joint_states") == pytest.approx(200.0) and d.rate("/ground_truth/pose") == pytest.approx(50.0)
    t = js.stamps - js.stamps[0]
    np.testing.assert_allclose(js.column("joint_1"), 0.3 + 0.4 * np.sin(2 * np.pi * (t - dt) / 2.0), atol=1e-9)


def test_contact_wrench_reaches_the_commanded_force(tmp_path: Path) -> None:
    sc = {
        "robot": {
            "urdf": str(CONFIG / "robots" / "humanoid.urdf"),
            "model": str(CONFIG / "robots" / "humanoid_model.yaml"),
        },
        "seed": 3,
        "truth": {"perturbations": "once"},
        "trajectory": {
            "start": {
                "shoulder_pitch_joint": -0.5,
                "elbow_joint": -1.2,
                "wrist_flex_joint": 0.6,
                "index_mcp_joint": 0.3,
                "index_pip_joint": -0.2,
                "index_dip_joint": -0.1,
            },
            "dwell": 0.5,
            "move_time": 0.5,
            "stops": [
                {"joints": {"shoulder_pitch_joint": -0.8}},
                {"joints": {}, "contact": {"press_joint": "shoulder_pitch_joint", "force": 12.0}},
            ],
        },
        "contact": {"stiffness": 1e5, "force_sigma": 0.0},
    }
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(sc))
    simulate(p, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    f = np.linalg.norm(d.wrench.force, axis=1)
    assert f.max() == pytest.approx(12.0, abs=1e-3)
    assert f[0] == 0.0  # free at the start
    assert d.rate("/wrench") == pytest.approx(100.0)


def test_scenario_file_that_is_not_text(tmp_path: Path) -> None:
    sc = tmp_path / "binary.yaml"
    sc.write_bytes(b"\xff\xfe\x00robot")
    with pytest.raises(ScenarioError, match=r"binary.yaml: scenario is not UTF-8 text"):
        simulate(sc, tmp_path / "bag")


@pytest.mark.parametrize(
    "patch,match",
    [
        ({"bogus": 1}, r"unknown keys \['bogus'\]"),
        ({"truth": {"effects": [{"name": "wobble", "location": "joint_2"}]}}, "unknown effect 'wobble'"),
        (
            {"truth": {"effects": [{"name": "joint_offset", "location": "mount_joint", "parameters": {"offset": 1}}]}},
            "needs a movable joint",
        ),
        ({"trajectory": {"joint_rate": 20.0, "stops": [{"joints": {}}]}}, r"joint_rate = 20.0 out of range"),
        ({"trajectory": {"stops": [{"joints": {"nojoint": 1.0}}]}}, "'nojoint' is not a movable joint"),
        ({"trajectory": {"stops": [{"joints": {"joint_2": float("nan")}}]}}, r"joints.joint_2 must be finite"),
        ({"camera": {"rate": 60.0}}, r"camera.rate = 60.0 out of range"),
    ],
)
def test_scenario_errors_name_file_and_key(tmp_path: Path, patch: dict, match: str) -> None:
    sc = _scenario(tmp_path, **patch)
    with pytest.raises(ScenarioError, match=match) as exc:
        simulate(sc, tmp_path / "bag")
    assert str(sc) in str(exc.value)


def test_cli_writes_bag_and_truth(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from ppoe_ros.cli import main

    sc = _scenario(
        tmp_path,
        truth={
            "perturbations": "once",
            "effects": [{"name": "joint_offset", "location": "joint_2", "parameters": {"offset": 0.01}}],
        },
    )
    assert main(["simulate", str(sc), "--out", str(tmp_path / "bag"), "--seed", "9", "--json"]) == 0
    out = yaml.safe_load(capsys.readouterr().out)
    assert out["counts"]["/ground_truth/pose"] == 3
    truth = yaml.safe_load((tmp_path / "bag.truth.yaml").read_text())
    assert truth["seed"] == 9 and truth["effects"][0]["parameters"]["offset"] == 0.01
    assert main(["simulate", str(sc), "--out", str(tmp_path / "bag")]) == 2  # exists, no --force


# ------------------------------------------------------------------ camera and tag truths, encoder noise

#: a camera scenario of arm7 whose stops show the gripper tags (as bags/effect_camera_extrinsics.yaml)
_CAM_STOPS = {"count": 4, "around": {"joint_1": 0.0, "joint_2": 0.0, "joint_3": 0.0, "joint_4": -1.0, "joint_5": 0.0,
                                     "joint_6": 0.5, "joint_7": 0.0},
              "spread": {"joint_1": 1.0, "joint_2": 0.8, "joint_4": 0.6, "joint_6": 0.8, "joint_7": 1.5},
              "min_visible_tags": 1, "min_link_z": {"tool0": 0.15}, "max_tries": 20000}
_K_DECL = [700.0, 700.0, 320.0, 240.0]
_D_DECL = [-0.05, 0.02, 0.0, 0.0, 0.0]


def _camera_scenario(tmp_path: Path, effects_: list, fmt: str = "observations", **cam: object) -> Path:
    return _scenario(tmp_path, truth={"perturbations": "none", "joint_noise": False, "effects": effects_},
                     trajectory={"joint_rate": 100.0, "dwell": 0.3, "move_time": 0.3, "start": dict(ARM7_START),
                                 "random_stops": dict(_CAM_STOPS)},
                     camera={"width": 640, "height": 480, "intrinsics": _K_DECL, "D": _D_DECL, "rate": 2.0,
                             "format": fmt, "pixel_sigma": 0.0, **cam},
                     ground_truth=None, imus=None)


def _cv_project(P_cam: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """OpenCV's own projection (independent of ppoe_core.estimation.camera)."""
    import cv2

    uv, _ = cv2.projectPoints(P_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    return uv.reshape(-1, 2)


def _expm_twist(xi: np.ndarray) -> np.ndarray:
    """Exp of a twist [rho; theta] by the matrix exponential (independent of ppoe_core.lie)."""
    from scipy.linalg import expm

    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
    X[:3, 3] = xi[:3]
    return expm(X)


def _observed_corners(tmp_path: Path, sc: Path, offsets: dict[int, np.ndarray], K: np.ndarray, D: np.ndarray
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(observed corner pixels, OpenCV projection of the tag corners on the nominal robot with the tag mounts
    times ``offsets`` through K, D) per observed tag of the bag ``tmp_path / "bag"`` made from ``sc``."""
    d = bagio.read_bag(tmp_path / "bag")
    scen = load_scenario(sc)
    items = {it.id: it for it in scen.model.tags.items}
    tree = KinematicTree(scen.robot)
    js, obs = d.joint_states, d.tag_observations
    out = []
    for i in range(len(obs)):
        m = obs.message(i)
        k = int(np.searchsorted(js.stamps, obs.stamps[i], side="right") - 1)
        P = tree.link_poses({n: js.positions[k, j] for j, n in enumerate(js.names)})
        for tid in np.unique(m["ids"]):
            it = items[int(tid)]
            T = np.linalg.inv(P["camera_optical_frame"]) @ P[it.link] @ it.T_link_tag @ offsets.get(int(tid), np.eye(4))
            pts = tags.tag_points_local(it.size)[1:] @ T[:3, :3].T + T[:3, 3]
            sel = (m["ids"] == tid) & (m["corners"] > 0)
            out.append((m["uv"][sel][np.argsort(m["corners"][sel])], _cv_project(pts, K, D)))
    assert out, "no tag observed"
    return out


def test_camera_intrinsics_truth_projects_through_the_true_camera(tmp_path: Path) -> None:
    """Observations are the corners through the TRUE camera (declared + the effect), checked with OpenCV's own
    projection; camera_info carries the declared camera; x, y are undistorted with the declared one."""
    import cv2

    delta = {"fx": 12.0, "fy": 9.0, "cx": -7.0, "cy": 5.0, "k1": 0.04, "p2": 0.001}
    sc = _camera_scenario(tmp_path, [{"name": "camera_intrinsics", "location": "camera_optical_frame",
                                      "parameters": delta}])
    truth = simulate(sc, tmp_path / "bag").truth
    K_true = np.array([[700.0 + 12, 0, 320.0 - 7], [0, 700.0 + 9, 240.0 + 5], [0, 0, 1]])
    D_true = np.array([-0.05 + 0.04, 0.02, 0.0, 0.001, 0.0])
    for uv, uv_true in _observed_corners(tmp_path, sc, {}, K_true, D_true):
        np.testing.assert_allclose(uv, uv_true, atol=1e-6)
    d = bagio.read_bag(tmp_path / "bag")
    K_decl = np.array([[700.0, 0, 320.0], [0, 700.0, 240.0], [0, 0, 1]])
    # the error is visible: through the declared camera the corners miss by pixels
    assert min(np.abs(uv - uv_decl).max() for uv, uv_decl in _observed_corners(tmp_path, sc, {}, K_decl,
                                                                              np.array(_D_DECL))) > 2.0
    np.testing.assert_allclose(d.camera_info.K[0], K_decl)
    np.testing.assert_allclose(d.camera_info.D[0], _D_DECL)
    m = d.tag_observations.message(0)
    xy = cv2.undistortPoints(m["uv"].reshape(-1, 1, 2), K_decl, np.array(_D_DECL),
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    corner = m["corners"] > 0
    np.testing.assert_allclose(m["xy"][corner], xy[corner], atol=1e-9)
    np.testing.assert_allclose(truth["camera"]["K_true"], K_true)
    np.testing.assert_allclose(truth["camera"]["D_true"], D_true)


def test_rendered_images_use_the_true_intrinsics(tmp_path: Path) -> None:
    """Tags detected in the rendered images sit at the projection through the TRUE camera (< 0.5 px), not the
    declared one (> 3 px off)."""
    delta = {"fx": 15.0, "cx": -9.0, "cy": 6.0, "k1": 0.05}
    sc = _camera_scenario(tmp_path, [{"name": "camera_intrinsics", "location": "camera_optical_frame",
                                      "parameters": delta}], fmt="png", noise_sigma=1.0)
    simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    scen = load_scenario(sc)
    tree = KinematicTree(scen.robot)
    K_true = np.array([[715.0, 0, 311.0], [0, 700.0, 246.0], [0, 0, 1]])
    D_true = np.array([0.0, 0.02, 0.0, 0.0, 0.0])
    err_true, err_decl = [], []
    for i in range(len(d.images)):
        k = int(np.searchsorted(d.joint_states.stamps, d.images.stamps[i], side="right") - 1)
        P = tree.link_poses({n: d.joint_states.positions[k, j] for j, n in enumerate(d.joint_states.names)})
        for det in tags.detect_tags(d.images.decode(i)):
            it = next(t for t in scen.model.tags.items if t.id == det.id)
            T = np.linalg.inv(P["camera_optical_frame"]) @ P[it.link] @ it.T_link_tag
            pts = tags.tag_points_local(it.size)[1:] @ T[:3, :3].T + T[:3, 3]
            err_true.append(np.abs(det.corners - _cv_project(pts, K_true, D_true)).max())
            err_decl.append(np.abs(det.corners - _cv_project(pts, d.camera_info.K[i], d.camera_info.D[i])).max())
    assert err_true and max(err_true) < 0.5 and min(err_decl) > 3.0, (err_true, err_decl)


def test_tag_offset_truth_moves_that_tag_only(tmp_path: Path) -> None:
    """tag_offset at tag_11: its corners are those of the model's mount times Exp([x y z rx ry rz]) (a matrix
    exponential here); tag 10 stays where the model says."""
    xi = np.array([0.003, -0.002, 0.001, 0.0, 0.02, 0.05])
    sc = _camera_scenario(tmp_path, [{"name": "tag_offset", "location": 11, "parameters": dict(
        zip(("x", "y", "z", "rx", "ry", "rz"), xi.tolist()))}])
    truth = simulate(sc, tmp_path / "bag").truth
    K, D = np.array([[700.0, 0, 320.0], [0, 700.0, 240.0], [0, 0, 1]]), np.array(_D_DECL)
    for uv, uv_true in _observed_corners(tmp_path, sc, {11: _expm_twist(xi)}, K, D):
        np.testing.assert_allclose(uv, uv_true, atol=1e-6)
    # tag 11 seen, and off its declared mount by pixels (tag 10 where declared)
    moved = [np.abs(uv - uv_decl).max() for uv, uv_decl in _observed_corners(tmp_path, sc, {}, K, D)]
    obs = bagio.read_bag(tmp_path / "bag").tag_observations
    ids = [int(i) for i in obs.ids[obs.corners == 1]]
    assert 11 in ids and all((m > 1.0) == (i == 11) for m, i in zip(moved, ids)), (moved, ids)
    assert truth["effects"][0]["location"] == "tag_11"


@pytest.mark.parametrize("entry,match", [
    ({"name": "camera_intrinsics", "location": "camera_optical_frame", "parameters": {"fx": 1.0}},
     "needs the scenario camera"),
    ({"name": "camera_intrinsics", "location": "nolink", "parameters": {"fx": 1.0}}, "is not a link"),
    ({"name": "tag_offset", "location": "tag_99", "parameters": {"x": 0.001}}, "the model .* has the tags"),
    ({"name": "tag_offset", "location": "gripper", "parameters": {"x": 0.001}}, "tag_<id> or the tag id"),
    ({"name": "tag_offset", "location": "tag_10", "parameters": {"x": {"step": {"at": 1, "before": 0, "after": 1}}}},
     "cannot change during the recording"),
])
def test_camera_and_tag_truth_errors_name_the_entry(tmp_path: Path, entry: dict, match: str) -> None:
    sc = _scenario(tmp_path, truth={"perturbations": "none", "effects": [entry]}, ground_truth=None, imus=None)
    with pytest.raises(ScenarioError, match=match) as exc:
        simulate(sc, tmp_path / "bag")
    assert "truth.effects[0]" in str(exc.value)


def test_encoder_noise_jitters_the_joint_states_not_the_robot(tmp_path: Path) -> None:
    """White noise on every /joint_states sample (at rest too); the ground truth is the commanded pose."""
    sc = _scenario(tmp_path, truth={"perturbations": "none", "joint_noise": False,
                                    "encoder_noise": {"joint_2": 0.001, "joint_5": 0.0005}, "effects": []},
                   trajectory={"joint_rate": 100.0, "dwell": 2.0, "start": dict(ARM7_START), "stops": [{"joints": {}}]},
                   ground_truth={"pose": {"sigma_xyz": 0.0, "sigma_rot": 0.0}}, imus=None)
    simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    js = d.joint_states
    for j, sig in (("joint_2", 0.001), ("joint_5", 0.0005), ("joint_1", 0.0)):
        dev = js.column(j) - ARM7_START[j]
        assert abs(dev.mean()) < 4 * sig / np.sqrt(len(dev)) + 1e-12
        assert np.std(dev) == pytest.approx(sig, rel=0.2, abs=1e-12)
    P = KinematicTree(ARM7).link_poses({j: np.array(v) for j, v in ARM7_START.items()})
    np.testing.assert_allclose(d.ground_truth_pose.T[0], P["tool0"], atol=1e-12)


def test_the_tracker_measures_while_moving(tmp_path: Path) -> None:
    """ground_truth.point.during: always: points at the given rate through the moves, each at the true pose of
    that instant (the commanded joints, interpolated)."""
    sc = _scenario(tmp_path, truth={"perturbations": "none", "joint_noise": False, "effects": []},
                   ground_truth={"point": {"sigma": 0.0, "rate": 20.0, "during": "always"}}, imus=None)
    simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    pts, js = d.ground_truth_point, d.joint_states
    assert d.rate("/ground_truth/point") == pytest.approx(20.0)
    moving = [np.ptp(js.positions[np.abs(js.stamps - t) < 0.02, :7], axis=0).max() > 1e-6 for t in pts.stamps]
    assert sum(moving) >= 5
    q = {n: np.interp(pts.stamps, js.stamps, js.positions[:, j]) for j, n in enumerate(js.names)}
    p = (KinematicTree(ARM7).link_poses(q)["tool0"] @ np.array([0, 0, 0.02, 1.0]))[:, :3]  # identity registration
    np.testing.assert_allclose(pts.p, p, atol=1e-9)


def test_a_scenario_extends_a_base_and_builds_its_robot_from_dh(tmp_path: Path) -> None:
    """`extends`: mappings merged, lists replaced, the base's paths relative to the base; `robot.dh`: the URDF of
    `ppoe urdf from-dh` goes to /robot_description; scenario_files lists what a bag depends on."""
    from ppoe_core.robot.dh import dh_to_urdf
    from ppoe_core.sim.scenario import scenario_files

    base_dir, robots = tmp_path / "base", tmp_path / "robots"
    base_dir.mkdir()
    robots.mkdir()
    dh, model = robots / "r_dh.yaml", robots / "r_model.yaml"
    dh.write_text((CONFIG / "robots" / "ind6_dh.yaml").read_text())
    model.write_text((CONFIG / "robots" / "ind6_model.yaml").read_text())
    (base_dir / "_b.yaml").write_text(yaml.safe_dump({
        "robot": {"dh": "../robots/r_dh.yaml", "model": "../robots/r_model.yaml"},
        "seed": 3, "truth": {"perturbations": "none", "joint_noise": False, "effects": [
            {"name": "joint_offset", "location": "joint_2", "parameters": {"offset": 0.1}}]},
        "trajectory": {"joint_rate": 50.0, "dwell": 0.2, "move_time": 0.2, "stops": [{"joints": {}},
                                                                                     {"joints": {"joint_2": 0.3}}]},
        "ground_truth": {"point": {"sigma": 0.0}}}))
    child = tmp_path / "c.yaml"
    child.write_text(yaml.safe_dump({"extends": "base/_b.yaml", "seed": 4, "truth": {"effects": []},
                                     "trajectory": {"stops": [{"joints": {"joint_3": 0.2}}]}}))
    sc = load_scenario(child)
    assert sc.seed == 4 and sc.raw["truth"] == {"perturbations": "none", "joint_noise": False, "effects": []}
    assert sc.raw["trajectory"]["joint_rate"] == 50.0 and len(sc.raw["trajectory"]["stops"]) == 1
    assert sc.urdf_text == dh_to_urdf(dh) and sc.robot.root == "world"
    res = simulate(child, tmp_path / "bag")
    assert res.n_stops == 1 and bagio.read_bag(tmp_path / "bag").robot_description == sc.urdf_text
    assert scenario_files(child) == [child.resolve(), (base_dir / "_b.yaml").resolve(), dh.resolve(), model.resolve()]
    child.write_text(yaml.safe_dump({"extends": "c.yaml"}))
    with pytest.raises(ScenarioError, match="extends: more than 8 levels"):
        load_scenario(child)


# ------------------------------------------------------------------ shipped bags
SHIPPED = [
    "table1_exp1",
    "table1_exp2",
    "contact",
    "no_effect",
    "effect_joint_offset",
    "effect_gravity_compliance",
    "effect_mount_bending",
    "effect_unexplained",
    "effect_camera_extrinsics",
]
#: least fraction of a bag's images with a detected tag
MIN_DETECTED = {"table1_exp1": 1.0, "table1_exp2": 1.0, "effect_camera_extrinsics": 0.8}


def test_shipped_bags_total_size() -> None:
    total = sum(f.stat().st_size for name in SHIPPED for f in (BAGS / name).rglob("*") if f.is_file())
    assert total < 40e6


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_bag_follows_the_contract(name: str) -> None:
    path = BAGS / name
    first = next(bagio.iter_raw(path))
    assert first.topic == "/robot_description"
    d = bagio.read_bag(path)
    assert d.unknown_topics == {}
    for topic, (msgtype, _) in d.topics.items():
        expected = bagio.CONTRACT_TYPES.get(topic, "sensor_msgs/msg/Imu" if topic.startswith("/imu/") else None)
        assert msgtype == expected, topic
    robot = parse_urdf(d.require_robot_description())
    assert set(robot.independent_joints) <= set(d.joint_states.names)
    assert not np.isnan(d.joint_states.positions).any()
    assert d.rate("/joint_states") >= 50.0
    assert np.all(np.diff(d.joint_states.stamps) > 0)
    truth = yaml.safe_load((BAGS / f"{name}.truth.yaml").read_text())
    scen = yaml.safe_load((BAGS / f"{name}.yaml").read_text())
    assert truth["effects"] == [
        dict(e, parameters={**dict.fromkeys(e["parameters"], 0.0), **e["parameters"]}) for e in truth["effects"]
    ]  # plain mapping
    assert [e["name"] for e in truth["effects"]] == [e["name"] for e in scen["truth"]["effects"]]
    if len(d.images):
        assert d.rate(d.images.topic) <= 30.0
        np.testing.assert_array_equal(d.images.stamps, d.camera_info.stamps)  # camera_info with each image
        assert set(d.images.formats) == {"png"}
        detected = [bool(tags.detect_tags(d.images.decode(i))) for i in range(len(d.images))]
        assert np.mean(detected) >= MIN_DETECTED[name], detected
    if len(d.ground_truth_pose):
        # every stop's ground truth is stamped inside a joint-state burst
        gaps = np.min(np.abs(d.joint_states.stamps[None, :] - d.ground_truth_pose.stamps[:, None]), axis=1)
        assert gaps.max() < 0.011


# candidate effects for the identifiability check of the shipped arm7 bags
_CANDIDATES = [
    ("joint_offset", "joint_2"),
    ("gravity_compliance", "joint_2"),
    ("mount_bending", "mount_joint"),
    ("joint_offset", "joint_3"),
    ("gravity_compliance", "joint_4"),
    ("joint_offset", "joint_4"),
]


def _gls_fits(name: str) -> tuple[float, dict]:
    """Single-effect GLS fits of tool positions (ground truth vs nominal FK, weighted by the PPOE covariance)."""
    from ppoe_core.model.ppoe import PPOEModel

    d = bagio.read_bag(BAGS / name, load_images=False)
    m = PPOEModel.from_files(str(CONFIG / "robots" / "arm7.urdf"), str(CONFIG / "robots" / "arm7_model.yaml"))
    js, gt = d.joint_states, d.ground_truth_pose
    idx = np.searchsorted(js.stamps, gt.stamps, side="right") - 1
    q = {n: js.positions[idx, i] for i, n in enumerate(js.names)}
    T, cov = m.fk(q, "base_link", "tool0")
    R = T[:, :3, :3]
    W = np.linalg.inv(R @ cov[:, :3, :3] @ np.swapaxes(R, 1, 2) + 1e-8 * np.eye(3))  # + tracker noise
    r = gt.T[:, :3, 3] - T[:, :3, 3]
    chi0 = np.einsum("ni,nij,nj->", r, W, r)
    tree = KinematicTree(m.robot)
    fits = {}
    for nm, loc in _CANDIDATES:
        J = effects.make_effect(nm, loc, tree).point_jacobian(q, "tool0", np.zeros(3))
        A = np.einsum("nip,nij,njq->pq", J, W, J)
        x = np.linalg.solve(A, np.einsum("nip,nij,nj->p", J, W, r))
        rr = r - np.einsum("nip,p->ni", J, x)
        fits[(nm, loc)] = (x, np.sqrt(np.diag(np.linalg.inv(A))), chi0 - np.einsum("ni,nij,nj->", rr, W, rr))
    return chi0 / r.size, fits


@pytest.mark.parametrize("name", ["effect_joint_offset", "effect_gravity_compliance", "effect_mount_bending"])
def test_shipped_effect_bags_are_identifiable(name: str) -> None:
    """The bag's true effect is the best single candidate, and a GLS fit recovers it within 3 sigma."""
    truth = yaml.safe_load((BAGS / f"{name}.truth.yaml").read_text())["effects"][0]
    _, fits = _gls_fits(name)
    key = (truth["name"], truth["location"])
    best = max(fits, key=lambda k: fits[k][2])
    assert best == key, {k: round(v[2], 1) for k, v in fits.items()}
    x, sd, gain = fits[key]
    true = np.array(list(truth["parameters"].values()))
    assert np.all(np.abs(x - true) < 3 * sd), (x, sd, true)
    assert gain > 50.0


def test_shipped_no_effect_bag_is_consistent() -> None:
    chi2_per_dof, fits = _gls_fits("no_effect")
    assert chi2_per_dof < 1.5
    assert max(f[2] for f in fits.values()) < 16.0  # no candidate explains much (max of 6 tests)


# ------------------------------------------------------------------ a diagnosis against the truth (sim.verdict)


def _doc(*effects_: tuple) -> dict:
    return {"effects": [{"name": n, "location": loc, "parameters": {k: v[0] for k, v in p.items()},
                         "ci": {k: [v[1], v[2]] for k, v in p.items()}} for n, loc, p in effects_]}


def test_judge_names_missing_extra_and_parameters_outside_their_ci() -> None:
    from ppoe_core.sim.verdict import judge

    truth = {"effects": [{"name": "joint_offset", "location": "joint_2", "parameters": {"offset": 0.01}},
                         {"name": "transmission_error", "location": "joint_3",
                          "parameters": {"amplitude": 0.001, "periods": 3}}]}
    ok = judge(truth, _doc(("joint_offset", "joint_2", {"offset": (0.0101, 0.0098, 0.0104)}),
                           ("tracker_registration", "/ground_truth/point", {"x": (0.1, 0.0, 0.2)})))
    assert ok.exact and ok.expected == ["joint_offset@joint_2"] and ok.reported == ["joint_offset@joint_2"]
    bad = judge(truth, _doc(("joint_offset", "joint_2", {"offset": (0.0105, 0.0102, 0.0108)}),
                            ("joint_offset", "joint_3", {"offset": (0.001, 0.0, 0.002)})))
    assert bad.named and not bad.exact and bad.extra == ["joint_offset@joint_3"]
    assert bad.out_of_ci == ["joint_offset@joint_2.offset: truth 0.01 not in [0.0102, 0.0108]"]
    assert judge(truth, _doc(("joint_offset", "joint_3", {"offset": (0.001, 0.0, 0.002)})),
                 allowed_extra=["joint_offset@joint_3"]).missing == ["joint_offset@joint_2"]
    # a reported parameter the truth does not have must cover 0; a true one not reported is missing
    le = {"effects": [{"name": "link_error", "location": "joint_4", "parameters": {"x": 0.001, "y": 0.0}}]}
    v = judge(le, _doc(("link_error", "joint_4", {"y": (0.0, -1e-4, 1e-4), "rz": (2e-4, 1e-4, 3e-4)})))
    assert v.out_of_ci == ["link_error@joint_4.rz: truth 0 not in [0.0001, 0.0003]",
                           "link_error@joint_4.x: truth 0.001 not reported"]


def test_judge_reads_intrinsics_as_changes_or_absolute_and_tags_by_id() -> None:
    from ppoe_core.sim.verdict import judge

    truth = {"effects": [{"name": "camera_intrinsics", "location": "cam", "parameters": {"fx": 8.0, "cx": -5.0}},
                         {"name": "tag_offset", "location": "tag_7", "parameters": {"x": 0.002}}],
             "camera": {"K_true": [[708.0, 0, 315.0], [0, 700.0, 240.0], [0, 0, 1]], "D_true": [0.0] * 5}}
    tag = ("tag_offset", "7", {"x": (0.002, 0.0019, 0.0021)})
    delta = _doc(("camera_intrinsics", "cam", {"fx": (8.1, 7.0, 9.0), "cx": (-5.2, -6.0, -4.0)}), tag)
    absolute = _doc(("camera_intrinsics", "cam", {"fx": (708.1, 707.0, 709.0), "cx": (314.8, 314.0, 316.0),
                                                  "k1": (0.001, -0.002, 0.004)}), tag)
    assert judge(truth, delta).exact and judge(truth, absolute).exact
    off = _doc(("camera_intrinsics", "cam", {"fx": (700.5, 700.0, 701.0), "cx": (315.0, 314.0, 316.0)}), tag)
    assert judge(truth, off).out_of_ci == ["camera_intrinsics@cam.fx: truth 708 not in [700, 701]"]


def test_judge_accepts_the_camera_frames_of_a_camera_mount_joint() -> None:
    from ppoe_core.sim.verdict import judge

    truth = {"effects": [{"name": "camera_extrinsics", "location": "camera_joint", "parameters": {"x": 0.01}}]}
    at_frame = judge(truth, _doc(("camera_extrinsics", "camera_optical_frame", {"x": (0.01, 0.009, 0.011)})), ARM7)
    assert at_frame.named and at_frame.out_of_ci == [
        "camera_extrinsics@camera_joint: reported at camera_optical_frame, parameters not comparable"]
    assert judge(truth, _doc(("camera_extrinsics", "joint_2", {"x": (0.01, 0.009, 0.011)})), ARM7).missing


def test_the_true_model_scores_the_sensor_noise(tmp_path: Path) -> None:
    """truth_scores: the truth's own parameters leave the tracker noise (RMS 3D = sigma sqrt(3) within 15 % on
    60 stops); the reflector error is what the effect does; error_budget: the model's declared prior and noise."""
    from ppoe_core.sim.verdict import error_budget, truth_scores

    sig = 2e-4
    sc = _scenario(tmp_path, truth={"perturbations": "none", "joint_noise": False, "effects": [
                       {"name": "gravity_compliance", "location": "joint_2", "parameters": {"compliance": 3e-4}}]},
                   trajectory={"joint_rate": 50.0, "dwell": 0.2, "move_time": 0.2, "start": dict(ARM7_START),
                               "random_stops": dict(_CAM_STOPS, count=60, min_visible_tags=0)},
                   ground_truth={"point": {"sigma": sig, "T_tracker_base": {"xyz": [1, 2, 0], "rpy": [0, 0, 1]}}},
                   imus=None)
    res = simulate(sc, tmp_path / "bag")
    d = bagio.read_bag(tmp_path / "bag")
    scen = load_scenario(sc)
    s = truth_scores(d, scen.robot, scen.model, res.truth)
    assert s.n == 60 and s.rms == pytest.approx(sig * np.sqrt(3), rel=0.15)
    nominal = truth_scores(d, scen.robot, scen.model, {"effects": [], "start_time": 100.0})
    assert nominal.rms > 5 * s.rms and s.reflector_error == pytest.approx(nominal.rms, rel=0.1)
    b = error_budget(d, scen.robot, scen.model, res.truth)
    assert b.noise == pytest.approx(0.0005 * np.sqrt(3)) and b.prior > b.true_error == s.reflector_error > 0
