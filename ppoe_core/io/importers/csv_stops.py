"""``ppoe import csv``: any robot's static calibration data (one CSV row per stop) as a contract bag.

The CSV has a header row; a small mapping YAML says which columns are what (every key checked, errors name
the file and line, CSV errors the row and column)::

    joints:                        # URDF joint -> CSV column (required)
      joint_1: q1
      joint_2: q2
    angle_unit: rad                # rad [default] or deg: unit of revolute joint columns
    length_unit: m                 # m [default] or mm: unit of prismatic joint and position columns
    points:                        # tracker points (optional): one entry per reflector
      - {topic: /ground_truth/point, columns: [x, y, z], frame: tracker}
    pose:                          # tool pose in the base frame (optional)
      {columns: [x, y, z, qx, qy, qz, qw], frame: base_link}
    time: t                        # column of the stop time [s] (optional; else one stop per 2 s)
    station: station               # column naming the registration session (optional)
    role: role                     # column: stationing | evaluation (optional; the stop roles of --test)

Per stop the bag holds (docs/conventions.md sec. 3, static dataset): a ``/dataset/stop`` JSON object
(``stop``, ``station``, ``role``), a burst of :data:`BURST_COUNT` identical ``/joint_states`` at 50 Hz, then
the measurements, stamped inside the stop.  Empty cells of a measurement column skip that measurement
for that stop (counted); an empty or non-numeric joint cell is an error naming ``FILE:LINE`` and the column.
A column named twice in the header, a row with more or fewer cells than the header, or two stops closer
than :data:`STOP_MIN_SPACING_S` in time are errors; a UTF-8 byte-order mark (Excel) is accepted.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.errors import DatasetError
from ppoe_core.io.importers import STOP_TOPIC
from ppoe_core.robot.urdf import Robot

__all__ = ["import_csv", "load_mapping", "read_csv_rows", "STOP_MIN_SPACING_S"]

BURST_COUNT = 5
BURST_PERIOD_S = 0.02
MEASUREMENT_DELAY_S = 0.1
#: closest two stop times may be [s]: a stop's burst of joint states and its measurements take 0.1 s, and the
#: measurement holds the stop's joint values only across a gap of more than 5 burst periods (0.1 s) before the
#: next stop (:func:`ppoe_core.model.context.sample_series`)
STOP_MIN_SPACING_S = 0.2
_TOP = ("joints", "angle_unit", "length_unit", "points", "pose", "time", "station", "role")


def load_mapping(path: str | Path, robot: Robot) -> dict[str, Any]:
    """The mapping YAML, checked against the URDF (joint names) and the key set (module docstring)."""
    from ppoe_core.robot.config_checks import check_keys, CheckContext, check_mapping
    from ppoe_core.robot.yaml_io import read_yaml_file

    data, where = read_yaml_file(path, "CSV mapping", error=DatasetError)
    ctx = CheckContext(where)
    try:
        top = check_mapping(ctx, data, None, None, "mapping")
        check_keys(ctx, top, _TOP, "mapping", required=("joints",))
        joints = check_mapping(ctx, top["joints"], top, "joints", "joints")
        for jn in joints:
            if jn not in robot.joints or not robot.joints[jn].independent:
                raise ctx.error(joints, jn, f"joints.{jn}", f"not an independent movable joint of {robot.source}")
        for key, allowed in (("angle_unit", ("rad", "deg")), ("length_unit", ("m", "mm"))):
            if top.get(key, allowed[0]) not in allowed:
                raise ctx.error(top, key, key, f"must be one of {list(allowed)}, got {top[key]!r}")
        points = top.get("points") or []
        if not isinstance(points, list):
            raise ctx.error(top, "points", "points", "must be a list of {topic, columns, frame}")
        for i, p in enumerate(points):
            p = check_mapping(ctx, p, points, None, f"points[{i}]")
            check_keys(ctx, p, ("topic", "columns", "frame"), f"points[{i}]", required=("columns",))
            if len(p["columns"]) != 3:
                raise ctx.error(p, "columns", f"points[{i}].columns", "must name 3 columns (x, y, z)")
        if "pose" in top:
            pose = check_mapping(ctx, top["pose"], top, "pose", "pose")
            check_keys(ctx, pose, ("columns", "frame"), "pose", required=("columns",))
            if len(pose["columns"]) != 7:
                raise ctx.error(pose, "columns", "pose.columns", "must name 7 columns (x y z qx qy qz qw)")
    except Exception as exc:  # config_checks raise ModelConfigError: re-raise as the importer's error
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(str(exc)) from None
    return dict(top)


def import_csv(csv_path: str | Path, mapping_path: str | Path, urdf_path: str | Path, out: str | Path,
               overwrite: bool = False) -> dict[str, Any]:
    """Write the contract bag ``out`` from ``csv_path``; returns the counts written and skipped.

    Every row is read and checked before the bag is written: a bad file leaves no bag behind.

    Raises
    ------
    DatasetError
        A bad mapping, a missing or repeated column, a row longer or shorter than the header, a bad cell, stop
        times closer than :data:`STOP_MIN_SPACING_S` (naming ``FILE:LINE`` and the column).
    """
    from ppoe_core.io.importers import check_outputs
    from ppoe_core.robot.urdf import parse_urdf

    check_outputs(Path(out), None, overwrite)
    try:
        urdf_xml = Path(urdf_path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{urdf_path}: cannot read the URDF: {getattr(exc, 'strerror', None) or exc}") from None
    robot = parse_urdf(urdf_xml, text_source=str(urdf_path))  # UrdfError naming the user's file and line
    m = load_mapping(mapping_path, robot)
    rows, header = read_csv_rows(csv_path)
    needed = list(m["joints"].values()) + [c for p in m.get("points") or [] for c in p["columns"]]
    needed += list((m.get("pose") or {}).get("columns", [])) + [m[k] for k in ("time", "station", "role") if k in m]
    missing = [c for c in needed if c not in header]
    if missing:
        raise DatasetError(f"{csv_path}: columns {missing} named by {mapping_path} are not in the header {header}")
    stops = _parse_stops(csv_path, rows, m, robot)
    return _write(stops, m, urdf_xml, out, overwrite)


#: (line number in the file, cells by column name)
CsvRow = tuple[int, dict[str, str]]


def read_csv_rows(path: str | Path) -> tuple[list[CsvRow], list[str]]:
    """Data rows of a CSV with a header row: ``([(line, {column: cell})], header)``.

    A UTF-8 byte-order mark (Excel) is skipped, header names are stripped, blank lines skipped.

    Raises
    ------
    DatasetError
        Unreadable file, no header or no data rows, a column named twice in the header, a row with more or
        fewer cells than the header, a control character such as NUL (``FILE:LINE``, the column).
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            first = next(reader, None)
            header = [h.strip() for h in first or []]
            _check_text(path, 1, dict(zip(header, header)))
            _check_header(path, header)
            rows: list[CsvRow] = []
            line = reader.line_num + 1
            for cells in reader:
                if cells and len(cells) != len(header):
                    raise DatasetError(f"{path}:{line}: {len(cells)} cells but the header has {len(header)} "
                                       f"columns; every row must have one cell per column (empty cells allowed)")
                if cells:
                    rows.append((line, _check_text(path, line, dict(zip(header, cells)))))
                line = reader.line_num + 1
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{path}: cannot read as CSV: {getattr(exc, 'strerror', None) or exc}") from None
    if not rows:
        raise DatasetError(f"{path}: no data rows")
    return rows, header


#: characters no text cell holds (C0 controls but tab, line feed and carriage return; DEL)
_CONTROL = frozenset(chr(c) for c in [*range(0x00, 0x09), 0x0B, 0x0C, *range(0x0E, 0x20), 0x7F])


def _check_text(path: str | Path, line: int, cells: dict[str, str]) -> dict[str, str]:
    """``cells``, or an error naming the line and column of a control character (NUL: a binary or damaged file)."""
    for col, text in cells.items():
        bad = next((ch for ch in text if ch in _CONTROL), None)
        if bad is not None:
            raise DatasetError(f"{path}:{line}: column {col!r}: control character {bad!r} in {text!r}: not a text "
                               "CSV (binary or damaged file?)")
    return cells


def _check_header(path: str | Path, header: list[str]) -> None:
    if not header:
        raise DatasetError(f"{path}: empty file: no header row")
    for name in header:
        where = [k + 1 for k, h in enumerate(header) if h == name]
        if name and len(where) > 1:
            raise DatasetError(f"{path}:1: column {name!r} appears {len(where)} times in the header (columns "
                               f"{', '.join(map(str, where))}); rename one of them")


def _cell(path: str | Path, row: CsvRow, col: str, required: bool) -> float | None:
    line, cells = row
    text = (cells.get(col) or "").strip()
    if not text:
        if required:
            raise DatasetError(f"{path}:{line}: column {col!r}: empty")
        return None
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(f"{path}:{line}: column {col!r}: not a number: {text!r}") from None
    if not math.isfinite(v):
        raise DatasetError(f"{path}:{line}: column {col!r}: not finite: {text!r}")
    return v


class _Stop(NamedTuple):
    """One CSV row, checked: stop time [s], joint values [rad, m], stop info, points and pose (None: empty)."""

    t: float
    q: np.ndarray
    info: dict[str, Any]
    points: list[tuple[str, str, np.ndarray | None]]
    pose: np.ndarray | None


def _parse_stops(path: str | Path, rows: list[CsvRow], m: dict[str, Any], robot: Robot) -> list[_Stop]:
    """Every row checked and converted (units applied) before anything is written."""
    ang = math.pi / 180.0 if m.get("angle_unit") == "deg" else 1.0
    lin = 1e-3 if m.get("length_unit") == "mm" else 1.0
    names = list(m["joints"])
    scale = np.array([lin if robot.joints[j].type == "prismatic" else ang for j in names])
    times = _stop_times(path, rows, m)
    stops = []
    for i, (row, t) in enumerate(zip(rows, times)):
        q = np.array([_cell(path, row, m["joints"][j], True) for j in names], dtype=float) * scale
        info: dict[str, Any] = {"stop": i}
        for key in ("station", "role"):
            if key in m:
                info[key] = row[1][m[key]].strip()
        if info.get("role", "stationing") not in ("stationing", "evaluation"):
            raise DatasetError(f"{path}:{row[0]}: column {m['role']!r}: role must be stationing or evaluation, "
                               f"got {info['role']!r}")
        points = []
        for p in m.get("points") or []:
            v = [_cell(path, row, c, False) for c in p["columns"]]
            xyz = None if any(x is None for x in v) else np.array(v, float) * lin
            points.append((str(p.get("topic", "/ground_truth/point")), str(p.get("frame", "tracker")), xyz))
        pose = _pose(path, row, m["pose"], lin) if "pose" in m else None
        stops.append(_Stop(t, q, info, points, pose))
    return stops


def _stop_times(path: str | Path, rows: list[CsvRow], m: dict[str, Any]) -> list[float]:
    """Stop times [s] (the ``time`` column, else one stop per 2 s); stops closer than
    :data:`STOP_MIN_SPACING_S` are an error naming both lines (their joint states would interleave)."""
    if "time" not in m:
        return [2.0 * (i + 1) for i in range(len(rows))]
    times = [float(_cell(path, row, m["time"], True) or 0.0) for row in rows]
    order = sorted(range(len(rows)), key=times.__getitem__)
    for a, b in zip(order, order[1:]):
        if times[b] - times[a] < STOP_MIN_SPACING_S:
            raise DatasetError(
                f"{path}:{rows[b][0]}: column {m['time']!r}: stop time {times[b]:g} s is "
                f"{'the same as' if times[b] == times[a] else f'{times[b] - times[a]:.3g} s after'} the stop at line "
                f"{rows[a][0]} ({times[a]:g} s); stops must be at least {STOP_MIN_SPACING_S:g} s apart, or one "
                "stop's measurements would get the other stop's joint values")
    return times


def _write(stops: list[_Stop], m: dict[str, Any], urdf_xml: str, out: str | Path,
           overwrite: bool) -> dict[str, Any]:
    from ppoe_core.io.bagio import BagWriter, typestore

    names = list(m["joints"])
    skipped: dict[str, int] = {}
    String = typestore().types["std_msgs/msg/String"]
    with BagWriter(out, overwrite=overwrite) as w:
        w.write_robot_description(urdf_xml, stamp=0.0)
        for s in stops:
            w.write_message(STOP_TOPIC, String(data=json.dumps(s.info)), s.t)
            for k in range(BURST_COUNT):
                w.write_joint_state(s.t + k * BURST_PERIOD_S, names, s.q)
            tm = s.t + MEASUREMENT_DELAY_S
            for topic, frame, xyz in s.points:
                if xyz is None:
                    skipped[topic] = skipped.get(topic, 0) + 1
                else:
                    w.write_ground_truth_point(tm, frame, xyz, topic=topic)
            if s.pose is None and "pose" in m:
                skipped["/ground_truth/pose"] = skipped.get("/ground_truth/pose", 0) + 1
            elif s.pose is not None:
                w.write_ground_truth_pose(tm, str(m["pose"].get("frame", "base_link")), s.pose)
        counts = dict(w.counts)
    return {"counts": counts, "skipped": skipped, "stops": len(stops)}


def _pose(path: str | Path, row: CsvRow, pose: dict[str, Any], lin: float) -> np.ndarray | None:
    """Tool pose (4, 4) of a row's pose columns (x y z [length unit], qx qy qz qw); None if a cell is empty."""
    from ppoe_core import lie

    v = [_cell(path, row, c, False) for c in pose["columns"]]
    if any(x is None for x in v):
        return None
    quat = np.array(v[3:], float)
    if abs(np.linalg.norm(quat) - 1.0) > 1e-3:
        raise DatasetError(f"{path}:{row[0]}: pose quaternion {quat.tolist()} is not unit length")
    return lie.from_rt(lie.matrix_from_quat(quat), np.array(v[:3], float) * lin)
