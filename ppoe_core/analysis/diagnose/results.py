"""Options and result of a diagnose run."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core.model.effects import Effect

# =============================================================================
# Selection
# =============================================================================


@dataclass
class DiagnoseOptions:
    """Selection settings.

    Attributes
    ----------
    folds : int
        Stop-wise cross-validation folds (within sessions) when there are fewer than 3 groups
        or ``cv="stops"``.
    cv : str
        ``"auto"`` (leave-one-group-out with >= 3 groups, else stops), ``"groups"``, ``"stops"``.
    min_gain : float
        Minimum relative reduction of the held-out mean squared error to accept an effect.
    min_t : float
        Minimum paired one-sided t statistic of that reduction over held-out stops.
    max_condition : float
        Identifiability limit of the scaled reduced information matrix.
    max_absorbed : float
        A parameter whose information is absorbed by the registration beyond this fraction is
        not separable from it.
    max_effects : int
    screen : int
        Per round, only the candidates with the largest in-sample gain are cross-validated.
    seed : int
        Fold assignment.
    imu_sigma : dict or None
        Accelerometer 1-sigma per axis [m/s^2] by IMU name (model ``imus`` section); default 4e-4.
    candidates : list of str or None
        Only candidate keys that start with one of these (e.g. ``"mount_bending"``).
    """

    folds: int = 5
    cv: str = "auto"
    min_gain: float = 0.03
    min_t: float = 4.0
    max_condition: float = 1e6
    max_absorbed: float = 0.999
    max_effects: int = 8
    screen: int = 6
    seed: int = 0
    candidates: list[str] | None = None
    imu_sigma: dict[str, float] | None = None


@dataclass
class DiagnoseResult:
    """Everything ``ppoe diagnose`` reports."""

    effects: list[dict[str, Any]]
    residual_before: float
    residual_after: float
    residual_before_insample: float
    residual_after_insample: float
    noise_floor: float
    unexplained: float
    steps: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    nees_before: float
    nees_after: float
    sigma_scale: float
    linearisation_error: float
    cv: str
    n_stops: int
    n_sessions: int
    e2_before: np.ndarray
    e2_after: np.ndarray
    chosen: list[Effect]
    summary: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The contract JSON (sec. 6) plus details."""
        return {
            "effects": self.effects,
            "residual_before": self.residual_before,
            "residual_after": self.residual_after,
            "residual_before_insample": self.residual_before_insample,
            "residual_after_insample": self.residual_after_insample,
            "noise_floor": self.noise_floor,
            "unexplained": self.unexplained,
            "nees_before": self.nees_before,
            "nees_after": self.nees_after,
            "sigma_scale": self.sigma_scale,
            "linearisation_error": self.linearisation_error,
            "cv": self.cv,
            "n_stops": self.n_stops,
            "n_sessions": self.n_sessions,
            "steps": self.steps,
            "rejected": self.rejected,
            "summary": self.summary,
            **self.extra,
        }
