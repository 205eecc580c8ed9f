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
        if e["name"] in drop:
            continue
        entry = {"name": e["name"], "location": e["location"], "parameters": e["parameters"]}
        for key in ("variable", "reference"):
            if key in e:
                entry[key] = e[key]
        entry["ci"] = {k: [float(a), float(b)] for k, (a, b) in e["ci"].items()}
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
        elif not doc.get("joint_noise") and result.extra.get("fitted_joint_noise"):
            doc["joint_noise"] = result.extra["fitted_joint_noise"]
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    header = ("# Model updated by `ppoe diagnose`: effects found (with 95 % CIs) appended to `effects`,\n"
              f"# perturbation sigmas scaled by {k:.4g} for held-out NEES = 3.\n"
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
    lines = (_md_effects(result, title) + _md_test(result) + _md_imu_tilt(result) + _md_imu_fit(result)
             + _md_pixels(result) + _md_steps(result))
    paths["md"].write_text("\n".join(lines) + "\n", encoding="utf-8")
    if not _plot(result, paths["png"]):
        paths.pop("png")
    return paths


def _md_effects(result: DiagnoseResult, title: str) -> list[str]:
    """Title, residuals before/after, noise floor, NEES and the table of effects found."""
    lines = [f"# {title}", "", result.summary, "",
             f"* held-out residual (RMS 3D, {result.cv} cross-validation, {result.n_stops} stops, "
             f"{result.n_sessions} sessions): before **{1e3 * result.residual_before:.3f} mm**, after "
             f"**{1e3 * result.residual_after:.3f} mm**",
             f"* in-sample: {1e3 * result.residual_before_insample:.3f} mm -> "
             f"{1e3 * result.residual_after_insample:.3f} mm; noise floor (declared PPOE covariance + sensor noise) "
             f"{1e3 * result.noise_floor:.3f} mm; unexplained above it {1e3 * result.unexplained:.3f} mm",
             f"* NEES (held-out, expectation 3): {result.nees_before:.3g} with the model's sigmas, "
             f"{result.nees_after:.3g} after scaling them by {result.sigma_scale:.4g}",
             f"* linearisation error of the selection stage at the final estimate (the final fit is "
             f"relinearised on the full chain): {1e6 * result.linearisation_error:.3f} um", "",
             "| effect | location | parameter | value | 95 % CI | share of residual |",
             "|---|---|---|---|---|---|"]
    for e in result.effects:
        for i, (k, v) in enumerate(e["parameters"].items()):
            lo, hi = e["ci"][k]
            share = f"{100 * e['share']:.1f} %" if i == 0 else ""
            lines.append(f"| {e['name'] if i == 0 else ''} | {e['location'] if i == 0 else ''} | {k} | "
                         f"{v:.6g} | [{lo:.6g}, {hi:.6g}] | {share} |")
    if not result.effects:
        lines.append("| (none) | | | | | |")
    return lines


def _md_test(result: DiagnoseResult) -> list[str]:
    """``--test``: the fitted model scored, unchanged, on each test bag (mm), before -> after."""
    test = result.extra.get("test")
    if not test:
        return []
    lines = ["", "## Test bags (fitted model unchanged; only tracker registrations fitted)", "",
             "| bag | n | RMS | mean | median | p95 | max | r95 xy | protocol |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, t in test.items():
        b = t["before"]
        cells = [f"{1e3 * b[k]:.3f} -> {1e3 * t[k]:.3f}" if k in t and k in b else "-"
                 for k in ("rms", "mean", "median", "p95", "max", "r95_xy")]
        lines.append(f"| {name} | {t['n']} | " + " | ".join(cells) + f" | {t['protocol']} |")
    return lines


def _md_imu_tilt(result: DiagnoseResult) -> list[str]:
    """Accelerometer tilt residuals before/after (not used by the fit)."""
    lines: list[str] = []
    if result.extra.get("imu_tilt"):
        lines += ["", "## Accelerometer tilt residuals (not used by the fit; per-session mean removed)", "",
                  "| IMU | link | stops | RMS rx, ry before [mrad] | after [mrad] |", "|---|---|---|---|---|"]
        for k, v in result.extra["imu_tilt"].items():
            lines.append(f"| {k} | {v['link']} | {v['n']} | {1e3 * v['rms_before'][0]:.3f}, "
                         f"{1e3 * v['rms_before'][1]:.3f} | {1e3 * v['rms_after'][0]:.3f}, "
                         f"{1e3 * v['rms_after'][1]:.3f} |")
    return lines


def _md_imu_fit(result: DiagnoseResult) -> list[str]:
    """The accelerometer stage: base tilt per bag/file and IMU-visible effects."""
    lines: list[str] = []
    fit = result.extra.get("imu_fit")
    if fit:
        lines += ["", "## Accelerometer stage (base tilt per bag/file, effects seen by the IMUs)", "",
                  f"Reference IMU (its mounting is part of the base tilt): {fit['reference_imu']}. "
                  "Held-out tilt RMS per IMU, rx / ry [mrad]: "
                  + ", ".join(f"{k} {1e3 * b[0]:.3f} / {1e3 * b[1]:.3f} -> {1e3 * fit['tilt_rms_after'][k][0]:.3f}"
                              f" / {1e3 * fit['tilt_rms_after'][k][1]:.3f}" for k, b in fit["tilt_rms_before"].items())
                  + ".", ""]
        for e in fit["effects"]:
            if e["name"] == "base_tilt":
                for g, v in e["per_group"].items():
                    lines.append(f"* base_tilt {g}: tilt_x {1e3 * v['tilt_x']:.3f} mrad "
                                 f"[{1e3 * v['ci']['tilt_x'][0]:.3f}, {1e3 * v['ci']['tilt_x'][1]:.3f}], "
                                 f"tilt_y {1e3 * v['tilt_y']:.3f} mrad "
                                 f"[{1e3 * v['ci']['tilt_y'][0]:.3f}, {1e3 * v['ci']['tilt_y'][1]:.3f}]")
            else:
                lines.append(f"* {e['name']}@{e['location']}: " + ", ".join(
                    f"{k} {v:.4g} [{e['ci'][k][0]:.4g}, {e['ci'][k][1]:.4g}]" for k, v in e["parameters"].items()))
        if not fit["effects"]:
            lines.append("* nothing found (no base tilt, no IMU-visible effect)")
    return lines


def _md_pixels(result: DiagnoseResult) -> list[str]:
    """The tag-pixel stage: held-out and in-sample pixel RMS per camera."""
    lines: list[str] = []
    if result.extra.get("pixels"):
        px = result.extra["pixels"]
        lines += ["", f"## Tag pixels ({px['n']} points; effects marked `measurement: pixels` above, share = of "
                  "the pixel residual)", ""]
        if "pixel_rms_declared_only" in px:
            lines += ["In-sample RMS with only the declared effects (without the tracker/pose effects above): "
                      + ", ".join(f"{f} {v:.2f} px" for f, v in px["pixel_rms_declared_only"].items()), ""]
        lines += ["| camera frame | held-out RMS before [px] | after [px] | in-sample before | after |",
                  "|---|---|---|---|---|"]
        for f in px["pixel_rms_before"]:
            lines.append(f"| {f} | {px['pixel_rms_before'][f]:.2f} | {px['pixel_rms_after'][f]:.2f} | "
                         f"{px['pixel_rms_before_insample'][f]:.2f} | {px['pixel_rms_after_insample'][f]:.2f} |")
    return lines


def _md_steps(result: DiagnoseResult) -> list[str]:
    """The selection steps and the candidates never attributed (not identifiable)."""
    lines: list[str] = []
    lines += ["", "## Selection steps", "", "| candidate | accepted | held-out RMS [mm] | gain | t |",
              "|---|---|---|---|---|"]
    for s in result.steps:
        lines.append(f"| {s['candidate']} | {s['accepted']} | {1e3 * s['heldout_rms']:.3f} | "
                     f"{100 * s['gain']:.1f} % | {s['t']:.2f} |")
    if result.rejected:
        lines += ["", "## Not identifiable (never attributed)", ""]
        lines += [f"* {r['candidate']}: {r['reason']}" for r in result.rejected]
    return lines


def _plot(result: DiagnoseResult, png: Path) -> bool:
    """Held-out error histogram and RMS per accepted step into ``png``; False without matplotlib."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ok = np.isfinite(result.e2_before) & np.isfinite(result.e2_after)
        eb, ea = 1e3 * np.sqrt(result.e2_before[ok]), 1e3 * np.sqrt(result.e2_after[ok])
        bins = np.linspace(0, max(eb.max(initial=1e-3), ea.max(initial=1e-3)), 40)
        ax[0].hist(eb, bins, alpha=0.6, label="before")
        ax[0].hist(ea, bins, alpha=0.6, label="after")
        ax[0].set_xlabel("held-out 3D error [mm]")
        ax[0].legend()
        accepted = [s for s in result.steps if s["accepted"]]  # the selection's steps (a simplification after
        rms = [1e3 * result.residual_before] + [1e3 * s["heldout_rms"] for s in accepted]  # it may rename them)
        ax[1].plot(range(len(rms)), rms, "o-")
        ax[1].axhline(1e3 * result.noise_floor, ls="--", color="k", label="noise floor")
        ax[1].set_xticks(range(len(rms)), ["nominal"] + ["+" + s["candidate"].replace("@", "\n", 1) for s in accepted],
                         fontsize=6, rotation=30)
        ax[1].set_ylabel("held-out RMS [mm]")
        ax[1].legend()
        fig.tight_layout()
        fig.savefig(png, dpi=100)
        plt.close(fig)
    except ImportError:  # matplotlib is optional for the report
        return False
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
