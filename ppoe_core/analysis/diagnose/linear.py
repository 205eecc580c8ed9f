"""The linearised least-squares problem of the tracker/pose stage: registrations eliminated, folds, identifiability."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.candidates import Candidate
from ppoe_core.analysis.diagnose.results import DiagnoseOptions
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import PpoeError
from ppoe_core.model.effects import make_effect
from ppoe_core.robot.tree import KinematicTree


@dataclass
class FitResult:
    """Result of one fit: parameters, registrations, covariance and identifiability."""

    theta: np.ndarray
    regs: dict[int, np.ndarray]
    cov: np.ndarray
    s2: float
    condition: float
    absorbed: np.ndarray
    rows: np.ndarray


class LinearProblem:
    """The linearised diagnosis problem ``x = x0 + G theta`` with per-session registration.

    Parameters
    ----------
    stops : Stops
    x0 : (N, 3) nominal predicted positions (base frame)
    R0 : (N, 3, 3) or None, nominal tool orientation (``pose`` only)
    W_base : (N, 3, 3) or None
        Whitening of the position residual in base-frame axes, ``L_i^-1`` with
        ``L_i L_i^T = C_i`` the expected residual covariance of stop ``i`` (the model's PPOE
        covariance of the point plus the sensor noise); None: ``I / sigma``.
    W_rot : (N, 3, 3) or None
        ``pose`` only: whitening of the rotation residual (tangent at the tool), from the
        rotation block of the model's covariance plus ``sigma_rot^2 I``; None: ``I / sigma_rot``.
    """

    def __init__(self, stops: Stops, x0: np.ndarray, R0: np.ndarray | None,
                 W_base: np.ndarray | None = None, W_rot: np.ndarray | None = None) -> None:
        self.stops = stops
        self.x0 = x0
        self.R0 = R0
        self.register = stops.kind == "point"
        self._regs0: dict[bytes, dict[int, np.ndarray]] = {}
        self._step0: dict[bytes, tuple] = {}
        self.W = (np.eye(3) / stops.sigma_rows()[:, None, None] if W_base is None
                  else W_base)
        self.W_rot = (np.broadcast_to(np.eye(3) / stops.sigma_rot, (len(stops), 3, 3)) if W_rot is None
                      else W_rot)
        if stops.kind == "pose":
            assert stops.R_meas is not None and R0 is not None  # pose stops carry measured rotations
            self.r0_rot = lie.so3_log(np.swapaxes(R0, -1, -2) @ stops.R_meas)

    # -- residuals ---------------------------------------------------------------
    def _per_row(self, regs: Mapping[int, np.ndarray], sess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Registration of each row (n, 4, 4) and whether its session has one (n,)."""
        table = np.full((len(self.stops.session_names) + 1, 4, 4), np.nan)
        for k, T in regs.items():
            table[k] = T
        Tn = table[sess]
        return Tn, np.isfinite(Tn[:, 0, 0])

    def residuals(self, G: np.ndarray, theta: np.ndarray, regs: Mapping[int, np.ndarray],
                  rows: np.ndarray) -> np.ndarray:
        """Residuals measured minus predicted, (n, dim) [m, rad], NaN where no registration."""
        s = self.stops
        x = self.x0[rows] + (G[rows, :3] @ theta if theta.size else 0.0)
        if self.register:
            Tn, _ = self._per_row(regs, s.session[rows])
            return s.p_meas[rows] - (np.einsum("nij,nj->ni", Tn[:, :3, :3], x) + Tn[:, :3, 3])
        out = np.empty((rows.size, s.dim))
        out[:, :3] = s.p_meas[rows] - x
        out[:, 3:] = self.r0_rot[rows] - (G[rows, 3:] @ theta if theta.size else 0.0)
        return out

    def whitened(self, r: np.ndarray, regs: Mapping[int, np.ndarray], rows: np.ndarray) -> np.ndarray:
        """Residuals (n, dim) whitened: position part rotated into base axes, times ``W``."""
        out = np.array(r, dtype=float)
        if self.register:
            Tn, _ = self._per_row(regs, self.stops.session[rows])
            rb = np.einsum("nji,nj->ni", Tn[:, :3, :3], r[:, :3])
        else:
            rb = r[:, :3]
            out[:, 3:] = np.einsum("nij,nj->ni", self.W_rot[rows], r[:, 3:])
        out[:, :3] = np.einsum("nij,nj->ni", self.W[rows], rb)
        return out

    def kabsch_regs(self, G: np.ndarray, theta: np.ndarray, rows: np.ndarray) -> dict[int, np.ndarray]:
        """Registration per session from ``rows`` with ``theta`` fixed (Kabsch, batched over
        sessions; sessions with fewer than 3 rows or collinear points get none)."""
        s = self.stops
        if not self.register or rows.size == 0:
            return {}
        rows = rows[np.argsort(s.session[rows], kind="stable")]
        x = self.x0[rows] + (G[rows, :3] @ theta if theta.size else 0.0)
        p = s.p_meas[rows]
        sids, starts, counts = np.unique(s.session[rows], return_index=True, return_counts=True)
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

    # -- fit ------------------------------------------------------------------------
    def _start_regs(self, rows: np.ndarray) -> dict[int, np.ndarray]:
        """Kabsch registrations of ``rows`` at ``theta = 0`` (the start of every fit): they depend on the rows
        only, so they are computed once per row set (the selection fits every candidate on the same rows)."""
        key = _rows_key(rows)
        if key not in self._regs0:
            self._regs0[key] = self.kabsch_regs(np.zeros((len(self.stops), 3, 0)), np.zeros(0), rows)
        return dict(self._regs0[key])

    def fit(self, G: np.ndarray, rows: np.ndarray, iterations: int = 2) -> FitResult:
        """Gauss-Newton over ``theta`` and the registrations of the sessions of ``rows``.

        Returns the estimate, the covariance ``s^2 H_red^-1`` of ``theta`` (H_red: information
        reduced by the registrations, Schur complement), the condition number of the
        column-scaled ``H_red`` and, per parameter, the fraction of its information absorbed
        by the registrations.
        """
        s = self.stops
        P = G.shape[-1]
        theta = np.zeros(P)
        key = _rows_key(rows)
        regs = self._start_regs(rows)
        if self.register:
            rows = rows[np.isin(s.session[rows], list(regs))]
            rows = rows[np.argsort(s.session[rows], kind="stable")]
        Gr = G[rows]
        Wr = self.W[rows]
        if self.register:
            sids, starts, inv = np.unique(s.session[rows], return_index=True, return_inverse=True)
            T = np.stack([regs[int(k)] for k in sids]) if sids.size else np.zeros((0, 4, 4))

            def seg(a: np.ndarray) -> np.ndarray:  # per-session sums of per-row terms
                return np.add.reduceat(a, starts, axis=0) if a.shape[0] else a[:0]
        H_red = np.zeros((P, P))
        H_tt = np.zeros((P, P))
        for it in range(iterations):
            if self.register:
                # the first step starts at theta = 0 and the Kabsch registrations: its registration terms
                # depend on the rows only (computed once per row set; the selection fits many candidates)
                finite = it > 0 or bool(np.all(np.isfinite(Gr)))
                if it == 0 and finite and key in self._step0:
                    Js, r, pre = self._step0[key]
                else:
                    x = self.x0[rows] + Gr[:, :3] @ theta
                    Tn = T[inv]  # per-row registration
                    y = np.einsum("nij,nj->ni", Tn[:, :3, :3], x) + Tn[:, :3, 3]
                    A = Wr @ np.swapaxes(Tn[:, :3, :3], -1, -2)  # whitening in the tracker axes
                    r = (A @ (s.p_meas[rows] - y)[:, :, None])[..., 0]
                    Js = -A @ np.concatenate([np.broadcast_to(np.eye(3), (y.shape[0], 3, 3)), -lie.hat3(y)],
                                             axis=-1)
                    pre = _registration_terms(Js, r, seg)
                    if it == 0 and finite:
                        self._step0[key] = (Js, r, pre)
                H_tt, H_red, dtheta, d = _schur_step(Js, -(Wr @ Gr[:, :3]), r, seg, P, pre)
                T = lie.exp(d) @ T
                theta = theta + dtheta
                if (it > 0 and np.abs(d).max(initial=0.0) < 1e-12
                        and np.all(np.abs(dtheta) <= 1e-10 * (1 + np.abs(theta)))):
                    break
            else:
                r = self.whitened(self.residuals(G, theta, regs, rows), regs, rows)
                Jw = -np.concatenate([Wr @ Gr[:, :3], self.W_rot[rows] @ Gr[:, 3:]], axis=1)
                Jf = Jw.reshape(Jw.shape[0] * Jw.shape[1], P)
                H_tt = H_red = Jf.T @ Jf
                dtheta = -_solve(H_red, Jf.T @ r.reshape(-1)) if P else np.zeros(0)
                theta = theta + dtheta
                break  # linear in theta
        if self.register:
            regs = {int(k): T[i] for i, k in enumerate(sids)}
        r = self.whitened(self.residuals(G, theta, regs, rows), regs, rows)
        n_par = P + 6 * len(regs)
        s2 = float(np.nansum(r**2) / max(r.size - n_par, 1))
        cond, absorbed = _identifiability(H_red, H_tt, r.size)
        cov = s2 * np.linalg.pinv(H_red) if P else np.zeros((0, 0))
        return FitResult(theta, regs, cov, s2, cond, absorbed, rows)

    def heldout(
        self, G: np.ndarray, folds: Sequence[tuple[np.ndarray, np.ndarray]]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Held-out residuals over ``folds``: ``(r_meas, r_base, e2w)``; ``r_meas`` and ``r_base``
        (N, 3) [m], NaN where a stop is not scored, in the measurement frame and rotated into
        the robot base frame axes; ``e2w`` (N,) the whitened squared position error
        ``|W r_base|^2`` (Mahalanobis distance under the model's covariance).

        A test stop whose session has training rows uses that session's training registration;
        otherwise the registration is fitted on the session's ``reg_mask`` test rows with theta
        fixed and only its ``score_mask`` rows that did not define it are scored (the Hilti
        protocol).
        """
        s = self.stops
        R = np.full((len(s), 3), np.nan)
        Rb = np.full((len(s), 3), np.nan)
        for train, test in folds:
            fit = self.fit(G, train)
            regs = dict(fit.regs)
            scored = test
            if self.register:
                missing = np.setdiff1d(np.unique(s.session[test]), list(regs))
                if missing.size:
                    reg_rows = test[np.isin(s.session[test], missing) & s.reg_mask[test]]
                    regs.update(self.kabsch_regs(G, fit.theta, reg_rows))
                    own = np.isin(s.session[test], missing)
                    split = s.score_mask[test] & ~s.reg_mask[test]
                    # a session without separate scored stops is scored on the stops that
                    # registered it (rigid fit per session, as in the Motoman README)
                    whole = own & ~np.isin(s.session[test], s.session[test][own & split])
                    scored = test[~own | split | whole]
            r = self.residuals(G, fit.theta, regs, scored)[:, :3]
            R[scored] = r
            if self.register:
                for sid in np.unique(s.session[scored]):
                    if int(sid) in regs:
                        m = s.session[scored] == sid
                        Rb[scored[m]] = r[m] @ regs[int(sid)][:3, :3]
            else:
                Rb[scored] = r
        return R, Rb, np.sum(np.einsum("nij,nj->ni", self.W, Rb) ** 2, axis=1)


def _ssr(problem: LinearProblem, G: np.ndarray, rows: np.ndarray) -> float:
    """In-sample sum of squared residuals after a fit (screening of candidates)."""
    fit = problem.fit(G, rows, iterations=2)
    return float(
        np.nansum(problem.whitened(problem.residuals(G, fit.theta, fit.regs, fit.rows), fit.regs, fit.rows) ** 2)
    )


def _solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Minimum-norm solution of ``H x = g`` with column scaling; parameters that do not act
    (information below 1e-12, see :func:`_identifiability`) stay at zero."""
    x = np.zeros(len(g))
    act = np.diag(H) > 1e-12
    if not act.any():
        return x
    Ha = H[np.ix_(act, act)]
    d = np.sqrt(np.diag(Ha))
    Hs = Ha / d[:, None] / d[None, :]
    x[act] = np.linalg.lstsq(Hs, g[act] / d, rcond=1e-12)[0] / d
    return x


def _identifiability(H_red: np.ndarray, H_tt: np.ndarray, n_res: int) -> tuple[float, np.ndarray]:
    """Condition number of the column-scaled reduced information, and per parameter the
    fraction of its information absorbed by the registrations (1 = fully absorbed; also 1 for
    a parameter that moves the weighted measurement by less than 1e-6 sigma per unit over
    the ``n_res`` residuals, i.e. does not act on it at all)."""
    P = H_red.shape[0]
    if P == 0:
        return 1.0, np.zeros(0)
    dt = np.diag(H_tt)
    acts = dt > 1e-12 * max(n_res, 1)
    absorbed = np.where(acts, 1.0 - np.diag(H_red) / np.where(acts, dt, 1.0), 1.0)
    d = np.sqrt(np.maximum(np.diag(H_red), 1e-300))
    ev = np.linalg.eigvalsh(H_red / d[:, None] / d[None, :])
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
    if np.any(np.diag(H_red) <= 0):
        cond = math.inf
    return cond, absorbed


def make_folds(stops: Stops, options: DiagnoseOptions) -> tuple[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Cross-validation folds ``(train_rows, test_rows)``; returns the scheme and the folds."""
    n = len(stops)
    groups = np.unique(stops.group)
    mode = options.cv
    if mode == "auto":
        mode = "groups" if groups.size >= 3 else "stops"
    if mode == "groups":
        if groups.size < 2:
            raise PpoeError("diagnose: leave-one-group-out needs at least 2 bags/files")
        return mode, [(np.flatnonzero(stops.group != g), np.flatnonzero(stops.group == g)) for g in groups]
    rng = np.random.default_rng(options.seed)
    fold = np.zeros(n, dtype=int)
    for sid in np.unique(stops.session):
        idx = np.flatnonzero(stops.session == sid)
        fold[idx] = rng.permutation(np.arange(idx.size) % options.folds)
    return mode, [(np.flatnonzero(fold != k), np.flatnonzero(fold == k)) for k in range(options.folds)]


def _stack(cands: Sequence[Candidate], n: int, dim: int) -> np.ndarray:
    if not cands:
        return np.zeros((n, dim, 0))
    return np.concatenate([c.G for c in cands], axis=-1)


def _restrict(c: Candidate, keep: Sequence[int], tree: KinematicTree) -> Candidate:
    e = c.effect
    comps = [e.param_names[i] for i in keep]
    eff = make_effect(e.name, e.location, tree, components=comps)
    return Candidate(eff, c.G[..., list(keep)])


def _identifiable_subset(
    problem: LinearProblem,
    chosen: Sequence[Candidate],
    cand: Candidate,
    options: DiagnoseOptions,
    tree: KinematicTree,
    rows: np.ndarray,
) -> tuple[Candidate | None, str, float]:
    """Candidate (possibly with fewer link_error components) identifiable together with the
    registration and ``chosen``, with physically signed parameters; also its in-sample SSR.

    Returns ``(candidate or None, reason if None, in-sample weighted SSR)``.
    """
    base = _stack(chosen, len(problem.stops), problem.stops.dim)
    nb = base.shape[-1]

    def check(G_c: np.ndarray, names: Sequence[str]) -> tuple[bool, str, float]:
        G = np.concatenate([base, G_c], axis=-1)
        fit = problem.fit(G, rows, iterations=2)
        if np.any(fit.absorbed[nb:] > options.max_absorbed):
            return False, "not separable from the tracker registration", math.inf
        if fit.condition > options.max_condition:
            return False, (f"not separable from the effects already chosen (condition {fit.condition:.2g})"), math.inf
        th = fit.theta[nb:]
        sd = np.sqrt(np.maximum(np.diag(fit.cov)[nb:], 0.0))
        neg = [k for k, v, s in zip(names, th, sd) if k in cand.effect.nonnegative and v + 1.96 * s < 0]
        if neg:
            return False, f"fitted {', '.join(neg)} < 0: unphysical sign", math.inf
        ssr = float(
            np.nansum(problem.whitened(problem.residuals(G, fit.theta, fit.regs, fit.rows), fit.regs, fit.rows) ** 2)
        )
        return True, "", ssr

    ok, why, ssr = check(cand.G, cand.effect.param_names)
    if ok:
        return cand, "", ssr
    if "unphysical" in why and len(cand.effect.nonnegative) > 1:  # two-axis bending: drop only the negative axis
        names = cand.effect.param_names
        signed = [i for i, n in enumerate(names) if n not in why.split(":")[0]]
        if signed and len(signed) < len(names):
            ok_k, _, ssr_k = check(cand.G[..., signed], [names[i] for i in signed])
            if ok_k:
                return _restrict(cand, signed, tree), "", ssr_k
        return None, why, math.inf
    if cand.effect.name != "link_error" or "unphysical" in why:
        return None, why, math.inf
    keep: list[int] = []
    for i in range(cand.G.shape[-1]):
        ok_i, _, ssr_i = check(cand.G[..., keep + [i]], [cand.effect.param_names[j] for j in keep + [i]])
        if ok_i:
            keep.append(i)
            ssr = ssr_i
    if not keep:
        return None, why, math.inf
    return _restrict(cand, keep, tree), "", ssr


def _rows_key(rows: np.ndarray) -> bytes:
    """A dictionary key of a row set (index or mask array)."""
    a = np.asarray(rows)
    return a.dtype.str.encode() + a.tobytes()


def _registration_terms(Js: np.ndarray, r: np.ndarray, seg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The parts of a Gauss-Newton step that involve the registrations only: ``Js^T``, the inverse of the
    per-session information ``Hss`` and the per-session gradient ``gs``."""
    JsT = np.swapaxes(Js, -1, -2)
    Hss = seg(JsT @ Js) + 1e-12 * np.eye(6)
    gs = seg((JsT @ r[:, :, None])[..., 0])
    return JsT, np.linalg.inv(Hss), gs


def _schur_step(Js: np.ndarray, Jts: np.ndarray, r: np.ndarray, seg: Any, P: int,
                pre: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Newton step with the registrations eliminated (Schur complement): ``(H_tt, H_red, dtheta, d)``
    with ``d`` the registration steps per session; ``seg`` sums per-row terms per session; ``pre``: the
    :func:`_registration_terms` of ``Js`` and ``r`` if the caller has them."""
    JsT, Hinv, gs = pre if pre is not None else _registration_terms(Js, r, seg)
    Hst = seg(JsT @ Jts)
    Jf = Jts.reshape(Jts.shape[0] * 3, P)
    H_tt = Jf.T @ Jf
    g_t = Jf.T @ r.reshape(-1)
    HiHst = Hinv @ Hst  # (S, 6, P)
    H_red = H_tt - np.einsum("sap,saq->pq", Hst, HiHst)
    g_red = g_t - np.einsum("sap,sa->p", Hst, np.einsum("sab,sb->sa", Hinv, gs))
    dtheta = -_solve(H_red, g_red) if P else np.zeros(0)
    d = -(np.einsum("sab,sb->sa", Hinv, gs) + HiHst @ dtheta)
    return H_tt, H_red, dtheta, d
