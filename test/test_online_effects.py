"""Online effects (issue 11 item 1): drifting truth in ``ppoe simulate``, the augmented-state filter, and
``ppoe evaluate --online`` on simulated drift bags (base moved onto a tilted floor halfway, temperature ramp,
load picked up).  The bags are simulated here from ``bags/online/*.yaml`` (nothing binary is committed)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO

from ppoe_core import lie
from ppoe_core.analysis.evaluate.online import evaluate_online, load_online_config
from ppoe_core.errors import BagError, ModelConfigError, ScenarioError
from ppoe_core.estimation.online_effects import OnlineEffects, parse_online_config
from ppoe_core.io.bagio import read_bag
from ppoe_core.model.ppoe import PPOEModel
from ppoe_core.sim.schedule import parse_value, truth_values
from ppoe_core.sim.simulate import simulate

ONLINE = REPO / "bags" / "online"
MODEL = ONLINE / "arm7_drift_model.yaml"
URDF = REPO / "config" / "robots" / "arm7.urdf"


def _scenario(name: str, tmp: Path, **changes) -> Path:
    """``bags/online/<name>.yaml`` with absolute robot paths (and ``changes`` merged at the top level)."""
    raw = yaml.safe_load((ONLINE / f"{name}.yaml").read_text())
    raw["robot"] = {"urdf": str(URDF), "model": str(MODEL)}
    raw.update(changes)
    p = tmp / f"{name}.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


@pytest.fixture(scope="module")
def drift_bags(tmp_path_factory) -> dict[str, tuple[Path, dict]]:
    """The drift bags of bags/online and their truth (tilt_imu: an accelerometer instead of the tracker)."""
    tmp = tmp_path_factory.mktemp("drift")
    out = {}
    for name in ("tilt", "thermal", "load", "tilt_imu"):
        res = simulate(_scenario(name, tmp), tmp / name)
        out[name] = (tmp / name, res.truth)
    return out


@pytest.fixture(scope="module")
def evaluations(drift_bags) -> dict:
    out = {}
    for name, (bag, truth) in drift_bags.items():
        cfg, jump = load_online_config(ONLINE / ("online_thermal.yaml" if name == "thermal" else
                                                 "online_effects.yaml"))
        out[name] = evaluate_online(bag, MODEL, cfg, jump, truth=truth)
    return out


# ----------------------------------------------------------------------------- schedules and the simulator
def test_schedule_forms_and_errors():
    t = np.array([0.0, 9.99, 10.0, 30.0])
    assert parse_value({"step": {"at": 10.0, "before": 1.0, "after": 2.0}}, "x")(t).tolist() == [1, 1, 2, 2]
    np.testing.assert_allclose(parse_value({"ramp": {"start": 0, "end": 20, "from": 0, "to": 2}}, "x")(t),
                               [0, 0.999, 1.0, 2.0])
    np.testing.assert_allclose(parse_value({"table": [[0, 0], [10, 1], [20, 0]]}, "x")(t), [0, 0.999, 1, 0])
    assert parse_value(3.5, "x")(t).tolist() == [3.5] * 4
    with pytest.raises(ScenarioError, match=r"p\.ramp: end"):
        parse_value({"ramp": {"start": 5, "end": 1, "from": 0, "to": 1}}, "p")
    with pytest.raises(ScenarioError, match="step"):
        parse_value({"stepp": {"at": 1}}, "p")
    with pytest.raises(ScenarioError, match=r"table: times must increase"):
        parse_value({"table": [[0, 0], [0, 1]]}, "p")


def test_sim_drift_truth_and_temperature(drift_bags):
    bag, truth = drift_bags["thermal"]
    data = read_bag(bag, load_images=False)
    temp = data.temperatures["/temperature"]
    assert len(temp) > 50
    # the ramp 20 -> 50 deg C over 50 s (noise 0.05)
    expect = np.interp(temp.stamps - truth["start_time"], [0, 50], [20, 50])
    assert np.max(np.abs(temp.temperature - expect)) < 0.3
    _, tilt_truth = drift_bags["tilt"]
    v = truth_values(tilt_truth, tilt_truth["start_time"] + np.array([10.0, 40.0]))
    assert v["base_tilt@base_link/tilt_x"].tolist() == [0.0, 0.003]
    assert v["base_tilt@base_link/tilt_y"].tolist() == [-0.001, -0.001]


def test_sim_step_moves_the_tool(tmp_path):
    """The same stops before and after a tilt step: the tracked tool moves by the tilt times its lever arm."""
    raw_stops = {"joint_rate": 50.0, "dwell": 0.3, "move_time": 0.5,
                 "stops": [{"joints": {"joint_2": 0.5, "joint_4": -1.0}}] * 6}
    sc = _scenario("tilt", tmp_path, trajectory=raw_stops,
                   truth={"perturbations": "none", "joint_noise": False, "effects": [
                       {"name": "base_tilt", "location": "base_link",
                        "parameters": {"tilt_x": {"step": {"at": 3.0, "before": 0.0, "after": 0.01}}}}]})
    simulate(sc, tmp_path / "b")
    gt = read_bag(tmp_path / "b", load_images=False).ground_truth_pose
    after = gt.stamps - 100.0 >= 3.0
    assert after.any() and (~after).any()
    p = gt.T[:, :3, 3]
    assert np.ptp(p[~after], axis=0).max() < 1e-3 and np.ptp(p[after], axis=0).max() < 1e-3
    moved = np.linalg.norm(p[after][0] - p[~after][0])
    lever = np.linalg.norm(np.cross([1.0, 0, 0], p[~after][0]))
    assert moved == pytest.approx(0.01 * lever, rel=0.05)


def test_sim_rejects_bad_drift(tmp_path):
    bad = {"perturbations": "none", "effects": [{"name": "time_offset", "location": "/joint_states",
                                                 "parameters": {"dt": {"ramp": {"start": 0, "end": 1, "from": 0,
                                                                                "to": 1}}}}]}
    with pytest.raises(ScenarioError, match="time_offset dt cannot change"):
        simulate(_scenario("tilt", tmp_path, truth=bad), tmp_path / "b")
    thermal = {"effects": [{"name": "thermal_growth", "location": "joint_4", "variable": "temperature",
                            "parameters": {"alpha": 1e-5}}]}
    with pytest.raises(ScenarioError, match="needs the scenario's temperature section"):
        simulate(_scenario("tilt", tmp_path, truth=thermal), tmp_path / "c")


# ----------------------------------------------------------------------------- the filter
def _filter(entries=None, jump=1e-6) -> OnlineEffects:
    model = PPOEModel.from_files(URDF, MODEL)
    return OnlineEffects(model, parse_online_config(entries, model), jump)


Q0 = {"joint_1": 0.3, "joint_2": 0.6, "joint_3": -0.2, "joint_4": -1.2, "joint_5": 0.4, "joint_6": 0.9,
      "joint_7": 0.1, "finger_left_joint": 0.02}


def test_jacobians_match_finite_differences():
    f = _filter([{"name": "base_tilt", "location": "base_link"},
                 {"name": "gravity_compliance", "location": "joint_2"},
                 {"name": "thermal_growth", "location": "joint_4", "variable": "temperature", "reference": 20.0}])
    f.set_temperature(0.0, 45.0)
    f.theta = f.theta + np.array([0.002, -0.001, 1e-4, 1e-4])
    xyz = np.array([0.0, 0.0, 0.02])
    p0, J = f.point(Q0, "tool0", xyz)
    T0, Jt = f.tool_jacobian(Q0, "mount_plate", "tool0")
    th0 = f.theta.copy()
    for i, h in enumerate([1e-6, 1e-6, 1e-7, 1e-7]):
        f.theta = th0.copy()
        f.theta[i] += h
        p1, _ = f.point(Q0, "tool0", xyz)
        T1, _ = f.tool_jacobian(Q0, "mount_plate", "tool0")
        f.theta[i] -= 2 * h
        p2, _ = f.point(Q0, "tool0", xyz)
        T2, _ = f.tool_jacobian(Q0, "mount_plate", "tool0")
        np.testing.assert_allclose((p1 - p2) / (2 * h), J[:, i], atol=1e-6 * max(1, np.abs(J[:, i]).max()))
        fd = (lie.log(lie.inverse(T0) @ T1) - lie.log(lie.inverse(T0) @ T2)) / (2 * h)
        np.testing.assert_allclose(fd, Jt[:, i], atol=1e-5 * max(1, np.abs(Jt[:, i]).max()))
    assert np.abs(J).max() > 0.1  # not a trivially zero Jacobian


def test_gravity_update_jacobian_and_information():
    """An accelerometer update: its H (GravityObservation's state Jacobian times the link's parameter Jacobian)
    matches finite differences of the predicted specific force, and it informs the tilt but not the root's yaw."""
    from ppoe_core.estimation.direct_measurements import GravityObservation

    f = _filter([{"name": "base_tilt", "location": "base_link"}])
    obs = GravityObservation(4e-4)
    T, J = f.tool_jacobian(Q0, "base_link", "arm_link_4")
    H = obs.jacobian_state(T) @ J
    for i in range(2):
        th0 = f.theta.copy()
        f.theta[i] += 1e-6
        a1 = obs.h(f.tool_jacobian(Q0, "base_link", "arm_link_4")[0])
        f.theta[i] -= 2e-6
        a2 = obs.h(f.tool_jacobian(Q0, "base_link", "arm_link_4")[0])
        f.theta = th0
        np.testing.assert_allclose((a1 - a2) / 2e-6, H[:, i], atol=1e-5)
    P0 = f.P.copy()
    f.update_gravity(1.0, Q0, "arm_link_4", obs.h(T), 4e-4)
    assert np.all(np.diag(f.P) < 0.1 * np.diag(P0))
    assert f.counts.gravity == 1


def test_mean_equals_the_model_with_the_estimate():
    """The filter's chain at its estimate is the PPOE model's mean with those effects (one effect math)."""
    f = _filter()
    f.theta = f.theta + 0.001
    T, _ = f.tool_pose(Q0, "base_link", "tool0")
    model = PPOEModel.from_strings(URDF.read_text(), f.model_yaml(yaml.safe_load(MODEL.read_text())))
    np.testing.assert_allclose(model.fk_mean(Q0, "base_link", "tool0"), T, atol=1e-12)
    entries = f.effect_entries()
    assert [e["name"] for e in entries] == ["base_tilt", "gravity_compliance"]
    assert entries[0]["ci"]["tilt_x"] == pytest.approx(1.96 * f.sigmas()[0])


def test_online_config_errors():
    with pytest.raises(ModelConfigError, match=r"online_effects\[0\]: effect 'backlash' cannot be tracked"):
        _filter([{"name": "backlash", "location": "joint_2"}])
    with pytest.raises(ModelConfigError, match=r"online_effects\[0\].process_noise"):
        _filter([{"name": "base_tilt", "location": "base_link", "process_noise": [1e-4, -1.0]}])
    with pytest.raises(ModelConfigError, match="listed twice"):
        _filter([{"name": "base_tilt", "location": "base_link"}] * 2)
    with pytest.raises(ModelConfigError, match="no tracker_registration effect for tracker frame 'laser'"):
        _filter().registration("laser", "/ground_truth/point")


def test_process_noise_rule():
    f = _filter([{"name": "base_tilt", "location": "base_link", "process_noise": 2e-4, "initial_sigma": 0.0}])
    f.predict(10.0)
    f.predict(35.0)
    np.testing.assert_allclose(np.diag(f.P), [(2e-4) ** 2 * 25.0] * 2)
    f.predict(20.0)  # late stamp: no change
    np.testing.assert_allclose(np.diag(f.P), [(2e-4) ** 2 * 25.0] * 2)


# ----------------------------------------------------------------------------- the drift bags
def test_constant_effects_converge_within_ci(evaluations):
    """tilt_y is constant in every bag, alpha in the thermal bag: the final estimate is within 3 sigma."""
    for name, ev in evaluations.items():
        d = ev.to_dict()["parameters"]
        for lab, p in d.items():
            truth_final = ev.truth[lab][-1]
            assert abs(p["final"] - truth_final) <= 3 * p["final_sigma"], (name, lab, p, truth_final)
    alpha = evaluations["thermal"].to_dict()["parameters"]["thermal_growth@joint_4/alpha"]
    assert alpha["final_sigma"] < 0.1 * 1.5e-4  # learnt, not the prior


@pytest.mark.parametrize("name,label", [("tilt", "base_tilt@base_link/tilt_x"),
                                        ("load", "gravity_compliance@joint_2/compliance"),
                                        ("thermal", "thermal_growth@joint_4/alpha"),
                                        ("tilt_imu", "base_tilt@base_link/tilt_x")])
def test_drift_is_followed_with_coverage(evaluations, name, label):
    ev = evaluations[name]
    i = ev.labels.index(label)
    err = np.abs(ev.theta[:, i] - ev.truth[label])
    coverage = np.mean(err <= 3 * ev.sigma[:, i])
    assert coverage >= 0.9, coverage
    assert err[-10:].max() <= 3 * ev.sigma[-10:, i].max()


@pytest.mark.parametrize("name", ["tilt", "load", "thermal", "tilt_imu"])
def test_online_tool_error_stays_fresh_while_static_drifts(evaluations, name):
    d = evaluations[name].to_dict()["tool_error"]
    second = {m: d[m]["position_second_half"]["mean"] for m in d}
    assert second["online"] <= 1.3 * second["fresh"], second
    assert second["static"] >= 1.5 * second["fresh"], second
    assert second["static"] > second["online"]


def test_cli_online_json_equals_api(drift_bags, evaluations, tmp_path):
    bag, truth = drift_bags["tilt"]
    tf = tmp_path / "truth.yaml"
    tf.write_text(yaml.safe_dump(truth))
    cmd = [sys.executable, "-m", "ppoe_ros.cli", "evaluate", str(bag), "--model", str(MODEL), "--online",
           "--online-config", str(ONLINE / "online_effects.yaml"), "--truth", str(tf), "--json",
           "--out", str(tmp_path / "o")]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    want = evaluations["tilt"].to_dict()
    assert got["tool_error"] == want["tool_error"]
    assert got["parameters"] == want["parameters"]
    assert (tmp_path / "o" / "online_parameters.png").stat().st_size > 10_000
    # written back: the diagnosed model with the final estimate, loadable as a model
    written = PPOEModel.from_files(URDF, tmp_path / "o" / "model_online.yaml")
    tilt = next(e for e in written.effects if e.name == "base_tilt")
    np.testing.assert_allclose(tilt.params, evaluations["tilt"].theta[-1][:2])
    assert [e.name for e in written.effects].count("base_tilt") == 1


def test_node_parameter_file_is_the_same_config(tmp_path):
    """``--online-config`` also reads a node parameter file (the live configuration, flat form)."""
    pf = tmp_path / "node.yaml"
    pf.write_text(yaml.safe_dump({"/**": {"ros__parameters": {
        "online_effects": ["base_tilt:base_link", "gravity_compliance:joint_2", "thermal_growth:joint_4"],
        "online_process_noise": [1.0e-5, 1.0e-6, 1.0e-7], "online_initial_sigma": [0.005, 5.0e-4, 3.0e-4],
        "online_thermal_reference": 20.0, "online_jump_probability": 1.0e-6}}}))
    flat, jump = load_online_config(pf)
    listed, jump2 = load_online_config(ONLINE / "online_thermal.yaml")
    assert jump == jump2 == 1e-6
    model = PPOEModel.from_files(URDF, MODEL)
    a, b = parse_online_config(flat, model), parse_online_config(listed, model)
    assert [(t.effect.describe(), list(t.process_noise), list(t.initial_sigma)) for t in a] == \
        [(t.effect.describe(), list(t.process_noise), list(t.initial_sigma)) for t in b]
    assert a[2].effect.variable == "temperature" and a[2].effect.reference == 20.0
    pf.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"online_effects": ["base_tilt"]}}}))
    with pytest.raises(ModelConfigError, match="expected '<effect name>:<location>'"):
        load_online_config(pf)


def test_cli_online_bad_input_is_one_line(drift_bags):
    bag, _ = drift_bags["tilt"]
    cmd = [sys.executable, "-m", "ppoe_ros.cli", "evaluate", str(bag), "--model", str(MODEL), "--online",
           "--online-config", str(ONLINE / "online_thermal.yaml")]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode != 0
    assert "needs /temperature" in r.stderr and "Traceback" not in r.stderr
    with pytest.raises(BagError, match="needs /temperature"):
        evaluate_online(bag, MODEL, [{"name": "thermal_growth", "location": "joint_4", "variable": "temperature"}])
