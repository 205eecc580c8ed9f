"""Offered QoS in the bags we write (metadata.yaml, rosbag2 Jazzy's version-9 form) and rosbag2's playback rule.

Without ROS: :mod:`ppoe_core.io.bag_qos` and the writer.  The live half (a player that offers what the bag
recorded, a node that then gets the URDF) is test/test_bag_qos_live.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO
from rosbags.interfaces import QosDurability, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from ppoe_core.errors import BagError
from ppoe_core.io.bag_qos import (
    DURATION_INFINITE,
    make_qos,
    offered_qos,
    playback_qos,
    recorded_qos,
)
from ppoe_core.io.bag_qos_fill import fill_offered_qos
from ppoe_core.io.bagio import BagWriter, typestore

SHIPPED = sorted(p.parent for p in (REPO / "bags").glob("*/metadata.yaml"))
URDF = "<robot name='r'><link name='base_link'/></robot>"


def _policies(q) -> tuple:
    return q.reliability, q.durability


@pytest.mark.parametrize("topic", ["/robot_description", "/robot1/robot_description", "/tf_static",
                                   "robot_description"])
def test_latched_topics_are_offered_transient_local(topic: str) -> None:
    (q,) = offered_qos(topic)
    assert _policies(q) == (QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL) and q.depth == 1


@pytest.mark.parametrize("topic", ["/joint_states", "/tf", "/camera/image_raw/compressed", "/robot_description_x",
                                   "/imu/forearm"])
def test_other_topics_are_offered_reliable_volatile(topic: str) -> None:
    (q,) = offered_qos(topic)
    assert _policies(q) == (QosReliability.RELIABLE, QosDurability.VOLATILE) and q.depth == 10


def test_playback_rule_is_rosbag2s() -> None:
    """rosbag2's adapt_offer_to_recorded_offers: no profile -> reliable volatile; equal offers (history, depth and
    lifespan do not count) -> that offer; differing offers -> the default.  ``fallback`` only replaces the first."""
    latched = make_qos(transient_local=True, depth=1)
    assert _policies(playback_qos([])) == (QosReliability.RELIABLE, QosDurability.VOLATILE)
    assert playback_qos([], fallback=latched) == latched
    deeper = latched._replace(depth=50, lifespan=QosTime(3, 0))
    assert playback_qos([latched, deeper]) == latched
    best_effort = make_qos(reliable=False)
    assert playback_qos([best_effort], fallback=latched) == best_effort
    mixed = playback_qos([latched, make_qos()], fallback=latched)
    assert _policies(mixed) == (QosReliability.RELIABLE, QosDurability.VOLATILE)
    assert playback_qos([latched._replace(deadline=QosTime(1, 0)), latched]) == make_qos()


def test_writer_stores_qos_per_topic_and_recorder_profiles_win(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag) as w:
        w.offered_qos["/wrench"] = [make_qos(reliable=False, depth=5)]
        w.write_robot_description(URDF, 0.0)
        w.write_joint_state(1.0, ["a"], [0.1])
        w.write_wrench(1.0, "tool0", [0, 0, 1], [0, 0, 0])
    got = recorded_qos(bag)
    assert got["/robot_description"] == offered_qos("/robot_description")
    assert got["/joint_states"] == offered_qos("/joint_states")
    assert got["/wrench"] == [make_qos(reliable=False, depth=5)]
    # rosbag2 Jazzy's version-9 form: a YAML sequence of mappings with policy names, infinite durations
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9
    rd = next(t["topic_metadata"] for t in meta["topics_with_message_count"]
              if t["topic_metadata"]["name"] == "/robot_description")
    assert rd["offered_qos_profiles"] == [{
        "history": "keep_last", "depth": 1, "reliability": "reliable", "durability": "transient_local",
        "deadline": {"sec": DURATION_INFINITE.sec, "nsec": DURATION_INFINITE.nsec},
        "lifespan": {"sec": 9223372036, "nsec": 854775807}, "liveliness": "automatic",
        "liveliness_lease_duration": {"sec": 9223372036, "nsec": 854775807},
        "avoid_ros_namespace_conventions": False}]


def _plain_rosbags_bag(path: Path) -> None:
    """A bag as the writer made it before it stored QoS (rosbags' Writer, no profiles)."""
    from ppoe_core.io.bagio import cdr_joint_state

    store = typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/robot_description", "std_msgs/msg/String", typestore=store)
        w.write(conn, 0, store.serialize_cdr(store.types["std_msgs/msg/String"](data=URDF), "std_msgs/msg/String"))
        js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        for k in range(3):
            ns = (1 + k) * 10**9
            w.write(js, ns, cdr_joint_state(ns, ["a"], np.array([0.1 * k]), np.zeros(0), np.zeros(0)))


def _messages(bag: Path) -> list[tuple[str, str, int, bytes]]:
    """Every message of a bag as rosbags' reader yields it (it matches metadata.yaml with the mcap channels)."""
    with Reader(bag) as reader:
        return [(c.topic, c.msgtype, t, bytes(d)) for c, t, d in reader.messages()]


def test_fill_gives_the_writers_bag_and_keeps_every_message(tmp_path: Path) -> None:
    old, new = tmp_path / "old" / "b", tmp_path / "new" / "b"
    old.parent.mkdir()
    new.parent.mkdir()
    _plain_rosbags_bag(old)
    before = _messages(old)
    assert recorded_qos(old) == {"/robot_description": [], "/joint_states": []}
    with BagWriter(new) as w:
        w.write_robot_description(URDF, 0.0)
        for k in range(3):
            w.write_joint_state(1.0 + k, ["a"], [0.1 * k])
    assert fill_offered_qos(old) == ["/robot_description", "/joint_states"]
    assert (old / "metadata.yaml").read_text() == (new / "metadata.yaml").read_text()
    assert _messages(old) == before == _messages(new)
    assert sorted(p.name for p in old.parent.iterdir()) == ["b"]  # no work directory left
    with Reader(old) as reader:  # the mcap channels carry the profiles too (rosbags compares both)
        assert [c.ext.offered_qos_profiles for c in reader.connections] == [
            offered_qos("/robot_description"), offered_qos("/joint_states")]
    assert fill_offered_qos(old) == []  # topics with profiles keep them


def test_fill_refuses_a_directory_without_a_bag(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no metadata.yaml"):
        fill_offered_qos(tmp_path)


def test_recorded_qos_reads_the_humble_string_form(tmp_path: Path) -> None:
    """Metadata versions 4-8 hold the list as one YAML string with integer policies (a Humble/Iron bag)."""
    bag = tmp_path / "humble"
    bag.mkdir()
    profiles = ("- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n  deadline:\n    sec: 0\n    nsec: 0\n"
                "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n"
                "    nsec: 0\n  avoid_ros_namespace_conventions: false")
    doc = {"rosbag2_bagfile_information": {"version": 5, "topics_with_message_count": [
        {"message_count": 1, "topic_metadata": {"name": "/robot_description", "type": "std_msgs/msg/String",
                                                "serialization_format": "cdr", "offered_qos_profiles": profiles}}]}}
    (bag / "metadata.yaml").write_text(yaml.safe_dump(doc))
    (q,) = recorded_qos(bag)["/robot_description"]
    assert _policies(q) == (QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [")
    with pytest.raises(BagError, match="cannot read"):
        recorded_qos(bag)


@pytest.mark.parametrize("bag", SHIPPED, ids=[p.name for p in SHIPPED])
def test_shipped_bags_record_the_offered_qos(bag: Path) -> None:
    """Every topic of every shipped bag has the profile the writer stores now (so ``ros2 bag play`` latches the
    URDF), in metadata.yaml and in the mcap channels alike: rosbags reads every message the metadata counts."""
    got = recorded_qos(bag)
    assert "/robot_description" in got
    for topic, profiles in got.items():
        assert profiles == offered_qos(topic), f"{bag.name}: {topic}: {profiles}"
    with Reader(bag) as reader:
        n_read = sum(1 for _ in reader.messages())
        assert n_read == reader.message_count > 0
