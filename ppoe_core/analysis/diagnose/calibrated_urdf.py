"""An installable calibration: the static effects folded into the URDF (``robot_calibrated.urdf``).

``joint_offset``, ``link_error`` and ``camera_extrinsics`` do not depend on the configuration: with paper
eq. 16, ``Exp(p_j) Exp(dxi_j) Exp(zeta_j (q_j + dq_j)) = [Exp(p_j) Exp(dxi_j) Exp(zeta_j dq_j)] Exp(zeta_j q_j)``,
so the joint's ``<origin>`` becomes ``Exp(p_j) Exp(dxi_j) Exp(zeta_j dq_j)`` (the joint turns or slides about an
axis through its origin) and a mimic joint driven by a corrected master gains ``multiplier * dq`` in its
``<mimic offset>``.  The other effects (compliances, backlash, thermal growth, time offsets) depend on the
configuration or the context and stay in the model YAML.  The calibrated URDF's nominal forward kinematics
equals the corrected one of the original URDF to rounding (``repr`` floats are written).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import UrdfError
from ppoe_core.model.effects import Effect, sum_effect_corrections
from ppoe_core.model.tf_frames import STATIC_EFFECTS  # the effects folded into the URDF
from ppoe_core.robot.urdf import Robot

__all__ = ["STATIC_EFFECTS", "calibrated_urdf"]


def calibrated_urdf(urdf_xml: str, robot: Robot, effects: Sequence[Effect]) -> tuple[str, list[Effect]]:
    """Fold the static ``effects`` into the URDF text; returns the new URDF and the effects not folded.

    Raises
    ------
    UrdfError
        The URDF text does not parse, or lacks a joint the effects name.
    """
    static = [e for e in effects if e.name in STATIC_EFFECTS]
    rest = [e for e in effects if e.name not in STATIC_EFFECTS]
    zeros = {j: np.zeros(()) for j in robot.independent_joints}
    dq, dxi = sum_effect_corrections(static, zeros, {})
    try:
        root = ET.fromstring(urdf_xml, parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    except ET.ParseError as exc:
        raise UrdfError(f"calibrated URDF: the URDF does not parse: {exc}") from None
    elements = {el.get("name"): el for el in root.iter("joint")}
    for jn in sorted(set(dq) | set(dxi)):
        if jn not in elements:
            raise UrdfError(f"calibrated URDF: joint {jn!r} of an effect is not in the URDF")
        j = robot.joints[jn]
        T = j.origin @ lie.exp(np.asarray(dxi.get(jn, np.zeros(6)), dtype=float).reshape(6))
        d = float(np.asarray(dq.get(jn, 0.0)))
        if d:
            T = T @ lie.exp(j.twist * d)
        _set_origin(elements[jn], T)
    for jn, j in robot.joints.items():  # mimic followers of a corrected master
        if j.mimic is not None and j.mimic.joint in dq and float(np.asarray(dq[j.mimic.joint])):
            mimic = elements[jn].find("mimic")
            if mimic is not None:
                off = float(mimic.get("offset", "0")) + j.mimic.multiplier * float(np.asarray(dq[j.mimic.joint]))
                mimic.set("offset", repr(off))
    comment = ET.Comment(" calibrated by ppoe diagnose: " + ", ".join(e.describe() for e in static)
                         + " folded into the joint origins ")
    root.insert(0, comment)
    return ET.tostring(root, encoding="unicode") + "\n", rest


def _set_origin(joint: ET.Element, T: np.ndarray) -> None:
    """Write ``T`` (4x4) as the joint's ``<origin xyz rpy>`` (full precision)."""
    origin = joint.find("origin")
    if origin is None:
        origin = ET.SubElement(joint, "origin")
    xyz = T[:3, 3]
    rpy = lie.rpy_from_matrix(T[:3, :3])
    origin.set("xyz", " ".join(repr(float(v)) for v in xyz))
    origin.set("rpy", " ".join(repr(float(v)) for v in rpy))
