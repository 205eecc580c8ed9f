"""Replay of a bag through the nodes' own core code (kinematics -> tags/contact -> fusion), stop by stop."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.evaluate.metrics import (
    METHODS,
    _nees,
    _regularised,
    error_stats,
    nees_stats,
    point_covariance,
    position_errors,
    rotation_errors,
)
from ppoe_core.analysis.evaluate.options import EvaluateOptions, Evaluation
from ppoe_core.errors import BagError, JointValueError, ModelConfigError, PpoeError, UnknownJointError
from ppoe_core.estimation import fusion
from ppoe_core.estimation.pipeline import FUSION_SETTINGS

# ----------------------------------------------------------------------------
# Progress bar
# ----------------------------------------------------------------------------


class ProgressBar:
    """A minimal text progress bar on a stream (stderr by default), throttled to 10 Hz.

    Parameters
    ----------
    total : int
        Number of steps.
    enabled : bool
        Draw nothing when False.
    label : str
    stream : file-like, optional
    """

    def __init__(self, total: int, enabled: bool, label: str = "evaluate", stream: Any = None) -> None:
        self.total = max(int(total), 1)
        self.enabled = bool(enabled)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self._last = 0.0
        self._t0 = time.monotonic()

    def update(self, done: int) -> None:
        """Redraw for ``done`` steps finished (at most every 0.1 s)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < 0.1 and done < self.total:
            return
        self._last = now
        frac = min(done / self.total, 1.0)
        width = 30
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        el = now - self._t0
        eta = f"{el / frac - el:6.1f}s" if frac > 0 else "     ?"
        self.stream.write(f"\r{self.label} [{bar}] {100 * frac:5.1f}% {el:6.1f}s eta {eta}")
        self.stream.flush()

    def close(self) -> None:
        """Finish the line."""
        if self.enabled:
            self.update(self.total)
            self.stream.write("\n")
            self.stream.flush()


# ----------------------------------------------------------------------------
# Replay
# ----------------------------------------------------------------------------


def _load_model(urdf_xml: str, model_yaml: str | Path) -> Any:
    from ppoe_core.model.ppoe import PPOEModel

    path = Path(model_yaml)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ModelConfigError(f"{path}: cannot read model YAML: {exc}") from None
    try:
        return PPOEModel.from_strings(urdf_xml, text)
    except ModelConfigError as exc:
        raise ModelConfigError(f"{path}: {exc}") from None


def joint_matrix(js: Any, joint_names: Sequence[str], bag: str) -> tuple[np.ndarray, int]:
    """Joint states -> (N, n) in ``joint_names`` order; gaps filled from the previous message.

    Returns the matrix and the number of values held from a previous message.  A joint the
    model needs that the bag never carries, or lacks in its first message, is a BagError.
    """
    N = len(js)
    Q = np.empty((N, len(joint_names)))
    held = 0
    for j, name in enumerate(joint_names):
        if name not in js.names:
            raise BagError(
                f"bag {bag}: topic /joint_states never carries joint {name!r} that the model chain needs "
                f"(carries {js.names})"
            )
        col = js.positions[:, js.names.index(name)].copy()
        bad = ~np.isfinite(col)
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            if first == 0 and bad.all():
                raise BagError(f"bag {bag}: topic /joint_states: joint {name!r} has no finite value")
            idx = np.where(bad, 0, np.arange(N))
            np.maximum.accumulate(idx, out=idx)
            if bad[0]:
                raise BagError(
                    f"bag {bag}: topic /joint_states message 0 (stamp {js.stamps[0]:.6f}): joint {name!r} "
                    "missing or not finite and no earlier value to hold"
                )
            col = col[idx]
            held += int(bad.sum())
        Q[:, j] = col
    return Q, held


def _camera_lookup(data: Any) -> Callable[[str, float], tuple[np.ndarray, np.ndarray] | None]:
    """frame_id, stamp -> (K, D) of the latest camera_info of that frame at or before the stamp
    (or the first one after it if there is none before)."""
    ci = data.camera_info
    per: dict[str, tuple[np.ndarray, list[int]]] = {}
    for i, f in enumerate(ci.frame_ids):
        per.setdefault(f, (np.zeros(0), []))[1].append(i)
    table = {f: (ci.stamps[idx], idx) for f, (_, idx) in per.items()}

    def lookup(frame: str, stamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        if frame not in table:
            return None
        st, idx = table[frame]
        k = int(np.searchsorted(st, stamp, side="right")) - 1
        i = idx[max(k, 0)]
        return ci.K[i], ci.D[i]

    return lookup


def tag_measurements(
    data: Any, model: Any, bag: str, refine: str = "subpix"
) -> tuple[list[Any], dict[str, int]]:
    """Measurements of tag observations: recorded ``/tag_bearing/observations`` if present,
    else detections on the camera images (``ppoe_core.sensing.tags.detect_tags``, as the tag node)."""
    from ppoe_core.estimation.pipeline import Measurement, TagMeasurement, source_key
    from ppoe_core.sensing.tag_rows import observe_tags

    counts = {"tag_messages": 0, "tag_points": 0, "images": 0, "images_without_tags": 0}
    cams = _camera_lookup(data)
    out = []
    obs = data.tag_observations
    if len(obs):
        topic = "/tag_bearing/observations"
        for i in range(len(obs)):
            m = obs.message(i)
            counts["tag_messages"] += 1
            if m["ids"].size == 0:
                continue
            counts["tag_points"] += int(m["ids"].size)
            frame, stamp = obs.frame_ids[i], float(obs.stamps[i])
            KD = cams(frame, stamp)
            fx, fy = (float(KD[0][0, 0]), float(KD[0][1, 1])) if KD is not None else (None, None)
            payload = TagMeasurement(frame, m["ids"], m["corners"], m["xy"], m["uv"], fx, fy)
            out.append(Measurement(stamp, source_key(topic, frame), payload))
        return out, counts
    imgs = data.images
    if len(imgs) == 0 or model.config.tags is None:
        return out, counts
    family = model.config.tags.family
    topic = imgs.topic
    for i in range(len(imgs)):
        counts["images"] += 1
        frame, stamp = imgs.frame_ids[i], float(imgs.stamps[i])
        KD = cams(frame, stamp)
        if KD is None:
            raise BagError(f"bag {bag}: topic {topic} message {i}: no /camera/camera_info with frame_id {frame!r}")
        K, D = KD
        rows, _ = observe_tags(imgs.decode(i), K, D, family, (), refine)
        counts["tag_messages"] += 1
        if rows.shape[0] == 0:
            counts["images_without_tags"] += 1
            continue
        counts["tag_points"] += int(rows.shape[0])
        ids, corners = np.rint(rows[:, 0]).astype(int), np.rint(rows[:, 1]).astype(int)
        payload = TagMeasurement(frame, ids, corners, rows[:, 4:6], rows[:, 2:4], float(K[0, 0]), float(K[1, 1]))
        out.append(Measurement(stamp, source_key("/tag_bearing/observations", frame), payload))
    return out, counts


def contact_measurements(
    data: Any, model: Any, model_yaml: str | Path, settings: dict[str, Any]
) -> tuple[list[Any], dict[str, Any]]:
    """Contact plane measurements, as the contact node would publish them and the fusion node
    would receive them.

    * Recorded ``/contact/plane`` (contact node output) is used as it is.
    * Otherwise a ``/wrench`` stream is replayed through :class:`ppoe_core.sensing.contact.ContactDetector`
      (:func:`ppoe_core.sensing.contact.contact_stamps`: thresholds and force measure from ``settings``, 0
      = the model YAML's ``contact`` section, as the node's parameters) and every wrench in contact
      gives the model YAML's plane (:func:`ppoe_core.sensing.contact.plane_from_config`) at the wrench's
      stamp.  Its ``Sigma_v`` goes the node's way: plane tangent space -> ROS convention (contact
      node) -> plane tangent space (fusion node).
    * A ``/wrench`` without a model YAML ``contact`` section fuses nothing: counted
      (``wrench_without_contact_config``), not an error (a bag may carry wrenches for other uses).

    Returns
    -------
    (measurements, counts)
        ``counts``: ``contact_source`` (``"/contact/plane"``, ``"/wrench"`` or None),
        ``contact_planes``, and for a replayed wrench its ``wrench`` counts (received, bad,
        contacts, published).
    """
    from ppoe_core.estimation.pipeline import ContactMeasurement, Measurement, source_key
    from ppoe_core.sensing.contact import ContactDetector, contact_stamps, plane_from_config

    topic = "/contact/plane"
    counts: dict[str, Any] = {"contact_source": None, "contact_planes": 0}
    series = data.poses_with_covariance.get(topic)
    out = []
    if series is not None and len(series):
        counts["contact_source"] = topic
        for i in range(len(series)):
            T = series.T[i]
            cov = lie.cov_ros_to_local(T, series.cov_ros[i])
            frame = series.frame_ids[i]
            payload = ContactMeasurement(frame, T, cov)
            out.append(Measurement(float(series.stamps[i]), source_key(topic, frame), payload))
        counts["contact_planes"] = len(out)
        return out, counts
    wr = data.wrench
    if len(wr) == 0:
        return out, counts
    contact = model.config.contact
    if contact is None:
        counts["wrench_without_contact_config"] = int(len(wr))
        return out, counts
    cfg = model.config
    where = f"{model_yaml}: contact"
    plane = plane_from_config(contact, cfg.frames.base if cfg.frames is not None else None, where=where)
    enter = float(settings["force_threshold"]) or contact.force_threshold
    release = float(settings["release_threshold"]) or contact.release_threshold
    try:
        detector = ContactDetector(enter, release)
    except ModelConfigError as exc:
        raise ModelConfigError(f"{where}: {exc}") from None
    stamps, wcounts = contact_stamps(wr.stamps, wr.force, detector, str(settings["force_component"]), "/wrench")
    # the fusion node's view of the message: the pose through the message's quaternion (as
    # ppoe_ros.common writes and reads it), the ROS-convention covariance back to the plane
    # tangent space at that pose
    q = lie.quat_from_matrix(plane.T_frame_plane[:3, :3])
    T_wire = plane.T_frame_plane.copy()
    T_wire[:3, :3] = lie.matrix_from_quat(q / np.linalg.norm(q))
    cov_plane = lie.check_covariance(lie.cov_ros_to_local(T_wire, plane.cov_ros), name=f"{topic} covariance", size=6)
    payload = ContactMeasurement(plane.frame, T_wire, cov_plane)
    source = source_key(topic, plane.frame)
    out = [Measurement(float(t), source, payload) for t in stamps]
    counts.update(
        {
            "contact_source": "/wrench",
            "contact_planes": len(out),
            "wrench": wcounts,
            "force_threshold": enter,
            "release_threshold": release,
        }
    )
    return out, counts


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
            if r["role"] == "stationing" and (fit_set == "all" or fit_set in r.get("point_sets", [])):
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


def evaluate_bag(bag: str | Path, model_yaml: str | Path, options: EvaluateOptions | None = None) -> Evaluation:
    """Replay ``bag`` through the core pipeline and score FK, PPOE-fused and naive-fused poses.

    Parameters
    ----------
    bag : str or Path
        Contract bag (CONTRACT.md section 3).
    model_yaml : str or Path
        The project's model YAML for the bag's ``/robot_description``.
    options : EvaluateOptions, optional

    Returns
    -------
    Evaluation

    Raises
    ------
    BagError
        The bag breaks the contract, has no joint states or no ground truth (names the topic).
    ModelConfigError, UnknownFrameError
        Bad model YAML or frame names.
    """
    from ppoe_core.estimation.pipeline import make_pipeline, make_updater
    from ppoe_core.io.bagio import read_bag

    opt = options or EvaluateOptions()
    bag = str(bag)
    t_start = time.perf_counter()
    data = read_bag(bag)
    urdf_xml = data.require_robot_description()
    model = _load_model(urdf_xml, model_yaml)
    cfg = model.config
    base = opt.base or (cfg.frames.base if cfg.frames is not None else None)
    tool = opt.tool or (cfg.frames.tool if cfg.frames is not None else None)
    if not base or not tool:
        raise ModelConfigError(f"{model_yaml}: no frames.base/frames.tool and no --base/--tool given")
    js = data.joint_states
    if len(js) == 0:
        raise BagError(f"bag {bag}: no /joint_states messages")
    gt_pose, gt_point = data.ground_truth_pose, data.ground_truth_point
    if len(gt_pose) == 0 and len(gt_point) == 0:
        raise BagError(f"bag {bag}: neither /ground_truth/pose nor /ground_truth/point: nothing to score against")
    if opt.ground_truth not in ("auto", "pose", "point"):
        raise PpoeError(f"ground_truth must be auto, pose or point, not {opt.ground_truth!r}")
    kind = opt.ground_truth if opt.ground_truth != "auto" else ("pose" if len(gt_pose) else "point")
    if len(gt_pose if kind == "pose" else gt_point) == 0:
        raise BagError(f"bag {bag}: no /ground_truth/{kind} messages to score against")
    if kind == "pose":
        bad = [f for f in set(gt_pose.frame_ids) if f != base]
        if bad:
            raise BagError(
                f"bag {bag}: topic /ground_truth/pose has frame_id {bad[0]!r}, expected the base frame {base!r}"
            )
    elif cfg.tracker is None:
        raise ModelConfigError(
            f"{model_yaml}: the bag has /ground_truth/point but the model YAML has no 'tracker' section"
        )

    order = np.argsort(js.stamps, kind="stable")
    stamps = js.stamps[order]
    Q, held = joint_matrix(js, model.joint_names, bag)
    Q = Q[order]
    joints = {n: Q[:, j] for j, n in enumerate(model.joint_names)}
    try:
        T_all, cov_all = model.fk(joints, base, tool, order=opt.order)
    except (UnknownJointError, JointValueError) as exc:
        raise BagError(f"bag {bag}: topic /joint_states: {exc}") from None
    cov_naive = cfg.naive.covariance if cfg.naive is not None else None
    # validated once for the whole batch here (and the naive one by the model YAML loader), so
    # the pipelines skip the per-prior check
    lie.check_covariance(cov_all, name=f"bag {bag}: forward-kinematics covariance of {tool} in {base}", size=6)
    if cov_naive is not None:
        lie.check_covariance(cov_naive, name=f"{model_yaml}: naive covariance", size=6)

    fs = opt.fusion_settings()
    tag_meas, tag_counts = tag_measurements(data, model, bag, refine=str(fs["corner_refinement"]))
    contact_meas, contact_counts = contact_measurements(data, model, model_yaml, fs)
    meas = sorted(tag_meas + contact_meas, key=lambda m: m.stamp)

    # the fusion node's pipeline and updater (ppoe_core.estimation.pipeline.make_pipeline / make_updater
    # with the node's settings); the naive model knows nothing of the camera chain's covariance
    node_settings = {k: fs[k] for k in FUSION_SETTINGS}
    pipes: dict[str, Any] = {}
    updaters: dict[str, Any] = {}
    for name in ("ppoe", "naive"):
        if name == "naive" and cov_naive is None:
            continue
        s_name = {**node_settings, "camera_covariance": bool(fs["camera_covariance"]) and name == "ppoe"}
        try:
            updaters[name] = make_updater(model, base, tool, s_name)
            pipes[name] = make_pipeline(model, base, tool, s_name, updater=updaters[name])
        except (TypeError, ValueError) as exc:
            raise ModelConfigError(f"fusion settings: {exc}") from None

    gt_stamps = gt_pose.stamps if kind == "pose" else gt_point.stamps
    # events: (stamp, kind rank, index); priors first, then measurements, then ground truth
    ev_t = np.concatenate([stamps, [m.stamp for m in meas], gt_stamps])
    ev_k = np.concatenate([np.zeros(len(stamps), int), np.ones(len(meas), int), np.full(len(gt_stamps), 2)])
    ev_i = np.concatenate([np.arange(len(stamps)), np.arange(len(meas)), np.arange(len(gt_stamps))])
    ev = np.lexsort((ev_i, ev_k, ev_t))
    n_gt = len(gt_stamps)
    est_T = {m: np.full((n_gt, 4, 4), np.nan) for m in METHODS}
    est_cov = {m: np.full((n_gt, 6, 6), np.nan) for m in METHODS}
    gt_joints = np.full((n_gt, len(model.joint_names)), np.nan)
    nis: dict[str, list[tuple[float, int]]] = {m: [] for m in pipes}
    outcomes: dict[str, dict[str, int]] = {m: {} for m in pipes}
    errors: dict[str, list[str]] = {m: [] for m in pipes}

    def record(name: str, outs: Sequence[Any]) -> None:
        for o in outs:
            outcomes[name][o.status] = outcomes[name].get(o.status, 0) + 1
            if o.status in ("accepted", "rejected") and math.isfinite(o.nis):
                pl = o.measurement.payload
                known = updaters[name].tags
                dim = 2 * sum(int(t) in known for t in pl.ids) if hasattr(pl, "ids") else 1
                nis[name].append((o.nis, dim))
            if o.status == "bad" and len(errors[name]) < 20:
                errors[name].append(o.error)

    bar = ProgressBar(len(ev), opt.progress)
    for done, e in enumerate(ev):
        k, i = int(ev_k[e]), int(ev_i[e])
        if k == 0:
            for name, pipe in pipes.items():
                cov = cov_all[i] if name == "ppoe" else cov_naive
                _, outs = pipe.add_prior(float(stamps[i]), T_all[i], cov, Q[i], validated=True)
                record(name, outs)
        elif k == 1:
            for name, pipe in pipes.items():
                o = pipe.add_measurement(meas[i])
                if o.status != "pending":
                    record(name, [o])
        else:
            t = float(gt_stamps[i])
            for name, pipe in pipes.items():
                # stamps near 1.7e9 s resolve ~0.24 us in float64: 1 us margin
                record(name, pipe.flush(older_than=t + 1e-6))
                status, prior = pipe.buffer.lookup_hold(t)
                if prior is None:
                    continue
                fused = pipe.fuse(prior)
                est_T[name][i], est_cov[name][i] = fused.T_base_tool, fused.cov_tool
                if name == "ppoe":
                    est_T["fk"][i], est_cov["fk"][i] = prior.T_base_tool, prior.cov_tool
                    gt_joints[i] = prior.joints
            if not pipes:  # no fusion at all: FK from the nearest joint state
                j = int(np.clip(np.searchsorted(stamps, t, side="right") - 1, 0, len(stamps) - 1))
                est_T["fk"][i], est_cov["fk"][i], gt_joints[i] = T_all[j], cov_all[j], Q[j]
        if done % 256 == 0:
            bar.update(done)
    for name, pipe in pipes.items():
        record(name, pipe.flush())
    bar.close()

    have = np.all(np.isfinite(est_T["fk"].reshape(n_gt, -1)), axis=1)
    summary: dict[str, Any] = {
        "bag": bag,
        "model": str(model_yaml),
        "base": base,
        "tool": tool,
        "units": {"length": "m", "angle": "rad"},
        "joint_states": int(len(js)),
        "joint_values_held": int(held),
        "bag_duration_s": float(stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0,
        "ground_truth": {
            "topic": f"/ground_truth/{kind}",
            "kind": kind,
            "samples": int(n_gt),
            "without_prior": int(np.sum(~have)),
        },
        "measurements": {"total": len(meas), **tag_counts, **contact_counts},
        "fusion_settings": fs,
        "methods": {},
    }
    samples: dict[str, np.ndarray] = {}
    # without any measurement the fused estimates are the priors: only FK is scored
    methods = ["fk"] + (list(pipes) if meas else [])
    if not meas:
        summary["fusion"] = (
            "no tag observations, images, contact planes or wrenches in contact in the bag: only "
            "forward kinematics scored"
        )

    if kind == "pose":
        sel = np.flatnonzero(have)
        T_gt = gt_pose.T[sel]
        z_axis = T_gt[:, :3, 2]
        p_gt = T_gt[:, :3, 3]
        samples["stamp"] = gt_stamps[sel]
        for m in methods:
            Te, Ce = est_T[m][sel], est_cov[m][sel]
            e3, el = position_errors(Te[:, :3, 3], p_gt, z_axis)
            rot = rotation_errors(Te, T_gt)
            def pose_nees(Te: np.ndarray = Te, Ce: np.ndarray = Ce) -> Any:
                return fusion.nees(Te, _regularised(Ce), T_gt)

            ne = _nees(pose_nees, bag, m)
            samples.update(
                {
                    f"{m}_position_3d": e3,
                    f"{m}_lateral": el,
                    f"{m}_rotation": rot,
                    f"{m}_nees": ne,
                    f"{m}_position_error": Te[:, :3, 3] - p_gt,
                }
            )
            summary["methods"][m] = {
                "position_3d": error_stats(e3),
                "lateral": error_stats(el),
                "rotation": error_stats(rot),
                "nees": nees_stats(ne, 6),
            }
    else:
        tr = cfg.tracker
        roles = _stop_roles(bag, gt_stamps)
        groups, desc, unscored = registration_split(roles, n_gt, opt.fit_set)
        usable = have & np.all(np.isfinite(gt_point.p), axis=1)
        # reflector in tool coordinates at each sample (the chain tool -> tracker link may move)
        r_tool = np.full((n_gt, 3), np.nan)
        if usable.any():
            jd = {n: gt_joints[usable, j] for j, n in enumerate(model.joint_names)}
            T_tool_link = model.fk_mean(jd, tool, tr.link)
            r_tool[usable] = T_tool_link[..., :3, :3] @ tr.xyz + T_tool_link[..., :3, 3]
        Tfk = est_T["fk"]
        p_fk = np.einsum("nij,nj->ni", Tfk[:, :3, :3], r_tool) + Tfk[:, :3, 3]
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
            res_fit = np.linalg.norm(
                gt_point.p[fit] @ T_base_tracker[:3, :3].T + T_base_tracker[:3, 3] - p_fk[fit], axis=1
            )
            reg.append(
                {
                    "group": name,
                    "fit": int(len(fit)),
                    "scored": int(len(ev_idx)),
                    "fit_rms": float(np.sqrt(np.mean(res_fit**2))),
                }
            )
            scored.extend(ev_idx.tolist())
        sel = np.array(sorted(scored), int)
        summary["ground_truth"]["registration"] = {"method": desc, "groups": reg, "unscored": int(unscored)}
        samples["stamp"] = gt_stamps[sel]
        cov_gt = np.eye(3) * tr.sigma**2
        z_axis = Tfk[sel, :3, 2]
        for m in methods:
            Te, Ce = est_T[m][sel], est_cov[m][sel]
            p_e = np.einsum("nij,nj->ni", Te[:, :3, :3], r_tool[sel]) + Te[:, :3, 3]
            e3, el = position_errors(p_e, p_gt_base[sel], z_axis)
            Cp = point_covariance(Te, Ce, r_tool[sel]) + cov_gt
            # e^T C^-1 e of the reflector position error (fusion.nis: the same quadratic form)
            def point_nees(p_e: np.ndarray = p_e, Cp: np.ndarray = Cp) -> Any:
                return fusion.nis(p_e - p_gt_base[sel], _regularised(Cp))

            ne = _nees(point_nees, bag, m)
            samples.update(
                {
                    f"{m}_position_3d": e3,
                    f"{m}_lateral": el,
                    f"{m}_nees": ne,
                    f"{m}_position_error": p_e - p_gt_base[sel],
                }
            )
            summary["methods"][m] = {
                "position_3d": error_stats(e3),
                "lateral": error_stats(el),
                "nees": nees_stats(ne, 3),
            }
    for name, pipe in pipes.items():
        if name not in methods:
            continue
        v = np.array(nis[name]) if nis[name] else np.zeros((0, 2))
        summary["methods"][name]["measurements"] = {
            "counts": dict(pipe.counts),
            "outcomes": outcomes[name],
            "unknown_tag_points": int(updaters[name].unknown_tag_points),
            "errors": errors[name],
        }
        summary["methods"][name]["nis"] = {
            "mean": float(np.mean(v[:, 0])) if len(v) else float("nan"),
            "mean_per_dim": float(np.mean(v[:, 0] / v[:, 1])) if len(v) else float("nan"),
            "n": int(len(v)),
        }
    summary["wall_time_s"] = float(time.perf_counter() - t_start)
    return Evaluation(summary, samples)
