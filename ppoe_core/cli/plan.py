"""``ppoe plan``: choose the calibration poses before the robot moves (D-optimal, docs/plan.md).

::

    ppoe plan --urdf ROBOT.urdf --model MODEL.yaml --effects EFFECTS.yaml|NAME@LOCATION[comp,...] ... --n N
              --out DIR [--candidates 2000] [--seed 0] [--margin 0.05] [--region JOINT=LO:HI ...]
              [--box XMIN YMIN ZMIN XMAX YMAX ZMAX] [--clearance 0.01] [--tracker-at X Y Z]
              [--camera-info CAMERA_INFO.yaml --min-tags 1 --max-view-angle 60]
              [--dwell 1.0 --max-speed 0.5 --min-move 1.0] [--given BAG ...] [--json]

Writes ``DIR/poses.csv`` (``ppoe fk --batch`` format, ``trajectory.stops_csv`` of ``ppoe simulate``),
``DIR/trajectory.yaml`` (``trajectory_msgs/JointTrajectory``), ``DIR/plan.json`` (predicted 95 % half-widths of
every target parameter, predicted held-out error, Sun and Hollerbach's O1..O5 and the condition number, for the plan
and for ``n`` and ``4 n`` random feasible poses) and ``DIR/plan.png``.  The measurements planned for are the model's
``trackers`` (reflectors); the effects vocabulary is ``ppoe diagnose --effects``'s.  Bad input (an effect at a
location the URDF lacks, fewer poses than parameters, an empty feasible set, ...) is a :class:`PpoeError` naming
it: exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.cli.checks import float_range, int_range

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``ppoe plan`` options to ``parser``."""
    parser.add_argument("--urdf", required=True, metavar="URDF", help="robot description (URDF file)")
    parser.add_argument("--model", required=True, metavar="MODEL.yaml", help="model YAML (trackers, declared effects)")
    parser.add_argument("--effects", nargs="+", required=True, metavar="NAME@LOCATION",
                        help="target effects: NAME@LOCATION[comp,...] specs or YAML files with an 'effects' list "
                             "(the ppoe diagnose --effects vocabulary)")
    parser.add_argument("--n", type=int_range(1), required=True, help="number of poses to plan")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--candidates", type=int_range(10), default=2000,
                        help="random feasible configurations to choose from (default 2000)")
    parser.add_argument("--seed", type=int_range(0), default=0, help="RNG seed (default 0)")
    parser.add_argument("--criterion", choices=("d", "minimax"), default="d",
                        help="d (default): D-optimal (log det); minimax: then exchanges lowering the worst CI relative "
                             "to 4N random poses' with the D-efficiency kept >= 0.9 (docs/plan.md)")
    parser.add_argument("--margin", type=float_range(0.0), default=0.05,
                        help="distance kept from every joint limit [rad or m] (default 0.05)")
    parser.add_argument("--region", nargs="+", default=[], metavar="JOINT=LO:HI",
                        help="sample these joints only inside [LO, HI] [rad or m]")
    parser.add_argument("--box", nargs=6, type=float, default=None, metavar="V",
                        help="workspace box XMIN YMIN ZMIN XMAX YMAX ZMAX of every reflector (root frame) [m]")
    parser.add_argument("--clearance", type=float_range(0.0), default=0.01,
                        help="extra distance between collision capsules [m] (default 0.01)")
    parser.add_argument("--tracker-at", nargs=3, type=float, default=None, metavar="V",
                        help="tracker position (root frame) [m]: check the line of sight to every reflector")
    parser.add_argument("--camera-info", default=None, metavar="YAML",
                        help="ROS camera_info YAML of the model's camera: at least --min-tags tags in view")
    parser.add_argument("--min-tags", type=int_range(1), default=1, help="tags in view with --camera-info")
    parser.add_argument("--pixels", choices=("design", "constraint"), default="design",
                        help="with --camera-info: the tag pixels count in the design (camera pose a nuisance; "
                             "default) or only constrain the poses")
    parser.add_argument("--max-view-angle", type=float_range(0.0, 90.0), default=60.0,
                        help="largest angle between a tag's normal and the line of sight [deg] (default 60)")
    parser.add_argument("--dwell", type=float_range(0.0), default=1.0, help="time at each pose [s] (default 1)")
    parser.add_argument("--max-speed", type=float_range(0.0, min_open=True), default=0.5,
                        help="joint speed of the moves [rad/s or m/s] (default 0.5)")
    parser.add_argument("--min-move", type=float_range(0.0), default=1.0, help="shortest move [s] (default 1)")
    parser.add_argument("--given", nargs="+", default=[], metavar="BAG",
                        help="bags already recorded: plan the poses that add most to them")
    parser.add_argument("--json", action="store_true", help="print plan.json on stdout")


def _region(items: list[str]) -> dict[str, tuple[float, float]]:
    from ppoe_core.errors import PpoeError

    out = {}
    for it in items:
        name, _, rng = it.partition("=")
        lo, _, hi = rng.partition(":")
        try:
            out[name] = (float(lo), float(hi))
        except ValueError:
            raise PpoeError(f"--region {it!r}: expected JOINT=LO:HI with numbers") from None
    return out


def _camera(path: str, model: Any) -> Any:
    """The :class:`CameraView` of ``--camera-info`` (ROS camera_info YAML) on the model's camera frame."""
    import yaml

    from ppoe_core.analysis.plan.constraints import CameraView
    from ppoe_core.errors import PpoeError

    if model.camera is None or model.tags is None:
        raise PpoeError(f"--camera-info {path}: the model has no camera and tags sections")
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
        K = np.array(doc["camera_matrix"]["data"], dtype=float).reshape(3, 3)
        D = np.zeros(5)
        d = np.array((doc.get("distortion_coefficients") or {}).get("data") or [], dtype=float)
        D[:min(5, d.size)] = d[:5]
        return CameraView(model.camera.frame, K, D, int(doc["image_width"]), int(doc["image_height"]))
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise PpoeError(f"--camera-info {path}: not a camera_info YAML ({type(exc).__name__}: {exc})") from None


def constraints_of(args: argparse.Namespace, model: Any) -> Any:
    """The :class:`Constraints` of the parsed arguments (collision capsules from the ``--urdf`` file)."""
    from ppoe_core.analysis.plan.constraints import Constraints, collision_capsules

    caps, meshes = collision_capsules(Path(args.urdf).read_text(encoding="utf-8"))
    box = (np.array(args.box[:3]), np.array(args.box[3:])) if args.box else None
    return Constraints(margin=args.margin, region=_region(args.region), box=box, capsules=caps,
                       skipped_meshes=meshes, clearance=args.clearance,
                       tracker_at=np.array(args.tracker_at) if args.tracker_at else None,
                       camera=_camera(args.camera_info, model) if args.camera_info else None,
                       tags=model.tags.items if (args.camera_info and model.tags) else (), min_tags=args.min_tags,
                       max_view_angle=args.max_view_angle,
                       points=[(t.link, np.asarray(t.xyz, dtype=float)) for t in model.trackers])


def run(args: argparse.Namespace) -> int:
    """Run ``ppoe plan``; returns the exit code."""
    from ppoe_core.analysis.diagnose.engine import declared_specs
    from ppoe_core.analysis.diagnose.load_stops import stops_from_bag
    from ppoe_core.analysis.plan.information import given_information, target_effects
    from ppoe_core.analysis.plan.outputs import design_table, write_outputs
    from ppoe_core.analysis.plan.planner import PlanOptions, plan
    from ppoe_core.errors import PpoeError
    from ppoe_core.model.effects import effect_from_config
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    if not Path(args.urdf).is_file():
        raise PpoeError(f"--urdf {args.urdf}: no such file")
    robot = parse_urdf(args.urdf)
    model = load_model_config(args.model, robot)
    if not model.trackers:
        raise PpoeError(f"--model {args.model}: declares no tracker (trackers:); ppoe plan designs for tracker "
                        "reflectors")
    tree = KinematicTree(robot)
    declared = [effect_from_config(e, tree, f"{args.model}: effects[{i}]") for i, e in enumerate(model.effects)]
    chain = list(dict.fromkeys(j for t in model.trackers for j in robot.path_from_root(t.link)))
    targets = target_effects(tree, [(d.name, d.location, d.components) for d in declared_specs(args.effects)], chain)
    given = None
    if args.given:
        from ppoe_core.analysis.diagnose.stops import Stops
        stops = Stops.concat([stops_from_bag(b, robot, trackers=model.trackers, group_name=f"{i}:{Path(b).name}")
                              for i, b in enumerate(args.given)])
        given = given_information(tree, stops, targets, declared)
    result = plan(tree, model.trackers, targets, constraints_of(args, model),
                  PlanOptions(n=args.n, candidates=args.candidates, seed=args.seed,
                              minimax=args.criterion == "minimax",
                              pixel_sigma=model.camera.pixel_sigma if (model.camera and args.camera_info
                                                                       and args.pixels == "design") else None),
                  declared, given)
    doc = write_outputs(Path(args.out), result, args.dwell, args.max_speed, args.min_move,
                        {"urdf": str(args.urdf), "model": str(args.model), "given": list(args.given)})
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(f"wrote {args.out}/poses.csv, trajectory.yaml, plan.json" + (", plan.png" if doc["plot"] else "")
              + f": {args.n} poses, {len(result.names)} parameters, condition number "
              f"{result.planned.indices['condition_number']:.3g}; predicted 95 % half-widths [rad or m]:")
        print("\n".join(design_table(doc)))
    return 0
