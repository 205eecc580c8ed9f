"""Tracker points: a reflector on a link, measured in the tracker's own frame, one registration per session.

Row ``i`` (a reflector at a stop) measures ``p_i = T_s x_i`` with ``x_i`` the reflector in the root frame on the
corrected chain and ``T_s`` the tracker-to-root registration of its session ``s`` (a nuisance).  The registration is
``T_s = T0_s Exp(d_s)`` (right perturbation, root axes, ``d = [rho; theta]``): the residual in root axes is
``z_i - x_i`` with ``z_i = T0_s^-1 p_i``, and the prediction moves by ``[I, -[z_i]x] d_s``.  ``T0_s`` starts as the
Kabsch fit of the session's rows; the solver's registration steps update it.  (Exactly: ``z`` moves by
``-[I, -[z_i]x] d_s``, written as a move of the prediction.)  Sessions with fewer than 3 rows or
collinear points cannot be registered: their rows are dropped (counted in :attr:`TrackerBlock.dropped`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock, chain_columns, prior_covariance
from ppoe_core.analysis.diagnose.candidates import candidate_effects, chain_jacobians, pose_links, predict_nominal
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import MeasurementError
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["TrackerBlock", "kabsch_per_session", "configuration_columns", "time_columns", "spline_basis"]


def kabsch_per_session(x: np.ndarray, p: np.ndarray, session: np.ndarray) -> dict[int, np.ndarray]:
    """Rigid fit ``p ~ T_s x`` per session (batched Kabsch): session -> ``T_s`` (4, 4); sessions with fewer than
    3 rows or collinear points get none.  ``x``, ``p``: (n, 3); ``session``: (n,) ints."""
    if len(x) == 0:
        return {}
    order = np.argsort(session, kind="stable")
    x, p, session = x[order], p[order], session[order]
    sids, starts, counts = np.unique(session, return_index=True, return_counts=True)
    xc = np.add.reduceat(x, starts, axis=0) / counts[:, None]
    pc = np.add.reduceat(p, starts, axis=0) / counts[:, None]
    inv = np.repeat(np.arange(sids.size), counts)
    H = np.add.reduceat(np.einsum("ni,nj->nij", x - xc[inv], p - pc[inv]), starts, axis=0)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.broadcast_to(np.eye(3), H.shape).copy()
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    t = pc - np.einsum("sij,sj->si", R, xc)
    good = (counts >= 3) & (S[:, 1] > 1e-8 * np.maximum(S[:, 0], 1e-300))
    return {int(k): lie.from_rt(R[i], t[i]) for i, k in enumerate(sids) if good[i]}


def spline_basis(v: np.ndarray, n_basis: int = 8) -> np.ndarray:
    """Cubic B-spline basis (n, n_basis) with uniform knots over the range of ``v`` (a partition of unity)."""
    lo, hi = float(np.min(v)), float(np.max(v))
    if hi - lo <= 1e-12:
        return np.zeros((v.size, 0))
    inner = n_basis - 3
    h = (hi - lo) / inner
    knots = lo + h * np.arange(-3, inner + 4)
    x = np.clip(np.asarray(v, dtype=float), lo, hi - 1e-12 * (hi - lo))
    B = ((knots[:-1, None] <= x[None, :]) & (x[None, :] < knots[1:, None])).astype(float)
    for k in range(1, 4):
        left = (x[None, :] - knots[:-k - 1, None]) / (knots[k:-1, None] - knots[:-k - 1, None]) * B[:-1]
        right = (knots[k + 1:, None] - x[None, :]) / (knots[k + 1:, None] - knots[1:-k, None]) * B[1:]
        B = left + right
    return B[:n_basis].T


def configuration_columns(tree: KinematicTree, q: Mapping[str, np.ndarray], Jq: Mapping[str, np.ndarray],
                          n_basis: int = 8) -> dict[str, np.ndarray]:
    """Predictors of a residual that follows the configuration, per independent joint ``j`` (n, d, m): the joint's
    Jacobian ``Jq[j]`` (n, d) times a cubic B-spline basis of its own value (:func:`spline_basis`): a joint error
    that is any smooth function of the joint's value (a cyclic transmission error, a nonlinear compliance)."""
    out: dict[str, np.ndarray] = {}
    for jn, J in Jq.items():
        j = tree.robot.joints.get(jn)
        if j is None or not j.independent or jn not in q or not np.any(J):
            continue
        B = spline_basis(np.asarray(q[jn], dtype=float), n_basis)
        if B.shape[1]:
            out[f"configuration of {jn}"] = J[:, :, None] * B[:, None, :]
    return out


def time_columns(time: np.ndarray | None, group: np.ndarray, d: int, degree: int = 2) -> np.ndarray:
    """Predictors of a drift in time (n, d, m): per group, Legendre polynomials of degree 1..``degree`` of the
    normalised time, on each residual axis separately (a constant is the nuisance's or an offset's)."""
    n = group.size
    if time is None or n == 0:
        return np.zeros((n, d, 0))
    cols = []
    for g in np.unique(group):
        m = group == g
        t = np.asarray(time, dtype=float)
        span = float(np.ptp(t[m])) if m.any() else 0.0
        if span <= 0.0:
            continue
        s = 2.0 * (t - t[m].min()) / span - 1.0
        for k in range(1, degree + 1):
            f = np.where(m, np.polynomial.legendre.legval(s, [0.0] * k + [1.0]), 0.0)
            for a in range(d):
                c = np.zeros((n, d))
                c[:, a] = f
                cols.append(c)
    return np.stack(cols, axis=-1) if cols else np.zeros((n, d, 0))


class TrackerBlock(ResidualBlock):
    """Tracker points (module docstring); ``stops.kind`` must be ``"point"``."""

    kind = "tracker"
    dim = 3
    nuisance_dim = 6
    unit = "m"

    def __init__(self, tree: KinematicTree, stops: Stops, declared: Sequence[Effect] = ()) -> None:
        if stops.kind != "point":
            raise MeasurementError(f"tracker block: {stops.group_names}: stops are {stops.kind!r}, not tracker points")
        x0 = predict_nominal(tree, stops, list(declared))[0]
        regs = kabsch_per_session(x0, stops.p_meas, stops.session)
        keep = np.isin(stops.session, list(regs))
        self.dropped = int((~keep).sum())
        stops = stops if keep.all() else stops.subset(keep)
        if len(stops) == 0:
            raise MeasurementError(f"tracker block: {stops.group_names}: no session has 3 non-collinear tracker points")
        self.stops = stops
        super().__init__(tree, stops.q, stops.context, stops.session, stops.session_names, stops.group,
                         stops.group_names, stops.reg_mask, stops.score_mask)
        self.T0 = np.stack([regs.get(k, np.eye(4)) for k in range(len(stops.session_names))])

    def measured_in_root(self) -> np.ndarray:
        """``z_i = T0_s^-1 p_i`` (n, 3): the measured points in root axes through the current registrations."""
        T = lie.inverse(self.T0)[self.segment]
        return np.einsum("nij,nj->ni", T[:, :3, :3], self.stops.p_meas) + T[:, :3, 3]

    def linearise(self, effects: Sequence[Effect], candidates: Sequence[Effect], pert: Mapping[str, np.ndarray],
                  jnoise: Mapping[str, float], chain: bool = False) -> Linearisation:
        s = self.stops
        poses, dq, dxi = self.chain(effects)
        x = predict_nominal(self.tree, s, (), (dq, dxi), poses=poses)[0]
        n = len(s)
        z = self.measured_in_root()
        r = z - x
        need_chain = chain or bool(candidates) or bool(pert) or bool(jnoise)
        joints = self.chain_joints(candidates, pert, jnoise, chain)
        Jq, Jx, _, _ = chain_jacobians(self.tree, s, poses, dq, dxi, joints) if need_chain else ({}, {}, {}, {})
        J = [chain_columns(Jq, Jx, self.basis(c), c.n_params, (n, 3)) for c in candidates]
        N = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), -lie.hat3(z)], axis=-1)
        S = s.sigma_rows()[:, None, None] ** 2 * np.eye(3)
        Q = prior_covariance(Jq, Jx, pert, jnoise, (n, 3))
        return Linearisation(r, J, N, S, Q, Jq=Jq)

    def residual(self, effects: Sequence[Effect]) -> np.ndarray:
        """:meth:`linearise`'s ``r`` alone (no Jacobians, nuisance columns or covariances: a refit's trial)."""
        poses, dq, dxi = self.chain(effects)
        x = predict_nominal(self.tree, self.stops, (), (dq, dxi), poses=poses)[0]
        return self.measured_in_root() - x

    def apply_nuisance(self, step: np.ndarray) -> None:
        self.T0 = self.T0 @ lie.exp(np.asarray(step, dtype=float).reshape(-1, 6))

    def nuisance_state(self) -> np.ndarray:
        return self.T0.copy()

    def set_nuisance_state(self, state: np.ndarray) -> None:
        self.T0 = state.copy()

    def reset_nuisance(self, effects: Sequence[Effect]) -> None:
        x = predict_nominal(self.tree, self.stops, (), self.corrections(effects), self.motions)[0]
        regs = kabsch_per_session(x, self.stops.p_meas, self.stops.session)
        for k, T in regs.items():
            self.T0[k] = T

    def pose_links(self) -> list[str]:
        return pose_links(self.stops)

    def candidates(self) -> list[Effect]:
        return candidate_effects(self.tree, self.stops)

    def chain_links(self) -> list[str]:
        return self.stops.chain_links()

    def structure_columns(self, lin: Linearisation) -> dict[str, np.ndarray]:
        return {**configuration_columns(self.tree, self.q, lin.Jq),
                "time": time_columns(self.context.get("time"), self.group, 3)}
