"""THE camera projection (compiled, numba): pinhole with plumb_bob distortion and its Jacobian, for one point
(:func:`project_one`, also called by the compiled measurement updates, :mod:`ppoe_core.estimation.update_kernels`)
and a flat batch (:func:`project_kernel`, behind :func:`ppoe_core.estimation.camera.project_points_jacobian`).
The numpy reference the tests compare with is ``test/camera_reference.py``."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["project_one", "project_kernel"]


@njit(cache=True)
def project_one(p: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool, uv: np.ndarray, J: np.ndarray) -> None:
    """One camera point ``p`` (3,) -> ``uv`` (2,) and ``J = d uv / d p`` (2, 3): undistorted normalised
    ``(X/Z, Y/Z)``, or (``pixel``) ``K * plumb_bob(X/Z, Y/Z)`` with ``D = (k1, k2, p1, p2, k3)``."""
    X, Y, Z = p[0], p[1], p[2]
    x, y = X / Z, Y / Z
    jp00, jp02, jp11, jp12 = 1 / Z, -X / Z**2, 1 / Z, -Y / Z**2
    if not pixel:
        uv[0], uv[1] = x, y
        J[0, 0], J[0, 1], J[0, 2] = jp00, 0.0, jp02
        J[1, 0], J[1, 1], J[1, 2] = 0.0, jp11, jp12
        return
    k1, k2, p1, p2, k3 = D[0], D[1], D[2], D[3], D[4]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drad = k1 + 2 * k2 * r2 + 3 * k3 * r2**2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    d00 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    d01 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    d11 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    uv[0] = xd * K[0, 0] + yd * K[0, 1] + K[0, 2]
    uv[1] = xd * K[1, 0] + yd * K[1, 1] + K[1, 2]
    for i in range(2):
        a0 = K[i, 0] * d00 + K[i, 1] * d01  # (A Jd)[i, :]
        a1 = K[i, 0] * d01 + K[i, 1] * d11
        J[i, 0] = a0 * jp00
        J[i, 1] = a1 * jp11
        J[i, 2] = a0 * jp02 + a1 * jp12


@njit(cache=True)
def project_kernel(P: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool, uv: np.ndarray, J: np.ndarray) -> None:
    """:func:`project_one` of points ``P`` (N, 3) into ``uv`` (N, 2) and ``J`` (N, 2, 3)."""
    for n in range(P.shape[0]):
        project_one(P[n], K, D, pixel, uv[n], J[n])
