"""Small statistics shared by the diagnose stages: RMS, paired tests, robust z."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ppoe_core.analysis.diagnose.candidates import chain_jacobians
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.robot.tree import KinematicTree

_CHI2_DIM = {3: 3.0, 6: 6.0}


def _paired_t(d: np.ndarray) -> float:
    """Paired one-sample t statistic of the held-out error reductions ``d`` (N,); 0 if constant."""
    d = np.asarray(d, dtype=float)
    sd = float(d.std(ddof=1)) if d.size > 1 else 0.0
    return float(d.mean() / (sd / math.sqrt(d.size))) if sd > 0 else 0.0


def _rankdata(a: np.ndarray) -> np.ndarray:
    """Ranks 1..n of ``a`` (n,), ties given their average rank (``scipy.stats.rankdata``'s default, without
    importing scipy: about 3 s of a diagnose run)."""
    order = np.argsort(a, kind="mergesort")
    s = a[order]
    dense = np.cumsum(np.r_[True, s[1:] != s[:-1]])
    count = np.r_[np.flatnonzero(np.r_[True, s[1:] != s[:-1]]), a.size]
    out = np.empty(a.size)
    out[order] = 0.5 * (count[dense] + count[dense - 1] + 1)
    return out


def _signed_rank_z(d: np.ndarray) -> float:
    """Normal-approximation z of the one-sided Wilcoxon signed-rank test that ``d > 0``."""
    d = d[d != 0]
    n = d.size
    if n < 3:
        return 0.0
    w = float(np.sum(_rankdata(np.abs(d))[d > 0]))
    mu = n * (n + 1) / 4.0
    sd = math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
    return (w - mu) / sd


def _rms_m(R: np.ndarray) -> float:
    """RMS 3D norm [m] of the finite rows of residuals (N, 3)."""
    e2 = np.sum(R ** 2, axis=1)
    e2 = e2[np.isfinite(e2)]
    return float(np.sqrt(np.mean(e2))) if e2.size else float("nan")


def _rms3(r: np.ndarray) -> float:
    r = r[np.all(np.isfinite(r), axis=1)]
    return float(np.sqrt(np.mean(np.sum(r[:, :3] ** 2, axis=1)))) if r.size else float("nan")


def _rotation_covariance(stops: Stops, Fq: Mapping, Fx: Mapping, pert: Mapping[str, np.ndarray],
                         jnoise: Mapping[str, float]) -> np.ndarray:
    """First-order PPOE covariance (N, 3, 3) of the measured frame's rotation (right tangent at
    the frame) from the perturbation covariances and joint noise (rotation rows of eq. 18)."""
    C = np.zeros((len(stops), 3, 3))
    for jn, F in Fx.items():
        if jn in pert:
            C += F[:, 3:] @ pert[jn] @ np.swapaxes(F[:, 3:], -1, -2)
    for jn, sd in jnoise.items():
        if jn in Fq:
            C += sd ** 2 * Fq[jn][:, 3:, None] * Fq[jn][:, None, 3:]
    return C


def _point_covariance(tree: KinematicTree, stops: Stops, poses: Mapping, dq: Mapping, dxi: Mapping,
                      pert: Mapping[str, np.ndarray], jnoise: Mapping[str, float]) -> np.ndarray:
    """First-order PPOE covariance (N, 3, 3) of the measured point in the base/root frame axes,
    from the perturbation covariances (tangent right after each joint's origin) and joint noise."""
    Jq, Jx, _, _ = chain_jacobians(tree, stops, poses, dq, dxi)
    C = np.zeros((len(stops), 3, 3))
    for jn, J in Jx.items():
        if jn in pert:
            C += J @ pert[jn] @ np.swapaxes(J, -1, -2)
    for jn, s in jnoise.items():
        if jn in Jq:
            C += s ** 2 * Jq[jn][:, :, None] * Jq[jn][:, None, :]
    return C


def _pose_folds(pose: np.ndarray, folds: int, seed: int = 0) -> list[np.ndarray]:
    """Test masks of ``folds`` folds over poses (all observations of a pose in one fold)."""
    ids = np.unique(pose)
    perm = np.random.default_rng(seed).permutation(ids)
    return [np.isin(pose, perm[k::folds]) for k in range(folds)]


def _lstsq(G: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    H = G.T @ G
    s = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / np.outer(s, s)
    th = np.linalg.solve(Hs + 1e-12 * np.eye(len(s)), (G.T @ r) / s) / s
    return th, Hs
