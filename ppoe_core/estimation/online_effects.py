"""Online estimation of drifting effects (issue 11 item 1, issue 22; the paper's future work): an augmented-state EKF.

The state is the stacked parameter vector ``theta`` of a few effects of the catalogue
(:mod:`ppoe_core.model.effects`: per-placement ``base_tilt``, ``thermal_growth`` with the temperature as its
variable, a ``gravity_compliance``, ``camera_extrinsics``, ...) with covariance ``P``; every other effect of the
diagnosed model stays fixed.  Between measurements each parameter is a random walk,
``P += diag(q^2) dt`` with ``q`` the process noise in *parameter unit per sqrt(s)*: the rule for how fast a
parameter may drift.

Every measurement (:class:`~ppoe_core.estimation.online_models.OnlineRow`) is one or more measurement models on a
pose ``X = T_ref_link`` of the robot (:mod:`ppoe_core.estimation.online_models`: tracker points, accelerometers, tag
pixels, 6D poses, contact planes).  ``X`` is the chain of eq. 16 with the effects' corrections
(``Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))``, :meth:`KinematicTree.link_poses`) at the current
estimate, and the update is::

    nu = z ominus h(X),   H = H_X J_theta,   S = H P H^T + M R M^T + H_X Sigma_ppoe H_X^T,   K = P H^T S^-1

with ``H_X = dh/dxi`` of the model, ``J_theta = d xi_rel / d theta`` the chain Jacobian of ``T_ref_link``
(:meth:`KinematicTree.frame_jacobian` of both frames) times the effects' exact bases (:meth:`Effect.basis`), and
``Sigma_ppoe`` the PPOE covariance of ``T_ref_link`` (paper eq. 18): the model's random errors act as measurement
noise.  A placement change (the base moved onto another floor) is a jump, not a drift: with ``jump_probability``
set, an innovation whose NIS exceeds that chi-square quantile (of the measurement's dimension) re-opens the
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
from ppoe_core.estimation.online_config import (
    DEFAULT_INITIAL_SIGMA,
    DEFAULT_PROCESS_NOISE,
    ONLINE_EFFECT_NAMES,
    TrackedEffect,
    entries_from_flat,
    parse_online_config,
)
from ppoe_core.estimation.online_models import OnlineRow, imu_parts, tracker_parts
from ppoe_core.model.effects import Effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree

__all__ = [
    "DEFAULT_INITIAL_SIGMA",
    "DEFAULT_PROCESS_NOISE",
    "ONLINE_EFFECT_NAMES",
    "FrameChain",
    "OnlineEffects",
    "OnlineUpdate",
    "PartLinearization",
    "PointUpdate",
    "TrackedEffect",
    "entries_from_flat",
    "parse_online_config",
    "replace_effects",
]


@dataclass
class OnlineUpdate:
    """Outcome of one update.

    Attributes
    ----------
    innovation : ndarray (m,)
        ``z ominus h`` at the estimate before the update [the measurement's units].
    nis : float
        ``nu^T S^-1 nu`` with the covariance before the update.
    jump : bool
        The jump rule re-opened the covariance.
    dim : int
        ``m``, the chi-square degrees of freedom of ``nis``.
    nis_monitor : float
        The NIS the drift monitor tests: ``nis``, or after a jump the NIS with the re-opened covariance (a jump of
        the tracked effects that they can explain is not a drift they fail to explain).
    """

    innovation: np.ndarray
    nis: float
    jump: bool
    dim: int = 3
    nis_monitor: float = float("nan")


#: the name of :class:`OnlineUpdate` before issue 22 (tracker points only)
PointUpdate = OnlineUpdate


@dataclass
class FrameChain:
    """``T_ref_link`` (4, 4) on the chain with effects and its Jacobians w.r.t. the eq. 16 insertions, right tangent
    at the link: ``Jq`` joint -> (6,), ``Jx`` joint -> (6, 6); ``nominal`` the link poses without effects (the
    effects' bases are taken there)."""

    T: np.ndarray
    Jq: dict[str, np.ndarray]
    Jx: dict[str, np.ndarray]
    nominal: dict[str, np.ndarray]


@dataclass
class PartLinearization:
    """One :class:`~ppoe_core.estimation.online_models.FramePart` at an estimate: residual (m,), ``H_X`` (m, 6),
    noise covariance (m, m) (sensor plus the PPOE covariance of ``T_ref_link``) and the frame chain."""

    residual: np.ndarray
    H_state: np.ndarray
    noise: np.ndarray
    chain: FrameChain


@dataclass
class _Counts:
    points: int = 0
    gravity: int = 0
    updates: int = 0
    jumps: int = 0
    waiting_for_temperature: int = 0
    temperatures: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)


class OnlineEffects:
    """The augmented-state filter of the module docstring.

    Parameters
    ----------
    model : PPOEModel
        The diagnosed model: robot, perturbations (noise) and its effects (the tracked ones start there).
    tracked : list of TrackedEffect
        :func:`parse_online_config`.
    jump_probability : float or None
        NIS tail probability above which a measurement is taken as a jump of the tracked parameters (None: off).
    """

    def __init__(self, model: Any, tracked: Sequence[TrackedEffect], jump_probability: float | None = 1e-6) -> None:
        if not tracked:
            raise ModelConfigError("online effects: nothing to track (empty online_effects list)")
        self.model = model
        self.tree = KinematicTree(model.robot)
        self.tracked: list[TrackedEffect] = []
        keys = {(t.effect.name, t.effect.location) for t in tracked}
        self.fixed = [e for e in model.effects
                      if (e.name, e.location) not in keys and e.name != "tracker_registration"]
        self.registrations = {e.location: e.transform() for e in model.effects if e.name == "tracker_registration"}
        self.theta = np.zeros(0)
        self.P = np.zeros((0, 0))
        self.sigma0 = np.zeros(0)
        self.q = np.zeros(0)
        self.slices: list[slice] = []
        self.add_effects(tracked)
        #: the effects of the diagnosed model as the run began (the tracked ones at their initial values)
        self.diagnosed_effects: list[Effect] = list(self._static.effects)
        self.stamp: float | None = None
        self.context: dict[str, Any] = {}
        #: the first temperature seen [deg C]: the diagnosed model holds there (reference of a named thermal effect)
        self.reference_temperature: float | None = None
        self.jump_probability = jump_probability or None
        self._gates: dict[int, float] = {}
        self.counts = _Counts()

    # -- state ---------------------------------------------------------------------
    @property
    def labels(self) -> list[str]:
        """``"<name>@<location>/<parameter>"`` of each state entry, in state order."""
        return [f"{t.effect.name}@{t.effect.location}/{p}" for t in self.tracked for p in t.effect.param_names]

    @property
    def static_model(self) -> Any:
        """The diagnosed model with the tracked effects at their initial values (its covariance is the noise)."""
        return self._static

    def effects(self, theta: np.ndarray | None = None) -> list[Effect]:
        """Every effect at the estimate ``theta`` (default: the current one): the fixed ones and the tracked ones."""
        th = self.theta if theta is None else theta
        return self.fixed + [t.effect.with_params(th[s]) for t, s in zip(self.tracked, self.slices)]

    def add_effects(self, new: Sequence[TrackedEffect], P_new: np.ndarray | None = None) -> None:
        """Append tracked effects to the state (their ``effect.params`` the initial estimate; covariance ``P_new``, or
        their initial sigma squared), e.g. an effect the drift monitor named.  A fixed effect of the same name and
        location leaves the fixed set (its value is the new effect's start)."""
        keys = {(t.effect.name, t.effect.location) for t in self.tracked}
        for t in new:
            if (t.effect.name, t.effect.location) in keys:
                raise ModelConfigError(f"online effects: {t.effect.describe()} is tracked already")
        n0 = self.theta.shape[0]
        k = n0
        for t in new:
            self.tracked.append(t)
            self.slices.append(slice(k, k + t.effect.n_params))
            k += t.effect.n_params
        add_keys = {(t.effect.name, t.effect.location) for t in new}
        self.fixed = [e for e in self.fixed if (e.name, e.location) not in add_keys]
        self.theta = np.concatenate([self.theta] + [t.effect.params for t in new])
        self.sigma0 = np.concatenate([self.sigma0] + [t.initial_sigma for t in new])
        self.q = np.concatenate([self.q] + [t.process_noise for t in new])
        P = np.zeros((k, k))
        P[:n0, :n0] = self.P
        P[n0:, n0:] = np.diag(self.sigma0[n0:] ** 2) if P_new is None else P_new
        self.P = P
        self._static = self.model.with_effects(self.fixed + [t.effect for t in self.tracked])

    def predict(self, stamp: float) -> None:
        """Random walk to ``stamp`` [s]: ``P += diag(q^2) dt`` (a stamp before the last one changes nothing)."""
        if self.stamp is not None and stamp > self.stamp:
            self.P = self.P + np.diag(self.q ** 2) * (stamp - self.stamp)
        if self.stamp is None or stamp > self.stamp:
            self.stamp = float(stamp)
        self.context["time"] = self.stamp

    def set_temperature(self, stamp: float, value: float) -> None:
        """The latest temperature [deg C], the variable of tracked or fixed ``thermal_growth``."""
        if not np.isfinite(value):
            raise MeasurementError(f"online effects: temperature {value!r} at {stamp} is not finite")
        self.context["temperature"] = float(value)
        if self.reference_temperature is None:
            self.reference_temperature = float(value)
        self.counts.temperatures += 1

    def needs_temperature(self) -> bool:
        """True while a thermal effect (variable temperature) waits for its first temperature."""
        return "temperature" not in self.context and any(
            getattr(e, "variable", None) == "temperature" for e in self.effects())

    # -- chain and Jacobians ----------------------------------------------------------
    def frame_chain(self, q: Mapping[str, float], ref: str, link: str, effects: Sequence[Effect] | None = None,
                    context: Mapping[str, Any] | None = None) -> FrameChain:
        """``T_ref_link`` with ``effects`` (default: at the current estimate) and its insertion Jacobians: the
        right perturbation of ``T_ref_link`` is ``xi_link - Ad(T_ref_link^-1) xi_ref`` (both of the root)."""
        ctx = self.context if context is None else context
        nominal = self.tree.link_poses(q)
        dq, dxi = sum_effect_corrections(self.effects() if effects is None else effects, q, ctx, nominal)
        poses = self.tree.link_poses(q, dq, dxi)
        T = lie.inverse(poses[ref]) @ poses[link]
        Jq, Jx = self.tree.frame_jacobian(q, link, poses, dq, dxi)
        if ref != self.model.robot.root:
            Ad = lie.adjoint(lie.inverse(T))
            Jqb, Jxb = self.tree.frame_jacobian(q, ref, poses, dq, dxi)
            Jq, Jx = _minus(Jq, Jqb, Ad), _minus(Jx, Jxb, Ad)
        return FrameChain(T, Jq, Jx, nominal)

    def pose(self, q: Mapping[str, float], ref: str, link: str, effects: Sequence[Effect] | None = None,
             context: Mapping[str, Any] | None = None) -> np.ndarray:
        """``T_ref_link`` (4, 4) on the chain with ``effects`` (default: at the current estimate), no Jacobians."""
        ctx = self.context if context is None else context
        nominal = self.tree.link_poses(q)
        dq, dxi = sum_effect_corrections(self.effects() if effects is None else effects, q, ctx, nominal)
        poses = self.tree.link_poses(q, dq, dxi)
        return lie.inverse(poses[ref]) @ poses[link]

    def param_jacobian(self, q: Mapping[str, float], chain: FrameChain, effects: Sequence[Effect] | None = None,
                       context: Mapping[str, Any] | None = None) -> np.ndarray:
        """Chain rule: the chain's insertion Jacobians times each effect's basis -> (6, sum of n_params); default
        ``effects``: the tracked ones (the state order)."""
        effs = [t.effect for t in self.tracked] if effects is None else list(effects)
        ctx = self.context if context is None else context
        cols = []
        for e in effs:
            Bq, Bx = e.basis(q, ctx, chain.nominal)
            Hc = np.zeros((6, e.n_params))
            for k, b in Bq.items():
                if k in chain.Jq:
                    Hc += np.outer(chain.Jq[k], b)
            for k, b in Bx.items():
                if k in chain.Jx:
                    Hc += chain.Jx[k] @ b
            cols.append(Hc)
        return np.concatenate(cols, axis=1) if cols else np.zeros((6, 0))

    def point(self, q: Mapping[str, float], link: str, xyz: Any) -> tuple[np.ndarray, np.ndarray]:
        """Root-frame position (3,) of ``xyz`` on ``link`` at the current estimate and its Jacobian (3, P)."""
        ch = self.frame_chain(q, self.model.robot.root, link)
        p = np.asarray(xyz, dtype=float)
        R = ch.T[:3, :3]
        return ch.T[:3, :3] @ p + ch.T[:3, 3], np.hstack([R, -R @ lie.hat3(p)]) @ self.param_jacobian(q, ch)

    def linearize(self, row: OnlineRow, effects: Sequence[Effect] | None = None) -> list[PartLinearization]:
        """Every part of ``row`` at ``effects`` (default: the current estimate), in the row's context."""
        out = []
        ctx = {**self.context, **row.context}
        for part in row.parts:
            ch = self.frame_chain(row.q, part.ref, part.link, effects, ctx)
            obs = part.obs
            Hs, M = obs.jacobian_state(ch.T), obs.jacobian_noise(ch.T)
            if Hs is None or M is None:
                raise MeasurementError(f"{obs.name}: the online filter needs analytic Jacobians")
            _, cov = self._static.fk(row.q, part.ref, part.link, context=ctx)
            noise = M @ obs.noise_cov @ M.T + Hs @ cov @ Hs.T
            out.append(PartLinearization(np.asarray(obs.residual(part.z, obs.h(ch.T)), float), Hs, noise, ch))
        return out

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

    def update(self, row: OnlineRow, kind: str = "") -> OnlineUpdate | None:
        """One measurement (all its parts in one update); None (counted in ``counts.waiting_for_temperature``) while
        a thermal effect has no temperature yet.  ``kind`` names the measurement kind in ``counts.by_kind``."""
        if self.needs_temperature():
            self.counts.waiting_for_temperature += 1
            return None
        self.predict(row.stamp)
        row.context = {**self.context, **row.context}
        lins = self.linearize(row)
        nu = np.concatenate([lin.residual for lin in lins])
        H = np.concatenate([lin.H_state @ self.param_jacobian(row.q, lin.chain) for lin in lins])
        m = nu.shape[0]
        Rm = np.zeros((m, m))
        i = 0
        for lin in lins:
            k = lin.residual.shape[0]
            Rm[i:i + k, i:i + k] = lin.noise
            i += k
        self.counts.updates += 1
        if kind:
            self.counts.by_kind[kind] = self.counts.by_kind.get(kind, 0) + 1
        return self._kalman(nu, H, Rm)

    def update_point(self, stamp: float, q: Mapping[str, float], link: str, xyz: Any, p_tracker: Any,
                     T_tracker_root: np.ndarray, sigma: float) -> OnlineUpdate | None:
        """One tracker point ``p_tracker`` (3,) [m] of the reflector ``xyz`` on ``link``, noise ``sigma`` [m];
        None while a thermal effect has no temperature yet."""
        z = np.asarray(p_tracker, dtype=float).reshape(3)
        if not np.all(np.isfinite(z)):
            raise MeasurementError(f"online effects: tracker point {z} at {stamp} is not finite")
        parts = tracker_parts(self.model.robot.root, link, xyz, z, T_tracker_root, sigma, "tracker point")
        up = self.update(OnlineRow(float(stamp), "tracker", dict(q), parts), "tracker")
        self.counts.points += up is not None
        return up

    def update_gravity(self, stamp: float, q: Mapping[str, float], link: str, accel_link: Any,
                       sigma: float) -> OnlineUpdate | None:
        """One accelerometer at rest on ``link`` (specific force (3,) [m/s^2] in the link axes, noise ``sigma``
        [m/s^2]): the link's tilt, through :class:`~ppoe_core.estimation.direct_measurements.GravityObservation`
        (gravity is -z of the root); needs no registration.  None while waiting for a temperature."""
        z = np.asarray(accel_link, dtype=float).reshape(3)
        if not np.all(np.isfinite(z)):
            raise MeasurementError(f"online effects: acceleration {z} at {stamp} on {link} is not finite")
        parts = imu_parts(self.model.robot.root, link, z, sigma, f"accelerometer on {link}")
        up = self.update(OnlineRow(float(stamp), "imu", dict(q), parts), "imu")
        self.counts.gravity += up is not None
        return up

    def _jump_gate(self, dim: int) -> float | None:
        if self.jump_probability is None:
            return None
        if dim not in self._gates:
            self._gates[dim] = float(chi2.isf(self.jump_probability, dim))
        return self._gates[dim]

    def _kalman(self, nu: np.ndarray, H: np.ndarray, Rm: np.ndarray) -> OnlineUpdate:
        """EKF update with innovation ``nu`` (m,), ``H`` (m, P), noise ``Rm`` (m, m); the jump rule first."""
        S = H @ self.P @ H.T + Rm
        nis = float(nu @ np.linalg.solve(S, nu))
        gate = self._jump_gate(nu.shape[0])
        jump = gate is not None and nis > gate
        nis_monitor = nis
        if jump:
            self.P = self.P + np.diag(self.sigma0 ** 2)
            S = H @ self.P @ H.T + Rm
            nis_monitor = float(nu @ np.linalg.solve(S, nu))
            self.counts.jumps += 1
        K = np.linalg.solve(S, H @ self.P).T
        self.theta = self.theta + K @ nu
        IKH = np.eye(self.theta.shape[0]) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ Rm @ K.T  # Joseph form
        return OnlineUpdate(nu, nis, bool(jump), int(nu.shape[0]), nis_monitor)

    # -- outputs -------------------------------------------------------------------------
    def tool_pose(self, q: Mapping[str, float], base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
        """Fused ``T_base_tool`` (4, 4) at the current estimate and its covariance (6, 6) in the tool's tangent
        space: the PPOE covariance plus ``J P J^T`` of the parameters' uncertainty."""
        T, J = self.tool_jacobian(q, base, tool)
        _, cov = self._static.fk(q, base, tool, context=self.context)
        return T, cov + J @ self.P @ J.T

    def tool_jacobian(self, q: Mapping[str, float], base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
        """``T_base_tool`` (4, 4) at the current estimate and ``d xi_tool / d theta`` (6, P), right tangent at the
        tool (``xi_rel = xi_tool - Ad(T_base_tool^-1) xi_base`` when the base is not the root)."""
        ch = self.frame_chain(q, base, tool)
        return ch.T, self.param_jacobian(q, ch)

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


def _minus(J_link: Mapping[str, np.ndarray], J_ref: Mapping[str, np.ndarray], Ad: np.ndarray) -> dict[str, np.ndarray]:
    """``J_link - Ad J_ref`` per joint (a joint missing on one side contributes zero)."""
    out = dict(J_link)
    for k, v in J_ref.items():
        out[k] = out[k] - Ad @ v if k in out else -(Ad @ v)
    return out
