"""Compiled (numba) batched evaluation of a chain program (:mod:`ppoe_core.model.chain`): mean poses and
second-order covariances ``cov = G^T G`` (paper eq. 15/18, tangent space at the chain's end pose) of many
configurations, the batched FK's fast path (:func:`ppoe_core.model.chain_eval.evaluate` takes it for two or more
configurations at order 0 or 2 without the columns; everything else is :func:`ppoe_core.model.chain_kernel.eval_chain`).

The arithmetic is :func:`~ppoe_core.model.chain_kernel.eval_chain`'s, expression for expression (the compiler may fuse
multiply-adds differently: covariances agree to a few ulp of their largest entry, test/test_chain_kernel.py); what
differs is the layout.  A chunk's working set is one flat array of *panels*, rows of :data:`CHUNK` configurations:
the suffix products ``S[k]`` (12 rows each), the 21 rows of the covariance's upper triangle and the motions' sines
and cosines.  Because the row stride is a compile-time constant, every loop over the configurations has one
straight-line body (a whole factor product or a whole column with its 21 products) whose accesses the compiler sees
as constant distances in one array: it vectorises without the run-time overlap checks and the short loops per
matrix entry of the 4-D layout (docs/performance.md, "Batched FK").
"""

from __future__ import annotations

import numpy as np

from ppoe_core.jit import njit
from ppoe_core.model.chain_kernel import CHUNK, FASTMATH, SINCOS_LIMIT, sincos

__all__ = ["eval_panels", "panel_rows"]

#: rows of one suffix product ``S[k]`` (its 3x4 top, row by row)
_S_ROWS = 12
#: rows of the covariance's upper triangle
_ACC_ROWS = 21


@njit(cache=True, inline="always")
def panel_rows(n_factors: int, n_motion: int) -> int:
    """Rows of the work array of :func:`eval_panels`: ``n_factors + 1`` suffix products, the covariance, two per
    motion."""
    return (n_factors + 1) * _S_ROWS + _ACC_ROWS + 2 * n_motion


@njit(cache=True, inline="always")
def _rows(P: np.ndarray, r0: int, n: int) -> np.ndarray:
    """Rows ``r0 .. r0 + n`` of the panels (a view; indexed ``[r * CHUNK + configuration]`` with constant ``r``, so
    the compiler sees non-negative indices at constant distances)."""
    return P[r0 * CHUNK: (r0 + n) * CHUNK]


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _angles(theta: np.ndarray, n0: int, C: int, P: np.ndarray, cs: int) -> None:
    """Rows ``cs + 2 m``, ``cs + 2 m + 1`` = sine, cosine of motion ``m`` (:func:`sincos`; numpy's beyond
    :data:`SINCOS_LIMIT`, as :func:`ppoe_core.model.chain_kernel._angles`)."""
    for m in range(theta.shape[0]):
        big = False  # an OR, not a max: a floating-point max reduction would keep the loop scalar
        R = _rows(P, cs + 2 * m, 2)
        for n in range(C):
            s, c = sincos(theta[m, n0 + n])
            R[n] = s
            R[CHUNK + n] = c
            big = big | (abs(theta[m, n0 + n]) > SINCOS_LIMIT)
        if big:
            for n in range(C):
                if abs(theta[m, n0 + n]) > SINCOS_LIMIT:
                    R[n] = np.sin(theta[m, n0 + n])
                    R[CHUNK + n] = np.cos(theta[m, n0 + n])


@njit(cache=True, fastmath=FASTMATH)
def _static(Fk: np.ndarray, o: np.ndarray, x: np.ndarray, C: int) -> None:
    """``S[k] = F_k S[k + 1]`` for a constant factor (``o``, ``x``: the 12 rows of ``S[k]``, ``S[k + 1]``; not inlined:
    as two arguments the compiler checks their overlap once and vectorises, as two views of one array it does
    not)."""
    f00, f01, f02, f03, f10, f11 = Fk[0, 0], Fk[0, 1], Fk[0, 2], Fk[0, 3], Fk[1, 0], Fk[1, 1]
    f12, f13, f20, f21, f22, f23 = Fk[1, 2], Fk[1, 3], Fk[2, 0], Fk[2, 1], Fk[2, 2], Fk[2, 3]
    for n in range(C):
        a0, a1, a2, a3 = x[n], x[CHUNK + n], x[2 * CHUNK + n], x[3 * CHUNK + n]
        b0, b1, b2, b3 = x[4 * CHUNK + n], x[5 * CHUNK + n], x[6 * CHUNK + n], x[7 * CHUNK + n]
        c0, c1, c2, c3 = x[8 * CHUNK + n], x[9 * CHUNK + n], x[10 * CHUNK + n], x[11 * CHUNK + n]
        o[n] = f00 * a0 + f01 * b0 + f02 * c0
        o[CHUNK + n] = f00 * a1 + f01 * b1 + f02 * c1
        o[2 * CHUNK + n] = f00 * a2 + f01 * b2 + f02 * c2
        o[3 * CHUNK + n] = f00 * a3 + f01 * b3 + f02 * c3 + f03
        o[4 * CHUNK + n] = f10 * a0 + f11 * b0 + f12 * c0
        o[5 * CHUNK + n] = f10 * a1 + f11 * b1 + f12 * c1
        o[6 * CHUNK + n] = f10 * a2 + f11 * b2 + f12 * c2
        o[7 * CHUNK + n] = f10 * a3 + f11 * b3 + f12 * c3 + f13
        o[8 * CHUNK + n] = f20 * a0 + f21 * b0 + f22 * c0
        o[9 * CHUNK + n] = f20 * a1 + f21 * b1 + f22 * c1
        o[10 * CHUNK + n] = f20 * a2 + f21 * b2 + f22 * c2
        o[11 * CHUNK + n] = f20 * a3 + f21 * b3 + f22 * c3 + f23


@njit(cache=True, fastmath=FASTMATH)
def _rot_z(o: np.ndarray, x: np.ndarray, r: np.ndarray, C: int) -> None:
    """``S[k] = Rz(theta) S[k + 1]``, ``r``: the sine and cosine rows (arguments as :func:`_static`)."""
    for n in range(C):
        s = r[n]
        c = r[CHUNK + n]
        a, b = x[n], x[4 * CHUNK + n]
        o[n] = c * a - s * b
        o[4 * CHUNK + n] = s * a + c * b
        o[8 * CHUNK + n] = x[8 * CHUNK + n]
        a, b = x[CHUNK + n], x[5 * CHUNK + n]
        o[CHUNK + n] = c * a - s * b
        o[5 * CHUNK + n] = s * a + c * b
        o[9 * CHUNK + n] = x[9 * CHUNK + n]
        a, b = x[2 * CHUNK + n], x[6 * CHUNK + n]
        o[2 * CHUNK + n] = c * a - s * b
        o[6 * CHUNK + n] = s * a + c * b
        o[10 * CHUNK + n] = x[10 * CHUNK + n]
        a, b = x[3 * CHUNK + n], x[7 * CHUNK + n]
        o[3 * CHUNK + n] = c * a - s * b
        o[7 * CHUNK + n] = s * a + c * b
        o[11 * CHUNK + n] = x[11 * CHUNK + n]


@njit(cache=True, fastmath=FASTMATH)
def _general(Dk: np.ndarray, n0: int, o: np.ndarray, x: np.ndarray, C: int) -> None:
    """``S[k] = D_k S[k + 1]`` for per-configuration factors ``Dk`` (4, 4, N) (arguments as :func:`_static`)."""
    for n in range(C):
        for i in range(3):
            for j in range(4):
                v = Dk[i, 0, n0 + n] * x[j * CHUNK + n] + Dk[i, 1, n0 + n] * x[(4 + j) * CHUNK + n] \
                    + Dk[i, 2, n0 + n] * x[(8 + j) * CHUNK + n]
                o[(4 * i + j) * CHUNK + n] = v + Dk[i, 3, n0 + n] if j == 3 else v


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _suffixes(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, theta: np.ndarray, D: np.ndarray, n0: int, C: int,
              P: np.ndarray, cs: int) -> None:
    """Suffix products ``S[k]`` (rows ``12 k ..``) of the chunk, from the chain's end."""
    nf = F.shape[0]
    _angles(theta, n0, C, P, cs)
    last = _rows(P, nf * _S_ROWS, _S_ROWS)
    for r in range(_S_ROWS):
        for n in range(C):
            last[r * CHUNK + n] = 1.0 if r == 0 or r == 5 or r == 10 else 0.0
    for k in range(nf - 1, -1, -1):
        code = kind[k]
        o, x = _rows(P, k * _S_ROWS, _S_ROWS), _rows(P, (k + 1) * _S_ROWS, _S_ROWS)
        if code == 0:
            _static(F[k], o, x, C)
        elif code == 1:
            _rot_z(o, x, _rows(P, cs + 2 * arg[k], 2), C)
        elif code == 2:
            for r in range(_S_ROWS):
                for n in range(C):
                    o[r * CHUNK + n] = x[r * CHUNK + n]
            for n in range(C):
                o[11 * CHUNK + n] += theta[arg[k], n0 + n]
        else:
            _general(D[arg[k]], n0, o, x, C)


@njit(cache=True, fastmath=FASTMATH)
def _column_products(B: np.ndarray, X: np.ndarray, c: int, A: np.ndarray, C: int) -> None:
    """Covariance rows ``acc ..`` ``+=`` the 21 products of local column ``c``,
    ``Ad_{B^-1} [v; w] = [R^T (v + w x t); R^T w]`` for the suffix ``B = [R t]`` at rows ``b ..`` (the expressions of
    :func:`ppoe_core.model.chain_kernel._column`)."""
    v0, v1, v2 = X[c, 0, 0], X[c, 0, 1], X[c, 0, 2]
    w0, w1, w2 = X[c, 1, 0], X[c, 1, 1], X[c, 1, 2]
    for n in range(C):
        r00, r01, r02, t0 = B[n], B[CHUNK + n], B[2 * CHUNK + n], B[3 * CHUNK + n]
        r10, r11, r12, t1 = B[4 * CHUNK + n], B[5 * CHUNK + n], B[6 * CHUNK + n], B[7 * CHUNK + n]
        r20, r21, r22, t2 = B[8 * CHUNK + n], B[9 * CHUNK + n], B[10 * CHUNK + n], B[11 * CHUNK + n]
        a0 = v0 + w1 * t2 - w2 * t1
        a1 = v1 + w2 * t0 - w0 * t2
        a2 = v2 + w0 * t1 - w1 * t0
        g0, g1, g2 = a0 * r00 + a1 * r10 + a2 * r20, a0 * r01 + a1 * r11 + a2 * r21, a0 * r02 + a1 * r12 + a2 * r22
        g3, g4, g5 = w0 * r00 + w1 * r10 + w2 * r20, w0 * r01 + w1 * r11 + w2 * r21, w0 * r02 + w1 * r12 + w2 * r22
        A[n] += g0 * g0
        A[CHUNK + n] += g0 * g1
        A[2 * CHUNK + n] += g0 * g2
        A[3 * CHUNK + n] += g0 * g3
        A[4 * CHUNK + n] += g0 * g4
        A[5 * CHUNK + n] += g0 * g5
        A[6 * CHUNK + n] += g1 * g1
        A[7 * CHUNK + n] += g1 * g2
        A[8 * CHUNK + n] += g1 * g3
        A[9 * CHUNK + n] += g1 * g4
        A[10 * CHUNK + n] += g1 * g5
        A[11 * CHUNK + n] += g2 * g2
        A[12 * CHUNK + n] += g2 * g3
        A[13 * CHUNK + n] += g2 * g4
        A[14 * CHUNK + n] += g2 * g5
        A[15 * CHUNK + n] += g3 * g3
        A[16 * CHUNK + n] += g3 * g4
        A[17 * CHUNK + n] += g3 * g5
        A[18 * CHUNK + n] += g4 * g4
        A[19 * CHUNK + n] += g4 * g5
        A[20 * CHUNK + n] += g5 * g5


@njit(cache=True, fastmath=FASTMATH)
def _translation_products(B: np.ndarray, X: np.ndarray, c: int, A: np.ndarray, C: int) -> None:
    """:func:`_column_products` of a column without rotation (``w = 0`` exactly): ``[R^T v; 0]``, only the six
    products of its rr block are not exactly zero (the others would add ``+-0``: skipping them gives the same bits)."""
    v0, v1, v2 = X[c, 0, 0], X[c, 0, 1], X[c, 0, 2]
    for n in range(C):
        g0 = v0 * B[n] + v1 * B[4 * CHUNK + n] + v2 * B[8 * CHUNK + n]
        g1 = v0 * B[CHUNK + n] + v1 * B[5 * CHUNK + n] + v2 * B[9 * CHUNK + n]
        g2 = v0 * B[2 * CHUNK + n] + v1 * B[6 * CHUNK + n] + v2 * B[10 * CHUNK + n]
        A[n] += g0 * g0
        A[CHUNK + n] += g0 * g1
        A[2 * CHUNK + n] += g0 * g2
        A[6 * CHUNK + n] += g1 * g1
        A[7 * CHUNK + n] += g1 * g2
        A[11 * CHUNK + n] += g2 * g2


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _write(P: np.ndarray, acc: int, want_cov: bool, n0: int, C: int, T: np.ndarray, cov: np.ndarray) -> None:
    """Mean poses (``S[0]``) and covariances (rows ``acc ..``) of the chunk into ``T`` (N, 4, 4), ``cov`` (N, 6, 6)."""
    A = _rows(P, acc, _ACC_ROWS)
    for n in range(C):
        for r in range(_S_ROWS):
            T[n0 + n, r // 4, r % 4] = P[r * CHUNK + n]
        T[n0 + n, 3, 0] = 0.0
        T[n0 + n, 3, 1] = 0.0
        T[n0 + n, 3, 2] = 0.0
        T[n0 + n, 3, 3] = 1.0
        if want_cov:
            k = 0
            for i in range(6):
                for j in range(i, 6):
                    cov[n0 + n, i, j] = A[k * CHUNK + n]
                    cov[n0 + n, j, i] = A[k * CHUNK + n]
                    k += 1


@njit(cache=True, fastmath=FASTMATH)
def eval_panels(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, col_pos: np.ndarray, X: np.ndarray,
                theta: np.ndarray, D: np.ndarray, order: int, T: np.ndarray, cov: np.ndarray) -> None:
    """Mean poses ``T`` (N, 4, 4) and, for ``order`` 2, covariances ``cov`` (N, 6, 6) of ``N`` configurations
    (arguments as :func:`ppoe_core.model.chain_kernel.eval_chain`; ``order`` 0 or 2; ``cov`` in the tangent space at
    ``T``: frame of the chain's end, right perturbation, ``[rho; theta]``)."""
    N = theta.shape[1]
    nf = F.shape[0]
    acc = (nf + 1) * _S_ROWS
    cs = acc + _ACC_ROWS
    P = np.empty(panel_rows(nf, theta.shape[0]) * CHUNK)
    for n0 in range(0, N, CHUNK):
        C = min(CHUNK, N - n0)
        _suffixes(F, kind, arg, theta, D, n0, C, P, cs)
        if order == 2:
            A = _rows(P, acc, _ACC_ROWS)
            A[:] = 0.0
            for c in range(col_pos.shape[0]):
                if X[c, 1, 0] == 0.0 and X[c, 1, 1] == 0.0 and X[c, 1, 2] == 0.0:
                    _translation_products(_rows(P, col_pos[c] * _S_ROWS, _S_ROWS), X, c, A, C)
                else:
                    _column_products(_rows(P, col_pos[c] * _S_ROWS, _S_ROWS), X, c, A, C)
        _write(P, acc, order == 2, n0, C, T, cov)
