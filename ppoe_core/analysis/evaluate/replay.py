"""Replay of a bag through the nodes' own core code (kinematics -> tags/contact -> fusion), stop by stop."""

from __future__ import annotations

import gc
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.evaluate.options import EvaluateOptions, Evaluation
from ppoe_core.analysis.evaluate.inputs import JOINT_MAX_AGE_S, joint_matrix, recorded_estimate, required_joints
from ppoe_core.analysis.evaluate.scoring import score_points, score_poses
from ppoe_core.analysis.evaluate.replay_loop import MeasurementSlots, ReplayRun, replay_events
from ppoe_core.analysis.evaluate.sources import source_measurements
from ppoe_core.analysis.evaluate.tag_stream import TagStream
from ppoe_core.errors import BagError, JointValueError, ModelConfigError, PpoeError, UnknownJointError
from ppoe_core.io.messages import (
    TOPIC_CAMERA_INFO, TOPIC_COMPRESSED_IMAGE, TOPIC_IMAGE, TOPIC_ROBOT_DESCRIPTION, TOPIC_TAG_OBSERVATIONS,
)
from ppoe_core.estimation.pipeline import FUSION_SETTINGS
from ppoe_core.model.context import batch_context

# ----------------------------------------------------------------------------
# Replay
# ----------------------------------------------------------------------------


def _load_model(urdf_xml: str, model_yaml: str | Path, bag: str, urdf_file: str | None = None) -> Any:
    """The bag's URDF (or ``urdf_file``) with the model YAML; errors name the YAML file and line, or the URDF."""
    from ppoe_core.model.ppoe import PPOEModel

    path = Path(model_yaml)
    if not path.is_file():
        raise ModelConfigError(f"{path}: cannot read model YAML: no such file")
    if urdf_file is not None:
        try:
            urdf_xml = Path(urdf_file).read_text(encoding="utf-8")
        except OSError as exc:
            raise ModelConfigError(f"{urdf_file}: cannot read URDF: {exc.strerror}") from None
        return PPOEModel.from_strings(urdf_xml, path, urdf_source=str(urdf_file))
    return PPOEModel.from_strings(urdf_xml, path, urdf_source=f"bag {bag} /robot_description")


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


#: the topics the tag measurements need (with the model): read before the others, so that the images' workers start
#: while the rest of the bag is read
TAG_INPUT_TOPICS = (TOPIC_ROBOT_DESCRIPTION, TOPIC_CAMERA_INFO, TOPIC_COMPRESSED_IMAGE, TOPIC_IMAGE,
                    TOPIC_TAG_OBSERVATIONS)

_NO_MEASUREMENTS = (  # (a configured source without messages is an error before)
    "no tag observations, images, contact planes or wrenches in contact in the bag: only forward kinematics scored"
)

@contextmanager
def _gc_paused() -> Iterator[None]:
    """The cyclic garbage collector off while a bag is evaluated (and on again after, if it was): its full
    collections walk every object of the process (the bag's rows, the priors, the measurements; a tenth of a second
    each on the 10-minute bench bag) for cycles the replay does not make; reference counting frees the rest."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


class _EarlyTags:
    """The bag read with the tags' inputs first (:func:`ppoe_core.io.reader.read_bag`'s ``first``): the model is
    loaded and, unless the tags are looked for in predicted windows, the images' :class:`TagStream` started as soon
    as the images, camera infos and ``/robot_description`` are read, so that its worker processes detect while the
    joint states and the rest are read.  :meth:`close` stops the stream."""

    def __init__(self, bag: str, model_yaml: str | Path, opt: EvaluateOptions) -> None:
        self.bag, self.model_yaml, self.opt = bag, model_yaml, opt
        self.model: Any = None
        self.fs: dict[str, Any] = {}
        self.tags: TagStream | None = None
        self._images: Any = None

    def read(self) -> Any:
        """The bag's data, with :attr:`model`, :attr:`fs` (fusion settings) and :attr:`tags` (None: start it after
        the priors)."""
        from ppoe_core.io.bagio import read_bag

        data = read_bag(self.bag, accept_partial=self.opt.accept_partial, first=TAG_INPUT_TOPICS,
                        on_first=self._start)
        if self.model is None:  # read record by record (no early phase)
            self._start(data)
        elif self.tags is not None and data.images is not self._images:  # a damaged file read again: start anew
            self.tags.close()
            self.tags = None
            self._start(data)
        return data

    def _start(self, data: Any) -> None:
        opt = self.opt
        self.model = _load_model(data.require_robot_description(), self.model_yaml, self.bag, opt.urdf)
        self.fs = opt.fusion_settings()
        if not opt.tag_windows:
            self._images = data.images
            self.tags = TagStream(data, self.model, self.bag, refine=str(self.fs["corner_refinement"]),
                                  processes=opt.image_processes)

    def close(self) -> None:
        """Stop the tag stream's workers (if started)."""
        if self.tags is not None:
            self.tags.close()


@_gc_paused()
def evaluate_bag(bag: str | Path, model_yaml: str | Path, options: EvaluateOptions | None = None) -> Evaluation:
    """Replay ``bag`` through the core pipeline and score FK, PPOE-fused and naive-fused poses.

    Parameters
    ----------
    bag : str or Path
        Contract bag (docs/conventions.md section 3).
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
    opt = options or EvaluateOptions()
    bag = str(bag)
    t_start = time.perf_counter()
    early = _EarlyTags(bag, model_yaml, opt)
    try:
        data = early.read()
        model, fs, tags = early.model, early.fs, early.tags
        base, tool, kind = _check_inputs(data, model, model_yaml, opt, bag)
        sensors = {base, tool, *data.camera_info.frame_ids, *data.tag_observations.frame_ids}
        pri = _fk_priors(data.joint_states, model, base, tool, opt.order, bag, model_yaml,
                         required_joints(model, sensors), data.temperatures)
        if tags is None:  # in windows predicted from the priors' joint states: detected from here on
            tags = early.tags = TagStream(data, model, bag, refine=str(fs["corner_refinement"]),
                                          priors=(pri.stamps, pri.Q), processes=opt.image_processes)
        contact_meas, contact_counts = contact_measurements(data, model, model_yaml, fs)
        src_meas, src_counts = source_measurements(data, model, opt.sources, bag)
        pipes, updaters = _pipelines(model, base, tool, fs, pri.cov_naive)
        gt_stamps = data.ground_truth_pose.stamps if kind == "pose" else data.ground_truth_point.stamps
        # the images' tags are taken as the replay reaches their stamps, while the worker processes detect the
        # later ones (threads would wait for the GIL beside the pure-Python replay, and make it wait)
        slots = MeasurementSlots(tags, contact_meas + src_meas)
        run = replay_events(pri, slots, gt_stamps, pipes, updaters, len(model.joint_names), opt.progress)
        meas = slots.resolved()
    finally:
        early.close()
    tag_counts = tags.counts

    have = np.all(np.isfinite(run.est_T["fk"].reshape(len(gt_stamps), -1)), axis=1)
    counts = {"total": len(meas), **tag_counts, **contact_counts, **({"sources": src_counts} if src_counts else {})}
    summary = _summary_head(bag, model_yaml, base, tool, kind, data, pri, have, counts, fs)
    samples: dict[str, np.ndarray] = {}
    # without any measurement the fused estimates are the priors: only FK is scored
    methods = ["fk"] + (list(pipes) if meas else [])
    if not meas:
        summary["fusion"] = _NO_MEASUREMENTS
    if opt.estimate:
        recorded_estimate(run.est_T, run.est_cov, data, opt.estimate, base, gt_stamps, bag)
        methods.append("recorded")
        summary["recorded_estimate"] = opt.estimate
    if kind == "pose":
        score_poses(summary, samples, run, data.ground_truth_pose, have, methods, bag)
    else:
        score_points(summary, samples, run, data.ground_truth_point, have, methods, model, tool, opt.fit_set, bag,
                     tracker=pick_reflector(model.config, data, tool, bag),
                     context_source=(float(np.min(data.joint_states.stamps)), data.temperatures))
    _measurement_summary(summary, run, pipes, updaters, methods)
    if data.notes:
        summary["bag_notes"] = list(data.notes)
    return Evaluation({**summary, "wall_time_s": float(time.perf_counter() - t_start)}, samples)


def _summary_head(bag: str, model_yaml: str | Path, base: str, tool: str, kind: str, data: Any, pri: _Priors,
                  have: np.ndarray, counts: dict[str, Any], fs: dict[str, Any]) -> dict[str, Any]:
    """The summary's fields before the methods' scores (``have``: a prior at each ground-truth sample)."""
    return {
        "bag": bag,
        "model": str(model_yaml),
        "base": base,
        "tool": tool,
        "units": {"length": "m", "angle": "rad"},
        "joint_states": int(len(data.joint_states)),
        "joint_values_held": int(pri.held),
        "joint_states_incomplete": int(pri.incomplete),
        "bag_duration_s": float(pri.stamps[-1] - pri.stamps[0]) if len(pri.stamps) > 1 else 0.0,
        "ground_truth": {
            "topic": f"/ground_truth/{kind}",
            "kind": kind,
            "samples": int(len(have)),
            "without_prior": int(np.sum(~have)),
        },
        "measurements": counts,
        "fusion_settings": fs,
        "methods": {},
    }


def _check_inputs(data: Any, model: Any, model_yaml: str | Path, opt: EvaluateOptions,
                  bag: str) -> tuple[str, str, str]:
    """``(base, tool, ground-truth kind)``; refuses a bag without joint states or ground truth, a ground-truth
    pose in another frame than the base, or tracker points without a model ``tracker``."""
    cfg = model.config
    base = opt.base or (cfg.frames.base if cfg.frames is not None else None)
    tool = opt.tool or (cfg.frames.tool if cfg.frames is not None else None)
    if not base or not tool:
        raise ModelConfigError(f"{model_yaml}: no frames.base/frames.tool and no --base/--tool given")
    if len(data.joint_states) == 0:
        raise BagError(f"bag {bag}: no /joint_states messages")
    tracker = pick_reflector(cfg, data, tool, bag)
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
    elif tracker is None:
        raise ModelConfigError(
            f"{model_yaml}: the bag has /ground_truth/point but the model YAML has no 'tracker' section"
        )
    return base, tool, kind


def pick_reflector(cfg: Any, data: Any, tool: str, bag: str) -> Any:
    """The reflector ``ppoe evaluate`` scores (a ``TrackerConfig`` or None) and, as a side effect, its points
    in ``data.ground_truth_point``: the only declared reflector with messages, else the one on the tool link.

    Raises
    ------
    ModelConfigError
        A reflector topic of the bag that the model does not declare, or several reflectors none (or more
        than one) of which is on the tool link.
    """
    named = data.ground_truth_points
    declared = {t.topic for t in cfg.trackers}
    undeclared = sorted(set(named) - declared)
    if undeclared:
        raise ModelConfigError(f"bag {bag}: {', '.join(undeclared)} carry reflector points, but the model's "
                               f"trackers list has no entry for them (declared: {sorted(declared)})")

    def series(t: Any) -> Any:
        return data.ground_truth_point if t.topic == "/ground_truth/point" else named.get(t.topic)

    present = [t for t in cfg.trackers if series(t) is not None and len(series(t)) > 0]
    if len(present) > 1:
        present = [t for t in present if t.link == tool]
        if len(present) != 1:
            raise ModelConfigError(f"bag {bag}: several reflectors ({sorted(declared)}); evaluate scores the one on "
                                   f"the tool link {tool!r}: pass --tool with the link of the one to score")
    if not present:
        return cfg.tracker
    data.ground_truth_point = series(present[0])
    return present[0]


@dataclass
class _Priors:
    """Kinematics priors of every joint state (stamp order): ``T_base_tool`` and its covariance (tool frame)."""

    stamps: np.ndarray
    Q: np.ndarray
    held: int
    T_all: np.ndarray
    cov_all: np.ndarray
    cov_naive: np.ndarray | None
    incomplete: int = 0


def _fk_priors(js: Any, model: Any, base: str, tool: str, order: int, bag: str,
               model_yaml: str | Path, required: set[str] | None = None,
               temperatures: Any = None) -> _Priors:
    """PPOE mean and covariance of the tool for every joint state (the kinematics node's output); effects that
    need a context (time, motion sign, temperature) get it from the joint states as in ``ppoe diagnose``."""
    Q, held = joint_matrix(js, model.joint_names, bag, required=required)
    complete = np.all(np.isfinite(Q), axis=1)  # split joint states: rows before every joint is known (or fresh)
    if not complete.any():
        raise BagError(f"bag {bag}: topic /joint_states: no message gives (with values at most "
                       f"{JOINT_MAX_AGE_S:g} s old from earlier ones) every joint the model needs")
    idx = np.flatnonzero(complete)[np.argsort(js.stamps[complete], kind="stable")]
    stamps = js.stamps[idx]
    Q = Q[idx]
    joints = {n: Q[:, j] for j, n in enumerate(model.joint_names)}
    try:
        ctx = batch_context(model.effects, model.joint_names, stamps, Q, float(np.min(js.stamps)), temperatures,
                            where=f"bag {bag}")
        T_all, cov_all = model.fk(joints, base, tool, order=order, context=ctx)
    except (UnknownJointError, JointValueError) as exc:
        raise BagError(f"bag {bag}: topic /joint_states: {exc}") from None
    cfg = model.config
    cov_naive = cfg.naive.covariance if cfg.naive is not None else None
    # validated once for the whole batch here (and the naive one by the model YAML loader), so
    # the pipelines skip the per-prior check
    lie.check_covariance(cov_all, name=f"bag {bag}: forward-kinematics covariance of {tool} in {base}", size=6)
    if cov_naive is not None:
        lie.check_covariance(cov_naive, name=f"{model_yaml}: naive covariance", size=6)
    return _Priors(stamps, Q, held, T_all, cov_all, cov_naive, int((~complete).sum()))


def _pipelines(model: Any, base: str, tool: str, fs: dict[str, Any],
               cov_naive: np.ndarray | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The fusion node's pipeline and updater (``make_pipeline`` / ``make_updater`` with the node's settings and
    updater class) for the PPOE and the naive prior; the naive model knows nothing of the camera chain's covariance."""
    from ppoe_core.estimation.pipeline import make_pipeline, make_updater
    from ppoe_core.estimation.source_updater import SourceUpdater

    node_settings = {k: fs[k] for k in FUSION_SETTINGS}
    pipes: dict[str, Any] = {}
    updaters: dict[str, Any] = {}
    for name in ("ppoe", "naive"):
        if name == "naive" and cov_naive is None:
            continue
        s_name = {**node_settings, "camera_covariance": bool(fs["camera_covariance"]) and name == "ppoe"}
        try:
            updaters[name] = make_updater(model, base, tool, s_name, cls=SourceUpdater)
            pipes[name] = make_pipeline(model, base, tool, s_name, updater=updaters[name])
        except (TypeError, ValueError) as exc:
            raise ModelConfigError(f"fusion settings: {exc}") from None
    return pipes, updaters


def _measurement_summary(summary: dict[str, Any], run: ReplayRun, pipes: dict[str, Any], updaters: dict[str, Any],
                         methods: list[str]) -> None:
    """Per fused method: pipeline counts, outcomes, unknown tag points, first errors, mean NIS."""
    for name, pipe in pipes.items():
        if name not in methods:
            continue
        v = np.array(run.nis[name]) if run.nis[name] else np.zeros((0, 2))
        summary["methods"][name]["measurements"] = {
            "counts": dict(pipe.counts),
            "outcomes": run.outcomes[name],
            "unknown_tag_points": int(updaters[name].unknown_tag_points),
            "errors": run.errors[name],
        }
        summary["methods"][name]["nis"] = {
            "mean": float(np.mean(v[:, 0])) if len(v) else float("nan"),
            "mean_per_dim": float(np.mean(v[:, 0] / v[:, 1])) if len(v) else float("nan"),
            "n": int(len(v)),
        }
