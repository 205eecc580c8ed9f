"""Damaged and unfinished bags (issue 13 items 1, 9, 13, 14): the fault is injected, the exact behaviour asserted.

* a block of zeros in the middle of the mcap: refused naming per topic what was lost (exit 2), or,
  with ``--accept-partial``, used with a warning saying the same;
* half the file zeroed: one line naming the bag, exit 2, no traceback;
* no footer and no ``metadata.yaml`` (a recorder killed): read record by record, with a note;
* ``ppoe record`` killed with ``-9``: the bag reads back, at most about one flush period lost;
* ``ppoe record`` under SIGTERM: exit 0 and a closed bag, every time.

The bags are written here (a joint-state stream, or a short simulated scenario), not the shipped ones.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from ppoe_core.errors import BagError
from ppoe_core.io.bagio import BagWriter, check_bag, iter_raw, read_bag

REPO = Path(__file__).resolve().parents[1]
N_JS, N_GT = 3000, 30


def _stream_bag(path: Path) -> Path:
    """3000 joint states (3 joints, 100 Hz) and 30 ground-truth points; small chunks so damage hits some."""
    rng = np.random.default_rng(11)
    with BagWriter(path) as bag:
        bag.write_robot_description((REPO / "config" / "robots" / "planar3.urdf").read_text(), 0.0)
        for k in range(N_JS):
            if k % 500 == 499:
                bag.flush()  # a chunk per 500 joint states
            bag.write_joint_state(0.01 * k, ["joint_1", "joint_2", "joint_3"], rng.normal(size=3))
            if k % 100 == 0:
                bag.write_ground_truth_point(0.01 * k + 0.001, "tracker", rng.normal(size=3))
    return path


def _mcap(bag: Path) -> Path:
    (f,) = sorted(bag.glob("*.mcap"))
    return f


def _zero(bag: Path, at: float, size: int) -> None:
    f = _mcap(bag)
    buf = bytearray(f.read_bytes())
    start = int(at * len(buf))
    buf[start:start + size] = bytes(min(size, len(buf) - start))
    f.write_bytes(bytes(buf))


def test_flushed_writer_leaves_whole_chunks_and_interim_metadata(tmp_path: Path) -> None:
    """While open, the file holds whole chunks and ``metadata.yaml`` the counts on disk (marked in progress)."""
    from ppoe_core.io.recovery import RECORDING_KEY

    w = BagWriter(tmp_path / "open", flush_period=0.0).open()
    for k in range(50):
        w.write_joint_state(0.01 * k, ["a"], np.array([k * 1.0]))
    meta = yaml.safe_load((tmp_path / "open" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["message_count"] == 50 and RECORDING_KEY in meta["custom_data"]
    data = read_bag(tmp_path / "open")  # the writer is still open: no footer
    assert data.joint_states.positions[:, 0].tolist() == [float(k) for k in range(50)]
    assert "never closed" in data.notes[0] and "recovered 50 messages" in data.notes[0]
    w.close()
    meta = yaml.safe_load((tmp_path / "open" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert RECORDING_KEY not in (meta.get("custom_data") or {})
    assert read_bag(tmp_path / "open").notes == []


def test_zeroed_block_is_refused_per_topic_or_accepted_with_a_note(tmp_path: Path) -> None:
    bag = _stream_bag(tmp_path / "bag")
    assert read_bag(bag).notes == [] and check_bag(bag)[0] == []
    _zero(bag, 0.05, 20_000)
    with pytest.raises(BagError) as err:
        read_bag(bag)
    msg = str(err.value)
    assert f"bag {bag}: damaged: read " in msg and "--accept-partial" in msg
    assert f" of {N_JS}" in msg and "/joint_states " in msg  # per topic: read r of n
    data = read_bag(bag, accept_partial=True)
    n = len(data.joint_states.stamps)
    assert 0 < n < N_JS
    assert f"/joint_states {n} of {N_JS}" in data.notes[-1] and "accepted" in data.notes[-1]
    # every message before and after the hole that was readable was kept: far more than the prefix
    assert n > 0.9 * N_JS
    check = check_bag(bag, accept_partial=True)
    assert check.counts["/joint_states"] == n and check.notes and check.scanned
    assert len(list(iter_raw(bag, ["/joint_states"], scanned=True))) == n  # what play will send


def test_half_zeroed_bag_is_one_line_with_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from ppoe_ros.cli import main

    bag = _stream_bag(tmp_path / "bag")
    f = _mcap(bag)
    _zero(bag, 0.5, f.stat().st_size)
    model = REPO / "config" / "robots" / "planar3_model.yaml"
    for argv in (["evaluate", str(bag), "--model", str(model), "--no-progress"],
                 ["diagnose", str(bag), "--model", str(model)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "Traceback" not in err and "OverflowError" not in err
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and f"bag {bag}" in lines[0] and "damaged" in lines[0], err


def test_bag_without_footer_or_metadata_is_recovered_with_a_note(tmp_path: Path) -> None:
    bag = _stream_bag(tmp_path / "bag")
    f = _mcap(bag)
    whole = read_bag(bag)
    (bag / "metadata.yaml").unlink()
    buf = f.read_bytes()
    f.write_bytes(buf[: int(0.8 * len(buf))])  # the summary, footer and the last chunks are gone
    data = read_bag(bag)
    n = len(data.joint_states.stamps)
    assert 0.5 * N_JS < n < N_JS
    np.testing.assert_array_equal(data.joint_states.positions, whole.joint_states.positions[:n])
    assert len(data.notes) == 1 and "recovered" in data.notes[0] and "no footer" in data.notes[0]


def test_a_file_that_is_no_mcap_is_one_clear_error(tmp_path: Path) -> None:
    bag = _stream_bag(tmp_path / "bag")
    _mcap(bag).write_bytes(b"\0" * 4096)
    with pytest.raises(BagError, match="does not start with the MCAP magic"):
        read_bag(bag)


# ----------------------------------------------------------------------------- live: play and record


def _ros():
    pytest.importorskip("rclpy")
    from ros_helpers import NodeProcess, ros_env

    return NodeProcess, ros_env


@pytest.mark.ros
def test_play_refuses_a_damaged_bag_and_plays_what_is_readable_when_accepted(tmp_path: Path) -> None:
    NodeProcess, ros_env = _ros()
    bag = _stream_bag(tmp_path / "bag")
    _zero(bag, 0.05, 20_000)
    n = len(read_bag(bag, accept_partial=True).joint_states.stamps)
    env = ros_env(tmp_path)
    proc = NodeProcess.ppoe(["play", str(bag), "--topics", "/joint_states"], env, tmp_path, "refused")
    try:
        assert proc.wait(60) == 2, proc.output()
    finally:
        proc.stop()
    assert f"/joint_states {n} of {N_JS}" in proc.output() and "Traceback" not in proc.output()
    proc = NodeProcess.ppoe(["play", str(bag), "--topics", "/joint_states", "--accept-partial", "--rate", "100",
                             "--delay", "0.1"], env, tmp_path, "accepted")
    try:
        assert proc.wait(60) == 0, proc.output()
    finally:
        proc.stop()
    out = proc.output()
    assert "warning" in out and f"/joint_states ({n})" in out


def _start_player(NodeProcess, env, tmp_path: Path, name: str):  # noqa: N803 - the class
    """``ppoe play`` of a 60 s, 100 Hz joint-state bag at real time (a steady publisher)."""
    src = tmp_path / f"{name}_src"
    if not src.exists():
        with BagWriter(src) as bag:
            for k in range(6000):
                bag.write_joint_state(0.01 * k, ["j"], np.array([float(k)]))
    return NodeProcess.ppoe(["play", str(src), "--topics", "/joint_states", "--delay", "0.2"], env, tmp_path, name)


@pytest.mark.ros
def test_record_killed_with_sigkill_leaves_a_readable_bag(tmp_path: Path) -> None:
    """Killed -9 after ~3 s of messages: the bag reads back, and what is missing is under about a second."""
    NodeProcess, ros_env = _ros()
    env = ros_env(tmp_path)
    out = tmp_path / "rec"
    recorder = NodeProcess.ppoe(["record", "--out", str(out), "/joint_states"], env, tmp_path, "record")
    player = _start_player(NodeProcess, env, tmp_path, "play")
    try:
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and not (out / "metadata.yaml").exists():
            time.sleep(0.1)
        first = None
        while time.monotonic() < deadline:
            meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
            if meta["message_count"] > 0:
                first = first or time.time()
                if time.time() - first > 3.0:
                    break
            time.sleep(0.1)
        assert first is not None, recorder.output() + player.output()
        os.killpg(recorder.proc.pid, signal.SIGKILL)
        killed_at = time.time()
        recorder.proc.wait(10)
    finally:
        player.stop()
        recorder.stop()
    data = read_bag(out)
    assert data.notes and "never closed" in data.notes[0]
    stamps = data.joint_states.stamps
    assert len(stamps) > 150
    assert np.all(np.diff(data.joint_states.positions[:, 0]) == 1.0)  # no hole inside what was kept
    log_times = [m.stamp_ns for m in iter_raw(out)]
    assert killed_at - max(log_times) * 1e-9 < 1.0  # at most about one flush period (0.5 s) lost


@pytest.mark.ros
def test_record_under_sigterm_exits_0_with_a_closed_bag(tmp_path: Path) -> None:
    NodeProcess, ros_env = _ros()
    env = ros_env(tmp_path)
    player = _start_player(NodeProcess, env, tmp_path, "play")
    try:
        for run in range(5):
            out = tmp_path / f"rec{run}"
            rec = NodeProcess.ppoe(["record", "--out", str(out), "/joint_states"], env, tmp_path, f"rec{run}")
            time.sleep(1.0 + 0.3 * run)  # vary the moment: the race was in start-up and spinning
            rec.proc.send_signal(signal.SIGTERM)
            assert rec.proc.wait(20) == 0, rec.output()
            out_text = rec.output()
            assert "Traceback" not in out_text and "RCLError" not in out_text and "wrote" in out_text
            assert read_bag(out).notes == []  # closed properly: footer and final metadata
    finally:
        player.stop()
    shutil.rmtree(tmp_path / "play_src", ignore_errors=True)
