"""Diagnose results out: the updated model YAML and the markdown report."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.results import DiagnoseResult
from ppoe_core.model.effects import Effect, effect_from_config
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot


def write_model_yaml(model_yaml: str | Path | Mapping | None, result: DiagnoseResult, out_path: str | Path,
                     scale_sigmas: bool = True, drop: Sequence[str] = ()) -> Path:
    """Updated model YAML: the input plus the found ``effects`` (with ``ci``) and, if
    ``scale_sigmas``, perturbation sigmas / covariances and joint noise scaled by the NEES fit.
    The input file is edited as a round trip (ruamel.yaml): its comments and key order are kept; a header
    says what changed.  Effects named in ``drop`` (declared or found) are left out: those folded into a
    calibrated URDF (:func:`~ppoe_core.analysis.diagnose.calibrated_urdf.calibrated_urdf`)."""
    from ruamel.yaml import YAML

    rt = YAML()
    rt.width = 120
    if model_yaml is None:
        doc: Any = {}
    elif isinstance(model_yaml, Mapping):
        doc = dict(model_yaml)
    else:
        with open(model_yaml, encoding="utf-8") as fh:
            doc = rt.load(fh) or {}
    effects = [e for e in (doc.get("effects") or []) if e.get("name") not in drop]
    for e in result.effects:
        if e.name in drop:
            continue
        entry: dict[str, Any] = {"name": e.name, "location": e.location, "parameters": e.parameters}
        for key in ("variable", "reference", "camera_info"):
            if getattr(e, key) is not None:
                entry[key] = getattr(e, key)
        entry["ci"] = {k: [float(a), float(b)] for k, (a, b) in e.ci.items()}
        effects.append(entry)
    doc["effects"] = effects
    k = result.sigma_scale
    if scale_sigmas and math.isfinite(k):
        pert = doc.get("perturbations") or {}
        if pert:
            for _jn, entry in pert.items():
                if "sigma" in entry:
                    entry["sigma"] = [float(v * k) for v in entry["sigma"]]
                if "covariance" in entry:
                    entry["covariance"] = [[float(v * k * k) for v in row] for row in entry["covariance"]]
            jn_sec = doc.get("joint_noise") or {}
            for jn in list(jn_sec):
                jn_sec[jn] = float(jn_sec[jn] * k)
        elif not doc.get("joint_noise") and result.fitted_joint_noise:
            doc["joint_noise"] = result.fitted_joint_noise
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    header = ("# Model updated by `ppoe diagnose`: effects found (with 95 % CIs) appended to `effects`,\n"
              f"# perturbation sigmas and joint noise scaled by {k:.4g}: the declared prior's scale as the data "
              "estimate it.\n"
              + (f"# For robot_calibrated.urdf: the effects {list(drop)} are folded into its joint origins.\n"
                 if drop else ""))
    buf = io.StringIO()
    rt.dump(doc, buf)
    out_path.write_text(header + buf.getvalue(), encoding="utf-8")
    return out_path


def write_report(result: DiagnoseResult, out_dir: str | Path, title: str = "ppoe diagnose") -> dict[str, Path]:
    """``diagnose.json``, ``diagnose.md`` and ``diagnose.png`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "diagnose.json", "md": out / "diagnose.md", "png": out / "diagnose.png"}
    paths["json"].write_text(json.dumps(result.to_json(), indent=2), encoding="utf-8")
    lines = _md_effects(result, title) + _md_blocks(result) + _md_test(result) + _md_steps(result)
    paths["md"].write_text("\n".join(lines) + "\n", encoding="utf-8")
    if not _plot(result, paths["png"]):
        paths.pop("png")
    return paths


def _md_effects(result: DiagnoseResult, title: str) -> list[str]:
    """Title, summary and the table of effects found."""
    lines = [f"# {title}", "", result.summary, "",
             f"* cross-validation: {result.cv} over {result.n_poses} robot poses ({result.n_stops} tracker / pose "
             f"rows, {result.n_sessions} registration sessions)", "",
             "| effect | location | measured by | parameter | value | 95 % CI | share of held-out error |",
             "|---|---|---|---|---|---|---|"]
    for e in result.effects:
        for i, (k, v) in enumerate(e.parameters.items()):
            lo, hi = e.ci[k]
            first = i == 0
            lines.append(f"| {e.name if first else ''} | {e.location if first else ''} | "
                         f"{e.measurement if first else ''} | {k} | {v:.6g} | [{lo:.6g}, {hi:.6g}] | "
                         f"{f'{100 * e.share:.1f} %' if first else ''} |")
        if e.camera_info:
            K = e.camera_info["K"]
            lines.append(f"| | | | camera_info | fx {K[0]:.2f}, fy {K[4]:.2f}, cx {K[2]:.2f}, cy {K[5]:.2f}; "
                         f"D {', '.join(f'{d:.4g}' for d in e.camera_info['D'])} | | |")
    if not result.effects:
        lines.append("| (none) | | | | | | |")
    return lines


def _md_blocks(result: DiagnoseResult) -> list[str]:
    """Per measurement kind: held-out / in-sample RMS before -> after, noise, structure of what is left."""
    lines = ["", "## Measurements", "",
             "| measurement | rows | held-out RMS before -> after | in-sample | noise floor | unexplained | "
             "sensor / prior scale | NEES declared before -> after | residual structure (held-out gain, t) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for b in result.blocks.values():
        f, u = (1e3, "mm") if b.unit == "m" else (1.0, b.unit)
        st = "; ".join(f"{s.predictor} {100 * s.gain:.1f} %, t {s.t:.1f}{' **significant**' if s.significant else ''}"
                       for s in b.structure)
        lines.append(f"| {b.kind} | {b.n} | {f * b.rms_before:.4g} -> {f * b.rms_after:.4g} {u} | "
                     f"{f * b.rms_before_insample:.4g} -> {f * b.rms_after_insample:.4g} {u} | "
                     f"{f * b.noise_floor:.4g} {u} | {f * b.unexplained:.4g} {u} | {b.sensor_scale:.3g} / "
                     f"{b.prior_scale:.3g} | {b.nees_before:.3g} -> {b.nees_after:.3g} | {st} |")
        for name, v in b.per_sensor.items():
            lines.append(f"| {b.kind} {name} | | {f * v['rms_before']:.4g} -> {f * v['rms_after']:.4g} {u} | "
                         f"{f * v['rms_before_insample']:.4g} -> {f * v['rms_after_insample']:.4g} {u} | | | | | |")
    return lines


def _md_test(result: DiagnoseResult) -> list[str]:
    """``--test``: the fitted model scored, unchanged, on each test bag (mm), before -> after."""
    if not result.test:
        return []
    lines = ["", "## Test bags (fitted model unchanged; only tracker registrations fitted)", "",
             "| bag | n | RMS | mean | median | p95 | max | r95 xy | protocol |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, t in result.test.items():
        b = t["before"]
        cells = [f"{1e3 * b[k]:.3f} -> {1e3 * t[k]:.3f}" if k in t and k in b else "-"
                 for k in ("rms", "mean", "median", "p95", "max", "r95_xy")]
        lines.append(f"| {name} | {t['n']} | " + " | ".join(cells) + f" | {t['protocol']} |")
    return lines


def _md_steps(result: DiagnoseResult) -> list[str]:
    """The selection steps and the candidates never attributed (not identifiable)."""
    lines = ["", "## Selection steps", "", "| action | move | held-out gain | change of L | t | z |",
             "|---|---|---|---|---|---|"]
    for s in result.steps:
        mark = "" if s.get("accepted", True) else " (refused)"
        lines.append(f"| {s['action']}{mark} | {s['move']} | {s['heldout_gain']:.4g} | {s['delta_L']:.4g} | "
                     f"{s['t']:.2f} | {s['z']:.2f} |")
    if result.rejected:
        lines += ["", "## Not identifiable or unphysical (never attributed)", ""]
        lines += [f"* {r['candidate']}: {r['reason']}" for r in result.rejected]
    return lines


def _plot(result: DiagnoseResult, png: Path) -> bool:
    """Held-out RMS before / after per measurement (relative to before) into ``png``; False without matplotlib."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # matplotlib is optional for the report
        return False
    fig, ax = plt.subplots(figsize=(6, 3.5))
    names = list(result.blocks)
    before = [1.0 for _ in names]
    after = [b.rms_after / b.rms_before if b.rms_before > 0 else np.nan for b in result.blocks.values()]
    floor = [b.noise_floor / b.rms_before if b.rms_before > 0 else np.nan for b in result.blocks.values()]
    x = np.arange(len(names))
    ax.bar(x - 0.2, before, 0.4, label="before")
    ax.bar(x + 0.2, after, 0.4, label="after")
    ax.plot(x + 0.2, floor, "k_", markersize=20, label="noise floor")
    ax.set_xticks(x, names)
    ax.set_ylabel("held-out RMS / before")
    ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return True


def load_model(model_yaml: str | Path | None, robot: Robot) -> tuple[Any, list[Effect], dict, dict]:
    """Model YAML -> (config, declared effects, perturbation covariances, joint noise)."""
    from ppoe_core.robot.config import load_model_config

    cfg = load_model_config(str(model_yaml) if model_yaml is not None else None, robot)
    tree = KinematicTree(robot)
    declared = [effect_from_config(e, tree, where=w) for e, w in
                zip(cfg.effects, cfg.effect_wheres or [f"{model_yaml} effects[{i}]" for i in range(len(cfg.effects))])]
    pert = {j: p.covariance for j, p in cfg.perturbations.items()}
    return cfg, declared, pert, dict(cfg.joint_noise)
