"""Render tags at known poses with ppoe_core.sensing.tags and detect them again."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import REPO

from ppoe_core.errors import MeasurementError
from ppoe_core.estimation import camera
from ppoe_core.sensing import tags

K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
D = np.array([-0.1, 0.05, 0.001, -0.001, 0.0])


def _pose(rpy: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = t
    return T


# tag z must point towards the camera: roll about pi
POSES = [
    ((np.pi, 0.0, 0.0), (0.0, 0.0, 0.5)),
    ((np.pi + 0.4, 0.3, 0.2), (0.1, -0.05, 0.6)),
    ((np.pi - 0.5, -0.4, 1.0), (-0.15, 0.1, 0.8)),
    ((np.pi, 0.2, 2.5), (0.2, 0.15, 1.2)),
    ((np.pi + 0.7, 0.0, -0.7), (-0.25, -0.2, 0.9)),
]


@pytest.mark.parametrize("rpy,t", POSES)
def test_render_then_detect_matches_projection(rpy: tuple, t: tuple) -> None:
    T = _pose(rpy, t)
    size = 0.06
    img, drawn = tags.render_tags((640, 480), K, D, [T], [7], size, noise_sigma=1.0,
                                  rng=np.random.default_rng(0))
    assert drawn == [7]
    det = tags.detect_tags(img)
    assert [d.id for d in det] == [7]
    P = tags.tag_points_local(size) @ T[:3, :3].T + T[:3, 3]
    uv = camera.project_points(P, K, D)
    err_corners = np.linalg.norm(det[0].corners - uv[1:], axis=1)
    assert err_corners.max() < 0.15, err_corners           # edge-fit refinement (default)
    # centre: diagonal intersection; with lens distortion it is within a fraction of a pixel
    assert np.linalg.norm(det[0].centre - uv[0]) < 0.15
    # OpenCV's sub-pixel corners alone are within a pixel
    det_cv = tags.detect_tags(img, refine="subpix")
    assert np.linalg.norm(det_cv[0].corners - uv[1:], axis=1).max() < 1.0


def test_several_tags_and_visibility() -> None:
    T_front = _pose((np.pi, 0, 0), (-0.1, 0, 0.6))
    T_front2 = _pose((np.pi, 0, 0.3), (0.12, 0.05, 0.7))
    T_back = _pose((0.0, 0, 0), (0.0, -0.15, 0.6))         # printed face away from camera
    T_behind = _pose((np.pi, 0, 0), (0.0, 0.0, -0.5))       # behind the camera
    T_outside = _pose((np.pi, 0, 0), (3.0, 0.0, 0.5))       # outside the field of view
    img, drawn = tags.render_tags((640, 480), K, D, [T_front, T_front2, T_back, T_behind, T_outside],
                                  [1, 2, 3, 4, 5], 0.05)
    assert drawn == [1, 2]
    assert [d.id for d in tags.detect_tags(img)] == [1, 2]


def test_other_dictionary_and_bgr_input() -> None:
    T = _pose((np.pi, 0.1, 0.0), (0.0, 0.0, 0.5))
    img, drawn = tags.render_tags((320, 240), K * np.array([[0.5], [0.5], [1]]), np.zeros(5), [T], [11], 0.08,
                                  dictionary="4x4_50")
    assert drawn == [11]
    bgr = np.repeat(img[..., None], 3, axis=2)
    assert [d.id for d in tags.detect_tags(bgr, dictionary="DICT_4X4_50")] == [11]
    # the same image holds no tag36h11
    assert tags.detect_tags(img, dictionary="tag36h11") == []


def test_corner_order_is_documented_order() -> None:
    # camera looking at an upright tag: corner 1 top-left, 2 top-right, 3 bottom-right, 4 bottom-left
    T = _pose((np.pi, 0, 0), (0, 0, 0.5))  # tag x = camera x, tag y = -camera y (up in the image)
    img, _ = tags.render_tags((640, 480), K, np.zeros(5), [T], [0], 0.1)
    c = tags.detect_tags(img)[0].corners
    assert c[0, 0] < c[1, 0] and c[0, 1] < c[3, 1]          # 1 left of 2, 1 above 4
    assert c[2, 0] > c[3, 0] and c[2, 1] > c[1, 1]          # 3 right of 4, 3 below 2


def test_edge_refinement_on_small_tags() -> None:
    """Tags of 15-30 px: the edge fit beats OpenCV's corner refinement (seeded, 20 poses)."""
    rng = np.random.default_rng(4)
    err_edges, err_cv = [], []
    for _ in range(20):
        T = _pose((np.pi + rng.uniform(-0.8, 0.8), rng.uniform(-0.3, 0.3), rng.uniform(0, 6)),
                  (rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(1.0, 1.8)))
        img, _ = tags.render_tags((640, 480), K, D, [T], [10], 0.04, noise_sigma=1.0, rng=rng)
        uv = camera.project_points(tags.tag_points_local(0.04) @ T[:3, :3].T + T[:3, 3], K, D)[1:]
        for refine, errs in (("edges", err_edges), ("subpix", err_cv)):
            det = tags.detect_tags(img, refine=refine)
            if det:
                errs.append(np.linalg.norm(det[0].corners - uv, axis=1))
    rms_edges = np.sqrt(np.mean(np.concatenate(err_edges) ** 2))
    rms_cv = np.sqrt(np.mean(np.concatenate(err_cv) ** 2))
    assert len(err_edges) >= 18
    assert rms_edges < 0.2 and rms_edges < 0.5 * rms_cv, (rms_edges, rms_cv)


def test_edge_passes_converge_below_a_tenth_of_a_pixel_on_blurred_noisy_tags() -> None:
    """Two tags of 4 cm at 0.35-1.2 m, tilted, blur 0.8 px, noise 2 grey levels (bench/bench_tags.py's images): each
    pass of the edge fit re-centres its profiles, four reach about 0.1 px RMS (one: about 0.2 px); in one pass a
    corner never moves by a cell or more."""
    import sys

    sys.path.insert(0, str(REPO / "bench"))
    import bench_tags

    pngs, truth = bench_tags.render_set(12, 7)
    import cv2

    errs: dict[int, list[float]] = {1: [], tags.EDGE_PASSES: []}
    for png, true in zip(pngs, truth):
        grey = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
        for det in tags.detect_tags(grey, refine="subpix"):
            for passes in errs:
                c = tags.refine_edges(grey, det.corners, 8, passes)  # tag36h11: 8 cells across the black square
                if passes == 1:
                    assert np.all(np.linalg.norm(c - det.corners, axis=1) < np.linalg.norm(
                        det.corners - np.roll(det.corners, -1, axis=0), axis=1) / 8)
                errs[passes] += bench_tags._errors({det.id: c}, true)
    rms = {p: float(np.sqrt(np.mean(np.square(e)))) for p, e in errs.items()}
    assert len(errs[1]) >= 80
    assert rms[tags.EDGE_PASSES] < 0.13 and rms[tags.EDGE_PASSES] < 0.75 * rms[1], rms


def test_errors_name_the_problem() -> None:
    with pytest.raises(MeasurementError, match="unknown tag dictionary 'tag99'"):
        tags.aruco_dictionary("tag99")
    with pytest.raises(MeasurementError, match="uint8"):
        tags.detect_tags(np.zeros((10, 10), dtype=float))
    with pytest.raises(MeasurementError, match="2 poses but 1 ids"):
        tags.render_tags((64, 48), K, D, [np.eye(4), np.eye(4)], [1], 0.05)


def test_undistort_inverts_project() -> None:
    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), rng.uniform(0.5, 2.0, 50)])
    uv = camera.project_points(P, K, D)
    xy = camera.undistort_pixels(uv, K, D)
    np.testing.assert_allclose(xy, P[:, :2] / P[:, 2:], atol=1e-8)


def test_diagonal_intersection_is_the_cross_product_formula_bit_for_bit() -> None:
    """The Python-float version gives the bits of the homogeneous ``np.cross`` construction it replaced."""
    rng = np.random.default_rng(8)
    for k in range(3000):
        c = rng.uniform(0, 640, (4, 2)) if k % 2 else rng.normal(size=(4, 2)) * 10 ** rng.uniform(-6, 3)
        if k % 97 == 0:
            c[2] = c[0] + (c[0] - c[2])  # diagonals 1-3 and 2-4 on parallel lines through degenerate quads
            c[3] = c[1] + (c[2] - c[0])
        h = np.column_stack([c, np.ones(4)])
        x = np.cross(np.cross(h[0], h[2]), np.cross(h[1], h[3]))
        ref = c.mean(axis=0) if abs(x[2]) < 1e-12 else x[:2] / x[2]
        assert np.array_equal(tags._diagonal_intersection(c), ref), c


def _frames(n: int) -> list[np.ndarray]:
    """Grey frames with a few tags each (some with none)."""
    rng = np.random.default_rng(5)
    out = []
    for i in range(n):
        poses = [_pose(*POSES[(i + j) % len(POSES)]) for j in range(i % 3)]
        img, _ = tags.render_tags((320, 240), K * [[0.5], [0.5], [1]], D, poses, list(range(i % 3)), 0.06,
                                  noise_sigma=2.0, rng=rng)
        out.append(img)
    return out


def test_threaded_detection_equals_sequential_and_keeps_the_error_order() -> None:
    from ppoe_core.errors import BagError
    from ppoe_core.sensing.tag_rows import detections_in_images

    frames = _frames(12)
    seq = list(detections_in_images(frames.__getitem__, len(frames), "tag36h11", "subpix", workers=1))
    assert sum(len(d) for d in seq) >= 8
    for workers in (2, 3):
        par = list(detections_in_images(frames.__getitem__, len(frames), "tag36h11", "subpix", workers=workers))
        assert [[d.id for d in ds] for ds in par] == [[d.id for d in ds] for ds in seq]
        for a, b in zip(par, seq):
            for da, db in zip(a, b):
                assert np.array_equal(da.corners, db.corners) and np.array_equal(da.centre, db.centre)

    def decode(i: int) -> np.ndarray:
        if i == 7:
            raise BagError(f"topic /camera/image_raw/compressed: message {i} is not a decodable png image")
        return frames[i]

    got = []
    gen = detections_in_images(decode, len(frames), "tag36h11", "subpix", workers=2)
    with pytest.raises(BagError, match="message 7 "):
        for ds in gen:
            got.append(ds)
    assert len(got) == 7  # images 0..6 first, then image 7's error, as in the sequential loop
