"""SO(3): hat/vee, Exp/Log (exact near 0 and pi), quaternions ``(x, y, z, w)``, roll-pitch-yaw, left/right Jacobians.

Batched over leading axes (docs/conventions.md); Exp, Log, the Jacobians and the quaternions are the compiled maps
of :mod:`ppoe_core.lie.kernels`."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core.lie.compiled import Array, as_float, batched, lie_kernels

__all__ = ["Array", "hat3", "vee3", "so3_exp", "so3_log", "so3_left_jacobian", "so3_left_jacobian_inv",
           "so3_right_jacobian", "so3_right_jacobian_inv", "quat_from_matrix", "matrix_from_quat", "matrix_from_rpy",
           "rpy_from_matrix"]


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
    w = as_float(w)
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
    W = as_float(W)
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


# ----------------------------------------------------------------------------
# SO(3)
# ----------------------------------------------------------------------------


def so3_exp(w: ArrayLike) -> Array:
    """Rodrigues' formula: rotation vector ``(..., 3)`` -> rotation ``(..., 3, 3)``."""
    return batched("so3_exp_kernel", w, (3,), (3, 3))


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
    R = as_float(R)
    if R.shape == (3, 3):  # one rotation (one message): no batch reshaping, the same operations
        q = np.empty(4)
        lie_kernels().quat_from_matrix_one(R, q)
        return q
    return batched("quat_from_matrix_kernel", R, (3, 3), (4,))


def matrix_from_quat(q: ArrayLike) -> Array:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised here): ``(..., 4) -> (..., 3, 3)``; a zero or
    non-finite quaternion gives NaN."""
    return batched("matrix_from_quat_kernel", q, (4,), (3, 3))


def so3_log(R: ArrayLike) -> Array:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``: ``(..., 3, 3) -> (..., 3)``.

    Accurate at 0, near 0 and at/near pi (via the quaternion).  At exactly pi
    the sign of the axis is arbitrary (both are valid logarithms).
    """
    return batched("so3_log_kernel", R, (3, 3), (3,))


def so3_left_jacobian(w: ArrayLike) -> Array:
    """Left Jacobian of SO(3): ``J_l = I + B [w] + C [w]^2`` (Barfoot eq. 7.77)."""
    return batched("so3_left_jacobian_kernel", w, (3,), (3, 3))


def so3_left_jacobian_inv(w: ArrayLike) -> Array:
    """Inverse left Jacobian of SO(3): ``I - [w]/2 + D [w]^2``, D = (1 - A/(2B)) / t^2."""
    return batched("so3_left_jacobian_inv_kernel", w, (3,), (3, 3))


def so3_right_jacobian(w: ArrayLike) -> Array:
    """Right Jacobian of SO(3), ``J_r(w) = J_l(-w)``."""
    return so3_left_jacobian(-as_float(w))


def so3_right_jacobian_inv(w: ArrayLike) -> Array:
    """Inverse right Jacobian of SO(3), ``J_r^-1(w) = J_l^-1(-w)``."""
    return so3_left_jacobian_inv(-as_float(w))


# ----------------------------------------------------------------------------
# Construction and conversion
# ----------------------------------------------------------------------------


def matrix_from_rpy(rpy: ArrayLike) -> Array:
    """URDF fixed-axis roll-pitch-yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``: ``(..., 3) -> (..., 3, 3)``."""
    rpy = as_float(rpy)
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
    R = as_float(R)
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))  # accurate near +-pi/2 too
    gimbal = np.abs(R[..., 2, 0]) > 1.0 - 1e-12
    roll = np.where(gimbal, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(gimbal, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    return np.stack([roll, pitch, yaw], axis=-1)
