"""How a diagnosis of a simulated bag compares with the bag's truth (``ppoe simulate``'s ``<bag>.truth.yaml``).

:func:`judge` reads a ``ppoe diagnose --json`` document (CONTRACT.md sec. 6: ``effects`` as ``{name, location,
parameters, ci}``) against the truth: every true effect of the contract vocabulary named at its location, nothing
else named, every parameter's truth inside its confidence interval ("exact").  :func:`truth_scores` scores the
TRUE model on a bag the way ``--test`` scores a fitted one (one rigid registration per tracker session, fitted on
all its points): the best any model can do, the sensor noise.  :func:`error_budget` says how large the true error
is at the reflector next to the declared prior (the PPOE spread there) and the sensor noise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.io.series import BagData
from ppoe_core.model.context import motion_signs, sample_series
from ppoe_core.robot.config import ModelConfig
from ppoe_core.robot.config_types import TrackerConfig
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot
from ppoe_core.sim.schedule import parse_value
from ppoe_core.sim.truth import TrueRobot, tag_location

__all__ = ["OUTSIDE_CATALOGUE", "NUISANCES", "Verdict", "judge", "truth_robot", "truth_scores", "error_budget",
           "TruthScores", "ErrorBudget"]

#: truth effects outside the contract vocabulary: a diagnosis should leave them unexplained (and say so)
OUTSIDE_CATALOGUE = ("transmission_error",)
#: reported effects that are nuisances, never counted as extra
NUISANCES = ("tracker_registration",)
#: a reported fx above this is an absolute focal length [px], below it a change of the declared one
ABSOLUTE_FOCAL_PX = 50.0


@dataclass
class Verdict:
    """A diagnosis against the truth.  Effects are written ``name@location``."""

    expected: list[str]
    reported: list[str]
    missing: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)
    out_of_ci: list[str] = field(default_factory=list)  #: ``name@location.param: truth v not in [lo, hi]``

    @property
    def named(self) -> bool:
        """Every true effect named at its location (extra ones allowed)."""
        return not self.missing

    @property
    def exact(self) -> bool:
        """Named, nothing extra, every parameter's truth in its CI."""
        return not (self.missing or self.extra or self.out_of_ci)


def _locations(robot: Robot | None, name: str, loc: str) -> set[str]:
    """Names under which a true effect at ``loc`` may be reported: the location itself; a tag's id forms; for a
    camera mount joint, the links hanging on it through fixed joints (the camera link and optical frame)."""
    out = {loc}
    if name == "tag_offset":
        n = loc[4:]
        out |= {n, f"tag{n}", f"tag_{n}"}
    if name == "camera_extrinsics" and robot is not None and loc in robot.joints:
        todo = [robot.joints[loc].child]
        while todo:
            link = todo.pop()
            out.add(link)
            todo += [robot.joints[j].child for j in robot.children(link) if not robot.joints[j].movable]
    return out


def _true_params(e: Mapping[str, Any], rep: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, float]:
    """The true parameters to compare with the reported ones of the same effect: as written in the truth, except
    an intrinsics report in absolute values (``fx`` > :data:`ABSOLUTE_FOCAL_PX`), compared with the true
    camera."""
    p = {k: float(v) for k, v in (e.get("parameters") or {}).items() if not isinstance(v, Mapping)}
    if e["name"] == "camera_intrinsics" and abs(float(rep.get("parameters", {}).get("fx", 0.0))) > ABSOLUTE_FOCAL_PX:
        cam = truth.get("camera") or {}
        K, D = np.asarray(cam["K_true"], float), np.asarray(cam["D_true"], float)
        p = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
             **dict(zip(("k1", "k2", "p1", "p2", "k3"), D.tolist()))}
    return p


def _check_params(key: str, truth_p: Mapping[str, float], rep: Mapping[str, Any], required: set[str]) -> list[str]:
    """``name@loc.param`` lines for every reported parameter whose truth (0 if the truth does not have it) lies
    outside its CI, and every ``required`` parameter (the effect's non-zero true ones) not reported."""
    out = []
    ci = rep.get("ci") or {}
    params = rep.get("parameters") or {}
    for k in sorted(set(params) | required):
        t = truth_p.get(k, 0.0)
        if k not in ci:
            out.append(f"{key}.{k}: truth {t:.4g} not reported" if k not in params else
                       f"{key}.{k}: no CI (estimate {params[k]:.4g}, truth {t:.4g})")
            continue
        lo, hi = (float(v) for v in ci[k])
        if not lo <= t <= hi:
            out.append(f"{key}.{k}: truth {t:.4g} not in [{lo:.4g}, {hi:.4g}]")
    return out


def judge(truth: Mapping[str, Any], diagnosis: Mapping[str, Any], robot: Robot | None = None,
          allowed_extra: Sequence[str] = ()) -> Verdict:
    """Compare a diagnosis with the truth.

    Parameters
    ----------
    truth : mapping
        The truth file (``effects``: ``{name, location, parameters}``; ``camera`` with ``K_true``, ``D_true``).
    diagnosis : mapping
        ``ppoe diagnose --json``: ``effects`` as ``{name, location, parameters, ci}``.
    robot : Robot, optional
        The bag's robot (for the frames a camera mount joint carries).
    allowed_extra : sequence of str
        ``name@location`` that do not count as extra (e.g. the joint offset a transmission error's sample mean
        amounts to).
    """
    true = [e for e in truth.get("effects") or [] if e["name"] not in OUTSIDE_CATALOGUE]
    reported = [e for e in diagnosis.get("effects") or [] if e["name"] not in NUISANCES]
    v = Verdict([f"{e['name']}@{e['location']}" for e in true], [f"{e['name']}@{e['location']}" for e in reported])
    used: set[int] = set()
    for e in true:
        key = f"{e['name']}@{e['location']}"
        locs = _locations(robot, e["name"], str(e["location"]))
        hit = next((i for i, r in enumerate(reported) if i not in used and r["name"] == e["name"]
                    and str(r["location"]) in locs), None)
        if hit is None:
            v.missing.append(key)
            continue
        used.add(hit)
        rep = reported[hit]
        if str(rep["location"]) != str(e["location"]) and e["name"] == "camera_extrinsics":
            v.out_of_ci.append(f"{key}: reported at {rep['location']}, parameters not comparable")
            continue
        required = {k for k, x in (e.get("parameters") or {}).items() if isinstance(x, Mapping) or float(x) != 0.0}
        v.out_of_ci += _check_params(key, _true_params(e, rep, truth), rep, required)
    v.extra = [v.reported[i] for i in range(len(reported)) if i not in used and v.reported[i] not in allowed_extra]
    return v


# =============================================================================
# the true model on a bag
# =============================================================================


def truth_robot(robot: Robot, truth: Mapping[str, Any]) -> TrueRobot:
    """The true robot of a truth file (effects; a thermal growth over time gets its reference back from the bag
    clock to seconds since the start; the temperature schedule)."""
    start = float(truth.get("start_time", 0.0))
    effects = []
    for e in truth.get("effects") or []:
        e = dict(e)
        if e["name"] == "thermal_growth" and e.get("variable", "time") == "time" and "reference" in e:
            e["reference"] = float(e["reference"]) - start
        if e["name"] == "tag_offset":
            e["location"] = tag_location(e["location"], "truth")
        effects.append(e)
    temp = truth.get("temperature")
    sched = parse_value(temp["value"], "truth temperature") if temp else None
    return TrueRobot(robot, effects, where="truth.effects", temperature=sched)


@dataclass
class TruthScores:
    """Scores of the true model on a bag's tracker points [m] (3D distances after one rigid registration per
    session), as ``ppoe diagnose --test`` reports them; ``reflector_error`` [m]: RMS 3D distance between the true
    and the nominal reflector after the best rigid registration (what the effects do at the reflectors)."""

    rms: float
    mean: float
    median: float
    p95: float
    max: float
    n: int
    reflector_error: float


def _trackers(model: ModelConfig) -> list[TrackerConfig]:
    """The model's reflectors (``trackers``, or the single ``tracker``)."""
    return list(model.trackers) or ([model.tracker] if model.tracker is not None else [])


def _tracker_rows(data: BagData, model: ModelConfig) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(session frame, link, xyz (3,), stamps (N,), points (N, 3))`` per tracker topic of the bag."""
    series = dict(data.ground_truth_points)
    if len(data.ground_truth_point):
        series["/ground_truth/point"] = data.ground_truth_point
    out = []
    for tr in _trackers(model):
        s = series.get(tr.topic)
        if s is not None and len(s):
            out.append((s.frame_ids[0], tr.link, np.asarray(tr.xyz, float), s.stamps, s.p))
    return out


def truth_scores(data: BagData, robot: Robot, model: ModelConfig, truth: Mapping[str, Any]) -> TruthScores:
    """Score the TRUE model (the truth file's effects, no fit) on the tracker points of ``data``."""
    true = truth_robot(robot, truth)
    nominal = KinematicTree(robot)
    js = data.joint_states
    order = np.argsort(js.stamps, kind="stable")
    t_js, P_js = js.stamps[order], js.positions[order]
    dt = true.effect_param("time_offset", "dt")
    joints = robot.independent_joints
    start = float(truth.get("start_time", 0.0))
    sessions: dict[str, list[np.ndarray]] = {}
    err2 = []
    for frame, link, xyz, stamps, p in _tracker_rows(data, model):
        cols = [js.names.index(j) for j in joints]
        q = {j: sample_series(t_js, P_js[:, c], stamps + dt) for j, c in zip(joints, cols)}  # the true joints
        q_rec = {j: sample_series(t_js, P_js[:, c], stamps) for j, c in zip(joints, cols)}  # as recorded
        sg = motion_signs(t_js, P_js[:, cols], stamps + dt)
        poses = true.poses(q, {}, {}, {j: sg[:, i] for i, j in enumerate(joints)}, stamps - start, len(stamps))
        pred = (poses[link] @ np.append(xyz, 1.0))[:, :3]
        nom = (nominal.link_poses(q_rec, links=[link])[link] @ np.append(xyz, 1.0))[:, :3]
        sessions.setdefault(frame, []).append(np.concatenate([pred, p, nom], axis=1))
    dist = []
    for rows in sessions.values():
        r = np.concatenate(rows)
        T = lie.fit_rigid(r[:, 0:3], r[:, 3:6])
        dist.append(np.linalg.norm(r[:, 0:3] @ T[:3, :3].T + T[:3, 3] - r[:, 3:6], axis=1))
        T2 = lie.fit_rigid(r[:, 6:9], r[:, 0:3])
        err2.append(np.sum((r[:, 6:9] @ T2[:3, :3].T + T2[:3, 3] - r[:, 0:3]) ** 2, axis=1))
    d = np.concatenate(dist) if dist else np.zeros(0)
    e2 = np.concatenate(err2) if err2 else np.zeros(0)
    if not d.size:
        return TruthScores(math.nan, math.nan, math.nan, math.nan, math.nan, 0, math.nan)
    return TruthScores(float(np.sqrt(np.mean(d ** 2))), float(d.mean()), float(np.median(d)),
                       float(np.percentile(d, 95)), float(d.max()), int(d.size), float(np.sqrt(e2.mean())))


@dataclass
class ErrorBudget:
    """At the reflectors of a bag [m, RMS of the 3D vector]: the true effects' error after the best rigid
    registration, the declared prior (first-order PPOE spread of the reflector, no registration), and the tracker
    noise (``sigma * sqrt(3)``, the floor of a held-out residual)."""

    true_error: float
    prior: float
    noise: float


def error_budget(data: BagData, robot: Robot, model: ModelConfig, truth: Mapping[str, Any]) -> ErrorBudget:
    """:class:`ErrorBudget` of a simulated bag."""
    from ppoe_core.model.ppoe import PPOEModel

    scores = truth_scores(data, robot, model, truth)
    ppoe = PPOEModel(robot, model)
    js = data.joint_states
    traces, sig = [], []
    for _frame, link, xyz, stamps, _p in _tracker_rows(data, model):
        q = {j: sample_series(js.stamps, js.positions[:, js.names.index(j)], stamps) for j in robot.independent_joints}
        _, cov = ppoe.fk(q, robot.root, link)
        A = np.concatenate([np.eye(3), -lie.hat(np.concatenate([np.zeros(3), xyz]))[:3, :3]], axis=1)
        traces.append(np.trace(A @ cov @ A.T, axis1=-2, axis2=-1))
        sig.append(next(t.sigma for t in _trackers(model) if t.link == link))
    prior = float(np.sqrt(np.mean(np.concatenate(traces)))) if traces else math.nan
    noise = float(np.sqrt(3) * np.mean(sig)) if sig else math.nan
    return ErrorBudget(scores.reflector_error, prior, noise)
