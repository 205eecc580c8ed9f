"""The selection routine (:mod:`selection`) on a problem linearised elsewhere: whitened rows, free (nuisance)
columns, the columns of every candidate effect and a cluster per row.

Used where the caller linearises its own measurements -- the online loop's drift naming
(:mod:`ppoe_core.analysis.drift_naming`: the filter's whitened innovations, the tracked parameters free, the
catalogue's candidates through the filter's chain rule).  The problem is held fixed (no nonlinear refit: the
caller's linearisation is the model), so forward steps, group moves and the backward pass run exactly as in
``ppoe diagnose`` on a system that does not change.  Per chosen term, the drop-one statistics say what it carries:
the relative held-out gain of the final model over the model without it, and the paired t of the per-cluster gains.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ppoe_core.analysis.diagnose.crossval import Linearised
from ppoe_core.analysis.diagnose.linsys import BlockPart, LinearSystem, NuisanceSet
from ppoe_core.analysis.diagnose.selection import SelectionOptions, select
from ppoe_core.analysis.diagnose.stats import paired_t
from ppoe_core.analysis.diagnose.terms import Catalogue, Term, model_key
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["LinearProblem", "ChosenTerm", "LinearSelection", "select_linear"]


@dataclass
class LinearProblem:
    """A linearised problem (module docstring).

    Attributes
    ----------
    e : ndarray (n,)
        Whitened residual components.
    free : ndarray (n, P)
        Columns free in every fit (the caller's own parameters; eliminated, never selected).
    candidates : list of Effect
        Candidate effects (zero parameters; several at one place: the one with the most parameters is kept).
    columns : list of ndarray (n, P_c)
        Whitened Jacobian of each candidate's parameters.
    cluster : ndarray (n,) int
        Cluster of each component (a robot pose, a measurement time): the unit of the cross-validation.
    fold : ndarray (U,) int
        Fold of each cluster (clusters numbered 0..U-1).
    tree : KinematicTree
    chains : measured links (group moves run along the path from the root to each)
    """

    e: np.ndarray
    free: np.ndarray
    candidates: list[Effect]
    columns: list[np.ndarray]
    cluster: np.ndarray
    fold: np.ndarray
    tree: KinematicTree
    chains: Sequence[str] = field(default_factory=tuple)


@dataclass
class ChosenTerm:
    """A selected term: the candidate's index in :attr:`LinearProblem.candidates`, the parameters it frees (indices
    into the effect's parameters), the effect of just those parameters (zero values), the drop-one relative
    held-out gain and paired t."""

    candidate: int
    comps: tuple[int, ...]
    effect: Effect
    gain: float
    t: float


@dataclass
class LinearSelection:
    """The chosen terms, the selection's steps and refusals, and the held-out error per cluster before / after."""

    chosen: list[ChosenTerm]
    steps: list[dict]
    rejected: dict[str, str]
    d_before: np.ndarray
    d_after: np.ndarray


class _Fixed:
    """The refitter of a fixed linearisation: nothing to refit, the linearisation always holds."""

    def __init__(self, lin: Linearised) -> None:
        self.lin = lin

    def relinearise(self, model: tuple[Term, ...]) -> Linearised:
        return self.lin

    def confirm(self, model: tuple[Term, ...], predicted: float) -> bool:
        return True


def _system(p: LinearProblem, catalogue: Catalogue, source: list[int]) -> LinearSystem:
    """The stacked system: the catalogue's columns (from the candidates ``source`` maps to), the free columns as
    one nuisance segment spanning every component."""
    n = p.e.size
    blocks = [np.asarray(p.columns[i], dtype=float).reshape(n, -1) for i in source]
    G = np.concatenate(blocks, axis=1) if blocks else np.zeros((n, 0))
    stops = np.cumsum([0, *(b.shape[1] for b in blocks)])
    cols = [slice(int(a), int(b)) for a, b in zip(stops[:-1], stops[1:])]
    unit = np.asarray(p.cluster, dtype=int)
    nuisances = []
    if p.free.size:
        nuisances.append(NuisanceSet(np.arange(n), np.asarray(p.free, dtype=float).reshape(n, -1),
                                     np.zeros(n, dtype=int), 0, 1))
    ones = np.ones(n, dtype=bool)
    return LinearSystem(np.asarray(p.e, dtype=float), G, cols, unit, int(unit.max()) + 1 if n else 0,
                        np.zeros(n, dtype=int), ones, ones, nuisances, [BlockPart(0, 0, n, 1, np.ones((n, 1, 1)))])


def select_linear(problem: LinearProblem, options: SelectionOptions | None = None) -> LinearSelection:
    """Stepwise selection (:func:`~ppoe_core.analysis.diagnose.selection.select`) on ``problem`` (module
    docstring)."""
    catalogue = Catalogue(problem.tree, problem.candidates, problem.chains)
    where = {(e.name, e.location, str(getattr(e, "variable", "")), e.n_params): i
             for i, e in enumerate(problem.candidates)}
    source = [where[(e.name, e.location, str(getattr(e, "variable", "")), e.n_params)] for e in catalogue.effects]
    sys = _system(problem, catalogue, source)
    lin = Linearised(sys, catalogue, np.zeros(sys.n_columns), np.asarray(problem.fold, dtype=int))
    sel = select(catalogue, _Fixed(lin), options or SelectionOptions())
    final = lin.heldout(sel.model)
    chosen = []
    for t in sel.model:
        without = lin.heldout(model_key(x for x in sel.model if x != t))
        ok = np.isfinite(without) & np.isfinite(final)
        total = float(without[ok].sum())
        diff = without[ok] - final[ok]
        gain = float(diff.sum()) / total if total > 0 else 0.0
        chosen.append(ChosenTerm(source[t.cand], t.comps, catalogue.effect(t), gain, paired_t(diff)))
    return LinearSelection(chosen, sel.steps, sel.rejected, sel.d_before, final)
