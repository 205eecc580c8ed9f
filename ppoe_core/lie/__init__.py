"""SE(3) and SO(3) Lie group tools, batched over leading axes.

Conventions (CONTRACT.md section 1, paper section III):

* A twist is ``xi = [rho; theta]`` with shape ``(..., 6)``: translation first.
* Poses are homogeneous matrices of shape ``(..., 4, 4)``.
* Perturbations are right / local: ``X = Xbar @ exp(xi)`` (paper eq. 8); a
  covariance ``E[xi xi^T]`` lives in the tangent space at ``Xbar`` (eq. 9).

Every function broadcasts over leading batch axes, in the style of
pytransform3d's ``trajectories`` module.  Small angles are handled with
vectorised ``np.where`` and Taylor series (as in jaxlie's ``_so3.py``); the
logarithm goes through a quaternion (Shepperd's method), which keeps it
accurate at and near ``pi``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ppoe_core.errors import CovarianceError, MeasurementError

__all__ = [
    "hat3",
    "vee3",
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "exp",
    "log",
    "adjoint",
    "curly_hat",
    "left_jacobian",
    "right_jacobian",
    "left_jacobian_inv",
    "right_jacobian_inv",
    "inverse",
    "compose",
    "oplus",
    "ominus",
    "from_rt",
    "fit_rigid",
    "from_xyz_rpy",
    "matrix_from_rpy",
    "rpy_from_matrix",
    "quat_from_matrix",
    "matrix_from_quat",
    "interpolate",
    "cov_local_to_ros",
    "cov_ros_to_local",
    "check_covariance",
]

Array = NDArray[np.float64]

# Below these angles the closed forms lose precision and Taylor series are used.
_SMALL = 1e-4
_SMALL_Q = 1e-2


def _f(x: ArrayLike) -> Array:
    return np.asarray(x, dtype=np.float64)


# ----------------------------------------------------------------------------
# hat / vee
# ----------------------------------------------------------------------------


def hat3(w: ArrayLike) -> Array:
    """Skew-symmetric matrix ``[w]_x`` of a 3-vector.

    Parameters
    ----------
    w : array_like, shape (..., 3)

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    w = _f(w)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee3(W: ArrayLike) -> Array:
    """Inverse of :func:`hat3`: ``(..., 3, 3) -> (..., 3)``."""
    W = _f(W)
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


def hat(xi: ArrayLike) -> Array:
    """``xi^`` in se(3) (paper eq. 2): ``(..., 6) -> (..., 4, 4)``."""
    xi = _f(xi)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = hat3(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def vee(X: ArrayLike) -> Array:
    """Inverse of :func:`hat`: ``(..., 4, 4) -> (..., 6)``."""
    X = _f(X)
    return np.concatenate([X[..., :3, 3], vee3(X[..., :3, :3])], axis=-1)


# ----------------------------------------------------------------------------
# SO(3)
# ----------------------------------------------------------------------------


def _theta2(w: Array) -> Array:
    return np.sum(w * w, axis=-1)


def _coeffs_abc(t2: Array) -> tuple[Array, Array, Array]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 with series near 0."""
    small = t2 < _SMALL**2 * 100
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    s, c = np.sin(t), np.cos(t)
    A = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, s / t)
    B = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - c) / t2s)
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - s) / (t2s * t))
    return A, B, C


def so3_exp(w: ArrayLike) -> Array:
    """Rodrigues' formula: rotation vector ``(..., 3)`` -> rotation ``(..., 3, 3)``."""
    w = _f(w)
    A, B, _ = _coeffs_abc(_theta2(w))
    W = hat3(w)
    WW = W @ W
    return np.eye(3) + A[..., None, None] * W + B[..., None, None] * WW


def quat_from_matrix(R: ArrayLike) -> Array:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (Shepperd).

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)

    Returns
    -------
    ndarray, shape (..., 4)
    """
    R = _f(R)
    if R.shape == (3, 3):
        return _quat_from_matrix_single(R)
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    # Four candidate formulas, each well conditioned when its pivot is largest.
    cand = np.stack(
        [
            np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1], 1.0 + tr], -1),
            np.stack([1.0 + r00 - r11 - r22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 2, 1] - R[..., 1, 2]], -1),
            np.stack([R[..., 0, 1] + R[..., 1, 0], 1.0 - r00 + r11 - r22, R[..., 1, 2] + R[..., 2, 1], R[..., 0, 2] - R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1.0 - r00 - r11 + r22, R[..., 1, 0] - R[..., 0, 1]], -1),
        ],
        axis=-2,
    )
    pivot = np.argmax(np.stack([tr, r00, r11, r22], -1), axis=-1)
    q = np.take_along_axis(cand, pivot[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def _quat_from_matrix_single(R: Array) -> Array:
    """:func:`quat_from_matrix` of one ``(3, 3)`` matrix with Python floats (the fusion node
    converts one pose per message).  The same operations in the same order as the batched
    code, so the result is bit-identical (tested); non-finite input takes the batched code."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    tr = r00 + r11 + r22
    if not math.isfinite(tr + r01 + r02 + r10 + r12 + r20 + r21):
        return quat_from_matrix(R[None])[0]
    pivots = [tr, r00, r11, r22]
    k = pivots.index(max(pivots))  # first maximum, as np.argmax
    if k == 0:
        q = (r21 - r12, r02 - r20, r10 - r01, 1.0 + tr)
    elif k == 1:
        q = (1.0 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12)
    elif k == 2:
        q = (r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21, r02 - r20)
    else:
        q = (r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22, r10 - r01)
    qa = np.array(q)
    out = qa / np.linalg.norm(qa, axis=-1, keepdims=True)  # the batched code's reduction order
    return -out if out[3] < 0.0 else out


def matrix_from_quat(q: ArrayLike) -> Array:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised here): ``(..., 4) -> (..., 3, 3)``."""
    q_arr = _f(q)
    q_arr = q_arr / np.linalg.norm(q_arr, axis=-1, keepdims=True)
    if q_arr.shape == (4,):  # one quaternion (one message): Python floats, the same operations
        x, y, z, w = q_arr.tolist()
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
    x, y, z, w = q_arr[..., 0], q_arr[..., 1], q_arr[..., 2], q_arr[..., 3]
    R = np.empty(q_arr.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def so3_log(R: ArrayLike) -> Array:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``: ``(..., 3, 3) -> (..., 3)``.

    Accurate at 0, near 0 and at/near pi (via the quaternion).  At exactly pi
    the sign of the axis is arbitrary (both are valid logarithms).
    """
    q = quat_from_matrix(R)
    v, w = q[..., :3], q[..., 3]
    s = np.linalg.norm(v, axis=-1)
    small = s < _SMALL_Q
    # 2 atan2(s, w) / s; series for small s (w ~ 1): 2/w (1 - s^2/(3 w^2) + s^4/(5 w^4))
    ws = np.where(small, w, 1.0)
    r2 = (s / ws) ** 2
    series = 2.0 / ws * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)
    ss = np.where(small, 1.0, s)
    factor = np.where(small, series, 2.0 * np.arctan2(s, w) / ss)
    return factor[..., None] * v


def so3_left_jacobian(w: ArrayLike) -> Array:
    """Left Jacobian of SO(3): ``J_l = I + B [w] + C [w]^2`` (Barfoot eq. 7.77)."""
    w = _f(w)
    _, B, C = _coeffs_abc(_theta2(w))
    W = hat3(w)
    return np.eye(3) + B[..., None, None] * W + C[..., None, None] * (W @ W)


def so3_left_jacobian_inv(w: ArrayLike) -> Array:
    """Inverse left Jacobian of SO(3): ``I - [w]/2 + D [w]^2``, D = (1 - A/(2B)) / t^2."""
    w = _f(w)
    t2 = _theta2(w)
    small = t2 < 1e-6
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    D = np.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        (1.0 - t * np.sin(t) / (2.0 * (1.0 - np.cos(t)))) / t2s,
    )
    W = hat3(w)
    return np.eye(3) - 0.5 * W + D[..., None, None] * (W @ W)


def so3_right_jacobian(w: ArrayLike) -> Array:
    """Right Jacobian of SO(3), ``J_r(w) = J_l(-w)``."""
    return so3_left_jacobian(-_f(w))


def so3_right_jacobian_inv(w: ArrayLike) -> Array:
    """Inverse right Jacobian of SO(3), ``J_r^-1(w) = J_l^-1(-w)``."""
    return so3_left_jacobian_inv(-_f(w))


# ----------------------------------------------------------------------------
# SE(3)
# ----------------------------------------------------------------------------


def from_rt(R: ArrayLike, t: ArrayLike) -> Array:
    """Pose from rotation ``(..., 3, 3)`` and translation ``(..., 3)`` (broadcast)."""
    R, t = _f(R), _f(t)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def fit_rigid(P_src: ArrayLike, P_dst: ArrayLike) -> Array:
    """Rigid transform (rotation + translation, no scale) fitting ``P_dst ~ R P_src + t``.

    Least squares over corresponding points (Kabsch / Umeyama without scale): with the
    centroids ``c``, the SVD ``U S V^T`` of ``sum_i (p_src,i - c_src)(p_dst,i - c_dst)^T``
    gives ``R = V diag(1, 1, d) U^T``, ``d = sign det(V U^T)`` (a reflection is turned into
    the best proper rotation), and ``t = c_dst - R c_src``.  Broadcasts over leading axes.

    Parameters
    ----------
    P_src, P_dst : array_like, shape (..., n, 3)
        Corresponding points in the source and destination frames, ``n >= 3`` and not all
        on one line (same shape).

    Returns
    -------
    ndarray, shape (..., 4, 4)
        ``T_dst_src``: maps source coordinates to destination coordinates.

    Raises
    ------
    MeasurementError
        Shapes differ or are not ``(..., n, 3)``, fewer than 3 point pairs, non-finite
        points, or a collinear point set (rotation about the line undetermined).
    """
    P_src, P_dst = _f(P_src), _f(P_dst)
    if P_src.shape != P_dst.shape or P_src.ndim < 2 or P_src.shape[-1] != 3:
        raise MeasurementError(f"fit_rigid: point sets must both be (..., n, 3), got {P_src.shape} and {P_dst.shape}")
    if P_src.shape[-2] < 3:
        raise MeasurementError(f"fit_rigid: need at least 3 point pairs, got {P_src.shape[-2]}")
    if not (np.all(np.isfinite(P_src)) and np.all(np.isfinite(P_dst))):
        raise MeasurementError("fit_rigid: the points contain NaN or infinite values")
    c_src, c_dst = P_src.mean(axis=-2), P_dst.mean(axis=-2)
    A, B = P_src - c_src[..., None, :], P_dst - c_dst[..., None, :]
    U, s, Vt = np.linalg.svd(np.swapaxes(A, -1, -2) @ B)
    if np.any(s[..., 1] <= 1e-9 * np.maximum(s[..., 0], 1e-300)):
        raise MeasurementError("fit_rigid: the points are collinear (or coincide); the rotation is not determined")
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    D = np.zeros(d.shape + (3, 3))
    D[..., 0, 0] = D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = V @ D @ Ut
    return from_rt(R, c_dst - np.einsum("...ij,...j->...i", R, c_src))


def exp(xi: ArrayLike) -> Array:
    """Exponential map ``Exp: R^6 -> SE(3)`` (paper eq. 3).

    Parameters
    ----------
    xi : array_like, shape (..., 6)
        Twist ``[rho; theta]``.

    Returns
    -------
    ndarray, shape (..., 4, 4)
        ``[[Exp(theta), J_l(theta) rho], [0, 1]]``.
    """
    xi = _f(xi)
    if xi.shape == (6,):
        return _exp_single(xi)
    rho, w = xi[..., :3], xi[..., 3:]
    A, B, C = _coeffs_abc(_theta2(w))
    W = hat3(w)
    WW = W @ W
    eye = np.eye(3)
    R = eye + A[..., None, None] * W + B[..., None, None] * WW
    V = eye + B[..., None, None] * W + C[..., None, None] * WW
    return from_rt(R, np.einsum("...ij,...j->...i", V, rho))


def _exp_single(xi: Array) -> Array:
    """:func:`exp` of one ``(6,)`` twist without the batch machinery (``np.where`` over both
    series branches, broadcasting); bit-identical to the batched code (tested)."""
    rho, w = xi[:3], xi[3:]
    w0, w1, w2 = w.tolist()
    t2 = float(_theta2(w))  # the batched code's reduction order
    if not math.isfinite(t2):
        return exp(xi[None])[0]
    if t2 < _SMALL**2 * 100:
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        t = math.sqrt(t2)
        s, c = float(np.sin(t)), float(np.cos(t))  # numpy's sin/cos, as the batched code
        A, B, C = s / t, (1.0 - c) / t2, (t - s) / (t2 * t)
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    WW = W @ W
    eye = np.eye(3)
    T = np.zeros((4, 4))
    T[:3, :3] = eye + A * W + B * WW
    V = eye + B * W + C * WW
    T[:3, 3] = np.einsum("...ij,...j->...i", V, rho)
    T[3, 3] = 1.0
    return T


def log(T: ArrayLike) -> Array:
    """Logarithmic map ``Log: SE(3) -> R^6`` (paper eq. 4): ``(..., 4, 4) -> (..., 6)``."""
    T = _f(T)
    w = so3_log(T[..., :3, :3])
    rho = np.einsum("...ij,...j->...i", so3_left_jacobian_inv(w), T[..., :3, 3])
    return np.concatenate([rho, w], axis=-1)


def inverse(T: ArrayLike) -> Array:
    """Inverse pose ``[[R^T, -R^T t], [0, 1]]``: ``(..., 4, 4) -> (..., 4, 4)``."""
    T = _f(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    t = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    if T.shape == (4, 4):  # one pose: skip from_rt's broadcasting (same values)
        out = np.zeros((4, 4))
        out[:3, :3] = Rt
        out[:3, 3] = t
        out[3, 3] = 1.0
        return out
    return from_rt(Rt, t)


def compose(*Ts: ArrayLike) -> Array:
    """Product ``T_1 @ T_2 @ ...`` of poses, broadcasting batch axes."""
    out = _f(Ts[0])
    for T in Ts[1:]:
        out = out @ _f(T)
    return out


def oplus(T: ArrayLike, xi: ArrayLike) -> Array:
    """Right plus: ``T @ Exp(xi)`` (perturbation in the tangent space at ``T``)."""
    return _f(T) @ exp(xi)


def ominus(T1: ArrayLike, T0: ArrayLike) -> Array:
    """Right minus: ``Log(T0^-1 @ T1)``, a twist in the tangent space at ``T0``."""
    return log(inverse(T0) @ _f(T1))


def adjoint(T: ArrayLike) -> Array:
    """Adjoint ``Ad_T = [[R, [t]_x R], [0, R]]`` (paper eq. 7): ``(..., 4, 4) -> (..., 6, 6)``.

    Maps a right (local) twist at ``T`` to a left (global) one: ``E_xi = Ad_T X_xi`` (eq. 6).
    """
    T = _f(T)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = hat3(t) @ R
    return out


def curly_hat(xi: ArrayLike) -> Array:
    """``xi^curly = [[[theta]_x, [rho]_x], [0, [theta]_x]]`` (paper eq. 13), i.e. ad(xi)."""
    xi = _f(xi)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    Wt = hat3(xi[..., 3:])
    out[..., :3, :3] = Wt
    out[..., 3:, 3:] = Wt
    out[..., :3, 3:] = hat3(xi[..., :3])
    return out


def _q_matrix(xi: Array) -> Array:
    """Barfoot's ``Q(rho, theta)`` block of the SE(3) left Jacobian (eq. 7.86b)."""
    rho, w = xi[..., :3], xi[..., 3:]
    t2 = _theta2(w)
    small = t2 < 1e-4
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    s, c = np.sin(t), np.cos(t)
    c1 = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - s) / (t2s * t))
    c2 = np.where(
        small, 1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0, (t2s + 2.0 * c - 2.0) / (2.0 * t2s * t2s)
    )
    c3 = np.where(
        small,
        1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0,
        (2.0 * t - 3.0 * s + t * c) / (2.0 * t2s * t2s * t),
    )
    P, W = hat3(rho), hat3(w)
    WP, PW = W @ P, P @ W
    WPW = WP @ W
    WW = W @ W
    return (
        0.5 * P
        + c1[..., None, None] * (WP + PW + WPW)
        + c2[..., None, None] * (WW @ P + PW @ W - 3.0 * WPW)
        + c3[..., None, None] * (WPW @ W + W @ WPW)
    )


def left_jacobian(xi: ArrayLike) -> Array:
    """Left Jacobian of SE(3) ``[[J, Q], [0, J]]``: ``(..., 6) -> (..., 6, 6)``.

    ``Exp(xi + d) ~= Exp(J_l(xi) d) Exp(xi)`` for small ``d``.
    """
    xi = _f(xi)
    J = so3_left_jacobian(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = J
    out[..., 3:, 3:] = J
    out[..., :3, 3:] = _q_matrix(xi)
    return out


def right_jacobian(xi: ArrayLike) -> Array:
    """Right Jacobian of SE(3), ``J_r(xi) = J_l(-xi)``.

    ``Exp(xi + d) ~= Exp(xi) Exp(J_r(xi) d)`` for small ``d``.
    """
    return left_jacobian(-_f(xi))


def left_jacobian_inv(xi: ArrayLike) -> Array:
    """Inverse left Jacobian of SE(3) ``[[J^-1, -J^-1 Q J^-1], [0, J^-1]]``."""
    xi = _f(xi)
    Ji = so3_left_jacobian_inv(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Ji
    out[..., 3:, 3:] = Ji
    out[..., :3, 3:] = -Ji @ _q_matrix(xi) @ Ji
    return out


def right_jacobian_inv(xi: ArrayLike) -> Array:
    """Inverse right Jacobian of SE(3), ``J_r^-1(xi) = J_l^-1(-xi)``.

    ``Log(Exp(xi) Exp(d)) ~= xi + J_r^-1(xi) d`` for small ``d``.
    """
    return left_jacobian_inv(-_f(xi))


# ----------------------------------------------------------------------------
# Construction and conversion
# ----------------------------------------------------------------------------


def matrix_from_rpy(rpy: ArrayLike) -> Array:
    """URDF fixed-axis roll-pitch-yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``: ``(..., 3) -> (..., 3, 3)``."""
    rpy = _f(rpy)
    cr, sr = np.cos(rpy[..., 0]), np.sin(rpy[..., 0])
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    R = np.empty(rpy.shape[:-1] + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def rpy_from_matrix(R: ArrayLike) -> Array:
    """Inverse of :func:`matrix_from_rpy` (pitch in ``[-pi/2, pi/2]``): ``(..., 3, 3) -> (..., 3)``."""
    R = _f(R)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    gimbal = np.abs(R[..., 2, 0]) > 1.0 - 1e-12
    roll = np.where(gimbal, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(
        gimbal,
        np.arctan2(-R[..., 0, 1], R[..., 1, 1]),
        np.arctan2(R[..., 1, 0], R[..., 0, 0]),
    )
    return np.stack([roll, pitch, yaw], axis=-1)


def from_xyz_rpy(xyz: ArrayLike = (0.0, 0.0, 0.0), rpy: ArrayLike = (0.0, 0.0, 0.0)) -> Array:
    """Pose from a URDF ``<origin xyz rpy>``: ``(..., 3), (..., 3) -> (..., 4, 4)``."""
    return from_rt(matrix_from_rpy(rpy), xyz)


def interpolate(T0: ArrayLike, T1: ArrayLike, s: ArrayLike) -> Array:
    """Geodesic interpolation ``T0 Exp(s Log(T0^-1 T1))``; ``s`` in [0, 1], broadcast as ``(...)``."""
    T0 = _f(T0)
    d = ominus(T1, T0)
    return T0 @ exp(_f(s)[..., None] * d)


# ----------------------------------------------------------------------------
# Covariances
# ----------------------------------------------------------------------------


def _ros_block(T: Array) -> Array:
    R = T[..., :3, :3]
    B = np.zeros(T.shape[:-2] + (6, 6))
    B[..., :3, :3] = R
    B[..., 3:, 3:] = R
    return B


def cov_local_to_ros(T: ArrayLike, cov: ArrayLike) -> Array:
    """Local covariance -> ROS ``PoseWithCovariance`` convention (CONTRACT section 2).

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        Mean pose ``T_parent_child``.
    cov : array_like, shape (..., 6, 6)
        Covariance in the tangent space at ``T`` (right perturbation, ``[rho; theta]``).

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``B cov B^T`` with ``B = blockdiag(R, R)``: translation and small rotations both in
        the axes of the parent frame (``header.frame_id``), order ``(x, y, z, rx, ry, rz)``.
    """
    B = _ros_block(_f(T))
    return B @ _f(cov) @ np.swapaxes(B, -1, -2)


def cov_ros_to_local(T: ArrayLike, cov_ros: ArrayLike) -> Array:
    """Inverse of :func:`cov_local_to_ros`: ROS covariance (parent axes) -> tangent space at ``T``.

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        Mean pose ``T_parent_child``.
    cov_ros : array_like, shape (..., 6, 6)
        ``PoseWithCovariance.covariance`` as 6x6: order ``(x, y, z, rx, ry, rz)``, all in the
        axes of the parent frame (``header.frame_id``), CONTRACT section 2.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``B^T cov_ros B`` with ``B = blockdiag(R, R)``: the covariance in the tangent space at
        ``T`` (child frame, right perturbation, ``[rho; theta]``).
    """
    B = _ros_block(_f(T))
    Bt = np.swapaxes(B, -1, -2)
    return Bt @ _f(cov_ros) @ B


def check_covariance(
    cov: ArrayLike, name: str = "covariance", size: int | None = None, tol: float = 1e-9
) -> Array:
    """Validate a covariance matrix and return it as a float array.

    Parameters
    ----------
    cov : array_like, shape (..., n, n)
    name : str
        What the covariance belongs to (joint, topic, file:line); used in the error message.
    size : int, optional
        Required ``n``.
    tol : float
        Relative tolerance for symmetry and for negative eigenvalues.

    Raises
    ------
    CovarianceError
        Not square / wrong size, non-finite, not symmetric or not positive semi-definite.
    """
    try:
        C = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CovarianceError(f"{name}: not a numeric matrix ({exc})") from None
    if C.ndim < 2 or C.shape[-1] != C.shape[-2]:
        raise CovarianceError(f"{name}: must be a square matrix, got shape {C.shape}")
    if size is not None and C.shape[-1] != size:
        raise CovarianceError(f"{name}: must be {size}x{size}, got {C.shape[-2]}x{C.shape[-1]}")
    # array methods instead of np.all / np.max: the same reductions without the dispatch
    # overhead (this runs once per message in the nodes)
    if not np.isfinite(C).all():
        raise CovarianceError(f"{name}: contains NaN or infinite entries")
    scale = max(float(np.abs(C).max()), 1e-300)
    Ct = np.swapaxes(C, -1, -2)
    asym = float(np.abs(C - Ct).max())
    if asym > tol * scale:
        raise CovarianceError(f"{name}: not symmetric (max |C - C^T| = {asym:.3g})")
    eig_min = float(np.linalg.eigvalsh(0.5 * (C + Ct)).min())
    if eig_min < -tol * scale:
        raise CovarianceError(f"{name}: not positive semi-definite (smallest eigenvalue {eig_min:.3g})")
    return C
