"""Tracker points or poses of a contract bag as :class:`~ppoe_core.analysis.diagnose.stops.Stops` (with the
accelerometers at the measurement stamps and the effect context: time, motion sign, joint velocity, temperature,
gravity, measured base tilt)."""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.stops import Stops, base_tilt_context
from ppoe_core.errors import BagError, ModelConfigError, PpoeError, PpoeWarning
from ppoe_core.model.context import at_rest, motion_band, motion_signs, sample_series, temperature_at
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["stops_from_bag", "static_mean"]


def _stop_info(path: str | Path) -> list[tuple[float, dict]]:
    """``/dataset/stop`` JSON objects of a bag (importer metadata), with their stamps."""
    from ppoe_core.io import bagio

    out = []
    for msg in bagio.iter_raw(path, ["/dataset/stop"]):
        m = bagio.deserialize(msg.data, msg.msgtype, topic=msg.topic)
        try:
            out.append((msg.stamp_ns * 1e-9, json.loads(m.data)))
        except (ValueError, AttributeError) as exc:
            raise BagError(f"bag {path}: topic /dataset/stop: message is not JSON: {exc}") from None
    return out


def stops_from_bag(path: str | Path, robot: Robot, *, tracker_link: str | None = None,
                   tracker_xyz: Sequence[float] = (0.0, 0.0, 0.0), tracker_sigma: float = 5e-4,
                   base: str | None = None, tool: str | None = None, pose_sigma: float = 5e-4,
                   pose_sigma_rot: float = 1e-3, stationing_set: str | None = "cross",
                   group_name: str | None = None, measurement: str = "auto",
                   accept_partial: bool = False, trackers: Sequence[Any] = ()) -> Stops:
    """Measurements of a contract bag as :class:`Stops`.

    Tracker points (preferred by ``measurement="auto"``) or ``/ground_truth/pose``
    (``measurement="point"`` / ``"pose"`` forces one); joint values are interpolated
    at each measurement stamp; context ``time``, ``motion_sign`` and ``joint_velocity`` come
    from ``/joint_states``, ``temperature`` from ``/temperature`` (the first such topic) if the bag has
    it, ``gravity`` (direction in the root frame) from the first ``/imu/<name>`` on a link rigidly
    fixed to the root, if any.

    Tracker points: with ``trackers`` (the model's ``trackers`` entries: topic, link, xyz, sigma)
    every reflector topic becomes rows on its link, and reflectors measured in the same
    ``header.frame_id`` share a registration session; else ``/ground_truth/point`` on
    ``tracker_link`` at ``tracker_xyz``.  A reflector topic of the bag that no entry declares is an
    error.  One registration session per bag (and tracker frame) unless the bag carries importer
    metadata ``/dataset/stop`` (``station``, ``role``, ``point_sets``): then one session per
    station, stationing stops (of ``stationing_set`` if given) define the registration and
    evaluation stops are scored.  ``accept_partial``: use what can be read of a damaged bag
    (:func:`ppoe_core.io.bagio.read_bag`).
    """
    from ppoe_core.io import bagio

    data = bagio.read_bag(path, load_images=False, accept_partial=accept_partial)
    for note in data.notes:  # a recovered or (accepted) partial bag: the user is told
        warnings.warn(note, PpoeWarning, stacklevel=2)
    js = data.joint_states
    if len(js) == 0:
        raise BagError(f"bag {path}: no /joint_states")
    name = group_name or Path(path).name
    if measurement not in ("auto", "point", "pose"):
        raise PpoeError(f"diagnose: measurement must be auto, point or pose, not {measurement!r}")
    has_points = len(data.ground_truth_point) > 0 or bool(data.ground_truth_points)
    if has_points and measurement in ("auto", "point"):
        if not trackers and tracker_link is None:
            raise ModelConfigError(f"bag {path} has tracker points but neither --tool nor the model's "
                                   "tracker.link / trackers names the link carrying the reflector")
        rows = _point_rows(path, data, robot, trackers or [_Reflector(tracker_link, tracker_xyz, tracker_sigma)])
        kind, R_meas = "point", None
    elif len(data.ground_truth_pose) > 0 and measurement in ("auto", "pose"):
        rows, R_meas, base = _pose_rows(path, data, robot, base, tool, pose_sigma)
        kind = "pose"
    else:
        raise BagError(f"bag {path}: no /ground_truth/point or /ground_truth/pose "
                       f"(measurement={measurement}): nothing to diagnose against")
    rows, R_meas = _within_joint_states(path, js, rows, R_meas)
    stamps, links = rows.stamps, rows.links
    q, ctx = _joint_context(js, robot, sorted(set(links)), stamps, path)
    _gravity_context(data, robot, stamps, ctx)
    _temperature_context(data, stamps, ctx)
    imus = _imu_samples(data, robot, stamps)
    n = len(stamps)
    session, session_names, reg, score = _sessions(path, data, name, stamps, stationing_set)
    session, session_names = _split_by_frame(session, session_names, rows.frames)
    if "gravity" in ctx:
        ctx["base_tilt"] = base_tilt_context(ctx["gravity"], session)
    several = len(set(links)) > 1 or len(rows.trackers) > 1
    return Stops(q=q, p_meas=rows.meas, R_meas=R_meas, kind=kind, link=links[0],
                 point=rows.points if several else rows.points[0],
                 sigma=rows.sigmas if several else float(rows.sigmas[0]), links=np.array(links, dtype=object)
                 if several else None, sigma_rot=pose_sigma_rot, base=base or robot.root, session=session,
                 session_names=session_names, group=np.zeros(n, dtype=int), group_names=[name],
                 reg_mask=reg, score_mask=score, context=ctx, imus=imus)


@dataclass
class _Reflector:
    """A reflector given by ``--tool`` / ``tracker``: on ``/ground_truth/point``."""

    link: str | None
    xyz: Sequence[float]
    sigma: float
    topic: str = "/ground_truth/point"


@dataclass
class _Rows:
    """Measurement rows of one bag: values, stamps, link / point / sigma / frame of each row."""

    meas: np.ndarray
    stamps: np.ndarray
    links: list[str]
    points: np.ndarray
    sigmas: np.ndarray
    frames: list[str]
    trackers: list[str]


def _point_rows(path: str | Path, data: Any, robot: Robot, trackers: Sequence[Any]) -> _Rows:
    """Rows of every declared reflector topic; an undeclared reflector topic of the bag is an error."""
    declared = {t.topic for t in trackers}
    undeclared = sorted(set(data.ground_truth_points) - declared)
    if len(data.ground_truth_point) and "/ground_truth/point" not in declared:
        undeclared.insert(0, "/ground_truth/point")
    if undeclared:
        raise ModelConfigError(f"bag {path}: {', '.join(undeclared)} carry reflector points, but the model's "
                               f"trackers list has no entry for them (declared: {sorted(declared)}); add "
                               "{topic, link, xyz, sigma} entries")
    parts = []
    for t in trackers:
        series = data.ground_truth_point if t.topic == "/ground_truth/point" else data.ground_truth_points.get(t.topic)
        if series is None or len(series) == 0:
            continue
        robot.check_link(t.link)
        m = len(series)
        parts.append((series.p, series.stamps, [t.link] * m, np.tile(np.asarray(t.xyz, float), (m, 1)),
                      np.full(m, float(t.sigma)), list(series.frame_ids), t.topic))
    if not parts:
        raise BagError(f"bag {path}: none of the model's tracker topics {sorted(declared)} has messages")
    return _Rows(np.concatenate([p[0] for p in parts]).astype(float), np.concatenate([p[1] for p in parts]),
                 [x for p in parts for x in p[2]], np.concatenate([p[3] for p in parts]),
                 np.concatenate([p[4] for p in parts]), [x for p in parts for x in p[5]], [p[6] for p in parts])


def _within_joint_states(path: str | Path, js: Any, rows: _Rows,
                         R_meas: np.ndarray | None) -> tuple[_Rows, np.ndarray | None]:
    """Drop measurements stamped before the first joint state (no joint values known there: stamps from
    another clock, or running backwards), with a warning that counts them; none left is an error."""
    t = np.sort(js.stamps[np.isfinite(js.stamps)])
    dt = np.diff(t)
    tol = 5.0 * float(np.median(dt[dt > 0])) if np.any(dt > 0) else 0.0
    keep = rows.stamps >= (t[0] - tol if t.size else np.inf)
    if keep.all():
        return rows, R_meas
    n_bad = int((~keep).sum())
    first = float(rows.stamps[~keep][0])
    what = (f"{n_bad} of {keep.size} measurements are stamped before the first /joint_states message "
            f"({first:.9g} s < {t[0]:.9g} s): no joint values are known there (stamps from another clock, or "
            "running backwards?)")
    if not keep.any():
        raise BagError(f"bag {path}: {what}; nothing to diagnose")
    warnings.warn(f"bag {path}: {what}; those measurements are left out", PpoeWarning, stacklevel=3)
    idx = np.flatnonzero(keep)
    sub = _Rows(rows.meas[idx], rows.stamps[idx], [rows.links[i] for i in idx], rows.points[idx], rows.sigmas[idx],
                [rows.frames[i] for i in idx], rows.trackers)
    return sub, None if R_meas is None else R_meas[idx]


def _pose_rows(path: str | Path, data: Any, robot: Robot, base: str | None, tool: str | None,
               sigma: float) -> tuple[_Rows, np.ndarray, str]:
    """Rows of ``/ground_truth/pose`` (tool ``tool`` in frame ``base``), their rotations and the base."""
    gt = data.ground_truth_pose
    frame_ids = set(gt.frame_ids)
    if base is not None and frame_ids - {base}:
        raise BagError(f"bag {path}: /ground_truth/pose is in frame(s) {sorted(frame_ids)}, "
                       f"not the base frame {base!r} given by --base/frames.base")
    base = base or next(iter(frame_ids))
    if tool is None:
        raise ModelConfigError(f"bag {path} has /ground_truth/pose but no --tool/frames.tool")
    robot.check_link(tool)
    n = len(gt)
    rows = _Rows(np.asarray(gt.T[:, :3, 3], dtype=float), gt.stamps, [tool] * n, np.zeros((n, 3)),
                 np.full(n, float(sigma)), [""] * n, ["/ground_truth/pose"])
    return rows, gt.T[:, :3, :3], base


def _split_by_frame(session: np.ndarray, names: list[str], frames: list[str]) -> tuple[np.ndarray, list[str]]:
    """One registration per session and tracker frame: sessions split by the rows' ``header.frame_id``."""
    if len(set(frames)) <= 1:
        return session, names
    keys = [(names[s], f) for s, f in zip(session.tolist(), frames)]
    uniq = list(dict.fromkeys(keys))
    return np.array([uniq.index(k) for k in keys]), [f"{s}@{f}" for s, f in uniq]


def _temperature_context(data: Any, stamps: np.ndarray, ctx: dict[str, Any]) -> None:
    """``ctx["temperature"]``: the first ``/temperature[/<name>]`` topic at the stamps (none: no key)."""
    temp = temperature_at(data.temperatures, stamps)
    if temp is not None:
        ctx["temperature"] = temp


def _check_joint_samples(path: str | Path, jn: str, t: np.ndarray, n_messages: int) -> None:
    """A joint needs finite values, and its stamps (sorted) must advance: repeated stamps (all 0, a clock that
    ran backwards and was sorted) make velocities and motion signs meaningless.

    Raises
    ------
    BagError
        Naming the bag, the joint and what is wrong.
    """
    if t.size == 0:
        raise BagError(f"bag {path}: /joint_states carries no finite value of joint {jn!r} "
                       f"(NaN or inf in all {n_messages} messages)")
    repeated = int(np.sum(np.diff(t) <= 0.0))
    if repeated:
        raise BagError(f"bag {path}: /joint_states stamps of joint {jn!r} do not advance: {repeated} of {t.size} "
                       f"messages repeat an earlier stamp (first stamp {t[0]:.9g} s); stamps must come from one "
                       "running clock")


def _joint_context(js: Any, robot: Robot, links: Sequence[str], stamps: np.ndarray,
                   path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Joint values at the measurement stamps and the context (time, motion sign, joint velocity)."""
    order = np.argsort(js.stamps, kind="stable")
    t_js = js.stamps[order]
    q: dict[str, np.ndarray] = {}
    vel: dict[str, np.ndarray] = {}
    pos_cols = []
    jnames = [j for j in robot.independent_joints if j in js.names]
    for link in links:
        missing = [j for j in robot.path_from_root(link) if robot.joints[j].independent and j not in js.names]
        if missing:
            raise BagError(f"bag {path}: /joint_states never carries {missing} (needed for link {link})")
    for jn in jnames:
        col = js.positions[order, js.names.index(jn)]
        good = np.isfinite(col)
        tg, cg = t_js[good], col[good]
        _check_joint_samples(path, jn, tg, len(col))
        q[jn] = sample_series(tg, cg, stamps)
        pos_cols.append(np.interp(t_js, tg, cg))
        v = np.gradient(cg, tg) if good.sum() > 1 else np.zeros(good.sum())
        vel[jn] = sample_series(tg, v, stamps)
    if pos_cols:  # at rest, the mean of the stop's samples (a noisy encoder's jitter averaged away)
        P = np.column_stack(pos_cols)
        q.update(zip(jnames, static_mean(t_js, P, stamps, motion_band(P), np.column_stack([q[j] for j in jnames])).T))
    absent = [j for j in robot.independent_joints if j not in q]  # off every measured chain (checked above)
    if absent:
        warnings.warn(f"bag {path}: /joint_states never carries {absent}; they are off the measured chains and "
                      "held at 0 (they only move the masses the gravity effects see)", PpoeWarning, stacklevel=3)
        q.update({j: np.zeros(len(stamps)) for j in absent})
    P = np.column_stack(pos_cols) if pos_cols else np.zeros((len(t_js), 0))
    signs = motion_signs(t_js, P, stamps, motion_band(P)) if pos_cols else np.zeros((len(stamps), 0))
    ctx = {"time": stamps - t_js[0], "motion_sign": {j: signs[:, i] for i, j in enumerate(jnames)},
           "joint_velocity": vel, "at_rest": at_rest(t_js, P, stamps)}
    return q, ctx


#: half-width [s] of the window of joint samples averaged at a measurement taken at rest
STATIC_WINDOW = 0.25


def static_mean(t: np.ndarray, P: np.ndarray, at: np.ndarray, band: np.ndarray, q_at: np.ndarray) -> np.ndarray:
    """Joint values (N, J) at times ``at``: where every joint rests (the samples within :data:`STATIC_WINDOW` of
    the time that stay within twice the motion dead band ``band`` (J,) of the interpolated value ``q_at`` (N, J),
    at least 3), the mean of those samples; elsewhere ``q_at``."""
    out = q_at.copy()
    lo, hi = np.searchsorted(t, at - STATIC_WINDOW), np.searchsorted(t, at + STATIC_WINDOW, side="right")
    for i in range(at.size):
        W = P[lo[i]:hi[i]]
        keep = np.all(np.abs(W - q_at[i]) <= 2.0 * band, axis=1)
        if keep.sum() >= 3:
            out[i] = W[keep].mean(axis=0)
    return out


def _gravity_context(data: Any, robot: Robot, stamps: np.ndarray, ctx: dict[str, Any]) -> None:
    """``ctx["gravity"]``: gravity direction in the root frame from the first accelerometer on a link
    rigidly fixed to the root (none: no key)."""
    tree = KinematicTree(robot)
    for _imu_name, imu in sorted(data.imus.items()):
        frame = imu.frame_ids[0] if imu.frame_ids else ""
        if (len(imu) and frame in robot.links
                and not any(robot.joints[j].movable for j in robot.path_from_root(frame))):
            R = tree.link_poses({}, links=[frame])[frame][:3, :3]
            a = imu.linear_acceleration / np.linalg.norm(imu.linear_acceleration, axis=1)[:, None]
            g = -np.column_stack([sample_series(imu.stamps, a[:, k], stamps) for k in range(3)]) @ R.T
            ctx["gravity"] = g / np.linalg.norm(g, axis=1)[:, None]
            break


def _imu_samples(data: Any, robot: Robot, stamps: np.ndarray) -> dict[str, tuple[str, np.ndarray]]:
    """Accelerometer readings (name -> (link, (n, 3))) at the measurement stamps."""
    imus: dict[str, tuple[str, np.ndarray]] = {}
    for imu_name, imu in sorted(data.imus.items()):
        frame = imu.frame_ids[0] if imu.frame_ids else ""
        if len(imu) and frame in robot.links:
            imus[imu_name] = (frame, np.column_stack([sample_series(imu.stamps, imu.linear_acceleration[:, k], stamps)
                                                      for k in range(3)]))
    return imus


def _sessions(path: str | Path, data: Any, name: str, stamps: np.ndarray,
              stationing_set: str | None) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """Registration sessions and stop roles: one session per bag, or per station with ``/dataset/stop``."""
    n = len(stamps)
    session = np.zeros(n, dtype=int)
    session_names = [name]
    reg = np.ones(n, dtype=bool)
    score = np.ones(n, dtype=bool)
    info = _stop_info(path) if "/dataset/stop" in data.topics else []
    if info:
        t_info = np.array([t for t, _ in info])
        k = np.clip(np.searchsorted(t_info, stamps, side="right") - 1, 0, len(info) - 1)
        stations = [info[i][1].get("station", "?") for i in k]
        session_names = [f"{name}:{s}" for s in dict.fromkeys(stations)]
        session = np.array([session_names.index(f"{name}:{s}") for s in stations])
        roles = [info[i][1].get("role", "") for i in k]
        sets = [info[i][1].get("point_sets") for i in k]  # None: the stop is in every set
        reg = np.array([(r == "stationing" and (stationing_set is None or s is None or stationing_set in s))
                        or r not in ("stationing", "evaluation") for r, s in zip(roles, sets)])
        score = np.array([r != "stationing" for r in roles])  # a stop without a role registers and is scored
    return session, session_names, reg, score
