"""Fourth-order covariance of a compounded pose (Barfoot & Furgale 2014, right perturbations; the paper's eq. 15
beyond second order), compiled (numba) with the batch axis innermost.

Covariances live in the tangent space at the mean (docs/conventions.md); ``[rho; theta]`` order.  Ported from
pytransform3d's ``_compound_cov_fourth_order_terms`` (BSD-3; it orders twists ``[omega; v]``).

Layout and speed: a covariance is symmetric, so the compiled compounding takes and gives its upper triangle, row
by row (:data:`PACKED`, 21 rows, configurations along the last axis).  Each configuration's compounding is one
straight-line body over 3x3 blocks held as tuples (registers; no work array), and the loop over configurations
around it vectorises: the same terms as the 6x6 formula, each product computed once (``tr`` = ``rt`` transposed, the
rr and tt blocks of the result symmetric).  The former version kept 29 blocks of 3x3xC in a work array (134 KB, out
of L1) and compounded at 3.7 us per configuration and 15 sites; docs/performance.md has the numbers."""

from __future__ import annotations

import numpy as np
from ppoe_core.jit import njit
from numpy.typing import ArrayLike

__all__ = ["compound_fourth_order", "compound_chunk", "packed_index", "CHUNK", "PACKED"]

#: configurations per call of the compiled compounding
CHUNK = 64
#: rows of a packed symmetric 6x6 covariance: its upper triangle row by row, ``(i, j)`` at ``packed_index(i, j)``
PACKED = 21
#: (i, j) of each packed row
_UPPER_I, _UPPER_J = np.triu_indices(6)


@njit(cache=True, inline="always")
def packed_index(i: int, j: int) -> int:
    """Row of entry ``(i, j)``, ``i <= j``, of a packed symmetric 6x6 matrix (row ``i`` starts at
    ``i (13 - i) / 2``)."""
    return i * (13 - i) // 2 + j - i


@njit(cache=True, inline="always")
def _at(c: np.ndarray, n: int, i: int, j: int) -> float:
    """Entry ``(i, j)``, ``i <= j``, of configuration ``n`` of a flat packed panel (row stride :data:`CHUNK`)."""
    return c[packed_index(i, j) * CHUNK + n]


@njit(cache=True, inline="always")
def _block(c: np.ndarray, n: int, r0: int, c0: int) -> tuple:
    """3x3 block at rows ``r0..``, columns ``c0..`` of configuration ``n`` of a flat packed panel (9-tuple, row by
    row; a diagonal block is read from the upper triangle)."""
    if r0 == c0:
        a, b, d = _at(c, n, r0, r0), _at(c, n, r0, r0 + 1), _at(c, n, r0, r0 + 2)
        e, f, g = _at(c, n, r0 + 1, r0 + 1), _at(c, n, r0 + 1, r0 + 2), _at(c, n, r0 + 2, r0 + 2)
        return (a, b, d, b, e, f, d, f, g)
    return (_at(c, n, r0, c0), _at(c, n, r0, c0 + 1), _at(c, n, r0, c0 + 2), _at(c, n, r0 + 1, c0),
            _at(c, n, r0 + 1, c0 + 1), _at(c, n, r0 + 1, c0 + 2), _at(c, n, r0 + 2, c0), _at(c, n, r0 + 2, c0 + 1),
            _at(c, n, r0 + 2, c0 + 2))


@njit(cache=True, inline="always")
def _t(a: tuple) -> tuple:
    """Transpose of a 3x3 tuple."""
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


@njit(cache=True, inline="always")
def _add(a: tuple, b: tuple) -> tuple:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5], a[6] + b[6],
            a[7] + b[7], a[8] + b[8])


@njit(cache=True, inline="always")
def _op1(a: tuple) -> tuple:
    """Barfoot's ``<<A>> = -tr(A) I + A``."""
    tr = a[0] + a[4] + a[8]
    return (a[0] - tr, a[1], a[2], a[3], a[4] - tr, a[5], a[6], a[7], a[8] - tr)


@njit(cache=True, inline="always")
def _mm(a: tuple, b: tuple) -> tuple:
    """``A @ B`` of 3x3 tuples."""
    return (a[0] * b[0] + a[1] * b[3] + a[2] * b[6], a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
            a[0] * b[2] + a[1] * b[5] + a[2] * b[8], a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
            a[3] * b[1] + a[4] * b[4] + a[5] * b[7], a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[3] + a[8] * b[6], a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
            a[6] * b[2] + a[7] * b[5] + a[8] * b[8])


@njit(cache=True, inline="always")
def _pair(L: tuple, R: tuple) -> tuple:
    """Barfoot's ``<<L, R>> = <<L>> <<R>> + <<R L>>``."""
    return _pair_sum(_mm(_op1(L), _op1(R)), _mm(R, L))


@njit(cache=True, inline="always")
def _pair_sum(p: tuple, q: tuple) -> tuple:
    """``P + <<Q>>`` (``<<Q>> = Q - tr(Q) I``)."""
    tr = q[0] + q[4] + q[8]
    return (p[0] + q[0] - tr, p[1] + q[1], p[2] + q[2], p[3] + q[3], p[4] + q[4] - tr, p[5] + q[5], p[6] + q[6],
            p[7] + q[7], p[8] + q[8] - tr)


@njit(cache=True, inline="always")
def _store(c1: np.ndarray, c2: np.ndarray, out: np.ndarray, n: int, r0: int, c0: int, B: tuple, X: tuple,
           Y: tuple) -> None:
    """Block ``(r0, c0)`` of the result, its upper-triangle entries only: ``c1 + c2 + B / 4 + (X + Y) / 12``."""
    for i in range(3):
        for j in range(3):
            if r0 + i <= c0 + j:
                k = packed_index(r0 + i, c0 + j) * CHUNK + n
                out[k] = c1[k] + c2[k] + B[3 * i + j] / 4.0 + (X[3 * i + j] + Y[3 * i + j]) / 12.0


@njit(cache=True, inline="always")
def _compound_one(c1: np.ndarray, c2: np.ndarray, out: np.ndarray, n: int) -> None:
    """:func:`compound_chunk` of configuration ``n``: blocks rr, rt, tt of both (``tr = rt^T``), Barfoot and Furgale's
    ``B`` (pairs ``<<L, R>>``) and ``X = A1 c2 + A2 c1`` with ``A_i = [[a_i, b_i], [0, a_i]]``, ``a_i = <<tt_i>>``,
    ``b_i = <<rt_i>> + <<tr_i>>``; the result's rt block takes ``X_rt + X_tr^T``."""
    rr1, rt1, tt1 = _block(c1, n, 0, 0), _block(c1, n, 0, 3), _block(c1, n, 3, 3)
    rr2, rt2, tt2 = _block(c2, n, 0, 0), _block(c2, n, 0, 3), _block(c2, n, 3, 3)
    tr1, tr2 = _t(rt1), _t(rt2)
    a1, b1 = _op1(tt1), _add(_op1(rt1), _op1(tr1))
    a2, b2 = _op1(tt2), _add(_op1(rt2), _op1(tr2))
    B_rr = _add(_add(_add(_pair(tt1, rr2), _pair(tr1, rt2)), _pair(rt1, tr2)), _pair(rr1, tt2))
    B_rt = _add(_pair(tt1, tr2), _pair(tr1, tt2))
    B_tt = _pair(tt1, tt2)
    X_rr = _add(_add(_add(_mm(a1, rr2), _mm(b1, tr2)), _mm(a2, rr1)), _mm(b2, tr1))
    X_rt = _add(_add(_add(_mm(a1, rt2), _mm(b1, tt2)), _mm(a2, rt1)), _mm(b2, tt1))
    X_tr = _add(_mm(a1, tr2), _mm(a2, tr1))
    X_tt = _add(_mm(a1, tt2), _mm(a2, tt1))
    _store(c1, c2, out, n, 0, 0, B_rr, X_rr, _t(X_rr))
    _store(c1, c2, out, n, 0, 3, B_rt, X_rt, _t(X_tr))
    _store(c1, c2, out, n, 3, 3, B_tt, X_tt, _t(X_tt))


@njit(cache=True, fastmath={"contract"})
def compound_chunk(c1: np.ndarray, c2: np.ndarray, out: np.ndarray, C: int) -> None:
    """Covariance of ``Exp(xi1) Exp(xi2)`` to fourth order (Barfoot & Furgale 2014, eq. 55) for ``C``
    configurations: ``c1 + c2 + (X + X^T) / 12 + B / 4`` with ``X = A1 c2 + A2 c1``.

    Parameters
    ----------
    c1, c2 : ndarray, shape (PACKED, CHUNK), C-contiguous
        Panels of upper triangles (:func:`packed_index`; the row stride is the constant :data:`CHUNK`, so that the
        loop's accesses to one panel form one range and the compiler's overlap check stays small) of the
        covariances of the left and the right factor's twist
        ``[rho; theta]`` in the SAME tangent space (transport them first:
        ``X1 Exp(x1) X2 Exp(x2) = X1 X2 Exp(Ad_{X2^-1} x1) Exp(x2)``).
    out : ndarray, shape (PACKED, CHUNK)
        Result's panel; a third array (an ``out`` that is ``c1`` would keep the loop from vectorising).
    C : int
        Configurations, ``<= CHUNK``.
    """
    a, b, o = c1.reshape(c1.size), c2.reshape(c2.size), out.reshape(out.size)
    for n in range(C):
        _compound_one(a, b, o, n)


def compound_fourth_order(cov1: ArrayLike, cov2: ArrayLike) -> np.ndarray:
    """Covariance of ``Exp(xi1) Exp(xi2)`` to fourth order (Barfoot & Furgale 2014, eq. 55).

    Both covariances live in the SAME tangent space (see :func:`compound_chunk`), broadcasting over batch axes.

    Parameters
    ----------
    cov1, cov2 : array_like, shape (..., 6, 6)
        Covariances (symmetric: their upper triangles are read) of the left and the right factor's twist
        ``[rho; theta]``.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``cov1 + cov2 + (A1 cov2 + cov2 A1^T + A2 cov1 + cov1 A2^T) / 12 + B / 4`` (symmetric).
    """
    c1, c2 = np.broadcast_arrays(np.asarray(cov1, dtype=float), np.asarray(cov2, dtype=float))
    shape = c1.shape
    a = np.ascontiguousarray(c1.reshape(-1, 6, 6)[:, _UPPER_I, _UPPER_J].T)
    b = np.ascontiguousarray(c2.reshape(-1, 6, 6)[:, _UPPER_I, _UPPER_J].T)
    N = a.shape[-1]
    packed = np.empty((PACKED, N))
    pa, pb, o = np.zeros((PACKED, CHUNK)), np.zeros((PACKED, CHUNK)), np.empty((PACKED, CHUNK))
    for n0 in range(0, N, CHUNK):
        n1 = min(N, n0 + CHUNK)
        pa[:, : n1 - n0] = a[:, n0:n1]
        pb[:, : n1 - n0] = b[:, n0:n1]
        compound_chunk(pa, pb, o, n1 - n0)
        packed[:, n0:n1] = o[:, : n1 - n0]
    out = np.empty((N, 6, 6))
    out[:, _UPPER_I, _UPPER_J] = packed.T
    out[:, _UPPER_J, _UPPER_I] = packed.T
    return out.reshape(shape)
