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
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ppoe_ros.common.diagnostics import NodeStats, guarded

__all__ = ["SequenceGaps", "counted_subscription"]


class SequenceGaps:
    """Counts gaps in one topic's publication sequence numbers into ``stats['lost_before_node']``."""

    __slots__ = ("topic", "stats", "last", "tracking", "empty_since")

    def __init__(self, topic: str, stats: NodeStats) -> None:
        self.topic = topic
        self.stats = stats
        self.last: int | None = None
        self.tracking = True
        #: wall time [ns] since which the node has seen no publisher and no message (None: not so)
        self.empty_since: int | None = None

    def observe(self, info: Any) -> None:
        """Account for one received message given its message info (dict or object)."""
        if not self.tracking:
            self.empty_since = None  # a message while paused: a publisher's start can no longer be told
            return
        seq = info.get("publication_sequence_number") if isinstance(info, dict) else \
            getattr(info, "publication_sequence_number", None)
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

    def set_publishers(self, count: int) -> None:
        """Track only while exactly one publisher numbers the messages; note when there is none."""
        if count == 0 and self.empty_since is None:
            import time

            self.empty_since = time.time_ns()
        tracking = count == 1
        if tracking != self.tracking:
            self.last = None
        self.tracking = tracking


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
