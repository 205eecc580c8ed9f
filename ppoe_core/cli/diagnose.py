"""``ppoe diagnose BAG... --model MODEL.yaml [--base FRAME] [--tool FRAME] [--out DIR] [--json] [--test BAG...]``.

Finds the systematic effects (CONTRACT sec. 6 vocabulary) that the model lacks, from every measurement the bags
carry -- tracker points (``/ground_truth/point[/<name>]``, registration per session) or ``/ground_truth/pose``, tag
pixels (``/tag_bearing/observations`` or camera images, with the model's ``tags``), accelerometers (``/imu/<name>``)
and contacts (``/wrench`` with the model's ``contact`` plane) -- in one fit (:mod:`ppoe_core.analysis.diagnose`).
It runs :func:`~ppoe_core.analysis.diagnose.files.diagnose_bags`, the library call, and prints a markdown summary
or, with ``--json``, that result's JSON (keys ``effects``, ``residual_before``, ``residual_after``,
``unexplained``, ``unexplained_significant``, ``test``, ...); ``--out DIR`` also writes ``diagnose.md``,
``diagnose.json``, ``diagnose.png``, ``model_diagnosed.yaml`` and the calibration ``robot_calibrated.urdf`` +
``model_calibrated.yaml``.

``--effects NAME@LOCATION[comp,...] ...`` fits that declared set instead of selecting (CIs and test scores as
usual).  ``--test TEST_BAG...`` scores the fitted model, unchanged, on other bags of the same robot (JSON ``test``).
``--tool`` names the link that carries the tracker's reflector (default: the model's ``tracker.link``) or, for
pose bags, the tool frame (default ``frames.tool``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ppoe_core.cli.check import print_failures
from ppoe_core.cli.checks import check_diagnose_inputs, float_range, int_range

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``diagnose`` options (CONTRACT.md section 6 plus ours)."""
    parser.add_argument("bags", nargs="+", metavar="BAG", help="contract bag directories (one robot)")
    parser.add_argument("--model", required=True, metavar="MODEL.yaml", help="model YAML of the bags' robot")
    parser.add_argument("--base", default=None, help="frame of /ground_truth/pose (default: frames.base)")
    parser.add_argument("--tool", default=None,
                        help="link carrying the tracker reflector, or tool frame of /ground_truth/pose")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="write diagnose.md/.json/.png, model_diagnosed.yaml and the calibration here")
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    parser.add_argument("--test", nargs="+", default=[], metavar="TEST_BAG",
                        help="score the fitted model, unchanged, on these bags (JSON key 'test': rms, mean, "
                             "median, p95, max [m] and n per bag; stop roles scored by their protocol)")
    parser.add_argument("--effects", nargs="+", default=None, metavar="NAME@LOCATION",
                        help="fit this set (e.g. joint_offset@joint_2 'link_error@joint_5[x,y]') instead of "
                             "selecting; CIs and test scores as usual")
    parser.add_argument("--planned", default=None, metavar="PLAN.json",
                        help="ppoe plan's plan.json: report the achieved 95 %% half-widths next to the planned ones "
                             "(JSON key 'planned')")
    parser.add_argument("--accept-partial", action="store_true",
                        help="use what can be read of a damaged bag (default: refuse it, naming per topic "
                             "what was lost)")
    parser.add_argument("--cv", default="auto", choices=("auto", "stops", "groups"),
                        help="cross-validation: over robot poses, or leave-one-bag-out (auto: bags if >= 3)")
    parser.add_argument("--folds", type=int_range(2), default=5,
                        help="folds of the cross-validation over poses (default 5)")
    parser.add_argument("--min-t", type=float_range(0.0), default=4.0,
                        help="minimum paired t (or signed-rank z) over poses of a step's held-out gains (default 4)")
    parser.add_argument("--min-gain", type=float_range(0.0, 1.0, max_open=True), default=0.0,
                        help="minimum relative held-out gain of a step (default 0: the penalised likelihood decides)")
    parser.add_argument("--penalty", type=float_range(0.0), default=None,
                        help="price per parameter in held-out -2 log L (default: ln of the number of poses)")
    parser.add_argument("--max-effects", type=int_range(1), default=None,
                        help="optional cap on the number of effects (default: none; selection stops when nothing "
                             "significant is left)")
    parser.add_argument("--no-groups", action="store_true",
                        help="no group moves (one effect kind on every joint of a measured chain)")
    parser.add_argument("--robust", default="linear", choices=("linear", "soft_l1"),
                        help="loss of the fit (soft_l1: robust to gross outliers, scale 3 whitened units)")
    parser.add_argument("--measurement", default="auto", choices=("auto", "point", "pose"),
                        help="residuals of /ground_truth/point (auto: preferred) or /ground_truth/pose")
    parser.add_argument("--stationing-set", default="cross", choices=("cross", "square", "all"),
                        help="stationing set defining the registration in bags with /dataset/stop roles")
    parser.add_argument("--pixels", default="auto", choices=("auto", "on", "off"),
                        help="fit tag pixels too (auto: if the model has tags and a bag has tag observations or "
                             "images)")
    parser.add_argument("--imu", default="auto", choices=("auto", "off"),
                        help="fit accelerometer tilts too (auto: if the bags have /imu/<name>)")
    bar = parser.add_mutually_exclusive_group()
    bar.add_argument("--progress", dest="progress", action="store_true", default=None,
                     help="the running stage and time on stderr (default: only when stderr is a terminal)")
    bar.add_argument("--no-progress", dest="progress", action="store_false")
    bar.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    parser.add_argument("--pixel-sigma", type=float_range(0.0, min_open=True), default=None,
                        help="declared pixel noise 1-sigma per axis [px] (default: the model's camera.pixel_sigma, "
                             "else 1; the fit estimates the actual noise)")
    parser.add_argument("--learn-perturbations", action="store_true",
                        help="learn the perturbation covariances per joint and axis from the held-out residual, "
                             "write them into model_diagnosed.yaml and compare declared / one global scale / learned "
                             "on held-out data (docs/covariance.md)")


def run(args: argparse.Namespace) -> int:
    """Diagnose, print and optionally write the report, the diagnosed model and the calibration; returns 0.

    The running stage and the time spent are shown on stderr (:class:`ppoe_core.io.progress.Ticker`) when it
    is a terminal, unless ``--quiet``."""
    from ppoe_core.io.progress import Ticker, progress_wanted

    with Ticker("diagnose", progress_wanted(args.quiet, args.progress)) as tick:
        return _run(args, tick)


def _run(args: argparse.Namespace, tick: Any) -> int:
    """:func:`run` with its progress ticker ``tick`` (``tick.stage(text)`` names each stage)."""
    from ppoe_core.analysis.diagnose.files import LoadOptions, diagnose_bags
    from ppoe_core.analysis.diagnose.report import write_model_yaml, write_report
    from ppoe_core.cli.output import prepare_out_dir

    check_diagnose_inputs(args)  # every bag before the fit: readable, not twice, one robot (cli/checks.py)
    print_failures("diagnose", [*args.bags, *args.test], args.model)  # ppoe check's FAIL lines first (cli/check.py)
    if args.out:  # checked before the run, not after it
        prepare_out_dir(args.out)
    done = diagnose_bags(args.bags, args.model, args.test, options(args), LoadOptions(
        base=args.base, tool=args.tool, measurement=args.measurement,
        stationing_set=None if args.stationing_set == "all" else args.stationing_set, pixels=args.pixels,
        pixel_sigma=args.pixel_sigma, accept_partial=args.accept_partial), stage=tick.stage)
    res = done.result
    paths = {}
    if args.out:
        tick.stage("writing the report")
        paths = write_report(res, args.out, title="ppoe diagnose " + " ".join(Path(b).name for b in args.bags),
                             declared=done.declared, bags=args.bags)
        model_out = write_model_yaml(args.model, res, Path(args.out) / "model_diagnosed.yaml")
        calibrated = _write_calibrated(args, done)
        print("wrote " + ", ".join(str(p) for p in [*paths.values(), model_out, *calibrated]), file=sys.stderr)
    doc = res.to_json()
    if args.planned:  # ppoe plan's predicted intervals next to the achieved ones
        from ppoe_core.analysis.plan.outputs import compare_planned
        doc["planned"] = compare_planned(doc, args.planned)
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(paths["md"].read_text() if paths else res.summary)
        if args.planned:
            from ppoe_core.analysis.plan.outputs import planned_lines
            print("\n".join(planned_lines(doc["planned"])))
    return 0


def options(args: argparse.Namespace) -> Any:
    """The :class:`DiagnoseOptions` of the parsed arguments."""
    from ppoe_core.analysis.diagnose.results import DiagnoseOptions

    blocks = None if args.imu == "auto" else ["tracker", "pose", "pixels", "contact"]
    return DiagnoseOptions(folds=args.folds, cv=args.cv, min_t=args.min_t, min_gain=args.min_gain,
                           penalty=args.penalty, max_effects=args.max_effects, groups=not args.no_groups,
                           effects=args.effects, loss=args.robust, blocks=blocks,
                           learn_perturbations=args.learn_perturbations)


def _write_calibrated(args: argparse.Namespace, done: Any) -> list[Path]:
    """``robot_calibrated.urdf`` (declared static effects and the significant components of the found ones
    folded into the joint origins: :func:`~ppoe_core.analysis.diagnose.calibrated_urdf.plan_calibration`) and
    ``model_calibrated.yaml`` (the model without static effects) in ``--out``."""
    from ppoe_core.analysis.diagnose.calibrated_urdf import STATIC_EFFECTS, calibrated_urdf, plan_calibration
    from ppoe_core.analysis.diagnose.report import write_model_yaml

    text, _ = calibrated_urdf(done.urdf, done.robot, plan_calibration(done.result, done.declared).folded)
    urdf_out = Path(args.out) / "robot_calibrated.urdf"
    urdf_out.write_text(text, encoding="utf-8")
    model_out = write_model_yaml(args.model, done.result, Path(args.out) / "model_calibrated.yaml",
                                 drop=STATIC_EFFECTS)
    return [urdf_out, model_out]
