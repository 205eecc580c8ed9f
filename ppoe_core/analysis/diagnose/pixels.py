"""Tag-pixel measurement model of the pixel stage: predicted pixels, chain Jacobians, PPOE pixel covariance,
candidates."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.candidates import row_link_poses
from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.estimation.camera import project_points_jacobian
from ppoe_core.model.effects import Effect, make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

# =============================================================================
# Marker pixels: reprojection residuals and camera_extrinsics
# =============================================================================


@dataclass
class PixelObs:
    """Marker-centre pixels: one row per (pose, marker, camera) observation.

    Attributes
    ----------
    q : dict joint -> ndarray, shape (M,)
        Joint values of each observation [rad, m].
    link : str
        Link that carries the markers (e.g. ``EE1`` or ``tool0``); with ``links`` set, the first one.
    point : ndarray, shape (M, 3)
        Marker origin (the point whose image is measured) in its link's coordinates [m].
    camera : ndarray, shape (M,), int
        Index into ``cameras``.
    cameras : list[str]
        Camera optical frames (URDF links; z forward, x right, y down).
    K : list of ndarray (3, 3); D : list of ndarray (5,)
        Intrinsics [px] and plumb_bob distortion of each camera.
    uv : ndarray, shape (M, 2)
        Measured raw (distorted) pixels.
    pose : ndarray, shape (M,), int
        Robot pose index of each observation (cross-validation folds keep a pose together).
    sigma_px : float
        Pixel noise, 1-sigma per axis [px]: residuals are whitened with it.
    name : str
        Source (file or bag), used in messages.
    context : dict
        Effect context per observation (``motion_sign``: joint -> (M,), ``time`` (M,),
        ``joint_velocity``: joint -> (M,)), as in :class:`Stops`.
    links : ndarray, shape (M,), of str, or None
        Tags on several links: the link of each row's point (None: every row on ``link``).
    """

    q: dict[str, np.ndarray]
    link: str
    point: np.ndarray
    camera: np.ndarray
    cameras: list[str]
    K: list[np.ndarray]
    D: list[np.ndarray]
    uv: np.ndarray
    pose: np.ndarray
    sigma_px: float = 1.0
    name: str = ""
    context: dict[str, Any] = field(default_factory=dict)
    links: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def row_links(self) -> np.ndarray:
        """The tag link of each row, (M,) of str."""
        return self.links if self.links is not None else np.full(len(self), self.link, dtype=object)

    def tag_links(self) -> list[str]:
        """The tag links, in first-seen order (one unless ``links`` is set)."""
        return list(dict.fromkeys(self.row_links().tolist())) if self.links is not None else [self.link]

    def subset(self, rows: np.ndarray) -> PixelObs:
        """The observations ``rows`` (index or boolean array)."""
        return PixelObs(
            q={k: v[rows] for k, v in self.q.items()},
            link=self.link,
            point=self.point[rows],
            camera=self.camera[rows],
            cameras=self.cameras,
            K=self.K,
            D=self.D,
            uv=self.uv[rows],
            pose=self.pose[rows],
            sigma_px=self.sigma_px,
            name=self.name,
            context=_map_ctx(lambda v: v[rows], [self.context]),
            links=None if self.links is None else self.links[rows],
        )


def _map_ctx(fn: Any, ctxs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Apply ``fn`` to the per-observation arrays of one or several contexts (keys of the first;
    nested joint dictionaries kept)."""
    out: dict[str, Any] = {}
    for k, v in ctxs[0].items():
        if isinstance(v, Mapping):
            out[k] = {j: fn(*[c[k][j] for c in ctxs]) for j in v if all(j in c.get(k, {}) for c in ctxs)}
        elif all(k in c for c in ctxs):
            out[k] = fn(*[c[k] for c in ctxs])
    return out


def _camera_points(
    tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect]
) -> tuple[np.ndarray, dict, dict, dict]:
    """Marker points in their camera's optical frame, shape (M, 3) [m], with the chain used."""
    dq, dxi = sum_effect_corrections(list(effects), obs.q, obs.context)
    links = obs.tag_links()
    poses = tree.link_poses(obs.q, dq, dxi, links=[*links, *obs.cameras])
    T_root_tag = tag_link_poses(obs, poses)
    p_root = np.einsum("mij,mj->mi", T_root_tag[:, :3, :3], obs.point) + T_root_tag[:, :3, 3]
    P = np.empty_like(p_root)  # filled per camera
    for c, frame in enumerate(obs.cameras):
        m = obs.camera == c
        T = poses[frame][m]
        P[m] = np.einsum("mji,mj->mi", T[:, :3, :3], p_root[m] - T[:, :3, 3])
    return P, poses, dq, dxi


def tag_link_poses(obs: PixelObs, poses: Mapping[str, np.ndarray]) -> np.ndarray:
    """``T_root_link`` of each row's tag link, (M, 4, 4), from :meth:`KinematicTree.link_poses` output."""
    return row_link_poses(poses, obs.link, obs.links, len(obs))


def _tag_frame_jacobians(tree: KinematicTree, obs: PixelObs, poses: Mapping[str, np.ndarray], dq: Mapping,
                         dxi: Mapping) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """:meth:`KinematicTree.frame_jacobian` of each row's tag link ((M, 6), (M, 6, 6); zero for joints off
    that link's path)."""
    if obs.links is None:
        return tree.frame_jacobian(obs.q, obs.link, poses, dq, dxi)
    rows, n = obs.row_links(), len(obs)
    Jq: dict[str, np.ndarray] = {}
    Jx: dict[str, np.ndarray] = {}
    for ln in obs.tag_links():
        m = rows == ln
        jq, jx = tree.frame_jacobian(obs.q, ln, poses, dq, dxi)
        for k, v in jq.items():
            Jq[k] = Jq.get(k, np.zeros((n, 6))) + np.where(m[:, None], np.broadcast_to(v, (n, 6)), 0.0)
        for k, v in jx.items():
            Jx[k] = Jx.get(k, np.zeros((n, 6, 6))) + np.where(m[:, None, None], np.broadcast_to(v, (n, 6, 6)), 0.0)
    return Jq, Jx


def predict_pixels(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> np.ndarray:
    """Predicted raw pixels (M, 2): marker origin on ``obs.link`` -> root -> camera optical frame,
    projected with the intrinsics and plumb_bob distortion (:func:`ppoe_core.estimation.camera.project_points`).

    Raises
    ------
    MeasurementError
        A marker is behind its camera (names the source and the observation row).
    """
    from ppoe_core.estimation.camera import project_points

    P = _camera_points(tree, obs, effects)[0]
    _check_in_front(obs, P)
    uv = np.empty((len(obs), 2))
    for c in range(len(obs.cameras)):
        m = obs.camera == c
        uv[m] = project_points(P[m], obs.K[c], obs.D[c])
    return uv


def _check_in_front(obs: PixelObs, P: np.ndarray) -> None:
    """MeasurementError naming the source and row if a marker point ``P`` (M, 3) is behind its camera."""
    bad = P[:, 2] <= 1e-6
    if np.any(bad):
        raise MeasurementError(
            f"{obs.name}: observation {int(np.flatnonzero(bad)[0])}: marker is behind "
            f"camera '{obs.cameras[int(obs.camera[bad][0])]}' (z = {P[bad][0, 2]:.3g} m)"
        )


def pixel_chain_jacobians(
    tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Analytic derivatives of the predicted pixels w.r.t. the eq. 16 insertions, on the chain
    corrected by ``effects``.

    With the right perturbations ``xi_cam`` of ``T_root_cam`` and ``xi_l`` of ``T_root_link``
    (:meth:`KinematicTree.frame_jacobian`),
    ``dP_cam = R_cam^T R_l [I, -[p]x] xi_l + [-I, [P_cam]x] xi_cam``, then the plumb_bob
    projection Jacobian ``d uv / d P_cam``.

    Returns
    -------
    J_dq : dict joint -> ndarray (M, 2)
        ``d uv / d dq_j`` [px/rad or px/m].
    J_dxi : dict joint -> ndarray (M, 2, 6)
        ``d uv / d dxi_j`` (tangent right after joint ``j``'s origin, ``[rho; theta]``).
    """
    return predict_pixels_with_jacobians(tree, obs, effects)[1:]


def predict_pixels_with_jacobians(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()
                                  ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """:func:`predict_pixels` and :func:`pixel_chain_jacobians` from one chain evaluation: ``(uv (M, 2), J_dq,
    J_dxi)``."""
    P, poses, dq, dxi = _camera_points(tree, obs, effects)
    _check_in_front(obs, P)
    n = len(obs)
    uv = np.empty((n, 2))
    Jq_l, Jx_l = _tag_frame_jacobians(tree, obs, poses, dq, dxi)
    R_l = tag_link_poses(obs, poses)[:, :3, :3]
    B_l = np.concatenate([R_l, -R_l @ lie.hat3(obs.point)], axis=-1)  # (M, 3, 6): d p_root / d xi_l
    A = np.zeros((n, 3, 3))  # d P_cam / d p_root = R_cam^T
    B_c = np.zeros((n, 3, 6))  # d P_cam / d xi_cam
    Jproj = np.zeros((n, 2, 3))
    cam_jac = []
    for c, frame in enumerate(obs.cameras):
        m = obs.camera == c
        if not np.any(m):
            continue
        A[m] = np.swapaxes(poses[frame][m][:, :3, :3], -1, -2)
        B_c[m] = np.concatenate([-np.broadcast_to(np.eye(3), (int(m.sum()), 3, 3)), lie.hat3(P[m])], axis=-1)
        uv[m], Jproj[m] = project_points_jacobian(P[m], obs.K[c], obs.D[c])
        cam_jac.append((m, tree.frame_jacobian(obs.q, frame, poses, dq, dxi)))
    G_l = Jproj @ A @ B_l  # (M, 2, 6): d uv / d xi_l
    J_dq: dict[str, np.ndarray] = {k: np.einsum("mij,mj->mi", G_l, v) for k, v in Jq_l.items()}
    J_dxi: dict[str, np.ndarray] = {k: G_l @ v for k, v in Jx_l.items()}
    G_c = Jproj @ B_c
    for m, (Jq_c, Jx_c) in cam_jac:
        for k, v in Jq_c.items():  # rows of this camera only
            J_dq[k] = J_dq[k].copy() if k in J_dq else np.zeros((n, 2))
            J_dq[k][m] += np.einsum("mij,mj->mi", G_c[m], v[m])
        for k, v in Jx_c.items():
            J_dxi[k] = J_dxi[k].copy() if k in J_dxi else np.zeros((n, 2, 6))
            J_dxi[k][m] += G_c[m] @ v[m]
    return uv, J_dq, J_dxi


def pixel_jacobian(tree: KinematicTree, obs: PixelObs, effect: Effect, effects: Sequence[Effect] = ()) -> np.ndarray:
    """Analytic derivative (M, 2, P) of the predicted pixels w.r.t. ``effect``'s parameters,
    evaluated on the chain corrected by ``effects``: :func:`pixel_chain_jacobians` times
    :meth:`Effect.basis` (evaluated on the nominal chain)."""
    Jq, Jx = pixel_chain_jacobians(tree, obs, effects)
    return effect_jacobian(Jq, Jx, effect, obs.q, obs.context, tree.link_poses(obs.q), (len(obs), 2))


def effect_jacobian(Jq: Mapping[str, np.ndarray], Jx: Mapping[str, np.ndarray], effect: Effect,
                    q: Mapping[str, np.ndarray], context: Mapping[str, Any], nominal: Mapping[str, np.ndarray],
                    shape: tuple[int, int]) -> np.ndarray:
    """Chain Jacobians (``Jq``: joint -> (M, d), ``Jx``: joint -> (M, d, 6)) times ``effect``'s basis
    (:meth:`Effect.basis` on the ``nominal`` link poses): the derivative (M, d, P) of a measurement of
    shape ``shape`` = (M, d) w.r.t. the effect's parameters."""
    Bq, Bx = effect.basis(q, context, nominal)
    out = np.zeros((*shape, effect.n_params))
    for k, b in Bq.items():
        if k in Jq:
            out = out + Jq[k][:, :, None] * b[:, None, :]
    for k, b in Bx.items():
        if k in Jx:
            out = out + Jx[k] @ b
    return out


def pixel_covariance(
    tree: KinematicTree,
    obs: PixelObs,
    effects: Sequence[Effect] = (),
    pert: Mapping[str, np.ndarray] | None = None,
    jnoise: Mapping[str, float] | None = None,
) -> np.ndarray:
    """Expected covariance (M, 2, 2) of each pixel residual [px^2], image axes: the first-order
    PPOE covariance (paper eq. 18 to first order: ``pert`` = 6x6 covariances of the insertions,
    tangent right after each joint's origin; ``jnoise`` = joint 1-sigma [rad, m]) propagated
    through :func:`pixel_chain_jacobians`, plus ``obs.sigma_px^2 I``."""
    C = np.broadcast_to(float(obs.sigma_px) ** 2 * np.eye(2), (len(obs), 2, 2)).copy()
    if pert or jnoise:
        Jq, Jx = pixel_chain_jacobians(tree, obs, effects)
        for jn, S in (pert or {}).items():
            if jn in Jx:
                C += Jx[jn] @ np.asarray(S, float) @ np.swapaxes(Jx[jn], -1, -2)
        for jn, sg in (jnoise or {}).items():
            if jn in Jq:
                C += float(sg) ** 2 * Jq[jn][:, :, None] * Jq[jn][:, None, :]
    return C


def camera_mount_joint(robot: Robot, frame: str) -> str:
    """The fixed joint a ``camera_extrinsics`` correction of camera ``frame`` sits at: the first
    fixed joint after the last movable joint on the path from the root to ``frame``."""
    if frame not in robot.links:
        raise ModelConfigError(f"camera frame '{frame}' is not a link of URDF {robot.source}")
    path = robot.path_from_root(frame)
    if not path:
        raise ModelConfigError(f"camera frame '{frame}' is the root link of URDF {robot.source}")
    k = len(path)
    while k > 0 and not robot.joints[path[k - 1]].movable:
        k -= 1
    if k == len(path):
        raise ModelConfigError(f"camera frame '{frame}' hangs on movable joint '{path[-1]}' (URDF {robot.source})")
    return path[k]


def pixel_candidates(robot: Robot, obs: PixelObs) -> list[Effect]:
    """Candidate effects of the pixel residual: ``camera_extrinsics`` (6-DoF) at the mount joint
    of every camera that has observations (:func:`camera_mount_joint`), and a ``time_offset`` of every
    camera that saw the robot move (joint speed above 1 mrad/s at some of its images: motion makes a
    stamp offset visible; context ``sensor`` gives each row's camera)."""
    tree = KinematicTree(robot)
    out: list[Effect] = []
    vel = obs.context.get("joint_velocity") or {}
    speed = np.max(np.abs(np.stack(list(vel.values()))), axis=0) if vel else np.zeros(len(obs))
    for c, frame in enumerate(obs.cameras):
        if np.any(obs.camera == c):
            out.append(make_effect("camera_extrinsics", camera_mount_joint(robot, frame), tree))
            if "sensor" in obs.context and np.any(speed[obs.camera == c] > 1e-3):
                out.append(make_effect("time_offset", frame, tree))
    return out


def pixel_stats(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> dict[str, dict[str, float]]:
    """Per camera frame: ``n``, ``rms``, ``median`` and ``max`` of the 2D reprojection error [px]
    (norm of measured minus predicted pixel, every observation counted)."""
    e = np.linalg.norm(obs.uv - predict_pixels(tree, obs, effects), axis=1)
    return {
        f: {
            "n": int(np.sum(obs.camera == c)),
            "rms": float(np.sqrt(np.mean(e[obs.camera == c] ** 2))),
            "median": float(np.median(e[obs.camera == c])),
            "max": float(np.max(e[obs.camera == c])),
        }
        for c, f in enumerate(obs.cameras)
        if np.any(obs.camera == c)
    }


def pixel_rms(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> dict[str, float]:
    """RMS of the 2D reprojection error [px] per camera frame (cameras without rows omitted)."""
    e = obs.uv - predict_pixels(tree, obs, effects)
    return {
        f: float(np.sqrt(np.mean(np.sum(e[obs.camera == c] ** 2, axis=1))))
        for c, f in enumerate(obs.cameras)
        if np.any(obs.camera == c)
    }
