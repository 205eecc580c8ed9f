"""``ppoe evaluate --online``: drifting effects tracked through a bag, tool error before / static / online.

The bag is replayed in stamp order through :class:`~ppoe_core.estimation.online_effects.OnlineEffects`, the
object the fusion node runs live (``ppoe_ros.common.online_effects``): each ``/temperature`` message sets the
thermal variable, each tracker point (``/ground_truth/point[/<name>]``, the model's ``trackers``) and each
accelerometer message (``/imu/<name>``, the model's ``imus``) updates the tracked effects, and at each
``/ground_truth/pose`` the tool pose is scored by

* ``before``: the nominal model (no effects),
* ``static``: the diagnosed model, its effects fixed,
* ``online``: the current estimate (from every tracker point / accelerometer message stamped before the ground
  truth),
* ``fresh`` (with ``--truth``): the true effects at that moment, i.e. a robot calibrated just then.

Joint values of a measurement are those of the latest ``/joint_states`` at or before its stamp (merged per joint
as the kinematics node does, :func:`~ppoe_core.analysis.evaluate.inputs.joint_matrix`).  With ``--truth
BAG.truth.yaml`` (``ppoe simulate``) the estimate is compared with the true parameters over time
(:func:`ppoe_core.sim.schedule.truth_values`): error, 3-sigma coverage, and the plot ``online_parameters.png``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.evaluate.inputs import joint_matrix, required_joints
from ppoe_core.analysis.evaluate.metrics import error_stats, rotation_errors
from ppoe_core.errors import BagError, ModelConfigError
from ppoe_core.estimation.online_inputs import IMU_TOPIC, OnlineMeasurement, apply_measurement
from ppoe_core.estimation.online_effects import (
    OnlineEffects,
    entries_from_flat,
    parse_online_config,
    replace_effects,
)
from ppoe_core.io.bagio import read_bag
from ppoe_core.model.effects import effect_from_config
from ppoe_core.model.ppoe import PPOEModel
from ppoe_core.robot.yaml_io import read_yaml_file
from ppoe_core.sim.schedule import parse_value, truth_values

__all__ = ["ONLINE_METHODS", "OnlineEvaluation", "evaluate_online", "load_online_config", "markdown_online",
           "write_online_report"]

ONLINE_METHODS = ("before", "static", "online", "fresh")


@dataclass
class OnlineEvaluation:
    """Result of :func:`evaluate_online`: the parameter trace and the scored tool errors."""

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

    def to_dict(self) -> dict[str, Any]:
        """JSON numbers: tool error per method (all, first half, second half), parameter summary, counts."""
        half = self.gt_stamps[0] + 0.5 * (self.gt_stamps[-1] - self.gt_stamps[0]) if len(self.gt_stamps) else 0.0
        second = self.gt_stamps > half
        tool = {m: {"position": error_stats(e), "position_first_half": error_stats(e[~second]),
                    "position_second_half": error_stats(e[second]), "rotation": error_stats(self.rotation_error[m])}
                for m, e in self.position_error.items()}
        params: dict[str, Any] = {}
        for i, lab in enumerate(self.labels):
            d: dict[str, Any] = {"final": float(self.theta[-1, i]) if len(self.stamps) else None,
                                 "final_sigma": float(self.sigma[-1, i]) if len(self.stamps) else None}
            if self.truth is not None and lab in self.truth and len(self.stamps):
                err = self.theta[:, i] - self.truth[lab]
                d["error"] = error_stats(np.abs(err))
                d["coverage_3sigma"] = float(np.mean(np.abs(err) <= 3 * self.sigma[:, i]))
            params[lab] = d
        return {"bag": self.bag, "tool_error": tool, "parameters": params, "counts": dict(self.counts),
                "effects": self.model_effects}


def load_online_config(path: str | Path | None) -> tuple[Any, float | None]:
    """``--online-config FILE`` -> (``online_effects`` list or None, jump probability).

    The file holds ``online_effects:`` (list of ``{name, location, process_noise, initial_sigma}``,
    :func:`~ppoe_core.estimation.online_effects.parse_online_config`) and optionally ``jump_probability``
    (0 = off, default 1e-6); or it is a node parameter file whose ``online_*`` parameters are read (the same
    configuration offline and live).
    """
    if path is None:
        return None, 1e-6
    raw, _ = read_yaml_file(Path(path), "online config", ModelConfigError)
    if isinstance(raw, Mapping) and len(raw) == 1:  # a node parameter file (``/**: ros__parameters: online_*``)
        node = next(iter(raw.values()))
        if isinstance(node, Mapping) and isinstance(node.get("ros__parameters"), Mapping):
            return _from_node_params(node["ros__parameters"], path)
    if not isinstance(raw, Mapping) or set(raw) - {"online_effects", "jump_probability"}:
        raise ModelConfigError(f"online config {path}: a mapping with keys online_effects, jump_probability")
    jp = raw.get("jump_probability", 1e-6)
    if not isinstance(jp, (int, float)) or not 0 <= jp < 1:
        raise ModelConfigError(f"online config {path}: jump_probability must be in [0, 1), got {jp!r}")
    return raw.get("online_effects"), (float(jp) or None)


def _from_node_params(p: Mapping[str, Any], path: str | Path) -> tuple[Any, float | None]:
    """The ``online_*`` parameters of a node parameter file (docs/online.md) -> (entries, jump probability)."""
    try:
        entries = entries_from_flat(list(p.get("online_effects") or []), list(p.get("online_process_noise") or []),
                                    list(p.get("online_initial_sigma") or []),
                                    float(p.get("online_thermal_reference", 20.0)), where=f"{path}: online_effects")
        jp = float(p.get("online_jump_probability", 1e-6))
    except (TypeError, ValueError) as exc:
        raise ModelConfigError(f"online config {path}: {exc}") from None
    return entries, (jp or None)


def _fresh_model(model: PPOEModel, truth: Mapping[str, Any], stamp: float) -> PPOEModel:
    """The model with the TRUE effects at ``stamp`` (a robot calibrated at that moment)."""
    t = stamp - float(truth.get("start_time", 0.0))
    effs = []
    for i, e in enumerate(truth.get("effects") or []):
        params = {k: float(parse_value(v, f"truth effects[{i}].{k}")(t)) for k, v in e["parameters"].items()}
        entry = {k: e[k] for k in ("name", "location", "variable", "reference") if k in e}
        effs.append(effect_from_config({**entry, "parameters": params}, model.robot, where=f"truth effects[{i}]"))
    return model.with_effects(effs)


def _ns(stamp: float) -> int:
    """A bag stamp [s] in integer nanoseconds (the live messages' stamps; ``* 1e-9`` gives it back)."""
    return int(round(float(stamp) * 1e9))


def _events(data: Any, model: PPOEModel, base: str, tool: str, temperature_topic: str) -> list[tuple]:
    """(stamp, order, kind, payload) of the temperatures, tracker points and ground-truth poses, in stamp order."""
    ev: list[tuple] = []
    temps = data.temperatures.get(temperature_topic)
    if temps is not None:
        ev += [(float(t), 0, "temp", (float(v),)) for t, v in zip(temps.stamps, temps.temperature)]
    series = dict(data.ground_truth_points)
    if len(data.ground_truth_point):
        series["/ground_truth/point"] = data.ground_truth_point
    for tr in model.config.trackers:
        s = series.get(tr.topic)
        if s is not None:
            ev += [(float(t), 2, "point", OnlineMeasurement(_ns(t), tr.topic, s.frame_ids[i], s.p[i]))
                   for i, t in enumerate(s.stamps)]
    for name in model.config.imus:
        s = data.imus.get(name)
        if s is not None:
            ev += [(float(t), 2, "imu", OnlineMeasurement(_ns(t), f"{IMU_TOPIC}{name}", s.frame_ids[i],
                                                          s.linear_acceleration[i], name))
                   for i, t in enumerate(s.stamps)]
    gt = data.ground_truth_pose
    if len(gt) == 0:
        raise BagError(f"bag {data.path}: --online needs /ground_truth/pose to score the tool")
    ev += [(float(t), 1, "gt", (gt.frame_ids[i], gt.T[i])) for i, t in enumerate(gt.stamps)]
    if not any(e[2] in ("point", "imu") for e in ev):
        raise BagError(f"bag {data.path}: --online needs tracker points of the model's trackers "
                       f"({[t.topic for t in model.config.trackers]}) or accelerometers of its imus "
                       f"({['/imu/' + n for n in model.config.imus]}); the bag has none")
    return sorted(ev, key=lambda e: (e[0], e[1]))


def evaluate_online(bag: str | Path, model_path: str | Path, online_effects: Any = None,
                    jump_probability: float | None = 1e-6, truth: Mapping[str, Any] | None = None,
                    base: str | None = None, tool: str | None = None,
                    temperature_topic: str = "/temperature") -> OnlineEvaluation:
    """Replay ``bag`` with the online filter (module docstring).

    Raises
    ------
    BagError
        No ground-truth pose or tracker point; joints missing.
    ModelConfigError
        Bad online config; a tracker frame without ``tracker_registration`` in the model.
    """
    data = read_bag(bag, load_images=False)
    model = PPOEModel.from_strings(data.require_robot_description(), Path(model_path))
    fr = model.config.frames
    base = base or (fr.base if fr is not None and fr.base else model.robot.root)
    tool = tool or (fr.tool if fr is not None else None)
    if tool is None:
        raise ModelConfigError(f"{model_path}: no frames.tool and no --tool given")
    filt = OnlineEffects(model, parse_online_config(online_effects, model), jump_probability)
    if filt.needs_temperature() and temperature_topic not in data.temperatures:
        raise BagError(f"bag {bag}: a thermal_growth effect with variable temperature needs {temperature_topic}; "
                       f"the bag has {sorted(data.temperatures) or 'no temperature topic'}")
    names = list(model.joint_names)
    Q, _ = joint_matrix(data.joint_states, names, str(bag), required=required_joints(model, {base, tool}))
    js_t = np.asarray(data.joint_states.stamps, float)
    nominal = model.with_effects([])
    rec: dict[str, Any] = {"st": [], "th": [], "sg": [], "gt": [], "T": {m: [] for m in ONLINE_METHODS},
                           "Tgt": [], "skipped_no_joints": 0, "nis": []}
    for stamp, _, kind, pl in _events(data, model, base, tool, temperature_topic):
        if kind == "temp":
            filt.set_temperature(stamp, pl[0])
            continue
        i = int(np.searchsorted(js_t, stamp, side="right")) - 1
        if i < 0 or not np.all(np.isfinite(Q[i])):
            rec["skipped_no_joints"] += 1
            continue
        q = dict(zip(names, Q[i]))
        if kind in ("point", "imu"):
            up = apply_measurement(filt, pl, q)
            if up is not None:
                rec["st"].append(stamp)
                rec["th"].append(filt.theta.copy())
                rec["sg"].append(filt.sigmas())
                rec["nis"].append(up.nis)
        elif not filt.needs_temperature():
            _score(rec, filt, model, nominal, truth, q, stamp, base, tool, pl)
    return _result(str(bag), filt, rec, truth)


def _score(rec: dict, filt: OnlineEffects, model: PPOEModel, nominal: PPOEModel, truth: Mapping | None,
           q: dict, stamp: float, base: str, tool: str, pl: tuple) -> None:
    """Tool poses of every method at one ground-truth pose."""
    frame_id, T_gt = pl
    if frame_id != base:
        raise BagError(f"/ground_truth/pose: frame_id {frame_id!r}, expected the base frame {base!r}")
    filt.predict(stamp)
    ctx = filt.context
    rec["T"]["before"].append(nominal.fk_mean(q, base, tool, context=ctx))
    rec["T"]["static"].append(model.fk_mean(q, base, tool, context=ctx))
    rec["T"]["online"].append(filt.tool_pose(q, base, tool)[0])
    if truth is not None:
        rec["T"]["fresh"].append(_fresh_model(model, truth, stamp).fk_mean(q, base, tool, context=ctx))
    rec["gt"].append(stamp)
    rec["Tgt"].append(T_gt)


def _result(bag: str, filt: OnlineEffects, rec: dict, truth: Mapping | None) -> OnlineEvaluation:
    P = len(filt.labels)
    st = np.asarray(rec["st"], float)
    Tgt = np.asarray(rec["Tgt"], float).reshape(-1, 4, 4)
    pos, rot = {}, {}
    for m, Ts in rec["T"].items():
        if Ts:
            T = np.asarray(Ts)
            pos[m] = np.linalg.norm(T[:, :3, 3] - Tgt[:, :3, 3], axis=1)
            rot[m] = rotation_errors(T, Tgt)
    tv = None
    if truth is not None:
        allv = truth_values(truth, st)
        tv = {lab: allv.get(lab, np.zeros_like(st)) for lab in filt.labels}
    counts = {"tracker_points": filt.counts.points, "accelerations": filt.counts.gravity, "jumps": filt.counts.jumps,
              "temperatures": filt.counts.temperatures, "ground_truth_poses": int(len(Tgt)),
              "skipped_waiting_for_temperature": filt.counts.waiting_for_temperature,
              "skipped_no_joint_state": int(rec["skipped_no_joints"])}
    nis = np.asarray(rec["nis"], float)
    counts["nis_above_99pct"] = int(np.sum(nis > 11.345))
    return OnlineEvaluation(bag, filt.labels, st, np.asarray(rec["th"], float).reshape(-1, P),
                            np.asarray(rec["sg"], float).reshape(-1, P), tv, np.asarray(rec["gt"], float), pos, rot,
                            counts, filt.effect_entries())


def write_online_report(ev: OnlineEvaluation, out_dir: str | Path, model_yaml: str | Path | None = None
                        ) -> list[Path]:
    """``online.json`` and ``online_parameters.png`` (estimate with 3-sigma band vs truth over time, and the
    tool position error per method) in ``out_dir``; with ``model_yaml`` (the diagnosed model) also
    ``model_online.yaml``: that model with the tracked effects at their final estimate (with ``ci``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "online.json", out / "online_parameters.png"]
    paths[0].write_text(json.dumps(ev.to_dict(), indent=1, allow_nan=False))
    if model_yaml is not None:
        paths.append(_write_model(ev, Path(model_yaml), out / "model_online.yaml"))
    P = len(ev.labels)
    fig, axes = plt.subplots(P + 1, 1, figsize=(8, 2.2 * (P + 1)), squeeze=False, sharex=True)
    t0 = ev.gt_stamps[0] if len(ev.gt_stamps) else 0.0
    for i, (ax, lab) in enumerate(zip(axes[:P, 0], ev.labels)):
        x, m, s = ev.stamps - t0, ev.theta[:, i], ev.sigma[:, i]
        ax.fill_between(x, m - 3 * s, m + 3 * s, color="C0", alpha=0.25, label="online +-3 sigma")
        ax.plot(x, m, "C0", label="online")
        if ev.truth is not None:
            ax.plot(x, ev.truth[lab], "k--", label="truth")
        ax.set_ylabel(lab, fontsize=7)
        ax.legend(fontsize=7, loc="best")
    ax = axes[P, 0]
    for k, (meth, e) in enumerate(ev.position_error.items()):
        ax.plot(ev.gt_stamps - t0, 1e3 * e, f"C{k}.-", lw=0.8, ms=3, label=meth)
    ax.set_ylabel("tool position error [mm]")
    ax.set_xlabel("time since first ground truth [s]")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)
    return paths


def _write_model(ev: OnlineEvaluation, model_yaml: Path, out: Path) -> Path:
    """The diagnosed model YAML with its tracked effects replaced by (or added as) the final estimate."""
    import yaml

    raw, _ = read_yaml_file(model_yaml, "model file", ModelConfigError)
    doc = replace_effects(raw, ev.model_effects)
    out.write_text(f"# {model_yaml.name} with the online estimate at the end of {ev.bag} (ppoe evaluate --online)\n"
                   + yaml.safe_dump(json.loads(json.dumps(doc)), sort_keys=False, default_flow_style=None))
    return out


def markdown_online(ev: OnlineEvaluation) -> str:
    """The before / static / online (/ fresh) table: tool position error over the bag and in each half [mm]."""
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
    return "\n".join(rows) + f"\n\ncounts: {d['counts']}"

