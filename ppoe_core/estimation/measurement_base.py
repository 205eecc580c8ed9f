"""Base of the measurement models ``z = h(X, v)`` of the LG-EKF (paper eq. 19-24): the interface and shared checks.

``H = dh/dxi`` at the state ``X`` (right perturbation, tangent ``[rho; theta]``), ``M = dh/dv``; docs/conventions.md."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError


def _hat(v: np.ndarray) -> np.ndarray:
    return lie.hat3(np.asarray(v, dtype=float))


def _check_cov(cov: Any, dim: int, name: str) -> np.ndarray:
    from ppoe_core.estimation.fusion import check_noise_covariance  # local import: fusion imports nothing from here

    return check_noise_covariance(cov, dim, name)


def _check_pose(T: Any, name: str) -> np.ndarray:
    from ppoe_core.estimation.fusion import check_pose

    return check_pose(T, name)


def _block_diag(*blocks: np.ndarray) -> np.ndarray:
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        k = b.shape[0]
        out[i : i + k, i : i + k] = b
        i += k
    return out


class MeasurementModel:
    """Base class: vector measurement ``z`` of shape ``(dim,)`` with additive-style residual.

    Subclasses set ``name``, ``dim``, ``noise_dim``, ``noise_cov`` and implement ``h``,
    ``jacobian_state`` and ``jacobian_noise`` (returning ``None`` selects central
    differences in :mod:`ppoe_core.estimation.fusion`).
    """

    name: str = "measurement"
    dim: int = 0
    noise_dim: int = 0
    noise_cov: np.ndarray = np.zeros((0, 0))

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

    def _noise(self, v: np.ndarray | None) -> np.ndarray:
        if v is None:
            return np.zeros(self.noise_dim)
        v = np.asarray(v, dtype=float)
        if v.shape != (self.noise_dim,):
            raise MeasurementError(
                f"{self.name}: noise vector has shape {v.shape}, expected ({self.noise_dim},)"
            )
        return v


def _block_diag_rect(blocks: Sequence[np.ndarray]) -> np.ndarray:
    rows = sum(b.shape[0] for b in blocks)
    cols = sum(b.shape[1] for b in blocks)
    out = np.zeros((rows, cols))
    i = j = 0
    for b in blocks:
        out[i : i + b.shape[0], j : j + b.shape[1]] = b
        i += b.shape[0]
        j += b.shape[1]
    return out
