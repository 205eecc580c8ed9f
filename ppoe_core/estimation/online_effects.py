"""Online estimation of drifting effects (issue 11 item 1; the paper's future work): an augmented-state EKF.

The state is the stacked parameter vector ``theta`` of a few effects of the catalogue
(:mod:`ppoe_core.model.effects`: per-placement ``base_tilt``, ``thermal_growth`` with the temperature as its
variable, a ``gravity_compliance``, ``camera_extrinsics``, ...) with covariance ``P``; every other effect of the
diagnosed model stays fixed.  Between measurements each parameter is a random walk,
``P += diag(q^2) dt`` with ``q`` the process noise in *parameter unit per sqrt(s)*: the rule for how fast a
parameter may drift.  A tracker point on a link (``/ground_truth/point[/<name>]`` in the tracker frame, the
registration ``T_tracker_base`` known from the diagnosed model's ``tracker_registration`` effect) updates it::

    z = T_tracker_root p_root(q; theta) + v,   H = R_tracker_root dp_root/dtheta,
    S = H P H^T + R_tracker_root (Sigma_ppoe + sigma^2 I) R_tracker_root^T,   K = P H^T S^-1

(an accelerometer at rest on a link updates it through the same step with the existing gravity model,
:meth:`OnlineEffects.update_gravity`: it sees a tilt without any registration)
where ``p_root`` is the reflector on the chain of eq. 16 with the effects' corrections
(``Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))``, :meth:`KinematicTree.link_poses`),
``dp_root/dtheta`` the chain Jacobian (:meth:`KinematicTree.point_jacobian`) times the effects' exact bases
(:meth:`Effect.basis`) and ``Sigma_ppoe`` the PPOE covariance of the point (paper eq. 18), i.e. the random
errors of the model act as measurement noise.  A placement change (the base moved onto another floor) is a jump,
not a drift: with ``jump_probability`` set, an innovation whose NIS exceeds that chi-square quantile re-opens the
covariance of the tracked parameters to their initial sigma before the update (counted in ``jumps``).

The fused tool pose uses the current estimate: the mean of the chain with all effects, and the covariance
``Sigma_ppoe + J P J^T`` in the tool's tangent space (``J = d xi_tool / d theta``).  Everything is numpy; the
fusion node (``ppoe_ros.common.online_effects``) and ``ppoe evaluate --online``
(:mod:`ppoe_core.analysis.evaluate.online`) call the same object, so live equals offline.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.estimation.direct_measurements import GravityObservation
from ppoe_core.model.effects import Effect, effect_from_config, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree

__all__ = [
    "DEFAULT_INITIAL_SIGMA",
    "DEFAULT_PROCESS_NOISE",
    "ONLINE_EFFECT_NAMES",
    "OnlineEffects",
    "PointUpdate",
    "TrackedEffect",
    "entries_from_flat",
    "parse_online_config",
    "replace_effects",
]

#: process noise per parameter of each trackable effect [parameter unit / sqrt(s)]
DEFAULT_PROCESS_NOISE: dict[str, float] = {
    "base_tilt": 1e-4,            # rad/sqrt(s)
    "thermal_growth": 1e-7,       # (1/K)/sqrt(s)
    "gravity_compliance": 1e-6,   # rad/(N m)/sqrt(s)
    "mount_bending": 1e-6,        # rad/(N m)/sqrt(s)
    "camera_extrinsics": 1e-4,    # m/sqrt(s) and rad/sqrt(s)
    "joint_offset": 1e-5,         # rad/sqrt(s)
    "link_error": 1e-5,           # m/sqrt(s) and rad/sqrt(s)
}
#: prior 1-sigma of a tracked parameter that the diagnosed model does not hold (and after a jump) [parameter unit]
DEFAULT_INITIAL_SIGMA: dict[str, float] = {
    "base_tilt": 0.005, "thermal_growth": 1e-4, "gravity_compliance": 1e-3, "mount_bending": 1e-3,
    "camera_extrinsics": 0.01, "joint_offset": 0.005, "link_error": 0.002,
}
ONLINE_EFFECT_NAMES = tuple(DEFAULT_PROCESS_NOISE)
_ENTRY_KEYS = ("name", "location", "process_noise", "initial_sigma", "variable", "reference", "parameters")


@dataclass
class TrackedEffect:
    """One effect whose parameters are estimated online.

    Attributes
    ----------
    effect : Effect
        Catalogue object; its ``params`` are the initial estimate (the diagnosed value, or zeros).
    process_noise : ndarray (P,)
        Random-walk intensity per parameter [parameter unit / sqrt(s)].
    initial_sigma : ndarray (P,)
        Prior 1-sigma [parameter unit]; also the covariance re-opened after a jump.
    """

    effect: Effect
    process_noise: np.ndarray
    initial_sigma: np.ndarray


@dataclass
class PointUpdate:
    """Outcome of one update: innovation (3,) [m or m/s^2], NIS, whether a jump re-opened the covariance."""

    innovation: np.ndarray
    nis: float
    jump: bool


def _vector(raw: Any, n: int, default: float, where: str) -> np.ndarray:
    if raw is None:
        return np.full(n, default)
    v = np.atleast_1d(np.asarray(raw, dtype=float)) if not isinstance(raw, str) else np.array([np.nan])
    if v.shape == (1,):
        v = np.full(n, v[0])
    if v.shape != (n,) or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ModelConfigError(f"{where}: expected {n} non-negative numbers (or one), got {raw!r}")
    return v


def parse_online_config(raw: Any, model: Any, where: str = "online_effects") -> list[TrackedEffect]:
    """The ``online_effects`` list (of a node YAML or ``ppoe evaluate --online-config``) -> tracked effects.

    Each entry is ``{name, location[, process_noise, initial_sigma, variable, reference]}``: ``process_noise``
    [parameter unit / sqrt(s)] and ``initial_sigma`` [parameter unit] are one number or one per parameter.  An
    effect the model already holds starts at the model's values; a new one at zero.  ``None`` tracks every
    effect of the model whose name is in :data:`ONLINE_EFFECT_NAMES`, and ``base_tilt`` at the root link.

    Raises
    ------
    ModelConfigError
        Unknown keys, names or parameters, bad numbers, an effect listed twice; the message names the entry.
    """
    if raw is None:
        raw = [{"name": "base_tilt", "location": model.robot.root}] + [
            {"name": e.name, "location": e.location} for e in model.effects
            if e.name in ONLINE_EFFECT_NAMES and not (e.name == "base_tilt")]
    if not isinstance(raw, Sequence) or isinstance(raw, str):
        raise ModelConfigError(f"{where} must be a list of {{name, location, process_noise, initial_sigma}}")
    out: list[TrackedEffect] = []
    for i, entry in enumerate(raw):
        w = f"{where}[{i}]"
        if not isinstance(entry, Mapping) or set(entry) - set(_ENTRY_KEYS):
            raise ModelConfigError(f"{w}: an entry is a mapping with keys {list(_ENTRY_KEYS)}, got {entry!r}")
        name = entry.get("name")
        if name not in ONLINE_EFFECT_NAMES:
            raise ModelConfigError(f"{w}: effect {name!r} cannot be tracked online (can: {list(ONLINE_EFFECT_NAMES)})")
        held = next((e for e in model.effects if e.name == name and e.location == str(entry.get("location"))), None)
        if held is not None:
            eff = held
        else:
            cfg = {k: entry[k] for k in ("name", "location", "variable", "reference", "parameters") if k in entry}
            cfg.setdefault("parameters", {})
            eff = effect_from_config(cfg, model.robot, where=w)
        if any(t.effect.name == eff.name and t.effect.location == eff.location for t in out):
            raise ModelConfigError(f"{w}: effect {eff.describe()} is listed twice")
        noise = _vector(entry.get("process_noise"), eff.n_params, DEFAULT_PROCESS_NOISE[name], w + ".process_noise")
        sigma = _vector(entry.get("initial_sigma"), eff.n_params, DEFAULT_INITIAL_SIGMA[name], w + ".initial_sigma")
        if np.any((noise == 0.0) & (sigma == 0.0)):  # issue 25: such a parameter could never move
            raise ModelConfigError(f"{w}: process_noise and initial_sigma are both 0 for parameter(s) "
                                   f"{np.flatnonzero((noise == 0.0) & (sigma == 0.0)).tolist()} of "
                                   f"{eff.describe()}: the filter could never move them; give one of them > 0")
        out.append(TrackedEffect(eff, noise, sigma))
    return out


def entries_from_flat(names: Sequence[str], process_noise: Sequence[float], initial_sigma: Sequence[float],
                      thermal_reference: float, where: str = "online_effects") -> list[dict[str, Any]] | None:
    """The flat form of a node parameter file -> ``online_effects`` entries for :func:`parse_online_config`.

    ``names`` are ``"<name>:<location>"`` (empty: None, the default set); ``process_noise`` [parameter unit /
    sqrt(s)] and ``initial_sigma`` [parameter unit] hold one number per effect (or are empty: defaults);
    a ``thermal_growth`` uses the temperature with ``thermal_reference`` [deg C] as its variable.

    Raises
    ------
    ModelConfigError
        A name without ``:``, or a list whose length is not the number of effects.
    """
    if not names:
        return None
    out: list[dict[str, Any]] = []
    for i, nl in enumerate(names):
        name, sep, loc = str(nl).partition(":")
        if not sep or not name or not loc:
            raise ModelConfigError(f"{where}[{i}]: expected '<effect name>:<location>', got {nl!r}")
        out.append({"name": name, "location": loc})
        if name == "thermal_growth":
            out[-1].update(variable="temperature", reference=float(thermal_reference))
    for key, vals in (("process_noise", process_noise), ("initial_sigma", initial_sigma)):
        if len(vals) and len(vals) != len(out):
            raise ModelConfigError(f"online_{key}: one number per entry of {where} ({len(out)}), got {len(vals)}")
        for e, v in zip(out, vals):
            e[key] = float(v)
    return out


@dataclass
class _Counts:
    points: int = 0
    gravity: int = 0
    jumps: int = 0
    waiting_for_temperature: int = 0
    temperatures: int = 0
    extra: dict[str, int] = field(default_factory=dict)


class OnlineEffects:
    """The augmented-state filter of the module docstring.

    Parameters
    ----------
    model : PPOEModel
        The diagnosed model: robot, perturbations (noise) and its effects (the tracked ones start there).
    tracked : list of TrackedEffect
        :func:`parse_online_config`.
    jump_probability : float or None
        NIS quantile above which a tracker point is taken as a jump of the tracked parameters (None: off).
    """

    def __init__(self, model: Any, tracked: Sequence[TrackedEffect], jump_probability: float | None = 1e-6) -> None:
        if not tracked:
            raise ModelConfigError("online effects: nothing to track (empty online_effects list)")
        self.model = model
        self.tree = KinematicTree(model.robot)
        self.tracked = list(tracked)
        keys = {(t.effect.name, t.effect.location) for t in self.tracked}
        self.fixed = [e for e in model.effects
                      if (e.name, e.location) not in keys and e.name != "tracker_registration"]
        self.registrations = {e.location: e.transform() for e in model.effects if e.name == "tracker_registration"}
        self.static_model = model.with_effects(self.fixed + [t.effect for t in self.tracked])
        self.slices: list[slice] = []
        k = 0
        for t in self.tracked:
            self.slices.append(slice(k, k + t.effect.n_params))
            k += t.effect.n_params
        self.theta = np.concatenate([t.effect.params for t in self.tracked])
        self.sigma0 = np.concatenate([t.initial_sigma for t in self.tracked])
        self.q = np.concatenate([t.process_noise for t in self.tracked])
        self.P = np.diag(self.sigma0 ** 2)
        self.stamp: float | None = None
        self.context: dict[str, Any] = {}
        self.jump_nis = None if not jump_probability else float(chi2.isf(jump_probability, 3))
        self.counts = _Counts()

    # -- state ---------------------------------------------------------------------
    @property
    def labels(self) -> list[str]:
        """``"<name>@<location>/<parameter>"`` of each state entry, in state order."""
        return [f"{t.effect.name}@{t.effect.location}/{p}" for t in self.tracked for p in t.effect.param_names]

    def effects(self) -> list[Effect]:
        """Every effect at the current estimate: the fixed ones and the tracked ones."""
        return self.fixed + [t.effect.with_params(self.theta[s]) for t, s in zip(self.tracked, self.slices)]

    def predict(self, stamp: float) -> None:
        """Random walk to ``stamp`` [s]: ``P += diag(q^2) dt`` (a stamp before the last one changes nothing)."""
        if self.stamp is not None and stamp > self.stamp:
            self.P = self.P + np.diag(self.q ** 2) * (stamp - self.stamp)
        if self.stamp is None or stamp > self.stamp:
            self.stamp = float(stamp)

    def set_temperature(self, stamp: float, value: float) -> None:
        """The latest temperature [deg C], the variable of tracked or fixed ``thermal_growth``."""
        if not np.isfinite(value):
            raise MeasurementError(f"online effects: temperature {value!r} at {stamp} is not finite")
        self.context["temperature"] = float(value)
        self.counts.temperatures += 1

    def needs_temperature(self) -> bool:
        """True while a thermal effect (variable temperature) waits for its first temperature."""
        return "temperature" not in self.context and any(
            getattr(e, "variable", None) == "temperature" for e in self.effects())

    # -- chain and Jacobians ----------------------------------------------------------
    def _chain(self, q: Mapping[str, float], effects: Sequence[Effect] | None = None
               ) -> tuple[dict, dict, dict, dict]:
        """Corrections of ``effects`` (default: current), corrected and nominal link poses."""
        nominal = self.tree.link_poses(q)
        dq, dxi = sum_effect_corrections(self.effects() if effects is None else effects, q, self.context, nominal)
        return dq, dxi, self.tree.link_poses(q, dq, dxi), nominal

    def _param_jacobian(self, q: Mapping[str, float], J_dq: Mapping[str, np.ndarray],
                        J_dxi: Mapping[str, np.ndarray], nominal: Mapping[str, np.ndarray]) -> np.ndarray:
        """Chain rule: chain Jacobian w.r.t. the insertions ``(J_dq: joint -> (m,), J_dxi: joint -> (m, 6))``
        times each tracked effect's basis -> (m, P)."""
        m = next(iter(J_dxi.values())).shape[0] if J_dxi else next(iter(J_dq.values())).shape[0]
        H = np.zeros((m, self.theta.shape[0]))
        for t, s in zip(self.tracked, self.slices):
            Bq, Bx = t.effect.basis(q, self.context, nominal)
            for k, b in Bq.items():
                if k in J_dq:
                    H[:, s] += np.outer(J_dq[k], b)
            for k, b in Bx.items():
                if k in J_dxi:
                    H[:, s] += J_dxi[k] @ b
        return H

    def point(self, q: Mapping[str, float], link: str, xyz: Any) -> tuple[np.ndarray, np.ndarray]:
        """Root-frame position (3,) of ``xyz`` on ``link`` at the current estimate and its Jacobian (3, P)."""
        dq, dxi, poses, nominal = self._chain(q)
        Jq, Jx = self.tree.point_jacobian(q, link, xyz, poses, dq, dxi)
        p_root = (poses[link] @ np.append(np.asarray(xyz, float), 1.0))[:3]
        return p_root, self._param_jacobian(q, Jq, Jx, nominal)

    def _point_cov_ppoe(self, q: Mapping[str, float], link: str, xyz: Any) -> np.ndarray:
        """PPOE covariance (3, 3) of the point in the root frame (eq. 18 at the link, moved to the point)."""
        T, cov = self.static_model.fk(q, self.model.robot.root, link, context=self.context)
        B = np.concatenate([T[:3, :3], -T[:3, :3] @ lie.hat3(np.asarray(xyz, float))], axis=1)
        return B @ cov @ B.T

    # -- measurement -------------------------------------------------------------------
    def registration(self, frame_id: str, topic: str) -> np.ndarray:
        """``T_tracker_root`` (4, 4) of a tracker frame from the model's ``tracker_registration`` (by frame or
        topic).

        Raises
        ------
        ModelConfigError
            The model holds no registration for it (the tilt and the registration cannot both be free).
        """
        for key in (frame_id, topic):
            if key in self.registrations:
                return self.registrations[key]
        raise ModelConfigError(
            f"online effects: no tracker_registration effect for tracker frame {frame_id!r} (topic {topic}) in the "
            f"model; known: {sorted(self.registrations)}")

    def update_point(self, stamp: float, q: Mapping[str, float], link: str, xyz: Any, p_tracker: Any,
                     T_tracker_root: np.ndarray, sigma: float) -> PointUpdate | None:
        """One tracker point ``p_tracker`` (3,) [m] of the reflector ``xyz`` on ``link``, noise ``sigma`` [m];
        None (counted in ``counts.waiting_for_temperature``) while a thermal effect has no temperature yet."""
        z = np.asarray(p_tracker, dtype=float).reshape(3)
        if not np.all(np.isfinite(z)):
            raise MeasurementError(f"online effects: tracker point {z} at {stamp} is not finite")
        if self.needs_temperature():
            self.counts.waiting_for_temperature += 1
            return None
        self.predict(stamp)
        p_root, J = self.point(q, link, xyz)
        R_tr = T_tracker_root[:3, :3]
        nu = z - (R_tr @ p_root + T_tracker_root[:3, 3])
        Rm = R_tr @ (self._point_cov_ppoe(q, link, xyz) + sigma ** 2 * np.eye(3)) @ R_tr.T
        self.counts.points += 1
        return self._kalman(nu, R_tr @ J, Rm)

    def update_gravity(self, stamp: float, q: Mapping[str, float], link: str, accel_link: Any,
                       sigma: float) -> PointUpdate | None:
        """One accelerometer at rest on ``link`` (specific force (3,) [m/s^2] in the link axes, noise ``sigma``
        [m/s^2]): the link's tilt, through :class:`~ppoe_core.estimation.direct_measurements.GravityObservation`
        (gravity is -z of the root); needs no registration.  None while waiting for a temperature."""
        z = np.asarray(accel_link, dtype=float).reshape(3)
        if not np.all(np.isfinite(z)):
            raise MeasurementError(f"online effects: acceleration {z} at {stamp} on {link} is not finite")
        if self.needs_temperature():
            self.counts.waiting_for_temperature += 1
            return None
        self.predict(stamp)
        root = self.model.robot.root
        T_link, J = self.tool_jacobian(q, root, link)
        obs = GravityObservation(sigma)
        Hs = obs.jacobian_state(T_link)
        _, cov_link = self.static_model.fk(q, root, link, context=self.context)
        self.counts.gravity += 1
        return self._kalman(z - obs.h(T_link), Hs @ J, obs.noise_cov + Hs @ cov_link @ Hs.T)

    def _kalman(self, nu: np.ndarray, H: np.ndarray, Rm: np.ndarray) -> PointUpdate:
        """EKF update with innovation ``nu`` (3,), ``H`` (3, P), noise ``Rm`` (3, 3); the jump rule first."""
        S = H @ self.P @ H.T + Rm
        nis = float(nu @ np.linalg.solve(S, nu))
        jump = self.jump_nis is not None and nis > self.jump_nis
        if jump:
            self.P = self.P + np.diag(self.sigma0 ** 2)
            S = H @ self.P @ H.T + Rm
            self.counts.jumps += 1
        K = np.linalg.solve(S, H @ self.P).T
        self.theta = self.theta + K @ nu
        IKH = np.eye(self.theta.shape[0]) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ Rm @ K.T  # Joseph form
        return PointUpdate(nu, nis, bool(jump))

    # -- outputs -------------------------------------------------------------------------
    def tool_pose(self, q: Mapping[str, float], base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
        """Fused ``T_base_tool`` (4, 4) at the current estimate and its covariance (6, 6) in the tool's tangent
        space: the PPOE covariance plus ``J P J^T`` of the parameters' uncertainty."""
        T, J = self.tool_jacobian(q, base, tool)
        _, cov = self.static_model.fk(q, base, tool, context=self.context)
        return T, cov + J @ self.P @ J.T

    def tool_jacobian(self, q: Mapping[str, float], base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
        """``T_base_tool`` (4, 4) at the current estimate and ``d xi_tool / d theta`` (6, P), right tangent at the
        tool (``xi_rel = xi_tool - Ad(T_base_tool^-1) xi_base`` when the base is not the root)."""
        dq, dxi, poses, nominal = self._chain(q)
        T = lie.inverse(poses[base]) @ poses[tool]
        Jq, Jx = self.tree.frame_jacobian(q, tool, poses, dq, dxi)
        J = self._param_jacobian(q, Jq, Jx, nominal)
        if base != self.model.robot.root:
            Jqb, Jxb = self.tree.frame_jacobian(q, base, poses, dq, dxi)
            J = J - lie.adjoint(lie.inverse(T)) @ self._param_jacobian(q, Jqb, Jxb, nominal)
        return T, J

    def sigmas(self) -> np.ndarray:
        """1-sigma of each tracked parameter (P,)."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))

    def effect_entries(self, z: float = 1.96) -> list[dict[str, Any]]:
        """Model-YAML ``effects`` entries of the tracked effects at the current estimate, with ``ci`` (the
        ``z``-sigma half width, 95 % by default) and ``sigma``."""
        out = []
        sig = self.sigmas()
        for t, s in zip(self.tracked, self.slices):
            entry = t.effect.with_params(self.theta[s]).to_config(ci=list(z * sig[s]))
            entry["sigma"] = {k: float(v) for k, v in zip(t.effect.param_names, sig[s])}
            out.append(entry)
        return out

    def model_yaml(self, model_raw: Mapping[str, Any]) -> dict[str, Any]:
        """``model_raw`` (the diagnosed model YAML as a mapping) with the tracked effects at their current estimate
        (:func:`replace_effects`)."""
        return replace_effects(model_raw, self.effect_entries())


def replace_effects(model_raw: Mapping[str, Any], entries: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``model_raw`` with its ``effects`` entries of the same name and location as ``entries`` replaced by them
    (others added at the end); everything else unchanged."""
    keys = {(e["name"], str(e["location"])) for e in entries}
    kept = [e for e in (model_raw.get("effects") or []) if (e.get("name"), str(e.get("location"))) not in keys]
    return {**dict(model_raw), "effects": kept + [dict(e) for e in entries]}
