"""SO(3): hat/vee, Exp/Log (exact near 0 and pi), quaternions ``(x, y, z, w)``, roll-pitch-yaw, left/right Jacobians.

Batched over leading axes; small angles with vectorised ``np.where`` (docs/conventions.md)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray


Array = NDArray[np.float64]

# Below these angles the closed forms lose precision and Taylor series are used.
_SMALL = 1e-4
_SMALL_Q = 1e-2


def _f(x: ArrayLike) -> Array:
    return np.asarray(x, dtype=np.float64)


_KERNELS: Any = None


def _kernels() -> Any:
    """:mod:`ppoe_core.lie.kernels`, imported on first use (numba only when used: `ppoe record` starts fast) and
    kept (an import statement per message costs more than the kernel call)."""
    global _KERNELS
    if _KERNELS is None:
        from ppoe_core.lie import kernels

        _KERNELS = kernels
    return _KERNELS


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
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (Shepperd; compiled loop,
    :func:`ppoe_core.lie.kernels.quat_from_matrix_kernel`).

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)

    Returns
    -------
    ndarray, shape (..., 4)
    """
    R = _f(R)
    kernels = _kernels()
    if R.shape == (3, 3):  # one rotation (one message): no batch reshaping, the same operations
        q = np.empty(4)
        kernels.quat_from_matrix_one(R, q)
        return q
    shape = R.shape[:-2]
    flat = np.ascontiguousarray(R.reshape(-1, 3, 3))
    out = np.empty((flat.shape[0], 4))
    kernels.quat_from_matrix_kernel(flat, out)
    return out.reshape(shape + (4,))


def matrix_from_quat(q: ArrayLike) -> Array:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised here): ``(..., 4) -> (..., 3, 3)``."""
    q_arr = _f(q)
    if q_arr.shape == (4,):  # one quaternion (one message): Python floats, the same operations
        x, y, z, w = q_arr.tolist()
        n = math.sqrt(x * x + y * y + z * z + w * w)  # np.linalg.norm's sum order
        if not 0.0 < n < math.inf:  # zero / non-finite: numpy's NaN semantics of the batched code
            return matrix_from_quat(q_arr[None])[0]
        x, y, z, w = x / n, y / n, z / n, w / n
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
    q_arr = q_arr / np.linalg.norm(q_arr, axis=-1, keepdims=True)
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
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))  # accurate near +-pi/2 too
    gimbal = np.abs(R[..., 2, 0]) > 1.0 - 1e-12
    roll = np.where(gimbal, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(
        gimbal,
        np.arctan2(-R[..., 0, 1], R[..., 1, 1]),
        np.arctan2(R[..., 1, 0], R[..., 0, 0]),
    )
    return np.stack([roll, pitch, yaw], axis=-1)
