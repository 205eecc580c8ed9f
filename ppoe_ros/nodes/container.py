"""``ppoe_container``: any subset of the nodes in ONE process, on one executor (rclpy's ``EventsExecutor``).

Each node in its own process pays Python, rclpy and numba's LLVM runtime again (about 300 MB per node before,
docs/performance.md "Memory"); in one process they share them.  The nodes are the same classes with the same
parameters, topics and diagnostics as ``kinematics_node``, ``fusion_node`` ... (the same live tests run against
both: ``test/test_container.py``).

Usage::

    ppoe_container NODE[:PARAMS_FILE[,PARAMS_FILE...]] ... [--ros-args GLOBAL_ARGS...]
    ppoe_container kinematics_node:config/nodes/kinematics_node.yaml fusion_node:config/nodes/fusion_node.yaml \\
        --ros-args -p robot_description:="$(cat config/robots/arm7.urdf)" -p model_file:=config/robots/arm7_model.yaml

``NODE`` is an executable name (``kinematics_node``, ``fusion_node``, ``tag_bearing_node``, ``contact_node``);
``PARAMS_FILE`` s after it apply to that node only (as the shipped defaults in ``config/nodes/`` are written for
``/**``, each node's own file must be given this way, not globally); ``--ros-args`` after the node list applies to
every node, as in one process of its own (``-p``, ``--params-file``, ``-r __ns:=``, ``--log-level``).  Renaming a
node (``-r __node:=``) would rename all of them: use the namespace instead.  No node given: all four.

The nodes are built in the order given (the kinematics node first is best: the others wait for its poses); a
:class:`~ppoe_core.errors.PpoeError` while building any of them (bad parameter, unreadable model file) is printed as
one line and stops the container with exit code 2, as a node alone would.  With the kinematics node alone the
ahead-of-time kernels are used as in ``kinematics_node`` (no numba); with others numba is loaded anyway.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["NODES", "main", "parse_node_specs"]

#: executable name -> (module, class) of each node the container runs
NODES: dict[str, tuple[str, str]] = {
    "kinematics_node": ("ppoe_ros.nodes.kinematics_node", "KinematicsNode"),
    "fusion_node": ("ppoe_ros.nodes.fusion_node", "FusionNode"),
    "tag_bearing_node": ("ppoe_ros.nodes.tag_bearing_node", "TagBearingNode"),
    "contact_node": ("ppoe_ros.nodes.contact_node", "ContactNode"),
}


def parse_node_specs(argv: Sequence[str]) -> tuple[list[tuple[str, list[str]]], list[str]]:
    """``(nodes, rest)``: each ``NODE[:FILE,...]`` before ``--ros-args`` as ``(name, [files])`` and the rest of
    the command line (program name and ``--ros-args ...``) for ``rclpy.init``.

    Raises
    ------
    ValueError
        An unknown node name or a node given twice, naming it and the known ones.
    """
    argv = list(argv)
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    specs: list[tuple[str, list[str]]] = []
    for item in argv[1:cut]:
        name, _, files = item.partition(":")
        if name not in NODES:
            raise ValueError(f"unknown node '{name}' (known: {', '.join(NODES)})")
        if any(name == n for n, _ in specs):
            raise ValueError(f"node '{name}' given twice")
        specs.append((name, [f for f in files.split(",") if f]))
    if not specs:
        specs = [(name, []) for name in NODES]
    return specs, argv[:1] + argv[cut:]


def _factory(name: str, files: list[str]) -> Callable[[], Any]:
    """Builds node ``name`` with its own parameter files (``cli_args``: they apply to this node only)."""
    module, cls = NODES[name]

    def build() -> Any:
        node_class = getattr(importlib.import_module(module), cls)
        cli: list[str] = []
        for f in files:
            cli += ["--params-file", f]
        return node_class(cli_args=["--ros-args", *cli]) if cli else node_class()

    build.__name__ = name
    return build


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``ppoe_container``."""
    from ppoe_core.errors import PpoeError
    from ppoe_ros.common.runner import check_params_files, run_nodes

    argv = list(sys.argv if args is None else args)
    try:
        specs, ros_argv = parse_node_specs(argv)
        for _, files in specs:
            check_params_files(["--ros-args", *[a for f in files for a in ("--params-file", f)]])
    except (ValueError, PpoeError) as exc:  # an unknown node, or a parameter file that cannot be read
        print(f"[FATAL] ppoe_container: {exc}", file=sys.stderr, flush=True)
        return 2
    names = [name for name, _ in specs]
    if names == ["kinematics_node"]:
        from ppoe_core import aot

        aot.load()  # as kinematics_node alone: its ahead-of-time kernels, no numba
    return run_nodes([_factory(name, files) for name, files in specs], ros_argv, executor="events",
                     kernels=[n for n in names if n != "kinematics_node"])


if __name__ == "__main__":
    sys.exit(main())
