"""Tag pixels: the observations (:class:`PixelObs`) and their prediction through link -> root -> camera -> image.

A tag point on its link, ``p_link = T_link_tag Exp(delta) t`` (``delta`` the tag's ``tag_offset``, ``t`` the point
in the tag frame; or the given link point when the tag is not known), goes to the root on the chain corrected by
the effects (eq. 16 hooks), into the camera optical frame, and through the camera's ``camera_info`` corrected by its
``camera_intrinsics`` (pinhole + plumb_bob, :mod:`ppoe_core.estimation.camera`).  :func:`project` gives the pixels
and, on request, every derivative a residual block needs: w.r.t. the eq. 16 insertions of every joint (through the
tag link's and the camera's frame Jacobians, ``dP_cam = R_cam^T R_l [I, -[p]x] xi_l + [-I, [P_cam]x] xi_cam``),
w.r.t. the intrinsics (:mod:`ppoe_core.estimation.camera_intrinsics`) and w.r.t. the tag pose.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.candidates import row_link_poses
from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.estimation.camera_intrinsics import project_with_intrinsics_jacobian
from ppoe_core.model import tf_frames
from ppoe_core.model.effects import Effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["PixelObs", "Projection", "project", "predict_pixels", "pixel_rms", "pixel_stats", "camera_mount_joint",
           "concat_pixel_obs", "map_context", "tag_link_poses"]


@dataclass
class PixelObs:
    """Tag-point pixels: one row per (pose, point, camera) observation.

    Attributes
    ----------
    q : dict joint -> ndarray (M,)
        Joint values of each observation [rad, m].
    link : str
        Link that carries the points; with ``links`` set, the first one.
    point : ndarray (M, 3)
        The observed point in its link's coordinates [m] (at the nominal tag pose).
    camera : ndarray (M,) int
        Index into ``cameras``.
    cameras : list of str
        Camera optical frames (URDF links; z forward, x right, y down).
    K, D : lists of ndarray (3, 3) / (5,)
        Intrinsics [px] and plumb_bob distortion of each camera (its ``camera_info``).
    uv : ndarray (M, 2)
        Measured raw (distorted) pixels.
    pose : ndarray (M,) int
        Image of each observation (the points of one image share it).
    sigma_px : float
        Pixel noise, 1-sigma per axis [px] (declared).
    name : str
        Source (file or bag), for messages.
    context : dict
        Effect context per observation (``motion_sign``, ``time``, ``joint_velocity``, ``sensor``).
    links : ndarray (M,) of str or None
        Points on several links: the link of each row (None: every row on ``link``).
    tag : ndarray (M,) int or None
        Tag id of each row (-1: none); with ``tag_point`` and ``tag_poses`` the ``tag_offset`` effects apply.
    tag_point : ndarray (M, 3) or None
        The point in its tag's frame [m].
    tag_poses : dict id -> ndarray (4, 4)
        ``T_link_tag`` of each tag.
    group : ndarray (M,) int or None
        Source bag / file of each row (index into ``group_names``; None: one group, ``name``).
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
    tag: np.ndarray | None = None
    tag_point: np.ndarray | None = None
    tag_poses: dict[int, np.ndarray] = field(default_factory=dict)
    group: np.ndarray | None = None
    group_names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def row_groups(self) -> tuple[np.ndarray, list[str]]:
        """Group of each row (M,) and the group names."""
        if self.group is None:
            return np.zeros(len(self), dtype=int), [self.name]
        return np.asarray(self.group, dtype=int), list(self.group_names)

    def row_links(self) -> np.ndarray:
        """The link of each row, (M,) of str."""
        return self.links if self.links is not None else np.full(len(self), self.link, dtype=object)

    def tag_links(self) -> list[str]:
        """The point links, in first-seen order (one unless ``links`` is set)."""
        return list(dict.fromkeys(self.row_links().tolist())) if self.links is not None else [self.link]

    def subset(self, rows: np.ndarray) -> PixelObs:
        """The observations ``rows`` (index or boolean array)."""
        return PixelObs(
            q={k: v[rows] for k, v in self.q.items()}, link=self.link, point=self.point[rows],
            camera=self.camera[rows], cameras=self.cameras, K=self.K, D=self.D, uv=self.uv[rows],
            pose=self.pose[rows], sigma_px=self.sigma_px, name=self.name,
            context=map_context(lambda v: v[rows], [self.context]),
            links=None if self.links is None else self.links[rows],
            tag=None if self.tag is None else self.tag[rows],
            tag_point=None if self.tag_point is None else self.tag_point[rows], tag_poses=self.tag_poses,
            group=None if self.group is None else self.group[rows], group_names=self.group_names)


def map_context(fn: Callable[..., Any], ctxs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Apply ``fn`` to the per-observation arrays of one or several contexts (keys of the first; nested joint
    dictionaries kept)."""
    out: dict[str, Any] = {}
    for k, v in ctxs[0].items():
        if isinstance(v, Mapping):
            out[k] = {j: fn(*[c[k][j] for c in ctxs]) for j in v if all(j in c.get(k, {}) for c in ctxs)}
        elif all(k in c for c in ctxs):
            out[k] = fn(*[c[k] for c in ctxs])
    return out


def tag_link_poses(obs: PixelObs, poses: Mapping[str, np.ndarray]) -> np.ndarray:
    """``T_root_link`` of each row's link, (M, 4, 4), from :meth:`KinematicTree.link_poses` output."""
    return row_link_poses(poses, obs.link, obs.links, len(obs))


@dataclass
class Projection:
    """:func:`project` output: pixels (M, 2) and, with Jacobians, ``J_dq`` (joint -> (M, 2)), ``J_dxi`` (joint ->
    (M, 2, 6)), ``J_intrinsics`` (M, 2, 9) and ``J_point`` (M, 2, 3) (w.r.t. the point in its link)."""

    uv: np.ndarray
    J_dq: dict[str, np.ndarray] = field(default_factory=dict)
    J_dxi: dict[str, np.ndarray] = field(default_factory=dict)
    J_intrinsics: np.ndarray | None = None
    J_point: np.ndarray | None = None


def sensor_corrections(obs: PixelObs, effects: Sequence[Effect]) -> tuple[list[np.ndarray], list[np.ndarray],
                                                                         np.ndarray]:
    """The cameras' ``(K, D)`` corrected by their ``camera_intrinsics`` and the rows' link points moved by their
    tags' ``tag_offset`` (other effects ignored)."""
    K, D = [np.asarray(k, dtype=float) for k in obs.K], [np.asarray(d, dtype=float) for d in obs.D]
    point = obs.point
    for e in effects:
        if e.name == "camera_intrinsics" and e.location in obs.cameras:
            c = obs.cameras.index(e.location)
            K[c], D[c] = e.corrected(K[c], D[c])  # type: ignore[attr-defined]
        elif e.name == "tag_offset" and obs.tag is not None and obs.tag_point is not None:
            m = obs.tag == e.tag_id  # type: ignore[attr-defined]
            if m.any() and e.tag_id in obs.tag_poses:  # type: ignore[attr-defined]
                T = e.corrected(obs.tag_poses[e.tag_id])  # type: ignore[attr-defined]
                point = point.copy() if point is obs.point else point
                point[m] = obs.tag_point[m] @ T[:3, :3].T + T[:3, 3]
    return K, D, point


def project(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = (), jacobians: bool = False,
            corrections: tuple[dict, dict] | None = None) -> Projection:
    """Predicted raw pixels of ``obs`` with ``effects`` (chain and sensor effects), and their derivatives
    (module docstring) if ``jacobians``; ``corrections``: the chain effects' ``(dq, dxi)`` if the caller has them.

    Raises
    ------
    MeasurementError
        A point behind its camera (names the source and the row).
    """
    chain = [e for e in effects if not e.sensor]
    K, D, point = sensor_corrections(obs, effects)
    dq, dxi = corrections if corrections is not None else sum_effect_corrections(chain, obs.q, obs.context)
    links = obs.tag_links()
    poses = tree.link_poses(obs.q, dq, dxi, links=[*links, *obs.cameras])
    T_l = tag_link_poses(obs, poses)
    p_root = np.einsum("mij,mj->mi", T_l[:, :3, :3], point) + T_l[:, :3, 3]
    n = len(obs)
    P = np.empty((n, 3))
    R_cam = np.empty((n, 3, 3))
    for c, frame in enumerate(obs.cameras):
        m = obs.camera == c
        T = poses[frame][m]
        R_cam[m] = T[:, :3, :3]
        P[m] = np.einsum("mji,mj->mi", T[:, :3, :3], p_root[m] - T[:, :3, 3])
    bad = P[:, 2] <= 1e-6
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise MeasurementError(f"{obs.name}: observation {i}: point is behind camera "
                               f"'{obs.cameras[int(obs.camera[i])]}' (z = {P[i, 2]:.3g} m)")
    uv, Jproj, Jint = np.empty((n, 2)), np.empty((n, 2, 3)), np.empty((n, 2, 9))
    for c in range(len(obs.cameras)):
        m = obs.camera == c
        if m.any():
            uv[m], Jproj[m], Jint[m] = project_with_intrinsics_jacobian(P[m], K[c], D[c])
    if not jacobians:
        return Projection(uv)
    return _with_jacobians(tree, obs, poses, dq, dxi, point, P, R_cam, T_l, uv, Jproj, Jint)


def _with_jacobians(tree: KinematicTree, obs: PixelObs, poses: Mapping[str, np.ndarray], dq: Mapping, dxi: Mapping,
                    point: np.ndarray, P: np.ndarray, R_cam: np.ndarray, T_l: np.ndarray, uv: np.ndarray,
                    Jproj: np.ndarray, Jint: np.ndarray) -> Projection:
    """The derivatives of :func:`project` w.r.t. the eq. 16 insertions, the intrinsics and the link point."""
    n = len(obs)
    R_l = T_l[:, :3, :3]
    A = np.swapaxes(R_cam, -1, -2)  # d P_cam / d p_root
    J_point = Jproj @ A @ R_l
    G_l = J_point @ np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), -lie.hat3(point)], axis=-1)
    J_dq: dict[str, np.ndarray] = {}
    J_dxi: dict[str, np.ndarray] = {}
    rows = obs.row_links()
    for ln in obs.tag_links():
        m = rows == ln
        jq, jx = tree.frame_jacobian(obs.q, ln, poses, dq, dxi)
        for k, v in jq.items():
            J_dq.setdefault(k, np.zeros((n, 2)))[m] += np.einsum("mij,mj->mi", G_l[m], v[m])
        for k, v in jx.items():
            J_dxi.setdefault(k, np.zeros((n, 2, 6)))[m] += G_l[m] @ v[m]
    G_c = Jproj @ np.concatenate([-np.broadcast_to(np.eye(3), (n, 3, 3)), lie.hat3(P)], axis=-1)
    for c, frame in enumerate(obs.cameras):
        m = obs.camera == c
        if not m.any():
            continue
        jq, jx = tree.frame_jacobian(obs.q, frame, poses, dq, dxi)
        for k, v in jq.items():
            J_dq.setdefault(k, np.zeros((n, 2)))[m] += np.einsum("mij,mj->mi", G_c[m], v[m])
        for k, v in jx.items():
            J_dxi.setdefault(k, np.zeros((n, 2, 6)))[m] += G_c[m] @ v[m]
    return Projection(uv, J_dq, J_dxi, Jint, J_point)


def predict_pixels(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> np.ndarray:
    """Predicted raw pixels (M, 2) with ``effects`` (:func:`project`)."""
    return project(tree, obs, effects).uv


def pixel_stats(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> dict[str, dict[str, float]]:
    """Per camera frame: ``n``, ``rms``, ``median`` and ``max`` of the 2D reprojection error [px]."""
    e = np.linalg.norm(obs.uv - predict_pixels(tree, obs, effects), axis=1)
    return {f: {"n": int(np.sum(obs.camera == c)), "rms": float(np.sqrt(np.mean(e[obs.camera == c] ** 2))),
                "median": float(np.median(e[obs.camera == c])), "max": float(np.max(e[obs.camera == c]))}
            for c, f in enumerate(obs.cameras) if np.any(obs.camera == c)}


def pixel_rms(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> dict[str, float]:
    """RMS of the 2D reprojection error [px] per camera frame (cameras without rows omitted)."""
    return {f: v["rms"] for f, v in pixel_stats(tree, obs, effects).items()}


def camera_mount_joint(robot: Robot, frame: str) -> str:
    """The fixed joint a ``camera_extrinsics`` correction of camera ``frame`` sits at: the first fixed joint after
    the last movable joint on the path from the root to ``frame`` (:func:`ppoe_core.model.tf_frames.camera_mount_joint`,
    the one owner), with an error naming the frame where there is none.

    Raises
    ------
    ModelConfigError
        ``frame`` is not a link, is the root link, or hangs on a movable joint.
    """
    if frame not in robot.links:
        raise ModelConfigError(f"camera frame '{frame}' is not a link of URDF {robot.source}")
    path = robot.path_from_root(frame)
    if not path:
        raise ModelConfigError(f"camera frame '{frame}' is the root link of URDF {robot.source}")
    joint = tf_frames.camera_mount_joint(robot, frame)
    if joint is None:
        raise ModelConfigError(f"camera frame '{frame}' hangs on movable joint '{path[-1]}' (URDF {robot.source})")
    return joint


def concat_pixel_obs(parts: Sequence[PixelObs]) -> PixelObs:
    """Join :class:`PixelObs` of several sources (points on any links); images and cameras renumbered."""
    if not parts:
        raise MeasurementError("concat_pixel_obs: no pixel observations given")
    several = any(p.links is not None for p in parts) or len({p.link for p in parts}) > 1
    cams: list[str] = []
    K: list[np.ndarray] = []
    D: list[np.ndarray] = []
    for p in parts:
        for c, f in enumerate(p.cameras):
            if f not in cams:
                cams.append(f)
                K.append(p.K[c])
                D.append(p.D[c])
            elif not (np.allclose(K[cams.index(f)], p.K[c]) and np.allclose(D[cams.index(f)], p.D[c])):
                raise MeasurementError(f"{p.name}: camera '{f}' has other intrinsics than in {parts[0].name}")
    off, pose, groups = 0, [], []
    gnames: list[str] = []
    for p in parts:
        pose.append(p.pose + off)
        off += int(p.pose.max()) + 1 if len(p) else 0
        g, names_g = p.row_groups()
        groups.append(g + len(gnames))
        gnames.extend(names_g)
    names = sorted(set().union(*[p.q for p in parts]))  # a named order, not the strings' hashes
    tags = all(p.tag is not None for p in parts)
    return PixelObs(
        q={j: np.concatenate([p.q[j] for p in parts]) for j in names}, link=parts[0].link,
        links=np.concatenate([p.row_links() for p in parts]) if several else None,
        point=np.concatenate([p.point for p in parts]),
        camera=np.concatenate([[cams.index(p.cameras[c]) for c in p.camera] for p in parts]).astype(int),
        cameras=cams, K=K, D=D, uv=np.concatenate([p.uv for p in parts]), pose=np.concatenate(pose),
        sigma_px=parts[0].sigma_px, name="+".join(p.name for p in parts),
        context=map_context(lambda *v: np.concatenate(v), [p.context for p in parts]),
        tag=np.concatenate([p.tag for p in parts if p.tag is not None]) if tags else None,
        tag_point=np.concatenate([p.tag_point for p in parts if p.tag_point is not None]) if tags else None,
        tag_poses={k: v for p in parts for k, v in p.tag_poses.items()}, group=np.concatenate(groups),
        group_names=gnames)
