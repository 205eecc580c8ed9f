"""Reading contract bags: raw messages in log order (:func:`iter_raw`) and typed series (:func:`read_bag`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import BagError
from ppoe_core.io.messages import (
    CONTRACT_TYPES,
    IMU_TOPIC_PREFIX,
    T_IMU,
    T_POSE_COV,
    TAG_OBSERVATION_FIELDS,
    TOPIC_CAMERA_INFO,
    TOPIC_COMPRESSED_IMAGE,
    TOPIC_GT_POINT,
    TOPIC_GT_POSE,
    TOPIC_IMAGE,
    TOPIC_JOINT_STATES,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_TAG_OBSERVATIONS,
    TOPIC_WRENCH,
    _stamp_s,
    deserialize,
)
from ppoe_core.io.series import (
    BagData,
    CameraInfos,
    Images,
    ImuSeries,
    JointStates,
    PointSeries,
    PoseCovSeries,
    PoseSeries,
    RawMessage,
    TagObservationRows,
    Wrenches,
)


def _open_reader(path: str | Path) -> Any:
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise BagError(f"bag {p} does not exist")
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:
        raise BagError(f"bag {p}: cannot open as a rosbag2 directory: {exc}") from exc
    return reader


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topics of a bag -> (message type, message count), without reading messages."""
    reader = _open_reader(path)
    try:
        return {c.topic: (c.msgtype, int(c.msgcount)) for c in reader.connections}
    finally:
        reader.close()


def iter_raw(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
    """Yield the messages of a bag in log-time order as :class:`RawMessage` (for ``ppoe play``).

    ``topics`` restricts to these topic names (unknown names are ignored).
    """
    reader = _open_reader(path)
    try:
        wanted = set(topics) if topics is not None else None
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        for conn, stamp_ns, data in reader.messages(connections=conns):
            yield RawMessage(conn.topic, conn.msgtype, int(stamp_ns), bytes(data))
    finally:
        reader.close()


def _expected_type(topic: str) -> str | None:
    if topic in CONTRACT_TYPES:
        return CONTRACT_TYPES[topic]
    if topic.startswith(IMU_TOPIC_PREFIX):
        return T_IMU
    return None


def _pose_to_T(pose: Any) -> np.ndarray:
    T = np.eye(4)
    o = pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise ValueError(f"invalid quaternion {q}")
    T[:3, :3] = lie.matrix_from_quat(q)
    T[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return T


def _v3(v: Any) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def _parse_cloud(msg: Any, topic: str, k: int) -> np.ndarray:
    """PointCloud2 -> (P, 6) float array in TAG_OBSERVATION_FIELDS order."""
    dt = {7: "f4", 8: "f8"}
    offsets: dict[str, tuple[int, str]] = {}
    for f in msg.fields:
        if f.name in TAG_OBSERVATION_FIELDS:
            if f.datatype not in dt:
                raise BagError(f"topic {topic}: message {k} field {f.name!r} must be FLOAT32/FLOAT64")
            offsets[f.name] = (int(f.offset), dt[f.datatype])
    missing = [n for n in TAG_OBSERVATION_FIELDS if n not in offsets]
    if missing:
        raise BagError(f"topic {topic}: message {k} lacks PointCloud2 fields {missing}")
    n = int(msg.width) * int(msg.height)
    raw = np.asarray(msg.data, dtype=np.uint8).tobytes()
    step = int(msg.point_step)
    if len(raw) < n * step:
        raise BagError(f"topic {topic}: message {k} has {len(raw)} data bytes for {n} points of {step}")
    endian = ">" if msg.is_bigendian else "<"
    out = np.empty((n, len(TAG_OBSERVATION_FIELDS)))
    buf = np.frombuffer(raw[: n * step], dtype=np.uint8).reshape(n, step) if n else np.zeros((0, step), np.uint8)
    for j, name in enumerate(TAG_OBSERVATION_FIELDS):
        off, code = offsets[name]
        size = int(code[1])
        out[:, j] = np.ascontiguousarray(buf[:, off:off + size]).view(endian + code).reshape(-1)
    return out


def read_bag(path: str | Path, *, topics: Iterable[str] | None = None, load_images: bool = True) -> BagData:
    """Read a contract bag into numpy arrays.

    Parameters
    ----------
    path
        rosbag2 directory (mcap or sqlite3).
    topics
        Parse only these topics (all by default); the others are still listed in ``topics``.
    load_images
        Keep the encoded image bytes (``False`` keeps only stamps and formats).

    Returns
    -------
    BagData

    Raises
    ------
    BagError
        Bag missing/unreadable, a contract topic with the wrong type, or a
        message that breaks the contract; the message names the topic.
    """
    reader = _open_reader(path)
    data = BagData(path=str(path))
    try:
        conns = list(reader.connections)
        for c in conns:
            cnt = data.topics.get(c.topic, (c.msgtype, 0))[1] + int(c.msgcount)
            data.topics[c.topic] = (c.msgtype, cnt)
        wanted = set(topics) if topics is not None else None
        parse = []
        for c in conns:
            exp = _expected_type(c.topic)
            if exp is not None and c.msgtype != exp:
                raise BagError(f"bag {path}: topic {c.topic} carries {c.msgtype}, the contract requires {exp}")
            if exp is None and c.msgtype != T_POSE_COV:
                data.unknown_topics[c.topic] = c.msgtype
                continue
            if wanted is not None and c.topic not in wanted:
                continue
            parse.append(c)

        acc: dict[str, list[Any]] = {}
        counters: dict[str, int] = {}
        for conn, stamp_ns, raw in (reader.messages(connections=parse) if parse else ()):
            topic = conn.topic
            k = counters.get(topic, 0)
            counters[topic] = k + 1
            msg = deserialize(raw, conn.msgtype, topic=topic)
            try:
                _collect(data, acc, topic, conn.msgtype, msg, stamp_ns, k, load_images)
            except BagError:
                raise
            except (ValueError, TypeError, AttributeError) as exc:
                raise BagError(f"bag {path}: topic {topic} message {k}: {exc}") from exc
    finally:
        reader.close()
    _finish(data, acc)
    return data


# -- per-topic parsers: message -> one row of the topic's accumulator --------------------------------------------


def _row_joint_state(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    names = list(msg.name)
    pos = np.asarray(msg.position, dtype=float)
    if pos.shape[0] != len(names):
        raise BagError(f"topic {topic}: message {k} has {len(names)} names but {pos.shape[0]} positions")
    if len(set(names)) != len(names):
        raise BagError(f"topic {topic}: message {k} lists a joint twice: {names}")
    vel = np.asarray(msg.velocity, dtype=float)
    eff = np.asarray(msg.effort, dtype=float)
    for what, arr in (("velocities", vel), ("efforts", eff)):
        if arr.shape[0] not in (0, len(names)):
            raise BagError(f"topic {topic}: message {k} has {len(names)} names but {arr.shape[0]} {what}")
    return (_stamp_s(msg.header), names, pos, vel, eff)


def _row_camera_info(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    K = np.asarray(msg.k, dtype=float).reshape(3, 3)
    return (_stamp_s(msg.header), msg.header.frame_id, K, np.asarray(msg.d, dtype=float),
            int(msg.width), int(msg.height), msg.distortion_model)


def _row_compressed_image(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    f = msg.format.lower()
    fmt = "png" if "png" in f else "jpeg" if ("jpeg" in f or "jpg" in f) else None
    if fmt is None:
        raise BagError(f"topic {topic}: message {k} format {msg.format!r} is neither png nor jpeg")
    return (_stamp_s(msg.header), msg.header.frame_id, fmt,
            np.asarray(msg.data, dtype=np.uint8).tobytes() if load_images else b"", None)


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
    return (_stamp_s(msg.header), msg.header.frame_id, enc,
            np.ascontiguousarray(img).tobytes() if load_images else b"", shape)


def _row_wrench(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (_stamp_s(msg.header), msg.header.frame_id, _v3(msg.wrench.force), _v3(msg.wrench.torque))


def _row_pose(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (_stamp_s(msg.header), msg.header.frame_id, _pose_to_T(msg.pose))


def _row_point(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    p = msg.point
    return (_stamp_s(msg.header), msg.header.frame_id, [p.x, p.y, p.z])


def _row_imu(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (_stamp_s(msg.header), msg.header.frame_id, _v3(msg.linear_acceleration),
            _v3(msg.angular_velocity), np.asarray(msg.linear_acceleration_covariance, float).reshape(3, 3))


def _row_tag_cloud(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (_stamp_s(msg.header), msg.header.frame_id, _parse_cloud(msg, topic, k))


def _row_pose_cov(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (_stamp_s(msg.header), msg.header.frame_id, _pose_to_T(msg.pose.pose),
            np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6))


_RowParser = Callable[[Any, str, int, bool], tuple]
#: topic -> parser of one message into a row (``/imu/<name>`` and pose-with-covariance topics by prefix / type)
_ROW_PARSERS: dict[str, _RowParser] = {
    TOPIC_JOINT_STATES: _row_joint_state,
    TOPIC_CAMERA_INFO: _row_camera_info,
    TOPIC_COMPRESSED_IMAGE: _row_compressed_image,
    TOPIC_IMAGE: _row_image,
    TOPIC_WRENCH: _row_wrench,
    TOPIC_GT_POSE: _row_pose,
    TOPIC_GT_POINT: _row_point,
    TOPIC_TAG_OBSERVATIONS: _row_tag_cloud,
}


def _row_parser(topic: str, msgtype: str) -> _RowParser:
    if topic in _ROW_PARSERS:
        return _ROW_PARSERS[topic]
    if topic.startswith(IMU_TOPIC_PREFIX):
        return _row_imu
    if msgtype == T_POSE_COV:
        return _row_pose_cov
    raise BagError(f"topic {topic}: no parser for {msgtype}")  # pragma: no cover - filtered before


def _collect(data: BagData, acc: dict[str, list[Any]], topic: str, msgtype: str, msg: Any,
             stamp_ns: int, k: int, load_images: bool) -> None:
    lst = acc.setdefault(topic, [])
    if topic == TOPIC_ROBOT_DESCRIPTION:
        if data.robot_description is not None and msg.data != data.robot_description:
            raise BagError(f"topic {topic}: message {k} differs from the first (contract: once)")
        data.robot_description = msg.data
        return
    lst.append(_row_parser(topic, msgtype)(msg, topic, k, load_images))


# -- per-topic finishers: accumulated rows -> the series of BagData ----------------------------------------------


def _finish_joint_states(data: BagData, topic: str, stamps: np.ndarray, frames: list, lst: list) -> None:
    names: list[str] = []
    index: dict[str, int] = {}
    for e in lst:
        for n in e[1]:
            if n not in index:
                index[n] = len(names)
                names.append(n)
    N, n = len(lst), len(names)
    P = np.full((N, n), np.nan)
    V = np.full((N, n), np.nan)
    E = np.full((N, n), np.nan)
    for i, (_, nm, pos, vel, eff) in enumerate(lst):
        cols = np.fromiter((index[x] for x in nm), dtype=int, count=len(nm))
        P[i, cols] = pos
        if vel.shape[0]:
            V[i, cols] = vel
        if eff.shape[0]:
            E[i, cols] = eff
    data.joint_states = JointStates(stamps, names, P, V, E)


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


def _finish(data: BagData, acc: dict[str, list[Any]]) -> None:
    for topic, lst in acc.items():
        if not lst:
            continue
        stamps = np.array([e[0] for e in lst], dtype=float)
        frames = [e[1] for e in lst]
        if topic in _FINISHERS:
            finisher = _FINISHERS[topic]
        elif topic.startswith(IMU_TOPIC_PREFIX):
            finisher = _finish_imu
        else:
            finisher = _finish_pose_cov
        finisher(data, topic, stamps, frames, lst)
