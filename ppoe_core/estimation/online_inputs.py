"""The online filter's inputs (docs/online.md): what a measurement does to
:class:`~ppoe_core.estimation.online_effects.OnlineEffects`, the live alignment of measurements with the joint states
and temperatures at their stamps, the rules for bad input, and the correction of a kinematics prior by the estimate.

* :meth:`OnlineInputs.step`: one measurement at given joints (and temperature) into the filter and the drift monitor;
  the one step of the live hook (``ppoe_ros.common.online_effects``) and of ``ppoe evaluate --online``
  (:mod:`ppoe_core.analysis.evaluate.online`).
* :class:`OnlineInputs`: the live alignment.  Inputs arrive on their own queues, so a measurement waits until a
  joint state ``reorder_ns`` after its stamp (and, for a thermal effect, a temperature, at most
  ``temperature_wait_ns`` of joint-state time) has arrived; waiting measurements are taken in stamp order (ties by
  source), with the joints of :meth:`JointHistory.at <ppoe_core.model.joint_history.JointHistory.at>` their stamp
  (merged per joint, the nodes' rule) and the latest temperature at or before it: the values and the order
  ``ppoe evaluate --online`` takes from the whole bag.
* Bad input is counted and described in :attr:`OnlineInputs.notes` (the node logs them, evaluate reports them): a
  camera whose ``camera_info`` changes (``camera_info_changed``; the new focal lengths are used), a tag seen by two
  cameras at once (``tags_seen_twice``: the second view of that tag at that instant is dropped, its error is
  correlated with the first's through the tag's chain), a temperature stream that stopped (``temperature_stale``:
  thermal effects keep the last value).
* :func:`correct_prior`: a kinematics prior of the static model moved to the online estimate.
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.estimation.online_effects import OnlineEffects, OnlineUpdate
from ppoe_core.estimation.online_models import OnlineRow, check_frames, imu_parts, payload_parts, tracker_parts
from ppoe_core.estimation.updater import TagMeasurement
from ppoe_core.model.joint_history import JointHistory, StampedHistory
from ppoe_core.model.stamp_policy import StampResetPolicy

__all__ = ["IMU_TOPIC", "OnlineInputs", "OnlineMeasurement", "OnlineStep", "apply_measurement", "build_row",
           "check_measurement", "correct_prior"]

#: topic prefix of the accelerometers (``/imu/<name>`` of the model's ``imus``)
IMU_TOPIC = "/imu/"
#: two cameras see a tag "at once" when their images are stamped closer than this [ns] (one frame at 1 kHz)
SAME_INSTANT_NS = 1_000_000


@dataclass(frozen=True)
class OnlineMeasurement:
    """A tracker point, an accelerometer reading, or a fusion payload for the online filter.

    Attributes
    ----------
    stamp_ns : int
    topic : str
        The tracker topic (model ``trackers``), ``/imu/<name>``, or the payload's topic.
    frame_id : str
        ``header.frame_id``: the tracker frame, the IMU's link, the camera or the pose frame.
    value : ndarray, shape (3,), optional
        Point in the tracker frame [m], or specific force in the IMU link's axes [m/s^2].
    imu : str, optional
        The IMU's name in the model's ``imus``.
    payload : optional
        A fusion payload (:class:`~ppoe_core.estimation.updater.TagMeasurement`, ``ContactMeasurement``, or a
        point / pose / accelerometer source of :mod:`ppoe_core.estimation.source_updater`); then ``value`` is None.
    """

    stamp_ns: int
    topic: str
    frame_id: str
    value: np.ndarray | None = None
    imu: str | None = None
    payload: Any = None

    @property
    def source(self) -> str:
        """``"<topic> [<frame_id>]"``: the stream the drift monitor tests (one per camera on a shared topic)."""
        return f"{self.topic} [{self.frame_id}]" if self.frame_id else self.topic

    @property
    def kind(self) -> str:
        """``tracker``, ``imu`` or the payload's kind (``tags``, ``contact``, ``point``, ``pose``, ``gravity``)."""
        if self.payload is None:
            return "imu" if self.imu is not None else "tracker"
        name = type(self.payload).__name__
        return {"TagMeasurement": "tags", "ContactMeasurement": "contact", "PointMeasurement": "point",
                "PoseMeasurement": "pose", "GravityMeasurement": "gravity"}.get(name, name)


def check_measurement(filt: OnlineEffects, m: OnlineMeasurement) -> None:
    """Refuse now what could never be used (not when it is due): an IMU frame that is not its link, a tracker frame
    without a registration in the model, NaN.

    Raises
    ------
    MeasurementError, ModelConfigError
    """
    if m.payload is not None:
        return
    if m.imu is not None:
        imu = filt.model.config.imus[m.imu]
        if m.frame_id != imu.link:
            raise MeasurementError(f"header.frame_id {m.frame_id!r} is not the IMU's link {imu.link!r} of the model")
    else:
        filt.registration(m.frame_id, m.topic)
    v = np.asarray(m.value, dtype=float)
    if not np.all(np.isfinite(v)):
        raise MeasurementError(f"measurement ({v[0]}, {v[1]}, {v[2]}) is not finite")


def build_row(filt: OnlineEffects, m: OnlineMeasurement, q: Mapping[str, float], base: str,
              skip_ids: frozenset[int] = frozenset()) -> tuple[OnlineRow, int]:
    """The :class:`~ppoe_core.estimation.online_models.OnlineRow` of ``m`` at the joints ``q``; also the number of
    points of tags the model does not know (skipped).

    Raises
    ------
    MeasurementError, ModelConfigError
        A bad measurement, a frame the URDF lacks, a tracker frame without registration.
    """
    model, root = filt.model, filt.model.robot.root
    name = f"{m.source} at {m.stamp_ns * 1e-9:.6f}"
    unknown = 0
    if m.payload is not None:
        cam = getattr(model.config, "camera", None)
        parts, unknown = payload_parts(model, m.payload, base, name, cam.pixel_sigma if cam is not None else 0.5,
                                       skip_ids=skip_ids)
        check_frames(model, parts, name)
    elif m.imu is not None:
        imu = model.config.imus[m.imu]
        parts = imu_parts(root, imu.link, m.value, imu.sigma, name)
    else:
        tr = next(t for t in model.config.trackers if t.topic == m.topic)
        parts = tracker_parts(root, tr.link, tr.xyz, m.value, filt.registration(m.frame_id, m.topic), tr.sigma, name)
    return OnlineRow(m.stamp_ns * 1e-9, m.source, dict(q), parts), unknown


def apply_measurement(filt: OnlineEffects, m: OnlineMeasurement, q: Mapping[str, float],
                      temperature: float | None = None, base: str | None = None) -> OnlineUpdate | None:
    """One measurement at the joints ``q`` (and the temperature at its stamp, if any) into the filter; None while a
    thermal effect waits for its first temperature, or when a tag image keeps no point."""
    if temperature is not None and filt.context.get("temperature") != temperature:
        filt.set_temperature(m.stamp_ns * 1e-9, temperature)
    row, _ = build_row(filt, m, q, base or _base(filt))
    if not row.parts:
        return None
    return filt.update(row, m.kind)


def _base(filt: OnlineEffects) -> str:
    fr = filt.model.config.frames
    return fr.base if fr is not None and fr.base else filt.model.robot.root


def correct_prior(filt: OnlineEffects, q: Mapping[str, float], T_base_tool: np.ndarray, cov_tool: np.ndarray,
                  base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
    """A kinematics prior of the static model moved to the online estimate: ``T_static Exp(d)`` with ``Exp(d) =
    T_static(q)^-1 T_online(q)`` at the joints ``q``, covariance (tool tangent space) ``+ J P J^T``."""
    T_on, J = filt.tool_jacobian(q, base, tool)
    T_st = filt.static_model.fk_mean(q, base, tool, context=filt.context)
    return T_base_tool @ lie.inverse(T_st) @ T_on, cov_tool + J @ filt.P @ J.T


@dataclass(frozen=True)
class OnlineStep:
    """A measurement taken by the filter: its stamp, the update, the row, a drift event the monitor raised, and the
    estimate right after it (``labels``, ``theta`` (P,), covariance ``P`` (P, P): what the live hook publishes; a
    drain of several steps must not publish the last state for each)."""

    stamp_ns: int
    update: OnlineUpdate
    row: OnlineRow | None = None
    drift: Any = None
    labels: tuple[str, ...] = ()
    theta: np.ndarray | None = None
    P: np.ndarray | None = None


@dataclass
class _Counts:
    no_joints: int = 0
    waiting: int = 0
    dropped_pending: int = 0
    jumps: int = 0
    bad: int = 0
    unknown_tag_points: int = 0
    camera_info_changed: int = 0
    tags_seen_twice: int = 0
    temperature_stale: int = 0
    extra: dict[str, int] = field(default_factory=dict)


class OnlineInputs:
    """The live alignment of the online filter's inputs and its one step (module docstring).

    Parameters
    ----------
    filt : OnlineEffects
    joint_max_age_ns : a joint value a split joint-state message lacks is held this long (0: no limit)
    keep_ns : joint states and temperatures kept for the lookup at a measurement's stamp
    temperature_wait_ns : a measurement waits at most this long (joint-state time) for a newer temperature
    max_pending : measurements waiting for their joint state beyond this are dropped, oldest first (counted)
    policy : the stamp rule of the joint states
    monitor : the drift monitor (:class:`~ppoe_core.estimation.online_monitor.DriftMonitor`), fed after each step
    reorder_ns : a measurement waits for a joint state this long after its stamp, so that measurements of several
        streams are taken in stamp order
    temperature_timeout_ns : a temperature older than this at a measurement's stamp is stale (counted, noted)
    base : frame of the fusion payloads' ``T_base_frame`` (default: model frames.base, else the root)
    joint_gap_ns : joint states around a measurement's stamp further apart than this leave it out (0: no check;
        default 0.1 s, five periods of the contract's 50 Hz)
    """

    def __init__(self, filt: OnlineEffects, joint_max_age_ns: int = 0, keep_ns: int = 10_000_000_000,
                 temperature_wait_ns: int = 2_000_000_000, max_pending: int = 1000,
                 policy: StampResetPolicy | None = None, monitor: Any = None, reorder_ns: int = 100_000_000,
                 temperature_timeout_ns: int = 10_000_000_000, base: str | None = None,
                 joint_gap_ns: int = 100_000_000) -> None:
        model = filt.model
        self.filter = filt
        self.monitor = monitor
        self.base = base or _base(filt)
        self.names = list(model.joint_names)
        # a measurement is taken up to reorder + temperature wait after its stamp (later, when the joint stream has a
        # gap): its joints must still be kept then
        keep_ns = max(int(keep_ns), 3 * int(reorder_ns) + int(temperature_wait_ns))
        self.joints = JointHistory(self.names, known=model.robot.joints, max_age_ns=joint_max_age_ns,
                                   keep_ns=keep_ns, policy=policy)
        self.temperatures = StampedHistory(keep_ns)
        self.temperature_wait_ns = int(temperature_wait_ns)
        self.temperature_timeout_ns = int(temperature_timeout_ns)
        self.reorder_ns = int(reorder_ns)
        self.joint_gap_ns = int(joint_gap_ns)
        self.max_pending = int(max_pending)
        self.pending: list[tuple[tuple[int, str], OnlineMeasurement]] = []
        self.counts = _Counts()
        self.notes: list[tuple[str, str]] = []
        self.cameras: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._last_temperature_ns: int | None = None
        self._stale = False
        self._recent_tags: tuple[int, dict[int, str]] = (-(10 ** 18), {})
        self.uses_temperature = any(getattr(e, "variable", None) == "temperature" for e in filt.effects())

    # ---------------------------------------------------------------- inputs
    def joint_state(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int) -> list[OnlineStep]:
        """Take a joint state (refused ones raise, see :meth:`JointHistory.update`); the measurements it made ready."""
        self.joints.update(names, positions, stamp_ns)
        return self._drain()

    def temperature(self, stamp_ns: int, value: float) -> list[OnlineStep]:
        """Take a temperature [deg C]; the measurements it made ready."""
        if not np.isfinite(value):
            raise MeasurementError(f"temperature {value!r} is not finite")
        self.temperatures.add(stamp_ns, float(value))
        return self._drain()

    def camera_info(self, frame: str, K: Any, D: Any) -> str | None:
        """Take a ``camera_info`` (K (3, 3), D) of camera ``frame``; returns a note (and counts
        ``camera_info_changed``) when it differs from the one seen before: the tag bearing node's normalised
        coordinates and the focal lengths change with it, the filter takes the new ones from then on."""
        K, D = np.asarray(K, float).reshape(3, 3), np.asarray(D, float).reshape(-1)
        old = self.cameras.get(frame)
        self.cameras[frame] = (K, D)
        if old is None or (np.allclose(old[0], K, rtol=1e-9, atol=1e-9) and old[1].shape == D.shape
                           and np.allclose(old[1], D, rtol=1e-9, atol=1e-12)):
            return None
        self.counts.camera_info_changed += 1
        note = (f"camera_info of camera {frame!r} changed mid-run (fx {old[0][0, 0]:.6g} -> {K[0, 0]:.6g}, fy "
                f"{old[0][1, 1]:.6g} -> {K[1, 1]:.6g}, cx {old[0][0, 2]:.6g} -> {K[0, 2]:.6g}, cy {old[0][1, 2]:.6g}"
                f" -> {K[1, 2]:.6g}, D {old[1].tolist()} -> {D.tolist()}): its tag points are taken with the new "
                "intrinsics from now on")
        self.notes.append(("camera_info_changed", note))
        return note

    def measurement(self, m: OnlineMeasurement) -> list[OnlineStep]:
        """Take a measurement (checked now, :func:`check_measurement`); processed in stamp order once its joint state
        is known."""
        check_measurement(self.filter, m)
        bisect.insort(self.pending, ((m.stamp_ns, m.source), m), key=lambda e: e[0])
        if len(self.pending) > self.max_pending:
            self.pending.pop(0)
            self.counts.dropped_pending += 1
        return self._drain()

    def flush(self) -> list[OnlineStep]:
        """Take every waiting measurement whose joints are known now (the end of a bag)."""
        out = []
        while self.pending:
            step = self._process(self.pending.pop(0)[1])
            if step is not None:
                out.append(step)
        return out

    def _ready(self, stamp_ns: int) -> bool:
        j = self.joints.history.newest
        if j is None or j < stamp_ns + self.reorder_ns:
            return False
        newest_t = self.temperatures.newest
        if not self.uses_temperature or (newest_t is not None and newest_t >= stamp_ns):
            return True
        return j - stamp_ns > self.temperature_wait_ns

    def _drain(self) -> list[OnlineStep]:
        out = []
        while self.pending and self._ready(self.pending[0][0][0]):
            step = self._process(self.pending.pop(0)[1])
            if step is not None:
                out.append(step)
        return out

    def joints_known(self, stamps_ns: Sequence[int], m: OnlineMeasurement) -> bool:
        """Whether the joint states around ``m``'s stamp are complete: the ones just before and after it (sorted
        ``stamps_ns``) at most ``joint_gap_ns`` apart.  A larger gap (messages lost before the node, a stalled
        driver) is counted in ``no_joints`` and noted: the arm may have moved in it."""
        i = bisect.bisect_right(stamps_ns, m.stamp_ns) - 1
        if i < 0:
            self.counts.no_joints += 1
            self.notes.append(("no_joints", f"{m.source} at {m.stamp_ns * 1e-9:.6f} s: no joint state at or before "
                                            "its stamp (kept); skipped"))
            return False
        if self.joint_gap_ns <= 0 or i + 1 >= len(stamps_ns) or stamps_ns[i + 1] - stamps_ns[i] <= self.joint_gap_ns:
            return True
        self.counts.no_joints += 1
        self.notes.append(("no_joints", (
            f"{m.source} at {m.stamp_ns * 1e-9:.6f} s: no joint state between {stamps_ns[i] * 1e-9:.6f} and "
            f"{stamps_ns[i + 1] * 1e-9:.6f} s (gap above {self.joint_gap_ns * 1e-9:g} s: lost?); skipped")))
        return False

    def _process(self, m: OnlineMeasurement) -> OnlineStep | None:
        if not self.joints_known(self.joints.history.stamps, m):
            return None
        q = self.joints.at(m.stamp_ns)
        if q is None or not np.isfinite(q).all():
            self.counts.no_joints += 1
            return None
        t = self.temperatures.at(m.stamp_ns)
        t_ns = self._temperature_stamp(m.stamp_ns)
        return self.take(m, dict(zip(self.names, q.tolist())), None if t is None else (t_ns, t))

    def _temperature_stamp(self, stamp_ns: int) -> int:
        """Stamp of the latest temperature at or before ``stamp_ns``."""
        st = self.temperatures.stamps
        i = bisect.bisect_right(st, stamp_ns) - 1
        return int(st[i]) if i >= 0 else int(stamp_ns)

    # ---------------------------------------------------------------- the step
    def take(self, m: OnlineMeasurement, q: Mapping[str, float],
             temperature: tuple[int, float] | None = None) -> OnlineStep | None:
        """:meth:`step`, with a bad measurement counted (``bad``, per kind in ``extra``) and noted instead of
        raised: the one entry of the live alignment and of ``ppoe evaluate --online``."""
        try:
            return self.step(m, q, temperature)
        except PpoeError as exc:
            self.counts.bad += 1
            self.counts.extra[f"bad_{m.kind}"] = self.counts.extra.get(f"bad_{m.kind}", 0) + 1
            self.notes.append(("bad", f"{m.source} at {m.stamp_ns * 1e-9:.6f} s: {exc}"))
            return None

    def step(self, m: OnlineMeasurement, q: Mapping[str, float],
             temperature: tuple[int, float] | None = None) -> OnlineStep | None:
        """One measurement at the joints ``q`` with the latest temperature ``(stamp_ns, deg C)`` at or before its
        stamp: the bad-input rules, the filter's update, the drift monitor.  None when the measurement was not used
        (waiting for a temperature, no known tag point; counted).

        Raises
        ------
        MeasurementError, ModelConfigError
            A bad measurement (the caller counts it).
        """
        filt = self.filter
        if temperature is not None:
            self._check_temperature(m, temperature[0])
            if filt.context.get("temperature") != temperature[1]:
                filt.set_temperature(temperature[0] * 1e-9, temperature[1])
        m = self._with_focal(m)
        skip = self._skip_tags(m)
        row, unknown = build_row(filt, m, q, self.base, skip)
        self.counts.unknown_tag_points += unknown
        self._seen_tags(m, skip)
        if not row.parts:
            return None
        jumps = filt.counts.jumps
        up = filt.update(row, m.kind)
        if up is None:
            self.counts.waiting += 1
            return None
        self.counts.jumps += filt.counts.jumps - jumps
        drift = self.monitor.observe(filt, row, up) if self.monitor is not None else None
        return OnlineStep(m.stamp_ns, up, row, drift, tuple(filt.labels), filt.theta.copy(), filt.P.copy())

    def _with_focal(self, m: OnlineMeasurement) -> OnlineMeasurement:
        """A tag image that reached the node before its camera's first ``camera_info`` takes the focal lengths of
        the camera_info seen since (the measurement waited for its joint state in between)."""
        p = m.payload
        if isinstance(p, TagMeasurement) and (p.fx is None or p.fy is None) and p.camera_frame in self.cameras:
            K = self.cameras[p.camera_frame][0]
            return replace(m, payload=replace(p, fx=float(K[0, 0]), fy=float(K[1, 1])))
        return m

    def _check_temperature(self, m: OnlineMeasurement, t_ns: int) -> None:
        """A temperature older than ``temperature_timeout_ns`` at the measurement's stamp: counted, noted once per
        stale stretch (the thermal effects keep its value)."""
        age = m.stamp_ns - t_ns
        stale = self.temperature_timeout_ns > 0 and age > self.temperature_timeout_ns
        if stale:
            self.counts.temperature_stale += 1
            if not self._stale:
                self.notes.append(("temperature_stale", (
                    f"the temperature stream stopped: its last message is {age * 1e-9:.1f} s older than the "
                    f"measurement at {m.stamp_ns * 1e-9:.3f} s (timeout {self.temperature_timeout_ns * 1e-9:g} s); "
                    f"thermal effects use the last value {self.filter.context.get('temperature')} degC")))
        elif self._stale:
            self.notes.append(("temperature_resumed", f"the temperature stream is back at {t_ns * 1e-9:.3f} s"))
        self._stale = stale

    def _skip_tags(self, m: OnlineMeasurement) -> frozenset[int]:
        """Tags of ``m`` another camera saw at the same instant (dropped, counted, noted)."""
        p = m.payload
        if not isinstance(p, TagMeasurement):
            return frozenset()
        stamp, seen = self._recent_tags
        if abs(m.stamp_ns - stamp) > SAME_INSTANT_NS:
            return frozenset()
        ids = set(np.asarray(p.ids).astype(int).reshape(-1).tolist())
        twice = {i for i in ids if i in seen and seen[i] != p.camera_frame}
        if twice:
            self.counts.tags_seen_twice += len(twice)
            others = sorted({seen[i] for i in twice})
            self.notes.append(("tags_seen_twice", (
                f"tag(s) {sorted(twice)} seen by cameras {others} and {p.camera_frame!r} at {m.stamp_ns * 1e-9:.6f} s:"
                f" used once (the first camera's view), the second view dropped: the two views' errors are "
                "correlated through the tag's chain")))
        return frozenset(twice)

    def _seen_tags(self, m: OnlineMeasurement, used: frozenset[int]) -> None:
        """Remember the tags an image was used with (for :meth:`_skip_tags` of another camera's image)."""
        p = m.payload
        if not isinstance(p, TagMeasurement):
            return
        stamp, seen = self._recent_tags
        if abs(m.stamp_ns - stamp) > SAME_INSTANT_NS:
            stamp, seen = m.stamp_ns, {}
        for i in set(np.asarray(p.ids).astype(int).reshape(-1).tolist()) - used:
            seen.setdefault(i, p.camera_frame)
        self._recent_tags = (stamp, seen)

    def correct_prior(self, stamp_ns: int, T_base_tool: np.ndarray, cov_tool: np.ndarray, base: str,
                      tool: str) -> tuple[np.ndarray, np.ndarray]:
        """:func:`correct_prior` at the joints of ``stamp_ns``; the prior unchanged while those are not all known or
        a thermal effect waits for its temperature."""
        q = self.joints.at(stamp_ns)
        if q is None or not np.isfinite(q).all() or self.filter.needs_temperature():
            return T_base_tool, cov_tool
        return correct_prior(self.filter, dict(zip(self.names, q.tolist())), T_base_tool, cov_tool, base, tool)
