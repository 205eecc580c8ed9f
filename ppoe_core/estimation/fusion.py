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
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import scipy.linalg
import scipy.stats

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, MeasurementError, PpoeError

__all__ = [
    "MeasurementModelLike",
    "UpdateResult",
    "iterated_update",
    "numerical_jacobian_state",
    "numerical_jacobian_noise",
    "check_noise_covariance",
    "check_pose",
    "nees",
    "nis",
    "nees_bounds",
    "nis_bounds",
    "chi2_gate",
]


@runtime_checkable
class MeasurementModelLike(Protocol):
    """What :func:`iterated_update` needs from a measurement model.

    Attributes
    ----------
    name : str
        Human-readable name used in error messages (e.g. ``"tags@camera_optical_frame"``).
    dim : int
        Size ``m`` of the residual vector ``z ominus h``.
    noise_dim : int
        Size ``k`` of the noise vector ``v``.
    noise_cov : ndarray, shape (k, k)
        Noise covariance ``R`` (``Sigma_v`` of eq. 19), in the noise's own coordinates
        documented by each model.

    A model may also have ``linearize(T_state) -> (h(T), H, M)`` (H or M None = numerical) to
    share work between the prediction and its Jacobians; :func:`iterated_update` uses it when
    present.
    """

    name: str
    dim: int
    noise_dim: int
    noise_cov: np.ndarray

    def validate(self, z: Any) -> np.ndarray:
        """Return ``z`` as an array of the model's shape or raise MeasurementError."""

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Predicted measurement for state ``T_state`` (4, 4) and noise ``v`` (k,)."""

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        """``z ominus z_pred`` as a vector (m,); ``z - z_pred`` for vector measurements."""

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        """``H`` (m, 6) w.r.t. the right perturbation of the state, or None (numerical)."""

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        """``M`` (m, k) w.r.t. the noise at ``v = 0``, or None (numerical)."""


@dataclass(frozen=True)
class UpdateResult:
    """Result of :func:`iterated_update`.

    Attributes
    ----------
    T : ndarray, shape (4, 4)
        Posterior pose ``T_ref_state`` (the prior itself if the measurement was rejected).
    cov : ndarray, shape (6, 6)
        Posterior covariance in the tangent space at ``T`` (right perturbation).
    accepted : bool
        False if the gate rejected the measurement (then ``T``/``cov`` are the prior).
    nis : float
        Normalised innovation squared at the prior, ``y0^T S0^-1 y0``.
    gate : float
        Chi-square threshold the NIS was compared with (``inf`` when gating is off).
    iterations : int
        Number of linearisations done (0 when rejected).
    converged : bool
        True if the last step was below ``step_tolerance``.
    innovation : ndarray, shape (m,)
        Innovation at the prior ``z ominus h(X_0)``.
    S : ndarray, shape (m, m)
        Innovation covariance at the prior ``H P H^T + M R M^T``.
    residual : ndarray, shape (m,)
        Post-fit residual ``z ominus h(T)``.
    gain : ndarray, shape (6, m)
        Kalman gain of the last iteration.
    H : ndarray, shape (m, 6)
        State Jacobian of the last iteration.
    correction : ndarray, shape (6,)
        ``Log(X_0^-1 T)``: total correction in the tangent space at the prior.
    steps : tuple of float
        Norm of each iteration's step ``|d_i|``.
    cost : float
        ``with_cost``: the cost of the solution, ``r+^T (M R M^T)^-1 r+ + d^T P^+ d`` (see
        :func:`ppoe_core.estimation.updater.posterior_cost`); NaN when not computed.
    """

    T: np.ndarray
    cov: np.ndarray
    accepted: bool
    nis: float
    gate: float
    iterations: int
    converged: bool
    innovation: np.ndarray
    S: np.ndarray
    residual: np.ndarray
    gain: np.ndarray
    H: np.ndarray
    correction: np.ndarray
    steps: tuple[float, ...] = field(default_factory=tuple)
    cost: float = float("nan")


# --------------------------------------------------------------------------- checks
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


def _spd(P: np.ndarray) -> np.ndarray:
    """Symmetrise ``P`` and lift tiny negative eigenvalues (round-off) to a small floor."""
    P = 0.5 * (P + P.T)
    w, V = np.linalg.eigh(P)
    floor = 1e-15 * max(float(np.max(w)), 1e-300)
    if w[0] < floor:
        w = np.maximum(w, floor)
        P = (V * w) @ V.T
        P = 0.5 * (P + P.T)
    return P


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
    """``(h(T), H, M)``; uses ``model.linearize`` when the model has it (shared work)."""
    H = M = None
    if jacobians != "numerical" and hasattr(model, "linearize"):
        z_pred, H, M = model.linearize(T)
    else:
        z_pred = model.h(T)
        if jacobians != "numerical":
            H = model.jacobian_state(T)
            M = model.jacobian_noise(T)
    if jacobians == "analytic" and (H is None or M is None):
        raise MeasurementError(f"{model.name}: no analytic Jacobian available")
    if H is None:
        H = numerical_jacobian_state(model, T)
    if M is None:
        M = numerical_jacobian_noise(model, T)
    H = np.asarray(H, dtype=float)
    M = np.asarray(M, dtype=float)
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
        "auto" uses the model's analytic Jacobians when it has them.  A model with ``compiled_args()``
        (tag bearing, contact plane) runs the whole update compiled
        (:mod:`ppoe_core.estimation.compiled_update`) unless ``"numerical"``.
    with_cost : bool
        Also compute ``UpdateResult.cost`` (compiled path only; NaN otherwise).

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
    if jacobians != "numerical" and hasattr(model, "compiled_args"):
        compiled = _compiled(T_prior, cov_prior, z, model, max_iterations, step_tolerance, gate_probability,
                             transport_covariance, with_cost)
        if compiled is not None:
            return compiled
    X0 = check_pose(T_prior, f"{model.name}: prior pose")
    P0 = check_noise_covariance(cov_prior, 6, f"{model.name}: prior covariance")
    R = check_noise_covariance(model.noise_cov, model.noise_dim, f"{model.name}: noise covariance")
    z = model.validate(z)

    Xi = X0
    y0: Any = None  # innovation and its covariance at the prior (set by iteration 1)
    S0: Any = None
    nis_value = float("nan")
    gate = float("inf")
    steps = []
    converged = False
    for it in range(1, max_iterations + 1):
        z_pred, H, M = _linearize(model, Xi, jacobians)
        r = np.asarray(model.residual(z, z_pred), dtype=float)
        e, Pi = _prior_at(Xi, X0, P0, first=it == 1)
        MRM = M @ R @ M.T
        S, cho = _innovation_covariance(H, Pi, MRM, model.name)
        if it == 1:
            y0, S0 = r, S
            nis_value = float(r @ scipy.linalg.cho_solve(cho, r))
            if gate_probability is not None:
                gate = chi2_gate(int(model.dim), float(gate_probability))
                if not nis_value <= gate:
                    return UpdateResult(
                        T=X0.copy(), cov=P0.copy(), accepted=False, nis=nis_value, gate=gate,
                        iterations=0, converged=False, innovation=r, S=S, residual=r,
                        gain=np.zeros((6, model.dim)), H=H, correction=np.zeros(6), steps=(),
                    )
        K = scipy.linalg.cho_solve(cho, H @ Pi).T  # P H^T S^-1 (P and S symmetric)
        y = r - H @ e
        d = e + K @ y
        X_next = Xi @ lie.exp(d)
        step = float(np.linalg.norm(d))
        steps.append(step)
        if step < step_tolerance or it == max_iterations:
            converged = step < step_tolerance
            P_post = _posterior_covariance(K, H, Pi, MRM, d if transport_covariance else None)
            Xi = X_next
            break
        Xi = X_next
    Xi = _reorthonormalise(Xi)
    res = np.asarray(model.residual(z, model.h(Xi)), dtype=float)
    return UpdateResult(
        T=Xi, cov=P_post, accepted=True, nis=nis_value, gate=gate, iterations=len(steps),
        converged=converged, innovation=y0, S=S0, residual=res, gain=K, H=H,
        correction=lie.log(lie.inverse(X0) @ Xi), steps=tuple(steps),
    )


def _compiled(T_prior: Any, cov_prior: Any, z: Any, model: Any, max_iterations: int, step_tolerance: float,
              gate_probability: float | None, transport: bool, with_cost: bool) -> UpdateResult | None:
    """The compiled update of a model with ``compiled_args()`` (None: a prior check failed, the Python path
    raises its error)."""
    from ppoe_core.estimation.compiled_update import checked_noise_covariance, compiled_update

    R = checked_noise_covariance(model)
    if R is None:
        R = check_noise_covariance(model.noise_cov, model.noise_dim, f"{model.name}: noise covariance")
    try:
        zv = np.ascontiguousarray(z, dtype=np.float64)  # finiteness is checked in the kernel
    except (TypeError, ValueError):
        zv = None
    if zv is None or zv.shape != (model.dim,):
        zv = np.ascontiguousarray(model.validate(z), dtype=np.float64)  # raises the model's message
    gate = float("inf") if gate_probability is None else chi2_gate(int(model.dim), float(gate_probability))
    return compiled_update(T_prior, cov_prior, zv, model, np.ascontiguousarray(R), int(max_iterations),
                           float(step_tolerance), gate, bool(transport), bool(with_cost))


def _prior_at(Xi: np.ndarray, X0: np.ndarray, P0: np.ndarray, first: bool) -> tuple[np.ndarray, np.ndarray]:
    """The prior seen from the iterate ``X_i``: ``e = X_0 ominus X_i`` and ``P_i = J P_0 J^T`` (tangent at ``X_i``)."""
    if first:
        return np.zeros(6), P0
    e = lie.log(lie.inverse(Xi) @ X0)  # X_0 ominus X_i, tangent at X_i
    J = lie.right_jacobian_inv(e)
    return e, J @ P0 @ J.T


def _innovation_covariance(H: np.ndarray, Pi: np.ndarray, MRM: np.ndarray, name: str) -> tuple[np.ndarray, Any]:
    """``S = H P H^T + M R M^T`` (symmetrised) and its Cholesky factor (eq. 20).

    Raises
    ------
    CovarianceError
        ``S`` is not positive definite (a measurement without noise).
    """
    S = H @ Pi @ H.T + MRM
    S = 0.5 * (S + S.T)
    try:
        cho = scipy.linalg.cho_factor(S, lower=True, check_finite=True)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise CovarianceError(
            f"{name}: innovation covariance H P H^T + M R M^T is not positive "
            f"definite ({exc}); give the measurement a non-zero noise"
        ) from None
    return S, cho


def _posterior_covariance(K: np.ndarray, H: np.ndarray, Pi: np.ndarray, MRM: np.ndarray,
                          d_transport: np.ndarray | None) -> np.ndarray:
    """Joseph form ``(I-KH) P (I-KH)^T + K M R M^T K^T`` (eq. 23), moved to the tangent space at the
    new estimate with the right Jacobian of the last step ``d`` when given."""
    A = np.eye(6) - K @ H
    P_post = A @ Pi @ A.T + K @ MRM @ K.T
    if d_transport is not None:
        Jr = lie.right_jacobian(d_transport)
        P_post = Jr @ P_post @ Jr.T
    return _spd(P_post)


def _reorthonormalise(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (guards against round-off drift)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


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
    return (
        float(scipy.stats.chi2.ppf(a, dof) / n_trials),
        float(scipy.stats.chi2.ppf(1.0 - a, dof) / n_trials),
    )


def nis_bounds(dim: int, n_trials: int = 1, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square bounds for the NIS (averaged over ``n_trials``) of an ``m = dim``
    dimensional measurement; same formula as :func:`nees_bounds`."""
    return nees_bounds(dim, n_trials, probability)
