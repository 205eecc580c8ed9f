"""The detector's smallest candidate (``ppoe_core.sensing.tags.min_perimeter_rate``): dropping the quads smaller than
one pixel per cell before identification loses no tag OpenCV would have decoded, and moves no corner.

Tags are rendered small (6-16 px black square, random angle and sub-pixel position, 4x supersampled, blur 0.8 px,
noise 2 grey levels) and detected by OpenCV's default detector (``minMarkerPerimeterRate`` 0.03: 19.2 px of
perimeter on 640 px) and by the project's (:func:`ppoe_core.sensing.tags.opencv_detector`)."""

from __future__ import annotations

import numpy as np
import pytest

from ppoe_core.sensing import tags

cv2 = pytest.importorskip("cv2")

W, H = 640, 480
SIDES = np.arange(6.0, 16.01, 1.0)
TRIALS = 12


def _small_tag_image(d: object, tag_id: int, side: float, rng: np.random.Generator) -> np.ndarray:
    """A 640x480 grey image with one tag whose black square is ``side`` pixels."""
    cells = int(d.markerSize) + 2  # type: ignore[attr-defined]
    px = 10
    marker = np.pad(cv2.aruco.generateImageMarker(d, tag_id, cells * px, borderBits=1), px, constant_values=255)
    half = marker.shape[0] / 2.0
    ss = 4
    A = cv2.getRotationMatrix2D((half, half), float(rng.uniform(0.0, 90.0)), side / (cells * px))
    A[:, 2] += [rng.uniform(100, W - 100) - half, rng.uniform(100, H - 100) - half]
    big = cv2.warpAffine(marker, A * ss, (W * ss, H * ss), flags=cv2.INTER_LINEAR, borderValue=200)
    img = cv2.GaussianBlur(cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA), (0, 0), 0.8)
    return np.clip(img + rng.normal(0.0, 2.0, img.shape), 0, 255).astype(np.uint8)


def test_the_bound_loses_no_tag_opencv_decodes_and_moves_no_corner() -> None:
    rng = np.random.default_rng(7)
    d = tags.aruco_dictionary("tag36h11")
    default = cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters())
    assert default.getDetectorParameters().minMarkerPerimeterRate == pytest.approx(0.03)
    ours, _ = tags.opencv_detector("tag36h11", "none", W)
    assert ours.getDetectorParameters().minMarkerPerimeterRate == pytest.approx(32.0 / W)  # 8 cells x 1 px x 4
    found_default: dict[float, int] = {}
    for side in SIDES:
        n = 0
        for _ in range(TRIALS):
            tag_id = int(rng.integers(0, 587))
            img = _small_tag_image(d, tag_id, float(side), rng)
            c0, ids0, _ = default.detectMarkers(img)
            c1, ids1, _ = ours.detectMarkers(img)
            got0 = [] if ids0 is None else ids0.ravel().tolist()
            got1 = [] if ids1 is None else ids1.ravel().tolist()
            assert got1 == got0, f"side {side} px: default found {got0}, ours {got1}"
            for a, b in zip(c0, c1):
                np.testing.assert_array_equal(a, b)
            n += tag_id in got0
        found_default[float(side)] = n
    # OpenCV decodes nothing below one pixel per cell (the bound), and does decode tags of about 2 px per cell:
    # the experiment can tell a bound that drops decodable tags from one that does not
    assert sum(found_default[s] for s in SIDES if s < 8.0) == 0
    assert found_default[16.0] >= TRIALS // 3


def test_opencv_default_rate_kept_where_stricter() -> None:
    d = tags.aruco_dictionary("tag36h11")
    assert tags.min_perimeter_rate(d, 0) == pytest.approx(0.03)
    assert tags.min_perimeter_rate(d, 640) == pytest.approx(0.05)
    assert tags.min_perimeter_rate(d, 1920) == pytest.approx(0.03)  # OpenCV's 57.6 px is the larger bound there
    small = tags.aruco_dictionary("tag16h5")  # 4x4 data bits: 6 cells across
    assert tags.min_perimeter_rate(small, 480) == pytest.approx(0.05)
    assert tags.min_perimeter_rate(small, 640) == pytest.approx(0.0375)


def test_detect_tags_uses_the_image_size() -> None:
    d = tags.aruco_dictionary("tag36h11")
    rng = np.random.default_rng(3)
    img = _small_tag_image(d, 5, 40.0, rng)
    found = tags.detect_tags(img, "tag36h11", "subpix")
    assert [t.id for t in found] == [5]
    detector, _ = tags.opencv_detector("tag36h11", "subpix", W)
    assert detector.getDetectorParameters().minMarkerPerimeterRate == pytest.approx(0.05)
