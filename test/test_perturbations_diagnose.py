"""``diagnose(..., learn_perturbations=True)`` / ``ppoe diagnose --learn-perturbations``: the learned covariances
in the result's JSON, the cross-fitted check of the three covariance choices, and the diagnosed model YAML (comments
kept) carrying the learned ``perturbations``."""

from __future__ import annotations

import numpy as np
import pytest
from ruamel.yaml import YAML

from perturbation_sim import DECLARED, TRUTH, sigma_matrices, simulate_poses, soft5
from ppoe_core.analysis.diagnose import DiagnoseOptions, diagnose, write_model_yaml

MODEL_YAML = """\
# the soft5 test arm's model
perturbations:   # paper eq. 16
  j1:
    sigma: [0.0002, 0.0002, 0.0002, 0.001, 0.001, 0.001]   # declared by the user
  j2:
    sigma: [0.0002, 0.0002, 0.0002, 0.001, 0.001, 0.001]
  j3:
    sigma: [0.0002, 0.0002, 0.0002, 0.001, 0.001, 0.001]
  j4:
    sigma: [0.0002, 0.0002, 0.0002, 0.001, 0.001, 0.001]
  j5:
    sigma: [0.0002, 0.0002, 0.0002, 0.001, 0.001, 0.001]
"""


@pytest.fixture(scope="module")
def result():
    robot = soft5()
    stops = simulate_poses(robot, sigma_matrices(robot, TRUTH), 500, seed=21)
    return diagnose(robot, stops, perturbation_cov=sigma_matrices(robot, DECLARED),
                    options=DiagnoseOptions(learn_perturbations=True, folds=4))


def test_json_and_check(result):
    js = result.to_json()
    lp = js["learned_perturbations"]
    assert lp["block"] == "pose"
    names = {f"{'+'.join(c['joints'])}/{c['axis']}" for c in lp["components"]}
    assert "j2/lateral" in names, names
    soft = next(c for c in lp["components"] if c["joints"] == ["j2"] and c["axis"] == "lateral")
    assert soft["sigma_ci"][0] <= 5e-3 <= soft["sigma_ci"][1]
    check = lp["check"]
    assert set(check) == {"declared", "global_scale", "learned"}
    assert check["learned"]["n"] == 500
    # cross-fitted held-out: the learned covariances predict better than one global scale, which beats the
    # declared ones (NEES far from 6 there)
    assert check["learned"]["loglik_per_row"] > check["global_scale"]["loglik_per_row"]
    assert check["global_scale"]["loglik_per_row"] > check["declared"]["loglik_per_row"]
    assert abs(check["learned"]["nees"] - 6.0) < 0.6
    assert "learned perturbations (pose)" in result.summary
    # without the option nothing is added
    assert "learned_perturbations" not in _plain().to_json()


def _plain():
    robot = soft5()
    stops = simulate_poses(robot, sigma_matrices(robot, TRUTH), 60, seed=22)
    return diagnose(robot, stops, perturbation_cov=sigma_matrices(robot, DECLARED), options=DiagnoseOptions(folds=3))


def test_model_yaml_gets_the_learned_covariances(result, tmp_path):
    src = tmp_path / "model.yaml"
    src.write_text(MODEL_YAML)
    out = write_model_yaml(src, result, tmp_path / "model_diagnosed.yaml")
    text = out.read_text()
    assert "# declared by the user" in text and "# paper eq. 16" in text
    assert "perturbations learned from the held-out residual" in text
    doc = YAML(typ="safe").load(text)
    C = result.learned_prior.covariances
    for jn, entry in doc["perturbations"].items():
        if jn in C:
            want = np.sqrt(np.diag(C[jn])) if "sigma" in entry else np.asarray(C[jn])
            got = np.asarray(entry.get("sigma", entry.get("covariance")), dtype=float)
            np.testing.assert_allclose(got, want, rtol=1e-12)
    # j2 (axis y): its lateral variance sits on rot_x and rot_z
    s2 = np.asarray(doc["perturbations"]["j2"]["sigma"])
    assert s2[3] == pytest.approx(s2[5]) and s2[3] > 3e-3 > s2[4]


def test_report_has_the_learned_section(result, tmp_path):
    from ppoe_core.analysis.diagnose import write_report

    paths = write_report(result, tmp_path, title="soft5")
    md = paths["md"].read_text()
    assert "## Learned perturbations" in md
    assert "| j2 | lateral |" in md
    for choice in ("declared", "global_scale", "learned"):
        assert f"| {choice} |" in md


def test_joints_the_block_does_not_see_keep_their_declared_covariance(result, tmp_path):
    src = tmp_path / "model.yaml"
    src.write_text(MODEL_YAML + "  tool_joint:\n    sigma: [0.001, 0.0, 0.0, 0.0, 0.0, 0.0]   # unseen\n"
                   "joint_noise:\n  j1: 0.0005   # encoder\n")
    lp = result.learned_prior
    lp_unseen = type(lp)(lp.block, lp.fit, {k: v for k, v in lp.covariances.items()}, lp.check, lp.split,
                         [j for j in lp.joints if j != "tool_joint"])
    res = type(result)(**{**result.__dict__, "learned_prior": lp_unseen})
    doc = YAML(typ="safe").load(write_model_yaml(src, res, tmp_path / "out.yaml").read_text())
    assert doc["perturbations"]["tool_joint"]["sigma"] == [0.001, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert "j1" not in (doc.get("joint_noise") or {})  # the learned axial class holds it
    assert lp.best == "learned"


@pytest.mark.parametrize("best", ["global_scale", "declared"])
def test_learned_covariances_are_not_written_when_the_check_prefers_another(result, tmp_path, best):
    """The held-out check decides: when the declared prior (scaled, or as it is) predicts the held-out rows
    better than the learned covariances, the YAML keeps the declared sigmas and its header says why."""
    import dataclasses

    src = tmp_path / "model.yaml"
    src.write_text(MODEL_YAML)
    lp = result.learned_prior
    top = max(c.loglik for c in lp.check.values())
    check = {name: dataclasses.replace(c, loglik=top + 1.0 if name == best else c.loglik)
             for name, c in lp.check.items()}
    res = type(result)(**{**result.__dict__, "learned_prior": dataclasses.replace(lp, check=check)})
    assert res.learned_prior.best == best
    text = write_model_yaml(src, res, tmp_path / "out.yaml").read_text()
    assert f"learned covariances are NOT written: the held-out check's best log-likelihood is '{best}'" in text
    assert "perturbations learned from the held-out residual" not in text
    doc = YAML(typ="safe").load(text)
    k = result.sigma_scale if best == "global_scale" else 1.0
    for jn in ("j1", "j2", "j5"):
        np.testing.assert_allclose(doc["perturbations"][jn]["sigma"],
                                   k * np.array([0.0002, 0.0002, 0.0002, 0.001, 0.001, 0.001]), rtol=1e-12)


def test_cli_on_a_shipped_tracker_bag():
    """A tracker bag of the arm7 (few stops, mount plate dominant): this start was numerically singular once."""
    import contextlib
    import io
    import json

    from conftest import BAGS, CONFIG

    from ppoe_ros.cli import main

    bag = BAGS / "effect_joint_offset"
    if not bag.exists():
        pytest.fail(f"shipped bag {bag} is missing (bags/make_bags.sh regenerates it)")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["diagnose", str(bag), "--model", str(CONFIG / "robots" / "arm7_model.yaml"), "--json",
                     "--quiet", "--learn-perturbations"]) == 0
    lp = json.loads(out.getvalue())["learned_perturbations"]
    assert lp["block"] == "tracker" and lp["components"]
    assert "camera_joint" not in lp["joints"]  # the tracker does not see the camera mount
    assert lp["best_heldout"] in ("declared", "global_scale", "learned")
