"""The diagnose engine: forward selection of effects on tracker points or poses, final fit, CIs, sigma refit."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.candidates import (
    Candidate,
    candidate_effects,
    chain_jacobians,
    measurement_jacobian,
    predict_nominal,
)
from ppoe_core.analysis.diagnose.imu import _imu_cost, diagnose_imu, imu_tilt_residuals
from ppoe_core.analysis.diagnose.linear import FitResult, LinearProblem, _identifiable_subset, _ssr, _stack, make_folds
from ppoe_core.analysis.diagnose.parsimony import simplify
from ppoe_core.analysis.diagnose.results import DiagnoseOptions, DiagnoseResult
from ppoe_core.analysis.diagnose.stats import (
    _paired_t,
    _point_covariance,
    _rms3,
    _rms_m,
    _rotation_covariance,
    _signed_rank_z,
)
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot


def diagnose(robot: Robot, stops: Stops, declared: Sequence[Effect] = (),
             perturbation_cov: Mapping[str, np.ndarray] | None = None,
             joint_noise: Mapping[str, float] | None = None,
             options: DiagnoseOptions | None = None) -> DiagnoseResult:
    """Find the catalogue effects that explain the residual of ``stops`` (module docstring).

    Parameters
    ----------
    robot : Robot
    stops : Stops
    declared : effects the model already declares (part of the nominal prediction)
    perturbation_cov : joint -> 6x6 covariance of the model's perturbation xi_j, in the tangent
        space right after the joint's origin (docs/conventions.md sec. 5)
    joint_noise : joint -> 1-sigma along the joint axis [rad or m]
    options : DiagnoseOptions

    Returns
    -------
    DiagnoseResult
    """
    options = options or DiagnoseOptions()
    tree = KinematicTree(robot)
    _check_finite(robot, stops)
    pert, jnoise = perturbation_cov or {}, joint_noise or {}
    lin = _linearise(tree, stops, declared, pert, jnoise)
    problem = LinearProblem(stops, lin.x0, lin.R0, lin.W_base, lin.W_rot)
    cands = _candidates(tree, stops, lin, options)
    mode, folds = make_folds(stops, options)
    all_rows = np.arange(len(stops))
    sel = _forward_selection(tree, problem, stops, cands, folds, options, all_rows)
    chosen, simplified = simplify(tree, problem, cands, sel.chosen, folds, options, all_rows, sel.e2)
    share_steps = sel.steps
    if simplified:
        sel, share_steps = _rescore(problem, stops, chosen, folds, sel)
    # locations the tracker cannot tell apart: let the accelerometers decide (not fitted to them)
    relocated = _relocate_by_imu(tree, problem, stops, declared, chosen, cands, all_rows) if stops.imus else []
    fit, ins_before, ins_after, lin_err = _final_fit(tree, stops, declared, chosen, problem, lin, all_rows)
    effects_out, found = _effect_entries(chosen, fit, share_steps, _rms_m(sel.R_before) ** 2)

    # sigma refit (NEES on held-out stops)
    ok = np.isfinite(sel.e2)
    nees_before, nees_after, k_scale, fitted_jn = _refit_sigma(
        tree, stops, lin.poses, lin.dq0, lin.dxi0, pert, jnoise, sel.Rb_after)
    floor = math.sqrt(float(np.mean(np.trace(lin.C_exp, axis1=-2, axis2=-1))))
    rms_b = _rms_m(sel.R_before)
    rms_a = _rms_m(sel.R_after)
    unexplained = math.sqrt(max(rms_a ** 2 - floor ** 2, 0.0))
    res = DiagnoseResult(
        effects=effects_out, residual_before=rms_b, residual_after=rms_a,
        residual_before_insample=ins_before, residual_after_insample=ins_after,
        noise_floor=floor, unexplained=unexplained, steps=sel.steps,
        rejected=[{"candidate": k, "reason": v} for k, v in sel.rejected.items()],
        nees_before=nees_before, nees_after=nees_after, sigma_scale=k_scale,
        linearisation_error=lin_err, cv=mode, n_stops=int(ok.sum()), n_sessions=len(np.unique(stops.session)),
        e2_before=np.sum(sel.R_before ** 2, axis=1), e2_after=np.sum(sel.R_after ** 2, axis=1), chosen=found)
    res.extra["per_group"] = {stops.group_names[g]: {"before": _scores(sel.R_before[stops.group == g]),
                                                     "after": _scores(sel.R_after[stops.group == g])}
                              for g in np.unique(stops.group)}
    if fitted_jn:
        res.extra["fitted_joint_noise"] = fitted_jn
    if simplified:
        res.extra["simplified"] = simplified
    if relocated:
        res.extra["relocated_by_imu"] = relocated
    if stops.imus:
        _accelerometer_extras(res, robot, tree, stops, declared, found, options, perturbation_cov, joint_noise)
    # a systematic residual remains if the held-out mean squared Mahalanobis distance under the
    # declared covariance exceeds its expectation 3 by more than 3 standard errors (chi^2_3 mean); the rows of
    # several reflectors at one stop share its perturbation draw: count stops (distinct configurations)
    m2 = float(np.nanmean(sel.e2))
    n_ok = _independent_rows(stops, np.isfinite(sel.e2))
    res.extra["heldout_mahalanobis2"] = m2
    res.extra["unexplained_significant"] = bool(m2 > 3.0 + 3.0 * math.sqrt(6.0 / max(n_ok, 1)))
    res.summary = _summary(res)
    return res


def _check_finite(robot: Robot, stops: Stops) -> None:
    """At least 6 stops; no NaN/inf in the measurements or in the joint values the measured link needs."""
    n = len(stops)
    if n < 6:
        raise PpoeError(f"diagnose: only {n} stops with measurements; need at least 6")
    bad = ~np.all(np.isfinite(stops.p_meas), axis=1)
    for jn, v in stops.q.items():
        if jn in stops.chain_joints(robot):
            bad |= ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeasurementError(f"diagnose: {int(bad.sum())} stops have non-finite measurements or joint "
                               f"values (first: stop {i} of {stops.group_names[stops.group[i]]}, session "
                               f"{stops.session_names[stops.session[i]]})")


@dataclass
class _Linearisation:
    """The nominal prediction with the declared effects, chain Jacobians and whitening (expected covariance of the
    measured point: declared PPOE covariance + sensor noise, base frame)."""

    x0: np.ndarray
    R0: np.ndarray | None
    poses: dict[str, np.ndarray]
    dq0: dict[str, np.ndarray]
    dxi0: dict[str, np.ndarray]
    chain: tuple
    base_R: np.ndarray | None
    nominal: dict[str, np.ndarray]
    C_exp: np.ndarray
    W_base: np.ndarray
    W_rot: np.ndarray | None


def _linearise(tree: KinematicTree, stops: Stops, declared: Sequence[Effect], pert: Mapping[str, np.ndarray],
               jnoise: Mapping[str, float]) -> _Linearisation:
    """Prediction, Jacobians and whitening at the declared model (see :class:`_Linearisation`)."""
    x0, R0, poses, dq0, dxi0 = predict_nominal(tree, stops, declared)
    base_R = None
    Jq, Jx, Fq, Fx = chain_jacobians(tree, stops, poses, dq0, dxi0)
    if stops.kind == "pose" and stops.base and stops.base != tree.root:
        base_R = poses[stops.base][..., :3, :3]
    nominal = tree.link_poses(stops.q)
    C_exp = _point_covariance(tree, stops, poses, dq0, dxi0, pert, jnoise)
    C_exp = C_exp + stops.sigma_rows()[:, None, None] ** 2 * np.eye(3)
    W_base = np.linalg.inv(np.linalg.cholesky(C_exp))
    W_rot = None
    if stops.kind == "pose":
        C_rot = _rotation_covariance(stops, Fq, Fx, pert, jnoise)
        W_rot = np.linalg.inv(np.linalg.cholesky(C_rot + stops.sigma_rot ** 2 * np.eye(3)))
    return _Linearisation(x0, R0, poses, dq0, dxi0, (Jq, Jx, Fq, Fx), base_R, nominal, C_exp, W_base, W_rot)


def _candidates(tree: KinematicTree, stops: Stops, lin: _Linearisation, options: DiagnoseOptions) -> list[Candidate]:
    """Catalogue effects at plausible locations that move the measurement at all (``options.candidates`` filter)."""
    cands = []
    for eff in candidate_effects(tree, stops):
        c = Candidate(eff, measurement_jacobian(tree, stops, eff, lin.nominal, lin.chain, lin.base_R))
        if options.candidates and not any(c.key.startswith(p) for p in options.candidates):
            continue
        if np.abs(c.G).max() > 0.0:
            cands.append(c)
    return cands


@dataclass
class _Selection:
    """Forward selection: chosen candidates, steps, rejections, held-out residuals before/after (metres, whitened
    base-frame rows ``Rb``) and the held-out squared Mahalanobis distance per stop ``e2``."""

    chosen: list[Candidate]
    steps: list[dict[str, Any]]
    rejected: dict[str, str]
    R_before: np.ndarray
    R_after: np.ndarray
    Rb_after: np.ndarray
    e2: np.ndarray


def _forward_selection(tree: KinematicTree, problem: LinearProblem, stops: Stops, cands: list[Candidate],
                       folds: Any, options: DiagnoseOptions, all_rows: np.ndarray) -> _Selection:
    """Greedy forward selection by held-out error with paired t and signed-rank statistics (module docstring)."""
    n = len(stops)
    chosen: list[Candidate] = []
    R_before, Rb_before, e2 = problem.heldout(_stack(chosen, n, stops.dim), folds)
    R_after, Rb_after = R_before, Rb_before
    steps: list[dict[str, Any]] = []
    rejected: dict[str, str] = {}
    while len(chosen) < options.max_effects:
        best = _best_candidate(tree, problem, stops, cands, chosen, rejected, folds, options, all_rows, e2)
        # (mse: mean whitened squared held-out error; reported RMS values are in metres)
        if best is None:
            break
        c2, mse1, gain, (t, z), e2c, key, Rc, Rbc = best
        step = {"candidate": c2.key, "accepted": bool(gain >= options.min_gain and t >= options.min_t),
                "heldout_rms": _rms_m(Rc), "heldout_mahalanobis2": mse1, "gain": gain, "t": t, "z": z}
        steps.append(step)
        if not step["accepted"]:
            break
        chosen.append(c2)
        e2 = e2c
        R_after, Rb_after = Rc, Rbc
    return _Selection(chosen, steps, rejected, R_before, R_after, Rb_after, e2)


def _independent_rows(stops: Stops, ok: np.ndarray) -> int:
    """Rows ``ok`` counted once per stop: distinct joint configurations (one row per reflector of a stop)."""
    if stops.links is None:
        return int(ok.sum())
    Q = np.column_stack([stops.q[j][ok] for j in sorted(stops.q)]) if stops.q else np.zeros((int(ok.sum()), 0))
    return int(np.unique(np.round(Q, 9), axis=0).shape[0]) if Q.size else int(ok.sum())


def _rescore(problem: LinearProblem, stops: Stops, chosen: list[Candidate], folds: Any,
             sel: _Selection) -> tuple[_Selection, list[dict[str, Any]]]:
    """After a simplification: held-out residuals of the new chosen set, and its cumulative held-out RMS per
    effect (the shares of the report)."""
    n = len(stops)
    cumulative = []
    for k in range(1, len(chosen) + 1):
        Rc, Rbc, e2c = problem.heldout(_stack(chosen[:k], n, stops.dim), folds)
        cumulative.append({"candidate": chosen[k - 1].key, "heldout_rms": _rms_m(Rc)})
    new = _Selection(chosen, sel.steps, sel.rejected, sel.R_before, Rc, Rbc, e2c) if chosen else sel
    return new, cumulative


def _best_candidate(tree: KinematicTree, problem: LinearProblem, stops: Stops, cands: list[Candidate],
                    chosen: list[Candidate], rejected: dict[str, str], folds: Any, options: DiagnoseOptions,
                    all_rows: np.ndarray, e2: np.ndarray) -> tuple | None:
    """The candidate with the lowest held-out error among the ``options.screen`` best screened in-sample."""
    n = len(stops)
    best = None
    screened = []
    G_now = _stack(chosen, n, stops.dim)
    ssr_now = _ssr(problem, G_now, all_rows)
    for c in cands:
        if c.key in rejected or any(c.key == k.key for k in chosen):
            continue
        if any(ch.effect.name == c.effect.name and ch.effect.location == c.effect.location for ch in chosen):
            continue
        c2, why, ssr = _identifiable_subset(problem, chosen, c, options, tree, all_rows)
        if c2 is None:
            rejected[c.key] = why
            continue
        screened.append((1.0 - ssr / ssr_now, c, c2))
    screened.sort(key=lambda z: -z[0])
    tried = []
    for _, c, c2 in screened[:options.screen]:
        Rc, Rbc, e2c = problem.heldout(_stack(chosen + [c2], n, stops.dim), folds)
        ok = np.isfinite(e2) & np.isfinite(e2c)
        if ok.sum() < 3:
            continue
        mse0, mse1 = float(np.mean(e2[ok])), float(np.mean(e2c[ok]))
        d = e2[ok] - e2c[ok]
        t = _paired_t(d)
        z = _signed_rank_z(d)
        gain = 1.0 - mse1 / mse0
        tried.append((c2, mse1, gain, (t, z), e2c, c.key, Rc, Rbc))
        if best is None or mse1 < best[1]:
            best = tried[-1]
    return _simplest_as_good(best, tried, options)


def _simplest_as_good(best: tuple | None, tried: list[tuple], options: DiagnoseOptions) -> tuple | None:
    """The parsimony rule (CONTRACT sec. 6): of the candidates that would be accepted, the one with the fewest
    parameters whose held-out error is not significantly worse than the best's (paired t below 2); among those,
    the lowest held-out error.  A zero offset is then a ``joint_offset``, not a ``link_error``."""
    if best is None:
        return None
    ok_best = np.isfinite(best[4])
    good = []
    for cand in tried:
        if (cand[0].effect.n_params >= best[0].effect.n_params or cand[2] < options.min_gain
                or cand[3][0] < options.min_t):
            continue
        ok = ok_best & np.isfinite(cand[4])
        if ok.sum() >= 3 and _paired_t(cand[4][ok] - best[4][ok]) < 2.0:
            good.append(cand)
    if not good:
        return best
    return min(good, key=lambda c: (c[0].effect.n_params, c[1]))


def _final_fit(tree: KinematicTree, stops: Stops, declared: Sequence[Effect], chosen: list[Candidate],
               problem: LinearProblem, lin: _Linearisation,
               all_rows: np.ndarray) -> tuple[FitResult, float, float, float]:
    """Final fit on all stops, relinearised at the estimate (Gauss-Newton on the full chain): fit, in-sample RMS
    before/after and the linearisation error of the selection stage at the final estimate."""
    n = len(stops)
    G = _stack(chosen, n, stops.dim)
    fit = problem.fit(G, all_rows, iterations=6)
    fit0 = problem.fit(G[..., :0], all_rows)
    ins_before = _rms3(problem.residuals(G[..., :0], np.zeros(0), fit0.regs, fit0.rows))
    ins_after = _rms3(problem.residuals(G, fit.theta, fit.regs, fit.rows))
    theta = fit.theta.copy()
    lin_err = 0.0
    for _ in range(3 if chosen else 0):
        current = _with_thetas(chosen, theta)
        xk, Rk, pk, dqk, dxik = predict_nominal(tree, stops, list(declared) + current)
        chain = chain_jacobians(tree, stops, pk, dqk, dxik)
        Gk = np.concatenate([measurement_jacobian(tree, stops, c.effect, lin.nominal, chain, lin.base_R)
                             for c in chosen], axis=-1)
        pk_problem = LinearProblem(stops, xk, Rk, lin.W_base, lin.W_rot)
        gn_step = pk_problem.fit(Gk, all_rows, iterations=6)
        theta = theta + gn_step.theta
        ins_after = _rms3(pk_problem.residuals(Gk, gn_step.theta, gn_step.regs, gn_step.rows))
        fit = FitResult(theta.copy(), gn_step.regs, gn_step.cov, gn_step.s2, gn_step.condition, gn_step.absorbed,
                        gn_step.rows)
        if np.all(np.abs(gn_step.theta) <= 1e-8 * np.abs(theta) + 1e-15):
            break
    if chosen:  # accuracy of the linear model used during selection, at the final estimate
        x_nl = predict_nominal(tree, stops, list(declared) + _with_thetas(chosen, theta))[0]
        lin_err = float(np.max(np.linalg.norm(x_nl - (lin.x0 + G[:, :3] @ theta), axis=1)))
    return fit, ins_before, ins_after, lin_err


def _effect_entries(chosen: list[Candidate], fit: FitResult, steps: list[dict[str, Any]],
                    mse_before: float) -> tuple[list[dict[str, Any]], list[Effect]]:
    """Contract entries (name, location, parameters, 95 % CI, sigma, share of the residual) and the effects."""
    effects_out: list[dict[str, Any]] = []
    found: list[Effect] = []
    i = 0
    for k, c in enumerate(chosen):
        P = c.effect.n_params
        th = fit.theta[i:i + P]
        sd = np.sqrt(np.maximum(np.diag(fit.cov)[i:i + P], 0.0))
        i += P
        eff = c.effect.with_params(th)
        found.append(eff)
        entry = eff.to_config()
        entry["ci"] = {name: [float(v - 1.96 * s), float(v + 1.96 * s)]
                       for name, v, s in zip(eff.param_names, th, sd)}
        entry["sigma"] = {name: float(s) for name, s in zip(eff.param_names, sd)}
        prev = mse_before if k == 0 else steps[k - 1]["heldout_rms"] ** 2
        entry["share"] = float((prev - steps[k]["heldout_rms"] ** 2) / mse_before)
        effects_out.append(entry)
    return effects_out, found


def _accelerometer_extras(res: DiagnoseResult, robot: Robot, tree: KinematicTree, stops: Stops,
                          declared: Sequence[Effect], found: list[Effect], options: DiagnoseOptions,
                          perturbation_cov: Mapping[str, np.ndarray] | None,
                          joint_noise: Mapping[str, float] | None) -> None:
    """Accelerometer tilt residuals before/after (in-sample, not used by the fit) and the accelerometer stage
    (without a ``base_tilt`` driven by the measured tilt: it is made of these accelerometers' readings)."""
    found = [e for e in found if not (e.name == "base_tilt" and getattr(e, "variable", None))]
    before = imu_tilt_residuals(tree, stops, list(declared))
    after = imu_tilt_residuals(tree, stops, list(declared) + found)
    res.extra["imu_tilt"] = {k: {"link": before[k]["link"], "n": before[k]["n"],
                                 "rms_before": before[k]["rms"], "rms_after": after[k]["rms"]}
                             for k in before}
    # accelerometer stage: per-file base tilt and IMU-visible effects on top of declared + found
    imu_fit = diagnose_imu(robot, stops, list(declared) + found, seed=options.seed,
                           sigma=options.imu_sigma if options.imu_sigma else 4e-4,
                           perturbation_cov=perturbation_cov, joint_noise=joint_noise)
    res.extra["imu_fit"] = {k: v for k, v in imu_fit.items() if k not in ("found", "tilt")}


def _relocate_by_imu(tree: KinematicTree, problem: LinearProblem, stops: Stops, declared: Sequence[Effect],
                     chosen: list[Candidate], cands: Sequence[Candidate], rows: np.ndarray) -> list[dict]:
    """Swap a chosen effect for the same effect at another location when the tracker data fit
    both equally well (in-sample weighted SSR within 0.5 %) and the accelerometer tilt residuals
    prefer the other location; ``chosen`` is modified in place.  Returns the swaps made."""
    swaps: list[dict] = []
    for k, c in enumerate(list(chosen)):
        others = [x for i, x in enumerate(chosen) if i != k]

        def fitted(cand: Candidate, others: list[Candidate] = others) -> tuple[float, list[Effect]]:
            G = _stack(others + [cand], len(stops), stops.dim)
            fit = problem.fit(G, rows, iterations=2)
            ssr = float(np.nansum(problem.whitened(problem.residuals(G, fit.theta, fit.regs, fit.rows),
                                                   fit.regs, fit.rows) ** 2))
            return ssr, _with_thetas(others + [cand], fit.theta)

        ssr0, effs0 = fitted(c)
        best = (_imu_cost(tree, stops, list(declared) + effs0), c)
        for alt in cands:
            if alt.effect.name != c.effect.name or alt.effect.location == c.effect.location \
                    or alt.G.shape[-1] != c.G.shape[-1] or any(alt.effect.location == o.effect.location
                                                               and alt.effect.name == o.effect.name for o in others):
                continue
            ssr1, effs1 = fitted(alt)
            if ssr1 > 1.005 * ssr0:
                continue
            th = effs1[-1].params
            if any(v < 0 for name, v in zip(alt.effect.param_names, th) if name in alt.effect.nonnegative):
                continue
            cost = _imu_cost(tree, stops, list(declared) + effs1)
            if cost < 0.8 * best[0]:
                best = (cost, alt)
        if best[1] is not c:
            swaps.append(
                {
                    "from": c.key,
                    "to": best[1].key,
                    "imu_cost_from": _imu_cost(tree, stops, list(declared) + effs0),
                    "imu_cost_to": best[0],
                }
            )
            chosen[k] = best[1]
    return swaps


def _with_thetas(chosen: Sequence[Candidate], theta: np.ndarray) -> list[Effect]:
    """The chosen effects with their slices of the stacked parameter vector."""
    out, i = [], 0
    for c in chosen:
        out.append(c.effect.with_params(theta[i : i + c.effect.n_params]))
        i += c.effect.n_params
    return out


def _summary(res: DiagnoseResult) -> str:
    if res.effects:
        names = ", ".join(f"{e['name']} at {e['location']}" for e in res.effects)
        head = f"found {len(res.effects)} effect(s): {names}"
    else:
        head = "no catalogue effect explains the residual significantly"
    tail = (
        f"held-out RMS {1e3 * res.residual_before:.3f} mm -> {1e3 * res.residual_after:.3f} mm "
        f"(noise floor {1e3 * res.noise_floor:.3f} mm)"
    )
    if res.extra.get("unexplained_significant"):
        tail += (
            f"; UNEXPLAINED: {1e3 * res.unexplained:.3f} mm RMS above the noise floor is not "
            f"explained by any catalogue effect (held-out mean Mahalanobis^2 "
            f"{res.extra['heldout_mahalanobis2']:.2f}, expected 3)"
        )
    return head + "; " + tail


def append_test_summary(res: DiagnoseResult) -> None:
    """One summary line per ``--test`` bag (``res.extra["test"]``): RMS and p95 before -> after [mm]."""
    for name, t in res.extra.get("test", {}).items():
        b = t["before"]
        if t["n"] and b["n"]:
            res.summary += (f"\ntest {name} ({t['n']} stops; {t['protocol']}): RMS {1e3 * b['rms']:.3f} -> "
                            f"{1e3 * t['rms']:.3f} mm, p95 {1e3 * b['p95']:.3f} -> {1e3 * t['p95']:.3f} mm")
        else:
            res.summary += f"\ntest {name}: no stop could be scored ({t['unscored']} without a registration)"


def _scores(R: np.ndarray) -> dict[str, float]:
    """Error statistics of residuals (n, 3) [m] in a z-up frame: RMS 3D, max 3D, r95 xy, r95 z."""
    R = R[np.all(np.isfinite(R), axis=1)]
    if not R.size:
        return {"n": 0}
    n3 = np.linalg.norm(R, axis=1)
    return {
        "n": int(R.shape[0]),
        "rms": float(np.sqrt(np.mean(n3**2))),
        "max": float(n3.max()),
        "r95_xy": float(np.percentile(np.linalg.norm(R[:, :2], axis=1), 95)),
        "r95_z": float(np.percentile(np.abs(R[:, 2]), 95)),
    }


def _refit_sigma(
    tree: KinematicTree,
    stops: Stops,
    poses: Mapping,
    dq: Mapping,
    dxi: Mapping,
    pert: Mapping[str, np.ndarray],
    jnoise: Mapping[str, float],
    Rb: np.ndarray,
) -> tuple[float, float, float, dict[str, float] | None]:
    """Scale ``k`` of the model covariance so that the mean held-out NEES is 3.

    ``C_i = k^2 C_model,i + sigma^2 I`` with ``C_model`` the first-order PPOE covariance of the
    measured point (base-frame axes) and ``Rb`` the held-out residuals in base-frame axes.
    A model without any uncertainty gets a common joint noise ``k`` [rad or m] on the movable
    joints of the chain instead.  Returns ``(NEES at k=1, NEES at k, k, fitted joint noise)``.
    """
    fitted: dict[str, float] | None = None
    if pert or jnoise:
        C_model = _point_covariance(tree, stops, poses, dq, dxi, pert, jnoise)
    else:
        unit = {j: 1.0 for j in stops.chain_joints(tree.robot) if tree.robot.joints[j].independent}
        C_model = _point_covariance(tree, stops, poses, dq, dxi, {}, unit)
    ok = np.all(np.isfinite(Rb), axis=1)
    if not ok.any():
        return float("nan"), float("nan"), 1.0, None
    S0 = stops.sigma_rows()[ok, None, None] ** 2 * np.eye(3)

    def nees(k: float) -> float:
        C = k * k * C_model[ok] + S0
        return float(np.mean(np.einsum("ni,nij,nj->n", Rb[ok], np.linalg.inv(C), Rb[ok])))

    n1 = nees(1.0) if (pert or jnoise) else float("nan")
    lo, hi = 1e-9, 1e4
    if nees(lo) <= 3.0:
        k = lo
    elif nees(hi) >= 3.0:
        k = hi
    else:
        for _ in range(100):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if nees(mid) > 3.0 else (lo, mid)
        k = math.sqrt(lo * hi)
    if not (pert or jnoise):
        fitted = {j: float(k) for j in stops.chain_joints(tree.robot) if tree.robot.joints[j].independent}
    return n1, nees(k), k, fitted


def protocol_scores(robot: Robot, stops: Stops, effects: Sequence[Effect] = ()) -> dict[str, float]:
    """Score a model with ``effects`` by the stationing protocol, with nothing fitted but the
    registrations: per session Kabsch on the ``reg_mask`` stops, error of the ``score_mask``
    stops (measured minus predicted, measurement frame).  Returns RMS / max 3D, r95 xy and z [m]
    and ``n`` (see the Hilti README "Baseline").
    """
    tree = KinematicTree(robot)
    x = predict_nominal(tree, stops, list(effects))[0]
    problem = LinearProblem(stops, x, None)
    G0 = np.zeros((len(stops), 3, 0))
    regs = problem.kabsch_regs(G0, np.zeros(0), np.flatnonzero(stops.reg_mask))
    rows = np.flatnonzero(stops.score_mask & ~stops.reg_mask & np.isin(stops.session, list(regs)))
    return _scores(problem.residuals(G0, np.zeros(0), regs, rows))
