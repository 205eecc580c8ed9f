"""What the catalogue did not explain: can held-out data predict the residual? (``unexplained_significant``)

The declared prior covariance is not asked (users declare loose priors).  Instead every block offers predictors of a
residual that the catalogue cannot express (:meth:`ResidualBlock.structure_columns`): the **configuration** (each
joint's Jacobian times a cubic B-spline basis of its own value: any smooth joint error, e.g. a cyclic transmission
error), **time** (a drift per bag) and, for pixels, the **image position** (a polynomial in the normalised image
coordinates per camera: intrinsics or distortion the model lacks).  At the final model, each predictor's columns are
added to the chosen effects' and both are cross-validated over the same folds (effects refitted per fold,
:mod:`linsys`): the residual is *systematic* when the predictor lowers the held-out whitened error by at least
:data:`MIN_SHARE` with a paired t (or signed-rank z) over robot poses of at least :data:`STRUCTURE_T`.  With the
significant predictors together, the held-out residual that remains is its **noise floor** (the data's own noise:
what nothing predicts; without a significant predictor, the held-out residual itself), and ``unexplained`` =
``sqrt(max(rms_after^2 - floor^2, 0))``.  The configuration is tested joint by joint (a spline in each joint's
value, so one joint's error is not diluted among all of them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ppoe_core.analysis.diagnose.linsys import BlockPart, LinearSystem
from ppoe_core.analysis.diagnose.results import StructureTest
from ppoe_core.analysis.diagnose.solver import Problem
from ppoe_core.analysis.diagnose.stats import paired_t, signed_rank_z
from ppoe_core.model.effects import Effect

__all__ = ["MIN_SHARE", "BlockStructure", "structure_tests", "heldout_residual"]

#: smallest held-out gain (share of the block's held-out whitened error) that counts as structure
MIN_SHARE = 0.05
#: paired t (or signed-rank z) over robot poses that makes structure significant: about ten predictors are tested
#: per block (one-sided 0.1 % each, about 1 % for all of them)
STRUCTURE_T = 3.0
#: relative ridge of the predictor fits (a flexible predictor must not explode where a fold's training data are thin)
RIDGE = 1e-3


@dataclass
class BlockStructure:
    """Per block: the tests of each predictor and the held-out raw residual rows with all predictors."""

    tests: list[StructureTest] = field(default_factory=list)
    residual: np.ndarray | None = None


def heldout_residual(sys: LinearSystem, cols: np.ndarray, unit_fold: np.ndarray, ridge: float = RIDGE) -> np.ndarray:
    """Held-out whitened residual of every component (NaN if not scored) with the columns ``cols`` refitted on
    each fold's training poses (relative ridge ``ridge`` on the column-scaled information)."""
    out = np.full(sys.e.size, np.nan)
    comp_fold = unit_fold[sys.unit]
    scale = np.sqrt(np.einsum("ij,ij->j", sys.G, sys.G))  # over all data: a thin column is not blown up in a fold
    for f in range(int(unit_fold.max()) + 1 if unit_fold.size else 0):
        fold = sys.fold(comp_fold != f)
        out[fold.idx] = fold.heldout(cols, fold.fit(cols, ridge=ridge, scale=scale))
    return out


def _per_unit(e: np.ndarray, unit: np.ndarray, n: int) -> np.ndarray:
    ok = np.isfinite(e)
    d = np.bincount(unit[ok], e[ok] ** 2, minlength=n)
    cnt = np.bincount(unit[ok], minlength=n)
    d[cnt == 0] = np.nan
    return d


def _only(e: np.ndarray, part: BlockPart) -> np.ndarray:
    """The components of ``part`` of ``e``; NaN elsewhere."""
    out = np.full(e.size, np.nan)
    out[part.start:part.stop] = e[part.start:part.stop]
    return out


def _augmented(sys: LinearSystem, part: BlockPart, X: np.ndarray) -> LinearSystem:
    """``sys`` with the predictor columns ``X`` (n_rows, d, m) of ``part``'s rows (whitened) appended."""
    G = np.zeros((sys.e.size, X.shape[-1]))
    G[part.start:part.stop] = (part.W @ X).reshape(-1, X.shape[-1])
    return replace(sys, G=np.concatenate([sys.G, G], axis=1))


def structure_tests(problem: Problem, effects: Sequence[Effect], unit_fold: np.ndarray,
                    min_t: float) -> dict[int, BlockStructure]:
    """The structure tests of every block at the fitted ``effects`` (module docstring)."""
    sys = problem.system(effects, effects, rewhiten=False)
    P = sys.n_columns
    base = heldout_residual(sys, np.arange(P), unit_fold)
    out: dict[int, BlockStructure] = {}
    for part in sys.parts:
        blk = problem.blocks[part.index]
        lin = blk.linearise([*problem.declared, *effects], (), {}, {}, chain=True)
        preds = {k: v for k, v in blk.structure_columns(lin).items() if v.shape[-1]}
        res = BlockStructure()
        d0 = _per_unit(_only(base, part), sys.unit, sys.n_units)
        significant = []
        for name, X in preds.items():
            e1 = heldout_residual(_augmented(sys, part, X), np.arange(P + X.shape[-1]), unit_fold)
            d1 = _per_unit(_only(e1, part), sys.unit, sys.n_units)
            ok = np.isfinite(d0) & np.isfinite(d1)
            diff = d0[ok] - d1[ok]
            total = float(d0[ok].sum())
            share = float(diff.sum() / total) if total > 0 else 0.0
            t, z = paired_t(diff), signed_rank_z(diff)
            res.tests.append(StructureTest(name, share, t, bool(share >= MIN_SHARE and max(t, z) >= min_t)))
            if res.tests[-1].significant:
                significant.append(X)
        if significant:  # the floor: what the significant predictors together leave
            X = np.concatenate(significant, axis=-1)
            res.residual = part.raw(heldout_residual(_augmented(sys, part, X), np.arange(P + X.shape[-1]),
                                                     unit_fold))
        out[part.index] = res
    return out
