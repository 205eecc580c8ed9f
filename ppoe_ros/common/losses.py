"""Messages lost before a node's callback: publisher sequence gaps and the middleware's lost events.

Two counters go to ``/diagnostics`` for every input subscribed with :func:`counted_subscription`:

``lost_before_node``
    Gaps in the publisher's sequence numbers (``publication_sequence_number`` of the message
    info rclpy hands to a two-argument callback): messages the publisher sent that never reached
    the callback, whatever dropped them (the network, a full subscription history under
    ``KEEP_LAST``, a slow executor).  Sequence numbers are per publisher and the message info
    does not say which publisher sent a message, so the count is kept while the topic has
    exactly one publisher; with several it is paused (``loss_tracking`` on ``/diagnostics``
    names the topics) and restarts when one is left.
``lost_in_transport``
    What the middleware reports through the subscription's ``message_lost`` event (samples
    the DDS reader knows it missed).  These are part of ``lost_before_node`` when that is tracked.

A publisher that restarts begins its sequence again: a number not larger than the last one
starts a new count and loses nothing.  What a publisher sent before the first message the node
received from it is not known when the publisher was there before the node (the node may simply have
started later), so it is not counted; but for a publisher that appeared while the node was subscribed (the
node saw no publisher, then this one's first message, stamped after that), its numbers start at 1, so a
first number ``s > 1`` means the ``s - 1`` messages before it were lost (the start of a burst dropped from a
full subscription history before the node's first take: issue 25, ``bench/bench_soak.py``).

Also on ``/diagnostics``: ``loss_tracking_paused`` (how often tracking paused) and ``received_untracked`` (messages
received while it was paused).  A pause in which the graph saw no publisher and that ends on the same publisher
(same endpoint GID) is bridged: the gaps across it are counted.

Not countable: what a publisher sends while the node is still starting, once its subscription exists and before it
spins (the history keeps the newest ``depth``; the first message taken then looks like a late join).  So a node
subscribes after its slow start-up work: the kinematics node once its model's kernels are loaded (before that, in
``bench/bench_soak.py`` under load, a 23 s cold compile left 22892 of 120001 messages uncounted; issue 25).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ppoe_ros.common.diagnostics import NodeStats, guarded

__all__ = ["SequenceGaps", "counted_subscription"]


class SequenceGaps:
    """Counts gaps in one topic's publication sequence numbers into ``stats['lost_before_node']``.

    Also counts ``loss_tracking_paused`` (how often tracking paused: the topic had no or several publishers
    at a diagnostics period) and ``received_untracked`` (messages received while paused).  A pause during
    which no other publisher was seen and that ends on the same publisher (same endpoint GID: its sequence
    continues; the graph only lost sight of it for a while, as under heavy load) is bridged: the gaps in the
    numbers it received during the pause and across it are counted when tracking resumes.  A publisher replaced
    by another between two looks (the count stays 1, the GID changes) starts a new count.
    """

    __slots__ = ("topic", "stats", "last", "tracking", "empty_since", "gid", "bridge", "pending")

    def __init__(self, topic: str, stats: NodeStats) -> None:
        self.topic = topic
        self.stats = stats
        self.last: int | None = None
        self.tracking = True
        #: wall time [ns] since which the node has seen no publisher and no message (None: not so)
        self.empty_since: int | None = None
        #: endpoint GID of the one publisher while tracking (None: not known)
        self.gid: bytes | None = None
        #: while paused: can the pause still be bridged (only the same publisher seen, its numbers increasing)?
        self.bridge = False
        #: while paused: messages missing from the numbers seen, counted if the pause is bridged
        self.pending = 0

    def observe(self, info: Any) -> None:
        """Account for one received message given its message info (dict or object)."""
        seq = info.get("publication_sequence_number") if isinstance(info, dict) else \
            getattr(info, "publication_sequence_number", None)
        if not self.tracking:
            self.stats.inc("received_untracked")
            self.empty_since = None  # a message while paused: a publisher's start can no longer be told
            if seq and self.bridge and self.last is not None and seq > self.last:
                self.pending += int(seq) - self.last - 1
                self.last = int(seq)
            else:
                self.bridge = False
            return
        if not seq:  # None or 0: the middleware does not number its samples
            return
        if self.last is None and self.empty_since is not None:
            self._first_of_new_publisher(int(seq), info)
        last, self.last = self.last, int(seq)
        if last is not None and seq > last + 1:
            n = int(seq) - last - 1
            self.stats.inc("lost_before_node", n)
            self.stats.last_reason = f"{self.topic}: {n} message(s) lost before the node (sequence {last} -> {seq})"

    def _first_of_new_publisher(self, seq: int, info: Any) -> None:
        """The first message after the node saw no publisher: if it was sent after that (a new publisher, not
        one still in flight from a publisher that left), the ``seq - 1`` messages before it were lost."""
        stamp = info.get("source_timestamp") if isinstance(info, dict) else getattr(info, "source_timestamp", None)
        since, self.empty_since = self.empty_since, None
        if seq > 1 and stamp and since is not None and int(stamp) > since:
            self.stats.inc("lost_before_node", seq - 1)
            self.stats.last_reason = (f"{self.topic}: the first {seq - 1} message(s) of a publisher that appeared "
                                      "after the node subscribed were lost before the node")

    def refresh(self, node: Any) -> None:
        """:meth:`set_publishers` from the node's graph: the topic's publishers and their endpoint GIDs."""
        gids = {bytes(info.endpoint_gid) for info in node.get_publishers_info_by_topic(self.topic)}
        self.set_publishers(len(gids), next(iter(gids)) if len(gids) == 1 else None)

    def set_publishers(self, count: int, gid: bytes | None = None) -> None:
        """Track only while exactly one publisher (endpoint ``gid`` if known) numbers the messages; note when
        there is none; bridge a pause that ends on the same publisher without another one seen."""
        if count == 0 and self.empty_since is None:
            import time

            self.empty_since = time.time_ns()
        if self.tracking and count != 1:  # pause
            self.stats.inc("loss_tracking_paused")
            self.bridge, self.pending = count == 0 and self.gid is not None and self.last is not None, 0
            self.tracking = False
        elif not self.tracking and count != 1:
            self.bridge = self.bridge and count == 0
        elif not self.tracking:  # resume
            if self.bridge and gid is not None and gid == self.gid:
                if self.pending:
                    self.stats.inc("lost_before_node", self.pending)
                    self.stats.last_reason = (f"{self.topic}: {self.pending} message(s) lost before the node "
                                              "while its publisher was out of sight")
                self.empty_since = None  # the same publisher continues: not a new one
            else:
                self.last = None
            self.bridge, self.pending = False, 0
            self.tracking = True
        elif gid is not None and self.gid is not None and gid != self.gid:
            self.last = None  # another publisher took over between two looks: its numbers are its own
        if count == 1:
            self.gid = gid


def counted_subscription(node: Any, stats: NodeStats, msg_type: Any, topic: str,
                         callback: Callable[[Any], Any], qos: Any, raw: bool = False) -> tuple[Any, SequenceGaps]:
    """Subscribe ``callback`` (guarded: a bad message is counted, never fatal) with loss counting.

    Returns the subscription and its :class:`SequenceGaps` (also registered on ``stats`` so
    that :class:`~ppoe_ros.common.diagnostics.DiagnosticsPublisher` refreshes its publisher
    count once per period).  ``raw``: the callback gets the serialised bytes.  Works on both executors of
    :func:`~ppoe_ros.common.runner.run_node`: the ``SingleThreadedExecutor`` calls ``(msg, info)``, the
    ``EventsExecutor`` one ``(msg, info)`` tuple.
    """
    from rclpy.event_handler import SubscriptionEventCallbacks

    gaps = SequenceGaps(topic, stats)
    stats.gap_counters.append(gaps)
    stats.warn_keys |= {"lost_before_node", "lost_in_transport"}
    for key in ("lost_before_node", "lost_in_transport"):
        stats.counts.setdefault(key, 0)
    safe = guarded(stats, topic)(callback)

    def on_message(*args: Any) -> None:
        msg, info = args if len(args) == 2 else args[0]
        gaps.observe(info)
        safe(msg)

    def on_lost(event: Any) -> None:
        n = int(getattr(event, "total_count_change", 0))
        stats.inc("lost_in_transport", n)
        stats.last_reason = f"{topic}: the middleware reports {n} message(s) lost"

    try:
        events = SubscriptionEventCallbacks(message_lost=on_lost)
        sub = node.create_subscription(msg_type, topic, on_message, qos, event_callbacks=events, raw=raw)
    except Exception:  # noqa: BLE001 - an rmw without the message-lost event: count the gaps only
        sub = node.create_subscription(msg_type, topic, on_message, qos, raw=raw)
    # ``(*args)`` binds one argument, so rclpy would call it without the message info
    sub._callback_type = sub.CallbackType.WithMessageInfo
    return sub, gaps
