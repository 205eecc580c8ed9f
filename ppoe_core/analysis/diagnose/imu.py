"""Accelerometer stage: per-placement base tilt and IMU-visible effects from gravity directions."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.candidates import _carried_mass
from ppoe_core.analysis.diagnose.selection import GainSelection, select_by_heldout_gain
from ppoe_core.analysis.diagnose.stats import _lstsq, _pose_folds, _rotation_covariance
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import MeasurementError
from ppoe_core.model.effects import Effect, make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot


def _imu_cost(tree: KinematicTree, stops: Stops, effects: Sequence[Effect]) -> float:
    """Sum over accelerometers of the mean squared tilt residual [rad^2]."""
    return float(sum(sum(v ** 2 for v in r["rms"]) for r in imu_tilt_residuals(tree, stops, effects).values()))


def imu_tilt_residuals(tree: KinematicTree, stops: Stops, effects: Sequence[Effect]) -> dict[str, dict]:
    """Tilt residuals of the accelerometers (measured minus predicted, small angles about the
    sensor's x and y axes [rad]) with each session's mean removed (the session's base tilt and
    the sensor's mounting are nuisances), for a model with ``effects``.

    The predicted up direction in the sensor frame is ``R_root_link^T z_root``; the measured one
    the normalised specific force.  Returns ``{imu: {"link", "rms": [rx, ry], "n"}}``.
    """
    out: dict[str, dict] = {}
    if not stops.imus:
        return out
    dq, dxi = sum_effect_corrections(list(effects), stops.q, stops.context, nominal_poses(tree, stops))
    poses = tree.link_poses(stops.q, dq, dxi, links=[ln for ln, _ in stops.imus.values()])
    for name, (link, acc) in stops.imus.items():
        u_m = acc / np.linalg.norm(acc, axis=1)[:, None]
        u_p = poses[link][..., 2, :3]  # third row of R_root_link = R^T z
        d = np.column_stack([u_m[:, 1] - u_p[:, 1], -(u_m[:, 0] - u_p[:, 0])])
        ok = np.all(np.isfinite(d), axis=1)
        for sid in np.unique(stops.session):
            m = ok & (stops.session == sid)
            d[m] -= d[m].mean(axis=0)
        out[name] = {"link": link, "rms": [float(v) for v in np.sqrt(np.mean(d[ok] ** 2, axis=0))],
                     "n": int(ok.sum())}
    return out


# =============================================================================
# Accelerometer stage (base tilt and the effects upstream of the IMU links)
# =============================================================================


def nominal_poses(tree: KinematicTree, stops: Stops) -> dict[str, np.ndarray]:
    """``tree.link_poses(stops.q)`` (every link, nominal chain), computed once per ``stops`` object: the
    gravity effects evaluate their loads on it, and the accelerometer fit evaluates them hundreds of times."""
    cache = stops.__dict__.setdefault("_nominal_poses", {})
    if id(tree) not in cache:
        cache.clear()
        cache[id(tree)] = tree.link_poses(stops.q)
    return cache[id(tree)]


def imu_tilt_raw(tree: KinematicTree, stops: Stops, effects: Sequence[Effect],
                  tilt_group: np.ndarray | None = None, corrections: tuple[dict, dict] | None = None) -> np.ndarray:
    """Tilt residuals (measured minus predicted) of every accelerometer, shape (N, K, 2) [rad].

    Predicted up direction in the IMU link: ``u = R_root_link^T Exp(-w_g) z_root`` with
    ``w_g = [tilt_x, tilt_y, 0]`` the base tilt of the stop's group (``tilt_group`` (G, 2), root
    axes: the root is rotated by ``Exp(w_g)`` w.r.t. gravity, the ``base_tilt`` effect); measured:
    the normalised specific force.  Components: small rotations about the link's x and y axes.
    ``corrections``: the ``(dq, dxi)`` of ``effects`` when the caller has them (finite differences).
    """
    dq, dxi = corrections or sum_effect_corrections(list(effects), stops.q, stops.context, nominal_poses(tree, stops))
    links = [ln for ln, _ in stops.imus.values()]
    poses = tree.link_poses(stops.q, dq, dxi, links=links)
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (len(stops), 3))
    if tilt_group is not None:
        w = np.zeros((len(stops), 3))
        w[:, :2] = np.asarray(tilt_group)[stops.group]
        up = np.einsum("nji,nj->ni", lie.exp(np.concatenate([np.zeros_like(w), w], axis=1))[:, :3, :3], up)
    out = np.empty((len(stops), len(stops.imus), 2))
    for k, (link, acc) in enumerate(stops.imus.values()):
        u_m = acc / np.linalg.norm(acc, axis=1)[:, None]
        u_p = np.einsum("nji,nj->ni", poses[link][:, :3, :3], up)
        out[:, k, 0] = u_m[:, 1] - u_p[:, 1]
        out[:, k, 1] = -(u_m[:, 0] - u_p[:, 0])
    return out


def imu_candidates(tree: KinematicTree, stops: Stops) -> list[Effect]:
    """Effects that rotate an accelerometer's link w.r.t. gravity (zero parameters):
    ``joint_offset``, ``gravity_compliance`` and ``mount_bending`` on the paths from the root to
    the IMU links (rotations only; ``link_error`` is left out: a constant rotation is the sensor's
    mounting).  ``base_tilt`` is handled separately, per group (bag / file = robot placement)."""
    robot = tree.robot
    out: list[Effect] = []
    seen: set[str] = set()
    for link, _ in stops.imus.values():
        for jn in robot.path_from_root(link):
            if jn in seen:
                continue
            seen.add(jn)
            j = robot.joints[jn]
            mass = _carried_mass(tree, jn)
            if j.movable and j.type != "prismatic":
                out.append(make_effect("joint_offset", jn, tree))
                if mass > 0.0:
                    out.append(make_effect("gravity_compliance", jn, tree))
            if (not j.movable or j.type == "prismatic") and mass > 0.0:
                out.append(make_effect("mount_bending", jn, tree))
    return out


def imu_jacobian(tree: KinematicTree, stops: Stops, effect: Effect | None, current: Sequence[Effect],
                  tilt_group: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central finite-difference Jacobian (N, K, 2, P) of the tilt *prediction* w.r.t. the
    parameters of ``effect`` (``None``: the per-group base tilt, P = 2 G), at ``current``."""
    cols = []
    poses = nominal_poses(tree, stops)
    if effect is None:
        fixed = sum_effect_corrections(list(current), stops.q, stops.context, poses)  # the same at every step
        for i in range(tilt_group.size):
            d = np.zeros(tilt_group.size)
            d[i] = h
            rp = imu_tilt_raw(tree, stops, current, tilt_group + d.reshape(tilt_group.shape), fixed)
            rm = imu_tilt_raw(tree, stops, current, tilt_group - d.reshape(tilt_group.shape), fixed)
            cols.append(-(rp - rm) / (2 * h))
    else:
        others = [e for e in current if not (e.name == effect.name and e.location == effect.location)]
        base = sum_effect_corrections(others, stops.q, stops.context, poses)  # summed once, in the same order

        def raw(e: Effect) -> np.ndarray:
            return imu_tilt_raw(tree, stops, [], tilt_group,
                                sum_effect_corrections([e], stops.q, stops.context, poses, start=base))

        for i in range(effect.n_params):
            d = np.zeros(effect.n_params)
            d[i] = h
            cols.append(-(raw(effect.with_params(effect.params + d)) - raw(effect.with_params(effect.params - d)))
                        / (2 * h))
    return np.stack(cols, axis=-1)


def imu_tilt_covariance(tree: KinematicTree, stops: Stops, declared: Sequence[Effect], sigma: np.ndarray,
                        perturbation_cov: Mapping[str, np.ndarray] | None = None,
                        joint_noise: Mapping[str, float] | None = None) -> np.ndarray:
    """Expected covariance (N, K, 2, 2) [rad^2] of the tilt residuals of :func:`imu_tilt_raw`.

    ``(sigma_k / |a|)^2 I`` (``sigma`` (K,) accelerometer 1-sigma per axis [m/s^2]) plus the
    first-order PPOE covariance of the IMU link's rotation (right tangent at the link, rotation
    rows of eq. 18, :func:`_rotation_covariance`; ``perturbation_cov``: joint -> 6x6 in the
    tangent space right after the joint's origin) mapped to the tilt angles: for
    ``R' = R Exp(phi)`` the up direction ``u = R^T z`` becomes ``u + u x phi``.
    """
    n, K = len(stops), len(stops.imus)
    dq_d, dxi_d = sum_effect_corrections(list(declared), stops.q, stops.context)
    poses_d = tree.link_poses(stops.q, dq_d, dxi_d)
    C_tilt = np.zeros((n, K, 2, 2))
    for k, (link, acc) in enumerate(stops.imus.values()):
        C_tilt[:, k] = (sigma[k] / np.linalg.norm(acc, axis=1))[:, None, None] ** 2 * np.eye(2)
        if perturbation_cov or joint_noise:
            Fq, Fx = tree.frame_jacobian(stops.q, link, poses_d, dq_d, dxi_d)
            C_rot = _rotation_covariance(stops, Fq, Fx, perturbation_cov or {}, joint_noise or {})
            u = poses_d[link][:, 2, :3]  # up in the link
            A = np.zeros((n, 2, 3))
            A[:, 0, 0], A[:, 0, 2] = u[:, 2], -u[:, 0]
            A[:, 1, 1], A[:, 1, 2] = u[:, 2], -u[:, 1]
            C_tilt[:, k] += A @ C_rot @ np.swapaxes(A, -1, -2)
    return C_tilt


def diagnose_imu(robot: Robot, stops: Stops, declared: Sequence[Effect] = (),
                 sigma: float | Mapping[str, float] = 4e-4, candidates: Sequence[Effect] | None = None,
                 folds: int = 5, min_gain: float = 0.03, min_t: float = 4.0, max_condition: float = 1e6,
                 max_effects: int = 3, iterations: int = 3, seed: int = 0,
                 perturbation_cov: Mapping[str, np.ndarray] | None = None,
                 joint_noise: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Fit the accelerometers: per-group ``base_tilt`` and the effects that rotate the IMU links.

    Residual per stop and accelerometer: the two tilt angles (measured minus predicted up
    direction in the IMU link, :func:`imu_tilt_raw`), whitened by ``sigma / |a|`` [rad]
    (``sigma`` [m/s^2] per axis, one value or per IMU name; model ``imus`` section, default
    4e-4) plus the declared PPOE covariance of the IMU link's rotation (``perturbation_cov``:
    joint -> 6x6 in the tangent space right after the joint's origin, ``joint_noise``: joint ->
    1-sigma; first order, rotation rows of eq. 18, right tangent at the IMU link) mapped to the
    two tilt angles.  The IMU nearest the root is the reference: its mounting is part of the base
    tilt; every other IMU gets a constant mounting rotation (2 nuisance parameters, always fitted).
    Candidates: ``base_tilt`` (2 parameters per group = bag / file, one robot placement each) and
    :func:`imu_candidates`.  Selection as in :func:`diagnose_pixels` (same helpers): linearised at
    the declared chain (central finite-difference Jacobian), greedy forward selection, ``folds``-fold
    CV over stops (all IMUs of a stop in one fold), accepted when the column-scaled normal matrix
    has condition < ``max_condition``, the held-out mean squared whitened error drops by
    >= ``min_gain`` with a paired t >= ``min_t`` over stops, and compliances are not negative.
    Final fit: Gauss-Newton on the nonlinear chain; 95 % CIs ``theta +- 1.96 sigma`` from
    ``max(s^2, 1) H^-1``.

    Returns
    -------
    dict with ``effects`` (as in :func:`diagnose`, ``"measurement": "imu"``; ``base_tilt`` has
    ``per_group`` {group: {tilt_x, tilt_y, ci}}), ``steps``, ``rejected``, ``tilt_rms_before`` /
    ``tilt_rms_after`` (held-out, per IMU [rad], x / y), ``sigma_scale``, ``n``.
    """
    if not stops.imus:
        raise MeasurementError("diagnose_imu: the stops carry no accelerometer (/imu/<name>) data")
    ip = _ImuProblem(robot, stops, list(declared), sigma, candidates, folds, seed, perturbation_cov, joint_noise)
    sel = select_by_heldout_gain(len(ip.effs), lambda i: ip.names[i],
                                 lambda idx: ip.stacked(idx).reshape(-1, ip.stacked(idx).shape[2]),
                                 ip.heldout, ip.e0, max_effects=max_effects, max_condition=max_condition,
                                 min_gain=min_gain, min_t=min_t, skip_rejected=True, check=ip.negative_compliance)
    fitted, theta, tilt, mount, s2, sd = ip.gauss_newton(sel.chosen, iterations)
    nm = ip.nm
    mount_sd = sd[:nm].reshape(-1, 2)
    mounting = {list(stops.imus)[k]: {"rx": float(mount[k, 0]), "ry": float(mount[k, 1]),
                                      "sigma": [float(v) for v in mount_sd[c]]}
                for c, k in enumerate(ip.mount_imus)}
    effects_out = ip.effects_out(sel, fitted, theta[nm:], sd[nm:])
    K = ip.K
    return {
        "effects": effects_out,
        "steps": sel.steps,
        "rejected": sel.rejected,
        "tilt_rms_before": ip.rms_per_imu([]),
        "tilt_rms_after": ip.rms_per_imu(sel.chosen),
        "heldout_mahalanobis2_before": float(np.mean(sel.base0)) / (2 * K),
        "heldout_mahalanobis2_after": float(np.mean(sel.base)) / (2 * K),
        "sigma_scale": math.sqrt(s2),
        "n": ip.n,
        "reference_imu": list(stops.imus)[ip.ref],
        "mounting": mounting,
        "imus": {k: ln for k, (ln, _) in stops.imus.items()},
        "found": list(fitted.values()),
        "tilt": tilt,
    }


class _ImuProblem:
    """The whitened, linearised accelerometer problem of :func:`diagnose_imu`: tilt residuals per stop and IMU
    (rad, IMU link), candidate Jacobians, IMU mounting nuisance columns and stop-wise folds."""

    def __init__(self, robot: Robot, stops: Stops, declared: list[Effect], sigma: float | Mapping[str, float],
                 candidates: Sequence[Effect] | None, folds: int, seed: int,
                 perturbation_cov: Mapping[str, np.ndarray] | None, joint_noise: Mapping[str, float] | None) -> None:
        self.stops, self.declared = stops, declared
        self.tree = tree = KinematicTree(robot)
        self.n, self.K = n, K = len(stops), len(stops.imus)
        if n < folds:
            raise MeasurementError(f"diagnose_imu: {n} stops with accelerometer data, need >= {folds}")
        sig = np.array([sigma.get(k, 4e-4) if isinstance(sigma, Mapping) else float(sigma) for k in stops.imus])
        C_tilt = imu_tilt_covariance(tree, stops, declared, sig, perturbation_cov, joint_noise)
        self.W = np.linalg.inv(np.linalg.cholesky(C_tilt))  # (N, K, 2, 2) whitening
        self.n_grp = len(stops.group_names)
        self.zero_tilt = np.zeros((self.n_grp, 2))
        e_raw = imu_tilt_raw(tree, stops, declared, self.zero_tilt)
        if not np.all(np.isfinite(e_raw)):
            i = int(np.flatnonzero(~np.all(np.isfinite(e_raw), axis=(1, 2)))[0])
            raise MeasurementError(f"diagnose_imu: non-finite accelerometer or joint values (first: stop {i} "
                                   f"of {stops.group_names[stops.group[i]]})")
        self.e0 = self.wh(e_raw).reshape(n, -1)  # (N, 2K) whitened
        cands = list(candidates) if candidates is not None else imu_candidates(tree, stops)
        self.names = ["base_tilt@" + tree.root] + [c.describe() for c in cands]
        self.effs: list[Effect | None] = [None, *cands]
        self.Gs = [self.wh(imu_jacobian(tree, stops, e, declared, self.zero_tilt)).reshape(n, 2 * K, -1)
                   for e in self.effs]
        self.test_masks = _pose_folds(np.arange(n), folds, seed)
        # mounting of every IMU but the reference (the one nearest the root, whose mounting is part of
        # the base tilt): a constant small rotation, additive on its two tilt components (nuisance)
        depth = [len(robot.path_from_root(ln)) for ln, _ in stops.imus.values()]
        self.ref = int(np.argmin(depth))
        self.mount_imus = [k for k in range(K) if k != self.ref]
        Gm_axes = np.zeros((n, K, 2, 2 * len(self.mount_imus)))
        for c, k in enumerate(self.mount_imus):
            Gm_axes[:, k, 0, 2 * c] = 1.0
            Gm_axes[:, k, 1, 2 * c + 1] = 1.0
        self.Gm = self.wh(Gm_axes).reshape(n, 2 * K, -1)
        self.nm = self.Gm.shape[2]

    def wh(self, x: np.ndarray) -> np.ndarray:
        """Whiten (N, K, 2) residuals or (N, K, 2, P) Jacobians."""
        return np.einsum("nkij,nkj...->nki...", self.W, x)

    def stacked(self, idx: Sequence[int]) -> np.ndarray:
        return np.concatenate([self.Gm] + [self.Gs[i] for i in idx], axis=2)

    def _cv_residual(self, G: np.ndarray) -> np.ndarray:
        """Held-out whitened residual per stop (N, 2K) with the design ``G`` (groups without training stops stay 0)."""
        e0 = self.e0
        rr = np.zeros_like(e0)
        for test in self.test_masks:
            r = e0
            if G.shape[2]:
                Gt = G[~test].reshape(-1, G.shape[2])
                live = np.any(Gt != 0.0, axis=0)
                th = np.zeros(G.shape[2])
                th[live], _ = _lstsq(Gt[:, live], e0[~test].reshape(-1))
                r = e0 - G @ th
            rr[test] = r[test]
        return rr

    def heldout(self, idx: Sequence[int]) -> np.ndarray:
        """Held-out squared whitened error per stop with the candidates ``idx``."""
        return np.sum(self._cv_residual(self.stacked(idx)) ** 2, axis=1)

    def negative_compliance(self, i: int, th: np.ndarray) -> str | None:
        """Reject a candidate whose in-sample fit gives a negative compliance."""
        P = self.Gs[i].shape[2]
        eff = self.effs[i]
        if eff is not None and any(th[-P + k] < 0 for k, p in enumerate(eff.param_names) if p in eff.nonnegative):
            return "negative compliance"
        return None

    def gauss_newton(self, chosen: list[int], iterations: int) -> tuple[dict[int, Effect], np.ndarray, np.ndarray,
                                                                         np.ndarray, float, np.ndarray]:
        """Final Gauss-Newton on the nonlinear chain: fitted effects, theta, tilt per group, IMU mounting,
        residual variance and parameter sigmas (``max(s^2, 1) H^-1``)."""
        tree, stops, n, K, nm, effs = self.tree, self.stops, self.n, self.K, self.nm, self.effs
        tilt = self.zero_tilt.copy()
        fitted = {i: e.with_params(np.zeros(e.n_params)) for i in chosen if (e := effs[i]) is not None}
        sizes = [self.Gs[i].shape[2] for i in chosen]
        theta = np.zeros(nm + sum(sizes))
        G = np.zeros((n * 2 * K, 0))
        live = np.zeros(0, dtype=bool)
        mount = np.zeros((K, 2))
        for _ in range(iterations):
            cur = self.declared + list(fitted.values())
            r = self.wh(imu_tilt_raw(tree, stops, cur, tilt) - mount).reshape(-1)
            G = np.concatenate([self.Gm.reshape(n * 2 * K, -1)]
                               + [self.wh(imu_jacobian(tree, stops, fitted.get(i), cur, tilt)).reshape(n * 2 * K, -1)
                                  for i in chosen], axis=1)
            live = np.any(G != 0.0, axis=0)
            dth = np.zeros(G.shape[1])
            dth[live], _ = _lstsq(G[:, live], r)
            theta = theta + dth
            mount[self.mount_imus] = theta[:nm].reshape(-1, 2)
            for i, p in zip(chosen, np.split(theta[nm:], np.cumsum(sizes)[:-1])):
                if effs[i] is None:
                    tilt = p.reshape(self.n_grp, 2).copy()
                else:
                    fitted[i] = fitted[i].with_params(p)
        cur = self.declared + list(fitted.values())
        r = self.wh(imu_tilt_raw(tree, stops, cur, tilt) - mount).reshape(-1)
        s2 = float(r @ r / max(r.size - int(live.sum()), 1))
        cov = np.zeros((theta.size, theta.size))
        if theta.size:
            cov[np.ix_(live, live)] = np.linalg.pinv(G[:, live].T @ G[:, live]) * max(s2, 1.0)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        return fitted, theta, tilt, mount, s2, sd

    def effects_out(self, sel: GainSelection, fitted: dict[int, Effect], theta: np.ndarray,
                    sd: np.ndarray) -> list[dict[str, Any]]:
        """Effect entries: ``base_tilt`` per group (tilt_x, tilt_y, CI) and the IMU-visible effects."""
        sizes = [self.Gs[i].shape[2] for i in sel.chosen]
        out: list[dict[str, Any]] = []
        tot0 = float(sel.base0.sum())
        prev = tot0
        for k, (i, th, s) in enumerate(zip(sel.chosen, np.split(theta, np.cumsum(sizes)[:-1]),
                                           np.split(sd, np.cumsum(sizes)[:-1]))):
            share = float(sel.steps[k]["heldout_gain"] * prev / tot0) if tot0 > 0 else 0.0
            prev = prev * (1.0 - sel.steps[k]["heldout_gain"])
            if self.effs[i] is None:
                out.append({"name": "base_tilt", "location": self.tree.root, "measurement": "imu",
                            "per_group": self._tilt_per_group(th, s), "share": share})
            else:
                f = fitted[i]
                out.append({"name": f.name, "location": f.location, "measurement": "imu",
                            "parameters": {p: float(v) for p, v in zip(f.param_names, th)},
                            "ci": {p: [float(v - 1.96 * q), float(v + 1.96 * q)]
                                   for p, v, q in zip(f.param_names, th, s)},
                            "sigma": {p: float(q) for p, q in zip(f.param_names, s)}, "share": share})
        return out

    def _tilt_per_group(self, th: np.ndarray, s: np.ndarray) -> dict[str, Any]:
        stops = self.stops
        tv, ts = th.reshape(self.n_grp, 2), s.reshape(self.n_grp, 2)
        return {g: {"tilt_x": float(tv[j, 0]), "tilt_y": float(tv[j, 1]),
                    "ci": {"tilt_x": [float(tv[j, 0] - 1.96 * ts[j, 0]), float(tv[j, 0] + 1.96 * ts[j, 0])],
                           "tilt_y": [float(tv[j, 1] - 1.96 * ts[j, 1]), float(tv[j, 1] + 1.96 * ts[j, 1])]},
                    "sigma": {"tilt_x": float(ts[j, 0]), "tilt_y": float(ts[j, 1])}}
                for j, g in enumerate(stops.group_names) if np.any(stops.group == j)}

    def rms_per_imu(self, err_idx: Sequence[int]) -> dict[str, list[float]]:
        """Held-out tilt RMS per IMU [rad], x / y, with the candidates ``err_idx``."""
        rr = self._cv_residual(self.stacked(err_idx))
        raw = np.einsum("nkij,nkj->nki", np.linalg.inv(self.W), rr.reshape(self.n, self.K, 2))
        return {k: [float(v) for v in np.sqrt(np.mean(raw[:, j] ** 2, axis=0))] for j, k in enumerate(self.stops.imus)}
