"""The kinematic tree of a URDF: nominal link poses, chain Jacobians and the gravity wrench a joint carries.

Joint values may be corrected through eq. 16's hooks (``dq`` per joint, ``dxi`` per joint origin) by the effects of
:mod:`ppoe_core.model.effects`.  Twists ``[rho; theta]``, right perturbations (docs/conventions.md)."""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import UnknownFrameError, UnknownJointError
from ppoe_core.robot.urdf import Robot

#: standard gravity [m/s^2]
GRAVITY = 9.80665


# =============================================================================
# Nominal kinematic tree (link poses and Jacobians with dq / dxi insertions)
# =============================================================================


class LinkPoses(dict):
    """:meth:`KinematicTree.link_poses`' result (link -> ``T_root_link``) with what the Jacobians of the same
    evaluation reuse: per joint the frame right after its origin (``origin``) and after its ``dxi`` insertion
    (``inserted``), and the insertions' right Jacobians ``J_r(dxi)`` (``dxi_jacobians``, filled on first use)."""

    def __init__(self) -> None:
        super().__init__()
        self.origin: dict[str, np.ndarray] = {}
        self.inserted: dict[str, np.ndarray] = {}
        self.dxi_jacobians: dict[str, np.ndarray] = {}


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
                   links: Sequence[str] | None = None,
                   dT: Mapping[str, np.ndarray] | None = None,
                   motions: dict[str, np.ndarray] | None = None) -> LinkPoses:
        """``T_root_link`` for every link (or the ancestors of ``links``), shape ``(..., 4, 4)``.

        Implements the mean of paper eq. 17 with eq. 16 links
        ``Exp(p_i) Exp(dxi_i) dT_i Exp(zeta_i (q_i + dq_i))``; ``dT`` (joint -> ``(..., 4, 4)``) are
        insertions given as transforms (the simulator's composed truth), identity where absent.
        ``motions``: the caller's cache of the motions ``Exp(zeta_i q_i)`` of joints that no ``dq`` touches, for
        callers that evaluate the same ``q`` (unchanged arrays) many times with different corrections (a fit); it
        is filled on the first call and must be dropped when ``q`` changes.
        """
        dxi = dxi or {}
        dT = dT or {}
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
                                    *[np.shape(v)[:-1] for v in dxi.values()],
                                    *[np.shape(v)[:-2] for v in dT.values()])
        eye = np.broadcast_to(np.eye(4), batch + (4, 4))
        poses = LinkPoses()
        poses[self.root] = eye
        for jn in joints:
            j = self.robot.joints[jn]
            T = poses.origin[jn] = _times_constant(poses[j.parent], j.origin)
            if jn in dxi:
                T = poses.inserted[jn] = T @ lie.exp(np.asarray(dxi[jn], dtype=float))
            if jn in dT:
                T = T @ dT[jn]
            if j.movable:
                T = T @ self._cached_motion(j, jn, vals[jn], dq, motions)
            poses[j.child] = T
        return poses

    def _cached_motion(self, joint: Any, name: str, v: np.ndarray, dq: Mapping[str, Any] | None,
                       motions: dict[str, np.ndarray] | None) -> np.ndarray:
        """``Exp(zeta v)`` of ``joint``, from ``motions`` (:meth:`link_poses`) when no ``dq`` changes its value."""
        if motions is None or (dq and (name in dq or (joint.mimic_root is not None and joint.mimic_root[0] in dq))):
            return self._motion(joint, v)
        M = motions.get(name)
        if M is None:
            M = motions[name] = self._motion(joint, v)
        return M

    def joint_frames(self, poses: Mapping[str, np.ndarray], joint: str,
                     dxi: Mapping[str, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(T_root_a, T_root_c)``: frame right after the joint's origin and its ``dxi``
        insertion (``Exp(p) Exp(dxi)``), and the child link frame after the motion."""
        j = self.robot.joints[joint]
        done = poses if isinstance(poses, LinkPoses) else None  # the same products, made by link_poses
        if dxi and joint in dxi:
            if done is not None and joint in done.inserted:
                return done.inserted[joint], poses[j.child]
            T_a = _times_constant(poses[j.parent], j.origin) @ lie.exp(np.asarray(dxi[joint], dtype=float))
            return T_a, poses[j.child]
        if done is not None and joint in done.origin:
            return done.origin[joint], poses[j.child]
        return _times_constant(poses[j.parent], j.origin), poses[j.child]

    # -- Jacobians ---------------------------------------------------------------
    def frame_jacobian(self, q: Mapping[str, Any], link: str,
                       poses: Mapping[str, np.ndarray] | None = None,
                       dq: Mapping[str, Any] | None = None,
                       dxi: Mapping[str, Any] | None = None,
                       joints: Collection[str] | None = None
                       ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Right-tangent Jacobians of ``T_root_link`` w.r.t. the eq. 16 insertions (of the path's ``joints`` only,
        and the mimic joints driven by them, when given).

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
            if joints is not None and jn not in joints and (j.mimic_root is None or j.mimic_root[0] not in joints):
                continue
            T_root_a, T_root_c = self.joint_frames(poses, jn, dxi)
            J_dxi[jn] = lie.adjoint(T_l_root @ T_root_a)
            if dxi and jn in dxi:
                J_dxi[jn] = J_dxi[jn] @ self._dxi_jacobian(poses, jn, dxi[jn])
            if j.movable:
                col = np.einsum("...ij,j->...i", lie.adjoint(T_l_root @ T_root_c), j.twist)
                if j.mimic_root is not None:
                    src, mult, _ = j.mimic_root
                    J_dq[src] = J_dq.get(src, 0.0) + mult * col
                    J_dq[jn] = J_dq.get(jn, 0.0) + col
                else:
                    J_dq[jn] = J_dq.get(jn, 0.0) + col
        return J_dq, J_dxi

    @staticmethod
    def _dxi_jacobian(poses: Mapping[str, np.ndarray], joint: str, dxi: Any) -> np.ndarray:
        """``J_r(dxi)`` of ``joint``'s insertion (kept in ``poses`` when they are :class:`LinkPoses`)."""
        cache = poses.dxi_jacobians if isinstance(poses, LinkPoses) else {}
        if joint not in cache:
            cache[joint] = lie.right_jacobian(np.asarray(dxi, dtype=float))
        return cache[joint]

    def point_jacobian(self, q: Mapping[str, Any], link: str, point: Any,
                       poses: Mapping[str, np.ndarray] | None = None,
                       dq: Mapping[str, Any] | None = None,
                       dxi: Mapping[str, Any] | None = None,
                       frame: tuple[dict[str, np.ndarray], dict[str, np.ndarray]] | None = None
                       ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Jacobians of the root-frame position of ``point`` (link coordinates, (3,)) on ``link``.

        Returns ``(J_dq: joint -> (..., 3), J_dxi: joint -> (..., 3, 6))``, derived from
        :meth:`frame_jacobian` with ``d(T p)/d xi = R [I, -[p]_x]`` (``frame``: its result for these ``poses``,
        when the caller has it).
        """
        if poses is None:
            poses = self.link_poses(q, dq, dxi, links=[link])
        J_dq, J_dxi = frame if frame is not None else self.frame_jacobian(q, link, poses, dq, dxi)
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


def _times_constant(T: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``T @ M`` of poses ``T`` (..., 4, 4) and one matrix ``M`` (4, 4) as one matrix product of the stacked rows
    (the same sums, one BLAS call instead of one per pose)."""
    if T.ndim <= 2:
        return T @ M
    return (T.reshape(-1, 4) @ M).reshape(T.shape[:-2] + (4, 4))


# =============================================================================
# Effects
# =============================================================================


def batch_shape(q: Mapping[str, Any]) -> tuple[int, ...]:
    return np.broadcast_shapes(*[np.shape(v) for v in q.values()]) if q else ()


#: the underscore name, for model/effects.py (the engine's rewrite; test/test_architecture.py lists it): remove once
#: it imports :func:`batch_shape`
_batch = batch_shape
