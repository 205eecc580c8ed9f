"""Node start-up shared by every node: the URDF source and the ``main()`` runner (as in ros2/demos, Jazzy)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import rclpy
from rclpy._rclpy_pybind11 import RCLError
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


def check_params_files(argv: Sequence[str]) -> None:
    """Every ``--params-file PATH`` after ``--ros-args`` names a readable YAML mapping (else rcl fails later with a
    raw ``RCLError``).

    Raises
    ------
    ModelConfigError
        Naming the file (and the line of a YAML error).
    """
    from ppoe_core.errors import ModelConfigError
    from ppoe_core.robot.yaml_io import read_yaml_file

    if "--ros-args" not in argv:
        return
    ros = list(argv[argv.index("--ros-args") + 1:])
    for i, a in enumerate(ros):
        if a == "--params-file":
            if i + 1 >= len(ros):
                raise ModelConfigError("--params-file without a path")
            data, where = read_yaml_file(ros[i + 1], "parameter file")
            if not isinstance(data, dict):
                raise ModelConfigError(f"{where}: parameter file must be a mapping of node names, got "
                                       f"{type(data).__name__}")


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, executor: str = "single") -> int:
    """The standard ``main()`` of a node: init, build, spin, shut down; returns the exit code.

    Parameters
    ----------
    factory : callable
        Builds the node (after ``rclpy.init``).  A :class:`PpoeError` from it (bad
        parameter, unreadable model file) is printed as one line and gives exit code 2.
    args : sequence of str or None
        Command line (``sys.argv`` when None), including ``--ros-args``.
    executor : {"single", "events"}
        ``SingleThreadedExecutor``, or rclpy's ``EventsExecutor`` (Jazzy, experimental): about a third of the CPU
        per message at 1 kHz (``bench/bench_nodes.py``).  Its ``spin()`` (and ``spin_until_future_complete``
        without a timeout) spins at a full core without running callbacks and ignores SIGINT here, so it is
        spun in 1 s slices until the context shuts down (SIGINT / SIGTERM).
    """
    argv = list(sys.argv if args is None else args)
    name = getattr(factory, "__name__", "node")
    try:
        check_params_files(argv)
        rclpy.init(args=argv)
    except PpoeError as exc:
        print(f"[FATAL] {name}: {exc}", file=sys.stderr, flush=True)
        return 2
    except RCLError as exc:  # rcl's own argument parsing (e.g. a malformed --remap)
        print(f"[FATAL] {name}: cannot start: {str(exc).split(', at ')[0]}", file=sys.stderr, flush=True)
        return 2
    node: Node | None = None
    code = 0
    try:
        warm_node_kernels()
        node = factory()
        _spin(node, executor)
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


def warm_node_kernels() -> None:
    """Compile (or load from numba's cache) the per-message pose conversions, the fusion update and the fusion
    pipeline's per-prior steps before the node subscribes: on a fresh install the first call compiles for a few
    seconds, which must not fall on the first message (inputs queue up and may be lost meanwhile)."""
    import numpy as np

    from ppoe_core import lie

    lie.quat_from_matrix(np.eye(3))
    lie.cov_ros_to_local(np.eye(4), lie.cov_local_to_ros(np.eye(4), np.eye(6)))
    from ppoe_core.estimation.warmup import warm_kernels, warm_pipeline
    from ppoe_core.io import joint_pose
    from ppoe_ros.common.conversions import pose_cov_from_msg, pose_cov_stamped_msg

    warm_kernels()
    joint_pose.warm_kernels()  # the kinematics node's per-message path
    warm_pipeline()
    pose_cov_from_msg(pose_cov_stamped_msg(np.eye(4), np.eye(6), 0, "warm-up"))


def _spin(node: Node, executor: str) -> None:
    """Spin ``node`` until shutdown on the chosen executor (see :func:`run_node`)."""
    if executor == "events":
        from rclpy.experimental import EventsExecutor
        from rclpy.task import Future

        ex: Any = EventsExecutor(context=node.context)
        ex.add_node(node)
        never = Future()
        while node.context.ok():
            ex.spin_until_future_complete(never, timeout_sec=1.0)
        return
    ex = rclpy.executors.SingleThreadedExecutor()
    ex.add_node(node)
    ex.spin()
