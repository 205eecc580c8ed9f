"""The data's own noise: two variance components per measurement block, and the whitening they give.

A block's residual row ``r_i`` (d components) is modelled as ``N(0, C_i)`` with ``C_i = a^2 S_i + k^2 Q_i``: ``S_i``
the declared sensor noise, ``Q_i`` the declared PPOE prior propagated to the measurement (first order, eq. 18).
``a`` (the sensor's scale) and ``k`` (the prior's scale) are estimated by maximum likelihood from the residual of
the current fit (Fisher scoring; in-sample residuals are corrected for the parameters fitted, ``dof``), so the
weights follow the data, not the declaration: a prior declared five times too loose gets ``k ~ 0.2`` (or 0 if the
data hold no random perturbation at all), a sensor whose residual is ten times its declared noise gets ``a ~ 10``.
``k`` is what the report calls the prior's estimated scale (``sigma_scale``: the NEES of the declared covariance).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["NoiseScales", "estimate_scales", "whitening", "mahalanobis2"]

#: lower bound of a scale (relative): a component estimated at zero keeps this much, for a regular whitening
MIN_SCALE = 1e-3


@dataclass
class NoiseScales:
    """Scales of one block's declared noise: ``a`` (sensor) and ``k`` (prior)."""

    a: float = 1.0
    k: float = 1.0


def estimate_scales(r: np.ndarray, S: np.ndarray, Q: np.ndarray, dof_fraction: float = 1.0,
                    start: NoiseScales | None = None) -> NoiseScales:
    """Maximum-likelihood scales of ``C_i = a^2 S_i + k^2 Q_i`` for residuals ``r`` (n, d) (module docstring):
    ``-2 log L = sum_i log det C_i + r_i^T C_i^-1 r_i`` minimised over ``log a^2``, ``log k^2`` (L-BFGS-B with the
    analytic gradient ``dL/dlam_j = sum_i tr(C_i^-1 D_j) - r_i^T C_i^-1 D_j C_i^-1 r_i``, from three starts, or from
    ``start``, a previous estimate: it is not convex).  The prior's share is kept only when it lowers ``-2 log L``
    by more than ``ln n`` (BIC) against the sensor alone (then ``k = 0``): with too few rows the two shapes are not
    told apart.

    ``dof_fraction`` (0, 1]: the share of the residual's degrees of freedom left after the fit (in-sample residuals
    are smaller than the noise by that factor).  Rows with non-finite residuals are ignored.
    """
    from scipy.optimize import minimize

    ok = np.all(np.isfinite(r), axis=1)
    r, S, Q = r[ok] / np.sqrt(dof_fraction), S[ok], Q[ok]
    if r.shape[0] == 0:
        return start or NoiseScales()
    has_q = bool(np.any(np.abs(Q) > 0))
    D = [S, Q] if has_q else [S]
    f, s_scale = _likelihood(r, S, Q if has_q else None)
    base = np.array([s_scale if s_scale is not None else _scale_of(r, S, 1.0)]
                    + ([_scale_of(r, Q, 1.0)] if has_q else []))
    lo = np.log(np.maximum(base, 1e-300) * MIN_SCALE ** 2)
    hi = np.log(np.maximum(base, 1e-300) * 1e2)

    # the likelihood is not convex in the two scales (one of them alone may explain the residual): start from each
    # extreme and between, keep the best
    starts = [np.log(np.maximum(w * base, np.exp(lo))) for w in ([0.5, 0.5], [1e-4, 0.9], [0.9, 1e-4])[:2 * len(D) - 1]]
    if start is not None:  # a previous estimate: refine it alone (the residual changed a little since)
        prev = np.array([start.a ** 2, start.k ** 2])[:len(D)]
        starts = [np.log(np.clip(prev, np.exp(lo), np.exp(hi)))]
    sols = [minimize(f, x0[:len(D)], jac=True, method="L-BFGS-B", bounds=list(zip(lo, hi))) for x0 in starts]
    best = min(sols, key=lambda z: float(z.fun))
    lam = np.exp(best.x)
    if has_q and f(np.array([np.log(base[0]), lo[1]]))[0] - float(best.fun) < np.log(r.shape[0]):
        return NoiseScales(a=float(np.sqrt(base[0])), k=0.0)  # the prior's share is not needed (BIC)
    return NoiseScales(a=float(np.sqrt(lam[0])), k=float(np.sqrt(lam[1])) if has_q else 0.0)


def _likelihood(r: np.ndarray, S: np.ndarray, Q: np.ndarray | None
                ) -> tuple[Callable[[np.ndarray], tuple[float, np.ndarray]], float | None]:
    """``-2 log L`` of :func:`estimate_scales` and its gradient as a function of ``log [a^2, k^2]`` (``[log a^2]``
    without ``Q``), and :func:`_scale_of` ``S`` (None: not computed).  ``S`` and ``Q`` are diagonalised together
    once (``S = L L^T``, ``L^-1 Q L^-T = U diag(mu) U^T``): then ``C = L U diag(a^2 + k^2 mu) U^T L^T`` and every
    evaluation is elementwise; a singular ``S`` keeps the direct inverse per evaluation."""
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return _likelihood_direct(r, [S] if Q is None else [S, Q]), None
    Li = np.linalg.inv(L)
    logdet_s = 2.0 * float(np.sum(np.log(np.einsum("nii->ni", L))))
    if Q is None:
        mu, t2 = np.zeros_like(r), np.einsum("nij,nj->ni", Li, r) ** 2
    else:
        mu, U = np.linalg.eigh(Li @ Q @ np.swapaxes(Li, -1, -2))
        t2 = np.einsum("nji,njk,nk->ni", U, Li, r) ** 2
    s_scale = float(np.mean(np.sum(t2, axis=1))) / r.shape[1]  # mean r^T S^-1 r / d
    mu, t2 = mu.reshape(-1), t2.reshape(-1)

    def f(x: np.ndarray) -> tuple[float, np.ndarray]:
        lam = np.exp(x)
        c = lam[0] + lam[1] * mu if lam.size > 1 else np.full_like(mu, lam[0])  # C's eigenvalues, whitened by S
        inv = 1.0 / c
        w = inv - t2 * inv * inv  # d/dc of log c + t2 / c
        val = logdet_s + float(np.sum(np.log(c)) + np.sum(t2 * inv))
        grad = np.array([np.sum(w), *([float(np.sum(w * mu))] if lam.size > 1 else [])]) * lam
        return val, grad

    return f, s_scale


def _likelihood_direct(r: np.ndarray, D: list[np.ndarray]) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    """:func:`_likelihood` with an inverse of ``C`` per row and evaluation (a singular sensor covariance)."""

    def f(x: np.ndarray) -> tuple[float, np.ndarray]:
        lam = np.exp(x)
        C = sum(l_ * Dj for l_, Dj in zip(lam, D))
        Ci = np.linalg.inv(C)
        u = np.einsum("nij,nj->ni", Ci, r)
        val = float(np.sum(np.linalg.slogdet(C)[1]) + np.einsum("ni,ni->", r, u))
        grad = np.array([np.einsum("nij,nji->", Ci, Dj) - np.einsum("ni,nij,nj->", u, Dj, u) for Dj in D]) * lam
        return val, grad

    return f


def _scale_of(r: np.ndarray, D: np.ndarray, dof_fraction: float) -> float:
    """The variance scale if ``D`` alone explained ``r``: mean ``r^T D^-1 r / d`` (pseudo-inverse)."""
    Di = np.linalg.pinv(D)
    return float(np.mean(np.einsum("ni,nij,nj->n", r, Di, r)) / r.shape[1] / dof_fraction)


def whitening(S: np.ndarray, Q: np.ndarray, scales: NoiseScales) -> np.ndarray:
    """``W_i`` (n, d, d) with ``W_i C_i W_i^T = I``, ``C_i = a^2 S_i + k^2 Q_i`` (inverse Cholesky factor)."""
    C = scales.a ** 2 * S + scales.k ** 2 * Q
    d = C.shape[-1]
    C = C + 1e-15 * np.trace(C, axis1=-2, axis2=-1)[:, None, None] / d * np.eye(d)
    return np.linalg.inv(np.linalg.cholesky(C))


def mahalanobis2(r: np.ndarray, S: np.ndarray, Q: np.ndarray, scales: NoiseScales) -> np.ndarray:
    """``r_i^T C_i^-1 r_i`` (n,) (NaN rows stay NaN)."""
    C = scales.a ** 2 * S + scales.k ** 2 * Q
    ok = np.all(np.isfinite(r), axis=1)
    out = np.full(r.shape[0], np.nan)
    out[ok] = np.einsum("ni,nij,nj->n", r[ok], np.linalg.inv(C[ok]), r[ok])
    return out
