"""Pose covariances: local (tangent space at the mean) <-> ROS (``B S B^T``, parent-frame axes; docs/conventions.md
sec. 2), and THE covariance check of ppoe_core (shape, symmetry, positive semi-definiteness)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core.errors import CovarianceError
from ppoe_core.lie.compiled import Array, as_float, lie_kernels

# ----------------------------------------------------------------------------
# Covariances
# ----------------------------------------------------------------------------


def _rotate(T: ArrayLike, cov: ArrayLike, inverse: bool) -> Array:
    """``B cov B^T`` (``B^T cov B`` with ``inverse``), ``B = blockdiag(R, R)``, broadcast over leading axes."""
    kernels = lie_kernels()
    T_a = T if type(T) is np.ndarray and T.dtype == np.float64 else as_float(T)
    cov_a = cov if type(cov) is np.ndarray and cov.dtype == np.float64 else as_float(cov)
    if T_a.shape == (4, 4) and cov_a.shape == (6, 6):  # one message: no batch reshaping, the same operations
        out1 = np.empty((6, 6))
        kernels.rotate_covariance_one(T_a, cov_a, inverse, out1)
        return out1
    if T_a.shape[:-2] == cov_a.shape[:-2]:
        shape = cov_a.shape[:-2]
        T_flat = np.ascontiguousarray(T_a.reshape(-1, 4, 4))
        cov_flat = np.ascontiguousarray(cov_a.reshape(-1, 6, 6))
    else:
        shape = np.broadcast_shapes(T_a.shape[:-2], cov_a.shape[:-2])
        T_flat = np.ascontiguousarray(np.broadcast_to(T_a, shape + T_a.shape[-2:]).reshape(-1, 4, 4))
        cov_flat = np.ascontiguousarray(np.broadcast_to(cov_a, shape + (6, 6)).reshape(-1, 6, 6))
    out = np.empty_like(cov_flat)
    kernels.rotate_covariance_kernel(T_flat, cov_flat, inverse, out)
    return out.reshape(shape + (6, 6))


def cov_local_to_ros(T: ArrayLike, cov: ArrayLike) -> Array:
    """Local covariance -> ROS ``PoseWithCovariance`` convention (docs/conventions.md section 2).

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        Mean pose ``T_parent_child``.
    cov : array_like, shape (..., 6, 6)
        Covariance in the tangent space at ``T`` (right perturbation, ``[rho; theta]``).

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``B cov B^T`` with ``B = blockdiag(R, R)``: translation and small rotations both in
        the axes of the parent frame (``header.frame_id``), order ``(x, y, z, rx, ry, rz)``.
    """
    return _rotate(T, cov, False)


def cov_ros_to_local(T: ArrayLike, cov_ros: ArrayLike) -> Array:
    """Inverse of :func:`cov_local_to_ros`: ROS covariance (parent axes) -> tangent space at ``T``.

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        Mean pose ``T_parent_child``.
    cov_ros : array_like, shape (..., 6, 6)
        ``PoseWithCovariance.covariance`` as 6x6: order ``(x, y, z, rx, ry, rz)``, all in the
        axes of the parent frame (``header.frame_id``), docs/conventions.md section 2.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``B^T cov_ros B`` with ``B = blockdiag(R, R)``: the covariance in the tangent space at
        ``T`` (child frame, right perturbation, ``[rho; theta]``).
    """
    return _rotate(T, cov_ros, True)


def check_covariance(cov: ArrayLike, name: str = "covariance", size: int | None = None, tol: float = 1e-9,
                     eig_tol: float | None = None, symmetrize: bool = False) -> Array:
    """Validate a covariance matrix and return it as a float array.

    Parameters
    ----------
    cov : array_like, shape (..., n, n)
    name : str
        What the covariance belongs to (joint, topic, file:line); used in the error message.
    size : int, optional
        Required ``n``.
    tol : float
        Relative tolerance for symmetry and (unless ``eig_tol`` is given) for negative eigenvalues.
    eig_tol : float, optional
        Relative tolerance for negative eigenvalues (the filter's noise covariances: 1e-12).
    symmetrize : bool
        Return ``(C + C^T) / 2`` instead of ``C``.

    Raises
    ------
    CovarianceError
        Not square / wrong size, non-finite, not symmetric or not positive semi-definite.
    """
    try:
        C = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CovarianceError(f"{name}: not a numeric matrix ({exc})") from None
    if C.ndim < 2 or C.shape[-1] != C.shape[-2]:
        raise CovarianceError(f"{name}: must be a square matrix, got shape {C.shape}")
    if size is not None and C.shape[-1] != size:
        raise CovarianceError(f"{name}: must be {size}x{size}, got {C.shape[-2]}x{C.shape[-1]}")
    if C.ndim == 2 and 0 < C.shape[0] <= 12:  # one message's covariance: the compiled quick pass
        if lie_kernels().covariance_passes_kernel(np.ascontiguousarray(C), tol, tol if eig_tol is None else eig_tol):
            return 0.5 * (C + C.T) if symmetrize else C
    elif C.ndim == 3 and 0 < C.shape[0] and 0 < C.shape[1] <= 12:  # a batch (all forward-kinematics priors of a bag)
        if lie_kernels().covariances_pass_kernel(np.ascontiguousarray(C), tol, tol if eig_tol is None else eig_tol):
            return 0.5 * (C + np.swapaxes(C, -1, -2)) if symmetrize else C
    # array methods instead of np.all / np.max: the same reductions without the dispatch
    # overhead (this runs once per message in the nodes)
    if not np.isfinite(C).all():
        raise CovarianceError(f"{name}: contains NaN or infinite entries")
    scale = max(float(np.abs(C).max()), 1e-300)
    Ct = np.swapaxes(C, -1, -2)
    asym = float(np.abs(C - Ct).max())
    if asym > tol * scale:
        raise CovarianceError(f"{name}: not symmetric (max |C - C^T| = {asym:.3g})")
    C_sym = 0.5 * (C + Ct)
    eig_min = float(np.linalg.eigvalsh(C_sym).min()) if C.shape[-1] else 0.0
    if eig_min < -(tol if eig_tol is None else eig_tol) * scale - 1e-300:
        raise CovarianceError(f"{name}: not positive semi-definite (smallest eigenvalue {eig_min:.3g})")
    return C_sym if symmetrize else C
