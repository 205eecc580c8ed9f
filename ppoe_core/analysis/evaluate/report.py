"""Reports of ``ppoe evaluate``: markdown table, JSON and plots."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.evaluate.metrics import METHODS
from ppoe_core.analysis.evaluate.options import Evaluation

# ----------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------

_LABELS = {"fk": "forward kinematics", "ppoe": "fused, PPOE covariance", "naive": "fused, naive covariance",
           "recorded": "recorded estimate (--estimate)"}


def _fmt_mm(st: dict[str, Any]) -> str:
    if not st or st.get("n", 0) == 0:
        return "-"
    extra = (f", median {1e3 * st['median']:.2f}, p95 {1e3 * st['p95']:.2f}" if "median" in st else "")
    return (f"{1e3 * st['mean']:.2f} ± {1e3 * st['std']:.2f} (rms {1e3 * st['rms']:.2f}{extra}, "
            f"max {1e3 * st['max']:.2f})")


def _fmt_deg(st: dict[str, Any] | None) -> str:
    if not st or st.get("n", 0) == 0:
        return "-"
    return f"{math.degrees(st['mean']):.3f} ± {math.degrees(st['std']):.3f} (max {math.degrees(st['max']):.3f})"


def markdown_report(ev: Evaluation) -> str:
    """The markdown report (errors in mm and degrees)."""
    s = ev.summary
    gt = s["ground_truth"]
    lines = [
        f"# ppoe evaluate: `{s['bag']}`",
        "",
        f"- model: `{s['model']}`, state `T_{s['base']}_{s['tool']}`",
        f"- joint states: {s['joint_states']} over {s['bag_duration_s']:.1f} s; "
        f"values held from the previous message: {s['joint_values_held']}; joint states that could not be "
        "completed (split publishers, a joint not yet seen or older than 0.5 s): "
        f"{s.get('joint_states_incomplete', 0)}",
        f"- ground truth: `{gt['topic']}`, {gt['samples']} samples, {gt['without_prior']} without a prior",
    ]
    if "registration" in gt:
        r = gt["registration"]
        lines.append(
            f"- tracker-to-base registration: {r['method']}; {len(r['groups'])} group(s), "
            f"{sum(g['fit'] for g in r['groups'])} fit / {sum(g['scored'] for g in r['groups'])} scored samples, "
            f"{r['unscored']} not scored"
        )
    lines += _measurement_lines(s["measurements"])
    if "fusion" in s:
        lines.append(f"- {s['fusion']}")
    lines += [
        "",
        "Errors in mm (mean ± std, rms, median, p95, max) and degrees; lateral = perpendicular to the tool z axis.",
        "",
        "| method | n | 3D position [mm] | lateral [mm] | rotation [deg] | NEES mean (dof, 95% bounds) |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in ev.table_rows():
        ne = r["nees"]
        lines.append(
            f"| {_LABELS[name]} | {r['position_3d']['n']} | {_fmt_mm(r['position_3d'])} | {_fmt_mm(r['lateral'])} | "
            f"{_fmt_deg(r.get('rotation'))} | {ne['mean']:.3g} "
            f"({ne['dof']}, {ne['bounds95'][0]:.2f}-{ne['bounds95'][1]:.2f}) |"
        )
    fused = [(n, r) for n, r in ev.table_rows() if "measurements" in r]
    if fused:
        lines += [
            "",
            "| method | accepted | rejected | stale | no prior | bad | NIS mean / dim |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in fused:
            c = r["measurements"]["counts"]
            lines.append(
                f"| {_LABELS[name]} | {c['accepted']} | {c['rejected']} | {c['dropped_stale']} | "
                f"{c['dropped_no_prior']} | {c['bad']} | {r['nis']['mean_per_dim']:.3g} |"
            )
    lines.append("")
    return "\n".join(lines)


def write_tum(ev: Evaluation, out: Path) -> list[Path]:
    """``trajectory_ground_truth.tum`` and ``trajectory_<method>.tum`` (TUM format for evo: ``stamp x y z qx qy qz
    qw`` per scored sample, base frame; with tracker points the positions of the reflector and identity rotations)."""
    from ppoe_core import lie

    written = []
    stamps = ev.samples.get("stamp")
    names = [("ground_truth", "gt_T")] + [(m, f"{m}_T") for m in METHODS]
    for name, key in names:
        T = ev.samples.get(key)
        if stamps is None or T is None or len(T) == 0:
            continue
        q = lie.quat_from_matrix(T[:, :3, :3])
        rows = np.column_stack([stamps, T[:, :3, 3], q])
        path = out / f"trajectory_{name}.tum"
        np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")
        written.append(path)
    return written


def write_report(ev: Evaluation, out_dir: str | Path) -> list[Path]:
    """Write ``evaluation.md``, ``evaluation.json``, ``errors.png`` and the TUM trajectories (:func:`write_tum`)
    into ``out_dir``.

    Returns the written paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "evaluation.md", out / "evaluation.json", out / "errors.png"]
    paths[0].write_text(markdown_report(ev))
    paths[1].write_text(json.dumps(ev.to_dict(), indent=2, allow_nan=False) + "\n")
    paths += write_tum(ev, out)
    plot_errors(ev, paths[2])
    return paths


#: colours of the methods in the plots (ground truth black)
_COLORS = {"fk": "tab:orange", "ppoe": "tab:blue", "naive": "tab:green", "recorded": "tab:purple"}


def plot_errors(ev: Evaluation, path: Path) -> None:
    """``errors.png``: each error metric and the NEES against time since the first scored sample (left), and the
    trajectory of the ground truth and of every method seen from the top (x-y) and the side (x-z) in the base frame
    (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [k for k in ("position_3d", "lateral", "rotation") if f"fk_{k}" in ev.samples]
    rows = len(metrics) + 1
    fig = plt.figure(figsize=(13, 2.4 * rows + 0.4))
    grid = fig.add_gridspec(rows, 2, width_ratios=(1.9, 1.0))
    stamps = np.asarray(ev.samples.get("stamp", []), dtype=float)
    t = stamps - stamps[0] if stamps.size else stamps
    axes = [fig.add_subplot(grid[i, 0]) for i in range(rows)]
    for ax in axes[1:]:
        ax.sharex(axes[0])
    _plot_metrics(ev, axes, metrics, t)
    half = max(1, rows // 2)
    top = fig.add_subplot(grid[:half, 1])
    side = fig.add_subplot(grid[half:, 1])
    _plot_trajectory(ev, top, (0, 1), "top view")
    _plot_trajectory(ev, side, (0, 2), "side view")
    fig.suptitle(f"ppoe evaluate: {Path(str(ev.summary.get('bag', ''))).name}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_metrics(ev: Evaluation, axes: list, metrics: list[str], t: np.ndarray) -> None:
    """The error metrics and the NEES (with its 95 % band) of every method against time ``t`` [s]."""
    import scipy.stats

    for ax, k in zip(axes, metrics):
        scale, unit = (math.degrees(1), "deg") if k == "rotation" else (1e3, "mm")
        for name in METHODS:
            if f"{name}_{k}" in ev.samples:
                ax.plot(t, scale * ev.samples[f"{name}_{k}"], ".-", ms=3, lw=0.6, color=_COLORS[name],
                        label=_LABELS[name])
        ax.set_ylabel(f"{k.replace('_', ' ')} [{unit}]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    ax = axes[-1]
    for name in METHODS:
        if f"{name}_nees" in ev.samples:
            ax.semilogy(t, ev.samples[f"{name}_nees"], ".", ms=3, color=_COLORS[name], label=_LABELS[name])
    dof = ev.summary["methods"]["fk"]["nees"]["dof"]
    for q in (0.025, 0.975):
        ax.axhline(float(scipy.stats.chi2.ppf(q, dof)), color="grey", lw=0.8, ls="--")
    ax.set_ylabel(f"NEES ({dof} dof; 95 % band)")
    ax.set_xlabel("time since the first scored sample [s]")
    ax.grid(alpha=0.3)


def _plot_trajectory(ev: Evaluation, ax: Any, axes_xyz: tuple[int, int], title: str) -> None:
    """Positions of the ground truth and of every method [m] on two base-frame axes (equal scale)."""
    names = "xyz"
    tracks = [("ground truth", "gt_T", "black")] + [(_LABELS[m], f"{m}_T", _COLORS[m]) for m in METHODS]
    for label, key, color in tracks:
        T = ev.samples.get(key)
        if T is None or len(T) == 0:
            continue
        p = np.asarray(T)[:, :3, 3]
        style = dict(ls="-", lw=0.5, ms=3, alpha=0.9) if key == "gt_T" else dict(ls="none", ms=2.5, alpha=0.8)
        ax.plot(p[:, axes_xyz[0]], p[:, axes_xyz[1]], marker=".", color=color, label=label, **style)
    ax.set_xlabel(f"{names[axes_xyz[0]]} [m]")
    ax.set_ylabel(f"{names[axes_xyz[1]]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{title} ({ev.summary.get('base', 'base')} frame)", fontsize=9)
    ax.grid(alpha=0.3)
    if axes_xyz == (0, 1):
        ax.legend(fontsize=7)


def _measurement_lines(m: dict) -> list[str]:
    """Report lines on the measurements used: tags, contact planes, the wrench contact detector."""
    lines: list[str] = []
    lines.append(
        f"- measurements: {m['total']} ({m.get('tag_messages', 0)} tag messages, {m.get('tag_points', 0)} tag points, "
        f"{m.get('contact_planes', 0)} contact planes)"
    )
    if m.get("contact_source") == "/wrench":
        w = m["wrench"]
        lines.append(
            f"- contact planes from `/wrench` through the contact detector (enter {m['force_threshold']:g} N, "
            f"release {m['release_threshold']:g} N): {w['received']} wrenches, {w['contacts']} contacts, "
            f"{w['bad']} bad"
        )
    if m.get("wrench_without_contact_config"):
        lines.append(f"- {m['wrench_without_contact_config']} `/wrench` messages not used: the model YAML has no "
                     "`contact` section")
    return lines
