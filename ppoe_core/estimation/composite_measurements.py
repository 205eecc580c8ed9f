"""Measurement combinators: a sensor on another link than the state (chained) and several measurements at once
(stacked)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.linalg

from ppoe_core import lie
from ppoe_core.estimation.checks import check_noise_covariance, check_pose
from ppoe_core.errors import MeasurementError
from ppoe_core.estimation.direct_measurements import PoseObservation
from ppoe_core.estimation.update_types import MeasurementModel


# --------------------------------------------------------------------------- composition
class ChainedObservation(MeasurementModel):
    """A model of link ``L`` used with the state ``X = T_ref_tool`` (see module docstring).

    The inner model's state is ``T_ref_L = X @ T_tool_L @ Exp(w)``, ``w ~ N(0, cov_L)``
    (tangent space at ``T_tool_L``); noise ``v = [v_inner; w]``.  ``H = H_in Ad(T_tool_L^-1)``,
    ``M = [M_in, H_in]``.  The correlation of ``w`` with the state's prior is neglected.

    Parameters
    ----------
    inner : MeasurementModel
        Model whose state is the pose of link ``L``.
    T_tool_L : array_like, shape (4, 4)
        Mean pose of ``L`` in the state's child frame (e.g. ``model.fk(q, tool, L)``).
    cov_L : array_like, shape (6, 6), optional
        Its covariance in the tangent space at ``T_tool_L`` (``None``: exact).
    """

    def __init__(self, inner: MeasurementModel, T_tool_L: Any, cov_L: Any = None, name: str = "") -> None:
        self.inner = inner
        self.name = name or f"{inner.name} (chained)"
        self.T_tool_L = check_pose(T_tool_L, f"{self.name}: T_tool_L")
        self.Ad_L_tool = lie.adjoint(lie.inverse(self.T_tool_L))
        self.has_link_noise = cov_L is not None
        blocks = [np.asarray(inner.noise_cov, dtype=float)]
        if self.has_link_noise:
            blocks.append(check_noise_covariance(cov_L, 6, f"{self.name}: cov_L"))
        self.noise_cov = scipy.linalg.block_diag(*blocks)
        self.noise_dim = self.noise_cov.shape[0]
        self.dim = inner.dim

    def validate(self, z: Any) -> np.ndarray:
        return self.inner.validate(z)

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        return self.inner.residual(z, z_pred)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        v = self.noise_vector(v)
        k = self.inner.noise_dim
        T_L = T_state @ self.T_tool_L
        if self.has_link_noise:
            T_L = T_L @ lie.exp(v[k:])
        return self.inner.h(T_L, v[:k])

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        H_in = self.inner.jacobian_state(T_state @ self.T_tool_L)
        return None if H_in is None else H_in @ self.Ad_L_tool

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        T_L = T_state @ self.T_tool_L
        M_in = self.inner.jacobian_noise(T_L)
        if M_in is None:
            return None
        if not self.has_link_noise:
            return M_in
        H_in = self.inner.jacobian_state(T_L)
        return None if H_in is None else np.hstack([M_in, H_in])


class StackedObservation(MeasurementModel):
    """Several independent measurements of the same state fused in one update.

    ``z`` is the concatenation of the parts' measurements (each flattened: a 6D pose part
    takes 16 numbers, row-major); the residual and noise are stacked block-wise.

    Parameters
    ----------
    parts : sequence of MeasurementModel
        Models of the same state ``X``.  Their noises are treated as independent.
    """

    def __init__(self, parts: Sequence[MeasurementModel], name: str = "stacked") -> None:
        if not parts:
            raise MeasurementError(f"{name}: needs at least one part")
        self.parts = list(parts)
        self.name = name
        self.dim = sum(p.dim for p in self.parts)
        self.noise_cov = scipy.linalg.block_diag(*[np.asarray(p.noise_cov, float) for p in self.parts])
        self.noise_dim = self.noise_cov.shape[0]
        self._zsizes = [16 if isinstance(p, PoseObservation) else p.dim for p in self.parts]

    def _split(self, z: np.ndarray, sizes: Sequence[int]) -> list:
        out, i = [], 0
        for s in sizes:
            out.append(z[i : i + s])
            i += s
        return out

    def validate(self, z: Any) -> np.ndarray:
        arr = np.asarray(z, dtype=float).ravel()
        if arr.size != sum(self._zsizes):
            raise MeasurementError(f"{self.name}: measurement has {arr.size} numbers, expected {sum(self._zsizes)}")
        parts = []
        for p, zp in zip(self.parts, self._split(arr, self._zsizes)):
            zp = zp.reshape(4, 4) if isinstance(p, PoseObservation) else zp
            parts.append(np.asarray(p.validate(zp), dtype=float).ravel())
        return np.concatenate(parts)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        v = self.noise_vector(v)
        vs = self._split(v, [p.noise_dim for p in self.parts])
        return np.concatenate([np.asarray(p.h(T_state, vp), float).ravel() for p, vp in zip(self.parts, vs)])

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        out = []
        for p, a, b in zip(self.parts, self._split(z, self._zsizes), self._split(z_pred, self._zsizes)):
            if isinstance(p, PoseObservation):
                a, b = a.reshape(4, 4), b.reshape(4, 4)
            out.append(p.residual(a, b))
        return np.concatenate(out)

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        Hs = [p.jacobian_state(T_state) for p in self.parts]
        Hs_known = [H for H in Hs if H is not None]
        return None if len(Hs_known) < len(Hs) else np.vstack(Hs_known)

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        Ms = [p.jacobian_noise(T_state) for p in self.parts]
        Ms_known = [M for M in Ms if M is not None]
        if len(Ms_known) < len(Ms):
            return None
        return scipy.linalg.block_diag(*Ms_known)
