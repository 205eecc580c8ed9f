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

Compile time and speed (docs/performance.md): the fourth-order code is compiled only into the specialisations
that are given its work array (``fourth``): numba prunes the ``fourth is None`` branch when the argument's type is
``none``, so a second-order caller (the kinematics node's default) never compiles it (about half of the cold
compile).  The working set of a call is sized ``min(N, CHUNK)`` (one configuration allocates 3 KB, not 100 KB), the
covariance accumulates in two vectorised passes per column (the column into ``g``, then the 21 products; a column
without rotation only its six non-zero products), and ``fastmath={"contract"}`` lets LLVM fuse multiply-adds
(results differ from separate rounding in the last bit).  The joint angles' sines and cosines are :func:`sincos`
(Cephes' reduction and polynomials, within 2 ulp of libm's, no call), in a loop whose big-angle test is an OR (a
floating-point max reduction kept it scalar).  Two or more configurations at order 0 or 2 without the columns take
the same expressions on another layout, :mod:`ppoe_core.model.chain_panel` (about 1.5-2x faster); this kernel
serves one configuration, the fourth order and the columns.
"""

from __future__ import annotations

import numpy as np
from ppoe_core.jit import njit

from ppoe_core.model.fourth_order import CHUNK as PANEL
from ppoe_core.model.fourth_order import PACKED, compound_chunk

__all__ = ["CHUNK", "FOURTH_WORK", "SINCOS_LIMIT", "eval_chain", "fk_one", "sincos"]

#: configurations per chunk (the working set ``(n_f + 1, 3, 4, CHUNK)`` stays in cache); at most the fourth-order
#: compounding's panel width (:data:`ppoe_core.model.fourth_order.CHUNK`)
CHUNK = PANEL
#: leading shape of the fourth-order work array ``fourth`` of :func:`eval_chain` and :func:`fk_one` (any last axis,
#: e.g. 1): four panels of packed covariances (:mod:`~ppoe_core.model.fourth_order`)
FOURTH_WORK = (4, PACKED * PANEL)
#: floating-point flags of every kernel here: fused multiply-add allowed, nothing else (no reassociation)
FASTMATH = {"contract"}


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _static(Fk: np.ndarray, nx: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out = F_k @ nx`` for a constant factor (rows ``(3, 4, C)``)."""
    for i in range(3):
        f0, f1, f2, f3 = Fk[i, 0], Fk[i, 1], Fk[i, 2], Fk[i, 3]
        for j in range(4):
            for n in range(C):
                out[i, j, n] = f0 * nx[0, j, n] + f1 * nx[1, j, n] + f2 * nx[2, j, n]
        for n in range(C):
            out[i, 3, n] += f3


#: the sine and cosine of :func:`sincos`: |x| beyond this takes numpy's (the three-part reduction by pi/4 keeps
#: its accuracy up to about 2**30; a joint angle is never near it)
SINCOS_LIMIT = 1.0e6
# Cody-Waite reduction by pi/4 in three parts and minimax polynomials on [-pi/4, pi/4] (Cephes sin.c, S. Moshier)
_FOUR_OVER_PI = 1.27323954473516268615
_DP1, _DP2, _DP3 = 7.85398125648498535156e-1, 3.77489470793079817668e-8, 2.69515142907905952645e-15
_S0, _S1, _S2 = 1.58962301576546568060e-10, -2.50507477628578072866e-8, 2.75573136213857245213e-6
_S3, _S4, _S5 = -1.98412698295895385996e-4, 8.33333333332211858878e-3, -1.66666666666666307295e-1
_C0, _C1, _C2 = -1.13585365213876817300e-11, 2.08757008419747316778e-9, -2.75573141792967388112e-7
_C3, _C4, _C5 = 2.48015872888517045348e-5, -1.38888888888730564116e-3, 4.16666666666665929218e-2


@njit(cache=True, fastmath=FASTMATH, inline="always")
def sincos(x: float) -> tuple[float, float]:
    """``(sin x, cos x)`` within 2 ulp of libm's for ``|x| <= SINCOS_LIMIT``, without a call or a branch, so that
    the loop over configurations vectorises (libm's ``sin`` and ``cos`` are 20 ns per angle, called one by one:
    two thirds of the chain's suffix products)."""
    a = abs(x)
    j = np.int64(a * _FOUR_OVER_PI)
    j += j & 1
    y = float(j)
    z = ((a - y * _DP1) - y * _DP2) - y * _DP3
    zz = z * z
    ps = z + z * zz * (((((_S0 * zz + _S1) * zz + _S2) * zz + _S3) * zz + _S4) * zz + _S5)
    pc = 1.0 - 0.5 * zz + zz * zz * (((((_C0 * zz + _C1) * zz + _C2) * zz + _C3) * zz + _C4) * zz + _C5)
    q = j & 7
    swap = (q == 2) | (q == 6)
    s = pc if swap else ps
    c = ps if swap else pc
    s = -s if (q >= 4) != (x < 0) else s
    c = -c if (q == 2) | (q == 4) else c
    return s, c


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _angles(theta: np.ndarray, n0: int, C: int, cs: np.ndarray) -> None:
    """``cs[m, 0, n], cs[m, 1, n]`` = sine, cosine of ``theta[m, n0 + n]`` for the chunk (:func:`sincos`; numpy's
    beyond :data:`SINCOS_LIMIT`).  A chunk of one configuration takes numpy's: the single-configuration paths
    (:func:`fk_one` compiled into any caller, :func:`eval_chain` of one configuration) then give the same bits
    whatever the compiler makes of the inlined polynomial (fused multiply-adds); a row of a batch may differ from
    them by 2 ulp of the sine."""
    if C == 1:
        for m in range(theta.shape[0]):
            cs[m, 0, 0] = np.sin(theta[m, n0])
            cs[m, 1, 0] = np.cos(theta[m, n0])
        return
    for m in range(theta.shape[0]):
        big = False  # an OR, not a max: a floating-point max reduction would keep the loop scalar
        for n in range(C):
            s, c = sincos(theta[m, n0 + n])
            cs[m, 0, n] = s
            cs[m, 1, n] = c
            big = big | (abs(theta[m, n0 + n]) > SINCOS_LIMIT)
        if big:
            for n in range(C):
                if abs(theta[m, n0 + n]) > SINCOS_LIMIT:
                    cs[m, 0, n] = np.sin(theta[m, n0 + n])
                    cs[m, 1, n] = np.cos(theta[m, n0 + n])


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _rot_z(sc: np.ndarray, nx: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out = Rz(theta) @ nx`` for the chunk, ``sc`` = (2, C) its sines and cosines."""
    for j in range(4):
        for n in range(C):
            s = sc[0, n]
            c = sc[1, n]
            a = nx[0, j, n]
            b = nx[1, j, n]
            out[0, j, n] = c * a - s * b
            out[1, j, n] = s * a + c * b
            out[2, j, n] = nx[2, j, n]


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _general(Dk: np.ndarray, n0: int, nx: np.ndarray, out: np.ndarray, C: int) -> None:
    """``out = D_k @ nx`` for per-configuration factors ``Dk`` (4, 4, N)."""
    for i in range(3):
        for j in range(4):
            for n in range(C):
                out[i, j, n] = Dk[i, 0, n0 + n] * nx[0, j, n] + Dk[i, 1, n0 + n] * nx[1, j, n] \
                    + Dk[i, 2, n0 + n] * nx[2, j, n]
        for n in range(C):
            out[i, 3, n] += Dk[i, 3, n0 + n]


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _suffixes(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, theta: np.ndarray, D: np.ndarray, n0: int,
              C: int, S: np.ndarray, cs: np.ndarray) -> None:
    """Suffix products ``S[k]`` (rows ``(3, 4, C)``) of the chain for configurations ``n0 .. n0 + C`` (``cs``: work
    array (n_motion, 2, >= C) of the motions' sines and cosines)."""
    nf = F.shape[0]
    _angles(theta, n0, C, cs)
    for i in range(3):
        for j in range(4):
            for n in range(C):
                S[nf, i, j, n] = 1.0 if i == j else 0.0
    for k in range(nf - 1, -1, -1):
        code = kind[k]
        if code == 0:
            _static(F[k], S[k + 1], S[k], C)
        elif code == 1:
            _rot_z(cs[arg[k]], S[k + 1], S[k], C)
        elif code == 2:
            for i in range(3):
                for j in range(4):
                    for n in range(C):
                        S[k, i, j, n] = S[k + 1, i, j, n]
            for n in range(C):
                S[k, 2, 3, n] += theta[arg[k], n0 + n]
        else:
            _general(D[arg[k]], n0, S[k + 1], S[k], C)


@njit(cache=True, fastmath=FASTMATH, inline="always")
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


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _column_rows(B: np.ndarray, X: np.ndarray, c: int, C: int, g: np.ndarray, n0: int) -> None:
    """Local covariance column ``c`` (:func:`_column`) of the configurations ``0 .. C`` of the chunk into
    ``g[:, n0 + n]`` (6 rows)."""
    for n in range(C):
        g0, g1, g2, g3, g4, g5 = _column(B, n, X, c)
        g[0, n0 + n] = g0
        g[1, n0 + n] = g1
        g[2, n0 + n] = g2
        g[3, n0 + n] = g3
        g[4, n0 + n] = g4
        g[5, n0 + n] = g5


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _cov_one(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, acc: np.ndarray) -> None:
    """:func:`_cov_chunk` for a chunk of ONE configuration: the 21 sums accumulate column by column without the
    loops over configurations (which cost more than the arithmetic for one)."""
    acc[:, 0] = 0.0
    for c in range(col_pos.shape[0]):
        g = _column(S[col_pos[c]], 0, X, c)
        k = 0
        for i in range(6):
            for j in range(i, 6):
                acc[k, 0] += g[i] * g[j]
                k += 1


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _translation_products(B: np.ndarray, X: np.ndarray, c: int, C: int, acc: np.ndarray) -> None:
    """:func:`_accumulate` of a column without rotation (``w = 0`` exactly): the column is ``[R^T v; 0]``, so only
    the six products of its rr block are not exactly zero (the others would add ``+-0``: skipping them gives the
    same bits)."""
    v0, v1, v2 = X[c, 0, 0], X[c, 0, 1], X[c, 0, 2]
    for n in range(C):
        g0 = v0 * B[0, 0, n] + v1 * B[1, 0, n] + v2 * B[2, 0, n]
        g1 = v0 * B[0, 1, n] + v1 * B[1, 1, n] + v2 * B[2, 1, n]
        g2 = v0 * B[0, 2, n] + v1 * B[1, 2, n] + v2 * B[2, 2, n]
        acc[0, n] += g0 * g0
        acc[1, n] += g0 * g1
        acc[2, n] += g0 * g2
        acc[6, n] += g1 * g1
        acc[7, n] += g1 * g2
        acc[11, n] += g2 * g2


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _accumulate(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, c_lo: int, c_hi: int, C: int, acc: np.ndarray,
                g: np.ndarray) -> None:
    """``acc[:, :C] +=`` the upper triangle (21 rows, row by row) of ``G^T G`` over the columns ``c_lo .. c_hi``: per
    column, the column into ``g`` (6, C), then the 21 products (two simple loops over the configurations, both
    vectorised); a column without rotation takes :func:`_translation_products`."""
    for c in range(c_lo, c_hi):
        if X[c, 1, 0] == 0.0 and X[c, 1, 1] == 0.0 and X[c, 1, 2] == 0.0:
            _translation_products(S[col_pos[c]], X, c, C, acc)
            continue
        _column_rows(S[col_pos[c]], X, c, C, g, 0)
        k = 0
        for i in range(6):
            for j in range(i, 6):
                for n in range(C):
                    acc[k, n] += g[i, n] * g[j, n]
                k += 1


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _cov_chunk(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, C: int, acc: np.ndarray, g: np.ndarray) -> None:
    """Upper triangle of ``G^T G`` (21 entries per configuration, row by row) into ``acc`` (21, C)."""
    acc[:, :C] = 0.0
    _accumulate(S, col_pos, X, 0, col_pos.shape[0], C, acc, g)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _columns_chunk(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, n0: int, C: int, G: np.ndarray) -> None:
    """Local covariance columns ``Ad_{B_k^-1} L_k`` into ``G`` (m, 6, N)."""
    for c in range(col_pos.shape[0]):
        _column_rows(S[col_pos[c]], X, c, C, G[c], n0)


@njit(cache=True, fastmath=FASTMATH, inline="always")
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


@njit(cache=True, fastmath=FASTMATH, inline="always")
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


@njit(cache=True, fastmath=FASTMATH)
def _fourth_chunk(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, site_start: np.ndarray, C: int,
                  W: np.ndarray) -> int:
    """Fourth-order covariance (Barfoot & Furgale 2014) of the chunk: the local site covariances
    ``Sigma_k = G_k^T G_k`` (upper triangles, :func:`_accumulate`) compounded in chain order
    (:func:`~ppoe_core.model.fourth_order.compound_chunk`).  ``W`` (4, PACKED, PANEL): two result panels, the
    site's covariance, the column.  A site whose columns are all exactly zero is skipped (compounding with a zero
    covariance gives the same bits).  Returns the buffer (0 or 1) holding the result."""
    a = 0
    W[0, :, :C] = 0.0
    _accumulate(S, col_pos, X, site_start[0], site_start[1], C, W[0], W[3])
    for k in range(1, site_start.shape[0] - 1):
        zero = True
        for c in range(site_start[k], site_start[k + 1]):
            for i in range(2):
                for j in range(3):
                    zero = zero and X[c, i, j] == 0.0
        if zero:
            continue
        W[2, :, :C] = 0.0
        _accumulate(S, col_pos, X, site_start[k], site_start[k + 1], C, W[2], W[3])
        compound_chunk(W[a], W[2], W[1 - a], C)
        a = 1 - a
    return a


@njit(cache=True, fastmath=FASTMATH)
def eval_chain(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, col_pos: np.ndarray, X: np.ndarray,
               mot_pos: np.ndarray, mot_kind: np.ndarray, site_start: np.ndarray, theta: np.ndarray,
               D: np.ndarray, order: int, T: np.ndarray, cov: np.ndarray, G: np.ndarray, J: np.ndarray,
               fourth: np.ndarray | None) -> None:
    """Evaluate a chain program for ``N`` configurations (the module docstring gives the program arrays).

    Parameters
    ----------
    theta : ndarray, shape (n_motion, N)
        Motion values (after mimic multiplier, offset and direction sign).
    D : ndarray, shape (n_d, 4, 4, N)
        Effect factors ``Exp(dxi)`` per effect slot (``n_d = 0`` without effects).
    order : int
        0: no covariance; 2: ``cov = G^T G`` (eq. 15/18); 4: fourth order (needs ``fourth``).  ``cov`` (N, 6, 6)
        lives in the tangent space at ``T`` (frame of the chain's end, right perturbation).
    T : ndarray, shape (N, 4, 4)
        Output mean poses.
    G, J : ndarray, shapes (m, 6, N) / (n_motion, 6, N), or with a last axis of 0 to skip them
        Output local covariance columns / joint-motion columns.
    fourth : ndarray, shape (*FOURTH_WORK, >= min(N, CHUNK)), or None
        Work array of the fourth-order compounding; None: this specialisation has no fourth-order code (order 4
        then gives no covariance: the caller must not ask for it).
    """
    N = theta.shape[1]
    C0 = min(N, CHUNK)
    S = np.empty((F.shape[0] + 1, 3, 4, C0))
    cs = np.empty((theta.shape[0], 2, C0))
    acc = np.zeros((21, C0))
    g = np.empty((6, C0))
    for n0 in range(0, N, CHUNK):
        C = min(CHUNK, N - n0)
        _suffixes(F, kind, arg, theta, D, n0, C, S, cs)
        if order == 2 and C == 1:
            _cov_one(S, col_pos, X, acc)
        elif order == 2:
            _cov_chunk(S, col_pos, X, C, acc, g)
        if G.shape[2]:
            _columns_chunk(S, col_pos, X, n0, C, G)
        if J.shape[2]:
            _motion_chunk(S, mot_pos, mot_kind, n0, C, J)
        _write_chunk(S, acc, order == 2, n0, C, T, cov)
        if fourth is not None and order == 4:
            _fourth_into(S, col_pos, X, site_start, n0, C, fourth, cov)


@njit(cache=True, fastmath=FASTMATH)
def _fourth_into(S: np.ndarray, col_pos: np.ndarray, X: np.ndarray, site_start: np.ndarray, n0: int, C: int,
                 W: np.ndarray, cov: np.ndarray) -> None:
    """Fourth-order covariances of the chunk (:func:`_fourth_chunk`) into ``cov[n0 : n0 + C]``."""
    panels = W.reshape(W.size)[: 4 * PACKED * PANEL].reshape((4, PACKED, PANEL))
    P = panels[_fourth_chunk(S, col_pos, X, site_start, C, panels)]
    for n in range(C):
        k = 0
        for i in range(6):
            for j in range(i, 6):
                cov[n0 + n, i, j] = P[k, n]
                cov[n0 + n, j, i] = P[k, n]
                k += 1


@njit(cache=True, fastmath=FASTMATH)
def fk_one(F: np.ndarray, kind: np.ndarray, arg: np.ndarray, col_pos: np.ndarray, X: np.ndarray,
           mot_pos: np.ndarray, mot_kind: np.ndarray, site_start: np.ndarray, q: np.ndarray, motion_col: np.ndarray,
           mult: np.ndarray, off: np.ndarray, order: int, T: np.ndarray, cov: np.ndarray,
           fourth: np.ndarray | None) -> bool:
    """:func:`eval_chain` of ONE configuration without effects, from the joint values: the one-configuration path of
    :meth:`PPOEModel.fk <ppoe_core.model.ppoe.PPOEModel.fk>` and of the kinematics node's compiled per-message path
    (:mod:`ppoe_core.io.joint_pose`).

    Parameters
    ----------
    q, motion_col, mult, off : ndarray
        ``theta[i] = q[motion_col[i]] * mult[i] + off[i]`` (the chain's :class:`~ppoe_core.model.chain.LeanChain`).
    order : {0, 2, 4}
        As :func:`eval_chain` (order 4 needs ``fourth``, shape ``(*FOURTH_WORK, >= 1)``).
    T, cov : ndarray, shapes (4, 4) / (6, 6)
        Outputs (``cov`` untouched for order 0 or a chain without perturbation columns).

    Returns
    -------
    bool
        False (outputs untouched) when a motion value is not finite: the caller's general path names the joint.
    """
    n_mot = motion_col.shape[0]
    theta = np.empty((n_mot, 1))
    for i in range(n_mot):
        theta[i, 0] = q[motion_col[i]] * mult[i] + off[i]
        if not np.isfinite(theta[i, 0]):
            return False
    S = np.empty((F.shape[0] + 1, 3, 4, 1))
    acc = np.zeros((21, 1))
    _suffixes(F, kind, arg, theta, np.zeros((0, 4, 4, 1)), 0, 1, S, np.empty((n_mot, 2, 1)))
    for i in range(3):
        for j in range(4):
            T[i, j] = S[0, i, j, 0]
    T[3, 0] = 0.0
    T[3, 1] = 0.0
    T[3, 2] = 0.0
    T[3, 3] = 1.0
    if col_pos.shape[0] == 0 or order == 0:
        return True
    if order == 2:
        _cov_one(S, col_pos, X, acc)
        k = 0
        for i in range(6):
            for j in range(i, 6):
                cov[i, j] = acc[k, 0]
                cov[j, i] = acc[k, 0]
                k += 1
    elif fourth is not None:
        cov1 = np.empty((1, 6, 6))
        _fourth_into(S, col_pos, X, site_start, 0, 1, fourth, cov1)
        cov[:, :] = cov1[0]
    return True
