"""D-optimal pose design by greedy forward selection and exchange over a candidate set.

Criterion: ``log det I(S)`` of the target parameters with the nuisances (registration) eliminated
(:func:`~ppoe_core.analysis.plan.information.reduced_information`), on columns scaled to unit RMS over the
candidates (the argmax does not depend on the scaling: ``det D I D = det D^2 det I``; the scaling only makes the
small ridge that carries the first, rank-deficient steps act alike on every parameter).

Method: the candidates are random configurations that pass every constraint (:mod:`constraints`); the design is
built greedily (each step adds the candidate that raises ``log det`` most) and then improved by exchange passes
(each planned pose in turn is replaced by the best candidate if that raises ``log det`` by more than
:data:`EXCHANGE_TOL`; Cook and Nachtsheim's modified Fedorov exchange), until a pass changes nothing.  Why not a
convex relaxation (weights on the candidates, ``max log det sum w_u I_u``): the nuisance elimination makes the
information a Schur complement (concave, but no longer a weighted sum), the relaxation's weights must be rounded to
N distinct poses (the rounding loses the guarantee at small N, the case here: N a few times the parameter count),
and the exchange works on exactly N poses, keeps a fixed given data set as a constant part of the information
(``--given``), and costs a few batched ``P x P`` determinants per step.  Every evaluation is exact (no rank-one
update drift); a step evaluates all candidates at once.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ppoe_core.analysis.plan.information import PoseInformation, reduced_information
from ppoe_core.errors import PpoeError

__all__ = ["Design", "design", "information_of", "log_det", "observability_indices", "EXCHANGE_TOL", "minimax",
           "relative_variance", "MIN_D_EFFICIENCY", "SOFT_MAX_POWER"]

#: an exchange is taken when it raises ``log det`` by more than this (relative improvement of the determinant)
EXCHANGE_TOL = 1e-6
#: ridge on the scaled information (unit RMS columns): carries the first greedy steps, negligible after
RIDGE = 1e-8
#: at most this many exchange passes (each pass tries every planned pose once)
MAX_PASSES = 10
#: second stage (:func:`minimax`): the D-efficiency ``exp((log det - log det_D) / P)`` w.r.t. the D-optimal design
#: is kept at least this (the named D criterion stays within 10 % per parameter of its optimum)
MIN_D_EFFICIENCY = 0.9
#: second stage's soft maximum ``(mean r_k^p)^(1/p)`` of the relative variances: large enough that the worst
#: parameter dominates, finite so that an exchange helping the second worst is still seen
SOFT_MAX_POWER = 16.0


@dataclass
class Design:
    """The chosen candidate indices (in design order), ``log det`` of the scaled reduced information, the number of
    exchange passes and of exchanges taken."""

    chosen: np.ndarray
    log_det: float
    passes: int
    exchanges: int
    refined: int = 0  #: poses moved by the local refinement (:mod:`~ppoe_core.analysis.plan.refine`)
    minimax_exchanges: int = 0  #: exchanges taken by the second, minimax stage (:func:`minimax`)


def information_of(info: PoseInformation, idx: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
    """Reduced information (P, P) of the candidates ``idx`` (one registration), plus ``base`` (given data's)."""
    idx = np.asarray(idx, dtype=int)
    out = reduced_information(info.A[idx].sum(0), info.B[idx].sum(0), info.C[idx].sum(0))
    return out if base is None else out + base


def log_det(H: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``log det(D H D + ridge I)``, ``D = diag(1/scale)``, over leading batch axes of ``H`` (..., P, P)."""
    d = 1.0 / scale
    Hs = H * d[:, None] * d[None, :] + RIDGE * np.eye(scale.size)
    sign, ld = np.linalg.slogdet(Hs)
    return np.where(sign > 0, ld, -np.inf)


class _Sums:
    """Running sums of the design's ``A``, ``B``, ``C`` and the evaluation of one more candidate each."""

    def __init__(self, info: PoseInformation, base: np.ndarray | None) -> None:
        self.info = info
        P, K = info.B.shape[1:]
        self.A, self.B, self.C = np.zeros((P, P)), np.zeros((P, K)), np.zeros((K, K))
        self.base = np.zeros((P, P)) if base is None else base

    def add(self, u: int, sign: float = 1.0) -> None:
        self.A = self.A + sign * self.info.A[u]
        self.B = self.B + sign * self.info.B[u]
        self.C = self.C + sign * self.info.C[u]

    def with_each(self) -> np.ndarray:
        """``log det`` of the design plus each candidate (M,)."""
        i = self.info
        H = reduced_information(self.A + i.A, self.B + i.B, self.C + i.C) + self.base
        return log_det(H, i.scale)

    def each_information(self) -> np.ndarray:
        """Reduced information (M, P, P) of the design plus each candidate."""
        i = self.info
        return reduced_information(self.A + i.A, self.B + i.B, self.C + i.C) + self.base

    def current(self) -> float:
        return float(log_det(reduced_information(self.A, self.B, self.C) + self.base, self.info.scale))


def _exchange_passes(sums: _Sums, picked: list[int], taken: np.ndarray, best: float,
                    score: Callable[[_Sums, np.ndarray], np.ndarray], better: Callable[[float, float], bool],
                    max_passes: int) -> tuple[float, int, int]:
    """The exchange passes of :func:`design` and :func:`minimax` (Cook and Nachtsheim's modified Fedorov exchange):
    each planned pose in turn is taken out and replaced by the candidate of the highest ``score(sums, free)``
    ((M,), higher is better, ``-inf`` where not allowed; ``free`` marks the candidates not in the design) when
    ``better(score, best)``; until a pass changes nothing or ``max_passes``.  ``picked``, ``taken`` and ``sums`` are
    updated in place.  Returns the criterion's final value, the passes and the exchanges taken."""
    passes = exchanges = 0
    for passes in range(1, max_passes + 1):  # noqa: B007 - the count is returned
        changed = False
        for k in range(len(picked)):
            u = picked[k]
            sums.add(u, -1.0)
            taken[u] = False
            s = score(sums, ~taken)
            v = int(np.argmax(s))
            if v != u and better(float(s[v]), best):
                best, changed, exchanges = float(s[v]), True, exchanges + 1
                picked[k] = v
            sums.add(picked[k])
            taken[picked[k]] = True
        if not changed:
            break
    return best, passes, exchanges


def design(info: PoseInformation, n: int, base: np.ndarray | None = None, max_passes: int = MAX_PASSES) -> Design:
    """Choose ``n`` distinct candidates maximising ``log det`` (module docstring); ``base``: information already
    there (``--given`` data, its own registration eliminated).

    Raises
    ------
    PpoeError
        Fewer candidates than ``n``.
    """
    M = info.A.shape[0]
    if M < n:
        raise PpoeError(f"plan: only {M} feasible candidate configurations for {n} poses (relax the constraints or "
                        "draw more candidates)")
    sums = _Sums(info, base)
    taken = np.zeros(M, bool)
    chosen: list[int] = []
    for _ in range(n):
        score = np.where(taken, -np.inf, sums.with_each())
        u = int(np.argmax(score))
        chosen.append(u)
        taken[u] = True
        sums.add(u)
    _, passes, exchanges = _exchange_passes(
        sums, chosen, taken, sums.current(), lambda h, free: np.where(free, h.with_each(), -np.inf),
        lambda new, best: new > best + EXCHANGE_TOL, max_passes)
    return Design(np.array(chosen, dtype=int), float(sums.current()), passes, exchanges)


def relative_variance(H: np.ndarray, scale: np.ndarray, ref_var: np.ndarray) -> np.ndarray:
    """Soft maximum over the parameters of ``r_k = (H^-1)_kk / ref_var_k`` (:data:`SOFT_MAX_POWER`), over leading
    batch axes of ``H`` (..., P, P); ``ref_var`` (P,) the reference variances (the 4N-random median's)."""
    d = 1.0 / scale
    Hs = H * d[:, None] * d[None, :] + RIDGE * np.eye(scale.size)
    try:
        var = np.diagonal(np.linalg.inv(Hs), axis1=-2, axis2=-1) * d**2
    except np.linalg.LinAlgError:
        return np.full(H.shape[:-2], np.inf)
    r = np.where(var > 0, var / ref_var, np.inf)
    top = r.max(-1, keepdims=True)
    with np.errstate(invalid="ignore"):
        soft = top[..., 0] * np.mean((r / top) ** SOFT_MAX_POWER, axis=-1) ** (1.0 / SOFT_MAX_POWER)
    return np.where(np.isfinite(top[..., 0]), soft, np.inf)


def minimax(info: PoseInformation, chosen: np.ndarray, ref_var: np.ndarray, base: np.ndarray | None = None,
            min_efficiency: float = MIN_D_EFFICIENCY, max_passes: int = MAX_PASSES) -> Design:
    """Second stage: exchange passes from the D-optimal ``chosen`` minimising the worst relative variance
    (:func:`relative_variance`, reference ``ref_var``) while ``log det`` stays within ``P log(min_efficiency)`` of
    the start's (a constrained minimax design); an exchange is taken when it lowers the criterion by more than
    :data:`EXCHANGE_TOL` (relative).  A start whose every variance is already at most the reference is kept (the
    goal is met; the D-optimum is the better design for everything else, e.g. separating a pair)."""
    M, P = info.A.shape[0], info.A.shape[1]
    sums = _Sums(info, base)
    picked = [int(u) for u in chosen]
    taken = np.zeros(M, bool)
    for u in picked:
        sums.add(u)
        taken[u] = True
    floor = sums.current() + P * np.log(min_efficiency)
    H0 = reduced_information(sums.A, sums.B, sums.C) + sums.base
    if np.all(np.diag(np.linalg.pinv(H0)) <= ref_var):
        return Design(np.array(picked, dtype=int), float(sums.current()), 0, 0)

    def score(h: _Sums, free: np.ndarray) -> np.ndarray:
        H = h.each_information()
        ok = free & (log_det(H, info.scale) >= floor)
        return np.where(ok, -relative_variance(H, info.scale, ref_var), -np.inf)

    # the criterion is negated (higher is better): lowering it by more than EXCHANGE_TOL relative is
    # ``-new > -best * (1 - EXCHANGE_TOL)``
    _, passes, exchanges = _exchange_passes(
        sums, picked, taken, -float(relative_variance(H0, info.scale, ref_var)), score,
        lambda new, best: new > best * (1.0 - EXCHANGE_TOL), max_passes)
    return Design(np.array(picked, dtype=int), float(sums.current()), passes, exchanges)


def observability_indices(H: np.ndarray, scale: np.ndarray, n_poses: int) -> dict[str, float]:
    """Sun and Hollerbach's observability indices O1..O5 and the condition number of the reduced information ``H``
    (P, P) of ``n_poses`` poses, on columns scaled by ``scale`` (the singular values ``s_i`` of the scaled, whitened
    identification Jacobian with the nuisances projected out are ``sqrt(eig(D H D))``):

    * O1 = ``(s_1 ... s_L)^(1/L) / sqrt(n_poses)`` (D-optimality, Borm and Menq)
    * O2 = ``s_L / s_1`` (inverse condition number, Driels and Pathre)
    * O3 = ``s_L`` (E-optimality, Nahvi et al.)
    * O4 = ``s_L^2 / s_1`` (noise amplification index, Nahvi and Hollerbach)
    * O5 = ``1 / (1/s_1 + ... + 1/s_L)`` (A-optimality-like, Sun and Hollerbach)
    """
    d = 1.0 / scale
    ev = np.linalg.eigvalsh(H * d[:, None] * d[None, :])
    s = np.sqrt(np.clip(ev, 0.0, None))[::-1]
    L = s.size
    with np.errstate(divide="ignore"):
        o1 = float(np.exp(np.mean(np.log(s))) / np.sqrt(max(n_poses, 1))) if s[-1] > 0 else 0.0
        o5 = float(1.0 / np.sum(1.0 / s)) if s[-1] > 0 else 0.0
    return {"O1": o1, "O2": float(s[-1] / s[0]) if s[0] > 0 else 0.0, "O3": float(s[-1]),
            "O4": float(s[-1] ** 2 / s[0]) if s[0] > 0 else 0.0, "O5": o5,
            "condition_number": float(s[0] / s[-1]) if s[-1] > 0 else float("inf"), "n_parameters": float(L)}
