"""``ppoe evaluate BAG --model MODEL.yaml --perturbations A.yaml [B.yaml ...] [--global-scale K]``: the same bag
replayed with several choices of the PPOE perturbation covariances, fused error and NEES side by side.

Each choice is the model YAML with only its ``perturbations`` and ``joint_noise`` sections replaced: by those of
another model file (e.g. ``model_diagnosed.yaml`` of ``ppoe diagnose --learn-perturbations``, or of a plain
``ppoe diagnose``, whose sigmas are the declared ones times one global scale), or by the declared ones times ``K``.
Everything else (effects, tags, camera, naive covariance, fusion settings) stays the model's, so the differences
are the covariances' alone.  The declared model itself is always the first column.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ppoe_core.analysis.evaluate.options import EvaluateOptions, Evaluation
from ppoe_core.errors import ModelConfigError

__all__ = ["PERTURBATION_KEYS", "compare_perturbations", "comparison_json", "comparison_table", "ellipsoid_coverage",
           "variant_doc"]

#: the model sections a choice replaces
PERTURBATION_KEYS = ("perturbations", "joint_noise")


def _load(path: str | Path) -> dict[str, Any]:
    from ruamel.yaml import YAML

    try:
        with open(path, encoding="utf-8") as fh:
            doc = YAML(typ="safe").load(fh) or {}
    except OSError as exc:
        raise ModelConfigError(f"{path}: cannot read model YAML: {exc.strerror}") from None
    if not isinstance(doc, dict):
        raise ModelConfigError(f"{path}: a model YAML must be a mapping")
    return doc


def variant_doc(model: Mapping[str, Any], source: Mapping[str, Any] | None = None, scale: float | None = None
                ) -> dict[str, Any]:
    """The model document with :data:`PERTURBATION_KEYS` taken from ``source`` (absent there: empty), or with the
    model's own sigmas / covariances / joint noise times ``scale``."""
    out = dict(model)
    if source is not None:
        for k in PERTURBATION_KEYS:
            out[k] = source.get(k) or {}
        return out
    if scale is None:
        return out
    pert = {}
    for jn, entry in (model.get("perturbations") or {}).items():
        e = dict(entry)
        if "sigma" in e:
            e["sigma"] = [float(v) * scale for v in e["sigma"]]
        if "covariance" in e:
            e["covariance"] = [[float(v) * scale ** 2 for v in row] for row in e["covariance"]]
        pert[jn] = e
    out["perturbations"] = pert
    out["joint_noise"] = {j: float(v) * scale for j, v in (model.get("joint_noise") or {}).items()}
    return out


def compare_perturbations(bag: str | Path, model_yaml: str | Path, sources: Sequence[str | Path] = (),
                          global_scale: float | None = None, options: EvaluateOptions | None = None
                          ) -> dict[str, Evaluation]:
    """Label -> :class:`Evaluation` of ``bag`` for the declared model (``declared``), each of ``sources`` (by file
    name) and the global scale (``global x K``)."""
    from ruamel.yaml import YAML

    from ppoe_core.analysis.evaluate.replay import evaluate_bag

    model = _load(model_yaml)
    variants: dict[str, dict[str, Any]] = {}
    names = [Path(s).name for s in sources]
    for s in sources:  # by file name, with its folder when two share one
        label = Path(s).name if names.count(Path(s).name) == 1 else f"{Path(s).parent.name}/{Path(s).name}"
        if label in variants or label == "declared":
            raise ModelConfigError(f"--perturbations: {s} given twice (or named like another choice)")
        variants[label] = variant_doc(model, _load(s))
    if global_scale is not None:
        variants[f"global x {global_scale:g}"] = variant_doc(model, scale=global_scale)
    out = {"declared": evaluate_bag(bag, model_yaml, options)}
    with tempfile.TemporaryDirectory(prefix="ppoe_perturbations_") as tmp:
        for i, (label, doc) in enumerate(variants.items()):
            path = Path(tmp) / f"variant_{i}.yaml"
            with open(path, "w", encoding="utf-8") as fh:
                YAML(typ="safe").dump(doc, fh)
            out[label] = evaluate_bag(bag, path, options)
    return out


def _method(ev: Evaluation, method: str) -> dict[str, Any]:
    return dict(ev.summary.get("methods", {}).get(method, {}))


def ellipsoid_coverage(ev: Evaluation, method: str, levels: Sequence[float] = (0.68, 0.95, 0.99)) -> dict[str, float]:
    """Share of the scored samples inside the method's ``p`` ellipsoid (``NEES <= chi2_dof(p)``) per level."""
    import numpy as np
    from scipy.stats import chi2

    v = np.asarray(ev.samples.get(f"{method}_nees", []), dtype=float)
    v = v[np.isfinite(v)]
    dof = int(_method(ev, method).get("nees", {}).get("dof", 6) or 6)
    return {f"{p:g}": float(np.mean(v <= chi2.ppf(p, dof))) if v.size else float("nan") for p in levels}


def comparison_json(evs: Mapping[str, Evaluation]) -> dict[str, Any]:
    """Per choice: the fk and ppoe methods' metrics (the summary's ``methods`` entries) with their ellipsoid
    coverage (:func:`ellipsoid_coverage`)."""
    return {label: {m: {**_method(ev, m), "coverage": ellipsoid_coverage(ev, m)} for m in ("fk", "ppoe")
                    if _method(ev, m)} for label, ev in evs.items()}


def comparison_table(evs: Mapping[str, Evaluation]) -> str:
    """Markdown: per choice, the fused (``ppoe``) position and rotation error RMS, and for FK and fused the NEES
    mean and the coverage of the 68 / 95 / 99 % ellipsoids [%]."""
    lines = ["| perturbations | fused position RMS [mm] | fused rotation RMS [mrad] | FK NEES mean | FK coverage "
             "68/95/99 % | fused NEES mean | fused coverage 68/95/99 % | samples |",
             "|---|---|---|---|---|---|---|---|"]
    for label, ev in evs.items():
        fk, fu = _method(ev, "fk"), _method(ev, "ppoe")
        cov = {m: "/".join(f"{100 * v:.0f}" for v in ellipsoid_coverage(ev, m).values()) for m in ("fk", "ppoe")}
        lines.append(f"| {label} | {_get(fu, 'position_3d', 'rms', 1e3)} | {_get(fu, 'rotation', 'rms', 1e3)} | "
                     f"{_get(fk, 'nees', 'mean')} | {cov['fk']} | {_get(fu, 'nees', 'mean')} | {cov['ppoe']} | "
                     f"{_get(fu, 'nees', 'n')} |")
    return "\n".join(lines)


def _get(m: Mapping[str, Any], key: str, stat: str, scale: float = 1.0) -> str:
    v = (m.get(key) or {}).get(stat)
    return "-" if v is None else f"{scale * float(v):.4g}"
