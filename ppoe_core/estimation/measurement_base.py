"""Base of the measurement models ``z = h(X, v)`` of the LG-EKF (paper eq. 19-24): the interface and shared checks.

``H = dh/dxi`` at the state ``X`` (right perturbation, tangent ``[rho; theta]``), ``M = dh/dv``; docs/conventions.md."""

from __future__ import annotations

from typing import Any

import numpy as np

from ppoe_core.errors import MeasurementError
from ppoe_core.estimation.update_types import CompiledModel

__all__ = ["MeasurementModel"]


class MeasurementModel:
    """Base class: vector measurement ``z`` of shape ``(dim,)`` with additive-style residual.

    Subclasses set ``name``, ``dim``, ``noise_dim``, ``noise_cov`` and implement ``h``,
    ``jacobian_state`` and ``jacobian_noise`` (returning ``None`` selects central
    differences in :mod:`ppoe_core.estimation.fusion`); ``noise_checked`` when ``noise_cov`` is built
    from checked blocks, ``compiled`` when the model's linearisation is compiled
    (:class:`~ppoe_core.estimation.update_types.CompiledModel`).
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
            raise MeasurementError(
                f"{self.name}: measurement has shape {arr.shape}, expected ({self.dim},)"
            )
        if not np.all(np.isfinite(arr)):
            bad = np.flatnonzero(~np.isfinite(arr)).tolist()
            raise MeasurementError(f"{self.name}: measurement contains NaN/inf at index {bad}")
        return arr

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        """``z - z_pred`` (m,)."""
        return np.asarray(z, dtype=float) - np.asarray(z_pred, dtype=float)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        return None

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        return None

    def linearize(
        self, T_state: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``(h(T), H, M)`` in one call (models override it to share work); H or M may be
        None (numerical)."""
        return self.h(T_state), self.jacobian_state(T_state), self.jacobian_noise(T_state)

    def noise_vector(self, v: np.ndarray | None) -> np.ndarray:
        """``v`` as the model's noise vector (zeros for None); MeasurementError for a wrong shape."""
        if v is None:
            return np.zeros(self.noise_dim)
        v = np.asarray(v, dtype=float)
        if v.shape != (self.noise_dim,):
            raise MeasurementError(
                f"{self.name}: noise vector has shape {v.shape}, expected ({self.noise_dim},)"
            )
        return v
