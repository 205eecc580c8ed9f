"""Measurement models ``z = h(X, v)`` for the iterated LG-EKF (paper eq. 19, 24, 25).

Every model works on one state pose ``X = T_ref_state`` (4, 4) with the right / local
perturbation ``X Exp(xi)``, ``xi = [rho; theta]`` (CONTRACT sec. 1), and gives

* ``h(X, v=None)`` - the predicted measurement for noise ``v`` (``None`` = zero noise);
* ``jacobian_state(X)`` - ``H = dh/dxi`` (m, 6), analytic;
* ``jacobian_noise(X)`` - ``M = dh/dv`` (m, k), analytic;
* ``noise_cov`` - ``R = Sigma_v`` (k, k), the noise covariance;
* ``residual(z, z_pred)`` - ``z ominus z_pred`` (``z - z_pred`` except for the 6D pose);
* ``validate(z)`` - the measurement as an array, or :class:`MeasurementError`.

Models
------
:class:`TagBearingModel`
    Pixel (plumb_bob distorted) or normalised image coordinates of points fixed to the state's
    child frame (tag centres and corners), seen from a camera.  Eq. 25 of the paper is the
    special case of one point at the origin of ``X = T_camera_tool`` in normalised
    coordinates times the focal lengths (with ``p2`` in the second row, as CONTRACT says).
    The camera pose ``T_ref_camera`` may be uncertain: its 6x6 covariance (tangent space at
    ``T_ref_camera``) then enters as extra noise through ``M``.  This is how the fusion node
    uses state ``T_base_tool`` with the camera chain ``T_base_camera`` from the PPOE model.
:class:`ContactPlaneModel`
    Signed distance of a tool point from a plane along the plane's normal (its z axis);
    in contact ``z = 0``.  The plane pose covariance ``Sigma_v`` (6x6, tangent space at the
    plane pose, i.e. in the plane frame, paper section V-B) enters through ``M``.
:class:`PointObservation`
    A 3D point fixed to the state's child frame (laser-tracker reflector, total-station
    prism), measured in a sensor frame whose pose in ``ref`` may be uncertain.
:class:`PoseObservation`
    A full 6D pose of the state with a 6x6 covariance in the tangent space at the measured
    pose; residual ``Log(h^-1 z)``.
:class:`GravityObservation`
    The specific force measured by an accelerometer at rest on the state's child frame:
    ``g * R_sensor_ref @ up_ref``; observes the two tilt angles.

Measurements of several frames at once
--------------------------------------
The state is one pose.  A sensor on another link ``L`` (an accelerometer on the upper arm while
the state is ``T_base_tool``) is wrapped by :class:`ChainedObservation`: the inner model sees
``T_ref_L = X @ T_state_L @ Exp(w)`` where ``T_state_L`` (mean) and its covariance
``cov_L`` (tangent space at ``T_state_L``, e.g. from ``model.fk(tool, L)``) come from the PPOE
model, and ``w ~ N(0, cov_L)`` enters as extra noise through ``M``.  Several independent sensors
are fused together in one update with :class:`StackedObservation` (concatenated ``z``,
block-diagonal noise).  **Approximation**: the correlation between the prior of the state and
``w`` (they share the joints between ``L`` and the tool) is neglected, and so is the
correlation of the ``w`` of two chained sensors; this counts the shared joint errors twice,
which inflates ``S`` (the update is weaker than the optimum, never stronger because of it).
A stacked state of several frames with their full joint PPOE covariance would remove this but
needs cross-covariances the model API does not give.

All models are for a single state (no batch axis); :func:`ppoe_core.estimation.fusion.iterated_update`
calls them once per iteration.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, MeasurementError
from ppoe_core.estimation.camera import distortion_coefficients, project_points_jacobian

__all__ = [
    "MeasurementModel",
    "TagBearingModel",
    "ContactPlaneModel",
    "PointObservation",
    "PoseObservation",
    "GravityObservation",
    "ChainedObservation",
    "StackedObservation",
    "tag_points",
]

STANDARD_GRAVITY = 9.80665  # m/s^2


def _hat(v: np.ndarray) -> np.ndarray:
    return lie.hat3(np.asarray(v, dtype=float))


def _check_cov(cov: Any, dim: int, name: str) -> np.ndarray:
    from ppoe_core.estimation.fusion import check_noise_covariance  # local import: fusion imports nothing from here

    return check_noise_covariance(cov, dim, name)


def _check_pose(T: Any, name: str) -> np.ndarray:
    from ppoe_core.estimation.fusion import check_pose

    return check_pose(T, name)


def _block_diag(*blocks: np.ndarray) -> np.ndarray:
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        k = b.shape[0]
        out[i : i + k, i : i + k] = b
        i += k
    return out


class MeasurementModel:
    """Base class: vector measurement ``z`` of shape ``(dim,)`` with additive-style residual.

    Subclasses set ``name``, ``dim``, ``noise_dim``, ``noise_cov`` and implement ``h``,
    ``jacobian_state`` and ``jacobian_noise`` (returning ``None`` selects central
    differences in :mod:`ppoe_core.estimation.fusion`).
    """

    name: str = "measurement"
    dim: int = 0
    noise_dim: int = 0
    noise_cov: np.ndarray = np.zeros((0, 0))

    def validate(self, z: Any) -> np.ndarray:
        """Return ``z`` as a float array of shape ``(dim,)``; MeasurementError otherwise."""
        try:
            arr = np.asarray(z, dtype=float)
        except (TypeError, ValueError):
            raise MeasurementError(f"{self.name}: measurement is not numeric") from None
        if arr.shape != (self.dim,):
            raise MeasurementError(
                f"{self.name}: measurement has shape {arr.shape}, expected ({self.dim},)"
            )
        if not np.all(np.isfinite(arr)):
            bad = np.flatnonzero(~np.isfinite(arr)).tolist()
            raise MeasurementError(f"{self.name}: measurement contains NaN/inf at index {bad}")
        return arr

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        """``z - z_pred`` (m,)."""
        return np.asarray(z, dtype=float) - np.asarray(z_pred, dtype=float)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        return None

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        return None

    def linearize(
        self, T_state: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``(h(T), H, M)`` in one call (models override it to share work); H or M may be
        None (numerical)."""
        return self.h(T_state), self.jacobian_state(T_state), self.jacobian_noise(T_state)

    def _noise(self, v: np.ndarray | None) -> np.ndarray:
        if v is None:
            return np.zeros(self.noise_dim)
        v = np.asarray(v, dtype=float)
        if v.shape != (self.noise_dim,):
            raise MeasurementError(
                f"{self.name}: noise vector has shape {v.shape}, expected ({self.noise_dim},)"
            )
        return v


# --------------------------------------------------------------------------- camera
def tag_points(size: float, T_link_tag: np.ndarray | None = None) -> np.ndarray:
    """Centre and four corners of a square tag in the link frame.

    Parameters
    ----------
    size : float
        Edge length of the black square [m].
    T_link_tag : ndarray, shape (4, 4), optional
        Tag centre pose in the link (tag z = normal, x right, y down as in OpenCV's ArUco
        corner order: top-left, top-right, bottom-right, bottom-left seen from the front).

    Returns
    -------
    ndarray, shape (5, 3)
        Row 0 = centre, rows 1..4 = corners in OpenCV's detector order.
    """
    s = 0.5 * float(size)
    pts = np.array([[0, 0, 0], [-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]], dtype=float)
    if T_link_tag is not None:
        T = np.asarray(T_link_tag, dtype=float)
        pts = pts @ T[:3, :3].T + T[:3, 3]
    return pts


class TagBearingModel(MeasurementModel):
    """Image coordinates of points fixed to the state's child frame (eq. 25 generalised).

    State ``X = T_ref_tool``: the points' frame in a reference frame ``ref``.  The camera
    optical frame has pose ``T_ref_camera`` (identity when ``ref`` is the camera: the paper's
    state ``T_camera_tool``).  Prediction for point ``p_i`` (tool frame)::

        p_c = (T_ref_camera Exp(w))^-1 X p_i,   z_i = pi(p_c) + v_i

    with ``pi`` the normalised projection ``(X/Z, Y/Z)`` or the distorted pixel projection
    ``K * plumb_bob(X/Z, Y/Z)``.  Noise ``v = [v_1..v_n (2n, pixel noise); w (6, camera pose,
    only if cov_camera is given)]``.

    Parameters
    ----------
    points_tool : array_like, shape (n, 3)
        Observed points in the state's child frame [m] (see :func:`tag_points`).
    K : array_like, shape (3, 3)
        Camera intrinsics (CameraInfo.K).
    D : array_like, shape (5,), optional
        plumb_bob distortion (CameraInfo.D); ignored in "normalized" mode.
    pixel_sigma : float
        1-sigma pixel noise [px] per coordinate; in "normalized" mode divided by fx / fy.
    mode : {"pixel", "normalized"}
        Measurement in raw pixels ``(u, v)`` or undistorted normalised ``(x, y)``; ``z`` is
        ``(2n,)`` ordered ``[u_0, v_0, u_1, v_1, ...]``.
    T_ref_camera : array_like, shape (4, 4), optional
        Camera optical-frame pose in ``ref`` (default identity: state is ``T_camera_tool``).
    cov_camera : array_like, shape (6, 6), optional
        Covariance of ``T_ref_camera`` in its tangent space (camera frame), e.g. the PPOE
        covariance of ``model.fk(base, camera)``; enters as noise through ``M``.
    min_depth : float
        Points with camera z below this [m] raise MeasurementError (behind the camera).
    labels : sequence of str, optional
        One label per point for error messages (e.g. ``"tag 3 corner 2"``).
    name : str
        Name for error messages.
    """

    def __init__(
        self,
        points_tool: Any,
        K: Any,
        D: Any = None,
        pixel_sigma: float = 0.5,
        mode: str = "pixel",
        T_ref_camera: Any = None,
        cov_camera: Any = None,
        min_depth: float = 1e-3,
        labels: Sequence[str] | None = None,
        name: str = "tag observation",
    ) -> None:
        self.name = name
        pts = np.asarray(points_tool, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
            raise MeasurementError(f"{name}: points_tool must have shape (n, 3), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise MeasurementError(f"{name}: points_tool contains NaN/inf")
        if mode not in ("pixel", "normalized"):
            raise MeasurementError(f"{name}: mode must be 'pixel' or 'normalized', not {mode!r}")
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise MeasurementError(f"{name}: K must be a finite 3x3 matrix with fx, fy > 0, got {K.tolist()}")
        if not (np.isfinite(pixel_sigma) and pixel_sigma > 0):
            raise CovarianceError(f"{name}: pixel_sigma must be > 0, got {pixel_sigma}")
        self.points_tool = pts
        self.K = K
        self.D = distortion_coefficients(D, name)
        self.mode = mode
        self.pixel_sigma = float(pixel_sigma)
        self.T_ref_camera = (
            np.eye(4) if T_ref_camera is None else _check_pose(T_ref_camera, f"{name}: T_ref_camera")
        )
        self.T_camera_ref = lie.inverse(self.T_ref_camera)
        self.min_depth = float(min_depth)
        n = pts.shape[0]
        self.labels = list(labels) if labels is not None else [f"point {i}" for i in range(n)]
        if len(self.labels) != n:
            raise MeasurementError(f"{name}: {len(self.labels)} labels for {n} points")
        self.dim = 2 * n
        if mode == "pixel":
            sig = np.tile([self.pixel_sigma, self.pixel_sigma], n)
        else:
            sig = np.tile([self.pixel_sigma / K[0, 0], self.pixel_sigma / K[1, 1]], n)
        blocks = [np.diag(sig**2)]
        self.has_camera_noise = cov_camera is not None
        if self.has_camera_noise:
            blocks.append(_check_cov(cov_camera, 6, f"{name}: cov_camera"))
        self.noise_cov = _block_diag(*blocks)
        self.noise_dim = self.noise_cov.shape[0]

    def points_camera(self, T_state: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Points in the camera frame (n, 3) for state ``T_ref_tool`` and camera noise ``w``."""
        T_cam_tool = self.T_camera_ref @ T_state
        if w is not None:
            T_cam_tool = lie.exp(-np.asarray(w, dtype=float)) @ T_cam_tool
        p = self.points_tool @ T_cam_tool[:3, :3].T + T_cam_tool[:3, 3]
        bad = np.flatnonzero(p[:, 2] < self.min_depth)
        if bad.size:
            i = int(bad[0])
            raise MeasurementError(
                f"{self.name}: {self.labels[i]} is behind the camera or too close "
                f"(z = {p[i, 2]:.4g} m < min_depth {self.min_depth} m)"
            )
        return p

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Predicted ``[u_0, v_0, u_1, v_1, ...]`` (2n,) for ``T_state = T_ref_tool``."""
        if v is None:
            uv, _ = project_points_jacobian(self.points_camera(T_state), self.K, self.D, self.mode)
            return uv.ravel()
        v = self._noise(v)
        w = v[self.dim :] if self.has_camera_noise else None
        uv, _ = project_points_jacobian(self.points_camera(T_state, w), self.K, self.D, self.mode)
        return uv.ravel() + v[: self.dim]

    def linearize(self, T_state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(h(T), H, M)`` sharing one projection (see :meth:`jacobian_state`,
        :meth:`jacobian_noise`)."""
        p_c = self.points_camera(T_state)
        uv, Jproj = project_points_jacobian(p_c, self.K, self.D, self.mode)
        n = p_c.shape[0]
        R_ct = (self.T_camera_ref @ T_state)[:3, :3]
        Jx = np.empty((n, 3, 6))
        Jx[:, :, :3] = R_ct
        Jx[:, :, 3:] = -R_ct @ _hat(self.points_tool)
        H = np.einsum("nij,njk->nik", Jproj, Jx).reshape(2 * n, 6)
        M = np.zeros((self.dim, self.noise_dim))
        M[:, : self.dim] = np.eye(self.dim)
        if self.has_camera_noise:
            Jw = np.empty((n, 3, 6))
            Jw[:, :, :3] = -np.eye(3)
            Jw[:, :, 3:] = _hat(p_c)
            M[:, self.dim :] = np.einsum("nij,njk->nik", Jproj, Jw).reshape(2 * n, 6)
        return uv.ravel(), H, M

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (2n, 6): ``d pi / d p_c * R_camera_tool [I, -[p_i]x]``."""
        return self.linearize(T_state)[1]

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        """``M`` (2n, 2n[+6]): identity for the pixel noise, ``d pi/d p_c [-I, [p_c]x]`` for w."""
        return self.linearize(T_state)[2]


# --------------------------------------------------------------------------- contact
class ContactPlaneModel(MeasurementModel):
    """Signed distance of a tool point from a plane along the plane normal (paper V-B).

    State ``X = T_ref_tool``; plane pose ``T_ref_plane`` (normal = plane z axis) with
    covariance ``cov_plane`` (the paper's ``Sigma_v``, 6x6 in the tangent space at the plane
    pose, i.e. expressed in the plane frame)::

        z = e_z^T (T_ref_plane Exp(w))^-1 X p_tool + v_d        (in contact: z = 0)

    Noise ``v = [w (6); v_d (1, only if distance_sigma > 0)]``.

    Parameters
    ----------
    T_ref_plane : array_like, shape (4, 4)
    cov_plane : array_like, shape (6, 6)
        Plane pose covariance in the plane frame, [m^2, rad^2] (e.g. the paper's Sigma_v
        ``diag(0.5, 0.5, 0.001, 0.017, 0.017, 0.17)`` read as 1-sigma values, i.e. the square
        of those numbers on the diagonal, as ``config/robots/humanoid_model.yaml`` and docs/studies.md do).
    point_tool : array_like, shape (3,)
        Contact point in the state's child frame [m].
    distance_sigma : float
        Extra 1-sigma noise of the distance itself [m] (contact detection); 0 = none.
    """

    def __init__(
        self,
        T_ref_plane: Any,
        cov_plane: Any,
        point_tool: Any = (0.0, 0.0, 0.0),
        distance_sigma: float = 0.0,
        name: str = "contact plane",
    ) -> None:
        self.name = name
        self.T_ref_plane = _check_pose(T_ref_plane, f"{name}: T_ref_plane")
        self.T_plane_ref = lie.inverse(self.T_ref_plane)
        p = np.asarray(point_tool, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise MeasurementError(f"{name}: point_tool must be 3 finite numbers, got {p.tolist()}")
        self.point_tool = p
        if not (np.isfinite(distance_sigma) and distance_sigma >= 0):
            raise CovarianceError(f"{name}: distance_sigma must be >= 0, got {distance_sigma}")
        self.distance_sigma = float(distance_sigma)
        blocks = [_check_cov(cov_plane, 6, f"{name}: cov_plane")]
        if self.distance_sigma > 0:
            blocks.append(np.array([[self.distance_sigma**2]]))
        self.noise_cov = _block_diag(*blocks)
        self.noise_dim = self.noise_cov.shape[0]
        self.dim = 1

    def point_plane(self, T_state: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Tool point in the (perturbed) plane frame, shape (3,)."""
        T = self.T_plane_ref @ T_state
        if w is not None:
            T = lie.exp(-np.asarray(w, dtype=float)) @ T
        return T[:3, :3] @ self.point_tool + T[:3, 3]

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Signed distance (1,) [m], positive on the side the normal points to."""
        if v is None:
            return np.array([self.point_plane(T_state)[2]])
        v = self._noise(v)
        d = self.point_plane(T_state, v[:6])[2]
        if self.distance_sigma > 0:
            d = d + v[6]
        return np.array([d])

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (1, 6) = ``e_z^T R_plane_tool [I, -[p]x]``."""
        R = (self.T_plane_ref @ T_state)[:3, :3]
        H = np.empty((1, 6))
        H[0, :3] = R[2]
        H[0, 3:] = -(R[2] @ _hat(self.point_tool))
        return H

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        """``M`` (1, 6[+1]) = ``e_z^T [-I, [p_plane]x]`` (+ 1 for the distance noise)."""
        p = self.point_plane(T_state)
        M = np.zeros((1, self.noise_dim))
        M[0, 2] = -1.0
        M[0, 3:6] = _hat(p)[2]
        if self.distance_sigma > 0:
            M[0, 6] = 1.0
        return M


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

    def __init__(
        self,
        point_link: Any,
        sigma: Any,
        T_ref_sensor: Any = None,
        cov_sensor: Any = None,
        name: str = "point",
    ) -> None:
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
            cov_point = _check_cov(sig, 3, f"{name}: point covariance")
        self.T_ref_sensor = (
            np.eye(4) if T_ref_sensor is None else _check_pose(T_ref_sensor, f"{name}: T_ref_sensor")
        )
        self.T_sensor_ref = lie.inverse(self.T_ref_sensor)
        blocks = [cov_point]
        self.has_sensor_noise = cov_sensor is not None
        if self.has_sensor_noise:
            blocks.append(_check_cov(cov_sensor, 6, f"{name}: cov_sensor"))
        self.noise_cov = _block_diag(*blocks)
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
        v = self._noise(v)
        w = v[3:] if self.has_sensor_noise else None
        return self.point_sensor(T_state, w) + v[:3]

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (3, 6) = ``R_sensor_link [I, -[p]x]``."""
        R = (self.T_sensor_ref @ T_state)[:3, :3]
        return np.hstack([R, -R @ _hat(self.point_link)])

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        """``M`` (3, 3[+6]) = ``[I, (-I, [p_sensor]x)]``."""
        M = np.zeros((3, self.noise_dim))
        M[:, :3] = np.eye(3)
        if self.has_sensor_noise:
            M[:, 3:6] = -np.eye(3)
            M[:, 6:9] = _hat(self.point_sensor(T_state))
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
        self.noise_cov = _check_cov(cov, 6, f"{name}: covariance")
        self.noise_dim = 6
        self.dim = 6

    def validate(self, z: Any) -> np.ndarray:
        return _check_pose(z, f"{self.name}: measurement")

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        return lie.log(lie.inverse(z_pred) @ z)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        v = self._noise(v)
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

    def __init__(
        self,
        sigma: float,
        R_link_sensor: Any = None,
        up_ref: Any = (0.0, 0.0, 1.0),
        gravity: float = STANDARD_GRAVITY,
        name: str = "gravity",
    ) -> None:
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
        v = self._noise(v)
        a_link = self.gravity * (T_state[:3, :3].T @ self.up_ref)
        return self.R_link_sensor.T @ a_link + v

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (3, 6) = ``[0, R_ls^T [a_link]x]``."""
        a_link = self.gravity * (T_state[:3, :3].T @ self.up_ref)
        return np.hstack([np.zeros((3, 3)), self.R_link_sensor.T @ _hat(a_link)])

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        return np.eye(3)


# --------------------------------------------------------------------------- composition
class ChainedObservation(MeasurementModel):
    """A model of link ``L`` used with the state ``X = T_ref_tool`` (see module docstring).

    The inner model's state is ``T_ref_L = X @ T_tool_L @ Exp(w)``, ``w ~ N(0, cov_L)``
    (tangent space at ``T_tool_L``); noise ``v = [v_inner; w]``.  ``H = H_in Ad(T_tool_L^-1)``,
    ``M = [M_in, H_in]``.  The correlation of ``w`` with the state's prior is neglected.

    Parameters
    ----------
    inner : MeasurementModel
        Model whose state is the pose of link ``L``.
    T_tool_L : array_like, shape (4, 4)
        Mean pose of ``L`` in the state's child frame (e.g. ``model.fk(q, tool, L)``).
    cov_L : array_like, shape (6, 6), optional
        Its covariance in the tangent space at ``T_tool_L`` (``None``: exact).
    """

    def __init__(self, inner: MeasurementModel, T_tool_L: Any, cov_L: Any = None, name: str = "") -> None:
        self.inner = inner
        self.name = name or f"{inner.name} (chained)"
        self.T_tool_L = _check_pose(T_tool_L, f"{self.name}: T_tool_L")
        self.Ad_L_tool = lie.adjoint(lie.inverse(self.T_tool_L))
        self.has_link_noise = cov_L is not None
        blocks = [np.asarray(inner.noise_cov, dtype=float)]
        if self.has_link_noise:
            blocks.append(_check_cov(cov_L, 6, f"{self.name}: cov_L"))
        self.noise_cov = _block_diag(*blocks)
        self.noise_dim = self.noise_cov.shape[0]
        self.dim = inner.dim

    def validate(self, z: Any) -> np.ndarray:
        return self.inner.validate(z)

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        return self.inner.residual(z, z_pred)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        v = self._noise(v)
        k = self.inner.noise_dim
        T_L = T_state @ self.T_tool_L
        if self.has_link_noise:
            T_L = T_L @ lie.exp(v[k:])
        return self.inner.h(T_L, v[:k])

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        H_in = self.inner.jacobian_state(T_state @ self.T_tool_L)
        return None if H_in is None else H_in @ self.Ad_L_tool

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        T_L = T_state @ self.T_tool_L
        M_in = self.inner.jacobian_noise(T_L)
        if M_in is None:
            return None
        if not self.has_link_noise:
            return M_in
        H_in = self.inner.jacobian_state(T_L)
        return None if H_in is None else np.hstack([M_in, H_in])


class StackedObservation(MeasurementModel):
    """Several independent measurements of the same state fused in one update.

    ``z`` is the concatenation of the parts' measurements (each flattened: a 6D pose part
    takes 16 numbers, row-major); the residual and noise are stacked block-wise.

    Parameters
    ----------
    parts : sequence of MeasurementModel
        Models of the same state ``X``.  Their noises are treated as independent.
    """

    def __init__(self, parts: Sequence[MeasurementModel], name: str = "stacked") -> None:
        if not parts:
            raise MeasurementError(f"{name}: needs at least one part")
        self.parts = list(parts)
        self.name = name
        self.dim = sum(p.dim for p in self.parts)
        self.noise_cov = _block_diag(*[np.asarray(p.noise_cov, float) for p in self.parts])
        self.noise_dim = self.noise_cov.shape[0]
        self._zsizes = [16 if isinstance(p, PoseObservation) else p.dim for p in self.parts]

    def _split(self, z: np.ndarray, sizes: Sequence[int]) -> list:
        out, i = [], 0
        for s in sizes:
            out.append(z[i : i + s])
            i += s
        return out

    def validate(self, z: Any) -> np.ndarray:
        arr = np.asarray(z, dtype=float).ravel()
        if arr.size != sum(self._zsizes):
            raise MeasurementError(
                f"{self.name}: measurement has {arr.size} numbers, expected {sum(self._zsizes)}"
            )
        parts = []
        for p, zp in zip(self.parts, self._split(arr, self._zsizes)):
            zp = zp.reshape(4, 4) if isinstance(p, PoseObservation) else zp
            parts.append(np.asarray(p.validate(zp), dtype=float).ravel())
        return np.concatenate(parts)

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        v = self._noise(v)
        vs = self._split(v, [p.noise_dim for p in self.parts])
        return np.concatenate([np.asarray(p.h(T_state, vp), float).ravel() for p, vp in zip(self.parts, vs)])

    def residual(self, z: np.ndarray, z_pred: np.ndarray) -> np.ndarray:
        out = []
        for p, a, b in zip(self.parts, self._split(z, self._zsizes), self._split(z_pred, self._zsizes)):
            if isinstance(p, PoseObservation):
                a, b = a.reshape(4, 4), b.reshape(4, 4)
            out.append(p.residual(a, b))
        return np.concatenate(out)

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray | None:
        Hs = [p.jacobian_state(T_state) for p in self.parts]
        Hs_known = [H for H in Hs if H is not None]
        return None if len(Hs_known) < len(Hs) else np.vstack(Hs_known)

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray | None:
        Ms = [p.jacobian_noise(T_state) for p in self.parts]
        Ms_known = [M for M in Ms if M is not None]
        if len(Ms_known) < len(Ms):
            return None
        return _block_diag_rect(Ms_known)


def _block_diag_rect(blocks: Sequence[np.ndarray]) -> np.ndarray:
    rows = sum(b.shape[0] for b in blocks)
    cols = sum(b.shape[1] for b in blocks)
    out = np.zeros((rows, cols))
    i = j = 0
    for b in blocks:
        out[i : i + b.shape[0], j : j + b.shape[1]] = b
        i += b.shape[0]
        j += b.shape[1]
    return out
