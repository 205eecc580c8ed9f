"""Catalogue of systematic effects that a nominal PPOE model may lack (docs/conventions.md sec. 6): the one place
that builds them by name (:func:`make_effect`, :func:`effect_from_config`).  The classes live by what they model:
:mod:`~ppoe_core.model.effect_base` (the base, the summed corrections), :mod:`~ppoe_core.model.effects_static`
(constant chain corrections), :mod:`~ppoe_core.model.effects_load` (gravity-load compliances),
:mod:`~ppoe_core.model.effects_context` (backlash, thermal growth, time offset) and
:mod:`~ppoe_core.model.effects_sensor` (camera intrinsics, tag placement).

Every effect is a small physical parametrisation that changes the kinematic chain through
the two hooks of paper eq. 16, ``Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))``:
* ``dq``: an offset added to a joint value (for a mimic master it propagates through the mimic multiplier), and
* ``dxi``: a non-zero-mean twist ``[rho; theta]`` placed right after a joint's static origin ``p_i``, where the
  joint's perturbation ``xi_i`` sits.

All catalogued effects are *linear in their parameters*: ``corrections(q, context)`` is
``basis(q, context) @ params``, where :meth:`Effect.basis` gives the exact analytic
derivative of the corrections with respect to the parameters.  The derivative of a measured
quantity (a point, a frame) follows by the chain rule with
:meth:`KinematicTree.frame_jacobian` / :meth:`KinematicTree.point_jacobian`, see
:meth:`Effect.point_jacobian`.

Vocabulary (``name``: location, parameters, unit):

==========================  ===================  =========================================
``joint_offset``            movable joint        ``offset`` [rad or m]
``link_error``              any joint            subset of ``x y z rx ry rz`` [m, rad]
``gravity_compliance``      movable joint        ``compliance`` [rad/(N m) or m/N]
``mount_bending``           any joint            ``compliance_x``, ``compliance_y`` [rad/(N m)]
``lateral_compliance``      revolute joint       ``compliance_u``, ``compliance_v`` [rad/(N m)]
``base_tilt``               root link            ``tilt_x``, ``tilt_y`` [rad] (or ``gain`` of the measured tilt)
``backlash``                movable joint        ``play`` [rad or m] (half the dead band)
``thermal_growth``          any joint            ``alpha`` [1/K or 1/s]
``time_offset``             topic / sensor       ``dt`` [s]
``camera_extrinsics``       camera frame/joint   ``x y z rx ry rz`` [m, rad]
``camera_intrinsics``       camera optical frame ``fx fy cx cy`` [px], ``k1 k2 p1 p2 k3`` (corrections)
``tag_offset``              ``tag_<id>``         ``x y z rx ry rz`` [m, rad] of the tag on its link
``tracker_registration``    topic / frame        ``x y z rx ry rz`` [m, rad] (nuisance)
==========================  ===================  =========================================

Context keys (``context`` of :meth:`Effect.corrections`), each broadcast like the joints:

``gravity``
    Gravity direction in the root frame, ``(..., 3)`` unit vector, default ``[0, 0, -1]``.
``base_tilt``
    ``(..., 2)`` [rad]: root tilt about its x, y axes measured by an accelerometer on it, minus its session mean.
``motion_sign``
    ``{joint: (...)}``: sign (+1, -1, 0) of each joint's last motion (backlash).
``temperature`` / ``time``
    ``(...)`` [K or degC] / [s]: variable of thermal growth (difference to ``reference``).
``joint_velocity``
    ``{joint: (...)}`` [rad/s or m/s] (time offset).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core.errors import ModelConfigError, UnknownJointError
from ppoe_core.model.effect_base import TWIST_KEYS, Corrections, Effect, sum_effect_corrections
from ppoe_core.model.effects_context import Backlash, ThermalGrowth, TimeOffset
from ppoe_core.model.effects_load import GravityCompliance, LateralCompliance, MountBending, perpendicular_axes
from ppoe_core.model.effects_sensor import INTRINSIC_KEYS, CameraIntrinsics, TagOffset
from ppoe_core.model.effects_static import BaseTilt, CameraExtrinsics, JointOffset, LinkError, TrackerRegistration
from ppoe_core.robot.config import EFFECT_NAMES as _CONFIG_EFFECT_NAMES
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["EFFECT_NAMES", "Effect", "Corrections", "JointOffset", "LinkError", "GravityCompliance", "MountBending",
           "LateralCompliance", "perpendicular_axes", "BaseTilt", "Backlash", "ThermalGrowth", "TimeOffset",
           "CameraExtrinsics", "CameraIntrinsics", "TagOffset", "TrackerRegistration", "effect_from_config",
           "make_effect", "sum_effect_corrections"]

#: the contract vocabulary (docs/conventions.md sec. 6), in catalogue order (defined in config)
EFFECT_NAMES = _CONFIG_EFFECT_NAMES


_CLASSES: dict[str, type] = {
    "joint_offset": JointOffset,
    "link_error": LinkError,
    "gravity_compliance": GravityCompliance,
    "mount_bending": MountBending,
    "lateral_compliance": LateralCompliance,
    "base_tilt": BaseTilt,
    "backlash": Backlash,
    "thermal_growth": ThermalGrowth,
    "time_offset": TimeOffset,
    "camera_extrinsics": CameraExtrinsics,
    "camera_intrinsics": CameraIntrinsics,
    "tag_offset": TagOffset,
    "tracker_registration": TrackerRegistration,
}
#: effects whose parameters are a subset (``components``) of their catalogue list, and that list
_COMPONENTS: dict[str, tuple[str, ...]] = {
    "link_error": TWIST_KEYS, "camera_extrinsics": TWIST_KEYS, "tag_offset": TWIST_KEYS,
    "camera_intrinsics": INTRINSIC_KEYS,
    "mount_bending": MountBending.axis_names + ("extension_x", "extension_y"),
    "lateral_compliance": LateralCompliance.axis_names,
}


def make_effect(name: str, location: str, robot_or_tree: Robot | KinematicTree,
                params: Sequence[float] | None = None, **options: Any) -> Effect:
    """Build effect ``name`` at ``location`` with parameters in catalogue order (zeros if None)."""
    tree = robot_or_tree if isinstance(robot_or_tree, KinematicTree) else KinematicTree(robot_or_tree)
    if name not in _CLASSES:
        raise ModelConfigError(f"unknown effect '{name}' (vocabulary: {', '.join(EFFECT_NAMES)})")
    return _CLASSES[name](tree, location, params, **options)


#: keys ``ppoe diagnose`` adds to an effect entry; they describe the fit, not the effect, and are ignored on load
_REPORT_KEYS = ("ci", "sigma", "share", "measurement", "frame", "camera_info")


def effect_from_config(entry: Mapping[str, Any], robot: Robot | KinematicTree,
                       where: str = "effects") -> Effect:
    """Build an effect from a model-YAML entry ``{name, location, parameters}``.

    ``parameters`` maps parameter names to values; a ``link_error`` /
    ``camera_extrinsics`` entry uses only the twist components it lists (``x y z rx ry rz``).
    ``thermal_growth`` accepts ``variable`` and ``reference``; ``camera_intrinsics`` / ``tag_offset`` / the bending
    effects use the parameters they list (``fx fy cx cy k1 k2 p1 p2 k3``; a twist; the bending axes).  The
    annotations ``ppoe diagnose`` adds to an entry (``ci``, ``sigma``, ``share``, ``measurement``, ``frame``,
    ``camera_info``) are ignored, so its JSON entries load as they are.

    Raises
    ------
    ModelConfigError
        Unknown name or parameter, missing key; the message names ``where`` (the entry).
    UnknownJointError
        A location that is not a joint of the URDF.
    """
    if not isinstance(entry, Mapping):
        raise ModelConfigError(f"{where}: an effect entry must be a mapping, got {type(entry).__name__}")
    extra = set(entry) - {"name", "location", "parameters", "variable", "reference", *_REPORT_KEYS}
    if extra:
        raise ModelConfigError(f"{where}: unknown keys {sorted(extra)}")
    for key in ("name", "location", "parameters"):
        if key not in entry:
            raise ModelConfigError(f"{where}: missing key '{key}'")
    name, loc, params = entry["name"], str(entry["location"]), entry["parameters"]
    if name not in _CLASSES:
        raise ModelConfigError(f"{where}: unknown effect '{name}' (vocabulary: {', '.join(EFFECT_NAMES)})")
    if not isinstance(params, Mapping):
        raise ModelConfigError(f"{where}: 'parameters' must be a mapping name -> value")
    tree = robot if isinstance(robot, KinematicTree) else KinematicTree(robot)
    options = _options(name, entry, params)
    try:
        eff = _CLASSES[name](tree, loc, None, **options)
    except (UnknownJointError, ModelConfigError) as exc:
        raise type(exc)(f"{where}: {exc}") from None
    unknown = set(params) - set(eff.param_names)
    if unknown:
        raise ModelConfigError(f"{where}: effect {name} at '{loc}' has no parameters {sorted(unknown)} "
                               f"(expected {list(eff.param_names)})")
    try:
        vals = [float(params.get(k, 0.0)) for k in eff.param_names]
    except (TypeError, ValueError):
        raise ModelConfigError(f"{where}: effect {name} at '{loc}': parameters must be numbers") from None
    if not np.all(np.isfinite(vals)):
        raise ModelConfigError(f"{where}: effect {name} at '{loc}': parameters must be finite")
    return eff.with_params(vals)


def _options(name: str, entry: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """Constructor options of a model-YAML effect entry: the listed components, the thermal / tilt variable."""
    options: dict[str, Any] = {}
    if name in _COMPONENTS:
        listed = tuple(k for k in _COMPONENTS[name] if k in params)
        if listed:
            options["components"] = listed
        elif name in ("link_error", "camera_extrinsics"):
            options["components"] = ()  # an entry without parameters: refused by the class, naming it
    if name == "base_tilt" and "variable" in entry:
        options["variable"] = entry["variable"]
    if name == "thermal_growth":
        options["variable"] = entry.get("variable", "temperature")
        options["reference"] = float(entry.get("reference", 0.0))
    return options
