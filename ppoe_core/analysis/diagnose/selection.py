"""Greedy forward selection by held-out gain: the one selection loop of the pixel and accelerometer stages.

A candidate ``i`` joins the chosen set when the design of ``chosen + [i]`` is identifiable (condition number of the
column-scaled normal matrix below ``max_condition``; optional extra ``check``, e.g. no negative compliance) and it
gives the largest held-out gain ``1 - sum(new) / sum(base)`` of the held-out squared whitened errors; it is accepted
when that gain is at least ``min_gain`` with a paired t statistic or a one-sided signed-rank z >= ``min_t`` over the
held-out units (poses or stops): the rank test sees an improvement confined to some units (images in motion, for
a camera's time offset) that the t statistic, dominated by their spread, misses.  The tracker/pose stage
(:func:`ppoe_core.analysis.diagnose.engine.diagnose`) screens in-sample first and picks by held-out Mahalanobis
error; it shares :func:`~ppoe_core.analysis.diagnose.stats._paired_t` with this loop.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.stats import _lstsq, _paired_t, _signed_rank_z

__all__ = ["GainSelection", "select_by_heldout_gain"]


@dataclass
class GainSelection:
    """Chosen candidate indices, accepted steps, rejections, the final held-out errors per unit and the history of
    their sums (one entry before any candidate, one per accepted step)."""

    chosen: list[int] = field(default_factory=list)
    steps: list[dict[str, Any]] = field(default_factory=list)
    rejected: list[dict[str, Any]] = field(default_factory=list)
    base: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hist: list[float] = field(default_factory=list)
    base0: np.ndarray = field(default_factory=lambda: np.zeros(0))


def select_by_heldout_gain(n_candidates: int, name: Callable[[int], str],
                           design: Callable[[Sequence[int]], np.ndarray],
                           heldout: Callable[[Sequence[int]], np.ndarray], e0: np.ndarray, *, max_effects: int,
                           max_condition: float, min_gain: float, min_t: float, skip_rejected: bool = False,
                           check: Callable[[int, np.ndarray], str | None] | None = None) -> GainSelection:
    """Forward selection (module docstring).

    Parameters
    ----------
    n_candidates : number of candidates; ``name(i)`` describes candidate ``i``
    design : ``idx -> (rows, columns)`` whitened Jacobian of the candidates ``idx`` (with any nuisance columns)
    heldout : ``idx -> (units,)`` held-out squared whitened error per unit with the candidates ``idx``
    e0 : whitened residual, flattened to the rows of ``design``
    skip_rejected : a candidate rejected once is not tried again
    check : ``(i, theta) -> reason`` to reject candidate ``i`` from its in-sample fit ``theta`` (None: keep)
    """
    sel = GainSelection()
    sel.base = heldout(sel.chosen)
    sel.base0 = sel.base.copy()
    sel.hist = [float(sel.base.sum())]
    while len(sel.chosen) < max_effects:
        best = _best_by_gain(n_candidates, name, design, heldout, e0, sel, max_condition, skip_rejected, check)
        if best is None:
            break
        i, gain, t, new, cond = best
        z = _signed_rank_z(sel.base - new)
        step = {"effect": name(i), "heldout_gain": gain, "t": t, "z": z, "condition": cond}
        if gain < min_gain or max(t, z) < min_t:
            sel.rejected.append({**step, "reason": f"held-out gain {gain:.3f} (min {min_gain}), t {t:.2f} and "
                                                   f"signed-rank z {z:.2f} (min {min_t})"})
            break
        sel.steps.append(step)
        sel.chosen.append(i)
        sel.base = new
        sel.hist.append(float(new.sum()))
    return sel


def _best_by_gain(n_candidates: int, name: Callable[[int], str], design: Callable[[Sequence[int]], np.ndarray],
                  heldout: Callable[[Sequence[int]], np.ndarray], e0: np.ndarray, sel: GainSelection,
                  max_condition: float, skip_rejected: bool,
                  check: Callable[[int, np.ndarray], str | None] | None) -> tuple | None:
    """``(i, gain, t, new held-out errors, condition)`` of the identifiable candidate with the largest gain."""
    best = None
    for i in range(n_candidates):
        if i in sel.chosen or (skip_rejected and any(r.get("effect") == name(i) for r in sel.rejected)):
            continue
        idx = sel.chosen + [i]
        th, Hs = _lstsq(design(idx), e0.reshape(-1))
        cond = float(np.linalg.cond(Hs))
        if not np.isfinite(cond) or cond > max_condition:
            sel.rejected.append({"effect": name(i), "reason": f"not identifiable (condition {cond:.3g})"})
            continue
        reason = check(i, th) if check is not None else None
        if reason is not None:
            sel.rejected.append({"effect": name(i), "reason": reason})
            continue
        new = heldout(idx)
        d = sel.base - new
        gain = float(d.sum() / max(sel.base.sum(), 1e-300))
        t = _paired_t(d)
        if best is None or gain > best[1]:
            best = (i, gain, t, new, cond)
    return best
