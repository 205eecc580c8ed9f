"""The one camera model of ppoe_core: pinhole with plumb_bob distortion (ROS ``camera_info``).

Points are in the camera optical frame (z forward, x right, y down; docs/conventions.md).
``K`` is the 3x3 intrinsic matrix, ``D`` the plumb_bob coefficients ``(k1, k2, p1, p2, k3)``
(longer vectors are accepted when the extra coefficients are zero).

* :func:`project_points` - points -> distorted pixels, batched over leading axes;
* :func:`project_points_jacobian` - the same (or undistorted normalised coordinates) with
  ``d uv / d P`` for the measurement models and the pixel stage of ``ppoe diagnose`` (compiled,
  :mod:`ppoe_core.estimation.camera_kernel`, the projection of the compiled updates too);
* :func:`undistort_pixels` - pixels -> undistorted normalised coordinates (the inverse, iterative,
  through OpenCV), as the tag bearing node publishes them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core.errors import MeasurementError
from ppoe_core.lie.compiled import compiled

__all__ = ["distortion_coefficients", "project_points", "project_points_jacobian", "undistort_pixels"]

_NO_K = np.eye(3)
_NO_D = np.zeros(5)


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


def project_points_jacobian(p_camera: np.ndarray, K: np.ndarray | None, D: np.ndarray | Sequence[float] | None,
                            mode: str = "pixel") -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points and return the Jacobian w.r.t. the 3D point (the compiled projection,
    :func:`ppoe_core.estimation.camera_kernel.project_one`).

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
    flat = np.ascontiguousarray(P.reshape(-1, 3))
    pixel = mode != "normalized"
    K_arr = np.ascontiguousarray(K, dtype=float) if pixel else _NO_K
    D_arr = (np.zeros(5) if D is None else distortion_coefficients(D)) if pixel else _NO_D
    uv = np.empty((flat.shape[0], 2))
    J = np.empty((flat.shape[0], 2, 3))
    compiled("ppoe_core.estimation.camera_kernel").project_kernel(flat, K_arr, D_arr, pixel, uv, J)
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
