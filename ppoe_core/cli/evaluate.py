"""``ppoe evaluate BAG --model MODEL.yaml [--base FRAME] [--tool FRAME] [--out DIR] [--json] [--online ...]``.

Replays a contract bag offline through the core code of the nodes (tag observations from images,
contact planes from ``/wrench``, the fusion node's pipeline) and scores forward
kinematics, PPOE-fused and naive-fused poses against the bag's ground truth
(:mod:`ppoe_core.analysis.evaluate` documents the metrics and the tracker registration).
Prints the markdown table (or, with ``--json``, one JSON document on stdout); ``--out``
also writes ``evaluation.md``, ``evaluation.json`` and ``errors.png`` there.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import yaml

from ppoe_core.cli.check import print_failures
from ppoe_core.cli.checks import check_online_entries, float_range, int_range
from ppoe_core.errors import ModelConfigError

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``evaluate`` options (docs/conventions.md section 6 plus ours)."""
    parser.add_argument("bag", metavar="BAG", help="contract bag directory")
    parser.add_argument("--model", required=True, metavar="MODEL.yaml", help="model YAML for the bag's robot")
    parser.add_argument("--base", default=None, help="reference frame (default: model YAML frames.base)")
    parser.add_argument("--tool", default=None, help="tool frame (default: model YAML frames.tool)")
    parser.add_argument("--out", default=None, metavar="DIR", help="write evaluation.md/.json and errors.png here")
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    parser.add_argument("--estimate", default=None, metavar="TOPIC",
                        help="also score this recorded PoseWithCovarianceStamped topic of the bag (base frame), e.g. "
                             "/ppoe/fused_pose of a live run (method 'recorded')")
    parser.add_argument("--urdf", default=None, metavar="URDF",
                        help="use this URDF instead of the bag's /robot_description (e.g. robot_calibrated.urdf "
                             "from ppoe diagnose --out)")
    parser.add_argument("--accept-partial", action="store_true",
                        help="use what can be read of a damaged bag (default: refuse it, naming per topic "
                             "what was lost)")
    parser.add_argument("--tag-windows", action="store_true",
                        help="detect tags only in windows around where the forward kinematics puts them (the same "
                             "corners, faster; tags of ids the model lacks are then not counted; default: whole "
                             "images)")
    parser.add_argument("--order", type=int, choices=(2, 4), default=2, help="covariance order of the PPOE model")
    parser.add_argument(
        "--ground-truth", default="auto", choices=("auto", "pose", "point"),
        help="score against /ground_truth/pose or /ground_truth/point (default: pose if present)",
    )
    parser.add_argument(
        "--fit-set", default="cross", choices=("cross", "square", "all"),
        help="stationing set for per-station tracker registration (bags with /dataset/stop roles)",
    )
    _add_fusion_options(parser)
    parser.add_argument("--perturbations", nargs="+", default=[], metavar="MODEL.yaml",
                        help="also replay with the perturbations / joint_noise of these model files (e.g. the "
                             "model_diagnosed.yaml of `ppoe diagnose --learn-perturbations`) and print fused error "
                             "and NEES per choice side by side (docs/covariance.md)")
    parser.add_argument("--global-scale", type=float_range(0.0, min_open=True), default=None, metavar="K",
                        help="also replay with the declared perturbation sigmas and joint noise times K")
    parser.add_argument("--online", action="store_true",
                        help="track drifting effects online (docs/online.md): tool error before / static / online, "
                             "online.json and online_parameters.png in --out")
    parser.add_argument("--online-config", default=None, metavar="ONLINE.yaml",
                        help="with --online: online_effects list (process noise per parameter [unit/sqrt(s)]), "
                             "jump_probability, the drift monitor, or a node parameter file (its online_* parameters "
                             "and sources); default: the model's trackable effects and the base tilt when a stream "
                             "sees it, the monitor on (docs/online.md)")
    parser.add_argument("--truth", default=None, metavar="BAG.truth.yaml",
                        help="with --online: the simulation truth (ppoe simulate) to compare the estimate with")
    bar = parser.add_mutually_exclusive_group()
    bar.add_argument("--progress", dest="progress", action="store_true", default=None,
                     help="progress bar on stderr (default: only when stderr is a terminal)")
    bar.add_argument("--no-progress", dest="progress", action="store_false")
    bar.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")


def _add_fusion_options(parser: argparse.ArgumentParser) -> None:
    """The fusion settings of the replay: a parameter file, ``--set``, and three overrides (ranges of the node)."""
    from ppoe_core.estimation.updater import FUSION_RANGES

    iterations, gate = FUSION_RANGES["max_iterations"], FUSION_RANGES["gate_probability"]
    parser.add_argument(
        "--fusion-params", default=None, metavar="PARAMS.yaml",
        help="a ROS 2 parameter file of the fusion node (buffer, gating, correction policy, its 'sources': tracker "
             "points, 6D poses, accelerometers from the bag; a /** file shared by the nodes also sets "
             "corner_refinement, force_threshold, release_threshold, force_component); default: the nodes' defaults",
    )
    parser.add_argument(
        "--set", dest="fusion_set", action="append", default=[], metavar="KEY=VALUE",
        help="override one setting (a fusion node parameter, e.g. use_tag_corners=false, or corner_refinement, "
             "force_threshold, release_threshold, force_component of the tag bearing / contact node); unknown keys "
             "are an error; repeatable",
    )
    parser.add_argument("--iterations", type=int_range(int(iterations[0]), int(iterations[1])), default=None,
                        help="override max_iterations of the LG-EKF update")
    parser.add_argument("--gate", type=float_range(*gate), default=None,
                        help=f"override gate_probability, in [{gate[0]:g}, {gate[1]:g}] (1 = no gate)")
    parser.add_argument("--pixel-sigma", type=float_range(0.0), default=None,
                        help="override pixel_sigma [px] (0: the model's)")


def run(args: argparse.Namespace) -> int:
    """Evaluate, print and optionally write the report; returns 0.

    ``--out`` is checked and locked before the run (:mod:`ppoe_core.cli.output`); the lock goes at the end,
    also on an error."""
    from ppoe_core.cli.output import prepare_out_dir, release_out_dir

    online = bool(args.online or args.online_config or args.truth)
    print_failures("evaluate", [args.bag], args.model)  # ppoe check's FAIL lines first (cli/check.py)
    if args.out:  # checked before the run, not after it
        prepare_out_dir(args.out, kind="evaluate --online" if online else "evaluate")
    try:
        return _run_online(args) if online else _run_offline(args)
    finally:
        if args.out:
            release_out_dir(args.out)


def _run_offline(args: argparse.Namespace) -> int:
    """Replay the bag through the nodes' core code and score it (the default)."""
    from ppoe_core.analysis.evaluate import (
        EvaluateOptions,
        evaluate_bag,
        load_fusion_params,
        load_sources,
        markdown_report,
        write_report,
    )
    from ppoe_core.io.progress import progress_wanted

    progress = progress_wanted(args.quiet, args.progress)
    fusion = load_fusion_params(args.fusion_params) if args.fusion_params else {}
    for key, value in (("max_iterations", args.iterations), ("gate_probability", args.gate),
                       ("pixel_sigma", args.pixel_sigma)):
        if value is not None:
            fusion[key] = value
    for item in args.fusion_set:
        key, sep, text = item.partition("=")
        if not sep:
            raise ModelConfigError(f"--set {item!r}: expected KEY=VALUE")
        fusion[key.strip()] = yaml.safe_load(text)
    opts = EvaluateOptions(
        base=args.base, tool=args.tool, order=args.order, fit_set=args.fit_set, fusion=fusion,
        ground_truth=args.ground_truth, progress=progress, accept_partial=args.accept_partial, urdf=args.urdf,
        estimate=args.estimate, sources=load_sources(args.fusion_params) if args.fusion_params else [],
        tag_windows=args.tag_windows,
    )
    if args.perturbations or args.global_scale is not None:
        return _compare(args, opts)
    ev = evaluate_bag(args.bag, args.model, opts)
    for note in ev.summary.get("bag_notes", []):
        print(f"ppoe evaluate: warning: {note}", file=sys.stderr)
    if args.out:
        _written(args, write_report(ev, args.out))
    if args.json:
        json.dump(ev.to_dict(), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(markdown_report(ev))
    return 0


def _compare(args: argparse.Namespace, opts: Any) -> int:
    """``--perturbations`` / ``--global-scale``: the bag replayed per covariance choice, one table."""
    from ppoe_core.analysis.diagnose.results import finite_json
    from ppoe_core.analysis.evaluate.perturbation_compare import (
        compare_perturbations,
        comparison_json,
        comparison_table,
    )

    evs = compare_perturbations(args.bag, args.model, args.perturbations, args.global_scale, opts)
    doc = {"bag": args.bag, "model": args.model, "perturbation_comparison": comparison_json(evs)}
    table = comparison_table(evs)
    if args.out:
        out = Path(args.out)
        (out / "perturbations_comparison.md").write_text(table + "\n", encoding="utf-8")
        (out / "perturbations_comparison.json").write_text(json.dumps(finite_json(doc), allow_nan=False),
                                                             encoding="utf-8")
        _written(args, [out / "perturbations_comparison.md", out / "perturbations_comparison.json"])
    if args.json:
        json.dump(finite_json(doc), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(table)
    return 0


def _written(args: argparse.Namespace, paths: list) -> None:
    """Finish ``--out`` (stale files of this kind removed, run logged, lock released) and say what was written."""
    from ppoe_core.cli.output import finish_out_dir

    run_id = finish_out_dir(args.out, paths)
    if not args.json:
        print("wrote " + ", ".join(str(p) for p in paths) + f" (run {run_id})", file=sys.stderr)


def _run_online(args: argparse.Namespace) -> int:
    """``--online``: replay with the online effect filter, print the before / static / online table (or JSON)."""
    from ppoe_core.analysis.evaluate.online import (
        evaluate_online,
        load_online_settings,
        markdown_online,
        write_online_report,
    )
    from ppoe_core.robot.yaml_io import read_yaml_file

    if not args.online:
        raise ModelConfigError("--online-config and --truth need --online")
    settings = load_online_settings(args.online_config)
    check_online_entries(settings.entries, settings.jump_probability, args.online_config)  # naming the file
    truth = read_yaml_file(args.truth, "truth file", ModelConfigError)[0] if args.truth else None
    ev = evaluate_online(args.bag, args.model, truth=truth, base=args.base, tool=args.tool, settings=settings)
    if args.out:
        _written(args, write_online_report(ev, args.out, args.model))
    if args.json:
        json.dump(ev.to_dict(), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(markdown_online(ev))
    return 0
