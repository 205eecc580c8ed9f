"""Diagnose results out: the updated model YAML and the report (``diagnose.md``, ``.json``, ``.png``).

The report's words have one meaning each, listed under its "Terms" (:data:`SHARE`, :data:`SHARE_DEFINITION`,
:data:`TERMS`; docs/diagnose_report.md): an effect's *share of the residual* is the only "share"; what is left in a
measurement kind has a *predictable part*; a selection step has a *held-out drop of -2 log L* (not a fraction).
The "How to apply" section and the camera files come from :mod:`report_apply`, the figure from :mod:`report_plot`.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ppoe_core.analysis.diagnose.calibrated_urdf import STATIC_EFFECTS, plan_calibration, significant
from ppoe_core.analysis.diagnose.report_apply import apply_section, camera_sizes, write_camera_infos
from ppoe_core.analysis.diagnose.report_plot import display_unit, ordered_blocks, plot_blocks
from ppoe_core.analysis.diagnose.results import DiagnoseResult
from ppoe_core.model.effects import Effect, effect_from_config
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["SHARE", "SHARE_DEFINITION", "TERMS", "headline", "load_model", "write_model_yaml", "write_report"]


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
    k, learned = result.sigma_scale, result.learned_prior
    written = ""
    if scale_sigmas and learned is not None and learned.best in ("learned", ""):
        # --learn-perturbations: the learned covariances, when the held-out check does not prefer another choice
        from ppoe_core.analysis.diagnose.learned_prior import write_into_model

        written = "\n".join(write_into_model(doc, learned)) + "\n"
    elif scale_sigmas and (learned is None or learned.best == "global_scale") and math.isfinite(k):
        _scale_prior(doc, result, k)
        written = (f"# perturbation sigmas and joint noise scaled by {k:.4g}: the declared prior's scale as the data "
                   "estimate it.\n")
    if scale_sigmas and learned is not None and learned.best not in ("learned", ""):
        kept = "the declared sigmas scaled, above" if written else "the declared sigmas kept"
        written += ("# --learn-perturbations: the learned covariances are NOT written: the held-out check's best "
                    f"log-likelihood is '{learned.best}'\n# ({kept}; diagnose.md, Learned perturbations, has the "
                    "learned ones).\n")
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    header = ("# Model updated by `ppoe diagnose`: effects found (with 95 % CIs) appended to `effects`,\n"
              + written
              + (f"# For robot_calibrated.urdf: the static effects {list(drop)} are left out here: the declared ones\n"
                 "# and the significant components of the found ones are folded into its joint origins (diagnose.md,\n"
                 "# section How to apply, lists the components left out).\n" if drop else ""))
    buf = io.StringIO()
    rt.dump(doc, buf)
    out_path.write_text(header + buf.getvalue(), encoding="utf-8")
    return out_path


def _scale_prior(doc: Any, result: DiagnoseResult, k: float) -> None:
    """Scale the document's perturbation sigmas / covariances and joint noise by ``k`` (the NEES fit); with no
    perturbations and no joint noise declared, write the fitted joint noise."""
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


#: the one name of the quantity in the effects table (docs/diagnose_report.md uses the same words)
SHARE = "share of the residual"

#: its definition, printed under the report's "Terms"
SHARE_DEFINITION = (
    "the part of the held-out residual of the nominal model (the sum over every measurement of the squared whitened "
    "held-out residuals) that the effect removes: how much that sum rises when this effect alone is left out of "
    "the diagnosed model, divided by the sum before any effect. Two effects that explain the same error both "
    "count it, so the effects' values need not add up to the total drop")

#: the other terms of the report
TERMS = (
    ("held out", "predicted by a fit that did not see the row (cross-validation over robot poses, or over bags)"),
    ("before -> after", "the nominal model (URDF + declared effects) -> the diagnosed model (+ the effects found)"),
    ("noise floor", "the held-out RMS a model with nothing systematic left would reach (the declared noise as the "
                    "data scale it)"),
    ("unexplained", "the RMS above the noise floor after the diagnosis"),
    ("predictable part", "of what is left in a measurement kind after the diagnosis: the fraction of its held-out "
                         "whitened residual a smooth function of the predictor (configuration, time, image position) "
                         "predicts held out; significant ones are named \"structure left\". Negative: predicting "
                         "does worse than not predicting"),
    ("held-out drop of -2 log L", "of a selection step: how much the step lowers the held-out -2 log L (the "
                                  "whitened squared residuals in units of the current residual variance; JSON "
                                  "steps[].heldout_gain); a count, not a fraction"),
)


def write_report(result: DiagnoseResult, out_dir: str | Path, title: str = "ppoe diagnose", *,
                 declared: Sequence[Effect] = (), bags: Sequence[str | Path] = ()) -> dict[str, Path]:
    """``diagnose.json``, ``diagnose.md``, ``diagnose.png`` and, for corrected camera intrinsics,
    ``camera_info_<frame>.yaml`` (image size from the ``bags``' camera_info) in ``out_dir``.

    ``declared``: the model YAML's effects (its static ones are folded into the calibrated URDF in full)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "diagnose.json", "md": out / "diagnose.md", "png": out / "diagnose.png"}
    paths["json"].write_text(json.dumps(result.to_json(), indent=2), encoding="utf-8")
    plan = plan_calibration(result, declared)
    static_declared = [e.key for e in declared if e.name in STATIC_EFFECTS]
    from ppoe_core.analysis.diagnose.learned_prior import markdown_section

    lines = (_md_head(result, title) + _md_effects(result) + _md_blocks(result)
             + markdown_section(result.learned_prior) + apply_section(result, plan, out, static_declared)
             + _md_test(result) + _md_steps(result) + _md_terms())
    paths["md"].write_text("\n".join(lines) + "\n", encoding="utf-8")
    if not plot_blocks(result, paths["png"], title):
        paths.pop("png")
    sizes = camera_sizes(bags) if bags and any(e.camera_info for e in result.effects) else {}
    for cam in write_camera_infos(result, out, sizes):
        paths[cam.stem] = cam
    return paths


def headline(result: DiagnoseResult) -> list[str]:
    """What was found and, per measurement kind, the held-out RMS before -> after (the report's first lines)."""
    if result.effects:
        head = (f"Found {len(result.effects)} effect(s): "
                + ", ".join(f"{e.name} at {e.location} ({SHARE} {_pct(e.share)})" for e in result.effects) + ".")
    else:
        head = "No catalogue effect was found: none lowers the held-out residual significantly."
    lines = [head, ""]
    for b in ordered_blocks(result):
        f, u = display_unit(b.unit)
        line = (f"* {b.kind}: held-out RMS {f * b.rms_before:.4g} -> {f * b.rms_after:.4g} {u} (noise floor "
                f"{f * b.noise_floor:.4g} {u})")
        sig = [s for s in b.structure if s.significant]
        if sig:
            line += (f"; structure left: {f * b.unexplained:.4g} {u} RMS above the floor, predictable part "
                     + ", ".join(f"{_pct(s.gain)} from the {s.predictor}" for s in sig) + " (outside the catalogue)")
        lines.append(line)
    return lines


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %" if math.isfinite(x) else "-"


def _md_head(result: DiagnoseResult, title: str) -> list[str]:
    """Title, headline, cross-validation, the plot."""
    return [f"# {title}", "", *headline(result), "",
            f"Cross-validation: {result.cv} over {result.n_poses} robot poses ({result.n_stops} tracker / pose rows, "
            f"{result.n_sessions} registration sessions).", "", "![held-out RMS per measurement](diagnose.png)"]


def _md_effects(result: DiagnoseResult) -> list[str]:
    """The table of effects found: values, 95 % intervals, significance, share of the residual."""
    lines = ["", "## Effects found", "",
             f"| effect | location | measured by | parameter | value | 95 % CI | CI excludes 0 | {SHARE} |",
             "|---|---|---|---|---|---|---|---|"]
    for e in result.effects:
        for i, (k, v) in enumerate(e.parameters.items()):
            lo, hi = e.ci[k]
            first = i == 0
            sig = "yes" if significant((lo, hi)) else "no"
            lines.append(f"| {e.name if first else ''} | {e.location if first else ''} | "
                         f"{e.measurement if first else ''} | {k} | {v:.6g} | [{lo:.6g}, {hi:.6g}] | {sig} | "
                         f"{_pct(e.share) if first else ''} |")
        if e.camera_info:
            K = e.camera_info["K"]
            lines.append(f"| | | | camera_info | fx {K[0]:.2f}, fy {K[4]:.2f}, cx {K[2]:.2f}, cy {K[5]:.2f}; "
                         f"D {', '.join(f'{d:.4g}' for d in e.camera_info['D'])} | | | |")
    if not result.effects:
        lines.append("| (none) | | | | | | | |")
    return lines


def _md_blocks(result: DiagnoseResult) -> list[str]:
    """Per measurement kind: held-out / in-sample RMS before -> after, noise, the predictable part of what is left."""
    lines = ["", "## Measurements", "",
             "| measurement | rows | held-out RMS before -> after | in-sample | noise floor | unexplained | "
             "sensor / prior scale | NEES declared before -> after | predictable part of what is left (t) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for b in ordered_blocks(result):
        f, u = display_unit(b.unit)
        st = "; ".join(f"{s.predictor} {_pct(s.gain)}, t {s.t:.1f}{' **structure left**' if s.significant else ''}"
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
    lines = ["", "## Selection steps", "", "| action | move | held-out drop of -2 log L | change of L | t | z |",
             "|---|---|---|---|---|---|"]
    for s in result.steps:
        mark = "" if s.get("accepted", True) else " (refused)"
        lines.append(f"| {s['action']}{mark} | {s['move']} | {s['heldout_gain']:.4g} | {s['delta_L']:.4g} | "
                     f"{s['t']:.2f} | {s['z']:.2f} |")
    if result.rejected:
        lines += ["", "## Not identifiable or unphysical (never attributed)", ""]
        lines += [f"* {r['candidate']}: {r['reason']}" for r in result.rejected]
    return lines


def _md_terms() -> list[str]:
    """What the report's words mean (one definition each)."""
    return ["", "## Terms", "", f"* **{SHARE}** (of an effect): {SHARE_DEFINITION}."] + [
        f"* **{name}**: {text}." for name, text in TERMS]


def load_model(model_yaml: str | Path | None, robot: Robot) -> tuple[Any, list[Effect], dict, dict]:
    """Model YAML -> (config, declared effects, perturbation covariances, joint noise)."""
    from ppoe_core.robot.config import load_model_config

    cfg = load_model_config(str(model_yaml) if model_yaml is not None else None, robot)
    tree = KinematicTree(robot)
    declared = [effect_from_config(e, tree, where=w) for e, w in
                zip(cfg.effects, cfg.effect_wheres or [f"{model_yaml} effects[{i}]" for i in range(len(cfg.effects))])]
    pert = {j: p.covariance for j, p in cfg.perturbations.items()}
    return cfg, declared, pert, dict(cfg.joint_noise)
