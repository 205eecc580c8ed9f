"""Compiled (numba) evaluation of a chain program (:mod:`ppoe_core.model.chain`): the mean pose, the second-order
covariance ``cov = G^T G`` (paper eq. 15/18, tangent space at the chain's end pose), the local covariance columns
``G`` and the joint-motion columns, for one or many configurations.

The chain is evaluated from its END (suffix products ``S[k]`` = product of factors ``k, k+1, ...``): at a
perturbation site ``S`` is the paper's "everything after it" ``B_k``, so the site's local columns are
``Ad_{B_k^-1} L_k = [R^T (v + w x t); R^T w]`` without any inverse.  Configurations are processed in chunks of
:data:`CHUNK` with the batch axis innermost, so the compiler vectorises over configurations (SIMD); a single
configuration is a chunk of one.

Program arrays (:class:`ppoe_core.model.chain.ChainProgram`, built once per chain):

* ``F`` (n_f, 4, 4): constant factors, identity at motion and effect slots;
* ``kind`` (n_f,): 0 constant, 1 rotation about z by ``theta[arg]``, 2 translation along z by ``theta[arg]``,
  3 the effect factor ``D[arg]``;  ``arg`` (n_f,);
* ``col_pos`` (m,): suffix index of each covariance column; ``X`` (m, 2, 3): its rows ``[v^T; w^T]``;
* ``mot_pos`` (n_motion,): factor index of each motion; ``mot_kind``: 1 revolute, 2 prismatic;
* ``site_start`` (n_sites + 1,): first column of each perturbation site (columns are grouped by site, chain
  order), for the fourth-order compounding.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ppoe_core.model.fourth_order import compound_chunk

__all__ = ["CHUNK", "eval_chain"]

#: configurations per chunk (the working set ``(n_f + 1, 3, 4, CHUNK)`` stays in cache)
CHUNK = 64


@njit(cache=True)
def _static(Fk: np.ndarray, nx: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out = F_k @ nx`` for a constant factor (rows ``(3, 4, C)``)."""
    for i in range(3):
        f0, f1, f2, f3 = Fk[i, 0], Fk[i, 1], Fk[i, 2], Fk[i, 3]
        for j in range(4):
            for n in range(C):
                out[i, j, n] = f0 * nx[0, j, n] + f1 * nx[1, j, n] + f2 * nx[2, j, n]
        for n in range(C):
            out[i, 3, n] += f3


@njit(cache=True)
def _rot_z(th: np.ndarray, n0: int, nx: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out = Rz(theta) @ nx`` for the configurations ``n0 .. n0 + C``."""
    for n in range(C):
        c = np.cos(th[n0 + n])
        s = np.sin(th[n0 + n])
        for j in range(4):
            a = nx[0, j, n]
            b = nx[1, j, n]
            out[0, j, n] = c * a - s * b
            out[1, j, n] = s * a + c * b
            out[2, j, n] = nx[2, j, n]


@njit(cache=True)
def _general(Dk: np.ndarray, n0: int, nx: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out = D_k @ nx`` for per-configuration factors ``Dk`` (4, 4, N)."""
    for i in range(3):
        for j in range(4):
            for n in range(C):
                out[i, j, n] = Dk[i, 0, n0 + n] * nx[0, j, n] + Dk[i, 1, n0 + n] * nx[1, j, n] \
                    + Dk[i, 2, n0 + n] * nx[2, j, n]
        for n in range(C):
            out[i, 3, n] += Dk[i, 3, n0 + n]


@njit(cache=True)
def _suffixes(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, theta: np.ndarray, D: np.ndarray, n0: int,
              C: int, S: np.ndarray) -> None:
    """Suffix products ``S[k]`` (rows ``(3, 4, C)``) of the chain for configurations ``n0 .. n0 + C``."""
    nf = F.shape[0]
    for i in range(3):
        for j in range(4):
            for n in range(C):
                S[nf, i, j, n] = 1.0 if i == j else 0.0
    for k in range(nf - 1, -1, -1):
        code = kind[k]
        if code == 0:
            _static(F[k], S[k + 1], S[k], C)
        elif code == 1:
            _rot_z(theta[arg[k]], n0, S[k + 1], S[k], C)
        elif code == 2:
            for i in range(3):
                for j in range(4):
                    for n in range(C):
                        S[k, i, j, n] = S[k + 1, i, j, n]
            for n in range(C):
                S[k, 2, 3, n] += theta[arg[k], n0 + n]
        else:
            _general(D[arg[k]], n0, S[k + 1], S[k], C)


@njit(cache=True, inline="always")
def _column(B: np.ndarray, n: int, X: np.ndarray, c: int) -> tuple[float, float, float, float, float, float]:
    """Local covariance column ``c`` of configuration ``n``: ``Ad_{B^-1} [v; w] = [R^T (v + w x t); R^T w]`` for
    the suffix ``B = [R t]`` (rows ``(3, 4, C)``) and the factor column ``X[c]`` = rows ``[v^T; w^T]``."""
    w0, w1, w2 = X[c, 1, 0], X[c, 1, 1], X[c, 1, 2]
    a0 = X[c, 0, 0] + w1 * B[2, 3, n] - w2 * B[1, 3, n]
    a1 = X[c, 0, 1] + w2 * B[0, 3, n] - w0 * B[2, 3, n]
    a2 = X[c, 0, 2] + w0 * B[1, 3, n] - w1 * B[0, 3, n]
    return (a0 * B[0, 0, n] + a1 * B[1, 0, n] + a2 * B[2, 0, n],
            a0 * B[0, 1, n] + a1 * B[1, 1, n] + a2 * B[2, 1, n],
            a0 * B[0, 2, n] + a1 * B[1, 2, n] + a2 * B[2, 2, n],
            w0 * B[0, 0, n] + w1 * B[1, 0, n] + w2 * B[2, 0, n],
            w0 * B[0, 1, n] + w1 * B[1, 1, n] + w2 * B[2, 1, n],
            w0 * B[0, 2, n] + w1 * B[1, 2, n] + w2 * B[2, 2, n])


@njit(cache=True)
def _cov_chunk(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, C: int, acc: np.ndarray) -> None:
    """Upper triangle of ``G^T G`` (21 entries per configuration, row by row) into ``acc`` (21, C)."""
    acc[:, :C] = 0.0
    for c in range(col_pos.shape[0]):
        B = S[col_pos[c]]
        for n in range(C):
            g = _column(B, n, X, c)
            k = 0
            for i in range(6):
                for j in range(i, 6):
                    acc[k, n] += g[i] * g[j]
                    k += 1


@njit(cache=True)
def _columns_chunk(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, n0: int, C: int, G: np.ndarray) -> None:
    """Local covariance columns ``Ad_{B_k^-1} L_k`` into ``G`` (m, 6, N)."""
    for c in range(col_pos.shape[0]):
        B = S[col_pos[c]]
        for n in range(C):
            g = _column(B, n, X, c)
            for i in range(6):
                G[c, i, n0 + n] = g[i]


@njit(cache=True)
def _motion_chunk(S: np.ndarray, mot_pos: np.ndarray, mot_kind: np.ndarray, n0: int, C: int,
                  J: np.ndarray) -> None:
    """Local columns of unit joint motions into ``J`` (n_motion, 6, N): ``Ad_{B^-1}`` of ``[0; e_z]`` (revolute)
    or ``[e_z; 0]`` (prismatic), ``B`` = everything after the motion."""
    for i in range(mot_pos.shape[0]):
        B = S[mot_pos[i] + 1]
        for n in range(C):
            for j in range(3):
                if mot_kind[i] == 1:
                    J[i, j, n0 + n] = B[1, j, n] * B[0, 3, n] - B[0, j, n] * B[1, 3, n]
                    J[i, 3 + j, n0 + n] = B[2, j, n]
                else:
                    J[i, j, n0 + n] = B[2, j, n]
                    J[i, 3 + j, n0 + n] = 0.0


@njit(cache=True)
def _write_chunk(S: np.ndarray, acc: np.ndarray, want_cov: bool, n0: int, C: int, T: np.ndarray,
                 cov: np.ndarray) -> None:
    """Mean poses (and covariances from ``acc``) of the chunk into ``T`` (N, 4, 4) and ``cov`` (N, 6, 6)."""
    for n in range(C):
        for i in range(3):
            for j in range(4):
                T[n0 + n, i, j] = S[0, i, j, n]
        T[n0 + n, 3, 0] = 0.0
        T[n0 + n, 3, 1] = 0.0
        T[n0 + n, 3, 2] = 0.0
        T[n0 + n, 3, 3] = 1.0
        if want_cov:
            k = 0
            for i in range(6):
                for j in range(i, 6):
                    cov[n0 + n, i, j] = acc[k, n]
                    cov[n0 + n, j, i] = acc[k, n]
                    k += 1


@njit(cache=True)
def _fourth_chunk(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, site_start: np.ndarray, C: int,
                  Gc: np.ndarray, Sk: np.ndarray, cov4: np.ndarray, W: np.ndarray) -> None:
    """Fourth-order covariance (Barfoot & Furgale 2014) of the chunk into ``cov4`` (6, 6, C): the local site
    covariances ``Sigma_k = G_k^T G_k`` compounded in chain order."""
    _columns_chunk(S, col_pos, X, 0, C, Gc)
    for k in range(site_start.shape[0] - 1):
        target = cov4 if k == 0 else Sk
        target[:, :, :C] = 0.0
        for c in range(site_start[k], site_start[k + 1]):
            for i in range(6):
                for j in range(i, 6):
                    for n in range(C):
                        target[i, j, n] += Gc[c, i, n] * Gc[c, j, n]
        for i in range(6):
            for j in range(i + 1, 6):
                for n in range(C):
                    target[j, i, n] = target[i, j, n]
        if k > 0:
            compound_chunk(cov4, Sk, cov4, C, W)


@njit(cache=True)
def eval_chain(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, col_pos: np.ndarray, X: np.ndarray,
               mot_pos: np.ndarray, mot_kind: np.ndarray, site_start: np.ndarray, theta: np.ndarray,
               D: np.ndarray, order: int, T: np.ndarray, cov: np.ndarray, G: np.ndarray, J: np.ndarray) -> None:
    """Evaluate a chain program for ``N`` configurations (the module docstring gives the program arrays).

    Parameters
    ----------
    theta : ndarray, shape (n_motion, N)
        Motion values (after mimic multiplier, offset and direction sign).
    D : ndarray, shape (n_d, 4, 4, N)
        Effect factors ``Exp(dxi)`` per effect slot (``n_d = 0`` without effects).
    order : int
        0: no covariance; 2: ``cov = G^T G`` (eq. 15/18); 4: fourth order.  ``cov`` (N, 6, 6) lives in the
        tangent space at ``T`` (frame of the chain's end, right perturbation).
    T : ndarray, shape (N, 4, 4)
        Output mean poses.
    G, J : ndarray, shapes (m, 6, N) / (n_motion, 6, N), or with a last axis of 0 to skip them
        Output local covariance columns / joint-motion columns.
    """
    N = theta.shape[1]
    S = np.empty((F.shape[0] + 1, 3, 4, CHUNK))
    acc = np.zeros((21, CHUNK))
    if order == 4:
        Gc = np.empty((col_pos.shape[0], 6, CHUNK))
        Sk = np.empty((6, 6, CHUNK))
        cov4 = np.empty((6, 6, CHUNK))
        W = np.empty((29, 3, 3, CHUNK))
    for n0 in range(0, N, CHUNK):
        C = min(CHUNK, N - n0)
        _suffixes(F, kind, arg, theta, D, n0, C, S)
        if order == 2:
            _cov_chunk(S, col_pos, X, C, acc)
        if G.shape[2]:
            _columns_chunk(S, col_pos, X, n0, C, G)
        if J.shape[2]:
            _motion_chunk(S, mot_pos, mot_kind, n0, C, J)
        _write_chunk(S, acc, order == 2, n0, C, T, cov)
        if order == 4:
            _fourth_chunk(S, col_pos, X, site_start, C, Gc, Sk, cov4, W)
            for n in range(C):
                for i in range(6):
                    for j in range(6):
                        cov[n0 + n, i, j] = cov4[i, j, n]
