"""Offered QoS per topic in the bags we write, and rosbag2's rule for the QoS a player offers.

rosbag2 records, per topic, the QoS profiles its publishers offered (``offered_qos_profiles`` in
``metadata.yaml``); ``ros2 bag play`` offers the recorded profile again, and a bag without one is played
*reliable, volatile*.  A volatile ``/robot_description`` never reaches a transient-local subscriber
(robot_state_publisher's consumers, our nodes): the DDS durability check refuses the pair.  So every bag
written by :class:`~ppoe_core.io.writer.BagWriter` (``ppoe simulate``, ``ppoe import``, ``ppoe record``)
stores a profile per topic: what the publishers offered when recorded live (``ppoe record``), else
:func:`offered_qos` (transient local for ``robot_description`` and ``tf_static``, as robot_state_publisher
and tf2's static broadcaster offer them; reliable and volatile otherwise).

Format: rosbag2 Jazzy writes metadata version 9, where ``offered_qos_profiles`` is a YAML *sequence* of
mappings with policy names (``history: keep_last``, ``reliability: reliable``, durations as ``sec`` /
``nsec``); versions 4-8 (Humble, Iron) stored the same list as one YAML string with integer policies.
rosbags' writer (version 9) writes the sequence; its reader understands both.

Pure Python (rosbags' QoS types): no ROS.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from ppoe_core.errors import BagError

__all__ = [
    "LATCHED_TOPIC_NAMES",
    "DURATION_INFINITE",
    "make_qos",
    "offered_qos",
    "playback_qos",
    "recorded_qos",
    "read_bag_metadata",
]

#: last name component of the topics offered transient local ("latched"): the URDF as robot_state_publisher
#: offers it, the static transforms as tf2's StaticTransformBroadcaster does; any namespace
LATCHED_TOPIC_NAMES = ("robot_description", "tf_static")

#: RMW_DURATION_INFINITE as a recorder reads it from a publisher with no deadline / lifespan / lease
DURATION_INFINITE = QosTime(9223372036, 854775807)

#: rosbag2's default offer (``Rosbag2QoS{}`` = ``rclcpp::QoS(10)``): keep last 10, reliable, volatile
_ROSBAG2_DEFAULT_DEPTH = 10

#: depth of a latched topic's offer: robot_state_publisher and tf2's static broadcaster keep one message
_LATCHED_DEPTH = 1


def make_qos(*, reliable: bool = True, transient_local: bool = False, depth: int = _ROSBAG2_DEFAULT_DEPTH) -> Qos:
    """One QoS profile as a recorder stores it (keep last ``depth``, automatic liveliness, no deadline)."""
    return Qos(
        QosHistory.KEEP_LAST, int(depth),
        QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        DURATION_INFINITE, DURATION_INFINITE, QosLiveliness.AUTOMATIC, DURATION_INFINITE, False)


def offered_qos(topic: str) -> list[Qos]:
    """Profiles recorded for ``topic`` when no live publisher told them: one profile, as one publisher offers.

    Transient local, depth 1 for ``.../robot_description`` and ``.../tf_static``; reliable, volatile,
    keep last 10 (rclcpp's default publisher) for every other topic.
    """
    if topic.rstrip("/").rsplit("/", 1)[-1] in LATCHED_TOPIC_NAMES:
        return [make_qos(transient_local=True, depth=_LATCHED_DEPTH)]
    return [make_qos()]


def _compatibility_key(q: Qos) -> tuple:
    """The policies that decide whether two endpoints match (history, depth and lifespan do not)."""
    return (q.reliability, q.durability, q.deadline, q.liveliness, q.liveliness_lease_duration)


def playback_qos(profiles: Sequence[Qos], fallback: Qos | None = None) -> Qos:
    """The profile a player offers for a topic recorded with ``profiles``, by rosbag2's rule.

    rosbag2 (``Rosbag2QoS::adapt_offer_to_recorded_offers``): no recorded profile -> its default offer
    (reliable, volatile, keep last 10); all profiles equal in the policies that decide a match -> that
    profile; publishers that differed -> the default offer.  ``fallback`` replaces the default offer for
    a topic recorded without any profile (``ppoe play`` passes :func:`offered_qos` there, so an old bag's
    ``/robot_description`` is still latched); None = rosbag2's behaviour exactly.
    """
    default = make_qos()
    if not profiles:
        return fallback if fallback is not None else default
    first = profiles[0]
    if all(_compatibility_key(p) == _compatibility_key(first) for p in profiles[1:]):
        return first
    return default


def recorded_qos(bag: str | Path) -> dict[str, list[Qos]]:
    """``offered_qos_profiles`` per topic from a bag's ``metadata.yaml`` (empty without the file).

    Understands metadata version 9 (a sequence) and 4-8 (a YAML string).

    Raises
    ------
    BagError
        The file exists but its YAML or a profile cannot be read (naming the file and topic).
    """
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.rosbag2.metadata import parse_qos

    path = Path(bag) / "metadata.yaml"
    if not path.is_file():
        return {}
    info = read_bag_metadata(path)
    out: dict[str, list[Qos]] = {}
    for entry in info.get("topics_with_message_count") or []:
        meta = entry.get("topic_metadata") or {}
        name = str(meta.get("name", ""))
        try:
            out[name] = parse_qos(meta.get("offered_qos_profiles") or [])
        except (ReaderError, KeyError, TypeError, ValueError) as exc:
            raise BagError(f"{path}: topic {name}: offered_qos_profiles cannot be read: {exc}") from None
    return out


def read_bag_metadata(path: Path) -> dict:
    """The ``rosbag2_bagfile_information`` mapping of a ``metadata.yaml`` (:class:`BagError` naming the file)."""
    from ruamel.yaml import YAML
    from ruamel.yaml.error import YAMLError

    try:
        doc = YAML(typ="safe").load(path.read_text())
    except (OSError, YAMLError) as exc:
        raise BagError(f"{path}: cannot read: {exc}") from None
    return _info_of(doc, path)


def _info_of(doc: object, path: Path) -> dict:
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise BagError(f"{path}: no 'rosbag2_bagfile_information' mapping")
    return info
