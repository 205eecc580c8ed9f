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
for that stop (counted); an empty or non-numeric joint cell is an error naming the row.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.errors import DatasetError
from ppoe_core.io.importers import STOP_TOPIC
from ppoe_core.robot.urdf import Robot

__all__ = ["import_csv", "load_mapping"]

BURST_COUNT = 5
BURST_PERIOD_S = 0.02
MEASUREMENT_DELAY_S = 0.1
_TOP = ("joints", "angle_unit", "length_unit", "points", "pose", "time", "station", "role")


def load_mapping(path: str | Path, robot: Robot) -> dict[str, Any]:
    """The mapping YAML, checked against the URDF (joint names) and the key set (module docstring)."""
    from ppoe_core.robot.config_checks import _check_keys, _Ctx, _mapping
    from ppoe_core.robot.yaml_io import read_yaml_file

    data, where = read_yaml_file(path, "CSV mapping", error=DatasetError)
    ctx = _Ctx(where)
    try:
        top = _mapping(ctx, data, None, None, "mapping")
        _check_keys(ctx, top, _TOP, "mapping", required=("joints",))
        joints = _mapping(ctx, top["joints"], top, "joints", "joints")
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
            p = _mapping(ctx, p, points, None, f"points[{i}]")
            _check_keys(ctx, p, ("topic", "columns", "frame"), f"points[{i}]", required=("columns",))
            if len(p["columns"]) != 3:
                raise ctx.error(p, "columns", f"points[{i}].columns", "must name 3 columns (x, y, z)")
        if "pose" in top:
            pose = _mapping(ctx, top["pose"], top, "pose", "pose")
            _check_keys(ctx, pose, ("columns", "frame"), "pose", required=("columns",))
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

    Raises
    ------
    DatasetError
        A bad mapping, a missing column, a bad cell (naming the row and column).
    """
    from ppoe_core.robot.urdf import parse_urdf

    urdf_xml = Path(urdf_path).read_text(encoding="utf-8")
    robot = parse_urdf(urdf_xml, text_source=str(urdf_path))
    m = load_mapping(mapping_path, robot)
    rows, header = _read_csv(csv_path)
    needed = list(m["joints"].values()) + [c for p in m.get("points") or [] for c in p["columns"]]
    needed += list((m.get("pose") or {}).get("columns", [])) + [m[k] for k in ("time", "station", "role") if k in m]
    missing = [c for c in needed if c not in header]
    if missing:
        raise DatasetError(f"{csv_path}: columns {missing} named by {mapping_path} are not in the header {header}")
    return _write(csv_path, rows, m, robot, urdf_xml, out, overwrite)


def _read_csv(path: str | Path) -> tuple[list[dict[str, str]], list[str]]:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            header = list(reader.fieldnames or [])
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{path}: cannot read as CSV: {exc}") from None
    if not rows:
        raise DatasetError(f"{path}: no data rows")
    return rows, header


def _cell(path: str | Path, row: dict[str, str], i: int, col: str, required: bool) -> float | None:
    text = (row.get(col) or "").strip()
    if not text:
        if required:
            raise DatasetError(f"{path}: row {i + 2} column {col!r}: empty")
        return None
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(f"{path}: row {i + 2} column {col!r}: not a number: {text!r}") from None
    if not math.isfinite(v):
        raise DatasetError(f"{path}: row {i + 2} column {col!r}: not finite: {text!r}")
    return v


def _write(path: str | Path, rows: list[dict[str, str]], m: dict[str, Any], robot: Robot, urdf_xml: str,
           out: str | Path, overwrite: bool) -> dict[str, Any]:
    from ppoe_core.io.bagio import BagWriter, typestore

    ang = math.pi / 180.0 if m.get("angle_unit") == "deg" else 1.0
    lin = 1e-3 if m.get("length_unit") == "mm" else 1.0
    names = list(m["joints"])
    scale = np.array([lin if robot.joints[j].type == "prismatic" else ang for j in names])
    skipped: dict[str, int] = {}
    String = typestore().types["std_msgs/msg/String"]
    with BagWriter(out, overwrite=overwrite) as w:
        w.write_robot_description(urdf_xml, stamp=0.0)
        for i, row in enumerate(rows):
            t = _cell(path, row, i, m["time"], True) if "time" in m else 2.0 * (i + 1)
            assert t is not None
            q = np.array([_cell(path, row, i, m["joints"][j], True) for j in names], dtype=float) * scale
            info: dict[str, Any] = {"stop": i}
            for key in ("station", "role"):
                if key in m:
                    info[key] = row[m[key]].strip()
            if info.get("role", "stationing") not in ("stationing", "evaluation"):
                raise DatasetError(f"{path}: row {i + 2} column {m['role']!r}: role must be stationing or "
                                   f"evaluation, got {info['role']!r}")
            w.write_message(STOP_TOPIC, String(data=json.dumps(info)), t)
            for k in range(BURST_COUNT):
                w.write_joint_state(t + k * BURST_PERIOD_S, names, q)
            tm = t + MEASUREMENT_DELAY_S
            for p in m.get("points") or []:
                topic = p.get("topic", "/ground_truth/point")
                v = [_cell(path, row, i, c, False) for c in p["columns"]]
                if any(x is None for x in v):
                    skipped[topic] = skipped.get(topic, 0) + 1
                    continue
                w.write_ground_truth_point(tm, str(p.get("frame", "tracker")), np.array(v, float) * lin, topic=topic)
            if "pose" in m:
                _pose(path, w, row, i, m["pose"], tm, lin, skipped)
        counts = dict(w.counts)
    return {"counts": counts, "skipped": skipped, "stops": len(rows)}


def _pose(path: str | Path, w: Any, row: dict[str, str], i: int, pose: dict[str, Any], tm: float, lin: float,
          skipped: dict[str, int]) -> None:
    from ppoe_core import lie

    v = [_cell(path, row, i, c, False) for c in pose["columns"]]
    if any(x is None for x in v):
        skipped["/ground_truth/pose"] = skipped.get("/ground_truth/pose", 0) + 1
        return
    quat = np.array(v[3:], float)
    if abs(np.linalg.norm(quat) - 1.0) > 1e-3:
        raise DatasetError(f"{path}: row {i + 2}: pose quaternion {quat.tolist()} is not unit length")
    T = lie.from_rt(lie.matrix_from_quat(quat), np.array(v[:3], float) * lin)
    w.write_ground_truth_pose(tm, str(pose.get("frame", "base_link")), T)
