"""Tag pixels: reprojection residuals of tag points seen by cameras (:mod:`pixels`), no nuisance.

Row ``i``: measured minus predicted raw pixel (2, [px]).  Derivatives of the prediction: chain effects through the
tag link's and the camera's frame Jacobians times :meth:`Effect.basis`; ``camera_intrinsics`` of the row's camera
through the intrinsics Jacobian (:mod:`ppoe_core.estimation.camera_intrinsics`); ``tag_offset`` of the row's tag
through ``d uv / d p_link R_link_tag [I, -[t]x] J_r(delta)`` (right perturbation of the tag pose, ``t`` the point in
the tag frame).  Noise: ``sigma_px`` per axis plus the declared prior propagated to the pixels.  Candidates: every
observing camera's ``camera_extrinsics`` (at its mount joint) and ``camera_intrinsics`` (nested levels), a
``time_offset`` of every camera that saw the robot move, every known tag's ``tag_offset``, and the arm effects on
the tag links' chains.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock, chain_columns, prior_covariance
from ppoe_core.analysis.diagnose.block_tracker import configuration_columns, time_columns
from ppoe_core.analysis.diagnose.candidates import chain_candidates
from ppoe_core.analysis.diagnose.pixels import PixelObs, camera_mount_joint, project, sensor_corrections
from ppoe_core.model.effects import Effect, make_effect
from ppoe_core.model.effects_sensor import INTRINSIC_KEYS, tag_location
from ppoe_core.robot.tree import KinematicTree

__all__ = ["PixelBlock", "image_position_columns"]

#: joint speed [rad/s or m/s] above which a camera's images show a stamp offset (time_offset candidate)
MOVING = 1e-3


def image_position_columns(obs: PixelObs, uv: np.ndarray, K: Sequence[np.ndarray], degree: int = 3) -> np.ndarray:
    """Predictors of a residual that follows the image position (M, 2, m): per camera and pixel axis, the monomials
    of degree 1..``degree`` of the normalised *predicted* position ``uv`` (``((u - cx) / fx, (v - cy) / fy)``),
    times the focal length (a principal point, focal length or distortion error the model lacks).  Not the measured
    position: the residual is a linear function of it and the focal-length columns."""
    n = len(obs)
    cols = []
    for c in range(len(obs.cameras)):
        m = obs.camera == c
        if not m.any():
            continue
        Kc = np.asarray(K[c], dtype=float)
        x = (uv[:, 0] - Kc[0, 2]) / Kc[0, 0]
        y = (uv[:, 1] - Kc[1, 2]) / Kc[1, 1]
        for deg in range(1, degree + 1):
            for a in range(deg + 1):
                f = np.where(m, x ** (deg - a) * y ** a, 0.0)
                for axis in range(2):
                    col = np.zeros((n, 2))
                    col[:, axis] = f * Kc[axis, axis]
                    cols.append(col)
    return np.stack(cols, axis=-1) if cols else np.zeros((n, 2, 0))


class PixelBlock(ResidualBlock):
    """Tag pixels (module docstring)."""

    kind = "pixels"
    dim = 2
    nuisance_dim = 0
    unit = "px"

    def __init__(self, tree: KinematicTree, obs: PixelObs) -> None:
        self.obs = obs
        group, names = obs.row_groups()
        super().__init__(tree, obs.q, obs.context, np.full(len(obs), -1), [], group, names)
        self.dropped = 0

    def linearise(self, effects: Sequence[Effect], candidates: Sequence[Effect], pert: Mapping[str, np.ndarray],
                  jnoise: Mapping[str, float], chain: bool = False) -> Linearisation:
        obs, n = self.obs, len(self.obs)
        need = chain or bool(candidates) or bool(pert) or bool(jnoise)
        pr = project(self.tree, obs, effects, jacobians=need, corrections=self.corrections(effects))
        r = obs.uv - pr.uv
        J = [self._columns(c, pr, effects) for c in candidates]
        S = np.broadcast_to(float(obs.sigma_px) ** 2 * np.eye(2), (n, 2, 2)).copy()
        Q = prior_covariance(pr.J_dq, pr.J_dxi, pert, jnoise, (n, 2))
        return Linearisation(r, J, np.zeros((n, 2, 0)), S, Q, Jq=pr.J_dq)

    def _columns(self, c: Effect, pr, effects: Sequence[Effect]) -> np.ndarray:
        """Derivative (M, 2, P) of the predicted pixels w.r.t. candidate ``c``'s parameters."""
        obs, n = self.obs, len(self.obs)
        if c.name == "camera_intrinsics":
            out = np.zeros((n, 2, c.n_params))
            if c.location in obs.cameras:
                m = obs.camera == obs.cameras.index(c.location)
                idx = [INTRINSIC_KEYS.index(p) for p in c.param_names]
                out[m] = pr.J_intrinsics[m][:, :, idx]
            return out
        if c.name == "tag_offset":
            return self._tag_columns(c, pr, effects)
        return chain_columns(pr.J_dq, pr.J_dxi, self.basis(c), c.n_params, (n, 2))

    def _tag_columns(self, c: Effect, pr, effects: Sequence[Effect]) -> np.ndarray:
        obs, n = self.obs, len(self.obs)
        out = np.zeros((n, 2, c.n_params))
        tid = getattr(c, "tag_id", None)
        if obs.tag is None or obs.tag_point is None or tid not in obs.tag_poses:
            return out
        m = obs.tag == tid
        if not m.any():
            return out
        T = obs.tag_poses[tid]
        Jr = np.eye(6)
        for e in effects:
            if e.name == "tag_offset" and getattr(e, "tag_id", None) == tid:
                T = e.corrected(T)  # type: ignore[attr-defined]
                Jr = lie.right_jacobian(e.twist())  # type: ignore[attr-defined]
        t = obs.tag_point[m]
        B = T[:3, :3] @ np.concatenate([np.broadcast_to(np.eye(3), (t.shape[0], 3, 3)), -lie.hat3(t)], axis=-1) @ Jr
        full = pr.J_point[m] @ B  # (m, 2, 6)
        idx = [("x", "y", "z", "rx", "ry", "rz").index(p) for p in c.param_names]
        out[m] = full[:, :, idx]
        return out

    def candidates(self) -> list[Effect]:
        obs, tree, out = self.obs, self.tree, []
        vel = obs.context.get("joint_velocity") or {}
        speed = np.max(np.abs(np.stack(list(vel.values()))), axis=0) if vel else np.zeros(len(obs))
        for c, frame in enumerate(obs.cameras):
            if not np.any(obs.camera == c):
                continue
            out.append(make_effect("camera_extrinsics", camera_mount_joint(tree.robot, frame), tree))
            out.append(make_effect("camera_intrinsics", frame, tree))
            if "sensor" in obs.context and np.any(speed[obs.camera == c] > MOVING):
                out.append(make_effect("time_offset", frame, tree))
        if obs.tag is not None and obs.tag_point is not None:
            out.extend(make_effect("tag_offset", tag_location(t), tree) for t in sorted(set(obs.tag.tolist()))
                       if t in obs.tag_poses)
        joints = list(dict.fromkeys(j for ln in obs.tag_links() for j in tree.robot.path_from_root(ln)))
        return out + chain_candidates(tree, joints, obs.context, point=True)

    def chain_links(self) -> list[str]:
        return self.obs.tag_links()

    def camera_mounts(self) -> dict[str, str]:
        return {camera_mount_joint(self.tree.robot, f): f for f in self.obs.cameras}

    def camera_of_mount(self, joint: str) -> str | None:
        """The camera frame whose ``camera_extrinsics`` sits at ``joint``."""
        return next((f for f in self.obs.cameras if camera_mount_joint(self.tree.robot, f) == joint), None)

    def intrinsics_of(self, frame: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The given ``(K, D)`` of camera ``frame``."""
        if frame not in self.obs.cameras:
            return None
        c = self.obs.cameras.index(frame)
        return np.asarray(self.obs.K[c], dtype=float), np.asarray(self.obs.D[c], dtype=float)

    def structure_columns(self, lin: Linearisation) -> dict[str, np.ndarray]:
        K, _, _ = sensor_corrections(self.obs, [])
        return {**configuration_columns(self.tree, self.q, lin.Jq),
                "time": time_columns(self.context.get("time"), self.group, 2),
                "image position": image_position_columns(self.obs, self.obs.uv - lin.r, K)}

    def report_groups(self) -> dict[str, np.ndarray]:
        return {f: self.obs.camera == c for c, f in enumerate(self.obs.cameras)}
