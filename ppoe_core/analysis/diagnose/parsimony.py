"""The parsimony rule across steps (CONTRACT sec. 6): a chosen effect replaced by simpler ones that explain the
data as well.

Greedy forward selection compares one candidate with another; it cannot see that a six-parameter
``link_error`` found in one step is two one-parameter ``joint_offset`` s at two joints (an encoder offset
upstream turns the downstream frame).  After the selection, each chosen effect with more than two
parameters is tried against every single and every pair of simpler candidates (fewer parameters in
total), with the other chosen effects kept: the replacement with the fewest parameters (then the lowest
held-out error) whose held-out error is not significantly worse (paired t below 2 against the chosen set)
is taken.  Only the few replacements that best reproduce what the chosen effect adds to the predictions
(a small least-squares screen) are scored held-out.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.candidates import Candidate
from ppoe_core.analysis.diagnose.linear import LinearProblem, _identifiable_subset, _stack
from ppoe_core.analysis.diagnose.results import DiagnoseOptions
from ppoe_core.analysis.diagnose.stats import _paired_t
from ppoe_core.robot.tree import KinematicTree

__all__ = ["simplify"]

#: replacements scored held-out per chosen effect (the best by in-sample fit)
SCREEN = 6


def simplify(tree: KinematicTree, problem: LinearProblem, cands: Sequence[Candidate], chosen: list[Candidate],
             folds: Any, options: DiagnoseOptions, all_rows: np.ndarray,
             e2: np.ndarray) -> tuple[list[Candidate], list[dict[str, Any]]]:
    """Replace chosen effects by simpler ones where they explain the data as well (module docstring).

    Returns the (possibly) new chosen list and one record per replacement made (for the report).
    """
    n, dim = len(problem.stops), problem.stops.dim
    done: list[dict[str, Any]] = []
    for i in range(len(chosen)):
        c = chosen[i]
        if c.effect.n_params <= 2:
            continue
        others = chosen[:i] + chosen[i + 1:]
        simple = [k for k in cands if k.effect.n_params < c.effect.n_params and k.effect.name != "link_error"
                  and not any(k.key == o.key for o in others)]
        combos = [(a,) for a in simple] + [(a, b) for a, b in itertools.combinations(simple, 2)
                                           if a.effect.n_params + b.effect.n_params < c.effect.n_params
                                           and a.effect.location != b.effect.location]
        v = _contribution(problem, chosen, i, all_rows)
        scored = sorted(((_unexplained(v, combo), combo) for combo in combos), key=lambda z: z[0])
        best = None
        for _, combo in scored[:SCREEN]:
            if not _identifiable(tree, problem, others, combo, options, all_rows):
                continue
            _, _, e2c = problem.heldout(_stack(others + list(combo), n, dim), folds)
            ok = np.isfinite(e2) & np.isfinite(e2c)
            if ok.sum() < 3 or _paired_t(e2c[ok] - e2[ok]) >= 2.0:
                continue
            key = (sum(k.effect.n_params for k in combo), float(np.mean(e2c[ok])))
            if best is None or key < best[0]:
                best = (key, combo, e2c)
        if best is not None:
            done.append({"replaced": c.key, "by": [k.key for k in best[1]],
                         "heldout_mahalanobis2": best[0][1], "before": float(np.nanmean(e2))})
            chosen = others[:i] + list(best[1]) + others[i:]
            e2 = best[2]
    return chosen, done


def _contribution(problem: LinearProblem, chosen: list[Candidate], i: int, rows: np.ndarray) -> np.ndarray:
    """What chosen effect ``i`` adds to the predictions in the fit of the chosen set, flattened (N * dim,)."""
    n, dim = len(problem.stops), problem.stops.dim
    fit = problem.fit(_stack(chosen, n, dim), rows)
    start = sum(c.effect.n_params for c in chosen[:i])
    P = chosen[i].effect.n_params
    return (chosen[i].G @ fit.theta[start:start + P]).reshape(-1)


def _unexplained(v: np.ndarray, combo: Sequence[Candidate]) -> float:
    """Screening: the part of ``v`` the columns of ``combo`` cannot reproduce (relative least-squares residual).
    Cheap (no registration refit); only the best few combinations are then fitted and scored held out."""
    A = np.concatenate([k.G.reshape(v.size, -1) for k in combo], axis=1)
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    return float(np.linalg.norm(v - A @ coef) / max(float(np.linalg.norm(v)), 1e-300))


def _identifiable(tree: KinematicTree, problem: LinearProblem, others: list[Candidate],
                  combo: Sequence[Candidate], options: DiagnoseOptions, all_rows: np.ndarray) -> bool:
    """Each candidate of ``combo`` identifiable (and physically signed) with the rest, as in the selection."""
    base = list(others)
    for k in combo:
        k2, _, _ = _identifiable_subset(problem, base, k, options, tree, all_rows)
        if k2 is None or k2.effect.n_params != k.effect.n_params:
            return False
        base.append(k2)
    return True
