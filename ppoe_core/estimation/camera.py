"""The one camera model of ppoe_core: pinhole with plumb_bob distortion (ROS ``camera_info``).

Points are in the camera optical frame (z forward, x right, y down; docs/conventions.md).
``K`` is the 3x3 intrinsic matrix, ``D`` the plumb_bob coefficients ``(k1, k2, p1, p2, k3)``
(longer vectors are accepted when the extra coefficients are zero).

* :func:`project_points` - points -> distorted pixels, batched over leading axes;
* :func:`project_points_jacobian` - the same (or undistorted normalised coordinates) with
  ``d uv / d P`` for the measurement models and the pixel stage of ``ppoe diagnose``;
* :func:`undistort_pixels` - pixels -> undistorted normalised coordinates (the inverse, iterative,
  through OpenCV), as the tag bearing node publishes them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core.errors import MeasurementError

__all__ = ["distortion_coefficients", "distort", "project_points", "project_points_jacobian", "undistort_pixels"]


def distortion_coefficients(D: Sequence[float] | np.ndarray | None, name: str = "camera") -> np.ndarray:
    """``D`` as the five plumb_bob coefficients ``(k1, k2, p1, p2, k3)`` (None: no distortion).

    Raises
    ------
    MeasurementError
        Non-zero coefficients beyond the fifth (not plumb_bob) or NaN/inf; names ``name``.
    """
    if D is None:
        return np.zeros(5)
    D_arr = np.asarray(D, dtype=float).ravel()
    if D_arr.size > 5 and np.any(D_arr[5:] != 0):
        raise MeasurementError(
            f"{name}: only the plumb_bob model (k1, k2, p1, p2, k3) is supported, got {D_arr.size} "
            "non-zero-padded distortion coefficients"
        )
    if not np.all(np.isfinite(D_arr)):
        raise MeasurementError(f"{name}: distortion coefficients contain NaN/inf")
    out = np.zeros(5)
    out[: min(5, D_arr.size)] = D_arr[:5]
    return out


def distort(xy: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """plumb_bob distortion of normalised points ``xy`` (n, 2) -> (xd (n, 2), J (n, 2, 2) = d xd / d xy)."""
    k1, k2, p1, p2, k3 = D
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drad = k1 + 2 * k2 * r2 + 3 * k3 * r2**2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    J = np.empty((xy.shape[0], 2, 2))
    J[:, 0, 0] = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    J[:, 0, 1] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    J[:, 1, 0] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    J[:, 1, 1] = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return np.stack([xd, yd], axis=-1), J


def project_points_jacobian(
    p_camera: np.ndarray,
    K: np.ndarray | None,
    D: np.ndarray | Sequence[float] | None,
    mode: str = "pixel",
) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points and return the Jacobian w.r.t. the 3D point.

    Parameters
    ----------
    p_camera : ndarray, shape (..., 3)
        Points in the camera optical frame (z forward), z > 0.
    K : ndarray, shape (3, 3) or None
        Intrinsics (only used in "pixel" mode).
    D : array, shape (5,) or None
        plumb_bob coefficients (k1, k2, p1, p2, k3) (only used in "pixel" mode).
    mode : {"pixel", "normalized"}
        Raw distorted pixels ``(u, v)`` or undistorted normalised ``(X/Z, Y/Z)``.

    Returns
    -------
    uv : ndarray, shape (..., 2)
    J : ndarray, shape (..., 2, 3)
        ``d uv / d p_camera``.
    """
    P = np.asarray(p_camera, dtype=float)
    lead = P.shape[:-1]
    P = P.reshape(-1, 3)
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    xy = np.stack([X / Z, Y / Z], axis=-1)
    Jp = np.zeros((P.shape[0], 2, 3))
    Jp[:, 0, 0] = 1 / Z
    Jp[:, 0, 2] = -X / Z**2
    Jp[:, 1, 1] = 1 / Z
    Jp[:, 1, 2] = -Y / Z**2
    if mode == "normalized":
        return xy.reshape(lead + (2,)), Jp.reshape(lead + (2, 3))
    xyd, Jd = distort(xy, np.zeros(5) if D is None else distortion_coefficients(D))
    A = np.asarray(K, dtype=float)[:2, :2]
    uv = xyd @ A.T + np.asarray(K, dtype=float)[:2, 2]
    J = np.einsum("ij,njk,nkl->nil", A, Jd, Jp)
    return uv.reshape(lead + (2,)), J.reshape(lead + (2, 3))


def project_points(P_cam: np.ndarray, K: np.ndarray, D: np.ndarray | Sequence[float]) -> np.ndarray:
    """Distorted pixel coordinates ``(..., 2)`` of points ``(..., 3)`` in the camera optical frame [m]."""
    return project_points_jacobian(P_cam, K, D)[0]


def undistort_pixels(uv: np.ndarray, K: np.ndarray, D: np.ndarray | Sequence[float]) -> np.ndarray:
    """Distorted pixels (..., 2) -> undistorted normalised coordinates (x = X/Z, y = Y/Z), (..., 2)."""
    import cv2

    uv = np.asarray(uv, dtype=float)
    flat = uv.reshape(-1, 1, 2)
    if flat.shape[0] == 0:
        return uv.copy()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    xy = cv2.undistortPoints(flat, np.asarray(K, float), np.asarray(D, float).reshape(-1), R=np.eye(3),
                             P=np.eye(3), criteria=crit)
    return xy.reshape(uv.shape)
