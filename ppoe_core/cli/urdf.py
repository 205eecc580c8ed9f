"""``ppoe urdf from-dh DH.yaml --out ROBOT.urdf``: a URDF from a Denavit-Hartenberg table.

The table format (standard or modified convention, limits, masses, a tool frame) is in
:mod:`ppoe_core.robot.dh`; a worked example is ``docs/dh.md``.  The URDF is checked by parsing it
back before it is written.  Exit codes: 0 written, 2 bad table or output exists (without ``--force``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_arguments", "run", "GENERATED_MARKER"]

#: what the second line of a URDF written here holds (dh.py's comment): --force replaces only such a file
GENERATED_MARKER = "by ppoe urdf from-dh -->"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``urdf`` options."""
    parser.add_argument("action", choices=("from-dh",), help="from-dh: URDF from a DH table (YAML)")
    parser.add_argument("table", metavar="DH.yaml", help="the DH table (format: ppoe_core/robot/dh.py, docs/dh.md)")
    parser.add_argument("--out", required=True, metavar="ROBOT.urdf", help="URDF file to write")
    parser.add_argument("--force", action="store_true", help="overwrite an existing URDF written by this command")


def run(args: argparse.Namespace) -> int:
    """Write the URDF; returns the exit code."""
    from ppoe_core.errors import PpoeError, UrdfError
    from ppoe_core.io.outputs import check_generated_file
    from ppoe_core.robot.dh import dh_to_urdf
    from ppoe_core.robot.urdf import parse_urdf

    out = Path(args.out)
    if out.exists() and not args.force:
        raise PpoeError(f"--out {out}: exists (pass --force to overwrite)")
    check_generated_file(out, args.force, GENERATED_MARKER, "--out")  # --force replaces only a URDF made here
    text = dh_to_urdf(args.table)
    try:
        robot = parse_urdf(text, text_source=f"URDF from {args.table}")
    except UrdfError as exc:  # the table's checks should catch everything: name the table, not a generated line
        detail = str(exc).split(": ", 1)[-1]
        raise PpoeError(f"{args.table}: the URDF made from this table does not parse ({detail}); check the names "
                        "and values of the table") from None
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise PpoeError(f"--out {out}: cannot write there ({exc.strerror})") from None
    movable = [j for j in robot.joints.values() if j.movable]
    print(f"ppoe urdf: wrote {out} ({len(movable)} movable joints, {len(robot.links)} links)", file=sys.stderr)
    return 0
