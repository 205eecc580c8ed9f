"""The compiled edge fit (:mod:`ppoe_core.sensing.edge_kernel`) gives bit for bit the corners of its previous
implementation (``test/edge_kernel_reference.py``): on rendered tags detected by OpenCV, on random quads over noisy
images (profiles inside the image, across its border and outside it), on tiny images, after each number of passes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from edge_kernel_reference import edge_pass_reference  # noqa: E402

from ppoe_core.sensing.tags import EDGE_PASSES, opencv_detector, refine_edges, render_tags  # noqa: E402

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
D = np.array([0.05, -0.02, 0.001, -0.001, 0.0])
#: refine_edges' profiles per edge, sample step [px] and half width [cells] (ppoe_core.sensing.tags' constants)
PROFILES, STEP, WINDOW = 40, 0.1, 0.55


def reference(grey: np.ndarray, corners: np.ndarray, n_cells: int, passes: int = EDGE_PASSES) -> np.ndarray:
    """``refine_edges`` as it was: ``passes`` calls of the previous kernel."""
    c = np.array(corners, dtype=np.float64)
    img = np.ascontiguousarray(grey, dtype=np.uint8)
    for _ in range(passes):
        edge_pass_reference(img, c, int(n_cells), PROFILES, STEP, WINDOW, c)
    return c


def _pose(rng: np.random.Generator) -> np.ndarray:
    """A tag 0.4-1.5 m in front of the camera, tilted up to about 50 degrees, anywhere in the view."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = (Rotation.from_euler("x", np.pi) * Rotation.from_rotvec(rng.normal(0.0, 0.45, 3))).as_matrix()
    z = rng.uniform(0.4, 1.5)
    T[:3, 3] = [rng.uniform(-0.45, 0.45) * z, rng.uniform(-0.35, 0.35) * z, z]
    return T


def test_opencv_corners_of_rendered_tags_refine_to_the_same_bits() -> None:
    rng = np.random.default_rng(31)
    n_tags = 0
    for _ in range(12):
        poses = [_pose(rng), _pose(rng)]
        img, drawn = render_tags((640, 480), K, D, poses, [3, 17], 0.12, blur_sigma=rng.uniform(0.3, 1.2),
                                 noise_sigma=2.0, rng=rng, background=int(rng.integers(60, 200)))
        detector, d = opencv_detector("tag36h11", "edges", 640)
        corners, ids, _ = detector.detectMarkers(img)
        for c4 in corners if ids is not None else []:
            c4 = np.asarray(c4, dtype=float).reshape(4, 2)
            n_tags += 1
            n_cells = int(d.markerSize) + 2
            assert np.array_equal(refine_edges(img, c4, n_cells), reference(img, c4, n_cells))
    assert n_tags >= 12


def _random_quad(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A convex-ish quad, clockwise in the image, 2-80 px across, its centre up to 30 px beyond the border."""
    centre = rng.uniform([-30.0, -30.0], [w + 30.0, h + 30.0])
    r = rng.uniform(1.0, 40.0)
    ang = rng.uniform(0, 2 * np.pi) + np.array([0.0, 0.5, 1.0, 1.5]) * np.pi + rng.normal(0.0, 0.15, 4)
    return centre + (r * rng.uniform(0.7, 1.3, 4))[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=-1)


@pytest.mark.parametrize("shape", [(480, 640), (60, 90), (7, 5), (2, 2), (1, 30)])
def test_random_quads_over_noisy_images_refine_to_the_same_bits(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(shape))
    h, w = shape
    img = rng.integers(0, 256, size=shape).astype(np.uint8)
    big = np.zeros(shape, dtype=np.uint8)
    big[h // 4 : 3 * h // 4 + 1, w // 4 : 3 * w // 4 + 1] = 200  # one dark-to-light border to fit
    moved = 0
    for k in range(300 if h > 10 else 60):
        grey = img if k % 2 else np.clip(big.astype(int) + rng.integers(-3, 4, size=shape), 0, 255).astype(np.uint8)
        c = _random_quad(rng, w, h)
        for passes in (1, EDGE_PASSES):
            got = refine_edges(grey, c, 10, passes)
            assert np.array_equal(got, reference(grey, c, 10, passes)), (shape, k, passes, c)
        moved += not np.array_equal(got, c)
    if h > 10:
        assert moved > 30  # the comparison covers fitted corners, not only corners kept as they were


def test_an_axis_aligned_square_fits_its_edges_inside_and_across_the_border() -> None:
    grey = np.full((120, 160), 220, dtype=np.uint8)
    grey[30:91, 40:101] = 20
    for shift in (0.0, -45.0, 70.0):  # inside; the left edge outside; the right edge outside
        c = np.array([[39.6, 29.7], [100.3, 29.4], [100.5, 90.4], [39.5, 90.6]]) + [shift, 0.0]
        got = refine_edges(grey, c, 10)
        assert np.array_equal(got, reference(grey, c, 10))
    c = np.array([[39.6, 29.7], [100.3, 29.4], [100.5, 90.4], [39.5, 90.6]])
    assert np.abs(refine_edges(grey, c, 10) - [[39.5, 29.5], [100.5, 29.5], [100.5, 90.5], [39.5, 90.5]]).max() < 0.05


def test_zero_passes_and_non_finite_corners_keep_the_input() -> None:
    grey = np.full((50, 50), 200, dtype=np.uint8)
    grey[10:40, 10:40] = 30
    c = np.array([[9.5, 9.5], [39.5, 9.5], [39.5, 39.5], [9.5, 39.5]]) + 0.3
    assert np.array_equal(refine_edges(grey, c, 10, 0), c)
    for bad in (np.nan, np.inf):
        cb = c.copy()
        cb[2, 1] = bad
        assert np.array_equal(refine_edges(grey, cb, 10), cb, equal_nan=True)
