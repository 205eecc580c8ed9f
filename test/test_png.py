"""ppoe_core.io.png.decode_png against cv2.imdecode: the same pixels wherever it decodes, None (OpenCV decides)
for every other PNG and for damaged bytes; never an image where OpenCV refuses the bytes."""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest

from ppoe_core.io.bagio import read_bag
from ppoe_core.io import png
from ppoe_core.io.png import decode_png

cv2 = pytest.importorskip("cv2")
REPO = Path(__file__).resolve().parents[1]


def _cv(data: bytes) -> np.ndarray | None:
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:  # e.g. no bytes at all
        return None
    return None if img is None or img.size == 0 else img


def _agrees(data: bytes) -> bool:
    """decode_png gives None, or exactly what OpenCV gives (and OpenCV gives an image)."""
    fast, ref = decode_png(data), _cv(data)
    if fast is None:
        return True
    return (ref is not None and fast.dtype == ref.dtype and fast.shape == ref.shape and np.array_equal(fast, ref)
            and fast.flags.c_contiguous)


def _image(rng: np.random.Generator, h: int, w: int, ch: int) -> np.ndarray:
    """Smooth gradients with noise and flat patches (compressible like camera frames, every byte value)."""
    yy, xx = np.mgrid[0:h, 0:w]
    base = (3 * xx + 5 * yy)[..., None] + 40 * np.arange(ch)[None, None, :]
    img = (base + rng.normal(0, 6, (h, w, ch))).astype(np.int64) % 256
    img[h // 3: h // 2, w // 4: w // 2] = 255
    img = img.astype(np.uint8)
    return img[..., 0] if ch == 1 else img


def test_images_of_the_shipped_bags_decode_to_opencv_pixels() -> None:
    n = 0
    for bag in ("table1_exp1", "table1_exp2", "effect_camera_extrinsics"):
        imgs = read_bag(REPO / "bags" / bag, topics=["/camera/image_raw/compressed"]).images
        for data in imgs.data:
            assert decode_png(data) is not None and _agrees(data)  # OpenCV-written: always the fast path
            n += 1
    assert n >= 80


@pytest.mark.parametrize("ch", [1, 3])
def test_opencv_encodings_decode_to_opencv_pixels_or_are_left_to_opencv(ch: int) -> None:
    rng = np.random.default_rng(ch)
    fast = 0
    sizes = [(1, 1), (1, 7), (9, 1), (37, 53), (120, 160)]
    settings = [[], [cv2.IMWRITE_PNG_COMPRESSION, 0], [cv2.IMWRITE_PNG_COMPRESSION, 9],
                [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY],
                [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE],
                [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_FIXED]]
    settings += [[cv2.IMWRITE_PNG_FILTER, f] for f in (cv2.IMWRITE_PNG_FILTER_NONE, cv2.IMWRITE_PNG_FILTER_SUB,
                                                       cv2.IMWRITE_PNG_FILTER_UP, cv2.IMWRITE_PNG_FILTER_AVG,
                                                       cv2.IMWRITE_PNG_FILTER_PAETH, cv2.IMWRITE_PNG_ALL_FILTERS)]
    for h, w in sizes:
        img = _image(rng, h, w, ch)
        for params in settings:
            ok, buf = cv2.imencode(".png", img, params)
            data = buf.tobytes()
            assert _agrees(data), (h, w, params)
            if decode_png(data) is not None:
                fast += 1
                np.testing.assert_array_equal(decode_png(data), img)
    assert fast >= 30  # the plain (None / Sub) encodings take the fast path
    img = _image(rng, 60, 80, ch)
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_PAETH])
    assert decode_png(buf.tobytes()) is None  # another filter: OpenCV's


def test_other_pngs_and_other_formats_are_left_to_opencv() -> None:
    rng = np.random.default_rng(4)
    for img in (_image(rng, 20, 30, 3).astype(np.uint16) * 200,  # 16 bit
                np.dstack([_image(rng, 20, 30, 3), np.full((20, 30), 7, np.uint8)])):  # BGRA
        data = cv2.imencode(".png", img)[1].tobytes()
        assert decode_png(data) is None and _cv(data) is not None
    assert decode_png(cv2.imencode(".jpg", _image(rng, 20, 30, 1))[1].tobytes()) is None
    assert decode_png(b"") is None and decode_png(b"\x89PNG\r\n\x1a\n") is None


@pytest.fixture(params=["installed", "zlib"])
def inflate(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The inflate :func:`decode_png` uses: the installed one (ISA-L's) or Python's ``zlib`` (the fallback)."""
    if request.param == "zlib":
        monkeypatch.setattr(png, "_decompressobj", zlib.decompressobj)
    return str(request.param)


def test_isal_inflates_when_installed() -> None:
    isal = pytest.importorskip("isal")
    assert png.INFLATE == "isal" and isal is not None


def test_isal_and_zlib_inflate_the_same_pixels(monkeypatch: pytest.MonkeyPatch) -> None:
    data = [d for bag in ("table1_exp1", "effect_camera_extrinsics")
            for d in read_bag(REPO / "bags" / bag, topics=["/camera/image_raw/compressed"]).images.data]
    fast = [decode_png(d) for d in data]
    monkeypatch.setattr(png, "_decompressobj", zlib.decompressobj)
    slow = [decode_png(d) for d in data]
    assert len(fast) >= 30 and all(a is not None and b is not None and np.array_equal(a, b) for a, b in zip(fast, slow))


def test_damaged_bytes_never_decode_differently_from_opencv(inflate: str) -> None:
    rng = np.random.default_rng(5)
    data = cv2.imencode(".png", _image(rng, 12, 17, 1))[1].tobytes()
    assert decode_png(data) is not None
    cases = [data[:n] for n in range(len(data))]
    cases += [data + b"\x00", data + data]
    for i in range(len(data)):
        for flip in (0x01, 0xFF):
            cases.append(data[:i] + bytes([data[i] ^ flip]) + data[i + 1:])
    refused = 0
    for bad in cases:
        assert _agrees(bad), bad
        refused += decode_png(bad) is None
    assert refused >= len(cases) - 3  # CRC, length and structure checks leave damaged files to OpenCV
