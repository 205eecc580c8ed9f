"""PNG decoding without libpng for the PNGs OpenCV writes (``cv2.imencode``: every row "Sub"-filtered).

``cv2.imdecode`` of a 640x480 grey PNG of the bench bag costs 1.9-2.1 ms; the inflate of its zlib stream alone
costs 1.25 ms with Python's ``zlib`` and 0.61 ms with ISA-L's (``isal.isal_zlib`` of the ``isal`` package: the
same bytes, GIL released).  That inflate plus a compiled loop inverting the "Sub" filter
(:mod:`ppoe_core.io.png_kernel`) gives the same pixels in about 1 ms (one thread; without ``isal`` installed
Python's ``zlib`` inflates, about 1.6 ms).  :func:`decode_png` handles only the plain case: 8-bit grey or RGB,
not interlaced, only the chunks ``IHDR``, ``IDAT`` and ``IEND`` (each CRC checked), rows filtered with "None" or
"Sub", one complete zlib stream of exactly the image's size, nothing after ``IEND``.  For anything else it
returns None and the caller uses ``cv2.imdecode``, which then decodes or refuses the bytes itself.
``test/test_png.py`` compares both on the shipped bags' images, OpenCV-encoded images and damaged bytes.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

try:  # ISA-L's inflate: twice as fast as zlib's on these streams, the same bytes (test/test_png.py)
    from isal import isal_zlib

    _decompressobj: Callable[[], Any] = isal_zlib.decompressobj
    _INFLATE_ERRORS: tuple[Any, ...] = (isal_zlib.error, zlib.error)
    #: the library inflating the IDAT stream: ``"isal"`` or ``"zlib"``
    INFLATE = "isal"
except ImportError:  # pragma: no cover - isal is in setup.py's install_requires
    _decompressobj = zlib.decompressobj
    _INFLATE_ERRORS = (zlib.error,)
    INFLATE = "zlib"

__all__ = ["decode_png", "INFLATE"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHUNK = struct.Struct(">I4s")
_CRC = struct.Struct(">I")
_IHDR = struct.Struct(">IIBBBBB")
#: larger images are left to OpenCV (its own size limits apply)
_MAX_PIXELS = 1 << 26


def _chunks(data: bytes) -> tuple[tuple[int, ...], list[memoryview]] | None:
    """``IHDR`` fields and the ``IDAT`` bodies, or None unless the file is exactly IHDR, IDAT..., IEND."""
    view = memoryview(data)
    pos, n = len(_SIGNATURE), len(data)
    header = None
    idat: list[memoryview] = []
    while pos + 12 <= n:
        length, ctype = _CHUNK.unpack_from(data, pos)
        end = pos + 12 + length
        if end > n:
            return None
        body = view[pos + 8:end - 4]
        if _CRC.unpack_from(data, end - 4)[0] != zlib.crc32(body, zlib.crc32(ctype)):
            return None
        if ctype == b"IHDR" and header is None and length == _IHDR.size:
            header = _IHDR.unpack(body)
        elif ctype == b"IDAT" and header is not None:
            idat.append(body)
        elif ctype == b"IEND" and header is not None and idat and length == 0:
            return (header, idat) if end == n else None
        else:
            return None
        pos = end
    return None


def decode_png(data: bytes) -> np.ndarray | None:
    """The pixels of a plain 8-bit PNG as ``cv2.imdecode(..., IMREAD_UNCHANGED)`` gives them: (H, W) grey or
    (H, W, 3) BGR uint8; None for any other PNG (see the module docstring) and for bytes that are no PNG."""
    if not data.startswith(_SIGNATURE):
        return None
    found = _chunks(data)
    if found is None:
        return None
    (w, h, depth, color, compression, filtering, interlace), idat = found
    if depth != 8 or color not in (0, 2) or compression or filtering or interlace or not 0 < w * h <= _MAX_PIXELS:
        return None
    ch = 1 if color == 0 else 3
    z = _decompressobj()
    try:
        raw = b"".join([z.decompress(b) for b in idat]) + z.flush()
    except _INFLATE_ERRORS:
        return None
    if not z.eof or z.unused_data or len(raw) != h * (1 + w * ch):
        return None
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(h, 1 + w * ch)
    if np.any(rows[:, 0] > 1):  # Up, Average, Paeth (or no filter type): left to libpng
        return None
    from ppoe_core.io.png_kernel import unfilter_sub

    img = unfilter_sub(rows, ch)
    return np.ascontiguousarray(img.reshape(h, w, 3)[:, :, ::-1]) if ch == 3 else img
