"""The one solver: all residual blocks as one whitened least-squares problem, nuisances eliminated, nonlinear refit.

:class:`Problem` holds the blocks, the declared effects and covariance, each block's noise scales
(:mod:`noise`) and the robot pose (unit) of every row.  :meth:`Problem.system` linearises every block at a model
and stacks the whitened components into a :class:`~ppoe_core.analysis.diagnose.linsys.LinearSystem` (columns of the
given candidates, nuisance columns per segment).  :meth:`Problem.refit` is the nonlinear fit of a set of effects:
Gauss-Newton with Levenberg-Marquardt damping on the full chain, each step the reduced (Schur-eliminated) normal
equations of that system, the nuisance steps applied to each block's linearisation point (a registration
``T0 <- T0 Exp(d)``), until the parameter steps are below 1 % of their standard deviations.  An optional robust
loss (``soft_l1``: weights ``1 / sqrt(1 + (e / c)^2)`` of the whitened residual, iteratively reweighted) damps gross
outliers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock
from ppoe_core.analysis.diagnose.linsys import BlockPart, LinearSystem, NuisanceSet, solve_scaled
from ppoe_core.analysis.diagnose.noise import NoiseScales, whitening
from ppoe_core.model.effects import Effect

__all__ = ["Problem", "Refit", "assign_units", "global_groups"]

#: convergence: every parameter step below this many of its standard deviations
STEP_TOL = 1e-2
#: convergence: the relative change of the cost below this (rounding and the second-order error of the eliminated
#: nuisances), and a step no worse than this is taken
REL_COST_TOL = 1e-6


def global_groups(blocks: Sequence[ResidualBlock]) -> tuple[list[str], list[np.ndarray]]:
    """The union of the blocks' group (bag / file) names, and every block's rows in that numbering."""
    names: list[str] = []
    for b in blocks:
        names.extend(g for g in b.group_names if g not in names)
    return names, [np.array([names.index(b.group_names[g]) for g in b.group], dtype=int) for b in blocks]


def assign_units(blocks: Sequence[ResidualBlock], groups: Sequence[np.ndarray], decimals: int = 7) -> list[np.ndarray]:
    """Robot pose (unit) of every row of every block: rows of one group (``groups``: per block, the global group of
    each row) with the same values of the joints all blocks carry (rounded to ``decimals``) are one pose (a tracker
    stop and the images taken at it)."""
    common = set.intersection(*[set(b.q) for b in blocks]) if blocks else set()
    joints = sorted(j for j in common if blocks[0].tree.robot.joints[j].independent)
    keys = []
    for k, (b, g) in enumerate(zip(blocks, groups)):
        cols = [np.round(np.asarray(b.q[j], dtype=float), decimals) for j in joints]
        own = [] if cols else [np.full(len(b), float(k)), np.arange(len(b), dtype=float)]
        keys.append(np.column_stack([g.astype(float), *own, *cols]))
    allk = np.concatenate(keys) if keys else np.zeros((0, 1))
    _, inv = np.unique(allk, axis=0, return_inverse=True)
    inv = np.asarray(inv).reshape(-1)
    out, k = [], 0
    for b in blocks:
        out.append(inv[k:k + len(b)])
        k += len(b)
    return out


@dataclass
class Refit:
    """Result of :meth:`Problem.refit`: the effects with their fitted values, the final whitened cost, Gauss-Newton
    iterations and whether the steps converged."""

    effects: list[Effect]
    cost: float
    iterations: int
    converged: bool


@dataclass
class BlockState:
    """Per block: noise scales, the whitening of its rows, the declared covariance pieces (S, Q) it was computed
    from, and its last linearisation."""

    scales: NoiseScales = field(default_factory=NoiseScales)
    W: np.ndarray | None = None
    S: np.ndarray | None = None
    Q: np.ndarray | None = None
    lin: Linearisation | None = None


class Problem:
    """Blocks, declared model and noise (module docstring).

    Parameters
    ----------
    blocks : residual blocks (one per measurement kind present)
    declared : effects of the model file (part of every prediction)
    pert, jnoise : declared perturbation covariances (joint -> 6x6) and joint noise (joint -> 1-sigma)
    loss : ``"linear"`` or ``"soft_l1"``; ``loss_scale``: its scale in whitened units
    """

    def __init__(self, blocks: Sequence[ResidualBlock], declared: Sequence[Effect] = (),
                 pert: Mapping[str, np.ndarray] | None = None, jnoise: Mapping[str, float] | None = None,
                 loss: str = "linear", loss_scale: float = 3.0) -> None:
        self.blocks = list(blocks)
        self.declared = list(declared)
        self.pert, self.jnoise = dict(pert or {}), dict(jnoise or {})
        self.group_names, self.groups = global_groups(self.blocks)
        self.units = assign_units(self.blocks, self.groups)
        self.n_units = int(max((u.max() for u in self.units if u.size), default=-1)) + 1
        self.state = [BlockState() for _ in self.blocks]
        self.loss, self.loss_scale = loss, loss_scale
        self.whitening_count = 0  #: how many times the whitening was recomputed (a Jacobian is valid in its own)

    # -- linear system -------------------------------------------------------------------------------
    def system(self, effects: Sequence[Effect], candidates: Sequence[Effect], rewhiten: bool = True) -> LinearSystem:
        """Whitened components of every block at ``effects`` (chosen, with values; the declared ones are added)
        with the columns of ``candidates``.  ``rewhiten``: recompute the whitening from the blocks' noise scales
        and the prior at this point (else keep the last one)."""
        model = [*self.declared, *effects]
        parts: dict[str, list[np.ndarray]] = {k: [] for k in ("e", "unit", "group", "reg", "score")}
        nuisances, partsb, offset = [], [], 0
        if rewhiten or any(st.W is None for st in self.state):
            self.whitening_count += 1
        sizes = [c.n_params for c in candidates]
        ends = np.cumsum([0, *sizes])
        G = np.empty((sum(len(b) * b.dim for b in self.blocks), int(ends[-1])))  # every block's rows written in
        for i, (b, st, unit) in enumerate(zip(self.blocks, self.state, self.units)):
            fresh = rewhiten or st.W is None
            lin = b.linearise(model, candidates, self.pert if fresh else {}, self.jnoise if fresh else {})
            if fresh:
                st.S, st.Q = lin.S, lin.Q
                st.W = whitening(lin.S, lin.Q, st.scales)
            st.lin = lin
            n, d = lin.r.shape
            W = st.W
            assert W is not None
            w = self._robust_weights(np.einsum("nij,nj->ni", W, lin.r))
            Wr = W * w[:, None, None]
            parts["e"].append(np.einsum("nij,nj->ni", Wr, lin.r).reshape(-1))
            if lin.J:
                np.matmul(Wr, np.concatenate(lin.J, axis=2), out=G[offset:offset + n * d].reshape(n, d, -1))
            parts["unit"].append(np.repeat(unit, d))
            parts["group"].append(np.repeat(self.groups[i], d))
            parts["reg"].append(np.repeat(b.reg_mask, d))
            parts["score"].append(np.repeat(b.score_mask, d))
            k = lin.N.shape[2]
            has = np.repeat(b.segment >= 0, d)
            if k and has.any():
                N = (Wr @ lin.N).reshape(n * d, k)
                nuisances.append(NuisanceSet(offset + np.flatnonzero(has), N[has], np.repeat(b.segment, d)[has], i,
                                             b.n_segments))
            partsb.append(BlockPart(i, offset, offset + n * d, d, Wr))
            offset += n * d
        cols = [slice(int(ends[i]), int(ends[i + 1])) for i in range(len(sizes))]
        cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}
        return LinearSystem(cat["e"], G, cols, cat["unit"].astype(int), self.n_units, cat["group"].astype(int),
                            cat["reg"].astype(bool), cat["score"].astype(bool), nuisances, partsb)

    def _robust_weights(self, e: np.ndarray) -> np.ndarray:
        """Per-row IRLS weight (square root) of the robust loss at whitened residual rows ``e`` (n, d)."""
        if self.loss == "linear":
            return np.ones(e.shape[0])
        z = np.sum(e ** 2, axis=1) / e.shape[1] / self.loss_scale ** 2
        return (1.0 + z) ** -0.25

    # -- nonlinear fit -------------------------------------------------------------------------------
    def cost(self, effects: Sequence[Effect]) -> float:
        """Whitened sum of squares at ``effects`` with the current whitening and nuisance points."""
        model = [*self.declared, *effects]
        total = 0.0
        for b, st in zip(self.blocks, self.state):
            r = b.residual(model)
            assert st.W is not None
            e = np.einsum("nij,nj->ni", st.W, r)
            w = self._robust_weights(e)
            total += float(np.sum((e * w[:, None]) ** 2))
        return total

    def whitened(self, effects: Sequence[Effect]) -> np.ndarray:
        """The whitened residual components of every block at ``effects`` (stacked as in :meth:`system`), with the
        current whitening and nuisance points (no robust weights)."""
        model = [*self.declared, *effects]
        parts = []
        for b, st in zip(self.blocks, self.state):
            assert st.W is not None
            parts.append(np.einsum("nij,nj->ni", st.W, b.residual(model)).reshape(-1))
        return np.concatenate(parts) if parts else np.zeros(0)

    def refit(self, effects: Sequence[Effect], max_iterations: int = 20,
              jacobian: LinearSystem | None = None) -> Refit:
        """Nonlinear Gauss-Newton / Levenberg-Marquardt fit of ``effects`` (start: their current values) and the
        nuisances (module docstring); the whitening is the one of the last :meth:`system` call.

        The Jacobian is kept while it serves (a chord Gauss-Newton: the effects are small corrections, their
        Jacobian barely changes; the same minimum for a fraction of the cost): the iterations evaluate the residuals
        only and linearise again when a step does not lower the cost.  ``jacobian``: the columns of ``effects`` (in
        order) and the nuisance columns from an earlier linearisation near this point (the selection's), used from
        the start.  With a robust loss every point is linearised (its weights change with the residual)."""
        effects = list(effects)
        fresh = any(st.W is None for st in self.state)
        if jacobian is None or fresh or self.loss != "linear":
            jacobian = self.system(effects, effects, rewhiten=fresh)
            sys = jacobian
        else:
            sys = jacobian.with_residual(self.whitened(effects))
        return self._iterate(effects, sys, max_iterations)

    def _trial(self, jacobian: LinearSystem, trial: list[Effect]) -> LinearSystem:
        """The system at ``trial``: its residuals with ``jacobian``'s columns (a robust loss: linearised there)."""
        if self.loss != "linear":
            return self.system(trial, trial, rewhiten=False)
        return jacobian.with_residual(self.whitened(trial))

    def _iterate(self, effects: list[Effect], sys: LinearSystem, max_iterations: int) -> Refit:
        """The damped Gauss-Newton iterations of :meth:`refit` from the system ``sys`` at ``effects`` (its columns
        the Jacobian kept).  A step that does not lower the cost with a kept Jacobian linearises at the current
        point; with a fresh one, it raises the damping."""
        full = sys.full()
        cost = full.ee  # the cost with the nuisances at their best (linearly), at these effects
        lam, iterations, converged, kept = 0.0, 0, False, True
        for iterations in range(1, max_iterations + 1):  # noqa: B007 - the count is returned
            H = full.H.copy()
            if lam:
                H[np.diag_indices_from(H)] *= 1.0 + lam
            step = solve_scaled(H, full.b)
            if not lam and step.size and _small(step, full.H):
                converged = True  # the undamped step is below the tolerance: evaluating it would change nothing
                break
            saved = [b.nuisance_state() for b in self.blocks]
            for i, d in sys.nuisance_step(step, np.arange(step.size)).items():
                self.blocks[i].apply_nuisance(d)
            trial = _stepped(effects, step)
            sys_t = self._trial(sys, trial)
            full_t = sys_t.full()
            cost_t = full_t.ee
            gain = (cost - cost_t) / max(cost, 1e-300)
            if gain >= -REL_COST_TOL:  # not worse (up to rounding): take it
                small = gain <= REL_COST_TOL or ((bool(lam) or not step.size) and _small(step, full.H))
                effects, sys, full, cost = trial, sys_t, full_t, cost_t
                lam, kept = (lam / 10.0 if lam > 1e-6 else 0.0), True
                if small:
                    converged = True
                    break
                continue
            for b, st in zip(self.blocks, saved):
                b.set_nuisance_state(st)
            if kept and self.loss == "linear":  # the kept Jacobian is off here: linearise at this point
                sys, kept = self.system(effects, effects, rewhiten=False), False
                # the cost of this point in the new linearisation: the nuisances' linear best depends on their
                # Jacobian, so the kept one's cost is not what the fresh trials are to be compared with
                full = sys.full()
                cost = full.ee
                continue
            lam = max(10.0 * lam, 1e-3)
            if lam > 1e8:
                break
        return Refit(effects, cost, iterations, converged)


def _small(step: np.ndarray, H: np.ndarray) -> bool:
    """Whether every parameter step is below :data:`STEP_TOL` of its standard deviation (``H``: the information)."""
    if not step.size:
        return True
    sd = np.sqrt(np.maximum(np.diag(np.linalg.pinv(H)), 1e-300))
    return bool(np.all(np.abs(step) <= STEP_TOL * sd + 1e-15))


def _stepped(effects: Sequence[Effect], step: np.ndarray) -> list[Effect]:
    """The effects with ``step`` added to their parameters (in order)."""
    out, i = [], 0
    for e in effects:
        out.append(e.with_params(e.params + step[i:i + e.n_params]))
        i += e.n_params
    return out
