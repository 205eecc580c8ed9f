"""The result of ``ppoe evaluate --online`` and its report: ``online.json``, the markdown table with the drift
monitor's section, ``online_parameters.png`` (each tracked parameter with its 3-sigma band and the truth, the
monitor's statistic per source next to them, the tool error per method) and ``model_online.yaml``."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.evaluate.metrics import error_stats, rotation_errors
from ppoe_core.errors import ModelConfigError
from ppoe_core.estimation.online_effects import replace_effects
from ppoe_core.robot.yaml_io import read_yaml_file
from ppoe_core.sim.schedule import truth_values

__all__ = ["ONLINE_METHODS", "OnlineEvaluation", "build_evaluation", "markdown_online", "write_online_report"]

ONLINE_METHODS = ("before", "static", "online", "fresh")


@dataclass
class OnlineEvaluation:
    """Result of :func:`~ppoe_core.analysis.evaluate.online.evaluate_online`: the parameter trace, the scored tool
    errors, the drift monitor's events and statistic.

    ``labels`` are the state's labels at the end (an effect the monitor added appears from its step on: ``theta``
    and ``sigma`` are NaN before)."""

    bag: str
    labels: list[str]
    stamps: np.ndarray                      # (K,) stamps of the parameter trace [s] (after each update)
    theta: np.ndarray                       # (K, P) estimate
    sigma: np.ndarray                       # (K, P) 1-sigma
    truth: dict[str, np.ndarray] | None     # label -> (K,) true value at the trace stamps
    gt_stamps: np.ndarray                   # (N,)
    position_error: dict[str, np.ndarray]   # method -> (N,) [m]
    rotation_error: dict[str, np.ndarray]   # method -> (N,) [rad]
    counts: dict[str, int] = field(default_factory=dict)
    model_effects: list[dict[str, Any]] = field(default_factory=list)
    drift: list[dict[str, Any]] = field(default_factory=list)
    monitor: dict[str, Any] = field(default_factory=dict)
    significance: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)   # (K,) source of each step
    nis: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def to_dict(self) -> dict[str, Any]:
        """JSON numbers: tool error per method (all, first half, second half), parameter summary, counts, the drift
        monitor (test, events, false-alarm bound), the drift's significance (with a truth)."""
        half = self.gt_stamps[0] + 0.5 * (self.gt_stamps[-1] - self.gt_stamps[0]) if len(self.gt_stamps) else 0.0
        second = self.gt_stamps > half
        tool = {m: {"position": error_stats(e), "position_first_half": error_stats(e[~second]),
                    "position_second_half": error_stats(e[second]), "rotation": error_stats(self.rotation_error[m])}
                for m, e in self.position_error.items()}
        params: dict[str, Any] = {}
        for i, lab in enumerate(self.labels):
            ok = np.isfinite(self.theta[:, i]) if len(self.stamps) else np.zeros(0, bool)
            d: dict[str, Any] = {"final": float(self.theta[-1, i]) if ok.any() else None,
                                 "final_sigma": float(self.sigma[-1, i]) if ok.any() else None}
            if self.truth is not None and lab in self.truth and ok.any():
                err = self.theta[ok, i] - self.truth[lab][ok]
                d["error"] = error_stats(np.abs(err))
                d["coverage_3sigma"] = float(np.mean(np.abs(err) <= 3 * self.sigma[ok, i]))
            params[lab] = d
        sig = None
        if self.significance is not None:
            sig = {k: v for k, v in self.significance.items() if k != "delta"}
        return {"bag": self.bag, "tool_error": tool, "parameters": params, "counts": dict(self.counts),
                "effects": self.model_effects, "drift": {"events": self.drift, **self.monitor},
                "significance": sig, "notes": self.notes}


def build_evaluation(bag: str, filt: Any, inputs: Any, monitor: Any, rep: Any, scored: Mapping[str, Any],
                     truth: Mapping[str, Any] | None, sig: dict[str, Any] | None) -> OnlineEvaluation:
    """The evaluation from the replay (:mod:`ppoe_core.analysis.evaluate.online`)."""
    labels = filt.labels
    K, P = len(rep.thetas), len(labels)
    theta, sigma = np.full((K, P), np.nan), np.full((K, P), np.nan)
    for k, (labs, th, sg) in enumerate(rep.thetas):
        idx = [labels.index(lab) for lab in labs]
        theta[k, idx], sigma[k, idx] = th, sg
    st = np.array([s.stamp_ns * 1e-9 for s in rep.steps])
    Tgt = np.asarray(scored["Tgt"], float).reshape(-1, 4, 4)
    pos, rot = {}, {}
    for m, Ts in scored["T"].items():
        if Ts:
            T = np.asarray(Ts)
            pos[m] = np.linalg.norm(T[:, :3, 3] - Tgt[:, :3, 3], axis=1)
            rot[m] = rotation_errors(T, Tgt)
    tv = None
    if truth is not None:
        allv = truth_values(truth, st)
        tv = {lab: allv.get(lab, np.zeros_like(st)) for lab in labels}
    nis = np.array([s.update.nis for s in rep.steps])
    c, fc = inputs.counts, filt.counts
    counts = {"updates": fc.updates, **{f"updates_{k}": v for k, v in sorted(fc.by_kind.items())},
              "jumps": fc.jumps, "temperatures_used": fc.temperatures, "ground_truth_poses": int(len(Tgt)),
              "skipped_waiting_for_temperature": fc.waiting_for_temperature,
              "skipped_no_joint_state": c.no_joints, "unknown_tag_points": c.unknown_tag_points,
              "camera_info_changed": c.camera_info_changed, "tags_seen_twice": c.tags_seen_twice,
              "temperature_stale": c.temperature_stale, "nis_above_99pct": int(np.sum(_above_99(rep.steps))),
              "bad": c.bad, **dict(sorted(c.extra.items()))}
    mon: dict[str, Any] = {"enabled": monitor is not None}
    if monitor is not None:
        s = monitor.settings
        mon.update(window=s.window, false_alarm=s.false_alarm, name_window=s.name_window, add_named=s.add_named,
                   tests=monitor.tests, alarms=len(monitor.events),
                   false_alarm_bound=s.false_alarm * monitor.tests,
                   trace=[{"stamp": t, "source": src, "statistic": a, "threshold": b}
                          for t, src, a, b in monitor.trace])
    notes = [n for _, n in inputs.notes][:50]
    return OnlineEvaluation(bag, labels, st, theta, sigma, tv, np.asarray(scored["stamps"], float), pos, rot, counts,
                            filt.effect_entries(), [e.to_dict() for e in (monitor.events if monitor else [])], mon,
                            sig, notes, [s.row.source for s in rep.steps], nis)


def _above_99(steps: list[Any]) -> np.ndarray:
    from scipy.stats import chi2

    return np.array([s.update.nis > chi2.ppf(0.99, s.update.dim) for s in steps], dtype=bool)


def write_online_report(ev: OnlineEvaluation, out_dir: str | Path, model_yaml: str | Path | None = None
                        ) -> list[Path]:
    """``online.json`` and ``online_parameters.png`` in ``out_dir``; with ``model_yaml`` (the diagnosed model) also
    ``model_online.yaml``: that model with the tracked effects at their final estimate (with ``ci``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "online.json", out / "online_parameters.png"]
    paths[0].write_text(json.dumps(ev.to_dict(), indent=1, allow_nan=False, default=_json_default))
    if model_yaml is not None:
        paths.append(_write_model(ev, Path(model_yaml), out / "model_online.yaml"))
    _plot(ev, paths[1])
    return paths


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(f"not JSON: {type(x).__name__}")


def _plot(ev: OnlineEvaluation, path: Path) -> None:
    """Parameters (estimate, 3-sigma band, truth), the monitor's statistic per source (window NIS over its alarm
    threshold, alarms marked), the tool position error per method; one shared time axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = len(ev.labels)
    trace = ev.monitor.get("trace") or []
    rows = P + 1 + (1 if trace else 0)
    fig, axes = plt.subplots(rows, 1, figsize=(8, 2.1 * rows), squeeze=False, sharex=True)
    t0 = ev.gt_stamps[0] if len(ev.gt_stamps) else (ev.stamps[0] if len(ev.stamps) else 0.0)
    for i, (ax, lab) in enumerate(zip(axes[:P, 0], ev.labels)):
        x, m, s = ev.stamps - t0, ev.theta[:, i], ev.sigma[:, i]
        ax.fill_between(x, m - 3 * s, m + 3 * s, color="C0", alpha=0.25, label="online +-3 sigma")
        ax.plot(x, m, "C0", label="online")
        if ev.truth is not None:
            ax.plot(x, ev.truth[lab], "k--", label="truth")
        ax.set_ylabel(lab, fontsize=7)
        ax.legend(fontsize=7, loc="best")
    k = P
    if trace:
        ax = axes[k, 0]
        steps = {s: i for i, s in enumerate(ev.stamps.tolist())}
        for j, src in enumerate(dict.fromkeys(e["source"] for e in trace)):
            pts = [(e["stamp"], e["statistic"] / e["threshold"]) for e in trace if e["source"] == src]
            x, y = _gaps([p[0] for p in pts], [p[1] for p in pts], steps, ev.sources, src)
            ax.semilogy(np.asarray(x) - t0, y, f"C{j}-", lw=0.8, label=src)
        ax.axhline(1.0, color="r", lw=0.8, ls="--", label="alarm threshold")
        for e in ev.drift:
            named = ", ".join(n["effect"] for n in e["named"]) or "unnamed"
            ax.axvline(e["stamp"] - t0, color="r", lw=0.6)
            ax.annotate(named, (e["stamp"] - t0, 1.0), fontsize=6, rotation=90, va="bottom")
        ax.set_ylabel("window NIS /\nthreshold", fontsize=7)
        ax.legend(fontsize=6, loc="best")
        k += 1
    ax = axes[k, 0]
    for j, (meth, err) in enumerate(ev.position_error.items()):
        ax.plot(ev.gt_stamps - t0, 1e3 * err, f"C{j}.-", lw=0.8, ms=3, label=meth)
    ax.set_ylabel("tool position error [mm]", fontsize=7)
    ax.set_xlabel("time since first ground truth [s]")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _gaps(x: list[float], y: list[float], steps: Mapping[float, int], sources: list[str], src: str
          ) -> tuple[list[float], list[float]]:
    """Break the statistic's line where tests of ``src`` are missing (its window restarted)."""
    ox: list[float] = []
    oy: list[float] = []
    own = [i for i, s in enumerate(sources) if s == src]
    rank = {i: k for k, i in enumerate(own)}
    last = None
    for a, b in zip(x, y):
        k = rank.get(steps.get(a, -1))
        if last is not None and k is not None and k - last > 1:
            ox.append(float("nan"))
            oy.append(float("nan"))
        ox.append(a)
        oy.append(b)
        last = k
    return ox, oy


def _write_model(ev: OnlineEvaluation, model_yaml: Path, out: Path) -> Path:
    """The diagnosed model YAML with its tracked effects replaced by (or added as) the final estimate."""
    import yaml

    raw, _ = read_yaml_file(model_yaml, "model file", ModelConfigError)
    doc = replace_effects(raw, ev.model_effects)
    out.write_text(f"# {model_yaml.name} with the online estimate at the end of {ev.bag} (ppoe evaluate --online)\n"
                   + yaml.safe_dump(json.loads(json.dumps(doc, default=_json_default)), sort_keys=False,
                                    default_flow_style=None))
    return out


def markdown_online(ev: OnlineEvaluation) -> str:
    """The before / static / online (/ fresh) table: tool position error over the bag and in each half [mm]; the
    parameters; the drift monitor's section."""
    d = ev.to_dict()
    rows = ["| method | mean [mm] | RMS [mm] | p95 [mm] | 1st half mean | 2nd half mean | rotation mean [deg] |",
            "|---|---|---|---|---|---|---|"]
    for m, st in d["tool_error"].items():
        p = st["position"]
        rows.append(f"| {m} | {1e3 * p['mean']:.3f} | {1e3 * p['rms']:.3f} | {1e3 * p['p95']:.3f} | "
                    f"{1e3 * st['position_first_half']['mean']:.3f} | {1e3 * st['position_second_half']['mean']:.3f}"
                    f" | {np.degrees(st['rotation']['mean']):.4f} |")
    for lab, p in d["parameters"].items():
        extra = f", 3-sigma coverage {p['coverage_3sigma']:.2f}" if "coverage_3sigma" in p else ""
        if p["final"] is not None:
            rows.append(f"\n{lab}: final {p['final']:.6g} +- {p['final_sigma']:.2g}{extra}")
    return "\n".join(rows) + "\n\n" + _markdown_drift(d) + f"\n\ncounts: {d['counts']}" + (
        "\n\nnotes:\n" + "\n".join(f"- {n}" for n in d["notes"]) if d["notes"] else "")


def _markdown_drift(d: Mapping[str, Any]) -> str:
    """The drift monitor's section: the test, its false-alarm bound, each alarm and what it named."""
    dr = d["drift"]
    if not dr.get("enabled"):
        return "## Drift monitor\n\noff"
    out = ["## Drift monitor", "",
           f"Test per source: sum of the last {dr['window']} NIS > chi-square quantile (false alarm "
           f"{dr['false_alarm']:g} per test); {dr['tests']} tests, expected false alarms at most "
           f"{dr['false_alarm_bound']:.3g}; alarms: {dr['alarms']}."]
    sig = d.get("significance")
    if sig is not None:
        out.append(f"Drift significant (truth) from measurement {sig['index']} (t = {sig['stamp']})."
                   if sig["index"] is not None else "The truth never moves the measurements by one sigma.")
    for e in dr["events"]:
        out.append(f"- measurement {e['measurement']}: {e['message']}")
    return "\n".join(out)
