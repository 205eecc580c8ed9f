"""SE(3) with twists ``xi = [rho; theta]`` (translation first) and right perturbations ``X = Xbar Exp(xi)``
(paper eq. 3-9, docs/conventions.md): Exp/Log, inverse, compose, oplus/ominus, adjoint, left/right Jacobians,
rigid fits.  Batched over leading axes ``(..., 4, 4)`` / ``(..., 6)``; Exp, Log, the Jacobians and the inverse are
the compiled maps of :mod:`ppoe_core.lie.kernels`."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core.errors import MeasurementError
from ppoe_core.lie.compiled import Array, as_float, batched, lie_kernels
from ppoe_core.lie.so3 import hat3, matrix_from_rpy, vee3

__all__ = ["hat", "vee", "from_rt", "fit_rigid", "exp", "log", "inverse", "compose", "oplus", "ominus", "adjoint",
           "curly_hat", "left_jacobian", "right_jacobian", "left_jacobian_inv", "right_jacobian_inv", "from_xyz_rpy",
           "interpolate"]


def hat(xi: ArrayLike) -> Array:
    """``xi^`` in se(3) (paper eq. 2): ``(..., 6) -> (..., 4, 4)``."""
    xi = as_float(xi)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = hat3(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def vee(X: ArrayLike) -> Array:
    """Inverse of :func:`hat`: ``(..., 4, 4) -> (..., 6)``."""
    X = as_float(X)
    return np.concatenate([X[..., :3, 3], vee3(X[..., :3, :3])], axis=-1)


# ----------------------------------------------------------------------------
# SE(3)
# ----------------------------------------------------------------------------


def from_rt(R: ArrayLike, t: ArrayLike) -> Array:
    """Pose from rotation ``(..., 3, 3)`` and translation ``(..., 3)`` (broadcast)."""
    R, t = as_float(R), as_float(t)
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
    P_src, P_dst = as_float(P_src), as_float(P_dst)
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
    xi = as_float(xi)
    if xi.shape == (6,):  # one twist (one message): no batch reshaping, the same operations
        T = np.empty((4, 4))
        lie_kernels().se3_exp_one(xi, T)
        return T
    return batched("se3_exp_kernel", xi, (6,), (4, 4))


def log(T: ArrayLike) -> Array:
    """Logarithmic map ``Log: SE(3) -> R^6`` (paper eq. 4): ``(..., 4, 4) -> (..., 6)``."""
    T = as_float(T)
    if T.shape == (4, 4):
        xi = np.empty(6)
        lie_kernels().se3_log_one(T, xi)
        return xi
    return batched("se3_log_kernel", T, (4, 4), (6,))


def inverse(T: ArrayLike) -> Array:
    """Inverse pose ``[[R^T, -R^T t], [0, 1]]``: ``(..., 4, 4) -> (..., 4, 4)``."""
    T = as_float(T)
    if T.shape == (4, 4):
        out = np.empty((4, 4))
        lie_kernels().se3_inverse_one(T, out)
        return out
    return batched("se3_inverse_kernel", T, (4, 4), (4, 4))


def compose(*Ts: ArrayLike) -> Array:
    """Product ``T_1 @ T_2 @ ...`` of poses, broadcasting batch axes."""
    out = as_float(Ts[0])
    for T in Ts[1:]:
        out = out @ as_float(T)
    return out


def oplus(T: ArrayLike, xi: ArrayLike) -> Array:
    """Right plus: ``T @ Exp(xi)`` (perturbation in the tangent space at ``T``)."""
    return as_float(T) @ exp(xi)


def ominus(T1: ArrayLike, T0: ArrayLike) -> Array:
    """Right minus: ``Log(T0^-1 @ T1)``, a twist in the tangent space at ``T0``."""
    return log(inverse(T0) @ as_float(T1))


def adjoint(T: ArrayLike) -> Array:
    """Adjoint ``Ad_T = [[R, [t]_x R], [0, R]]`` (paper eq. 7): ``(..., 4, 4) -> (..., 6, 6)``.

    Maps a right (local) twist at ``T`` to a left (global) one: ``E_xi = Ad_T X_xi`` (eq. 6).
    """
    T = as_float(T)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = hat3(t) @ R
    return out


def curly_hat(xi: ArrayLike) -> Array:
    """``xi^curly = [[[theta]_x, [rho]_x], [0, [theta]_x]]`` (paper eq. 13), i.e. ad(xi)."""
    xi = as_float(xi)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    Wt = hat3(xi[..., 3:])
    out[..., :3, :3] = Wt
    out[..., 3:, 3:] = Wt
    out[..., :3, 3:] = hat3(xi[..., :3])
    return out


def left_jacobian(xi: ArrayLike) -> Array:
    """Left Jacobian of SE(3) ``[[J, Q], [0, J]]`` (Barfoot eq. 7.86): ``(..., 6) -> (..., 6, 6)``.

    ``Exp(xi + d) ~= Exp(J_l(xi) d) Exp(xi)`` for small ``d``.
    """
    return batched("se3_left_jacobian_kernel", xi, (6,), (6, 6))


def right_jacobian(xi: ArrayLike) -> Array:
    """Right Jacobian of SE(3), ``J_r(xi) = J_l(-xi)``.

    ``Exp(xi + d) ~= Exp(xi) Exp(J_r(xi) d)`` for small ``d``.
    """
    return left_jacobian(-as_float(xi))


def left_jacobian_inv(xi: ArrayLike) -> Array:
    """Inverse left Jacobian of SE(3) ``[[J^-1, -J^-1 Q J^-1], [0, J^-1]]``."""
    return batched("se3_left_jacobian_inv_kernel", xi, (6,), (6, 6))


def right_jacobian_inv(xi: ArrayLike) -> Array:
    """Inverse right Jacobian of SE(3), ``J_r^-1(xi) = J_l^-1(-xi)``.

    ``Log(Exp(xi) Exp(d)) ~= xi + J_r^-1(xi) d`` for small ``d``.
    """
    return left_jacobian_inv(-as_float(xi))


def from_xyz_rpy(xyz: ArrayLike = (0.0, 0.0, 0.0), rpy: ArrayLike = (0.0, 0.0, 0.0)) -> Array:
    """Pose from a URDF ``<origin xyz rpy>``: ``(..., 3), (..., 3) -> (..., 4, 4)``."""
    return from_rt(matrix_from_rpy(rpy), xyz)


def interpolate(T0: ArrayLike, T1: ArrayLike, s: ArrayLike) -> Array:
    """Geodesic interpolation ``T0 Exp(s Log(T0^-1 T1))``; ``s`` in [0, 1], broadcast as ``(...)``."""
    T0 = as_float(T0)
    d = ominus(T1, T0)
    return T0 @ exp(as_float(s)[..., None] * d)
