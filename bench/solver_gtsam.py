"""The joint tracker + pixel problem as a GTSAM factor graph (solver comparison, ``bench/bench_solver.py``).

Variables: one ``Vector`` per effect (its parameters) and one ``Pose3`` per tracker session (the registration
``T_tracker_root``).  Factors: one ``CustomFactor`` per residual block, a tracker stop (3 rows; keys: the
effects and its session) or the pixels of one robot pose (2 per point; keys: the effects), unit noise (the
residuals of :class:`JointProblem` are already whitened), no robust loss.  The residuals and Jacobians are
those of :meth:`JointProblem.evaluate`, computed once per linearisation point for all factors (cached on the
current values).  GTSAM's ``Pose3`` tangent is ``[omega; v]`` (rotation first) and its retraction a right
perturbation; ours is ``[rho; theta]``: :func:`to_gtsam_tangent` / :func:`from_gtsam_tangent` convert at the
boundary.  ``gtsam`` is imported only here (optional dependency).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.joint_fit import JointProblem

#: permutation of a 6-vector between the orderings (an involution: the same both ways)
_SWAP = np.array([3, 4, 5, 0, 1, 2])


def to_gtsam_tangent(xi: np.ndarray) -> np.ndarray:
    """``[rho; theta]`` (ours) -> ``[omega; v]`` (GTSAM ``Pose3``), last axis of size 6."""
    return np.asarray(xi, dtype=float)[..., _SWAP]


def from_gtsam_tangent(xi: np.ndarray) -> np.ndarray:
    """``[omega; v]`` (GTSAM ``Pose3``) -> ``[rho; theta]`` (ours), last axis of size 6."""
    return np.asarray(xi, dtype=float)[..., _SWAP]


class _Cache:
    """Residuals and Jacobian of the problem at the last values asked for."""

    def __init__(self, prob: JointProblem, keys_e: list[int], keys_s: list[int]) -> None:
        self.prob, self.keys_e, self.keys_s = prob, keys_e, keys_s
        self.x_key = b""
        self.r = np.zeros(0)
        self.J_e = np.zeros((0, 0))
        self.J_s = np.zeros((0, 0, 6))
        self.T = np.zeros((0, 4, 4))

    def update(self, values: Any) -> None:
        """Evaluate at ``values`` unless they are the cached ones; registration Jacobians w.r.t. the GTSAM
        right perturbation of each ``Pose3`` (``[omega; v]``)."""
        th = [values.atVector(k) for k in self.keys_e]
        T = np.stack([values.atPose3(k).matrix() for k in self.keys_s]) if self.keys_s else np.zeros((0, 4, 4))
        d = lie.log(T @ lie.inverse(self.prob.T0)) if len(T) else np.zeros((0, 6))  # T = Exp(d) T0
        x = np.concatenate([*th, d.reshape(-1)])
        if x.tobytes() == self.x_key:
            return
        r, J = self.prob.evaluate(x, jac=True)
        assert J is not None
        P = self.prob.P
        J_s = np.zeros((len(r), len(self.keys_s), 6))
        for k in range(len(self.keys_s)):
            # d r / d xi (right, ours) = d r / d d  Jl(d)^-1  Ad(T)   (Exp(d) T Exp(xi) = Exp(Jl(d) dd) Exp(d) T)
            Jd = J[:, P + 6 * k:P + 6 * k + 6] @ lie.left_jacobian_inv(d[k]) @ lie.adjoint(T[k])
            J_s[:, k] = Jd[:, _SWAP]
        self.x_key, self.r, self.J_e, self.J_s, self.T = x.tobytes(), r, J[:, :P], J_s, T


def solve_gtsam(prob: JointProblem, x0: np.ndarray | None = None, max_iterations: int = 100) -> dict[str, Any]:
    """Levenberg-Marquardt on the factor graph of ``prob`` (module docstring), started at ``x0`` (default
    :meth:`JointProblem.x0`).

    Returns
    -------
    dict
        ``x`` (the solution in :class:`JointProblem` unknowns), ``cost`` (``sum r^2 / 2``), ``iterations``,
        ``cov_theta`` (P, P): the marginal covariance of the effect parameters (``gtsam.Marginals``, unit noise:
        ``(J^T J)^-1`` block, registrations marginalised).
    """
    import gtsam

    x0 = prob.x0() if x0 is None else np.asarray(x0, dtype=float)
    keys_e = [gtsam.symbol("e", i) for i in range(len(prob.effects))]
    keys_s = [gtsam.symbol("r", k) for k in range(len(prob.sessions))]
    cache = _Cache(prob, keys_e, keys_s)
    values = gtsam.Values()
    for k, p in zip(keys_e, np.split(x0[:prob.P], np.cumsum(prob.sizes)[:-1])):
        values.insert(k, np.asarray(p, dtype=float))
    T_start = prob.split(x0)[1]
    for k, key in enumerate(keys_s):
        values.insert(key, gtsam.Pose3(T_start[k]))
    graph = gtsam.NonlinearFactorGraph()
    for rows, s in _blocks(prob):
        keys = keys_e + ([keys_s[s]] if s >= 0 else [])
        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(len(rows)), keys, _error_fn(cache, rows, s)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    cache.update(result)
    marg = gtsam.Marginals(graph, result)
    cov = np.zeros((prob.P, prob.P))
    offs = np.concatenate([[0], np.cumsum(prob.sizes)])
    if keys_e:
        cov_blocks = marg.jointMarginalCovariance(gtsam.KeyVector(keys_e))
        for i, ki in enumerate(keys_e):
            for j, kj in enumerate(keys_e):
                cov[offs[i]:offs[i + 1], offs[j]:offs[j + 1]] = cov_blocks.at(ki, kj)
    x = np.frombuffer(cache.x_key, dtype=float).copy()
    return {"x": x, "cost": float(graph.error(result)), "iterations": int(opt.iterations()), "cov_theta": cov}


def _blocks(prob: JointProblem) -> list[tuple[np.ndarray, int]]:
    """Residual rows of each factor and its session index (-1: pixels of one pose)."""
    out = []
    for i in range(prob.n_tracker):
        assert prob.stops is not None
        out.append((np.arange(3 * i, 3 * i + 3), int(np.searchsorted(prob.sessions, prob.stops.session[i]))))
    if prob.pixels is not None:
        off = 3 * prob.n_tracker
        for p in np.unique(prob.pixels.pose):
            m = np.flatnonzero(prob.pixels.pose == p)
            out.append((off + np.stack([2 * m, 2 * m + 1], axis=1).reshape(-1), -1))
    return out


def _error_fn(cache: _Cache, rows: np.ndarray, s: int) -> Any:
    """GTSAM error function of one block: whitened residual rows, Jacobians per key (effects, then session)."""

    def error(this: Any, values: Any, H: Any) -> np.ndarray:
        cache.update(values)
        if H is not None:
            offs = np.concatenate([[0], np.cumsum(cache.prob.sizes)])
            for i in range(len(cache.keys_e)):
                H[i] = np.ascontiguousarray(cache.J_e[rows, offs[i]:offs[i + 1]])
            if s >= 0:
                H[len(cache.keys_e)] = np.ascontiguousarray(cache.J_s[rows, s])
        return cache.r[rows]

    return error
