"""Per-topic rows of :func:`ppoe_core.io.reader.read_bag`: message fields -> one row of the topic's accumulator
(with the contract checks), and the finishers that turn the accumulated rows into the series of ``BagData``.

Every topic has a :class:`RowKind`: ``fields`` takes a typed (rosbags) message apart, ``build`` checks the
fields and makes the row.  The hot topics also have ``parse``, which reads the same fields from the raw
CDR bytes (:func:`ppoe_core.io.cdr.parse_fields`); where it cannot, the reader deserialises the typed message, so both
paths build the same rows through the same checks and error messages.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.lie.compiled import lie_kernels
from ppoe_core.errors import BagError, MeasurementError
from ppoe_core.io import cdr
from ppoe_core.io.messages import (
    IMU_TOPIC_PREFIX, T_COMPRESSED_IMAGE, T_JOINT_STATE, T_POINT, T_POSE, T_POSE_COV, T_TEMPERATURE, T_WRENCH,
    TAG_OBSERVATION_FIELDS, TOPIC_CAMERA_INFO, TOPIC_COMPRESSED_IMAGE, TOPIC_GT_POINT, TOPIC_GT_POSE, TOPIC_IMAGE,
    TOPIC_JOINT_STATES, TOPIC_TAG_OBSERVATIONS, TOPIC_TEMPERATURE, TOPIC_WRENCH, deserialize, stamp_seconds,
)
from ppoe_core.io.series import (
    BagData, CameraInfos, Images, ImuSeries, JointStates, PointSeries, PoseCovSeries, PoseSeries, TagObservationRows,
    TemperatureSeries, Wrenches,
)

__all__ = ["RowKind", "row_kind", "finish", "expected_type", "named", "tag_rows_from_cloud", "JOINT_STATE_KIND",
           "finish_joint_state_block", "block_topic", "finish_block", "restamped_topic", "finish_restamped"]


def expected_type(topic: str) -> str | None:
    """The message type the contract requires on ``topic`` (None: not a contract topic)."""
    from ppoe_core.io.messages import CONTRACT_TYPES, T_IMU

    if topic in CONTRACT_TYPES:
        return CONTRACT_TYPES[topic]
    if topic.startswith(IMU_TOPIC_PREFIX):
        return T_IMU
    if named(topic, TOPIC_GT_POINT):
        return T_POINT
    if topic == TOPIC_TEMPERATURE or named(topic, TOPIC_TEMPERATURE):
        return T_TEMPERATURE
    return None


def named(topic: str, prefix: str) -> bool:
    """``topic`` is ``<prefix>/<name>`` (one of several sensors of a kind)."""
    return topic.startswith(prefix + "/") and len(topic) > len(prefix) + 1


#: a pose message's quaternion shorter than this is refused (no rotation to normalise)
_MIN_QUAT_NORM = 1e-9


def _pose_to_T(v: tuple[float, ...]) -> np.ndarray:
    """``(px, py, pz, qx, qy, qz, qw)`` -> (4, 4); ValueError for a zero or non-finite quaternion."""
    x, y, z, w = (float(c) for c in v[3:7])
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z) and math.isfinite(w)) \
            or math.sqrt(x * x + y * y + z * z + w * w) < _MIN_QUAT_NORM:
        raise ValueError(f"invalid quaternion {np.array(v[3:7])}")
    T = np.empty((4, 4))
    lie_kernels().pose_from_quat_one(x, y, z, w, float(v[0]), float(v[1]), float(v[2]), T)  # lie.matrix_from_quat's
    return T


def _pose_values(pose: Any) -> tuple[float, ...]:
    p, o = pose.position, pose.orientation
    return (p.x, p.y, p.z, o.x, o.y, o.z, o.w)


def _v3(v: Any) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def tag_rows_from_cloud(msg: Any) -> np.ndarray:
    """A ``/tag_bearing/observations`` ``PointCloud2`` (a ROS or a rosbags message: its fields read as attributes)
    -> (n, 6) float rows in :data:`~ppoe_core.io.messages.TAG_OBSERVATION_FIELDS` order ``[id, corner, u, v, x,
    y]``.  Fields are read by name and offset (FLOAT64 or FLOAT32), so a producer may order them differently or add
    fields.

    Raises
    ------
    MeasurementError
        A required field is missing or not float, or the data size does not match.
    """
    by_name = {f.name: f for f in msg.fields}
    n, step = int(msg.width) * int(msg.height), int(msg.point_step)
    raw = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if len(raw) < n * step:
        raise MeasurementError(f"PointCloud2 has {len(raw)} bytes for {n} points of {step} bytes")
    endian = ">" if msg.is_bigendian else "<"
    buf = np.frombuffer(raw[: n * step], dtype=np.uint8).reshape(n, step) if n else np.zeros((0, step), np.uint8)
    out = np.empty((n, len(TAG_OBSERVATION_FIELDS)))
    for j, name in enumerate(TAG_OBSERVATION_FIELDS):
        f = by_name.get(name)
        if f is None:
            raise MeasurementError(f"PointCloud2 has no field '{name}' (fields: {sorted(by_name)})")
        code = {7: "f4", 8: "f8"}.get(int(f.datatype))
        if code is None:
            raise MeasurementError(f"PointCloud2 field '{name}' has datatype {f.datatype}, expected FLOAT64/FLOAT32")
        off, size = int(f.offset), int(code[1])
        if off + size > step:
            raise MeasurementError(f"PointCloud2 field '{name}' offset {off} outside point_step {step}")
        out[:, j] = np.ascontiguousarray(buf[:, off:off + size]).view(endian + code).reshape(-1)
    return out


# -- per-topic rows: fields of a typed message (``fields``) or of the raw bytes (``parse``) -> row (``build``) ---------


def _js_fields(msg: Any) -> tuple:
    return (stamp_seconds(msg.header), msg.header.frame_id, tuple(msg.name), np.asarray(msg.position, dtype=float),
            np.asarray(msg.velocity, dtype=float), np.asarray(msg.effort, dtype=float))


#: the last joint-name tuple found free of duplicates (the raw parser hands out one tuple per publisher)
_unique_names: list[tuple[str, ...]] = [()]


def _js_row(f: tuple, topic: str, k: int, load_images: bool) -> tuple:
    stamp, _, names, pos, vel, eff = f
    n = len(names)
    if pos.shape[0] != n:
        raise BagError(f"topic {topic}: message {k} has {n} names but {pos.shape[0]} positions")
    if names is not _unique_names[0]:
        if len(set(names)) != n:
            raise BagError(f"topic {topic}: message {k} lists a joint twice: {list(names)}")
        _unique_names[0] = names
    for what, m in (("velocities", vel.shape[0]), ("efforts", eff.shape[0])):
        if m and m != n:
            raise BagError(f"topic {topic}: message {k} has {n} names but {m} {what}")
    return (stamp, names, pos, vel, eff)


def _row_camera_info(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    K = np.asarray(msg.k, dtype=float).reshape(3, 3)
    return (stamp_seconds(msg.header), msg.header.frame_id, K, np.asarray(msg.d, dtype=float),
            int(msg.width), int(msg.height), msg.distortion_model)


def _compressed_fields(msg: Any) -> tuple:
    return (stamp_seconds(msg.header), msg.header.frame_id, msg.format, np.asarray(msg.data, dtype=np.uint8))


def _compressed_row(f: tuple, topic: str, k: int, load_images: bool) -> tuple:
    stamp, frame, format_, data = f
    low = format_.lower()
    fmt = "png" if "png" in low else "jpeg" if ("jpeg" in low or "jpg" in low) else None
    if fmt is None:
        raise BagError(f"topic {topic}: message {k} format {format_!r} is neither png nor jpeg")
    return (stamp, frame, fmt, bytes(data) if load_images else b"", None)


def _row_image(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    enc = msg.encoding
    ch = {"mono8": 1, "bgr8": 3, "rgb8": 3}.get(enc)
    if ch is None:
        raise BagError(f"topic {topic}: message {k} encoding {enc!r} not supported (mono8, bgr8, rgb8)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.asarray(msg.data, dtype=np.uint8)
    if step < w * ch or buf.shape[0] < h * step:
        raise BagError(f"topic {topic}: message {k} data size {buf.shape[0]} too small for {w}x{h} {enc}")
    img = buf[: h * step].reshape(h, step)[:, : w * ch]
    shape = (h, w) if ch == 1 else (h, w, 3)
    return (stamp_seconds(msg.header), msg.header.frame_id, enc,
            np.ascontiguousarray(img).tobytes() if load_images else b"", shape)


def _wrench_fields(msg: Any) -> tuple:
    f, t = msg.wrench.force, msg.wrench.torque
    return (stamp_seconds(msg.header), msg.header.frame_id, (f.x, f.y, f.z, t.x, t.y, t.z))


def _wrench_row(f: tuple, topic: str, k: int, load_images: bool) -> tuple:
    v = f[2]
    return (f[0], f[1], [float(v[0]), float(v[1]), float(v[2])], [float(v[3]), float(v[4]), float(v[5])])


def _pose_fields(msg: Any) -> tuple:
    return (stamp_seconds(msg.header), msg.header.frame_id, _pose_values(msg.pose))


def _pose_row(f: tuple, topic: str, k: int, load_images: bool) -> tuple:
    return (f[0], f[1], _pose_to_T(f[2]))


def _point_fields(msg: Any) -> tuple:
    p = msg.point
    return (stamp_seconds(msg.header), msg.header.frame_id, (p.x, p.y, p.z))


def _point_row(f: tuple, topic: str, k: int, load_images: bool) -> tuple:
    return (f[0], f[1], list(f[2]))


def _row_temperature(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (stamp_seconds(msg.header), msg.header.frame_id, float(msg.temperature), float(msg.variance))


def _row_imu(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (stamp_seconds(msg.header), msg.header.frame_id, _v3(msg.linear_acceleration),
            _v3(msg.angular_velocity), np.asarray(msg.linear_acceleration_covariance, float).reshape(3, 3))


def _row_tag_cloud(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    try:
        rows = tag_rows_from_cloud(msg)
    except MeasurementError as exc:
        raise BagError(f"topic {topic}: message {k}: {exc}") from None
    return (stamp_seconds(msg.header), msg.header.frame_id, rows)


def _pose_cov_fields(msg: Any) -> tuple:
    return (stamp_seconds(msg.header), msg.header.frame_id, _pose_values(msg.pose.pose), msg.pose.covariance)


def _pose_cov_row(f: tuple, topic: str, k: int, load_images: bool) -> tuple:
    return (f[0], f[1], _pose_to_T(f[2]), np.asarray(f[3], dtype=float).reshape(6, 6))


def _itself(msg: Any) -> Any:
    return msg


class RowKind(NamedTuple):
    """How one topic's messages become rows: ``parse`` (raw CDR bytes -> fields, or None: typed only),
    ``fields`` (typed message -> fields) and ``build`` (fields, topic, message index, load_images -> row)."""

    parse: Callable[[bytes], tuple] | None
    fields: Callable[[Any], Any]
    build: Callable[[Any, str, int, bool], tuple]


def _typed(build: Callable[[Any, str, int, bool], tuple]) -> RowKind:
    return RowKind(None, _itself, build)


def _raw(msgtype: str) -> Callable[[bytes], tuple]:
    """Raw bytes -> the fields the typed path gives (stamp [s] as :func:`stamp_seconds`, frame_id, the rest), by
    the one CDR reader (:func:`ppoe_core.io.cdr.parse_fields`)."""
    return functools.partial(cdr.parse_fields, msgtype)


_JOINT_STATE = RowKind(_raw(T_JOINT_STATE), _js_fields, _js_row)
#: the row kind of ``/joint_states`` (whose messages the reader may read at once: :func:`finish_joint_state_block`)
JOINT_STATE_KIND = _JOINT_STATE
_POINT = RowKind(_raw(T_POINT), _point_fields, _point_row)
_POSE_COV = RowKind(_raw(T_POSE_COV), _pose_cov_fields, _pose_cov_row)
_IMU = _typed(_row_imu)
_TEMPERATURE = _typed(_row_temperature)
#: topic -> its rows (``/imu/<name>``, point, temperature and pose-with-covariance topics by prefix / type)
_KINDS: dict[str, RowKind] = {
    TOPIC_JOINT_STATES: _JOINT_STATE,
    TOPIC_CAMERA_INFO: _typed(_row_camera_info),
    TOPIC_COMPRESSED_IMAGE: RowKind(_raw(T_COMPRESSED_IMAGE), _compressed_fields, _compressed_row),
    TOPIC_IMAGE: _typed(_row_image),
    TOPIC_WRENCH: RowKind(_raw(T_WRENCH), _wrench_fields, _wrench_row),
    TOPIC_GT_POSE: RowKind(_raw(T_POSE), _pose_fields, _pose_row),
    TOPIC_GT_POINT: _POINT,
    TOPIC_TAG_OBSERVATIONS: _typed(_row_tag_cloud),
}


def row_kind(topic: str, msgtype: str) -> RowKind:
    """The :class:`RowKind` of a contract topic (or a pose-with-covariance topic) carrying ``msgtype``."""
    if topic in _KINDS:
        return _KINDS[topic]
    if topic.startswith(IMU_TOPIC_PREFIX):
        return _IMU
    if msgtype == T_POINT:
        return _POINT
    if msgtype == T_TEMPERATURE:
        return _TEMPERATURE
    if msgtype == T_POSE_COV:
        return _POSE_COV
    raise BagError(f"topic {topic}: no parser for {msgtype}")  # pragma: no cover - filtered before


# -- per-topic finishers: accumulated rows -> the series of BagData ----------------------------------------------


def _finish_joint_states(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    """Rows aligned by name (union in first-seen order); the rows with the same names are written together."""
    names: list[str] = []
    index: dict[str, int] = {}
    groups: dict[tuple[str, ...], list[int]] = {}
    for i, e in enumerate(lst):
        rows = groups.get(e[1])
        if rows is None:
            rows = groups[e[1]] = []
            for n in e[1]:
                if n not in index:
                    index[n] = len(names)
                    names.append(n)
        rows.append(i)
    N, n = len(lst), len(names)
    out = [np.full((N, n), np.nan) for _ in range(3)]  # positions, velocities, efforts
    for nm, rows in groups.items():
        cols = np.array([index[x] for x in nm], dtype=int)
        for j, A in enumerate(out):
            have = rows if j == 0 else [i for i in rows if lst[i][2 + j].shape[0]]  # empty: NaN
            if have:
                A[np.ix_(np.asarray(have, dtype=int), cols)] = np.stack([lst[i][2 + j] for i in have])
    data.joint_states = JointStates(stamps, names, out[0], out[1], out[2])


def _finish_camera_info(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    Ds = [e[3] for e in lst]
    width = max(d.shape[0] for d in Ds)
    D = np.zeros((len(lst), width))
    for i, d in enumerate(Ds):
        D[i, : d.shape[0]] = d
    data.camera_info = CameraInfos(stamps, frames, np.stack([e[2] for e in lst]), D,
                                   np.array([e[4] for e in lst]), np.array([e[5] for e in lst]),
                                   [e[6] for e in lst])


def _finish_images(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    imgs = Images(topic, stamps, frames, [e[2] for e in lst], [e[3] for e in lst], [e[4] for e in lst])
    if topic == TOPIC_IMAGE:
        data.raw_images = imgs
        if not len(data.images):
            data.images = imgs
    else:
        data.images = imgs


def _finish_wrench(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.wrench = Wrenches(stamps, frames, np.array([e[2] for e in lst]), np.array([e[3] for e in lst]))


def _finish_pose(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.ground_truth_pose = PoseSeries(stamps, frames, np.stack([e[2] for e in lst]))


def _finish_point(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.ground_truth_point = PointSeries(stamps, frames, np.array([e[2] for e in lst], dtype=float))


def _finish_named_point(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.ground_truth_points[topic] = PointSeries(stamps, frames, np.array([e[2] for e in lst], dtype=float))


def _finish_temperature(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.temperatures[topic] = TemperatureSeries(stamps, frames, np.array([e[2] for e in lst], dtype=float),
                                                 np.array([e[3] for e in lst], dtype=float))


def _finish_imu(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.imus[topic[len(IMU_TOPIC_PREFIX):]] = ImuSeries(
        stamps, frames, np.array([e[2] for e in lst]), np.array([e[3] for e in lst]),
        np.stack([e[4] for e in lst]))


def _finish_tag_cloud(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    clouds = [e[2] for e in lst]
    idx = np.concatenate([np.full(c.shape[0], i, dtype=int) for i, c in enumerate(clouds)])
    allp = np.concatenate(clouds, axis=0) if clouds else np.zeros((0, 6))
    data.tag_observations = TagObservationRows(stamps, frames, idx, np.rint(allp[:, 0]).astype(int),
                                               np.rint(allp[:, 1]).astype(int), allp[:, 2:4].copy(),
                                               allp[:, 4:6].copy())


def _finish_pose_cov(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    data.poses_with_covariance[topic] = PoseCovSeries(stamps, frames, np.stack([e[2] for e in lst]),
                                                      np.stack([e[3] for e in lst]))


_FINISHERS: dict[str, Callable[[BagData, str, np.ndarray, list, list], None]] = {
    TOPIC_JOINT_STATES: _finish_joint_states,
    TOPIC_CAMERA_INFO: _finish_camera_info,
    TOPIC_COMPRESSED_IMAGE: _finish_images,
    TOPIC_IMAGE: _finish_images,
    TOPIC_WRENCH: _finish_wrench,
    TOPIC_GT_POSE: _finish_pose,
    TOPIC_GT_POINT: _finish_point,
    TOPIC_TAG_OBSERVATIONS: _finish_tag_cloud,
}


def finish_joint_state_block(data: BagData, topic: str, block: cdr.JointStateBlock) -> None:
    """``data.joint_states`` of messages read at once (:func:`ppoe_core.io.cdr.joint_state_block`): what
    :func:`finish` makes of their rows one by one (the first message's row checks, names and value counts, hold for
    all: they have its bytes there).

    Raises
    ------
    BagError
        As the row of message 0 would.
    """
    n, N = len(block.names), block.stamps.shape[0]
    _js_row((block.stamps[0], block.frame, block.names, block.positions[0], block.velocities[0], block.effort[0]),
            topic, 0, True)
    pos, vel, eff = (A.copy() if A.shape[1] else np.full((N, n), np.nan)
                     for A in (block.positions, block.velocities, block.effort))
    data.joint_states = JointStates(block.stamps.copy(), list(block.names), pos, vel, eff)


def _pose_block(data: BagData, topic: str, block: cdr.HeaderBlock) -> bool:
    """``/ground_truth/pose`` of a block: the poses :func:`_pose_to_T` makes (the same rule for a zero or non-finite
    quaternion, then the same compiled rotation, :func:`ppoe_core.lie.so3.matrix_from_quat`)."""
    from ppoe_core.lie.se3 import from_rt
    from ppoe_core.lie.so3 import matrix_from_quat

    v = block.values
    x, y, z, w = v[:, 3], v[:, 4], v[:, 5], v[:, 6]
    valid = np.isfinite(v[:, 3:7]).all(axis=1) & ~(np.sqrt(x * x + y * y + z * z + w * w) < _MIN_QUAT_NORM)
    if not valid.all():  # message by message, for the error naming the first
        return False
    T = from_rt(matrix_from_quat(v[:, 3:7]), v[:, :3])
    data.ground_truth_pose = PoseSeries(block.stamps, [block.frame] * v.shape[0], T)
    return True


def _wrench_block(data: BagData, topic: str, block: cdr.HeaderBlock) -> bool:
    N = block.values.shape[0]
    data.wrench = Wrenches(block.stamps, [block.frame] * N, block.values[:, :3].copy(), block.values[:, 3:6].copy())
    return True


def _point_block(data: BagData, topic: str, block: cdr.HeaderBlock) -> bool:
    data.ground_truth_point = PointSeries(block.stamps, [block.frame] * block.values.shape[0], block.values.copy())
    return True


#: topics whose messages the reader may read at once (:func:`finish_block`)
_BLOCK_FINISHERS: dict[str, Callable[[BagData, str, cdr.HeaderBlock], bool]] = {
    TOPIC_GT_POSE: _pose_block, TOPIC_WRENCH: _wrench_block, TOPIC_GT_POINT: _point_block,
}


def block_topic(topic: str) -> bool:
    """The messages of ``topic`` can be read at once (:func:`ppoe_core.io.cdr.header_rows_block`,
    :func:`finish_block`)."""
    return topic in _BLOCK_FINISHERS


def finish_block(data: BagData, topic: str, block: cdr.HeaderBlock) -> bool:
    """The series of a :func:`block_topic` from its messages read at once: what :func:`finish` makes of their rows
    one by one; False (nothing set) where a message's row would raise (read them one by one then)."""
    return _BLOCK_FINISHERS[topic](data, topic, block)


#: typed topics whose messages are usually one message restamped (a camera's calibration), read at once where they are
_RESTAMPED = {TOPIC_CAMERA_INFO}


def restamped_topic(topic: str) -> bool:
    """The messages of ``topic`` may be read at once where they are one message restamped (:func:`finish_restamped`)."""
    return topic in _RESTAMPED


def finish_restamped(data: BagData, topic: str, msgtype: str, arr: np.ndarray, load_images: bool) -> bool:
    """The series of a :func:`restamped_topic` from its messages, the rows of ``arr`` (N, size) uint8, where they are
    the first message restamped (:func:`ppoe_core.io.cdr.restamped_stamps`): the first deserialised and its row built
    as one by one, every other row the same with its own stamp (their bytes deserialise to the same fields): what
    :func:`finish` makes of their rows one by one.  False (nothing set) where other bytes differ, or the first message
    would be rejected or its row raise: read them one by one then (the same rejections and errors)."""
    stamps = cdr.restamped_stamps(arr)
    if stamps is None:
        return False
    kind = row_kind(topic, msgtype)
    try:
        msg = deserialize(arr[0].tobytes(), msgtype, topic=topic)
        row = kind.build(kind.fields(msg), topic, 0, load_images)
    except Exception:  # noqa: BLE001 - one by one gives the rejection or the error, in the reader's order
        return False
    finish(data, {topic: [(stamp, *row[1:]) for stamp in stamps.tolist()]})
    return True


def finish(data: BagData, acc: dict[str, list[Any]]) -> None:
    for topic, lst in acc.items():
        if not lst:
            continue
        stamps = np.array([e[0] for e in lst], dtype=float)
        frames = [e[1] for e in lst]
        if topic in _FINISHERS:
            finisher = _FINISHERS[topic]
        elif topic.startswith(IMU_TOPIC_PREFIX):
            finisher = _finish_imu
        elif named(topic, TOPIC_GT_POINT):
            finisher = _finish_named_point
        elif expected_type(topic) == T_TEMPERATURE:
            finisher = _finish_temperature
        else:
            finisher = _finish_pose_cov
        finisher(data, topic, stamps, frames, lst)
