"""numpy reference of the compiled camera projection (:mod:`ppoe_core.estimation.camera_kernel`, THE
implementation): the tests compare the kernel with this, nothing else uses it."""

from __future__ import annotations

import numpy as np


def project_points_jacobian_reference(P_cam: np.ndarray, K: np.ndarray, D: np.ndarray,
                                      mode: str = "pixel") -> tuple[np.ndarray, np.ndarray]:
    """Pinhole + plumb_bob ``(k1, k2, p1, p2, k3)`` projection of (n, 3) points and ``d uv / d P`` (n, 2, 3)."""
    P = np.asarray(P_cam, dtype=float).reshape(-1, 3)
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    xy = np.stack([X / Z, Y / Z], axis=-1)
    Jp = np.zeros((P.shape[0], 2, 3))
    Jp[:, 0, 0] = 1 / Z
    Jp[:, 0, 2] = -X / Z**2
    Jp[:, 1, 1] = 1 / Z
    Jp[:, 1, 2] = -Y / Z**2
    if mode == "normalized":
        return xy, Jp
    k1, k2, p1, p2, k3 = np.asarray(D, dtype=float)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drad = k1 + 2 * k2 * r2 + 3 * k3 * r2**2
    xd = np.stack([x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y],
                  axis=-1)
    Jd = np.empty((P.shape[0], 2, 2))
    Jd[:, 0, 0] = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    Jd[:, 0, 1] = Jd[:, 1, 0] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    Jd[:, 1, 1] = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    A = np.asarray(K, dtype=float)[:2, :2]
    return xd @ A.T + np.asarray(K, dtype=float)[:2, 2], np.einsum("ij,njk,nkl->nil", A, Jd, Jp)
