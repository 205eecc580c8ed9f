"""THE implementation (compiled, numba) of the SO(3)/SE(3) maps of :mod:`ppoe_core.lie`: Exp/Log, left/right
Jacobians and their inverses (paper eq. 3-9, Barfoot eq. 7.77, 7.86b), inverse, quaternions (Shepperd), the rotation
of pose covariances into the ROS convention, the quick covariance check, and the Cholesky factorisation of the
compiled updates.

Each map has a one-element function (``*_one``, also called from the other compiled code: the measurement updates,
the carried corrections, the kinematics node's per-message path) and a loop over a flat batch ``(N, ...)``
(``*_kernel``).  The public numpy-facing functions of :mod:`ppoe_core.lie.so3`, :mod:`ppoe_core.lie.se3` and
:mod:`ppoe_core.lie.covariance` reshape their input and call these, for one pose or many.  Small angles use Taylor
series below ``theta^2 < 1e-6`` (``1e-4`` for the ``Q`` block), the logarithm goes through the quaternion (accurate at
and near pi); the numpy references the tests compare with are ``test/lie_reference.py``."""

from __future__ import annotations

import math

import numpy as np
from ppoe_core.jit import njit

__all__ = [
    "quat_into", "quat_from_matrix_kernel", "quat_from_matrix_one", "pose_fields_one", "pose_cov_fields_into",
    "pose_from_quat_one",
    "matrix_from_quat_kernel", "rotate_covariance_into", "rotate_covariance_kernel", "rotate_covariance_one",
    "so3_exp_kernel", "so3_log_kernel", "so3_log_one", "so3_left_jacobian_kernel", "so3_left_jacobian_inv_kernel",
    "se3_exp_one", "se3_exp_kernel", "se3_log_one", "se3_log_kernel", "se3_left_jacobian_one",
    "se3_left_jacobian_kernel", "se3_left_jacobian_inv_one", "se3_left_jacobian_inv_kernel",
    "se3_right_jacobian_one", "se3_right_jacobian_inv_one", "se3_inverse_one", "se3_inverse_kernel", "se3_mul",
    "cholesky_into", "covariance_passes_kernel", "covariances_pass_kernel", "mat_mul", "mat_mul_t", "sandwich",
]


@njit(cache=True, inline="always")
def quat_into(R: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
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
        quat_into(R[n], q, out[n])


@njit(cache=True)
def quat_from_matrix_one(R: np.ndarray, out: np.ndarray) -> None:
    """:func:`quat_from_matrix_kernel` of one rotation ``R`` (3, 3) (any layout, e.g. ``T[:3, :3]``) into ``out``
    (4,) (an output argument: a returned array costs more than the arithmetic)."""
    quat_into(R, np.empty(4), out)


@njit(cache=True)
def pose_fields_one(T: np.ndarray, out: np.ndarray) -> None:
    """A pose message's fields of ``T`` (4, 4) into ``out`` (7,): the quaternion ``(x, y, z, w)`` of
    :func:`quat_from_matrix_kernel` (the same floats) and the translation."""
    quat_into(T[:3, :3], np.empty(4), out[:4])
    out[4], out[5], out[6] = T[0, 3], T[1, 3], T[2, 3]


@njit(cache=True)
def pose_cov_fields_into(T: np.ndarray, cov_tool: np.ndarray, out: np.ndarray) -> None:
    """A ``geometry_msgs/PoseWithCovariance``'s 43 doubles of ``T`` (4, 4) and ``cov_tool`` (6, 6, the tangent space
    at ``T``) into ``out`` (43,): position, the quaternion ``(x, y, z, w)`` of :func:`quat_from_matrix_kernel` and
    the covariance in the ROS convention, ``B cov_tool B^T`` (docs/conventions.md sec. 2), row-major.  The one
    writer of these fields: the kinematics node's per-message path and the fusion node's output both call it."""
    out[0], out[1], out[2] = T[0, 3], T[1, 3], T[2, 3]
    quat_into(T[:3, :3], np.empty(4), out[3:7])
    ros = np.empty((6, 6))
    rotate_covariance_into(T, cov_tool, False, ros, np.empty((3, 3)), np.empty((3, 3)))
    for i in range(6):
        for j in range(6):
            out[7 + 6 * i + j] = ros[i, j]


@njit(cache=True, inline="always")
def _rotation_of_quat(x: float, y: float, z: float, w: float, R: np.ndarray) -> None:
    """Rotation matrix of the quaternion ``(x, y, z, w)`` (normalised here) into ``R`` (3, 3); a zero or non-finite
    norm gives NaN entries."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (0.0 < n < math.inf):
        x = y = z = w = math.nan
    else:
        x, y, z, w = x / n, y / n, z / n, w / n
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)


@njit(cache=True)
def matrix_from_quat_kernel(q: np.ndarray, out: np.ndarray) -> None:
    """Rotation matrices ``out`` (N, 3, 3) of the quaternions ``q`` (N, 4) ``(x, y, z, w)``, each normalised."""
    for n in range(q.shape[0]):
        _rotation_of_quat(q[n, 0], q[n, 1], q[n, 2], q[n, 3], out[n])


@njit(cache=True)
def pose_from_quat_one(x: float, y: float, z: float, w: float, px: float, py: float, pz: float,
                       T: np.ndarray) -> None:
    """Homogeneous (4, 4) of the quaternion ``(x, y, z, w)`` (normalised here, as :func:`matrix_from_quat_kernel`)
    and translation ``(px, py, pz)`` into ``T``."""
    _rotation_of_quat(x, y, z, w, T)
    T[0, 3], T[1, 3], T[2, 3] = px, py, pz
    T[3, 0], T[3, 1], T[3, 2], T[3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True, inline="always")
def rotate_covariance_into(T: np.ndarray, cov: np.ndarray, inverse: bool, out: np.ndarray, A: np.ndarray,
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
        rotate_covariance_into(T[n], cov[n], inverse, out[n], A, tmp)


@njit(cache=True)
def rotate_covariance_one(T: np.ndarray, cov: np.ndarray, inverse: bool, out: np.ndarray) -> None:
    """:func:`rotate_covariance_kernel` of one pose ``T`` (4, 4) and covariance ``cov`` (6, 6) into ``out``
    (6, 6)."""
    rotate_covariance_into(T, cov, inverse, out, np.empty((3, 3)), np.empty((3, 3)))


# ----------------------------------------------------------------------------
# SO(3) / SE(3) maps: one element (3x3 products written out) and a loop over a flat batch
# ----------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _abc(t2: float) -> tuple[float, float, float]:
    """``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` (series below ``t^2 < 1e-6``)."""
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


@njit(cache=True, inline="always")
def _exp_blocks(w0: float, w1: float, w2: float, R: np.ndarray, V: np.ndarray) -> None:
    """``R = Exp(w) = I + A W + B W^2`` (Rodrigues) and ``V = J_l(w) = I + B W + C W^2`` into (3, 3) blocks."""
    _exp_work(w0, w1, w2, R, V, np.empty((3, 3)), np.empty((3, 3)))


@njit(cache=True, inline="always")
def _exp_work(w0: float, w1: float, w2: float, R: np.ndarray, V: np.ndarray, W: np.ndarray, WW: np.ndarray) -> None:
    """:func:`_exp_blocks` with the work blocks ``W``, ``WW`` (3, 3) given (a batch loop allocates them once: the
    allocation cost more than the arithmetic)."""
    A, B, C = _abc(w0 * w0 + w1 * w1 + w2 * w2)
    _hat_into(w0, w1, w2, W)
    _mm3(W, W, WW)
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            R[i, j] = e + A * W[i, j] + B * WW[i, j]
            V[i, j] = e + B * W[i, j] + C * WW[i, j]


@njit(cache=True)
def se3_exp_one(xi: np.ndarray, T: np.ndarray) -> None:
    """``T = Exp(xi)`` (paper eq. 3) for one twist ``[rho; theta]`` (6,) into ``T`` (4, 4)."""
    _se3_exp_work(xi, T, np.empty((3, 3, 3)))


@njit(cache=True, inline="always")
def _se3_exp_work(xi: np.ndarray, T: np.ndarray, work: np.ndarray) -> None:
    """:func:`se3_exp_one` with its work blocks ``work`` (3, 3, 3) given."""
    V = work[0]
    _exp_work(xi[3], xi[4], xi[5], T, V, work[1], work[2])
    for i in range(3):
        T[i, 3] = V[i, 0] * xi[0] + V[i, 1] * xi[1] + V[i, 2] * xi[2]
        T[3, i] = 0.0
    T[3, 3] = 1.0


@njit(cache=True)
def se3_exp_kernel(xi: np.ndarray, out: np.ndarray) -> None:
    """:func:`se3_exp_one` of twists ``xi`` (N, 6) into ``out`` (N, 4, 4)."""
    work = np.empty((3, 3, 3))
    for n in range(xi.shape[0]):
        _se3_exp_work(xi[n], out[n], work)


@njit(cache=True)
def so3_exp_kernel(w: np.ndarray, out: np.ndarray) -> None:
    """Rodrigues' ``Exp`` of rotation vectors ``w`` (N, 3) into ``out`` (N, 3, 3)."""
    V = np.empty((3, 3))
    for n in range(w.shape[0]):
        _exp_blocks(w[n, 0], w[n, 1], w[n, 2], out[n], V)


@njit(cache=True)
def so3_left_jacobian_kernel(w: np.ndarray, out: np.ndarray) -> None:
    """Left Jacobian of SO(3) ``I + B [w] + C [w]^2`` (Barfoot eq. 7.77) of ``w`` (N, 3) into ``out`` (N, 3, 3)."""
    R = np.empty((3, 3))
    for n in range(w.shape[0]):
        _exp_blocks(w[n, 0], w[n, 1], w[n, 2], R, out[n])


@njit(cache=True)
def so3_log_one(R: np.ndarray, w: np.ndarray) -> None:
    """Rotation vector ``w`` (3,) of ``R`` (3, 3), angle in ``[0, pi]``, through the quaternion (exact near 0 and
    pi; at exactly pi the axis sign is arbitrary)."""
    q = np.empty(4)
    quat_into(R, np.empty(4), q)
    v0, v1, v2, qw = q[0], q[1], q[2], q[3]
    s = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if s < 1e-2:
        r2 = (s / qw) ** 2
        f = 2.0 / qw * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)
    else:
        f = 2.0 * math.atan2(s, qw) / s
    w[0], w[1], w[2] = f * v0, f * v1, f * v2


@njit(cache=True)
def so3_log_kernel(R: np.ndarray, out: np.ndarray) -> None:
    """:func:`so3_log_one` of rotations ``R`` (N, 3, 3) into ``out`` (N, 3)."""
    for n in range(R.shape[0]):
        so3_log_one(R[n], out[n])


@njit(cache=True)
def _so3_jl_inv_into(w0: float, w1: float, w2: float, out: np.ndarray) -> None:
    """Inverse left Jacobian of SO(3) ``I - [w]/2 + D [w]^2``, ``D = (1 - t sin t / (2 (1 - cos t))) / t^2``
    (series below ``t^2 < 1e-6``), into ``out`` (3, 3)."""
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
def so3_left_jacobian_inv_kernel(w: np.ndarray, out: np.ndarray) -> None:
    """Inverse left Jacobian of SO(3) of ``w`` (N, 3) into ``out`` (N, 3, 3)."""
    for n in range(w.shape[0]):
        _so3_jl_inv_into(w[n, 0], w[n, 1], w[n, 2], out[n])


@njit(cache=True)
def se3_log_one(T: np.ndarray, xi: np.ndarray) -> None:
    """``xi = Log(T)`` (paper eq. 4) for one pose (4, 4) into ``xi`` (6,)."""
    w = np.empty(3)
    so3_log_one(T[:3, :3], w)
    Ji = np.empty((3, 3))
    _so3_jl_inv_into(w[0], w[1], w[2], Ji)
    for i in range(3):
        xi[i] = Ji[i, 0] * T[0, 3] + Ji[i, 1] * T[1, 3] + Ji[i, 2] * T[2, 3]
        xi[3 + i] = w[i]


@njit(cache=True)
def se3_log_kernel(T: np.ndarray, out: np.ndarray) -> None:
    """:func:`se3_log_one` of poses ``T`` (N, 4, 4) into ``out`` (N, 6)."""
    for n in range(T.shape[0]):
        se3_log_one(T[n], out[n])


@njit(cache=True)
def _q_block(r0: float, r1: float, r2: float, w0: float, w1: float, w2: float, Q: np.ndarray) -> None:
    """Barfoot's ``Q(rho, theta)`` block of the SE(3) left Jacobian (eq. 7.86b); series below ``theta^2 < 1e-4``."""
    _q_work(r0, r1, r2, w0, w1, w2, Q, np.empty((10, 3, 3)))


@njit(cache=True, inline="always")
def _q_work(r0: float, r1: float, r2: float, w0: float, w1: float, w2: float, Q: np.ndarray,
            work: np.ndarray) -> None:
    """:func:`_q_block` with its work blocks ``work`` (10, 3, 3) given."""
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
    P, W, WP, PW, WPW, WW, A1, A2, A3, A4 = (work[0], work[1], work[2], work[3], work[4], work[5], work[6], work[7],
                                             work[8], work[9])
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


@njit(cache=True, inline="always")
def _upper_block_triangular(A: np.ndarray, B: np.ndarray, J: np.ndarray) -> None:
    """``J = [[A, B], [0, A]]`` (6, 6) of 3x3 blocks."""
    for i in range(3):
        for j in range(3):
            J[i, j] = A[i, j]
            J[3 + i, 3 + j] = A[i, j]
            J[i, 3 + j] = B[i, j]
            J[3 + i, j] = 0.0


@njit(cache=True)
def se3_left_jacobian_one(xi: np.ndarray, J: np.ndarray) -> None:
    """Left Jacobian of SE(3) ``[[J_l, Q], [0, J_l]](xi)`` into ``J`` (6, 6): ``Exp(xi + d) ~ Exp(J d) Exp(xi)``."""
    _se3_left_jacobian_work(xi, J, np.empty((15, 3, 3)))


@njit(cache=True, inline="always")
def _se3_left_jacobian_work(xi: np.ndarray, J: np.ndarray, work: np.ndarray) -> None:
    """:func:`se3_left_jacobian_one` with its work blocks ``work`` (15, 3, 3) given."""
    R, V, Q = work[0], work[1], work[2]
    _exp_work(xi[3], xi[4], xi[5], R, V, work[3], work[4])
    _q_work(xi[0], xi[1], xi[2], xi[3], xi[4], xi[5], Q, work[5:])
    _upper_block_triangular(V, Q, J)


@njit(cache=True)
def se3_left_jacobian_inv_one(xi: np.ndarray, J: np.ndarray) -> None:
    """Inverse left Jacobian of SE(3) ``[[Ji, -Ji Q Ji], [0, Ji]](xi)`` into ``J`` (6, 6)."""
    Ji = np.empty((3, 3))
    Q = np.empty((3, 3))
    JQ = np.empty((3, 3))
    JQJ = np.empty((3, 3))
    _so3_jl_inv_into(xi[3], xi[4], xi[5], Ji)
    _q_block(xi[0], xi[1], xi[2], xi[3], xi[4], xi[5], Q)
    for i in range(3):
        for j in range(3):
            JQ[i, j] = -Ji[i, 0] * Q[0, j] - Ji[i, 1] * Q[1, j] - Ji[i, 2] * Q[2, j]
    _mm3(JQ, Ji, JQJ)
    _upper_block_triangular(Ji, JQJ, J)


@njit(cache=True)
def se3_right_jacobian_one(xi: np.ndarray, J: np.ndarray) -> None:
    """Right Jacobian of SE(3) ``J_r(xi) = J_l(-xi)`` into ``J`` (6, 6): ``Exp(xi + d) ~ Exp(xi) Exp(J d)``."""
    se3_left_jacobian_one(-xi, J)


@njit(cache=True)
def se3_right_jacobian_inv_one(xi: np.ndarray, J: np.ndarray) -> None:
    """Inverse right Jacobian of SE(3) ``J_r^-1(xi) = J_l^-1(-xi)`` into ``J`` (6, 6)."""
    se3_left_jacobian_inv_one(-xi, J)


@njit(cache=True)
def se3_left_jacobian_kernel(xi: np.ndarray, out: np.ndarray) -> None:
    """:func:`se3_left_jacobian_one` of twists ``xi`` (N, 6) into ``out`` (N, 6, 6)."""
    work = np.empty((15, 3, 3))
    for n in range(xi.shape[0]):
        _se3_left_jacobian_work(xi[n], out[n], work)


@njit(cache=True)
def se3_left_jacobian_inv_kernel(xi: np.ndarray, out: np.ndarray) -> None:
    """:func:`se3_left_jacobian_inv_one` of twists ``xi`` (N, 6) into ``out`` (N, 6, 6)."""
    for n in range(xi.shape[0]):
        se3_left_jacobian_inv_one(xi[n], out[n])


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
def se3_inverse_kernel(T: np.ndarray, out: np.ndarray) -> None:
    """:func:`se3_inverse_one` of poses ``T`` (N, 4, 4) into ``out`` (N, 4, 4)."""
    for n in range(T.shape[0]):
        se3_inverse_one(T[n], out[n])


@njit(cache=True)
def se3_mul(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """``out = A @ B`` for 4x4 poses (last rows ``[0, 0, 0, 1]``; ``out`` must not alias ``A`` or ``B``)."""
    for i in range(3):
        for j in range(4):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j] + A[i, 3] * B[3, j]
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True)
def cholesky_into(S: np.ndarray, L: np.ndarray) -> int:
    """THE Cholesky factorisation of the compiled code: lower ``L`` with ``S = L L^T`` (``S`` (n, n) symmetric, only
    its lower triangle read); returns 0, or the 1-based leading minor that is not positive (``L`` then partial)."""
    n = S.shape[0]
    L[:, :] = 0.0
    for j in range(n):
        s = S[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return j + 1
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = S[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    return 0


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
    return cholesky_into(A, np.empty((n, n))) == 0


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
    return mat_mul(A, B.T)


@njit(cache=True)
def sandwich(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``A @ P @ A^T``."""
    return mat_mul_t(mat_mul(A, P), A)
