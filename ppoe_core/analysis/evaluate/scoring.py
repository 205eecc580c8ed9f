"""Scoring of ``ppoe evaluate``: estimates against ground-truth poses, or against tracker points through one rigid
registration per group (the dataset's stationing protocol when the bag marks stop roles, else even/odd samples).

Errors are in the base frame [m, rad]; NEES uses the estimate's covariance (tool frame) and, for points, the
tracker noise (docs/conventions.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.evaluate.metrics import (
    nees_named, regularised, error_stats, nees_stats, point_covariance, position_errors, rotation_errors,
)
from ppoe_core.errors import PpoeError
from ppoe_core.model.context import batch_context
from ppoe_core.estimation import fusion

if TYPE_CHECKING:
    from ppoe_core.analysis.evaluate.replay import ReplayRun


def _stop_roles(bag: str, gt_stamps: np.ndarray) -> list[dict[str, Any] | None]:
    """For each ground-truth stamp, the ``/dataset/stop`` info of the stop it belongs to (or None)."""
    from ppoe_core.io.stops import read_stop_info

    stops = read_stop_info(bag)
    if not stops:
        return [None] * len(gt_stamps)
    st = np.array([s for s, _ in stops])
    k = np.searchsorted(st, gt_stamps, side="right") - 1
    return [stops[j][1] if j >= 0 else None for j in k]


def registration_split(
    roles: list[dict[str, Any] | None], n: int, fit_set: str
) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], str, int]:
    """Groups ``(name, fit_idx, eval_idx)`` for point ground truth, a description, unscored count."""
    if fit_set not in ("cross", "square", "all"):
        raise PpoeError(f"--fit-set must be cross, square or all, not {fit_set!r}")
    if all(r is not None and "role" in r and "station" in r for r in roles) and n:
        groups: dict[str, tuple[list[int], list[int]]] = {}
        for i, r in enumerate(roles):
            assert r is not None
            g = groups.setdefault(str(r["station"]), ([], []))
            sets = r.get("point_sets")  # absent: the stop is in every set (``ppoe import csv``)
            if r["role"] == "stationing" and (fit_set == "all" or sets is None or fit_set in sets):
                g[0].append(i)
            elif r["role"] == "evaluation":
                g[1].append(i)
        out, unscored = [], 0
        for name, (fit, ev) in groups.items():
            if len(fit) < 3:
                unscored += len(ev)
                continue
            out.append((name, np.array(fit, int), np.array(ev, int)))
        desc = (
            f"per station (/dataset/stop): fitted on its stationing stops of set '{fit_set}', "
            "scored on its evaluation stops"
        )
        return out, desc, unscored
    idx = np.arange(n)
    return [("all", idx[0::2], idx[1::2])], "one registration: fitted on even-numbered samples, scored on odd", 0


def _at(p: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) with positions ``p`` and no rotation (a tracker measures only the point)."""
    T = np.broadcast_to(np.eye(4), (len(p), 4, 4)).copy()
    T[:, :3, 3] = p
    return T


def score_poses(summary: dict[str, Any], samples: dict[str, np.ndarray], run: ReplayRun, gt_pose: Any,
                have: np.ndarray, methods: list[str], bag: str) -> None:
    """Position (3D, lateral), rotation and pose NEES of every method against ``/ground_truth/pose``."""
    sel = np.flatnonzero(have)
    T_gt = gt_pose.T[sel]
    z_axis = T_gt[:, :3, 2]
    p_gt = T_gt[:, :3, 3]
    samples["stamp"] = gt_pose.stamps[sel]
    for m in methods:
        Te, Ce = run.est_T[m][sel], run.est_cov[m][sel]
        e3, el = position_errors(Te[:, :3, 3], p_gt, z_axis)
        rot = rotation_errors(Te, T_gt)

        def pose_nees(Te: np.ndarray = Te, Ce: np.ndarray = Ce) -> Any:
            return fusion.nees(Te, regularised(Ce), T_gt)

        ne = nees_named(pose_nees, bag, m)
        samples.update(
            {
                f"{m}_position_3d": e3,
                f"{m}_lateral": el,
                f"{m}_rotation": rot,
                f"{m}_nees": ne,
                f"{m}_position_error": Te[:, :3, 3] - p_gt,
                f"{m}_T": Te,
            }
        )
        samples["gt_T"] = T_gt
        summary["methods"][m] = {
            "position_3d": error_stats(e3),
            "lateral": error_stats(el),
            "rotation": error_stats(rot),
            "nees": nees_stats(ne, 6),
        }


def _register(run: ReplayRun, gt_point: Any, usable: np.ndarray, p_fk: np.ndarray, groups: list,
              unscored: int) -> tuple[np.ndarray, list[int], list[dict[str, Any]], int]:
    """Tracker points in the base frame through one rigid registration per group (fitted on its fit stops)."""
    n_gt = len(gt_point.stamps)
    p_gt_base = np.full((n_gt, 3), np.nan)
    scored: list[int] = []
    reg = []
    for name, fit, ev_idx in groups:
        fit = fit[usable[fit]]
        ev_idx = ev_idx[usable[ev_idx]]
        if len(fit) < 3:
            unscored += len(ev_idx)
            continue
        T_tracker_base = lie.fit_rigid(p_fk[fit], gt_point.p[fit])
        T_base_tracker = lie.inverse(T_tracker_base)
        p_gt_base[ev_idx] = gt_point.p[ev_idx] @ T_base_tracker[:3, :3].T + T_base_tracker[:3, 3]
        res_fit = np.linalg.norm(gt_point.p[fit] @ T_base_tracker[:3, :3].T + T_base_tracker[:3, 3] - p_fk[fit], axis=1)
        reg.append(
            {
                "group": name,
                "fit": int(len(fit)),
                "scored": int(len(ev_idx)),
                "fit_rms": float(np.sqrt(np.mean(res_fit**2))),
            }
        )
        scored.extend(ev_idx.tolist())
    return p_gt_base, scored, reg, unscored


def score_points(summary: dict[str, Any], samples: dict[str, np.ndarray], run: ReplayRun, gt_point: Any,
                 have: np.ndarray, methods: list[str], model: Any, tool: str, fit_set: str, bag: str,
                 tracker: Any = None, context_source: tuple[float, Any] = (0.0, None)) -> None:
    """Reflector position errors (3D, lateral) and NEES of every method against the points of ``tracker``
    (default: the model's ``tracker``; ``/ground_truth/point`` or ``/ground_truth/point/<name>``).
    ``context_source``: first joint-state time [s] and the temperature series of the bag, for effects
    that read a context (:func:`ppoe_core.model.context.batch_context`)."""
    tr = tracker if tracker is not None else model.config.tracker
    gt_stamps = gt_point.stamps
    n_gt = len(gt_stamps)
    roles = _stop_roles(bag, gt_stamps)
    groups, desc, unscored = registration_split(roles, n_gt, fit_set)
    usable = have & np.all(np.isfinite(gt_point.p), axis=1)
    # reflector in tool coordinates at each sample (the chain tool -> tracker link may move)
    r_tool = np.full((n_gt, 3), np.nan)
    if usable.any():
        jd = {n: run.gt_joints[usable, j] for j, n in enumerate(model.joint_names)}
        # effects reading a context (motion signs over the scored samples: only effects on the chain
        # tool -> reflector link matter here)
        ctx = batch_context(model.effects, model.joint_names, gt_stamps[usable], run.gt_joints[usable],
                            context_source[0], context_source[1], where=f"bag {bag}")
        T_tool_link = model.fk_mean(jd, tool, tr.link, context=ctx)
        r_tool[usable] = T_tool_link[..., :3, :3] @ tr.xyz + T_tool_link[..., :3, 3]
    Tfk = run.est_T["fk"]
    p_fk = np.einsum("nij,nj->ni", Tfk[:, :3, :3], r_tool) + Tfk[:, :3, 3]
    p_gt_base, scored, reg, unscored = _register(run, gt_point, usable, p_fk, groups, unscored)
    sel = np.array(sorted(scored), int)
    summary["ground_truth"]["registration"] = {"method": desc, "groups": reg, "unscored": int(unscored)}
    if tr.topic != "/ground_truth/point":
        summary["ground_truth"]["topic"] = tr.topic
    samples["stamp"] = gt_stamps[sel]
    cov_gt = np.eye(3) * tr.sigma**2
    z_axis = Tfk[sel, :3, 2]
    for m in methods:
        Te, Ce = run.est_T[m][sel], run.est_cov[m][sel]
        p_e = np.einsum("nij,nj->ni", Te[:, :3, :3], r_tool[sel]) + Te[:, :3, 3]
        e3, el = position_errors(p_e, p_gt_base[sel], z_axis)
        Cp = point_covariance(Te, Ce, r_tool[sel]) + cov_gt

        # e^T C^-1 e of the reflector position error (fusion.nis: the same quadratic form)
        def point_nees(p_e: np.ndarray = p_e, Cp: np.ndarray = Cp) -> Any:
            return fusion.nis(p_e - p_gt_base[sel], regularised(Cp))

        ne = nees_named(point_nees, bag, m)
        samples.update(
            {
                f"{m}_position_3d": e3,
                f"{m}_lateral": el,
                f"{m}_nees": ne,
                f"{m}_position_error": p_e - p_gt_base[sel],
                f"{m}_T": _at(p_e),
            }
        )
        samples["gt_T"] = _at(p_gt_base[sel])
        summary["methods"][m] = {"position_3d": error_stats(e3), "lateral": error_stats(el), "nees": nees_stats(ne, 3)}
