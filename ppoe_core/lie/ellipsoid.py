"""Confidence ellipsoids of a position covariance: the geometry of an RViz ``SPHERE`` marker, and its surface.

For ``P`` (3, 3), the position covariance in the axes of a frame (the parent frame of a ROS pose: the upper-left
block of the ROS-convention covariance, docs/conventions.md sec. 2), the ellipsoid ``{x : x^T P^-1 x <= k^2}``
has its principal axes along the eigenvectors of ``P`` and semi-axes ``k sqrt(lambda_i)``.  An RViz sphere marker
draws it with ``pose.orientation`` = the rotation whose columns are the eigenvectors (right-handed) and
``scale`` = the full axis lengths ``2 k sqrt(lambda_i)``.  ``k`` for a probability ``p`` of a 3-D Gaussian:
``sqrt(chi2.ppf(p, 3))`` (:func:`sigma_scale`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ppoe_core.errors import CovarianceError
from ppoe_core.lie.so3 import quat_from_matrix

__all__ = ["Ellipsoid", "position_ellipsoid", "position_covariance_from_local", "sigma_scale", "ellipsoid_surface"]


class Ellipsoid(NamedTuple):
    """A confidence ellipsoid (batched over leading axes ``...``).

    Attributes
    ----------
    center : (..., 3)
        Centre in the frame the covariance's axes belong to [m].
    rotation : (..., 3, 3)
        Columns = principal axes (unit eigenvectors, right-handed), largest first.
    radii : (..., 3)
        Semi-axis lengths ``k sqrt(lambda)`` along those columns [m].
    quat_xyzw : (..., 4)
        ``rotation`` as a unit quaternion ``(x, y, z, w)``, ``w >= 0`` (a marker's ``pose.orientation``).
    """

    center: np.ndarray
    rotation: np.ndarray
    radii: np.ndarray
    quat_xyzw: np.ndarray

    @property
    def scale(self) -> np.ndarray:
        """(..., 3) full axis lengths ``2 * radii``: an RViz ``SPHERE`` marker's ``scale``."""
        return 2.0 * self.radii


def sigma_scale(probability: float) -> float:
    """``k`` such that a 3-D Gaussian lies inside the ``k``-sigma ellipsoid with ``probability`` (chi-square, 3 dof).

    0.199 -> 1.0 (the one-sigma ellipsoid holds only 19.9 % in 3-D), 0.95 -> 2.796, 0.997 -> 3.73.
    """
    from scipy.stats import chi2

    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")
    return float(np.sqrt(chi2.ppf(probability, 3)))


def position_covariance_from_local(T: np.ndarray, cov_local: np.ndarray) -> np.ndarray:
    """(..., 3, 3) position covariance in the parent axes, ``R S_rho R^T``, from a local covariance (..., 6, 6)
    at ``T`` (..., 4, 4): the translation block of ``cov_local_to_ros`` (first order, docs/conventions.md sec. 2)."""
    R = np.asarray(T, dtype=float)[..., :3, :3]
    S = np.asarray(cov_local, dtype=float)[..., :3, :3]
    return R @ S @ np.swapaxes(R, -1, -2)


def position_ellipsoid(center: np.ndarray, cov_position: np.ndarray, k: float = 1.0) -> Ellipsoid:
    """The ``k``-sigma ellipsoid of a position covariance ``cov_position`` (..., 3, 3) around ``center`` (..., 3).

    Raises
    ------
    CovarianceError
        A covariance that is not finite and symmetric, or has an eigenvalue below ``-1e-12 * trace``
        (a numerically negative eigenvalue above that is taken as zero).
    """
    P = np.asarray(cov_position, dtype=float)
    c = np.asarray(center, dtype=float)
    if P.shape[-2:] != (3, 3) or c.shape[-1:] != (3,):
        raise CovarianceError(f"position covariance must be (..., 3, 3) and centre (..., 3), got {P.shape}, "
                              f"{c.shape}")
    if not np.all(np.isfinite(P)) or not np.allclose(P, np.swapaxes(P, -1, -2), rtol=1e-9, atol=1e-15):
        raise CovarianceError("position covariance must be finite and symmetric")
    lam, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, -1, -2)))
    tol = 1e-12 * np.maximum(np.trace(P, axis1=-2, axis2=-1), 1e-300)
    if np.any(lam < -tol[..., None]):
        raise CovarianceError(f"position covariance is not positive semi-definite (eigenvalue {lam.min():.3g})")
    lam, V = lam[..., ::-1], V[..., :, ::-1]  # largest first
    V = V.copy()
    V[..., :, 2] *= np.sign(np.linalg.det(V))[..., None]  # right-handed: a rotation
    radii = float(k) * np.sqrt(np.clip(lam, 0.0, None))
    return Ellipsoid(np.broadcast_to(c, radii.shape).copy(), V, radii, quat_from_matrix(V))


def ellipsoid_surface(e: Ellipsoid, n: int = 24) -> np.ndarray:
    """(..., n, n, 3) points of the ellipsoid surface (for drawing, e.g. matplotlib ``plot_wireframe``)."""
    u = np.linspace(0.0, 2.0 * np.pi, n)
    v = np.linspace(0.0, np.pi, n)
    unit = np.stack([np.outer(np.cos(u), np.sin(v)), np.outer(np.sin(u), np.sin(v)),
                     np.outer(np.ones_like(u), np.cos(v))], axis=-1)  # (n, n, 3)
    local = unit * e.radii[..., None, None, :]
    return np.einsum("...ij,...abj->...abi", e.rotation, local) + e.center[..., None, None, :]
