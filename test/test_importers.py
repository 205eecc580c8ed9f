"""Tests of ``ppoe import hilti|motoman`` (ppoe_core.io.importers).

The dataset tests read ``$PPOE_DATASETS`` (default ``<repo>/../shared/datasets``) and are
marked ``datasets``; they are skipped only when that folder is absent.  Nothing they write is
kept (pytest tmp dirs).  The expected counts and baseline numbers are those stated in the
datasets' README files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import yaml
from conftest import DATASETS

from ppoe_core import lie
from ppoe_core.errors import DatasetError
from ppoe_core.io.bagio import read_bag
from ppoe_core.io.importers import hilti as hi
from ppoe_core.io.importers import motoman as mo
from ppoe_core.io.importers import read_stop_info

HILTI = DATASETS / "hilti_stationing"
MOTOMAN = DATASETS / "motoman_leica"
needs_data = pytest.mark.skipif(not DATASETS.is_dir(), reason=f"datasets folder {DATASETS} not present")


# ----------------------------------------------------------------------------- synthetic (no data)

_HILTI_WAYPOINT = {
    "id": 0,
    "time": 100.0,
    "upside_down": False,
    "doosan_cmd": [0.25, 0.15, 0.48],
    "joint_states": [2.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
    "prism_position": [1.0, 2.0, 3.0],
    "tilt_sensor_base_accel": [0.0, 0.0, 9.8],
    "tilt_sensor_column_accel": [0.0, 0.1, 9.8],
}


def _hilti_doc(**changes):
    wp = dict(_HILTI_WAYPOINT, **changes)
    wp2 = dict(_HILTI_WAYPOINT, id=1, time=110.0, doosan_cmd=[0.3, 0.0, 0.4])
    return {
        "joint_names": ["column_prismatic_joint"] + [f"dsr_joint{i}" for i in range(1, 7)],
        "column_heights": {2.0: {"solution_spaces": {0: {"stationing_measurements": [wp],
                                                        "evaluation_measurements": [wp2]}}}},
    }


def test_hilti_parse_synthetic(tmp_path):
    f = tmp_path / "x.yaml"
    f.write_text(yaml.safe_dump(_hilti_doc()))
    ds = hi.load_hilti(f)
    assert [s.role for s in ds.stops] == ["stationing", "evaluation"]
    s0 = ds.stops[0]
    assert s0.station == "h2_s0" and s0.point_sets == ["cross"]
    assert ds.stops[1].point_sets == []  # evaluation stops belong to no stationing set
    np.testing.assert_allclose(s0.prism_position, [1.0, 2.0, 3.0])


@pytest.mark.parametrize(
    "change, needle",
    [
        ({"joint_states": [1.0, 2.0]}, "joint_states"),
        ({"prism_position": [1.0, float("nan"), 3.0]}, "prism_position"),
        ({"time": "soon"}, "bad value"),
    ],
)
def test_hilti_bad_values_name_the_waypoint(tmp_path, change, needle):
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(_hilti_doc(**change)))
    with pytest.raises(DatasetError) as ei:
        hi.load_hilti(f)
    msg = str(ei.value)
    assert str(f) in msg and "stationing_measurements[0]" in msg and needle in msg


def test_hilti_missing_key_and_wrong_joints(tmp_path):
    doc = _hilti_doc()
    del doc["column_heights"][2.0]["solution_spaces"][0]["stationing_measurements"][0]["prism_position"]
    f = tmp_path / "a.yaml"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError, match="missing key 'prism_position'"):
        hi.load_hilti(f)
    doc = _hilti_doc()
    doc["joint_names"][0] = "lift"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError, match="joint_names"):
        hi.load_hilti(f)
    with pytest.raises(DatasetError, match="cannot read"):
        hi.load_hilti(tmp_path / "missing.yaml")


def test_hilti_synthetic_bag_layout(tmp_path):
    f = tmp_path / "x.yaml"
    f.write_text(yaml.safe_dump(_hilti_doc()))
    urdf = tmp_path / "r.urdf"
    urdf.write_text('<robot name="r"><link name="base_link"/></robot>')
    res = hi.import_hilti(f, tmp_path / "bag", urdf=urdf)
    data = read_bag(tmp_path / "bag")
    assert len(data.joint_states) == 2 * hi.BURST_COUNT
    assert len(data.ground_truth_point) == 2 and data.ground_truth_point.frame_ids[0] == hi.TRACKER_FRAME
    assert set(data.imus) == {"base", "column_tip"}
    assert data.imus["base"].frame_ids[0] == "tilt_sensor_base"
    np.testing.assert_allclose(data.imus["column_tip"].linear_acceleration[0], [0.0, 0.1, 9.8])
    # every measurement is stamped inside its stop, after the joint-state burst
    js_t = data.joint_states.stamps
    for t in data.ground_truth_point.stamps:
        burst = js_t[(js_t <= t) & (js_t > t - 1.0)]
        assert len(burst) == hi.BURST_COUNT
    stops = read_stop_info(str(tmp_path / "bag"))
    assert [s[1]["role"] for s in stops] == ["stationing", "evaluation"]
    assert Path(res["model"]).is_file()


def _motoman_rows():
    """Two poses, three observations; the second pose has no Leica point."""
    D = np.zeros((3, 26))
    D[:, 0] = [1, 1, 2]
    D[:, 1] = [3, 4, 3]
    D[:, 2] = 1
    D[:, 3] = [1, 2, 1]
    D[:, 4:6] = [[2000, 3000], [2100, 2900], [1900, 3100]]
    D[:2, 6:13] = 0.1
    D[2, 6:13] = 0.2
    D[:2, 19:22] = [1.0, 2.0, 3.0]
    D[2, 19:26] = np.nan
    return D


def test_motoman_parse_synthetic(tmp_path):
    f = tmp_path / "m.mat"
    scipy.io.savemat(f, {"dataset": _motoman_rows()})
    ds = mo.load_motoman(f)
    assert list(ds.pose_ids) == [1, 2]
    assert list(ds.has_tracker) == [True, False]
    assert list(ds.obs_camera) == [1, 2, 1] and list(ds.obs_pose) == [0, 0, 1]


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda D: D.__setitem__((1, 2), 2), "row 2: arm number 2"),
        (lambda D: D.__setitem__((0, 3), 3), "row 1: camera number 3"),
        (lambda D: D.__setitem__((1, 7), 0.5), "row 2: joint/Leica values differ"),
        (lambda D: D.__setitem__((2, 8), np.nan), "row 3: NaN"),
        (lambda D: D.__setitem__((0, 1), 21), "marker face 21"),
    ],
)
def test_motoman_bad_rows(tmp_path, mutate, needle):
    D = _motoman_rows()
    mutate(D)
    f = tmp_path / "m.mat"
    scipy.io.savemat(f, {"dataset": D})
    with pytest.raises(DatasetError) as ei:
        mo.load_motoman(f)
    assert needle in str(ei.value) and str(f) in str(ei.value)


def test_motoman_wrong_shape_and_variable(tmp_path):
    f = tmp_path / "m.mat"
    scipy.io.savemat(f, {"dataset": np.zeros((3, 20))})
    with pytest.raises(DatasetError, match="N x 26"):
        mo.load_motoman(f)
    scipy.io.savemat(f, {"other": np.zeros((3, 26))})
    with pytest.raises(DatasetError, match="no variable 'dataset'"):
        mo.load_motoman(f)


# ----------------------------------------------------------------------------- real datasets


@pytest.fixture(scope="module")
def flat_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("hilti") / "flat_bag"
    res = hi.import_hilti(HILTI / "flat.yaml", out)
    return out, res


@pytest.fixture(scope="module")
def moto_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("motoman") / "m6_bag"
    res = mo.import_motoman(MOTOMAN / "leica_right_hand_6x6x6_dataset.mat", MOTOMAN / "model.yaml", out)
    return out, res


@pytest.mark.datasets
@needs_data
def test_hilti_flat_counts_match_readme(flat_bag):
    out, res = flat_bag
    ds = hi.load_hilti(HILTI / "flat.yaml")
    assert len(ds.stations) == 15  # 5 heights x 3 solution spaces
    stationed = {s.station for s in ds.stops if s.role == "stationing"}
    assert len(stationed) == 10  # README: 10 stations (spaces 0 and 7)
    n_eval = sum(1 for s in ds.stops if s.role == "evaluation" and s.station in stationed)
    assert n_eval == 321  # README: flat.yaml eval pts
    data = read_bag(out)
    n = len(ds.stops)
    assert 430 <= n <= 450  # README: about 440 waypoints per file
    assert len(data.joint_states) == hi.BURST_COUNT * n
    assert len(data.ground_truth_point) == n and len(data.imus["base"]) == n and len(data.imus["column_tip"]) == n
    assert data.joint_states.names == ds.joint_names
    stops = read_stop_info(str(out))
    assert len(stops) == n
    assert sum(1 for _, s in stops if s["role"] == "evaluation" and s["station"] in stationed) == 321
    # the bag keeps the file's values
    i = int(np.argmin(np.abs(data.ground_truth_point.stamps - (ds.stops[7].time + hi.MEASUREMENT_DELAY_S))))
    np.testing.assert_allclose(data.ground_truth_point.p[i], ds.stops[7].prism_position, atol=1e-12)
    assert "prism_calib" in data.robot_description


@pytest.mark.datasets
@needs_data
def test_motoman_counts_match_readme(moto_bag):
    out, res = moto_bag
    data = read_bag(out)
    assert len(data.joint_states) == mo.BURST_COUNT * 216
    assert len(data.ground_truth_point) == 212  # README: 212 poses with Leica
    obs = data.tag_observations
    cam = np.array([obs.frame_ids[i] for i in obs.msg_index])
    assert np.sum(cam == "camera_1_optical_frame") == 503 and np.sum(cam == "camera_2_optical_frame") == 811
    assert set(obs.corners.tolist()) == {0} and obs.ids.min() >= 1 and obs.ids.max() <= 20
    assert res["counts"]["points:camera_1"] == 503 and res["counts"]["points:camera_2"] == 811
    assert data.joint_states.names == mo.JOINT_NAMES
    # undistorted x, y project back onto the raw pixels with the camera_info of that camera
    import cv2

    for frame in ("camera_1_optical_frame", "camera_2_optical_frame"):
        k = data.camera_info.frame_ids.index(frame)
        sel = cam == frame
        P = np.column_stack([obs.xy[sel], np.ones(sel.sum())])
        uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), data.camera_info.K[k], data.camera_info.D[k])
        np.testing.assert_allclose(uv.reshape(-1, 2), obs.uv[sel], atol=1e-6)


@pytest.mark.datasets
@needs_data
def test_motoman_model_yaml_validates(moto_bag):
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.urdf import parse_urdf

    out, res = moto_bag
    robot = parse_urdf(MOTOMAN / "motoman_right.urdf")
    cfg = load_model_config(res["model"], robot)
    assert len(cfg.tags.items) == 20 and cfg.tracker.link == "LR1"
    assert {t.link for t in cfg.tags.items} == {"EE1"}


@pytest.mark.datasets
@needs_data
def test_motoman_tracker_and_reprojection_baselines():
    """README (i) 0.34 mm Leica RMS and (ii) 23.5 / 25.0 px marker RMS, with our model."""
    from ppoe_core.estimation.camera import project_points
    from ppoe_core.lie import fit_rigid as kabsch
    from ppoe_core.model.ppoe import PPOEModel

    ds = mo.load_motoman(MOTOMAN / "leica_right_hand_6x6x6_dataset.mat")
    model = PPOEModel.from_files(MOTOMAN / "motoman_right.urdf")
    q = {n: ds.joints[:, j] for j, n in enumerate(mo.JOINT_NAMES)}
    T_base_lr = model.fk_mean(q, "base", "LR1")
    ok = ds.has_tracker
    p_fk = T_base_lr[ok, :3, 3]
    T = kabsch(p_fk, ds.leica[ok])
    res = np.linalg.norm(p_fk @ T[:3, :3].T + T[:3, 3] - ds.leica[ok], axis=1)
    assert ok.sum() == 212
    assert abs(np.sqrt(np.mean(res**2)) - 0.34e-3) < 0.005e-3
    assert abs(res.max() - 0.63e-3) < 0.005e-3
    cams = mo.load_motoman_cameras(MOTOMAN / "model.yaml")
    expected = {1: 23.5, 2: 25.0}
    for n, cam in cams.items():
        sel = np.flatnonzero(ds.obs_camera == n)
        qs = {k: v[ds.obs_pose[sel]] for k, v in q.items()}
        err = np.empty(len(sel))
        for face in np.unique(ds.obs_face[sel]):
            f = ds.obs_face[sel] == face
            qf = {k: v[f] for k, v in qs.items()}
            T_cam_mk = model.fk_mean(qf, cam.frame, f"MK1{face:02d}")
            uv = project_points(T_cam_mk[:, :3, 3], cam.K, cam.D)
            err[f] = np.linalg.norm(uv - ds.obs_uv[sel][f], axis=1)
        assert abs(np.sqrt(np.mean(err**2)) - expected[n]) < 0.05, (n, np.sqrt(np.mean(err**2)))


@pytest.mark.datasets
@needs_data
def test_hilti_nominal_baseline_cross_set():
    """README: flat.yaml, cross set, per-station Kabsch: RMS 3D 8.64 mm, max 24.66 mm (mimic-aware FK)."""
    from ppoe_core.lie import fit_rigid as kabsch
    from ppoe_core.model.ppoe import PPOEModel

    ds = hi.load_hilti(HILTI / "flat.yaml")
    model = PPOEModel.from_files(HILTI / "trailblazer.urdf")
    Q = np.array([s.joints for s in ds.stops])
    p = model.fk_mean({n: Q[:, j] for j, n in enumerate(ds.joint_names)}, "base_link", "prism")[:, :3, 3]
    errs = []
    for station in ds.stations:
        idx = [i for i, s in enumerate(ds.stops) if s.station == station]
        fit = [i for i in idx if "cross" in ds.stops[i].point_sets]
        ev = [i for i in idx if ds.stops[i].role == "evaluation"]
        if len(fit) < 3:
            continue
        T = kabsch(p[fit], np.array([ds.stops[i].prism_position for i in fit]))
        pred = p[ev] @ T[:3, :3].T + T[:3, 3]
        errs.append(np.linalg.norm(np.array([ds.stops[i].prism_position for i in ev]) - pred, axis=1))
    e = np.concatenate(errs)
    assert e.size == 321
    assert abs(np.sqrt(np.mean(e**2)) - 8.64e-3) < 0.1e-3
    assert abs(e.max() - 24.66e-3) < 0.1e-3


def test_cli_import_json(tmp_path, capsys):
    """``ppoe import hilti --json`` prints one JSON document with the counts."""
    from ppoe_ros.cli import main

    f = tmp_path / "x.yaml"
    f.write_text(yaml.safe_dump(_hilti_doc()))
    urdf = tmp_path / "r.urdf"
    urdf.write_text('<robot name="r"><link name="base_link"/></robot>')
    rc = main(["import", "hilti", str(f), "--out", str(tmp_path / "b"), "--urdf", str(urdf), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["counts"]["/joint_states"] == 2 * hi.BURST_COUNT
    # a second import to the same place is refused without --force, naming the bag
    rc = main(["import", "hilti", str(f), "--out", str(tmp_path / "b"), "--urdf", str(urdf)])
    assert rc == 2 and "exists" in capsys.readouterr().err


@pytest.mark.parametrize("state", ["null", "missing"])
def test_hilti_incomplete_station_refused_then_counted(tmp_path, capsys, state):
    """Issue 13 item 4: a station whose stationing list is null/missing/empty is not dropped silently."""
    from ppoe_ros.cli import main

    doc = _hilti_doc()
    station = doc["column_heights"][2.0]["solution_spaces"][0]
    if state == "missing":
        del station["stationing_measurements"]
    else:
        station["stationing_measurements"] = None
    f = tmp_path / "x.yaml"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(DatasetError) as ei:
        hi.load_hilti(f)
    msg = str(ei.value)
    assert str(f) in msg and f"solution_spaces/0/stationing_measurements is {state}" in msg
    assert "1 evaluation stops are kept" in msg and "--allow-incomplete" in msg
    urdf = tmp_path / "r.urdf"
    urdf.write_text('<robot name="r"><link name="base_link"/></robot>')
    out = tmp_path / "b"
    assert main(["import", "hilti", str(f), "--out", str(out), "--urdf", str(urdf)]) == 2
    assert "stationing_measurements is" in capsys.readouterr().err and not out.exists()
    rc = main(["import", "hilti", str(f), "--out", str(out), "--urdf", str(urdf), "--allow-incomplete", "--json"])
    captured = capsys.readouterr()
    assert rc == 0 and "warning" in captured.err and f"stationing_measurements is {state}" in captured.err
    doc_out = json.loads(captured.out)
    assert len(doc_out["incomplete"]) == 1 and doc_out["counts"]["/joint_states"] == hi.BURST_COUNT
    station["stationing_measurements"] = []  # an explicit empty list (the data's space 4) is accepted
    f.write_text(yaml.safe_dump(doc))
    assert [s.role for s in hi.load_hilti(f).stops] == ["evaluation"]


# ----------------------------------------------------------------------------- the left arm (arm number 2)


def _dh_product(rows, q):
    """Standard DH (model.yaml conventions) product of ``rows`` with joint values ``q`` (independent of the URDF)."""
    T = np.eye(4)
    for row, qi in zip(rows, q):
        th, d, a, al = row.get("offset", 0.0) + qi, row["d"], row["a"], row["alpha"]
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                          [0, 0, 0, 1.0]])
    return T


def _left_arm_file(tmp_path, offset_L=0.0, n=40, seed=5):
    """An arm-2 .mat file in the right-arm files' format: left-arm joints in columns 14-19, Leica points of LR2
    from model.yaml's left-arm DH (plus an encoder offset at L if given), one marker row per pose."""
    import yaml as _yaml

    doc = _yaml.safe_load((MOTOMAN / "model.yaml").read_text())
    rows, lr2 = doc["left_arm"]["dh"], doc["left_arm"]["tools"]["LR2"]["dh"]
    rng = np.random.default_rng(seed)
    T_leica_base = lie.from_xyz_rpy([3.0, -1.0, 0.5], [0.0, 0.0, 0.8])
    D = np.full((n, 26), np.nan)
    for k in range(n):
        q = np.concatenate([[rng.uniform(-0.5, 0.5)], rng.uniform(-1.0, 1.0, 6)])
        dq = np.array([0, 0, offset_L, 0, 0, 0, 0])
        p = (_dh_product([*rows, lr2], [*(q + dq), 0.0]) @ [0, 0, 0, 1.0])
        D[k, :6] = [k + 1, 1 + k % 20, 2, 1 + k % 2, 2000 + k, 3000 - k]
        D[k, 6], D[k, 7:13], D[k, 13:19] = q[0], 0.0, q[1:]
        D[k, 19:22] = (T_leica_base @ p)[:3] + rng.normal(0, 1e-4, 3)
        D[k, 22:26] = 0.0
    f = tmp_path / "leica_left_synthetic.mat"
    scipy.io.savemat(f, {"dataset": D})
    return f, rows, lr2


@pytest.mark.datasets
@needs_data
def test_left_arm_urdf_matches_the_model_yaml_dh(tmp_path):
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    urdf = mo.left_arm_urdf((MOTOMAN / "motoman_right.urdf").read_text(), MOTOMAN / "model.yaml")
    robot = parse_urdf(urdf)
    tree = KinematicTree(robot)
    import yaml as _yaml

    doc = _yaml.safe_load((MOTOMAN / "model.yaml").read_text())
    rows, tools = doc["left_arm"]["dh"], doc["left_arm"]["tools"]
    rng = np.random.default_rng(1)
    names = mo.ARM_JOINTS[2]
    for _ in range(10):
        q = rng.uniform(-2, 2, 7)
        qd = {n: np.array(v) for n, v in zip(names, q)}
        qd.update({j: np.array(0.0) for j in robot.independent_joints if j not in qd})
        poses = tree.link_poses(qd)
        for link, extra in (("T2", []), ("EE2", [tools["EE2"]["dh"]]), ("LR2", [tools["LR2"]["dh"]])):
            want = _dh_product([*rows, *extra], [*q, *([0.0] * len(extra))])
            np.testing.assert_allclose(poses[link], want, atol=1e-12, err_msg=link)
    assert "joint_S1" in robot.joints and "MK220" in robot.links  # the right arm is kept, markers on EE2


@pytest.mark.datasets
@needs_data
def test_left_arm_file_imports_and_its_encoder_offset_is_diagnosed(tmp_path, capsys):
    from ppoe_ros.cli import main

    f, _, _ = _left_arm_file(tmp_path, offset_L=0.01)
    res = mo.import_motoman(f, MOTOMAN / "model.yaml", tmp_path / "bag")
    assert res["arm"] == 2 and res["counts"]["/ground_truth/point"] == 40
    model = yaml.safe_load(Path(res["model"]).read_text())
    assert model["tracker"]["link"] == "LR2" and model["frames"]["tool"] == "EE2"
    assert {t["link"] for t in model["tags"]["items"]} == {"EE2"} and "joint_L2" in model["joint_noise"]
    assert main(["diagnose", str(tmp_path / "bag"), "--model", res["model"], "--json", "--pixels", "off"]) == 0
    doc = json.loads(capsys.readouterr().out)
    found = [(e["name"], e["location"]) for e in doc["effects"]]
    assert found[:1] == [("joint_offset", "joint_L2")], doc["summary"]
    lo, hi = doc["effects"][0]["ci"]["offset"]
    assert lo <= 0.01 <= hi


@pytest.mark.datasets
@needs_data
def test_left_arm_marker_pixels_go_through_the_pixel_stage(tmp_path, capsys):
    """An arm-2 file whose marker pixels are projections of the MK2xx markers (model.yaml cameras, true
    intrinsics): the bag goes through diagnose's tracker and pixel stages (markers on EE2, both cameras), and
    the pixels of the nominal model reproject to well under a pixel (no camera effect is invented)."""
    from ppoe_core.estimation.camera import project_points
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf
    from ppoe_ros.cli import main

    f, _, _ = _left_arm_file(tmp_path, n=60, seed=9)
    D = scipy.io.loadmat(f)["dataset"]
    robot = parse_urdf(mo.left_arm_urdf((MOTOMAN / "motoman_right.urdf").read_text(), MOTOMAN / "model.yaml"))
    tree = KinematicTree(robot)
    cams = mo.load_motoman_cameras(MOTOMAN / "model.yaml")
    rows = []
    for r in D:
        q = {n: np.array(v) for n, v in zip(mo.ARM_JOINTS[2], [r[6], *r[13:19]])}
        q.update({j: np.array(0.0) for j in robot.independent_joints if j not in q})
        poses = tree.link_poses(q)
        for cam_n, cam in cams.items():
            for face in range(1, 21):
                T_cam_mk = np.linalg.inv(poses[cam.frame]) @ poses[f"MK2{face:02d}"]
                p, z = T_cam_mk[:3, 3], T_cam_mk[:3, 2]
                if p[2] > 0.3 and z @ (-p / np.linalg.norm(p)) > 0.5:  # in front, facing the camera
                    uv = project_points(p[None], cam.K, cam.D)[0]
                    if 0 < uv[0] < 6000 and 0 < uv[1] < 4000:
                        row = r.copy()
                        row[1], row[3], row[4:6] = face, cam_n, uv
                        rows.append(row)
    assert len(rows) > 40
    scipy.io.savemat(f, {"dataset": np.array(rows)})
    res = mo.import_motoman(f, MOTOMAN / "model.yaml", tmp_path / "bag")
    assert main(["diagnose", str(tmp_path / "bag"), "--model", res["model"], "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    pix = doc["pixels"]
    assert set(pix["pixel_rms_before"]) <= {"camera_1_optical_frame", "camera_2_optical_frame"}
    # the nominal model's reprojection (in-sample, no effect), per camera
    assert all(v < 0.5 for v in pix["pixel_rms_before_insample"].values()), pix["pixel_rms_before_insample"]
    assert not [e for e in doc["effects"] if e["name"] == "camera_extrinsics"]
    # evaluate too: the right arm's joints, never in this bag, are off every chain it uses
    assert main(["evaluate", str(tmp_path / "bag"), "--model", res["model"], "--json", "--no-progress"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["methods"]["fk"]["position_3d"]["n"] > 5 and ev["methods"]["ppoe"]["measurements"]["counts"]


# ----------------------------------------------------------------------------- a file cut short (issue 25)


def _two_heights_doc(spaces_at_last=(0, 7), evaluations_at_last=1):
    """Two column heights with solution spaces 0 and 7 each, as the real files repeat one pattern per height."""
    doc = _hilti_doc()
    t = [200.0]

    def wps(n):
        out = []
        for _ in range(n):
            t[0] += 10.0
            out.append(dict(_HILTI_WAYPOINT, id=int(t[0]), time=t[0]))
        return out

    doc["column_heights"][2.0]["solution_spaces"][7] = {"stationing_measurements": wps(1),
                                                         "evaluation_measurements": wps(2)}
    doc["column_heights"][2.5] = {"solution_spaces": {
        sp: {"stationing_measurements": wps(1), "evaluation_measurements": wps(2 if sp != spaces_at_last[-1]
                                                                             else evaluations_at_last)}
        for sp in spaces_at_last}}
    return doc


def test_hilti_file_cut_short_is_refused_with_counts_then_imported_with_a_warning(tmp_path, capsys):
    """Was: a file cut on a line boundary imported what was left, exit 0, no note."""
    from ppoe_ros.cli import main

    assert hi.load_hilti(_write_yaml(tmp_path / "whole.yaml", _two_heights_doc(evaluations_at_last=2))).truncated \
        == []
    f = _write_yaml(tmp_path / "cut.yaml", _two_heights_doc(spaces_at_last=(0,)))
    with pytest.raises(DatasetError) as ei:
        hi.load_hilti(f)
    msg = str(ei.value)
    assert f"{f}: the file looks cut short (column height 2.5, the last in the file, lacks solution space(s) 7 " \
        "that every other height has); it holds 7 stops in 3 stations (the format declares no total); pass " \
        "--allow-incomplete" in msg, msg
    f2 = _write_yaml(tmp_path / "cut2.yaml", _two_heights_doc(evaluations_at_last=1))
    assert hi.load_hilti(f2, allow_incomplete=True).truncated == [
        "its last station h2.5_s7 has 1 evaluation stops where solution space 7 has 2-2 at the other heights"]
    urdf = tmp_path / "r.urdf"
    urdf.write_text('<robot name="r"><link name="base_link"/></robot>')
    assert main(["import", "hilti", str(f2), "--out", str(tmp_path / "b"), "--urdf", str(urdf)]) == 2
    assert "looks cut short" in capsys.readouterr().err and not (tmp_path / "b").exists()
    assert main(["import", "hilti", str(f2), "--out", str(tmp_path / "b"), "--urdf", str(urdf),
                 "--allow-incomplete"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "has 1 evaluation stops" in err
    assert f"{f2}: 10 stops in 4 stations imported (the Hilti format declares no total)" in err, err


def _write_yaml(path: Path, doc) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))  # the file order matters: the last list is the cut one
    return path


@pytest.mark.datasets
@needs_data
def test_hilti_flat_cut_after_199_stops_is_refused(tmp_path):
    """The case of the issue: flat.yaml cut on a line boundary after waypoint 198 (199 of 444 stops)."""
    lines = (HILTI / "flat.yaml").read_text().splitlines(keepends=True)
    cut = next(i for i, line in enumerate(lines) if line.strip() == "- id: 199")
    f = tmp_path / "flat_cut.yaml"
    f.write_text("".join(lines[:cut]))
    with pytest.raises(DatasetError, match=r"looks cut short .* it holds 199 stops in 7 stations"):
        hi.load_hilti(f)
    assert len(hi.load_hilti(f, allow_incomplete=True).stops) == 199
