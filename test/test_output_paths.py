"""``--force`` never removes a path we did not create (issue 25): ``ppoe import csv``, ``ppoe simulate`` and
``ppoe record`` replace an existing *bag* only (atomically, written beside it and renamed), refuse a folder holding
anything else (naming it) and an existing file, and keep the old bag when the new one fails or records nothing.
Was: ``shutil.rmtree`` of whatever ``--out`` named, and a raw ``NotADirectoryError`` for a file."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import BAGS, CONFIG_ROBOTS

from ppoe_core.errors import BagError, PpoeError
from ppoe_core.io.bagio import BagWriter, read_bag
from ppoe_ros.cli import main


def _small_bag(path: Path, n: int = 10, value: float = 0.0) -> Path:
    with BagWriter(path) as bag:
        for k in range(n):
            bag.write_joint_state(0.01 * k, ["j"], [value])
    return path


def _user_folder(path: Path) -> Path:
    """A folder of the user's: a bag in it, and their own notes and a sub-folder."""
    _small_bag(path)
    (path / "notes.txt").write_text("my notes\n")
    (path / "sub").mkdir()
    (path / "sub" / "keep.csv").write_text("a,b\n1,2\n")
    return path


def _tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _siblings(path: Path) -> list[str]:
    return sorted(p.name for p in path.parent.iterdir() if p.name.startswith(f".{path.name}."))


@pytest.fixture(scope="module")
def csv_input(tmp_path_factory) -> list[str]:
    """``ppoe import csv`` arguments without ``--out``: two stops of planar3."""
    tmp = tmp_path_factory.mktemp("csv")
    (tmp / "stops.csv").write_text("t,a,b,c\n1.0,0.1,0.2,0.3\n3.0,0.2,0.1,0.0\n")
    (tmp / "map.yaml").write_text("joints: {joint1: a, joint2: b, joint3: c}\ntime: t\n")
    return ["import", "csv", str(tmp / "stops.csv"), "--mapping", str(tmp / "map.yaml"),
            "--urdf", str(CONFIG_ROBOTS / "planar3.urdf")]


def _scenario() -> list[str]:
    return ["simulate", str(BAGS / "contact.yaml"), "--truth", "none"]


def test_force_refuses_a_folder_holding_anything_but_a_bag_and_names_it(tmp_path, capsys, csv_input):
    for k, args in enumerate([csv_input, _scenario()]):
        out = _user_folder(tmp_path / f"mine{k}")
        before = _tree(out)
        assert main([*args, "--out", str(out), "--force"]) == 2
        err = capsys.readouterr().err
        assert f"bag {out}: --force refused: the folder holds 2 entries that are not part of a bag (notes.txt, sub/)" \
            in err, err
        assert _tree(out) == before and _siblings(out) == []  # nothing removed, nothing left beside it


def test_force_on_an_existing_file_is_a_clear_error(tmp_path, capsys, csv_input):
    target = tmp_path / "afile.txt"
    target.write_text("precious\n")
    for args in (csv_input, _scenario()):
        assert main([*args, "--out", str(target), "--force"]) == 2
        err = capsys.readouterr().err
        assert f"bag {target}: is an existing file, not a bag directory; --force replaces only a bag directory" \
            in err and "Traceback" not in err, err
        assert target.read_text() == "precious\n"


def test_force_replaces_our_own_bag_atomically(tmp_path, capsys, csv_input):
    out = _small_bag(tmp_path / "bag", n=3)
    assert main([*csv_input, "--out", str(out)]) == 2 and "exists already" in capsys.readouterr().err
    assert len(read_bag(out).joint_states) == 3
    assert main([*csv_input, "--out", str(out), "--force"]) == 0
    capsys.readouterr()
    data = read_bag(out)
    assert len(data.joint_states) == 2 * 5 and data.robot_description  # the new bag, in place
    assert sorted(p.name for p in out.iterdir()) == ["bag.mcap", "metadata.yaml"] and _siblings(out) == []


def test_an_error_while_writing_keeps_the_old_bag(tmp_path):
    out = _small_bag(tmp_path / "bag", n=4, value=1.0)
    before = _tree(out)
    with pytest.raises(RuntimeError, match="boom"), BagWriter(out, overwrite=True) as bag:
        assert bag.replaces_existing and bag.write_path != out
        bag.write_joint_state(0.0, ["j"], [2.0])
        raise RuntimeError("boom")
    assert _tree(out) == before and _siblings(out) == []
    with BagWriter(out, overwrite=True) as bag:  # and a successful one replaces it
        bag.write_joint_state(0.0, ["j"], [3.0])
    assert read_bag(out).joint_states.positions.tolist() == [[3.0]] and _siblings(out) == []


def test_a_file_appearing_in_the_old_bag_while_writing_is_not_deleted(tmp_path):
    out = _small_bag(tmp_path / "bag")
    bag = BagWriter(out, overwrite=True).open()
    bag.write_joint_state(0.0, ["j"], [2.0])
    (out / "late.txt").write_text("written meanwhile\n")
    with pytest.raises(BagError, match="late.txt appeared in it; the new bag is left in"):
        bag.close()
    assert (out / "late.txt").read_text() == "written meanwhile\n"


def test_generated_files_are_replaced_only_when_ours(tmp_path):
    from ppoe_core.io.outputs import check_generated_file

    mine = tmp_path / "model.yaml"
    mine.write_text("joint_noise: {}\n")
    with pytest.raises(PpoeError, match="exists already"):
        check_generated_file(mine, False, "# ppoe model for ", "model file")
    with pytest.raises(PpoeError, match="--force refused: the file was not written by ppoe"):
        check_generated_file(mine, True, "# ppoe model for ", "model file")
    ours = tmp_path / "bag.model.yaml"
    ours.write_text("# ppoe model for x.urdf, generated by `ppoe import hilti`\n")
    check_generated_file(ours, True, "# ppoe model for ", "model file")  # no error


def test_simulate_refuses_to_overwrite_a_users_truth_file(tmp_path, capsys):
    truth = tmp_path / "truth.yaml"
    truth.write_text("my own yaml\n")
    assert main([*_scenario()[:2], "--out", str(tmp_path / "bag"), "--truth", str(truth), "--force"]) == 2
    assert f"truth file {truth}: --force refused" in capsys.readouterr().err
    assert truth.read_text() == "my own yaml\n" and not (tmp_path / "bag").exists()


# ----------------------------------------------------------------------------- live: record


@pytest.mark.ros
def test_record_keeps_the_old_bag_when_it_records_nothing_and_refuses_a_users_folder(tmp_path):
    pytest.importorskip("rclpy")
    from ros_helpers import NodeProcess, ros_env

    env = ros_env(tmp_path)
    out = _small_bag(tmp_path / "old", n=7, value=5.0)
    before = _tree(out)
    rec = NodeProcess.ppoe(["record", "--out", str(out), "--force", "--duration", "1.5", "/nobody_publishes_this"],
                           env, tmp_path, "rec")
    assert rec.wait(60) == 0, rec.output()
    assert f"recorded nothing; the existing bag {out} is kept as it was" in rec.output(), rec.output()
    assert _tree(out) == before and _siblings(out) == []
    mine = _user_folder(tmp_path / "mine")
    rec = NodeProcess.ppoe(["record", "--out", str(mine), "--force", "--duration", "0.5", "/x"], env, tmp_path, "r2")
    assert rec.wait(60) == 2 and "--force refused" in rec.output() and (mine / "notes.txt").exists(), rec.output()


# ----------------------------------------------------------------------------- report folders (--out of evaluate)


def _evaluate(out: Path, *extra: str) -> int:
    return main(["evaluate", str(BAGS / "no_effect"), "--model", str(CONFIG_ROBOTS / "arm7_model.yaml"), "--json",
                 "--out", str(out), *extra])


def test_a_second_run_into_a_locked_folder_is_refused_naming_the_lock(tmp_path, capsys):
    import json
    import subprocess
    import sys

    from ppoe_core.cli.output import LOCK_NAME

    out = tmp_path / "report"
    out.mkdir()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        import socket

        (out / LOCK_NAME).write_text(json.dumps({"pid": other.pid, "host": socket.gethostname(),
                                                 "command": "ppoe evaluate", "run_id": "R1", "started": "then"}))
        assert _evaluate(out) == 2
        err = capsys.readouterr().err
        assert f"--out {out}: another run is writing there (lock {out / LOCK_NAME}: ppoe evaluate pid {other.pid}" \
            in err and "run R1" in err, err
        assert not (out / "evaluation.json").exists()
    finally:
        other.kill()
        other.wait()
    # its process is gone: a stale lock, taken over with a warning
    assert _evaluate(out) == 0
    cap = capsys.readouterr()
    assert "took over the lock of run R1" in cap.err and not (out / LOCK_NAME).exists(), cap.err


def test_evaluate_leaves_other_runs_files_names_them_and_logs_its_run(tmp_path, capsys):
    import json

    out = tmp_path / "report"
    out.mkdir()
    for name in ("online.json", "online_parameters.png", "notes.txt", "trajectory_recorded.tum"):
        (out / name).write_text("an earlier run's\n")
    assert _evaluate(out) == 0
    err = capsys.readouterr().err
    assert f"--out {out} also holds 3 file(s) this run does not write (notes.txt, online.json, " \
        "online_parameters.png): left as they are" in err, err
    assert (out / "online.json").read_text() == "an earlier run's\n" and (out / "notes.txt").exists()
    assert not (out / "trajectory_recorded.tum").exists()  # of our kind, not rewritten: an older run's, removed
    runs = [json.loads(line) for line in (out / "ppoe_runs.jsonl").read_text().splitlines()]
    assert len(runs) == 1 and runs[0]["command"] == "ppoe evaluate" and "evaluation.json" in runs[0]["wrote"]
    assert runs[0]["removed_stale"] == ["trajectory_recorded.tum"] and runs[0]["run_id"].endswith(f"-{os.getpid()}")
    assert not (out / ".ppoe.lock").exists()


def test_urdf_from_dh_force_replaces_only_a_urdf_it_wrote(tmp_path, capsys):
    table = CONFIG_ROBOTS / "arm5_dh.yaml"
    mine = tmp_path / "robot.urdf"
    mine.write_text((CONFIG_ROBOTS / "planar3.urdf").read_text())  # a hand-written URDF
    assert main(["urdf", "from-dh", str(table), "--out", str(mine), "--force"]) == 2
    assert f"--out {mine}: --force refused: the file was not written by ppoe" in capsys.readouterr().err
    assert mine.read_text() == (CONFIG_ROBOTS / "planar3.urdf").read_text()
    ours = tmp_path / "arm5.urdf"
    assert main(["urdf", "from-dh", str(table), "--out", str(ours)]) == 0
    assert main(["urdf", "from-dh", str(table), "--out", str(ours), "--force"]) == 0  # its own output: replaced
