"""Pixel stage: camera extrinsics and arm effects from tag pixels, held out per pose."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.pixels import (
    PixelObs,
    _map_ctx,
    camera_mount_joint,
    pixel_candidates,
    pixel_covariance,
    pixel_jacobian,
    pixel_rms,
    pixel_stats,
    predict_pixels,
)
from ppoe_core.analysis.diagnose.report import load_model
from ppoe_core.analysis.diagnose.results import DiagnoseResult
from ppoe_core.analysis.diagnose.selection import select_by_heldout_gain
from ppoe_core.analysis.diagnose.stats import _lstsq, _pose_folds
from ppoe_core.analysis.diagnose.stops import motion_signs
from ppoe_core.model.context import sample_series as _sample_joint
from ppoe_core.errors import BagError, MeasurementError
from ppoe_core.model.effects import Effect, effect_from_config
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot


@dataclass
class PixelDiagnosis:
    """Result of :func:`diagnose_pixels`.

    ``effects``: list of ``{name, location, frame, parameters, ci, sigma, share}`` (``ci``: 95 %
    interval per parameter; ``location`` the camera's mount joint, ``frame`` its optical frame);
    ``rms_before`` / ``rms_after``: held-out (cross-validated over poses) pixel RMS per camera
    frame [px], the norm of the 2D error; ``*_insample``: the same on all data with the final fit;
    ``steps`` and ``rejected``: the selection; ``fitted``: the effect objects (parameters set).
    ``noise_floor``: per camera, the RMS [px] the expected covariance (:func:`pixel_covariance`)
    predicts; ``unexplained``: held-out RMS above it [px]; ``nees_before`` / ``nees_after``:
    held-out mean squared Mahalanobis distance per point (expectation 2); ``unexplained_flag``:
    ``nees_after`` exceeds 2 by more than 3 standard errors (per-pose means).
    ``stats_before`` / ``stats_after``: in-sample :func:`pixel_stats` (n, RMS, median, max).
    """

    effects: list[dict[str, Any]]
    fitted: list[Effect]
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    rms_before_insample: dict[str, float]
    rms_after_insample: dict[str, float]
    steps: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    sigma_scale: float
    n: int
    noise_floor: dict[str, float] = field(default_factory=dict)
    unexplained: dict[str, float] = field(default_factory=dict)
    nees_before: float = float("nan")
    nees_after: float = float("nan")
    unexplained_flag: bool = False
    stats_before: dict[str, dict[str, float]] = field(default_factory=dict)
    stats_after: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (pixel RMS in px)."""
        return {"effects": self.effects, "pixel_rms_before": self.rms_before, "pixel_rms_after": self.rms_after,
                "pixel_noise_floor": self.noise_floor, "pixel_unexplained": self.unexplained,
                "pixel_nees_before": self.nees_before, "pixel_nees_after": self.nees_after,
                "pixel_unexplained_flag": self.unexplained_flag,
                "pixel_stats_before_insample": self.stats_before, "pixel_stats_after_insample": self.stats_after,
                "pixel_rms_before_insample": self.rms_before_insample,
                "pixel_rms_after_insample": self.rms_after_insample, "steps": self.steps,
                "rejected": self.rejected, "sigma_scale": self.sigma_scale, "n": self.n}


def diagnose_pixels(robot: Robot, obs: PixelObs, declared: Sequence[Effect] = (),
                    candidates: Sequence[Effect] | None = None, folds: int = 5, min_gain: float = 0.03,
                    min_t: float = 4.0, max_condition: float = 1e6, max_effects: int = 4,
                    iterations: int = 3, seed: int = 0, robust: bool = True,
                    pert: Mapping[str, np.ndarray] | None = None,
                    jnoise: Mapping[str, float] | None = None) -> PixelDiagnosis:
    """Trace the marker-pixel residual to ``camera_extrinsics`` (or given candidate) effects.

    The pixel residual (measured minus predicted with ``declared``), whitened by its expected
    covariance (:func:`pixel_covariance`: ``obs.sigma_px`` plus, if given, the declared
    perturbations ``pert`` and joint noise ``jnoise`` propagated to the pixels), is linearised
    at the declared chain, ``e = e0 - G theta``
    (:func:`pixel_jacobian`).  Greedy forward selection as in :func:`diagnose`: a candidate is
    accepted when the column-scaled normal matrix of the chosen set has condition number below
    ``max_condition`` and the held-out mean squared error (``folds``-fold cross-validation over
    poses) drops by at least ``min_gain`` with a paired t statistic >= ``min_t`` over the held-out
    poses.  The final fit is Gauss-Newton on the nonlinear chain (``iterations``); CIs are
    ``theta +- 1.96 sigma``.  With ``robust`` (default) the parameter covariance is the
    cluster-robust sandwich ``H^-1 (sum_pose g g^T) H^-1 * P/(P-1)`` (``g = G_pose^T r_pose``):
    the points seen at one pose share that pose's arm and camera error, so they are not
    independent; otherwise ``s^2 H^-1`` (``s^2`` the whitened residual variance, reported as
    ``sigma_scale``: the factor by which ``obs.sigma_px`` underestimates the residual).

    Raises
    ------
    MeasurementError
        Fewer than ``folds`` poses, or a marker behind its camera.
    """
    pp = _PixelProblem(robot, obs, list(declared), candidates, folds, seed, pert, jnoise)
    chosen, steps, rejected, hist = pp.select(max_effects, max_condition, min_gain, min_t)
    fitted, theta, G, r, sizes = pp.gauss_newton([pp.cands[i] for i in chosen], iterations)
    cur = pp.declared + fitted
    dof = max(len(r) - len(theta), 1)
    s2 = float(r @ r / dof)
    effects_out = pp.effects_out(fitted, G, r, sizes, hist, robust, s2) if fitted else []

    def per_cam(v: np.ndarray, root: bool = True) -> dict[str, float]:
        return {f: float(np.sqrt(np.mean(v[obs.camera == c])) if root else np.mean(v[obs.camera == c]))
                for c, f in enumerate(obs.cameras) if np.any(obs.camera == c)}

    sq0, m0 = pp.cv_errors([])
    sq1, m1 = pp.cv_errors(chosen)
    floor = per_cam(np.trace(pp.C, axis1=1, axis2=2))
    unexplained = {f: float(np.sqrt(max(per_cam(sq1)[f] ** 2 - floor[f] ** 2, 0.0))) for f in floor}
    # held-out mean Mahalanobis^2 per point (expectation 2 if the declared covariance is right);
    # standard error from the per-pose sums (points of a pose are correlated)
    counts = np.maximum(np.bincount(pp.pose_idx, minlength=len(pp.poses_u)), 1)
    pm = np.bincount(pp.pose_idx, m1, minlength=len(pp.poses_u)) / counts
    se = float(np.std(pm, ddof=1) / math.sqrt(len(pm))) if len(pm) > 1 else float("inf")
    nees_after = float(np.mean(m1))
    flagged = nees_after > 2.0 + 3.0 * se
    tree = pp.tree
    return PixelDiagnosis(effects=effects_out, fitted=fitted, rms_before=per_cam(sq0), rms_after=per_cam(sq1),
                          rms_before_insample=pixel_rms(tree, obs, pp.declared),
                          rms_after_insample=pixel_rms(tree, obs, cur),
                          stats_before=pixel_stats(tree, obs, pp.declared),
                          stats_after=pixel_stats(tree, obs, cur), steps=steps, rejected=rejected,
                          sigma_scale=math.sqrt(s2), n=len(obs), noise_floor=floor, unexplained=unexplained,
                          nees_before=float(np.mean(m0)), nees_after=nees_after, unexplained_flag=bool(flagged))


class _PixelProblem:
    """The whitened, linearised pixel problem of :func:`diagnose_pixels`: ``e = e0 - G theta`` per candidate,
    pose-wise folds, and the steps of the stage (selection, Gauss-Newton fit, covariance, effects out)."""

    def __init__(self, robot: Robot, obs: PixelObs, declared: list[Effect], candidates: Sequence[Effect] | None,
                 folds: int, seed: int, pert: Mapping[str, np.ndarray] | None,
                 jnoise: Mapping[str, float] | None) -> None:
        self.robot, self.obs, self.declared = robot, obs, declared
        self.tree = tree = KinematicTree(robot)
        self.cands = list(candidates) if candidates is not None else pixel_candidates(robot, obs)
        if len(np.unique(obs.pose)) < folds:
            raise MeasurementError(f"{obs.name}: {len(np.unique(obs.pose))} poses with pixels, need >= {folds} folds")
        self.C = pixel_covariance(tree, obs, declared, pert, jnoise)  # (M, 2, 2) [px^2]
        self.W = np.linalg.inv(np.linalg.cholesky(self.C))  # whitening: W C W^T = I
        self.e_raw = obs.uv - predict_pixels(tree, obs, declared)  # (M, 2) [px]
        self.e0 = np.einsum("mij,mj->mi", self.W, self.e_raw)
        self.J_raw = [pixel_jacobian(tree, obs, c, declared) for c in self.cands]  # (M, 2, P) [px / unit]
        self.Gs = [self.W @ J for J in self.J_raw]
        self.test_masks = _pose_folds(obs.pose, folds, seed)
        self.poses_u, self.pose_idx = np.unique(obs.pose, return_inverse=True)

    def heldout(self, idx: Sequence[int]) -> np.ndarray:
        """Per-pose held-out sum of squared whitened errors with candidates ``idx``."""
        obs, Gs, e0 = self.obs, self.Gs, self.e0
        err = np.zeros(len(obs))
        for test in self.test_masks:
            G = np.concatenate([Gs[i] for i in idx], axis=2) if idx else np.zeros((len(obs), 2, 0))
            r = e0.copy()
            if idx:
                th, _ = _lstsq(G[~test].reshape(-1, G.shape[2]), e0[~test].reshape(-1))
                r = e0 - G @ th
            err[test] = np.sum(r[test] ** 2, axis=1)
        return np.bincount(self.pose_idx, err, minlength=len(self.poses_u))

    def select(self, max_effects: int, max_condition: float, min_gain: float,
               min_t: float) -> tuple[list[int], list[dict[str, Any]], list[dict[str, Any]], list[float]]:
        """Greedy forward selection by held-out gain with a paired t test over poses (see diagnose_pixels)."""
        Gs = self.Gs

        def design(idx: Sequence[int]) -> np.ndarray:
            return np.concatenate([Gs[k] for k in idx], axis=2).reshape(-1, sum(Gs[k].shape[2] for k in idx))

        sel = select_by_heldout_gain(len(self.cands), lambda i: self.cands[i].describe(), design, self.heldout,
                                     self.e0, max_effects=max_effects, max_condition=max_condition,
                                     min_gain=min_gain, min_t=min_t)
        return sel.chosen, sel.steps, sel.rejected, sel.hist

    def gauss_newton(self, chosen: list[Effect],
                     iterations: int) -> tuple[list[Effect], np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """Nonlinear Gauss-Newton fit of the chosen effects on all data: (fitted, theta, G, whitened r, sizes)."""
        tree, obs, W, declared = self.tree, self.obs, self.W, self.declared
        fitted = [c.with_params(np.zeros(c.n_params)) for c in chosen]
        sizes = [f.n_params for f in fitted]
        theta = np.zeros(sum(sizes))
        G = np.zeros((len(obs) * 2, 0))
        r = self.e0.reshape(-1)
        for _ in range(iterations if fitted else 0):
            cur = declared + fitted
            r = np.einsum("mij,mj->mi", W, obs.uv - predict_pixels(tree, obs, cur)).reshape(-1)
            G = np.concatenate([W @ pixel_jacobian(tree, obs, f, cur) for f in fitted], axis=2).reshape(len(r), -1)
            dth, _ = _lstsq(G, r)
            theta = theta + dth
            fitted = [f.with_params(p) for f, p in zip(fitted, np.split(theta, np.cumsum(sizes)[:-1]))]
        cur = declared + fitted
        r = np.einsum("mij,mj->mi", W, obs.uv - predict_pixels(tree, obs, cur)).reshape(-1)
        return fitted, theta, G, r, sizes

    def param_covariance(self, G: np.ndarray, r: np.ndarray, robust: bool, s2: float) -> np.ndarray:
        """Parameter covariance: cluster-robust sandwich over poses (``robust``) or ``s^2 H^-1``."""
        H_inv = np.linalg.pinv(G.T @ G)
        if not robust:
            return H_inv * s2
        # cluster-robust (sandwich) covariance, clusters = poses: errors of the points seen at
        # one pose share that pose's arm and camera error
        obs = self.obs
        rp = r.reshape(len(obs), 2)
        Gp = G.reshape(len(obs), 2, -1)
        S = np.zeros((G.shape[1], G.shape[1]))
        for g in range(len(self.poses_u)):
            m = self.pose_idx == g
            sg = np.einsum("mki,mk->i", Gp[m], rp[m])
            S += np.outer(sg, sg)
        n_g = len(self.poses_u)
        return H_inv @ S @ H_inv * (n_g / max(n_g - 1, 1))

    def effects_out(self, fitted: list[Effect], G: np.ndarray, r: np.ndarray, sizes: list[int], hist: list[float],
                    robust: bool, s2: float) -> list[dict[str, Any]]:
        """Effect entries (parameters, 95 % CI, sigma, share of the pixel residual) of the fitted effects."""
        cov_theta = self.param_covariance(G, r, robust, s2)
        sig = np.sqrt(np.maximum(np.diag(cov_theta), 0.0))
        out: list[dict[str, Any]] = []
        for k, (f, sg) in enumerate(zip(fitted, np.split(sig, np.cumsum(sizes)[:-1]))):
            frame = next((cf for cf in self.obs.cameras if camera_mount_joint(self.robot, cf) == f.location), None)
            out.append({
                "name": f.name, "location": f.location, "frame": frame, "measurement": "pixels",
                "parameters": {p: float(v) for p, v in zip(f.param_names, f.params)},
                "ci": {p: [float(v - 1.96 * s), float(v + 1.96 * s)] for p, v, s in zip(f.param_names, f.params, sg)},
                "sigma": {p: float(s) for p, s in zip(f.param_names, sg)},
                "share": float((hist[k] - hist[k + 1]) / hist[0]) if hist[0] > 0 else 0.0,
            })
        return out

    def cv_errors(self, idx: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Held-out squared raw error [px^2] and Mahalanobis^2 per observation."""
        obs, Gs, e0, e_raw = self.obs, self.Gs, self.e0, self.e_raw
        sq = np.zeros(len(obs))
        maha = np.zeros(len(obs))
        for test in self.test_masks:
            rr, ww = e_raw, e0
            if idx:
                Gi = np.concatenate([Gs[k] for k in idx], axis=2)
                th, _ = _lstsq(Gi[~test].reshape(-1, Gi.shape[2]), e0[~test].reshape(-1))
                rr = e_raw - np.concatenate([self.J_raw[k] for k in idx], axis=2) @ th
                ww = e0 - Gi @ th
            sq[test] = np.sum(rr[test] ** 2, axis=1)
            maha[test] = np.sum(ww[test] ** 2, axis=1)
        return sq, maha


def pixels_from_bag(path: str | Path, robot: Robot, model_yaml: str | Path, sigma_px: float = 1.0,
                    refine: str = "subpix", accept_partial: bool = False) -> PixelObs:
    """Tag pixels of a contract bag as :class:`PixelObs` (centre and corner points).

    ``/tag_bearing/observations`` if the bag has it (e.g. the Motoman importer: marker centres),
    else tags detected on the camera images with the tag bearing node's function
    (:func:`ppoe_core.sensing.tag_rows.observe_tags`).  Tags (id -> link, size, pose) come from the
    model YAML's ``tags`` section; intrinsics from ``/camera/camera_info`` (per ``frame_id``);
    joint values from ``/joint_states`` at each observation stamp.  Each message is one pose.

    Raises
    ------
    BagError
        No tag observations or images, a camera frame without CameraInfo, an observed id the
        model does not list.  Tags on several links give a per-row ``links`` array.
    """
    from ppoe_core.estimation.measurements import tag_points
    from ppoe_core.io import bagio

    cfg = load_model(model_yaml, robot)[0]
    if cfg.tags is None or not cfg.tags.items:
        raise BagError(f"{model_yaml}: no 'tags' section: pixels of bag {path} cannot be attributed to links")
    by_id = cfg.tags.by_id()
    links = sorted({t.link for t in cfg.tags.items})
    data = bagio.read_bag(path, load_images=True, accept_partial=accept_partial)
    ci = data.camera_info
    intr: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for i, f in enumerate(ci.frame_ids):
        intr.setdefault(f, (ci.K[i], ci.D[i]))
    rows_all, frames, stamps = _pixel_rows(data, path, intr, cfg, by_id, refine)
    rows = np.concatenate(rows_all) if rows_all else np.zeros((0, 5))
    if len(rows) == 0:
        raise BagError(f"bag {path}: no tag observed in {len(frames)} messages")
    msg = rows[:, 0].astype(int)
    ids = np.rint(rows[:, 1]).astype(int)
    unknown = sorted(set(ids.tolist()) - set(by_id))
    if unknown:
        raise BagError(f"bag {path}: observed tag ids {unknown} are not in {model_yaml} tags")
    corner = np.rint(rows[:, 2]).astype(int)
    point = np.array([tag_points(by_id[t].size, by_id[t].T_link_tag)[c] for t, c in zip(ids, corner)])
    cams = sorted(set(frames[k] for k in np.unique(msg)))
    missing = [f for f in cams if f not in intr]
    if missing:
        raise BagError(f"bag {path}: no /camera/camera_info for camera frames {missing}")
    for f in cams:
        if f not in robot.links:
            raise BagError(f"bag {path}: camera frame {f!r} is not a link of URDF {robot.source}")
    q, ctx = _joints_at(data.joint_states, robot, np.asarray(stamps)[msg], path, [*links, *cams])
    ctx["sensor"] = np.array([frames[k] for k in msg])  # the camera of each row (a camera's time_offset)
    row_links = np.array([by_id[t].link for t in ids], dtype=object)
    return PixelObs(q=q, context=ctx, link=str(row_links[0]), point=point,
                    camera=np.array([cams.index(frames[k]) for k in msg]), cameras=cams,
                    K=[intr[f][0] for f in cams], D=[intr[f][1] for f in cams], uv=rows[:, 3:5].copy(),
                    pose=msg, sigma_px=float(sigma_px), name=Path(path).name,
                    links=row_links if len(set(row_links.tolist())) > 1 else None)


def concat_pixel_obs(parts: Sequence[PixelObs]) -> PixelObs:
    """Join :class:`PixelObs` of several sources (tags on any links); poses and cameras renumbered."""
    if not parts:
        raise MeasurementError("concat_pixel_obs: no pixel observations given")
    several = any(p.links is not None for p in parts) or len({p.link for p in parts}) > 1
    cams: list[str] = []
    K: list[np.ndarray] = []
    D: list[np.ndarray] = []
    for p in parts:
        for c, f in enumerate(p.cameras):
            if f not in cams:
                cams.append(f)
                K.append(p.K[c])
                D.append(p.D[c])
            elif not (np.allclose(K[cams.index(f)], p.K[c]) and np.allclose(D[cams.index(f)], p.D[c])):
                raise MeasurementError(f"{p.name}: camera '{f}' has other intrinsics than in {parts[0].name}")
    off = 0
    pose = []
    for p in parts:
        pose.append(p.pose + off)
        off += int(p.pose.max()) + 1 if len(p) else 0
    names = set().union(*[p.q for p in parts])
    links = np.concatenate([p.row_links() for p in parts]) if several else None
    return PixelObs(q={j: np.concatenate([p.q[j] for p in parts]) for j in names}, link=parts[0].link, links=links,
                    point=np.concatenate([p.point for p in parts]),
                    camera=np.concatenate([[cams.index(p.cameras[c]) for c in p.camera] for p in parts]).astype(int),
                    cameras=cams, K=K, D=D, uv=np.concatenate([p.uv for p in parts]), pose=np.concatenate(pose),
                    sigma_px=parts[0].sigma_px, name="+".join(p.name for p in parts),
                    context=_map_ctx(lambda *v: np.concatenate(v), [p.context for p in parts]))


def add_pixel_diagnosis(result: DiagnoseResult, robot: Robot, obs: PixelObs, declared: Sequence[Effect] = (),
                        **options: Any) -> PixelDiagnosis:
    """Run :func:`diagnose_pixels` on top of a tracker/pose ``result`` and merge it.

    The pixels are predicted with the declared effects plus the effects ``result`` found (the
    arm's errors move the markers too).  The pixel effects found are appended to
    ``result.effects`` (so the contract JSON and :func:`write_model_yaml` carry them),
    ``result.extra["pixels"]`` holds :meth:`PixelDiagnosis.to_json` and the summary says the
    pixel RMS before -> after (and UNEXPLAINED when the held-out pixel NEES is too large).
    ``options`` go to :func:`diagnose_pixels` (e.g. ``pert``, ``jnoise``: the declared
    covariance, ``folds``).
    """
    tree = KinematicTree(robot)
    keys = ("name", "location", "parameters", "variable", "reference")
    found = [effect_from_config({k: e[k] for k in keys if k in e}, tree,
                                where=f"diagnose effect {e['name']}@{e['location']}") for e in result.effects]
    pres = diagnose_pixels(robot, obs, list(declared) + found, **options)
    if pres.unexplained_flag:
        result.summary += (f"\nTag pixels UNEXPLAINED: held-out mean Mahalanobis^2 {pres.nees_after:.3g} per point "
                           f"(expected 2); RMS above the noise floor: "
                           + ", ".join(f"{f} {v:.2f} px" for f, v in pres.unexplained.items()))
    result.effects.extend(pres.effects)
    result.extra["pixels"] = pres.to_json()
    # the tracker/pose effects can move the markers away from the pixels (components a tracker
    # registration absorbs are seen by a camera fixed to the base): report the pixels without them
    result.extra["pixels"]["pixel_rms_declared_only"] = pixel_rms(tree, obs, declared)
    per = ", ".join(f"{f} {pres.rms_before[f]:.2f} -> {pres.rms_after[f]:.2f} px" for f in pres.rms_before)
    names = ", ".join(f"{e['name']}@{e['location']}" for e in pres.effects) or "none"
    result.summary += f"\nTag pixels ({pres.n} points): effects {names}; held-out RMS {per}."
    return pres


def _pixel_rows(data: Any, path: str | Path, intr: dict[str, tuple[np.ndarray, np.ndarray]], cfg: Any,
                by_id: dict, refine: str) -> tuple[list[np.ndarray], list[str], list[float]]:
    """Rows ``[message, id, corner, u, v]`` per message from ``/tag_bearing/observations`` or, without it, from
    tags detected on the images (the tag bearing node's function); camera frame and stamp per message."""
    from ppoe_core.sensing.tag_rows import observe_tags

    rows_all: list[np.ndarray] = []  # [msg, id, corner, u, v]
    frames: list[str] = []
    stamps: list[float] = []
    obs = data.tag_observations
    if len(obs):
        for i in range(len(obs)):
            m = obs.message(i)
            frames.append(obs.frame_ids[i])
            stamps.append(float(obs.stamps[i]))
            rows_all.append(np.column_stack([np.full(m["ids"].shape, i), m["ids"], m["corners"], m["uv"]]))
    elif len(data.images):
        imgs = data.images
        for i in range(len(imgs)):
            f = imgs.frame_ids[i]
            if f not in intr:
                raise BagError(f"bag {path}: topic {imgs.topic} message {i}: "
                               f"no /camera/camera_info with frame_id {f!r}")
            r, _ = observe_tags(imgs.decode(i), *intr[f], cfg.tags.family, tuple(by_id), refine)
            frames.append(f)
            stamps.append(float(imgs.stamps[i]))
            rows_all.append(np.column_stack([np.full(len(r), i), r[:, :4]]))
    else:
        raise BagError(f"bag {path}: neither /tag_bearing/observations nor camera images")
    return rows_all, frames, stamps


def _joints_at(js: Any, robot: Robot, at: np.ndarray, path: str | Path,
               links: Sequence[str] = ()) -> tuple[dict[str, np.ndarray], dict]:
    """Joint values at the observation stamps ``at`` and the context (time, joint velocity, motion sign).

    A joint the bag never carries is held at 0 when it is off the chains of ``links`` (markers, cameras: e.g.
    the other arm of a dual-arm robot), else an error naming it."""
    order = np.argsort(js.stamps, kind="stable")
    t_js = js.stamps[order]
    q: dict[str, np.ndarray] = {}
    vel: dict[str, np.ndarray] = {}
    cols = []
    needed = {j for ln in links for j in robot.path_from_root(ln)}
    for j in KinematicTree(robot).joint_names:
        if j not in js.names and links and j not in needed:
            q[j], vel[j] = np.zeros(len(at)), np.zeros(len(at))
            cols.append(np.zeros(len(t_js)))
            continue
        col = js.column(j)[order]
        good = np.isfinite(col)
        if not np.any(good):
            raise BagError(f"bag {path}: /joint_states carries no value of joint {j!r}")
        q[j] = _sample_joint(t_js[good], col[good], at)
        cols.append(np.interp(t_js, t_js[good], col[good]))
        v = np.gradient(col[good], t_js[good]) if good.sum() > 1 else np.zeros(good.sum())
        vel[j] = _sample_joint(t_js[good], v, at)
    signs = motion_signs(t_js, np.column_stack(cols), at)
    ctx = {"time": at - t_js[0], "joint_velocity": vel,
           "motion_sign": {j: signs[:, i] for i, j in enumerate(q)}}
    return q, ctx
