"""The online filter's inputs (docs/online.md): what a tracker point or an accelerometer reading does to
:class:`~ppoe_core.estimation.online_effects.OnlineEffects`, the live alignment of measurements with the joint states
and temperatures at their stamps, and the correction of a kinematics prior by the estimate.

* :func:`apply_measurement`: one measurement at given joints (and temperature) into the filter; the one step of the
  live hook (``ppoe_ros.common.online_effects``) and of ``ppoe evaluate --online``
  (:mod:`ppoe_core.analysis.evaluate.online`).
* :class:`OnlineInputs`: the live alignment.  Inputs arrive on their own queues, so a measurement waits until a
  joint state at or after its stamp (and, for a thermal effect, a temperature, at most ``temperature_wait_ns`` of
  joint-state time) has arrived; it then takes the joints of :meth:`JointHistory.at
  <ppoe_core.model.joint_history.JointHistory.at>` its stamp (merged per joint, the nodes' rule) and the
  latest temperature at or before it: the values ``ppoe evaluate --online`` takes from the whole bag.
* :func:`correct_prior`: a kinematics prior of the static model moved to the online estimate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError
from ppoe_core.model.joint_history import JointHistory, StampedHistory
from ppoe_core.estimation.online_effects import OnlineEffects, PointUpdate
from ppoe_core.model.stamp_policy import StampResetPolicy

__all__ = ["IMU_TOPIC", "OnlineInputs", "OnlineMeasurement", "OnlineStep", "apply_measurement", "check_measurement",
           "correct_prior"]

#: topic prefix of the accelerometers (``/imu/<name>`` of the model's ``imus``)
IMU_TOPIC = "/imu/"


@dataclass(frozen=True)
class OnlineMeasurement:
    """A tracker point (``imu`` None) or an accelerometer reading for the online filter.

    Attributes
    ----------
    stamp_ns : int
    topic : str
        The tracker topic (model ``trackers``) or ``/imu/<name>``.
    frame_id : str
        ``header.frame_id``: the tracker frame, or the IMU's link.
    value : ndarray, shape (3,)
        Point in the tracker frame [m], or specific force in the IMU link's axes [m/s^2].
    imu : str, optional
        The IMU's name in the model's ``imus``.
    """

    stamp_ns: int
    topic: str
    frame_id: str
    value: np.ndarray
    imu: str | None = None


def check_measurement(filt: OnlineEffects, m: OnlineMeasurement) -> None:
    """Refuse now what could never be used (not when it is due): an IMU frame that is not its link, a tracker frame
    without a registration in the model, NaN.

    Raises
    ------
    MeasurementError, ModelConfigError
    """
    if m.imu is not None:
        imu = filt.model.config.imus[m.imu]
        if m.frame_id != imu.link:
            raise MeasurementError(f"header.frame_id {m.frame_id!r} is not the IMU's link {imu.link!r} of the model")
    else:
        filt.registration(m.frame_id, m.topic)
    v = np.asarray(m.value, dtype=float)
    if not np.all(np.isfinite(v)):
        raise MeasurementError(f"measurement ({v[0]}, {v[1]}, {v[2]}) is not finite")


def apply_measurement(filt: OnlineEffects, m: OnlineMeasurement, q: Mapping[str, float],
                      temperature: float | None = None) -> PointUpdate | None:
    """One measurement at the joints ``q`` (and the temperature at its stamp, if any) into the filter; None while a
    thermal effect waits for its first temperature."""
    stamp = m.stamp_ns * 1e-9
    if temperature is not None and filt.context.get("temperature") != temperature:
        filt.set_temperature(stamp, temperature)
    if m.imu is not None:
        imu = filt.model.config.imus[m.imu]
        return filt.update_gravity(stamp, q, imu.link, m.value, imu.sigma)
    tr = next(t for t in filt.model.config.trackers if t.topic == m.topic)
    return filt.update_point(stamp, q, tr.link, tr.xyz, m.value, filt.registration(m.frame_id, m.topic), tr.sigma)


def correct_prior(filt: OnlineEffects, q: Mapping[str, float], T_base_tool: np.ndarray, cov_tool: np.ndarray,
                  base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
    """A kinematics prior of the static model moved to the online estimate: ``T_static Exp(d)`` with ``Exp(d) =
    T_static(q)^-1 T_online(q)`` at the joints ``q``, covariance (tool tangent space) ``+ J P J^T``."""
    T_on, J = filt.tool_jacobian(q, base, tool)
    T_st = filt.static_model.fk_mean(q, base, tool, context=filt.context)
    return T_base_tool @ lie.inverse(T_st) @ T_on, cov_tool + J @ filt.P @ J.T


@dataclass(frozen=True)
class OnlineStep:
    """A measurement taken by the filter: its stamp and the update (the caller publishes the estimate)."""

    stamp_ns: int
    update: PointUpdate


@dataclass
class _Counts:
    no_joints: int = 0
    waiting: int = 0
    dropped_pending: int = 0
    jumps: int = 0
    extra: dict[str, int] = field(default_factory=dict)


class OnlineInputs:
    """The live alignment of the online filter's inputs (module docstring).

    Parameters
    ----------
    filt : OnlineEffects
    joint_max_age_ns : a joint value a split joint-state message lacks is held this long (0: no limit)
    keep_ns : joint states and temperatures kept for the lookup at a measurement's stamp
    temperature_wait_ns : a measurement waits at most this long (joint-state time) for a newer temperature
    max_pending : measurements waiting for their joint state beyond this are dropped, oldest first (counted)
    policy : the stamp rule of the joint states
    """

    def __init__(self, filt: OnlineEffects, joint_max_age_ns: int = 0, keep_ns: int = 10_000_000_000,
                 temperature_wait_ns: int = 2_000_000_000, max_pending: int = 1000,
                 policy: StampResetPolicy | None = None) -> None:
        model = filt.model
        self.filter = filt
        self.names = list(model.joint_names)
        self.joints = JointHistory(self.names, known=model.robot.joints, max_age_ns=joint_max_age_ns,
                                   keep_ns=keep_ns, policy=policy)
        self.temperatures = StampedHistory(keep_ns)
        self.temperature_wait_ns = int(temperature_wait_ns)
        self.max_pending = int(max_pending)
        self.pending: list[OnlineMeasurement] = []
        self.counts = _Counts()
        self.uses_temperature = any(getattr(e, "variable", None) == "temperature" for e in filt.effects())

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

    def measurement(self, m: OnlineMeasurement) -> list[OnlineStep]:
        """Take a tracker point or an accelerometer reading (checked now, :func:`check_measurement`); processed once
        its joint state is known (FIFO behind any waiting one)."""
        check_measurement(self.filter, m)
        if self.pending or not self._ready(m.stamp_ns):
            self.pending.append(m)
            if len(self.pending) > self.max_pending:
                self.pending.pop(0)
                self.counts.dropped_pending += 1
            return []
        step = self._process(m)
        return [step] if step is not None else []

    def _ready(self, stamp_ns: int) -> bool:
        j = self.joints.history.newest
        if j is None or j < stamp_ns:
            return False
        newest_t = self.temperatures.newest
        if not self.uses_temperature or (newest_t is not None and newest_t >= stamp_ns):
            return True
        return j - stamp_ns > self.temperature_wait_ns

    def _drain(self) -> list[OnlineStep]:
        out = []
        while self.pending and self._ready(self.pending[0].stamp_ns):
            step = self._process(self.pending.pop(0))
            if step is not None:
                out.append(step)
        return out

    def _process(self, m: OnlineMeasurement) -> OnlineStep | None:
        q = self.joints.at(m.stamp_ns)
        if q is None or not np.isfinite(q).all():
            self.counts.no_joints += 1
            return None
        jumps = self.filter.counts.jumps
        up = apply_measurement(self.filter, m, dict(zip(self.names, q.tolist())), self.temperatures.at(m.stamp_ns))
        if up is None:
            self.counts.waiting += 1
            return None
        self.counts.jumps += self.filter.counts.jumps - jumps
        return OnlineStep(m.stamp_ns, up)

    def correct_prior(self, stamp_ns: int, T_base_tool: np.ndarray, cov_tool: np.ndarray, base: str,
                      tool: str) -> tuple[np.ndarray, np.ndarray]:
        """:func:`correct_prior` at the joints of ``stamp_ns``; the prior unchanged while those are not all known or
        a thermal effect waits for its temperature."""
        q = self.joints.at(stamp_ns)
        if q is None or not np.isfinite(q).all() or self.filter.needs_temperature():
            return T_base_tool, cov_tool
        return correct_prior(self.filter, dict(zip(self.names, q.tolist())), T_base_tool, cov_tool, base, tool)
