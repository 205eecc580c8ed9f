"""numpy references of the compiled SO(3)/SE(3) maps (:mod:`ppoe_core.lie.kernels`, THE implementation): the tests
compare the kernels with these, nothing else uses them.  Vectorised ``np.where`` over the Taylor-series branches
(as in jaxlie's ``_so3.py``), the formulas of the paper (eq. 3, 4) and of Barfoot (eq. 7.77, 7.86b)."""

from __future__ import annotations

import numpy as np

from ppoe_core.lie import hat3

_SMALL2 = 1e-6  # theta^2 below which the series are used (the kernels' threshold)
_SMALL_Q = 1e-2  # quaternion vector norm below which the log series is used


def _theta2(w: np.ndarray) -> np.ndarray:
    return np.sum(w * w, axis=-1)


def _coeffs_abc(t2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 with series near 0."""
    small = t2 < _SMALL2
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    s, c = np.sin(t), np.cos(t)
    A = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, s / t)
    B = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - c) / t2s)
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - s) / (t2s * t))
    return A, B, C


def so3_exp_reference(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=float)
    A, B, _ = _coeffs_abc(_theta2(w))
    W = hat3(w)
    return np.eye(3) + A[..., None, None] * W + B[..., None, None] * (W @ W)


def quat_from_matrix_reference(R: np.ndarray) -> np.ndarray:
    """Shepperd's method, ``w >= 0`` (the pivot: the largest of trace, r00, r11, r22; the first on ties)."""
    R = np.asarray(R, dtype=float)
    r = R.reshape(-1, 3, 3)
    out = np.empty((r.shape[0], 4))
    for n, M in enumerate(r):
        tr = np.trace(M)
        k = int(np.argmax([tr, M[0, 0], M[1, 1], M[2, 2]]))
        if k == 0:
            q = [M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1], 1.0 + tr]
        elif k == 1:
            q = [1.0 + M[0, 0] - M[1, 1] - M[2, 2], M[0, 1] + M[1, 0], M[0, 2] + M[2, 0], M[2, 1] - M[1, 2]]
        elif k == 2:
            q = [M[0, 1] + M[1, 0], 1.0 - M[0, 0] + M[1, 1] - M[2, 2], M[1, 2] + M[2, 1], M[0, 2] - M[2, 0]]
        else:
            q = [M[0, 2] + M[2, 0], M[1, 2] + M[2, 1], 1.0 - M[0, 0] - M[1, 1] + M[2, 2], M[1, 0] - M[0, 1]]
        q = np.array(q) / np.linalg.norm(q)
        out[n] = -q if q[3] < 0 else q
    return out.reshape(R.shape[:-2] + (4,))


def so3_log_reference(R: np.ndarray) -> np.ndarray:
    q = quat_from_matrix_reference(R)
    v, w = q[..., :3], q[..., 3]
    s = np.linalg.norm(v, axis=-1)
    small = s < _SMALL_Q
    ws = np.where(small, w, 1.0)
    r2 = (s / ws) ** 2
    series = 2.0 / ws * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)
    ss = np.where(small, 1.0, s)
    factor = np.where(small, series, 2.0 * np.arctan2(s, w) / ss)
    return factor[..., None] * v


def so3_left_jacobian_reference(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=float)
    _, B, C = _coeffs_abc(_theta2(w))
    W = hat3(w)
    return np.eye(3) + B[..., None, None] * W + C[..., None, None] * (W @ W)


def so3_left_jacobian_inv_reference(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=float)
    t2 = _theta2(w)
    small = t2 < _SMALL2
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    D = np.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
                 (1.0 - t * np.sin(t) / (2.0 * (1.0 - np.cos(t)))) / t2s)
    W = hat3(w)
    return np.eye(3) - 0.5 * W + D[..., None, None] * (W @ W)


def matrix_from_quat_reference(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def exp_reference(xi: np.ndarray) -> np.ndarray:
    """SE(3) Exp (paper eq. 3): ``[[Exp(theta), J_l(theta) rho], [0, 1]]``."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = so3_exp_reference(xi[..., 3:])
    out[..., :3, 3] = np.einsum("...ij,...j->...i", so3_left_jacobian_reference(xi[..., 3:]), xi[..., :3])
    out[..., 3, 3] = 1.0
    return out


def log_reference(T: np.ndarray) -> np.ndarray:
    """SE(3) Log (paper eq. 4)."""
    T = np.asarray(T, dtype=float)
    w = so3_log_reference(T[..., :3, :3])
    rho = np.einsum("...ij,...j->...i", so3_left_jacobian_inv_reference(w), T[..., :3, 3])
    return np.concatenate([rho, w], axis=-1)


def q_matrix_reference(xi: np.ndarray) -> np.ndarray:
    """Barfoot's ``Q(rho, theta)`` block of the SE(3) left Jacobian (eq. 7.86b)."""
    rho, w = xi[..., :3], xi[..., 3:]
    t2 = _theta2(w)
    small = t2 < 1e-4
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    s, c = np.sin(t), np.cos(t)
    c1 = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - s) / (t2s * t))
    c2 = np.where(small, 1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0, (t2s + 2.0 * c - 2.0) / (2.0 * t2s * t2s))
    c3 = np.where(small, 1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0,
                  (2.0 * t - 3.0 * s + t * c) / (2.0 * t2s * t2s * t))
    P, W = hat3(rho), hat3(w)
    WP, PW = W @ P, P @ W
    WPW = WP @ W
    WW = W @ W
    return (0.5 * P + c1[..., None, None] * (WP + PW + WPW) + c2[..., None, None] * (WW @ P + PW @ W - 3.0 * WPW)
            + c3[..., None, None] * (WPW @ W + W @ WPW))


def left_jacobian_reference(xi: np.ndarray) -> np.ndarray:
    xi = np.asarray(xi, dtype=float)
    J = so3_left_jacobian_reference(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = out[..., 3:, 3:] = J
    out[..., :3, 3:] = q_matrix_reference(xi)
    return out


def left_jacobian_inv_reference(xi: np.ndarray) -> np.ndarray:
    xi = np.asarray(xi, dtype=float)
    Ji = so3_left_jacobian_inv_reference(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = out[..., 3:, 3:] = Ji
    out[..., :3, 3:] = -Ji @ q_matrix_reference(xi) @ Ji
    return out


def inverse_reference(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros(T.shape)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out
