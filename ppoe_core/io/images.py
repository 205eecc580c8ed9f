"""Image messages -> pixels, and the checks of an image against its camera: the tag bearing node's and
``ppoe evaluate``'s image input (no ROS: a message is read through its fields).

* :func:`decode_image`: ``CompressedImage`` (PNG / JPEG) or raw ``Image`` (mono8/16, bgr8, rgb8, bgra8, rgba8 ...)
  -> uint8 grey or BGR, the size checked from the header before decoding;
* :func:`image_size_from_header`: ``(width, height)`` of PNG / JPEG bytes without decoding;
* :func:`check_image_size`, :func:`camera_from_info`: the image against its ``camera_info``;
* :func:`draw_detections`: the debug image.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ppoe_core.errors import MeasurementError
from ppoe_core.io.series import decode_compressed

__all__ = ["DEFAULT_MAX_PIXELS", "decode_image", "image_size_from_header", "check_image_size", "camera_from_info",
           "draw_detections"]

#: an image with more pixels (from its header) is refused before decoding
DEFAULT_MAX_PIXELS = 4096 * 4096

_CHANNELS = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3, "8UC3": 3, "bgra8": 4, "rgba8": 4, "8UC4": 4,
             "mono16": 1, "16UC1": 1}


def decode_image(msg: Any, compressed: bool, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """An image message -> uint8 grey (H, W) or BGR (H, W, 3) array.

    ``msg`` has the fields of ``sensor_msgs/CompressedImage`` (``data``, ``format``; ``compressed`` true) or of
    ``sensor_msgs/Image`` (``data``, ``width``, ``height``, ``step``, ``encoding``, ``is_bigendian``), read as
    plain attributes (a ROS message or any record with them).  The size is checked from the PNG / JPEG header
    (or the ``Image`` fields) before decoding: more than ``max_pixels`` pixels is refused (a small file that
    decodes to a huge image would stall the node).

    Raises
    ------
    MeasurementError
        Empty data, too many pixels, undecodable compressed data, unknown encoding or inconsistent size.
    """
    data = bytes(msg.data)
    if not data:
        raise MeasurementError("empty image (no data)")
    size = image_size_from_header(data) if compressed else (int(msg.width), int(msg.height))
    if size is not None and size[0] * size[1] > max_pixels:
        raise MeasurementError(f"image of {size[0]}x{size[1]} pixels (from its header) is larger than "
                               f"max_image_pixels = {max_pixels}: not decoded")
    if compressed:
        img = decode_compressed(data)
        if img is None:
            raise MeasurementError(f"cannot decode compressed image (format '{msg.format}', {len(data)} bytes)")
        return _to_uint8(img)
    enc = msg.encoding
    ch = _CHANNELS.get(enc)
    if ch is None:
        raise MeasurementError(f"unsupported encoding '{enc}' (known: {sorted(_CHANNELS)})")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    depth = 2 if "16" in enc else 1
    if h <= 0 or w <= 0 or step < w * ch * depth or len(data) < step * h:
        raise MeasurementError(f"image {w}x{h} step {step} encoding {enc} does not fit {len(data)} bytes")
    dtype = np.dtype(">u2" if msg.is_bigendian else "<u2") if depth == 2 else np.uint8
    rows = np.frombuffer(data, np.uint8, count=step * h).reshape(h, step)[:, : w * ch * depth]
    img = rows.copy().view(dtype).reshape(h, w, ch) if ch > 1 else rows.copy().view(dtype).reshape(h, w)
    if enc in ("rgb8",):
        img = img[..., ::-1]
    elif enc in ("rgba8",):
        img = img[..., [2, 1, 0]]
    elif enc in ("bgra8", "8UC4"):
        img = img[..., :3]
    return _to_uint8(img)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    """8-bit grey or BGR (16-bit scaled down, alpha and a single channel axis dropped)."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.dtype != np.uint8:
        raise MeasurementError(f"unsupported pixel type {img.dtype}")
    return np.ascontiguousarray(img)


def image_size_from_header(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG IHDR or a JPEG SOF header without decoding; None if not found."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if data[:2] == b"\xff\xd8":  # JPEG: walk the markers to the first start-of-frame
        i = 2
        while i + 9 < len(data) and data[i] == 0xFF:
            marker, seg = data[i + 1], struct.unpack(">H", data[i + 2:i + 4])[0]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                h, w = struct.unpack(">HH", data[i + 5:i + 9])
                return int(w), int(h)
            i += 2 + seg
    return None


def check_image_size(image: np.ndarray, info_size: tuple[int, int] | None) -> None:
    """An image must have the size its ``camera_info`` gives (else the intrinsics do not apply).

    Raises
    ------
    MeasurementError
        Naming both sizes.
    """
    if info_size is None or info_size == (0, 0):
        return
    h, w = image.shape[:2]
    if (w, h) != info_size:
        raise MeasurementError(f"image is {w}x{h} but camera_info gives {info_size[0]}x{info_size[1]}: "
                               "its intrinsics do not apply, image not used")


def camera_from_info(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """``CameraInfo`` fields (``k``, ``d``, ``distortion_model``, as attributes) -> ``(K (3,3), D (k,))``.

    Raises
    ------
    MeasurementError
        K with zero / non-finite focal lengths, non-finite D, or a distortion model other
        than ``plumb_bob`` / ``rational_polynomial`` (or empty with all-zero D).
    """
    K = np.asarray(msg.k, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] == 0:
        raise MeasurementError(f"camera_info K is not a camera matrix (fx = {K[0, 0]}, fy = {K[1, 1]})")
    K = K / K[2, 2]
    D = np.asarray(msg.d, dtype=float).reshape(-1)
    if not np.all(np.isfinite(D)):
        raise MeasurementError("camera_info D contains NaN/inf")
    model = msg.distortion_model
    if model not in ("plumb_bob", "rational_polynomial") and not (model == "" and not np.any(D)):
        raise MeasurementError(f"camera_info distortion_model '{model}' is not supported "
                               "(plumb_bob, rational_polynomial)")
    if D.size not in (0, 4, 5, 8, 12, 14):
        raise MeasurementError(f"camera_info D has {D.size} coefficients")
    return K, (D if D.size else np.zeros(5))


def draw_detections(image: np.ndarray, rows: np.ndarray, dets: list[Any]) -> np.ndarray:
    """BGR copy of ``image`` with the detected tags and the observed centres (``rows`` of
    :func:`ppoe_core.sensing.tag_rows.observe_tags`) drawn."""
    import cv2

    img = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    if dets:
        cv2.aruco.drawDetectedMarkers(img, [d.corners.reshape(1, 4, 2).astype(np.float32) for d in dets],
                                      np.array([[d.id] for d in dets], dtype=np.int32))
    for r in rows[rows[:, 1] == 0]:
        cv2.circle(img, (int(round(r[2])), int(round(r[3]))), 3, (0, 0, 255), -1)
    return img


