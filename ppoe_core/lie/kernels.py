"""Compiled (numba) loops of :mod:`ppoe_core.lie` for the per-message hot path of the nodes: quaternions of
rotation matrices and the rotation of pose covariances into the ROS convention.  Each loops over a flat batch
``(N, ...)``; the public functions in :mod:`ppoe_core.lie.so3` / :mod:`ppoe_core.lie.covariance` reshape and call
them, for one pose or many."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["quat_from_matrix_kernel", "rotate_covariance_kernel"]


@njit(cache=True)
def quat_from_matrix_kernel(R: np.ndarray, out: np.ndarray) -> None:
    """Unit quaternions ``(x, y, z, w)``, ``w >= 0``, of rotation matrices ``R`` (N, 3, 3) into ``out`` (N, 4).

    Shepperd's method: of the four candidate formulas the one whose pivot (``tr``, ``r00``, ``r11``, ``r22``)
    is largest (the first one on ties; a NaN pivot wins, as ``np.argmax``), then normalised."""
    q = np.empty(4)
    for n in range(R.shape[0]):
        r00, r01, r02 = R[n, 0, 0], R[n, 0, 1], R[n, 0, 2]
        r10, r11, r12 = R[n, 1, 0], R[n, 1, 1], R[n, 1, 2]
        r20, r21, r22 = R[n, 2, 0], R[n, 2, 1], R[n, 2, 2]
        tr = r00 + r11 + r22
        k, best = 0, tr
        if not math.isnan(best):
            for i, v in ((1, r00), (2, r11), (3, r22)):
                if math.isnan(v):
                    k = i
                    break
                if v > best:
                    k, best = i, v
        if k == 0:
            q[0], q[1], q[2], q[3] = r21 - r12, r02 - r20, r10 - r01, 1.0 + tr
        elif k == 1:
            q[0], q[1], q[2], q[3] = 1.0 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12
        elif k == 2:
            q[0], q[1], q[2], q[3] = r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21, r02 - r20
        else:
            q[0], q[1], q[2], q[3] = r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22, r10 - r01
        norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        s = -1.0 / norm if q[3] / norm < 0.0 else 1.0 / norm
        for i in range(4):
            out[n, i] = q[i] * s


@njit(cache=True)
def rotate_covariance_kernel(T: np.ndarray, cov: np.ndarray, inverse: bool, out: np.ndarray) -> None:
    """``out = B cov B^T`` (or ``B^T cov B`` with ``inverse``), ``B = blockdiag(R, R)``, ``R`` the rotation of
    ``T`` (N, 4, 4); ``cov``, ``out`` (N, 6, 6)."""
    A = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for n in range(T.shape[0]):
        for i in range(3):
            for j in range(3):
                A[i, j] = T[n, j, i] if inverse else T[n, i, j]
        for bi in range(2):
            for bj in range(2):
                for i in range(3):
                    for m in range(3):
                        tmp[i, m] = A[i, 0] * cov[n, 3 * bi, 3 * bj + m] + A[i, 1] * cov[n, 3 * bi + 1, 3 * bj + m] \
                            + A[i, 2] * cov[n, 3 * bi + 2, 3 * bj + m]
                for i in range(3):
                    for j in range(3):
                        out[n, 3 * bi + i, 3 * bj + j] = tmp[i, 0] * A[j, 0] + tmp[i, 1] * A[j, 1] \
                            + tmp[i, 2] * A[j, 2]
