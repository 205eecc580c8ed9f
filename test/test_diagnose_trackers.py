"""Several reflectors in one fit (contract ``trackers``, ``/ground_truth/point/<name>``), lateral compliance, and
``ppoe diagnose --test`` (fit on some bags, score the fitted model unchanged on others).

The bags are simulated here from a scenario of our own (arm7 with a reflector on the flange and one
on the forearm, an encoder offset at joint_4), with a different seed, registration and stop count
for the fit and the test bag; none is a shipped bag.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import CONFIG

from ppoe_core.errors import BagError, ModelConfigError

TRUE_OFFSET = 0.03  # rad, joint_4 (the tools are never told)
TRACKERS = [
    {"topic": "/ground_truth/point/flange", "link": "tool0", "xyz": [0.0, 0.0, 0.02], "sigma": 0.0002},
    {"topic": "/ground_truth/point/elbow", "link": "arm_link_4", "xyz": [0.06, 0.0, 0.0], "sigma": 0.0002},
]


def _model(tmp: Path, trackers=TRACKERS) -> Path:
    model = yaml.safe_load((CONFIG / "robots" / "arm7_model.yaml").read_text())
    model.pop("tracker")
    model["trackers"] = trackers
    path = tmp / "model_two_reflectors.yaml"
    path.write_text(yaml.safe_dump(model))
    return path


def _bag(tmp: Path, name: str, model: Path, *, seed: int, stops: int, T_tracker_base: dict,
         effects=({"name": "joint_offset", "location": "joint_4", "parameters": {"offset": TRUE_OFFSET}},),
         reflectors=TRACKERS, pert: str = "per_stop", joint_noise: bool = True) -> Path:
    from ppoe_core.sim.simulate import simulate

    sc = {
        "robot": {"urdf": str(CONFIG / "robots" / "arm7.urdf"), "model": str(model)},
        "seed": seed, "start_time": 50.0,
        "truth": {"perturbations": pert, "joint_noise": joint_noise, "effects": [dict(e) for e in effects]},
        "trajectory": {"joint_rate": 100.0, "dwell": 0.4, "settle": 0.1, "move_time": 0.5,
                       "start": {"joint_1": 0.3, "joint_2": 0.6, "joint_3": 0.0, "joint_4": -1.2, "joint_5": 0.0,
                                 "joint_6": 0.9, "joint_7": 0.0, "finger_left_joint": 0.02},
                       "random_stops": {"count": stops,
                                        "around": {"joint_1": 0.0, "joint_2": 0.0, "joint_3": 0.0, "joint_4": -1.0,
                                                   "joint_5": 0.0, "joint_6": 0.5, "joint_7": 0.0},
                                        "spread": {"joint_1": 1.5, "joint_2": 1.2, "joint_3": 1.2, "joint_4": 0.9,
                                                   "joint_5": 1.2, "joint_6": 1.0, "joint_7": 1.5},
                                        "min_link_z": {"tool0": 0.15, "arm_link_4": 0.15}}},
        "ground_truth": {"point": [{"topic": r["topic"], "frame": "tracker", "T_tracker_base": T_tracker_base,
                                    "rate": 0.0} for r in reflectors]},
    }
    (tmp / f"{name}.yaml").write_text(yaml.safe_dump(sc))
    simulate(tmp / f"{name}.yaml", tmp / name)
    return tmp / name


@pytest.fixture(scope="module")
def two_reflector_bags(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("trackers")
    model = _model(tmp)
    fit = _bag(tmp, "fit", model, seed=71, stops=60, T_tracker_base={"xyz": [2.5, -0.8, 0.3], "rpy": [0, 0, 2.0]})
    test = _bag(tmp, "test", model, seed=72, stops=20, T_tracker_base={"xyz": [-1.0, 3.0, 0.1], "rpy": [0, 0.01, -0.7]})
    return model, fit, test


def test_trackers_section_is_read_and_checked():
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.urdf import parse_urdf

    robot = parse_urdf(CONFIG / "robots" / "arm7.urdf")
    cfg = load_model_config({"trackers": TRACKERS}, robot)
    assert [(t.topic, t.link) for t in cfg.trackers] == [(t["topic"], t["link"]) for t in TRACKERS]
    assert cfg.tracker is None  # two reflectors: no single one
    single = load_model_config(CONFIG / "robots" / "arm7_model.yaml", robot)
    assert single.trackers == (single.tracker,) and single.tracker.topic == "/ground_truth/point"
    bad = [("trackers:\n  - {topic: /ground_truth/point/a, link: no_such_link}\n", "trackers[0].link"),
           ("trackers:\n  - {topic: /tracker, link: tool0}\n", "trackers[0].topic: must be /ground_truth/point"),
           ("trackers:\n  - {topic: /ground_truth/point/a, link: tool0}\n"
            "  - {topic: /ground_truth/point/a, link: tool0}\n",
            "trackers[1].topic: topic /ground_truth/point/a is also trackers[0]"),
           ("trackers:\n  - {topic: /ground_truth/point/a, link: tool0, colour: red}\n", "colour")]
    for text, needle in bad:
        with pytest.raises((ModelConfigError, Exception)) as err:
            load_model_config(text, robot, is_text=True)
        assert needle in str(err.value) and "<string>:" in str(err.value)


def test_two_reflectors_on_two_links_are_diagnosed_in_one_fit_and_scored_on_a_test_bag(two_reflector_bags, capsys):
    from ppoe_ros.cli import main

    model, fit, test = two_reflector_bags
    assert main(["diagnose", str(fit), "--model", str(model), "--test", str(test), "--json", "--pixels", "off"]) == 0
    doc = json.loads(capsys.readouterr().out)
    named = [(e["name"], e["location"]) for e in doc["effects"]]
    assert named == [("joint_offset", "joint_4")], named
    lo, hi = doc["effects"][0]["ci"]["offset"]
    assert lo <= TRUE_OFFSET <= hi
    assert doc["residual_after"] < doc["residual_before"] and doc["residual_after"] < 1.1 * doc["noise_floor"]
    assert doc["n_sessions"] == 1  # both reflectors in the frame 'tracker': one registration
    t = doc["test"]["test"]
    n_rows = 2 * 20  # two reflectors per stop
    assert t["n"] == n_rows and t["protocol"].startswith("one rigid registration per session")
    for key in ("rms", "mean", "median", "p95", "max"):
        assert 0.0 < t[key] < t["before"][key], key
    assert t["mean"] <= t["rms"] <= t["max"] and t["median"] <= t["p95"] <= t["max"]


def test_test_scores_equal_a_direct_computation(two_reflector_bags):
    """The ``test`` numbers: after a Kabsch registration of all stops, the distances measured-predicted."""
    from ppoe_core import lie
    from ppoe_core.analysis.diagnose import load_model, stops_from_bag
    from ppoe_core.analysis.diagnose.testing import score_stops
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.model.effects import make_effect
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    model, _, test = two_reflector_bags
    robot = parse_urdf(read_bag(test, topics=["/robot_description"]).robot_description)
    cfg, declared, _, _ = load_model(model, robot)
    stops = stops_from_bag(test, robot, trackers=cfg.trackers)
    tree = KinematicTree(robot)
    eff = make_effect("joint_offset", "joint_4", tree).with_params(np.array([0.01]))
    got = score_stops(robot, stops, declared, [eff])
    q = dict(stops.q)
    q["joint_4"] = q["joint_4"] + 0.01
    poses = tree.link_poses(q)
    links, pts = stops.row_links(), stops.point_rows()
    x = np.stack([(poses[ln][i] @ np.append(pts[i], 1.0))[:3] for i, ln in enumerate(links)])
    T = lie.fit_rigid(x, stops.p_meas)
    d = np.linalg.norm(stops.p_meas - (x @ T[:3, :3].T + T[:3, 3]), axis=1)
    assert got["n"] == len(d)
    np.testing.assert_allclose([got["rms"], got["mean"], got["median"], got["p95"], got["max"]],
                               [np.sqrt(np.mean(d ** 2)), d.mean(), np.median(d), np.percentile(d, 95), d.max()],
                               rtol=1e-9)


def test_a_reflector_topic_the_model_does_not_declare_is_named(two_reflector_bags, tmp_path, capsys):
    from ppoe_ros.cli import main

    _, fit, _ = two_reflector_bags
    only_flange = _model(tmp_path, TRACKERS[:1])
    assert main(["diagnose", str(fit), "--model", str(only_flange), "--pixels", "off"]) == 2
    err = capsys.readouterr().err
    assert "/ground_truth/point/elbow carry reflector points, but the model's trackers list has no entry" in err
    assert "Traceback" not in err


def test_a_test_bag_of_another_robot_is_refused(two_reflector_bags, tmp_path, capsys):
    from ppoe_ros.cli import main

    model, fit, _ = two_reflector_bags
    other = tmp_path / "other"
    from ppoe_core.io.bagio import BagWriter

    with BagWriter(other) as bag:
        bag.write_robot_description((CONFIG / "robots" / "planar3.urdf").read_text())
        bag.write_joint_state(1.0, ["joint_1"], [0.0])
    assert main(["diagnose", str(fit), "--model", str(model), "--test", str(other), "--pixels", "off"]) == 2
    err = capsys.readouterr().err
    assert f"bag {other}: /robot_description is another robot than bag {fit}'s" in err
    assert "joints only in the fitted robot" in err and "Traceback" not in err
    with pytest.raises(BagError):  # and through the library
        from ppoe_core.analysis.diagnose.testing import check_same_robot
        from ppoe_core.robot.urdf import parse_urdf

        check_same_robot(parse_urdf(CONFIG / "robots" / "arm7.urdf"), parse_urdf(CONFIG / "robots" / "planar3.urdf"),
                         "a", "b")


def test_named_points_and_temperature_are_read(tmp_path):
    from ppoe_core.io.bagio import BagWriter, read_bag

    with BagWriter(tmp_path / "b") as bag:
        for k in range(4):
            bag.write_ground_truth_point(k, "trk", [k, 1.0, 2.0], topic="/ground_truth/point/left")
            bag.write_temperature(k + 0.5, "base_link", 20.0 + k, 0.01, topic="/temperature/motor")
    data = read_bag(tmp_path / "b")
    assert data.ground_truth_points["/ground_truth/point/left"].p[:, 0].tolist() == [0.0, 1.0, 2.0, 3.0]
    temp = data.temperatures["/temperature/motor"]
    assert temp.temperature.tolist() == [20.0, 21.0, 22.0, 23.0] and temp.variance.tolist() == [0.01] * 4
    assert data.unknown_topics == {}


def test_evaluate_scores_the_reflector_on_the_tool_link(two_reflector_bags, tmp_path, capsys):
    """Two reflectors: ``ppoe evaluate`` scores the one on the tool link (frames.tool = tool0) and says which;
    with ``--tool`` on a link that carries none of them it says what to do."""
    from ppoe_ros.cli import main

    model, _, test = two_reflector_bags
    assert main(["evaluate", str(test), "--model", str(model), "--json", "--no-progress"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ground_truth"]["topic"] == "/ground_truth/point/flange"
    assert doc["ground_truth"]["samples"] == 20
    assert main(["evaluate", str(test), "--model", str(model), "--tool", "arm_link_6", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "several reflectors" in err and "pass --tool with the link" in err and "Traceback" not in err


def test_lateral_compliance_alone_is_named_with_the_truth_in_its_cis(tmp_path, capsys):
    """A bag whose only undeclared effect is lateral compliance at the upper-arm roll joint (bending about both
    axes perpendicular to it, 3e-4 rad/(N m) each): named at that joint, each axis's CI covers the truth."""
    from ppoe_ros.cli import main

    model = _model(tmp_path)
    truth = {"compliance_u": 3e-4, "compliance_v": 3e-4}
    bag = _bag(tmp_path, "lateral", model, seed=81, stops=60, T_tracker_base={"xyz": [1.5, 0.5, 0.2], "rpy": [0, 0, 1]},
               effects=({"name": "lateral_compliance", "location": "joint_3", "parameters": truth},))
    assert main(["diagnose", str(bag), "--model", str(model), "--json", "--pixels", "off"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(e["name"], e["location"]) for e in doc["effects"]] == [("lateral_compliance", "joint_3")]
    for k, v in truth.items():
        lo, hi = doc["effects"][0]["ci"][k]
        assert lo <= v <= hi, (k, lo, hi)
    assert doc["unexplained_significant"] is False


def test_two_encoder_offsets_are_two_joint_offsets_not_one_link_error(tmp_path, capsys):
    """Two effects at once: encoder offsets at joint_2 and joint_3.  One link_error at joint_3 explains both
    (an upstream offset turns the downstream frame); the selection names the two one-parameter joint_offsets
    instead, each with the truth in its CI."""
    from ppoe_ros.cli import main

    model = _model(tmp_path)
    truth = {"joint_2": 0.02, "joint_3": -0.03}
    bag = _bag(tmp_path, "two", model, seed=5, stops=60, T_tracker_base={"xyz": [1.5, 0.5, 0.2], "rpy": [0, 0, 1]},
               effects=tuple({"name": "joint_offset", "location": j, "parameters": {"offset": v}}
                             for j, v in truth.items()))
    out = tmp_path / "out_two"  # the report's plot labels the selection steps (one) though two effects are named
    assert main(["diagnose", str(bag), "--model", str(model), "--json", "--pixels", "off", "--out", str(out)]) == 0
    assert (out / "diagnose.png").stat().st_size > 0
    doc = json.loads(capsys.readouterr().out)
    assert sorted((e["name"], e["location"]) for e in doc["effects"]) == [("joint_offset", "joint_2"),
                                                                            ("joint_offset", "joint_3")]
    for e in doc["effects"]:
        lo, hi = e["ci"]["offset"]
        assert lo <= truth[e["location"]] <= hi, e
    # a link_error at joint_3 was named on the way (it explains both) and replaced by the backward pass, or the
    # offsets were named directly: either way no link_error is left
    assert not any(e["name"] == "link_error" for e in doc["effects"])


def test_calibrated_urdf_reproduces_the_corrected_fk_and_loads_everywhere(two_reflector_bags, tmp_path, capsys):
    """``--out`` writes robot_calibrated.urdf (static effects folded into the joint origins) and
    model_calibrated.yaml (the model without them): the calibrated URDF's nominal FK equals the original URDF
    corrected by the found effects to 1e-9 m; ``ppoe fk``, ``ppoe evaluate --urdf`` and the library load them."""
    from ppoe_core.analysis.diagnose.calibrated_urdf import calibrated_urdf
    from ppoe_core.model.effects import effect_from_config, make_effect, sum_effect_corrections
    from ppoe_core.model.ppoe import PPOEModel
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf
    from ppoe_ros.cli import main

    model, fit, test = two_reflector_bags
    out = tmp_path / "cal"
    assert main(["diagnose", str(fit), "--model", str(model), "--out", str(out), "--pixels", "off"]) == 0
    capsys.readouterr()
    urdf0 = parse_urdf(CONFIG / "robots" / "arm7.urdf")
    urdf1 = parse_urdf(out / "robot_calibrated.urdf")
    doc = json.loads((out / "diagnose.json").read_text())
    found = [effect_from_config(e, urdf0) for e in doc["effects"]]
    assert [e.describe() for e in found] == ["joint_offset@joint_4"]
    rng = np.random.default_rng(9)
    q = {j: rng.uniform(-2, 2, 40) for j in urdf0.independent_joints}
    dq, dxi = sum_effect_corrections(found, q, {})
    P0, P1 = KinematicTree(urdf0).link_poses(q, dq, dxi), KinematicTree(urdf1).link_poses(q)
    assert max(float(np.abs(P0[ln] - P1[ln]).max()) for ln in P0) < 1e-9
    cal_model = yaml.safe_load((out / "model_calibrated.yaml").read_text())
    assert not any(e["name"] == "joint_offset" for e in cal_model.get("effects") or [])
    PPOEModel.from_files(out / "robot_calibrated.urdf", out / "model_calibrated.yaml")  # the library loads it
    q1 = {f"joint_{k}": 0.1 * k for k in range(1, 8)}
    assert main(["fk", "--urdf", str(out / "robot_calibrated.urdf"), "--model", str(out / "model_calibrated.yaml"),
                 "--from", "base_link", "--to", "tool0", "--joints", *[f"{k}={v}" for k, v in q1.items()],
                 "--json"]) == 0
    fk = json.loads(capsys.readouterr().out)
    T0 = KinematicTree(urdf0).link_poses({k: np.array(v) for k, v in q1.items()},
                                         {"joint_4": found[0].params[0]}, links=["tool0"])["tool0"]
    np.testing.assert_allclose(fk["T"], T0, atol=1e-9)
    assert main(["evaluate", str(test), "--model", str(out / "model_calibrated.yaml"), "--urdf",
                 str(out / "robot_calibrated.urdf"), "--json", "--no-progress"]) == 0
    cal = json.loads(capsys.readouterr().out)["methods"]["fk"]["position_3d"]["rms"]
    assert main(["evaluate", str(test), "--model", str(model), "--json", "--no-progress"]) == 0
    nominal = json.loads(capsys.readouterr().out)["methods"]["fk"]["position_3d"]["rms"]
    assert cal < nominal
    # mimic joints follow a corrected master; comments of the URDF are kept
    tree = KinematicTree(urdf0)
    text, rest = calibrated_urdf((CONFIG / "robots" / "arm7.urdf").read_text(), urdf0,
                                 [make_effect("link_error", "camera_joint", tree).with_params(np.full(6, 0.01)),
                                  make_effect("gravity_compliance", "joint_2", tree).with_params([1e-4])])
    assert [e.describe() for e in rest] == ["gravity_compliance@joint_2"] and "calibrated by ppoe diagnose" in text
    fingers = [make_effect("joint_offset", "finger_left_joint", tree).with_params([0.004])]
    text, _ = calibrated_urdf((CONFIG / "robots" / "arm7.urdf").read_text(), urdf0, fingers)
    dq, dxi = sum_effect_corrections(fingers, q, {})
    P0, P1 = tree.link_poses(q, dq, dxi), KinematicTree(parse_urdf(text)).link_poses(q)
    assert np.abs(P0["finger_right"] - P1["finger_right"]).max() < 1e-12  # the mimic follower moved too
    assert np.abs(P0["finger_right"] - tree.link_poses(q)["finger_right"]).max() > 1e-3


def test_temperature_becomes_the_thermal_growth_variable(tmp_path):
    """A bag with /temperature varying by more than 1 K: the stops carry it as context and thermal_growth is
    proposed against it (not against time); without it, a short bag gets no thermal candidate."""
    from ppoe_core.analysis.diagnose import candidate_effects, stops_from_bag
    from ppoe_core.io.bagio import BagWriter
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    urdf = (CONFIG / "robots" / "planar3.urdf").read_text()
    robot = parse_urdf(urdf)
    rng = np.random.default_rng(2)
    for with_temp in (True, False):
        path = tmp_path / f"t{with_temp}"
        with BagWriter(path) as bag:
            bag.write_robot_description(urdf)
            for k in range(12):
                t = 10.0 + 5.0 * k
                q = rng.uniform(-1, 1, 3)
                for m in range(5):
                    bag.write_joint_state(t + 0.01 * m, ["joint1", "joint2", "joint3"], q)
                bag.write_ground_truth_point(t + 0.1, "tracker", rng.normal(size=3))
                if with_temp:
                    bag.write_temperature(t + 0.05, "base_link", 20.0 + 0.5 * k)
        stops = stops_from_bag(path, robot, tracker_link="link3")
        thermal = [e for e in candidate_effects(KinematicTree(robot), stops) if e.name == "thermal_growth"]
        if with_temp:
            np.testing.assert_allclose(stops.context["temperature"], 20.0 + 0.5 * np.arange(12), atol=0.03)
            assert thermal and all(e.variable == "temperature" and e.reference == pytest.approx(20.0, abs=0.03)
                                   for e in thermal)
        else:
            assert "temperature" not in stops.context and not thermal


def test_backlash_alone_reaches_the_noise_floor(tmp_path, capsys):
    """A bag whose only error is 2 mrad of backlash at joint_2 (quiet model: no perturbations drawn, 0.2 mm
    tracker): named at joint_2 with the truth in its CI, and the held-out residual ends at the noise floor."""
    from ppoe_ros.cli import main

    model = _model(tmp_path)
    m = yaml.safe_load(model.read_text())
    m["perturbations"], m["joint_noise"] = {}, {f"joint_{k}": 1e-5 for k in range(1, 8)}
    model.write_text(yaml.safe_dump(m))
    bag = _bag(tmp_path, "bl", model, seed=7, stops=60, T_tracker_base={"xyz": [1.5, 0.5, 0.2], "rpy": [0, 0, 1]},
               effects=({"name": "backlash", "location": "joint_2", "parameters": {"play": 0.002}},),
               pert="none", joint_noise=False)
    assert main(["diagnose", str(bag), "--model", str(model), "--json", "--pixels", "off"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(e["name"], e["location"]) for e in doc["effects"]] == [("backlash", "joint_2")]
    lo, hi = doc["effects"][0]["ci"]["play"]
    assert lo <= 0.002 <= hi
    assert doc["residual_before"] > 2 * doc["noise_floor"]
    assert doc["residual_after"] < 1.1 * doc["noise_floor"]


@pytest.mark.parametrize("effects,pert,significant", [
    ((), "per_stop", False),
    (({"name": "transmission_error", "location": "joint_2", "parameters": {"amplitude": 0.01, "periods": 3}},),
     "none", True),
], ids=["no_effect", "outside_the_catalogue"])
def test_nothing_is_forced_onto_the_catalogue(tmp_path, capsys, effects, pert, significant):
    """Two reflectors, no undeclared effect (the model's random errors drawn at every stop): nothing found and no
    significant remainder; an error outside the catalogue (a transmission error, sinusoidal in the joint angle)
    under the declared prior, which is then loose (no random errors drawn; CONTRACT sec. 6: significance from
    held-out structure, not from the prior): nothing forced onto a wrong effect, the remainder flagged
    unexplained_significant and attributed to joint_2's configuration."""
    from ppoe_ros.cli import main

    model = _model(tmp_path)
    bag = _bag(tmp_path, "b", model, seed=17, stops=60, T_tracker_base={"xyz": [0.5, 1.5, 0.2], "rpy": [0, 0, -0.3]},
               effects=effects, pert=pert)
    assert main(["diagnose", str(bag), "--model", str(model), "--json", "--pixels", "off"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["effects"] == [] and doc["unexplained_significant"] is significant, doc["summary"]
    if significant:
        tests = doc["measurements"]["tracker"]["structure"]
        assert [t["predictor"] for t in tests if t["significant"]] == ["configuration of joint_2"]


def test_a_camera_stamped_late_gets_a_time_offset_within_ten_percent(tmp_path, capsys):
    """Images stamped 40 ms after their exposure while the arm moves (8 Hz images during the whole bag, no other
    error): the pixel stage names a time_offset of that camera with dt = -40 ms within 10 % (dt is the exposure
    time minus the stamp), not camera extrinsics."""
    from ppoe_core.sim.simulate import simulate
    from ppoe_ros.cli import main

    sc = yaml.safe_load((CONFIG.parent / "bags" / "effect_camera_extrinsics.yaml").read_text())
    sc["robot"] = {"urdf": str(CONFIG / "robots" / "arm7.urdf"), "model": str(CONFIG / "robots" / "arm7_model.yaml")}
    sc["seed"] = 404
    sc["truth"].update(effects=[], perturbations="none", joint_noise=False)
    sc["trajectory"].update(dwell=0.3, move_time=1.0)
    sc["trajectory"]["random_stops"]["count"] = 20
    sc["camera"].update(rate=8.0, during="always", time_offset=0.04)
    sc["ground_truth"].pop("pose")
    (tmp_path / "sc.yaml").write_text(yaml.safe_dump(sc))
    simulate(tmp_path / "sc.yaml", tmp_path / "bag")
    assert main(["diagnose", str(tmp_path / "bag"), "--model", str(CONFIG / "robots" / "arm7_model.yaml"),
                 "--json", "--pixels", "on"]) == 0
    doc = json.loads(capsys.readouterr().out)
    pix = [e for e in doc["effects"] if e["name"] in ("time_offset", "camera_extrinsics")]
    assert [(e["name"], e["location"]) for e in pix] == [("time_offset", "camera_optical_frame")], doc["summary"]
    assert abs(pix[0]["parameters"]["dt"] - (-0.04)) < 0.004
    before, after = doc["pixels"]["pixel_rms_before"], doc["pixels"]["pixel_rms_after"]
    assert after["camera_optical_frame"] < 0.3 * before["camera_optical_frame"]
