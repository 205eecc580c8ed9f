"""Paired tests of held-out gains (over robot poses): the t statistic and the one-sided signed-rank z."""

from __future__ import annotations

import math
import numpy as np

__all__ = ["paired_t", "rankdata", "signed_rank_z"]


def paired_t(d: np.ndarray) -> float:
    """Paired one-sample t statistic of the held-out error reductions ``d`` (N,); 0 if constant."""
    d = np.asarray(d, dtype=float)
    sd = float(d.std(ddof=1)) if d.size > 1 else 0.0
    return float(d.mean() / (sd / math.sqrt(d.size))) if sd > 0 else 0.0


def rankdata(a: np.ndarray) -> np.ndarray:
    """Ranks 1..n of ``a`` (n,), ties given their average rank (``scipy.stats.rankdata``'s default, without
    importing scipy: about 3 s of a diagnose run)."""
    order = np.argsort(a, kind="mergesort")
    s = a[order]
    dense = np.cumsum(np.r_[True, s[1:] != s[:-1]])
    count = np.r_[np.flatnonzero(np.r_[True, s[1:] != s[:-1]]), a.size]
    out = np.empty(a.size)
    out[order] = 0.5 * (count[dense] + count[dense - 1] + 1)
    return out


def signed_rank_z(d: np.ndarray) -> float:
    """Normal-approximation z of the one-sided Wilcoxon signed-rank test that ``d > 0``."""
    d = d[d != 0]
    n = d.size
    if n < 3:
        return 0.0
    w = float(np.sum(rankdata(np.abs(d))[d > 0]))
    mu = n * (n + 1) / 4.0
    sd = math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
    return (w - mu) / sd
