"""``ppoe diagnose BAG... --model MODEL.yaml [--base FRAME] [--tool FRAME] [--out DIR] [--json] [--test BAG...]``.

Finds the systematic effects (docs/conventions.md sec. 6 vocabulary) that the model lacks, from the
bags' ``/ground_truth/point`` (tracker, registration estimated per session) or
``/ground_truth/pose`` measurements; see :mod:`ppoe_core.analysis.diagnose`.  Prints a markdown summary
(or, with ``--json``, one JSON document on stdout with keys ``effects``, ``residual_before``,
``residual_after``); ``--out DIR`` also writes ``diagnose.md``, ``diagnose.json``,
``diagnose.png`` and the updated model ``model_diagnosed.yaml`` there.

Tag pixels (``--pixels``, default ``auto``: when the model has ``tags`` and a bag has
``/tag_bearing/observations`` or camera images) are diagnosed too, on top of the tracker/pose
effects: ``camera_extrinsics`` candidates per camera, JSON key ``pixels`` (held-out pixel RMS
per camera before -> after), found effects appended to ``effects``.

Joint fit (``--joint``, default ``auto``: when the bags carry tracker points and tag pixels): the effects the
stages chose plus every camera's ``camera_extrinsics`` fitted to tracker points and pixels at once
(:func:`ppoe_core.analysis.diagnose.joint_fit.joint_fit`), JSON key ``joint`` (effects with 95 % CIs,
held-out pixel RMS per camera and tracker RMS, cross-validated over poses); the other keys are unchanged.

``--test TEST_BAG...`` scores the fitted model, unchanged, on other bags of the same robot (JSON key
``test``, one object per bag: ``rms``, ``mean``, ``median``, ``p95``, ``max`` [m], ``n``, the same
``before``, and the ``protocol``: a bag with stop roles is scored by them, else one registration
per session on all its stops; see :mod:`ppoe_core.analysis.diagnose.testing`).

``--tool`` names the link that carries the tracker's reflector (default: the model's
``tracker.link``) or, for pose bags, the tool frame (default ``frames.tool``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ppoe_core.cli.checks import check_diagnose_inputs, float_range, int_range

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``diagnose`` options (docs/conventions.md section 6 plus ours)."""
    parser.add_argument("bags", nargs="+", metavar="BAG", help="contract bag directories (one robot)")
    parser.add_argument("--model", required=True, metavar="MODEL.yaml", help="model YAML of the bags' robot")
    parser.add_argument("--base", default=None, help="frame of /ground_truth/pose (default: frames.base)")
    parser.add_argument("--tool", default=None,
                        help="link carrying the tracker reflector, or tool frame of /ground_truth/pose")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="write diagnose.md/.json/.png and model_diagnosed.yaml here")
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    parser.add_argument("--test", nargs="+", default=[], metavar="TEST_BAG",
                        help="score the fitted model, unchanged, on these bags (JSON key 'test': rms, mean, "
                             "median, p95, max [m] and n per bag; stop roles scored by their protocol)")
    parser.add_argument("--accept-partial", action="store_true",
                        help="use what can be read of a damaged bag (default: refuse it, naming per topic "
                             "what was lost)")
    parser.add_argument("--cv", default="auto", choices=("auto", "stops", "groups"),
                        help="cross-validation: over stops, or leave-one-bag-out (auto: bags if >= 3)")
    parser.add_argument("--folds", type=int_range(2), default=5, help="folds of the stop-wise cross-validation")
    parser.add_argument("--min-gain", type=float_range(0.0, 1.0, max_open=True), default=0.03,
                        help="minimum relative held-out MSE reduction to accept an effect (default 0.03)")
    parser.add_argument("--min-t", type=float_range(0.0), default=4.0,
                        help="minimum paired t statistic of that reduction (default 4)")
    parser.add_argument("--max-effects", type=int_range(1), default=8, help="at most this many effects (default 8)")
    parser.add_argument("--measurement", default="auto", choices=("auto", "point", "pose"),
                        help="residuals of /ground_truth/point (auto: preferred) or /ground_truth/pose")
    parser.add_argument("--stationing-set", default="cross", choices=("cross", "square", "all"),
                        help="stationing set defining the registration in bags with /dataset/stop roles")
    parser.add_argument("--pixels", default="auto", choices=("auto", "on", "off"),
                        help="also diagnose tag pixels (auto: if the model has tags and a bag has tag "
                             "observations or images)")
    parser.add_argument("--joint", default="auto", choices=("auto", "on", "off"),
                        help="final joint tracker + pixel fit of the effects the stages chose plus every camera's "
                             "camera_extrinsics (auto: when the bags carry tracker points and tag pixels); JSON "
                             "key 'joint', held-out over poses")
    bar = parser.add_mutually_exclusive_group()
    bar.add_argument("--progress", dest="progress", action="store_true", default=None,
                     help="the running stage and time on stderr (default: only when stderr is a terminal)")
    bar.add_argument("--no-progress", dest="progress", action="store_false")
    bar.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    parser.add_argument("--pixel-sigma", type=float_range(0.0, min_open=True), default=None,
                        help="pixel noise 1-sigma per axis used to whiten tag residuals [px] "
                             "(default: the model's camera.pixel_sigma, else 1)")


def run(args: argparse.Namespace) -> int:
    """Diagnose, print and optionally write the report and the updated model; returns 0.

    The running stage and the time spent are shown on stderr (:class:`ppoe_core.io.progress.Ticker`) when it
    is a terminal, unless ``--quiet``."""
    from ppoe_core.io.progress import Ticker, progress_wanted

    with Ticker("diagnose", progress_wanted(args.quiet, args.progress)) as tick:
        return _run(args, tick)


def _run(args: argparse.Namespace, tick: Any) -> int:
    """:func:`run` with its progress ticker ``tick`` (``tick.stage(text)`` names each stage)."""
    from ppoe_core.analysis.diagnose import (
        DiagnoseOptions,
        Stops,
        diagnose,
        load_model,
        write_model_yaml,
        write_report,
    )
    from ppoe_core.cli.output import prepare_out_dir
    from ppoe_core.errors import BagError
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.urdf import parse_urdf

    check_diagnose_inputs(args)  # every bag before the fit: readable, not twice, one robot (cli/checks.py)
    if args.out:  # checked before the run, not after it
        prepare_out_dir(args.out)
    tick.stage(f"reading {len(args.bags)} bag(s)")
    urdf = read_bag(args.bags[0], topics=["/robot_description"], load_images=False).robot_description
    if not urdf:
        raise BagError(f"bag {args.bags[0]}: no /robot_description")
    robot = parse_urdf(urdf, text_source=f"bag {args.bags[0]} /robot_description")
    cfg, declared, pert, jnoise = load_model(args.model, robot)
    parts = [_stops(args, i, bag, robot, cfg) for i, bag in enumerate(args.bags)]
    stops = Stops.concat(parts)
    opts = DiagnoseOptions(folds=args.folds, cv=args.cv, min_gain=args.min_gain, min_t=args.min_t,
                           max_effects=args.max_effects,
                           imu_sigma={k: v.sigma for k, v in (getattr(cfg, "imus", None) or {}).items()} or None)
    tick.stage("fitting the effects")
    res = diagnose(robot, stops, declared, pert, jnoise, opts)
    tick.stage("tag pixels")
    pixels = _pixel_stage(args, res, robot, cfg, declared, pert, jnoise) if args.pixels != "off" else None
    tick.stage("joint fit")
    _joint_stage(args, res, robot, stops, pixels, declared)
    if args.test:
        tick.stage(f"scoring {len(args.test)} test bag(s)")
        _test_stage(args, res, robot, cfg, declared)
    paths = {}
    if args.out:
        tick.stage("writing the report")
        paths = write_report(res, args.out, title="ppoe diagnose " + " ".join(Path(b).name for b in args.bags))
        model_out = write_model_yaml(args.model, res, Path(args.out) / "model_diagnosed.yaml")
        calibrated = _write_calibrated(args, res, urdf, robot, declared)
        print("wrote " + ", ".join(str(p) for p in [*paths.values(), model_out, *calibrated]), file=sys.stderr)
    if args.json:
        json.dump(res.to_json(), sys.stdout)
        sys.stdout.write("\n")
    else:
        print(paths["md"].read_text() if paths else res.summary)
    return 0


def _stops(args: argparse.Namespace, i: int, bag: str, robot: Any, cfg: Any) -> Any:
    """The static stops of bag ``i`` (tracker reflector or ``--tool`` pose, frames from the model)."""
    from ppoe_core.analysis.diagnose import stops_from_bag

    tracker, frames = cfg.tracker, cfg.frames
    return stops_from_bag(
        bag, robot,
        tracker_link=args.tool or (tracker.link if tracker else None),
        tracker_xyz=tracker.xyz if (tracker and not args.tool) or (tracker and args.tool == tracker.link)
        else (0.0, 0.0, 0.0),
        tracker_sigma=tracker.sigma if tracker else 5e-4,
        base=args.base or (frames.base if frames else None),
        tool=args.tool or (frames.tool if frames else None),
        stationing_set=None if args.stationing_set == "all" else args.stationing_set,
        group_name=f"{i}:{Path(bag).name}", measurement=args.measurement, accept_partial=args.accept_partial,
        trackers=() if args.tool else tuple(getattr(cfg, "trackers", ()) or ()))


def _write_calibrated(args: argparse.Namespace, res: Any, urdf: str, robot: Any, declared: Any) -> list[Path]:
    """``robot_calibrated.urdf`` (declared and found static effects folded into the joint origins) and
    ``model_calibrated.yaml`` (the model without them) in ``--out``."""
    from ppoe_core.analysis.diagnose import write_model_yaml
    from ppoe_core.analysis.diagnose.calibrated_urdf import STATIC_EFFECTS, calibrated_urdf
    from ppoe_core.model.effects import effect_from_config

    found = [effect_from_config(e, robot, where=f"diagnose effect {e['name']}@{e['location']}") for e in res.effects]
    text, _ = calibrated_urdf(urdf, robot, [*declared, *found])
    urdf_out = Path(args.out) / "robot_calibrated.urdf"
    urdf_out.write_text(text, encoding="utf-8")
    model_out = write_model_yaml(args.model, res, Path(args.out) / "model_calibrated.yaml", drop=STATIC_EFFECTS)
    return [urdf_out, model_out]


def _test_stage(args: argparse.Namespace, res: Any, robot: Any, cfg: Any, declared: Any) -> None:
    """``--test``: each test bag scored with the fitted model (``res.extra["test"]``, keyed by bag name)."""
    from ppoe_core.analysis.diagnose.engine import append_test_summary
    from ppoe_core.analysis.diagnose.testing import check_same_robot, score_stops
    from ppoe_core.errors import BagError
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.urdf import parse_urdf

    test: dict[str, Any] = {}
    for k, bag in enumerate(args.test):
        urdf = read_bag(bag, topics=["/robot_description"], load_images=False).robot_description
        if not urdf:
            raise BagError(f"bag {bag}: no /robot_description")
        check_same_robot(robot, parse_urdf(urdf, text_source=f"bag {bag} /robot_description"), args.bags[0], bag)
        name = Path(bag).name if Path(bag).name not in test else f"{Path(bag).name}#{k}"
        stops = _stops(args, len(args.bags) + k, bag, robot, cfg)
        test[name] = score_stops(robot, stops, declared, res.chosen)
    res.extra["test"] = test
    append_test_summary(res)


def _joint_stage(args: argparse.Namespace, res: Any, robot: Any, stops: Any, pixels: Any, declared: Any) -> None:
    """``--joint auto|on``: the joint tracker + pixel fit into ``res`` (JSON key ``joint``) when there are tracker
    points and tag pixels (``on`` without both is an error)."""
    from ppoe_core.analysis.diagnose.joint_cv import add_joint_fit
    from ppoe_core.errors import BagError

    if args.joint == "off":
        return
    if pixels is None or stops.kind != "point":
        if args.joint == "on":
            raise BagError(f"--joint on needs tracker points and tag pixels; bags {args.bags} give "
                           f"{'pose' if stops.kind != 'point' else 'tracker'} measurements and "
                           f"{'no' if pixels is None else ''} tag pixels")
        return
    add_joint_fit(res, robot, stops, pixels, declared, folds=args.folds)


def _pixel_stage(args: argparse.Namespace, res: Any, robot: Any, cfg: Any, declared: Any, pert: Any,
                 jnoise: Any) -> Any:
    """Tag pixels of every bag with tags (``--pixels auto|on``) diagnosed into ``res``; returns them (or None)."""
    from ppoe_core.analysis.diagnose import add_pixel_diagnosis, concat_pixel_obs, pixels_from_bag
    from ppoe_core.errors import BagError
    from ppoe_core.io.bagio import bag_topics

    pix = []
    for bag in args.bags:
        topics = bag_topics(bag)
        has_tags = any(t == "/tag_bearing/observations" or t.startswith("/camera/image") for t in topics)
        if has_tags and cfg.tags is None and args.pixels == "auto":
            res.summary += (f"\nTag pixels of bag {bag} not diagnosed: model {args.model} has no 'tags' "
                            "section.")
        if cfg.tags is not None and has_tags:
            cam = getattr(cfg, "camera", None)
            sigma_px = args.pixel_sigma or (cam.pixel_sigma if cam is not None else 1.0)
            pix.append(pixels_from_bag(bag, robot, args.model, sigma_px=sigma_px,
                                       accept_partial=args.accept_partial))
        elif args.pixels == "on":
            raise BagError(f"bag {bag}: --pixels on, but no tag observations/images or no 'tags' in {args.model}")
    if not pix:
        return None
    obs = concat_pixel_obs(pix)
    add_pixel_diagnosis(res, robot, obs, declared, folds=args.folds, min_gain=args.min_gain, min_t=args.min_t,
                        pert=pert, jnoise=jnoise)
    return obs
