"""A URDF from a Denavit-Hartenberg table (``ppoe urdf from-dh``), standard or modified convention; one chain or a
tree of chains (a humanoid: torso, two arms, a head).

Table file (YAML; every key checked, errors name the file, line and row)::

    name: my_arm                 # robot name
    convention: standard         # standard (Denavit-Hartenberg 1955) or modified (Craig)
    base_link: base_link         # root link of the URDF [base_link]
    joints:                      # one row per joint, base to tip (the first chain, hanging on base_link)
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
        inertia: [0.05, 0.05, 0.01]   # about the centre of mass, link axes [kg m^2]: ixx iyy izz, or
                                      # ixx ixy ixz iyy iyz izz [0.01 0.01 0.01]
    tool: {name: tool0, xyz: [0, 0, 0.1], rpy: [0, 0, 0]}   # optional fixed frame on the last link
    chains:                      # optional further chains (a tree), built in this order
      - name: left_arm           # chain name: default link names <name>_link_<i>, flange joint <name>_flange_joint
        parent: link_3           # link it hangs on: base_link, or a link made above [base_link]
        mount: {name: l_shoulder, xyz: [0, 0.2, 0.3], rpy: [-1.57, 0, 0]}   # optional fixed frame on the parent
        joints: [...]            # rows as above; the first row's frame is the mount (or the parent)
        tool: {name: l_hand, xyz: [0, 0, 0.08]}   # optional fixed frame on the last link
    frames:                      # optional fixed frames anywhere (cameras, sensors), in this order
      - {name: camera_link, parent: base_link, joint: camera_joint, xyz: [1.5, 0, 1], rpy: [0, 0.5, 3.14]}

A fixed frame (``tool``, ``mount``, ``frames`` entry) has ``name`` (its link), ``joint`` (its fixed joint
[``<name>_joint``]), ``xyz`` [m], ``rpy`` [rad] (default 0), and optionally ``mass`` / ``com`` / ``inertia``
(a payload on a tool); ``parent`` only in ``frames``.  With ``chains``, top-level ``joints`` may be omitted.

Standard: ``T_i = Rz(theta_i + q) Tz(d_i) Tx(a_i) Rx(alpha_i)``; the joint moves about the previous frame's
z, so joint ``i``'s URDF origin is ``Tx(a_{i-1}) Rx(alpha_{i-1}) Rz(theta_i) Tz(d_i)`` and a fixed
``flange`` joint carries the last row's ``Tx(a_n) Rx(alpha_n)``.  Modified: ``T_i = Rx(alpha_{i-1})
Tx(a_{i-1}) Rz(theta_i + q) Tz(d_i)`` with ``a``/``alpha`` of the row itself being ``a_{i-1}``/``alpha_{i-1}``;
the origin is ``Rx(alpha) Tx(a) Rz(theta) Tz(d)``.  Rotations about z commute with translations along z, so
``origin * Rz(q)`` is the row's transform in both conventions; the joint axis is z.  Every chain starts in its
mount (or parent) frame as the first chain starts in ``base_link``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from ppoe_core import lie
from ppoe_core.robot.config_checks import check_keys, CheckContext, check_mapping, check_number, check_vector
from ppoe_core.robot.yaml_io import read_yaml_file

__all__ = ["dh_to_urdf"]

_ROW_KEYS = ("name", "type", "a", "alpha", "d", "theta", "lower", "upper", "mass", "com", "inertia", "link")
_TOP_KEYS = ("name", "convention", "base_link", "joints", "tool", "chains", "frames")
_CHAIN_KEYS = ("name", "parent", "mount", "joints", "tool")
_FIXED_KEYS = ("name", "joint", "xyz", "rpy", "mass", "com", "inertia")
#: inertia written when a link has a mass but no inertia [kg m^2] (the format's default before inertias existed)
_DEFAULT_INERTIA = np.array([0.01, 0.0, 0.0, 0.01, 0.0, 0.01])


def _rx(a: float) -> np.ndarray:
    return lie.from_rt(lie.matrix_from_rpy([a, 0.0, 0.0]), np.zeros(3))


def _rz(a: float) -> np.ndarray:
    return lie.from_rt(lie.matrix_from_rpy([0.0, 0.0, a]), np.zeros(3))


def _t(x: float, y: float, z: float) -> np.ndarray:
    return lie.from_rt(np.eye(3), np.array([x, y, z]))


class _Tree:
    """The URDF lines built so far and the names used (each name once, errors name the entry)."""

    def __init__(self, ctx: CheckContext, base: str) -> None:
        self.ctx = ctx
        self.links: set[str] = {base}
        self.joints: set[str] = set()
        self.lines: list[str] = [f"  <link name={quoteattr(base)}/>"]

    def add(self, obj: Any, key: Any, path: str, link: str, joint: str) -> None:
        for kind, name, used in (("link", link, self.links), ("joint", joint, self.joints)):
            if name in used or (kind == "link" and name in self.joints) or (kind == "joint" and name in self.links):
                raise self.ctx.error(obj, key, path, f"{kind} name '{name}' is used twice (joint and link names "
                                                     "must be unique)")
            used.add(name)

    def parent(self, obj: Any, key: Any, path: str, name: Any) -> str:
        if str(name) not in self.links:
            raise self.ctx.error(obj, key, path, f"unknown parent link '{name}' (links so far: "
                                                 f"{', '.join(sorted(self.links))})")
        return str(name)


def dh_to_urdf(source: str | os.PathLike[str]) -> str:
    """URDF text of the robot described by the DH table file ``source`` (module docstring).

    Raises
    ------
    ModelConfigError
        Unreadable file, unknown key, wrong value, a name used twice, an unknown parent link; the message names
        the file, line and row.
    """
    data, where = read_yaml_file(source, "DH table")
    ctx = CheckContext(where)
    top = check_mapping(ctx, data, None, None, "DH table")
    check_keys(ctx, top, _TOP_KEYS, "DH table")
    if "joints" not in top and "chains" not in top:
        raise ctx.error(top, None, "DH table", "missing required key 'joints' (or 'chains')")
    convention = top.get("convention", "standard")
    if convention not in ("standard", "modified"):
        raise ctx.error(top, "convention", "convention", f"must be standard or modified, got {convention!r}")
    base = _name(ctx, top, "base_link", "base_link", "base_link")
    tree = _Tree(ctx, base)
    if "joints" in top:
        _chain(ctx, tree, convention, top, "", base, None)
    chains = top.get("chains", [])
    if not isinstance(chains, list):
        raise ctx.error(top, "chains", "chains", "must be a list of chains")
    for k, ch in enumerate(chains):
        ch = check_mapping(ctx, ch, chains, None, f"chains[{k}]")
        check_keys(ctx, ch, _CHAIN_KEYS, f"chains[{k}]", required=("name", "joints"))
        parent = tree.parent(ch, "parent", f"chains[{k}].parent", ch.get("parent", base))
        _chain(ctx, tree, convention, ch, f"chains[{k}].", parent, _name(ctx, ch, "name", f"chains[{k}].name"))
    frames = top.get("frames", [])
    if not isinstance(frames, list):
        raise ctx.error(top, "frames", "frames", "must be a list of fixed frames")
    for k, fr in enumerate(frames):
        fr = check_mapping(ctx, fr, frames, None, f"frames[{k}]")
        check_keys(ctx, fr, _FIXED_KEYS + ("parent",), f"frames[{k}]", required=("name", "parent"))
        parent = tree.parent(fr, "parent", f"frames[{k}].parent", fr["parent"])
        _fixed(ctx, tree, {k_: v for k_, v in fr.items() if k_ != "parent"}, fr, f"frames[{k}]", parent)
    head = [f"<robot name={quoteattr(_name(ctx, top, 'name', 'name', 'dh_robot'))}>",
            f"  <!-- from the {convention} DH table {where} by ppoe urdf from-dh -->"]
    return "\n".join(head + tree.lines + ["</robot>", ""])


def _chain(ctx: CheckContext, tree: _Tree, convention: str, d: Mapping, prefix: str, parent: str,
           name: str | None) -> None:
    """Rows ``d["joints"]`` (and the optional ``mount`` and ``tool``) hanging on ``parent``, added to ``tree``."""
    if "mount" in d:
        parent = _fixed(ctx, tree, check_mapping(ctx, d["mount"], d, "mount", prefix + "mount"), d, prefix + "mount",
                        parent)
    rows = d["joints"]
    if not isinstance(rows, list) or not rows:
        raise ctx.error(d, "joints", prefix + "joints", "must be a non-empty list of rows")
    parsed = [_row(ctx, r, rows, i, prefix, name) for i, r in enumerate(rows)]
    prev = None
    for i, p in enumerate(parsed):
        tree.add(rows[i], None, f"{prefix}joints[{i}]", p["link"], p["name"])
        if convention == "standard":
            pre = np.eye(4) if prev is None else _t(prev["a"], 0, 0) @ _rx(prev["alpha"])
            origin = pre @ _rz(p["theta"]) @ _t(0, 0, p["d"])
        else:
            origin = _rx(p["alpha"]) @ _t(p["a"], 0, 0) @ _rz(p["theta"]) @ _t(0, 0, p["d"])
        tree.lines += _link(p["link"], p) + _joint(p["name"], p["type"], parent, p["link"], origin, p)
        parent, prev = p["link"], p
    if convention == "standard" and prev is not None and (prev["a"] or prev["alpha"]):
        flange = {"name": parent + "_flange", "joint": "flange_joint" if name is None else f"{name}_flange_joint"}
        tree.add(rows[-1], None, f"{prefix}joints[{len(rows) - 1}] (flange)", flange["name"], flange["joint"])
        tree.lines += [f"  <link name={quoteattr(flange['name'])}/>"]
        tree.lines += _joint(flange["joint"], "fixed", parent, flange["name"],
                             _t(prev["a"], 0, 0) @ _rx(prev["alpha"]), {})
        parent = flange["name"]
    if "tool" in d:
        _fixed(ctx, tree, check_mapping(ctx, d["tool"], d, "tool", prefix + "tool"), d, prefix + "tool", parent)


def _fixed(ctx: CheckContext, tree: _Tree, fr: Mapping, obj: Any, path: str, parent: str) -> str:
    """A fixed frame (tool, mount, ``frames`` entry) on ``parent``; returns its link name."""
    check_keys(ctx, fr, _FIXED_KEYS, path, required=("name",))
    xyz = check_vector(ctx, fr["xyz"], fr, "xyz", f"{path}.xyz", 3) if "xyz" in fr else np.zeros(3)
    rpy = check_vector(ctx, fr["rpy"], fr, "rpy", f"{path}.rpy", 3) if "rpy" in fr else np.zeros(3)
    link = _name(ctx, fr, "name", f"{path}.name")
    joint = _name(ctx, fr, "joint", f"{path}.joint", f"{link}_joint")
    tree.add(fr, "name", path, link, joint)
    tree.lines += _link(link, _mass(ctx, fr, path))
    tree.lines += _joint(joint, "fixed", parent, link, lie.from_xyz_rpy(xyz, rpy), {})
    return link


def _mass(ctx: CheckContext, row: Mapping, path: str) -> dict[str, Any]:
    """``mass`` [kg], ``com`` [m] and ``inertia`` (6 numbers, kg m^2) of a row or fixed frame, or {} without a
    mass."""
    out: dict[str, Any] = {}
    if "mass" in row:
        out["mass"] = check_number(ctx, row["mass"], row, "mass", f"{path}.mass", positive=True)
        out["com"] = check_vector(ctx, row["com"], row, "com", f"{path}.com", 3) if "com" in row else np.zeros(3)
        out["inertia"] = _DEFAULT_INERTIA
        if "inertia" in row:
            val = row["inertia"]
            if not isinstance(val, list) or len(val) not in (3, 6):
                raise ctx.error(row, "inertia", f"{path}.inertia", "must be a list of 3 numbers (ixx iyy izz) or 6 "
                                f"(ixx ixy ixz iyy iyz izz) [kg m^2], got {val!r}")
            v = check_vector(ctx, val, row, "inertia", f"{path}.inertia", len(val))
            out["inertia"] = np.array([v[0], 0.0, 0.0, v[1], 0.0, v[2]]) if len(val) == 3 else v
    else:
        for k in ("com", "inertia"):
            if k in row:
                raise ctx.error(row, k, f"{path}.{k}", f"a {'centre of mass' if k == 'com' else k} needs a mass")
    return out


def _row(ctx: CheckContext, row: Any, rows: list, i: int, prefix: str = "", chain: str | None = None) -> dict[str, Any]:
    path = f"{prefix}joints[{i}]"
    row = check_mapping(ctx, row, rows, None, path)
    check_keys(ctx, row, _ROW_KEYS, path, required=("name",))
    jtype = row.get("type", "revolute")
    if jtype not in ("revolute", "continuous", "prismatic"):
        raise ctx.error(row, "type", path + ".type", f"must be revolute, continuous or prismatic, got {jtype!r}")
    default_link = f"link_{i + 1}" if chain is None else f"{chain}_link_{i + 1}"
    out: dict[str, Any] = {"name": _name(ctx, row, "name", path + ".name"), "type": jtype,
                           "link": _name(ctx, row, "link", path + ".link", default_link)}
    for k in ("a", "alpha", "d", "theta"):
        out[k] = check_number(ctx, row[k], row, k, f"{path}.{k}") if k in row else 0.0
    for k in ("lower", "upper"):
        if k in row:
            out[k] = check_number(ctx, row[k], row, k, f"{path}.{k}")
    if jtype != "continuous" and not ("lower" in out and "upper" in out):
        raise ctx.error(row, None, path, f"a {jtype} joint needs both lower and upper limits (or type: continuous)")
    if "lower" in out and out["lower"] > out["upper"]:
        raise ctx.error(row, "lower", path + ".lower", f"lower {out['lower']} > upper {out['upper']}")
    return {**out, **_mass(ctx, row, path)}


def _name(ctx: CheckContext, obj: Mapping, key: str, path: str, default: str | None = None) -> str:
    """A link, joint, chain or robot name: non-empty text without spaces (issue 25: ``name: null`` became "None",
    an empty name an error in a line of the generated URDF)."""
    value = obj.get(key, default)
    if not isinstance(value, str) or not value or value != value.strip() or any(c.isspace() for c in value):
        raise ctx.error(obj, key, path, f"must be a name (non-empty text without spaces), got {value!r}")
    return value


def _fmt(v: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in v)


def _link(link: str, p: Mapping[str, Any]) -> list[str]:
    name = quoteattr(link)
    if "mass" not in p:
        return [f"  <link name={name}/>"]
    ixx, ixy, ixz, iyy, iyz, izz = (repr(float(v)) for v in p["inertia"])
    return [f"  <link name={name}>", "    <inertial>", f'      <origin xyz="{_fmt(p["com"])}" rpy="0 0 0"/>',
            f'      <mass value="{p["mass"]!r}"/>',
            f'      <inertia ixx="{ixx}" ixy="{ixy}" ixz="{ixz}" iyy="{iyy}" iyz="{iyz}" izz="{izz}"/>',
            "    </inertial>", "  </link>"]


def _joint(name: str, jtype: str, parent: str, child: str, origin: np.ndarray, p: Mapping[str, Any]) -> list[str]:
    rpy = lie.rpy_from_matrix(origin[:3, :3])
    lines = [f"  <joint name={quoteattr(name)} type={quoteattr(jtype)}>",
             f"    <parent link={quoteattr(parent)}/>", f"    <child link={quoteattr(child)}/>",
             f'    <origin xyz="{_fmt(origin[:3, 3])}" rpy="{_fmt(rpy)}"/>']
    if jtype != "fixed":
        lines.append('    <axis xyz="0 0 1"/>')
    if "lower" in p and jtype != "continuous":
        lines.append(f'    <limit lower="{p["lower"]!r}" upper="{p["upper"]!r}" effort="100" velocity="1"/>')
    return lines + ["  </joint>"]
