"""Catalogue of systematic effects that a nominal PPOE model may lack (CONTRACT sec. 6).

Every effect is a small physical parametrisation that changes the kinematic chain through
the two hooks of paper eq. 16, ``Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))``:

* ``dq``: an offset added to a joint value (for a mimic master it propagates through the
  mimic multiplier), and
* ``dxi``: a non-zero-mean twist ``[rho; theta]`` placed right after a joint's static
  origin ``p_i``, where the joint's perturbation ``xi_i`` sits.

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
``base_tilt``               root link            ``tilt_x``, ``tilt_y`` [rad]
``backlash``                movable joint        ``play`` [rad or m] (half the dead band)
``thermal_growth``          any joint            ``alpha`` [1/K or 1/s]
``time_offset``             topic / sensor       ``dt`` [s]
``camera_extrinsics``       camera frame/joint   ``x y z rx ry rz`` [m, rad]
``tracker_registration``    topic / frame        ``x y z rx ry rz`` [m, rad] (nuisance)
==========================  ===================  =========================================

Context keys (``context`` of :meth:`Effect.corrections`), each broadcast like the joints:

``gravity``
    Gravity direction in the root frame, ``(..., 3)`` unit vector, default ``[0, 0, -1]``.
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
from ppoe_core.errors import ModelConfigError, UnknownFrameError, UnknownJointError
from ppoe_core.robot.config import EFFECT_NAMES as _CONFIG_EFFECT_NAMES
from ppoe_core.robot.urdf import Robot

__all__ = [
    "GRAVITY",
    "EFFECT_NAMES",
    "KinematicTree",
    "Effect",
    "JointOffset",
    "LinkError",
    "GravityCompliance",
    "MountBending",
    "BaseTilt",
    "Backlash",
    "ThermalGrowth",
    "TimeOffset",
    "CameraExtrinsics",
    "TrackerRegistration",
    "effect_from_config",
    "make_effect",
    "sum_effect_corrections",
]

#: standard gravity [m/s^2]
GRAVITY = 9.80665

#: the contract vocabulary (CONTRACT.md sec. 6), in catalogue order (defined in config)
EFFECT_NAMES = _CONFIG_EFFECT_NAMES

_TWIST_KEYS = ("x", "y", "z", "rx", "ry", "rz")

Corrections = tuple[dict[str, np.ndarray], dict[str, np.ndarray]]


# =============================================================================
# Nominal kinematic tree (link poses and Jacobians with dq / dxi insertions)
# =============================================================================


class KinematicTree:
    """Nominal forward kinematics of a whole URDF tree with the eq. 16 effect hooks.

    Parameters
    ----------
    robot : Robot
        Parsed URDF (``ppoe_core.robot.urdf``); mimic joints are resolved through ``mimic_root``.
    """

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self.root = robot.root
        order: list[str] = []
        stack = [robot.root]
        while stack:  # depth-first, parents before children
            link = stack.pop()
            kids = robot.children(link)
            order.extend(kids)
            stack.extend(robot.joints[j].child for j in reversed(kids))
        self.order = order
        self.joint_names = robot.independent_joints

    # -- joint values ------------------------------------------------------------
    def joint_values(self, q: Mapping[str, Any], dq: Mapping[str, Any] | None = None,
                     joints: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """Values of movable joints (mimic resolved) with offsets ``dq`` added.

        ``dq`` on an independent joint propagates to its mimic joints with the multiplier;
        ``dq`` on a mimic joint is added to that joint only.
        """
        dq = dq or {}
        names = joints if joints is not None else [j for j in self.order if self.robot.joints[j].movable]
        out: dict[str, np.ndarray] = {}
        for jn in names:
            j = self.robot.joints[jn]
            if not j.movable:
                continue
            if j.mimic_root is not None:
                src, mult, off = j.mimic_root
                v = mult * (self._q(q, src, jn) + np.asarray(dq.get(src, 0.0))) + off
            else:
                v = self._q(q, jn, jn) + np.asarray(dq.get(jn, 0.0))
            if j.mimic_root is not None and jn in dq:
                v = v + np.asarray(dq[jn])
            out[jn] = np.asarray(v, dtype=float)
        return out

    def _q(self, q: Mapping[str, Any], name: str, needed_by: str) -> np.ndarray:
        if name not in q:
            raise UnknownJointError(
                f"joint '{name}' (needed by joint '{needed_by}' of URDF {self.robot.source}) "
                f"has no value; given: {', '.join(q) or 'none'}")
        return np.asarray(q[name], dtype=float)

    @staticmethod
    def _motion(joint: Any, v: np.ndarray) -> np.ndarray:
        return lie.exp(v[..., None] * joint.twist)

    # -- poses -------------------------------------------------------------------
    def link_poses(self, q: Mapping[str, Any], dq: Mapping[str, Any] | None = None,
                   dxi: Mapping[str, Any] | None = None,
                   links: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """``T_root_link`` for every link (or the ancestors of ``links``), shape ``(..., 4, 4)``.

        Implements the mean of paper eq. 17 with eq. 16 links
        ``Exp(p_i) Exp(dxi_i) Exp(zeta_i (q_i + dq_i))``.
        """
        dxi = dxi or {}
        if links is not None:
            need = set()
            for ln in links:
                need.update(self.robot.path_from_root(ln))
            joints = [j for j in self.order if j in need]
        else:
            joints = self.order
        vals = self.joint_values(q, dq, joints)
        # batch shape of all given joint values (also when the links asked for hang on fixed joints)
        batch = np.broadcast_shapes(*[np.shape(v) for v in q.values()], *[np.shape(v) for v in vals.values()],
                                    *[np.shape(v)[:-1] for v in dxi.values()])
        eye = np.broadcast_to(np.eye(4), batch + (4, 4))
        poses: dict[str, np.ndarray] = {self.root: eye}
        for jn in joints:
            j = self.robot.joints[jn]
            T = poses[j.parent] @ j.origin
            if jn in dxi:
                T = T @ lie.exp(np.asarray(dxi[jn], dtype=float))
            if j.movable:
                T = T @ self._motion(j, vals[jn])
            poses[j.child] = T
        return poses

    def joint_frames(self, poses: Mapping[str, np.ndarray], joint: str,
                     dxi: Mapping[str, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(T_root_a, T_root_c)``: frame right after the joint's origin and its ``dxi``
        insertion (``Exp(p) Exp(dxi)``), and the child link frame after the motion."""
        j = self.robot.joints[joint]
        T_a = poses[j.parent] @ j.origin
        if dxi and joint in dxi:
            T_a = T_a @ lie.exp(np.asarray(dxi[joint], dtype=float))
        return T_a, poses[j.child]

    # -- Jacobians ---------------------------------------------------------------
    def frame_jacobian(self, q: Mapping[str, Any], link: str,
                       poses: Mapping[str, np.ndarray] | None = None,
                       dq: Mapping[str, Any] | None = None,
                       dxi: Mapping[str, Any] | None = None
                       ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Right-tangent Jacobians of ``T_root_link`` w.r.t. the eq. 16 insertions.

        Returns
        -------
        J_dq : dict joint -> ndarray (..., 6)
            ``d xi_link / d dq_j`` for independent joints ``j`` (mimic joints on the path
            contribute through their multiplier) and mimic joints themselves.
        J_dxi : dict joint -> ndarray (..., 6, 6)
            ``d xi_link / d dxi_j`` = ``Ad(T_a_link^-1)`` for every joint on the path, where
            ``xi_link`` is the right perturbation of ``T_root_link`` (tangent at the link).
            With a non-zero insertion ``dxi_j`` this is ``Ad(T_a_link^-1) J_r(dxi_j)``.

        ``poses`` must be :meth:`link_poses` of the same ``q, dq, dxi`` (computed if None).
        """
        if link not in self.robot.links:
            raise UnknownFrameError(f"unknown link '{link}' (not in URDF {self.robot.source})")
        if poses is None:
            poses = self.link_poses(q, dq, dxi, links=[link])
        T_root_l = poses[link]
        T_l_root = lie.inverse(T_root_l)
        J_dq: dict[str, np.ndarray] = {}
        J_dxi: dict[str, np.ndarray] = {}
        for jn in self.robot.path_from_root(link):
            j = self.robot.joints[jn]
            T_root_a, T_root_c = self.joint_frames(poses, jn, dxi)
            J_dxi[jn] = lie.adjoint(T_l_root @ T_root_a)
            if dxi and jn in dxi:
                J_dxi[jn] = J_dxi[jn] @ lie.right_jacobian(np.asarray(dxi[jn], dtype=float))
            if j.movable:
                col = np.einsum("...ij,j->...i", lie.adjoint(T_l_root @ T_root_c), j.twist)
                if j.mimic_root is not None:
                    src, mult, _ = j.mimic_root
                    J_dq[src] = J_dq.get(src, 0.0) + mult * col
                    J_dq[jn] = J_dq.get(jn, 0.0) + col
                else:
                    J_dq[jn] = J_dq.get(jn, 0.0) + col
        return J_dq, J_dxi

    def point_jacobian(self, q: Mapping[str, Any], link: str, point: Any,
                       poses: Mapping[str, np.ndarray] | None = None,
                       dq: Mapping[str, Any] | None = None,
                       dxi: Mapping[str, Any] | None = None
                       ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Jacobians of the root-frame position of ``point`` (link coordinates, (3,)) on ``link``.

        Returns ``(J_dq: joint -> (..., 3), J_dxi: joint -> (..., 3, 6))``, derived from
        :meth:`frame_jacobian` with ``d(T p)/d xi = R [I, -[p]_x]``.
        """
        if poses is None:
            poses = self.link_poses(q, dq, dxi, links=[link])
        J_dq, J_dxi = self.frame_jacobian(q, link, poses, dq, dxi)
        R = poses[link][..., :3, :3]
        p = np.asarray(point, dtype=float)
        B = np.concatenate([R, -R @ lie.hat3(p)], axis=-1)
        return ({k: np.einsum("...ij,...j->...i", B, v) for k, v in J_dq.items()},
                {k: B @ v for k, v in J_dxi.items()})

    # -- gravity -------------------------------------------------------------------
    def subtree_links(self, joint: str) -> list[str]:
        """Links carried by ``joint`` (its child and everything below it)."""
        out: list[str] = []
        stack = [self.robot.joints[joint].child]
        while stack:
            ln = stack.pop()
            out.append(ln)
            stack.extend(self.robot.joints[j].child for j in self.robot.children(ln))
        return out

    def gravity_wrench(self, poses: Mapping[str, np.ndarray], joint: str,
                       gravity: Any = (0.0, 0.0, -1.0), about: str = "a") -> tuple[np.ndarray, np.ndarray]:
        """Force [N] and moment [N m] of the weight of the links carried by ``joint``.

        Both are expressed in the joint frame (``about="a"``: after the origin, where dxi sits;
        ``"c"``: after the motion), the moment taken about that frame's origin. URDF inertials
        give masses and centres of mass; ``gravity`` is the unit direction in the root frame.
        """
        g = GRAVITY * np.asarray(gravity, dtype=float)
        T_root_a, T_root_c = self.joint_frames(poses, joint)
        T = T_root_a if about == "a" else T_root_c
        F: Any = 0.0
        M: Any = 0.0
        for ln in self.subtree_links(joint):
            inert = self.robot.links[ln].inertial
            if inert is None or inert.mass <= 0.0:
                continue
            c = (poses[ln] @ inert.origin)[..., :3, 3]
            f = inert.mass * g
            F = F + f
            M = M + np.cross(c - T[..., :3, 3], np.broadcast_to(f, c.shape))
        F = np.broadcast_to(F, T.shape[:-2] + (3,))
        M = np.broadcast_to(M, T.shape[:-2] + (3,))
        Rt = np.swapaxes(T[..., :3, :3], -1, -2)
        return np.einsum("...ij,...j->...i", Rt, F), np.einsum("...ij,...j->...i", Rt, M)


# =============================================================================
# Effects
# =============================================================================


def _batch(q: Mapping[str, Any]) -> tuple[int, ...]:
    return np.broadcast_shapes(*[np.shape(v) for v in q.values()]) if q else ()


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


def _ones(q: Mapping[str, Any]) -> np.ndarray:
    return np.ones(_batch(q) + (1,))


class JointOffset(Effect):
    """Joint zero offset: ``dq_j = offset``."""

    name = "joint_offset"
    units = ("rad or m",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        _check_joint(tree, location, self.name, movable=True)
        super().__init__(tree, location, ("offset",), params)

    def basis(self, q, context=None, poses=None):
        return {self.location: _ones(q)}, {}


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


class MountBending(Effect):
    """Rotation at a (typically fixed) joint proportional to the gravity moment about it.

    ``theta = [c_x M_x, c_y M_y, 0]`` in the joint frame, ``M`` the moment [N m] of the weight of
    everything the joint carries about the joint frame origin, in the joint frame axes.
    """

    name = "mount_bending"
    units = ("rad/(N m)", "rad/(N m)")
    nonnegative = ("compliance_x", "compliance_y")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        _check_joint(tree, location, self.name)
        super().__init__(tree, location, ("compliance_x", "compliance_y"), params)

    def moment(self, q, context=None, poses=None) -> np.ndarray:
        """Gravity moment [N m] about the mount, joint-frame axes, shape (..., 3)."""
        context = context or {}
        poses = poses if poses is not None else self.tree.link_poses(q)
        return self.tree.gravity_wrench(poses, self.location, context.get("gravity", (0.0, 0.0, -1.0)))[1]

    def basis(self, q, context=None, poses=None):
        M = self.moment(q, context, poses)
        B = np.zeros(M.shape[:-1] + (6, 2))
        B[..., 3, 0] = M[..., 0]
        B[..., 4, 1] = M[..., 1]
        return {}, {self.location: B}


class BaseTilt(Effect):
    """Rotation of the root about its x and y axes: ``dxi`` on every joint hanging on the root."""

    name = "base_tilt"
    units = ("rad", "rad")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        if location != tree.root:
            raise ModelConfigError(f"effect {self.name}: location '{location}' must be the root link "
                                   f"'{tree.root}' of URDF {tree.robot.source}")
        super().__init__(tree, location, ("tilt_x", "tilt_y"), params)

    def basis(self, q, context=None, poses=None):
        out = {}
        for jn in self.tree.robot.children(self.tree.root):
            Ad = lie.adjoint(lie.inverse(self.tree.robot.joints[jn].origin))
            out[jn] = np.broadcast_to(Ad[:, 3:5], _batch(q) + (6, 2))
        return {}, out


class Backlash(Effect):
    """Backlash: ``dq_j = play * sign(last motion of j)`` (context ``motion_sign``)."""

    name = "backlash"
    units = ("rad or m",)

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
        self.variable = variable
        self.reference = float(reference)
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

    def to_config(self, ci=None):
        out = super().to_config(ci)
        out["variable"] = self.variable
        out["reference"] = self.reference
        return out


class TimeOffset(Effect):
    """Time offset of the joint states w.r.t. a sensor: ``dq_j = dt * qdot_j`` for every joint."""

    name = "time_offset"
    units = ("s",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        super().__init__(tree, location, ("dt",), params)

    def basis(self, q, context=None, poses=None):
        vel = (context or {}).get("joint_velocity")
        if vel is None:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context 'joint_velocity'")
        b = _batch(q)
        return {k: np.broadcast_to(np.asarray(v, dtype=float), b)[..., None]
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


def effect_from_config(entry: Mapping[str, Any], robot: Robot | KinematicTree,
                       where: str = "effects") -> Effect:
    """Build an effect from a model-YAML entry ``{name, location, parameters}``.

    ``parameters`` maps parameter names to values; a ``link_error`` /
    ``camera_extrinsics`` entry uses only the twist components it lists (``x y z rx ry rz``).
    ``thermal_growth`` accepts ``variable`` and ``reference``; a ``ci`` key is ignored.

    Raises
    ------
    ModelConfigError
        Unknown name or parameter, missing key; the message names ``where`` (the entry).
    UnknownJointError
        A location that is not a joint of the URDF.
    """
    if not isinstance(entry, Mapping):
        raise ModelConfigError(f"{where}: an effect entry must be a mapping, got {type(entry).__name__}")
    extra = set(entry) - {"name", "location", "parameters", "ci", "variable", "reference"}
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
                      poses: Mapping[str, np.ndarray] | None = None) -> Corrections:
    """Sum the corrections of several effects: ``(dq, dxi)`` dictionaries (eq. 16 hooks)."""
    dq: dict[str, np.ndarray] = {}
    dxi: dict[str, np.ndarray] = {}
    for eff in effects:
        a, b = eff.corrections(q, context or {}, poses)
        for k, v in a.items():
            dq[k] = dq.get(k, 0.0) + v
        for k, v in b.items():
            dxi[k] = dxi.get(k, 0.0) + v
    return dq, dxi
