"""Fourth-order covariance of a compounded pose (Barfoot & Furgale 2014, right perturbations; the paper's eq. 15
beyond second order), compiled (numba) with the batch axis innermost.

Covariances live in the tangent space at the mean (docs/conventions.md); ``[rho; theta]`` order.  Ported from
pytransform3d's ``_compound_cov_fourth_order_terms`` (BSD-3; it orders twists ``[omega; v]``)."""

from __future__ import annotations

import numpy as np
from ppoe_core.jit import njit
from numpy.typing import ArrayLike

__all__ = ["compound_fourth_order", "compound_chunk", "CHUNK"]

#: configurations per call of the compiled compounding
CHUNK = 64

# blocks of the two covariances, in the work array: rr1 rt1 tr1 tt1 rr2 rt2 tr2 tt2
_RR1, _RT1, _TR1, _TT1, _RR2, _RT2, _TR2, _TT2 = range(8)
# Barfoot & Furgale's B blocks, <<A, B>> = <<A>> <<B>> + <<B A>> over the pairs (left, right):
#   B_rr = <<tt1, rr2>> + <<tr1, rt2>> + <<rt1, tr2>> + <<rr1, tt2>>,  B_rt = <<tt1, tr2>> + <<tr1, tt2>>,
#   B_tt = <<tt1, tt2>>;   target: 0 = rr, 1 = rt, 3 = tt
_PAIR_LEFT = np.array([_TT1, _TR1, _RT1, _RR1, _TT1, _TR1, _TT1], dtype=np.int64)
_PAIR_RIGHT = np.array([_RR2, _RT2, _TR2, _TT2, _TR2, _TT2, _TT2], dtype=np.int64)
_PAIR_TARGET = np.array([0, 0, 0, 0, 1, 1, 3], dtype=np.int64)
# X = A1 c2 + A2 c1 with A_i = [[a_i, b_i], [0, a_i]], a_i = <<tt_i>>, b_i = <<rt_i + tr_i>>:
#   (operator, block, target): operator 0 = a1, 1 = b1, 2 = a2, 3 = b2
_X_TERMS = np.array([[0, _RR2, 0], [1, _TR2, 0], [2, _RR1, 0], [3, _TR1, 0],
                     [0, _RT2, 1], [1, _TT2, 1], [2, _RT1, 1], [3, _TT1, 1],
                     [0, _TR2, 2], [2, _TR1, 2], [0, _TT2, 3], [2, _TT1, 3]], dtype=np.int64)


@njit(cache=True)
def _op1(A: np.ndarray, out: np.ndarray, C: int) -> None:
    """Barfoot's ``<<A>> = -tr(A) I + A`` for blocks ``(3, 3, C)``."""
    for n in range(C):
        tr = A[0, 0, n] + A[1, 1, n] + A[2, 2, n]
        for i in range(3):
            for j in range(3):
                out[i, j, n] = A[i, j, n] - tr if i == j else A[i, j, n]


@njit(cache=True)
def _mm_add(A: np.ndarray, B: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out += A @ B`` for blocks ``(3, 3, C)``."""
    for i in range(3):
        for j in range(3):
            for n in range(C):
                out[i, j, n] += A[i, 0, n] * B[0, j, n] + A[i, 1, n] * B[1, j, n] + A[i, 2, n] * B[2, j, n]


@njit(cache=True)
def _pair_add(L: np.ndarray, R: np.ndarray, oL: np.ndarray, oR: np.ndarray, out: np.ndarray, C: int,
              tr: np.ndarray) -> None:
    """``out += <<L, R>> = <<L>> <<R>> + <<R L>>`` for blocks ``(3, 3, C)`` (``oL``, ``oR`` = ``<<L>>``, ``<<R>>``;
    ``tr`` (C,) work)."""
    for n in range(C):
        tr[n] = 0.0
    for k in range(3):
        for m in range(3):
            for n in range(C):
                tr[n] += R[k, m, n] * L[m, k, n]
    for i in range(3):
        for j in range(3):
            for n in range(C):
                out[i, j, n] += oL[i, 0, n] * oR[0, j, n] + oL[i, 1, n] * oR[1, j, n] + oL[i, 2, n] * oR[2, j, n] \
                    + R[i, 0, n] * L[0, j, n] + R[i, 1, n] * L[1, j, n] + R[i, 2, n] * L[2, j, n]
        for n in range(C):
            out[i, i, n] -= tr[n]


@njit(cache=True)
def _blocks(c1: np.ndarray, c2: np.ndarray, C: int, W: np.ndarray) -> None:
    """The 3x3 blocks of both covariances (``tr`` = ``rt`` transposed) into ``W[0:8]``."""
    for i in range(3):
        for j in range(3):
            for n in range(C):
                W[_RR1, i, j, n] = c1[i, j, n]
                W[_RT1, i, j, n] = c1[i, 3 + j, n]
                W[_TR1, i, j, n] = c1[j, 3 + i, n]
                W[_TT1, i, j, n] = c1[3 + i, 3 + j, n]
                W[_RR2, i, j, n] = c2[i, j, n]
                W[_RT2, i, j, n] = c2[i, 3 + j, n]
                W[_TR2, i, j, n] = c2[j, 3 + i, n]
                W[_TT2, i, j, n] = c2[3 + i, 3 + j, n]


@njit(cache=True)
def compound_chunk(c1: np.ndarray, c2: np.ndarray, out: np.ndarray, C: int, W: np.ndarray) -> None:
    """Covariance of ``Exp(xi1) Exp(xi2)`` to fourth order (Barfoot & Furgale 2014, eq. 55) for ``C``
    configurations: ``c1 + c2 + (X + X^T) / 12 + B / 4`` with ``X = A1 c2 + A2 c1``.

    Parameters
    ----------
    c1, c2 : ndarray, shape (6, 6, >= C)
        Covariances of the left and the right factor's twist ``[rho; theta]`` in the SAME tangent space
        (transport them first: ``X1 Exp(x1) X2 Exp(x2) = X1 X2 Exp(Ad_{X2^-1} x1) Exp(x2)``).
    out : ndarray, shape (6, 6, >= C)
        Result (may be ``c1``).
    W : ndarray, shape (29, 3, 3, >= C)
        Work array.
    """
    _blocks(c1, c2, C, W)
    for b in range(8):  # <<block>> of every block into W[20 + b]
        _op1(W[b], W[20 + b], C)
    # 8..11: B blocks rr rt tr tt; 12..15: X blocks; 16..19: operators a1 b1 a2 b2; 28: work
    for t in range(8, 16):
        for i in range(3):
            for j in range(3):
                for n in range(C):
                    W[t, i, j, n] = 0.0
    for i in range(3):
        for j in range(3):
            for n in range(C):
                W[16, i, j, n] = W[20 + _TT1, i, j, n]
                W[17, i, j, n] = W[20 + _RT1, i, j, n] + W[20 + _TR1, i, j, n]  # <<.>> is linear
                W[18, i, j, n] = W[20 + _TT2, i, j, n]
                W[19, i, j, n] = W[20 + _RT2, i, j, n] + W[20 + _TR2, i, j, n]
    for p in range(_PAIR_LEFT.shape[0]):
        left, right = _PAIR_LEFT[p], _PAIR_RIGHT[p]
        _pair_add(W[left], W[right], W[20 + left], W[20 + right], W[8 + _PAIR_TARGET[p]], C, W[28, 0, 0])
    for k in range(_X_TERMS.shape[0]):
        _mm_add(W[16 + _X_TERMS[k, 0]], W[_X_TERMS[k, 1]], W[12 + _X_TERMS[k, 2]], C)
    for i in range(3):
        for j in range(3):
            for n in range(C):
                b_rt = W[9, i, j, n] / 4.0
                out[i, j, n] = c1[i, j, n] + c2[i, j, n] + W[8, i, j, n] / 4.0 \
                    + (W[12, i, j, n] + W[12, j, i, n]) / 12.0
                out[i, 3 + j, n] = c1[i, 3 + j, n] + c2[i, 3 + j, n] + b_rt \
                    + (W[13, i, j, n] + W[14, j, i, n]) / 12.0
                out[3 + j, i, n] = c1[3 + j, i, n] + c2[3 + j, i, n] + b_rt \
                    + (W[14, j, i, n] + W[13, i, j, n]) / 12.0
                out[3 + i, 3 + j, n] = c1[3 + i, 3 + j, n] + c2[3 + i, 3 + j, n] + W[11, i, j, n] / 4.0 \
                    + (W[15, i, j, n] + W[15, j, i, n]) / 12.0


def compound_fourth_order(cov1: ArrayLike, cov2: ArrayLike) -> np.ndarray:
    """Covariance of ``Exp(xi1) Exp(xi2)`` to fourth order (Barfoot & Furgale 2014, eq. 55).

    Both covariances live in the SAME tangent space (see :func:`compound_chunk`), broadcasting over batch axes.

    Parameters
    ----------
    cov1, cov2 : array_like, shape (..., 6, 6)
        Covariances of the left and the right factor's twist ``[rho; theta]``.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``cov1 + cov2 + (A1 cov2 + cov2 A1^T + A2 cov1 + cov1 A2^T) / 12 + B / 4``.
    """
    c1, c2 = np.broadcast_arrays(np.asarray(cov1, dtype=float), np.asarray(cov2, dtype=float))
    shape = c1.shape
    a = np.ascontiguousarray(np.moveaxis(c1.reshape(-1, 6, 6), 0, -1))
    b = np.ascontiguousarray(np.moveaxis(c2.reshape(-1, 6, 6), 0, -1))
    N = a.shape[-1]
    out = np.empty_like(a)
    W = np.empty((29, 3, 3, CHUNK))
    for n0 in range(0, N, CHUNK):
        n1 = min(N, n0 + CHUNK)
        o = np.empty((6, 6, n1 - n0))
        compound_chunk(np.ascontiguousarray(a[..., n0:n1]), np.ascontiguousarray(b[..., n0:n1]), o, n1 - n0, W)
        out[..., n0:n1] = o
    return np.moveaxis(out, -1, 0).reshape(shape)
