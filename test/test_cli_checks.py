"""Numbers checked at parse time in every subcommand, and ``ppoe diagnose``'s bags checked before the fit
(issue 25; :mod:`ppoe_core.cli.checks`).  Was: ``--folds 0`` printed "held-out RMS nan mm", ``--folds 1``
trained on an empty set, ``--min-gain nan`` turned selection off, ``--max-effects 0`` blamed the catalogue,
two fit bags of different URDFs used the first URDF for both, the same bag twice shrank the CIs, a bad
``--test`` directory was found after the whole fit, ``process_noise: 0, initial_sigma: 0`` froze the filter."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import BAGS, CONFIG_ROBOTS

from ppoe_core.io.bagio import BagWriter
from ppoe_ros.cli import main

ARM7_URDF = CONFIG_ROBOTS / "arm7.urdf"
ARM7_MODEL = CONFIG_ROBOTS / "arm7_model.yaml"
NO_EFFECT = BAGS / "no_effect"

BAD_NUMBERS = [
    (["diagnose", "B", "--model", "M"], "--folds", ["0", "1", "nan", "2.5"], "must be an integer >= 2"),
    (["diagnose", "B", "--model", "M"], "--min-gain", ["nan", "1", "-0.1", "inf"],
     "must be a finite number >= 0 and < 1"),
    (["diagnose", "B", "--model", "M"], "--max-effects", ["0", "-3"], "must be an integer >= 1"),
    (["diagnose", "B", "--model", "M"], "--min-t", ["nan", "-1"], "must be a finite number >= 0"),
    (["diagnose", "B", "--model", "M"], "--pixel-sigma", ["0", "nan"], "must be a finite number > 0"),
    (["evaluate", "B", "--model", "M"], "--iterations", ["0", "101"], "must be an integer >= 1 and <= 100"),
    (["evaluate", "B", "--model", "M"], "--gate", ["nan", "0.2", "2"], "must be a finite number >= 0.5 and <= 1"),
    (["evaluate", "B", "--model", "M"], "--pixel-sigma", ["-1", "nan"], "must be a finite number >= 0"),
    (["simulate", "S.yaml", "--out", "O"], "--seed", ["-1", "x"], "must be an integer >= 0"),
    (["play", "B"], "--rate", ["0", "nan", "inf"], "must be a finite number > 0"),
    (["play", "B"], "--clock-hz", ["inf", "-5"], "must be a finite number > 0"),
    (["play", "B"], "--delay", ["-1", "nan"], "must be a finite number >= 0"),
    (["play", "B"], "--wait-for-subscribers", ["nan"], "must be a finite number >= 0"),
    (["record", "/t", "--out", "O"], "--duration", ["nan", "-1", "inf"], "must be a finite number >= 0"),
    (["record", "/t", "--out", "O"], "--max-messages", ["-1"], "must be an integer >= 0"),
    (["record", "/t", "--out", "O"], "--flush-period", ["0", "nan"], "must be a finite number > 0"),
]


@pytest.mark.parametrize("args,option,values,needle", BAD_NUMBERS, ids=[f"{a[0]}{o}" for a, o, _, _ in BAD_NUMBERS])
def test_numbers_out_of_range_or_nan_are_refused_at_parse_time(capsys, args, option, values, needle):
    for value in values:
        with pytest.raises(SystemExit) as exc:
            main([*args, f"{option}={value}"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and f"argument {option}: {needle}, got '{value}'" in err, err


def test_numbers_in_range_still_parse():
    from ppoe_ros.cli import build_parser

    a = build_parser("diagnose").parse_args(["diagnose", "B", "--model", "M", "--folds", "2", "--min-gain", "0",
                                             "--max-effects", "1", "--min-t", "0", "--pixel-sigma", "0.5"])
    assert (a.folds, a.min_gain, a.max_effects, a.min_t, a.pixel_sigma) == (2, 0.0, 1, 0.0, 0.5)
    r = build_parser("record").parse_args(["record", "/t", "--out", "O", "--duration", "0", "--max-messages", "0"])
    assert (r.duration, r.max_messages, r.flush_period) == (0.0, 0, 0.5)


# ----------------------------------------------------------------------------- diagnose's bags


def _bag_of(path: Path, urdf_text: str, seed: int) -> Path:
    """A few static stops of arm7 (joint states and tracker points): enough for the checks, not for a fit."""
    rng = np.random.default_rng(seed)
    names = [f"joint_{k}" for k in range(1, 8)]
    with BagWriter(path) as bag:
        bag.write_robot_description(urdf_text, 0.0)
        for s in range(4):
            t = 1.0 + 2.0 * s
            q = rng.uniform(-1, 1, 7)
            for k in range(5):
                bag.write_joint_state(t + 0.02 * k, names, q)
            bag.write_ground_truth_point(t + 0.1, "tracker", rng.normal(size=3))
    return path


def _refused(capsys, args: list[str], monkeypatch) -> str:
    """Run ``ppoe diagnose``; the fit must not start (the checks come first)."""
    import ppoe_core.analysis.diagnose as diag

    def no_fit(*a, **k):
        raise AssertionError("the fit started before the inputs were checked")

    monkeypatch.setattr(diag, "diagnose", no_fit)
    monkeypatch.setattr(diag, "stops_from_bag", no_fit)
    assert main(["diagnose", *args, "--model", str(ARM7_MODEL), "--pixels", "off"]) == 2
    return capsys.readouterr().err


def test_fit_bags_of_different_urdfs_are_refused_naming_the_joints(tmp_path, capsys, monkeypatch):
    text = ARM7_URDF.read_text()
    a = _bag_of(tmp_path / "a", text, 1)
    import re

    longer = re.sub(r'(<joint name="joint_4".*?<origin xyz=")([^"]*)"',
                    lambda m: m.group(1) + " ".join(f"{float(v) + (0.1 if i == 2 else 0):g}"
                                                    for i, v in enumerate(m.group(2).split())) + '"',
                    text, count=1, flags=re.S)
    assert longer != text
    b = _bag_of(tmp_path / "b", longer, 2)
    err = _refused(capsys, [str(a), str(b)], monkeypatch)
    assert f"bag {b}: /robot_description is another robot than bag {a}'s (joint_4: origin xyz [0, 0, 0.2155] vs " \
        "[0, 0, 0.3155])" in err, err
    assert "fit bags must all record one robot" in err


def test_the_same_bag_twice_is_refused(tmp_path, capsys, monkeypatch):
    a = _bag_of(tmp_path / "a", ARM7_URDF.read_text(), 1)
    err = _refused(capsys, [str(a), str(a)], monkeypatch)
    assert f"bag {a}: given twice (fit bags): its stops would count twice" in err, err
    copy = tmp_path / "copy_of_a"
    shutil.copytree(a, copy)
    err = _refused(capsys, [str(a), str(copy)], monkeypatch)
    assert f"bag {copy}: the same recording as bag {a} (fit bags)" in err, err
    err = _refused(capsys, [str(a), "--test", str(copy)], monkeypatch)
    assert "as a fit bag and a --test bag: a test bag must be held out" in err, err


def test_bad_test_directories_are_found_before_the_fit(tmp_path, capsys, monkeypatch):
    empty = tmp_path / "empty"
    empty.mkdir()
    for bad, needle in ((tmp_path / "missing", "does not exist"), (empty, "cannot open as a rosbag2 directory")):
        err = _refused(capsys, [str(NO_EFFECT), "--test", str(bad)], monkeypatch)
        assert f"bag {bad}" in err and needle in err, err
    other = _bag_of(tmp_path / "planar", (CONFIG_ROBOTS / "planar3.urdf").read_text(), 3)
    err = _refused(capsys, [str(NO_EFFECT), "--test", str(other)], monkeypatch)
    assert f"bag {other}: /robot_description is another robot" in err and "a test bag must record the fitted" in err


# ----------------------------------------------------------------------------- online config


def test_online_config_that_can_never_move_is_refused_naming_file_and_key(tmp_path, capsys):
    cfg = tmp_path / "online.yaml"
    cfg.write_text("online_effects:\n  - {name: base_tilt, location: base_link, process_noise: 0, initial_sigma: 0}\n")
    code = main(["evaluate", str(NO_EFFECT), "--model", str(ARM7_MODEL), "--online", "--online-config",
                 str(cfg)])
    err = capsys.readouterr().err
    assert code == 2 and f"online config {cfg}: online_effects[0] (base_tilt@base_link): process_noise and " \
        "initial_sigma are both 0: the filter could never move it" in err, err
    cfg.write_text("online_effects:\n  - {name: base_tilt, location: base_link, process_noise: .nan}\n")
    assert main(["evaluate", str(NO_EFFECT), "--model", str(ARM7_MODEL), "--online", "--online-config",
                 str(cfg)]) == 2
    assert "online_effects[0] (base_tilt@base_link).process_noise: expected non-negative finite" in \
        capsys.readouterr().err


def test_online_parse_refuses_both_zero_for_the_node_too():
    from ppoe_core import PPOEModel
    from ppoe_core.errors import ModelConfigError
    from ppoe_core.estimation.online_effects import entries_from_flat, parse_online_config

    model = PPOEModel.from_files(ARM7_URDF, ARM7_MODEL)
    entries = entries_from_flat(["base_tilt:base_link"], [0.0], [0.0], 20.0)
    with pytest.raises(ModelConfigError, match=r"online_effects\[0\]: process_noise and initial_sigma are both 0"):
        parse_online_config(entries, model)
    assert len(parse_online_config(entries_from_flat(["base_tilt:base_link"], [0.0], [0.01], 20.0), model)) == 1


# ----------------------------------------------------------------------------- messages cite the user's file


def _bad_model(tmp_path: Path) -> Path:
    text = ARM7_MODEL.read_text().replace("\n  joint_1: 0.0005", "\n  joint_99: 0.0005", 1)
    assert "joint_99" in text
    path = tmp_path / "bad_model.yaml"
    path.write_text(text)
    return path


def test_online_evaluate_names_the_bags_urdf_not_a_string(tmp_path, capsys):
    """Was: "unknown joint 'joint_99' (not in URDF <string>)"."""
    model = _bad_model(tmp_path)
    assert main(["evaluate", str(NO_EFFECT), "--model", str(model), "--online"]) == 2
    err = capsys.readouterr().err
    assert f"{model}:" in err and f"(not in URDF bag {NO_EFFECT} /robot_description)" in err and "<string>" not in err


@pytest.mark.ros
def test_kinematics_node_names_where_its_urdf_came_from(tmp_path):
    pytest.importorskip("rclpy")
    from ros_helpers import NodeProcess, ros_env, write_params_file

    model = _bad_model(tmp_path)
    params = write_params_file(tmp_path / "p.yaml", {"robot_description": ARM7_URDF.read_text(),
                                                     "model_file": str(model)})
    proc = NodeProcess.node("kinematics_node", ros_env(tmp_path), tmp_path, params_file=params)
    try:
        code = proc.wait(60)
    finally:
        proc.stop()
    out = proc.output()
    assert code == 2 and "(not in URDF parameter robot_description)" in out and "<string>" not in out, out
