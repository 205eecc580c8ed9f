"""Study of the learned perturbation covariances (docs/covariance.md): prints the numbers the doc quotes.

    PYTHONPATH=$PWD python bench/study_perturbations.py sim        # simulated 5-joint arm, large held-out set
    PPOE_DATASETS=../shared/datasets PYTHONPATH=$PWD python bench/study_perturbations.py hilti motoman

``sim``: the arm of ``test/perturbation_sim.py`` (true covariances differ per joint and axis: j2 5x softer
perpendicular to its axis, j3 3x about it), learned on ``--train`` poses, checked on ``--test`` fresh poses for the
three choices (declared, one global scale, learned) and the truth.
``fusion``: simulated rover bags (config/robots/rover.*) whose true perturbations differ from the declared
rover_model.yaml per joint and axis (:data:`ROVER_TRUTH`): a calibration bag with 6D ground-truth poses is
diagnosed twice (plain: one global scale; ``--learn-perturbations``: learned), then a camera-tag bag of the same
true robot is replayed with ``ppoe evaluate --perturbations`` for the declared / global / learned choices and the
truth.  Bags
go to a temporary directory (``--keep DIR`` to keep them).
``hilti`` / ``motoman``: ``diagnose(..., learn_perturbations=True)`` on the shared measured datasets with a
user-style declared prior (``--declared-rot`` rad on every movable joint's rotation, no translation): the
cross-fitted held-out check of the three choices (learned_prior.py).  Nothing derived from the datasets is written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))


def _table(checks: dict) -> None:
    print(f"  {'choice':14s} {'NEES':>7s} {'cov68':>6s} {'cov95':>6s} {'cov99':>6s} {'worst axis err':>14s} "
          f"{'loglik/row':>11s}  NEES per principal axis (small->large) | per size region")
    for k, c in checks.items():
        cv = c.coverage
        print(f"  {k:14s} {c.nees:7.3f} {100 * cv['0.68']:6.1f} {100 * cv['0.95']:6.1f} {100 * cv['0.99']:6.1f} "
              f"{100 * c.worst_coverage_error():13.1f}% {c.loglik:11.4g}  "
              + " ".join(f"{v:.2f}" for v in c.nees_per_axis) + " | "
              + " ".join(f"{v:.2f}" for v in c.nees_per_region))


def study_sim(n_train: int, n_test: int, seed: int) -> None:
    from perturbation_sim import DECLARED, TRUTH, sigma_matrices, simulate_poses, soft5

    from ppoe_core.analysis.diagnose.block_pose import PoseBlock
    from ppoe_core.analysis.diagnose.covariance_check import compare_choices
    from ppoe_core.analysis.diagnose.noise import estimate_scales
    from ppoe_core.analysis.diagnose.perturbations import component_matrices, joint_axes, learn_perturbations
    from ppoe_core.robot.tree import KinematicTree

    robot = soft5()
    tree = KinematicTree(robot)
    truth, declared = sigma_matrices(robot, TRUTH), sigma_matrices(robot, DECLARED)
    train = PoseBlock(tree, simulate_poses(robot, truth, n_train, seed))
    test = PoseBlock(tree, simulate_poses(robot, truth, n_test, seed + 1))
    axes = joint_axes(tree)
    t0 = time.process_time()
    lin = train.linearise([], (), declared, {})
    fit = learn_perturbations(lin.r, lin.S, component_matrices(train, [], axes))
    cpu = time.process_time() - t0
    g = estimate_scales(lin.r, lin.S, lin.Q)
    print(f"sim: {n_train} training / {n_test} held-out 6D poses, seed {seed}; learned in {cpu:.1f} s CPU")
    for c in fit.components:
        true = sorted({TRUTH[j][cls] for j, cls in c.members})
        lo, hi = np.sqrt(c.ci)
        print(f"  {c.name:32s} sigma {c.sigma:.5f}  95% CI [{lo:.5f}, {hi:.5f}]  truth {true}")
    print(f"  removed: {fit.removed}; sensor scale {fit.sensor_scale:.3g}; global scale of the declared prior "
          f"{g.k:.3g} (sensor {g.a:.3g})")
    lu = test.linearise([], (), declared, {})
    ll = test.linearise([], (), fit.covariances(axes), {})
    lt = test.linearise([], (), truth, {})
    _table(compare_choices(lu.r, {"declared": lu.S + lu.Q, "global_scale": g.a ** 2 * lu.S + g.k ** 2 * lu.Q,
                                  "learned": fit.sensor_scale ** 2 * ll.S + ll.Q, "truth": lt.S + lt.Q},
                           reference="learned"))


def _declared(robot, rot: float) -> dict:
    return {j: np.diag([0.0, 0.0, 0.0, rot ** 2, rot ** 2, rot ** 2]) for j, jt in robot.joints.items()
            if jt.movable}


def study_hilti(root: Path, rot: float) -> None:
    from ppoe_core.analysis.diagnose import DiagnoseOptions, Stops, diagnose
    from ppoe_core.cli.datasets import stops_from_hilti
    from ppoe_core.robot.urdf import parse_urdf

    d = root / "hilti_stationing"
    robot = parse_urdf(d / "trailblazer.urdf")
    files = ["flat", "pallet", "orthogonal_wood", "wood_left_track", "diagonal_wood"]
    stops = Stops.concat([stops_from_hilti(d / f"{f}.yaml", robot) for f in files])
    t0 = time.process_time()
    res = diagnose(robot, stops, perturbation_cov=_declared(robot, rot),
                   options=DiagnoseOptions(cv="groups", learn_perturbations=True))
    print(f"hilti (5 files, leave-one-file-out effects; declared {rot * 1e3:g} mrad per joint): "
          f"{time.process_time() - t0:.1f} s CPU; effects {[e.name + '@' + e.location for e in res.effects]}")
    _learned(res)


def study_motoman(root: Path, rot: float) -> None:
    from ppoe_core.analysis.diagnose import DiagnoseOptions, diagnose
    from ppoe_core.cli.datasets import stops_from_motoman
    from ppoe_core.robot.urdf import parse_urdf

    d = root / "motoman_leica"
    robot = parse_urdf(d / "motoman_right.urdf")
    stops = stops_from_motoman(d / "leica_right_hand_6x6x6_dataset.mat", robot)
    t0 = time.process_time()
    res = diagnose(robot, stops, perturbation_cov=_declared(robot, rot),
                   options=DiagnoseOptions(learn_perturbations=True))
    print(f"motoman right arm 6x6x6 (declared {rot * 1e3:g} mrad per joint): {time.process_time() - t0:.1f} s CPU; "
          f"effects {[e.name + '@' + e.location for e in res.effects]}")
    _learned(res)


def _learned(res) -> None:
    lp = res.learned_prior
    if lp is None:
        print("  no tracker / pose block")
        return
    print(f"  {lp.block}: {res.metric.n} rows; held-out RMS {1e3 * res.residual_after:.3f} mm; check split "
          f"{lp.split}; global scale (engine) {res.sigma_scale:.3g}")
    for c in lp.fit.components:
        lo, hi = np.sqrt(c.ci)
        print(f"  {c.name:48s} sigma {c.sigma:.3g}  95% CI [{lo:.3g}, {hi:.3g}]")
    print(f"  sensor scale {lp.fit.sensor_scale:.3g} CI {tuple(round(v, 3) for v in lp.fit.sensor_ci)}")
    _table(lp.check)


#: the rover's true perturbations, 1-sigma per axis class [rad / m] (declared: 0.5 deg about all three axes on every
#: arm joint): arm_joint_2 five times softer perpendicular to its axis, arm_joint_3 and arm_joint_5 stiff about
#: theirs, arm_joint_6 twice as soft about its axis; the mount plate as declared
ROVER_TRUTH = {"arm_joint_1": {"axial": 0.00873, "lateral": 0.00873},
               "arm_joint_2": {"axial": 0.00873, "lateral": 0.0436},
               "arm_joint_3": {"axial": 0.0015, "lateral": 0.00873},
               "arm_joint_4": {"axial": 0.00873, "lateral": 0.00873},
               "arm_joint_5": {"axial": 0.0015, "lateral": 0.00873},
               "arm_joint_6": {"axial": 0.0175, "lateral": 0.00873}}
AROUND = ("{pan_joint: -2.97, tilt_joint: 0.65, arm_joint_1: 0.37, arm_joint_2: -0.54, arm_joint_3: 1.93, "
          "arm_joint_4: -0.72, arm_joint_5: 1.39, arm_joint_6: 0.0}")
SCENARIO = """robot: {{urdf: {urdf}, model: {model}}}
seed: {seed}
truth: {{perturbations: per_stop, joint_noise: true, effects: []}}
trajectory:
  joint_rate: 50.0
  dwell: {dwell}
  settle: 0.1
  move_time: 0.4
  start: {around}
  random_stops:
    count: {count}
    around: {around}
    spread: {spread}
    min_visible_tags: {tags}
{camera}ground_truth:
  pose: {{frame: base_link, target: tool_link, sigma_xyz: 0.0001, sigma_rot: 0.0002, rate: 0.0}}
"""
CAMERA = """camera:
  width: 640
  height: 480
  intrinsics: [600.0, 600.0, 320.0, 240.0]
  D: [-0.05, 0.02, 0.0, 0.0, 0.0]
  rate: 2.0
  during: stops
  format: png
  noise_sigma: 1.0
"""


def _cli(args: list[str]) -> str:
    import contextlib
    import io

    from ppoe_ros.cli import main as ppoe

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = ppoe(args)
    if rc != 0:
        raise SystemExit(f"ppoe {' '.join(args)} failed ({rc})")
    return out.getvalue()


def study_fusion(work: Path, n_calib: int, n_fusion: int, seed: int) -> None:
    from ruamel.yaml import YAML

    from ppoe_core.analysis.diagnose.perturbations import axis_projectors
    from ppoe_core.robot.urdf import parse_urdf

    cfg = REPO / "config" / "robots"
    robot = parse_urdf(cfg / "rover.urdf")
    yaml = YAML()
    model = yaml.load((cfg / "rover_model.yaml").read_text())
    for jn, per in ROVER_TRUTH.items():
        P = axis_projectors(robot.joints[jn].axis)
        C = per["axial"] ** 2 * P["axial"] + per["lateral"] ** 2 * P["lateral"]
        model["perturbations"][jn] = {"covariance": [[float(v) for v in row] for row in C]}
    truth_model = work / "rover_truth_model.yaml"
    with open(truth_model, "w") as fh:
        yaml.dump(model, fh)
    spread = ("{arm_joint_1: 0.6, arm_joint_2: 0.4, arm_joint_3: 0.4, arm_joint_4: 0.9, arm_joint_5: 0.6, "
              "arm_joint_6: 1.5}")
    common = {"urdf": cfg / "rover.urdf", "model": truth_model, "around": AROUND, "spread": spread}
    (work / "calib.yaml").write_text(SCENARIO.format(seed=seed, dwell=0.3, count=n_calib, tags=0, camera="",
                                                     **common))
    (work / "fusion.yaml").write_text(SCENARIO.format(seed=seed + 1, dwell=1.1, count=n_fusion, tags=1,
                                                      camera=CAMERA, **common))
    t0 = time.time()
    for name in ("calib", "fusion"):
        _cli(["simulate", str(work / f"{name}.yaml"), "--out", str(work / name), "--force"])
    print(f"fusion study: bags simulated in {time.time() - t0:.0f} s ({n_calib} calibration stops with 6D poses, "
          f"{n_fusion} camera-tag stops), in {work}")
    declared = cfg / "rover_model.yaml"
    for label, extra in (("global", []), ("learned", ["--learn-perturbations"])):
        doc = json.loads(_cli(["diagnose", str(work / "calib"), "--model", str(declared), "--measurement", "pose",
                               "--json", "--quiet", "--out", str(work / f"diag_{label}"), *extra]))
        print(f"  diagnose ({label}): effects {[e['name'] + '@' + e['location'] for e in doc['effects']]}, "
              f"global scale {doc['sigma_scale']:.3g}")
        if label == "learned":
            lp = doc["learned_perturbations"]
            for c in lp["components"]:
                print(f"    {'+'.join(c['joints'])}/{c['axis']}: sigma {c['sigma']:.4g} CI "
                      f"[{c['sigma_ci'][0]:.4g}, {c['sigma_ci'][1]:.4g}]")
            print(f"    sensor scale {lp['sensor_scale']:.3g}")
            _table_json(lp["check"])
    print(_cli(["evaluate", str(work / "fusion"), "--model", str(declared), "--quiet", "--perturbations",
                str(work / "diag_global" / "model_diagnosed.yaml"),
                str(work / "diag_learned" / "model_diagnosed.yaml"), str(truth_model)]))


def _table_json(check: dict) -> None:
    for k, c in check.items():
        cv = c["coverage"]
        print(f"    {k:14s} NEES {c['nees']:.3f} coverage {100 * cv['0.68']:.1f}/{100 * cv['0.95']:.1f}/"
              f"{100 * cv['0.99']:.1f} % per axis " + " ".join(f"{v:.2f}" for v in c["nees_per_axis"])
              + f" loglik/row {c['loglik_per_row']:.4g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", nargs="+", choices=("sim", "hilti", "motoman", "fusion"))
    ap.add_argument("--calib", type=int, default=300, help="fusion: calibration stops")
    ap.add_argument("--fusion", type=int, default=40, help="fusion: camera-tag stops")
    ap.add_argument("--keep", default=None, metavar="DIR", help="fusion: keep the bags here")
    ap.add_argument("--train", type=int, default=4000)
    ap.add_argument("--test", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--declared-rot", type=float, default=2e-3)
    args = ap.parse_args()
    root = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets"))
    for w in args.what:
        if w == "sim":
            study_sim(args.train, args.test, args.seed)
        elif w == "fusion":
            if args.keep:
                Path(args.keep).mkdir(parents=True, exist_ok=True)
                study_fusion(Path(args.keep), args.calib, args.fusion, args.seed)
            else:
                import tempfile

                with tempfile.TemporaryDirectory(prefix="ppoe_fusion_study_") as tmp:
                    study_fusion(Path(tmp), args.calib, args.fusion, args.seed)
        elif w == "hilti":
            study_hilti(root, args.declared_rot)
        else:
            study_motoman(root, args.declared_rot)


if __name__ == "__main__":
    main()
