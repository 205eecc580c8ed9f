"""``ppoe plan``'s Must-show (issue 26), measured: plan, simulate, diagnose, compare.

Per robot study (:data:`STUDIES`: the 6-axis arm cobot6 (tracker; with the side camera and tags too), the
19-joint elastic humanoid19 with a marker on each hand, the prismatic-stage robot lift5 of ``test/data/plan``):
``ppoe plan`` chooses N poses for the study's target effects; N and 4N random feasible poses are drawn from the same
constraints (uniform); each pose set becomes a bag (``ppoe simulate``, the study's truth = the target effects,
``trajectory.stops_csv``) and is diagnosed with the declared set (``ppoe diagnose --effects``; with the camera also
its pose, the plan's nuisance).  Printed per target parameter: the predicted 95 % half-width of the plan, the
achieved ones (planned, random N, random 4N; mean over ``--repeats`` bags, each with its own noise and, for random
sets, its own draw) and the ratios planned / random 4N (Must-show: <= 1), predicted / achieved (Must-show:
within 20 %) and the information bound / predicted random 4N (``plan.json`` ``information_bound``: above 1, no N
poses of the pool can be as tight as 4N random ones for that parameter).

``--timing``: planning 30 poses for the 6-axis arm (6 target parameters, 2000 candidates) on one core, with the
same-run baseline of drawing 30 random feasible poses and scoring them (their predicted CIs).

Usage: ``python bench/bench_plan.py [--only cobot6 ...] [--repeats 2] [--criterion d|minimax] [--timing]
[--json OUT]``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import yaml  # noqa: E402

DATA = REPO / "test" / "data" / "plan"
WORK = Path(os.environ.get("PPOE_PLAN_CACHE", "/tmp/ppoe_plan_bench"))


@dataclass
class Study:
    """One robot: DH table, model, base scenario (truth + tracker), target effects, N, extra ``ppoe plan`` args."""

    name: str
    dh: Path
    model: Path
    base: Path
    effects: Path
    n: int
    plan_args: list[str] = field(default_factory=list)
    diagnose_effects: list[str] = field(default_factory=list)  #: fitted besides the targets (the plan's nuisances)


STUDIES = {
    "cobot6": Study("cobot6", REPO / "config/robots/cobot6_dh.yaml", REPO / "config/robots/cobot6_model.yaml",
                    DATA / "_cobot6.yaml", DATA / "cobot6_effects.yaml", 12,
                    ["--region", "shoulder_pan=-0.5:0.5", "shoulder_lift=-1.6:-1.0", "elbow=1.0:1.8",
                     "wrist_1=-2.0:-1.2", "--box", "-2", "-2", "0.85", "2", "2", "3"]),
    "humanoid19": Study("humanoid19", REPO / "config/robots/humanoid19_dh.yaml",
                        REPO / "config/robots/humanoid19_model.yaml", DATA / "_humanoid19.yaml",
                        DATA / "humanoid19_effects.yaml", 16, []),
    # the 6-axis arm with the camera and tags: pixels in the design (camera pose a nuisance: diagnosed with it)
    "cobot6_camera": Study("cobot6_camera", REPO / "config/robots/cobot6_dh.yaml",
                           REPO / "config/robots/cobot6_model.yaml", DATA / "_cobot6_camera.yaml",
                           DATA / "cobot6_effects.yaml", 12,
                           ["--region", "shoulder_pan=-1.9:-0.5", "--camera-info", str(DATA / "camera_info.yaml"),
                            "--max-view-angle", "55"], ["camera_extrinsics@camera_joint"]),
    # the pair random poses cannot separate: an elbow offset and the elbow's gravity compliance in a narrow workspace
    "cobot6_pair": Study("cobot6_pair", REPO / "config/robots/cobot6_dh.yaml",
                         REPO / "config/robots/cobot6_model.yaml", DATA / "_cobot6_pair.yaml",
                         DATA / "cobot6_pair_effects.yaml", 12,
                         ["--region", "shoulder_pan=-0.3:0.3", "shoulder_lift=-1.5:-1.2", "elbow=1.3:1.7",
                          "wrist_1=-1.8:-1.4"]),
    "lift5": Study("lift5", DATA / "lift5_dh.yaml", DATA / "lift5_model.yaml", DATA / "_lift5.yaml",
                   DATA / "lift5_effects.yaml", 12, ["--box", "-3", "-3", "0.3", "3", "3", "3"]),
}


def ppoe(argv: list[str]) -> str:
    """``ppoe ARGV`` in this process; its stdout (raises on a non-zero exit)."""
    from ppoe_ros.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    if rc != 0:
        raise RuntimeError(f"ppoe {' '.join(argv)} exited {rc}: {err.getvalue()[-2000:]}")
    return out.getvalue()


def urdf_of(study: Study, work: Path) -> Path:
    out = work / f"{study.name}.urdf"
    if not out.is_file():
        ppoe(["urdf", "from-dh", str(study.dh), "--out", str(out), "--force"])
    return out


#: ``ppoe plan --criterion`` of the studies (``--criterion`` of this script)
CRITERION = ["d"]


def plan_of(study: Study, work: Path, seed: int = 0) -> tuple[Path, dict[str, Any], float]:
    """``ppoe plan`` of a study (:data:`CRITERION`): its output directory, ``plan.json`` and the time [s]."""
    out = work / "plan"
    t0 = time.perf_counter()
    doc = json.loads(ppoe(["plan", "--urdf", str(urdf_of(study, work)), "--model", str(study.model), "--effects",
                           str(study.effects), "--n", str(study.n), "--out", str(out), "--seed", str(seed),
                           "--json", "--criterion", CRITERION[0], *study.plan_args]))
    return out, doc, time.perf_counter() - t0


def random_csv(study: Study, work: Path, n: int, seed: int) -> Path:
    """``n`` random feasible poses (uniform, the study's constraints) as a ``poses.csv``."""
    from ppoe_core.analysis.plan.constraints import sample_candidates
    from ppoe_core.analysis.plan.outputs import write_csv
    from ppoe_core.cli.plan import add_arguments, constraints_of
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    urdf = urdf_of(study, work)
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--urdf", str(urdf), "--model", str(study.model), "--effects", "x", "--n", "1", "--out",
                         "x", *study.plan_args])
    robot = parse_urdf(str(urdf))
    tree = KinematicTree(robot)
    q, _ = sample_candidates(tree, constraints_of(args, load_model_config(str(study.model), robot)), n,
                             np.random.default_rng(seed))
    out = work / f"random_{n}_{seed}.csv"
    write_csv(out, q)
    return out


def achieved(study: Study, work: Path, csv: Path, seed: int, tag: str) -> dict[str, tuple[float, float]]:
    """Simulate the poses ``csv`` with the study's truth (noise seed ``seed``), diagnose with ``--effects``: the
    estimate and the achieved 95 % half-width of every parameter (``name@location:parameter``; missing when the
    diagnosis left it out)."""
    from ppoe_core.sim.simulate import simulate

    scen = work / f"{tag}.yaml"
    scen.write_text(yaml.safe_dump({"extends": str(study.base), "seed": seed,
                                    "trajectory": {"stops_csv": str(csv)}}), encoding="utf-8")
    bag = work / f"{tag}_bag"
    simulate(scen, bag, overwrite=True)
    doc = json.loads(ppoe(["diagnose", str(bag), "--model", str(study.model), "--effects", str(study.effects),
                           *study.diagnose_effects, "--json", "--quiet"]))
    out: dict[str, tuple[float, float]] = {}
    for e in doc.get("effects") or []:
        for p, (lo, hi) in (e.get("ci") or {}).items():
            out[f"{e['name']}@{e['location']}:{p}"] = (float(e["parameters"][p]), (float(hi) - float(lo)) / 2.0)
    return out


def run_study(study: Study, repeats: int = 2, sets: tuple[str, ...] = ("planned", "random_n", "random_4n"),
              work: Path = WORK) -> dict[str, Any]:
    """One study (module docstring): per parameter the predicted and achieved half-widths (mean over ``repeats``
    bags of each pose set in ``sets``), the achieved estimates (``values``: the last bag's) and the ratios."""
    work = work / study.name
    work.mkdir(parents=True, exist_ok=True)
    plan_dir, doc, dt = plan_of(study, work)
    names = doc["parameters"]
    got: dict[str, list[dict[str, Any]]] = {k: [] for k in sets}
    sizes = {"random_n": study.n, "random_4n": 4 * study.n}
    for r in range(repeats):
        for k, key in enumerate(sets):
            csv = plan_dir / "poses.csv" if key == "planned" else random_csv(study, work, sizes[key], 200 + 10 * r + k)
            got[key].append(achieved(study, work, csv, 100 + 10 * r + k, f"{key}_{r}"))

    def mean(k: str, p: str) -> float:
        v = [d.get(p, (float("nan"), float("inf")))[1] for d in got.get(k, [])]
        return float(np.mean(v)) if v else float("nan")

    rows = {p: {"predicted": doc["planned"]["ci95"][p], "predicted_random_4n": doc["random_4n"]["ci95"][p],
                "bound_over_random_4n": doc["information_bound"]["over_random_4n"][p],
                **{k: mean(k, p) for k in ("planned", "random_n", "random_4n")},
                "values": {k: got[k][-1].get(p, (float("nan"), float("inf")))[0] for k in sets}}
            for p in names}
    for r in rows.values():
        r["planned_over_random_4n"] = r["planned"] / r["random_4n"]
        r["predicted_over_achieved"] = r["predicted"] / r["planned"]
    return {"robot": study.name, "n": study.n, "plan_seconds": dt, "repeats": repeats, "parameters": rows,
            "indices": doc["planned"]["indices"], "indices_random_n": doc["random_n"]["indices"]}


def print_study(res: dict[str, Any]) -> None:
    n = res["n"]
    print(f"\n== {res['robot']}: N = {n} planned vs {n} and {4 * n} random feasible poses "
          f"(mean of {res['repeats']} bags each; plan {res['plan_seconds']:.1f} s)")
    print(f"{'parameter':48s} {'pred':>9s} {'planned':>9s} {'rand N':>9s} {'rand 4N':>9s} {'pl/4N':>6s} "
          f"{'pred/ach':>8s} {'bnd/4N':>6s}")
    for p, r in res["parameters"].items():
        print(f"{p:48s} {r['predicted']:9.3g} {r['planned']:9.3g} {r['random_n']:9.3g} {r['random_4n']:9.3g} "
              f"{r['planned_over_random_4n']:6.2f} {r['predicted_over_achieved']:8.2f} "
              f"{r['bound_over_random_4n']:6.2f}")
    ind, rnd = res["indices"], res["indices_random_n"]
    print("indices planned:  " + " ".join(f"{k}={v:.3g}" for k, v in ind.items()))
    print("indices random N: " + " ".join(f"{k}={v:.3g}" for k, v in rnd.items()))


def timing(work: Path = WORK) -> dict[str, float]:
    """Planning 30 poses for the 6-axis arm (6 target parameters) vs drawing and scoring 30 random poses."""
    from ppoe_core.analysis.plan.constraints import Constraints, sample_candidates
    from ppoe_core.analysis.plan.information import pose_information, target_effects
    from ppoe_core.analysis.plan.planner import PlanOptions, plan, predict
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    study = STUDIES["cobot6"]
    work.mkdir(parents=True, exist_ok=True)
    robot = parse_urdf(str(urdf_of(study, work)))
    model = load_model_config(str(study.model), robot)
    tree = KinematicTree(robot)
    targets = target_effects(tree, [("joint_offset", j, []) for j in ("shoulder_lift", "elbow", "wrist_1",
                                                                          "wrist_2")]
                             + [("gravity_compliance", "shoulder_lift", []), ("gravity_compliance", "elbow", [])])
    c = Constraints(points=[(t.link, t.xyz) for t in model.trackers])
    pose_information(tree, model.trackers, sample_candidates(tree, c, 50, np.random.default_rng(9))[0], targets)
    t0 = time.perf_counter()
    plan(tree, model.trackers, targets, c, PlanOptions(n=30, candidates=2000))
    t_plan = time.perf_counter() - t0
    t0 = time.perf_counter()
    plan(tree, model.trackers, targets, c, PlanOptions(n=30, candidates=2000, minimax=True))
    t_minimax = time.perf_counter() - t0
    t0 = time.perf_counter()
    q, _ = sample_candidates(tree, c, 30, np.random.default_rng(1))
    info = pose_information(tree, model.trackers, q, targets)
    predict(info, np.arange(30))
    t_rand = time.perf_counter() - t0
    return {"plan_30_seconds": t_plan, "plan_30_minimax_seconds": t_minimax, "random_30_seconds": t_rand,
            "ratio": t_plan / t_rand}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", default=list(STUDIES), choices=list(STUDIES))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--timing", action="store_true", help="only the timing line")
    ap.add_argument("--json", default=None)
    ap.add_argument("--criterion", choices=("d", "minimax"), default="d", help="ppoe plan --criterion")
    a = ap.parse_args(argv)
    CRITERION[0] = a.criterion
    out: dict[str, Any] = {}
    if a.timing:
        t = timing()
        print(f"plan 30 poses, 6-axis arm, 6 parameters, 2000 candidates: {t['plan_30_seconds']:.2f} s "
              f"(target <= 10 s); baseline 30 random feasible poses drawn and scored: {t['random_30_seconds']:.3f} s;"
              f" ratio {t['ratio']:.1f}; with --criterion minimax {t['plan_30_minimax_seconds']:.2f} s")
        out["timing"] = t
    else:
        for name in a.only:
            res = run_study(STUDIES[name], a.repeats)
            print_study(res)
            out[name] = res
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
