"""Load-dependent effects: joint and link compliance under the gravity moment of what a joint carries (URDF
inertials), with the gravity direction from the context (``gravity``, default ``[0, 0, -1]`` in the root frame)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core.errors import ModelConfigError
from ppoe_core.model.effect_base import Effect, check_components, check_joint
from ppoe_core.robot.tree import KinematicTree

__all__ = ["GravityCompliance", "TwoAxisBending", "MountBending", "LateralCompliance", "perpendicular_axes"]


class GravityCompliance(Effect):
    """Joint compliance under gravity: ``dq_j = c_j * tau_j(q)``.

    ``tau_j`` is the gravity torque (force for prismatic joints) about joint ``j``'s axis of the
    weight of every link the joint carries (URDF inertials), in the configuration ``q``.
    """

    name = "gravity_compliance"
    units = ("rad/(N m) or m/N",)
    nonnegative = ("compliance",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        check_joint(tree, location, self.name, movable=True)
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


class TwoAxisBending(Effect):
    """A rotation at a joint proportional, per axis, to the gravity moment about it: ``theta_k = c_k M_k``.

    Each of the two axes has its own compliance and sign check; ``components`` keeps a subset of them
    (an axis whose fitted compliance is negative is dropped, not the whole effect).
    """

    axis_names: tuple[str, str] = ("compliance_x", "compliance_y")
    #: per axis, a compliance growing with the joint's own value (a telescopic stage: ``c_k + e_k q_j``)
    scaled_names: tuple[str, ...] = ()

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] | None = None) -> None:
        allowed = self.axis_names + self.scaled_names
        comps = check_components(self.name, location, components if components is not None else self.axis_names,
                                 allowed)
        self.all_components = allowed
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


class MountBending(TwoAxisBending):
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
        check_joint(tree, location, self.name)
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


class LateralCompliance(TwoAxisBending):
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
        check_joint(tree, location, self.name, movable=True)
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
