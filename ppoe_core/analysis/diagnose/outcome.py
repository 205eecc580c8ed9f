"""The result of a diagnosis: effect entries with intervals, per-block residuals before / after, structure, summary."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ppoe_core.analysis.diagnose.block import ResidualBlock
from ppoe_core.analysis.diagnose.covariance import parameter_covariance
from ppoe_core.analysis.diagnose.crossval import Linearised
from ppoe_core.analysis.diagnose.noise import NoiseScales, mahalanobis2
from ppoe_core.analysis.diagnose.results import BlockReport, DiagnoseOptions, DiagnoseResult, EffectReport
from ppoe_core.analysis.diagnose.selection import Selection
from ppoe_core.analysis.diagnose.significance import STRUCTURE_T, BlockStructure, structure_tests
from ppoe_core.analysis.diagnose.testing import error_stats
from ppoe_core.model.effects import Effect

if TYPE_CHECKING:
    from ppoe_core.analysis.diagnose.engine import Run

__all__ = ["build_result", "summary"]


def build_result(run: Run, before: Linearised, insample_before: Sequence[np.ndarray], selection: Selection,
                 mode: str, options: DiagnoseOptions) -> DiagnoseResult:
    """:class:`DiagnoseResult` of a finished run (module docstring)."""
    pr, lin = run.problem, run.lin
    assert lin is not None
    model, effects = selection.model, run.effects
    structure = structure_tests(pr, effects, run.unit_fold, STRUCTURE_T)
    after = lin.heldout_residual(model)
    held_before = before.heldout_residual(())
    blocks: dict[str, BlockReport] = {}
    for part in lin.sys.parts:
        b = pr.blocks[part.index]
        rb = before.sys.parts[part.index].raw(held_before)
        ra = part.raw(after)
        ins_a = b.residual([*pr.declared, *effects])
        st = pr.state[part.index]
        assert st.S is not None and st.Q is not None
        blocks[b.kind] = _block_report(b, st.scales, (st.S, st.Q), rb, ra, insample_before[part.index], ins_a,
                                       structure.get(part.index, BlockStructure()))
    reports = _effect_reports(run, model, effects)
    n_stops = 0
    metric = blocks.get("tracker") or blocks.get("pose")
    if metric is not None:
        n_stops = int(sum(v["after"].get("n", 0) for v in metric.per_group.values()))
    tracker = next((b for b in pr.blocks if b.kind == "tracker"), None)
    res = DiagnoseResult(
        effects=reports, found=list(effects), blocks=blocks, steps=selection.steps,
        rejected=[{"candidate": k, "reason": v} for k, v in selection.rejected.items()], cv=mode, n_stops=n_stops,
        n_sessions=tracker.n_segments if tracker is not None else 0, n_poses=pr.n_units)
    if options.learn_perturbations:  # docs/covariance.md
        from ppoe_core.analysis.diagnose.learned_prior import learn_prior

        res.learned_prior = learn_prior(run, selection.model)
    res.summary = summary(res)
    return res


def _rms(norms: np.ndarray) -> float:
    ok = np.isfinite(norms)
    return float(np.sqrt(np.mean(norms[ok] ** 2))) if ok.any() else math.nan


def _block_report(b: ResidualBlock, scales: NoiseScales, declared: tuple[np.ndarray, np.ndarray], rb: np.ndarray,
                  ra: np.ndarray, ins_b: np.ndarray, ins_a: np.ndarray, st: BlockStructure) -> BlockReport:
    """One block's :class:`BlockReport` from its held-out (``rb``, ``ra``) and in-sample residual rows;
    ``declared``: its declared covariance pieces (S, Q) for the NEES."""
    nb, na = b.error_norm(rb), b.error_norm(ra)
    S, Q = declared
    ones = NoiseScales(1.0, 1.0)
    nees_b, nees_a = mahalanobis2(rb, S, Q, ones), mahalanobis2(ra, S, Q, ones)
    floor = _rms(b.error_norm(st.residual)) if st.residual is not None else _rms(na)
    floor = min(floor, _rms(na)) if math.isfinite(floor) else _rms(na)
    per_group = {}
    for g, name in enumerate(b.group_names):
        m = b.group == g
        if m.any() and b.kind in ("tracker", "pose"):
            per_group[name] = {"before": error_stats(rb[m][:, :3]), "after": error_stats(ra[m][:, :3])}
    per_sensor = {name: {"rms_before": _rms(nb[m]), "rms_after": _rms(na[m]),
                         "rms_before_insample": _rms(b.error_norm(ins_b)[m]),
                         "rms_after_insample": _rms(b.error_norm(ins_a)[m])}
                  for name, m in b.report_groups().items() if m.any()}
    return BlockReport(
        kind=b.kind, unit=b.unit, n=len(b), rms_before=_rms(nb), rms_after=_rms(na),
        rms_before_insample=_rms(b.error_norm(ins_b)), rms_after_insample=_rms(b.error_norm(ins_a)),
        sensor_scale=scales.a, prior_scale=scales.k, noise_floor=floor,
        unexplained=math.sqrt(max(_rms(na) ** 2 - floor ** 2, 0.0)),
        nees_before=float(np.nanmean(nees_b)), nees_after=float(np.nanmean(nees_a)), per_group=per_group,
        per_sensor=per_sensor, structure=st.tests, dropped=int(getattr(b, "dropped", 0)))


def _effect_reports(run: Run, model: Sequence[Any], effects: Sequence[Effect]) -> list[EffectReport]:
    """Entries of the fitted effects: values, 95 % intervals (:mod:`covariance`), share of the held-out error,
    the measurements that see them, corrected ``camera_info`` for intrinsics."""
    pr, lin = run.problem, run.lin
    assert lin is not None
    if not effects:
        return []
    sys = pr.system(effects, effects, rewhiten=False)
    n_nuis = int(sum(ns.n_segments * ns.N.shape[1] for ns in sys.nuisances))
    pc = parameter_covariance(sys, np.arange(sys.n_columns), n_nuis)
    sd = np.sqrt(np.maximum(np.diag(pc.cov), 0.0))
    d_full, d_none = lin.heldout(model), lin.heldout(())
    total = float(np.nansum(d_none))
    out = []
    for k, (t, e) in enumerate(zip(model, effects)):
        sl = sys.cols[k]
        d_wo = lin.heldout(tuple(x for x in model if x != t))
        ok = np.isfinite(d_wo) & np.isfinite(d_full)
        seen = [pr.blocks[p.index].kind for p in sys.parts
                if np.abs(sys.G[p.start:p.stop, sl]).max(initial=0.0) > 0.0]
        names, vals, sg = e.param_names, e.params, sd[sl]
        out.append(EffectReport(
            name=e.name, location=e.location, parameters={p: float(v) for p, v in zip(names, vals)},
            ci={p: [float(v - 1.96 * s), float(v + 1.96 * s)] for p, v, s in zip(names, vals, sg)},
            sigma={p: float(s) for p, s in zip(names, sg)},
            share=float((d_wo[ok] - d_full[ok]).sum() / total) if total > 0 else 0.0,
            measurement="+".join(seen), frame=_frame(pr, e), camera_info=_camera_info(pr, e),
            variable=getattr(e, "variable", None), reference=getattr(e, "reference", None)))
    return out


def _frame(pr: Any, e: Effect) -> str | None:
    """The camera optical frame of a camera effect (``camera_extrinsics`` at its mount joint)."""
    if e.name == "camera_intrinsics":
        return e.location
    if e.name != "camera_extrinsics":
        return None
    for b in pr.blocks:
        frame = getattr(b, "camera_of_mount", lambda _: None)(e.location)
        if frame is not None:
            return str(frame)
    return getattr(e, "frame", None)


def _camera_info(pr: Any, e: Effect) -> dict[str, Any] | None:
    """The corrected ``K`` (row-major 9) and ``D`` (plumb_bob 5) of a ``camera_intrinsics`` effect."""
    if e.name != "camera_intrinsics":
        return None
    for b in pr.blocks:
        KD = getattr(b, "intrinsics_of", lambda _: None)(e.location)
        if KD is not None:
            K, D = e.corrected(*KD)  # type: ignore[attr-defined]
            return {"K": [float(v) for v in np.asarray(K).ravel()], "D": [float(v) for v in D],
                    "distortion_model": "plumb_bob"}
    return None


def summary(res: DiagnoseResult) -> str:
    """One paragraph: the effects found, the held-out residual per measurement before -> after, what is left."""
    if res.effects:
        head = f"found {len(res.effects)} effect(s): " + ", ".join(f"{e.name} at {e.location}" for e in res.effects)
    else:
        head = "no catalogue effect explains the residual significantly"
    lines = [head]
    for b in res.blocks.values():
        scale = 1e3 if b.unit == "m" else 1.0
        u = "mm" if b.unit == "m" else b.unit
        line = (f"{b.kind}: held-out RMS {scale * b.rms_before:.3f} {u} -> {scale * b.rms_after:.3f} {u} "
                f"(noise floor {scale * b.noise_floor:.3f} {u}; declared prior scaled by {b.prior_scale:.3g}, sensor "
                f"noise by {b.sensor_scale:.3g})")
        sig = [s for s in b.structure if s.significant]
        if sig:
            line += (f"; UNEXPLAINED: {scale * b.unexplained:.3f} {u} RMS above the floor follows the "
                     + " and the ".join(s.predictor for s in sig)
                     + f" (predictable part {max(s.gain for s in sig):.0%} of the held-out residual), "
                     "outside the effect catalogue")
        lines.append(line)
    if res.learned_prior is not None:
        lines.append(res.learned_prior.summary())
    return "; ".join(lines[:1]) + ("\n" + "\n".join(lines[1:]) if len(lines) > 1 else "")
