"""Options and typed results of a diagnose run (the JSON of ``ppoe diagnose --json`` is :meth:`DiagnoseResult.to_json`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ppoe_core.analysis.diagnose.selection import SelectionOptions
from ppoe_core.model.effects import Effect

__all__ = ["DiagnoseOptions", "EffectReport", "BlockReport", "StructureTest", "DiagnoseResult", "finite_json"]


@dataclass
class DiagnoseOptions:
    """Settings of :func:`~ppoe_core.analysis.diagnose.engine.diagnose`.

    Attributes
    ----------
    folds : int
        Folds of the cross-validation over robot poses (within bags) when there are fewer than 3 bags or
        ``cv="stops"``.
    cv : str
        ``"auto"`` (leave-one-bag-out with >= 3 bags, else poses), ``"groups"``, ``"stops"``.
    min_t : float
        Minimum paired t (or signed-rank z) over robot poses of a forward step's held-out gains.
    min_gain : float
        Minimum relative held-out gain of a forward step (0: none; the penalised likelihood decides).
    penalty : float or None
        Price per parameter in held-out ``-2 log L`` units (None: ``ln`` of the number of scored poses).
    max_condition, max_absorbed : float
        Identifiability limits (condition number of the scaled reduced information; share of a parameter's
        information a nuisance absorbs).
    max_effects : int or None
        Optional cap on the number of effects (None: stop when nothing significant is left).
    groups : bool
        Offer group moves (one kind of effect on every joint of a measured chain).
    seed : int
        Fold assignment.
    candidates : list of str or None
        Only candidates whose key (``name@location``) starts with one of these.
    effects : list of str or None
        Fit this declared set (``name@location`` or ``name@location[comp,...]``) instead of selecting.
    imu_sigma : dict or None
        Accelerometer 1-sigma per axis [m/s^2] by IMU name (model ``imus`` section); default 4e-4.
    loss : str
        ``"linear"`` or ``"soft_l1"`` (robust, scale ``loss_scale`` in whitened units).
    blocks : list of str or None
        Measurement kinds to use (``tracker``, ``pose``, ``pixels``, ``imu``, ``contact``); None: all present.
    learn_perturbations : bool
        Learn the perturbation covariances from the held-out residual and check the three covariance choices
        (:mod:`~ppoe_core.analysis.diagnose.learned_prior`); the result's ``learned_prior``.
    """

    folds: int = 5
    cv: str = "auto"
    # the selection's settings default to the selection's own (one place: SelectionOptions)
    min_t: float = SelectionOptions.min_t
    min_gain: float = SelectionOptions.min_gain
    penalty: float | None = SelectionOptions.penalty
    max_condition: float = SelectionOptions.max_condition
    max_absorbed: float = SelectionOptions.max_absorbed
    max_effects: int | None = SelectionOptions.max_effects
    groups: bool = SelectionOptions.groups
    seed: int = 0
    candidates: list[str] | None = None
    effects: list[str] | None = None
    imu_sigma: dict[str, float] | None = None
    loss: str = "linear"
    loss_scale: float = 3.0
    blocks: list[str] | None = None
    learn_perturbations: bool = False


@dataclass
class EffectReport:
    """One effect found (contract sec. 6 entry): parameters with 95 % intervals and sigmas, the share of the
    held-out residual it removed, the measurements that see it; ``camera_info`` for ``camera_intrinsics`` (the
    corrected ``K``, ``D``), ``frame`` for a camera effect."""

    name: str
    location: str
    parameters: dict[str, float]
    ci: dict[str, list[float]]
    sigma: dict[str, float]
    share: float = 0.0
    measurement: str = ""
    frame: str | None = None
    camera_info: dict[str, Any] | None = None
    variable: Any = None
    reference: Any = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "location": self.location, "parameters": self.parameters,
                               "ci": self.ci, "sigma": self.sigma, "share": self.share,
                               "measurement": self.measurement}
        for key in ("frame", "camera_info", "variable", "reference"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out


@dataclass
class StructureTest:
    """Can the held-out residual be predicted from ``predictor`` (configuration, time, image position) better than
    without it, cross-validated?  Held-out gain (share of the whitened error), paired t over poses, significant."""

    predictor: str
    gain: float
    t: float
    significant: bool

    def to_json(self) -> dict[str, Any]:
        return {"predictor": self.predictor, "heldout_gain": self.gain, "t": self.t, "significant": self.significant}


@dataclass
class BlockReport:
    """One measurement kind: held-out and in-sample RMS before / after (``unit``), per group and per sensor, its
    noise (sensor and prior scales, noise floor), held-out NEES under the declared and the estimated covariance,
    the structure tests and what is left above the floor."""

    kind: str
    unit: str
    n: int
    rms_before: float
    rms_after: float
    rms_before_insample: float
    rms_after_insample: float
    sensor_scale: float
    prior_scale: float
    noise_floor: float
    unexplained: float
    nees_before: float
    nees_after: float
    per_group: dict[str, dict[str, Any]] = field(default_factory=dict)
    per_sensor: dict[str, dict[str, float]] = field(default_factory=dict)
    structure: list[StructureTest] = field(default_factory=list)
    dropped: int = 0

    @property
    def significant(self) -> bool:
        return any(s.significant for s in self.structure)

    def to_json(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in ("kind", "unit", "n", "rms_before", "rms_after", "rms_before_insample",
                                             "rms_after_insample", "sensor_scale", "prior_scale", "noise_floor",
                                             "unexplained", "nees_before", "nees_after", "per_group", "per_sensor",
                                             "dropped")}
        out["structure"] = [s.to_json() for s in self.structure]
        out["unexplained_significant"] = self.significant
        return out


@dataclass
class DiagnoseResult:
    """Everything ``ppoe diagnose`` reports (:meth:`to_json` is its JSON, CONTRACT sec. 6 keys first)."""

    effects: list[EffectReport]
    found: list[Effect]
    blocks: dict[str, BlockReport]
    steps: list[dict[str, Any]]
    rejected: list[dict[str, str]]
    cv: str
    n_stops: int
    n_sessions: int
    n_poses: int
    summary: str = ""
    test: dict[str, dict[str, Any]] | None = None
    fitted_joint_noise: dict[str, float] | None = None
    #: :class:`~ppoe_core.analysis.diagnose.learned_prior.LearnedPrior` with ``learn_perturbations``
    learned_prior: Any = None

    @property
    def chosen(self) -> list[Effect]:
        """The effects found with their fitted parameters."""
        return self.found

    @property
    def metric(self) -> BlockReport | None:
        """The block whose residual is in metres (tracker points, else poses), if any."""
        return self.blocks.get("tracker") or self.blocks.get("pose")

    def _metric(self, key: str) -> float:
        m = self.metric
        return float(getattr(m, key)) if m is not None else math.nan

    @property
    def residual_before(self) -> float:
        return self._metric("rms_before")

    @property
    def residual_after(self) -> float:
        return self._metric("rms_after")

    @property
    def noise_floor(self) -> float:
        return self._metric("noise_floor")

    @property
    def unexplained(self) -> float:
        return self._metric("unexplained")

    @property
    def unexplained_significant(self) -> bool:
        return any(b.significant for b in self.blocks.values())

    @property
    def sigma_scale(self) -> float:
        """The declared prior's scale as the data estimate it (the metric block's, else the first block's)."""
        b = self.metric or next(iter(self.blocks.values()), None)
        return b.prior_scale if b is not None else math.nan

    def to_json(self) -> dict[str, Any]:
        """The contract JSON (sec. 6) plus details (docs/diagnose.md)."""
        m = self.metric
        out: dict[str, Any] = {
            "effects": [e.to_json() for e in self.effects],
            "residual_before": self.residual_before, "residual_after": self.residual_after,
            "unexplained": self.unexplained, "unexplained_significant": self.unexplained_significant,
            "noise_floor": self.noise_floor, "sigma_scale": self.sigma_scale,
            "residual_before_insample": self._metric("rms_before_insample"),
            "residual_after_insample": self._metric("rms_after_insample"),
            "nees_before": self._metric("nees_before"), "nees_after": self._metric("nees_after"),
            "cv": self.cv, "n_stops": self.n_stops, "n_sessions": self.n_sessions, "n_poses": self.n_poses,
            "measurements": {k: b.to_json() for k, b in self.blocks.items()},
            "per_group": m.per_group if m is not None else {},
            "steps": self.steps, "rejected": self.rejected, "summary": self.summary,
        }
        px = self.blocks.get("pixels")
        if px is not None:  # per camera [px], as the tag-pixel reports have always had them
            out["pixels"] = {"n": px.n, **{f"pixel_rms_{k}": {c: v[f"rms_{k}"] for c, v in px.per_sensor.items()}
                                           for k in ("before", "after", "before_insample", "after_insample")}}
        if self.test is not None:
            out["test"] = self.test
        if self.fitted_joint_noise:
            out["fitted_joint_noise"] = self.fitted_joint_noise
        if self.learned_prior is not None:
            out["learned_perturbations"] = self.learned_prior.to_json()
        return finite_json(out)


def finite_json(v: Any) -> Any:
    """``v`` (nested dicts and lists) with every NaN / inf float as None: strict JSON (``allow_nan=False``)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: finite_json(x) for k, x in v.items()}
    if isinstance(v, list):
        return [finite_json(x) for x in v]
    return v
