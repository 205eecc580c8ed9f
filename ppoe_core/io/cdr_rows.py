"""The fields of ``read_bag``'s hot contract messages straight from their raw CDR bytes (no typed messages).

rosbags' typed deserialisation builds a Python object per message (and per nested header, pose, point ...):
about 60 us for a ``JointState``, most of ``read_bag`` on a long bag.  These parsers read the same fields
with ``struct`` / ``numpy.frombuffer`` for ``sensor_msgs/JointState``, ``CompressedImage``,
``geometry_msgs/PoseStamped``, ``PointStamped``, ``WrenchStamped`` and ``PoseWithCovarianceStamped``.

They accept a strict subset of what :func:`ppoe_core.io.messages.deserialize` accepts: little-endian CDR
(XCDR1), every length inside the bytes, strings NUL-terminated UTF-8, at most 8 trailing bytes of padding
or only zero bytes after the last field (the rule of ``deserialize``).  Anything else raises
:class:`Fallback` (or a ``struct`` / ``numpy`` / Unicode error, see :data:`PARSE_ERRORS`): the caller then
runs the typed deserialiser, which accepts or rejects the message with its own error.  The values are the
ones the typed path gives (``test/test_cdr_rows.py`` compares both on every message of the shipped bags and
on malformed bytes).

Layout (OMG CDR, as :mod:`ppoe_core.io.cdr`): 4-byte encapsulation header, then the fields, each aligned to
its size relative to the end of the header; a string is ``uint32 length`` (NUL included) + bytes; a sequence
``uint32 count`` + elements (a ``float64`` sequence aligned to 8 only when not empty).
"""

from __future__ import annotations

import struct
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.errors import MeasurementError
from ppoe_core.io import cdr
from ppoe_core.io.cdr import align

__all__ = ["Fallback", "PARSE_ERRORS", "parse_joint_state", "parse_compressed_image", "parse_pose",
           "parse_point", "parse_wrench", "parse_pose_cov"]

_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_D3 = struct.Struct("<3d")
_D6 = struct.Struct("<6d")
_D7 = struct.Struct("<7d")


_EMPTY = np.zeros(0)
_EMPTY.flags.writeable = False


class Fallback(Exception):
    """The bytes are left to the typed deserialiser (big endian, truncated, a bad string ...)."""


#: errors of a parser that mean "use the typed deserialiser" (never a contract violation)
PARSE_ERRORS = (Fallback, MeasurementError, struct.error, UnicodeDecodeError, ValueError, IndexError)


def _string(raw: bytes, pos: int) -> tuple[str, int]:
    """The CDR string at ``pos`` (aligned here) -> (text, position after it): :mod:`ppoe_core.io.cdr`'s reader
    (length inside the bytes, NUL-terminated UTF-8, as rosbags' ``check_string``)."""
    return cdr._string(raw, align(pos, 4), "string")


def _header(raw: bytes) -> tuple[float, str, int]:
    """``header.stamp`` in seconds (as ``messages.stamp_seconds``), ``header.frame_id`` and the position after it."""
    if raw[:2] != b"\x00\x01":  # not little-endian CDR: the typed path handles (or refuses) it
        raise Fallback
    sec, nsec = _STAMP.unpack_from(raw, 4)
    frame, pos = _string(raw, 12)
    return float(sec) + 1e-9 * float(nsec), frame, pos


def _end(raw: bytes, pos: int) -> None:
    """``deserialize``'s rule after the last field: at most 8 trailing bytes of any content, or only zeros."""
    if pos > len(raw) or (len(raw) - pos > 8 and any(raw[pos:])):
        raise Fallback


def _names(raw: bytes, pos: int) -> tuple[tuple[str, ...], int]:
    """The ``string[]`` at ``pos`` -> (names, position after it): :mod:`ppoe_core.io.cdr`'s reader (the names
    cached by their bytes: a publisher sends the same names every time)."""
    return cdr._names(raw, align(pos, 4))


class _Layout(NamedTuple):
    """Where the fields of a ``JointState`` lie: a message of the same size and the same bytes but for the stamp
    and the float64 values (same encapsulation, frame_id, names and value counts) has the same fields there."""

    size: int
    head: bytes  # encapsulation header
    body: bytes  # from frame_id up to the position count included
    frame: str
    names: tuple[str, ...]
    seqs: tuple[tuple[int, int, int], ...]  # (count offset, count, data offset) of position, velocity, effort
    end: int


#: the layout of the last JointState parsed in full
_last_layout: list[_Layout | None] = [None]


def _sequence(raw: bytes, pos: int) -> tuple[tuple[int, int, int], int]:
    """A ``float64`` sequence at ``pos`` -> ((count offset, count, data offset), position after it)."""
    c = align(pos, 4)
    (n,) = _U32.unpack_from(raw, c)
    d = align(c + 4, 8) if n else c + 4
    if d + 8 * n > len(raw):
        raise Fallback
    return (c, n, d), d + 8 * n


def _values(raw: bytes, seq: tuple[int, int, int]) -> np.ndarray:
    return np.frombuffer(raw, dtype="<f8", count=seq[1], offset=seq[2]) if seq[1] else _EMPTY


def parse_joint_state(raw: bytes) -> tuple[float, str, tuple[str, ...], np.ndarray, np.ndarray, np.ndarray]:
    """``sensor_msgs/JointState`` -> (stamp [s], frame_id, names, position, velocity, effort).

    A message laid out as the previous one (:class:`_Layout`: a publisher sends the same frame and names every
    time) is read at the previous offsets, after comparing the bytes that decide them.
    """
    lay = _last_layout[0]
    if lay is not None and len(raw) == lay.size and raw.startswith(lay.body, 12) and raw.startswith(lay.head):
        p, v, e = lay.seqs
        if _U32.unpack_from(raw, v[0])[0] == v[1] and _U32.unpack_from(raw, e[0])[0] == e[1]:
            sec, nsec = _STAMP.unpack_from(raw, 4)
            _end(raw, lay.end)
            return float(sec) + 1e-9 * float(nsec), lay.frame, lay.names, _values(raw, p), _values(raw, v), \
                _values(raw, e)
    stamp, frame, pos = _header(raw)
    names, pos = _names(raw, pos)
    p, pos = _sequence(raw, pos)
    v, pos = _sequence(raw, pos)
    e, pos = _sequence(raw, pos)
    _end(raw, pos)
    _last_layout[0] = _Layout(len(raw), raw[:4], raw[12:p[0] + 4], frame, names, (p, v, e), pos)
    return stamp, frame, names, _values(raw, p), _values(raw, v), _values(raw, e)


def parse_compressed_image(raw: bytes) -> tuple[float, str, str, memoryview]:
    """``sensor_msgs/CompressedImage`` -> (stamp, frame_id, format, data as a view of ``raw``)."""
    stamp, frame, pos = _header(raw)
    fmt, pos = _string(raw, pos)
    pos = align(pos, 4)
    (n,) = _U32.unpack_from(raw, pos)
    pos += 4
    if pos + n > len(raw):
        raise Fallback
    _end(raw, pos + n)
    return stamp, frame, fmt, memoryview(raw)[pos:pos + n]


def _fixed(raw: bytes, layout: struct.Struct) -> tuple[float, str, tuple[float, ...], int]:
    """Header then ``layout``'s float64 values (aligned to 8) -> (stamp, frame_id, values, position after)."""
    stamp, frame, pos = _header(raw)
    pos = align(pos, 8)
    return stamp, frame, layout.unpack_from(raw, pos), pos + layout.size


def parse_pose(raw: bytes) -> tuple[float, str, tuple[float, ...]]:
    """``geometry_msgs/PoseStamped`` -> (stamp, frame_id, (px, py, pz, qx, qy, qz, qw))."""
    stamp, frame, values, pos = _fixed(raw, _D7)
    _end(raw, pos)
    return stamp, frame, values


def parse_point(raw: bytes) -> tuple[float, str, tuple[float, ...]]:
    """``geometry_msgs/PointStamped`` -> (stamp, frame_id, (x, y, z))."""
    stamp, frame, values, pos = _fixed(raw, _D3)
    _end(raw, pos)
    return stamp, frame, values


def parse_wrench(raw: bytes) -> tuple[float, str, tuple[float, ...]]:
    """``geometry_msgs/WrenchStamped`` -> (stamp, frame_id, (fx, fy, fz, tx, ty, tz))."""
    stamp, frame, values, pos = _fixed(raw, _D6)
    _end(raw, pos)
    return stamp, frame, values


def parse_pose_cov(raw: bytes) -> tuple[float, str, tuple[float, ...], np.ndarray]:
    """``geometry_msgs/PoseWithCovarianceStamped`` -> (stamp, frame_id, pose as :func:`parse_pose`,
    covariance (36,) read-only view)."""
    stamp, frame, values, pos = _fixed(raw, _D7)
    if pos + 8 * 36 > len(raw):
        raise Fallback
    cov = np.frombuffer(raw, dtype="<f8", count=36, offset=pos)
    _end(raw, pos + 8 * 36)
    return stamp, frame, values, cov


def as_bytes(data: Any) -> bytes:
    """The message bytes as ``bytes`` (the readers give ``bytes`` or a ``memoryview``)."""
    return data if type(data) is bytes else bytes(data)
