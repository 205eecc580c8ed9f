"""What ``ppoe plan`` writes: ``poses.csv``, ``trajectory.yaml``, ``plan.json`` and ``plan.png``.

* ``poses.csv``: header = the independent joint names, one planned configuration per row in execution order
  [rad or m] (the ``ppoe fk --batch`` format; ``trajectory.stops_csv`` of a ``ppoe simulate`` scenario).
* ``trajectory.yaml``: a ``trajectory_msgs/JointTrajectory`` (the message's fields as YAML) a controller can execute,
  stop and go: per pose an arrival point and a departure point ``dwell`` seconds later, zero velocities and
  accelerations at both; a move between poses takes ``max(min_move, largest joint move / max_speed)``.
* ``plan.json``: :func:`~ppoe_core.analysis.plan.planner.summary` plus the poses.
* ``plan.png``: the predicted 95 % half-widths of every target parameter, planned vs ``n`` and ``4 n`` random
  feasible poses, relative to the planned ones (log scale); needs matplotlib (skipped without it).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ppoe_core.analysis.plan.planner import PlanResult, summary

__all__ = ["write_csv", "trajectory_message", "write_outputs", "plot_plan", "compare_planned", "planned_lines",
           "design_table"]


def write_csv(path: Path, q: Mapping[str, np.ndarray]) -> None:
    """``poses.csv`` (module docstring)."""
    names = list(q)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(names)
        for row in np.stack([np.asarray(q[j], dtype=float) for j in names], axis=1):
            w.writerow([repr(float(v)) for v in row])


def _duration(t: float) -> dict[str, int]:
    sec = int(math.floor(t))
    return {"sec": sec, "nanosec": int(round((t - sec) * 1e9))}


def trajectory_message(q: Mapping[str, np.ndarray], dwell: float, max_speed: float, min_move: float,
                       frame_id: str = "") -> dict[str, Any]:
    """The ``trajectory_msgs/JointTrajectory`` of the poses ``q`` (module docstring) as a plain mapping."""
    names = list(q)
    Q = np.stack([np.asarray(q[j], dtype=float) for j in names], axis=1)
    zero = [0.0] * len(names)
    points, t = [], 0.0
    for k, row in enumerate(Q):
        if k:
            t += max(min_move, float(np.max(np.abs(row - Q[k - 1]))) / max_speed)
        for when in (t, t + dwell):
            points.append({"positions": [float(v) for v in row], "velocities": zero, "accelerations": zero,
                           "effort": [], "time_from_start": _duration(when)})
        t += dwell
    return {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": frame_id}, "joint_names": names,
            "points": points}


def plot_plan(path: Path, result: PlanResult) -> bool:
    """``plan.png`` (module docstring); False (nothing written) without matplotlib."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    names = result.names
    base = result.planned.ci95
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(names) + 2), 4.5))
    n = int(result.design.chosen.size)
    for k, (label, ci) in enumerate(((f"planned ({n})", base), (f"random ({n})", result.random_n.ci95),
                                     (f"random ({4 * n})", result.random_4n.ci95))):
        ax.bar(x + (k - 1) * 0.27, ci / np.maximum(base, 1e-300), width=0.27, label=label)
    ax.set_yscale("log")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("predicted 95 % half-width / planned")
    ax.set_title("ppoe plan: predicted confidence intervals (lower is better)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return True


def write_outputs(out: Path, result: PlanResult, dwell: float, max_speed: float, min_move: float,
                  extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write every output into the directory ``out`` (created); returns the ``plan.json`` document."""
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "poses.csv", result.q)
    msg = trajectory_message(result.q, dwell, max_speed, min_move)
    (out / "trajectory.yaml").write_text(
        f"# trajectory_msgs/JointTrajectory made by ppoe plan: stop and go, dwell {dwell:.3f} s per pose\n"
        + yaml.safe_dump(msg, sort_keys=False), encoding="utf-8")
    doc = {**summary(result), **(extra or {}),
           "poses": {j: [float(v) for v in a] for j, a in result.q.items()}}
    (out / "plan.json").write_text(json.dumps(doc, indent=1), encoding="utf-8")
    doc["plot"] = plot_plan(out / "plan.png", result)
    return doc


def compare_planned(diagnosed: Mapping[str, Any], plan_json: str | Path) -> dict[str, dict[str, float | None]]:
    """Per planned parameter (``name@location:parameter``): the planned 95 % half-width of ``plan_json`` (``ppoe
    plan``'s ``plan.json``), the achieved one of the diagnosis JSON ``diagnosed`` (``ppoe diagnose``'s effects'
    ``ci``; None when the diagnosis does not report it) and achieved / planned (``ppoe diagnose --planned``).

    Raises
    ------
    PpoeError
        ``plan_json`` unreadable or not a plan.
    """
    from ppoe_core.errors import PpoeError

    try:
        plan = json.loads(Path(plan_json).read_text(encoding="utf-8"))
        planned = {str(k): float(v) for k, v in plan["planned"]["ci95"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise PpoeError(f"--planned {plan_json}: not a ppoe plan plan.json ({type(exc).__name__}: {exc})") from None
    got: dict[str, float] = {}
    for e in diagnosed.get("effects") or []:
        for p, ci in (e.get("ci") or {}).items():
            got[f"{e['name']}@{e['location']}:{p}"] = (float(ci[1]) - float(ci[0])) / 2.0
    return {k: {"planned": v, "achieved": got.get(k), "ratio": got[k] / v if k in got and v > 0 else None}
            for k, v in planned.items()}


def planned_lines(cmp: Mapping[str, Mapping[str, float | None]]) -> list[str]:
    """The text table of :func:`compare_planned`."""
    out = ["", "Planned (ppoe plan) vs achieved 95 % half-widths:"]
    for k, r in cmp.items():
        a, q = r["achieved"], r["ratio"]
        out.append(f"  {k:50s} planned {r['planned']:.3g}  achieved " + (f"{a:.3g}  ratio {q:.2f}" if a is not None
                                                                          and q is not None else "not reported"))
    return out


def design_table(doc: Mapping[str, Any]) -> list[str]:
    """The text table ``ppoe plan`` prints from its ``plan.json`` document ``doc``: per target parameter the
    predicted 95 % half-width of the planned poses, of as many and of four times as many random feasible poses
    (medians of the draws), and the planned / 4 n random ratio; then the predicted held-out error of each."""
    n = int(doc["n"])
    head = f"| parameter | planned ({n}) | {n} random | {4 * n} random | planned / {4 * n} random |"
    out = [head, "|---|---|---|---|---|"]
    planned, one, four = (doc[k]["ci95"] for k in ("planned", "random_n", "random_4n"))
    for k, v in planned.items():
        out.append(f"| {k} | {v:.3g} | {one[k]:.3g} | {four[k]:.3g} | {v / four[k]:.2f} |")
    rms = [doc[k]["heldout_rms"] for k in ("planned", "random_n", "random_4n")]
    out.append(f"| predicted held-out error [m] | {rms[0]:.3g} | {rms[1]:.3g} | {rms[2]:.3g} | |")
    return out
