"""read_bag's raw-CDR field reading (the table-driven reader of ppoe_core/io/cdr.py) against rosbags' typed
deserialisation.

* every message of every shipped bag (and of a bag with every hot type written here): the raw parser reads the
  fields the typed path reads, bit for bit, and ``read_bag`` returns identical series with and without it;
* damaged bytes (cut, wrong header, no string terminator, trailing bytes): the raw parser declines wherever the
  typed deserialiser refuses, and where it accepts, it reads the typed path's fields.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppoe_core.errors import BagError
from ppoe_core.io import bagio, reader
from ppoe_core.io.cdr import PARSE_ERRORS
from ppoe_core.io.messages import deserialize
from ppoe_core.io.rows import row_kind

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted(p.parent for p in (REPO / "bags").glob("*/metadata.yaml"))


def _same(a: Any, b: Any) -> bool:
    """Equal values and types, arrays bit for bit (NaN equal to NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    if isinstance(a, (memoryview, bytes)) or isinstance(b, (memoryview, bytes)):
        return bytes(a) == bytes(b)
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(_same(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b):
        return True
    return type(a) is type(b) and a == b


def _hot_messages(bag: Path) -> list[tuple[str, str, bytes]]:
    """(topic, type, raw bytes) of every message whose topic has a raw parser."""
    from rosbags.rosbag2 import Reader

    with Reader(bag) as r:
        conns = [c for c in r.connections if reader.expected_type(c.topic) is not None or
                 c.msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped"]
        conns = [c for c in conns if c.topic != "/robot_description" and row_kind(c.topic, c.msgtype).parse]
        return [(c.topic, c.msgtype, bytes(raw)) for c, _, raw in r.messages(connections=conns)]


def _typed_fields(topic: str, msgtype: str, raw: bytes) -> tuple:
    return row_kind(topic, msgtype).fields(deserialize(raw, msgtype, topic=topic))


def _written_bag(path: Path) -> Path:
    """Every hot message type, with empty and non-empty sequences and odd-length strings (alignment)."""
    rng = np.random.default_rng(3)
    with bagio.BagWriter(path) as bag:
        for k in range(20):
            names = ["j1", "joint_two", "j3x"][: 1 + k % 3]
            vel = rng.normal(size=len(names)) if k % 2 else None
            bag.write_joint_state(0.01 * k, names, rng.normal(size=len(names)), velocities=vel)
            T = np.eye(4)
            T[:3, 3] = rng.normal(size=3)
            bag.write_ground_truth_pose(0.01 * k + 0.001, "b" * (k % 5), T)
            bag.write_ground_truth_point(0.01 * k + 0.002, "tr" * (k % 3), rng.normal(size=3))
            bag.write_wrench(0.01 * k + 0.003, "ft" + "x" * (k % 4), rng.normal(size=3), rng.normal(size=3))
            bag.write_compressed_image(0.01 * k + 0.004, "cam" + "y" * (k % 3), bytes(rng.integers(0, 255, 17 + k,
                                                                                                  dtype=np.uint8)),
                                       "png")
            bag.write_pose_with_covariance("/ppoe/fused_pose", 0.01 * k + 0.005, "base" + "z" * (k % 2), T,
                                           np.diag(rng.uniform(1, 2, 6)))
        # messages of one size whose layouts differ: velocities or efforts, other names of the same length
        for k, (names, with_vel) in enumerate([(["a", "b"], True), (["a", "b"], False), (["a", "c"], True),
                                               (["a", "c"], True), (["a", "b"], False)]):
            two = rng.normal(size=2)
            bag.write_joint_state(1.0 + 0.01 * k, names, rng.normal(size=2), velocities=two if with_vel else None,
                                  efforts=None if with_vel else two)
    return path


def _bags(tmp_path: Path) -> list[Path]:
    return [*SHIPPED, _written_bag(tmp_path / "written")]


def test_raw_fields_equal_typed_fields_on_every_message(tmp_path: Path) -> None:
    assert len(SHIPPED) >= 9
    seen: set[str] = set()
    for bag in _bags(tmp_path):
        for topic, msgtype, raw in _hot_messages(bag):
            fast = row_kind(topic, msgtype).parse(raw)  # type: ignore[misc]
            assert _same(fast, _typed_fields(topic, msgtype, raw)), (bag, topic)
            seen.add(msgtype)
    assert len(seen) == 6, seen  # JointState, CompressedImage, PoseStamped, PointStamped, Wrench, PoseWithCov


def test_read_bag_identical_without_raw_parsing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bags = _bags(tmp_path)
    fast = [reader.read_bag(b) for b in bags]
    monkeypatch.setattr(reader, "_raw_fields", lambda kind, raw: None)  # typed deserialisation only
    monkeypatch.setattr(reader, "_joint_state_block", lambda raws: None)  # /joint_states message by message too
    for bag, data in zip(bags, fast):
        assert _same(data, reader.read_bag(bag)), bag


def _mutations(raw: bytes) -> list[bytes]:
    """Cut at every length, big-endian and unknown headers, a string terminator overwritten, trailing bytes."""
    out = [raw[:n] for n in range(len(raw))]
    out += [b"\x00\x00" + raw[2:], b"\x00\x07" + raw[2:]]
    out += [raw + bytes(8), raw + b"\x01" * 8, raw + bytes(40), raw + b"\x01" * 9, raw + bytes(9) + b"\x01"]
    for i in range(4, len(raw)):
        if raw[i] == 0:
            out.append(raw[:i] + b"A" + raw[i + 1:])
    for i in range(4, min(len(raw), 40), 4):  # a length or count made huge
        out.append(raw[:i] + b"\xff\xff\xff\x7f" + raw[i + 4:])
    return out


def test_raw_parser_declines_what_the_typed_path_refuses(tmp_path: Path) -> None:
    bag = _written_bag(tmp_path / "written")
    samples: dict[str, tuple[str, bytes]] = {}
    for topic, msgtype, raw in _hot_messages(bag):
        samples.setdefault(msgtype, (topic, raw))
    accepted = declined = 0
    for msgtype, (topic, raw) in samples.items():
        parse = row_kind(topic, msgtype).parse
        assert parse is not None
        for bad in _mutations(raw):
            try:
                fast = parse(bad)
            except PARSE_ERRORS:
                declined += 1
                continue
            accepted += 1
            try:
                typed = _typed_fields(topic, msgtype, bad)
            except BagError:
                pytest.fail(f"{msgtype}: the raw parser accepts bytes the typed path refuses: {bad!r}")
            assert _same(fast, typed), (msgtype, bad)
    assert accepted > 20 and declined > 100


def test_contract_errors_are_the_same_on_the_raw_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ts = bagio.typestore()
    JS = ts.types["sensor_msgs/msg/JointState"]
    cases = {
        "has 2 names but 1 positions": JS(header=bagio.header_msg(0, ""), name=["a", "b"], position=np.array([1.0]),
                                         velocity=np.zeros(0), effort=np.zeros(0)),
        "lists a joint twice: ['a', 'a']": JS(header=bagio.header_msg(0, ""), name=["a", "a"],
                                             position=np.ones(2), velocity=np.zeros(0), effort=np.zeros(0)),
        "has 2 names but 1 efforts": JS(header=bagio.header_msg(0, ""), name=["a", "b"], position=np.ones(2),
                                        velocity=np.zeros(0), effort=np.ones(1)),
    }
    for i, (needle, msg) in enumerate(cases.items()):
        path = tmp_path / f"bad{i}"
        with bagio.BagWriter(path) as bag:
            bag.write_raw("/joint_states", "sensor_msgs/msg/JointState", 5, bagio.serialize(msg, JS.__msgtype__))
        errors = []
        for typed_only in (False, True):
            with monkeypatch.context() as m:
                if typed_only:
                    m.setattr(reader, "_raw_fields", lambda kind, raw: None)
                    m.setattr(reader, "_joint_state_block", lambda raws: None)
                with pytest.raises(BagError, match=re.escape(f"/joint_states: message 0 {needle}")) as err:
                    reader.read_bag(path)
            errors.append(str(err.value))
        assert errors[0] == errors[1]
    path = tmp_path / "badquat"
    with bagio.BagWriter(path) as bag:
        P = ts.types["geometry_msgs/msg/PoseStamped"]
        pose = ts.types["geometry_msgs/msg/Pose"](position=ts.types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                                  orientation=ts.types["geometry_msgs/msg/Quaternion"](
                                                      x=0.0, y=0.0, z=0.0, w=0.0))
        bag.write_raw("/ground_truth/pose", P.__msgtype__, 7,
                      bagio.serialize(P(header=bagio.header_msg(0, "base"), pose=pose), P.__msgtype__))
    with pytest.raises(BagError, match=r"topic /ground_truth/pose message 0: invalid quaternion"):
        reader.read_bag(path)


def test_joint_states_read_at_once_equal_message_by_message(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``/joint_states`` of one layout is read in one numpy operation (``cdr.joint_state_block``); a message of another
    layout anywhere (names, value counts, trailing bytes) sends the topic message by message; the series are the
    same bit for bit either way."""
    from ppoe_core.io.cdr import joint_state_block, parse_fields
    from ppoe_core.io.writer import cdr_joint_state

    rng = np.random.default_rng(3)

    def js(i: int, names: tuple[str, ...] = ("a", "b"), vel: bool = True) -> bytes:
        n = len(names)
        return cdr_joint_state(10**9 * (100 + i) + int(rng.integers(0, 10**9)), list(names), rng.normal(size=n),
                               rng.normal(size=n) if vel else np.zeros(0), np.zeros(0), frame_id="f")

    same = [js(i) for i in range(30)]
    block = joint_state_block(same)
    assert block is not None and block.positions.shape == (30, 2) and block.effort.shape == (30, 0)
    for i, raw in enumerate(same):
        stamp, frame, names, pos, vel, eff = parse_fields("sensor_msgs/msg/JointState", raw)
        assert block.stamps[i] == stamp and frame == block.frame and names == block.names
        assert _same(block.positions[i], pos) and _same(block.velocities[i], vel)
    variants = {"names": js(30, ("a", "c")), "more names": js(30, ("a", "b", "c")), "no velocities": js(30, vel=False),
                "trailing bytes": js(30) + b"\x01" * 9}
    for what, odd in variants.items():
        msgs = same[:12] + [odd] + same[12:]
        assert joint_state_block(msgs) is None, what
        if what == "trailing bytes":
            continue  # (the bag writer refuses such a message)
        path = tmp_path / what.replace(" ", "_")
        with bagio.BagWriter(path) as bag:
            for i, raw in enumerate(msgs):
                bag.write_raw("/joint_states", "sensor_msgs/msg/JointState", 100 + i, raw)
        at_once = reader.read_bag(path)
        with monkeypatch.context() as m:
            m.setattr(reader, "_joint_state_block", lambda raws: None)
            assert _same(at_once, reader.read_bag(path)), what
        assert len(at_once.joint_states) == 31
