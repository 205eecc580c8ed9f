"""Compiled (numba) per-prior step of the fusion pipeline: the Kalman update of a prior with the equivalent
measurements of the carried corrections (:func:`ppoe_core.estimation.corrections.apply_carried_corrections`); pose
(4, 4), covariance (6, 6) in the tool tangent space."""

from __future__ import annotations

import numpy as np
from numba import njit

from ppoe_core.lie.kernels import mat_mul, mat_mul_t, sandwich, se3_exp_one, se3_mul

__all__ = ["apply_corrections_kernel"]


@njit(cache=True)
def apply_corrections_kernel(T: np.ndarray, P_in: np.ndarray, H: np.ndarray, Rw: np.ndarray, z: np.ndarray,
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
