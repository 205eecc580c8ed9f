"""A callback whose publish fails because rclpy is shutting down (Ctrl-C while a message is handled: a cold
kinematics node stopped right after its first pose logged rclpy's "Exception in 'subscriptions' callback" with a
traceback) is not an error: no count, no log line, no exception; before the shutdown the same failure is counted."""

from __future__ import annotations

import pytest

pytest.importorskip("rclpy")


def test_a_failure_after_shutdown_is_silent() -> None:
    import rclpy
    from rclpy.context import Context

    from ppoe_ros.common import NodeStats, guarded

    ctx = Context()
    rclpy.init(context=ctx, domain_id=201)
    node = rclpy.create_node("guarded_shutdown_probe", context=ctx)
    stats = NodeStats(node, throttle_sec=0.0)

    @guarded(stats, "/joint_states")
    def cb() -> None:
        raise RuntimeError("publisher's context is invalid")

    cb()
    assert stats.counts["errors"] == 1 and "publisher's context is invalid" in stats.last_reason
    stats.last_reason = ""
    ctx.try_shutdown()
    cb()  # after the shutdown: nothing raised, nothing counted (so nothing logged)
    assert stats.counts["errors"] == 1 and stats.last_reason == ""
    node.destroy_node()
