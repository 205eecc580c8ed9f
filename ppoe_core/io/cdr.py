"""Hand-written CDR for the two messages on the kinematics node's hot path: ``sensor_msgs/JointState`` in,
``geometry_msgs/PoseWithCovarianceStamped`` out (ROS 2 XCDR1, little endian, as rclpy / Fast DDS write them).

rclpy's typed messages cost more per message than the PPOE model itself at 1 kHz (deserialising a
``JointState`` about 30 us, building and serialising a pose 20-30 us); parsing and writing the bytes with
``struct`` takes a few microseconds.  Layout (OMG CDR): a 4-byte encapsulation header (``00 01 00 00`` =
CDR little endian), then the fields, each aligned to its size (4 for lengths and ``int32``, 8 for ``float64``)
relative to the end of the header; a string is ``uint32 length`` (with the terminating NUL) + bytes + NUL;
a sequence is ``uint32 count`` + elements.  Fast DDS may pad the end of a message to 4 or 8 bytes: readers
here never rely on the total length.

Both are checked against rclpy's own serialisation in ``test/test_cdr.py``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from ppoe_core.errors import MeasurementError

__all__ = ["JointStateCdr", "parse_joint_state", "joint_state_names_block", "PoseCovarianceWriter"]

_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
CDR_LE_HEADER = b"\x00\x01\x00\x00"


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


def align(pos: int, a: int) -> int:
    """``pos`` (absolute) rounded up to a multiple of ``a`` relative to the end of the 4-byte header."""
    return pos + (-(pos - 4)) % a


def _string(data: bytes, pos: int, what: str) -> tuple[str, int]:
    """One CDR string at ``pos`` (aligned) -> (text, position after it)."""
    (n,) = _U32.unpack_from(data, pos)
    end = pos + 4 + n
    if n == 0 or end > len(data) or data[end - 1] != 0:
        raise MeasurementError(f"JointState CDR: {what} has length {n} at byte {pos} of {len(data)} "
                               "(or is not NUL-terminated)")
    return data[pos + 4:end - 1].decode("utf-8"), end


_names_cache: dict[bytes, tuple[str, ...]] = {}
_last_names: list[tuple[int, bytes, tuple[str, ...]] | None] = [None]  # (count, name bytes, names) of the last call


def _names_end(data: bytes, pos: int, count: int) -> int:
    """Position after the ``count`` strings of a name sequence whose first string is at ``pos``."""
    for _ in range(count):
        pos = align(pos, 4)
        (n,) = _U32.unpack_from(data, pos)
        pos += 4 + n
        if n == 0 or pos > len(data):
            raise MeasurementError(f"JointState CDR: a name has length {n} at byte {pos - n - 4} of {len(data)}")
    return pos


def joint_state_names_block(data: bytes) -> tuple[int, bytes]:
    """``(count, bytes of the name strings)`` of a serialised ``JointState`` that :func:`parse_joint_state`
    accepted: the name sequence as it is on the wire (what identifies a publisher's name layout)."""
    (n,) = _U32.unpack_from(data, 12)
    pos = align(16 + n, 4)
    (count,) = _U32.unpack_from(data, pos)
    return count, bytes(data[pos + 4:_names_end(data, pos + 4, count)])


def _names(data: bytes, pos: int) -> tuple[tuple[str, ...], int]:
    """The ``name`` sequence at ``pos`` (aligned to 4); the parsed tuple is cached by its bytes (a publisher
    sends the same names every time)."""
    (count,) = _U32.unpack_from(data, pos)
    start = pos = pos + 4
    last = _last_names[0]
    if last is not None and last[0] == count and data[start:start + len(last[1])] == last[1]:
        return last[2], start + len(last[1])  # the same names as the previous message
    pos = _names_end(data, start, count)
    key = data[start:pos]
    names = _names_cache.get(key)
    if names is None:
        out, p = [], start
        for k in range(count):
            name, p = _string(data, align(p, 4), f"name[{k}]")
            out.append(name)
        names = tuple(out)
        if len(_names_cache) > 64:
            _names_cache.clear()
        _names_cache[key] = names
    _last_names[0] = (count, key, names)
    return names, pos


def parse_joint_state(data: bytes) -> JointStateCdr:
    """Stamp, frame, names and positions of a serialised ``sensor_msgs/JointState`` (CDR little endian).

    Raises
    ------
    MeasurementError
        Not little-endian CDR, or truncated (names the field and the byte offset).
    """
    if len(data) < 16 or data[:2] != CDR_LE_HEADER[:2]:
        raise MeasurementError(f"JointState CDR: {len(data)} bytes without the little-endian CDR header")
    try:
        sec, nsec = _STAMP.unpack_from(data, 4)
        frame_id, pos = _string(data, 12, "header.frame_id")
        names, pos = _names(data, align(pos, 4))
        pos = align(pos, 4)
        (n_pos,) = _U32.unpack_from(data, pos)
        pos = align(pos + 4, 8) if n_pos else pos + 4
        if pos + 8 * n_pos > len(data):
            raise MeasurementError(f"JointState CDR: {n_pos} positions do not fit in {len(data)} bytes")
        positions = np.frombuffer(data, dtype="<f8", count=n_pos, offset=pos)
    except struct.error as exc:
        raise MeasurementError(f"JointState CDR: truncated message of {len(data)} bytes ({exc})") from None
    except UnicodeDecodeError as exc:
        raise MeasurementError(f"JointState CDR: a string is not UTF-8 ({exc})") from None
    return JointStateCdr(sec * 1_000_000_000 + nsec, frame_id, names, positions)


class PoseCovarianceWriter:
    """Serialises ``geometry_msgs/PoseWithCovarianceStamped`` with a fixed ``header.frame_id`` into bytes.

    Parameters
    ----------
    frame_id : str
        ``header.frame_id`` of every message.
    """

    def __init__(self, frame_id: str) -> None:
        frame = frame_id.encode("utf-8") + b"\x00"
        head = bytearray(CDR_LE_HEADER + bytes(8) + _U32.pack(len(frame)) + frame)
        self._offset = align(len(head), 8)
        self._buf = head + bytes(self._offset - len(head) + 8 * 43)
        # position (3), orientation x y z w (4), covariance (36, row-major, ROS convention)
        self._values = np.frombuffer(self._buf, dtype="<f8", count=43, offset=self._offset)
        #: the message buffer as bytes (uint8) and its 43 doubles, for a compiled writer
        #: (:mod:`ppoe_core.io.joint_pose`); :meth:`message` copies out what it wrote
        self.raw = np.frombuffer(self._buf, dtype=np.uint8)
        self.fields = self._values
        self.frame_id = frame_id

    def message(self) -> bytes:
        """The bytes of the buffer as last written (by :meth:`serialize` or a compiled writer)."""
        return bytes(self._buf)

    def serialize(self, stamp_ns: int, position: np.ndarray, quat_xyzw: np.ndarray, cov_ros: np.ndarray) -> bytes:
        """The message bytes.

        Parameters
        ----------
        stamp_ns : int
            ``header.stamp`` in integer nanoseconds (>= 0).
        position : ndarray, shape (3,)
        quat_xyzw : ndarray, shape (4,)
        cov_ros : ndarray, shape (6, 6) or (36,)
            ROS-convention covariance (docs/conventions.md sec. 2).
        """
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        _STAMP.pack_into(self._buf, 4, sec, nsec)
        v = self._values
        v[0:3] = position
        v[3:7] = quat_xyzw
        v[7:43] = cov_ros.reshape(36)
        return bytes(self._buf)
