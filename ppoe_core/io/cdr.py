"""THE CDR reader and writer of the messages ppoe handles as raw bytes (ROS 2 XCDR1, little endian, as rclpy /
Fast DDS write them): table-driven, one schema per message type (:data:`SCHEMAS`), one reader (:func:`read`) and one
writer (:func:`write`) walking it.

Typed messages cost more than the work on them: rclpy's ``JointState`` deserialisation about 30 us, rosbags' about
60 us per message, building and serialising a pose 20-30 us; walking the bytes with ``struct`` takes a few.  Users:
the kinematics node (``JointState`` in, ``PoseWithCovarianceStamped`` out: :func:`parse_joint_state`,
:class:`PoseCovarianceWriter`), TF (``tf2_msgs/TFMessage`` out, :func:`tf_message`), and the bag reader
(:func:`parse_fields`: the fields of ``JointState``, ``CompressedImage``, ``PoseStamped``, ``PointStamped``,
``WrenchStamped``, ``PoseWithCovarianceStamped``).  The kinematics node's compiled per-message path
(:mod:`ppoe_core.io.joint_pose`) reads the ``JointState`` header and names itself, with :func:`align`'s rule; it is
tested to give the same bytes out.

Layout (OMG CDR): a 4-byte encapsulation header (``00 01 00 00`` = CDR little endian), then the fields, each aligned to
its size (4 for lengths and ``int32``, 8 for ``float64``) relative to the end of the header; a string is ``uint32
length`` (with the terminating NUL) + bytes; a sequence ``uint32 count`` + elements (``float64`` elements aligned to 8
only when there are any).  The reader accepts a strict subset of what rosbags accepts: every length inside the bytes,
strings NUL-terminated UTF-8; after the last field at most 8 trailing bytes of padding or only zero bytes (the rule of
``ppoe_core.io.messages.deserialize``, :func:`check_end`).  Anything else raises :class:`CdrError` naming the field
and the byte offset (the bag reader then runs the typed deserialiser, which accepts or refuses with its own error).
Checked against rclpy's and rosbags' serialisation in ``test/test_cdr.py`` and ``test/test_cdr_rows.py``.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.errors import MeasurementError

__all__ = ["CDR_LE_HEADER", "SCHEMAS", "CdrError", "PARSE_ERRORS", "align", "read", "write", "check_end",
           "parse_fields", "parse_joint_state", "JointStateCdr", "joint_state_names_block", "PoseCovarianceWriter",
           "tf_message", "as_bytes", "JointStateBlock", "joint_state_block", "joint_state_rows_block",
           "joint_state_block_at", "JointStateLayout", "joint_state_layout", "JointStateReader", "HeaderBlock",
           "header_rows_block", "restamped_stamps", "header_stamps"]

CDR_LE_HEADER = b"\x00\x01\x00\x00"
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_F64 = {n: struct.Struct(f"<{n}d") for n in (3, 6, 7)}

#: field kinds of a schema: a header (stamp + frame_id), a string, a sequence of strings / float64 / uint8,
#: ``n`` float64 values in a row (a point 3, a wrench 6, a pose 7 = position + quaternion xyzw, a covariance 36), and
#: a sequence of elements of a nested schema (``("seq", schema)``)
HEADER, STRING, STRINGS, F64S, U8S = "header", "string", "string[]", "float64[]", "uint8[]"

_TRANSFORM_STAMPED = (HEADER, STRING, 7)
#: the message types read or written as raw bytes
SCHEMAS: dict[str, tuple[Any, ...]] = {
    "sensor_msgs/msg/JointState": (HEADER, STRINGS, F64S, F64S, F64S),
    "sensor_msgs/msg/CompressedImage": (HEADER, STRING, U8S),
    "geometry_msgs/msg/PoseStamped": (HEADER, 7),
    "geometry_msgs/msg/PointStamped": (HEADER, 3),
    "geometry_msgs/msg/WrenchStamped": (HEADER, 6),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (HEADER, 7, 36),
    "tf2_msgs/msg/TFMessage": (("seq", _TRANSFORM_STAMPED),),
}
_JOINT_STATE = SCHEMAS["sensor_msgs/msg/JointState"]
_EMPTY = np.zeros(0)
_EMPTY.flags.writeable = False


class CdrError(MeasurementError):
    """Bytes that are not a message of the schema (names the field and the byte offset)."""


#: errors of :func:`parse_fields` that mean "use the typed deserialiser" (never a contract violation)
PARSE_ERRORS = (CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError)


def align(pos: int, a: int) -> int:
    """``pos`` (absolute) rounded up to a multiple of ``a`` relative to the end of the 4-byte header."""
    return pos + (-(pos - 4)) % a


def as_bytes(data: Any) -> bytes:
    """The message bytes as ``bytes`` (the readers give ``bytes`` or a ``memoryview``)."""
    return data if type(data) is bytes else bytes(data)


# ------------------------------------------------------------------------------------------------ reading
def _u32(raw: bytes, pos: int, what: str) -> tuple[int, int]:
    """The ``uint32`` at ``pos`` (aligned here) and the position after it."""
    pos = align(pos, 4)
    if pos + 4 > len(raw):
        raise CdrError(f"{what}: truncated at byte {pos} of {len(raw)}")
    return _U32.unpack_from(raw, pos)[0], pos + 4


def _string(raw: bytes, pos: int, what: str) -> tuple[str, int]:
    """One string at ``pos`` -> (text, position after it)."""
    n, start = _u32(raw, pos, what)
    end = start + n
    if n == 0 or end > len(raw) or raw[end - 1] != 0:
        raise CdrError(f"{what} has length {n} at byte {start - 4} of {len(raw)} (or is not NUL-terminated)")
    return raw[start:end - 1].decode("utf-8"), end


_names_cache: dict[bytes, tuple[str, ...]] = {}


def _strings(raw: bytes, pos: int, what: str) -> tuple[tuple[str, ...], int]:
    """A string sequence (a publisher sends the same joint names every time: cached by their bytes)."""
    count, start = _u32(raw, pos, what)
    pos = start
    for k in range(count):
        n, p = _u32(raw, pos, f"{what}[{k}]")
        pos = p + n
        if n == 0 or pos > len(raw):
            raise CdrError(f"{what}[{k}] has length {n} at byte {p - 4} of {len(raw)}")
    key = raw[start:pos]
    names = _names_cache.get(key)
    if names is None:
        out, p = [], start
        for k in range(count):
            name, p = _string(raw, p, f"{what}[{k}]")
            out.append(name)
        names = tuple(out)
        if len(_names_cache) > 64:
            _names_cache.clear()
        _names_cache[key] = names
    return names, pos


def _seq(raw: bytes, pos: int, what: str, itemsize: int) -> tuple[tuple[int, int], int]:
    """A sequence of ``itemsize``-byte numbers -> ((data offset, count), position after it)."""
    n, pos = _u32(raw, pos, what)
    if n and itemsize == 8:
        pos = align(pos, 8)
    if pos + itemsize * n > len(raw):
        raise CdrError(f"{what}: {n} values do not fit in {len(raw)} bytes")
    return (pos, n), pos + itemsize * n


def _field(kind: Any, raw: bytes, pos: int, what: str, spans: list[tuple[int, int, int]] | None = None
           ) -> tuple[Any, int]:
    """One field of a schema at ``pos`` -> (value, position after it); a number sequence appends ``(count offset,
    data offset, count)`` to ``spans``."""
    if kind == HEADER:
        pos = align(pos, 4)
        if pos + 8 > len(raw):
            raise CdrError(f"{what}.stamp: truncated at byte {pos} of {len(raw)}")
        sec, nsec = _STAMP.unpack_from(raw, pos)
        frame, pos = _string(raw, pos + 8, f"{what}.frame_id")
        return (sec, nsec, frame), pos
    if kind == STRING:
        return _string(raw, pos, what)
    if kind == STRINGS:
        return _strings(raw, pos, what)
    if kind in (F64S, U8S):
        (start, n), end = _seq(raw, pos, what, 8 if kind == F64S else 1)
        if spans is not None:
            spans.append((align(pos, 4), start, n))
        if kind == U8S:
            return memoryview(raw)[start:end], end
        return (np.frombuffer(raw, dtype="<f8", count=n, offset=start) if n else _EMPTY), end
    if isinstance(kind, int):
        pos = align(pos, 8)
        if pos + 8 * kind > len(raw):
            raise CdrError(f"{what}: {kind} float64 do not fit in {len(raw)} bytes")
        st = _F64.get(kind)
        return (st.unpack_from(raw, pos) if st is not None else np.frombuffer(raw, "<f8", kind, pos)), pos + 8 * kind
    count, pos = _u32(raw, pos, what)  # ("seq", element schema)
    items = []
    for k in range(count):
        item, pos = _fields(kind[1], raw, pos, f"{what}[{k}]", len(kind[1]))
        items.append(item)
    return items, pos


def _fields(schema: Sequence[Any], raw: bytes, pos: int, what: str, upto: int,
            spans: list[tuple[int, int, int]] | None = None) -> tuple[list[Any], int]:
    out = []
    for i, kind in enumerate(schema[:upto]):
        value, pos = _field(kind, raw, pos, f"{what} field {i}", spans)
        out.append(value)
    return out, pos


def read(schema: Sequence[Any], raw: bytes, upto: int | None = None, what: str = "CDR",
         spans: list[tuple[int, int, int]] | None = None) -> tuple[list[Any], int]:
    """The fields of ``raw`` by ``schema`` (the first ``upto``), and the position after the last read: a header as
    ``(sec, nsec, frame_id)``, a string, a tuple of strings, a read-only float64 view, a ``memoryview`` of bytes,
    a tuple of ``n`` float64 (a float64 view for 36), a list of nested field lists.

    Raises
    ------
    CdrError
        Not little-endian CDR, or a length that does not fit (names ``what``, the field and the byte offset).
    """
    if len(raw) < 4 or raw[:2] != CDR_LE_HEADER[:2]:
        raise CdrError(f"{what}: {len(raw)} bytes without the little-endian CDR header")
    return _fields(schema, raw, 4, what, len(schema) if upto is None else upto, spans)


def check_end(raw: bytes, pos: int) -> None:
    """``deserialize``'s rule after the last field: at most 8 trailing bytes of any content, or only zeros."""
    if pos > len(raw) or (len(raw) - pos > 8 and any(raw[pos:])):
        raise CdrError(f"{len(raw) - pos} trailing bytes after the last field")


# ------------------------------------------------------------------------------------------------ writing
def _put(kind: Any, value: Any, buf: bytearray) -> None:
    if kind == HEADER:
        stamp_ns, frame = value
        buf += bytes(-(len(buf) - 4) % 4)
        buf += _STAMP.pack(*divmod(int(stamp_ns), 1_000_000_000))
        _put(STRING, frame, buf)
    elif kind == STRING:
        raw = value.encode("utf-8") + b"\x00"
        buf += bytes(-(len(buf) - 4) % 4) + _U32.pack(len(raw)) + raw
    elif isinstance(kind, int):
        buf += bytes(-(len(buf) - 4) % 8)
        buf += np.asarray(value, dtype="<f8").reshape(kind).tobytes()
    else:  # ("seq", element schema)
        buf += bytes(-(len(buf) - 4) % 4) + _U32.pack(len(value))
        for item in value:
            for k, v in zip(kind[1], item):
                _put(k, v, buf)


def write(schema: Sequence[Any], values: Sequence[Any]) -> bytes:
    """A message's bytes from its field values (a header as ``(stamp_ns, frame_id)``; strings, float64 blocks and
    sequences of nested field tuples)."""
    buf = bytearray(CDR_LE_HEADER)
    for kind, value in zip(schema, values):
        _put(kind, value, buf)
    return bytes(buf)


def tf_message(frames: Sequence[tuple[str, str, np.ndarray]], stamp_ns: int) -> bytes:
    """``tf2_msgs/TFMessage`` of ``(parent, child, pose (7,) = x y z qx qy qz qw)`` transforms, all at
    ``stamp_ns``."""
    return write(SCHEMAS["tf2_msgs/msg/TFMessage"],
                 [[((stamp_ns, parent), child, pose) for parent, child, pose in frames]])


class PoseCovarianceWriter:
    """``geometry_msgs/PoseWithCovarianceStamped`` with a fixed ``header.frame_id``, written into one buffer.

    Parameters
    ----------
    frame_id : str
        ``header.frame_id`` of every message.
    """

    def __init__(self, frame_id: str) -> None:
        self._buf = bytearray(write(SCHEMAS["geometry_msgs/msg/PoseWithCovarianceStamped"],
                                    [(0, frame_id), np.zeros(7), np.zeros(36)]))
        # position (3), orientation x y z w (4), covariance (36, row-major, ROS convention)
        self._values = np.frombuffer(self._buf, dtype="<f8", count=43, offset=len(self._buf) - 8 * 43)
        #: the message buffer as bytes (uint8) and its 43 doubles, for a compiled writer
        #: (:mod:`ppoe_core.io.joint_pose`); :meth:`message` copies out what it wrote
        self.raw = np.frombuffer(self._buf, dtype=np.uint8)
        self.fields = self._values
        self.frame_id = frame_id

    def message(self) -> bytes:
        """The bytes of the buffer as last written (by :meth:`serialize` or a compiled writer)."""
        return bytes(self._buf)

    def serialize(self, stamp_ns: int, position: np.ndarray, quat_xyzw: np.ndarray, cov_ros: np.ndarray) -> bytes:
        """The message bytes: ``header.stamp`` (integer ns), position (3,), quaternion (4,) and the ROS-convention
        covariance (6, 6) or (36,) (docs/conventions.md sec. 2)."""
        _STAMP.pack_into(self._buf, 4, *divmod(int(stamp_ns), 1_000_000_000))
        v = self._values
        v[0:3] = position
        v[3:7] = quat_xyzw
        v[7:43] = cov_ros.reshape(36)
        return bytes(self._buf)


# ------------------------------------------------------------------------------------------------ JointState
@dataclass(frozen=True)
class JointStateCdr:
    """What :func:`parse_joint_state` returns (velocities and efforts are not read).

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp`` in integer nanoseconds.
    frame_id : str
    names : tuple of str
    positions : ndarray, shape (len(names),) or another length (the caller checks)
        A read-only view of the message bytes (copy it to keep it).
    """

    stamp_ns: int
    frame_id: str
    names: tuple[str, ...]
    positions: np.ndarray


def parse_joint_state(data: bytes) -> JointStateCdr:
    """Stamp, frame, names and positions of a serialised ``sensor_msgs/JointState`` (the kinematics node's input).

    Raises
    ------
    CdrError
        Not little-endian CDR, or truncated (names the field and the byte offset).
    """
    try:
        (sec, nsec, frame), names, positions = read(_JOINT_STATE, data, 3, "JointState CDR")[0]
    except UnicodeDecodeError as exc:
        raise CdrError(f"JointState CDR: a string is not UTF-8 ({exc})") from None
    return JointStateCdr(sec * 1_000_000_000 + nsec, frame, names, positions)


def joint_state_names_block(data: bytes) -> tuple[int, bytes]:
    """``(count, bytes of the name strings)`` of a serialised ``JointState`` that :func:`parse_joint_state` accepted:
    the name sequence as it is on the wire (what identifies a publisher's name layout)."""
    _, pos = read(_JOINT_STATE, data, 1)
    count, start = _u32(data, pos, "name")
    return count, bytes(data[start:_strings(data, pos, "name")[1]])


class JointStateLayout(NamedTuple):
    """Where the fields of a ``JointState`` lie (:func:`joint_state_layout`): a message of the same size whose
    length-prefixed fields (frame_id, the name count and each name, the position, velocity and effort counts) are
    the same bytes at the same offsets has its stamp and float64 values at the same offsets.  The alignment padding
    between fields is not compared: rclpy leaves it unset, and no field is read from it."""

    size: int
    segments: tuple[tuple[int, bytes], ...]  # (offset, bytes) of each length-prefixed field and value count
    frame: str
    names: tuple[str, ...]
    spans: tuple[tuple[int, int, int], ...]  # (count offset, data offset, count) of position, velocity, effort
    end: int

    def matches(self, raw: bytes) -> bool:
        """``raw`` is laid out as this (little-endian CDR, same size, same length-prefixed fields)."""
        return (len(raw) == self.size and raw.startswith(_CDR_LE)
                and all(raw.startswith(seg, at) for at, seg in self.segments))

    def positions(self, raw: bytes) -> np.ndarray:
        """The positions of a matching ``raw`` (a read-only view of its bytes)."""
        return _values(raw, self.spans[0])


_CDR_LE = CDR_LE_HEADER[:2]  # what read checks: CDR, little endian


def joint_state_layout(raw: bytes) -> JointStateLayout:
    """The layout of a ``JointState`` read in full (every field, the trailing bytes not checked).

    Raises
    ------
    CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError
        :data:`PARSE_ERRORS`: ``raw`` does not parse.
    """
    spans: list[tuple[int, int, int]] = []
    values, end = read(_JOINT_STATE, raw, spans=spans)
    segments, pos = [], 12
    for k in range(2 + len(values[1])):  # frame_id, the name count, each name
        pos = align(pos, 4)
        n = 0 if k == 1 else _U32.unpack_from(raw, pos)[0]
        segments.append((pos, bytes(raw[pos:pos + 4 + n])))
        pos += 4 + n
    segments += [(at, bytes(raw[at:at + 4])) for at, _, _ in spans]
    return JointStateLayout(len(raw), tuple(segments), values[0][2], tuple(values[1]), tuple(spans), end)


class JointStateReader:
    """:func:`parse_joint_state` with the layout of the last message remembered (a publisher's messages share one):
    a message laid out as the last one (:meth:`JointStateLayout.matches`) has its stamp and positions read at its
    offsets, the same values; any other is parsed in full and its layout remembered."""

    def __init__(self) -> None:
        self.layout: JointStateLayout | None = None

    def parse(self, raw: bytes) -> JointStateCdr:
        """The :class:`JointStateCdr` of ``raw`` (the errors of :func:`parse_joint_state`)."""
        lay = self.layout
        if lay is not None and lay.matches(raw):
            sec, nsec = _STAMP.unpack_from(raw, 4)
            return JointStateCdr(sec * 1_000_000_000 + nsec, lay.frame, lay.names, lay.positions(raw))
        msg = parse_joint_state(raw)
        try:
            self.layout = joint_state_layout(raw)
        except PARSE_ERRORS:  # velocities or efforts unreadable: parse_joint_state does not read them
            self.layout = None
        return msg


#: the layout of the last JointState the bag reader read in full
_last_layout: list[JointStateLayout | None] = [None]


def _values(raw: bytes, span: tuple[int, int, int]) -> np.ndarray:
    return np.frombuffer(raw, dtype="<f8", count=span[2], offset=span[1]) if span[2] else _EMPTY


def _joint_state_fields(raw: bytes) -> tuple[Any, ...]:
    lay = _last_layout[0]
    if lay is None or not lay.matches(raw):
        lay = joint_state_layout(raw)
        _last_layout[0] = lay
    check_end(raw, lay.end)
    sec, nsec = _STAMP.unpack_from(raw, 4)
    return (float(sec) + 1e-9 * float(nsec), lay.frame, lay.names, *(_values(raw, sp) for sp in lay.spans))


class JointStateBlock(NamedTuple):
    """``JointState`` messages of one layout read at once (:func:`joint_state_block`): ``stamps`` (N,) [s],
    ``frame``, ``names``, ``positions`` (N, n), ``velocities`` (N, 0 or n), ``efforts`` (N, 0 or n)."""

    stamps: np.ndarray
    frame: str
    names: tuple[str, ...]
    positions: np.ndarray
    velocities: np.ndarray
    effort: np.ndarray


def joint_state_block(raws: Sequence[bytes]) -> JointStateBlock | None:
    """Every message of ``raws`` at once, when all are laid out as the first: :func:`joint_state_rows_block` of
    their bytes as rows (None also when they differ in size).

    Raises
    ------
    CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError
        The first message does not parse (:data:`PARSE_ERRORS`).
    """
    if not raws:
        return None
    _joint_state_fields(raws[0])  # the layout of the first message (or raises)
    lay = _last_layout[0]
    if lay is None or any(len(r) != lay.size for r in raws):
        return None
    return joint_state_rows_block(np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), lay.size))


def joint_state_rows_block(arr: np.ndarray) -> JointStateBlock | None:
    """``JointState`` messages of one size, the rows of ``arr`` (N, size) uint8, at once when all are laid out as
    the first: :func:`joint_state_block_at` of the rows.

    Raises
    ------
    CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError
        The first message does not parse (:data:`PARSE_ERRORS`).
    """
    n_msg, size = arr.shape
    return joint_state_block_at(np.ascontiguousarray(arr).reshape(-1), np.arange(n_msg, dtype=np.int64) * size, size)


def joint_state_block_at(buf: np.ndarray, offsets: np.ndarray, size: int) -> JointStateBlock | None:
    """``JointState`` messages ``buf[offsets[i]:offsets[i] + size]`` (uint8) at once when all are laid out as the
    first: the first read in full (:func:`parse_fields`), then the others compared with it as :func:`parse_fields`
    compares a message with the previous layout (same size, encapsulation, frame_id, names and value counts,
    trailing bytes) and their stamps and values copied out (:func:`ppoe_core.io.mcap_kernel.gather_layout`, one
    compiled pass: the same numbers, bit for bit, as message by message); None when one differs (read them one by
    one then).

    Raises
    ------
    CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError
        The first message does not parse (:data:`PARSE_ERRORS`).
    """
    from ppoe_core.io.mcap_kernel import gather_layout

    n_msg = offsets.shape[0]
    if not n_msg:
        return None
    first = buf[offsets[0]:offsets[0] + size].tobytes()
    _joint_state_fields(first)  # the layout of the first message (or raises)
    lay = _last_layout[0]
    if lay is None or lay.size != size or len(first) != size:
        return None
    # JointStateLayout.matches for every message: the encapsulation and the segments compared with the first's
    cols = np.concatenate([np.arange(2)] + [np.arange(at, at + len(seg)) for at, seg in lay.segments])
    zero_from = lay.end if lay.size - lay.end > 8 else size  # check_end: more than 8 trailing bytes must be zeros
    pieces = [(4, 8)] + [(at, 8 * n) for _, at, n in lay.spans]  # the stamp, positions, velocities, efforts
    outs = [np.empty((n_msg, width), dtype=np.uint8) for _, width in pieces]
    if not gather_layout(buf, offsets.astype(np.int64), np.frombuffer(first, dtype=np.uint8), cols.astype(np.int64),
                         zero_from, np.array([at for at, _ in pieces], dtype=np.int64), *outs):
        return None
    values = [out.view("<f8") if n else np.zeros((n_msg, 0)) for out, (_, _, n) in zip(outs[1:], lay.spans)]
    return JointStateBlock(header_stamps(outs[0], 0), lay.frame, lay.names, *values)


def header_stamps(arr: np.ndarray, at: int = 4) -> np.ndarray:
    """Stamps [s] of messages, the rows of ``arr`` (N, size) uint8, whose ``builtin_interfaces/Time`` (``int32 sec,
    uint32 nanosec``) starts at byte ``at`` (4: a ``std_msgs/Header`` after the encapsulation): ``sec + 1e-9 nanosec``,
    the same numbers as :func:`ppoe_core.io.messages.stamp_seconds` of each message."""
    sec = np.ascontiguousarray(arr[:, at:at + 4]).view("<i4")[:, 0].astype(np.float64)
    nsec = np.ascontiguousarray(arr[:, at + 4:at + 8]).view("<u4")[:, 0].astype(np.float64)
    return sec + 1e-9 * nsec


def restamped_stamps(arr: np.ndarray) -> np.ndarray | None:
    """The stamps [s] of messages that are one message restamped: the rows of ``arr`` (N, size) uint8, messages that
    start with a ``std_msgs/Header``, equal to the first row but for the header's stamp (bytes 4-12: ``int32 sec,
    uint32 nanosec``); the same numbers as :func:`ppoe_core.io.messages.stamp_seconds` of each message.  None when
    another byte differs (or there are no rows)."""
    if not arr.shape[0] or arr.shape[1] < 12:
        return None
    if (arr[:, :4] != arr[0, :4]).any() or (arr[:, 12:] != arr[0, 12:]).any():
        return None
    return header_stamps(arr)


class HeaderBlock(NamedTuple):
    """Messages of a header and float64 fields (``PoseStamped``, ``PointStamped``, ``WrenchStamped``,
    ``PoseWithCovarianceStamped``) read at once (:func:`header_rows_block`): ``stamps`` (N,) [s], ``frame`` (every
    message's ``header.frame_id``), ``values`` (N, k): each message's float64 fields in a row."""

    stamps: np.ndarray
    frame: str
    values: np.ndarray


def header_rows_block(msgtype: str, arr: np.ndarray) -> HeaderBlock | None:
    """Messages of ``msgtype`` (a schema of a header and float64 fields) of one size, the rows of ``arr`` (N, size)
    uint8, at once: the first parsed (:func:`parse_fields`), the others compared with it where :func:`parse_fields`
    reads anything but numbers (encapsulation, frame_id, more than 8 trailing bytes being zeros); their stamps and
    values read from the array (the same numbers, bit for bit, as :func:`parse_fields` gives); None when a row
    differs or the schema is not of this form.

    Raises
    ------
    CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError
        The first message does not parse (:data:`PARSE_ERRORS`).
    """
    schema = SCHEMAS[msgtype]
    if not arr.shape[0] or schema[0] != HEADER or not all(isinstance(k, int) for k in schema[1:]):
        return None
    first = arr[0].tobytes()
    values, end = read(schema, first)
    check_end(first, end)
    frame_end = 16 + _U32.unpack_from(first, 12)[0]
    cols = np.r_[0:2, 12:frame_end]
    ok = (arr[:, cols] == arr[0, cols]).all(axis=1)
    if arr.shape[1] - end > 8:
        ok &= ~arr[:, end:].any(axis=1)
    if not ok.all():
        return None
    start, n = align(frame_end, 8), sum(schema[1:])  # n float64 in a row: each field is whole float64 words
    return HeaderBlock(header_stamps(arr), values[0][2], np.ascontiguousarray(arr[:, start:start + 8 * n]).view("<f8"))


def parse_fields(msgtype: str, raw: bytes) -> tuple[Any, ...]:
    """The fields of a message of :data:`SCHEMAS` for the bag reader: ``(stamp [s], frame_id, the other fields as
    :func:`read` gives them)`` (``JointState`` messages laid out as the previous one are read at its offsets, after
    comparing the bytes that decide them); the trailing bytes checked (:func:`check_end`).

    Raises
    ------
    CdrError, struct.error, UnicodeDecodeError, ValueError, IndexError
        :data:`PARSE_ERRORS`: the typed deserialiser decides.
    """
    if msgtype == "sensor_msgs/msg/JointState":
        return _joint_state_fields(raw)
    values, end = read(SCHEMAS[msgtype], raw)
    check_end(raw, end)
    sec, nsec, frame = values[0]
    return (float(sec) + 1e-9 * float(nsec), frame, *values[1:])
