"""What the iterated measurement update takes and gives (:func:`ppoe_core.estimation.fusion.iterated_update`): the
measurement model (interface and base class), the description of a model whose linearisation is compiled, and the
result."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from ppoe_core.errors import MeasurementError

__all__ = ["KIND_TAG", "KIND_CONTACT", "CompiledModel", "MeasurementModel", "MeasurementModelLike", "UpdateResult"]

#: compiled linearisations (:mod:`ppoe_core.estimation.update_kernels`): tag bearing, contact plane
KIND_TAG = 0
KIND_CONTACT = 1


class CompiledModel(NamedTuple):
    """A model whose linearisation the compiled update evaluates itself (one call per update).

    Attributes
    ----------
    kind : int
        :data:`KIND_TAG` or :data:`KIND_CONTACT`.
    G : ndarray, shape (4, 4)
        ``T_camera_ref`` (tag) or ``T_plane_ref`` (contact).
    points : ndarray, shape (n, 3)
        The tag points in the state's frame, or the contact tool point (1, 3).
    K : ndarray, shape (3, 3)
        Camera intrinsics (tag; unused for contact).
    D : ndarray, shape (5,)
        plumb_bob coefficients (tag; unused for contact).
    pixel : bool
        Distorted pixels (True) or normalised coordinates (tag).
    extra : bool
        The camera pose noise (tag) or the distance noise (contact) is part of the noise vector.
    min_depth : float
        Points closer to the camera are an error [m] (tag).
    """

    kind: int
    G: np.ndarray
    points: np.ndarray
    K: np.ndarray
    D: np.ndarray
    pixel: bool
    extra: bool
    min_depth: float


class MeasurementModel:
    """The measurement model ``z = h(X, v)`` of the LG-EKF (paper eq. 19-24): what
    :func:`~ppoe_core.estimation.fusion.iterated_update` needs, and the base class of the project's models (a vector
    measurement of shape ``(dim,)`` with the residual ``z - z_pred``).  ``H = dh/dxi`` at the state ``X`` (right
    perturbation, tangent ``[rho; theta]``), ``M = dh/dv`` (docs/conventions.md).

    Attributes
    ----------
    name : str
        Human-readable name used in error messages (e.g. ``"tags@camera_optical_frame"``).
    dim : int
        Size ``m`` of the residual vector ``z ominus h``.
    noise_dim : int
        Size ``k`` of the noise vector ``v``.
    noise_cov : ndarray, shape (k, k)
        Noise covariance ``R`` (``Sigma_v`` of eq. 19), in the noise's own coordinates documented by each model.
    noise_checked : bool
        ``noise_cov`` was built from checked blocks (no need to check it again).
    compiled : CompiledModel or None
        The model's compiled linearisation (the whole update is then one compiled call); None: the update calls
        :meth:`linearize` at every iterate.

    Subclasses implement :meth:`h` and, unless ``None`` (central differences), :meth:`jacobian_state` /
    :meth:`jacobian_noise`, or :meth:`linearize` to share work between the prediction and its Jacobians.
    """

    name: str = "measurement"
    dim: int = 0
    noise_dim: int = 0
    noise_cov: np.ndarray = np.zeros((0, 0))
    noise_checked: bool = False
    compiled: CompiledModel | None = None

    def validate(self, z: Any) -> np.ndarray:
        """Return ``z`` as a float array of shape ``(dim,)``; MeasurementError otherwise."""
        try:
            arr = np.asarray(z, dtype=float)
        except (TypeError, ValueError):
            raise MeasurementError(f"{self.name}: measurement is not numeric") from None
        if arr.shape != (self.dim,):
            raise MeasurementError(f"{self.name}: measurement has shape {arr.shape}, expected ({self.dim},)")
        if not np.all(np.isfinite(arr)):
            bad = np.flatnonzero(~np.isfinite(arr)).tolist()
            raise MeasurementError(f"{self.name}: measurement contains NaN/inf at index {bad}")
        return arr

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        """``z ominus z_pred`` as a vector (m,): ``z - z_pred`` here."""
        return np.asarray(z, dtype=float) - np.asarray(z_pred, dtype=float)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Predicted measurement for state ``T_state`` (4, 4) and noise ``v`` (k,) (None: zero)."""
        raise NotImplementedError

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        """``H`` (m, 6) w.r.t. the right perturbation of the state, or None (numerical)."""
        return None

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        """``M`` (m, k) w.r.t. the noise at ``v = 0``, or None (numerical)."""
        return None

    def linearize(self, T_state: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``(h(T), H, M)`` in one call (models override it to share work); H or M may be None (numerical)."""
        return self.h(T_state), self.jacobian_state(T_state), self.jacobian_noise(T_state)

    def noise_vector(self, v: np.ndarray | None) -> np.ndarray:
        """``v`` as the model's noise vector (zeros for None); MeasurementError for a wrong shape."""
        if v is None:
            return np.zeros(self.noise_dim)
        v = np.asarray(v, dtype=float)
        if v.shape != (self.noise_dim,):
            raise MeasurementError(f"{self.name}: noise vector has shape {v.shape}, expected ({self.noise_dim},)")
        return v


#: what :func:`~ppoe_core.estimation.fusion.iterated_update` takes: a :class:`MeasurementModel` (or any object with
#: its members)
MeasurementModelLike = MeasurementModel


@dataclass(frozen=True)
class UpdateResult:
    """Result of :func:`~ppoe_core.estimation.fusion.iterated_update`.

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
        ``with_cost``: the cost of the solution, ``r+^T (M R M^T)^-1 r+ + d^T P^+ d``
        (:func:`ppoe_core.estimation.update_kernels.posterior_cost`); NaN when not computed.
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
