"""Compiled (numba) loops of :mod:`ppoe_core.lie` for the per-message hot path of the nodes: quaternions of
rotation matrices and the rotation of pose covariances into the ROS convention.  Each loops over a flat batch
``(N, ...)``; the public functions in :mod:`ppoe_core.lie.so3` / :mod:`ppoe_core.lie.covariance` reshape and call
them, for one pose or many."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "quat_from_matrix_kernel", "quat_from_matrix_one", "pose_fields_one", "pose_from_quat_one",
    "rotate_covariance_kernel",
    "rotate_covariance_one", "se3_exp_one", "se3_log_one", "so3_log_one",
    "se3_right_jacobian_one", "se3_right_jacobian_inv_one", "se3_inverse_one", "se3_mul",
    "covariance_passes_kernel", "covariances_pass_kernel", "mat_mul", "mat_mul_t", "sandwich",
]


@njit(cache=True, inline="always")
def _quat_into(R: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    """Shepperd's quaternion of one rotation ``R`` (3, 3) into ``out`` (4,); ``q`` (4,) scratch."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
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
        out[i] = q[i] * s


@njit(cache=True)
def quat_from_matrix_kernel(R: np.ndarray, out: np.ndarray) -> None:
    """Unit quaternions ``(x, y, z, w)``, ``w >= 0``, of rotation matrices ``R`` (N, 3, 3) into ``out`` (N, 4).

    Shepperd's method: of the four candidate formulas the one whose pivot (``tr``, ``r00``, ``r11``, ``r22``)
    is largest (the first one on ties; a NaN pivot wins, as ``np.argmax``), then normalised."""
    q = np.empty(4)
    for n in range(R.shape[0]):
        _quat_into(R[n], q, out[n])


@njit(cache=True)
def quat_from_matrix_one(R: np.ndarray, out: np.ndarray) -> None:
    """:func:`quat_from_matrix_kernel` of one rotation ``R`` (3, 3) (any layout, e.g. ``T[:3, :3]``) into ``out``
    (4,) (an output argument: a returned array costs more than the arithmetic)."""
    _quat_into(R, np.empty(4), out)


@njit(cache=True)
def pose_fields_one(T: np.ndarray, out: np.ndarray) -> None:
    """A pose message's fields of ``T`` (4, 4) into ``out`` (7,): the quaternion ``(x, y, z, w)`` of
    :func:`quat_from_matrix_kernel` (the same floats) and the translation."""
    _quat_into(T[:3, :3], np.empty(4), out[:4])
    out[4], out[5], out[6] = T[0, 3], T[1, 3], T[2, 3]


@njit(cache=True)
def pose_from_quat_one(x: float, y: float, z: float, w: float, px: float, py: float, pz: float,
                       T: np.ndarray) -> None:
    """Homogeneous (4, 4) of the quaternion ``(x, y, z, w)`` (normalised here) and translation ``(px, py, pz)``;
    the operations of the one-quaternion path of :func:`ppoe_core.lie.so3.matrix_from_quat` (bit-identical,
    tested), into ``T`` (4, 4).  A zero or non-finite norm gives NaN entries (the caller checks the norm first)."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    T[0, 0], T[0, 1], T[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    T[1, 0], T[1, 1], T[1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    T[2, 0], T[2, 1], T[2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    T[0, 3], T[1, 3], T[2, 3] = px, py, pz
    T[3, 0], T[3, 1], T[3, 2], T[3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True, inline="always")
def _rotate_cov_into(T: np.ndarray, cov: np.ndarray, inverse: bool, out: np.ndarray, A: np.ndarray,
                     tmp: np.ndarray) -> None:
    """One pose: ``out = B cov B^T`` (``B^T cov B`` with ``inverse``); ``A``, ``tmp`` (3, 3) scratch."""
    for i in range(3):
        for j in range(3):
            A[i, j] = T[j, i] if inverse else T[i, j]
    for bi in range(2):
        for bj in range(2):
            for i in range(3):
                for m in range(3):
                    tmp[i, m] = A[i, 0] * cov[3 * bi, 3 * bj + m] + A[i, 1] * cov[3 * bi + 1, 3 * bj + m] \
                        + A[i, 2] * cov[3 * bi + 2, 3 * bj + m]
            for i in range(3):
                for j in range(3):
                    out[3 * bi + i, 3 * bj + j] = tmp[i, 0] * A[j, 0] + tmp[i, 1] * A[j, 1] + tmp[i, 2] * A[j, 2]


@njit(cache=True)
def rotate_covariance_kernel(T: np.ndarray, cov: np.ndarray, inverse: bool, out: np.ndarray) -> None:
    """``out = B cov B^T`` (or ``B^T cov B`` with ``inverse``), ``B = blockdiag(R, R)``, ``R`` the rotation of
    ``T`` (N, 4, 4); ``cov``, ``out`` (N, 6, 6)."""
    A = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for n in range(T.shape[0]):
        _rotate_cov_into(T[n], cov[n], inverse, out[n], A, tmp)


@njit(cache=True)
def rotate_covariance_one(T: np.ndarray, cov: np.ndarray, inverse: bool, out: np.ndarray) -> None:
    """:func:`rotate_covariance_kernel` of one pose ``T`` (4, 4) and covariance ``cov`` (6, 6) into ``out``
    (6, 6)."""
    _rotate_cov_into(T, cov, inverse, out, np.empty((3, 3)), np.empty((3, 3)))


# ----------------------------------------------------------------------------
# SE(3) on one element, for the compiled measurement updates (ppoe_core.estimation.update_kernels).  The same
# formulas, series thresholds and operation order as the numpy functions of ppoe_core.lie.se3 / so3 (tested to
# agree to round-off); 3x3 products written out, no temporaries allocated.
# ----------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _abc(t2: float) -> tuple[float, float, float]:
    """``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` with the series of ``so3._coeffs_abc``."""
    if t2 < 1e-6:
        return (1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0,
                1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0)
    t = math.sqrt(t2)
    s, c = math.sin(t), math.cos(t)
    return s / t, (1.0 - c) / t2, (t - s) / (t2 * t)


@njit(cache=True, inline="always")
def _hat_into(w0: float, w1: float, w2: float, W: np.ndarray) -> None:
    W[0, 0], W[0, 1], W[0, 2] = 0.0, -w2, w1
    W[1, 0], W[1, 1], W[1, 2] = w2, 0.0, -w0
    W[2, 0], W[2, 1], W[2, 2] = -w1, w0, 0.0


@njit(cache=True, inline="always")
def _mm3(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """``out = A @ B`` for 3x3 blocks (``out`` must not alias ``A`` or ``B``)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True)
def se3_exp_one(xi: np.ndarray, T: np.ndarray) -> None:
    """``T = Exp(xi)`` (paper eq. 3) for one twist ``[rho; theta]`` (6,) into ``T`` (4, 4)."""
    w0, w1, w2 = xi[3], xi[4], xi[5]
    A, B, C = _abc(w0 * w0 + w1 * w1 + w2 * w2)
    W = np.empty((3, 3))
    WW = np.empty((3, 3))
    _hat_into(w0, w1, w2, W)
    _mm3(W, W, WW)
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            T[i, j] = e + A * W[i, j] + B * WW[i, j]
        v0 = (1.0 if i == 0 else 0.0) + B * W[i, 0] + C * WW[i, 0]
        v1 = (1.0 if i == 1 else 0.0) + B * W[i, 1] + C * WW[i, 1]
        v2 = (1.0 if i == 2 else 0.0) + B * W[i, 2] + C * WW[i, 2]
        T[i, 3] = v0 * xi[0] + v1 * xi[1] + v2 * xi[2]
        T[3, i] = 0.0
    T[3, 3] = 1.0


@njit(cache=True)
def so3_log_one(R: np.ndarray, w: np.ndarray) -> None:
    """Rotation vector ``w`` (3,) of ``R`` (3, 3) through the quaternion (exact near 0 and pi), as ``so3_log``."""
    q = np.empty((1, 4))
    quat_from_matrix_kernel(R.reshape(1, 3, 3), q)
    v0, v1, v2, qw = q[0, 0], q[0, 1], q[0, 2], q[0, 3]
    s = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if s < 1e-2:
        r2 = (s / qw) ** 2
        f = 2.0 / qw * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)
    else:
        f = 2.0 * math.atan2(s, qw) / s
    w[0], w[1], w[2] = f * v0, f * v1, f * v2


@njit(cache=True)
def _so3_jl_inv_into(w0: float, w1: float, w2: float, out: np.ndarray) -> None:
    """Inverse left Jacobian of SO(3) ``I - [w]/2 + D [w]^2`` into ``out`` (3, 3), as ``so3_left_jacobian_inv``."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-6:
        D = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        t = math.sqrt(t2)
        D = (1.0 - t * math.sin(t) / (2.0 * (1.0 - math.cos(t)))) / t2
    W = np.empty((3, 3))
    WW = np.empty((3, 3))
    _hat_into(w0, w1, w2, W)
    _mm3(W, W, WW)
    for i in range(3):
        for j in range(3):
            out[i, j] = (1.0 if i == j else 0.0) - 0.5 * W[i, j] + D * WW[i, j]


@njit(cache=True)
def se3_log_one(T: np.ndarray, xi: np.ndarray) -> None:
    """``xi = Log(T)`` (paper eq. 4) for one pose (4, 4) into ``xi`` (6,)."""
    w = np.empty(3)
    so3_log_one(np.ascontiguousarray(T[:3, :3]), w)
    Ji = np.empty((3, 3))
    _so3_jl_inv_into(w[0], w[1], w[2], Ji)
    for i in range(3):
        xi[i] = Ji[i, 0] * T[0, 3] + Ji[i, 1] * T[1, 3] + Ji[i, 2] * T[2, 3]
        xi[3 + i] = w[i]


@njit(cache=True)
def _q_block(r0: float, r1: float, r2: float, w0: float, w1: float, w2: float, Q: np.ndarray) -> None:
    """Barfoot's ``Q(rho, theta)`` block of the SE(3) left Jacobian (eq. 7.86b), as ``se3._q_matrix``."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-4:
        c1 = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
        c2 = 1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0
        c3 = 1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0
    else:
        t = math.sqrt(t2)
        s, c = math.sin(t), math.cos(t)
        c1 = (t - s) / (t2 * t)
        c2 = (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2)
        c3 = (2.0 * t - 3.0 * s + t * c) / (2.0 * t2 * t2 * t)
    P = np.empty((3, 3))
    W = np.empty((3, 3))
    WP = np.empty((3, 3))
    PW = np.empty((3, 3))
    WPW = np.empty((3, 3))
    WW = np.empty((3, 3))
    A1 = np.empty((3, 3))
    A2 = np.empty((3, 3))
    A3 = np.empty((3, 3))
    A4 = np.empty((3, 3))
    _hat_into(r0, r1, r2, P)
    _hat_into(w0, w1, w2, W)
    _mm3(W, P, WP)
    _mm3(P, W, PW)
    _mm3(WP, W, WPW)
    _mm3(W, W, WW)
    _mm3(WW, P, A1)
    _mm3(PW, W, A2)
    _mm3(WPW, W, A3)
    _mm3(W, WPW, A4)
    for i in range(3):
        for j in range(3):
            Q[i, j] = (0.5 * P[i, j] + c1 * (WP[i, j] + PW[i, j] + WPW[i, j])
                       + c2 * (A1[i, j] + A2[i, j] - 3.0 * WPW[i, j]) + c3 * (A3[i, j] + A4[i, j]))


@njit(cache=True)
def se3_right_jacobian_one(xi: np.ndarray, J: np.ndarray) -> None:
    """Right Jacobian ``J_r(xi) = J_l(-xi) = [[Jl, Q], [0, Jl]](-xi)`` of SE(3) into ``J`` (6, 6)."""
    r0, r1, r2, w0, w1, w2 = -xi[0], -xi[1], -xi[2], -xi[3], -xi[4], -xi[5]
    _, B, C = _abc(w0 * w0 + w1 * w1 + w2 * w2)
    W = np.empty((3, 3))
    WW = np.empty((3, 3))
    Q = np.empty((3, 3))
    _hat_into(w0, w1, w2, W)
    _mm3(W, W, WW)
    _q_block(r0, r1, r2, w0, w1, w2, Q)
    for i in range(3):
        for j in range(3):
            v = (1.0 if i == j else 0.0) + B * W[i, j] + C * WW[i, j]
            J[i, j] = v
            J[3 + i, 3 + j] = v
            J[i, 3 + j] = Q[i, j]
            J[3 + i, j] = 0.0


@njit(cache=True)
def se3_right_jacobian_inv_one(xi: np.ndarray, J: np.ndarray) -> None:
    """Inverse right Jacobian ``J_r^-1(xi) = [[Ji, -Ji Q Ji], [0, Ji]](-xi)`` of SE(3) into ``J`` (6, 6)."""
    r0, r1, r2, w0, w1, w2 = -xi[0], -xi[1], -xi[2], -xi[3], -xi[4], -xi[5]
    Ji = np.empty((3, 3))
    Q = np.empty((3, 3))
    JQ = np.empty((3, 3))
    JQJ = np.empty((3, 3))
    _so3_jl_inv_into(w0, w1, w2, Ji)
    _q_block(r0, r1, r2, w0, w1, w2, Q)
    for i in range(3):
        for j in range(3):
            JQ[i, j] = -Ji[i, 0] * Q[0, j] - Ji[i, 1] * Q[1, j] - Ji[i, 2] * Q[2, j]
    _mm3(JQ, Ji, JQJ)
    for i in range(3):
        for j in range(3):
            J[i, j] = Ji[i, j]
            J[3 + i, 3 + j] = Ji[i, j]
            J[i, 3 + j] = JQJ[i, j]
            J[3 + i, j] = 0.0


@njit(cache=True)
def se3_inverse_one(T: np.ndarray, out: np.ndarray) -> None:
    """``out = T^-1 = [[R^T, -R^T t], [0, 1]]`` for one pose (4, 4)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = T[j, i]
        out[i, 3] = -(T[0, i] * T[0, 3] + T[1, i] * T[1, 3] + T[2, i] * T[2, 3])
        out[3, i] = 0.0
    out[3, 3] = 1.0


@njit(cache=True)
def se3_mul(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """``out = A @ B`` for 4x4 poses (last rows ``[0, 0, 0, 1]``; ``out`` must not alias ``A`` or ``B``)."""
    for i in range(3):
        for j in range(4):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j] + A[i, 3] * B[3, j]
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True)
def covariance_passes_kernel(C: np.ndarray, tol: float, eig_tol: float) -> bool:
    """Quick pass of ``covariance.check_covariance`` for one ``(n, n)`` matrix: finite, ``max |C - C^T| <= tol
    scale`` and the Cholesky factorisation of ``(C + C^T) / 2 + (eig_tol scale + 1e-300) I`` succeeds (every
    eigenvalue above the tolerance), ``scale = max |C|``.  False means "decide with the eigenvalues"."""
    n = C.shape[0]
    scale = 1e-300
    for i in range(n):
        for j in range(n):
            v = C[i, j]
            if not math.isfinite(v):
                return False
            scale = max(scale, abs(v))
    A = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            if abs(C[i, j] - C[j, i]) > tol * scale:
                return False
            A[i, j] = 0.5 * (C[i, j] + C[j, i])
        A[i, i] += eig_tol * scale + 1e-300
    for j in range(n):  # in-place lower Cholesky
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        A[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= A[i, k] * A[j, k]
            A[i, j] = t / d
    return True



@njit(cache=True)
def covariances_pass_kernel(C: np.ndarray, tol: float, eig_tol: float) -> bool:
    """:func:`covariance_passes_kernel` of every matrix of a batch ``(N, n, n)``, each with its own scale.  True
    implies the batch check of ``covariance.check_covariance`` (one scale, the largest: a looser bound) passes too;
    False means "decide with the eigenvalues"."""
    for k in range(C.shape[0]):
        if not covariance_passes_kernel(C[k], tol, eig_tol):
            return False
    return True

# ----------------------------------------------------------------------------
# Small dense products without a BLAS call (the sizes of the measurement updates: 6x6, m x 6; a BLAS call and its
# result allocation cost more than the arithmetic here)
# ----------------------------------------------------------------------------


@njit(cache=True)
def mat_mul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` (n, k) x (k, m)."""
    n, k = A.shape
    m = B.shape[1]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for q in range(k):
                s += A[i, q] * B[q, j]
            out[i, j] = s
    return out


@njit(cache=True)
def mat_mul_t(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B^T`` (n, k) x (m, k)^T."""
    n, k = A.shape
    m = B.shape[0]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for q in range(k):
                s += A[i, q] * B[j, q]
            out[i, j] = s
    return out


@njit(cache=True)
def sandwich(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``A @ P @ A^T``."""
    return mat_mul_t(mat_mul(A, P), A)
