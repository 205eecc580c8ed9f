"""Solver choice for the joint tracker + pixel fit: scipy ``least_squares`` vs a GTSAM factor graph.

The same problem (:class:`ppoe_core.analysis.diagnose.joint_fit.JointProblem`, plain least squares, the
declared sensor noise) is solved by ``scipy.optimize.least_squares`` (``trf``, analytic dense Jacobian) and,
if ``gtsam`` imports, by GTSAM Levenberg-Marquardt (:mod:`ppoe_core.analysis.diagnose.joint_gtsam`,
``CustomFactor`` per residual block, ``Marginals``).  Prints the time and final cost of each, the largest
parameter difference in units of the parameter sigma, and the ratio of the marginal sigmas.

Problem: the Motoman 6x6x6 file (right arm, tracker + both cameras; effects ``link_error@U1_dh``, the two
cameras' ``camera_extrinsics``) if ``$PPOE_DATASETS/motoman_leica`` exists (or ``--synthetic``), else the
synthetic arm7 one (:mod:`ppoe_core.analysis.diagnose.joint_synthetic`).  Usage:
``python bench/bench_solver.py [--synthetic] [--repeat N]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ppoe_core.analysis.diagnose.joint_fit import JointProblem  # noqa: E402
from ppoe_core.robot.tree import KinematicTree  # noqa: E402
from ppoe_core.robot.urdf import parse_urdf  # noqa: E402


def problem(synthetic: bool) -> tuple[str, JointProblem]:
    """The bench problem (label, JointProblem at zero effects)."""
    from ppoe_core.model.effects import make_effect

    d = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets")) / "motoman_leica"
    if not synthetic and d.exists():
        from ppoe_core.analysis.diagnose import pixel_candidates
        from ppoe_core.cli.datasets import pixels_from_motoman, stops_from_motoman

        robot = parse_urdf(d / "motoman_right.urdf")
        tree = KinematicTree(robot)
        f = d / "leica_right_hand_6x6x6_dataset.mat"
        stops, obs = stops_from_motoman(f, robot), pixels_from_motoman(f, robot, d / "model.yaml")
        effects = [make_effect("link_error", "U1_dh", tree),
                   *[e for e in pixel_candidates(robot, obs) if e.name == "camera_extrinsics"]]
        return "motoman 6x6x6", JointProblem(tree, effects, stops, obs)
    from ppoe_core.analysis.diagnose.joint_synthetic import arm7_joint_data, arm7_truth

    robot = parse_urdf(REPO / "config" / "robots" / "arm7.urdf")
    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth, n=40, seed=0)
    return "synthetic arm7", JointProblem(KinematicTree(robot), [e.with_params(np.zeros(e.n_params)) for e in truth],
                                          stops, obs)


def main() -> None:
    from scipy.optimize import least_squares

    ap = argparse.ArgumentParser()
    ap.add_argument("--synthetic", action="store_true", help="the synthetic arm7 problem even with the dataset")
    ap.add_argument("--repeat", type=int, default=1, help="solves per solver (best time printed)")
    args = ap.parse_args()
    label, prob = problem(args.synthetic)
    x0 = prob.x0()
    print(f"problem: {label}, {prob.residuals(x0).size} residuals, {x0.size} unknowns "
          f"({prob.P} effect parameters, {len(prob.sessions)} registrations)")
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        sol = least_squares(prob.residuals, x0, jac=prob.jacobian, method="trf", x_scale=1.0, xtol=1e-12,
                            ftol=1e-12, gtol=1e-12, max_nfev=200)
        times.append(time.perf_counter() - t0)
    J = prob.jacobian(sol.x)
    cov = np.linalg.pinv(J.T @ J)[:prob.P, :prob.P]
    print(f"scipy least_squares trf: {min(times):.3f} s, cost {sol.cost:.6g}, nfev {sol.nfev}, njev {sol.njev}")
    try:
        import gtsam  # noqa: F401
    except ImportError:
        print("gtsam: not importable, comparison skipped")
        return
    from ppoe_core.analysis.diagnose.joint_gtsam import solve_gtsam

    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        g = solve_gtsam(prob, x0)
        times.append(time.perf_counter() - t0)
    sig = np.sqrt(np.diag(cov))
    dz = np.abs(g["x"][:prob.P] - sol.x[:prob.P]) / sig
    ratio = np.sqrt(np.diag(g["cov_theta"])) / sig
    print(f"gtsam LM + Marginals: {min(times):.3f} s, cost {g['cost']:.6g}, iterations {g['iterations']}")
    print(f"agreement: max |theta_gtsam - theta_scipy| / sigma = {dz.max():.2e}; marginal sigma ratio "
          f"gtsam / scipy in [{ratio.min():.4f}, {ratio.max():.4f}]; "
          f"{'AGREE' if dz.max() < 1e-2 and np.allclose(ratio, 1.0, atol=1e-3) else 'DISAGREE'}")


if __name__ == "__main__":
    main()
