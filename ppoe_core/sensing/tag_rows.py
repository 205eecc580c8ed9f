"""Tag observations of one image: detections -> centre and corner rows (no ROS).

The tag bearing node (``ppoe_ros/tag_bearing_node.py``) publishes these rows on
``/tag_bearing/observations`` and ``ppoe evaluate`` (``ppoe_core/evaluate.py``) computes them
from a bag's images: both call :func:`observe_tags`, so the replay sees exactly what the node
would publish.

One row per observed tag point, ``[id, corner, u, v, x, y]`` (the FLOAT64 fields of the topic,
:data:`OBSERVATION_FIELDS`): ``corner`` 0 is the tag centre, 1..4 the corners in the order of
:mod:`ppoe_core.sensing.tags` (top-left, top-right, bottom-right, bottom-left of an upright tag);
``u, v`` raw (distorted) pixels; ``x, y`` undistorted normalised coordinates ``X/Z, Y/Z`` in the
camera optical frame.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from itertools import islice
from typing import Any

import numpy as np

from ppoe_core.estimation.camera import project_points, undistort_pixels
from ppoe_core.sensing import tags as tagmod
from ppoe_core.sensing.tag_windows import TagWindow, detect_tags_in_windows

__all__ = ["OBSERVATION_FIELDS", "DEFAULT_CORNER_REFINEMENT", "observe_tags", "rows_from_detections",
           "detections_in_images", "ImageDetections", "centre_from_corners", "detect_tags_windowed"]

#: fields of one observation row (and FLOAT64 fields of one ``/tag_bearing/observations`` point)
OBSERVATION_FIELDS: tuple[str, ...] = ("id", "corner", "u", "v", "x", "y")
#: corner refinement of the tag bearing node and of ``ppoe evaluate`` by default: OpenCV's sub-pixel corners, then
#: the four outer edges fitted (:data:`ppoe_core.sensing.tags.EDGE_PASSES` passes); on rendered 640x480 images the
#: corner error is about 0.1 px RMS, below the AprilTag 3 C library's, where OpenCV's ``subpix`` alone gives 0.74 px
#: (bench/bench_tags.py)
DEFAULT_CORNER_REFINEMENT = "edges"


def centre_from_corners(xy_corners: np.ndarray) -> np.ndarray:
    """Image of the tag centre: intersection of the diagonals 1-3 and 2-4.

    For a pinhole camera the projection of a planar square's centre is exactly the
    intersection of the projected diagonals (projective maps keep lines and incidence), so
    this is computed on *undistorted* normalised coordinates.

    Parameters
    ----------
    xy_corners : ndarray, shape (..., 4, 2)
        Undistorted normalised corner coordinates ``X/Z, Y/Z`` in the order of
        :mod:`ppoe_core.sensing.tags`.

    Returns
    -------
    ndarray, shape (..., 2)
        Normalised centre coordinates; the corners' mean where the diagonals are parallel
        (degenerate quadrilateral).
    """
    xy = np.asarray(xy_corners, dtype=np.float64)
    h = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)  # (..., 4, 3)
    c = np.cross(np.cross(h[..., 0, :], h[..., 2, :]), np.cross(h[..., 1, :], h[..., 3, :]))
    ok = np.abs(c[..., 2]) > 1e-12
    w = np.where(ok, c[..., 2], 1.0)[..., None]
    return np.where(ok[..., None], c[..., :2] / w, xy.mean(axis=-2))


def observe_tags(
    image: np.ndarray,
    K: np.ndarray,
    D: np.ndarray,
    dictionary: str = "tag36h11",
    tag_ids: Sequence[int] = (),
    refine: str = DEFAULT_CORNER_REFINEMENT,
) -> tuple[np.ndarray, list[Any]]:
    """Detect tags in one image and return their observation rows.

    Corners come from :func:`ppoe_core.sensing.tags.detect_tags`, ``x, y`` from
    :func:`ppoe_core.estimation.camera.undistort_pixels` (``cv2.undistortPoints``); the centre is
    :func:`centre_from_corners` of the undistorted corners, distorted back with
    :func:`ppoe_core.estimation.camera.project_points` for its ``u, v``.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3), uint8
        Grey or BGR image.
    K : ndarray, shape (3, 3)
        Camera matrix [px].
    D : ndarray, shape (k,)
        Distortion coefficients, OpenCV order (``plumb_bob`` / ``rational_polynomial``).
    dictionary : str
        Tag family, see :func:`ppoe_core.sensing.tags.detect_tags`.
    tag_ids : sequence of int
        Ids to keep; empty = all detected tags.
    refine : str
        Corner refinement, see :func:`ppoe_core.sensing.tags.detect_tags`.

    Returns
    -------
    rows : ndarray, shape (5 n, 6), float64
        ``[id, corner, u, v, x, y]`` per point: centre (corner 0) then corners 1..4 of each of
        the ``n`` kept tags, in detection order; shape (0, 6) when no tag is kept.
    detections : list of ppoe_core.sensing.tags.TagDetection
        The kept detections (e.g. for drawing).

    Raises
    ------
    MeasurementError
        Unknown dictionary or refinement (from :func:`ppoe_core.sensing.tags.detect_tags`).
    """
    return rows_from_detections(tagmod.detect_tags(image, dictionary, refine), K, D, tag_ids)


def detect_tags_windowed(image: np.ndarray, windows: Sequence[TagWindow] | None, dictionary: str = "tag36h11",
                         refine: str = DEFAULT_CORNER_REFINEMENT, ids: Sequence[int] = ()) -> tuple[list[Any], bool]:
    """:func:`ppoe_core.sensing.tag_windows.detect_tags_in_windows` of ``image`` (grey or BGR; the tags ``ids``, default
    all), or where it gives no promise (or there are no ``windows``) :func:`ppoe_core.sensing.tags.detect_tags` of
    the whole image: ``(detections, True if the windows gave them)``."""
    if windows:
        import cv2

        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        found = detect_tags_in_windows(grey, windows, dictionary, refine, ids)
        if found is not None:
            return found, True
    return tagmod.detect_tags(image, dictionary, refine), False


def detections_in_images(decode: Callable[[int], np.ndarray], n: int, dictionary: str = "tag36h11",
                         refine: str = DEFAULT_CORNER_REFINEMENT, workers: int = 1,
                         ahead: int | None = None) -> ImageDetections:
    """:func:`ppoe_core.sensing.tags.detect_tags` of images ``decode(0) .. decode(n - 1)``, in that order (an
    iterator with ``close()``).

    With ``workers`` > 1, decoding and detection run on that many threads (OpenCV releases the GIL), started at
    once and ``ahead`` images (default ``4 * workers``) ahead of the consumer (OpenCV's own threads are set to one
    meanwhile); every image's detections, or the error its decoding or detection raised, are still handed out in
    image order, and the threads stop when the consumer stops (``close()``, also after an error).
    The detections do not depend on the thread (``test/test_tags.py``).
    """
    def one(i: int) -> list[Any]:
        return tagmod.detect_tags(decode(i), dictionary, refine)

    return ImageDetections(one, n, workers, 4 * workers if ahead is None else ahead)


class ImageDetections:
    """``one(0) .. one(n - 1)`` in order, on ``workers`` threads up to ``ahead`` images ahead of the consumer
    (:func:`detections_in_images`)."""

    def __init__(self, one: Callable[[int], Any], n: int, workers: int, ahead: int) -> None:
        self._one, self._n, self._next = one, n, 0
        self._ex: ThreadPoolExecutor | None = None
        self._pending: deque[Any] = deque()
        if workers <= 1 or n < 2:
            return
        import cv2

        self._cv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)  # the pool is the parallelism; OpenCV's own threads would only compete for the cores
        self._ex = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="detect_tags")
        self._todo = iter(range(n))
        self._pending.extend(self._ex.submit(one, i) for i in islice(self._todo, max(int(ahead), 1)))

    def __iter__(self) -> ImageDetections:
        return self

    def __next__(self) -> Any:
        if self._ex is None:
            if self._next >= self._n:
                raise StopIteration
            self._next += 1
            return self._one(self._next - 1)
        if not self._pending:
            self.close()
            raise StopIteration
        done = self._pending.popleft()
        nxt = next(self._todo, None)
        if nxt is not None:
            self._pending.append(self._ex.submit(self._one, nxt))
        try:
            return done.result()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop the threads (the images not started are dropped)."""
        if self._ex is not None:
            import cv2

            self._ex.shutdown(wait=True, cancel_futures=True)
            self._ex = None
            self._pending.clear()
            self._n = self._next  # nothing more to hand out
            cv2.setNumThreads(self._cv_threads)


def rows_from_detections(
    dets: list[Any], K: np.ndarray, D: np.ndarray, tag_ids: Sequence[int] = ()
) -> tuple[np.ndarray, list[Any]]:
    """The second half of :func:`observe_tags`: its rows (and kept detections) from the detections of one image.

    Parameters
    ----------
    dets : list of ppoe_core.sensing.tags.TagDetection
        :func:`ppoe_core.sensing.tags.detect_tags` of the image.
    K, D, tag_ids
        As :func:`observe_tags`.
    """
    keep = {int(i) for i in tag_ids}
    if keep:
        dets = [d for d in dets if d.id in keep]
    if not dets:
        return np.zeros((0, len(OBSERVATION_FIELDS))), []
    corners_uv = np.stack([d.corners for d in dets])  # (n, 4, 2)
    xy_c = undistort_pixels(corners_uv, K, D)  # (n, 4, 2)
    centre_xy = centre_from_corners(xy_c)  # (n, 2)
    centre_uv = project_points(np.concatenate([centre_xy, np.ones((len(dets), 1))], axis=1), K, D)
    rows = np.zeros((len(dets), 5, len(OBSERVATION_FIELDS)))
    rows[:, :, 0] = np.array([d.id for d in dets], dtype=float)[:, None]
    rows[:, :, 1] = np.arange(5)[None, :]
    rows[:, 0, 2:4] = centre_uv
    rows[:, 0, 4:6] = centre_xy
    rows[:, 1:, 2:4] = corners_uv
    rows[:, 1:, 4:6] = xy_c
    return rows.reshape(-1, len(OBSERVATION_FIELDS)), dets
