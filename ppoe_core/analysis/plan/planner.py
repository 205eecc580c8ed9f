"""``plan()``: the D-optimal poses for a set of target effects, their predicted CIs and the random baseline.

1. Candidates: :func:`~ppoe_core.analysis.plan.constraints.sample_candidates` (random feasible configurations,
   half of the joint values at an end of their interval: optimal designs sit there); a second, uniform, draw of
   as many feasible configurations is the random baseline and the held-out poses.
2. Information per candidate from the engine's tracker block (:mod:`information`), registration eliminated.
3. Design: greedy + exchange on ``log det`` (:mod:`design`), then each pose refined locally (:mod:`refine`); with
   ``given`` data, its reduced information is a fixed part of every evaluation (its own registration).
4. Predictions: covariance ``I^-1`` of the target parameters (whitened with the declared sensor noise: what
   ``ppoe diagnose --effects`` reports when the model explains the data to the noise floor); 95 % half-widths
   ``1.96 sigma``; the predicted held-out error (RMS reflector distance at random feasible poses after the fit:
   sensor noise plus the fitted parameters' and the registration's uncertainty propagated); Sun and Hollerbach's
   O1..O5 and the condition number; the same for ``n`` and ``4 n`` random feasible poses (median over
   :data:`RANDOM_REPEATS` draws).
5. Order: a nearest-neighbour tour in joint space (largest joint move, the time-limiting one) from ``start``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core.analysis.plan.constraints import Constraints, sample_candidates
from ppoe_core.analysis.plan.design import Design, design, minimax, observability_indices
from ppoe_core.analysis.plan.information import (
    PixelDesign,
    PoseInformation,
    Target,
    pose_information,
    reduced_information,
)
from ppoe_core.analysis.plan.refine import refine
from ppoe_core.errors import PpoeError
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["PlanOptions", "PlanResult", "Prediction", "plan", "predict", "tour", "information_bound", "RANDOM_REPEATS",
           "Z95"]

#: random baselines: median over this many draws
RANDOM_REPEATS = 20
#: 95 % normal quantile (the half-width of the intervals ``ppoe diagnose`` reports)
Z95 = 1.96


@dataclass
class PlanOptions:
    """``n`` poses, ``candidates`` random feasible configurations to choose from, the RNG ``seed``, ``start``
    configuration of the tour (joint -> value; missing: the first planned pose); ``extremes``: candidates' share of
    joints at an end of their interval (the random baselines are uniform draws)."""

    n: int = 30
    candidates: int = 2000
    seed: int = 0
    start: dict[str, float] = field(default_factory=dict)
    extremes: float = 0.5  #: :func:`sample_candidates`' probability of a joint at an end of its interval
    refine: bool = True  #: move each planned pose to a better feasible configuration near it (:mod:`refine`)
    pixel_sigma: float | None = None  #: with a camera in the constraints: its tag pixels in the design [px]
    minimax: bool = False  #: second stage: the worst CI relative to 4N random poses' (:func:`design.minimax`)


@dataclass
class Prediction:
    """Predicted 95 % half-widths (P,) of the target parameters, their covariance, the held-out RMS [m] and the
    observability indices of a pose set."""

    ci95: np.ndarray
    cov: np.ndarray
    heldout_rms: float
    indices: dict[str, float]


@dataclass
class PlanResult:
    """The plan: configurations in execution order (joint -> (n,)), parameter names, predictions for the plan and
    the random baselines (``random_n``, ``random_4n``: median half-widths), the design, rejection counts."""

    q: dict[str, np.ndarray]
    names: list[str]
    planned: Prediction
    random_n: Prediction
    random_4n: Prediction
    design: Design
    rejected: dict[str, int]
    n_candidates: int
    notes: list[str] = field(default_factory=list)
    #: (P,) :func:`information_bound` over the candidates, the random draw and the refined poses
    bound_ci95: np.ndarray | None = None


def _safe_inv(H: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    return np.linalg.pinv(H / d[:, None] / d[None, :]) / d[:, None] / d[None, :]


def predict(info: PoseInformation, idx: np.ndarray, base: np.ndarray | None = None,
            heldout: PoseInformation | None = None) -> Prediction:
    """:class:`Prediction` of the candidates ``idx`` of ``info`` (module docstring); the held-out error is averaged
    over the poses of ``heldout`` (random feasible poses; default: every candidate of ``info``)."""
    test = heldout if heldout is not None else info
    idx = np.asarray(idx, dtype=int)
    A, B, C = info.A[idx].sum(0), info.B[idx].sum(0), info.C[idx].sum(0)
    P, K = B.shape
    full = np.block([[A + (base if base is not None else 0.0), B], [B.T, C]])
    cov_full = _safe_inv(full)
    H = reduced_information(A, B, C) + (base if base is not None else 0.0)
    cov = cov_full[:P, :P]
    # held out: whitened rows times sigma back to metres; [G N] cov [G N]^T per component
    m = test.points if test.points >= 0 else test.G.shape[1]  # tracker components only
    GN = np.concatenate([test.G[:, :m], test.N[:, :m]], axis=2) * test.sigma[:, :m, None]
    var = np.einsum("umi,ij,umj->um", GN, cov_full, GN) + test.sigma[:, :m] ** 2
    R = max(m // 3, 1)
    rms = float(np.sqrt(np.mean(var.reshape(var.shape[0], R, -1).sum(-1))))
    return Prediction(Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0)), cov, rms,
                      observability_indices(H, info.scale, idx.size))


def _random_baseline(info: PoseInformation, n: int, rng: np.random.Generator,
                     base: np.ndarray | None) -> Prediction:
    """Median (over :data:`RANDOM_REPEATS` draws of ``n`` distinct candidates) of the predicted half-widths and
    held-out RMS; the indices and covariance of the median draw (by log det)."""
    M = info.A.shape[0]
    preds = [predict(info, rng.choice(M, size=min(n, M), replace=False), base) for _ in range(RANDOM_REPEATS)]
    o1 = np.array([p.indices["O1"] for p in preds])
    mid = preds[int(np.argsort(o1)[len(o1) // 2])]
    return Prediction(np.median(np.stack([p.ci95 for p in preds]), axis=0), mid.cov,
                      float(np.median([p.heldout_rms for p in preds])), mid.indices)


def _pool(a: PoseInformation, b: PoseInformation) -> PoseInformation:
    """The candidates of ``a`` followed by those of ``b`` (same parameters, scale and components)."""
    def cat(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.concatenate([x, y])

    return PoseInformation(cat(a.A, b.A), cat(a.B, b.B), cat(a.C, b.C), cat(a.G, b.G), cat(a.N, b.N), a.scale,
                           cat(a.sigma, b.sigma), a.points)


def information_bound(info: PoseInformation, n: int, base: np.ndarray | None = None) -> np.ndarray:
    """Smallest 95 % half-width (P,) any ``n`` of the poses of ``info`` can give each parameter: with the others
    and the registration eliminated the information of parameter ``k`` is at most ``sum_S A_u,kk`` (eliminating
    nuisances only removes information), so ``var_k >= 1 / (sum of the n largest A_u,kk (+ base_kk))``.  A
    parameter whose bound is wider than a reference cannot be made as tight as the reference by choosing poses from
    ``info``, whatever the criterion."""
    a = np.sort(np.diagonal(info.A, axis1=1, axis2=2), axis=0)[::-1][:n].sum(0)
    a = a + (np.diag(base) if base is not None else 0.0)
    with np.errstate(divide="ignore"):
        return np.asarray(Z95 / np.sqrt(a))


def _minimax_stage(info: PoseInformation, q: dict[str, np.ndarray], joints: list[str], d: Design, Q: np.ndarray,
                   final: PoseInformation, reference: Prediction, given: np.ndarray | None
                   ) -> tuple[Design, np.ndarray, PoseInformation, np.ndarray]:
    """Second stage (:func:`~ppoe_core.analysis.plan.design.minimax`) from the (refined) D-optimal poses ``Q`` over
    the candidates plus those poses; reference: the 4N-random median half-widths.  Returns the design (``chosen``:
    indices into the pool), its poses, the pool and the indices."""
    Qc = np.stack([q[j] for j in joints], axis=1)
    if final is info:  # not refined: the D-optimal poses are candidates
        pool, Qpool, start = info, Qc, d.chosen
    else:
        pool, Qpool = _pool(info, final), np.concatenate([Qc, Q])
        start = info.A.shape[0] + np.arange(Q.shape[0])
    mm = minimax(pool, start, (reference.ci95 / Z95) ** 2, given)
    d.chosen, d.log_det, d.minimax_exchanges = mm.chosen, mm.log_det, mm.exchanges
    return d, Qpool[mm.chosen], pool, mm.chosen


def tour(Q: np.ndarray, start: np.ndarray | None) -> np.ndarray:
    """Order (n,) of the rows of ``Q`` (n, J): nearest neighbour by the largest joint move, from ``start`` (J,) or
    from row 0."""
    n = Q.shape[0]
    left = list(range(n))
    cur = np.asarray(start, dtype=float) if start is not None else Q[0]
    order = []
    while left:
        d = np.max(np.abs(Q[left] - cur), axis=1)
        k = left.pop(int(np.argmin(d)))
        order.append(k)
        cur = Q[k]
    return np.array(order, dtype=int)


def plan(tree: KinematicTree, trackers: Sequence, targets: Sequence[Target], constraints: Constraints,
         options: PlanOptions, declared: Sequence[Effect] = (), given: np.ndarray | None = None) -> PlanResult:
    """Plan ``options.n`` poses (module docstring); ``given``: reduced information (P, P) of data already recorded.

    Raises
    ------
    PpoeError
        Fewer poses than parameters (without given data), an empty feasible set, a target no candidate observes.
    """
    names = [n for t in targets for n in t.names]
    if given is None and options.n < len(names):
        raise PpoeError(f"plan: --n {options.n} poses is fewer than the {len(names)} target parameters "
                        f"({', '.join(names)})")
    rng = np.random.default_rng(options.seed)
    q, rejected = sample_candidates(tree, constraints, options.candidates, rng, extremes=options.extremes)
    px = PixelDesign(constraints, options.pixel_sigma) if options.pixel_sigma and constraints.camera else None
    info = pose_information(tree, trackers, q, targets, declared, pixels=px)
    q_rand, _ = sample_candidates(tree, constraints, options.candidates, rng)
    rand = pose_information(tree, trackers, q_rand, targets, declared, pixels=px)
    d = design(info, options.n, given)
    joints = list(q)
    Q = np.stack([q[j][d.chosen] for j in joints], axis=1)
    final, idx = info, d.chosen
    if options.refine:
        ref = refine(tree, trackers, targets, declared, constraints, Q, info.scale, given, rng, pixels=px)
        Q, final, idx, d.log_det, d.refined = ref.Q, ref.info, np.arange(options.n), ref.log_det, ref.moved
    random_n = _random_baseline(rand, options.n, rng, given)  # after the refinement: its draws as in round 1
    random_4n = _random_baseline(rand, 4 * options.n, rng, given)
    pool = _pool(info, final) if final is not info else info
    bound = information_bound(_pool(pool, rand), options.n, given)  # over every configuration the plan has seen
    if options.minimax:
        d, Q, final, idx = _minimax_stage(info, q, joints, d, Q, final, random_4n, given)
    start = np.array([options.start.get(j, 0.0) for j in joints]) if options.start else None
    order = tour(Q, start)
    d.chosen, Q, idx = d.chosen[order], Q[order], idx[order]
    notes = []
    if not constraints.capsules:
        notes.append("self-collision not checked: the URDF has no <collision> geometry")
    if constraints.skipped_meshes:
        notes.append(f"{constraints.skipped_meshes} collision meshes not modelled (spheres, cylinders, boxes only)")
    return PlanResult({j: Q[:, i] for i, j in enumerate(joints)}, names, predict(final, idx, given, rand),
                      random_n, random_4n, d, rejected, int(info.A.shape[0]), notes, bound)


def summary(result: PlanResult) -> dict[str, Any]:
    """The JSON-able summary of a plan (``plan.json``)."""
    def pred(p: Prediction) -> dict[str, Any]:
        return {"ci95": dict(zip(result.names, p.ci95.tolist())), "heldout_rms": p.heldout_rms,
                "indices": p.indices}

    return {"n": int(result.design.chosen.size), "parameters": result.names,
            "planned": pred(result.planned), "random_n": pred(result.random_n),
            "random_4n": pred(result.random_4n),
            "design": {"log_det": result.design.log_det, "exchange_passes": result.design.passes,
                       "exchanges": result.design.exchanges, "refined_moves": result.design.refined,
                       "minimax_exchanges": result.design.minimax_exchanges,
                       "candidates": result.n_candidates},
            "information_bound": ({} if result.bound_ci95 is None else
                                  {"ci95": dict(zip(result.names, result.bound_ci95.tolist())),
                                   "over_random_4n": dict(zip(result.names,
                                                              (result.bound_ci95 / result.random_4n.ci95).tolist()))}),
            "rejected_draws": result.rejected, "notes": result.notes}
