"""Solver choice of the diagnose engine: its own Gauss-Newton / LM with the nuisances eliminated (Schur) vs scipy
``least_squares`` vs a GTSAM factor graph, on the same whitened problem.

The engine's :meth:`~ppoe_core.analysis.diagnose.solver.Problem.refit` runs every confirmation step of the
selection; scipy (``trf``, analytic dense Jacobian) and GTSAM (Levenberg-Marquardt, one ``CustomFactor`` per robot
pose, ``Marginals``; skipped if ``gtsam`` does not import) solve the same residuals as one flat function
(``bench/solver_flat.py``, ``bench/solver_gtsam.py``).  Prints per solver the time, the final whitened cost
(``sum r^2``), the iterations, and the largest difference of the effect parameters from the engine's in units of
their standard deviation (and GTSAM's marginal sigmas against the engine's ``H^-1``).

Problems: the Motoman right arm 6x6x6 (tracker + two cameras; ``link_error@U1_dh``, both cameras' extrinsics and
``camera_intrinsics`` fx..cy) when ``$PPOE_DATASETS/motoman_leica`` is there, and the synthetic arm7 (tracker + one
camera, ``test/synthetic_arm7.py``).  Usage: ``python bench/bench_solver.py [--synthetic] [--repeat N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "bench", REPO / "test"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from solver_flat import FlatProblem  # noqa: E402

from ppoe_core.analysis.diagnose import DiagnoseOptions, Measurements, Problem  # noqa: E402
from ppoe_core.analysis.diagnose.engine import build_blocks  # noqa: E402
from ppoe_core.model.effects import make_effect  # noqa: E402
from ppoe_core.robot.tree import KinematicTree  # noqa: E402
from ppoe_core.robot.urdf import parse_urdf  # noqa: E402

DATA = Path(os.environ.get("PPOE_DATASETS", "/work/shared/datasets"))
CACHE = Path(os.environ.get("PPOE_BENCH_CACHE", "/tmp/ppoe_bench_diagnose"))


def synthetic() -> tuple[str, Problem, list[Any]]:
    from synthetic_arm7 import arm7_joint_data, arm7_truth

    robot = parse_urdf(REPO / "config" / "robots" / "arm7.urdf")
    truth = arm7_truth(robot)
    stops, obs = arm7_joint_data(robot, truth, n=40, seed=0)
    tree = KinematicTree(robot)
    blocks = build_blocks(tree, Measurements(stops=stops, pixels=obs), (), DiagnoseOptions())
    return "synthetic arm7", Problem(blocks), [e.with_params(np.zeros(e.n_params)) for e in truth]


def motoman() -> tuple[str, Problem, list[Any]]:
    from ppoe_core.analysis.diagnose.files import LoadOptions, load_measurements, read_robot
    from ppoe_core.analysis.diagnose.report import load_model
    from ppoe_ros.cli import main

    d = DATA / "motoman_leica"
    bag = CACHE / "motoman_666"
    if not bag.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        with contextlib.redirect_stdout(io.StringIO()):
            main(["import", "motoman", str(d / "leica_right_hand_6x6x6_dataset.mat"), "--model-yaml",
                  str(d / "model.yaml"), "--out", str(bag)])
    model = f"{bag}.model.yaml"
    _, robot = read_robot(bag)
    cfg, declared, pert, jnoise = load_model(model, robot)
    data = load_measurements([bag], robot, cfg, LoadOptions(), model)
    tree = KinematicTree(robot)
    blocks = build_blocks(tree, data, declared, DiagnoseOptions())
    effects = [make_effect("link_error", "U1_dh", tree)]
    for b in blocks:
        for joint, frame in b.camera_mounts().items():
            effects.append(make_effect("camera_extrinsics", joint, tree))
            effects.append(make_effect("camera_intrinsics", frame, tree, components=("fx", "fy", "cx", "cy")))
    return "motoman 6x6x6", Problem(blocks, declared, pert, jnoise), effects


def best_time(fn: Any, repeat: int) -> tuple[float, Any]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def compare(label: str, problem: Problem, effects: list[Any], repeat: int) -> None:
    from scipy.optimize import least_squares

    flat = FlatProblem(problem, effects)
    x0 = flat.x0()
    print(f"problem: {label}, {flat.residuals(x0).size} residuals, {x0.size} unknowns ({flat.P} effect parameters, "
          f"{flat.K} nuisance)")

    def engine() -> Any:
        for b, st in zip(problem.blocks, flat.start):
            b.set_nuisance_state(st)
        return problem.refit(effects, max_iterations=50)

    t, fit = best_time(engine, repeat)
    theta = np.concatenate([e.params for e in fit.effects])
    H = problem.system(fit.effects, fit.effects, rewhiten=False).full().H
    sd = np.sqrt(np.diag(np.linalg.pinv(H)))
    print(f"  engine Gauss-Newton/LM (Schur): {t:.3f} s, cost {fit.cost:.8g}, iterations {fit.iterations}")
    t, sol = best_time(lambda: least_squares(flat.residuals, x0, jac=flat.jacobian, method="trf", xtol=1e-12,
                                             ftol=1e-12, gtol=1e-12, max_nfev=200), repeat)
    dz = np.max(np.abs(sol.x[:flat.P] - theta) / sd)
    print(f"  scipy least_squares trf: {t:.3f} s, cost {2 * sol.cost:.8g}, nfev {sol.nfev}, "
          f"max |theta - engine| / sigma {dz:.2e}")
    try:
        import gtsam  # noqa: F401
    except ImportError:
        print("  gtsam: not importable, skipped")
        return
    from solver_gtsam import solve_gtsam

    t, g = best_time(lambda: solve_gtsam(flat), repeat)
    dz = np.max(np.abs(g["x"][:flat.P] - theta) / sd)
    ratio = np.sqrt(np.diag(g["cov_theta"])) / sd
    print(f"  gtsam LM + Marginals: {t:.3f} s, cost {2 * g['cost']:.8g}, iterations {g['iterations']}, "
          f"max |theta - engine| / sigma {dz:.2e}, marginal sigma / engine's in [{ratio.min():.4f}, "
          f"{ratio.max():.4f}]")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--synthetic", action="store_true", help="only the synthetic arm7 problem")
    ap.add_argument("--repeat", type=int, default=1, help="solves per solver (best time printed)")
    args = ap.parse_args()
    compare(*synthetic(), args.repeat)
    if not args.synthetic and (DATA / "motoman_leica").exists():
        compare(*motoman(), args.repeat)


if __name__ == "__main__":
    main()
