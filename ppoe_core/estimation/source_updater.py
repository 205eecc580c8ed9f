"""Tracker points, 6D poses and accelerometers in the fusion pipeline: payloads and the updater that builds their
measurement models (the live counterpart of the core's point / pose / gravity models, issue 11 item 2).

The models themselves are :mod:`ppoe_core.estimation.direct_measurements` (``PointObservation``,
``PoseObservation``, ``GravityObservation``), chained from the link that carries the sensor to the state's tool
frame with :class:`~ppoe_core.estimation.composite_measurements.ChainedObservation` (the PPOE covariance of that
chain enters as noise).  :class:`SelectedObservation` keeps only the configured components (robot_localization's
``*_config`` booleans).  :class:`SourceUpdater` is :class:`~ppoe_core.estimation.updater.ModelUpdater` plus these
payloads; tags and contact go through the base class unchanged, so the gating and the iterated update are the one
implementation of ``updater.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError
from ppoe_core.estimation.composite_measurements import ChainedObservation
from ppoe_core.estimation.corrections import Measurement, ToolUpdate
from ppoe_core.estimation.direct_measurements import GravityObservation, PointObservation, PoseObservation
from ppoe_core.estimation.update_types import MeasurementModel
from ppoe_core.estimation.prior_buffer import Array, PriorSample
from ppoe_core.estimation.updater import ModelUpdater
from ppoe_core.robot.tree import GRAVITY

__all__ = [
    "PointMeasurement", "PoseMeasurement", "GravityMeasurement", "SOURCE_PAYLOADS", "SelectedObservation",
    "SourceUpdater",
]


@dataclass(frozen=True)
class PointMeasurement:
    """A tracker's measurement of a reflector fixed to a link (``geometry_msgs/PointStamped``).

    Attributes
    ----------
    link : str
        URDF link carrying the reflector.
    xyz_link : ndarray, shape (3,)
        Reflector position in ``link`` [m].
    frame : str
        The tracker's frame (``header.frame_id``, frame prefix removed).
    point_frame : ndarray, shape (3,)
        The measured point in ``frame`` [m].
    cov : ndarray, shape (3, 3)
        Its covariance [m^2].
    T_base_frame : ndarray, shape (4, 4), optional
        Pose of ``frame`` in the base frame (the tracker registration); None: ``frame`` is a frame of the model.
    mask : ndarray of bool, shape (3,), optional
        Components used (x, y, z); None = all.
    gate_probability : float, optional
        This source's gate; None = the updater's.
    """

    link: str
    xyz_link: Array
    frame: str
    point_frame: Array
    cov: Array
    T_base_frame: Array | None = None
    mask: Array | None = None
    gate_probability: float | None = None


@dataclass(frozen=True)
class PoseMeasurement:
    """A 6D pose of a link (``geometry_msgs/PoseWithCovarianceStamped``, e.g. motion capture).

    Attributes
    ----------
    link : str
        URDF link whose pose is measured.
    frame : str
        Frame the pose is given in (``header.frame_id``, frame prefix removed).
    T_frame_link : ndarray, shape (4, 4)
        The measured pose.
    cov : ndarray, shape (6, 6)
        Its covariance, local (tangent space at the measured pose, ``[rho; theta]``).
    T_base_frame, mask, gate_probability
        As in :class:`PointMeasurement` (mask over ``[x, y, z, rot_x, rot_y, rot_z]`` of the tangent).
    """

    link: str
    frame: str
    T_frame_link: Array
    cov: Array
    T_base_frame: Array | None = None
    mask: Array | None = None
    gate_probability: float | None = None


@dataclass(frozen=True)
class GravityMeasurement:
    """An accelerometer at rest on a link (``sensor_msgs/Imu.linear_acceleration``): the direction of gravity.

    Attributes
    ----------
    link : str
        Frame of the accelerometer (``header.frame_id``, frame prefix removed; a frame of the model).
    accel : ndarray, shape (3,)
        Measured specific force in ``link`` [m/s^2]; only its direction is used (scaled to ``GRAVITY``).
    cov : ndarray, shape (3, 3)
        Its covariance [(m/s^2)^2].
    up_base : ndarray, shape (3,)
        The up direction in the base frame.
    mask, gate_probability
        As in :class:`PointMeasurement` (mask over the accelerometer axes x, y, z).
    """

    link: str
    accel: Array
    cov: Array
    up_base: Array
    mask: Array | None = None
    gate_probability: float | None = None


SOURCE_PAYLOADS = (PointMeasurement, PoseMeasurement, GravityMeasurement)


class SelectedObservation(MeasurementModel):
    """The components ``rows`` of another model's residual (robot_localization's per-axis ``config``).

    ``h`` and ``validate`` are the inner model's; the residual, ``H`` and ``M`` keep the selected rows, so a pose
    measured without yaw constrains only the other five tangent directions.

    Parameters
    ----------
    inner : MeasurementModel
        With analytic Jacobians.
    mask : array_like of bool, shape (inner.dim,)
        True = use that component; at least one.
    """

    def __init__(self, inner: MeasurementModel, mask: Any) -> None:
        m = np.asarray(mask, dtype=bool).reshape(-1)
        if m.shape != (inner.dim,) or not m.any():
            raise MeasurementError(f"{inner.name}: component mask {m.tolist()} must have {inner.dim} entries, "
                                   "at least one true")
        self.inner = inner
        self.rows = np.flatnonzero(m)
        self.name = inner.name
        self.dim = int(self.rows.size)
        self.noise_cov = inner.noise_cov
        self.noise_dim = inner.noise_dim

    def validate(self, z: Any) -> np.ndarray:
        return self.inner.validate(z)

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        return np.asarray(self.inner.residual(z, z_pred), dtype=float)[self.rows]

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        return self.inner.h(T_state, v)

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        return self._rows(self.inner.jacobian_state(T_state), "H")

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        return self._rows(self.inner.jacobian_noise(T_state), "M")

    def _rows(self, J: np.ndarray | None, what: str) -> np.ndarray:
        if J is None:
            raise MeasurementError(f"{self.name}: component selection needs an analytic {what}")
        return np.asarray(J, dtype=float)[self.rows]


class SourceUpdater(ModelUpdater):
    """:class:`ModelUpdater` that also takes :data:`SOURCE_PAYLOADS` (module docstring).

    The sensor's link is chained to the tool frame at the prior's joints (``model.fk(joints, tool, link)``; its PPOE
    covariance enters as noise when non-zero); a tracker or pose frame that is a model frame is placed with
    ``model.fk_mean(joints, base, frame)``, else the payload carries ``T_base_frame``.  A link or frame the model
    does not know is a :class:`MeasurementError` naming it (the pipeline counts the measurement as bad).
    ``GravityObservation`` takes one isotropic sigma: the largest of the accelerometer covariance's diagonal
    (conservative for a per-axis covariance).
    """

    def build(self, measurement: Measurement, prior: PriorSample | None) -> tuple[Any, Array]:
        """Measurement model and ``z`` of a source payload, else :meth:`ModelUpdater.build`."""
        p = measurement.payload
        if not isinstance(p, SOURCE_PAYLOADS):
            return super().build(measurement, prior)
        joints = self._joints(prior)
        where = f"{measurement.source} at stamp {measurement.stamp:.6f}"
        inner: MeasurementModel
        if isinstance(p, PointMeasurement):
            T_base_frame = self._frame_pose(p.frame, p.T_base_frame, joints, where)
            inner, z = PointObservation(p.xyz_link, p.cov, T_ref_sensor=T_base_frame, name=where), p.point_frame
        elif isinstance(p, PoseMeasurement):
            T_base_frame = self._frame_pose(p.frame, p.T_base_frame, joints, where)
            inner, z = PoseObservation(p.cov, name=where), T_base_frame @ np.asarray(p.T_frame_link, float)
        else:
            a = np.asarray(p.accel, dtype=float)
            norm = float(np.linalg.norm(a))
            if not (np.all(np.isfinite(a)) and norm > 0.0):
                raise MeasurementError(f"{where}: linear_acceleration {a.tolist()} has no direction")
            sigma = float(np.sqrt(np.max(np.diag(p.cov))))
            inner, z = GravityObservation(sigma, up_ref=p.up_base, name=where), a * (GRAVITY / norm)
        obs: MeasurementModel = ChainedObservation(inner, *self._link_chain(p.link, joints, where), name=where)
        if p.mask is not None and not np.all(p.mask):
            obs = SelectedObservation(obs, p.mask)
        return obs, z

    def _link_chain(self, link: str, joints: Any, where: str) -> tuple[Array, Array | None]:
        """``T_tool_link`` and its PPOE covariance (None when exact)."""
        self._check_frame(link, where, "link")
        T, cov = self.model.fk(joints, self.tool_frame, link)
        return T, (None if float(np.max(np.abs(cov))) == 0.0 else cov)

    def _frame_pose(self, frame: str, T_base_frame: Array | None, joints: Any, where: str) -> Array:
        if T_base_frame is not None:
            return np.asarray(T_base_frame, dtype=float)
        self._check_frame(frame, where, "frame")
        return np.asarray(self.model.fk_mean(joints, self.base_frame, frame), dtype=float)

    def _check_frame(self, frame: str, where: str, what: str) -> None:
        if frame not in self.model.robot.links:
            raise MeasurementError(f"{where}: {what} '{frame}' is not a link of the URDF ({self.model.robot.source})")

    def __call__(
        self, T_base_tool: Array, cov_tool: Array, measurement: Measurement, prior: PriorSample | None = None
    ) -> ToolUpdate:
        """:meth:`ModelUpdater.__call__` with the source's own gate probability when it has one."""
        gate = getattr(measurement.payload, "gate_probability", None)
        if gate is None:
            return super().__call__(T_base_tool, cov_tool, measurement, prior)
        saved = self.gate_probability
        self.gate_probability = None if gate >= 1.0 else float(gate)
        try:
            return super().__call__(T_base_tool, cov_tool, measurement, prior)
        finally:
            self.gate_probability = saved


def pose_from_xyz_rpy(values: Any) -> Array:
    """``[x, y, z, roll, pitch, yaw]`` [m, rad] -> (4, 4) (a tracker registration given in the node YAML)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise MeasurementError(f"a pose needs 6 finite numbers [x, y, z, roll, pitch, yaw], got {v.tolist()}")
    return np.asarray(lie.from_xyz_rpy(v[:3], v[3:]), dtype=float)
