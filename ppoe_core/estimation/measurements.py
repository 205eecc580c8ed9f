"""Measurement models ``z = h(X, v)`` for the iterated LG-EKF (paper eq. 19, 24, 25).

Every model works on one state pose ``X = T_ref_state`` (4, 4) with the right / local
perturbation ``X Exp(xi)``, ``xi = [rho; theta]`` (docs/conventions.md sec. 1), and gives

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
    coordinates times the focal lengths (with ``p2`` in the second row, as docs/conventions.md says).
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

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.linalg

from ppoe_core import lie
from ppoe_core.estimation.checks import check_noise_covariance, check_pose
from ppoe_core.errors import CovarianceError, MeasurementError
from ppoe_core.estimation.camera import distortion_coefficients, project_points_jacobian
from ppoe_core.estimation.composite_measurements import ChainedObservation, StackedObservation
from ppoe_core.estimation.direct_measurements import GravityObservation, PointObservation, PoseObservation
from ppoe_core.estimation.update_types import MeasurementModel
from ppoe_core.estimation.update_types import KIND_CONTACT, KIND_TAG, CompiledModel
from ppoe_core.lie.compiled import compiled

__all__ = [
    "MeasurementModel", "TagBearingModel", "ContactPlaneModel", "PointObservation", "PoseObservation",
    "GravityObservation", "ChainedObservation", "StackedObservation", "tag_points",
]


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
    pose_checked : bool
        ``T_ref_camera`` is a rigid transform computed by the caller (e.g. the model's forward kinematics):
        not checked again.  Leave False for poses from user input.
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
        *,
        pose_checked: bool = False,
    ) -> None:
        self.name = name
        pts = np.asarray(points_tool, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
            raise MeasurementError(f"{name}: points_tool must have shape (n, 3), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise MeasurementError(f"{name}: points_tool contains NaN/inf")
        if mode not in ("pixel", "normalized"):
            raise MeasurementError(f"{name}: mode must be 'pixel' or 'normalized', not {mode!r}")
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise MeasurementError(f"{name}: K must be a finite 3x3 matrix with fx, fy > 0, got {K.tolist()}")
        if not (math.isfinite(pixel_sigma) and pixel_sigma > 0):
            raise CovarianceError(f"{name}: pixel_sigma must be > 0, got {pixel_sigma}")
        self.points_tool = pts
        self.K = K
        self.D = distortion_coefficients(D, name)
        self.mode = mode
        self.pixel_sigma = float(pixel_sigma)
        if T_ref_camera is None:
            self.T_ref_camera = np.eye(4)
        elif pose_checked:
            self.T_ref_camera = np.asarray(T_ref_camera, dtype=float)
        else:
            self.T_ref_camera = check_pose(T_ref_camera, f"{name}: T_ref_camera")
        self.T_camera_ref = lie.inverse(self.T_ref_camera)
        self.min_depth = float(min_depth)
        n = pts.shape[0]
        self.labels = list(labels) if labels is not None else [f"point {i}" for i in range(n)]
        if len(self.labels) != n:
            raise MeasurementError(f"{name}: {len(self.labels)} labels for {n} points")
        self.dim = 2 * n
        if mode == "pixel":
            var = np.array([self.pixel_sigma, self.pixel_sigma]) ** 2
        else:
            var = np.array([self.pixel_sigma / K[0, 0], self.pixel_sigma / K[1, 1]]) ** 2
        self.has_camera_noise = cov_camera is not None
        # blockdiag(diag(pixel variances), cov_camera): one array written in place (scipy's block_diag and np.diag
        # cost more than the update at 30 images/s)
        size = 2 * n + (6 if self.has_camera_noise else 0)
        self.noise_cov = np.zeros((size, size))
        diag = self.noise_cov.reshape(-1)[::size + 1]  # a view of the diagonal
        diag[0:2 * n:2], diag[1:2 * n:2] = var  # [var_x, var_y] per point
        if self.has_camera_noise:
            self.noise_cov[2 * n:, 2 * n:] = check_noise_covariance(cov_camera, 6, f"{name}: cov_camera")
        self.noise_checked = True  # built from checked blocks
        self.noise_dim = self.noise_cov.shape[0]
        #: the compiled linearisation (the whole update in one call)
        self.compiled = CompiledModel(
            KIND_TAG, np.ascontiguousarray(self.T_camera_ref), np.ascontiguousarray(self.points_tool),
            np.ascontiguousarray(self.K), np.ascontiguousarray(self.D, dtype=np.float64), self.mode == "pixel",
            self.has_camera_noise, self.min_depth)

    def points_camera(self, T_state: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Points in the camera frame (n, 3) for state ``T_ref_tool`` and camera noise ``w``."""
        T_cam_tool = self.T_camera_ref @ T_state
        if w is not None:
            T_cam_tool = lie.exp(-np.asarray(w, dtype=float)) @ T_cam_tool
        p = self.points_tool @ T_cam_tool[:3, :3].T + T_cam_tool[:3, 3]
        bad = np.flatnonzero(p[:, 2] < self.min_depth)
        if bad.size:
            self._behind(int(bad[0]), float(p[bad[0], 2]))
        return p

    def _behind(self, i: int, depth: float) -> None:
        raise MeasurementError(f"{self.name}: {self.labels[i]} is behind the camera or too close "
                               f"(z = {depth:.4g} m < min_depth {self.min_depth} m)")

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Predicted ``[u_0, v_0, u_1, v_1, ...]`` (2n,) for ``T_state = T_ref_tool``."""
        if v is None:
            return self.linearize(T_state)[0]
        v = self.noise_vector(v)
        w = v[self.dim :] if self.has_camera_noise else None
        uv, _ = project_points_jacobian(self.points_camera(T_state, w), self.K, self.D, self.mode)
        return uv.ravel() + v[: self.dim]

    def linearize(self, T_state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(h(T), H, M)``: ``H = d pi / d p_c R_camera_tool [I, -[p_i]x]`` (2n, 6), ``M`` identity for the pixel
        noise and ``d pi / d p_c [-I, [p_c]x]`` for the camera pose noise (the compiled linearisation,
        :func:`ppoe_core.estimation.update_kernels.linearize`)."""
        return _linearize_compiled(self, T_state)

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (2n, 6): ``d pi / d p_c * R_camera_tool [I, -[p_i]x]``."""
        return self.linearize(T_state)[1]

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        """``M`` (2n, 2n[+6]): identity for the pixel noise, ``d pi/d p_c [-I, [p_c]x]`` for w."""
        return self.linearize(T_state)[2]


def _linearize_compiled(model: Any, T_state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(h(T), H, M)`` of a model with a compiled linearisation (``model.compiled``)."""
    spec = model.compiled
    h, H = np.empty(model.dim), np.empty((model.dim, 6))
    M = np.empty((model.dim, model.noise_dim))
    bad = compiled("ppoe_core.estimation.update_kernels").linearize(
        spec.kind, np.ascontiguousarray(T_state, dtype=np.float64), spec.G, spec.points, spec.K, spec.D, spec.pixel,
        spec.extra, spec.min_depth, h, H, M)
    if bad >= 0:
        model._behind(int(bad), float(h[0]))
    return h, H, M


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

    def __init__(self, T_ref_plane: Any, cov_plane: Any, point_tool: Any = (0.0, 0.0, 0.0), distance_sigma: float = 0.0,
                 name: str = "contact plane") -> None:
        self.name = name
        self.T_ref_plane = check_pose(T_ref_plane, f"{name}: T_ref_plane")
        self.T_plane_ref = lie.inverse(self.T_ref_plane)
        p = np.asarray(point_tool, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise MeasurementError(f"{name}: point_tool must be 3 finite numbers, got {p.tolist()}")
        self.point_tool = p
        if not (np.isfinite(distance_sigma) and distance_sigma >= 0):
            raise CovarianceError(f"{name}: distance_sigma must be >= 0, got {distance_sigma}")
        self.distance_sigma = float(distance_sigma)
        blocks = [check_noise_covariance(cov_plane, 6, f"{name}: cov_plane")]
        if self.distance_sigma > 0:
            blocks.append(np.array([[self.distance_sigma**2]]))
        self.noise_cov = scipy.linalg.block_diag(*blocks)
        self.noise_checked = True  # built from checked blocks
        self.noise_dim = self.noise_cov.shape[0]
        self.dim = 1
        #: the compiled linearisation (the whole update in one call)
        self.compiled = CompiledModel(KIND_CONTACT, np.ascontiguousarray(self.T_plane_ref),
                                      self.point_tool.reshape(1, 3), np.eye(3), np.zeros(5), False,
                                      self.distance_sigma > 0, 0.0)

    def point_plane(self, T_state: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Tool point in the (perturbed) plane frame, shape (3,)."""
        T = self.T_plane_ref @ T_state
        if w is not None:
            T = lie.exp(-np.asarray(w, dtype=float)) @ T
        return T[:3, :3] @ self.point_tool + T[:3, 3]

    def h(self, T_state: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
        """Signed distance (1,) [m], positive on the side the normal points to."""
        if v is None:
            return self.linearize(T_state)[0]
        v = self.noise_vector(v)
        d = self.point_plane(T_state, v[:6])[2]
        if self.distance_sigma > 0:
            d = d + v[6]
        return np.array([d])

    def linearize(self, T_state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(h(T), H, M)``: ``H = e_z^T R_plane_tool [I, -[p]x]`` (1, 6), ``M = e_z^T [-I, [p_plane]x]`` (+ 1 for the
        distance noise) (the compiled linearisation, :func:`ppoe_core.estimation.update_kernels.linearize`)."""
        return _linearize_compiled(self, T_state)

    def jacobian_state(self, T_state: np.ndarray) -> np.ndarray:
        """``H`` (1, 6) = ``e_z^T R_plane_tool [I, -[p]x]``."""
        return self.linearize(T_state)[1]

    def jacobian_noise(self, T_state: np.ndarray) -> np.ndarray:
        """``M`` (1, 6[+1]) = ``e_z^T [-I, [p_plane]x]`` (+ 1 for the distance noise)."""
        return self.linearize(T_state)[2]
