"""Fit here, score there: a diagnosed model scored, unchanged, on test bags (``ppoe diagnose --test``).

Contract (``CONTRACT.md`` sec. 6): one object per test bag with ``rms``, ``mean``, ``median``, ``p95``,
``max`` [m] and ``n``.  The error of a stop is the distance between the measured and the predicted
position (the model with its declared effects and, for ``after``, the effects the fit found):

* **stop roles** (a bag whose ``/dataset/stop`` marks stationing and evaluation stops, as the Hilti
  importer writes them): per session, the tracker registration is fitted (Kabsch) on the
  stationing stops only and the evaluation stops are scored -- the dataset's protocol;
* **tracker points without roles**: one rigid registration per session fitted on all its stops,
  every stop scored (the registration absorbs part of the error: said in ``protocol``);
* **poses** (``/ground_truth/pose`` in the base frame): no registration, every stop scored.

Nothing of the model is refitted on a test bag; only the registrations, which are nuisances of the
measurement set-up.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.block_tracker import kabsch_per_session
from ppoe_core.analysis.diagnose.candidates import predict_nominal
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import BagError
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["error_stats", "score_stops", "check_same_robot", "protocol_scores"]

PROTOCOL_ROLES = "stop roles: registration per station on its stationing stops, evaluation stops scored"
PROTOCOL_ALL = "one rigid registration per session fitted on all its stops, every stop scored"
PROTOCOL_POSE = "poses in the base frame, no registration, every stop scored"


def error_stats(R: np.ndarray) -> dict[str, float | int]:
    """Statistics of position errors ``R`` (n, 3) [m]: ``n``, ``rms``, ``mean``, ``median``, ``p95``,
    ``max`` of the 3D distance, and ``r95_xy`` / ``r95_z`` (95th percentiles of the horizontal and
    vertical error in the measurement frame's axes, the Hilti protocol's numbers).  Rows with NaN are
    left out (and so not counted in ``n``)."""
    R = np.asarray(R, dtype=float).reshape(-1, 3)
    R = R[np.all(np.isfinite(R), axis=1)]
    if not R.size:
        return {"n": 0}
    d = np.linalg.norm(R, axis=1)
    return {"n": int(d.size), "rms": float(np.sqrt(np.mean(d ** 2))), "mean": float(d.mean()),
            "median": float(np.median(d)), "p95": float(np.percentile(d, 95)), "max": float(d.max()),
            "r95_xy": float(np.percentile(np.linalg.norm(R[:, :2], axis=1), 95)),
            "r95_z": float(np.percentile(np.abs(R[:, 2]), 95))}


def _errors(tree: KinematicTree, stops: Stops,
            effects: Sequence[Effect]) -> tuple[np.ndarray, str, np.ndarray, int]:
    """Position errors (n, 3) of the scored stops, the protocol used, the scored rows, and the number
    of stops that could not be scored (their session had no usable registration)."""
    x0, R0, *_ = predict_nominal(tree, stops, list(effects))
    every = np.arange(len(stops))
    if stops.kind == "pose":
        return stops.p_meas - x0, PROTOCOL_POSE, every, 0
    roles = not (bool(stops.reg_mask.all()) and bool(stops.score_mask.all()))
    if roles:
        reg_rows = np.flatnonzero(stops.reg_mask)
        wanted = np.flatnonzero(stops.score_mask & ~stops.reg_mask)
        protocol = PROTOCOL_ROLES
    else:
        reg_rows, wanted, protocol = every, every, PROTOCOL_ALL
    regs = kabsch_per_session(x0[reg_rows], stops.p_meas[reg_rows], stops.session[reg_rows])
    rows = wanted[np.isin(stops.session[wanted], list(regs))]
    T = np.stack([regs[int(k)] for k in stops.session[rows]]) if rows.size else np.zeros((0, 4, 4))
    pred = np.einsum("nij,nj->ni", T[:, :3, :3], x0[rows]) + T[:, :3, 3]
    return stops.p_meas[rows] - pred, protocol, rows, int(wanted.size - rows.size)


def score_stops(robot: Robot, stops: Stops, declared: Sequence[Effect], found: Sequence[Effect]) -> dict[str, Any]:
    """Score one test bag: the contract statistics of the model with ``declared`` + ``found`` effects
    (top level), the same ``before`` (declared effects only), the ``protocol`` and ``unscored`` stops.

    Parameters
    ----------
    robot : Robot
        The fitted robot (the test bag's URDF must describe the same robot: :func:`check_same_robot`).
    stops : Stops
        The test bag's stops (:func:`~ppoe_core.analysis.diagnose.stops.stops_from_bag`).
    declared, found : effects of the model file, and those the fit found (with their parameters).
    """
    tree = KinematicTree(robot)
    R_before, protocol, rows, unscored = _errors(tree, stops, declared)
    R_after, _, _, _ = _errors(tree, stops, [*declared, *found])
    out: dict[str, Any] = dict(error_stats(R_after))
    out["before"] = error_stats(R_before)
    out["protocol"] = protocol
    out["unscored"] = unscored
    per_session: dict[str, Any] = {}
    if len(stops.session_names) > 1 and stops.kind == "point":
        for sid, name in enumerate(stops.session_names):
            sub = stops.session[rows] == sid
            if sub.any():
                per_session[name] = {"after_rms": error_stats(R_after[sub]).get("rms"),
                                     "before_rms": error_stats(R_before[sub]).get("rms")}
    if per_session:
        out["per_session"] = per_session
    return out


def check_same_robot(fit_robot: Robot, test_robot: Robot, fit_bag: str, test_bag: str) -> None:
    """A test bag must carry the fitted robot: the same joints with the same types and parents.

    Raises
    ------
    BagError
        Naming the test bag and the first joints that differ.
    """
    def sig(robot: Robot) -> dict[str, tuple[str, str, str]]:
        return {n: (j.type, j.parent, j.child) for n, j in robot.joints.items()}

    a, b = sig(fit_robot), sig(test_robot)
    if a == b:
        return
    only_fit = sorted(set(a) - set(b))
    only_test = sorted(set(b) - set(a))
    changed = sorted(n for n in set(a) & set(b) if a[n] != b[n])
    parts = [f"joints only in the fitted robot: {only_fit[:5]}" if only_fit else "",
             f"joints only in the test bag: {only_test[:5]}" if only_test else "",
             f"joints that differ: {changed[:5]}" if changed else ""]
    raise BagError(f"bag {test_bag}: /robot_description is another robot than bag {fit_bag}'s ("
                   + "; ".join(p for p in parts if p) + "): a test bag must record the fitted robot")


def protocol_scores(robot: Robot, stops: Stops, effects: Sequence[Effect] = ()) -> dict[str, float | int]:
    """Score a model with ``effects`` by the stops' protocol with nothing fitted but the registrations
    (:func:`error_stats` of the scored stops: per session a Kabsch registration on the ``reg_mask`` stops, the
    ``score_mask`` stops scored; the Hilti README "Baseline")."""
    R, _, _, _ = _errors(KinematicTree(robot), stops, effects)
    return error_stats(R)
