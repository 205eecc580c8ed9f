"""``ppoe warmup``: compile every node's kernels once, at installation, instead of at a node's first start.

The README's set-up command and ``colcon build`` (setup.py) run it.  It

1. compiles (or finds in numba's cache) the kernels of each node (:data:`ppoe_ros.common.runner.NODE_KERNELS`), in
   the cache directory chosen by :mod:`ppoe_core.compile_cache` (the package's ``__pycache__`` when writable, else
   ``$XDG_CACHE_HOME/ppoe``, ...);
2. compiles the kernels ``ppoe evaluate`` adds to the nodes' by replaying a two-second simulated bag
   (:func:`ppoe_core.analysis.evaluate.warmup.warm_evaluate`; ``--no-evaluate`` skips it, and so does ``--nodes``);
3. compiles the kinematics node's kernels ahead of time (:mod:`ppoe_core.aot`), so that the node runs without numba
   (about 100 MB less; needs a C compiler: without one, the node uses the numba cache of step 1).

Each step prints one line with its time; a node's first start then loads instead of compiling (docs/performance.md,
"Start-up").  Running it again finds everything in the cache and takes seconds.

Usage::

    ppoe warmup [--nodes kinematics_node fusion_node ...] [--no-evaluate] [--no-aot]
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

__all__ = ["add_arguments", "run", "NODES"]

#: the nodes, in the order they are warmed
NODES = ("kinematics_node", "fusion_node", "tag_bearing_node", "contact_node")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``ppoe warmup``."""
    parser.add_argument("--nodes", nargs="+", choices=NODES, default=None, metavar="NODE",
                        help=f"compile only these nodes' kernels (default: all: {', '.join(NODES)}, and those of "
                             f"ppoe evaluate)")
    parser.add_argument("--no-evaluate", action="store_true",
                        help="do not compile the kernels of ppoe evaluate (a 2 s simulated replay; skipped with "
                             "--nodes too)")
    parser.add_argument("--no-aot", action="store_true",
                        help="do not compile the kinematics node's kernels ahead of time (it then uses numba)")


def _warmers() -> dict[str, Any]:
    """Each node's warm-up: the nodes' own (rclpy present) or, without ROS, the core part of each."""
    try:
        from ppoe_ros.common.runner import NODE_KERNELS

        return dict(NODE_KERNELS)
    except ImportError:  # no rclpy: the core kernels only (a pip install without the 'ros' extra)
        from ppoe_core.estimation.warmup import warm_kernels, warm_pipeline
        from ppoe_core.io.kinematics_warmup import warm_kinematics

        def fusion() -> None:
            warm_kernels()
            warm_pipeline()

        return {"kinematics_node": warm_kinematics, "fusion_node": fusion}


def run(args: argparse.Namespace) -> int:
    """Warm the kernels of ``args.nodes`` and build the ahead-of-time module; 0 unless a node's warm-up failed."""
    from ppoe_core.compile_cache import cache_location, compile_stats

    print(f"ppoe warmup: {cache_location().describe()}", flush=True)
    warmers = _warmers()
    nodes = list(NODES) if args.nodes is None else args.nodes
    for name in nodes:
        warm = warmers.get(name)
        if warm is None:
            print(f"ppoe warmup: {name}: skipped (needs ROS 2: rclpy is not importable)", flush=True)
            continue
        before, t0 = compile_stats().kernels, time.perf_counter()
        warm()
        print(f"ppoe warmup: {name}: {compile_stats().kernels - before} kernel(s) compiled, "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    if args.nodes is None and not args.no_evaluate:
        from ppoe_core.analysis.evaluate.warmup import warm_evaluate

        before, t0 = compile_stats().kernels, time.perf_counter()
        done = warm_evaluate()
        print(f"ppoe warmup: ppoe evaluate: {compile_stats().kernels - before} kernel(s) compiled, "
              f"{time.perf_counter() - t0:.1f} s ({done})", flush=True)
    if args.no_aot or "kinematics_node" not in nodes:
        return 0
    from ppoe_core import aot

    st = aot.status()
    if st.usable:
        print(f"ppoe warmup: kinematics node, ahead-of-time module up to date: {st.path}", flush=True)
        return 0
    t0 = time.perf_counter()
    try:
        path = aot.build(warmers["kinematics_node"])
    except RuntimeError as exc:
        print(f"ppoe warmup: kinematics node, no ahead-of-time module ({exc}); it uses numba", file=sys.stderr,
              flush=True)
        return 0
    print(f"ppoe warmup: kinematics node, ahead-of-time module {path} ({time.perf_counter() - t0:.1f} s)",
          flush=True)
    return 0
