"""Node start-up shared by every node: the URDF source and the ``main()`` runner (as in ros2/demos, Jazzy)."""

from __future__ import annotations

import gc
import os
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


#: environment variable overriding every node's executor ("single" or "events"): the benchmarks run a node on the
#: classic executor as their same-run baseline
ENV_EXECUTOR = "PPOE_EXECUTOR"


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, executor: str = "single",
             kernels: Sequence[str] = ()) -> int:
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
    kernels : sequence of str
        Nodes (:data:`NODE_KERNELS`) whose kernels are compiled or loaded before the node is built.
    """
    return run_nodes([factory], args, executor, kernels)


def run_nodes(factories: Sequence[Callable[[], Node]], args: Sequence[str] | None = None,
              executor: str = "single", kernels: Sequence[str] = ()) -> int:
    """:func:`run_node` for several nodes in one process, on ONE executor (``ppoe_container``): built in order,
    spun together, destroyed together; a :class:`PpoeError` while building any of them stops all (exit code 2)."""
    argv = list(sys.argv if args is None else args)
    executor = os.environ.get(ENV_EXECUTOR, executor)  # benchmarks' same-run baseline (bench_fusion_node.py)
    name = ", ".join(getattr(f, "__name__", "node") for f in factories)
    try:
        check_params_files(argv)
        rclpy.init(args=argv)
    except PpoeError as exc:
        print(f"[FATAL] {name}: {exc}", file=sys.stderr, flush=True)
        return 2
    except RCLError as exc:  # rcl's own argument parsing (e.g. a malformed --remap)
        print(f"[FATAL] {name}: cannot start: {str(exc).split(', at ')[0]}", file=sys.stderr, flush=True)
        return 2
    nodes: list[Node] = []
    code = 0
    try:
        _log_to_stderr()
        warm_node_kernels(kernels)
        for factory in factories:
            nodes.append(factory())
        nodes[0].get_logger().info(kernel_report())
        # what start-up built (modules, numba's dispatchers, the model: ~170k objects) lives as long as the process:
        # out of the collector's full passes, which otherwise stall the callbacks for ~140 ms now and then (measured
        # in the fusion node at 1 kHz, docs/performance.md).  No gc.collect() first: it would cost the start-up
        # ~0.1 s, and what start-up left as cyclic garbage is kept once, bounded
        gc.freeze()
        _spin(nodes, executor)
    except PpoeError as exc:
        print(f"[FATAL] {exc}", file=sys.stderr, flush=True)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        for node in nodes:
            try:
                node.destroy_node()
            except Exception:  # noqa: BLE001 - best effort during shutdown
                pass
        rclpy.try_shutdown()
    return code


def _log_to_stderr() -> None:
    """Show ppoe_core's log lines (the kernel cache, compiles, the ahead-of-time module) on stderr, as rclpy shows
    the node's own: what is compiled and why must be seen on a first start."""
    import logging

    core = logging.getLogger("ppoe_core")
    if not core.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("[%(levelname)s] [%(created).9f] [%(name)s]: %(message)s"))
        core.addHandler(handler)
        core.setLevel(logging.INFO)
        core.propagate = False


def kernel_report() -> str:
    """One line: where this process's compiled kernels come from (the ahead-of-time module, or numba's cache and
    how many it had to compile)."""
    from ppoe_core import aot, jit
    from ppoe_core.compile_cache import cache_location, compile_stats

    tried = aot.loaded()
    if jit.ahead_of_time_in_use() and tried is not None:
        return f"compiled kernels: ahead-of-time module {tried.path} (numba not loaded)"
    stats = compile_stats()
    why = f"; ahead-of-time module not used: {tried.why}" if tried is not None and not tried.usable else ""
    done = f"{stats.kernels} compiled now in {stats.seconds:.1f} s" if stats.kernels else "none compiled now"
    return f"compiled kernels: numba, {cache_location().describe()}; {done}{why}"


def _warm_kinematics() -> None:
    """The kinematics node's path on a small robot, both covariance orders (what ``ppoe warmup`` caches and
    compiles ahead of time; at run time the node warms its own model's kernels when the URDF arrives)."""
    from ppoe_core.io.kinematics_warmup import warm_kinematics

    warm_kinematics()


def _warm_pose_messages() -> None:
    """The pose message conversions (quaternion, ROS covariance both ways)."""
    import numpy as np

    from ppoe_ros.common.conversions import pose_cov_from_msg, pose_cov_stamped_msg

    pose_cov_from_msg(pose_cov_stamped_msg(np.eye(4), np.eye(6), 0, "warm-up"))


def _warm_fusion() -> None:
    """The measurement updates, carried corrections and per-prior pipeline steps, and the pose conversions."""
    from ppoe_core.estimation.warmup import warm_kernels, warm_pipeline

    warm_kernels()
    warm_pipeline()
    _warm_pose_messages()


def _warm_tags() -> None:
    """The camera model's projection and undistortion of the tag rows, and the corner refinement's edge fit."""
    import numpy as np

    from ppoe_core.estimation.camera import project_points, undistort_pixels
    from ppoe_core.sensing.tags import refine_edges

    grey = np.full((60, 60), 200, dtype=np.uint8)
    grey[20:40, 20:40] = 30
    refine_edges(grey, np.array([[19.5, 19.5], [39.5, 19.5], [39.5, 39.5], [19.5, 39.5]]), 10)
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    D = np.array([0.01, -0.01, 0.0, 0.0, 0.0])
    uv = np.array([[300.0, 200.0], [340.0, 260.0]])
    undistort_pixels(uv, K, D)
    project_points(np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]]), K, D)


def _warm_contact() -> None:
    """The contact plane's covariance check and conversion."""
    import numpy as np

    from ppoe_core import lie

    lie.cov_local_to_ros(np.eye(4), lie.check_covariance(np.eye(6), "warm-up", size=6))


#: what each node compiles (or loads from numba's cache) before it subscribes: only what that node uses
NODE_KERNELS: dict[str, Callable[[], None]] = {
    "kinematics_node": _warm_kinematics,
    "fusion_node": _warm_fusion,
    "tag_bearing_node": _warm_tags,
    "contact_node": _warm_contact,
}


def warm_node_kernels(nodes: Sequence[str] | None = None) -> None:
    """Compile (or load from numba's cache) the kernels of ``nodes`` (:data:`NODE_KERNELS`; None: every node)
    before they subscribe: on a fresh install the first call compiles for seconds, which must not fall on the first
    message (inputs queue up and may be lost meanwhile)."""
    for name in NODE_KERNELS if nodes is None else nodes:
        NODE_KERNELS[name]()


def _spin(nodes: Sequence[Node], executor: str) -> None:
    """Spin ``nodes`` until shutdown on one executor of the chosen kind (see :func:`run_node`)."""
    context = nodes[0].context
    if executor == "events":
        from rclpy.experimental import EventsExecutor
        from rclpy.task import Future

        ex: Any = EventsExecutor(context=context)
        for node in nodes:
            ex.add_node(node)
        never = Future()
        while context.ok():
            ex.spin_until_future_complete(never, timeout_sec=1.0)
        return
    ex = rclpy.executors.SingleThreadedExecutor(context=context)
    for node in nodes:
        ex.add_node(node)
    ex.spin()
