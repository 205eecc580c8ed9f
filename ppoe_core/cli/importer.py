"""``ppoe import hilti|motoman|csv``: turn measured datasets into contract bags.

::

    ppoe import hilti FILE.yaml --out BAG [--urdf trailblazer.urdf] [--ppoe-model OUT.yaml] [--force] [--json]
                      [--allow-incomplete]
    ppoe import motoman FILE.mat --model-yaml MODEL.yaml --out BAG [--urdf URDF]
                        [--ppoe-model OUT.yaml] [--force] [--json]
    ppoe import csv STOPS.csv --mapping MAP.yaml --urdf URDF --out BAG [--force] [--json]

The bag layouts are documented in :mod:`ppoe_core.io.importers.hilti` and
:mod:`ppoe_core.io.importers.motoman`.  Both also write a ppoe model YAML next to the bag
(``BAG.model.yaml``) for ``ppoe evaluate``.  The datasets are third-party data: never
commit the bags (or the generated model YAML) these commands write.
"""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``hilti`` and ``motoman`` sub-subcommands to ``parser``."""
    sub = parser.add_subparsers(dest="dataset", metavar="DATASET")
    sub.required = True
    h = sub.add_parser("hilti", help="Hilti stationing YAML -> contract bag")
    h.add_argument("file", metavar="FILE.yaml", help="dataset file, e.g. flat.yaml")
    h.add_argument("--out", required=True, metavar="BAG", help="output bag directory")
    h.add_argument("--urdf", default=None, help="robot URDF (default: trailblazer.urdf next to FILE)")
    h.add_argument(
        "--ppoe-model", default=None, metavar="OUT.yaml", help="where to write the ppoe model (default: BAG.model.yaml)"
    )
    h.add_argument("--allow-incomplete", action="store_true",
                   help="import a file in which some stations lack stationing or evaluation measurements, or that "
                        "looks cut short")
    m = sub.add_parser("motoman", help="Motoman Leica .mat -> contract bag + ppoe model YAML")
    m.add_argument("file", metavar="FILE.mat", help="dataset file, e.g. leica_right_hand_6x6x6_dataset.mat")
    m.add_argument("--model-yaml", required=True, metavar="MODEL.yaml", help="the dataset's model.yaml")
    m.add_argument("--out", required=True, metavar="BAG", help="output bag directory")
    m.add_argument("--urdf", default=None, help="robot URDF (default: motoman_right.urdf next to MODEL.yaml)")
    m.add_argument(
        "--ppoe-model", default=None, metavar="OUT.yaml", help="where to write the ppoe model (default: BAG.model.yaml)"
    )
    c = sub.add_parser("csv", help="any robot: one CSV row per stop + a mapping YAML -> contract bag")
    c.add_argument("file", metavar="STOPS.csv", help="CSV with a header row, one stop per row")
    c.add_argument("--mapping", required=True, metavar="MAP.yaml",
                   help="which columns are joints, points, pose, time, station, role "
                        "(ppoe_core/io/importers/csv_stops.py)")
    c.add_argument("--urdf", required=True, help="the robot's URDF (written on /robot_description)")
    c.add_argument("--out", required=True, metavar="BAG", help="output bag directory")
    for p in (h, m, c):
        p.add_argument("--force", action="store_true", help="overwrite an existing output bag")
        p.add_argument("--json", action="store_true", help="print the message counts as one JSON document")


def run(args: argparse.Namespace) -> int:
    """Run the import; prints a summary (or JSON with ``--json``) and returns 0."""
    if args.dataset == "csv":
        from ppoe_core.io.importers.csv_stops import import_csv

        res = import_csv(args.file, args.mapping, args.urdf, args.out, overwrite=args.force)
        for topic, n in res["skipped"].items():
            print(f"ppoe import: warning: {args.file}: {n} stops without {topic} (empty cells)", file=sys.stderr)
        if args.json:
            print(json.dumps({"bag": args.out, **res}))
        else:
            counts = ", ".join(f"{t}: {n}" for t, n in sorted(res["counts"].items()))
            print(f"ppoe import: wrote {args.out} ({res['stops']} stops; {counts})", file=sys.stderr)
        return 0
    if args.dataset == "hilti":
        from ppoe_core.io.importers.hilti import import_hilti

        res = import_hilti(args.file, args.out, urdf=args.urdf, overwrite=args.force, ppoe_model_out=args.ppoe_model,
                           allow_incomplete=args.allow_incomplete)
        for line in res["incomplete"] + res["truncated"]:
            print(f"ppoe import: warning: {args.file}: {line}", file=sys.stderr)
        print(f"ppoe import: {args.file}: {res['stops']} stops in {res['stations']} stations imported (the Hilti "
              "format declares no total)", file=sys.stderr)
        result = {"bag": args.out, **res}
    else:
        from ppoe_core.io.importers.motoman import import_motoman

        res = import_motoman(
            args.file, args.model_yaml, args.out, urdf=args.urdf, ppoe_model_out=args.ppoe_model, overwrite=args.force
        )
        result = {"bag": args.out, **res}
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(f"wrote {args.out}")
        for topic, n in sorted(result["counts"].items()):
            print(f"  {topic}: {n}")
        if "model" in result:
            print(f"model: {result['model']}  (derived from the dataset: do not commit)")
    return 0
