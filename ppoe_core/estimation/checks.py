"""The input checks of the measurement update: a pose (rigid transform) and a noise or prior covariance, each error
naming what it is (``MeasurementError`` / ``CovarianceError``).  The compiled update repeats them without messages
(:func:`ppoe_core.estimation.update_kernels.update_kernel`, status 4) and calls these to say what failed."""

from __future__ import annotations

from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError

__all__ = ["check_pose", "check_noise_covariance"]


def check_pose(T: Any, name: str) -> np.ndarray:
    """Return ``T`` as a float (4, 4) rigid transform or raise MeasurementError.

    Parameters
    ----------
    T : array_like, shape (4, 4)
    name : str
        What the pose is, for the message (e.g. ``"prior T_camera_tool"``).
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise MeasurementError(f"{name}: expected a 4x4 pose, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise MeasurementError(f"{name}: pose contains NaN or inf")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise MeasurementError(f"{name}: rotation block is not a proper rotation matrix")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise MeasurementError(f"{name}: last row is not [0, 0, 0, 1]")
    return T


def check_noise_covariance(cov: Any, dim: int, name: str, *, tol: float = 1e-12) -> np.ndarray:
    """``cov`` as a symmetric PSD float (dim, dim) array (symmetrised) or CovarianceError: the one covariance check
    (:func:`ppoe_core.lie.check_covariance`) with the filter's tolerances (asymmetry 1e-9, eigenvalues ``tol``,
    relative to the largest entry).

    Parameters
    ----------
    cov : array_like, shape (dim, dim)
        A covariance (its frame is whatever the caller documents).
    dim : int
        Expected size.
    name : str
        What the covariance is, for the message.
    tol : float
        Relative tolerance for negative eigenvalues.
    """
    return lie.check_covariance(cov, name, size=dim, tol=1e-9, eig_tol=tol, symmetrize=True)
