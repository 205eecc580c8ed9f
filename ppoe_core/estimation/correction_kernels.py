"""Compiled (numba) per-prior steps of the fusion pipeline: the Kalman update of a prior with the equivalent
measurements of the carried corrections (:func:`ppoe_core.estimation.corrections.apply_carried_corrections`), a
correction's weight (:meth:`CorrectionPolicy.ratio`), both in one call, the first prior of a run at which a correction
expires and the quick checks of a prior; pose (4, 4), covariance (6, 6) in the tool tangent space."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ppoe_core.lie.kernels import (
    covariance_passes_kernel, mat_mul, mat_mul_t, sandwich, se3_exp_one, se3_inverse_one, se3_log_one, se3_mul,
)

__all__ = [
    "apply_corrections_kernel", "correction_ratio", "first_expiry", "from_update_kernel", "fuse_one_kernel",
    "held_queries_checks", "held_queries_kernel", "prior_passes", "run_breaks",
]


@njit(cache=True)
def apply_corrections_kernel(T: np.ndarray, P_in: np.ndarray, H: np.ndarray, Rw: np.ndarray, z: np.ndarray,
                             T_out: np.ndarray, cov_out: np.ndarray) -> None:
    """:func:`_apply_into` (the compiled :func:`ppoe_core.estimation.corrections.apply_carried_corrections`)."""
    _apply_into(T, P_in, H, Rw, z, T_out, cov_out)


@njit(cache=True, inline="always")
def _apply_into(T: np.ndarray, P_in: np.ndarray, H: np.ndarray, Rw: np.ndarray, z: np.ndarray,
                T_out: np.ndarray, cov_out: np.ndarray) -> None:
    """Kalman update of the prior ``(T, P)`` with the equivalent measurement ``z = H e + n``, ``n ~ N(0,
    diag(Rw))``: ``T_out = T Exp(K z)``, ``cov_out = (I-KH) P (I-KH)^T + K diag(Rw) K^T`` (symmetrised), ``K = P
    H^T S^-1``, ``S = H P H^T + diag(Rw)``."""
    P = 0.5 * (P_in + P_in.T)
    r = H.shape[0]
    Rm = np.zeros((r, r))
    for i in range(r):
        Rm[i, i] = Rw[i]
    HP = mat_mul(H, P)
    S = mat_mul_t(HP, H) + Rm
    K = np.linalg.solve(S, HP).T.copy()
    m = mat_mul(K, z.reshape(-1, 1))[:, 0]
    IKH = np.eye(6) - mat_mul(K, H)
    cov = sandwich(IKH, P) + sandwich(K, Rm)
    cov_out[:, :] = 0.5 * (cov + cov.T)
    E = np.empty((4, 4))
    se3_exp_one(np.ascontiguousarray(m), E)
    se3_mul(T, E, T_out)


# ----------------------------------------------------------------------------
# When a carried correction fades (CorrectionPolicy.ratio): the ratio of one prior, and the first prior of a run at
# which a correction expires.  The operations (and their order) of the former Python code: the same floats.
# ----------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _ratio(dt_abs: float, q: np.ndarray, q_anchor: np.ndarray, T_rel: np.ndarray, timeout: float,
           joint_motion: float, tool_translation: float, tool_rotation: float) -> float:
    """Largest change ratio (see :func:`correction_ratio`); ``r = max(r, v)`` as Python's ``max`` (a NaN ``v``
    leaves ``r``)."""
    r = 0.0
    if timeout > 0.0:
        v = dt_abs / timeout
        if v > r:
            r = v
    if joint_motion > 0.0:
        found = False
        m = 0.0
        for k in range(q.shape[0]):
            d = abs(q[k] - q_anchor[k])
            if math.isfinite(d) and (not found or d > m):  # NaN = joint not (yet) known
                m = d
                found = True
        if found:
            v = m / joint_motion
            if v > r:
                r = v
    if tool_translation > 0.0:
        x, y, z = T_rel[0, 3], T_rel[1, 3], T_rel[2, 3]
        v = math.sqrt(x * x + y * y + z * z) / tool_translation
        if v > r:
            r = v
    if tool_rotation > 0.0:
        c = (T_rel[0, 0] + T_rel[1, 1] + T_rel[2, 2] - 1.0) / 2.0
        if -1.0 > c:
            c = -1.0
        if 1.0 < c:
            c = 1.0
        v = math.acos(c) / tool_rotation
        if v > r:
            r = v
    return r


@njit(cache=True)
def correction_ratio(dt_abs: float, q: np.ndarray, q_anchor: np.ndarray, T_rel: np.ndarray, timeout: float,
                     joint_motion: float, tool_translation: float, tool_rotation: float) -> float:
    """Largest change ratio of a correction for one prior (:meth:`CorrectionPolicy.ratio`).

    Parameters
    ----------
    dt_abs : float
        ``|t_prior - t_anchor|`` [s].
    q, q_anchor : ndarray, shape (n,)
        Joint positions of the prior and of the anchor (n = 0: no joint ratio); NaN entries are skipped.
    T_rel : ndarray, shape (4, 4)
        ``T_anchor^-1 T_prior`` (numpy's product: the angle from the trace is ill-conditioned near 0).
    timeout, joint_motion, tool_translation, tool_rotation : float
        The policy's limits; ``<= 0`` disables that ratio.
    """
    return _ratio(dt_abs, q, q_anchor, T_rel, timeout, joint_motion, tool_translation, tool_rotation)


@njit(cache=True)
def first_expiry(stamps: np.ndarray, anchor_stamp: float, Q: np.ndarray, q_anchor: np.ndarray, T_rel: np.ndarray,
                 timeout: float, joint_motion: float, tool_translation: float, tool_rotation: float) -> int:
    """First prior of a run at which a correction expires: ratio ``>= 1`` at a stamp not older than the anchor
    (:meth:`FusionPipeline.fuse`); -1 if none.

    Parameters
    ----------
    stamps : ndarray, shape (N,)
        [s]
    Q : ndarray, shape (N, n)
        Joint positions of the priors (n = 0: no joint ratio).
    T_rel : ndarray, shape (N, 4, 4)
        ``T_anchor^-1 T_prior`` of every prior (numpy's stacked product: the same floats as one at a time).
    """
    for i in range(stamps.shape[0]):
        if stamps[i] >= anchor_stamp and _ratio(abs(stamps[i] - anchor_stamp), Q[i], q_anchor, T_rel[i], timeout,
                                                joint_motion, tool_translation, tool_rotation) >= 1.0:
            return i
    return -1


@njit(cache=True)
def prior_passes(T: np.ndarray, cov: np.ndarray, check_cov: bool) -> bool:
    """Quick checks of a prior: ``T`` (4, 4) finite and, with ``check_cov``, ``cov`` (6, 6) passes the quick pass
    of :func:`ppoe_core.lie.check_covariance` (default tolerances).  False means "run the full checks" (they raise
    the error, or pass)."""
    for i in range(4):
        for j in range(4):
            if not math.isfinite(T[i, j]):
                return False
    return not check_cov or covariance_passes_kernel(cov, 1e-9, 1e-9)


@njit(cache=True)
def fuse_one_kernel(T: np.ndarray, P: np.ndarray, T_rel: np.ndarray, dt_abs: float, q: np.ndarray,
                    q_anchor: np.ndarray, timeout: float, joint_motion: float, tool_translation: float,
                    tool_rotation: float, linear: bool, H: np.ndarray, R: np.ndarray, z: np.ndarray,
                    T_out: np.ndarray, cov_out: np.ndarray) -> float:
    """One carried correction applied to a prior in one call: its weight (:meth:`CorrectionPolicy.weight`, ratio as
    :func:`correction_ratio`) and, if positive, the update of :func:`apply_corrections_kernel` with ``Rw = R / w``
    into ``T_out``, ``cov_out``.  Returns the weight (0: expired, outputs untouched)."""
    r = _ratio(dt_abs, q, q_anchor, T_rel, timeout, joint_motion, tool_translation, tool_rotation)
    if r >= 1.0:
        return 0.0
    w = 1.0 - r if linear else 1.0
    Rw = np.empty(R.shape[0])
    for i in range(R.shape[0]):
        Rw[i] = R[i] / w
    _apply_into(T, P, H, Rw, z, T_out, cov_out)
    return w


@njit(cache=True)
def held_queries_checks(t: np.ndarray, T: np.ndarray, tq: np.ndarray, nb: np.ndarray, rows: np.ndarray, n_out: int,
                        has_newest: bool, newest: float) -> int:
    """The conditions of :func:`held_queries_kernel`: 0 if they hold, -1 if the data are not in order (stamps
    increasing, finite, newer than the buffer's ``newest``; every query not older than the newest prior before it),
    -2 if ``nb`` is not non-decreasing in 0..N or a row not in 0..n_out - 1."""
    n = t.shape[0]
    for k in range(n):
        if not math.isfinite(t[k]) or (k > 0 and not t[k] > t[k - 1]) or not _finite(T[k]):
            return -1
    if n > 0 and has_newest and not t[0] > newest:
        return -1
    prev = 0
    for j in range(tq.shape[0]):
        b = nb[j]
        if b < prev or b > n or not 0 <= rows[j] < n_out:
            return -2
        prev = b
        if not math.isfinite(tq[j]) or (b > 0 and not tq[j] >= t[b - 1]) or (b == 0 and has_newest
                                                                              and not tq[j] >= newest):
            return -1
    return 0


@njit(cache=True)
def held_queries_kernel(t: np.ndarray, T: np.ndarray, P: np.ndarray, p_step: int, Q: np.ndarray, tq: np.ndarray,
                        nb: np.ndarray, rows: np.ndarray, has_newest: bool, newest: float, T_l: np.ndarray,
                        P_l: np.ndarray, q_l: np.ndarray, max_hold: float, has_corr: bool, anchor_stamp: float,
                        q_anchor: np.ndarray, T_rel: np.ndarray, T_rel_l: np.ndarray, timeout: float,
                        joint_motion: float, tool_translation: float, tool_rotation: float, linear: bool,
                        H: np.ndarray, R: np.ndarray, z: np.ndarray, found: np.ndarray, T_out: np.ndarray,
                        cov_out: np.ndarray, prior_T: np.ndarray, prior_cov: np.ndarray, prior_q: np.ndarray) -> int:
    """A run of priors and the queries between them, in their order, with at most one carried correction: query
    ``j`` comes after the first ``nb[j]`` priors and holds the newest prior before it (``lookup_hold``: found if
    at most ``max_hold`` older; the buffer's newest ``(newest, T_l, P_l, q_l)`` before the first prior).  A prior
    drops the correction as :func:`first_expiry`; a found query gets its prior with the correction applied as
    :func:`fuse_one_kernel` (weight from ``|tq[j] - anchor_stamp|``) or, at weight 0 or with none, the prior itself;
    a query at weight 0 not older than the anchor drops it too.  Outputs at row ``rows[j]``: ``found``, the fused
    ``T_out``, ``cov_out`` and the prior ``prior_T``, ``prior_cov``, ``prior_q``.

    Parameters
    ----------
    t, T, P, Q : ndarray, shapes (N,), (N, 4, 4), (N or 1, 6, 6), (N, n)
        The priors (tool-frame covariance of prior ``k``: ``P[k * p_step]``).
    tq, nb, rows : ndarray, shape (M,)
        Query stamps [s], priors before each, output rows.
    q_anchor : ndarray, shape (n,) or (0,)
        The anchor's joints; empty: no joint ratio.
    T_rel, T_rel_l : ndarray, shape (N, 4, 4), (4, 4)
        ``T_anchor^-1 T`` of every prior and of the buffer's newest (numpy's products; any values when the tool
        ratios are off).
    H, R, z : ndarray
        The correction (:class:`ppoe_core.estimation.corrections.CarriedCorrection`), if ``has_corr``.

    Returns
    -------
    int
        1 if the correction was dropped, else 0; -1 / -2 as :func:`held_queries_checks` (nothing done).
    """
    status = held_queries_checks(t, T, tq, nb, rows, found.shape[0], has_newest, newest)
    if status < 0:
        return status
    n, m, nq = t.shape[0], tq.shape[0], q_anchor.shape[0]
    Rw = np.empty(R.shape[0])
    alive = has_corr
    k = 0
    for j in range(m + 1):
        end = nb[j] if j < m else n
        while alive and k < end:
            if t[k] >= anchor_stamp and _ratio(abs(t[k] - anchor_stamp), Q[k, :nq], q_anchor, T_rel[k], timeout,
                                               joint_motion, tool_translation, tool_rotation) >= 1.0:
                alive = False
            k += 1
        if j == m:
            break
        b = nb[j]
        if b > 0:
            t_h, T_h, P_h, q_h = t[b - 1], T[b - 1], P[(b - 1) * p_step], Q[b - 1]
        elif has_newest:
            t_h, T_h, P_h, q_h = newest, T_l, P_l, q_l
        else:
            continue  # an empty buffer
        if not tq[j] - t_h <= max_hold:
            continue
        r = rows[j]
        found[r] = True
        prior_T[r, :, :] = T_h
        prior_cov[r, :, :] = P_h
        prior_q[r, :] = q_h
        if alive:
            ratio = _ratio(abs(tq[j] - anchor_stamp), q_h[:nq], q_anchor, T_rel[b - 1] if b > 0 else T_rel_l,
                           timeout, joint_motion, tool_translation, tool_rotation)
            if ratio < 1.0:
                w = 1.0 - ratio if linear else 1.0
                for i in range(R.shape[0]):
                    Rw[i] = R[i] / w
                _apply_into(T_h, P_h, H, Rw, z, T_out[r], cov_out[r])
                continue
            if tq[j] >= anchor_stamp:
                alive = False
        T_out[r, :, :] = T_h
        cov_out[r, :, :] = P_h
    return 1 if has_corr and not alive else 0


@njit(cache=True)
def run_breaks(t: np.ndarray, T: np.ndarray, finite: np.ndarray) -> np.ndarray:
    """Where a run of priors breaks (:meth:`FusionPipeline.add_priors`): ``finite[k]`` = every entry of ``T[k]``
    (N, 4, 4) finite; returns the indices ``k >= 1`` at which the stamp ``t[k]`` is not newer than ``t[k-1]`` or
    ``T[k]`` is not finite (increasing)."""
    n = t.shape[0]
    out = np.empty(n, dtype=np.int64)
    m = 0
    for k in range(n):
        ok = True
        for i in range(4):
            for j in range(4):
                if not math.isfinite(T[k, i, j]):
                    ok = False
        finite[k] = ok
        if k >= 1 and not (ok and t[k] > t[k - 1]):
            out[m] = k
            m += 1
    return out[:m]


# ----------------------------------------------------------------------------
# A new carried correction (CarriedCorrection.from_update)
# ----------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _finite(M: np.ndarray) -> bool:
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            if not math.isfinite(M[i, j]):
                return False
    return True


@njit(cache=True)
def from_update_kernel(T_anchor: np.ndarray, T_pre: np.ndarray, pre_is_anchor: bool, cov_pre: np.ndarray,
                       T_post: np.ndarray, cov_post: np.ndarray, jitter: float, H_out: np.ndarray, R_out: np.ndarray,
                       z_out: np.ndarray, T_anchor_inv: np.ndarray) -> int:
    """:meth:`CarriedCorrection.from_update` (the Python reference, the same steps: LAPACK's ``eigh`` and BLAS
    products as numpy's, one-pose SE(3) inverse and logarithm): the correction's ``H`` (r, 6), ``R``, ``z`` (r,)
    into the first ``r`` rows of ``H_out`` (6, 6), ``R_out``, ``z_out`` (6,), ``T_anchor^-1`` into
    ``T_anchor_inv``; returns ``r``, 0 when the update added no information, -1 when an input is not finite (the
    reference decides)."""
    if not (_finite(cov_pre) and _finite(cov_post) and _finite(T_anchor) and _finite(T_pre) and _finite(T_post)):
        return -1
    s0, U_all = np.linalg.eigh(0.5 * (cov_pre + cov_pre.T))
    keep0 = s0 > 1e-12 * max(s0.max(), 1e-300)
    n0 = int(keep0.sum())
    if n0 == 0:
        return 0
    U = np.ascontiguousarray(U_all[:, keep0])
    Ut = np.ascontiguousarray(U.T)
    info0 = np.zeros((n0, n0))
    s_keep = s0[keep0]
    for i in range(n0):
        info0[i, i] = 1.0 / s_keep[i]
    P1 = (Ut @ (0.5 * (cov_post + cov_post.T))) @ U
    P1 = 0.5 * (P1 + P1.T) + jitter * np.eye(n0)
    info1 = np.linalg.inv(P1)
    se3_inverse_one(T_anchor, T_anchor_inv)
    if pre_is_anchor:
        T_pre_inv = T_anchor_inv
    else:
        T_pre_inv = np.empty((4, 4))
        se3_inverse_one(T_pre, T_pre_inv)
    delta, pre = np.empty(6), np.empty(6)
    se3_log_one(T_pre_inv @ T_post, delta)
    se3_log_one(T_anchor_inv @ T_pre, pre)
    y = info1 @ (Ut @ delta)
    D = info1 - info0
    lam_all, V_all = np.linalg.eigh(0.5 * (D + D.T))
    keep = lam_all > 1e-9 * max(np.abs(lam_all).max(), 1e-300)
    r = int(keep.sum())
    if r == 0:
        return 0
    lam = lam_all[keep]
    Vt = np.ascontiguousarray(V_all[:, keep].T)
    H = Vt @ Ut
    Vy = Vt @ y
    Hp = H @ pre
    for i in range(r):
        R_out[i] = 1.0 / lam[i]
        z_out[i] = R_out[i] * Vy[i] + Hp[i]
        for j in range(6):
            H_out[i, j] = H[i, j]
    return r
