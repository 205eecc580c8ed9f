"""Held-out scoring of the joint tracker + pixel fit (:func:`joint_fit`): k-fold over robot poses, other sessions.

Protocol ("cross-validated over poses"): the robot poses (a tracker stop and the images taken at it share
one pose: :func:`joint_pose_ids`) are split into ``folds`` seeded folds; per fold, the effects and the
registrations are fitted on the other poses' tracker and pixel rows, then the held-out rows are predicted
with them: pixels directly (the cameras' extrinsics are effects of the fit), tracker points through the
*training* registration of their session, as the tracker stage scores held-out stops
(:meth:`LinearProblem.heldout`); a session with no training rows (never with k-fold over poses of one
session) is registered by Kabsch on its held-out rows with the effects fixed, also as there.  Nothing is
refitted on held-out rows that could see held-out effects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.joint_fit import JointFit, joint_fit, subset_stops, tracker_points
from ppoe_core.analysis.diagnose.linear import LinearProblem
from ppoe_core.analysis.diagnose.pixel_structure import pixel_residual_structure, structure_summary
from ppoe_core.analysis.diagnose.pixels import PixelObs, predict_pixels
from ppoe_core.analysis.diagnose.results import DiagnoseResult
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

PROTOCOL = "cross-validated over poses"


def joint_pose_ids(stops: Stops | None, pixels: PixelObs | None, decimals: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Robot pose of every tracker row and every pixel row: rows with the same joint values (rounded to
    ``decimals``, over the joints both carry) are one pose.  Returns ``(pose_t (N,), pose_p (M,))``."""
    n = 0 if stops is None else len(stops)
    m = 0 if pixels is None else len(pixels)
    names = sorted(set(stops.q if stops is not None else pixels.q if pixels is not None else {})
                   & set(pixels.q if pixels is not None else stops.q if stops is not None else {}))
    cols = []
    for j in names:
        parts = ([stops.q[j]] if stops is not None else []) + ([pixels.q[j]] if pixels is not None else [])
        cols.append(np.round(np.concatenate(parts).astype(float), decimals))
    Q = np.column_stack(cols) if cols else np.arange(n + m, dtype=float)[:, None]
    _, inv = np.unique(Q, axis=0, return_inverse=True)
    inv = np.asarray(inv).reshape(-1)
    return inv[:n], inv[n:]


def _tracker_errors(tree: KinematicTree, stops: Stops, effects: Sequence[Effect], regs: dict[int, np.ndarray],
                    rows: np.ndarray) -> np.ndarray:
    """Tracker residuals (len(rows), 3) [m] of ``rows`` with the effects fixed: the session's registration from
    ``regs`` or, for a session not in it, Kabsch on its own ``rows`` (NaN if it has fewer than 3)."""
    x_root = tracker_points(tree, stops, effects)[0]
    lin = LinearProblem(stops, x_root, None)
    regs = dict(regs)
    missing = np.setdiff1d(np.unique(stops.session[rows]), list(regs))
    if missing.size:
        regs.update(lin.kabsch_regs(np.zeros((len(stops), 3, 0)), np.zeros(0),
                                    rows[np.isin(stops.session[rows], missing)]))
    return lin.residuals(np.zeros((len(stops), 3, 0)), np.zeros(0), regs, rows)[:, :3]


def joint_heldout(tree: KinematicTree, effects: Sequence[Effect], stops: Stops | None = None,
                  pixels: PixelObs | None = None, declared: Sequence[Effect] = (), folds: int = 5, seed: int = 0,
                  **options: Any) -> dict[str, Any]:
    """Held-out errors of :func:`joint_fit` with ``effects`` over ``folds`` folds of robot poses (module docstring).

    Returns
    -------
    dict
        ``pixel_rms`` (camera frame -> held-out RMS of the 2D error [px]), ``tracker_rms`` (held-out RMS of the
        3D tracker error [m], NaN without tracker rows), ``pixel_error`` (M,) and ``tracker_error`` (N,)
        per row (norms; NaN where not scored), ``pixel_residual`` (M, 2) (measured minus predicted [px], for
        :func:`~ppoe_core.analysis.diagnose.pixel_structure.pixel_residual_structure`), ``folds``, ``protocol``.
    """
    pose_t, pose_p = joint_pose_ids(stops, pixels)
    ids = np.unique(np.concatenate([pose_t, pose_p]))
    perm = np.random.default_rng(seed).permutation(ids)
    e_t = np.full(0 if stops is None else len(stops), np.nan)
    r_p = np.full((0 if pixels is None else len(pixels), 2), np.nan)
    for k in range(folds):
        test_ids = perm[k::folds]
        tt, tp = np.isin(pose_t, test_ids), np.isin(pose_p, test_ids)
        st = None if stops is None or not (~tt).any() else subset_stops(stops, ~tt)
        px = None if pixels is None or not (~tp).any() else pixels.subset(~tp)
        fit = joint_fit(tree, effects, st, px, declared, pose_t=None if st is None else pose_t[~tt], **options)
        cur = [*declared, *fit.fitted]
        if pixels is not None and tp.any():
            r_p[tp] = pixels.uv[tp] - predict_pixels(tree, pixels.subset(tp), cur)
        if stops is not None and tt.any():
            e_t[tt] = np.linalg.norm(_tracker_errors(tree, stops, cur, fit.regs, np.flatnonzero(tt)), axis=1)
    e_p = np.linalg.norm(r_p, axis=1)
    return {"pixel_rms": _per_camera_rms(pixels, e_p), "tracker_rms": _rms(e_t), "pixel_error": e_p,
            "pixel_residual": r_p, "tracker_error": e_t, "folds": folds, "protocol": PROTOCOL}


def score_joint(tree: KinematicTree, fit: JointFit, stops: Stops | None = None, pixels: PixelObs | None = None,
                declared: Sequence[Effect] = ()) -> dict[str, Any]:
    """The fitted effects, unchanged, on other data (e.g. another session): pixel RMS per camera [px] and
    tracker RMS [m] after one Kabsch registration per session on all its stops (effects fixed)."""
    cur = [*declared, *fit.fitted]
    out: dict[str, Any] = {"pixel_rms": {}, "tracker_rms": float("nan"),
                           "protocol": "fitted effects unchanged; tracker: one registration per session"}
    if pixels is not None:
        out["pixel_rms"] = _per_camera_rms(pixels, np.linalg.norm(pixels.uv - predict_pixels(tree, pixels, cur),
                                                                  axis=1))
    if stops is not None:
        out["tracker_rms"] = _rms(np.linalg.norm(_tracker_errors(tree, stops, cur, {}, np.arange(len(stops))),
                                                 axis=1))
    return out


def _rms(e: np.ndarray) -> float:
    ok = np.isfinite(e)
    return float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else float("nan")


def _per_camera_rms(pixels: PixelObs | None, e: np.ndarray) -> dict[str, float]:
    if pixels is None:
        return {}
    return {f: _rms(e[pixels.camera == c]) for c, f in enumerate(pixels.cameras) if np.any(pixels.camera == c)}


def joint_effect_set(robot: Robot, result: DiagnoseResult, pixels: PixelObs) -> list[Effect]:
    """Effects of the final joint fit: those the stages found (``result.effects``, tracker and pixel stage),
    plus ``camera_extrinsics`` at the mount joint of every observing camera; zero start, no repeats."""
    from ppoe_core.analysis.diagnose.pixels import pixel_candidates
    from ppoe_core.model.effects import effect_from_config

    tree = KinematicTree(robot)
    keys = ("name", "location", "parameters", "variable", "reference")
    found = [effect_from_config({k: e[k] for k in keys if k in e}, tree, where=f"diagnose effect {e['name']}@"
                                f"{e['location']}") for e in result.effects]
    cams = [e for e in pixel_candidates(robot, pixels) if e.name == "camera_extrinsics"]
    out: dict[tuple[str, str], Effect] = {}
    for e in [*found, *cams]:
        out.setdefault((e.name, e.location), e.with_params(np.zeros(e.n_params)))
    return list(out.values())


def add_joint_fit(result: DiagnoseResult, robot: Robot, stops: Stops, pixels: PixelObs,
                  declared: Sequence[Effect] = (), folds: int = 5, seed: int = 0) -> dict[str, Any]:
    """The joint tracker + pixel fit as the final fit of a diagnosis: :func:`joint_effect_set`, fitted on all
    data (:func:`joint_fit`) and scored by :func:`joint_heldout`; ``result.extra["joint"]`` gets ``effects``
    (values and 95 % CIs), ``pixel_rms_heldout`` per camera [px], ``tracker_rms_heldout`` [m], the in-sample
    values, ``sensor_sigma``, ``iterations``, ``cost``, ``protocol``, ``pixel_structure`` (where the held-out
    pixel residual concentrates: :func:`pixel_residual_structure`); one summary line, and one per camera whose
    residual a model outside the catalogue explains.  The stages' keys are
    left as they are."""
    tree = KinematicTree(robot)
    effects = joint_effect_set(robot, result, pixels)
    pose_t, _ = joint_pose_ids(stops, pixels)
    fit = joint_fit(tree, effects, stops, pixels, declared, pose_t=pose_t)
    held = joint_heldout(tree, effects, stops, pixels, declared, folds=folds, seed=seed)
    block = {"effects": fit.effects, "pixel_rms_heldout": held["pixel_rms"], "tracker_rms_heldout": held["tracker_rms"],
             "pixel_rms_insample": fit.pixel_rms, "tracker_rms_insample": fit.tracker_rms,
             "sensor_sigma": fit.sensor_sigma, "iterations": fit.iterations, "cost": fit.cost,
             "solver": "scipy.optimize.least_squares trf, soft_l1", "folds": folds, "protocol": PROTOCOL,
             "pixel_structure": pixel_residual_structure(pixels, held["pixel_residual"], tree,
                                                         [*declared, *fit.fitted], folds=folds, seed=seed)}
    result.extra["joint"] = block
    per = ", ".join(f"{f} {v:.2f} px" for f, v in held["pixel_rms"].items())
    names = ", ".join(f"{e['name']}@{e['location']}" for e in fit.effects) or "none"
    result.summary += (f"\nJoint tracker + pixel fit ({len(stops)} stops, {len(pixels)} points; {names}): held-out "
                       f"({PROTOCOL}) tracker {1e3 * held['tracker_rms']:.3f} mm, pixels {per}.")
    result.summary += structure_summary(block["pixel_structure"])
    return block
