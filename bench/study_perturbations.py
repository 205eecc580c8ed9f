"""Study of the learned perturbation covariances (docs/covariance.md): prints the numbers the doc quotes.

    PYTHONPATH=$PWD python bench/study_perturbations.py sim        # simulated 5-joint arm, large held-out set
    PPOE_DATASETS=../shared/datasets PYTHONPATH=$PWD python bench/study_perturbations.py hilti motoman

``sim``: the arm of ``test/perturbation_sim.py`` (true covariances differ per joint and axis: j2 5x softer
perpendicular to its axis, j3 3x about it), learned on ``--train`` poses, checked on ``--test`` fresh poses for the
three choices (declared, one global scale, learned) and the truth.
``hilti`` / ``motoman``: ``diagnose(..., learn_perturbations=True)`` on the shared measured datasets with a
user-style declared prior (``--declared-rot`` rad on every movable joint's rotation, no translation): the
cross-fitted held-out check of the three choices (learned_prior.py).  Nothing derived from the datasets is written.
"""

from __future__ import annotations

import argparse
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", nargs="+", choices=("sim", "hilti", "motoman"))
    ap.add_argument("--train", type=int, default=4000)
    ap.add_argument("--test", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--declared-rot", type=float, default=2e-3)
    args = ap.parse_args()
    root = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets"))
    for w in args.what:
        if w == "sim":
            study_sim(args.train, args.test, args.seed)
        elif w == "hilti":
            study_hilti(root, args.declared_rot)
        else:
            study_motoman(root, args.declared_rot)


if __name__ == "__main__":
    main()
