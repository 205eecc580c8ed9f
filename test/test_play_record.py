"""``ppoe play`` -> live topics -> ``ppoe record``: the recorded bag reads back with plain rosbags.

Both run as separate processes in an isolated DDS domain.  The source bag has
the contract topics with messages whose FastCDR serialisation ends in alignment
padding (a JointState with one joint): rosbags' own ``deserialize_cdr`` must
read every recorded message, and each must equal its source message.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from ros_helpers import REPO, NodeProcess, ros_env  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from ppoe_core.io.bagio import BagWriter  # noqa: E402

pytestmark = pytest.mark.ros

TS = get_typestore(Stores.ROS2_JAZZY)
TOPICS = ["/robot_description", "/joint_states", "/wrench", "/camera/camera_info"]


def _make_source(path: Path) -> None:
    rng = np.random.default_rng(3)
    with BagWriter(path) as bag:
        bag.write_robot_description((REPO / "config" / "robots" / "planar3.urdf").read_text(), 0.5)
        for k in range(40):
            t = 1.0 + 0.01 * k
            n = 1 + k % 3  # 1, 2, 3 joints: different CDR lengths and paddings
            bag.write_joint_state(t, [f"joint_{i}" for i in range(n)], rng.normal(size=n))
            bag.write_wrench(t + 0.001, "tool0", rng.normal(size=3), rng.normal(size=3))
            if k % 10 == 0:
                bag.write_camera_info(t + 0.002, "camera_optical_frame", 640, 480,
                                      [[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]], [0.1, -0.05, 0, 0, 0.01])


def _read_strict(path: Path) -> dict[str, list]:
    """Every message of a bag, deserialised with rosbags' own (strict) deserialize_cdr."""
    out: dict[str, list] = {}
    with Reader(path) as reader:
        for conn, stamp, data in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, TS.deserialize_cdr(data, conn.msgtype)))
    return out


def _plain(msg) -> object:
    """rosbags message -> nested plain Python (arrays as lists) for equality."""
    if hasattr(msg, "__dataclass_fields__"):
        return {k: _plain(getattr(msg, k)) for k in msg.__dataclass_fields__ if k != "__msgtype__"}
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, list):
        return [_plain(m) for m in msg]
    return msg


def test_our_deserialiser_reads_rclpy_bytes_and_refuses_garbage() -> None:
    """rclpy's bytes of a one-joint JointState end in FastCDR padding; ``bagio.deserialize`` (what the
    recorder and the readers use) reads them as rclpy meant, and refuses truncated or trailing garbage
    with an error naming the topic."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from ppoe_core.errors import BagError
    from ppoe_core.io import bagio

    raw = serialize_message(JointState(name=["a"], position=[1.0]))
    msg = bagio.deserialize(raw, "sensor_msgs/msg/JointState", topic="/joint_states")
    assert list(msg.name) == ["a"] and msg.position.tolist() == [1.0]
    with pytest.raises(BagError, match="topic /joint_states: "):
        bagio.deserialize(raw[:10], "sensor_msgs/msg/JointState", topic="/joint_states")
    with pytest.raises(BagError, match="/joint_states: .* unexpected trailing bytes"):
        bagio.deserialize(raw + b"\x01" * 16, "sensor_msgs/msg/JointState", topic="/joint_states")


@pytest.mark.parametrize("sim_time", [False, True], ids=["wall_time", "use_sim_time"])
def test_play_record_round_trip(tmp_path: Path, sim_time: bool) -> None:
    """The round trip also holds when the recorder runs on sim time (``--use-sim-time``)."""
    src, rec = tmp_path / "src", tmp_path / "rec"
    _make_source(src)
    env = ros_env(tmp_path)
    extra = ["--use-sim-time"] if sim_time else []
    recorder = NodeProcess.ppoe(["record", "--out", str(rec), *extra, *TOPICS, "/clock"], env, tmp_path, "record")
    player = None
    try:
        time.sleep(1.0)  # the recorder's node is up before the player's topics appear
        player = NodeProcess.ppoe(["play", str(src), "--clock", "--rate", "2.0", "--wait-for-subscribers", "15"],
                                  env, tmp_path, "play")
        assert player.wait(40) == 0, player.output()
        time.sleep(0.5)
    finally:
        if player is not None:
            player.stop()
        code = recorder.stop()
    assert code == 0, recorder.output()
    assert "wrote" in recorder.output()

    source = _read_strict(src)
    recorded = _read_strict(rec)
    for topic in TOPICS:
        got = [_plain(m) for _, m in recorded.get(topic, [])]
        want = [_plain(m) for _, m in source[topic]]
        assert got == want, f"{topic}: {len(got)} recorded vs {len(want)} played, or contents differ"
    # the publishers' offers are recorded (as ros2 bag record does): the player's latched URDF stays latched
    from rosbags.interfaces import QosDurability

    from ppoe_core.io.bag_qos import recorded_qos

    offers = recorded_qos(rec)
    assert [q.durability for q in offers["/robot_description"]] == [QosDurability.TRANSIENT_LOCAL]
    assert [q.durability for q in offers["/joint_states"]] == [QosDurability.VOLATILE]  # (discovery: no depth)
    # /clock carried the bag time: non-decreasing, within the bag's span
    clock_ns = [m.clock.sec * 10**9 + m.clock.nanosec for _, m in recorded["/clock"]]
    assert len(clock_ns) >= 40
    assert all(b >= a for a, b in zip(clock_ns, clock_ns[1:]))
    assert clock_ns[0] >= 500_000_000 and clock_ns[-1] <= 1_400_000_000


def test_play_rate_paces_messages(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--rate 0.5``: the 0.39 s of joint states arrive over about 0.78 s (receipt times in a probe thread)."""
    import argparse
    import threading

    from ros_helpers import Probe
    from sensor_msgs.msg import JointState

    from ppoe_ros.cli import play as cli_play

    src = tmp_path / "src"
    _make_source(src)
    env = ros_env(tmp_path)
    monkeypatch.setenv("ROS_DOMAIN_ID", env["ROS_DOMAIN_ID"])
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with Probe(env) as probe:
        arrivals: list[float] = []
        probe.node.create_subscription(JointState, "/joint_states", lambda m: arrivals.append(time.monotonic()), 100)
        stop = threading.Event()

        def spin() -> None:
            while not stop.is_set():
                probe.executor.spin_once(timeout_sec=0.01)

        thread = threading.Thread(target=spin, daemon=True)
        thread.start()
        try:
            parser = argparse.ArgumentParser()
            cli_play.add_arguments(parser)
            args = parser.parse_args([str(src), "--rate", "0.5", "--topics", "/joint_states",
                                      "--wait-for-subscribers", "10"])
            assert cli_play.run(args) == 0
            time.sleep(0.2)
        finally:
            stop.set()
            thread.join(timeout=2)
    assert len(arrivals) == 40
    assert 0.6 < arrivals[-1] - arrivals[0] < 1.2


def test_play_unknown_topic_is_an_error(tmp_path: Path) -> None:
    src = tmp_path / "src"
    _make_source(src)
    env = ros_env(tmp_path)
    proc = NodeProcess.ppoe(["play", str(src), "--topics", "/nope"], env, tmp_path, "play_bad")
    try:
        assert proc.wait(30) == 2
    finally:
        proc.stop()
    assert "no topic /nope" in proc.output()


def test_play_loop_repeats_until_interrupted(tmp_path: Path) -> None:
    from ros_helpers import Probe
    from sensor_msgs.msg import JointState

    src = tmp_path / "src"
    _make_source(src)
    want = [_plain(m)["header"]["stamp"] for _, m in _read_strict(src)["/joint_states"]]
    env = ros_env(tmp_path)
    with Probe(env) as probe:
        got = probe.collect("/joint_states", JointState, 1000)
        player = NodeProcess.ppoe(["play", str(src), "--loop", "--rate", "4", "--topics", "/joint_states",
                                   "--wait-for-subscribers", "15"], env, tmp_path, "play_loop")
        try:
            probe.spin_until(lambda: len(got) >= 2 * len(want) + 5, 30, player, "two and a bit loops")
            code = player.stop()
        finally:
            player.stop()
    assert code == 0, player.output()
    stamps = [{"sec": m.header.stamp.sec, "nanosec": m.header.stamp.nanosec} for m in got]
    assert stamps[:len(want)] == want and stamps[len(want):2 * len(want)] == want


def test_play_skips_types_not_installed(tmp_path: Path) -> None:
    """A bag topic whose message package is not installed is skipped with a message.

    The type is one of our own making (registered only in the writer's rosbags type store), so no
    ROS install can have it and the test runs everywhere (a real package such as tf2_msgs is
    installed on a full ROS 2 install)."""
    from rosbags.typesys import get_types_from_msg

    from ppoe_core.io.bagio import typestore

    msgtype = "ppoe_test_not_installed_msgs/msg/Probe"
    store = typestore()
    if msgtype not in store.types:
        store.register(get_types_from_msg("float64 value\n", msgtype))
    src = tmp_path / "src"
    with BagWriter(src) as bag:
        bag.write_joint_state(1.0, ["j"], [0.5])
        bag.write_message("/probe", store.types[msgtype](value=1.0), 1.0)
    env = ros_env(tmp_path)
    proc = NodeProcess.ppoe(["play", str(src), "--delay", "0"], env, tmp_path, "play_skip")
    try:
        assert proc.wait(30) == 0, proc.output()
    finally:
        proc.stop()
    assert f"skipping /probe: message type '{msgtype}' is not installed" in proc.output()
    proc = NodeProcess.ppoe(["play", str(src), "--topics", "/probe"], env, tmp_path, "play_skip_named")
    try:
        assert proc.wait(30) == 2
    finally:
        proc.stop()
    assert f"topic /probe: message type '{msgtype}' is not installed" in proc.output()


def test_discovery_delay_comes_after_the_subscribers_are_found(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--wait-for-subscribers``: the publisher sees its subscriber before the subscriber has matched it, so the
    ``--delay`` runs after the last subscriber is found (a subscriber found at 0.3 s, delay 0.4 s: >= 0.7 s); one
    never found is named and the wait ends at its limit."""
    import rclpy
    from rclpy.context import Context

    from ppoe_ros.cli.play import wait_for_discovery

    class Pub:
        def __init__(self, found_after: float) -> None:
            self.at = time.monotonic() + found_after

        def get_subscription_count(self) -> int:
            return int(time.monotonic() >= self.at)

    class Log:
        def __init__(self) -> None:
            self.lines: list[str] = []

        def warning(self, text: str) -> None:
            self.lines.append(text)

    class Node:
        logger = Log()

        def get_logger(self) -> Log:
            return self.logger

    import rclpy.utilities

    ctx = Context()
    rclpy.init(context=ctx, domain_id=0)
    monkeypatch.setattr(rclpy.utilities, "get_default_context", lambda: ctx)  # rclpy.ok() of this context
    try:
        t0 = time.monotonic()
        wait_for_discovery(Node(), {"/a": Pub(0.3), "/b": Pub(0.1)}, 0.4, 5.0)
        assert time.monotonic() - t0 >= 0.7
        assert Node.logger.lines == []
        t0 = time.monotonic()
        wait_for_discovery(Node(), {"/a": Pub(0.0), "/never": Pub(1e9)}, 0.1, 0.3)
        assert 0.4 <= time.monotonic() - t0 < 3.0
        assert Node.logger.lines == ["no subscriber after 0.3 s on /never; playing anyway"]
    finally:
        ctx.try_shutdown()
