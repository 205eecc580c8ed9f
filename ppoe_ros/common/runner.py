"""Node start-up shared by every node: the URDF source and the ``main()`` runner (as in ros2/demos, Jazzy)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from ppoe_core.errors import PpoeError
from ppoe_ros.common.diagnostics import NodeStats, guarded
from ppoe_ros.common.qos import LATCHED_QOS


def take_robot_description(node: Node, params: Mapping[str, Any], stats: NodeStats,
                           set_model: Callable[[str, str], None],
                           on_message: Callable[[Any], None]) -> None:
    """Get the URDF as robot_state_publisher's consumers do.

    From the ``robot_description`` parameter when it is set (a bad URDF there is a start-up
    error: ``set_model`` raises), else by subscribing ``robot_description_topic`` with
    :data:`LATCHED_QOS`; a bad URDF on the topic is counted by :func:`guarded` and the node
    keeps its previous model.
    """
    if params["robot_description"]:
        set_model(params["robot_description"], "parameter robot_description")
        return
    from std_msgs.msg import String

    topic = params["robot_description_topic"]
    node.create_subscription(String, topic, guarded(stats, topic)(on_message), LATCHED_QOS)
    node.get_logger().info(f"waiting for the URDF on {topic}")


# ---------------------------------------------------------------------------- main


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """The standard ``main()`` of a node: init, build, spin, shut down; returns the exit code.

    Parameters
    ----------
    factory : callable
        Builds the node (after ``rclpy.init``).  A :class:`PpoeError` from it (bad
        parameter, unreadable model file) is printed as one line and gives exit code 2.
    args : sequence of str or None
        Command line (``sys.argv`` when None), including ``--ros-args``.

    Notes
    -----
    A ``SingleThreadedExecutor``: rclpy's experimental ``EventsExecutor`` (Jazzy) received
    no messages and spun at 100 % CPU after SIGTERM in a trial here, so it is not offered.
    """
    rclpy.init(args=list(sys.argv if args is None else args))
    node: Node | None = None
    code = 0
    try:
        node = factory()
        ex = rclpy.executors.SingleThreadedExecutor()
        ex.add_node(node)
        ex.spin()
    except PpoeError as exc:
        print(f"[FATAL] {exc}", file=sys.stderr, flush=True)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        if node is not None:
            try:
                node.destroy_node()
            except Exception:  # noqa: BLE001 - best effort during shutdown
                pass
        rclpy.try_shutdown()
    return code
