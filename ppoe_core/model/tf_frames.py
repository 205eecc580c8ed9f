"""The transforms the nodes offer on ``/tf`` and ``/tf_static``, computed from a PPOE model (no ROS; the nodes'
publishers are ``ppoe_ros.common.tf_broadcast``).

* :class:`JointFrames`: what robot_state_publisher publishes, from the model: for every movable joint the
  child link in its parent link at a joint state (``/tf``), for every fixed joint the same once
  (``/tf_static``).  The model's effects (``ppoe diagnose``) are applied as in :meth:`PPOEModel.fk_mean`,
  so composing the transforms from link ``a`` to link ``b`` gives ``model.fk_mean(q, a, b)``.
* :func:`calibrated_camera_frames`: the calibrated camera frame(s) of the model YAML relative to the link
  their fixed mount hangs on, with the model's static effects (e.g. ``camera_extrinsics``) applied.
* :func:`urdf_collision`: a child frame name that is already a URDF link (it would fight
  robot_state_publisher over that frame).
* :data:`STATIC_EFFECTS` and :func:`camera_mount_joint`: which effects do not depend on the configuration, and the
  fixed joint a camera's mount correction sits at (``ppoe diagnose`` puts ``camera_extrinsics`` there).

Frame names in variables as in docs/conventions.md sec. 7: ``T_parent_child`` maps child to parent
coordinates.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.model.joint_history import NEVER_NS, JointHistory
from ppoe_core.model.stamp_policy import StampResetPolicy
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.model.effects import sum_effect_corrections

__all__ = [
    "STATIC_EFFECTS", "TfFrame", "JointFrames", "camera_mount_joint", "camera_mount_parent", "calibrated_camera_frames",
    "urdf_collision",
]

#: effects that do not depend on the configuration (as ``ppoe diagnose`` folds into ``robot_calibrated.urdf``);
#: the others (compliances, backlash, thermal growth ...) are evaluated at every joint state
STATIC_EFFECTS = ("joint_offset", "link_error", "camera_extrinsics")


@dataclass(frozen=True)
class TfFrame:
    """One transform of TF: ``child`` in ``parent`` (``T_parent_child``, shape (4, 4))."""

    parent: str
    child: str
    T_parent_child: np.ndarray


def urdf_collision(robot: Any, frame: str) -> str | None:
    """Why ``frame`` may not be a TF child frame we publish (it is a link of the URDF), or None if it may."""
    if frame in robot.links:
        return (f"'{frame}' is a link of the URDF ({robot.source}): publishing it would fight "
                "robot_state_publisher over that frame")
    return None


# ------------------------------------------------------------------------- cameras


def camera_mount_joint(robot: Any, frame: str) -> str | None:
    """The fixed joint a camera ``frame``'s mount correction sits at: the first fixed joint after the last movable
    joint on the path from the root (where ``ppoe diagnose`` puts ``camera_extrinsics``); None when ``frame`` is
    the root link or hangs directly on a movable joint (then it is not static)."""
    path = robot.path_from_root(frame)
    k = len(path)
    while k > 0 and not robot.joints[path[k - 1]].movable:
        k -= 1
    return None if k == len(path) else str(path[k])


def camera_mount_parent(robot: Any, frame: str) -> str | None:
    """The link a camera ``frame`` is mounted on: the parent link of :func:`camera_mount_joint` (None as there)."""
    joint = camera_mount_joint(robot, frame)
    return None if joint is None else str(robot.joints[joint].parent)


def calibrated_camera_frames(model: Any, suffix: str) -> tuple[list[TfFrame], list[str]]:
    """Calibrated camera frames of ``model`` for ``/tf_static``, and notes on cameras left out.

    The cameras are the model YAML's ``camera.frame`` and the camera frame of every ``camera_extrinsics``
    effect located at a camera link.  Each is published as ``<camera frame><suffix>`` relative to the link
    its fixed mount hangs on (:func:`camera_mount_parent`), with ``T_mount_camera`` the mean pose of the model
    with its static effects (:data:`STATIC_EFFECTS`) applied: the calibrated extrinsic.

    Parameters
    ----------
    model : PPOEModel
    suffix : str
        Appended to the camera frame's name for the child frame (so the URDF's own frame stays intact).

    Returns
    -------
    frames : list of TfFrame
    notes : list of str
        One per camera that cannot be published (not static, or its child name is a URDF link).
    """
    robot = model.robot
    cameras: list[str] = []
    if model.config.camera is not None:
        cameras.append(model.config.camera.frame)
    for eff in model.effects:
        frame = getattr(eff, "frame", None)
        if eff.name == "camera_extrinsics" and frame and frame not in cameras:
            cameras.append(frame)
    static = model.with_effects([e for e in model.effects if e.name in STATIC_EFFECTS])
    zeros = {n: 0.0 for n in model.joint_names}
    frames, notes = [], []
    for cam in cameras:
        parent = camera_mount_parent(robot, cam)
        child = f"{cam}{suffix}"
        collision = urdf_collision(robot, child)
        if parent is None:
            notes.append(f"camera frame '{cam}' is not on a fixed mount (root link, or it hangs on a movable "
                         "joint): no static frame")
        elif collision:
            notes.append(f"parameter tf_camera_suffix = '{suffix}': calibrated camera frame {collision}; "
                         f"/tf_static for camera '{cam}' is off")
        else:
            frames.append(TfFrame(parent, child, np.asarray(static.fk_mean(zeros, parent, cam))))
    return frames, notes


# -------------------------------------------------------------------------- joints


class JointFrames:
    """robot_state_publisher's transforms from a PPOE model (module docstring).

    Parameters
    ----------
    model : PPOEModel
        Its URDF joints and its effects: static ones are folded into the joint origins once, the
        others are evaluated at every joint state on the latest value of every joint.
    policy : the stamp rule of the joint states (:class:`~ppoe_core.model.stamp_policy.StampResetPolicy`)
    """

    def __init__(self, model: Any, policy: StampResetPolicy | None = None) -> None:
        robot = self.robot = model.robot
        self.tree = KinematicTree(robot)
        self.independent = list(robot.independent_joints)
        zeros = self.tree.joint_values({n: np.zeros(()) for n in self.independent})
        self.dynamic = [e for e in model.effects if e.name not in STATIC_EFFECTS]
        dq0, dxi0 = sum_effect_corrections([e for e in model.effects if e.name in STATIC_EFFECTS], zeros, {})
        self.dq0 = {k: float(np.asarray(v)) for k, v in dq0.items()}
        self.dxi0 = {k: np.asarray(v, dtype=float).reshape(6) for k, v in dxi0.items()}
        dq_dyn, dxi_dyn = sum_effect_corrections(self.dynamic, zeros, {})
        #: joints whose transform a configuration-dependent effect changes: published only once the whole
        #: configuration is known, at every joint state
        self.dynamic_joints = set(dq_dyn) | set(dxi_dyn)
        self.movable = [j.name for j in robot.joints.values() if j.movable]
        # independent joint -> the movable joints its value moves (itself and its mimic followers)
        self._driven: dict[str, list[str]] = {n: [] for n in self.independent}
        for jn in self.movable:
            root = robot.joints[jn].mimic_root
            self._driven.setdefault(root[0] if root is not None else jn, []).append(jn)
        #: the latest value of every joint (no age limit: TF shows the last known configuration)
        self.history = JointHistory(self.independent, needed=[], policy=policy)
        self.latest: dict[str, float] = {}
        self._origins: dict[str, np.ndarray] = {}

    def _origin(self, jn: str, dxi: Mapping[str, Any]) -> np.ndarray:
        """``origin Exp(dxi)`` of joint ``jn`` (the static effects' ``dxi`` and the configuration-dependent one)."""
        if jn not in dxi and jn in self._origins:
            return self._origins[jn]
        T = self.robot.joints[jn].origin @ lie.exp(self.dxi0.get(jn, np.zeros(6)) + np.asarray(dxi.get(
            jn, np.zeros(6)), dtype=float))
        if jn not in dxi:
            self._origins[jn] = T
        return T

    def static_frames(self) -> list[TfFrame]:
        """Every fixed joint that no configuration-dependent effect touches: child in parent (``/tf_static``)."""
        return [TfFrame(j.parent, j.child, self._origin(j.name, {}))
                for j in self.robot.joints.values() if not j.movable and j.name not in self.dynamic_joints]

    def frames(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int = 0) -> list[TfFrame]:
        """The transforms a joint state changes: the movable joints it carries values for (and their mimic
        followers), and, once every joint has a value, every joint a configuration-dependent effect moves.

        The joint state is merged per joint by :attr:`history` (a refused one raises as there); joints the model
        does not know and non-finite values are ignored (the pose path reports them).
        """
        h = self.history
        h.update(names, positions, stamp_ns)
        pos = np.asarray(positions, dtype=float)
        moved = {jn for n, v in zip(names, pos) if n in self._driven and np.isfinite(v) for jn in self._driven[n]}
        self.latest = {n: float(v) for n, v, st in zip(self.independent, h.values, h.stamps) if st != NEVER_NS}
        dq: dict[str, Any] = {}
        dxi: dict[str, Any] = {}
        complete = len(self.latest) == len(self.independent)
        if self.dynamic and complete:
            dq, dxi = sum_effect_corrections(self.dynamic, self.tree.joint_values(self.latest), {})
            moved |= self.dynamic_joints
        elif self.dynamic:
            moved -= self.dynamic_joints
        dq_all = {k: self.dq0.get(k, 0.0) + float(np.asarray(dq.get(k, 0.0))) for k in set(self.dq0) | set(dq)}
        rows = [jn for jn in self.movable if jn in moved and (self.robot.joints[jn].mimic_root or (jn,))[0]
                in self.latest]
        values = self.tree.joint_values(self.latest, dq_all, rows)
        out = [TfFrame(self.robot.joints[jn].parent, self.robot.joints[jn].child,
                       self._origin(jn, dxi) @ lie.exp(self.robot.joints[jn].twist * values[jn])) for jn in rows]
        if dxi and complete:
            out += [TfFrame(self.robot.joints[jn].parent, self.robot.joints[jn].child, self._origin(jn, dxi))
                    for jn in sorted(self.dynamic_joints) if not self.robot.joints[jn].movable]
        return out
