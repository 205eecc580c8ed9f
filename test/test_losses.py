"""The start of a stream: messages a new publisher sent before the first one the node received are counted
(issue 25, found by ``bench/bench_soak.py``: in 6 of 21 bursts under load the first 11-196 messages were dropped
from the node's full subscription history before its first take, and no counter knew; the uncounted loss was
exactly the first sequence number - 1)."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("rclpy")


class _Logger:
    def __getattr__(self, name):
        return lambda *a, **k: None


class _Node:
    def get_logger(self):
        return _Logger()


def _gaps():
    from ppoe_ros.common import NodeStats, SequenceGaps

    stats = NodeStats(_Node(), throttle_sec=0.0)
    return stats, SequenceGaps("/joint_states", stats)


def _info(seq: int, stamp_ns: int) -> dict:
    return {"publication_sequence_number": seq, "source_timestamp": stamp_ns}


def test_a_publisher_that_appears_after_the_node_counts_its_lost_first_messages():
    stats, gaps = _gaps()
    gaps.set_publishers(0)  # the node runs, nobody publishes yet
    gaps.set_publishers(1)  # the publisher appears
    gaps.observe(_info(34, time.time_ns()))  # its messages 1..33 never reached the callback
    assert stats.counts["lost_before_node"] == 33 and "the first 33 message(s) of a publisher" in stats.last_reason
    gaps.observe(_info(36, time.time_ns()))
    assert stats.counts["lost_before_node"] == 34


def test_a_publisher_older_than_the_node_or_in_flight_is_not_counted():
    stats, gaps = _gaps()
    gaps.set_publishers(1)  # already there when the node started: a late join, not a loss
    gaps.observe(_info(5000, time.time_ns()))
    assert stats.counts.get("lost_before_node", 0) == 0
    left = time.time_ns()
    gaps.set_publishers(0)  # it left; a message of it still in flight, stamped before that, then a new one
    gaps.set_publishers(1)
    gaps.observe(_info(5001, left - 1_000_000))
    assert stats.counts.get("lost_before_node", 0) == 0
    gaps.observe(_info(1, time.time_ns()))  # the new publisher's first: a new count, nothing lost
    assert stats.counts.get("lost_before_node", 0) == 0


def test_a_message_while_paused_gives_up_the_start_count():
    stats, gaps = _gaps()
    gaps.set_publishers(0)
    gaps.observe(_info(1, time.time_ns()))  # before the node saw the publisher: received, start unknown
    gaps.set_publishers(1)
    gaps.observe(_info(9, time.time_ns()))
    assert stats.counts.get("lost_before_node", 0) == 0
