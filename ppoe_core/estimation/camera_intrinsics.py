"""Derivatives of the one camera model (:mod:`ppoe_core.estimation.camera`, pinhole + plumb_bob) w.r.t. the camera
intrinsics: the Jacobian of the ``camera_intrinsics`` effect (:class:`ppoe_core.model.effects_sensor.CameraIntrinsics`).

With ``x = X/Z, y = Y/Z``, ``r^2 = x^2 + y^2``, ``rad = 1 + k1 r^2 + k2 r^4 + k3 r^6`` and the plumb_bob distortion
``xd = x rad + 2 p1 x y + p2 (r^2 + 2 x^2)``, ``yd = y rad + p1 (r^2 + 2 y^2) + 2 p2 x y``, the pixel is
``u = fx xd + s yd + cx``, ``v = fy yd + cy`` (``s = K[0, 1]``, kept fixed), so

* ``du/dfx = xd``, ``dv/dfy = yd``, ``d(u, v)/dcx = (1, 0)``, ``d(u, v)/dcy = (0, 1)``;
* ``d(u, v)/dk = A d(xd, yd)/dk`` with ``A = K[:2, :2]`` and ``d(xd, yd)/dk1 = (x, y) r^2``, ``/dk2 = (x, y) r^4``,
  ``/dk3 = (x, y) r^6``, ``/dp1 = (2 x y, r^2 + 2 y^2)``, ``/dp2 = (r^2 + 2 x^2, 2 x y)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core.estimation.camera import distortion_coefficients, project_points_jacobian

__all__ = ["INTRINSIC_ORDER", "project_with_intrinsics_jacobian"]

#: the columns of the intrinsics Jacobian (``ppoe_core.model.effects_sensor.INTRINSIC_KEYS``)
INTRINSIC_ORDER = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def project_with_intrinsics_jacobian(P_cam: np.ndarray, K: np.ndarray, D: np.ndarray | Sequence[float] | None
                                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distorted pixels of camera-frame points with their Jacobians w.r.t. the point and the intrinsics.

    Parameters
    ----------
    P_cam : ndarray, shape (n, 3)
        Points in the camera optical frame [m], z > 0.
    K : ndarray, shape (3, 3)
    D : array, shape (5,) or None
        plumb_bob ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    uv : ndarray, shape (n, 2)
        [px], as :func:`~ppoe_core.estimation.camera.project_points`.
    J_point : ndarray, shape (n, 2, 3)
        ``d uv / d P_cam`` [px/m].
    J_intrinsics : ndarray, shape (n, 2, 9)
        ``d uv / d (fx, fy, cx, cy, k1, k2, p1, p2, k3)`` [px/px, px].
    """
    P = np.asarray(P_cam, dtype=float).reshape(-1, 3)
    Kf = np.asarray(K, dtype=float)
    Dv = distortion_coefficients(D)
    uv, J_point = project_points_jacobian(P, Kf, Dv)
    xy = P[:, :2] / P[:, 2:3]
    xyd = np.linalg.solve(Kf[:2, :2], (uv - Kf[:2, 2]).T).T  # the distorted normalised point the projection used
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    dd = np.zeros((P.shape[0], 2, 5))  # d (xd, yd) / d (k1, k2, p1, p2, k3)
    for col, power in ((0, 1), (1, 2), (4, 3)):
        dd[:, 0, col] = x * r2 ** power
        dd[:, 1, col] = y * r2 ** power
    dd[:, 0, 2], dd[:, 1, 2] = 2 * x * y, r2 + 2 * y * y
    dd[:, 0, 3], dd[:, 1, 3] = r2 + 2 * x * x, 2 * x * y
    J = np.zeros((P.shape[0], 2, 9))
    J[:, 0, 0] = xyd[:, 0]
    J[:, 1, 1] = xyd[:, 1]
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    J[:, :, 4:] = np.einsum("ij,njk->nik", Kf[:2, :2], dd)
    return uv, J_point, J
