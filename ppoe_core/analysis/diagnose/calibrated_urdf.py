"""An installable calibration: the static effects folded into the URDF (``robot_calibrated.urdf``).

``joint_offset``, ``link_error`` and ``camera_extrinsics`` do not depend on the configuration: with paper
eq. 16, ``Exp(p_j) Exp(dxi_j) Exp(zeta_j (q_j + dq_j)) = [Exp(p_j) Exp(dxi_j) Exp(zeta_j dq_j)] Exp(zeta_j q_j)``,
so the joint's ``<origin>`` becomes ``Exp(p_j) Exp(dxi_j) Exp(zeta_j dq_j)`` (the joint turns or slides about an
axis through its origin) and a mimic joint driven by a corrected master gains ``multiplier * dq`` in its
``<mimic offset>``.  The other effects (compliances, backlash, thermal growth, time offsets) depend on the
configuration or the context and stay in the model YAML.  The calibrated URDF's nominal forward kinematics
equals the corrected one of the original URDF to rounding (``repr`` floats are written).

:func:`plan_calibration` decides what goes in: the model YAML's declared static effects in full, and of the static
effects diagnose found only the *significant* components (95 % interval excluding zero); every other component
is listed as not applied, with the reason (:class:`NotApplied`), and is neither in the URDF nor in
``model_calibrated.yaml``.  A component set to zero is the one the data cannot tell from zero: folding its
estimate would move a joint origin by noise.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.results import DiagnoseResult, EffectReport
from ppoe_core.errors import UrdfError
from ppoe_core.model.effects import Effect, sum_effect_corrections
from ppoe_core.model.tf_frames import STATIC_EFFECTS  # the effects folded into the URDF
from ppoe_core.robot.urdf import Robot

__all__ = ["STATIC_EFFECTS", "CalibrationPlan", "NotApplied", "calibrated_urdf", "plan_calibration"]


@dataclass(frozen=True)
class NotApplied:
    """A component of a found static effect that the calibration leaves out: ``value`` with its 95 % interval
    ``ci`` (the parameter's unit), and why (the interval contains zero, or there is none)."""

    effect: str
    parameter: str
    value: float
    ci: tuple[float, float]
    reason: str


@dataclass
class CalibrationPlan:
    """What the installable calibration applies.

    Attributes
    ----------
    folded : list of Effect
        Folded into ``robot_calibrated.urdf``: the declared static effects in full, the found ones with their
        non-significant components set to zero (an effect without a significant component is left out).
    applied : dict effect key -> list of str
        The components of each found static effect that were folded.
    not_applied : list of NotApplied
        The found static components left out, with the reason.
    in_model : list of str
        Found effects that stay in ``model_calibrated.yaml`` (they depend on the configuration or the context).
    """

    folded: list[Effect] = field(default_factory=list)
    applied: dict[str, list[str]] = field(default_factory=dict)
    not_applied: list[NotApplied] = field(default_factory=list)
    in_model: list[str] = field(default_factory=list)


def significant(ci: Sequence[float]) -> bool:
    """A 95 % interval ``[lo, hi]`` that excludes zero (both ends finite)."""
    lo, hi = float(ci[0]), float(ci[1])
    return math.isfinite(lo) and math.isfinite(hi) and (lo > 0.0 or hi < 0.0)


def plan_calibration(result: DiagnoseResult, declared: Sequence[Effect] = ()) -> CalibrationPlan:
    """The :class:`CalibrationPlan` of a diagnosis: declared static effects in full, found static effects with
    their significant components only (module docstring)."""
    plan = CalibrationPlan(folded=[e for e in declared if e.name in STATIC_EFFECTS])
    for e, rep in _pairs(result):
        if e.name not in STATIC_EFFECTS:
            plan.in_model.append(e.key)
            continue
        keep = np.zeros(e.n_params, dtype=bool)
        for i, p in enumerate(e.param_names):
            ci = rep.ci.get(p, [math.nan, math.nan])
            keep[i] = significant(ci)
            if not keep[i]:
                why = (f"95 % CI [{ci[0]:.4g}, {ci[1]:.4g}] contains 0" if all(map(math.isfinite, ci))
                       else "no 95 % CI (the parameter is not identifiable from these data)")
                plan.not_applied.append(NotApplied(e.key, p, float(e.params[i]), (float(ci[0]), float(ci[1])), why))
        if keep.any():
            plan.folded.append(e.with_params(np.where(keep, e.params, 0.0)))
            plan.applied[e.key] = [p for p, k in zip(e.param_names, keep) if k]
    return plan


def _pairs(result: DiagnoseResult) -> list[tuple[Effect, EffectReport]]:
    """Each found effect with its report entry (same order; matched by name and location)."""
    reports = list(result.effects)
    out = []
    for e in result.found:
        rep = next((r for r in reports if r.name == e.name and r.location == e.location), None)
        if rep is None:
            raise ValueError(f"diagnose result: no report entry for the effect {e.key}")
        reports.remove(rep)
        out.append((e, rep))
    return out


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
    folded = ", ".join(e.describe() + "[" + ",".join(p for p, v in zip(e.param_names, e.params) if v) + "]"
                       for e in static)
    comment = ET.Comment(f" calibrated by ppoe diagnose: {folded or 'nothing'} folded into the joint origins ")
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
