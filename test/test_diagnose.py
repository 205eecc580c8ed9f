"""Tests of ppoe diagnose: synthetic data with a known injected effect (made here), the
contract JSON of the CLI on a bag, and one quick leave-one-file-out fit on the Hilti data."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from conftest import BAGS, CONFIG, DATASETS

from ppoe_core import lie
from ppoe_core.analysis.diagnose import (
    DiagnoseOptions,
    Stops,
    diagnose,
    load_model,
    motion_signs,
    write_model_yaml,
    write_report,
)
from ppoe_core.cli.datasets import stops_from_hilti
from ppoe_core.model.effects import make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

SIGMA = 1e-4  # tracker noise [m]
POINT = np.array([0.0, 0.0, 0.02])


@pytest.fixture(scope="module")
def robot():
    return parse_urdf(CONFIG / "robots" / "arm7.urdf")


def _synthetic(robot, true_effects=(), n=160, sessions=2, seed=0, extra_dq=None):
    """Tracker points of arm7 tool0 with the true effects, noise SIGMA, per-session registration."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(robot)
    names = tree.joint_names
    q = {j: rng.uniform(-1.2, 1.2, n) for j in names if robot.joints[j].type != "prismatic"}
    q.update({j: np.full(n, 0.01) for j in names if robot.joints[j].type == "prismatic"})
    Q = np.column_stack([q[j] for j in names])
    t = np.arange(n) * 5.0
    signs = motion_signs(t, Q, t)
    ctx = {"time": t, "motion_sign": {j: signs[:, i] for i, j in enumerate(names)}}
    dq, dxi = sum_effect_corrections(list(true_effects), q, ctx)
    for k, v in (extra_dq(q) if extra_dq else {}).items():
        dq[k] = dq.get(k, 0.0) + v
    x = (tree.link_poses(q, dq, dxi)["tool0"] @ np.append(POINT, 1.0))[:, :3]
    session = np.arange(n) % sessions
    p = np.empty_like(x)
    for s in range(sessions):
        T = lie.from_xyz_rpy(rng.uniform(-3, 3, 3), [0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        m = session == s
        p[m] = x[m] @ T[:3, :3].T + T[:3, 3]
    p += rng.normal(0.0, SIGMA, p.shape)
    R_imu = tree.link_poses(q, dq, dxi)["arm_link_4"][:, :3, :3]
    acc = 9.81 * R_imu[:, 2, :] + rng.normal(0.0, 4e-4, (n, 3))  # specific force in the link: R^T z g
    return Stops(q=q, p_meas=p, kind="point", link="tool0", point=POINT, sigma=SIGMA,
                 imus={"forearm": ("arm_link_4", acc)},
                 session=session, session_names=[f"s{i}" for i in range(sessions)],
                 group=np.zeros(n, dtype=int), group_names=["synthetic"],
                 reg_mask=np.ones(n, dtype=bool), score_mask=np.ones(n, dtype=bool), context=ctx,
                 base=robot.root)


def _inside(entry, truth):
    return all(entry["ci"][k][0] <= v <= entry["ci"][k][1] for k, v in truth.items())


def _effects(res):
    return res.to_json()["effects"]


@pytest.mark.parametrize("name,location,truth,seed", [
    ("gravity_compliance", "joint_2", {"compliance": 2e-5}, 11),
    ("mount_bending", "mount_joint", {"compliance_x": 3e-5, "compliance_y": 2e-5}, 12),
    ("joint_offset", "joint_4", {"offset": 0.004}, 13),
])
def test_injected_effect_is_named_with_true_parameter_in_ci(robot, name, location, truth, seed):
    eff = make_effect(name, location, robot, list(truth.values()))
    stops = _synthetic(robot, [eff], seed=seed)
    res = diagnose(robot, stops)
    assert [(e["name"], e["location"]) for e in _effects(res)] == [(name, location)], res.summary
    assert _inside(_effects(res)[0], truth), _effects(res)[0]
    assert res.residual_after < 0.5 * res.residual_before
    # the accelerometer (fitted with the tracker, the same effect) is at its noise after the fit
    imu = res.blocks["imu"]
    assert imu.rms_after < 1e-4 and (imu.rms_after < 0.3 * imu.rms_before or name == "joint_offset")
    # what remains is the sensor noise: nothing systematic left
    assert res.residual_after < 1.2 * res.blocks["tracker"].noise_floor + 1e-9
    assert res.unexplained_significant is False


def test_no_effect_finds_nothing(robot):
    res = diagnose(robot, _synthetic(robot, seed=3))
    assert res.effects == [], res.summary
    assert res.residual_after == pytest.approx(res.residual_before)
    assert res.unexplained_significant is False


def test_out_of_catalogue_effect_is_reported_unexplained(robot):
    """A cyclic (gear) error of joint 1, dq = 3 mrad sin(2 q): no catalogue effect is that; the residual follows
    joint_1's angle (held-out), so it is flagged, whatever the (absent) declared prior says."""
    stops = _synthetic(robot, seed=4, extra_dq=lambda q: {"joint_1": 3e-3 * np.sin(2 * q["joint_1"])})
    res = diagnose(robot, stops)
    assert res.unexplained_significant is True, res.summary
    tr = res.blocks["tracker"]
    assert any(s.significant and s.predictor == "configuration of joint_1" for s in tr.structure), tr.structure
    assert res.unexplained > 0.5 * res.residual_after
    assert "UNEXPLAINED" in res.summary


def test_unidentifiable_effect_is_not_attributed(robot):
    """A static error of the mount plate (before every joint) is absorbed by the per-session tracker registration
    (the accelerometer on the forearm sees its rotation, so only its rotation could be named, as the mount's
    link_error or a base tilt); an offset of joint 3 is named once (as the offset, not also as a link error)."""
    mount = make_effect("link_error", "mount_joint", robot, [0.002, -0.001, 0.0, 0.0, 0.0, 0.0])
    off = make_effect("joint_offset", "joint_3", robot, [0.003])
    res = diagnose(robot, _synthetic(robot, [mount, off], seed=5))
    locs = [(e["name"], e["location"]) for e in _effects(res)]
    assert locs == [("joint_offset", "joint_3")], locs
    assert res.residual_after < 1.2 * res.blocks["tracker"].noise_floor


def test_backlash_needs_and_uses_motion_sign(robot):
    eff = make_effect("backlash", "joint_2", robot, [0.002])
    res = diagnose(robot, _synthetic(robot, [eff], seed=6))
    assert [(e["name"], e["location"]) for e in _effects(res)] == [("backlash", "joint_2")], res.summary
    assert _inside(_effects(res)[0], {"play": 0.002})


def test_kabsch_recovers_transform():
    rng = np.random.default_rng(7)
    P = rng.normal(size=(10, 3))
    T = lie.from_xyz_rpy([1, 2, 3], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(lie.fit_rigid(P, P @ T[:3, :3].T + T[:3, 3]), T, atol=1e-12)


def test_updated_model_yaml_loads_and_reports_are_written(robot, tmp_path):
    eff = make_effect("gravity_compliance", "joint_2", robot, [2e-5])
    cfg0, _, pert0, jn0 = load_model(CONFIG / "robots" / "arm7_model.yaml", robot)
    res = diagnose(robot, _synthetic(robot, [eff], seed=8), (), pert0, jn0)
    out = write_model_yaml(CONFIG / "robots" / "arm7_model.yaml", res, tmp_path / "model.yaml")
    cfg, declared, pert, _ = load_model(out, robot)
    assert [(e.name, e.location) for e in declared] == [("gravity_compliance", "joint_2")]
    np.testing.assert_allclose(declared[0].params, [_effects(res)[0]["parameters"]["compliance"]])
    # sigmas are scaled by the prior's scale as the data estimate it (these data hold no random perturbation)
    src = yaml.safe_load((CONFIG / "robots" / "arm7_model.yaml").read_text())
    k = res.sigma_scale
    assert k < 0.5
    assert cfg.perturbations["joint_1"].covariance[0, 0] == pytest.approx((src["perturbations"]["joint_1"]["sigma"][0]
                                                                           * k) ** 2)
    assert cfg.joint_noise["joint_3"] == pytest.approx(src["joint_noise"]["joint_3"] * k)
    # the input's comments are kept (round trip), below a header saying what changed
    text = out.read_text()
    assert text.startswith("# Model updated by `ppoe diagnose`")
    for comment in [line.split("#", 1)[1] for line in (CONFIG / "robots" / "arm7_model.yaml").read_text().splitlines()
                    if "#" in line][:12]:
        assert comment in text, comment
    # a second diagnosis with the effect declared finds nothing new
    res2 = diagnose(robot, _synthetic(robot, [eff], seed=8), declared, pert)
    assert res2.effects == [], res2.summary
    paths = write_report(res, tmp_path)
    doc = json.loads(paths["json"].read_text())
    assert {"effects", "residual_before", "residual_after", "unexplained", "unexplained_significant"} <= set(doc)
    assert set(doc["effects"][0]) >= {"name", "location", "parameters", "ci"}
    assert "gravity_compliance" in paths["md"].read_text()


def test_prior_scale_is_estimated_from_the_data(robot):
    """True random joint errors of 1 mrad per stop and a model that declares 1/3 of it: the prior's scale comes
    out about 3 (the NEES of the declared covariance), and the declared NEES before is far above its expectation."""
    rng = np.random.default_rng(9)
    stops = _synthetic(robot, seed=9, n=300, extra_dq=lambda q: {j: rng.normal(0, 1e-3, 300)
                                                               for j in q if j.startswith("joint_")})
    jn = {f"joint_{i}": 1e-3 / 3 for i in range(1, 8)}
    res = diagnose(robot, stops, joint_noise=jn)
    assert res.sigma_scale == pytest.approx(3.0, rel=0.15)
    assert res.blocks["tracker"].nees_before > 3.0 * 4
    assert res.effects == [] and res.unexplained_significant is False, res.summary


@pytest.mark.datasets
def test_hilti_leave_one_file_out_lowers_heldout_rms():
    d = DATASETS / "hilti_stationing"
    if not (d / "flat.yaml").exists():
        pytest.fail(f"Hilti dataset not found in {d} (set PPOE_DATASETS)")
    robot = parse_urdf(d / "trailblazer.urdf")
    files = ["flat", "pallet", "orthogonal_wood"]
    stops = Stops.concat([stops_from_hilti(d / f"{f}.yaml", robot) for f in files])
    res = diagnose(robot, stops, options=DiagnoseOptions(
        cv="groups", candidates=["mount_bending@tracks_base_link_to_column_base", "link_error@dsr_joint5",
                                 "gravity_compliance@dsr_joint2"]))
    flat = res.metric.per_group["flat"]
    # README baseline (nominal URDF, cross set): 8.64 mm RMS, 15.2 mm r95 xy on flat.yaml
    assert flat["before"]["rms"] == pytest.approx(8.64e-3, abs=0.01e-3)
    assert flat["after"]["rms"] < 0.8 * flat["before"]["rms"]
    assert flat["after"]["r95_xy"] < 0.7 * flat["before"]["r95_xy"]
    # the column bending is the first step (the report lists effects in catalogue order, not by step)
    first = next(s for s in res.steps if s.get("accepted"))
    assert first["move"].startswith("mount_bending@tracks_base_link_to_column_base"), res.steps
    # the accelerometers are fitted in the same problem (a placement tilt per station): the column bending lowers
    # their held-out tilt residual too (the base accelerometer's own rocking stays in it: no effect predicts a
    # sensor's reading from itself)
    assert res.blocks["imu"].rms_after < 0.95 * res.blocks["imu"].rms_before


SHIPPED = [("no_effect", None, "point"), ("effect_joint_offset", "joint_offset", "point"),
           ("effect_gravity_compliance", "gravity_compliance", "point"),
           ("effect_mount_bending", "mount_bending", "point"), ("effect_unexplained", None, "point"),
           ("effect_mount_bending", "mount_bending", "pose"), ("effect_unexplained", None, "pose")]


@pytest.mark.parametrize("bag,expected,measurement", SHIPPED)
def test_shipped_bags(bag, expected, measurement):
    """The CLI on the shipped simulated bags (config/robots/arm7_model.yaml does not declare the effect; per-stop
    perturbations of the declared size), against the tracker points (registration estimated) and the ground-truth
    poses: the right effect at the right location with the truth inside the CI, nothing on no_effect, the declared
    prior's scale estimated near 1."""
    if not (BAGS / bag).exists():
        pytest.fail(f"shipped bag {BAGS / bag} is missing (bags/make_bags.sh regenerates it)")
    import contextlib
    import io

    from ppoe_ros.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["diagnose", str(BAGS / bag), "--model", str(CONFIG / "robots" / "arm7_model.yaml"), "--json",
                     "--measurement", measurement]) == 0
    doc = json.loads(out.getvalue())
    truth = yaml.safe_load((BAGS / f"{bag}.truth.yaml").read_text())["effects"]
    assert 0.7 < doc["sigma_scale"] < 1.4, doc["summary"]
    if expected is None:
        assert doc["effects"] == [], doc["summary"]
    else:
        assert len(doc["effects"]) == 1, doc["summary"]
        e, t = doc["effects"][0], truth[0]
        assert (e["name"], e["location"]) == (t["name"], t["location"])
        assert _inside(e, t["parameters"]), (e["ci"], t["parameters"])
        assert doc["residual_after"] < doc["residual_before"]
    assert doc["unexplained_significant"] is False or bag == "effect_unexplained", doc["summary"]


@pytest.mark.datasets
def test_motoman_tracker_heldout_rms_goes_down():
    d = DATASETS / "motoman_leica"
    if not (d / "leica_right_hand_6x6x6_dataset.mat").exists():
        pytest.fail(f"Motoman dataset not found in {d} (set PPOE_DATASETS)")
    from ppoe_core.cli.datasets import stops_from_motoman

    robot = parse_urdf(d / "motoman_right.urdf")
    stops = stops_from_motoman(d / "leica_right_hand_6x6x6_dataset.mat", robot)
    res = diagnose(robot, stops)
    # README: rigid fit of the nominal LR1 to the Leica points, 0.34 mm RMS (in-sample)
    assert res.metric.rms_before_insample == pytest.approx(0.34e-3, abs=0.01e-3)
    assert res.residual_after < 0.4 * res.residual_before


def test_bad_input_errors_name_the_stop(robot):
    from ppoe_core.errors import MeasurementError, PpoeError

    stops = _synthetic(robot, seed=12, n=20)
    stops.p_meas[7] = np.nan
    with pytest.raises(MeasurementError, match="stop 7 of synthetic"):
        diagnose(robot, stops)
    with pytest.raises(PpoeError, match="only 3 stops"):
        diagnose(robot, _synthetic(robot, seed=12, n=3))


def test_accelerometer_picks_the_location_the_tracker_cannot(tmp_path):
    """Two co-located mounts (mount_joint, then riser_joint on top of it) bend the same way for
    the tracker; an accelerometer on the plate between them sees only a bending of mount_joint.
    The true bending is at riser_joint: fitted with the accelerometer, the effect is named there."""
    urdf = (CONFIG / "robots" / "arm7.urdf").read_text()
    urdf = urdf.replace('''  <joint name="joint_1" type="revolute">
    <parent link="mount_plate"/>''', '''  <joint name="riser_joint" type="fixed">
    <parent link="mount_plate"/>
    <child link="riser"/>
    <origin xyz="0 0 0" rpy="0 0 0"/>
  </joint>
  <link name="riser"/>
  <joint name="joint_1" type="revolute">
    <parent link="riser"/>''')
    robot = parse_urdf(urdf)
    truth = {"compliance_x": 3e-5, "compliance_y": 2e-5}
    eff = make_effect("mount_bending", "riser_joint", robot, list(truth.values()))
    stops = _synthetic(robot, [eff], seed=14)
    tree = KinematicTree(robot)
    dq, dxi = sum_effect_corrections([eff], stops.q, stops.context)
    R_plate = tree.link_poses(stops.q, dq, dxi)["mount_plate"][:, :3, :3]
    stops.imus = {"plate": ("mount_plate", 9.81 * R_plate[:, 2, :]
                            + np.random.default_rng(15).normal(0, 4e-4, (len(stops), 3)))}
    res = diagnose(robot, stops)
    assert [(e["name"], e["location"]) for e in _effects(res)] == [("mount_bending", "riser_joint")], res.summary
    assert _inside(_effects(res)[0], truth)


def _rewrite_no_effect(tmp_path, stamp_js, value_js):
    """The shipped no_effect bag rewritten with joint-state stamps / values changed by the given functions."""
    from ppoe_core.io.bagio import BagWriter, read_bag

    data = read_bag(BAGS / "no_effect", load_images=False)
    js, gt = data.joint_states, data.ground_truth_point
    out = tmp_path / "bad"
    with BagWriter(out) as w:
        w.write_robot_description(data.robot_description, 0.0)
        for i in range(len(js)):
            w.write_joint_state(stamp_js(i, float(js.stamps[i])), js.names, value_js(js.names, js.positions[i]))
        for i in range(len(gt)):
            w.write_ground_truth_point(float(gt.stamps[i]), gt.frame_ids[i], gt.p[i])
    return out


def test_stamps_that_do_not_advance_or_a_nan_joint_are_refused(tmp_path, capsys):
    """Joint-state stamps all 0 (or repeated) or running backwards, or a chain joint NaN in every message: one
    line naming the bag and the joint, exit 2 (no 'nan mm', no numpy traceback); measurements stamped before
    the first joint state are left out with a warning that counts them."""
    from ppoe_ros.cli import main

    model = str(CONFIG / "robots" / "arm7_model.yaml")
    zero = _rewrite_no_effect(tmp_path / "zero", lambda i, t: 0.0, lambda names, q: q)
    assert main(["diagnose", str(zero), "--model", model]) == 2
    err = capsys.readouterr().err
    assert f"bag {zero}: /joint_states stamps of joint" in err and "do not advance" in err
    assert "Traceback" not in err and "nan mm" not in err

    def nan_joint_2(names, q):
        q = np.array(q, dtype=float)
        q[list(names).index("joint_2")] = np.nan
        return q

    back = _rewrite_no_effect(tmp_path / "back", lambda i, t: 1000.0 - t, lambda names, q: q)  # runs backwards
    assert main(["diagnose", str(back), "--model", model]) == 2
    err = capsys.readouterr().err
    assert f"bag {back}: 60 of 60 measurements are stamped before the first /joint_states message" in err
    assert "nan mm" not in err and "Traceback" not in err

    late = _rewrite_no_effect(tmp_path / "late", lambda i, t: t + 5.0, lambda names, q: q)  # first stops unjointed
    assert main(["diagnose", str(late), "--model", model]) == 0
    err = capsys.readouterr().err
    assert f"ppoe diagnose: warning: bag {late}: " in err and "of 60 measurements are stamped before" in err
    assert "those measurements are left out" in err

    nan_bag = _rewrite_no_effect(tmp_path / "nan", lambda i, t: t, nan_joint_2)
    assert main(["diagnose", str(nan_bag), "--model", model]) == 2
    err = capsys.readouterr().err
    assert f"bag {nan_bag}: /joint_states carries no finite value of joint 'joint_2'" in err


def test_diagnosed_model_goes_back_into_evaluate_and_the_library(tmp_path, capsys):
    """The result goes back in (issue 10): the diagnosed model YAML of a tracker bag loads in ``ppoe evaluate``
    scored against the tracker points (it crashed on a chain without moving joints before), and lowers the
    FK error; the JSON effect entries (with ci, sigma, share) load through ``effect_from_config``."""
    import json

    from ppoe_core.analysis.evaluate import evaluate_bag
    from ppoe_core.analysis.evaluate.options import EvaluateOptions
    from ppoe_core.model.effects import effect_from_config
    from ppoe_ros.cli import main

    bag, model = BAGS / "effect_joint_offset", CONFIG / "robots" / "arm7_model.yaml"
    out = tmp_path / "dg"
    assert main(["diagnose", str(bag), "--model", str(model), "--out", str(out)]) == 0
    capsys.readouterr()
    opts = EvaluateOptions(ground_truth="point")
    before = evaluate_bag(bag, model, opts).summary["methods"]["fk"]["position_3d"]["rms"]
    after = evaluate_bag(bag, out / "model_diagnosed.yaml", opts).summary["methods"]["fk"]["position_3d"]["rms"]
    assert after < 0.85 * before, (before, after)
    doc = json.loads((out / "diagnose.json").read_text())
    assert doc["effects"] and {"ci", "sigma", "share"} <= set(doc["effects"][0])
    effs = [effect_from_config(e, parse_urdf(CONFIG / "robots" / "arm7.urdf")) for e in doc["effects"]]
    assert [e.describe() for e in effs] == ["joint_offset@joint_2"]
    np.testing.assert_allclose(effs[0].params, [doc["effects"][0]["parameters"]["offset"]])
