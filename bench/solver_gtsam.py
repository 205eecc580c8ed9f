"""The engine's problem as a GTSAM factor graph (solver comparison, ``bench/bench_solver.py``).

Variables: one ``Vector`` per effect (its parameters) and one ``Vector`` per nuisance segment (its correction
``d``, :class:`solver_flat.FlatProblem`).  Factors: one ``CustomFactor`` per robot pose (its rows of every block;
keys: the effects and the segments the rows belong to), unit noise (the residuals are whitened), no robust loss.
Residuals and Jacobians are those of :meth:`FlatProblem.evaluate`, computed once per linearisation point for all
factors (cached on the current values).  ``gtsam`` is imported only here (optional).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from solver_flat import FlatProblem


class _Cache:
    """Residuals and Jacobian of the problem at the last values asked for."""

    def __init__(self, flat: FlatProblem, keys: list[int], sizes: list[int]) -> None:
        self.flat, self.keys, self.sizes = flat, keys, sizes
        self.x_key = b""
        self.r = np.zeros(0)
        self.J = np.zeros((0, 0))

    def x(self, values: Any) -> np.ndarray:
        return np.concatenate([values.atVector(k) for k in self.keys]) if self.keys else np.zeros(0)

    def update(self, values: Any) -> None:
        x = self.x(values)
        if x.tobytes() != self.x_key:
            r, J = self.flat.evaluate(x)
            assert J is not None
            self.x_key, self.r, self.J = x.tobytes(), r, J


def _variables(flat: FlatProblem) -> list[int]:
    """Size of every variable: the effects', then each segment's."""
    return [*flat.sizes, *(k for _, n, k in flat.segments for _ in range(n))]


def solve_gtsam(flat: FlatProblem, max_iterations: int = 100) -> dict[str, Any]:
    """Levenberg-Marquardt on the factor graph of ``flat`` (module docstring), from :meth:`FlatProblem.x0`.

    Returns ``x``, ``cost`` (``sum r^2 / 2``), ``iterations`` and ``cov_theta`` (P, P): the marginal covariance of
    the effect parameters (``gtsam.Marginals``, nuisances marginalised).
    """
    import gtsam

    sizes = _variables(flat)
    keys = [gtsam.symbol("x", i) for i in range(len(sizes))]
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    cache = _Cache(flat, keys, sizes)
    values = gtsam.Values()
    x0 = flat.x0()
    for i, k in enumerate(keys):
        values.insert(k, np.asarray(x0[offs[i]:offs[i + 1]], dtype=float))
    r, J = flat.evaluate(x0)
    assert J is not None
    sys = flat.problem.system(flat.effects, [], rewhiten=False)
    graph = gtsam.NonlinearFactorGraph()
    for u in np.unique(sys.unit):
        rows = np.flatnonzero(sys.unit == u)
        used = [i for i in range(len(sizes)) if np.any(J[rows, offs[i]:offs[i + 1]])]
        if not used:
            continue
        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows.size), [keys[i] for i in used],
                                     _error_fn(cache, rows, [(offs[i], offs[i + 1]) for i in used])))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    cache.update(result)
    n_eff = len(flat.sizes)
    cov = np.zeros((flat.P, flat.P))
    if n_eff:
        marg = gtsam.Marginals(graph, result)
        blocks = marg.jointMarginalCovariance(gtsam.KeyVector(keys[:n_eff]))
        for i in range(n_eff):
            for j in range(n_eff):
                cov[offs[i]:offs[i + 1], offs[j]:offs[j + 1]] = blocks.at(keys[i], keys[j])
    return {"x": cache.x(result), "cost": float(graph.error(result)), "iterations": int(opt.iterations()),
            "cov_theta": cov}


def _error_fn(cache: _Cache, rows: np.ndarray, spans: list[tuple[int, int]]) -> Any:
    """GTSAM error function of one robot pose's rows: whitened residual, the Jacobian per key."""

    def error(this: Any, values: Any, H: Any) -> np.ndarray:
        cache.update(values)
        if H is not None:
            for i, (a, b) in enumerate(spans):
                H[i] = np.ascontiguousarray(cache.J[np.ix_(rows, np.arange(a, b))])
        return cache.r[rows]

    return error
