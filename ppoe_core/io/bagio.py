"""Read and write recorded bags (docs/conventions.md section 3) with ``rosbags``.

Pure Python: no rclpy and no ROS message packages.  Messages are built and
parsed with the ``rosbags`` type store of ROS 2 Jazzy, so a bag written here is
readable by ``ros2 bag`` and a bag recorded by ``ros2 bag`` (or ``ppoe
record``) is readable here.

Writing::

    with BagWriter("out_bag") as bag:                # rosbag2 directory, storage mcap
        bag.write_robot_description(urdf_xml, stamp=0.0)
        bag.write_joint_state(0.01, ["j1", "j2"], [0.1, 0.2])
        bag.write_compressed_image(0.02, "camera_optical_frame", img)   # png
        ...

Reading::

    data = read_bag("out_bag")
    data.joint_states.positions          # (N, n) aligned by data.joint_states.names
    data.images.decode(0)                # numpy image, decoded on demand

All stamps are in seconds (float, from ``header.stamp``; the String of
``/robot_description`` carries no header and uses the bag's log time).
A topic of the contract carrying the wrong message type, or a message that
breaks the contract (e.g. a ``JointState`` whose ``position`` does not match
``name``), raises :class:`~ppoe_core.errors.BagError` naming the topic.
Topics outside the contract are not parsed, but listed in
:attr:`BagData.unknown_topics`; ``PoseWithCovarianceStamped`` topics (our node
outputs) are parsed into :attr:`BagData.poses_with_covariance`.

For replay (``ppoe play``) :func:`iter_raw` yields the raw CDR bytes.
"""

from __future__ import annotations

from ppoe_core.io.messages import (
    CONTRACT_TYPES, IMU_TOPIC_PREFIX, TAG_OBSERVATION_FIELDS, TOPIC_CAMERA_INFO, TOPIC_COMPRESSED_IMAGE, TOPIC_GT_POINT,
    TOPIC_GT_POSE, TOPIC_IMAGE, TOPIC_JOINT_STATES, TOPIC_ROBOT_DESCRIPTION, TOPIC_TAG_OBSERVATIONS, TOPIC_WRENCH,
    deserialize, header_msg, serialize, stamp_to_ns, typestore,
)
from ppoe_core.io.reader import bag_topics, BagCheck, check_bag, iter_raw, read_bag
from ppoe_core.io.series import (
    BagData, CameraInfos, Images, ImuSeries, JointStates, PointSeries, PoseCovSeries, PoseSeries, RawMessage,
    TagObservationRows, Wrenches,
)
from ppoe_core.io.writer import BagWriter, cdr_joint_state

__all__ = [
    "header_msg", "cdr_joint_state", "TOPIC_ROBOT_DESCRIPTION", "TOPIC_JOINT_STATES", "TOPIC_CAMERA_INFO",
    "TOPIC_COMPRESSED_IMAGE", "TOPIC_IMAGE", "TOPIC_WRENCH", "TOPIC_GT_POSE", "TOPIC_GT_POINT",
    "TOPIC_TAG_OBSERVATIONS", "IMU_TOPIC_PREFIX", "CONTRACT_TYPES", "TAG_OBSERVATION_FIELDS", "typestore", "BagWriter",
    "BagData", "JointStates", "CameraInfos", "Images", "Wrenches", "PoseSeries", "PointSeries", "ImuSeries",
    "TagObservationRows", "PoseCovSeries", "RawMessage", "read_bag", "iter_raw", "bag_topics", "BagCheck", "check_bag",
    "deserialize", "serialize", "stamp_to_ns",
]
