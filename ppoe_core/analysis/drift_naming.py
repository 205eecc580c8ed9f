"""Naming a drift the online effects do not track: the calibration engine's candidate screening on the drift
monitor's window (docs/online.md "Drift monitor").  The ONE place where the online loop calls the diagnose library
(only its public names: :func:`~ppoe_core.analysis.diagnose.candidate_effects`, :class:`Stops`), so that it can be
re-pointed when the engine changes.

At an alarm of :class:`~ppoe_core.estimation.online_monitor.DriftMonitor`, the last measurements of every source
(joints, measured values, context: temperature, time) are linearised at the current estimate: whitened residual
``y_k = L_k^-1 (z_k ominus h_k)`` (``L_k L_k^T`` = sensor noise plus the PPOE covariance, the filter's ``R``), the
whitened Jacobian of the tracked parameters and, for every candidate effect of the catalogue at every plausible
location of the measured chains (the engine's :func:`candidate_effects`, plus the constant ``base_tilt`` and each
seen camera's ``camera_extrinsics``), its whitened Jacobian through the same chain rule as the filter.

Screening is the engine's selection routine on that linear problem
(:func:`~ppoe_core.analysis.diagnose.select_linear`: penalised held-out likelihood over ``folds`` interleaved folds of
the window's measurements, the tracked parameters free in every fit, group moves and the backward pass, docs/
diagnose.md "Selection"); a term is named when its step lowers the held-out residual by at least ``min_gain``
(relative) with a paired t statistic over the held-out measurements of at least ``min_t``, is identifiable with the
effects already chosen (scaled condition number below ``max_condition``) and has a physical sign (compliances);
up to ``max_named`` effects.  A thermal candidate takes the first temperature of the run as its reference (the
diagnosed model held there).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose import (
    ChosenTerm,
    LinearProblem,
    SelectionOptions,
    Stops,
    candidate_effects,
    select_linear,
)
from ppoe_core.errors import PpoeError
from ppoe_core.estimation.online_config import ONLINE_EFFECT_NAMES
from ppoe_core.estimation.online_effects import OnlineEffects
from ppoe_core.estimation.online_models import OnlineRow
from ppoe_core.estimation.online_monitor import DriftMonitor, DriftNaming, MonitorSettings, NamedEffect
from ppoe_core.model.effects import Effect, make_effect

__all__ = ["SAME_COLUMNS", "NamingSettings", "make_monitor", "name_drift", "window_candidates"]

#: two candidates are the same on a window when the cosines of all principal angles between their whitened columns
#: exceed this (e.g. the growth of two segments that lie on one axis: proportional columns)
SAME_COLUMNS = 0.9999


@dataclass(frozen=True)
class NamingSettings:
    """Screening parameters: ``folds`` of the cross-validation (5), ``min_gain`` relative held-out gain (0.2),
    ``min_t`` paired t statistic (3.0), ``max_named`` effects (2), ``max_condition`` of the scaled normal matrix
    (1e8)."""

    folds: int = 5
    min_gain: float = 0.2
    min_t: float = 3.0
    max_named: int = 2
    max_condition: float = 1e8


@dataclass
class _Window:
    """The window linearised: per row its whitened residual, whitened ``H_X`` per part and the parts' chains."""

    y: list[np.ndarray]
    parts: list[list[tuple[np.ndarray, Any]]]   # per row: (W_p H_X (m_p, 6), FrameChain) of each part
    rows: list[OnlineRow]


def _linearise(filt: OnlineEffects, rows: Sequence[OnlineRow]) -> _Window:
    ys, parts, kept = [], [], []
    for row in rows:
        try:
            lins = filt.linearize(row)
        except PpoeError:
            continue  # a row the current estimate cannot evaluate (a frame behind the camera): left out
        y, ps = [], []
        for lin in lins:
            W = np.linalg.inv(np.linalg.cholesky(lin.noise))
            y.append(W @ lin.residual)
            ps.append((W @ lin.H_state, lin.chain))
        ys.append(np.concatenate(y))
        parts.append(ps)
        kept.append(row)
    return _Window(ys, parts, kept)


def _columns(filt: OnlineEffects, win: _Window, effects: Sequence[Effect] | None) -> list[np.ndarray] | None:
    """Whitened Jacobian (m_k, P) per row of ``effects`` (None: the tracked ones); None if an effect cannot be
    evaluated on the window (a context it needs is missing)."""
    out = []
    try:
        for row, ps in zip(win.rows, win.parts):
            out.append(np.concatenate([A @ filt.param_jacobian(row.q, ch, effects, row.context) for A, ch in ps]))
    except PpoeError:
        return None
    return out


def _window_stops(filt: OnlineEffects, rows: Sequence[OnlineRow]) -> Stops:
    """The window as engine stops (one per measured frame of each row): what :func:`candidate_effects` needs (the
    measured chains and the context); no measured values (the screening here works on the online residuals)."""
    q_rows, links, temps, times = [], [], [], []
    for row in rows:
        for part in row.parts:
            for frame in {part.ref, part.link}:
                q_rows.append(row.q)
                links.append(frame)
                temps.append(row.context.get("temperature", np.nan))
                times.append(row.stamp)
    n = len(links)
    names = filt.model.joint_names
    q = {j: np.array([r.get(j, 0.0) for r in q_rows]) for j in names}
    ctx: dict[str, Any] = {"time": np.asarray(times, float)}
    if np.all(np.isfinite(temps)):
        ctx["temperature"] = np.asarray(temps, float)
    zi, ones = np.zeros(n, dtype=int), np.ones(n, dtype=bool)
    return Stops(q=q, p_meas=np.zeros((n, 3)), kind="point", link=links[0], point=np.zeros(3), sigma=1.0,
                 session=zi, session_names=["online"], group=zi, group_names=["online"], reg_mask=ones,
                 score_mask=ones, context=ctx, links=np.asarray(links, dtype=object))


def window_candidates(filt: OnlineEffects, rows: Sequence[OnlineRow]) -> list[Effect]:
    """Candidate effects on the window (module docstring), none already tracked; thermal ones referenced to the
    run's first temperature."""
    tree, root = filt.tree, filt.model.robot.root
    cands = candidate_effects(tree, _window_stops(filt, rows))
    if filt.model.robot.children(root):
        cands.append(make_effect("base_tilt", root, tree))
    cams = {p.ref for r in rows for p in r.parts if type(p.obs).__name__ == "TagBearingModel"}
    cands += [make_effect("camera_extrinsics", c, tree) for c in sorted(cams) if c != root]
    ref = filt.reference_temperature
    out: list[Effect] = []
    seen = {(t.effect.name, t.effect.location) for t in filt.tracked} | {(e.name, e.location) for e in filt.fixed}
    for e in cands:
        if e.name == "thermal_growth" and getattr(e, "variable", "") == "temperature" and ref is not None:
            e = make_effect("thermal_growth", e.location, tree, variable="temperature", reference=ref)
        key = (e.name, e.location, e.param_names)
        if (e.name, e.location) in seen or key in {(c.name, c.location, c.param_names) for c in out}:
            continue
        out.append(e)
    return out


def _fit(G: np.ndarray, y: np.ndarray, max_condition: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Least squares ``y ~ G d`` with column scaling; (d, (G^T G)^-1), or None when not identifiable."""
    d = np.linalg.norm(G, axis=0)
    if np.any(d <= 1e-12 * max(1.0, float(d.max(initial=0.0)))):
        return None
    Gs = G / d
    N = Gs.T @ Gs
    ev = np.linalg.eigvalsh(N)
    if ev[0] <= 0 or ev[-1] / ev[0] > max_condition:
        return None
    Ni = np.linalg.inv(N)
    return (Ni @ (Gs.T @ y)) / d, Ni / np.outer(d, d)


def _problem(filt: OnlineEffects, win: _Window, s: NamingSettings) -> tuple[LinearProblem, list[Effect]] | None:
    """The window as the engine's linear problem: rows = measurements (interleaved folds), the tracked parameters
    free, every candidate that can be evaluated on the window; None if the tracked ones cannot be identified."""
    base = _columns(filt, win, None)
    assert base is not None  # the tracked effects are evaluated on every update
    if base[0].shape[1] and _fit(np.concatenate(base), np.concatenate(win.y), s.max_condition) is None:
        return None
    cands, cols = [], []
    for e in window_candidates(filt, win.rows):
        c = _columns(filt, win, [e])
        if c is not None:
            cands.append(e)
            cols.append(np.concatenate(c))
    sizes = [y.size for y in win.y]
    cluster = np.repeat(np.arange(len(sizes)), sizes)
    problem = LinearProblem(np.concatenate(win.y), np.concatenate(base), cands, cols, cluster,
                            np.arange(len(sizes)) % s.folds, filt.tree)
    return problem, cands


def name_drift(filt: OnlineEffects, rows: Sequence[OnlineRow], settings: NamingSettings | None = None
               ) -> DriftNaming:
    """The effects that explain the drift on ``rows`` (module docstring)."""
    s = settings or NamingSettings()
    win = _linearise(filt, rows)
    n = len(win.rows)
    if n < 2 * s.folds:
        return DriftNaming([], n, 0, f"{n} usable measurements in the window, fewer than {2 * s.folds}")
    built = _problem(filt, win, s)
    if built is None:
        return DriftNaming([], n, 0, "the tracked effects are not identifiable on the window")
    problem, cands = built
    sel = select_linear(problem, SelectionOptions(min_t=s.min_t, min_gain=s.min_gain, max_effects=s.max_named,
                                                  max_condition=s.max_condition))
    if not sel.chosen:
        return DriftNaming([], n, len(cands), f"no candidate lowers the penalised held-out residual by "
                                              f"{100 * s.min_gain:.0f} % with t >= {s.min_t:g} "
                                              f"(screened {len(cands)})")
    return _named(filt, problem, sel.chosen, win, n, len(cands))


def _named(filt: OnlineEffects, problem: LinearProblem, chosen: list[ChosenTerm], win: _Window, n: int,
           screened: int) -> DriftNaming:
    """The full-window fit of the tracked set plus the chosen terms: estimates, sigmas, covariance."""
    y = np.concatenate(win.y)
    Gf = np.concatenate([problem.free, *(problem.columns[c.candidate][:, list(c.comps)] for c in chosen)], axis=1)
    fit = _fit(Gf, y, math.inf)
    assert fit is not None  # the selection checked identifiability
    d, cov = fit
    r = y - Gf @ d
    cov = cov * max(1.0, float(r @ r) / max(1, y.size - d.size))
    P = filt.theta.shape[0]
    k, named = P, []
    for c in chosen:
        e = c.effect
        sl = slice(k, k + len(c.comps))
        named.append(NamedEffect(e.with_params(d[sl]), c.gain, c.t, np.sqrt(np.diag(cov)[sl]),
                                 e.name in ONLINE_EFFECT_NAMES, _equivalent(problem, c.candidate)))
        k += len(c.comps)
    theta = np.concatenate([filt.theta + d[:P], d[P:]])
    return DriftNaming(named, n, screened, "", theta, cov)


def _equivalent(problem: LinearProblem, i: int) -> list[str]:
    """Candidates whose window columns span the same space as candidate ``i``'s (cosines of all principal angles
    above :data:`SAME_COLUMNS`): the window cannot tell them apart (``name@location``)."""
    A = np.linalg.qr(problem.columns[i])[0]
    out = []
    for j, c in enumerate(problem.columns):
        e = problem.candidates[j]
        if j == i or c.shape[1] != A.shape[1]:
            continue
        if np.linalg.svd(A.T @ np.linalg.qr(c)[0], compute_uv=False).min() > SAME_COLUMNS:
            out.append(f"{e.name}@{e.location}")
    return out


def make_monitor(settings: MonitorSettings | None = None, naming: NamingSettings | None = None) -> DriftMonitor:
    """The drift monitor with this module's namer (what ``ppoe evaluate --online`` and the live hook run)."""
    return DriftMonitor(settings, lambda filt, rows: name_drift(filt, rows, naming))
