"""``ppoe init --urdf ROBOT.urdf [--bag BAG] --out MODEL.yaml``: a first, commented model YAML for a robot.

The guesses (:mod:`ppoe_core.robot.model_init`): frames from the tree (root; the leaf of the longest chain, the
other leaves listed), a default prior on every joint of that chain, and with ``--bag`` the trackers, camera, IMUs
and tag ids the bag shows (:func:`ppoe_core.io.bag_facts.bag_facts`).  Every guess is marked ``# GUESS: confirm``.
Without ``--urdf`` the bag's ``/robot_description`` is the URDF.  The YAML is loaded back
(:func:`ppoe_core.robot.config.load_model_config`) before it is written.  Exit codes: 0 written, 2 bad input or
an output that exists (without ``--force``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_arguments", "run", "INIT_MARKER"]

#: what the first line of a YAML written here holds: --force replaces only such a file
INIT_MARKER = "written by `ppoe init`"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``init`` options."""
    parser.add_argument("--urdf", default=None, metavar="ROBOT.urdf",
                        help="the robot's URDF (default: the bag's /robot_description)")
    parser.add_argument("--bag", default=None, metavar="BAG",
                        help="a contract bag of the robot: trackers, camera, IMUs and tags are guessed from it")
    parser.add_argument("--out", required=True, metavar="MODEL.yaml", help="model YAML to write")
    parser.add_argument("--force", action="store_true", help="overwrite a model YAML written by ppoe init")


def run(args: argparse.Namespace) -> int:
    """Guess, check by loading back, write; returns the exit code."""
    from ppoe_core.errors import PpoeError
    from ppoe_core.io.outputs import check_generated_file
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.model_init import guess_model, model_yaml, summary_lines
    from ppoe_core.robot.urdf import parse_urdf

    if args.urdf is None and args.bag is None:
        raise PpoeError("ppoe init needs --urdf ROBOT.urdf, or --bag BAG with a /robot_description")
    out = Path(args.out)
    check_generated_file(out, args.force, INIT_MARKER, "--out")
    facts = None
    if args.bag is not None:
        from ppoe_core.io.bag_facts import bag_facts, bag_urdf

        urdf_text = Path(args.urdf).read_text(encoding="utf-8") if args.urdf else bag_urdf(args.bag)
        robot = parse_urdf(urdf_text, text_source=args.urdf or f"{args.bag} /robot_description")
        facts = bag_facts(args.bag, robot)
    else:
        robot = parse_urdf(args.urdf)
    guess = guess_model(robot, facts)
    text = model_yaml(robot, guess, Path(args.urdf).name if args.urdf else f"{Path(args.bag).name}/robot_description",
                      [Path(args.bag).name] if args.bag else [])
    load_model_config(text, robot, is_text=True)  # what we write loads (a failure is our bug), before writing
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise PpoeError(f"--out {out}: cannot write there ({exc.strerror})") from None
    for line in summary_lines(guess):
        print(f"ppoe init: {line}", file=sys.stderr)
    print(f"ppoe init: wrote {out}; check every line marked '# GUESS: confirm'", file=sys.stderr)
    return 0
