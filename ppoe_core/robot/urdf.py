"""URDF parser: the kinematic tree of a robot as plain Python data.

Only what the PPOE model needs is read: links (with their optional
``<inertial>``), joints (type, parent, child, ``<origin>``, ``<axis>``,
``<limit>``, ``<mimic>``).  Visual, collision, material, transmission and
simulator tags carry no kinematics and are not interpreted.

The parser uses the standard library's expat so that every error names the
file and the line of the offending element (no extra dependency).

Conventions
-----------
* ``<origin xyz rpy>``: fixed-axis roll-pitch-yaw, ``R = Rz(yaw) Ry(pitch) Rx(roll)``
  (:func:`ppoe_core.lie.from_xyz_rpy`).
* ``Joint.origin`` is ``T_parent_jointframe`` (the paper's static ``Exp(p_i)``, eq. 16);
  the joint motion acts about / along the unit ``Joint.axis`` in the joint frame.
* A mimic joint moves with ``q = multiplier * q_master + offset``; chains of mimic
  joints are resolved to the independent master (:attr:`Joint.mimic_root`).
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path
from xml.parsers import expat

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import UrdfError
from ppoe_core.robot.robot_model import JOINT_TYPES, MOVABLE_TYPES, Inertial, Joint, JointLimit, Link, Mimic, Robot

__all__ = [
    "Inertial",
    "Link",
    "JointLimit",
    "Mimic",
    "Joint",
    "Robot",
    "parse_urdf",
    "JOINT_TYPES",
    "MOVABLE_TYPES",
]
_UNSUPPORTED = ("floating", "planar")


# ----------------------------------------------------------------------------
# Minimal line-aware XML tree (expat)
# ----------------------------------------------------------------------------


class _Element:
    __slots__ = ("tag", "attrib", "children", "line")

    def __init__(self, tag: str, attrib: dict[str, str], line: int) -> None:
        self.tag = tag
        self.attrib = attrib
        self.children: list[_Element] = []
        self.line = line

    def findall(self, tag: str) -> list[_Element]:
        return [c for c in self.children if c.tag == tag]

    def find(self, tag: str) -> _Element | None:
        for c in self.children:
            if c.tag == tag:
                return c
        return None


def _parse_xml(text: str | bytes, where: str) -> _Element:
    parser = expat.ParserCreate()
    stack: list[_Element] = []
    root: list[_Element] = []

    def start(tag: str, attrib: dict[str, str]) -> None:
        el = _Element(tag, dict(attrib), parser.CurrentLineNumber)
        if stack:
            stack[-1].children.append(el)
        else:
            root.append(el)
        stack.append(el)

    def end(tag: str) -> None:
        stack.pop()

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    # no external entities / DTD fetching
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    try:
        parser.Parse(text, True)
    except expat.ExpatError as exc:
        raise UrdfError(
            f"{where}:{exc.lineno}: URDF is not well-formed XML: "
            f"{expat.ErrorString(exc.code)} (line {exc.lineno}, column {exc.offset})"
        ) from None
    if not root:
        raise UrdfError(f"{where}: URDF is empty")
    return root[0]


# ----------------------------------------------------------------------------
# Parsing helpers
# ----------------------------------------------------------------------------


def _err(where: str, el: _Element, msg: str) -> UrdfError:
    return UrdfError(f"{where}:{el.line}: {msg}")


def _floats(where: str, el: _Element, attr: str, n: int, default: tuple | None = None) -> np.ndarray:
    raw = el.attrib.get(attr)
    if raw is None:
        if default is None:
            raise _err(where, el, f"<{el.tag}> is missing attribute '{attr}'")
        return np.array(default, dtype=float)
    parts = raw.split()
    try:
        vals = np.array([float(p) for p in parts], dtype=float)
    except ValueError:
        raise _err(where, el, f"<{el.tag} {attr}=\"{raw}\">: not {n} numbers") from None
    if vals.shape != (n,):
        raise _err(where, el, f"<{el.tag} {attr}=\"{raw}\">: expected {n} numbers, got {len(parts)}")
    if not np.all(np.isfinite(vals)):
        raise _err(where, el, f"<{el.tag} {attr}=\"{raw}\">: NaN or infinite value")
    return vals


def _float(where: str, el: _Element, attr: str, default: float | None = None, required: bool = False) -> float | None:
    raw = el.attrib.get(attr)
    if raw is None:
        if required:
            raise _err(where, el, f"<{el.tag}> is missing attribute '{attr}'")
        return default
    try:
        val = float(raw)
    except ValueError:
        raise _err(where, el, f"<{el.tag} {attr}=\"{raw}\">: not a number") from None
    if not math.isfinite(val):
        raise _err(where, el, f"<{el.tag} {attr}=\"{raw}\">: NaN or infinite value")
    return val


def _origin(where: str, parent: _Element) -> np.ndarray:
    o = parent.find("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(where, o, "xyz", 3, (0.0, 0.0, 0.0))
    rpy = _floats(where, o, "rpy", 3, (0.0, 0.0, 0.0))
    return lie.from_xyz_rpy(xyz, rpy)


def _name(where: str, el: _Element, what: str) -> str:
    name = el.attrib.get("name")
    if name is None or not name.strip():
        raise _err(where, el, f"<{what}> without a 'name' attribute")
    return name


def _parse_link(where: str, el: _Element) -> Link:
    name = _name(where, el, "link")
    inertial = None
    ie = el.find("inertial")
    if ie is not None:
        me = ie.find("mass")
        if me is None:
            raise _err(where, ie, f"link '{name}': <inertial> without <mass>")
        mass = _float(where, me, "value", required=True)
        assert mass is not None
        if mass < 0:
            raise _err(where, me, f"link '{name}': negative mass {mass}")
        I = np.zeros((3, 3))
        ine = ie.find("inertia")
        if ine is not None:
            v = {k: _float(where, ine, k, 0.0) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
            I = np.array(
                [
                    [v["ixx"], v["ixy"], v["ixz"]],
                    [v["ixy"], v["iyy"], v["iyz"]],
                    [v["ixz"], v["iyz"], v["izz"]],
                ],
                dtype=float,
            )
        inertial = Inertial(mass=float(mass), origin=_origin(where, ie), inertia=I)
    return Link(name=name, inertial=inertial, line=el.line)


def _parse_joint(where: str, el: _Element) -> Joint:
    name = _name(where, el, "joint")
    jtype = el.attrib.get("type")
    if jtype is None:
        raise _err(where, el, f"joint '{name}' has no 'type' attribute")
    if jtype in _UNSUPPORTED:
        raise _err(
            where,
            el,
            f"joint '{name}' has type '{jtype}', which the PPOE model does not support "
            f"(supported: {', '.join(JOINT_TYPES)}); model a free base as a fixed joint "
            "and estimate it separately",
        )
    if jtype not in JOINT_TYPES:
        raise _err(where, el, f"joint '{name}' has unknown type '{jtype}' (supported: {', '.join(JOINT_TYPES)})")
    pe, ce = el.find("parent"), el.find("child")
    if pe is None or "link" not in pe.attrib:
        raise _err(where, el, f"joint '{name}' has no <parent link=...>")
    if ce is None or "link" not in ce.attrib:
        raise _err(where, el, f"joint '{name}' has no <child link=...>")
    axis = np.array([1.0, 0.0, 0.0])
    ae = el.find("axis")
    if ae is not None:
        axis = _floats(where, ae, "xyz", 3, (1.0, 0.0, 0.0))
    norm = float(np.linalg.norm(axis))
    if jtype != "fixed":
        if norm < 1e-12:
            raise _err(where, ae if ae is not None else el, f"joint '{name}' has a zero axis")
        axis = axis / norm
    return Joint(
        name=name,
        type=jtype,
        parent=pe.attrib["link"],
        child=ce.attrib["link"],
        origin=_origin(where, el),
        axis=axis,
        limit=_parse_limit(where, el, name),
        mimic=_parse_mimic(where, el, name, jtype),
        line=el.line,
    )


def _parse_limit(where: str, el: _Element, name: str) -> JointLimit | None:
    """``<limit>`` of joint ``name`` (None when absent); lower must not exceed upper."""
    le = el.find("limit")
    if le is None:
        return None
    limit = JointLimit(
        lower=_float(where, le, "lower"),
        upper=_float(where, le, "upper"),
        effort=_float(where, le, "effort"),
        velocity=_float(where, le, "velocity"),
    )
    if limit.lower is not None and limit.upper is not None and limit.lower > limit.upper:
        raise _err(where, le, f"joint '{name}': limit lower {limit.lower} > upper {limit.upper}")
    return limit


def _parse_mimic(where: str, el: _Element, name: str, jtype: str) -> Mimic | None:
    """``<mimic>`` of joint ``name`` (None when absent); a fixed joint cannot mimic."""
    mie = el.find("mimic")
    if mie is None:
        return None
    mj = mie.attrib.get("joint")
    if not mj:
        raise _err(where, mie, f"joint '{name}': <mimic> without 'joint' attribute")
    if jtype == "fixed":
        raise _err(where, mie, f"joint '{name}': a fixed joint cannot mimic '{mj}'")
    return Mimic(
        joint=mj,
        multiplier=float(_float(where, mie, "multiplier", 1.0)),  # type: ignore[arg-type]
        offset=float(_float(where, mie, "offset", 0.0)),  # type: ignore[arg-type]
    )


def _looks_like_xml(source: str) -> bool:
    return source.lstrip().startswith("<")


# ----------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------


def parse_urdf(source: str | bytes | os.PathLike, *, text_source: str | None = None) -> Robot:
    """Parse a URDF into a :class:`Robot`.

    Parameters
    ----------
    source : str, bytes or path-like
        A file path, or the URDF XML text itself (a string starting with ``<``).
    text_source : str, optional
        Where XML text came from (e.g. ``"bag run1 /robot_description"``), named in error
        messages and :attr:`Robot.source` instead of ``"<string>"``; ignored for a path.

    Returns
    -------
    Robot

    Raises
    ------
    UrdfError
        File missing, XML not well-formed, unsupported joint type (floating, planar),
        zero axis, bad numbers, duplicate names, unknown parent/child links, a link with
        two parents, several roots or a cycle, bad mimic references.  The message names
        the file and the line.
    """
    if isinstance(source, bytes):
        text: str | bytes = source
        where = text_source or "<string>"
    elif isinstance(source, os.PathLike) or (isinstance(source, str) and not _looks_like_xml(source)):
        path = Path(source)
        try:
            text = path.read_bytes()
        except OSError as exc:
            raise UrdfError(f"{path}: cannot read URDF ({exc.strerror or exc})") from None
        where = str(path)
    elif isinstance(source, str):
        text = source
        where = text_source or "<string>"
    else:
        raise UrdfError(f"parse_urdf: expected a path or XML text, got {type(source).__name__}")

    root_el = _parse_xml(text, where)
    if root_el.tag != "robot":
        raise _err(where, root_el, f"root element is <{root_el.tag}>, expected <robot>")
    robot_name = root_el.attrib.get("name", "")

    links, joints = _elements(where, root_el)
    parent_joint, root = _tree_structure(where, links, joints)
    resolved = {j.name: _resolve_mimic(where, j, joints) for j in joints.values()}
    return Robot(
        name=robot_name,
        links=links,
        joints=resolved,
        root=root,
        source=where,
        _parent_joint=parent_joint,
    )


def _elements(where: str, root_el: _Element) -> tuple[dict[str, Link], dict[str, Joint]]:
    """The ``<link>`` and ``<joint>`` elements of ``<robot>``, names unique."""
    links: dict[str, Link] = {}
    joints: dict[str, Joint] = {}
    for el in root_el.children:
        if el.tag == "link":
            link = _parse_link(where, el)
            if link.name in links:
                raise _err(where, el, f"duplicate link name '{link.name}' (first at line {links[link.name].line})")
            links[link.name] = link
        elif el.tag == "joint":
            joint = _parse_joint(where, el)
            if joint.name in joints:
                raise _err(
                    where, el, f"duplicate joint name '{joint.name}' (first at line {joints[joint.name].line})"
                )
            joints[joint.name] = joint
    if not links:
        raise _err(where, root_el, "URDF has no <link>")
    return links, joints


def _tree_structure(where: str, links: dict[str, Link], joints: dict[str, Joint]) -> tuple[dict[str, str], str]:
    """``(child link -> parent joint, root link)``; refuses unknown links, two parents, several roots, cycles."""
    parent_joint: dict[str, str] = {}
    for j in joints.values():
        for role, ln in (("parent", j.parent), ("child", j.child)):
            if ln not in links:
                raise UrdfError(f"{where}:{j.line}: joint '{j.name}' has unknown {role} link '{ln}'")
        if j.parent == j.child:
            raise UrdfError(f"{where}:{j.line}: joint '{j.name}' connects link '{j.parent}' to itself")
        if j.child in parent_joint:
            other = joints[parent_joint[j.child]]
            raise UrdfError(
                f"{where}:{j.line}: link '{j.child}' has two parent joints "
                f"('{other.name}' at line {other.line} and '{j.name}'): not a tree"
            )
        parent_joint[j.child] = j.name
    roots = [ln for ln in links if ln not in parent_joint]
    if len(roots) == 0:
        raise UrdfError(f"{where}: the joints form a cycle (every link has a parent joint)")
    if len(roots) > 1:
        raise UrdfError(
            f"{where}: URDF has {len(roots)} root links ({', '.join(repr(r) for r in roots)}); "
            "exactly one link may have no parent joint"
        )
    # every link must reach the root (detects cycles not touching the root)
    for ln in links:
        seen = {ln}
        cur = ln
        while cur in parent_joint:
            cur = joints[parent_joint[cur]].parent
            if cur in seen:
                j = joints[parent_joint[ln]]
                raise UrdfError(f"{where}:{j.line}: the joints form a cycle through link '{ln}'")
            seen.add(cur)
    return parent_joint, roots[0]


def _resolve_mimic(where: str, j: Joint, joints: dict[str, Joint]) -> Joint:
    """``j`` with ``mimic_root = (independent joint, multiplier, offset)`` through chains of mimics."""
    if j.mimic is None:
        return j
    mult, off = 1.0, 0.0
    cur_j = j
    visited = [j.name]
    while cur_j.mimic is not None:
        m = cur_j.mimic
        if m.joint not in joints:
            raise UrdfError(f"{where}:{cur_j.line}: joint '{cur_j.name}' mimics unknown joint '{m.joint}'")
        master = joints[m.joint]
        if not master.movable:
            raise UrdfError(
                f"{where}:{cur_j.line}: joint '{cur_j.name}' mimics '{m.joint}', which is {master.type}"
            )
        # q_cur = m.multiplier * q_master + m.offset; q_j = mult * q_cur + off
        off = mult * m.offset + off
        mult = mult * m.multiplier
        if master.name in visited:
            raise UrdfError(f"{where}:{j.line}: mimic cycle {' -> '.join(visited + [master.name])}")
        visited.append(master.name)
        cur_j = master
    return replace(j, mimic_root=(cur_j.name, mult, off))
