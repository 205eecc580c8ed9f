"""Fuzzing the readers of user files with malformed input (issue 25): ``ppoe import csv`` and ``ppoe urdf
from-dh`` must answer every malformed file with one error line and exit code 2, never a traceback and never
exit 0.

Each example is a valid input (a stops CSV of planar3; a DH table with a second chain, a tool and a camera frame)
broken in one way hypothesis chooses (a cell, a row, the header, the bytes; a value, a key, a name, a parent), or
arbitrary bytes; the command runs in-process (``ppoe_ros.cli.main``), so any exception other than the tool's
own errors fails the test with its traceback.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import pytest
import yaml
from conftest import CONFIG_ROBOTS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ppoe_ros.cli import main

PLANAR3 = CONFIG_ROBOTS / "planar3.urdf"
HEADER = ["t", "a", "b", "c", "x", "y", "z", "station"]
MAPPING = ("joints: {joint1: a, joint2: b, joint3: c}\ntime: t\nstation: station\n"
           "points: [{topic: /ground_truth/point, columns: [x, y, z], frame: tracker}]\n")


def _valid_rows(n: int) -> list[list[str]]:
    return [[f"{2.0 * (i + 1):g}", f"{0.1 * i:g}", "0.2", "-0.3", "1.5", f"{-0.2 * i:g}", "0.7", f"S{i % 2}"]
            for i in range(n)]


def _csv(header: list[str], rows: list[list[str]]) -> str:
    return "\n".join(",".join(r) for r in [header, *rows]) + "\n"


BAD_CELLS = st.sampled_from(["", "abc", "nan", "inf", "-inf", "1e400", "0x10", "1,5", '"', "NaN", "--1", "1..2"])


@st.composite
def broken_csv(draw) -> bytes:
    """A valid CSV broken in one way."""
    rows = _valid_rows(draw(st.integers(2, 6)))
    header = list(HEADER)
    how = draw(st.sampled_from(["cell", "extra_cell", "missing_cell", "duplicate_column", "missing_column",
                                "same_time", "no_rows", "bytes", "nul", "truncated_quote"]))
    r = draw(st.integers(0, len(rows) - 1))
    if how == "cell":  # a joint or time cell (point cells may be empty: a skipped measurement, counted)
        rows[r][draw(st.integers(0, 3))] = draw(BAD_CELLS)
    elif how == "extra_cell":
        rows[r].append(draw(st.sampled_from(["", "1", "x"])))
    elif how == "missing_cell":
        rows[r].pop(draw(st.integers(0, len(rows[r]) - 1)))
    elif how == "duplicate_column":
        k = draw(st.integers(0, 3))
        header.append(header[k])
        rows = [row + [row[k]] for row in rows]
    elif how == "missing_column":
        k = draw(st.integers(0, 3))
        header[k] = header[k] + "_renamed"
    elif how == "same_time":
        rows[r][0] = rows[(r + 1) % len(rows)][0]
    elif how == "no_rows":
        rows = []
    text = _csv(header, rows)
    if how == "bytes":
        k = draw(st.integers(0, len(text) - 1))
        return text[:k].encode() + draw(st.sampled_from([b"\xff\xfe", b"\xc3", b"\x80\x81"])) + text[k:].encode()
    if how == "nul":
        k = draw(st.integers(0, len(text) - 1))
        return (text[:k] + "\x00" + text[k:]).encode()
    if how == "truncated_quote":
        return (text + '"1.0,0.1').encode()
    return text.encode()


def _run(data: bytes) -> tuple[int, str]:
    """``ppoe import csv`` of ``data``: (exit code, stderr)."""
    err = io.StringIO()
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stderr(err):
        csv_path, mapping = Path(tmp) / "stops.csv", Path(tmp) / "map.yaml"
        csv_path.write_bytes(data)
        mapping.write_text(MAPPING)
        code = main(["import", "csv", str(csv_path), "--mapping", str(mapping), "--urdf", str(PLANAR3),
                     "--out", str(Path(tmp) / "bag")])
    return code, err.getvalue()


def test_the_valid_file_imports():
    assert _run(_csv(HEADER, _valid_rows(4)).encode())[0] == 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(broken_csv())
def test_malformed_csv_is_one_error_never_a_traceback_or_exit_0(data):
    code, err = _run(data)
    assert code == 2, (data, err)
    assert err.startswith("ppoe import: error: ") and len(err.strip().splitlines()) == 1, err


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_arbitrary_bytes_are_one_error(data):
    code, err = _run(data)
    assert code == 2 and err.startswith("ppoe import: error: "), (data, err)



# ----------------------------------------------------------------------------- DH tables


def _valid_table() -> dict:
    row = {"a": 0.1, "alpha": 1.5, "d": 0.3, "theta": 0.0, "lower": -2.0, "upper": 2.0, "mass": 1.5,
           "com": [0.0, 0.0, 0.05], "inertia": [0.01, 0.01, 0.005]}
    return {"name": "fuzz_arm", "convention": "standard", "base_link": "base_link",
            "joints": [{"name": f"j{i}", **row} for i in range(1, 4)],
            "tool": {"name": "tool0", "xyz": [0.0, 0.0, 0.1], "rpy": [0.0, 0.0, 0.0]},
            "chains": [{"name": "aux", "parent": "link_2", "mount": {"name": "aux_mount", "xyz": [0.0, 0.1, 0.0]},
                        "joints": [{"name": "aux_j1", "type": "prismatic", "d": 0.1, "lower": 0.0, "upper": 0.2}]}],
            "frames": [{"name": "camera_link", "parent": "base_link", "xyz": [1.0, 0.0, 1.0],
                        "rpy": [0.0, 0.5, 3.1]}]}


BAD_VALUES = st.sampled_from([float("nan"), float("inf"), "abc", None, [1.0, 2.0], {"x": 1}, True, "", -1.0, 0.0])
NUMBER_KEYS = ["a", "alpha", "d", "theta", "lower", "upper", "mass"]
VECTOR_KEYS = ["com", "inertia"]


def _targets(table: dict) -> list[dict]:
    """The mappings a mutation may hit: rows, fixed frames, the chain."""
    return [*table["joints"], table["tool"], table["chains"][0], table["chains"][0]["mount"],
            *table["chains"][0]["joints"], *table["frames"]]


@st.composite
def broken_table(draw) -> dict:
    """A valid DH table broken in one way."""
    t = _valid_table()
    row = draw(st.sampled_from(t["joints"] + t["chains"][0]["joints"]))
    frame = draw(st.sampled_from([t["tool"], t["chains"][0]["mount"], *t["frames"]]))
    how = draw(st.sampled_from(["number", "vector", "frame_vector", "name", "duplicate", "unknown_key",
                                "missing_key", "parent", "type", "limits", "convention", "joints", "inertia_len"]))
    if how == "number":
        row[draw(st.sampled_from(NUMBER_KEYS))] = draw(BAD_VALUES.filter(lambda v: not isinstance(v, float)
                                                                        or not 0 <= abs(v) < 1e300))
    elif how == "vector":
        key = draw(st.sampled_from(VECTOR_KEYS))
        row.setdefault("mass", 1.0)
        row[key] = [draw(BAD_VALUES.filter(lambda v: not isinstance(v, float) or v != v or abs(v) == float("inf"))),
                    0.0, 0.0]
    elif how == "frame_vector":
        frame[draw(st.sampled_from(["xyz", "rpy"]))] = draw(st.sampled_from([[0.0, float("nan"), 0.0], [1.0, 2.0],
                                                                              "abc", None, [0.0, "x", 0.0]]))
    elif how == "name":
        draw(st.sampled_from([row, frame]))["name"] = draw(st.sampled_from(["", None, " ", "a b<", 3.5, [1]]))
    elif how == "duplicate":
        target = draw(st.sampled_from([row, frame]))
        names = [r["name"] for r in t["joints"]] + ["link_1", "base_link", "tool0", "camera_link"]
        target["name"] = draw(st.sampled_from([n for n in names if n != target["name"]]))
    elif how == "unknown_key":
        draw(st.sampled_from([row, frame, t, t["chains"][0]]))["bogus"] = 1
    elif how == "missing_key":
        del draw(st.sampled_from([row, frame, t["chains"][0]]))["name"]
    elif how == "parent":
        target = draw(st.sampled_from([t["chains"][0], t["frames"][0]]))
        target["parent"] = draw(st.sampled_from(["no_such_link", None, ""] + (  # a link made only later
            ["aux_link_1"] if target is t["chains"][0] else [])))
    elif how == "type":
        row["type"] = draw(st.sampled_from(["fixed", "floating", "", None, 1]))
    elif how == "limits":
        row.update(lower=1.0, upper=-1.0)
    elif how == "convention":
        t["convention"] = draw(st.sampled_from(["craig", "", None, 2]))
    elif how == "joints":
        draw(st.sampled_from([t, t["chains"][0]]))["joints"] = draw(st.sampled_from([[], None, "j1", {"a": 1}]))
    elif how == "inertia_len":
        row["inertia"] = [0.01] * draw(st.sampled_from([0, 1, 2, 4, 5, 7]))
    return t


def _urdf_from_dh(text: bytes) -> tuple[int, str]:
    """``ppoe urdf from-dh`` of a table file holding ``text``: (exit code, stderr)."""
    err = io.StringIO()
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stderr(err):
        table = Path(tmp) / "table.yaml"
        table.write_bytes(text)
        code = main(["urdf", "from-dh", str(table), "--out", str(Path(tmp) / "robot.urdf")])
    return code, err.getvalue()


def test_the_valid_table_converts():
    code, err = _urdf_from_dh(yaml.safe_dump(_valid_table()).encode())
    assert code == 0, err


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(broken_table())
def test_malformed_dh_table_is_one_error_never_a_traceback_or_exit_0(table):
    code, err = _urdf_from_dh(yaml.safe_dump(table, allow_unicode=True).encode())
    assert code == 2, (table, err)
    assert err.startswith("ppoe urdf: error: ") and len(err.strip().splitlines()) == 1, err
    assert "URDF from" not in err, err  # the table's file and line, not a line of the generated URDF


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_arbitrary_bytes_as_a_dh_table_are_one_error(data):
    code, err = _urdf_from_dh(data)
    assert code == 2 and err.startswith("ppoe urdf: error: "), (data, err)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
