"""Tag detection in windows of an image where the tags are expected (:func:`detect_tags_in_windows`): the same
detections, with the same corners bit for bit, as :func:`ppoe_core.sensing.tags.detect_tags` on the whole image for the
tags inside the windows, or None where that cannot be promised (``ppoe evaluate``, with windows predicted by the forward
kinematics: :mod:`ppoe_core.analysis.evaluate.tag_prediction`)."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.sensing.tags import TagDetection, aruco_dictionary, detections_from_corners, opencv_detector

__all__ = ["TagWindow", "WINDOW_CLEARANCE", "WINDOW_GROUP_REACH", "detect_tags_in_windows", "merge_windows"]

_per_thread = threading.local()


class TagWindow(NamedTuple):
    """A region of an image where tags are expected (e.g. predicted from the forward kinematics): pixel columns
    ``u0 <= u < u1``, rows ``v0 <= v < v1`` (may reach beyond the image: clipped), the ids expected in it."""

    u0: int
    v0: int
    u1: int
    v1: int
    ids: tuple[int, ...]


#: distance kept between a tag found in a window and the window's edges inside the image [px], on top of
#: :data:`WINDOW_GROUP_REACH` times the tag's perimeter: OpenCV's adaptive thresholds look at most 11 px around a
#: pixel (half its largest window, 23 px) and drop quads with a corner within 3 px of the image's edge
WINDOW_CLEARANCE = 14
#: OpenCV groups the candidate quads whose corners lie on average within 1/8 of a perimeter of each other and keeps
#: the largest of a group (dropping the whole group if that one is too near the image's edge), so a quad that a
#: window's edge changes must not be grouped with a tag: its corners lie within half the tag's perimeter of the
#: tag's and its contour within 3 % of its perimeter (at most 3 tag perimeters) of its sides, 0.6 in all (a chain of
#: quads, each grouped with the next, could reach further: not bounded here; test/test_tag_windows.py checks the
#: shipped bags' images bit for bit against the whole image)
WINDOW_GROUP_REACH = 0.6


def detect_tags_in_windows(image: np.ndarray, windows: Sequence[TagWindow], dictionary: str = "tag36h11",
                           refine: str = "edges", ids: Sequence[int] = ()) -> list[TagDetection] | None:
    """:func:`ppoe_core.sensing.tags.detect_tags` restricted to ``windows``: the same detections with the same corners
    (bit for bit) for the tags inside them, or None where that cannot be promised (then call ``detect_tags``).

    OpenCV's detector runs on each window's crop without corner refinement (with the full image's minimum and
    maximum marker perimeter in pixels); the corners, integer pixels, are shifted back and refined on the full
    image as OpenCV's ``CORNER_REFINE_SUBPIX`` does (``cv2.cornerSubPix``, its window size rule), then as
    ``detect_tags`` (edge fit).  None when a window in the image misses one of its expected ids, a tag comes
    within :data:`WINDOW_CLEARANCE` px + :data:`WINDOW_GROUP_REACH` of its perimeter of a window edge inside the
    image (where the crop could change what OpenCV finds near the tag), an id is
    found twice, no window lies in the image, or ``refine`` is OpenCV's ``contour`` or ``apriltag``; windows
    wholly outside the image are skipped.  Tags outside every window are not seen.

    ``ids``: the ids looked for (default: all of the dictionary).  The windows' detector then knows only their codes
    (with the dictionary's error correction), which makes OpenCV's identification of every candidate quad (a float
    comparison with each code in 4 rotations since OpenCV 4.14, about 1 ms per candidate against the 587 codes of
    36h11) that many times cheaper; a quad it identifies is the one the whole dictionary identifies, because the
    codes are further apart (36h11: 11 bits) than twice the correctable bits (3 at the default rate).  Tags of
    other ids are not seen.
    """
    if refine not in ("edges", "subpix", "none"):
        return None
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 2 or img.size == 0:
        return None
    h, w = img.shape
    full_detector, d = opencv_detector(dictionary, refine, max(h, w))
    full_params = full_detector.getDetectorParameters()
    detector, params, known = _window_detector(dictionary, full_detector, tuple(sorted({int(i) for i in ids})))
    n_min = int(full_params.minMarkerPerimeterRate * max(h, w))  # OpenCV's bounds in pixels for the full image
    n_max = int(full_params.maxMarkerPerimeterRate * max(h, w))
    corners: list[np.ndarray] = []
    tag_ids: list[int] = []
    in_image = False
    for win in merge_windows(windows):
        u0, v0, u1, v1 = max(win.u0, 0), max(win.v0, 0), min(win.u1, w), min(win.v1, h)
        if u1 - u0 < 8 or v1 - v0 < 8:
            if u1 > u0 and v1 > v0:
                return None  # a sliver of the image: nothing to promise
            continue
        in_image = True
        found = _window_corners(img, (u0, v0, u1, v1), (n_min, n_max), detector, params, known)
        if found is None or not set(win.ids) <= {i for i, _ in found}:
            return None
        for i, c in found:
            tag_ids.append(i)
            corners.append(c)
    if not in_image or len(set(tag_ids)) != len(tag_ids):
        return None
    if refine != "none":
        corners = [_subpix_as_aruco(img, c, full_params, int(d.markerSize)) for c in corners]
    return detections_from_corners(img, [c.astype(float) for c in corners], tag_ids, d, refine)


def merge_windows(windows: Sequence[TagWindow]) -> list[TagWindow]:
    """Windows that overlap (or touch) merged into their bounding box with the ids of both, until none overlap
    (a tag is then looked for in one window only)."""
    out = list(windows)
    merged = True
    while merged:
        merged = False
        for a in range(len(out)):
            for b in range(a + 1, len(out)):
                p, q = out[a], out[b]
                if p.u0 <= q.u1 and q.u0 <= p.u1 and p.v0 <= q.v1 and q.v0 <= p.v1:
                    out[a] = TagWindow(min(p.u0, q.u0), min(p.v0, q.v0), max(p.u1, q.u1), max(p.v1, q.v1),
                                       tuple(sorted(set(p.ids) | set(q.ids))))
                    del out[b]
                    merged = True
                    break
            if merged:
                break
    return out


def _window_corners(img: np.ndarray, box: tuple[int, int, int, int], n_bounds: tuple[int, int], detector: Any,
                    params: Any, known: list[int]) -> list[tuple[int, np.ndarray]] | None:
    """OpenCV's unrefined tags of one window of ``img`` (ids, (4, 2) float32 corners in the image), or None if one
    comes too near a window edge inside the image (:data:`WINDOW_CLEARANCE`)."""
    u0, v0, u1, v1 = box
    h, w = img.shape
    big = max(u1 - u0, v1 - v0)
    params.minMarkerPerimeterRate = (n_bounds[0] + 0.5) / big  # the same integer bound on the crop
    params.maxMarkerPerimeterRate = (n_bounds[1] + 0.5) / big
    detector.setDetectorParameters(params)
    cs, ids, _ = detector.detectMarkers(img[v0:v1, u0:u1])
    if ids is None:
        return []
    out = []
    for c, k in zip(cs, ids.reshape(-1).tolist()):
        i = known[k]  # the entry of the detector's dictionary -> the tag id
        c4 = np.asarray(c, dtype=np.float32).reshape(4, 2) + np.array([u0, v0], dtype=np.float32)
        perimeter = float(np.sum(np.linalg.norm(c4 - np.roll(c4, -1, axis=0), axis=1)))
        gap = WINDOW_CLEARANCE + WINDOW_GROUP_REACH * perimeter
        lo, hi = c4.min(axis=0), c4.max(axis=0)
        if ((u0 > 0 and lo[0] - u0 < gap) or (v0 > 0 and lo[1] - v0 < gap) or (u1 < w and u1 - 1 - hi[0] < gap)
                or (v1 < h and v1 - 1 - hi[1] < gap)):
            return None
        out.append((int(i), c4))
    return out


def _subpix_as_aruco(grey: np.ndarray, c4: np.ndarray, params: Any, marker_size: int) -> np.ndarray:
    """OpenCV's ``CORNER_REFINE_SUBPIX`` of one tag's corners (float32, (4, 2)): ``cv2.cornerSubPix`` with a window
    of ``min(cornerRefinementWinSize, max(1, round(relativeCornerRefinmentWinSize * module size)))``, the module
    size (mean side / cells incl. border) summed in float32 as OpenCV's ``getAverageModuleSize``."""
    import cv2

    side = np.float32(0.0)
    for k in range(4):
        dx, dy = c4[k] - c4[(k + 1) % 4]
        side = np.float32(side + np.sqrt(np.float32(dx * dx + dy * dy)))
    module = side / np.float32(4 * (marker_size + 2 * int(params.markerBorderBits)))
    win = min(int(params.cornerRefinementWinSize),
              max(1, int(round(float(np.float32(params.relativeCornerRefinmentWinSize) * module)))))
    c = np.ascontiguousarray(c4, dtype=np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS, int(params.cornerRefinementMaxIterations),
            float(params.cornerRefinementMinAccuracy))
    cv2.cornerSubPix(grey, c, (win, win), (-1, -1), crit)
    return c.reshape(4, 2)


def _window_detector(dictionary: str, full: Any, ids: tuple[int, ...]) -> tuple[Any, Any, list[int]]:
    """A detector of this thread with ``full``'s parameters but no corner refinement (for
    :func:`detect_tags_in_windows`, which sets the perimeter bounds per window), its parameters and the ids of its
    dictionary's entries: ``dictionary``'s codes of ``ids`` only (all if empty), with its error correction."""
    import cv2

    cache = _per_thread.__dict__.setdefault("detectors", {})
    hit = cache.get((dictionary, "window", ids))
    if hit is None:
        params = full.getDetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        d = aruco_dictionary(dictionary)
        known = [i for i in ids if 0 <= i < d.bytesList.shape[0]] if ids else list(range(d.bytesList.shape[0]))
        sub = cv2.aruco.Dictionary(np.ascontiguousarray(d.bytesList[known]), int(d.markerSize),
                                   int(d.maxCorrectionBits))
        hit = cache[(dictionary, "window", ids)] = (cv2.aruco.ArucoDetector(sub, params), params, known)
    return hit
