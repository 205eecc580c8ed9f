"""``ppoe check BAG... --model MODEL.yaml [--json]``: what the bags hold against what the model needs.

One table (:func:`ppoe_core.io.bag_check.check_bags`): topics and counts, joints present / missing / extra,
frames known / unknown, time span and stamp problems, static stops found, whether each joint's offset is
identifiable with these data; then one summary line.  Exit code 0 all ok, 1 warnings only, 2 a failure (or an
input that cannot be read).  ``ppoe diagnose`` and ``ppoe evaluate`` print the same check's failures first
(:func:`print_failures`).
"""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["add_arguments", "run", "print_failures"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``check`` options."""
    parser.add_argument("bags", nargs="+", metavar="BAG", help="contract bag directories")
    parser.add_argument("--model", required=True, metavar="MODEL.yaml", help="model YAML of the bags' robot")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON document: rows (bag, item, holds, needs, verdict), exit_code, summary")


def run(args: argparse.Namespace) -> int:
    """Print the table (or JSON) and the summary line; returns 0 / 1 / 2."""
    from ppoe_core.io.bag_check import check_bags

    report = check_bags(list(args.bags), args.model)
    if args.json:
        json.dump({"rows": [r.__dict__ for r in report.rows], "exit_code": report.exit_code,
                   "summary": report.summary()}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(report.markdown())
        print()
        print(report.summary())
    return report.exit_code


def print_failures(command: str, bags: list[str], model: str) -> None:
    """The check's FAIL lines that matter to ``command`` on stderr, before it starts (nothing when the bags pass;
    an unreadable bag, a missing URDF or a model that does not load the command says itself, in its own line)."""
    from ppoe_core.io.bag_check import check_bags

    try:
        fails = check_bags(bags, model, identifiability=False).failures(command)   # its rows only warn
    except Exception as exc:  # noqa: BLE001 -- the check must never stop the command it precedes; said, not hidden
        print(f"ppoe {command}: check: not run ({type(exc).__name__}: {exc}); `ppoe check` names the problem",
              file=sys.stderr)
        return
    for r in fails:
        print(f"ppoe {command}: check: {r.bag}: {r.item}: {r.holds} (the model needs: {r.needs})", file=sys.stderr)
    if fails:
        print(f"ppoe {command}: check: {len(fails)} failure(s); `ppoe check` shows the whole table", file=sys.stderr)
