"""Fuzzing the readers of user files with malformed input (issue 25): ``ppoe import csv`` must answer every
malformed file with one error line and exit code 2, never a traceback and never exit 0.

Each example is a valid stops CSV of planar3 broken in one way hypothesis chooses (a cell, a row, the header,
the bytes), or arbitrary text; the command runs in-process (``ppoe_ros.cli.main``), so any exception other than
the tool's own errors fails the test with its traceback.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import pytest
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


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
