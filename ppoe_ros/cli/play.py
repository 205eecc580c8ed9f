"""``ppoe play BAG [--ros-args ...]``: publish a recorded bag onto live ROS 2 topics (no ``ros2 bag`` needed).

The messages' stored CDR bytes are published unchanged (rclpy raw publish), in
log-time order, paced by the bag's log times divided by ``--rate``.  With
``--clock`` the bag time is published on ``/clock`` (``rosgraph_msgs/Clock``)
before each message and every ``1/--clock-hz`` seconds in between, so nodes with
``use_sim_time:=true`` run on the bag's clock.  ``--loop`` starts over at the end
(the clock then jumps back; nodes count that as a stamp reset).

QoS, as ``ros2 bag play`` does: each topic is offered with the profile recorded in the bag's
``metadata.yaml`` (:func:`ppoe_core.io.bag_qos.playback_qos`); a topic recorded without one gets
:func:`ppoe_core.io.bag_qos.offered_qos` (transient local for ``robot_description`` and ``tf_static``,
where ``ros2 bag play`` would offer volatile; reliable and volatile otherwise).  A latched topic keeps
all its messages for late subscribers; other topics are published with a deep history (1000).

Standard ROS arguments follow ``--ros-args`` (rclpy parses them): ``-r __ns:=/robot1`` plays the bag's
topics in that namespace (``/joint_states`` on ``/robot1/joint_states``; ``/clock``, ``/tf``,
``/tf_static``, ``/diagnostics`` stay global, as robot_state_publisher keeps them), ``-r FROM:=TO`` remaps
a topic, ``-r __node:=NAME`` renames the player, ``-p use_sim_time:=true`` runs its node on ``/clock``.

A topic whose message type is not installed here is skipped with a message on
stderr (an error if it was asked for with ``--topics``).

A damaged bag (fewer readable messages than its ``metadata.yaml`` says) is refused before
anything is published, naming per topic what was lost, unless ``--accept-partial``; an
unfinished recording (no footer or metadata) is read record by record, with a warning.

Exit codes: 0 done (or interrupted), 2 unreadable or damaged bag / unknown topic / nothing to play / bad
``--ros-args``.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from ppoe_core.cli.checks import float_range
from ppoe_core.errors import BagError, PpoeError
from ppoe_core.io import bagio

__all__ = ["add_arguments", "add_ros_args", "init_ros", "run", "wait_for_discovery", "ROBOT_DESCRIPTION_TOPIC",
           "GLOBAL_TOPICS", "play_name"]

ROBOT_DESCRIPTION_TOPIC = "/robot_description"

#: topics played under their absolute name whatever the namespace (robot_state_publisher's convention)
GLOBAL_TOPICS = ("/clock", "/tf", "/tf_static", "/diagnostics", "/rosout", "/parameter_events")

#: history depth of a volatile topic's publisher (a subscriber that falls this far behind loses the oldest)
_VOLATILE_DEPTH = 1000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``ppoe play``."""
    parser.add_argument("bag", metavar="BAG", help="rosbag2 directory (mcap or sqlite3)")
    parser.add_argument("--rate", type=float_range(0.0, min_open=True), default=1.0,
                        help="playback speed factor (default 1.0)")
    parser.add_argument("--clock", action="store_true", help="publish the bag time on /clock")
    parser.add_argument("--clock-hz", type=float_range(0.0, min_open=True), default=100.0,
                        help="/clock rate between messages [Hz] (default 100)")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics (default: all)")
    parser.add_argument("--loop", action="store_true", help="start over at the end, until interrupted")
    parser.add_argument("--delay", type=float_range(0.0), default=0.5,
                        help="seconds to wait after creating the publishers (and after their subscribers are found, "
                             "with --wait-for-subscribers), for the subscribers' side of discovery (default 0.5)")
    parser.add_argument("--accept-partial", action="store_true",
                        help="play what can be read of a damaged bag (default: refuse it, naming per topic "
                             "what was lost)")
    parser.add_argument("--wait-for-subscribers", type=float_range(0.0), default=0.0, metavar="SECONDS",
                        help="before playing, wait up to SECONDS until every played topic has a subscriber")
    add_ros_args(parser)


def play_name(topic: str) -> str:
    """Name the player publishes ``topic`` under: relative (so ``__ns`` applies) unless in :data:`GLOBAL_TOPICS`."""
    return topic if topic in GLOBAL_TOPICS else topic.lstrip("/")


def _publisher_qos(topic: str, recorded: list[Any], count: int) -> Any:
    """The rclpy profile for ``topic``: the recorded offer (rosbag2's rule), else ours; depth for replay."""
    from ppoe_core.io.bag_qos import offered_qos, playback_qos
    from ppoe_ros.common.bag_qos import qos_to_rclpy
    from rosbags.interfaces import QosDurability

    profile = playback_qos(recorded, fallback=offered_qos(topic)[0])
    latched = profile.durability == QosDurability.TRANSIENT_LOCAL
    return qos_to_rclpy(profile, depth=max(1, min(count, _VOLATILE_DEPTH)) if latched else _VOLATILE_DEPTH)


def add_ros_args(parser: argparse.ArgumentParser) -> None:
    """The ``--ros-args ...`` option (everything after it, for rclpy), shared with ``ppoe record``."""
    parser.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[], metavar="ARG",
                        help="standard ROS arguments, last on the line: -r __ns:=/robot1, -r FROM:=TO, "
                             "-p use_sim_time:=true, --log-level debug")


def init_ros(name: str, ros_args: list[str], **kwargs: Any) -> None:
    """``rclpy.init`` with the user's ``--ros-args`` (``kwargs`` to rclpy.init); a malformed one is a
    PpoeError (exit 2, one line)."""
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError, UnknownROSArgsError

    try:
        rclpy.init(args=[name, "--ros-args", *ros_args] if ros_args else [name], **kwargs)
    except UnknownROSArgsError as exc:
        raise PpoeError(f"--ros-args: not ROS arguments: {exc.args[0] if exc.args else exc}") from None
    except RCLError as exc:
        raise PpoeError(f"bad --ros-args {' '.join(ros_args)}: {str(exc).split(', at ')[0]}") from None


def run(args: argparse.Namespace) -> int:
    """Play the bag; returns the exit code."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rosgraph_msgs.msg import Clock

    from ppoe_core.io.bag_qos import recorded_qos
    from ppoe_ros.common import reliable_qos

    info = bagio.bag_topics(args.bag)  # raises BagError naming the bag
    selected, classes = _select_topics(args, info)
    # read it all once before playing: a damaged bag is refused (per topic, what was lost), or with
    # --accept-partial announced; the counts announced below are those that will be played
    check = bagio.check_bag(args.bag, selected, accept_partial=args.accept_partial)
    args.scanned = check.scanned  # read the file the way that recovered the most
    for note in check.notes:
        print(f"ppoe play: warning: {note}", file=sys.stderr)

    recorded = recorded_qos(args.bag)
    init_ros("ppoe_play", list(args.ros_args or []))
    node = rclpy.create_node("ppoe_play")
    log = node.get_logger()
    n_sent = 0
    try:
        pubs: dict[str, Any] = {}
        for topic in selected:
            qos = _publisher_qos(topic, recorded.get(topic, []), check.counts.get(topic, 0))
            pubs[topic] = node.create_publisher(classes[topic], play_name(topic), qos)
        clock_pub = node.create_publisher(Clock, "/clock", reliable_qos(10)) if args.clock else None
        wait_for_discovery(node, pubs, args.delay, args.wait_for_subscribers)
        counts = ", ".join(f"{pubs[t].topic_name} ({check.counts.get(t, 0)})" for t in selected)
        log.info(f"playing {args.bag}: {counts} at rate {args.rate:g}")
        while True:
            sent = _play_once(args, pubs, clock_pub)
            if sent is None:  # shut down while playing
                return 0
            n_sent += sent
            if not args.loop:
                break
        _drain(node, pubs, 1.0)
        log.info(f"played {n_sent} messages")
        return 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def wait_for_discovery(node: Any, pubs: dict[str, Any], delay: float, wait_subs: float) -> None:
    """Discovery: optionally wait until every publisher has a subscriber, then sleep ``delay``.

    A publisher counts a subscriber as soon as *its* side of discovery matched; the subscriber drops what
    arrives before its side matched the publisher (a volatile joint state is lost so), so the ``delay`` comes
    after the subscribers are found, not before.
    """
    import rclpy

    if wait_subs > 0:
        end = time.monotonic() + wait_subs
        lonely = list(pubs)
        while rclpy.ok() and time.monotonic() < end:
            lonely = [t for t, p in pubs.items() if p.get_subscription_count() == 0]
            if not lonely:
                break
            time.sleep(0.02)
        if lonely:
            node.get_logger().warning(f"no subscriber after {wait_subs:g} s on {', '.join(lonely)}; playing anyway")
    end = time.monotonic() + max(0.0, delay)
    while time.monotonic() < end and rclpy.ok():
        time.sleep(0.02)


def _drain(node: Any, pubs: dict[str, Any], timeout: float) -> None:
    """Give reliable subscribers time to fetch the last messages before the publishers go away."""
    import rclpy
    from rclpy.duration import Duration

    end = time.monotonic() + timeout
    while rclpy.ok() and time.monotonic() < end:
        if all(p.wait_for_all_acked(Duration(seconds=0.05)) for p in pubs.values()):
            return


def _select_topics(args: argparse.Namespace, info: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """Topics to play (``--topics`` or all) and their message classes; unknown types skipped with a word."""
    from ppoe_ros.common import message_class

    if args.topics:
        missing = [t for t in args.topics if t not in info]
        if missing:
            raise BagError(f"bag {args.bag}: no topic {', '.join(missing)} (topics: {', '.join(sorted(info))})")
        selected = list(dict.fromkeys(args.topics))
    else:
        selected = sorted(info)
    classes: dict[str, Any] = {}
    for topic in list(selected):
        try:
            classes[topic] = message_class(info[topic][0])
        except PpoeError as exc:
            if args.topics:  # asked for by name: an error
                raise BagError(f"bag {args.bag}: topic {topic}: {exc}") from None
            print(f"ppoe play: skipping {topic}: {exc}", file=sys.stderr)
            selected.remove(topic)
    if not selected:
        raise BagError(f"bag {args.bag}: no topic to play")
    return selected, classes


def _play_once(args: argparse.Namespace, pubs: dict[str, Any], clock_pub: Any) -> int | None:
    """One pass over the bag at ``args.rate``, publishing ``/clock`` while waiting; messages sent, or None
    when ROS shut down meanwhile."""
    import rclpy
    from rosgraph_msgs.msg import Clock

    from ppoe_ros.common import ns_to_stamp

    clock_period = 1.0 / args.clock_hz
    clock_msg = Clock()
    t0_ns: int | None = None
    start = time.monotonic()
    last_clock = -1.0
    n_sent = 0
    for msg in bagio.iter_raw(args.bag, list(pubs), scanned=getattr(args, "scanned", False)):
        if t0_ns is None:
            t0_ns = msg.stamp_ns
        target = start + (msg.stamp_ns - t0_ns) * 1e-9 / args.rate
        while True:
            if not rclpy.ok():
                return None
            now = time.monotonic()
            if now >= target:
                break
            if clock_pub is not None and now - last_clock >= clock_period:
                clock_msg.clock = ns_to_stamp(t0_ns + int((now - start) * args.rate * 1e9))
                clock_pub.publish(clock_msg)
                last_clock = now
            time.sleep(min(target - now, clock_period if clock_pub is not None else 0.05))
        if clock_pub is not None:
            clock_msg.clock = ns_to_stamp(msg.stamp_ns)
            clock_pub.publish(clock_msg)
            last_clock = time.monotonic()
        pubs[msg.topic].publish(msg.data)
        n_sent += 1
    return n_sent
