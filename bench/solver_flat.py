"""The engine's problem as one flat least-squares function ``x -> r(x), J(x)`` (solver comparison,
``bench/bench_solver.py``): a general-purpose solver (scipy, GTSAM) sees the same whitened residuals as the engine's
:meth:`~ppoe_core.analysis.diagnose.solver.Problem.refit`.

Unknowns ``x = [theta; d]``: the effects' parameters, then every nuisance segment's correction ``d`` applied to the
block's nuisance point at the start (a registration ``T0 Exp(d)``).  The Jacobian w.r.t. ``d`` is the blocks'
right-perturbation Jacobian at the current point (exact at ``d = 0``, first-order near it: the solvers use exact
residuals for their steps, so they reach the same minimum).  The whitening is fixed at the start (as in the engine's
refit).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core.analysis.diagnose.solver import Problem
from ppoe_core.model.effects import Effect


class FlatProblem:
    """``problem`` with the effects ``effects`` as one function of ``x`` (module docstring)."""

    def __init__(self, problem: Problem, effects: Sequence[Effect]) -> None:
        self.problem, self.effects = problem, list(effects)
        sys = problem.system(self.effects, self.effects)  # the whitening, once
        self.sizes = [e.n_params for e in self.effects]
        self.P = int(sum(self.sizes))
        self.start = [b.nuisance_state() for b in problem.blocks]
        self.segments = [(ns.block, ns.n_segments, ns.N.shape[1]) for ns in sys.nuisances]
        self.K = int(sum(n * k for _, n, k in self.segments))

    def x0(self) -> np.ndarray:
        return np.concatenate([*(e.params for e in self.effects), np.zeros(self.K)])

    def split(self, x: np.ndarray) -> tuple[list[Effect], dict[int, np.ndarray]]:
        out, i = [], 0
        for e in self.effects:
            out.append(e.with_params(x[i:i + e.n_params]))
            i += e.n_params
        steps = {}
        for block, n, k in self.segments:
            steps[block] = x[i:i + n * k].reshape(n, k)
            i += n * k
        return out, steps

    def evaluate(self, x: np.ndarray, jac: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residual (n,) and its Jacobian (n, P + K) at ``x``."""
        effects, steps = self.split(np.asarray(x, dtype=float))
        for b, st in zip(self.problem.blocks, self.start):
            b.set_nuisance_state(st)
        for block, d in steps.items():
            self.problem.blocks[block].apply_nuisance(d)
        sys = self.problem.system(effects, effects if jac else [], rewhiten=False)
        if not jac:
            return sys.e, None
        J = np.zeros((sys.e.size, self.P + self.K))
        J[:, :self.P] = -sys.G
        off = self.P
        for ns in sys.nuisances:
            k = ns.N.shape[1]
            for s in range(ns.n_segments):
                m = ns.seg == s
                J[ns.idx[m], off + k * s:off + k * (s + 1)] = -ns.N[m]
            off += ns.n_segments * k
        return sys.e, J

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x, jac=False)[0]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        J = self.evaluate(x)[1]
        assert J is not None
        return J
