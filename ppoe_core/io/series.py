"""What :func:`ppoe_core.io.bagio.read_bag` returns: per-topic series as numpy arrays (stamps in seconds)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ppoe_core.errors import BagError
from ppoe_core.io.messages import (
    IMU_TOPIC_PREFIX, TOPIC_CAMERA_INFO, TOPIC_GT_POINT, TOPIC_GT_POSE, TOPIC_JOINT_STATES, TOPIC_ROBOT_DESCRIPTION,
    TOPIC_TAG_OBSERVATIONS, TOPIC_WRENCH,
)


# ===================================================================== reader
@dataclass
class JointStates:
    """``/joint_states``, aligned by name.

    ``names`` is the union of names in first-seen order; ``positions[i, j]`` is
    joint ``names[j]`` in message ``i`` (NaN where a message does not carry it).
    ``velocities`` / ``efforts`` likewise (NaN where absent or empty).
    """

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    names: list[str] = field(default_factory=list)
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    velocities: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    efforts: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def as_dict(self, i: int) -> dict[str, float]:
        """Joint values of message ``i`` as ``{name: value}`` (joints it carried only)."""
        row = self.positions[i]
        return {n: float(v) for n, v in zip(self.names, row) if np.isfinite(v)}

    def column(self, name: str) -> np.ndarray:
        """Positions of one joint, (N,); raises BagError if the bag never lists it."""
        if name not in self.names:
            raise BagError(f"topic {TOPIC_JOINT_STATES}: joint {name!r} never appears (has {self.names})")
        return self.positions[:, self.names.index(name)]


@dataclass
class CameraInfos:
    """``/camera/camera_info``: per message ``K`` (N,3,3), ``D`` (N,k), sizes."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    K: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    D: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    width: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    height: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    distortion_models: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class Images:
    """Camera images (compressed or raw), kept encoded; :meth:`decode` on demand.

    ``formats[i]`` is "png", "jpeg" (compressed) or the raw encoding ("mono8", "bgr8", ...).
    """

    topic: str = ""
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    formats: list[str] = field(default_factory=list)
    data: list[bytes] = field(default_factory=list)
    shapes: list[tuple[int, ...] | None] = field(default_factory=list)  # raw images only

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def decode(self, i: int, grey: bool = False) -> np.ndarray:
        """Image ``i`` as uint8 (H,W) or (H,W,3) BGR; ``grey`` converts colour to mono.

        Raises
        ------
        BagError
            If the bytes do not decode (names the topic and the message index).
        """
        import cv2

        fmt = self.formats[i]
        if fmt in ("png", "jpeg"):
            from ppoe_core.io.png import decode_png

            # plain PNGs as OpenCV writes them without libpng (the same pixels, faster), the rest by OpenCV
            img = decode_png(self.data[i]) if fmt == "png" else None
            if img is None:
                img = decode_compressed(self.data[i])
            if img is None:
                raise BagError(f"topic {self.topic}: message {i} (stamp {self.stamps[i]:.6f} s) "
                               f"is not a decodable {fmt} image")
        else:
            shape = self.shapes[i]
            assert shape is not None
            img = np.frombuffer(self.data[i], dtype=np.uint8).reshape(shape)
            if fmt == "rgb8":
                img = img[..., ::-1]
        if grey and img.ndim == 3:
            img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(img)


def decode_compressed(data: bytes) -> np.ndarray | None:
    """PNG / JPEG bytes -> image array (as stored: grey, BGR or BGRA), or None if they do not decode.

    OpenCV's own log lines about broken data (``IHDR chunk shall be first`` ...) are silenced: the
    caller reports the failure in one line naming the topic or file.
    """
    import cv2

    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - an OpenCV build without the logging module
        pass
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    return None if img is None or img.size == 0 else img


@dataclass
class Wrenches:
    """``/wrench``: force (N,3) [N] and torque (N,3) [N m]."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    force: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    torque: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class PoseSeries:
    """``PoseStamped`` series: ``T`` (N,4,4) of the child in ``frame_ids[i]``."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class PointSeries:
    """``PointStamped`` series: ``p`` (N,3) [m] in ``frame_ids[i]``."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    p: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class TemperatureSeries:
    """``/temperature[/<name>]`` (``sensor_msgs/Temperature``): ``temperature`` (N,) [deg C], ``variance`` (N,)."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    temperature: np.ndarray = field(default_factory=lambda: np.zeros(0))
    variance: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class ImuSeries:
    """``/imu/<name>``: linear acceleration (N,3) [m/s^2], angular velocity (N,3) [rad/s],
    accelerometer covariance (N,3,3), in the link ``frame_ids[i]``."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    linear_acceleration: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    accel_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class TagObservationRows:
    """``/tag_bearing/observations``, flattened over messages.

    ``stamps``/``frame_ids`` are per message (M,); the point arrays are (P,) /
    (P,2) with ``msg_index`` giving each point's message.
    """

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    msg_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    corners: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def message(self, i: int) -> dict[str, np.ndarray]:
        """Points of message ``i``: keys ``ids``, ``corners``, ``uv``, ``xy``."""
        sel = self.msg_index == i
        return {"ids": self.ids[sel], "corners": self.corners[sel], "uv": self.uv[sel], "xy": self.xy[sel]}


@dataclass
class PoseCovSeries:
    """``PoseWithCovarianceStamped`` series: ``T`` (N,4,4), ``cov_ros`` (N,6,6) in the ROS
    convention (docs/conventions.md sec. 2: axes of ``frame_ids[i]``, order x y z rx ry rz)."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_ids: list[str] = field(default_factory=list)
    T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    cov_ros: np.ndarray = field(default_factory=lambda: np.zeros((0, 6, 6)))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass
class BagData:
    """Everything a contract bag carries, as numpy arrays (stamps in seconds).

    Absent optional topics give empty series (``len(...) == 0``).  ``images`` is the camera
    image stream: ``/camera/image_raw/compressed`` if the bag has it, else ``/camera/image_raw``;
    a bag with both keeps the raw stream in ``raw_images`` as well.
    """

    path: str
    robot_description: str | None = None
    joint_states: JointStates = field(default_factory=JointStates)
    camera_info: CameraInfos = field(default_factory=CameraInfos)
    images: Images = field(default_factory=Images)
    raw_images: Images = field(default_factory=Images)
    wrench: Wrenches = field(default_factory=Wrenches)
    ground_truth_pose: PoseSeries = field(default_factory=PoseSeries)
    ground_truth_point: PointSeries = field(default_factory=PointSeries)
    #: ``/ground_truth/point/<name>`` (several reflectors), keyed by the full topic name
    ground_truth_points: dict[str, PointSeries] = field(default_factory=dict)
    #: ``/temperature`` and ``/temperature/<name>``, keyed by the full topic name
    temperatures: dict[str, TemperatureSeries] = field(default_factory=dict)
    imus: dict[str, ImuSeries] = field(default_factory=dict)
    tag_observations: TagObservationRows = field(default_factory=TagObservationRows)
    poses_with_covariance: dict[str, PoseCovSeries] = field(default_factory=dict)
    #: every topic of the bag -> (message type, message count)
    topics: dict[str, tuple[str, int]] = field(default_factory=dict)
    #: topics that were not parsed (not in the contract) -> message type
    unknown_topics: dict[str, str] = field(default_factory=dict)
    #: what the user must be told about the reading: a recovered unfinished recording, or what was
    #: lost of a damaged bag read with ``accept_partial`` (one line each)
    notes: list[str] = field(default_factory=list)

    def require_robot_description(self) -> str:
        """The URDF; raises BagError if the bag has no ``/robot_description``."""
        if not self.robot_description:
            raise BagError(f"bag {self.path}: no {TOPIC_ROBOT_DESCRIPTION} message (contract: once, first)")
        return self.robot_description

    def rate(self, topic: str) -> float:
        """Mean message rate [Hz] of a parsed topic (median inter-stamp gap; 0 if < 2 msgs)."""
        stamps = self._stamps_of(topic)
        if stamps.shape[0] < 2:
            return 0.0
        gaps = np.diff(np.sort(stamps))
        gaps = gaps[gaps > 0]
        return float(1.0 / np.median(gaps)) if gaps.size else 0.0

    def _stamps_of(self, topic: str) -> np.ndarray:
        table = {TOPIC_JOINT_STATES: self.joint_states.stamps, TOPIC_CAMERA_INFO: self.camera_info.stamps,
                 TOPIC_WRENCH: self.wrench.stamps, TOPIC_GT_POSE: self.ground_truth_pose.stamps,
                 TOPIC_GT_POINT: self.ground_truth_point.stamps,
                 TOPIC_TAG_OBSERVATIONS: self.tag_observations.stamps}
        if topic in table:
            return table[topic]
        if topic == self.images.topic:
            return self.images.stamps
        if topic == self.raw_images.topic:
            return self.raw_images.stamps
        if topic.startswith(IMU_TOPIC_PREFIX) and topic[len(IMU_TOPIC_PREFIX):] in self.imus:
            return self.imus[topic[len(IMU_TOPIC_PREFIX):]].stamps
        if topic in self.poses_with_covariance:
            return self.poses_with_covariance[topic].stamps
        if topic in self.ground_truth_points:
            return self.ground_truth_points[topic].stamps
        if topic in self.temperatures:
            return self.temperatures[topic].stamps
        raise BagError(f"bag {self.path}: topic {topic} was not parsed (topics: {sorted(self.topics)})")


class RawMessage(NamedTuple):
    """One message of a bag as stored: topic, type, log time [ns], CDR bytes."""

    topic: str
    msgtype: str
    stamp_ns: int
    data: bytes
