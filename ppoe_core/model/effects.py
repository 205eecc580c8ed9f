"""Catalogue of systematic effects that a nominal PPOE model may lack (docs/conventions.md sec. 6).

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

from ppoe_core import lie
from ppoe_core.errors import ModelConfigError, UnknownJointError
from ppoe_core.robot.config import EFFECT_NAMES as _CONFIG_EFFECT_NAMES
from ppoe_core.robot.tree import KinematicTree, _batch
from ppoe_core.robot.urdf import Robot

__all__ = ["EFFECT_NAMES", "Effect", "JointOffset", "LinkError", "GravityCompliance", "MountBending",
           "LateralCompliance", "perpendicular_axes", "BaseTilt", "Backlash", "ThermalGrowth", "TimeOffset",
           "CameraExtrinsics", "TrackerRegistration", "effect_from_config", "make_effect", "sum_effect_corrections"]

#: the contract vocabulary (docs/conventions.md sec. 6), in catalogue order (defined in config)
EFFECT_NAMES = _CONFIG_EFFECT_NAMES

_TWIST_KEYS = ("x", "y", "z", "rx", "ry", "rz")

Corrections = tuple[dict[str, np.ndarray], dict[str, np.ndarray]]


class Effect:
    """One systematic effect: parameters, corrections (eq. 16 hooks) and their Jacobian.

    Attributes
    ----------
    name : str
        Contract vocabulary name.
    location : str
        URDF joint or link, topic or sensor frame.
    param_names : tuple[str, ...]
    params : ndarray, shape (P,)
    units : tuple[str, ...]
    """

    name = ""
    units: tuple[str, ...] = ()
    #: parameters that are physically non-negative (a compliance yields along the load)
    nonnegative: tuple[str, ...] = ()
    context_keys: tuple[str, ...] = ()  #: context it cannot do without (``ppoe_core.model.context``)

    def __init__(self, tree: KinematicTree, location: str, param_names: Sequence[str],
                 params: Sequence[float] | None = None) -> None:
        self.tree = tree
        self.location = location
        self.param_names = tuple(param_names)
        p = np.zeros(len(self.param_names)) if params is None else np.asarray(params, dtype=float)
        if p.shape != (len(self.param_names),):
            raise ModelConfigError(f"effect {self.name} at '{location}': expected "
                                   f"{len(self.param_names)} parameters, got shape {p.shape}")
        self.params = p

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def with_params(self, params: Sequence[float] | np.ndarray) -> Effect:
        """A copy with other parameter values."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.params = np.asarray(params, dtype=float).copy()
        return new

    def basis(self, q: Mapping[str, Any], context: Mapping[str, Any] | None = None,
              poses: Mapping[str, np.ndarray] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Exact derivative of the corrections w.r.t. the parameters.

        Returns
        -------
        dq_basis : dict joint -> ndarray (..., P)
        dxi_basis : dict joint -> ndarray (..., 6, P)
        """
        raise NotImplementedError

    def corrections(self, q: Mapping[str, Any], context: Mapping[str, Any] | None = None,
                    poses: Mapping[str, np.ndarray] | None = None) -> Corrections:
        """``(dq: joint -> (...), dxi: joint -> (..., 6))`` at joint values ``q`` (eq. 16)."""
        Bq, Bx = self.basis(q, context or {}, poses)
        return ({k: v @ self.params for k, v in Bq.items()},
                {k: v @ self.params for k, v in Bx.items()})

    def point_jacobian(self, q: Mapping[str, Any], link: str, point: Any,
                       context: Mapping[str, Any] | None = None) -> np.ndarray:
        """Derivative ``(..., 3, P)`` of the root-frame position of ``point`` on ``link``
        w.r.t. this effect's parameters (analytic: chain Jacobian at the corrected chain times
        :meth:`basis`, which is evaluated on the nominal chain)."""
        nominal = self.tree.link_poses(q)
        Bq, Bx = self.basis(q, context or {}, nominal)
        dq = {k: v @ self.params for k, v in Bq.items()}
        dxi = {k: v @ self.params for k, v in Bx.items()}
        Jq, Jx = self.tree.point_jacobian(q, link, point, None, dq, dxi)
        out = np.zeros(_batch(q) + (3, self.n_params))
        for k, b in Bq.items():
            if k in Jq:
                out = out + Jq[k][..., :, None] * b[..., None, :]
        for k, b in Bx.items():
            if k in Jx:
                out = out + Jx[k] @ b
        return out

    def to_config(self, ci: Sequence[float] | None = None) -> dict[str, Any]:
        """YAML entry ``{name, location, parameters[, ci]}`` (floats, for the model file)."""
        out: dict[str, Any] = {"name": self.name, "location": self.location,
                               "parameters": {k: float(v) for k, v in zip(self.param_names, self.params)}}
        for key in ("variable", "reference"):  # what a context-driven effect is driven by (thermal, base tilt)
            if getattr(self, key, None) is not None:
                out[key] = getattr(self, key)
        if ci is not None:
            out["ci"] = {k: float(v) for k, v in zip(self.param_names, ci)}
        return out

    def describe(self) -> str:
        return f"{self.name}@{self.location}"

    def __repr__(self) -> str:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in zip(self.param_names, self.params))
        return f"{type(self).__name__}({self.location!r}, {ps})"


def _check_joint(tree: KinematicTree, joint: str, effect: str, movable: bool = False) -> None:
    if joint not in tree.robot.joints:
        raise UnknownJointError(f"effect {effect}: location '{joint}' is not a joint of URDF "
                                f"{tree.robot.source}")
    if movable and not tree.robot.joints[joint].movable:
        raise ModelConfigError(f"effect {effect}: location '{joint}' is a "
                               f"{tree.robot.joints[joint].type} joint; it must be movable")


class JointOffset(Effect):
    """Joint zero offset: ``dq_j = offset``."""

    name = "joint_offset"
    units = ("rad or m",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        _check_joint(tree, location, self.name, movable=True)
        super().__init__(tree, location, ("offset",), params)

    def basis(self, q, context=None, poses=None):
        return {self.location: np.ones(_batch(q) + (1,))}, {}


class LinkError(Effect):
    """Static non-zero-mean twist at a joint: ``dxi_j`` with a subset of ``x y z rx ry rz``."""

    name = "link_error"

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] = _TWIST_KEYS) -> None:
        _check_joint(tree, location, self.name)
        bad = [c for c in components if c not in _TWIST_KEYS]
        if bad or not components:
            raise ModelConfigError(f"effect {self.name} at '{location}': components {list(components)} "
                                   f"must be a non-empty subset of {list(_TWIST_KEYS)}")
        self.components = tuple(components)
        self.units = tuple("m" if c in "xyz" else "rad" for c in self.components)
        super().__init__(tree, location, self.components, params)

    def basis(self, q, context=None, poses=None):
        S = np.zeros((6, len(self.components)))
        for i, c in enumerate(self.components):
            S[_TWIST_KEYS.index(c), i] = 1.0
        return {}, {self.location: np.broadcast_to(S, _batch(q) + S.shape)}


class CameraExtrinsics(LinkError):
    """6D correction of the fixed joint that carries a camera frame (a link error there)."""

    name = "camera_extrinsics"

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] = _TWIST_KEYS) -> None:
        if location in tree.robot.links and location not in tree.robot.joints:
            pj = tree.robot.parent_joint(location)
            if pj is None:
                raise ModelConfigError(f"effect {self.name}: camera frame '{location}' is the root link")
            self.frame = location
            location = pj.name
        super().__init__(tree, location, params, components)


class GravityCompliance(Effect):
    """Joint compliance under gravity: ``dq_j = c_j * tau_j(q)``.

    ``tau_j`` is the gravity torque (force for prismatic joints) about joint ``j``'s axis of the
    weight of every link the joint carries (URDF inertials), in the configuration ``q``.
    """

    name = "gravity_compliance"
    units = ("rad/(N m) or m/N",)
    nonnegative = ("compliance",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        _check_joint(tree, location, self.name, movable=True)
        super().__init__(tree, location, ("compliance",), params)

    def torque(self, q, context=None, poses=None) -> np.ndarray:
        """Gravity torque [N m] (force [N] if prismatic) about the joint axis, shape (...)."""
        context = context or {}
        poses = poses if poses is not None else self.tree.link_poses(q)
        j = self.tree.robot.joints[self.location]
        F, M = self.tree.gravity_wrench(poses, self.location, context.get("gravity", (0.0, 0.0, -1.0)),
                                        about="c")
        W = F if j.type == "prismatic" else M
        return W @ j.axis

    def basis(self, q, context=None, poses=None):
        return {self.location: self.torque(q, context, poses)[..., None]}, {}


class _TwoAxisBending(Effect):
    """A rotation at a joint proportional, per axis, to the gravity moment about it: ``theta_k = c_k M_k``.

    Each of the two axes has its own compliance and sign check; ``components`` keeps a subset of them
    (an axis whose fitted compliance is negative is dropped, not the whole effect).
    """

    axis_names: tuple[str, str] = ("compliance_x", "compliance_y")
    #: per axis, a compliance growing with the joint's own value (a telescopic stage: ``c_k + e_k q_j``)
    scaled_names: tuple[str, ...] = ()

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] | None = None) -> None:
        comps = tuple(components) if components is not None else self.axis_names
        allowed = self.axis_names + self.scaled_names
        if not comps or any(c not in allowed for c in comps):
            raise ModelConfigError(f"effect {self.name} at '{location}': components {list(comps)} must be a "
                                   f"non-empty subset of {list(allowed)}")
        self.components = comps
        self.units = tuple("rad/(N m)" if c in self.axis_names else "rad/(N m m)" for c in comps)
        scaled = [c for c in comps if c in self.scaled_names]  # then c_k is the value at q_j = 0, any sign
        self.nonnegative = tuple(scaled) or comps
        super().__init__(tree, location, comps, params)

    def axes_and_moment(self, q: Mapping[str, Any], context: Mapping[str, Any] | None,
                        poses: Mapping[str, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
        """Rotation axes in the dxi frame (..., 2, 3) and the moment about each of them (..., 2) [N m]."""
        raise NotImplementedError

    def basis(self, q, context=None, poses=None):
        axes, m = self.axes_and_moment(q, context or {}, poses)
        B = np.zeros(m.shape[:-1] + (6, len(self.components)))
        qj = self.tree.joint_values(q)[self.location][..., None] if self.scaled_names else 1.0
        for i, c in enumerate(self.components):
            k, f = (self.axis_names.index(c), 1.0) if c in self.axis_names else (self.scaled_names.index(c), qj)
            B[..., 3:, i] = axes[..., k, :] * m[..., k, None] * f
        return {}, {self.location: B}


class MountBending(_TwoAxisBending):
    """Rotation at a (typically fixed) joint proportional to the gravity moment about it.

    ``theta = [c_x M_x, c_y M_y, 0]`` in the joint frame, ``M`` the moment [N m] of the weight of
    everything the joint carries about the joint frame origin, in the joint frame axes.  At a prismatic
    joint (a telescopic stage, whose overlap shrinks as it extends) ``c_k + e_k q_j`` with components
    ``extension_x``, ``extension_y`` (``e_k`` >= 0; ``c_k`` then has any sign).
    """

    name = "mount_bending"
    units = ("rad/(N m)", "rad/(N m)")
    nonnegative = ("compliance_x", "compliance_y")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] | None = None) -> None:
        _check_joint(tree, location, self.name)
        if tree.robot.joints[location].type == "prismatic":
            self.scaled_names = ("extension_x", "extension_y")
        super().__init__(tree, location, params, components)

    def moment(self, q, context=None, poses=None) -> np.ndarray:
        """Gravity moment [N m] about the mount, joint-frame axes, shape (..., 3)."""
        context = context or {}
        poses = poses if poses is not None else self.tree.link_poses(q)
        return self.tree.gravity_wrench(poses, self.location, context.get("gravity", (0.0, 0.0, -1.0)))[1]

    def axes_and_moment(self, q, context, poses):
        M = self.moment(q, context, poses)
        return np.broadcast_to(np.eye(3)[:2], M.shape[:-1] + (2, 3)), M[..., :2]


def perpendicular_axes(axis: np.ndarray) -> np.ndarray:
    """Two unit axes ``(u, v)`` perpendicular to ``axis`` with ``u x v = axis``, (2, 3): ``u`` is the coordinate
    axis least parallel to ``axis`` (first on ties) with its ``axis`` component removed."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    u = e - (e @ a) * a
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(a, u)])


class LateralCompliance(_TwoAxisBending):
    """A revolute joint's link bending about the two axes perpendicular to the joint axis under the
    gravity moment it carries (Tenhumberg & Bäuml, Humanoids 2021).

    In the child frame (after the joint motion), ``theta_c = c_u (M.u) u + c_v (M.v) v`` with ``M`` the
    gravity moment [N m] of everything the joint carries about the joint origin and ``(u, v)``
    :func:`perpendicular_axes` of the joint axis; it is inserted at the joint's ``dxi`` (before the
    motion) as ``R_ac theta_c`` (the joint rotates about an axis through its origin).
    """

    name = "lateral_compliance"
    axis_names = ("compliance_u", "compliance_v")
    units = ("rad/(N m)", "rad/(N m)")
    nonnegative = ("compliance_u", "compliance_v")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] | None = None) -> None:
        _check_joint(tree, location, self.name, movable=True)
        if tree.robot.joints[location].type == "prismatic":
            raise ModelConfigError(f"effect {self.name} at '{location}': needs a revolute joint, not prismatic")
        super().__init__(tree, location, params, components)
        self.uv = perpendicular_axes(tree.robot.joints[location].axis)

    def axes_and_moment(self, q, context, poses):
        poses = poses if poses is not None else self.tree.link_poses(q)
        M_c = self.tree.gravity_wrench(poses, self.location, context.get("gravity", (0.0, 0.0, -1.0)),
                                       about="c")[1]
        T_a, T_c = self.tree.joint_frames(poses, self.location)
        R_ac = np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_c[..., :3, :3]
        axes = np.einsum("...ij,kj->...ki", R_ac, self.uv)
        return np.broadcast_to(axes, M_c.shape[:-1] + (2, 3)), np.einsum("...j,kj->...k", M_c, self.uv)


class BaseTilt(Effect):
    """Rotation of the root about its x and y axes: ``dxi`` on every joint hanging on the root.  With
    ``variable="measured"`` the tilt measured at each stop by an accelerometer fixed to the root (context
    ``base_tilt``; none without it) times ``gain`` (1: the robot rocks on its support as measured)."""

    name = "base_tilt"
    units: tuple[str, ...] = ("rad", "rad")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 variable: str | None = None) -> None:
        if location != tree.root:
            raise ModelConfigError(f"effect {self.name}: location '{location}' must be the root link "
                                   f"'{tree.root}' of URDF {tree.robot.source}")
        if variable not in (None, "measured"):
            raise ModelConfigError(f"effect {self.name}: variable must be 'measured' or absent, got {variable!r}")
        self.variable = variable
        self.units = ("rad", "rad") if variable is None else ("1",)
        super().__init__(tree, location, ("tilt_x", "tilt_y") if variable is None else ("gain",), params)

    def basis(self, q, context=None, poses=None):
        w = (context or {}).get("base_tilt")
        if self.variable is not None and w is None:  # nothing measured (fk, nodes): no rocking to correct
            return {}, {}
        Ads = {jn: np.broadcast_to(lie.adjoint(lie.inverse(self.tree.robot.joints[jn].origin))[:, 3:5],
                                   _batch(q) + (6, 2)) for jn in self.tree.robot.children(self.tree.root)}
        return {}, {jn: Ad if self.variable is None else Ad @ np.asarray(w, dtype=float)[..., :, None]
                    for jn, Ad in Ads.items()}


class Backlash(Effect):
    """Backlash: ``dq_j = play * sign(last motion of j)`` (context ``motion_sign``)."""

    name = "backlash"
    units = ("rad or m",)
    context_keys = ("motion_sign",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        _check_joint(tree, location, self.name, movable=True)
        super().__init__(tree, location, ("play",), params)

    def basis(self, q, context=None, poses=None):
        signs = (context or {}).get("motion_sign")
        if signs is None or self.location not in signs:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context "
                                   f"'motion_sign' for joint '{self.location}'")
        s = np.broadcast_to(np.asarray(signs[self.location], dtype=float), _batch(q))
        return {self.location: s[..., None]}, {}


class ThermalGrowth(Effect):
    """Length change of the link before a joint: ``rho = alpha (u - reference) R_p^T t_p``.

    ``u`` is context ``variable`` (``temperature`` or ``time``); ``t_p, R_p`` the joint origin.
    """

    name = "thermal_growth"
    units = ("1/unit of variable",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 variable: str = "temperature", reference: float = 0.0) -> None:
        _check_joint(tree, location, self.name)
        if variable not in ("temperature", "time"):
            raise ModelConfigError(f"effect {self.name} at '{location}': variable must be "
                                   f"'temperature' or 'time', got {variable!r}")
        self.variable, self.reference, self.context_keys = variable, float(reference), (variable,)
        super().__init__(tree, location, ("alpha",), params)

    def basis(self, q, context=None, poses=None):
        u = (context or {}).get(self.variable)
        if u is None:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context "
                                   f"'{self.variable}'")
        o = self.tree.robot.joints[self.location].origin
        d = o[:3, :3].T @ o[:3, 3]
        du = np.broadcast_to(np.asarray(u, dtype=float) - self.reference, _batch(q))
        B = np.zeros(du.shape + (6, 1))
        B[..., :3, 0] = du[..., None] * d
        return {}, {self.location: B}


class TimeOffset(Effect):
    """Time offset of the joint states w.r.t. a sensor: ``dq_j = dt * qdot_j`` for every joint.

    With context ``sensor`` (the sensor of each row, e.g. a camera frame), only the rows of the sensor named
    by ``location`` are shifted: each camera or tracker stream has its own offset.
    """

    name = "time_offset"
    units = ("s",)
    context_keys = ("joint_velocity",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        super().__init__(tree, location, ("dt",), params)

    def basis(self, q, context=None, poses=None):
        vel = (context or {}).get("joint_velocity")
        if vel is None:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context 'joint_velocity'")
        b = _batch(q)
        sensor = (context or {}).get("sensor")
        mask = 1.0 if sensor is None else (np.asarray(sensor) == self.location).astype(float)
        return {k: np.broadcast_to(np.asarray(v, dtype=float) * mask, b)[..., None]
                for k, v in vel.items() if k in q}, {}


class TrackerRegistration(Effect):
    """Per-session tracker-to-base transform ``T_tracker_base = from_xyz_rpy(x y z, rx ry rz)``.

    Not a chain correction (``corrections`` are empty); ``ppoe diagnose`` always estimates it as
    a nuisance per session.
    """

    name = "tracker_registration"
    units = ("m", "m", "m", "rad", "rad", "rad")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        super().__init__(tree, location, _TWIST_KEYS, params)

    def transform(self) -> np.ndarray:
        """``T_tracker_base`` (4, 4)."""
        return lie.from_xyz_rpy(self.params[:3], self.params[3:])

    def basis(self, q, context=None, poses=None):
        return {}, {}


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
    "tracker_registration": TrackerRegistration,
}


def make_effect(name: str, location: str, robot_or_tree: Robot | KinematicTree,
                params: Sequence[float] | None = None, **options: Any) -> Effect:
    """Build effect ``name`` at ``location`` with parameters in catalogue order (zeros if None)."""
    tree = robot_or_tree if isinstance(robot_or_tree, KinematicTree) else KinematicTree(robot_or_tree)
    if name not in _CLASSES:
        raise ModelConfigError(f"unknown effect '{name}' (vocabulary: {', '.join(EFFECT_NAMES)})")
    return _CLASSES[name](tree, location, params, **options)


#: keys ``ppoe diagnose`` adds to an effect entry; they describe the fit, not the effect, and are ignored on load
_REPORT_KEYS = ("ci", "sigma", "share", "measurement", "frame")


def effect_from_config(entry: Mapping[str, Any], robot: Robot | KinematicTree,
                       where: str = "effects") -> Effect:
    """Build an effect from a model-YAML entry ``{name, location, parameters}``.

    ``parameters`` maps parameter names to values; a ``link_error`` /
    ``camera_extrinsics`` entry uses only the twist components it lists (``x y z rx ry rz``).
    ``thermal_growth`` accepts ``variable`` and ``reference``.  The annotations ``ppoe diagnose`` adds to an
    entry (``ci``, ``sigma``, ``share``, ``measurement``, ``frame``) are ignored, so its JSON entries load as they
    are.

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
    options: dict[str, Any] = {}
    if name in ("link_error", "camera_extrinsics"):
        options["components"] = tuple(k for k in _TWIST_KEYS if k in params)
    if name in ("mount_bending", "lateral_compliance"):
        axes = LateralCompliance.axis_names if name == "lateral_compliance" else MountBending.axis_names
        options["components"] = tuple(k for k in axes + ("extension_x", "extension_y") if k in params) or axes
    if name == "base_tilt" and "variable" in entry:
        options["variable"] = entry["variable"]
    if name == "thermal_growth":
        options["variable"] = entry.get("variable", "temperature")
        options["reference"] = float(entry.get("reference", 0.0))
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


def sum_effect_corrections(effects: Sequence[Effect], q: Mapping[str, Any],
                      context: Mapping[str, Any] | None = None,
                      poses: Mapping[str, np.ndarray] | None = None, start: Corrections | None = None) -> Corrections:
    """Sum the corrections of several effects: ``(dq, dxi)`` dictionaries (eq. 16 hooks), added to ``start``'s."""
    dq: dict[str, np.ndarray] = dict(start[0]) if start else {}
    dxi: dict[str, np.ndarray] = dict(start[1]) if start else {}
    for eff in effects:
        a, b = eff.corrections(q, context or {}, poses)
        for k, v in a.items():
            dq[k] = dq.get(k, 0.0) + v
        for k, v in b.items():
            dxi[k] = dxi.get(k, 0.0) + v
    return dq, dxi
