"""Evaluation of compiled chains (:mod:`ppoe_core.model.chain`): the mean pose and the local covariance columns
(``cov = G^T G``, tangent space at the chain's end pose, paper eq. 15/18) for one or many configurations."""

from __future__ import annotations

from typing import Any

import numpy as np

from ppoe_core.model.chain import _D, _RZ, _S, _TZ, Array, _Chain

# ----------------------------------------------------------------------------
# Chain evaluation
# ----------------------------------------------------------------------------


def _eval_single(ch: _Chain, theta: Array, D: Array | None) -> tuple[Array, Array]:
    """One configuration: ``theta`` (n_motion,), ``D`` (n_d, 4, 4) or None.

    Returns ``(T (4, 4), suffixes (n_f + 1, 4, 4))`` with ``suffixes[k]`` = product of the
    factors ``k, k+1, ...`` (``suffixes[n_f]`` = identity, ``suffixes[0]`` = T).
    """
    F = ch.f_static.copy()
    if theta.size:
        rz, fz = ch.f_rz
        if fz.size:
            th = theta[rz]
            c, s = np.cos(th), np.sin(th)
            F[fz, 0, 0] = c
            F[fz, 1, 1] = c
            F[fz, 0, 1] = -s
            F[fz, 1, 0] = s
        tz, ft = ch.f_tz
        if ft.size:
            F[ft, 2, 3] = theta[tz]
    if D is not None and len(ch.f_d_idx):
        F[ch.f_d_idx] = D
    # Hillis-Steele inclusive suffix product (log depth, order-preserving)
    n = F.shape[0]
    S = np.empty((n + 1, 4, 4))
    S[:n] = F
    S[n] = np.eye(4)
    d = 1
    while d < n:
        S[: n - d] = S[: n - d] @ S[d:n]
        d *= 2
    return S[0], S


def _columns(B: Array, LvT: Array, LwT: Array, H: Array, rot_only: bool) -> Array:
    """``Ad_{B^-1} L`` for poses ``B`` as rows ``(3, 4, N)``; returns ``(r, 6, N)``.

    ``Ad_{B^-1} [v; w] = [R^T (v + w x t); R^T w]`` (paper eq. 7 for the inverse pose).
    """
    R = B[:, :3]
    t = B[:, 3]
    r = LwT.shape[0]
    N = B.shape[-1]
    out = np.empty((r, 6, N))
    out[:, 3:] = np.tensordot(LwT, R, axes=1)
    u = np.tensordot(H, t, axes=1)  # (r, 3, N): w x t
    if not rot_only:
        u += LvT[:, :, None]
    out[:, :3] = u[:, 0, None] * R[0] + u[:, 1, None] * R[1] + u[:, 2, None] * R[2]
    return out


# (e_j x t) = sum over (k, sign, l): sign * t_l e_k
_CROSS_E = (((1, -1.0, 2), (2, 1.0, 1)), ((0, 1.0, 2), (2, -1.0, 0)), ((0, -1.0, 1), (1, 1.0, 0)))


def _sparse_column(B: Array, vnz: tuple, wnz: tuple, out: Array) -> None:
    """``Ad_{B^-1} L`` for one column with few non-zeros, written into ``out`` (6, N).

    ``vnz`` / ``wnz``: ``((j, value), ...)`` of the translational / rotational part; the
    result is ``[R^T (v + w x t); R^T w]`` with ``R^T e_j`` = row ``j`` of ``R``.
    """
    R = B[:, :3]
    t = B[:, 3]
    first_v = True
    first_w = True
    for j, b in wnz:
        if first_w:
            np.multiply(R[j], b, out=out[3:])
            first_w = False
        else:
            out[3:] += b * R[j]
        for k, sg, l in _CROSS_E[j]:
            term = (sg * b) * t[l] * R[k]
            if first_v:
                out[:3] = term
                first_v = False
            else:
                out[:3] += term
    for j, a in vnz:
        if first_v:
            np.multiply(R[j], a, out=out[:3])
            first_v = False
        else:
            out[:3] += a * R[j]
    if first_w:
        out[3:] = 0.0
    if first_v:
        out[:3] = 0.0


def _motion_column(code: int, B: Array, J_k: Array) -> None:
    """Local column of a unit joint motion about / along z at the rest ``B`` of the chain: ``Ad_{B^-1}`` of
    ``[0; e_z]`` (revolute: ``[R^T (e_z x t); R^T e_z]``) or ``[e_z; 0]`` (prismatic), written into ``J_k`` (6, N)."""
    if code == _RZ:
        J_k[3:] = B[2, :3]
        J_k[:3] = B[1, :3] * B[0, 3] - B[0, :3] * B[1, 3]
    else:
        J_k[:3] = B[2, :3]
        J_k[3:] = 0.0


def _eval_backward(
    ch: _Chain, theta: Array, D: Array | None, want_cov: bool, want_jac: bool
) -> tuple[Array, Array | None, Array | None]:
    """Many configurations, walking the chain backwards with ``B`` = product of the rest.

    At a perturbation site, ``B`` is the paper's "everything after it", so the site's local
    columns are ``Ad_{B^-1} L_k`` (eq. 15/18) without any inverse; at the end ``B = T``.

    Parameters
    ----------
    theta : (n_motion, N)
    D : (n_d, 4, 4, N) or None

    Returns
    -------
    B : (3, 4, N) rows of ``T_frm_to``
    G : (m, 6, N) local covariance columns (``cov = G^T G``) or None
    J : (n_motion, 6, N) local joint-motion columns (unit joint speed, before the sign /
        multiplier) or None
    """
    N = theta.shape[1]
    B: Array | None = None  # None = identity
    G = np.empty((ch.L_all.shape[0], 6, N)) if want_cov else None
    J = np.empty((len(ch.motion_joint), 6, N)) if want_jac else None
    c: Any = None
    s: Any = None
    if theta.size:
        c, s = np.cos(theta), np.sin(theta)

    def ident() -> Array:
        out = np.zeros((3, 4, N))
        out[0, 0] = out[1, 1] = out[2, 2] = 1.0
        return out

    for code, arg in reversed(ch.ops):
        if code == _S:
            if B is None:
                B = np.repeat(arg[:3, :, None], N, axis=2)
            else:
                B = np.tensordot(arg[:3, :3], B, axes=1)
                B[:, 3] += arg[:3, 3, None]
            continue
        if B is None:
            B = ident()
        if code == _RZ or code == _TZ:
            if J is not None:
                _motion_column(code, B, J[arg])
            if code == _RZ:
                b0 = B[0].copy()
                ci, si = c[arg], s[arg]
                B[0] = ci * b0 - si * B[1]
                B[1] = si * b0 + ci * B[1]
            else:
                B[2, 3] += theta[arg]
        elif code == _D:
            assert D is not None  # a _D step exists only when displacements were given
            Dk = D[arg]
            Bn = np.einsum("ijn,jkn->ikn", Dk[:3, :3], B)
            Bn[:, 3] += Dk[:3, 3]
            B = Bn
        elif G is not None:  # site
            LvT, LwT, H, rot_only, c0, c1 = ch.site_cols[arg]
            sparse = ch.site_sparse[arg]
            if sparse is None:
                G[c0:c1] = _columns(B, LvT, LwT, H, rot_only)
            else:
                for col, vnz, wnz in sparse:
                    _sparse_column(B, vnz, wnz, G[col])
    if B is None:
        B = ident()
    return B, G, J


def _eval_forward(ch: _Chain, theta: Array, D: Array | None, pert: list) -> Array:
    """Forward product of the chain for many configurations with sampled perturbations.

    Used by the Monte-Carlo sampler: every perturbation ``Exp(xi_k)`` is inserted at its
    place (eq. 16-17), nothing is linearised.

    Parameters
    ----------
    theta : (n_motion, N)
    D : (n_d, 4, 4, N) or None
        ``Exp(dxi)`` per effect site.
    pert : list of (4, 4, N)
        ``Exp(xi_k)`` per perturbation site, right-multiplied at the site.

    Returns
    -------
    ndarray, shape (3, 4, N)
        Rows of ``T_frm_to``.
    """
    N = theta.shape[1]
    P = np.zeros((3, 4, N))
    P[0, 0] = P[1, 1] = P[2, 2] = 1.0
    if theta.size:
        c, s = np.cos(theta), np.sin(theta)
    for code, arg in ch.ops:
        if code == _S:
            P = np.einsum("ijn,jk->ikn", P, arg)
        elif code == _RZ:
            p0 = P[:, 0].copy()
            p1 = P[:, 1]
            P[:, 0] = p0 * c[arg] + p1 * s[arg]
            P[:, 1] = p1 * c[arg] - p0 * s[arg]
        elif code == _TZ:
            P[:, 3] += P[:, 2] * theta[arg]
        elif code == _D:
            assert D is not None
            P = _mul_rows(P, D[arg])
        else:  # perturbation site
            P = _mul_rows(P, pert[arg])
    return P


def _exp_batch_last(xi: Array) -> Array:
    """SE(3) ``Exp`` for twists ``(6, N)`` -> ``(4, 4, N)`` (batch last, elementwise).

    Same map as :func:`ppoe_core.lie.exp` (paper eq. 3): ``R = I + A W + B W^2``,
    ``t = (I + B W + C W^2) rho`` with ``A = sin t / t``, ``B = (1 - cos t) / t^2``,
    ``C = (t - sin t) / t^3`` (Taylor series below ``t^2 < 1e-6``) and ``W^2 = w w^T - t^2 I``.
    """
    rho, w = xi[:3], xi[3:]
    N = xi.shape[1]
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    small = t2 < 1e-6
    ts = np.sqrt(np.where(small, 1.0, t2))
    st, ct = np.sin(ts), np.cos(ts)
    A = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, st / ts)
    B = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - ct) / np.where(small, 1.0, t2))
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (ts - st) / (ts * np.where(small, 1.0, t2)))
    out = np.zeros((4, 4, N))
    # W w-cross matrix entries: W[0,1] = -w2, W[0,2] = w1, W[1,2] = -w0
    for i in range(3):
        for j in range(3):
            ww = w[i] * w[j]
            out[i, j] = B * ww
            if i == j:
                out[i, j] += 1.0 - B * t2
    out[0, 1] -= A * w[2]
    out[1, 0] += A * w[2]
    out[0, 2] += A * w[1]
    out[2, 0] -= A * w[1]
    out[1, 2] -= A * w[0]
    out[2, 1] += A * w[0]
    # t = rho + B (w x rho) + C (w x (w x rho)),  w x (w x rho) = w (w.rho) - t2 rho
    wxr = np.stack([w[1] * rho[2] - w[2] * rho[1], w[2] * rho[0] - w[0] * rho[2], w[0] * rho[1] - w[1] * rho[0]])
    wr = w[0] * rho[0] + w[1] * rho[1] + w[2] * rho[2]
    out[:3, 3] = rho + B * wxr + C * (w * wr - t2 * rho)
    out[3, 3] = 1.0
    return out


def _mul_rows(P: Array, E: Array) -> Array:
    """``P @ E`` for pose rows ``P`` (3, 4, N) and poses ``E`` (4, 4, N) (last row 0 0 0 1)."""
    out = np.empty_like(P)
    p0, p1, p2 = P[:, 0], P[:, 1], P[:, 2]
    for k in range(4):
        out[:, k] = p0 * E[0, k] + p1 * E[1, k] + p2 * E[2, k]
    out[:, 3] += P[:, 3]
    return out


# ----------------------------------------------------------------------------
# Covariance pieces
# ----------------------------------------------------------------------------


def _rows_to_T(P: Array) -> Array:
    """``(3, 4, N)`` pose rows -> ``(N, 4, 4)``."""
    N = P.shape[-1]
    T = np.zeros((N, 4, 4))
    T[:, :3, :] = np.moveaxis(P, 2, 0)
    T[:, 3, 3] = 1.0
    return T


def _local_columns_single(ch: _Chain, S: Array) -> Array:
    """``G`` (m, 6): columns ``Ad_{B_k^-1} L_k`` for one configuration (suffixes ``S``).

    ``Ad_{B^-1} [v; w] = [R^T (v + w x t); R^T w]``, evaluated as row vectors
    ``[(v + w x t)^T; w^T] @ R`` for all columns in one stacked product.
    """
    Bk = S[ch.col_pos]  # (m, 4, 4): everything after each column's site
    X = ch.X_rows.copy()  # (m, 2, 3): rows [v^T; w^T]
    X[:, 0] += (ch.H_all @ Bk[:, :3, 3:])[:, :, 0]  # + (w x t)^T
    return (X @ Bk[:, :3, :3]).reshape(-1, 6)
