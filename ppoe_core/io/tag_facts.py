"""Which link carries each tag a bag shows, for ``ppoe init`` (:func:`tag_guesses`).

Sightings of each tag id -- its centre and edge length in undistorted normalised image coordinates -- come from
``/tag_bearing/observations`` or, without them, from a detection pass over :data:`TAG_IMAGES` images (pixels
undistorted with ``camera_info``).  For every link that moves, the tag centre's position ``x`` in that link
follows from the pinhole constraint ``(R_i x + t_i)_{x,y} = n_i (R_i x + t_i)_z`` (``T_camera_link`` of each
sighting from the forward kinematics at its stamp), linear in ``x``; the link with the smallest reprojection
residual wins (among equal ones one named like a tag, then the deepest).  The tag's size is its edge length times
the fitted depth.  Its orientation on the link cannot be told from centres alone: the user sets it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.errors import BagError
from ppoe_core.io.bag_joints import joints_at, moved_joints
from ppoe_core.robot.model_init import tie_key
from ppoe_core.robot.robot_model import Robot
from ppoe_core.robot.tree import KinematicTree

__all__ = ["TAG_IMAGES", "TagSightings", "TagGuess", "tag_sightings", "tag_guesses", "fit_tag_point"]

#: images decoded when the bag has no tag observations (spread over the bag): a few views of each tag at
#: different poses, few enough to take a few seconds
TAG_IMAGES = 24
#: sightings needed to fit a point (3 unknowns, 2 equations per sighting, and some redundancy)
MIN_SIGHTINGS = 3
#: links within this factor of the best residual explain the sightings equally (a tag link and its parent)
TIE_RATIO = 1.05
#: among equal links one named like a tag is preferred (:func:`ppoe_core.robot.model_init.tie_key`)
TAG_NAME = re.compile(r"tag|marker|aruco|april|fiducial|^mk\d", re.IGNORECASE)


@dataclass
class TagSightings:
    """One tag id: ``stamps`` (N,), ``centre`` (N, 2) and mean ``edge`` (N,, NaN where the corners are not given)
    in normalised image coordinates (``x = X/Z``), ``frame``: the optical frame of the camera that saw it most."""

    stamps: np.ndarray
    centre: np.ndarray
    edge: np.ndarray
    frame: str


@dataclass
class TagGuess:
    """Where a tag sits: ``link`` (None if no link explains it), centre ``xyz`` in the link [m], edge ``size`` [m]
    (None if unknown), ``how`` it was found."""

    link: str | None
    xyz: tuple[float, float, float]
    size: float | None
    how: str


def _from_observations(obs: Any) -> dict[int, TagSightings]:
    out: dict[tuple[int, str], list[tuple[float, np.ndarray, float]]] = {}
    for m in range(len(obs)):
        pts = obs.message(m)
        for tag in np.unique(pts["ids"]).astype(int):
            sel = pts["ids"] == tag
            corners = {int(c): xy for c, xy in zip(pts["corners"][sel], pts["xy"][sel])}
            full = all(c in corners for c in (1, 2, 3, 4))
            if 0 not in corners and not full:
                continue
            quad = np.array([corners.get(c, np.full(2, np.nan)) for c in (1, 2, 3, 4)])
            centre = corners[0] if 0 in corners else np.mean(quad, axis=0)
            edge = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))   # NaN without corners
            out.setdefault((int(tag), obs.frame_ids[m]), []).append((float(obs.stamps[m]), centre, edge))
    best: dict[int, TagSightings] = {}   # per tag the camera that saw it most often
    for (tag, frame), rows in sorted(out.items(), key=lambda kv: -len(kv[1])):
        if tag not in best:
            best[tag] = TagSightings(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                                     np.array([r[2] for r in rows]), frame)
    return best


def _from_images(data: Any) -> dict[int, TagSightings]:
    import cv2

    from ppoe_core.sensing.tags import detect_tags

    imgs, info = data.images, data.camera_info
    if not len(info):
        return {}
    K, D, frame = info.K[0], info.D[0], info.frame_ids[0]
    rows: dict[int, list[tuple[float, np.ndarray, float]]] = {}
    for i in np.unique(np.linspace(0, len(imgs) - 1, min(TAG_IMAGES, len(imgs))).round().astype(int)):
        try:
            found = detect_tags(imgs.decode(int(i), grey=True))
        except BagError:
            continue
        for d in found:
            px = np.vstack([d.centre[None, :], d.corners]).astype(np.float64).reshape(-1, 1, 2)
            n = cv2.undistortPoints(px, K, D).reshape(-1, 2)
            edge = float(np.mean(np.linalg.norm(n[1:] - np.roll(n[1:], 1, axis=0), axis=1)))
            rows.setdefault(int(d.id), []).append((float(imgs.stamps[i]), n[0], edge))
    return {t: TagSightings(np.array([r[0] for r in v]), np.array([r[1] for r in v]), np.array([r[2] for r in v]),
                            frame) for t, v in rows.items()}


def tag_sightings(data: Any) -> tuple[dict[int, TagSightings], str]:
    """Sightings per tag id and where they came from (observations, or a detection pass over images)."""
    if len(data.tag_observations):
        return _from_observations(data.tag_observations), "from /tag_bearing/observations"
    if not len(data.images):
        return {}, ""
    n = min(TAG_IMAGES, len(data.images))
    return _from_images(data), f"tag36h11 detections in {n} of {len(data.images)} images of {data.images.topic}"


def fit_tag_point(T_cam_link: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Point ``x`` in the link whose projection is ``centre`` (N, 2) under ``T_cam_link`` (N, 4, 4); returns ``x``,
    the RMS reprojection residual (normalised units; inf if a sighting falls behind the camera) and the depths."""
    R, t = T_cam_link[:, :3, :3], T_cam_link[:, :3, 3]
    A = np.concatenate([R[:, 0] - centre[:, :1] * R[:, 2], R[:, 1] - centre[:, 1:] * R[:, 2]])
    b = np.concatenate([centre[:, 0] * t[:, 2] - t[:, 0], centre[:, 1] * t[:, 2] - t[:, 1]])
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    p = R @ x + t
    if np.any(p[:, 2] <= 0):
        return x, float("inf"), p[:, 2]
    res = p[:, :2] / p[:, 2:] - centre
    return x, float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))), p[:, 2]


def tag_guesses(data: Any, robot: Robot, sightings: dict[int, TagSightings]) -> dict[int, TagGuess]:
    """Tag id -> the link whose motion explains its sightings, the centre there and the size."""
    tree = KinematicTree(robot)
    links = [ln for ln in robot.links if any(robot.joints[j].movable for j in robot.path_from_root(ln))]
    out = {}
    for tag, s in sorted(sightings.items()):
        if s.frame not in robot.links or len(s.stamps) < MIN_SIGHTINGS:
            why = (f"camera frame {s.frame} not in the URDF" if s.frame not in robot.links
                   else f"seen {len(s.stamps)} times")
            out[tag] = TagGuess(None, (0.0, 0.0, 0.0), None, why)
            continue
        q = joints_at(data, robot, s.stamps)
        poses = tree.link_poses(q, links=[*links, s.frame])
        T_cam_root = np.linalg.inv(np.asarray(poses[s.frame]))
        fits = {ln: fit_tag_point(T_cam_root @ np.asarray(poses[ln]), s.centre) for ln in links if ln != s.frame}
        best = min(f[1] for f in fits.values())
        if not np.isfinite(best):
            out[tag] = TagGuess(None, (0.0, 0.0, 0.0), None, "no link puts it in front of the camera")
            continue
        tied = [ln for ln, f in fits.items() if f[1] <= best * TIE_RATIO + 1e-12]
        moved = moved_joints(q)
        link = max(tied, key=lambda ln: tie_key(robot, ln, TAG_NAME, moved))
        x, rms, depth = fits[link]
        others = sorted((f[1], ln) for ln, f in fits.items() if ln not in tied)
        how = (f"{len(s.stamps)} sightings fit to {rms * 1e3:.2f} mrad RMS"
               + (f"; next: {others[0][1]} {others[0][0] * 1e3:.1f} mrad" if others else ""))
        sizes = s.edge * depth
        size = round(float(np.median(sizes[np.isfinite(sizes)])), 3) if np.isfinite(sizes).any() else None
        out[tag] = TagGuess(link, tuple(round(float(v), 4) + 0.0 for v in x), size, how)  # type: ignore[arg-type]
    return out
