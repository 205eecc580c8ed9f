"""A URDF from a Denavit-Hartenberg table (``ppoe urdf from-dh``), standard or modified convention.

Table file (YAML; every key checked, errors name the file, line and row)::

    name: my_arm                 # robot name
    convention: standard         # standard (Denavit-Hartenberg 1955) or modified (Craig)
    base_link: base_link         # [base_link]
    joints:                      # one row per joint, base to tip
      - name: joint_1            # joint name; its child link is link_<i> unless `link` is given
        type: revolute           # revolute [default], continuous or prismatic
        a: 0.0                   # [m]
        alpha: 1.5707963         # [rad]
        d: 0.34                  # [m] (prismatic: offset added to the joint value)
        theta: 0.0               # [rad] (revolute: offset added to the joint value)
        lower: -2.9              # joint limits [rad or m] (optional)
        upper: 2.9
        mass: 4.0                # link mass [kg] (optional: gravity effects need it)
        com: [0.0, 0.0, 0.1]     # centre of mass in the link frame [m] (default 0)
    tool: {name: tool0, xyz: [0, 0, 0.1], rpy: [0, 0, 0]}   # optional fixed frame on the last link

Standard: ``T_i = Rz(theta_i + q) Tz(d_i) Tx(a_i) Rx(alpha_i)``; the joint moves about the previous frame's
z, so joint ``i``'s URDF origin is ``Tx(a_{i-1}) Rx(alpha_{i-1}) Rz(theta_i) Tz(d_i)`` and a fixed
``flange`` joint carries the last row's ``Tx(a_n) Rx(alpha_n)``.  Modified: ``T_i = Rx(alpha_{i-1})
Tx(a_{i-1}) Rz(theta_i + q) Tz(d_i)`` with ``a``/``alpha`` of the row itself being ``a_{i-1}``/``alpha_{i-1}``;
the origin is ``Rx(alpha) Tx(a) Rz(theta) Tz(d)``.  Rotations about z commute with translations along z, so
``origin * Rz(q)`` is the row's transform in both conventions; the joint axis is z.
"""

from __future__ import annotations

import os
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from ppoe_core import lie
from ppoe_core.robot.config_checks import _check_keys, _Ctx, _mapping, _number, _vector
from ppoe_core.robot.yaml_io import read_yaml_file

__all__ = ["dh_to_urdf"]

_ROW_KEYS = ("name", "type", "a", "alpha", "d", "theta", "lower", "upper", "mass", "com", "link")


def _rx(a: float) -> np.ndarray:
    return lie.from_rt(lie.matrix_from_rpy([a, 0.0, 0.0]), np.zeros(3))


def _rz(a: float) -> np.ndarray:
    return lie.from_rt(lie.matrix_from_rpy([0.0, 0.0, a]), np.zeros(3))


def _t(x: float, y: float, z: float) -> np.ndarray:
    return lie.from_rt(np.eye(3), np.array([x, y, z]))


def dh_to_urdf(source: str | os.PathLike[str]) -> str:
    """URDF text of the robot described by the DH table file ``source`` (module docstring).

    Raises
    ------
    ModelConfigError
        Unreadable file, unknown key, wrong value; the message names the file, line and row.
    """
    data, where = read_yaml_file(source, "DH table")
    ctx = _Ctx(where)
    top = _mapping(ctx, data, None, None, "DH table")
    _check_keys(ctx, top, ("name", "convention", "base_link", "joints", "tool"), "DH table", required=("joints",))
    convention = top.get("convention", "standard")
    if convention not in ("standard", "modified"):
        raise ctx.error(top, "convention", "convention", f"must be standard or modified, got {convention!r}")
    rows = top["joints"]
    if not isinstance(rows, list) or not rows:
        raise ctx.error(top, "joints", "joints", "must be a non-empty list of rows")
    parsed = [_row(ctx, r, rows, i) for i, r in enumerate(rows)]
    base = str(top.get("base_link", "base_link"))
    names = [base] + [p["link"] for p in parsed] + [p["name"] for p in parsed]
    if len(set(names)) != len(names):
        raise ctx.error(top, "joints", "joints", f"joint and link names must be unique, got {names}")
    out = [f"<robot name={quoteattr(str(top.get('name', 'dh_robot')))}>",
           f"  <!-- from the {convention} DH table {where} by ppoe urdf from-dh -->",
           f"  <link name={quoteattr(base)}/>"]
    parent, prev = base, None
    for p in parsed:
        if convention == "standard":
            pre = np.eye(4) if prev is None else _t(prev["a"], 0, 0) @ _rx(prev["alpha"])
            origin = pre @ _rz(p["theta"]) @ _t(0, 0, p["d"])
        else:
            origin = _rx(p["alpha"]) @ _t(p["a"], 0, 0) @ _rz(p["theta"]) @ _t(0, 0, p["d"])
        out += _link(p) + _joint(p["name"], p["type"], parent, p["link"], origin, p)
        parent, prev = p["link"], p
    last = parent
    if convention == "standard" and prev is not None and (prev["a"] or prev["alpha"]):
        out += [f"  <link name={quoteattr(last + '_flange')}/>"]
        out += _joint("flange_joint", "fixed", last, last + "_flange", _t(prev["a"], 0, 0) @ _rx(prev["alpha"]), {})
        last = last + "_flange"
    if "tool" in top:
        tool = _mapping(ctx, top["tool"], top, "tool", "tool")
        _check_keys(ctx, tool, ("name", "xyz", "rpy"), "tool", required=("name",))
        xyz = _vector(ctx, tool["xyz"], tool, "xyz", "tool.xyz", 3) if "xyz" in tool else np.zeros(3)
        rpy = _vector(ctx, tool["rpy"], tool, "rpy", "tool.rpy", 3) if "rpy" in tool else np.zeros(3)
        out += [f"  <link name={quoteattr(str(tool['name']))}/>"]
        out += _joint(f"{tool['name']}_joint", "fixed", last, str(tool["name"]), lie.from_xyz_rpy(xyz, rpy), {})
    return "\n".join(out + ["</robot>", ""])


def _row(ctx: _Ctx, row: Any, rows: list, i: int) -> dict[str, Any]:
    path = f"joints[{i}]"
    row = _mapping(ctx, row, rows, None, path)
    _check_keys(ctx, row, _ROW_KEYS, path, required=("name",))
    jtype = row.get("type", "revolute")
    if jtype not in ("revolute", "continuous", "prismatic"):
        raise ctx.error(row, "type", path + ".type", f"must be revolute, continuous or prismatic, got {jtype!r}")
    out: dict[str, Any] = {"name": str(row["name"]), "type": jtype, "link": str(row.get("link", f"link_{i + 1}"))}
    for k in ("a", "alpha", "d", "theta"):
        out[k] = _number(ctx, row[k], row, k, f"{path}.{k}") if k in row else 0.0
    for k in ("lower", "upper"):
        if k in row:
            out[k] = _number(ctx, row[k], row, k, f"{path}.{k}")
    if jtype != "continuous" and not ("lower" in out and "upper" in out):
        raise ctx.error(row, None, path, f"a {jtype} joint needs both lower and upper limits (or type: continuous)")
    if "lower" in out and out["lower"] > out["upper"]:
        raise ctx.error(row, "lower", path + ".lower", f"lower {out['lower']} > upper {out['upper']}")
    if "mass" in row:
        out["mass"] = _number(ctx, row["mass"], row, "mass", f"{path}.mass", positive=True)
        out["com"] = _vector(ctx, row["com"], row, "com", f"{path}.com", 3) if "com" in row else np.zeros(3)
    elif "com" in row:
        raise ctx.error(row, "com", path + ".com", "a centre of mass needs a mass")
    return out


def _fmt(v: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in v)


def _link(p: dict[str, Any]) -> list[str]:
    name = quoteattr(p["link"])
    if "mass" not in p:
        return [f"  <link name={name}/>"]
    return [f"  <link name={name}>", "    <inertial>", f'      <origin xyz="{_fmt(p["com"])}" rpy="0 0 0"/>',
            f'      <mass value="{p["mass"]!r}"/>',
            '      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>', "    </inertial>",
            "  </link>"]


def _joint(name: str, jtype: str, parent: str, child: str, origin: np.ndarray, p: dict[str, Any]) -> list[str]:
    rpy = lie.rpy_from_matrix(origin[:3, :3])
    lines = [f"  <joint name={quoteattr(name)} type={quoteattr(jtype)}>",
             f"    <parent link={quoteattr(parent)}/>", f"    <child link={quoteattr(child)}/>",
             f'    <origin xyz="{_fmt(origin[:3, 3])}" rpy="{_fmt(rpy)}"/>']
    if jtype != "fixed":
        lines.append('    <axis xyz="0 0 1"/>')
    if "lower" in p and jtype != "continuous":
        lines.append(f'    <limit lower="{p["lower"]!r}" upper="{p["upper"]!r}" effort="100" velocity="1"/>')
    return lines + ["  </joint>"]
