"""The PPOE perturbation covariances ``Sigma_i`` (paper eq. 16-18) learned from the residual the effects leave.

A residual row ``r_n`` (d components: a tracker point, a pose) is modelled as ``N(0, C_n)`` with

    ``C_n = a^2 S_n + sum_g lam_g D_{g,n}``,   ``D_{g,n} = sum_{(j, c) in g} J_{j,n} P_{j,c} J_{j,n}^T``

(first order of eq. 18): ``S_n`` the declared sensor noise (``a`` its scale), ``J_{j,n}`` the derivative of the
measurement w.r.t. the insertion ``xi_j`` of joint ``j`` (tangent right after the joint's origin, ``[rho; theta]``),
and ``P_{j,c}`` the projector of one *axis class* ``c`` of that tangent:

* ``axial``: rotation about the joint axis (``theta`` along ``u_j``; for a revolute joint the same as joint noise),
* ``lateral``: rotation perpendicular to it (both perpendicular directions alike),
* ``translation``: the three translations alike;

and for a fixed joint (no axis; e.g. a mount plate with a declared perturbation) ``rot_x``, ``rot_y``, ``rot_z``
(about its frame's axes) and ``translation``.

A *component* ``g`` is one variance ``lam_g`` shared by one or more (joint, class) pairs: so ``Sigma_j = sum_c
lam_{g(j,c)} P_{j,c}`` (6x6, right-after-origin tangent).  The variances are maximum-likelihood estimates
(L-BFGS-B on ``log lam`` with the analytic gradient ``d(-2 log L)/d lam_g = sum_n tr(C_n^-1 D_gn) - u_n^T D_gn u_n``,
``u_n = C_n^-1 r_n``), their 95 % intervals from the Fisher information of the log-variances
(``F_gh = 1/2 sum_n tr(C^-1 D_g C^-1 D_h) lam_g lam_h``).

The structure is chosen by a parsimony rule like the effects': starting from one component per joint and class,
a backward search removes a component (its variance to zero) or merges two components of the same class (joints
adjacent in the order of their variances) while ``-2 log L`` rises by less than ``ln n`` (BIC, ``n`` rows) per
parameter saved.  What the data cannot tell apart (the translation of the last joint and isotropic sensor noise,
for a point) ends merged or removed: the sensor noise is estimated beside the components.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core.analysis.diagnose.block import ResidualBlock
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["AXIS_CLASSES", "FIXED_CLASSES", "ComponentEstimate", "ComponentFit", "PerturbationFit", "axis_projectors",
           "component_matrices", "fit_components", "joint_axes", "learn_perturbations", "sigma_from_components"]

#: the axis classes of a joint's insertion (module docstring)
AXIS_CLASSES = ("axial", "lateral", "translation")
#: the classes of a fixed joint's insertion (no axis: a mount plate bends about its own frame's axes)
FIXED_CLASSES = ("rot_x", "rot_y", "rot_z", "translation")
#: two-sided normal quantile of the reported intervals (95 %)
Z95 = 1.959963984540054
#: lower bound of a variance relative to the scale of the data (log-parametrisation needs one; a component at it
#: is removed by the parsimony rule)
MIN_RELATIVE = 1e-8
#: the sensor's lower bound, relative: C_n stays positive definite whatever the perturbation components span
MIN_SENSOR = 1e-6
#: Fisher-scoring iterations at most, and the fall of ``-2 log L`` per row below which it has converged
MAX_ITER = 200
CONVERGED = 1e-7
#: simplifications refitted per step of the parsimony search (the cheapest by their Wald statistic)
REFIT_BEST = 3
#: a change of ``-2 log L`` below this is a tie (prefer the earlier, a merge)
TIE = 1e-3
#: a log-variance interval wider than this half-width is reported as [0, inf] (the data do not see the component)
MAX_LOG_WIDTH = 50.0


def axis_projectors(axis: ArrayLike | None) -> dict[str, np.ndarray]:
    """Projectors (6, 6) of the axis classes of an insertion ``[rho; theta]``: for a joint axis ``axis`` (3,) (joint
    frame; unit length is enforced) :data:`AXIS_CLASSES`; for None (a fixed joint: no axis) :data:`FIXED_CLASSES`,
    the rotations about the joint frame's x, y, z apart."""
    if axis is None:
        fixed = {c: np.zeros((6, 6)) for c in FIXED_CLASSES}
        for k, c in enumerate(FIXED_CLASSES[:3]):
            fixed[c][3 + k, 3 + k] = 1.0
        fixed["translation"][:3, :3] = np.eye(3)
        return fixed
    u = np.asarray(axis, dtype=float)
    u = u / max(float(np.linalg.norm(u)), 1e-300)
    out = {c: np.zeros((6, 6)) for c in AXIS_CLASSES}
    out["axial"][3:, 3:] = np.outer(u, u)
    out["lateral"][3:, 3:] = np.eye(3) - np.outer(u, u)
    out["translation"][:3, :3] = np.eye(3)
    return out


def joint_axes(tree: KinematicTree, joints: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """joint -> unit axis (3,) in its joint frame, for ``joints`` (default: every movable joint)."""
    rj = tree.robot.joints
    names = [j for j in rj if rj[j].movable] if joints is None else list(joints)
    return {j: np.asarray(rj[j].axis, dtype=float) for j in names}


def component_matrices(block: ResidualBlock, effects: Sequence[Effect],
                       axes: Mapping[str, ArrayLike | None]) -> dict[tuple[str, str], np.ndarray]:
    """``J_j P_{j,c} J_j^T`` (n, d, d) of each joint in ``axes`` and axis class at the model ``effects``: the
    block's own first-order propagation of a unit covariance on that class (:meth:`ResidualBlock.linearise`'s
    ``Q``), so any measurement kind works; pairs the block does not see (all zero) are left out."""
    out: dict[tuple[str, str], np.ndarray] = {}
    for j, u in axes.items():
        for c, P in axis_projectors(u).items():
            Q = block.linearise(effects, (), {j: P}, {}).Q
            if np.any(np.abs(Q) > 0):
                out[(j, c)] = Q
    return out


@dataclass
class ComponentEstimate:
    """One learned variance shared by ``members`` ((joint, axis class) pairs).

    ``variance`` [rad^2 or m^2 per direction of the class], ``ci``: its 95 % interval (from the Fisher information
    of ``log variance``), ``sigma`` = sqrt(variance)."""

    members: tuple[tuple[str, str], ...]
    variance: float
    ci: tuple[float, float]

    @property
    def sigma(self) -> float:
        return float(np.sqrt(max(self.variance, 0.0)))

    @property
    def name(self) -> str:
        joints = "+".join(j for j, _ in self.members)
        return f"{joints}/{self.members[0][1]}"

    def to_json(self) -> dict[str, Any]:
        return {"joints": [j for j, _ in self.members], "axis": self.members[0][1], "sigma": self.sigma,
                "variance": self.variance, "ci": [float(self.ci[0]), float(self.ci[1])],
                "sigma_ci": [float(np.sqrt(max(self.ci[0], 0.0))), float(np.sqrt(max(self.ci[1], 0.0)))]}


@dataclass
class PerturbationFit:
    """The learned covariances: components (with CIs), the sensor scale, the likelihood and the search steps."""

    components: list[ComponentEstimate]
    sensor_scale: float
    sensor_ci: tuple[float, float]
    neg2loglik: float
    n_rows: int
    removed: list[tuple[str, str]] = field(default_factory=list)
    steps: list[str] = field(default_factory=list)

    def covariances(self, axes: Mapping[str, ArrayLike | None]) -> dict[str, np.ndarray]:
        """joint -> ``Sigma_j`` (6, 6) (tangent right after the joint's origin, ``[rho; theta]``) for the joints
        with an axis in ``axes``; joints of no component are left out (exact)."""
        return sigma_from_components(self.components, axes)

    def to_json(self) -> dict[str, Any]:
        return {"components": [c.to_json() for c in self.components], "sensor_scale": self.sensor_scale,
                "sensor_scale_ci": list(self.sensor_ci), "neg2loglik": self.neg2loglik, "n_rows": self.n_rows,
                "removed": [f"{j}/{c}" for j, c in self.removed], "steps": list(self.steps)}


def sigma_from_components(components: Sequence[ComponentEstimate],
                          axes: Mapping[str, ArrayLike | None]) -> dict[str, np.ndarray]:
    """``Sigma_j = sum_c lam_{g(j,c)} P_{j,c}`` per joint (module docstring)."""
    out: dict[str, np.ndarray] = {}
    for comp in components:
        for j, c in comp.members:
            if j in axes:
                out[j] = out.get(j, np.zeros((6, 6))) + comp.variance * axis_projectors(axes[j])[c]
    return out


@dataclass
class ComponentFit:
    """One maximum-likelihood fit of a fixed structure (:func:`fit_components`)."""

    lam: np.ndarray  #: (K + 1,) sensor variance scale first
    cost: float  #: -2 log L (without the constant)
    fisher: np.ndarray  #: (K + 1, K + 1) Fisher information of log lam


def fit_components(r: np.ndarray, S: np.ndarray, D: Sequence[np.ndarray], start: np.ndarray | None = None,
                   max_iter: int = MAX_ITER) -> ComponentFit:
    """Maximum-likelihood ``a^2`` and ``lam_g`` of ``C_n = a^2 S_n + sum_g lam_g D_gn`` for rows ``r`` (n, d)
    (module docstring); ``S``, ``D[g]``: (n, d, d).  ``start``: a previous estimate (K + 1,) to refine.

    Fisher scoring in the variances: ``F lam_new = b``, ``F_gh = 1/2 sum_n tr(C^-1 A_g C^-1 A_h)``, ``b_g = 1/2
    sum_n u_n^T A_g u_n`` (the Newton step with the expected information), solved with ``lam >= floor`` (bounded
    least squares on the quadratic model) and halved while ``-2 log L`` does not fall."""
    A = np.stack([S, *D]) if D else S[None]
    scale = np.array([max(_alone(r, Ag), 1e-300) for Ag in A])
    floor = scale * MIN_RELATIVE
    floor[0] = scale[0] * MIN_SENSOR  # the sensor keeps every C_n regular
    lam = np.maximum(scale / len(A) if start is None else np.asarray(start, dtype=float), floor)
    cost, F, b = _score(r, A, lam)
    if not np.isfinite(cost):  # a start numerically singular somewhere: from the even split instead
        lam = np.maximum(scale / len(A), floor)
        lam[0] = max(lam[0], scale[0])  # the sensor alone of the residual's size: S_n is regular
        cost, F, b = _score(r, A, lam)
    for _ in range(max_iter):
        step = _newton_step(F, b, lam, floor, scale)
        for _half in range(20):
            trial = lam + step
            c_new, F_new, b_new = _score(r, A, trial)
            if c_new <= cost + 1e-9 * abs(cost):
                break
            step = 0.5 * step
        else:
            break
        done = cost - c_new < CONVERGED * max(r.shape[0], 1)
        lam, cost, F, b = trial, c_new, F_new, b_new
        if done:
            break
    fisher = F * np.outer(lam, lam)  # of log lam
    return ComponentFit(lam, cost, fisher)


def _newton_step(F: np.ndarray, b: np.ndarray, lam: np.ndarray, floor: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The bounded Newton step: ``x`` minimising the quadratic model ``1/2 x^T F x - b^T x`` of ``-log L`` over
    ``x >= floor`` (variables scaled by ``scale`` for conditioning), minus ``lam``."""
    from scipy.optimize import lsq_linear

    Fs = F * np.outer(scale, scale)
    Fs = Fs + 1e-12 * np.trace(Fs) / len(Fs) * np.eye(len(Fs))
    L = np.linalg.cholesky(Fs)
    sol = lsq_linear(L.T, np.linalg.solve(L, b * scale), bounds=(floor / scale, np.inf), method="bvls")
    return np.asarray(sol.x) * scale - lam


def _score(r: np.ndarray, A: np.ndarray, lam: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``-2 log L`` (without the constant), the Fisher information ``F`` (in the variances) and ``b``
    (:func:`fit_components`) at ``lam``."""
    C = np.tensordot(lam, A, axes=1)
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:  # not positive definite to machine precision: no likelihood here
        return float("inf"), np.zeros((len(A), len(A))), np.zeros(len(A))
    CiA = np.linalg.solve(C[None], A)  # (K+1, n, d, d): C^-1 A_g
    u = np.linalg.solve(C, r[..., None])[..., 0]
    cost = float(2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1))) + np.einsum("ni,ni->", r, u))
    F = 0.5 * np.einsum("gnij,hnji->gh", CiA, CiA)
    b = 0.5 * np.einsum("ni,gnij,nj->g", u, A, u)
    return cost, F, b


def _alone(r: np.ndarray, D: np.ndarray) -> float:
    """The variance scale if ``D`` alone explained ``r`` in total size: ``sum |r|^2 / sum tr D``."""
    return float(np.einsum("ni,ni->", r, r) / max(float(np.trace(D, axis1=-2, axis2=-1).sum()), 1e-300))


def _intervals(fit: ComponentFit) -> list[tuple[float, float]]:
    """95 % intervals of each variance from the Fisher information of the log-variances (a singular direction
    gives [0, inf])."""
    try:
        cov = np.linalg.inv(fit.fisher)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        sd = np.full(fit.lam.size, np.inf)
    out = []
    for lam, s in zip(fit.lam, sd):
        out.append((float(lam * np.exp(-Z95 * s)), float(lam * np.exp(Z95 * s))) if Z95 * s < MAX_LOG_WIDTH
                   else (0.0, float("inf")))
    return out


def learn_perturbations(r: np.ndarray, S: np.ndarray, parts: Mapping[tuple[str, str], np.ndarray],
                        dof_fraction: float = 1.0, select: bool = True,
                        groups: Sequence[Sequence[tuple[str, str]]] | None = None) -> PerturbationFit:
    """Learn the perturbation components (module docstring).

    Parameters
    ----------
    r : ndarray (n, d)
        Residual rows (held-out, or in-sample corrected by ``dof_fraction``); non-finite rows are ignored.
    S : ndarray (n, d, d)
        Declared sensor covariance of the rows.
    parts : (joint, axis class) -> ndarray (n, d, d)
        ``J_j P_{j,c} J_j^T`` of each candidate pair (:func:`component_matrices`).
    dof_fraction : float
        Share of the residual's degrees of freedom left after the fit (in-sample residuals are smaller).
    select : bool
        Run the parsimony search; else keep ``groups`` (default: one component per pair) as given.
    groups : the starting structure (default one component per pair).
    """
    ok = np.all(np.isfinite(r), axis=1)
    r = r[ok] / np.sqrt(dof_fraction)
    S = S[ok]
    parts = {k: v[ok] for k, v in parts.items() if np.any(np.abs(v[ok]) > 0)}
    struct = [tuple(g) for g in groups] if groups is not None else [(k,) for k in parts]
    struct = [g for g in struct if all(m in parts for m in g)]
    n = int(r.shape[0])

    def mats(st: Sequence[tuple[tuple[str, str], ...]]) -> list[np.ndarray]:
        return [np.sum([parts[m] for m in g], axis=0) for g in st]

    fit = fit_components(r, S, mats(struct))
    removed: list[tuple[str, str]] = []
    steps: list[str] = []
    if select:
        while struct:
            move = _best_move(r, S, struct, fit, mats)
            if move is None or move[1].cost - fit.cost >= np.log(max(n, 2)):
                break
            new_struct, new_fit, what = move
            if what.startswith("remove"):
                removed.extend(m for g in struct if g not in new_struct for m in g
                               if not any(m in h for h in new_struct))
            steps.append(f"{what} (-2 log L +{new_fit.cost - fit.cost:.2f} < ln n = {np.log(max(n, 2)):.2f})")
            struct, fit = new_struct, new_fit
    cis = _intervals(fit)
    comps = [ComponentEstimate(tuple(g), float(lam), ci) for g, lam, ci in zip(struct, fit.lam[1:], cis[1:])]
    a2_lo, a2_hi = cis[0]
    return PerturbationFit(comps, float(np.sqrt(fit.lam[0])), (float(np.sqrt(a2_lo)), float(np.sqrt(a2_hi))),
                           fit.cost, n, removed, steps)


def _best_move(r: np.ndarray, S: np.ndarray, struct: list[tuple[tuple[str, str], ...]], fit: ComponentFit,
               mats: Any) -> tuple[list[tuple[tuple[str, str], ...]], ComponentFit, str] | None:
    """The cheapest simplification of ``struct``: remove one component, or merge two of the same class adjacent in
    the order of their variances.  Every move is scored by its Wald statistic at the current fit (``(c^T lam)^2 /
    c^T H^-1 c``, ``H = 2 F`` the expected Hessian of ``-2 log L`` in the variances); the :data:`REFIT_BEST`
    cheapest are refitted from the current estimate and the best refit is returned."""
    lam = fit.lam
    H = 2.0 * fit.fisher / np.outer(lam, lam)
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hn = H / np.outer(d, d)  # unit diagonal: the rank test below is scale-free
    Hn_inv = np.linalg.pinv(Hn, rcond=1e-10)
    trials: list[tuple[float, list[tuple[tuple[str, str], ...]], np.ndarray, str]] = []

    def wald(c: np.ndarray) -> float:
        cn = c / d
        if np.linalg.norm(cn - Hn @ (Hn_inv @ cn)) > 1e-6 * np.linalg.norm(cn):
            return 0.0  # the data do not see this contrast: the constraint costs nothing
        v = float(cn @ Hn_inv @ cn)
        return float((c @ lam) ** 2 / v) if v > 0 else np.inf

    for g in range(len(struct)):
        c = np.zeros(lam.size)
        c[g + 1] = 1.0
        trials.append((wald(c), struct[:g] + struct[g + 1:], np.delete(lam, g + 1), f"remove {_label(struct[g])}"))
    for cls in dict.fromkeys(g[0][1] for g in struct):
        idx = sorted((g for g in range(len(struct)) if struct[g][0][1] == cls), key=lambda g: lam[g + 1])
        for g, h in zip(idx, idx[1:]):
            c = np.zeros(lam.size)
            c[g + 1], c[h + 1] = 1.0, -1.0
            st = [x for k, x in enumerate(struct) if k not in (g, h)] + [struct[g] + struct[h]]
            start = np.append(np.delete(lam, [g + 1, h + 1]), 0.5 * (lam[g + 1] + lam[h + 1]))
            trials.append((wald(c), st, start, f"merge {_label(struct[g])} with {_label(struct[h])}"))
    # a move the data do not see at all (Wald ~ 0) that merges goes first: the joint keeps the variance of its
    # class's group instead of none
    best = None
    order = sorted(trials, key=lambda t: (t[0] > TIE, t[3].startswith("remove"), t[0]))
    for _, st, start, what in order[:REFIT_BEST]:
        f = fit_components(r, S, mats(st), start)
        if best is None or f.cost < best[1].cost - TIE:
            best = (st, f, what)
    return best


def _label(g: Sequence[tuple[str, str]]) -> str:
    return "+".join(j for j, _ in g) + "/" + g[0][1]
