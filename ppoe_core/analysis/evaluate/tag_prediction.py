"""Where ``ppoe evaluate`` looks for the tags of a bag's images: windows around the tags' corners predicted by the
forward kinematics of the joint state at each image (:func:`predicted_windows`), for
:func:`ppoe_core.sensing.tag_windows.detect_tags_in_windows` (the same detections, bit for bit, as on the whole
image for the tags inside the windows; the whole image where it cannot promise that).

A window is the predicted corners' bounding box plus :data:`WINDOW_MARGIN_PX` and :data:`WINDOW_SIGMAS` standard
deviations of the predicted pixels (from the PPOE covariance of the camera-to-tag chain): a tag the model places in
view facing the camera is looked for there; a window that misses a tag seen at less than 60 deg from its normal
sends the image to the full detection (more oblique ones are looked for but not required), and so does an image
without any window in it.  Only the model's
tags are predicted: a tag of another id outside every window is not seen (the fusion ignores such tags; it is
counted in ``unknown_tag_points`` only when it is seen).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ppoe_core.errors import PpoeError
from ppoe_core.estimation.camera import project_points
from ppoe_core.sensing.tag_windows import WINDOW_CLEARANCE, WINDOW_GROUP_REACH, TagWindow
from ppoe_core.sensing.tags import tag_points_local

__all__ = ["WINDOW_MARGIN_PX", "WINDOW_SIGMAS", "predicted_windows"]

#: fixed margin of a window around the predicted corners [px], beyond the clearance
#: :func:`~ppoe_core.sensing.tag_windows.detect_tags_in_windows` needs (14 px + 0.6 perimeters), for the prediction
WINDOW_MARGIN_PX = 10.0
#: standard deviations of the predicted corner pixels added to the margin (the model's own uncertainty)
WINDOW_SIGMAS = 3.0
#: a tag whose normal makes less than this cosine with the ray away from the camera is looked for (about 84 deg:
#: slightly past edge-on, for the prediction's own error); one facing further away is not looked for
_FACING_COS = 0.1
#: a tag seen at less than 60 deg from its normal is expected: a window that misses it sends the image to the full
#: detection; one seen more obliquely (OpenCV often misses such tags in the whole image too) is looked for in its
#: window but not required
_EXPECT_COS = -0.5
#: nearer than this [m] (any corner) the projection is not trusted: the image goes to the full detection
_MIN_DEPTH = 0.05
#: a point straight ahead, projected in place of those nearer than _MIN_DEPTH (their images are not used)
_AHEAD = np.array([0.0, 0.0, 1.0])


def predicted_windows(model: Any, frames: Sequence[str], stamps: np.ndarray,
                      camera: Callable[[int], tuple[np.ndarray, np.ndarray] | None], prior_stamps: np.ndarray,
                      Q: np.ndarray) -> list[list[TagWindow] | None]:
    """Per image, the windows of the model's tags predicted in view (None: no prediction, detect on the whole image).

    Parameters
    ----------
    model : PPOEModel
        With ``config.tags``.
    frames, stamps : (N,)
        Each image's camera frame (``header.frame_id``, the optical frame) and stamp [s].
    camera : callable
        Image index -> ``(K, D)`` of that image (None: no camera model).
    prior_stamps : (M,) and Q : (M, n)
        The joint states of the forward kinematics (stamp order, ``model.joint_names`` order); an image takes the
        latest at or before its stamp (the first one before any).

    Returns
    -------
    list of (list of TagWindow or None), one per image.
    """
    n = len(stamps)
    out: list[list[TagWindow] | None] = [None] * n
    if model.config.tags is None or n == 0 or len(prior_stamps) == 0:
        return out
    k = np.clip(np.searchsorted(prior_stamps, np.asarray(stamps, dtype=float), side="right") - 1, 0,
                len(prior_stamps) - 1)
    for frame in sorted(set(frames)):
        sel = np.flatnonzero(np.asarray(frames) == frame)
        maybe = [_tag_corners(model, frame, item, Q[k[sel]]) for item in model.config.tags.items]
        per_tag = [p for p in maybe if p is not None]
        if len(per_tag) < len(maybe):
            continue  # a frame the model cannot place (e.g. not a link of the URDF): whole images
        by_camera: dict[bytes, list[int]] = {}  # the images of one camera model are projected together
        cams = [camera(i) for i in sel.tolist()]
        for j, KD in enumerate(cams):
            if KD is not None:
                by_camera.setdefault(np.asarray(KD[0]).tobytes() + np.asarray(KD[1]).tobytes(), []).append(j)
        for js in by_camera.values():
            K, D = cams[js[0]]  # type: ignore[misc]  # (not None: js holds only images with a camera)
            P = np.stack([p[1][js] for p in per_tag])  # (tags, images, 4, 3)
            uv = project_points(np.where(P[..., 2:3] < _MIN_DEPTH, _AHEAD, P), K, D)  # (near points: not used)
            for g, j in enumerate(js):
                out[int(sel[j])] = _windows(per_tag, j, uv[:, g], float(max(K[0, 0], K[1, 1])))
    return out


def _tag_corners(model: Any, frame: str, item: Any, Qs: np.ndarray) -> tuple[int, np.ndarray, np.ndarray,
                                                                            np.ndarray] | None:
    """``(id, corners (m, 4, 3) in the camera frame, cos (m,) of the tag normal with the ray from the camera,
    sigma (m,) [m]: the corners' position uncertainty across the view)`` of one tag for the joint states ``Qs``;
    None if the model cannot compute it."""
    try:
        T_cam_link, cov = model.fk(Qs, frame, item.link, order=2)
    except PpoeError:
        return None
    T = T_cam_link @ item.T_link_tag
    P = np.einsum("mij,cj->mci", T[:, :3, :3], tag_points_local(item.size)[1:]) + T[:, None, :3, 3]
    cos = np.einsum("mi,mi->m", T[:, :3, 2], T[:, :3, 3]) / np.linalg.norm(T[:, :3, 3], axis=1)
    # the link's uncertainty (tangent space at T_cam_link, [rho; theta], link frame): its position across the view
    # (rho turned into the camera frame, x and y) and its rotation's reach at the tag's corners
    R = T_cam_link[:, :3, :3]
    cov_xy = np.einsum("mij,mjk,mlk->mil", R, cov[:, :3, :3], R)[:, :2, :2]
    lever = float(np.linalg.norm(item.T_link_tag[:3, 3])) + float(item.size)
    rot = np.einsum("mii->m", cov[:, 3:, 3:])
    sigma = np.sqrt(np.maximum(np.einsum("mii->m", cov_xy), 0.0)) + lever * np.sqrt(np.maximum(rot, 0.0))
    return int(item.id), P, cos, sigma


def _windows(per_tag: list[Any], j: int, uv_tags: np.ndarray, f: float) -> list[TagWindow] | None:
    """The windows of one image (row ``j`` of every tag's prediction, its corners' pixels ``uv_tags`` (tags, 4, 2),
    focal length ``f`` [px]); None where no projection can be trusted."""
    wins: list[TagWindow] = []
    for (tag_id, P, cos, sigma), uv in zip(per_tag, uv_tags):
        if cos[j] >= _FACING_COS:
            continue
        pts = P[j]
        if np.any(pts[:, 2] < _MIN_DEPTH):
            if np.all(pts[:, 2] < 0.0):
                continue  # wholly behind the camera
            return None
        if not np.all(np.isfinite(uv)):
            return None
        perimeter = float(np.sum(np.linalg.norm(uv - np.roll(uv, -1, axis=0), axis=1)))
        margin = (WINDOW_CLEARANCE + WINDOW_GROUP_REACH * perimeter + WINDOW_MARGIN_PX
                  + WINDOW_SIGMAS * f * float(sigma[j]) / float(pts[:, 2].min()))
        lo = np.floor(uv.min(axis=0) - margin)
        hi = np.ceil(uv.max(axis=0) + margin) + 1
        if np.any(np.abs(np.concatenate([lo, hi])) > 1e6):
            return None
        expected = (tag_id,) if cos[j] < _EXPECT_COS else ()
        wins.append(TagWindow(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]), expected))
    return wins or None
