"""Evaluation of compiled chains (:mod:`ppoe_core.model.chain`): the mean pose and the local covariance columns
(``cov = G^T G``, tangent space at the chain's end pose, paper eq. 15/18) for one or many configurations."""

from __future__ import annotations

import numpy as np

from ppoe_core import lie
from ppoe_core.model.chain import OP_EFFECT, OP_ROT_Z, OP_STATIC, OP_TRANS_Z, Array, Chain

__all__ = ["evaluate", "evaluate_one", "forward_product", "exp_batch_last", "rows_to_poses"]

# ----------------------------------------------------------------------------
# Chain evaluation
# ----------------------------------------------------------------------------


_NO_D = np.zeros((0, 4, 4, 1))
#: the compiled kernel, imported on first use (numba is loaded then, not by ``import ppoe_core``); a list so that
#: the per-call lookup is one index, not an import statement
_KERNEL: list = []
_ONE: list = []


def _one_kernel() -> tuple:
    """``(fk_one, FOURTH_WORK)`` of :mod:`ppoe_core.model.chain_kernel`."""
    if not _ONE:
        from ppoe_core.model.chain_kernel import FOURTH_WORK, fk_one

        _ONE.append((fk_one, FOURTH_WORK))
    return _ONE[0]


def _kernel() -> tuple:
    """``(eval_chain, eval_panels, FOURTH_WORK)`` of :mod:`ppoe_core.model.chain_kernel` and
    :mod:`ppoe_core.model.chain_panel`."""
    if not _KERNEL:
        from ppoe_core.model.chain_kernel import FOURTH_WORK, eval_chain
        from ppoe_core.model.chain_panel import eval_panels

        _KERNEL.append((eval_chain, eval_panels, FOURTH_WORK))
    return _KERNEL[0]


def evaluate(ch: Chain, theta: Array, D: Array | None, order: int = 2, want_cols: bool = False,
             want_jac: bool = False) -> tuple[Array, Array | None, Array | None, Array | None]:
    """Mean poses, covariances, local covariance columns and joint-motion columns of a chain.

    The compiled kernel :func:`ppoe_core.model.chain_kernel.eval_chain` (suffix products from the chain's end, paper
    eq. 15/18); two or more configurations at order 0 or 2 without the columns take its panel layout
    (:func:`ppoe_core.model.chain_panel.eval_panels`: the same expressions, to a few ulp, faster).

    Parameters
    ----------
    theta : ndarray, shape (n_motion, N)
        Motion values (mimic multiplier, offset and direction sign applied).
    D : ndarray, shape (n_d, 4, 4, N), or None
        ``Exp(dxi)`` per effect site.
    order : {0, 2, 4}
        Covariance: none, second order (eq. 15/18) or fourth order (Barfoot & Furgale 2014).
    want_cols, want_jac : bool
        Also return the local covariance columns / joint-motion columns.

    Returns
    -------
    T : ndarray, shape (N, 4, 4)
        ``T_frm_to``.
    cov : ndarray, shape (N, 6, 6), or None (order 0)
        In the tangent space at ``T`` (frame ``to``, right perturbation, ``[rho; theta]``).
    G : ndarray, shape (m, 6, N), or None
        Local covariance columns (second order: ``cov = G^T G``).
    J : ndarray, shape (n_motion, 6, N), or None
        Local columns of unit joint motions (before the joint's sign / multiplier).
    """
    eval_chain, eval_panels, FOURTH_WORK = _kernel()
    N = theta.shape[1]
    F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start = ch.program
    m = col_pos.shape[0]
    T = np.empty((N, 4, 4))
    # the kernels write every entry of a covariance when the chain has columns; zeros stay when it has none
    cov = (np.empty if m > 0 else np.zeros)((N if order else 0, 6, 6))
    th = np.ascontiguousarray(theta, dtype=float)
    Dc = _NO_D if D is None or D.shape[0] == 0 else np.ascontiguousarray(D, dtype=float)
    if N > 1 and order != 4 and not want_cols and not want_jac:  # the batched fast path, same expressions
        eval_panels(F, kind, arg, col_pos, X, th, Dc, order if m > 0 else 0, T, cov)
        return T, (cov if order else None), None, None
    G = np.empty((m, 6, N if want_cols else 0))
    J = np.empty((mot_pos.shape[0], 6, N if want_jac else 0))
    # the fourth-order code is compiled only into the specialisation that gets its work array
    fourth = np.empty(FOURTH_WORK + (1,)) if order == 4 and m > 0 else None
    eval_chain(F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start, th, Dc, order if m > 0 else 0, T, cov, G, J,
               fourth)
    return T, (cov if order else None), (G if want_cols else None), (J if want_jac else None)


def evaluate_one(ch: Chain, q: Array, motion_col: Array, order: int) -> tuple[Array, Array] | None:
    """:func:`evaluate` of ONE configuration without effects from joint values, with as little Python around the
    kernel as possible (:func:`ppoe_core.model.chain_kernel.fk_one`; the one-configuration path of
    :meth:`PPOEModel.fk <ppoe_core.model.ppoe.PPOEModel.fk>`).

    Parameters
    ----------
    q : ndarray, shape (n,), float64
        Joint values; motion ``i`` takes ``q[motion_col[i]] * mult[i] + off[i]`` (mimic multiplier, offset, sign).
    motion_col : ndarray, shape (n_motion,), int64
    order : {0, 2, 4}

    Returns
    -------
    (T, cov) : ndarrays, shapes (4, 4) / (6, 6), or None when a motion value is not finite
        ``cov`` is zero for order 0 or a chain without perturbations, else in the tangent space at ``T``.
    """
    fk_one, FOURTH_WORK = _one_kernel()
    T = np.empty((4, 4))
    cov = np.zeros((6, 6))
    F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start = ch.program
    if not fk_one(F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start, q, motion_col, ch.motion_mult,
                  ch.motion_off, order, T, cov, np.empty(FOURTH_WORK + (1,)) if order == 4 else None):
        return None
    return T, cov


def forward_product(ch: Chain, theta: Array, D: Array | None, pert: list) -> Array:
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
        if code == OP_STATIC:
            P = np.einsum("ijn,jk->ikn", P, arg)
        elif code == OP_ROT_Z:
            p0 = P[:, 0].copy()
            p1 = P[:, 1]
            P[:, 0] = p0 * c[arg] + p1 * s[arg]
            P[:, 1] = p1 * c[arg] - p0 * s[arg]
        elif code == OP_TRANS_Z:
            P[:, 3] += P[:, 2] * theta[arg]
        elif code == OP_EFFECT:
            assert D is not None
            P = _mul_rows(P, D[arg])
        else:  # perturbation site
            P = _mul_rows(P, pert[arg])
    return P


def exp_batch_last(xi: Array) -> Array:
    """SE(3) ``Exp`` (:func:`ppoe_core.lie.exp`, paper eq. 3) of twists ``(6, N)`` -> ``(4, 4, N)`` (batch last)."""
    return np.moveaxis(lie.exp(np.asarray(xi).T), 0, -1)


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


def rows_to_poses(P: Array) -> Array:
    """``(3, 4, N)`` pose rows -> ``(N, 4, 4)``."""
    N = P.shape[-1]
    T = np.zeros((N, 4, 4))
    T[:, :3, :] = np.moveaxis(P, 2, 0)
    T[:, 3, 3] = 1.0
    return T
