"""AprilTag / ArUco rendering and detection with OpenCV (``cv2.aruco``).

Tag frame (the OpenCV ArUco convention): origin at the tag centre, ``x`` to the
right and ``y`` up when the tag is read upright, ``z`` out of the printed face
(towards a camera that sees it).  ``size`` is the edge of the black square
(the outer black border included, the white quiet zone around it excluded), in
metres.

Corner order (used everywhere in the project, also as ``corner`` 1..4 of
``/tag_bearing/observations``; 0 is the centre)::

    corner 1: (-s/2, +s/2)  top-left       corner 2: (+s/2, +s/2)  top-right
    corner 4: (-s/2, -s/2)  bottom-left    corner 3: (+s/2, -s/2)  bottom-right

i.e. clockwise in the image of an upright tag: the order ``cv2.aruco`` returns.
The centre pixel is the intersection of the diagonals of the four detected
corners, which is the exact image of the tag centre for a pinhole camera.

Pixel coordinates follow OpenCV: the centre of pixel (row r, column c) is (u, v) = (c, r).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from functools import cache, lru_cache
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.errors import MeasurementError
from ppoe_core.estimation.camera import project_points, undistort_pixels

__all__ = [
    "TagDetection",
    "TAG_CORNERS_UNIT",
    "aruco_dictionary",
    "tag_points_local",
    "detect_tags",
    "opencv_detector",
    "min_perimeter_rate",
    "MIN_PX_PER_CELL",
    "detections_from_corners",
    "refine_edges",
    "EDGE_PASSES",
    "render_tags",
]

#: corners 1..4 of a tag of unit size in the tag frame (x, y), see the module docstring
TAG_CORNERS_UNIT = np.array([[-0.5, 0.5], [0.5, 0.5], [0.5, -0.5], [-0.5, -0.5]])

_ALIASES = {
    "tag36h11": "DICT_APRILTAG_36h11",
    "tag36h10": "DICT_APRILTAG_36h10",
    "tag25h9": "DICT_APRILTAG_25h9",
    "tag16h5": "DICT_APRILTAG_16h5",
    "aruco_original": "DICT_ARUCO_ORIGINAL",
    "aruco_mip_36h12": "DICT_ARUCO_MIP_36h12",
}


class TagDetection(NamedTuple):
    """One detected tag: ``id``, ``corners`` (4,2) pixels in the documented order, ``centre`` (2,)."""

    id: int
    corners: np.ndarray
    centre: np.ndarray


@cache
def aruco_dictionary(name: str = "tag36h11") -> Any:
    """OpenCV dictionary by name: ``tag36h11`` (default), ``tag36h10``, ``tag25h9``,
    ``tag16h5``, ``aruco_original``, ``4x4_50`` ... ``7x7_1000``, or any ``DICT_*`` name.

    Raises
    ------
    MeasurementError
        Unknown dictionary name (the message lists the known ones).
    """
    import cv2

    key = name.strip()
    cand = _ALIASES.get(key.lower())
    if cand is None:
        up = key.upper()
        cand = up if up.startswith("DICT_") else "DICT_" + up
    if not hasattr(cv2.aruco, cand):
        known = sorted(set(_ALIASES) | {a[5:].lower() for a in dir(cv2.aruco)
                                        if a.startswith("DICT_") and "APRILTAG" not in a})
        raise MeasurementError(f"unknown tag dictionary {name!r}; known: {known}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cand))


def tag_points_local(size: float) -> np.ndarray:
    """Centre and corners 1..4 of a tag in its own frame, (5, 3) [m] (rows = corner 0..4)."""
    pts = np.zeros((5, 3))
    pts[1:, :2] = TAG_CORNERS_UNIT * float(size)
    return pts


def _diagonal_intersection(c: np.ndarray) -> np.ndarray:
    """Intersection of the diagonals 1-3 and 2-4 of a quadrilateral (4,2).

    Homogeneous lines and their crossing with ``np.cross``'s operations on Python floats (the same
    products and differences, so the same bits, without numpy's overhead for 3-vectors).
    """
    (x1, y1), (x2, y2), (x3, y3), (x4, y4) = c.tolist()
    # l = p1 x p3, m = p2 x p4 with p = (x, y, 1); multiplying by 1.0 is exact
    l0, l1, l2 = y1 * 1.0 - 1.0 * y3, 1.0 * x3 - x1 * 1.0, x1 * y3 - y1 * x3
    m0, m1, m2 = y2 * 1.0 - 1.0 * y4, 1.0 * x4 - x2 * 1.0, x2 * y4 - y2 * x4
    w = l0 * m1 - l1 * m0
    if abs(w) < 1e-12:
        return c.mean(axis=0)
    return np.array([(l1 * m2 - l2 * m1) / w, (l2 * m0 - l0 * m2) / w])


#: passes of the edge fit: each re-centres the profiles on the edges the previous one found (the gradient centroid of
#: a window that is off the edge is biased towards the window's middle); four bring the corner error of rendered
#: 640x480 images (blur 0.8 px, noise 2 grey levels) to 0.097 px RMS, the AprilTag 3 C library's 0.104 px on the same
#: images, one pass 0.22 px (bench/bench_tags.py)
EDGE_PASSES = 4
#: profile sample step across an edge [px]
_EDGE_STEP = 0.1
#: profiles per edge at most (evenly spaced over its middle 70 %); more change the corners by < 0.005 px
_EDGE_PROFILES = 40
#: half width of a profile [cells of the black square] (at most 2 px): wider reaches the next inner edge
_EDGE_WINDOW = 0.55


def refine_edges(grey: np.ndarray, corners: np.ndarray, n_cells: int, passes: int = EDGE_PASSES) -> np.ndarray:
    """Refine the 4 corners of a quad by fitting its 4 outer edges (AprilTag-style), ``passes`` times.

    Along each edge, intensity profiles across the edge (bilinear samples, step 0.1 px, half
    width ``min(2 px, 0.55 cell)``) give the sub-pixel edge position as the centroid of the
    dark-to-light gradient; a total-least-squares line is fitted to those points and the
    corners are the intersections of consecutive lines.  Corners that move by more than one
    cell, or edges with too few valid profiles, keep the input values.  Each pass starts from the
    previous pass's corners (:data:`EDGE_PASSES`); all passes are one compiled call
    (:func:`ppoe_core.sensing.edge_kernel.edge_fit`).

    Parameters
    ----------
    grey : (H, W) uint8
    corners : (4, 2)
        Corners in the module's order (clockwise in the image).
    n_cells : int
        Cells across the black square (8 for 36h11).
    passes : int

    Returns
    -------
    (4, 2) refined corners.
    """
    from ppoe_core.sensing.edge_kernel import edge_fit

    c = np.array(corners, dtype=np.float64)
    img = np.ascontiguousarray(grey, dtype=np.uint8)
    edge_fit(img, c, int(n_cells), int(passes), _EDGE_PROFILES, _EDGE_STEP, _EDGE_WINDOW, c)
    return c


_per_thread = threading.local()

#: OpenCV's default lower bound on a candidate's perimeter, as a fraction of the image's larger side
_OPENCV_MIN_PERIMETER_RATE = 0.03
#: pixels per cell below which a tag's bits are not sampled (less than one pixel per cell: below the image's
#: Nyquist limit).  Candidates with a smaller black square are dropped before identification, which is most of
#: ``detectMarkers``' time on them (rendered 640x480 images: 2.05 -> 1.44 ms per image, every tag still found).
#: ``cv2.aruco`` itself decodes no 36h11 tag below about 1.4 px per cell (``test/test_tags_min_size.py``), so the
#: bound loses none; OpenCV's own default (3 % of the larger image side: 4.8 px per side on 640 px) is kept where
#: it is the stricter one (images wider than about 1070 px).
MIN_PX_PER_CELL = 1.0


def min_perimeter_rate(d: Any, image_side: int) -> float:
    """``minMarkerPerimeterRate`` for a dictionary ``d`` and an image whose larger side is ``image_side`` [px]:
    a black square of at least :data:`MIN_PX_PER_CELL` pixels per cell (``markerSize + 2`` cells across), and at
    least OpenCV's default rate (``image_side`` 0: the default alone)."""
    if image_side <= 0:
        return _OPENCV_MIN_PERIMETER_RATE
    cells = int(d.markerSize) + 2
    return max(_OPENCV_MIN_PERIMETER_RATE, 4.0 * cells * MIN_PX_PER_CELL / float(image_side))


def opencv_detector(dictionary: str, refine: str, image_side: int = 0) -> tuple[Any, Any]:
    """The ``cv2.aruco.ArucoDetector`` of a dictionary and corner refinement (the one :func:`detect_tags` uses) for
    images whose larger side is ``image_side`` pixels (its minimum candidate size, :func:`min_perimeter_rate`; 0:
    OpenCV's default), and the dictionary; made once per thread (a detector is not shared between threads)."""
    import cv2

    cache = _per_thread.__dict__.setdefault("detectors", {})
    hit = cache.get((dictionary, refine, image_side))
    if hit is not None:
        return hit
    methods = {
        "edges": cv2.aruco.CORNER_REFINE_SUBPIX,
        "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
        "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
        "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
        "none": cv2.aruco.CORNER_REFINE_NONE,
    }
    if refine not in methods:
        raise MeasurementError(f"detect_tags: refine must be one of {sorted(methods)}, got {refine!r}")
    d = aruco_dictionary(dictionary)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = methods[refine]
    params.cornerRefinementWinSize = 3
    params.cornerRefinementMinAccuracy = 0.01
    params.cornerRefinementMaxIterations = 50
    params.minMarkerPerimeterRate = min_perimeter_rate(d, image_side)
    hit = cache[(dictionary, refine, image_side)] = (cv2.aruco.ArucoDetector(d, params), d)
    return hit


def detect_tags(image: np.ndarray, dictionary: str = "tag36h11", refine: str = "edges") -> list[TagDetection]:
    """Detect tags in an image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
        Mono or BGR image.
    dictionary
        Dictionary name, see :func:`aruco_dictionary`.
    refine
        Corner refinement: ``"edges"`` (default: OpenCV sub-pixel corners, then a line fit of the
        four outer edges, see :func:`refine_edges`), ``"subpix"``, ``"contour"``, ``"apriltag"``
        or ``"none"`` (OpenCV's methods alone).

    Returns
    -------
    list of TagDetection sorted by id; ``corners`` (4, 2) in the module's corner order,
    ``centre`` (2,) the diagonal intersection.

    Raises
    ------
    MeasurementError
        Empty image or wrong dtype/shape.
    """
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or img.size == 0:
        raise MeasurementError(f"detect_tags: need a non-empty uint8 (H,W) or (H,W,3) image, "
                               f"got {img.dtype} {img.shape}")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    detector, d = opencv_detector(dictionary, refine, max(img.shape[:2]))
    corners, ids, _ = detector.detectMarkers(img)
    if ids is None:
        return []
    four = [np.asarray(c, dtype=float).reshape(4, 2) for c in corners]
    return detections_from_corners(img, four, ids.reshape(-1).tolist(), d, refine)


def detections_from_corners(grey: np.ndarray, corners: list[np.ndarray], ids: list[int], d: Any,
                            refine: str) -> list[TagDetection]:
    """:class:`TagDetection` of OpenCV's corners (refined by OpenCV as ``refine`` asks), the edge fit applied for
    ``"edges"``; sorted by id."""
    out: list[TagDetection] = []
    for c4, i in zip(corners, ids):
        if refine == "edges":
            c4 = refine_edges(grey, c4, int(d.markerSize) + 2)
        out.append(TagDetection(int(i), c4, _diagonal_intersection(c4)))
    out.sort(key=lambda d: d.id)
    return out


@lru_cache(maxsize=64)
def _texture(dictionary: str, tag_id: int, px_per_cell: int, border_cells: int) -> np.ndarray:
    """Tag bitmap with its black border plus ``border_cells`` of white quiet zone, float32 in [0, 1]."""
    import cv2

    d = aruco_dictionary(dictionary)
    n_cells = int(d.markerSize) + 2
    if not 0 <= tag_id < d.bytesList.shape[0]:
        raise MeasurementError(f"tag id {tag_id} is not in dictionary {dictionary} (0..{d.bytesList.shape[0] - 1})")
    marker = cv2.aruco.generateImageMarker(d, int(tag_id), n_cells * px_per_cell, borderBits=1)
    pad = border_cells * px_per_cell
    tex = np.pad(marker, pad, constant_values=255).astype(np.float32) / 255.0
    return tex


@lru_cache(maxsize=4)
def _ray_grid(width: int, height: int, K_key: tuple[float, ...], D_key: tuple[float, ...]) -> np.ndarray:
    """Undistorted normalised coordinates at every pixel centre, with a 1-pixel border:
    entry ``[r + 1, c + 1]`` belongs to pixel (u, v) = (c, r); shape (H + 2, W + 2, 2) float32."""
    K = np.array(K_key).reshape(3, 3)
    D = np.array(D_key)
    uu, vv = np.meshgrid(np.arange(-1.0, width + 1.0), np.arange(-1.0, height + 1.0))
    uv = np.stack([uu, vv], axis=-1)
    if np.any(D != 0):
        xy = undistort_pixels(uv, K, D)
    else:
        xy = np.stack(
            [(uu - K[0, 2] - K[0, 1] * (vv - K[1, 2]) / K[1, 1]) / K[0, 0], (vv - K[1, 2]) / K[1, 1]], axis=-1
        )
    return xy.astype(np.float32)


def _rays(grid: np.ndarray, u0: int, v0: int, u1: int, v1: int, ss: int) -> np.ndarray:
    """Normalised coordinates of the ``ss`` x ``ss`` sub-pixel samples of pixels [u0..u1] x [v0..v1],
    bilinearly interpolated from the per-pixel grid (the distortion map is smooth), (.., .., 2)."""
    import cv2

    off = (np.arange(ss) + 0.5) / ss - 0.5
    us = (np.arange(u0, u1 + 1)[:, None] + off[None, :]).reshape(-1) + 1.0
    vs = (np.arange(v0, v1 + 1)[:, None] + off[None, :]).reshape(-1) + 1.0
    mx, my = np.meshgrid(us.astype(np.float32), vs.astype(np.float32))
    return cv2.remap(grid, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def render_tags(
    image_size: tuple[int, int],
    K: np.ndarray,
    D: np.ndarray | Sequence[float],
    T_cam_tag_list: np.ndarray | Sequence[np.ndarray],
    ids: Sequence[int],
    size: float | Sequence[float] | np.ndarray,
    dictionary: str = "tag36h11",
    background: np.ndarray | int = 128,
    border_cells: float = 1.0,
    black: int = 25,
    white: int = 235,
    supersample: int = 3,
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    min_depth: float = 0.05,
    max_angle_deg: float = 80.0,
    blur_sigma: float = 0.0,
) -> tuple[np.ndarray, list[int]]:
    """Draw tags at their true pose into a grey image (per-pixel inverse mapping).

    Every sub-pixel sample's camera ray (through the plumb_bob model, inverted
    exactly) is intersected with the tag plane; the tag texture (black square
    plus a white quiet zone of ``border_cells`` cells) is sampled there, and
    ``supersample`` x ``supersample`` samples are averaged per pixel.

    Parameters
    ----------
    image_size : (width, height)
    K : (3, 3), D : (k,)
        Camera intrinsics and plumb_bob distortion.
    T_cam_tag_list : (N, 4, 4)
        Tag poses in the camera optical frame (tag frame as in the module docstring).
    ids : (N,)
        Tag ids in ``dictionary``.
    size : float or (N,)
        Black-square edge [m].
    background
        Grey value or a (H, W) uint8 image to draw into.
    noise_sigma
        Standard deviation of additive Gaussian pixel noise [grey levels] (needs ``rng``).
    min_depth
        A tag with any corner (quiet zone included) closer than this [m] in z is not drawn.
    max_angle_deg
        Tags seen at more than this angle between their normal and the viewing ray are not drawn.
    blur_sigma
        Gaussian blur (optics, focus) applied before the noise [px]; 0 = none.

    Returns
    -------
    image : (H, W) uint8
    drawn : list of the ids drawn (in view, in front, facing the camera).
    """
    import cv2

    w, h = int(image_size[0]), int(image_size[1])
    K = np.asarray(K, dtype=float)
    D = np.asarray(D, dtype=float).reshape(-1)
    canvas = _canvas(w, h, background)
    T_all = np.asarray(T_cam_tag_list, dtype=float).reshape(-1, 4, 4)
    ids = [int(i) for i in ids]
    sizes = np.broadcast_to(np.asarray(size, dtype=float), (len(ids),))
    if T_all.shape[0] != len(ids):
        raise MeasurementError(f"render_tags: {T_all.shape[0]} poses but {len(ids)} ids")
    ss = max(1, int(supersample))
    rays = None
    drawn: list[int] = []
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    order = np.argsort(-T_all[:, 2, 3])  # far to near, so near tags occlude far ones
    for k in order:
        T = T_all[k]
        tag_id, s = ids[k], float(sizes[k])
        n_cells = int(aruco_dictionary(dictionary).markerSize) + 2
        half = 0.5 * s * (n_cells + 2 * border_cells) / n_cells  # half edge incl. quiet zone
        R, t = T[:3, :3], T[:3, 3]
        outer = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
        P = outer @ R.T + t
        if np.any(P[:, 2] < min_depth):
            continue
        normal = R[:, 2]
        view = t / np.linalg.norm(t)
        if -float(normal @ view) < cos_max:  # back side, or too grazing
            continue
        uv = project_points(P, K, D)
        u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 2
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w - 1), min(v1, h - 1)
        if u1 <= u0 or v1 <= v0:
            continue
        if rays is None:
            rays = _ray_grid(w, h, tuple(K.reshape(-1)), tuple(D))
        cover, col = _sample_tag(_rays(rays, u0, v0, u1, v1, ss).astype(float), (v1 - v0 + 1, u1 - u0 + 1), ss,
                                 R, t, s, half, dictionary, tag_id, black, white)
        patch = canvas[v0 : v1 + 1, u0 : u1 + 1]
        canvas[v0 : v1 + 1, u0 : u1 + 1] = patch * (1.0 - cover) + col
        drawn.append(tag_id)
    if blur_sigma > 0:
        canvas = np.asarray(cv2.GaussianBlur(canvas, (0, 0), float(blur_sigma)), dtype=np.float32)
    if noise_sigma > 0:
        if rng is None:
            raise MeasurementError("render_tags: noise_sigma > 0 needs an rng (np.random.default_rng(seed))")
        canvas = canvas + rng.normal(0.0, noise_sigma, canvas.shape).astype(np.float32)
    return np.clip(np.rint(canvas), 0, 255).astype(np.uint8), sorted(drawn)


def _canvas(w: int, h: int, background: np.ndarray | int) -> np.ndarray:
    """A float32 (h, w) canvas: a grey value or a copy of a (h, w) image."""
    if np.isscalar(background):
        return np.full((h, w), float(background), dtype=np.float32)  # type: ignore[arg-type]
    bg = np.asarray(background)
    if bg.shape != (h, w):
        raise MeasurementError(f"render_tags: background shape {bg.shape} != {(h, w)}")
    return bg.astype(np.float32)


def _sample_tag(
    xy: np.ndarray,
    hw: tuple[int, int],
    ss: int,
    R: np.ndarray,
    t: np.ndarray,
    s: float,
    half: float,
    dictionary: str,
    tag_id: int,
    black: int,
    white: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Coverage and grey sum per pixel of one tag over its pixel box, from the box's sub-pixel rays ``xy``.

    The ray ``(x, y, 1)`` meets the tag plane (normal ``R[:, 2]`` through ``t``, camera frame); the texture of the
    black square spans ``[-s/2, s/2]`` and the quiet zone (up to ``half``) is white.
    """
    import cv2

    normal = R[:, 2]
    # ray r = (x, y, 1); plane point p = R^T (s r - t), with normal_c . (s r - t) = 0
    d = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=-1)
    denom = d @ normal
    lam = float(normal @ t) / np.where(np.abs(denom) < 1e-12, 1e-12, denom)
    p_tag = (lam[..., None] * d - t) @ R  # (.., 3) in tag frame
    tex = _texture(dictionary, tag_id, 16, 0)
    tex_n = tex.shape[0]
    scale = tex_n / s
    map_x = ((p_tag[..., 0] + 0.5 * s) * scale - 0.5).astype(np.float32)
    map_y = ((0.5 * s - p_tag[..., 1]) * scale - 0.5).astype(np.float32)
    val = cv2.remap(tex, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
    inside = ((np.abs(p_tag[..., 0]) <= half) & (np.abs(p_tag[..., 1]) <= half) & (lam > 0)).astype(np.float32)
    grey = black + (white - black) * val
    hh, ww = hw
    cover = inside.reshape(hh, ss, ww, ss).mean(axis=(1, 3))
    col = (grey * inside).reshape(hh, ss, ww, ss).sum(axis=(1, 3)) / (ss * ss)
    return cover, col
