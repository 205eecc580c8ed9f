"""Reliability odds and ends of issue 13 that belong to no single module's tests."""

from __future__ import annotations

import numpy as np


def test_broken_png_decodes_to_none_without_opencv_log_lines(capfd):
    """OpenCV's ``[ERROR:0@...] IHDR chunk shall be first`` must not reach the user's terminal."""
    import cv2

    from ppoe_core.io.series import decode_compressed

    ok, buf = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    assert ok
    good = buf.tobytes()
    broken = bytearray(good)
    broken[12:16] = b"XXXX"  # the IHDR chunk type
    assert decode_compressed(bytes(broken)) is None
    assert decode_compressed(good).shape == (8, 8)
    out, err = capfd.readouterr()
    assert "IHDR" not in err and "ERROR" not in err and out == ""
