"""Message <-> numpy conversions: stamps, poses with ROS covariance (docs/conventions.md sec. 2),
wrenches, joint states, message classes."""

from __future__ import annotations

import importlib
import math
import os
import struct
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import Point, Pose, PoseWithCovariance, PoseWithCovarianceStamped, Quaternion
from std_msgs.msg import Header

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.lie.compiled import lie_kernels

#: ``header.stamp`` (int32 sec, uint32 nanosec) right after the 4-byte CDR encapsulation
_STAMP = struct.Struct("<iI")

#: The generated message classes' private fields, as the fast builder of :func:`pose_cov_stamped_msg` fills them
_MSG_SLOTS = {
    PoseWithCovarianceStamped: {"_header", "_pose", "_check_fields"},
    Header: {"_stamp", "_frame_id", "_check_fields"},
    TimeMsg: {"_sec", "_nanosec", "_check_fields"},
    PoseWithCovariance: {"_pose", "_covariance", "_check_fields"},
    Pose: {"_position", "_orientation", "_check_fields"},
    Point: {"_x", "_y", "_z", "_check_fields"},
    Quaternion: {"_x", "_y", "_z", "_w", "_check_fields"},
}
#: Build the published pose message without its constructors (each builds default sub-messages that are then
#: replaced: ~15 us per message): only with the field checks off (``ROS_PYTHON_CHECK_FIELDS`` not ``1``, the
#: constructors' default) and the fields as expected (else the constructors); tested equal to the constructors'.
_FAST_MSG = os.environ.get("ROS_PYTHON_CHECK_FIELDS", "") != "1" and all(
    set(getattr(cls, "__slots__", ())) == slots for cls, slots in _MSG_SLOTS.items())


def _bare(cls: Any) -> Any:
    """An instance of a generated message class without its constructor (fields set by the caller)."""
    obj = cls.__new__(cls)
    obj._check_fields = False
    return obj

# --------------------------------------------------------------------- conversions


def stamp_to_ns(stamp: TimeMsg) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> TimeMsg:
    """Integer nanoseconds -> ``builtin_interfaces/Time``."""
    ns = int(ns)
    if not _FAST_MSG:
        return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    t = _bare(TimeMsg)
    t._sec, t._nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    return t


def pose_msg_from_matrix(T: np.ndarray, out: Pose | None = None) -> Pose:
    """Homogeneous ``(4, 4)`` -> ``geometry_msgs/Pose`` (quaternion x, y, z, w)."""
    pose = Pose() if out is None else out
    T = np.asarray(T, dtype=float)
    q = lie.quat_from_matrix(T[:3, :3]).tolist()
    p = pose.position
    p.x, p.y, p.z = T[:3, 3].tolist()
    o = pose.orientation
    o.x, o.y, o.z, o.w = q
    return pose


def matrix_from_pose_msg(pose: Pose) -> np.ndarray:
    """``geometry_msgs/Pose`` -> homogeneous ``(4, 4)``; the quaternion is normalised."""
    o, p = pose.orientation, pose.position
    return _matrix_from_quat_xyz(float(o.x), float(o.y), float(o.z), float(o.w), p.x, p.y, p.z)


def _matrix_from_quat_xyz(x: float, y: float, z: float, w: float, px: Any, py: Any, pz: Any) -> np.ndarray:
    """Homogeneous ``(4, 4)`` of a message's quaternion (normalised) and position (see
    :func:`matrix_from_pose_msg`)."""
    nq = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(nq) or nq < 1e-9:
        raise ValueError(f"pose quaternion {[x, y, z, w]} is not a rotation")
    # lie.matrix_from_quat's one-quaternion operations (normalising again) and the translation, compiled
    T = np.empty((4, 4))
    lie_kernels().pose_from_quat_one(x / nq, y / nq, z / nq, w / nq, float(px), float(py), float(pz), T)
    return T


def pose_cov_stamped_msg(T_parent_child: np.ndarray, cov_ros: np.ndarray, stamp: TimeMsg | int,
                         frame_id: str) -> PoseWithCovarianceStamped:
    """Build a ``PoseWithCovarianceStamped``.

    Parameters
    ----------
    T_parent_child : (4, 4)
        Pose of the child frame in ``frame_id`` (the parent).
    cov_ros : (6, 6)
        Covariance in the ROS convention of docs/conventions.md sec. 2: order
        ``(x, y, z, rot_x, rot_y, rot_z)``, translation and small rotation both in
        the axes of ``frame_id``.  Convert a local (right-perturbation) covariance
        ``cov_child`` with ``lie.cov_local_to_ros(T_parent_child, cov_child)`` first.
    stamp : builtin_interfaces/Time or int
        Header stamp (int = nanoseconds).
    frame_id : str
        Parent frame.
    """
    cov = np.asarray(cov_ros, dtype=np.float64)
    if cov.shape != (6, 6):
        raise ValueError(f"covariance must be 6x6, got shape {cov.shape}")
    stamp_msg = ns_to_stamp(stamp) if isinstance(stamp, (int, np.integer)) else stamp
    if not _FAST_MSG:
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = stamp_msg
        msg.header.frame_id = frame_id
        pose_msg_from_matrix(T_parent_child, msg.pose.pose)
        msg.pose.covariance = cov.reshape(36).copy()  # the field's own type (float64[36]): no per-element check
        return msg
    fields = np.empty(7)
    lie_kernels().pose_fields_one(np.asarray(T_parent_child, dtype=np.float64), fields)  # lie.quat_from_matrix's floats
    qx, qy, qz, qw, px, py, pz = fields.tolist()
    header, pwc, pose, point, quat = _bare(Header), _bare(PoseWithCovariance), _bare(Pose), _bare(Point), \
        _bare(Quaternion)
    header._stamp, header._frame_id = stamp_msg, frame_id
    point._x, point._y, point._z = px, py, pz
    quat._x, quat._y, quat._z, quat._w = qx, qy, qz, qw
    pose._position, pose._orientation = point, quat
    pwc._pose, pwc._covariance = pose, cov.reshape(36).copy()
    msg = _bare(PoseWithCovarianceStamped)
    msg._header, msg._pose = header, pwc
    return msg


def pose_cov_from_msg(msg: PoseWithCovarianceStamped) -> tuple[np.ndarray, np.ndarray, int, str]:
    """``PoseWithCovarianceStamped`` -> ``(T (4,4), cov_ros (6,6), stamp_ns, frame_id)``.

    ``cov_ros`` is in the ROS convention (docs/conventions.md sec. 2, axes of ``frame_id``).
    """
    if _FAST_MSG and type(msg) is PoseWithCovarianceStamped:  # the fields checked at import: no property calls
        pwc, header = msg._pose, msg._header
        pose, stamp = pwc._pose, header._stamp
        o, p = pose._orientation, pose._position
        T = _matrix_from_quat_xyz(float(o._x), float(o._y), float(o._z), float(o._w), p._x, p._y, p._z)
        cov_ros = np.array(pwc._covariance, dtype=float).reshape(6, 6)  # a copy: the message keeps its array
        return T, cov_ros, int(stamp._sec) * 1_000_000_000 + int(stamp._nanosec), header._frame_id
    T = matrix_from_pose_msg(msg.pose.pose)
    cov_ros = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)  # a copy: the message keeps its array
    return T, cov_ros, stamp_to_ns(msg.header.stamp), msg.header.frame_id


def pose_cov_from_cdr(raw: bytes) -> tuple[np.ndarray, np.ndarray, int, str]:
    """:func:`pose_cov_from_msg` of a serialised ``PoseWithCovarianceStamped`` (a raw subscription's bytes), without
    building the typed message: the fields by :func:`ppoe_core.io.cdr.parse_fields` (the bag reader's), the
    stamp in integer nanoseconds from the header's bytes; anything that reader leaves to the typed path (big endian
    ...) takes it.

    Raises
    ------
    MeasurementError
        Bytes that are not a ``PoseWithCovarianceStamped``.
    """
    from ppoe_core.io import cdr

    try:
        _, frame, (px, py, pz, qx, qy, qz, qw), cov = cdr.parse_fields(_POSE_COV_TYPE, raw)
    except cdr.PARSE_ERRORS:
        from rclpy.serialization import deserialize_message

        try:
            return pose_cov_from_msg(deserialize_message(raw, PoseWithCovarianceStamped))
        except Exception as exc:  # noqa: BLE001 - rclpy raises plain exceptions for malformed bytes
            raise MeasurementError(f"not a PoseWithCovarianceStamped ({len(raw)} bytes): {exc}") from None
    sec, nsec = _STAMP.unpack_from(raw, 4)
    T = _matrix_from_quat_xyz(qx, qy, qz, qw, px, py, pz)
    return T, np.array(cov, dtype=float).reshape(6, 6), sec * 1_000_000_000 + nsec, frame


_POSE_COV_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"


class PoseCovarianceCdr:
    """:func:`pose_cov_stamped_msg` as bytes for a raw publisher (same floats: the quaternion by the same kernel),
    with a fixed ``frame_id``: no typed message is built (publishing a typed message converts it field by field);
    and :meth:`parse`, :func:`pose_cov_from_cdr` of messages laid out as this writer's.  :meth:`parse_local` and
    :meth:`serialize_local` take the covariance in the tangent space at the pose (the fusion node's per-prior path:
    one compiled call each, :mod:`ppoe_core.estimation.pose_fields`).
    """

    def __init__(self, frame_id: str) -> None:
        from ppoe_core.io.cdr import PoseCovarianceWriter

        self.writer = PoseCovarianceWriter(frame_id)
        #: the fields of the last message written: position (3), quaternion x y z w (4), ROS covariance (36)
        self.fields = self.writer.fields
        template = self.writer.message()
        self._size = len(template)
        self._values_at = self._size - 8 * 43  # position, quaternion, covariance: the message's last 43 doubles
        self._frame = template[12:16 + len(frame_id.encode("utf-8")) + 1]  # frame_id: length, bytes, NUL
        self._in = np.empty(43)  # the fields of a message read (aligned: the message's doubles are not)

    def serialize(self, T_parent_child: np.ndarray, cov_ros: np.ndarray, stamp_ns: int) -> bytes:
        """The message bytes (``cov_ros`` in the ROS convention, ``stamp_ns`` integer nanoseconds)."""
        f = np.empty(7)
        lie_kernels().pose_fields_one(np.asarray(T_parent_child, dtype=np.float64), f)  # qx qy qz qw px py pz
        return self.writer.serialize(stamp_ns, f[4:7], f[0:4], np.asarray(cov_ros, dtype=np.float64))

    def serialize_local(self, T_parent_child: np.ndarray, cov_child: np.ndarray, stamp_ns: int) -> bytes:
        """:meth:`serialize` of ``lie.cov_local_to_ros(T_parent_child, cov_child)`` (the same bytes), the fields in
        one compiled call (:func:`ppoe_core.lie.kernels.pose_cov_fields_into`)."""
        lie_kernels().pose_cov_fields_into(np.asarray(T_parent_child, dtype=np.float64),
                                           np.asarray(cov_child, dtype=np.float64), self.fields)
        _STAMP.pack_into(self.writer.raw, 4, *divmod(int(stamp_ns), 1_000_000_000))  # header.stamp, as the writer
        return self.writer.message()

    def parse(self, raw: bytes) -> tuple[np.ndarray, np.ndarray, int, str]:
        """:func:`pose_cov_from_cdr` of ``raw`` (the same values and errors): a message of this writer's size whose
        ``frame_id`` equals the writer's (and little-endian CDR; the padding after it is not compared: rclpy leaves
        it unset) has its stamp and 43 doubles at the writer's offsets; any other goes through
        :func:`pose_cov_from_cdr`."""
        if not self._same_layout(raw):
            return pose_cov_from_cdr(raw)
        sec, nsec = _STAMP.unpack_from(raw, 4)
        v = np.frombuffer(raw, dtype="<f8", count=43, offset=self._values_at)
        px, py, pz, qx, qy, qz, qw = v[:7].tolist()
        T = _matrix_from_quat_xyz(qx, qy, qz, qw, px, py, pz)
        return T, v[7:].astype(np.float64).reshape(6, 6), sec * 1_000_000_000 + nsec, self.writer.frame_id

    def parse_local(self, raw: bytes) -> tuple[np.ndarray, np.ndarray, int, str]:
        """:meth:`parse` with the covariance as ``lie.cov_ros_to_local`` gives it (the same floats and errors): for
        this writer's layout in one compiled call (:func:`ppoe_core.estimation.pose_fields.prior_from_fields`)."""
        if self._same_layout(raw):
            self._in[:] = np.frombuffer(raw, dtype="<f8", count=43, offset=self._values_at)
            T, cov = np.empty((4, 4)), np.empty((6, 6))
            if _pose_fields().prior_from_fields(self._in, T, cov):
                sec, nsec = _STAMP.unpack_from(raw, 4)
                return T, cov, sec * 1_000_000_000 + nsec, self.writer.frame_id
        T, cov_ros, stamp_ns, frame = self.parse(raw)  # not this layout, or a quaternion that is no rotation (raises)
        return T, lie.cov_ros_to_local(T, cov_ros), stamp_ns, frame

    def _same_layout(self, raw: bytes) -> bool:
        return len(raw) == self._size and raw.startswith(self._frame, 12) and raw.startswith(_CDR_LE)


def _pose_fields() -> Any:
    """:mod:`ppoe_core.estimation.pose_fields` (numba), imported on the first call and kept (an import statement
    per message costs more than the kernel call)."""
    if not _POSE_FIELDS:
        from ppoe_core.lie.compiled import compiled

        _POSE_FIELDS.append(compiled("ppoe_core.estimation.pose_fields"))
    return _POSE_FIELDS[0]


_POSE_FIELDS: list[Any] = []


_CDR_LE = b"\x00\x01"  # the bytes ppoe_core.io.cdr.read checks: CDR, little endian


def wrench_to_numpy(msg: Any) -> np.ndarray:
    """``geometry_msgs/WrenchStamped`` or ``Wrench`` -> ``(6,)`` ``[fx, fy, fz, tx, ty, tz]``."""
    w = getattr(msg, "wrench", msg)
    return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z])


def message_class(type_name: str) -> type:
    """ROS message class from its type name (``"sensor_msgs/msg/JointState"`` or ``"sensor_msgs/JointState"``).

    Raises
    ------
    PpoeError
        Malformed name, or the message package is not installed (message names the type).
    """
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise PpoeError(f"message type '{type_name}' is not of the form package/msg/Name")
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f"{pkg}.{kind}")
        cls = getattr(module, name)
    except (ImportError, AttributeError):
        raise PpoeError(
            f"message type '{type_name}' is not installed (no Python module {pkg}.{kind}.{name})") from None
    return cls
