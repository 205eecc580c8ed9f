"""``ppoe record --out BAG TOPIC...``: write live ROS 2 topics into a new bag (no ``ros2 bag`` needed).

Each requested topic is subscribed as soon as a publisher of it appears (its
type taken from the ROS graph), with ``raw=True``, so the CDR bytes are written
as received, after one normalisation step: the bytes FastCDR (rclpy) produces can
end in alignment padding that ``rosbags``' ``deserialize_cdr`` rejects as a size
mismatch, so :meth:`ppoe_core.io.bagio.BagWriter.write_raw` parses and re-serialises
them with rosbags.  The recorded bag therefore reads back with plain ``rosbags``.

The subscription QoS follows the publishers: transient local when all of them
are (``/robot_description``), best effort if any publisher is best effort.  The
profiles the publishers offered are stored per topic in ``metadata.yaml``
(``offered_qos_profiles``, as ``ros2 bag record`` does), so ``ros2 bag play`` and
``ppoe play`` offer them again.

Standard ROS arguments follow ``--ros-args``: ``-r __ns:=/robot1`` records the given relative topic
names in that namespace (``joint_states`` is ``/robot1/joint_states``; the bag keeps the full names),
``-r __node:=NAME`` renames the recorder.

The log time of a message is its receive time on the node clock
(``--use-sim-time`` to take it from ``/clock``).  Stops on SIGINT/SIGTERM or
after ``--duration``; the bag is closed properly either way (exit 0).

Every ``--flush-period`` seconds (0.5) the pending messages go to disk as one
mcap chunk and ``metadata.yaml`` is rewritten with the counts so far, so a
recorder killed with ``-9`` loses at most about that much: ``ppoe play`` /
``evaluate`` read such a bag from its chunks and say that it was not closed.

``--force`` replaces an existing bag directory only if it holds nothing but bag files, and only when the
recording ends (it is written beside it meanwhile); a recording that got no message keeps the old bag.

Exit codes: 0 done, 2 output exists (without ``--force``), is not a bag directory, or cannot be written.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from ppoe_core.cli.checks import float_range, int_range
from ppoe_core.errors import PpoeError
from ppoe_core.io.bagio import BagWriter
from ppoe_ros.cli import StopFlag
from ppoe_ros.cli.play import add_ros_args, init_ros

__all__ = ["add_arguments", "run", "Recorder"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``ppoe record``."""
    parser.add_argument("topics", nargs="+", metavar="TOPIC", help="topics to record")
    parser.add_argument("--out", "-o", required=True, metavar="BAG", help="bag directory to create")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="storage plugin (default mcap)")
    parser.add_argument("--duration", type=float_range(0.0), default=0.0, metavar="SECONDS",
                        help="stop after this many seconds (default: until interrupted)")
    parser.add_argument("--max-messages", type=int_range(0), default=0, metavar="N",
                        help="stop once N messages (all topics together) are written (default 0: no limit)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing bag directory")
    parser.add_argument("--use-sim-time", action="store_true", help="log times from /clock")
    parser.add_argument("--flush-period", type=float_range(0.0, min_open=True), default=0.5, metavar="SECONDS",
                        help="write the messages to disk at least this often, with metadata.yaml, so that a "
                             "recorder killed with -9 leaves a readable bag (mcap; default 0.5)")
    add_ros_args(parser)


def _qos_for(publishers: list[Any]) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    rel = ReliabilityPolicy.RELIABLE
    dur = DurabilityPolicy.VOLATILE
    if publishers and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers):
        dur = DurabilityPolicy.TRANSIENT_LOCAL
    if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers):
        rel = ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=rel, durability=dur)


class Recorder:
    """Subscribes the requested topics (raw) as they appear and writes them to a :class:`BagWriter`."""

    def __init__(self, node: Any, writer: BagWriter, topics: list[str]) -> None:
        from ppoe_ros.common import NodeStats

        self.node = node
        self.writer = writer
        self.pending = list(dict.fromkeys(node.resolve_topic_name(t) for t in topics))
        self.subs: dict[str, Any] = {}
        self.stats = NodeStats(node, ("received", "written", "bad"))
        from rclpy.clock import Clock, ClockType

        # steady clock: with use_sim_time a ROS-clock timer would not fire before /clock starts
        node.create_timer(0.1, self.discover, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.discover()

    def discover(self) -> None:
        """Subscribe every pending topic that now has a publisher."""
        from ppoe_ros.common import message_class
        from ppoe_ros.common.bag_qos import qos_from_rclpy

        if not self.pending:
            return
        types = dict(self.node.get_topic_names_and_types())
        for topic in list(self.pending):
            if topic not in types:
                continue
            msgtype = types[topic][0]
            if len(types[topic]) > 1:
                self.node.get_logger().warning(f"{topic} has several types {types[topic]}; recording {msgtype}")
            pubs = self.node.get_publishers_info_by_topic(topic)
            if not pubs:
                continue
            cls = message_class(msgtype)
            self.writer.offered_qos[topic] = [qos_from_rclpy(p.qos_profile) for p in pubs]
            self.subs[topic] = self.node.create_subscription(
                cls, topic, self._callback(topic, msgtype), _qos_for(pubs), raw=True)
            self.pending.remove(topic)
            self.node.get_logger().info(f"recording {topic} ({msgtype})")

    def _callback(self, topic: str, msgtype: str) -> Any:
        clock = self.node.get_clock()

        def cb(data: bytes) -> None:
            self.stats.inc("received")
            try:
                self.writer.write_raw(topic, msgtype, clock.now().nanoseconds, data)
            except PpoeError as exc:
                self.stats.bad(topic, str(exc))
                return
            self.stats.inc("written")

        return cb


def run(args: argparse.Namespace) -> int:
    """Record until SIGINT/SIGTERM or ``--duration``; returns the exit code.

    rclpy's own signal handlers are off: a signal only sets a flag that the spin loop checks, so
    the loop never spins a context that a handler has just shut down (that raced into ``RCLError:
    failed to initialize wait set`` under SIGTERM), and the bag is closed on every path.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    writer = BagWriter(args.out, storage=args.storage, overwrite=args.force,
                       flush_period=args.flush_period)  # BagError if it exists (or, with --force, is not a bag)
    if writer.replaces_existing:
        print(f"ppoe record: recording into {writer.write_path}; it replaces {args.out} when the recording ends",
              file=sys.stderr)
    stop = getattr(args, "stop_flag", None) or StopFlag()  # ``ppoe`` installs it before the imports
    recorder: Recorder | None = None
    node = None
    try:
        init_ros("ppoe_record", list(args.ros_args or []), signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("ppoe_record", parameter_overrides=[
            Parameter("use_sim_time", Parameter.Type.BOOL, bool(args.use_sim_time))])
        writer.open()
        recorder = Recorder(node, writer, args.topics)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        end = time.monotonic() + args.duration if args.duration > 0 else None
        limit = args.max_messages if args.max_messages > 0 else None
        while not stop.raised and rclpy.ok() and (end is None or time.monotonic() < end):
            if limit is not None and sum(writer.counts.values()) >= limit:
                break
            executor.spin_once(timeout_sec=0.05)
            writer.flush_if_due()
    finally:
        kept = writer.replaces_existing and not writer.counts  # recorded nothing: the old bag stays
        if kept:
            writer.discard()
        else:
            writer.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()
    counts = ", ".join(f"{t}: {n}" for t, n in sorted(writer.counts.items())) or "nothing"
    print(f"ppoe record: recorded nothing; the existing bag {args.out} is kept as it was" if kept
          else f"ppoe record: wrote {args.out} ({counts})", file=sys.stderr)
    if recorder is not None and recorder.pending:
        print(f"ppoe record: never saw a publisher of {', '.join(recorder.pending)}", file=sys.stderr)
    return 0
