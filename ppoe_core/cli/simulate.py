"""``ppoe simulate SCENARIO.yaml --out BAG [--seed N]``: record a simulated contract bag.

The scenario format is documented in :data:`ppoe_core.sim.simulate.SCENARIO_DOC`
(``ppoe simulate --help-scenario`` prints it); examples are in ``bags/``.
Besides the bag, the truth (effects, drawn perturbations, tracker registration) is
written to ``--truth`` (default ``BAG.truth.yaml`` next to the bag directory).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import yaml

from ppoe_core.cli.checks import int_range

__all__ = ["add_arguments", "run", "TRUTH_HEADER"]

#: first characters of the truth YAML written here: ``--force`` replaces only a file starting with them
TRUTH_HEADER = "# truth of bag "


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``ppoe simulate`` options to ``parser``."""
    parser.add_argument("scenario", nargs="?", metavar="SCENARIO.yaml", help="scenario file (see --help-scenario)")
    parser.add_argument("--out", metavar="BAG", help="bag directory to create")
    parser.add_argument("--seed", type=int_range(0), default=None, help="RNG seed >= 0 (overrides the scenario's)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing bag directory (only one holding nothing but bag files) and its "
                             "truth file")
    parser.add_argument("--truth", metavar="FILE", default=None,
                        help="where to write the truth YAML (default BAG.truth.yaml; 'none' to skip)")
    parser.add_argument("--json", action="store_true", help="print a JSON summary to stdout")
    parser.add_argument("--help-scenario", action="store_true", help="print the documented scenario format and exit")


def run(args: argparse.Namespace) -> int:
    """Run ``ppoe simulate``; returns the exit code."""
    from ppoe_core.errors import ScenarioError
    from ppoe_core.io.outputs import check_bag_target, check_generated_file
    from ppoe_core.sim.simulate import SCENARIO_DOC, simulate

    if args.help_scenario:
        sys.stdout.write(SCENARIO_DOC)
        return 0
    if not args.scenario or not args.out:
        raise ScenarioError("ppoe simulate needs SCENARIO.yaml and --out BAG")
    out = Path(args.out)
    truth_path = None
    if args.truth != "none":
        truth_path = Path(args.truth) if args.truth else out.parent / (out.name + ".truth.yaml")
    check_bag_target(out, args.force)  # before the work: a path we may not replace is refused now
    if truth_path is not None:
        check_generated_file(truth_path, args.force, TRUTH_HEADER, "truth file")
    t0 = time.perf_counter()
    res = simulate(args.scenario, args.out, seed=args.seed, storage=args.storage, overwrite=args.force)
    wall = time.perf_counter() - t0
    if truth_path is not None:
        truth_path.write_text(TRUTH_HEADER + out.name + " (written by ppoe simulate; tools are never told)\n"
                              + yaml.safe_dump(res.truth, sort_keys=False, default_flow_style=None))
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    summary = {"bag": str(out), "size_bytes": size, "duration_s": res.duration, "stops": res.n_stops,
               "counts": res.counts, "visible_tags": res.visible_tags, "wall_s": round(wall, 3),
               "truth": str(truth_path) if truth_path else None}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {out} ({size / 1e6:.2f} MB, {res.duration:.1f} s, {res.n_stops} stops) in {wall:.1f} s")
        for topic, n in sorted(res.counts.items()):
            print(f"  {topic}: {n}")
        if truth_path:
            print(f"truth: {truth_path}")
    return 0
