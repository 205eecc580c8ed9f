"""Cross-validation of models at one linearisation: folds over robot poses or bags, held-out errors, identifiability.

:func:`assign_folds` puts every robot pose (unit) in a fold: leave-one-group-out (``groups``: one fold per bag or
file) or ``k`` seeded folds over the poses of each group (``stops``).  :class:`Linearised` is the stacked system of
all blocks at the current model with the columns of *every* candidate (:mod:`linsys`), its folds precomputed; a
model (:class:`~ppoe_core.analysis.diagnose.terms.Term` s) is scored by :meth:`Linearised.heldout`: per unit, the
held-out sum of squared whitened residuals (``-2 log`` of the held-out Gaussian likelihood up to a constant, the noise
scales fixed).  Terms of the current model that a candidate model leaves out are held at zero (their values at the
linearisation point are undone); the others are refitted on each fold's training units.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ppoe_core.analysis.diagnose.linsys import Fold, FoldStack, LinearSystem, solve_scaled
from ppoe_core.analysis.diagnose.terms import Catalogue, Term
from ppoe_core.errors import PpoeError

__all__ = ["assign_folds", "Linearised", "Identifiability"]

_NONE, _NONE_F = np.zeros(0, dtype=int), np.zeros(0)


def _scaled_quotient(h: np.ndarray, g: np.ndarray, ridge: float = 1e-10) -> np.ndarray:
    """:func:`~ppoe_core.analysis.diagnose.linsys.solve_scaled` of many one-column systems ``h x = g`` (h, g: (m,))
    at once, the same arithmetic elementwise: ``x = (g / d) / (h / d / d + ridge) / d`` with ``d = sqrt(h)``, 0
    where ``h`` is not positive (no information)."""
    d = np.sqrt(np.maximum(h, 0.0))
    act = d > 0.0
    da = np.where(act, d, 1.0)
    x = (g / da) / (h / da / da + ridge) / da
    return np.where(act, x, 0.0)


def assign_folds(unit_group: np.ndarray, mode: str, folds: int, seed: int) -> tuple[str, np.ndarray]:
    """Fold of every unit: ``mode`` ``auto`` (``groups`` with >= 3 groups, else ``stops``), ``groups`` (one fold per
    group) or ``stops`` (``folds`` seeded folds over the units of each group).  Returns the mode used and the fold
    index per unit.

    Raises
    ------
    PpoeError
        ``groups`` with fewer than 2 groups, or fewer units than folds.
    """
    groups = np.unique(unit_group)
    if mode == "auto":
        mode = "groups" if groups.size >= 3 else "stops"
    if mode == "groups":
        if groups.size < 2:
            raise PpoeError("diagnose: leave-one-group-out needs at least 2 bags/files")
        return mode, np.searchsorted(groups, unit_group)
    if unit_group.size < folds:
        raise PpoeError(f"diagnose: {unit_group.size} robot poses, fewer than the {folds} folds")
    rng = np.random.default_rng(seed)
    out = np.zeros(unit_group.size, dtype=int)
    start = 0
    for g in groups:
        idx = np.flatnonzero(unit_group == g)
        out[idx] = (rng.permutation(idx.size) + start) % folds
        start += idx.size
    return mode, out


@dataclass
class Identifiability:
    """Whether a model's columns can be told apart: the condition number of the column-scaled reduced information,
    the largest share of a new column's information that the nuisances absorb, and a reason if not."""

    ok: bool
    condition: float
    absorbed: float
    reason: str = ""


class Linearised:
    """The system of every candidate at the current model, with its folds (module docstring).

    Parameters
    ----------
    sys : LinearSystem
        Columns of all catalogue candidates (in catalogue order).
    catalogue : Catalogue
    theta : ndarray (C,)
        Current values of every column (the chosen terms' values; zero elsewhere).
    unit_fold : ndarray (U,)
        Fold of every unit (:func:`assign_folds`).
    """

    def __init__(self, sys: LinearSystem, catalogue: Catalogue, theta: np.ndarray, unit_fold: np.ndarray) -> None:
        self.sys, self.catalogue, self.theta = sys, catalogue, np.asarray(theta, dtype=float)
        n_folds = int(unit_fold.max()) + 1 if unit_fold.size else 0
        comp_fold = unit_fold[sys.unit]
        self.folds: list[Fold] = sys.folds(comp_fold, n_folds)
        self.stack = FoldStack(self.folds)
        self.all = sys.full()
        self.raw_diag = np.einsum("ij,ij->j", sys.G, sys.G)
        self.n_units = sys.n_units
        comp_block = np.zeros(sys.e.size, dtype=int)
        for k, part in enumerate(sys.parts):
            comp_block[part.start:part.stop] = k
        self.n_blocks = max(len(sys.parts), 1)
        #: per scored held-out component, its (block, unit) cell
        self._cell = comp_block[self.stack.idx] * self.n_units + self.stack.unit
        self._nonzero = self.theta != 0.0
        self._any_value = bool(self._nonzero.any())
        self._cache: dict[tuple, np.ndarray] = {}
        self._idf: dict[tuple, Identifiability] = {}
        #: the linearisation where every effect is zero (None: this is it): a new term must be identifiable there too
        self.nominal: Linearised | None = None

    def columns(self, model: Sequence[Term]) -> np.ndarray:
        """Column indices of a model's terms (in term order)."""
        cols = self.sys.cols
        return np.array([cols[t.cand].start + c for t in model for c in t.comps], dtype=int)

    def _fixed(self, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Columns with a current value that ``cols`` does not free, and the steps that undo their values."""
        if not self._any_value:
            return _NONE, _NONE_F
        m = self._nonzero.copy()
        m[cols] = False
        fixed = np.flatnonzero(m)
        return fixed, -self.theta[fixed]

    def heldout(self, model: Sequence[Term]) -> np.ndarray:
        """Per unit (U,), the held-out sum of squared whitened residuals of ``model`` (NaN: not scored)."""
        key = tuple(sorted(model))
        if key in self._cache:
            return self._cache[key]
        d = np.nansum(self.heldout_blocks(key), axis=0)
        d[np.all(np.isnan(self.heldout_blocks(key)), axis=0)] = np.nan
        self._cache[key] = d
        return d

    def heldout_blocks(self, model: Sequence[Term]) -> np.ndarray:
        """Per block and unit (B, U), the held-out sum of squared whitened residuals of ``model`` (NaN: the unit has
        no scored component in that block)."""
        key = ("blocks", *sorted(model))
        if key not in self._cache:
            cols = self.columns(tuple(sorted(model)))
            r = self.stack.heldout(cols, *self._fixed(cols))
            size = self.n_blocks * self.n_units
            d = np.bincount(self._cell, r * r, minlength=size)
            d[np.bincount(self._cell, minlength=size) == 0] = np.nan
            self._cache[key] = d.reshape(self.n_blocks, self.n_units)
        return self._cache[key]

    def heldout_residual(self, model: Sequence[Term]) -> np.ndarray:
        """Held-out whitened residual of every component (n,) (NaN where not scored)."""
        cols = self.columns(model)
        out = np.full(self.sys.e.size, np.nan)
        out[self.stack.idx] = self.stack.heldout(cols, *self._fixed(cols))
        return out

    def fit(self, model: Sequence[Term]) -> tuple[np.ndarray, np.ndarray, float]:
        """All-data linear fit: the model's values (current + step, in column order), their covariance
        ``s^2 H^-1`` and ``s^2`` (reduced SSR per degree of freedom)."""
        cols = self.columns(model)
        step, s2 = self._fit_step(cols)
        H = self.all.H[cols[:, None], cols]
        cov = s2 * np.linalg.pinv(H) if cols.size else np.zeros((0, 0))
        return self.theta[cols] + step, cov, s2

    def term_fit(self, model: Sequence[Term], term: Term) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`fit` of ``model`` plus ``term``, of ``term``'s components only: their values and standard
        deviations (the variance from the Schur complement of ``model``'s information, whose inverse is computed
        once per model)."""
        m_cols, t_cols = self.columns(model), self.columns([term])
        cols = np.concatenate([m_cols, t_cols])
        step, s2 = self._fit_step(cols)
        H = self.all.H
        S = H[t_cols[:, None], t_cols]
        if m_cols.size:
            HmT = H[m_cols[:, None], t_cols]
            S = S - HmT.T @ self._model_pinv(m_cols) @ HmT
        var = s2 * np.diag(np.linalg.pinv(S))
        return (self.theta[cols] + step)[m_cols.size:], np.sqrt(np.maximum(var, 0.0))

    def _fit_step(self, cols: np.ndarray) -> tuple[np.ndarray, float]:
        """The all-data step on ``cols`` (the other columns' values undone) and ``s^2``."""
        fixed, fv = self._fixed(cols)
        step = self.all.fit(cols, fixed, fv)
        b = self.all.b[cols] - (self.all.H[cols[:, None], fixed] @ fv if fixed.size else 0.0)
        ee = self.all.ee - 2.0 * float(self.all.b[fixed] @ fv) + float(fv @ self.all.H[fixed[:, None], fixed] @ fv) \
            if fixed.size else self.all.ee
        ssr = max(ee - float(step @ b), 0.0)
        dof = max(self.sys.e.size - cols.size - self._n_nuisance(), 1)
        return step, ssr / dof

    def _model_pinv(self, cols: np.ndarray) -> np.ndarray:
        """``pinv`` of the information of the columns ``cols`` (cached per model)."""
        key = ("pinv", *cols.tolist())
        if key not in self._cache:  # one per model: every candidate of a round asks for it
            self._cache[key] = np.linalg.pinv(self.all.H[cols[:, None], cols])
        return self._cache[key]

    def ssr(self, model: Sequence[Term]) -> float:
        """In-sample reduced sum of squares of ``model`` (screening; cached per model)."""
        key = ("ssr", *sorted(model))
        if key not in self._cache:
            self._cache[key] = np.array(self._ssr(model))
        return float(self._cache[key])

    def _ssr(self, model: Sequence[Term]) -> float:
        cols = self.columns(model)
        fixed, fv = self._fixed(cols)
        b = self.all.b[cols] - (self.all.H[cols[:, None], fixed] @ fv if fixed.size else 0.0)
        ee = self.all.ee - 2.0 * float(self.all.b[fixed] @ fv) + float(fv @ self.all.H[fixed[:, None], fixed] @ fv) \
            if fixed.size else self.all.ee
        step = solve_scaled(self.all.H[cols[:, None], cols], b)
        return max(ee - float(step @ b), 0.0)

    def added_ssr(self, model: Sequence[Term], terms: Sequence[Term]) -> np.ndarray:
        """In-sample reduced sum of squares of ``model`` plus each of ``terms`` (one each), for screening: the
        Schur complement of ``model``'s fit (the other columns' current values held as for ``model`` alone)."""
        cols = self.columns(model)
        fixed, fv = self._fixed(cols)
        H = self.all.H
        base = self.ssr(model)
        out = np.full(len(terms), base)
        in_model = np.zeros(H.shape[0], dtype=bool)
        in_model[cols] = True
        own = [np.unique(c[~in_model[c]]) for c in (self.columns([t]) for t in terms)]
        need = np.unique(np.concatenate(own)) if own else np.zeros(0, dtype=int)
        if not need.size:
            return out
        idx = np.concatenate([need, cols])  # only the rows and columns the terms need (not all C x C)
        b = self.all.b[idx] - (H[idx[:, None], fixed] @ fv if fixed.size else 0.0)
        bU, bc = b[:need.size], b[need.size:]
        S, g = H[need[:, None], need], bU
        if cols.size:
            P = self._model_pinv(cols)
            HcU = H[cols[:, None], need]
            S = S - HcU.T @ P @ HcU
            g = bU - HcU.T @ (P @ bc)
        pos = np.zeros(H.shape[0], dtype=int)
        pos[need] = np.arange(need.size)
        one = np.array([c.size == 1 for c in own], dtype=bool)
        if one.any():  # one new column: solve_scaled's arithmetic elementwise
            i = pos[np.array([c[0] for c, o in zip(own, one) if o], dtype=int)]
            out[one] = base - g[i] * _scaled_quotient(np.diag(S)[i], g[i])
        for k, c in enumerate(own):
            if c.size > 1:
                i = pos[c]
                out[k] = base - float(g[i] @ solve_scaled(S[i[:, None], i], g[i]))
        return out

    def _n_nuisance(self) -> int:
        return int(sum(ns.n_segments * ns.N.shape[1] for ns in self.sys.nuisances))

    def identifiable(self, model: Sequence[Term], new: Sequence[Term], max_condition: float,
                     max_absorbed: float) -> Identifiability:
        """Whether ``new`` can be told apart from the nuisances and from ``model`` (all data; cached)."""
        key = (tuple(sorted(model)), tuple(new), max_condition, max_absorbed)
        if key not in self._idf:
            self._idf[key] = self._identifiable(model, new, max_condition, max_absorbed)
        return self._idf[key]

    def _condition(self, m_cols: np.ndarray, n_cols: np.ndarray) -> float:
        """Condition number of the new columns ``n_cols`` next to the model's ``m_cols``, the model's own
        conditioning left out: the column-scaled information of the new columns and of an orthonormal basis of the
        model's column space (``[[I, R], [R^T, M]]``, ``R`` their correlations).  Without a model it is the condition
        number of the new columns' scaled information; a new column correlated ``rho`` with the model gets
        ``(1 + rho) / (1 - rho)``, as when the model is one well-conditioned column.  A model whose own columns
        drifted near-dependent at a new linearisation (intrinsics k1 k2 k3 next to the camera poses) must not block
        every addition."""
        H = self.all.H
        Hnn = H[n_cols[:, None], n_cols]
        d = np.sqrt(np.maximum(np.diag(Hnn), 1e-300))
        M = Hnn / d[:, None] / d[None, :]
        if m_cols.size:
            key = ("model_basis", *m_cols.tolist())
            if key not in self._cache:  # one per model: every candidate of a round is checked against it
                Hmm = H[m_cols[:, None], m_cols]
                dm = np.sqrt(np.maximum(np.diag(Hmm), 1e-300))
                lam, V = np.linalg.eigh(Hmm / dm[:, None] / dm[None, :])
                keep = lam > 1e-12 * max(float(lam[-1]), 1e-300)
                self._cache[key] = V[:, keep] / np.sqrt(lam[keep]) / dm[:, None]  # W: W^T Hmm W = I
            W = self._cache[key]
            R = W.T @ H[m_cols[:, None], n_cols] / d[None, :]
            r, p = R.shape
            if p == 1 and r:  # [[I, R], [R^T, m]]: eigenvalues 1 (r - 1 times) and those of [[1, |R|], [|R|, m]]
                m, rho = float(M[0, 0]), float(np.linalg.norm(R[:, 0]))
                half, root = 0.5 + 0.5 * m, math.hypot(0.5 - 0.5 * m, rho)  # (no overflow: a reduced information
                ev2 = [half - root, half + root, *([1.0] if r > 1 else [])]  # rounded below zero scales to huge m)
                return max(ev2) / min(ev2) if min(ev2) > 0 and math.isfinite(max(ev2)) else math.inf
            full = np.zeros((r + p, r + p))
            full[np.arange(r), np.arange(r)] = 1.0
            full[:r, r:], full[r:, :r], full[r:, r:] = R, R.T, M
            M = full
        ev = np.linalg.eigvalsh(M)
        return float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf

    def _identifiable(self, model: Sequence[Term], new: Sequence[Term], max_condition: float,
                      max_absorbed: float) -> Identifiability:
        new_cols = self.columns(new)
        raw = self.raw_diag[new_cols]
        if np.any(raw <= 1e-18 * max(float(self.raw_diag.max(initial=0.0)), 1e-300)):
            return Identifiability(False, math.inf, 1.0, "does not act on the measurements")
        absorbed = float(np.max(self.sys.absorbed()[new_cols])) if new_cols.size else 0.0
        if absorbed > max_absorbed:
            return Identifiability(False, math.inf, absorbed, "not separable from the nuisances (registration)")
        cond = self._condition(self.columns(model), new_cols)
        if cond > max_condition:
            return Identifiability(False, cond, absorbed,
                                   f"not separable from the effects already chosen (condition {cond:.2g})")
        if self.nominal is not None and not self.nominal.identifiable((), new, max_condition, max_absorbed).ok:
            # a direction the measurements cannot see where the effects are zero, which other parameters' values
            # only seem to make visible (a link_error's rotation about the axis through a reflector becomes a shift
            # of it next to a translation: Exp([rho, omega]) moves by V(omega) rho): not a property of the robot
            return Identifiability(False, math.inf, absorbed, "not identifiable where the effects are zero (seen "
                                   "only through the values of other parameters)")
        return Identifiability(True, cond, absorbed)
