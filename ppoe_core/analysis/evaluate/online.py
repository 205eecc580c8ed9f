"""``ppoe evaluate --online``: drifting effects tracked through a bag, the drift monitor, tool error before / static /
online.

The bag's measurements are replayed in stamp order (ties by source) through the objects the fusion node runs live
(``ppoe_ros.common.online_effects``): :class:`~ppoe_core.estimation.online_inputs.OnlineInputs` (its :meth:`step`:
bad-input rules, :class:`~ppoe_core.estimation.online_effects.OnlineEffects`, the drift monitor of
:func:`~ppoe_core.analysis.drift_naming.make_monitor`).  Measurements: the model's tracker points
(``/ground_truth/point[/<name>]``, its ``trackers``) and accelerometers (``/imu/<name>``, its ``imus``), tag pixels
(recorded ``/tag_bearing/observations``, or tags detected on the images, with the focal lengths of ``camera_info``),
contact planes, and the fusion node's ``sources`` blocks of a node parameter file (6D poses, points,
accelerometers).  Each measurement takes the joints of the latest ``/joint_states`` at or before its stamp (merged
per joint as the nodes do) and the latest temperature at or before it.  At each ``/ground_truth/pose`` the tool pose
is scored by

* ``before``: the nominal model (no effects),
* ``static``: the diagnosed model, its effects fixed,
* ``online``: the estimate from every measurement stamped before the ground truth,
* ``fresh`` (with ``--truth``): the true effects at that moment, i.e. a robot calibrated just then.

With ``--truth BAG.truth.yaml`` (``ppoe simulate``) the estimate is compared with the true parameters over time
(:func:`ppoe_core.sim.schedule.truth_values`: error, 3-sigma coverage), and the drift's significance is located:
the first measurement from which the untracked truth moves the measurements by one noise sigma per component on
average over five measurements (:func:`significance`).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.drift_naming import make_monitor
from ppoe_core.analysis.evaluate.inputs import joint_matrix, required_joints
from ppoe_core.analysis.evaluate.online_config import OnlineSettings, load_online_config, load_online_settings
from ppoe_core.analysis.evaluate.online_report import (
    ONLINE_METHODS,
    OnlineEvaluation,
    markdown_online,
    write_online_report,
)
from ppoe_core.errors import BagError, ModelConfigError
from ppoe_core.estimation.online_effects import OnlineEffects, parse_online_config
from ppoe_core.estimation.online_inputs import IMU_TOPIC, OnlineInputs, OnlineMeasurement, OnlineStep
from ppoe_core.estimation.sources import complete_source, imu_payload, point_payload, pose_payload
from ppoe_core.io.bagio import read_bag
from ppoe_core.model.effects import effect_from_config
from ppoe_core.model.ppoe import PPOEModel
from ppoe_core.sim.schedule import parse_value

__all__ = ["ONLINE_METHODS", "OnlineEvaluation", "OnlineSettings", "evaluate_online", "load_online_config",
           "load_online_settings", "markdown_online", "significance", "truth_effects", "write_online_report"]

#: running mean over this many measurements decides when a drift is significant (:func:`significance`)
SIGNIFICANCE_RUN = 5


def _ns(stamp: float) -> int:
    """A bag stamp [s] in integer nanoseconds (the live messages' stamps; ``* 1e-9`` gives it back)."""
    return int(round(float(stamp) * 1e9))


def truth_effects(model: PPOEModel, truth: Mapping[str, Any], stamp: float) -> list[Any]:
    """The TRUE effects at ``stamp`` [s] of a simulation truth (a robot calibrated at that moment)."""
    t = stamp - float(truth.get("start_time", 0.0))
    effs = []
    for i, e in enumerate(truth.get("effects") or []):
        params = {k: float(parse_value(v, f"truth effects[{i}].{k}")(t)) for k, v in e["parameters"].items()}
        entry = {k: e[k] for k in ("name", "location", "variable", "reference") if k in e}
        effs.append(effect_from_config({**entry, "parameters": params}, model.robot, where=f"truth effects[{i}]"))
    return effs


def _topic(t: str) -> str:
    return "/" + t.strip("/")


def _source_measurements(data: Any, model: PPOEModel, sources: list[Any]) -> list[OnlineMeasurement]:
    """The fusion node's point / pose / accelerometer sources from the bag's series (the node's conversion rules,
    :mod:`ppoe_core.estimation.sources`)."""
    out: list[OnlineMeasurement] = []
    points = dict(data.ground_truth_points)
    if len(data.ground_truth_point):
        points["/ground_truth/point"] = data.ground_truth_point
    for src in sources:
        topic = _topic(src.topic)
        if src.off:
            continue
        rows: list[tuple[float, str, Any]]
        if src.kind == "pose":
            s = data.poses_with_covariance.get(topic)
            rows = [] if s is None else [(t, s.frame_ids[i], pose_payload(src, model, s.frame_ids[i], s.T[i],
                                                                           s.cov_ros[i]))
                                         for i, t in enumerate(s.stamps)]
        elif src.kind == "point":
            s = points.get(topic)
            rows = [] if s is None else [(t, s.frame_ids[i], point_payload(src, model, s.frame_ids[i], s.p[i]))
                                         for i, t in enumerate(s.stamps)]
        else:
            s = data.imus.get(topic[len(IMU_TOPIC):]) if topic.startswith(IMU_TOPIC) else None
            rows = [] if s is None else [(t, s.frame_ids[i], imu_payload(src, model, s.frame_ids[i],
                                                                          s.linear_acceleration[i],
                                                                          s.accel_covariance[i]))
                                         for i, t in enumerate(s.stamps)]
        out += [OnlineMeasurement(_ns(t), topic, f, payload=p) for t, f, p in rows if not isinstance(p, str)]
    return out


def _measurements(data: Any, model: PPOEModel, sources: list[Any], bag: str) -> list[OnlineMeasurement]:
    """Every measurement of the bag for the online filter, in the live processing order (stamp, then source)."""
    from ppoe_core.analysis.evaluate.replay import contact_measurements
    from ppoe_core.analysis.evaluate.tag_stream import tag_measurements

    taken = {_topic(s.topic) for s in sources if not s.off}
    out: list[OnlineMeasurement] = []
    points = dict(data.ground_truth_points)
    if len(data.ground_truth_point):
        points["/ground_truth/point"] = data.ground_truth_point
    for tr in model.config.trackers:
        s = points.get(tr.topic)
        if s is not None and tr.topic not in taken:
            out += [OnlineMeasurement(_ns(t), tr.topic, s.frame_ids[i], s.p[i]) for i, t in enumerate(s.stamps)]
    for name in model.config.imus:
        s = data.imus.get(name)
        if s is not None and f"{IMU_TOPIC}{name}" not in taken:
            out += [OnlineMeasurement(_ns(t), f"{IMU_TOPIC}{name}", s.frame_ids[i], s.linear_acceleration[i], name)
                    for i, t in enumerate(s.stamps)]
    if model.config.tags is not None:
        tags, _ = tag_measurements(data, model, bag)
        out += [_from_fusion(m) for m in tags]
    if len(data.wrench) or "/contact/plane" in data.poses_with_covariance:
        contacts, _ = contact_measurements(data, model, "", {})
        out += [_from_fusion(m) for m in contacts]
    out += _source_measurements(data, model, sources)
    return sorted(out, key=lambda m: (m.stamp_ns, m.source))


def _from_fusion(m: Any) -> OnlineMeasurement:
    """A fusion-pipeline :class:`~ppoe_core.estimation.corrections.Measurement` (source ``"<topic> [<frame>]"``)."""
    topic, _, frame = m.source.partition(" [")
    return OnlineMeasurement(_ns(m.stamp), topic, frame[:-1] if frame else "", payload=m.payload)


@dataclass
class _Replay:
    """The run's trace: after each step its stamp, estimate, effects; scored ground truths; counts."""

    steps: list[OnlineStep] = field(default_factory=list)
    thetas: list[tuple[list[str], np.ndarray, np.ndarray]] = field(default_factory=list)
    effects: list[list[Any]] = field(default_factory=list)


def evaluate_online(bag: str | Path, model_path: str | Path, online_effects: Any = None,
                    jump_probability: float | None = 1e-6, truth: Mapping[str, Any] | None = None,
                    base: str | None = None, tool: str | None = None, temperature_topic: str = "/temperature",
                    settings: OnlineSettings | None = None) -> OnlineEvaluation:
    """Replay ``bag`` with the online filter and the drift monitor (module docstring).  ``settings`` (a node
    parameter file's, :func:`load_online_settings`) overrides ``online_effects`` and ``jump_probability``.

    Raises
    ------
    BagError
        No ground-truth pose, no measurement for the filter; joints missing.
    ModelConfigError
        Bad online config; a tracker frame without ``tracker_registration`` in the model.
    """
    st = settings or OnlineSettings(online_effects, jump_probability)
    data = read_bag(bag, load_images=False)
    model = PPOEModel.from_strings(data.require_robot_description(), Path(model_path),
                                   urdf_source=f"bag {bag} /robot_description")
    if model.config.tags is not None and not len(data.tag_observations) and len(data.images):
        data = read_bag(bag, load_images=True)  # tags are detected on the images
    fr = model.config.frames
    base = base or (fr.base if fr is not None and fr.base else model.robot.root)
    tool = tool or (fr.tool if fr is not None else None)
    if tool is None:
        raise ModelConfigError(f"{model_path}: no frames.tool and no --tool given")
    sources = [copy.copy(s) for s in st.sources]
    for s in sources:
        s.off = complete_source(s, model)
    filt = OnlineEffects(model, parse_online_config(st.entries, model, sources=sources), st.jump_probability)
    monitor = make_monitor(st.monitor, st.naming) if st.monitor is not None else None
    inputs = OnlineInputs(filt, monitor=monitor, base=base, temperature_timeout_ns=_ns(st.temperature_timeout))
    temps = data.temperatures.get(temperature_topic)
    if filt.needs_temperature() and temps is None:
        raise BagError(f"bag {bag}: a thermal_growth effect with variable temperature needs {temperature_topic}; "
                       f"the bag has {sorted(data.temperatures) or 'no temperature topic'}")
    meas = _measurements(data, model, sources, str(bag))
    gt = data.ground_truth_pose
    if len(gt) == 0:
        raise BagError(f"bag {data.path}: --online needs /ground_truth/pose to score the tool")
    if not meas:
        raise BagError(f"bag {data.path}: --online needs measurements for the filter: tracker points of the model's "
                       f"trackers ({[t.topic for t in model.config.trackers]}), accelerometers of its imus "
                       f"({[IMU_TOPIC + n for n in model.config.imus]}), tag observations or the sources of the "
                       "online config; the bag has none")
    names = list(model.joint_names)
    Q, _ = joint_matrix(data.joint_states, names, str(bag), required=required_joints(model, {base, tool}))
    rep = _replay(inputs, data, meas, Q, names, temps)
    return _result(str(bag), model, filt, inputs, monitor, rep, data, Q, names, temps, truth, base, tool)


def _replay(inputs: OnlineInputs, data: Any, meas: list[OnlineMeasurement], Q: np.ndarray, names: list[str],
            temps: Any) -> _Replay:
    """Camera infos and measurements in stamp order through :meth:`OnlineInputs.step`."""
    rep = _Replay()
    js_t = np.asarray(data.joint_states.stamps, float)
    ci = data.camera_info
    cams = sorted((_ns(t), ci.frame_ids[i], i) for i, t in enumerate(ci.stamps))
    t_st = [_ns(t) for t in temps.stamps] if temps is not None else []
    js_ns = [_ns(t) for t in js_t]
    c = 0
    filt = inputs.filter
    for m in meas:
        while c < len(cams) and cams[c][0] <= m.stamp_ns:
            inputs.camera_info(cams[c][1], ci.K[cams[c][2]], ci.D[cams[c][2]])
            c += 1
        if not inputs.joints_known(js_ns, m):
            continue
        i = int(np.searchsorted(js_ns, m.stamp_ns, side="right")) - 1
        if not np.all(np.isfinite(Q[i])):
            inputs.counts.no_joints += 1
            continue
        k = int(np.searchsorted(t_st, m.stamp_ns, side="right")) - 1
        temp = (t_st[k], float(temps.temperature[k])) if k >= 0 else None
        step = inputs.take(m, dict(zip(names, Q[i].tolist())), temp)
        if step is not None:
            rep.steps.append(step)
            assert step.theta is not None and step.P is not None
            rep.thetas.append((list(step.labels), step.theta, np.sqrt(np.clip(np.diag(step.P), 0.0, None))))
            rep.effects.append(filt.effects())
    return rep


def _result(bag: str, model: PPOEModel, filt: OnlineEffects, inputs: OnlineInputs, monitor: Any, rep: _Replay,
            data: Any, Q: np.ndarray, names: list[str], temps: Any, truth: Mapping | None, base: str,
            tool: str) -> OnlineEvaluation:
    from ppoe_core.analysis.evaluate.online_report import build_evaluation

    scored = _score(filt, model, rep, data, Q, names, temps, truth, base, tool)
    sig = significance(filt, [s.row for s in rep.steps if s.row is not None], truth) if truth is not None else None
    return build_evaluation(bag, filt, inputs, monitor, rep, scored, truth, sig)


def _score(filt: OnlineEffects, model: PPOEModel, rep: _Replay, data: Any, Q: np.ndarray, names: list[str],
           temps: Any, truth: Mapping | None, base: str, tool: str) -> dict[str, Any]:
    """Tool poses of every method at each ground-truth pose (the online one from the last step stamped before)."""
    gt = data.ground_truth_pose
    js_t = np.asarray(data.joint_states.stamps, float)
    step_t = np.array([s.stamp_ns * 1e-9 for s in rep.steps])
    static = filt.diagnosed_effects
    out: dict[str, Any] = {"stamps": [], "T": {m: [] for m in ONLINE_METHODS}, "Tgt": []}
    for stamp, frame_id, T_gt in zip(gt.stamps, gt.frame_ids, gt.T):
        if frame_id != base:
            raise BagError(f"/ground_truth/pose: frame_id {frame_id!r}, expected the base frame {base!r}")
        i = int(np.searchsorted(js_t, stamp + 1e-12, side="right")) - 1
        if i < 0 or not np.all(np.isfinite(Q[i])):
            continue
        q = dict(zip(names, Q[i].tolist()))
        ctx: dict[str, Any] = {"time": float(stamp)}
        if temps is not None:
            k = int(np.searchsorted(temps.stamps, stamp, side="right")) - 1
            if k >= 0:
                ctx["temperature"] = float(temps.temperature[k])
        if any(getattr(e, "variable", None) == "temperature" for e in static) and "temperature" not in ctx:
            continue
        j = int(np.searchsorted(step_t, stamp - 1e-9, side="left")) - 1
        online = rep.effects[j] if j >= 0 else static
        out["T"]["before"].append(filt.pose(q, base, tool, [], ctx))
        out["T"]["static"].append(filt.pose(q, base, tool, static, ctx))
        out["T"]["online"].append(filt.pose(q, base, tool, online, ctx))
        if truth is not None:
            out["T"]["fresh"].append(filt.pose(q, base, tool, truth_effects(model, truth, stamp), ctx))
        out["stamps"].append(float(stamp))
        out["Tgt"].append(T_gt)
    return out


def significance(filt: OnlineEffects, rows: list[Any], truth: Mapping[str, Any]) -> dict[str, Any]:
    """Where the untracked truth becomes significant: per measurement the whitened squared difference between the
    prediction with the TRUE effects and with the diagnosed (static) ones, per component, ``delta_k =
    |L^-1 (h_true - h_static)|^2 / m_k`` (``L L^T`` the filter's measurement noise); the drift is significant from
    the first measurement where the mean of ``delta`` over the last :data:`SIGNIFICANCE_RUN` measurements reaches 1
    (one noise sigma per component).  Returns ``{"delta": [...], "index": k0 or None, "stamp": ...}``."""
    static = filt.diagnosed_effects
    delta = []
    for row in rows:
        lin_s = filt.linearize(row, static)
        lin_t = filt.linearize(row, truth_effects(filt.model, truth, row.stamp))
        d = 0.0
        for a, b in zip(lin_s, lin_t):
            W = np.linalg.inv(np.linalg.cholesky(a.noise))
            d += float(np.sum((W @ (a.residual - b.residual)) ** 2))
        delta.append(d / max(1, row.dim))
    run = np.convolve(delta, np.ones(SIGNIFICANCE_RUN) / SIGNIFICANCE_RUN, mode="full")[:len(delta)]
    hit = np.flatnonzero((np.arange(len(delta)) >= SIGNIFICANCE_RUN - 1) & (run >= 1.0))
    k0 = int(hit[0]) if hit.size else None
    return {"delta": delta, "index": k0, "stamp": rows[k0].stamp if k0 is not None else None}
