"""Fourth-order covariance of a compounded pose (Barfoot & Furgale 2014, right perturbations; the paper's eq. 15
beyond second order).

Covariances live in the tangent space at the mean (docs/conventions.md); ``[rho; theta]`` order."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core.model.chain import Array, _Chain

__all__ = ["compound_fourth_order", "compound_fourth_order_batch_last"]


def _covop1(A: Array) -> Array:
    """Barfoot's ``<<A>> = -tr(A) I + A`` for ``(..., 3, 3)``."""
    tr = np.trace(A, axis1=-2, axis2=-1)
    return A - tr[..., None, None] * np.eye(3)


def _covop2(A: Array, B: Array) -> Array:
    """Barfoot's ``<<A, B>> = <<A>> <<B>> + <<B A>>``."""
    return _covop1(A) @ _covop1(B) + _covop1(B @ A)


def compound_fourth_order(cov1: ArrayLike, cov2: ArrayLike) -> Array:
    """Covariance of ``Exp(xi1) Exp(xi2)`` to fourth order (Barfoot & Furgale 2014, eq. 55).

    Both covariances live in the SAME tangent space (transport them first, e.g. for right
    perturbations ``X1 Exp(x1) X2 Exp(x2) = X1 X2 Exp(Ad_{X2^-1} x1) Exp(x2)`` gives
    ``cov1 = Ad_{X2^-1} Sigma_1 Ad^T``, ``cov2 = Sigma_2``, both at ``X1 X2``).  Ported from
    pytransform3d's ``_compound_cov_fourth_order_terms`` (which orders twists
    ``[omega; v]``) to our ``[rho; theta]`` order, broadcasting over batch axes.

    Parameters
    ----------
    cov1, cov2 : array_like, shape (..., 6, 6)
        Covariances of the left and the right factor's twist ``[rho; theta]``.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``cov1 + cov2 + (A1 cov2 + cov2 A1^T + A2 cov1 + cov1 A2^T) / 12 + B / 4``.
    """
    c1 = np.asarray(cov1, dtype=float)
    c2 = np.asarray(cov2, dtype=float)
    if c1.shape != c2.shape:
        c1, c2 = np.broadcast_arrays(c1, c2)
    rr1, rt1, tt1 = c1[..., :3, :3], c1[..., :3, 3:], c1[..., 3:, 3:]
    rr2, rt2, tt2 = c2[..., :3, :3], c2[..., :3, 3:], c2[..., 3:, 3:]
    tr1 = np.swapaxes(rt1, -1, -2)
    tr2 = np.swapaxes(rt2, -1, -2)
    # all <<.>> and <<., .>> operands stacked, so the work is a handful of numpy calls
    # <<A, B>> = <<A>> <<B>> + <<B A>> for the pairs of Barfoot & Furgale's B blocks:
    #   B_rr = <<tt1, rr2>> + <<tr1, rt2>> + <<rt1, tr2>> + <<rr1, tt2>>
    #   B_rt = <<tt1, tr2>> + <<tr1, tt2>>,   B_tt = <<tt1, tt2>>
    left = np.stack([tt1, tr1, rt1, rr1, tt1, tr1, tt1])
    right = np.stack([rr2, rt2, tr2, tt2, tr2, tt2, tt2])
    ops = _covop1(np.concatenate([left, right, right @ left, np.stack([rt1 + tr1, rt2 + tr2])]))
    n = 7
    pair = ops[:n] @ ops[n : 2 * n] + ops[2 * n : 3 * n]
    shape = c1.shape
    B = np.empty(shape)
    B[..., :3, :3] = pair[0] + pair[1] + pair[2] + pair[3]
    B12 = pair[4] + pair[5]
    B[..., :3, 3:] = B12
    B[..., 3:, :3] = np.swapaxes(B12, -1, -2)
    B[..., 3:, 3:] = pair[6]
    # A_i = [[<<tt_i>>, <<rt_i + rt_i^T>>], [0, <<tt_i>>]]
    A1 = np.zeros(shape)
    A1[..., :3, :3] = A1[..., 3:, 3:] = ops[0]  # <<tt1>> (left[0] = tt1)
    A1[..., :3, 3:] = ops[3 * n]
    A2 = np.zeros(shape)
    A2[..., :3, :3] = A2[..., 3:, 3:] = ops[n + 3]  # <<tt2>> (right[3] = tt2)
    A2[..., :3, 3:] = ops[3 * n + 1]
    X = A1 @ c2 + A2 @ c1
    return c1 + c2 + (X + np.swapaxes(X, -1, -2)) / 12.0 + B / 4.0


def _fourth_order(ch: _Chain, G: Array) -> Array:
    """Sequential fourth-order compounding of the local site covariances.

    ``G`` (m, N, 6) local columns; returns ``(N, 6, 6)``.
    """
    cov = None
    for k in range(len(ch.site_L)):
        Gk = G[ch.col_site == k]  # (r, N, 6)
        Sk = np.einsum("rni,rnj->nij", Gk, Gk)
        cov = Sk if cov is None else compound_fourth_order(cov, Sk)
    assert cov is not None
    return cov


def _mm3(A: Array, B: Array) -> Array:
    """3x3 matrix products over trailing batch axes: ``(3, 3, ...) x (3, 3, ...)``."""
    out = np.empty(np.broadcast_shapes(A.shape, B.shape))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return out


def _op1(A: Array) -> Array:
    """``<<A>> = -tr(A) I + A`` for ``(3, 3, ...)``."""
    out = A.copy()
    tr = A[0, 0] + A[1, 1] + A[2, 2]
    for i in range(3):
        out[i, i] -= tr
    return out


def compound_fourth_order_batch_last(c1: Array, c2: Array) -> Array:
    """:func:`compound_fourth_order` for covariances ``(6, 6, N)`` (batch last, elementwise)."""
    rr1, rt1, tt1 = c1[:3, :3], c1[:3, 3:], c1[3:, 3:]
    rr2, rt2, tt2 = c2[:3, :3], c2[:3, 3:], c2[3:, 3:]
    tr1, tr2 = rt1.swapaxes(0, 1), rt2.swapaxes(0, 1)
    left = np.stack([tt1, tr1, rt1, rr1, tt1, tr1, tt1], axis=2)  # (3, 3, 7, N)
    right = np.stack([rr2, rt2, tr2, tt2, tr2, tt2, tt2], axis=2)
    oL, oR = _op1(left), _op1(right)
    pair = _mm3(oL, oR) + _op1(_mm3(right, left))
    out = c1 + c2
    out[:3, :3] += (pair[:, :, 0] + pair[:, :, 1] + pair[:, :, 2] + pair[:, :, 3]) / 4.0
    B12 = (pair[:, :, 4] + pair[:, :, 5]) / 4.0
    out[:3, 3:] += B12
    out[3:, :3] += B12.swapaxes(0, 1)
    out[3:, 3:] += pair[:, :, 6] / 4.0
    # X = A1 c2 + A2 c1 with A_i = [[a_i, b_i], [0, a_i]], a_i = <<tt_i>>, b_i = <<rt_i + tr_i>>
    a1, a2 = oL[:, :, 0], oR[:, :, 3]
    b1, b2 = _op1(rt1 + tr1), _op1(rt2 + tr2)
    P = _mm3(
        np.stack([a1, a1, a1, a1, b1, b1, a2, a2, a2, a2, b2, b2], axis=2),
        np.stack([rr2, rt2, tr2, tt2, tr2, tt2, rr1, rt1, tr1, tt1, tr1, tt1], axis=2),
    )
    X = np.empty_like(c1)
    X[:3, :3] = P[:, :, 0] + P[:, :, 4] + P[:, :, 6] + P[:, :, 10]
    X[:3, 3:] = P[:, :, 1] + P[:, :, 5] + P[:, :, 7] + P[:, :, 11]
    X[3:, :3] = P[:, :, 2] + P[:, :, 8]
    X[3:, 3:] = P[:, :, 3] + P[:, :, 9]
    out += (X + X.swapaxes(0, 1)) / 12.0
    return out


def _fourth_order_batch_last(ch: _Chain, G: Array) -> Array:
    """Sequential fourth-order compounding, ``G`` (m, 6, N) -> ``(6, 6, N)``."""
    cov = None
    for k in range(len(ch.site_L)):
        _, _, _, _, c0, c1 = ch.site_cols[k]
        Gk = G[c0:c1]
        Sk = np.einsum("rin,rjn->ijn", Gk, Gk)
        cov = Sk if cov is None else compound_fourth_order_batch_last(cov, Sk)
    assert cov is not None
    return cov
