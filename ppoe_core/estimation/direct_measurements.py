"""Measurement models of a point (tracker), a 6D pose and gravity (accelerometer) on the state's frame."""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

from ppoe_core import lie
from ppoe_core.estimation.checks import check_noise_covariance, check_pose
from ppoe_core.errors import CovarianceError, MeasurementError
from ppoe_core.estimation.update_types import MeasurementModel
from ppoe_core.robot.tree import GRAVITY


# --------------------------------------------------------------------------- 3D point
class PointObservation(MeasurementModel):
    """3D point fixed to the state's child frame, measured in a sensor frame.

    State ``X = T_ref_link``; sensor pose ``T_ref_sensor`` (identity: measured in ``ref``),
    optionally uncertain with ``cov_sensor`` (6x6, tangent space at ``T_ref_sensor``)::

        z = (T_ref_sensor Exp(w))^-1 X p_link + v,   v ~ N(0, cov_point)

    Noise ``v = [v (3); w (6, only if cov_sensor is given)]``.

    Parameters
    ----------
    point_link : array_like, shape (3,)
        Reflector / prism position in the state's child frame [m].
    sigma : float or array_like (3, 3)
        1-sigma point noise [m] (isotropic) or a 3x3 covariance in the sensor frame.
    T_ref_sensor, cov_sensor : optional
        Sensor pose in ``ref`` and its covariance (sensor frame).
    """

    def __init__(self, point_link: Any, sigma: Any, T_ref_sensor: Any = None, cov_sensor: Any = None,
                 name: str = "point") -> None:
        self.name = name
        p = np.asarray(point_link, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise MeasurementError(f"{name}: point_link must be 3 finite numbers, got {p.tolist()}")
        self.point_link = p
        sig = np.asarray(sigma, dtype=float)
        if sig.ndim == 0:
            if not (np.isfinite(sig) and sig > 0):
                raise CovarianceError(f"{name}: sigma must be > 0, got {float(sig)}")
            cov_point = np.eye(3) * float(sig) ** 2
        else:
            cov_point = check_noise_covariance(sig, 3, f"{name}: point covariance")
        self.T_ref_sensor = (np.eye(4) if T_ref_sensor is None else check_pose(T_ref_sensor, f"{name}: T_ref_sensor"))
        self.T_sensor_ref = lie.inverse(self.T_ref_sensor)
        blocks = [cov_point]
        self.has_sensor_noise = cov_sensor is not None
        if self.has_sensor_noise:
            blocks.append(check_noise_covariance(cov_sensor, 6, f"{name}: cov_sensor"))
        self.noise_cov = scipy.linalg.block_diag(*blocks)
        self.noise_dim = self.noise_cov.shape[0]
        self.dim = 3

    def point_sensor(self, T_state: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        T = self.T_sensor_ref @ T_state
        if w is not None:
            T = lie.exp(-np.asarray(w, dtype=float)) @ T
        return T[:3, :3] @ self.point_link + T[:3, 3]

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Predicted point in the sensor frame (3,) [m]."""
        if v is None:
            return self.point_sensor(T_state)
        v = self.noise_vector(v)
        w = v[3:] if self.has_sensor_noise else None
        return self.point_sensor(T_state, w) + v[:3]

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (3, 6) = ``R_sensor_link [I, -[p]x]``."""
        R = (self.T_sensor_ref @ T_state)[:3, :3]
        return np.hstack([R, -R @ lie.hat3(self.point_link)])

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        """``M`` (3, 3[+6]) = ``[I, (-I, [p_sensor]x)]``."""
        M = np.zeros((3, self.noise_dim))
        M[:, :3] = np.eye(3)
        if self.has_sensor_noise:
            M[:, 3:6] = -np.eye(3)
            M[:, 6:9] = lie.hat3(self.point_sensor(T_state))
        return M


# --------------------------------------------------------------------------- 6D pose
class PoseObservation(MeasurementModel):
    """Full 6D pose measurement of the state: ``z = X Exp(v)``, ``v ~ N(0, cov)``.

    ``z`` is a (4, 4) pose ``T_ref_state``; the residual is ``Log(z_pred^-1 z)`` (6,), so
    ``H = I`` and ``M = I`` (exact at zero residual; first order otherwise).

    Parameters
    ----------
    cov : array_like, shape (6, 6)
        Measurement covariance in the tangent space at the measured pose.
    """

    def __init__(self, cov: Any, name: str = "pose") -> None:
        self.name = name
        self.noise_cov = check_noise_covariance(cov, 6, f"{name}: covariance")
        self.noise_dim = 6
        self.dim = 6

    def validate(self, z: Any) -> np.ndarray:
        return check_pose(z, f"{self.name}: measurement")

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        return lie.log(lie.inverse(z_pred) @ z)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        v = self.noise_vector(v)
        return np.asarray(T_state, dtype=float) @ lie.exp(v)

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        return np.eye(6)

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        return np.eye(6)


# --------------------------------------------------------------------------- gravity
class GravityObservation(MeasurementModel):
    """Accelerometer at rest on the state's child frame (a link): it measures the tilt.

    State ``X = T_ref_link`` with ``ref`` having a known "up" direction ``up_ref`` (unit,
    default ``[0, 0, 1]`` for a gravity-aligned base).  At rest the accelerometer measures
    the specific force ``+g * up`` in its own frame::

        z = g * R_link_sensor^T R_ref_link^T up_ref + v,    v ~ N(0, sigma^2 I_3)  [m/s^2]

    Rotation about ``up`` and all translations are unobservable (zero columns in ``H``).

    Parameters
    ----------
    sigma : float
        1-sigma accelerometer noise per axis [m/s^2].
    R_link_sensor : array_like, shape (3, 3), optional
        Sensor axes in the link frame (default identity).
    up_ref : array_like, shape (3,)
        Up direction in ``ref``.
    gravity : float
        Magnitude [m/s^2].
    """

    def __init__(self, sigma: float, R_link_sensor: Any = None, up_ref: Any = (0.0, 0.0, 1.0), gravity: float = GRAVITY,
                 name: str = "gravity") -> None:
        self.name = name
        if not (np.isfinite(sigma) and sigma > 0):
            raise CovarianceError(f"{name}: sigma must be > 0, got {sigma}")
        self.R_link_sensor = np.eye(3) if R_link_sensor is None else np.asarray(R_link_sensor, float)
        up = np.asarray(up_ref, dtype=float)
        if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) == 0:
            raise MeasurementError(f"{name}: up_ref must be a non-zero 3-vector")
        self.up_ref = up / np.linalg.norm(up)
        self.gravity = float(gravity)
        self.noise_cov = np.eye(3) * float(sigma) ** 2
        self.noise_dim = 3
        self.dim = 3

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Predicted specific force in the sensor frame (3,) [m/s^2]."""
        v = self.noise_vector(v)
        a_link = self.gravity * (T_state[:3, :3].T @ self.up_ref)
        return self.R_link_sensor.T @ a_link + v

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (3, 6) = ``[0, R_ls^T [a_link]x]``."""
        a_link = self.gravity * (T_state[:3, :3].T @ self.up_ref)
        return np.hstack([np.zeros((3, 3)), self.R_link_sensor.T @ lie.hat3(a_link)])

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        return np.eye(3)
