"""``ppoe fk`` (CONTRACT.md sec. 6): JSON equals PPOEModel.fk, cov_ros = B cov B^T, batch row
order, text output, and every bad input -> exit code 2 with a message naming the item."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO
from hypothesis import given, settings
from hypothesis import strategies as st

from ppoe_core import lie
from ppoe_core.cli.fk import parse_joint_assignments
from ppoe_core.errors import JointValueError, UnknownJointError
from ppoe_core.model.ppoe import PPOEModel
from ppoe_ros.cli import main

URDF = str(REPO / "config" / "robots" / "planar3.urdf")
MODEL = str(REPO / "config" / "robots" / "planar3_model.yaml")
ARM7_URDF = str(REPO / "config" / "robots" / "arm7.urdf")
ARM7_MODEL = str(REPO / "config" / "robots" / "arm7_model.yaml")
BASE = ["fk", "--urdf", URDF, "--model", MODEL, "--from", "base_link", "--to", "tool0"]


@pytest.fixture(scope="module")
def planar3() -> PPOEModel:
    return PPOEModel.from_files(URDF, MODEL)


def _ros_cov(T: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """CONTRACT sec. 2, written out independently: B cov B^T with B = blockdiag(R, R)."""
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = T[:3, :3]
    return B @ cov @ B.T


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _check_doc(doc: dict, T: np.ndarray, cov: np.ndarray) -> None:
    assert set(doc) == {"T", "cov_local", "cov_ros"}
    # batched and single evaluations may differ in the last bit
    np.testing.assert_allclose(np.array(doc["T"]), T, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.array(doc["cov_local"]), cov, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.array(doc["cov_ros"]), _ros_cov(T, cov), rtol=1e-12, atol=1e-16)


@pytest.mark.parametrize("order", [2, 4])
def test_json_equals_model_fk(order: int, planar3: PPOEModel, capsys: pytest.CaptureFixture[str]) -> None:
    q = {"joint1": 0.3, "joint2": -0.5, "joint3": 0.9}
    argv = BASE + ["--joints"] + [f"{k}={v!r}" for k, v in q.items()] + ["--order", str(order), "--json"]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    T, cov = planar3.fk(q, "base_link", "tool0", order=order)
    _check_doc(json.loads(out), T, cov)
    assert np.array(json.loads(out)["cov_local"])[5, 5] > 0.01  # three 10 deg perturbations


def test_order4_is_closer_to_monte_carlo_than_order2_at_10_deg(planar3: PPOEModel,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """At 10 deg per joint (Fig. 3) the fourth-order covariance printed by ``ppoe fk --order 4`` is closer to
    a seeded Monte-Carlo covariance of the same model than the second-order one (paper Sec. III)."""
    q = {"joint1": 0.3, "joint2": 0.5, "joint3": 0.4}
    argv = BASE + ["--joints"] + [f"{k}={v}" for k, v in q.items()] + ["--json"]
    docs = {o: json.loads(_run(argv + ["--order", o], capsys)[1]) for o in ("2", "4")}
    T = np.array(docs["2"]["T"])
    S = planar3.sample(q, "base_link", "tool0", n=200_000, rng=np.random.default_rng(7))
    xi = lie.log(lie.inverse(T) @ S)  # tangent at the second-order mean (the mean is exact)
    cov_mc = xi.T @ xi / len(xi)
    err = {o: np.linalg.norm(np.array(d["cov_local"]) - cov_mc) / np.linalg.norm(cov_mc) for o, d in docs.items()}
    assert err["4"] < err["2"], err


def test_frames_default_to_model_frames_and_non_root_reference(capsys: pytest.CaptureFixture[str]) -> None:
    """No --from/--to: frames.base/tool of the YAML; a reference frame inside the chain works."""
    model = PPOEModel.from_files(ARM7_URDF, ARM7_MODEL)
    q = dict(joint_1=0.3, joint_2=0.6, joint_3=0.0, joint_4=-1.2, joint_5=0.0, joint_6=0.9, joint_7=0.0)
    joints = ["--joints"] + [f"{k}={v}" for k, v in q.items()]
    code, out, err = _run(["fk", "--urdf", ARM7_URDF, "--model", ARM7_MODEL, *joints, "--json"], capsys)
    assert code == 0, err
    _check_doc(json.loads(out), *model.fk(q, "base_link", "tool0"))
    argv = ["fk", "--urdf", ARM7_URDF, "--model", ARM7_MODEL, "--from", "camera_optical_frame", "--to", "tool0"]
    code, out, err = _run(argv + joints + ["--json"], capsys)
    assert code == 0, err
    _check_doc(json.loads(out), *model.fk(q, "camera_optical_frame", "tool0"))


def test_subprocess_entry_point(planar3: PPOEModel) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    argv = (
        [sys.executable, "-m", "ppoe_ros.cli"]
        + BASE
        + ["--joints", "joint1=0.1", "joint2=0.2", "joint3=-0.3", "--json"]
    )
    proc = subprocess.run(argv, capture_output=True, text=True, cwd=str(REPO), env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr
    _check_doc(
        json.loads(proc.stdout), *planar3.fk({"joint1": 0.1, "joint2": 0.2, "joint3": -0.3}, "base_link", "tool0")
    )
    bad = subprocess.run(
        argv[:-5] + ["--joints", "joint1=0.1", "--json"],
        capture_output=True,
        text=True,
        cwd=str(REPO),
        env=env,
        timeout=60,
    )
    assert bad.returncode == 2 and "joint2" in bad.stderr and "Traceback" not in bad.stderr


def test_batch_prints_rows_in_order(planar3: PPOEModel, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(7)
    Q = rng.uniform(-np.pi, np.pi, size=(9, 2))
    csv = tmp_path / "configs.csv"
    csv.write_text("joint2,joint1\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in Q))
    code, out, err = _run(BASE + ["--batch", str(csv), "--joints", "joint3=0.25", "--json"], capsys)
    assert code == 0, err
    lines = out.splitlines()
    assert len(lines) == len(Q)
    for line, (q2, q1) in zip(lines, Q):
        _check_doc(json.loads(line), *planar3.fk({"joint1": q1, "joint2": q2, "joint3": 0.25}, "base_link", "tool0"))


def test_text_output_is_readable_and_consistent(
    planar3: PPOEModel, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = _run(BASE + ["--joints", "joint1=0.3", "joint2=-0.5", "joint3=0.9"], capsys)
    assert code == 0, err
    T, cov = planar3.fk({"joint1": 0.3, "joint2": -0.5, "joint3": 0.9}, "base_link", "tool0")
    xyz_line = next(line for line in out.splitlines() if "xyz [m]" in line)
    np.testing.assert_allclose([float(v) for v in xyz_line.split(":")[1].split()], T[:3, 3], atol=1e-6)
    assert "cov_local" in out and "cov_ros" in out and "T_base_link_tool0" in out
    csv = tmp_path / "c.csv"
    csv.write_text("joint1,joint2,joint3\n0,0,0\n0.1,0.2,0.3\n")
    code, out, _ = _run(BASE + ["--batch", str(csv)], capsys)
    assert code == 0 and "# row 1" in out and "# row 2" in out


@pytest.mark.parametrize(
    ("joints", "needle"),
    [
        (["joint1"], "NAME=VALUE"),
        (["joint1=abc", "joint2=0", "joint3=0"], "joint1"),
        (["joint1=nan", "joint2=0", "joint3=0"], "not finite"),
        (["joint1=0", "joint2=0", "joint3=0", "elbow=1"], "elbow"),
        (["joint1=0", "joint2=0", "joint3=0", "tool_joint=1"], "tool_joint"),  # fixed joint
        (["joint1=0", "joint1=1", "joint2=0", "joint3=0"], "twice"),
        (["joint1=0", "joint2=0"], "joint3"),  # missing value the chain needs
    ],
)
def test_bad_joint_arguments_exit_2(joints: list[str], needle: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(BASE + ["--joints", *joints, "--json"], capsys)
    assert code == 2 and out == ""
    assert err.startswith("ppoe fk: error:") and needle in err


@pytest.mark.parametrize(
    ("content", "needles"),
    [
        ("joint1,joint2,joint3\n0,0,0\n0.1,nan,0\n", ["line 3", "row 2", "column 2", "joint2", "not finite"]),
        ("joint1,joint2,joint3\n0,0,0\n0.1,x,0\n", ["line 3", "column 2", "joint2", "not a number"]),
        ("joint1,bogus,joint3\n0,0,0\n", ["line 1", "column 2", "bogus"]),
        ("joint1,joint2,joint3\n0,0\n", ["line 2", "2 fields"]),
        ("joint1,joint2,joint3\n", ["no configuration rows"]),
        ("", ["empty header"]),
        ("joint1,joint1,joint3\n0,0,0\n", ["twice"]),
    ],
)
def test_bad_batch_csv_exit_2(
    content: str, needles: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv = tmp_path / "bad.csv"
    csv.write_text(content)
    code, out, err = _run(BASE + ["--batch", str(csv), "--json"], capsys)
    assert code == 2 and out == ""
    for needle in needles:
        assert needle in err, (needle, err)
    assert "bad.csv" in err


def test_batch_and_joints_overlap_and_missing_files_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "c.csv"
    csv.write_text("joint1,joint2,joint3\n0,0,0\n")
    code, _, err = _run(BASE + ["--batch", str(csv), "--joints", "joint1=0.1"], capsys)
    assert code == 2 and "joint1" in err and "both" in err
    code, _, err = _run(BASE + ["--batch", str(tmp_path / "missing.csv")], capsys)
    assert code == 2 and "missing.csv" in err
    code, _, err = _run(["fk", "--urdf", str(tmp_path / "nope.urdf"), "--joints", "joint1=0"], capsys)
    assert code == 2 and "nope.urdf" in err
    code, _, err = _run(["fk", "--urdf", URDF, "--model", str(tmp_path / "nope.yaml"), "--joints", "joint1=0"], capsys)
    assert code == 2 and "nope.yaml" in err
    code, _, err = _run(BASE[:-1] + ["no_such_link", "--joints", "joint1=0", "joint2=0", "joint3=0"], capsys)
    assert code == 2 and "no_such_link" in err


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=3, max_size=3))
def test_joint_assignments_round_trip(values: list[float]) -> None:
    names = ["joint1", "joint2", "joint3"]
    parsed = parse_joint_assignments([f"{n}={v!r}" for n, v in zip(names, values)], names)
    assert parsed == dict(zip(names, values))


def test_parse_errors_are_package_types() -> None:
    with pytest.raises(UnknownJointError, match="wrist"):
        parse_joint_assignments(["wrist=1"], ["joint1"])
    with pytest.raises(JointValueError, match="inf"):
        parse_joint_assignments(["joint1=inf"], ["joint1"])


def test_numerical_warnings_become_one_line(monkeypatch, capsys):
    """Issue 13: numpy RuntimeWarnings do not reach the terminal raw; the CLI prints one line."""
    import numpy as np

    import ppoe_core.cli.fk as fk_cli
    from ppoe_ros.cli import main

    def noisy_run(args):
        with np.errstate(all="warn"):
            np.log(np.array([-1.0, 0.0]))
            np.array([0.0]) / np.array([0.0])
        return 0

    monkeypatch.setattr(fk_cli, "run", noisy_run)
    assert main(["fk", "--urdf", "x", "--from", "a", "--to", "b"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ppoe fk: note: 3 numerical warning(s), first: "), err
    assert "RuntimeWarning" not in err[0]
