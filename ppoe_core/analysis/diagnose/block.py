"""The residual block: one measurement kind as rows of residuals, their Jacobians and their nuisances.

A :class:`ResidualBlock` holds the rows of one measurement kind (tracker points, 6D poses, tag pixels, accelerometer
tilts, contact distances).  At the current model (declared + chosen effects with their values) it gives a
:class:`Linearisation`: the raw residual ``r`` (measured minus predicted, ``(n, d)``), the derivative ``J_c`` of the
*prediction* w.r.t. the parameters of every candidate effect ``c`` (through :meth:`Effect.basis` and the chain
Jacobians, or the sensor's own Jacobian for a sensor effect), the derivative ``N`` w.r.t. a correction of its
nuisance parameters (per *segment*: a tracker session's registration, a placement's tilt), and the two covariance
pieces of its noise model, the declared sensor noise ``S`` and the declared PPOE prior propagated to the
measurement ``Q`` (first order, paper eq. 18); the engine whitens with ``a^2 S + k^2 Q`` (:mod:`noise`).  So
``r(theta + dtheta, nu + dnu) ~= r - J dtheta - N dnu``.

Every row has a *segment* (its nuisance block, -1 for none), a *group* (bag or file, for leave-one-group-out), the
joint values that make it a robot *pose* (its cluster for cross-validation, paired tests and clustered
covariances), and the stop roles ``reg_mask`` / ``score_mask`` (rows that may define a held-out segment's nuisance,
rows that are scored there).  Adding a measurement kind is one new subclass.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree, LinkPoses

__all__ = ["Linearisation", "ResidualBlock", "chain_columns", "prior_covariance"]

#: corrected chains a block keeps (a refit evaluates a trial, then linearises or re-estimates the noise at the last
#: accepted point, or at the one before a rejected trial: the same poses again)
CHAIN_CACHE = 4


@dataclass
class Linearisation:
    """One block at the current model (not whitened).

    Attributes
    ----------
    r : ndarray (n, d)
        Measured minus predicted.
    J : list of ndarray (n, d, P_c)
        Derivative of the prediction w.r.t. each candidate's parameters (in the order of the candidates given).
    N : ndarray (n, d, k)
        Derivative of the prediction w.r.t. a correction of the row's segment nuisance (k = 0: none).
    S : ndarray (n, d, d)
        Declared sensor covariance.
    Q : ndarray (n, d, d)
        Declared PPOE prior covariance of the measurement (first order), zeros if none is declared.
    Jq : dict joint -> ndarray (n, d)
        Derivative of the prediction w.r.t. each joint's value (when the chain Jacobians were computed).
    """

    r: np.ndarray
    J: list[np.ndarray]
    N: np.ndarray
    S: np.ndarray
    Q: np.ndarray
    Jq: dict[str, np.ndarray] = field(default_factory=dict)


class ResidualBlock(ABC):
    """One measurement kind (module docstring).

    Attributes
    ----------
    kind : str
        ``tracker``, ``pose``, ``pixels``, ``imu``, ``contact``.
    dim : int
        Residual components per row.
    nuisance_dim : int
        Nuisance parameters per segment.
    unit : str
        Unit of the residual for reports (``m``, ``px``, ``rad``).
    """

    kind = ""
    dim = 0
    nuisance_dim = 0
    unit = ""

    def __init__(self, tree: KinematicTree, q: Mapping[str, np.ndarray], context: Mapping[str, Any],
                 segment: np.ndarray, segment_names: Sequence[str], group: np.ndarray, group_names: Sequence[str],
                 reg_mask: np.ndarray | None = None, score_mask: np.ndarray | None = None) -> None:
        self.tree = tree
        self.q = dict(q)
        self.context = dict(context)
        self.segment = np.asarray(segment, dtype=int)
        self.segment_names = list(segment_names)
        self.group = np.asarray(group, dtype=int)
        self.group_names = list(group_names)
        n = self.segment.size
        self.reg_mask = np.ones(n, dtype=bool) if reg_mask is None else np.asarray(reg_mask, dtype=bool)
        self.score_mask = np.ones(n, dtype=bool) if score_mask is None else np.asarray(score_mask, dtype=bool)
        self._nominal: dict[str, np.ndarray] | None = None
        self._bases: dict[str, tuple[dict[str, np.ndarray], dict[str, np.ndarray]]] = {}
        #: :meth:`KinematicTree.link_poses`' cache of the joint motions at ``q`` (the rows' joint values never change)
        self.motions: dict[str, np.ndarray] = {}
        self._chain_last: list[tuple[tuple, tuple[LinkPoses, dict, dict]]] = []

    def __len__(self) -> int:
        return int(self.segment.size)

    @property
    def nominal(self) -> dict[str, np.ndarray]:
        """Link poses of the nominal chain at the rows' joint values (the effects' bases are evaluated there)."""
        if self._nominal is None:
            self._nominal = self.tree.link_poses(self.q)
        return self._nominal

    def basis(self, effect: Effect) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """:meth:`Effect.basis` at the rows (on the nominal chain), computed once per effect (it does not depend on
        the parameters: the gravity loads of a compliance, the motion signs of a backlash)."""
        key = f"{effect.key}|{sorted(effect.options().items())}"
        if key not in self._bases:
            self._bases[key] = ({}, {}) if effect.sensor else effect.basis(self.q, self.context, self.nominal)
        return self._bases[key]

    def corrections(self, effects: Sequence[Effect]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The summed eq. 16 corrections ``(dq, dxi)`` of ``effects`` at the rows (cached bases times parameters)."""
        dq: dict[str, np.ndarray] = {}
        dxi: dict[str, np.ndarray] = {}
        for e in effects:
            if e.sensor:
                continue
            Bq, Bx = self.basis(e)
            for k, v in Bq.items():
                dq[k] = dq.get(k, 0.0) + v @ e.params
            for k, v in Bx.items():
                dxi[k] = dxi.get(k, 0.0) + v @ e.params
        return dq, dxi

    def pose_links(self) -> list[str] | None:
        """The links whose poses :meth:`chain` gives (None: the block does not use it)."""
        return None

    def chain(self, effects: Sequence[Effect]) -> tuple[LinkPoses, dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The link poses of :meth:`pose_links` on the chain corrected by ``effects`` and the corrections ``(dq,
        dxi)`` (:meth:`corrections`), kept for the last :data:`CHAIN_CACHE` models (effects and values)."""
        key = tuple((e.key, tuple(sorted(e.options().items())), np.asarray(e.params, dtype=float).tobytes())
                    for e in effects if not e.sensor)
        for k, (ck, out) in enumerate(self._chain_last):
            if ck == key:
                self._chain_last.insert(0, self._chain_last.pop(k))
                return out
        dq, dxi = self.corrections(effects)
        out = (self.tree.link_poses(self.q, dq, dxi, links=self.pose_links(), motions=self.motions), dq, dxi)
        self._chain_last = [(key, out), *self._chain_last[:CHAIN_CACHE - 1]]
        return out

    def columns(self, Jq: Mapping[str, np.ndarray], Jx: Mapping[str, np.ndarray], effect: Effect) -> np.ndarray:
        """:func:`chain_columns` of ``effect`` with its cached basis."""
        shape = (len(self), next(iter(Jq.values())).shape[1] if Jq else (next(iter(Jx.values())).shape[1]
                                                                            if Jx else self.dim))
        return chain_columns(Jq, Jx, self.basis(effect), effect.n_params, shape)

    def chain_joints(self, candidates: Sequence[Effect], pert: Mapping[str, np.ndarray], jnoise: Mapping[str, float],
                     chain: bool) -> set[str] | None:
        """The joints whose chain Jacobians :meth:`linearise` needs: those the ``candidates``' bases insert at and
        the declared prior's (``pert``, ``jnoise``); None (all) with ``chain``."""
        if chain:
            return None
        out = set(pert) | set(jnoise)
        for c in candidates:
            Bq, Bx = self.basis(c)
            out.update(Bq, Bx)
        return out

    @property
    def n_segments(self) -> int:
        return len(self.segment_names)

    # -- model ---------------------------------------------------------------------------------------
    @abstractmethod
    def linearise(self, effects: Sequence[Effect], candidates: Sequence[Effect],
                  pert: Mapping[str, np.ndarray], jnoise: Mapping[str, float], chain: bool = False) -> Linearisation:
        """:class:`Linearisation` at the model ``effects`` (declared + chosen, with values) for ``candidates``;
        ``pert`` / ``jnoise``: the declared perturbation covariances and joint noise (for ``Q``); ``chain``: compute
        the chain Jacobians (``Jq``) even without candidates or prior."""

    def residual(self, effects: Sequence[Effect]) -> np.ndarray:
        """Raw residual (n, d) at ``effects`` (measured minus predicted)."""
        return self.linearise(effects, (), {}, {}).r

    def apply_nuisance(self, step: np.ndarray) -> None:
        """Apply a nuisance correction ``step`` (n_segments, nuisance_dim) to the linearisation point (a block
        whose nuisances are linear keeps none: nothing to do)."""
        return None

    def reset_nuisance(self, effects: Sequence[Effect]) -> None:
        """Re-estimate the nuisance linearisation point at ``effects`` (closed form where there is one)."""
        return None

    def nuisance_state(self) -> Any:
        """A copy of the nuisance linearisation point (to undo a rejected solver step)."""
        return None

    def set_nuisance_state(self, state: Any) -> None:
        """Restore a :meth:`nuisance_state`."""
        return None

    # -- selection -----------------------------------------------------------------------------------
    @abstractmethod
    def candidates(self) -> list[Effect]:
        """Catalogue effects (zero parameters) at every plausible location this measurement sees."""

    def camera_mounts(self) -> dict[str, str]:
        """Camera mount joint -> camera optical frame of the cameras this block sees (none by default)."""
        return {}

    def chain_links(self) -> list[str]:
        """The links whose chains this block measures (group moves run along the path to each)."""
        return []

    def structure_columns(self, lin: Linearisation) -> dict[str, np.ndarray]:
        """Derivatives ``(n, d, m)`` of predictors of a residual the catalogue cannot express, by name
        (``configuration``, ``time``, ``image position``): the significance test of what is left."""
        return {}

    def error_norm(self, r: np.ndarray) -> np.ndarray:
        """Per-row error magnitude (n,) for reports (default: the Euclidean norm of the raw residual)."""
        return np.linalg.norm(r, axis=-1)

    def report_groups(self) -> dict[str, np.ndarray]:
        """Row masks of sub-reports (e.g. per camera); default: none."""
        return {}


def chain_columns(Jq: Mapping[str, np.ndarray], Jx: Mapping[str, np.ndarray],
                  basis: tuple[Mapping[str, np.ndarray], Mapping[str, np.ndarray]], n_params: int,
                  shape: tuple[int, int]) -> np.ndarray:
    """Chain Jacobians (``Jq``: joint -> (n, d), ``Jx``: joint -> (n, d, 6)) times an effect's ``basis``
    (:meth:`Effect.basis` on the nominal link poses: ``(dq basis: joint -> (n, P), dxi basis: joint -> (n, 6, P))``):
    the derivative (n, d, P) of a measurement of shape ``shape`` = (n, d) w.r.t. the effect's parameters."""
    out = np.zeros((*shape, n_params))
    Bq, Bx = basis
    for k, b in Bq.items():
        if k in Jq:
            out += Jq[k][:, :, None] * np.broadcast_to(b, (shape[0], n_params))[:, None, :]
    for k, b in Bx.items():
        if k in Jx:
            out += Jx[k] @ np.broadcast_to(b, (shape[0], 6, n_params))
    return out


def prior_covariance(Jq: Mapping[str, np.ndarray], Jx: Mapping[str, np.ndarray], pert: Mapping[str, np.ndarray],
                     jnoise: Mapping[str, float], shape: tuple[int, int]) -> np.ndarray:
    """First-order PPOE covariance (n, d, d) of a measurement with chain Jacobians ``Jq`` / ``Jx``: ``pert`` =
    joint -> 6x6 covariance of the insertion ``xi_j`` (tangent right after the joint's origin), ``jnoise`` = joint
    -> 1-sigma along the joint axis (paper eq. 18 to first order)."""
    n, d = shape
    C = np.zeros((n, d, d))
    for jn, S in pert.items():
        if jn in Jx:
            C += Jx[jn] @ np.asarray(S, dtype=float) @ np.swapaxes(Jx[jn], -1, -2)
    for jn, s in jnoise.items():
        if jn in Jq:
            C += float(s) ** 2 * Jq[jn][:, :, None] * Jq[jn][:, None, :]
    return C
