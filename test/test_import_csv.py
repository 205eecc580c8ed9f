"""``ppoe import csv``: a robot's stops from a CSV and a mapping YAML, as a contract bag that diagnose and
evaluate use like any other (stations and stop roles included); bad input names the row and column."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import CONFIG

from ppoe_core import lie
from ppoe_core.errors import DatasetError
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

URDF = CONFIG / "robots" / "arm7.urdf"
JOINTS = [f"joint_{k}" for k in range(1, 8)]
REFLECTOR = np.array([0.0, 0.0, 0.02])


def _write(tmp: Path, n=48, offset=0.02, seed=1, deg=True, roles=True) -> tuple[Path, Path]:
    """Stops of arm7 with an encoder offset at joint_2, points of a reflector on tool0 in two total-station
    placements (stations), 0.2 mm noise, angles in degrees and positions in mm."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(parse_urdf(URDF))
    q = {j: rng.uniform(-1.2, 1.2, n) for j in JOINTS}
    q["finger_left_joint"] = np.full(n, 0.01)
    dq = {"joint_2": np.full(n, offset)}
    x = (tree.link_poses(q, dq, links=["tool0"])["tool0"] @ np.append(REFLECTOR, 1.0))[:, :3]
    station = np.arange(n) % 2
    regs = [lie.from_xyz_rpy([2.0, -1.0, 0.3], [0, 0, 0.4]), lie.from_xyz_rpy([-1.0, 2.5, 0.1], [0, 0, -1.1])]
    p = np.stack([regs[s][:3, :3] @ xi + regs[s][:3, 3] for s, xi in zip(station, x)]) + rng.normal(0, 2e-4, (n, 3))
    rows = []
    for i in range(n):
        row = {f"q{k}": np.degrees(q[j][i]) if deg else q[j][i] for k, j in enumerate(JOINTS, 1)}
        row.update(px=1e3 * p[i, 0], py=1e3 * p[i, 1], pz=1e3 * p[i, 2], t=10.0 + 3 * i, st=f"S{station[i]}")
        row["role"] = "stationing" if (i // 2) % 3 != 2 else "evaluation"
        rows.append(row)
    rows[5]["px"] = ""  # one stop without a point: skipped and counted
    path = tmp / "stops.csv"
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    mapping = {"joints": {j: f"q{k}" for k, j in enumerate(JOINTS, 1)}, "angle_unit": "deg" if deg else "rad",
               "length_unit": "mm", "points": [{"topic": "/ground_truth/point", "columns": ["px", "py", "pz"],
                                                "frame": "total_station"}], "time": "t", "station": "st"}
    if roles:
        mapping["role"] = "role"
    (tmp / "map.yaml").write_text(yaml.safe_dump(mapping))
    return path, tmp / "map.yaml"


def test_csv_stops_become_a_bag_that_diagnose_and_test_use(tmp_path, capsys):
    from ppoe_ros.cli import main

    (tmp_path / "fit").mkdir()
    fit_csv, fit_map = _write(tmp_path / "fit")
    test_dir = tmp_path / "test"
    test_dir.mkdir()
    test_csv, test_map = _write(test_dir, n=30, seed=2)
    model = tmp_path / "model.yaml"
    model.write_text(yaml.safe_dump({"joint_noise": {j: 1e-4 for j in JOINTS}, "frames": {"tool": "tool0"},
                                     "tracker": {"link": "tool0", "xyz": REFLECTOR.tolist(), "sigma": 2e-4}}))
    for c, m, out in ((fit_csv, fit_map, tmp_path / "fit_bag"), (test_csv, test_map, tmp_path / "test_bag")):
        assert main(["import", "csv", str(c), "--mapping", str(m), "--urdf", str(URDF), "--out", str(out)]) == 0
        err = capsys.readouterr().err
        assert "1 stops without /ground_truth/point (empty cells)" in err
    assert main(["diagnose", str(tmp_path / "fit_bag"), "--model", str(model), "--test", str(tmp_path / "test_bag"),
                 "--json", "--pixels", "off"]) == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    assert "/joint_states never carries ['finger_left_joint']; they are off the measured chains" in cap.err
    assert [(e["name"], e["location"]) for e in doc["effects"]][:1] == [("joint_offset", "joint_2")]
    lo, hi = doc["effects"][0]["ci"]["offset"]
    assert lo <= 0.02 <= hi
    assert doc["n_sessions"] == 2
    t = doc["test"]["test_bag"]
    assert t["protocol"].startswith("stop roles") and t["rms"] < 0.2 * t["before"]["rms"]
    assert t["n"] == sum(1 for i in range(30) if (i // 2) % 3 == 2 and i != 5)  # the evaluation stops


def test_radians_without_roles_and_the_joint_values_round_trip(tmp_path):
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.io.importers.csv_stops import import_csv

    c, m = _write(tmp_path, n=10, deg=False, roles=False)
    res = import_csv(c, m, URDF, tmp_path / "bag")
    assert res["stops"] == 10 and res["skipped"] == {"/ground_truth/point": 1}
    data = read_bag(tmp_path / "bag")
    assert len(data.ground_truth_point) == 9 and len(data.joint_states) == 10 * 5
    with open(c) as fh:
        first = next(csv.DictReader(fh))
    np.testing.assert_allclose(data.joint_states.positions[0, :7], [float(first[f"q{k}"]) for k in range(1, 8)])
    np.testing.assert_allclose(data.ground_truth_point.p[0], [1e-3 * float(first[k]) for k in ("px", "py", "pz")])


@pytest.mark.parametrize("mutate,needle", [
    (lambda rows, m: rows[3].update(q4="abc"), "stops.csv:5: column 'q4': not a number: 'abc'"),
    (lambda rows, m: rows[2].update(q1=""), "stops.csv:4: column 'q1': empty"),
    (lambda rows, m: m["joints"].update(joint_9="q1"), "joints.joint_9: not an independent movable joint"),
    (lambda rows, m: m.update(angle_unit="grad"), "angle_unit: must be one of ['rad', 'deg']"),
    (lambda rows, m: m["joints"].update(joint_1="nope"), "columns ['nope'] named by"),
    (lambda rows, m: rows[1].update(role="setup"), "role must be stationing or evaluation, got 'setup'"),
])
def test_bad_input_names_the_row_column_or_key(tmp_path, mutate, needle):
    from ppoe_core.io.importers.csv_stops import import_csv

    c, mp = _write(tmp_path, n=8)
    with open(c) as fh:
        rows = list(csv.DictReader(fh))
    m = yaml.safe_load(mp.read_text())
    mutate(rows, m)
    with open(c, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    mp.write_text(yaml.safe_dump(m))
    with pytest.raises(DatasetError, match=None) as err:
        import_csv(c, mp, URDF, tmp_path / "bag")
    assert needle in str(err.value)


def _rewrite(path: Path, edit) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n", encoding="utf-8")


def _import_exit(c: Path, mp: Path, out: Path, capsys) -> tuple[int, str]:
    from ppoe_ros.cli import main

    code = main(["import", "csv", str(c), "--mapping", str(mp), "--urdf", str(URDF), "--out", str(out)])
    return code, capsys.readouterr().err


def test_a_column_twice_in_the_header_is_an_error_naming_it(tmp_path, capsys):
    """Was: the last 'q1' used silently, exit 0."""
    c, mp = _write(tmp_path, n=6)
    _rewrite(c, lambda lines: [lines[0] + ",q1"] + [ln + ",0.5" for ln in lines[1:]])
    code, err = _import_exit(c, mp, tmp_path / "bag", capsys)
    assert code == 2 and f"{c}:1: column 'q1' appears 2 times in the header (columns 1, 14)" in err, err
    assert not (tmp_path / "bag").exists()


def test_a_row_longer_or_shorter_than_the_header_is_an_error_naming_the_line(tmp_path, capsys):
    """Was: the extra cell dropped silently (longer), exit 0."""
    c, mp = _write(tmp_path, n=6)
    _rewrite(c, lambda lines: lines[:3] + [lines[3] + ",7.5"] + lines[4:])
    code, err = _import_exit(c, mp, tmp_path / "bag", capsys)
    assert code == 2 and f"{c}:4: 14 cells but the header has 13 columns" in err, err
    _rewrite(c, lambda lines: lines[:3] + [lines[3].rsplit(",", 2)[0]] + lines[4:])
    code, err = _import_exit(c, mp, tmp_path / "bag", capsys)
    assert code == 2 and f"{c}:4: 12 cells but the header has 13 columns" in err, err
    assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("second", [10.0, 10.15])
def test_stops_at_the_same_time_are_an_error_naming_both_lines(tmp_path, capsys, second):
    """Was: two stops at t = 10 s interleaved their joint states, so one point got the other stop's joints."""
    c, mp = _write(tmp_path, n=6)
    with open(c, newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows[4]["t"] = str(second)  # line 6; line 2 is at t = 10 s
    with open(c, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    code, err = _import_exit(c, mp, tmp_path / "bag", capsys)
    what = "the same as" if second == 10.0 else "0.15 s after"
    assert code == 2 and f"{c}:6: column 't': stop time {second:g} s is {what} the stop at line 2 (10 s)" in err, err
    assert "at least 0.2 s apart" in err


def test_stops_out_of_time_order_but_apart_keep_their_own_joints(tmp_path):
    """Rows need not be in time order: each point is paired with its own row's joint values."""
    from ppoe_core.analysis.diagnose import stops_from_bag
    from ppoe_core.io.importers.csv_stops import import_csv

    c, mp = _write(tmp_path, n=6, deg=False, roles=False)
    with open(c, newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows[1]["t"], rows[4]["t"] = rows[4]["t"], rows[1]["t"]
    with open(c, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    import_csv(c, mp, URDF, tmp_path / "bag")
    stops = stops_from_bag(tmp_path / "bag", parse_urdf(URDF), tracker_link="tool0")
    order = sorted((float(r["t"]), i) for i, r in enumerate(rows) if r["px"])
    for k, (_t, i) in enumerate(order):
        np.testing.assert_allclose([stops.q[j][k] for j in JOINTS], [float(rows[i][f"q{n}"]) for n in range(1, 8)])


def test_a_utf8_byte_order_mark_is_accepted(tmp_path):
    """Was: "not in the header ['\\ufefft', ...]" for every Excel export."""
    from ppoe_core.io.importers.csv_stops import import_csv

    c, mp = _write(tmp_path, n=6)
    text = c.read_text()
    m = yaml.safe_load(mp.read_text())
    first = text.split(",", 1)[0]
    m["joints"]["joint_1"] = first  # the BOM sits on the first column name
    mp.write_text(yaml.safe_dump(m))
    c.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    assert import_csv(c, mp, URDF, tmp_path / "bag")["stops"] == 6


def test_an_unreadable_urdf_is_one_line(tmp_path, capsys):
    """Was: a FileNotFoundError traceback."""
    from ppoe_ros.cli import main

    c, mp = _write(tmp_path, n=6)
    missing = tmp_path / "nope.urdf"
    assert main(["import", "csv", str(c), "--mapping", str(mp), "--urdf", str(missing), "--out",
                 str(tmp_path / "bag")]) == 2
    err = capsys.readouterr().err
    assert f"{missing}: cannot read the URDF: No such file or directory" in err and "Traceback" not in err, err


@pytest.mark.parametrize("char", ["\x00", "\x07", "\x1b"])
def test_a_control_character_in_a_cell_is_an_error_naming_line_and_column(tmp_path, capsys, char):
    """Was: a NUL inside a station name imported with exit 0 (found by test_fuzz_inputs)."""
    c, mp = _write(tmp_path, n=6)
    _rewrite(c, lambda lines: lines[:4] + [lines[4].replace(",S", f",{char}S")] + lines[5:])
    code, err = _import_exit(c, mp, tmp_path / "bag", capsys)
    assert code == 2 and f"{c}:5: column 'st': control character {char!r}" in err, err
    assert not (tmp_path / "bag").exists()
