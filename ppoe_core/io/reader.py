"""Reading contract bags: raw messages in log order (:func:`iter_raw`) and typed series (:func:`read_bag`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import BagError
from ppoe_core.io.messages import (
    CONTRACT_TYPES,
    IMU_TOPIC_PREFIX,
    T_IMU,
    T_POINT,
    T_POSE_COV,
    T_TEMPERATURE,
    TAG_OBSERVATION_FIELDS,
    TOPIC_CAMERA_INFO,
    TOPIC_COMPRESSED_IMAGE,
    TOPIC_GT_POINT,
    TOPIC_GT_POSE,
    TOPIC_IMAGE,
    TOPIC_JOINT_STATES,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_TAG_OBSERVATIONS,
    TOPIC_TEMPERATURE,
    TOPIC_WRENCH,
    _stamp_s,
    deserialize,
    typestore,
)
from ppoe_core.io.recovery import RecoveredMcap, ReadStatus, account, lost_messages, recording_in_progress
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
    TemperatureSeries,
    Wrenches,
)


def _open_reader(path: str | Path) -> Any:
    """The rosbags reader of a bag directory; a bag it cannot open (no footer or no metadata: an
    unfinished recording) is read record by record instead (:class:`RecoveredMcap`, with a ``note``)."""
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise BagError(f"bag {p} does not exist")
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - any failure of rosbags: try the record-by-record scan
        if recording_in_progress(p):
            return RecoveredMcap(p, "the recording was never closed (its metadata.yaml is the recorder's interim one)")
        return RecoveredMcap(p, f"cannot open as a rosbag2 directory ({type(exc).__name__}: {exc})")
    return reader


def _messages(reader: Any, conns: list[Any], status: ReadStatus,
              validate: bool = False) -> Iterator[tuple[Any, int, Any]]:
    """``reader.messages`` that stops, instead of raising, where the file is damaged (noted in ``status``).

    ``validate``: deserialise each message of a known type and skip (count) those that do not parse.
    """
    known = typestore().types
    it = iter(reader.messages(connections=conns)) if conns else iter(())
    while True:
        try:
            conn, stamp_ns, data = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - ReaderError, struct/zstd errors, OverflowError of a damaged file
            status.error = f"{type(exc).__name__}: {exc}"
            return
        status.counts[conn.topic] = status.counts.get(conn.topic, 0) + 1
        if validate and conn.msgtype in known:
            try:
                deserialize(data, conn.msgtype, topic=conn.topic)
            except BagError as exc:
                status.reject(conn.topic, status.counts[conn.topic] - 1, exc)
                continue
        yield conn, stamp_ns, data


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topics of a bag -> (message type, message count), without reading messages."""
    reader = _open_reader(path)
    try:
        return {c.topic: (c.msgtype, int(c.msgcount)) for c in reader.connections}
    finally:
        reader.close()


class BagCheck(NamedTuple):
    """What :func:`check_bag` found: notes for the user, readable messages per topic, and whether the
    file had to be scanned record by record (pass ``scanned`` on to :func:`iter_raw`)."""

    notes: list[str]
    counts: dict[str, int]
    scanned: bool


def _count(reader: Any, topics: Iterable[str] | None) -> tuple[list[Any], ReadStatus]:
    """Read (and validate) every message of the wanted topics; the connections and what was read."""
    wanted = set(topics) if topics is not None else None
    conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
    status = ReadStatus()
    for _ in _messages(reader, conns, status, validate=True):
        pass
    return conns, status


def check_bag(path: str | Path, topics: Iterable[str] | None = None, *, accept_partial: bool = False) -> BagCheck:
    """Read every message (decoding it) and compare with the bag's metadata, before playing it.

    A damaged file is also scanned record by record (resynchronising over damaged bytes); the
    reading that recovers more messages is kept.

    Raises
    ------
    BagError
        Messages were lost (named per topic, read of expected) and ``accept_partial`` is False.
    """
    reader = _open_reader(path)
    try:
        conns, status = _count(reader, topics)
    finally:
        reader.close()
    if (status.problem() or lost_messages(path, conns, status)) and not isinstance(reader, RecoveredMcap):
        try:
            rescue = RecoveredMcap(Path(path), f"damaged ({status.problem() or 'messages missing'})")
            conns2, status2 = _count(rescue, topics)
            if sum(status2.counts.values()) > sum(status.counts.values()):
                reader, conns, status = rescue, conns2, status2
        except BagError:
            pass
    notes = account(path, reader, conns, status, accept_partial)
    return BagCheck(notes, dict(status.counts), isinstance(reader, RecoveredMcap))


def iter_raw(path: str | Path, topics: Iterable[str] | None = None, *, scanned: bool = False) -> Iterator[RawMessage]:
    """Yield the messages of a bag in log-time order as :class:`RawMessage` (for ``ppoe play``).

    ``topics`` restricts to these topic names (unknown names are ignored).  Messages that do not
    decode are skipped and reading stops quietly where the indexed reader fails: call
    :func:`check_bag` first to know what will be lost, and pass its ``scanned`` to read the file
    the way it recovered the most.
    """
    reader = RecoveredMcap(Path(path), "damaged") if scanned else _open_reader(path)
    try:
        wanted = set(topics) if topics is not None else None
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for conn, stamp_ns, data in _messages(reader, conns, ReadStatus(), validate=True):
            yield RawMessage(conn.topic, conn.msgtype, int(stamp_ns), bytes(data))
    finally:
        reader.close()


def _expected_type(topic: str) -> str | None:
    if topic in CONTRACT_TYPES:
        return CONTRACT_TYPES[topic]
    if topic.startswith(IMU_TOPIC_PREFIX):
        return T_IMU
    if _named(topic, TOPIC_GT_POINT):
        return T_POINT
    if topic == TOPIC_TEMPERATURE or _named(topic, TOPIC_TEMPERATURE):
        return T_TEMPERATURE
    return None


def _named(topic: str, prefix: str) -> bool:
    """``topic`` is ``<prefix>/<name>`` (one of several sensors of a kind)."""
    return topic.startswith(prefix + "/") and len(topic) > len(prefix) + 1


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


def read_bag(path: str | Path, *, topics: Iterable[str] | None = None, load_images: bool = True,
             accept_partial: bool = False) -> BagData:
    """Read a contract bag into numpy arrays.

    Parameters
    ----------
    path
        rosbag2 directory (mcap or sqlite3).
    topics
        Parse only these topics (all by default); the others are still listed in ``topics``.
    load_images
        Keep the encoded image bytes (``False`` keeps only stamps and formats).
    accept_partial
        Keep what could be read of a damaged bag (fewer messages than its ``metadata.yaml``
        says, or a file that stops being readable) instead of raising; :attr:`BagData.notes`
        then says per topic what was lost.  An unfinished recording (no footer or metadata) is
        always read record by record, with a note.

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
    try:
        data, parse, status = _read_with(reader, path, topics, load_images)
    finally:
        reader.close()
    if (status.problem() or lost_messages(path, parse, status)) and not isinstance(reader, RecoveredMcap):
        # a damaged file: the record-by-record scan may read more than the indexed reader
        try:
            rescue = RecoveredMcap(Path(path), f"damaged ({status.problem() or 'messages missing'})")
            data2, parse2, status2 = _read_with(rescue, path, topics, load_images)
            if sum(status2.counts.values()) > sum(status.counts.values()):
                reader, data, parse, status = rescue, data2, parse2, status2
        except BagError:
            pass
    data.notes = account(path, reader, parse, status, accept_partial)
    return data


def _read_with(reader: Any, path: str | Path, topics: Iterable[str] | None,
               load_images: bool) -> tuple[BagData, list[Any], ReadStatus]:
    """Parse the wanted contract topics of an open reader; returns the data, the parsed connections
    and what was read."""
    data = BagData(path=str(path))
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
    status = ReadStatus()
    for conn, stamp_ns, raw in _messages(reader, parse, status):
        topic = conn.topic
        k = status.counts[topic] - 1
        try:
            msg = deserialize(raw, conn.msgtype, topic=topic)
        except BagError as exc:
            status.reject(topic, k, exc)
            continue
        try:
            _collect(data, acc, topic, conn.msgtype, msg, stamp_ns, k, load_images)
        except BagError:
            raise
        except (ValueError, TypeError, AttributeError) as exc:
            raise BagError(f"bag {path}: topic {topic} message {k}: {exc}") from exc
    _finish(data, acc)
    return data, parse, status


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


def _row_temperature(msg: Any, topic: str, k: int, load_images: bool) -> tuple:
    return (_stamp_s(msg.header), msg.header.frame_id, float(msg.temperature), float(msg.variance))


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
    if msgtype == T_POINT:
        return _row_point
    if msgtype == T_TEMPERATURE:
        return _row_temperature
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
        elif _named(topic, TOPIC_GT_POINT):
            finisher = _finish_named_point
        elif _expected_type(topic) == T_TEMPERATURE:
            finisher = _finish_temperature
        else:
            finisher = _finish_pose_cov
        finisher(data, topic, stamps, frames, lst)
