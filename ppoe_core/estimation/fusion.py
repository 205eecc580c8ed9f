"""Iterated Lie-group EKF update on SE(3), gating and consistency tests (paper section V-A).

The state is one pose ``X = T_ref_state`` (e.g. ``T_camera_tool`` as in the paper, or
``T_base_tool`` in the fusion node) with a covariance ``cov_state`` in the tangent space at
``X`` (right / local perturbation, ``X_true = X @ Exp(xi)``, docs/conventions.md sec. 1).  A measurement
model (see :mod:`ppoe_core.estimation.measurements`) gives ``z = h(X, v)`` with noise ``v ~ N(0, R)``.

The update implements eq. 19-24 with the gain of docs/conventions.md sec. 1,
``K = P H^T (H P H^T + M R M^T)^-1``, where the innovation covariance ``S`` is factorised by
Cholesky (never inverted explicitly), the covariance is updated in Joseph form and the step
is iterated (iterated EKF, relinearising at the current estimate ``X_i``):

* prior seen from the iterate: ``X_0 = X_i Exp(e_i)`` with ``e_i = X_0 ominus X_i =
  Log(X_i^-1 X_0)``; to first order ``xi_i = e_i + Jr(e_i)^-1 xi_0``, so the prior covariance
  moved into the tangent space at ``X_i`` is ``P_i = Jr^-1(e_i) P_0 Jr^-T(e_i)``
  (**approximation**: first order in the prior perturbation ``xi_0``; exact for ``e_i = 0``);
* innovation ``y_i = (z ominus h(X_i)) - H_i e_i``, gain ``K_i = P_i H_i^T S_i^-1``,
  ``S_i = H_i P_i H_i^T + M_i R M_i^T``;
* correction ``d_i = e_i + K_i y_i`` (in the tangent space at ``X_i``),
  ``X_{i+1} = X_i Exp(d_i)`` (eq. 22); stop when ``|d_i| < step_tolerance`` or after
  ``max_iterations``;
* covariance (eq. 23 in Joseph form) ``P+ = (I-KH) P_i (I-KH)^T + K M R M^T K^T`` at ``X_i``,
  then moved to the tangent space at the returned estimate ``X_{i+1} = X_i Exp(d)`` with
  ``Jr(d) P+ Jr(d)^T`` (the usual LG-EKF reset; ``d`` is tiny once the iteration converged).

With ``max_iterations=1`` this is the plain LG-EKF update of Bourmaud et al. (paper ref. [18]).

Gating uses the normalised innovation squared (NIS) at the prior against the chi-square
quantile of the measurement's dimension; a rejected measurement returns the prior unchanged
with ``accepted=False``.

When a model has no analytic Jacobian (``jacobian_state`` / ``jacobian_noise`` return
``None``), central differences in the tangent space are used (paper ref. [19]).

The update itself is compiled and written once (:mod:`ppoe_core.estimation.update_kernels`, driven by
:func:`ppoe_core.estimation.compiled_update.run_update`): a model with a compiled linearisation (its ``compiled``
attribute, :class:`~ppoe_core.estimation.update_types.CompiledModel`: tag bearing, contact plane) runs in one call,
any other model gives its linearisation at each iterate.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import scipy.stats

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, MeasurementError, PpoeError
from ppoe_core.estimation.checks import check_noise_covariance, check_pose
from ppoe_core.estimation.compiled_update import run_update
from ppoe_core.estimation.update_types import MeasurementModelLike, UpdateResult

__all__ = [
    "MeasurementModelLike", "UpdateResult", "iterated_update", "numerical_jacobian_state", "numerical_jacobian_noise",
    "check_noise_covariance", "check_pose", "nees", "nis", "nees_bounds", "nis_bounds", "chi2_gate",
]


# --------------------------------------------------------------------------- Jacobians
def numerical_jacobian_state(
    model: MeasurementModelLike, T_state: np.ndarray, eps: float = 1e-6
) -> np.ndarray:
    """Central-difference ``H = d h(T Exp(xi)) / d xi`` at ``xi = 0`` (eq. 24, ref. [19]).

    Parameters
    ----------
    model : MeasurementModelLike
    T_state : ndarray, shape (4, 4)
        Linearisation point; ``xi`` lives in its tangent space (right perturbation).
    eps : float
        Step in metres / radians.

    Returns
    -------
    ndarray, shape (m, 6)
    """
    H = np.empty((model.dim, 6))
    for j in range(6):
        d = np.zeros(6)
        d[j] = eps
        zp = model.h(T_state @ lie.exp(d))
        zm = model.h(T_state @ lie.exp(-d))
        H[:, j] = model.residual(zp, zm) / (2.0 * eps)
    return H


def numerical_jacobian_noise(
    model: MeasurementModelLike, T_state: np.ndarray, eps: float = 1e-6
) -> np.ndarray:
    """Central-difference ``M = d h(T, v) / d v`` at ``v = 0`` (eq. 24).

    Returns
    -------
    ndarray, shape (m, k)
    """
    M = np.empty((model.dim, model.noise_dim))
    for j in range(model.noise_dim):
        d = np.zeros(model.noise_dim)
        d[j] = eps
        M[:, j] = model.residual(model.h(T_state, d), model.h(T_state, -d)) / (2.0 * eps)
    return M


def _linearize(
    model: MeasurementModelLike, T: np.ndarray, jacobians: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(h(T), H, M)`` by ``model.linearize`` (central differences for a None Jacobian, or all with
    ``jacobians="numerical"``)."""
    H = M = None
    if jacobians != "numerical":
        z_pred, H, M = model.linearize(T)
    else:
        z_pred = model.h(T)
    if jacobians == "analytic" and (H is None or M is None):
        raise MeasurementError(f"{model.name}: no analytic Jacobian available")
    if H is None:
        H = numerical_jacobian_state(model, T)
    if M is None:
        M = numerical_jacobian_noise(model, T)
    H = np.ascontiguousarray(H, dtype=np.float64)
    M = np.ascontiguousarray(M, dtype=np.float64)
    if H.shape != (model.dim, 6) or M.shape != (model.dim, model.noise_dim):
        raise MeasurementError(
            f"{model.name}: Jacobian shapes H {H.shape}, M {M.shape} do not match "
            f"dim {model.dim}, noise_dim {model.noise_dim}"
        )
    return z_pred, H, M


@functools.lru_cache(maxsize=256)
def chi2_gate(dim: int, probability: float) -> float:
    """Chi-square quantile used as Mahalanobis gate for a ``dim``-dimensional innovation
    (cached: scipy's ppf costs more than a whole contact update)."""
    return float(scipy.stats.chi2.ppf(probability, dim))


# --------------------------------------------------------------------------- update
def iterated_update(
    T_prior: Any,
    cov_prior: Any,
    z: Any,
    model: MeasurementModelLike,
    *,
    max_iterations: int = 10,
    step_tolerance: float = 1e-10,
    gate_probability: float | None = 0.9973,
    transport_covariance: bool = True,
    jacobians: str = "auto",
    with_cost: bool = False,
) -> UpdateResult:
    """Iterated LG-EKF measurement update on SE(3) (eq. 19-24, gain of docs/conventions.md sec. 1).

    Parameters
    ----------
    T_prior : array_like, shape (4, 4)
        Prior mean ``X_0 = T_ref_state`` (e.g. from ``model.fk``).
    cov_prior : array_like, shape (6, 6)
        Prior covariance in the tangent space at ``T_prior`` (right perturbation, [rho; theta]).
        May be singular (PPOE covariances often are): it is never inverted.
    z : array_like
        The measurement, in the shape the model validates.
    model : MeasurementModelLike
        Measurement model with ``h``, ``H``, ``M``, ``R`` (see :mod:`ppoe_core.estimation.measurements`).
    max_iterations : int
        Maximum number of relinearisations (1 = plain LG-EKF).
    step_tolerance : float
        Stop when the norm of the tangent step ``|d_i|`` falls below this.
    gate_probability : float or None
        Reject when the prior NIS exceeds ``chi2.ppf(gate_probability, m)``; None: no gating.
    transport_covariance : bool
        Move the posterior covariance to the tangent space at the returned estimate with the
        right Jacobian of the last step (see the module docstring).
    jacobians : {"auto", "analytic", "numerical"}
        "auto" uses the model's analytic Jacobians when it has them.  A model with a compiled linearisation
        (``model.compiled``: tag bearing, contact plane) runs the whole update in one compiled call unless
        ``"numerical"``.
    with_cost : bool
        Also compute ``UpdateResult.cost``, the posterior cost (NaN otherwise).

    Returns
    -------
    UpdateResult
        Posterior ``T`` and ``cov`` (tangent space at ``T``) and diagnostics.

    Raises
    ------
    MeasurementError
        NaN or wrongly shaped measurement, a point behind the camera, a bad prior pose.
    CovarianceError
        Non-PSD prior or noise covariance, or an innovation covariance that is not
        positive definite.
    """
    if jacobians not in ("auto", "analytic", "numerical"):
        raise PpoeError(f"iterated_update: jacobians must be auto, analytic or numerical, not {jacobians!r}")
    if max_iterations < 1:
        raise PpoeError(f"iterated_update: max_iterations must be >= 1, got {max_iterations}")
    R = model.noise_cov if model.noise_checked else check_noise_covariance(
        model.noise_cov, model.noise_dim, f"{model.name}: noise covariance")
    R = np.ascontiguousarray(R, dtype=np.float64)
    spec = model.compiled if jacobians != "numerical" else None
    gate = float("inf") if gate_probability is None else chi2_gate(int(model.dim), float(gate_probability))
    if spec is not None:
        try:
            zv = np.ascontiguousarray(z, dtype=np.float64)  # finiteness is checked in the kernel
        except (TypeError, ValueError):
            zv = None
        if zv is None or zv.shape != (model.dim,):
            zv = np.ascontiguousarray(model.validate(z), dtype=np.float64)  # raises the model's message
        return run_update(T_prior, cov_prior, zv, model, R, spec, None, int(max_iterations), float(step_tolerance),
                          gate, bool(transport_covariance), bool(with_cost))
    z_checked = model.validate(z)

    def linearise(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z_pred, H, M = _linearize(model, T, jacobians)
        return np.ascontiguousarray(model.residual(z_checked, z_pred), dtype=np.float64), H, M

    return run_update(T_prior, cov_prior, z_checked, model, R, None, linearise, int(max_iterations),
                      float(step_tolerance), gate, bool(transport_covariance), bool(with_cost))


# --------------------------------------------------------------------------- consistency
def nees(T_est: Any, cov_est: Any, T_true: Any) -> np.ndarray:
    """Normalised estimation error squared ``e^T P^-1 e``, ``e = Log(T_est^-1 T_true)``.

    Parameters
    ----------
    T_est : array_like, shape (..., 4, 4)
        Estimates.
    cov_est : array_like, shape (..., 6, 6)
        Their covariances, in the tangent space at ``T_est`` (must be positive definite).
    T_true : array_like, shape (..., 4, 4)
        True poses.

    Returns
    -------
    ndarray, shape (...)
        Chi-square distributed with 6 degrees of freedom for a consistent estimator.
    """
    T_est = np.asarray(T_est, dtype=float)
    T_true = np.asarray(T_true, dtype=float)
    cov = np.asarray(cov_est, dtype=float)
    e = lie.log(lie.inverse(T_est) @ T_true)
    return _mahalanobis(e, cov, "nees: estimate covariance")


def nis(innovation: Any, S: Any) -> np.ndarray:
    """Normalised innovation squared ``y^T S^-1 y``.

    Parameters
    ----------
    innovation : array_like, shape (..., m)
    S : array_like, shape (..., m, m)
        Innovation covariance (positive definite).

    Returns
    -------
    ndarray, shape (...)
    """
    return _mahalanobis(np.asarray(innovation, float), np.asarray(S, float), "nis: S")


def _mahalanobis(e: np.ndarray, cov: np.ndarray, name: str) -> np.ndarray:
    try:
        L = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise CovarianceError(f"{name} is not positive definite") from None
    w = np.linalg.solve(L, e[..., None])[..., 0]
    return np.sum(w * w, axis=-1)


def nees_bounds(dim: int = 6, n_trials: int = 1, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square bounds for the NEES averaged over ``n_trials`` runs.

    ``n_trials * mean(NEES)`` is chi-square with ``n_trials * dim`` degrees of freedom, so the
    bounds are ``chi2.ppf((1 -+ probability) / 2, n_trials * dim) / n_trials``.

    Returns
    -------
    (lower, upper) : tuple of float
    """
    a = (1.0 - probability) / 2.0
    dof = n_trials * dim
    return (float(scipy.stats.chi2.ppf(a, dof) / n_trials), float(scipy.stats.chi2.ppf(1.0 - a, dof) / n_trials))


def nis_bounds(dim: int, n_trials: int = 1, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square bounds for the NIS (averaged over ``n_trials``) of an ``m = dim``
    dimensional measurement; same formula as :func:`nees_bounds`."""
    return nees_bounds(dim, n_trials, probability)
