"""The noise scales' likelihood (ppoe_core.analysis.diagnose.noise): the jointly diagonalised evaluation finds the
same maximum-likelihood scales as the direct one (an inverse of ``a^2 S_i + k^2 Q_i`` per row, written out here as
the reference), with and without a prior part, and a singular sensor covariance still works."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from ppoe_core.analysis.diagnose.noise import estimate_scales


def _rows(seed: int, n: int = 400, d: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-row sensor covariances S (full, differing per row), a rank-2 prior Q and residuals drawn from
    ``a^2 S + k^2 Q`` with a = 0.7, k = 2.5."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, d, d)) * 0.3 + np.eye(d)
    S = A @ np.swapaxes(A, -1, -2) * 1e-6
    B = rng.normal(size=(n, d, 2)) * 1e-3
    Q = B @ np.swapaxes(B, -1, -2)
    C = 0.7 ** 2 * S + 2.5 ** 2 * Q
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, d)))
    return r, S, Q, C


def _direct(r: np.ndarray, D: list[np.ndarray], x0: np.ndarray) -> np.ndarray:
    """The reference: ``-2 log L`` with a per-row inverse, minimised over the log scales (Nelder-Mead, no
    gradient)."""

    def f(x: np.ndarray) -> float:
        C = sum(np.exp(xj) * Dj for xj, Dj in zip(x, D))
        return float(np.sum(np.linalg.slogdet(C)[1]) + np.einsum("ni,nij,nj->", r, np.linalg.inv(C), r))

    return np.sqrt(np.exp(minimize(f, x0, method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-9,
                                                                         "maxiter": 4000}).x))


@pytest.mark.parametrize("seed", [3, 11])
def test_the_scales_are_the_direct_likelihoods_maximum(seed: int) -> None:
    r, S, Q, _ = _rows(seed)
    got = estimate_scales(r, S, Q)
    a, k = _direct(r, [S, Q], np.log([0.5, 4.0]))
    assert got.a == pytest.approx(a, rel=1e-4)
    assert got.k == pytest.approx(k, rel=1e-4)
    assert 0.5 < got.a < 1.0 and 1.5 < got.k < 3.5  # near the truth the rows were drawn with


def test_without_a_prior_the_sensor_scale_is_the_direct_one() -> None:
    r, S, _, _ = _rows(5)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(S), np.random.default_rng(6).normal(size=r.shape)) * 1.7
    got = estimate_scales(r, S, np.zeros_like(S))
    (a,) = _direct(r, [S], np.log([1.0]))
    assert got.k == 0.0
    assert got.a == pytest.approx(a, rel=1e-4)
    assert got.a == pytest.approx(1.7, rel=0.1)


def test_a_singular_sensor_covariance_is_estimated_too() -> None:
    r, S, Q, _ = _rows(7)
    S[:, 2, :] = S[:, :, 2] = 0.0  # no sensor noise on the third axis: only the prior explains it there
    got = estimate_scales(r, S, Q)
    assert np.isfinite(got.a) and np.isfinite(got.k) and got.k > 0.0
