"""Local refinement of a planned design: each pose moved to a better feasible configuration near it.

The exchange (:mod:`design`) chooses among a finite candidate set; a D-optimal design's poses sit at the edges
of what the constraints allow, which random candidates only approach.  Each round draws, around every planned pose,
:data:`PER_POSE` configurations (normal steps of ``step`` times each joint's interval, halved every round, clipped
to the interval), keeps the feasible ones (:func:`~ppoe_core.analysis.plan.constraints.violations`) and replaces
the pose by the one that raises ``log det`` most (the others fixed), as the exchange does.  It never lowers
``log det`` and keeps every constraint.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ppoe_core.analysis.plan.constraints import Constraints, joint_bounds, violations
from ppoe_core.analysis.plan.design import EXCHANGE_TOL, log_det
from ppoe_core.analysis.plan.information import (
    PixelDesign,
    PoseInformation,
    Target,
    pose_information,
    reduced_information,
)
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Refined", "refine", "PER_POSE", "ROUNDS", "STEP"]

#: configurations drawn around each planned pose per round
PER_POSE = 32
#: rounds (the step halves every round)
ROUNDS = 3
#: first step: this share of each joint's interval (1-sigma)
STEP = 0.15


@dataclass
class Refined:
    """The refined poses ``Q`` (N, J) in the joint order ``joints``, their information, ``log det`` and the number
    of poses moved."""

    Q: np.ndarray
    joints: list[str]
    info: PoseInformation
    log_det: float
    moved: int


def _score(A: np.ndarray, B: np.ndarray, C: np.ndarray, base: np.ndarray | None, scale: np.ndarray) -> np.ndarray:
    H = reduced_information(A, B, C)
    return log_det(H if base is None else H + base, scale)


def refine(tree: KinematicTree, trackers: Sequence, targets: Sequence[Target], declared: Sequence[Effect],
           constraints: Constraints, Q: np.ndarray, scale: np.ndarray, base: np.ndarray | None,
           rng: np.random.Generator, rounds: int = ROUNDS, pixels: PixelDesign | None = None) -> Refined:
    """Refine the poses ``Q`` (N, J; joints in :func:`joint_bounds` order) (module docstring); ``pixels``: as
    :func:`pose_information`."""
    bounds = joint_bounds(tree, constraints)
    joints = list(bounds)
    lo, hi = np.array([bounds[j][0] for j in joints]), np.array([bounds[j][1] for j in joints])
    Q = np.array(Q, dtype=float)
    n = Q.shape[0]
    cur = pose_information(tree, trackers, {j: Q[:, i] for i, j in enumerate(joints)}, targets, declared, scale, pixels)
    A, B, C = cur.A.copy(), cur.B.copy(), cur.C.copy()
    best = float(_score(A.sum(0), B.sum(0), C.sum(0), base, scale))
    moved = 0
    for r in range(rounds):
        step = STEP * 0.5 ** r * (hi - lo)
        P = np.clip(Q[:, None, :] + rng.standard_normal((n, PER_POSE, len(joints))) * step, lo, hi)
        q = {j: P[..., i].reshape(-1) for i, j in enumerate(joints)}
        ok = ~np.any(np.stack(list(violations(tree, q, constraints).values())), axis=0).reshape(n, PER_POSE)
        if not ok.any():
            continue
        new = pose_information(tree, trackers, q, targets, declared, scale, pixels)
        nA, nB, nC = (x.reshape(n, PER_POSE, *x.shape[1:]) for x in (new.A, new.B, new.C))
        for k in range(n):
            rest = [x.sum(0) - x[k] for x in (A, B, C)]
            sc = np.where(ok[k], _score(rest[0] + nA[k], rest[1] + nB[k], rest[2] + nC[k], base, scale), -np.inf)
            v = int(np.argmax(sc))
            if sc[v] > best + EXCHANGE_TOL:
                best, moved = float(sc[v]), moved + 1
                Q[k], A[k], B[k], C[k] = P[k, v], nA[k, v], nB[k, v], nC[k, v]
    q_end = {j: Q[:, i] for i, j in enumerate(joints)}
    info = pose_information(tree, trackers, q_end, targets, declared, scale, pixels)
    return Refined(Q, joints, info, best, moved)
