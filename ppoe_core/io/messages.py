"""Contract topics and message types (docs/conventions.md sec. 3), the rosbags type store, CDR (de)serialisation."""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import BagError

TOPIC_ROBOT_DESCRIPTION = "/robot_description"
TOPIC_JOINT_STATES = "/joint_states"
TOPIC_CAMERA_INFO = "/camera/camera_info"
TOPIC_COMPRESSED_IMAGE = "/camera/image_raw/compressed"
TOPIC_IMAGE = "/camera/image_raw"
TOPIC_WRENCH = "/wrench"
TOPIC_GT_POSE = "/ground_truth/pose"
TOPIC_GT_POINT = "/ground_truth/point"
TOPIC_TAG_OBSERVATIONS = "/tag_bearing/observations"
IMU_TOPIC_PREFIX = "/imu/"

T_STRING = "std_msgs/msg/String"
T_JOINT_STATE = "sensor_msgs/msg/JointState"
T_CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
T_COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
T_IMAGE = "sensor_msgs/msg/Image"
T_WRENCH = "geometry_msgs/msg/WrenchStamped"
T_POSE = "geometry_msgs/msg/PoseStamped"
T_POINT = "geometry_msgs/msg/PointStamped"
T_IMU = "sensor_msgs/msg/Imu"
T_TEMPERATURE = "sensor_msgs/msg/Temperature"
#: ``/temperature`` or ``/temperature/<name>`` (docs/conventions.md sec. 3): thermal effects' variable
TOPIC_TEMPERATURE = "/temperature"
T_POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
T_POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"

#: topic -> required message type (docs/conventions.md sec. 3 plus our tag observations);
#: ``/imu/<name>`` topics must be ``sensor_msgs/msg/Imu``.
CONTRACT_TYPES: dict[str, str] = {
    TOPIC_ROBOT_DESCRIPTION: T_STRING,
    TOPIC_JOINT_STATES: T_JOINT_STATE,
    TOPIC_CAMERA_INFO: T_CAMERA_INFO,
    TOPIC_COMPRESSED_IMAGE: T_COMPRESSED_IMAGE,
    TOPIC_IMAGE: T_IMAGE,
    TOPIC_WRENCH: T_WRENCH,
    TOPIC_GT_POSE: T_POSE,
    TOPIC_GT_POINT: T_POINT,
    TOPIC_TAG_OBSERVATIONS: T_POINTCLOUD2,
}

#: FLOAT64 fields of one point of ``/tag_bearing/observations`` (ARCHITECTURE.md):
#: tag id, corner (0 = centre, 1..4 = corners in the detector's order), raw
#: distorted pixel (u, v), undistorted normalised coordinates (x = X/Z, y = Y/Z).
TAG_OBSERVATION_FIELDS: tuple[str, ...] = ("id", "corner", "u", "v", "x", "y")

IMU_TOPIC_RE = re.compile(r"^/imu/[A-Za-z0-9_]+(/[A-Za-z0-9_]+)*$")

_TYPESTORE: Any = None


def typestore() -> Any:
    """The ``rosbags`` type store of ROS 2 Jazzy (created once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def stamp_to_ns(stamp: float | int | np.integer | np.floating) -> int:
    """Seconds (float) -> integer nanoseconds, rounded to the nearest ns.

    Raises
    ------
    BagError
        If the stamp is negative, NaN or infinite.
    """
    s = float(stamp)
    if not np.isfinite(s) or s < 0.0:
        raise BagError(f"stamp {stamp!r} is not a finite non-negative time in seconds")
    return int(round(s * 1e9))


def _time_msg(stamp_ns: int) -> Any:
    Time = typestore().types["builtin_interfaces/msg/Time"]
    return Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def header_msg(stamp_ns: int, frame_id: str) -> Any:
    Header = typestore().types["std_msgs/msg/Header"]
    return Header(stamp=_time_msg(stamp_ns), frame_id=str(frame_id))


def stamp_seconds(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def pose_message(T: np.ndarray) -> Any:
    types = typestore().types
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BagError(f"pose must be a finite 4x4 matrix, got shape {T.shape}")
    q = lie.quat_from_matrix(T[:3, :3])
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                          w=float(q[3])),
    )


def vector3_message(v: Sequence[float] | np.ndarray, what: str) -> Any:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise BagError(f"{what} must be 3 finite numbers, got {v!r}")
    return typestore().types["geometry_msgs/msg/Vector3"](x=float(a[0]), y=float(a[1]), z=float(a[2]))


def serialize(msg: Any, msgtype: str) -> bytes:
    """Serialise a rosbags message object to CDR bytes (little endian)."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(data: bytes | memoryview, msgtype: str, *, topic: str = "?") -> Any:
    """CDR bytes -> rosbags message object, tolerant of trailing alignment padding.

    FastCDR (rclpy) pads the end of a message up to the next 8-byte boundary, with
    whatever was in memory (seen: non-zero bytes); rosbags' own size check rejects
    more than 3 bytes of it, so the payload is parsed here: up to 8 trailing bytes
    of any content, and any number of zero bytes, are accepted.

    Raises
    ------
    BagError
        Unknown type or bytes that do not parse; the message names ``topic``.
    """
    ts = typestore()
    raw = bytes(data)
    try:
        if len(raw) < 4 or raw[:2] not in (b"\x00\x00", b"\x00\x01"):
            raise ValueError("invalid or unsupported CDR encapsulation header")
        msgdef = ts.get_msgdef(msgtype)
        func = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
        message, pos = func(memoryview(raw)[4:], 0, msgdef.cls, ts)
    except Exception as exc:  # rosbags raises several types; re-raise as ours
        raise BagError(f"topic {topic}: cannot deserialise {msgtype}: {exc}") from exc
    tail = raw[4 + pos:]
    if len(tail) > 8 and any(tail):
        raise BagError(f"topic {topic}: {len(tail)} unexpected trailing bytes after a {msgtype} message")
    return message
