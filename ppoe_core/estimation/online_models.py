"""What each measurement tells the online filter (docs/online.md): a measurement -> frame pairs and measurement models.

Every measurement kind is one or more :class:`FramePart`: a measurement model of
:mod:`ppoe_core.estimation.measurements` whose state is the pose ``X = T_ref_link`` of a link in a reference frame
of the robot (right perturbation, tangent at the link), its measured value ``z``, and the two frame names.  The
online filter (:class:`~ppoe_core.estimation.online_effects.OnlineEffects`) evaluates ``X`` on the chain with the
effects at their current estimate and chains ``H = dh/dxi`` with ``d xi / d theta``; the PPOE covariance of
``T_ref_link`` (the model's random errors, eq. 18) is measurement noise.  So one update serves every sensor:

==================  ===========================  ================  =====================================
measurement         ref                          link              model, ``z``
==================  ===========================  ================  =====================================
tracker point       root (registration known)    reflector's link  ``PointObservation``, point [m]
accelerometer       root (or the source's base)  its link          ``GravityObservation``, force [m/s^2]
tag pixels          the camera's optical frame   each tag's link   ``TagBearingModel`` (normalised), xy
6D pose             the pose's frame (or base)   the measured link ``PoseObservation``, the pose
contact plane       the plane's frame            the contact link  ``ContactPlaneModel``, distance 0
==================  ===========================  ================  =====================================

Tags of one image on several links are one update of several parts (their noise block-diagonal: the correlation of
the chains through their common joints is neglected, as in :class:`~ppoe_core.estimation.measurements.
StackedObservation`).  A camera frame or tag link that the robot's effects move (a camera on the tool, tags on the
floor = the root link) makes the camera's extrinsics and the effects observable from pixels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core.errors import MeasurementError
from ppoe_core.estimation.direct_measurements import GravityObservation, PointObservation, PoseObservation
from ppoe_core.estimation.update_types import MeasurementModel
from ppoe_core.estimation.measurements import ContactPlaneModel, TagBearingModel, tag_points
from ppoe_core.estimation.source_updater import (
    GravityMeasurement,
    PointMeasurement,
    PoseMeasurement,
    SelectedObservation,
)
from ppoe_core.estimation.updater import ContactMeasurement, TagMeasurement
from ppoe_core.robot.tree import GRAVITY

__all__ = ["FramePart", "OnlineRow", "contact_parts", "gravity_parts", "point_parts", "pose_parts", "tag_parts",
           "tracker_parts", "imu_parts", "payload_parts", "check_frames"]


@dataclass(frozen=True)
class FramePart:
    """One measurement model on the pose ``T_ref_link``.

    Attributes
    ----------
    ref, link : str
        URDF frames: the state of ``obs`` is ``X = T_ref_link`` (4, 4).
    obs : MeasurementModel
        ``h(X)``, ``jacobian_state`` (m, 6), ``jacobian_noise``, ``noise_cov``, ``residual``.
    z : ndarray
        The measured value (``obs.validate`` form: (m,) or a (4, 4) pose).
    """

    ref: str
    link: str
    obs: MeasurementModel
    z: np.ndarray


@dataclass
class OnlineRow:
    """A measurement as the online filter takes it: stamp [s], source (topic and frame), joints, context and parts.

    ``context`` holds the effect variables at the stamp (``temperature`` [deg C], ``time`` [s]); the drift monitor
    keeps the rows of its window to screen candidate effects on them.
    """

    stamp: float
    source: str
    q: dict[str, float]
    parts: list[FramePart]
    context: dict[str, Any] = field(default_factory=dict)

    @property
    def dim(self) -> int:
        """Number of scalar components (sum of the parts' ``obs.dim``)."""
        return int(sum(p.obs.dim for p in self.parts))


def tracker_parts(root: str, link: str, xyz: Any, point: Any, T_tracker_root: np.ndarray, sigma: float,
                  name: str) -> list[FramePart]:
    """A tracker point ``point`` (3,) [m] in the tracker frame of the reflector ``xyz`` on ``link``; the registration
    ``T_tracker_root`` is known (the tracker stands on the ground: it sees a tilt of the robot)."""
    obs = PointObservation(np.asarray(xyz, float), float(sigma), T_ref_sensor=np.linalg.inv(T_tracker_root), name=name)
    return [FramePart(root, link, obs, obs.validate(point))]


def imu_parts(root: str, link: str, accel: Any, sigma: float, name: str,
              up: Sequence[float] = (0.0, 0.0, 1.0)) -> list[FramePart]:
    """An accelerometer at rest on ``link``: specific force (3,) [m/s^2] in the link's axes, noise ``sigma``; gravity
    is ``-up`` of ``root`` (it sees the tilt without any registration)."""
    obs = GravityObservation(float(sigma), up_ref=up, name=name)
    return [FramePart(root, link, obs, obs.validate(accel))]


def _selected(obs: MeasurementModel, mask: Any) -> MeasurementModel:
    return obs if mask is None or np.all(mask) else SelectedObservation(obs, mask)


def point_parts(p: PointMeasurement, base: str, name: str) -> list[FramePart]:
    """A point source (the fusion node's ``type: point``): in a URDF frame, or in an external frame placed in
    ``base`` by ``T_base_frame``."""
    ref = base if p.T_base_frame is not None else p.frame
    obs = PointObservation(p.xyz_link, p.cov, T_ref_sensor=p.T_base_frame, name=name)
    return [FramePart(ref, p.link, _selected(obs, p.mask), obs.validate(p.point_frame))]


def pose_parts(p: PoseMeasurement, base: str, name: str) -> list[FramePart]:
    """A 6D pose of ``p.link`` in ``p.frame`` (URDF frame) or in an external frame placed in ``base``."""
    obs = PoseObservation(p.cov, name=name)
    if p.T_base_frame is None:
        return [FramePart(p.frame, p.link, _selected(obs, p.mask), obs.validate(p.T_frame_link))]
    z = np.asarray(p.T_base_frame, float) @ np.asarray(p.T_frame_link, float)
    return [FramePart(base, p.link, _selected(obs, p.mask), obs.validate(z))]


def gravity_parts(p: GravityMeasurement, base: str, name: str) -> list[FramePart]:
    """An accelerometer source (only the direction of the specific force is used, scaled to ``GRAVITY``; the
    largest variance of its covariance as the isotropic sigma, as the fusion node does)."""
    a = np.asarray(p.accel, dtype=float)
    norm = float(np.linalg.norm(a))
    if not (np.all(np.isfinite(a)) and norm > 0.0):
        raise MeasurementError(f"{name}: linear_acceleration {a.tolist()} has no direction")
    obs = GravityObservation(float(np.sqrt(np.max(np.diag(p.cov)))), up_ref=p.up_base, name=name)
    return [FramePart(base, p.link, _selected(obs, p.mask), obs.validate(a * (GRAVITY / norm)))]


def contact_parts(model: Any, p: ContactMeasurement, distance_sigma: float, name: str) -> list[FramePart]:
    """The tool point (model ``contact``) lies on the plane ``p.T_frame_plane`` of ``p.frame``: distance 0."""
    c = getattr(model.config, "contact", None)
    if c is None:
        raise MeasurementError(f"{name}: the model YAML has no 'contact' section (tool point)")
    obs = ContactPlaneModel(p.T_frame_plane, p.cov_plane, c.tool_xyz, distance_sigma=distance_sigma, name=name)
    return [FramePart(p.frame, c.tool_link, obs, np.zeros(1))]


def tag_parts(model: Any, p: TagMeasurement, pixel_sigma: float, name: str,
              skip_ids: frozenset[int] = frozenset()) -> tuple[list[FramePart], int]:
    """Tag points of one image (normalised coordinates, ``fx``/``fy`` from camera_info): one part per link carrying
    an observed tag, state ``T_camera_link``.  Returns the parts and the number of points of unknown tags (not in
    the model YAML, skipped); tags in ``skip_ids`` are left out (seen by another camera at the same time).

    Raises
    ------
    MeasurementError
        No focal length, NaN, a corner index outside 0..4, a (tag, corner) twice, no point of a known tag.
    """
    tags = model.config.tags.by_id() if getattr(model.config, "tags", None) is not None else {}
    ids = np.asarray(p.ids).astype(int).reshape(-1)
    corners = np.asarray(p.corners).astype(int).reshape(-1)
    xy = np.asarray(p.xy, dtype=float).reshape(-1, 2)
    if not (ids.shape[0] == corners.shape[0] == xy.shape[0]) or not np.all(np.isfinite(xy)):
        raise MeasurementError(f"{name}: ids, corners and xy differ in length or hold NaN")
    if p.fx is None or p.fy is None or not (p.fx > 0 and p.fy > 0):
        raise MeasurementError(f"{name}: no focal length (no camera_info of camera {p.camera_frame!r} yet)")
    if len(set(zip(ids.tolist(), corners.tolist()))) != ids.size:
        raise MeasurementError(f"{name}: a (tag, corner) is listed twice; the whole image is refused")
    if p.camera_frame not in model.robot.links:
        raise MeasurementError(f"{name}: camera frame {p.camera_frame!r} is not a link of the URDF")
    by_link: dict[str, tuple[list, list, list]] = {}
    unknown = 0
    for i, (tid, c) in enumerate(zip(ids.tolist(), corners.tolist())):
        item = tags.get(tid)
        if item is None:
            unknown += 1
            continue
        if not 0 <= c <= 4:
            raise MeasurementError(f"{name}: tag {tid} has corner index {c}, expected 0..4")
        if tid in skip_ids:
            continue
        pts, z, labels = by_link.setdefault(item.link, ([], [], []))
        pts.append(tag_points(item.size, item.T_link_tag)[c])
        z.append(xy[i])
        labels.append(f"tag {tid} corner {c}")
    K = np.array([[p.fx, 0.0, 0.0], [0.0, p.fy, 0.0], [0.0, 0.0, 1.0]])
    parts = []
    for link, (pts, z, labels) in by_link.items():
        obs = TagBearingModel(np.asarray(pts), K, None, pixel_sigma=pixel_sigma, mode="normalized", labels=labels,
                              name=name)
        parts.append(FramePart(p.camera_frame, link, obs, obs.validate(np.asarray(z).reshape(-1))))
    return parts, unknown


def payload_parts(model: Any, payload: Any, base: str, name: str, pixel_sigma: float = 0.5,
                  contact_sigma: float = 0.0, skip_ids: frozenset[int] = frozenset()) -> tuple[list[FramePart], int]:
    """The parts of a fusion payload (the fusion node's and ``ppoe evaluate``'s: tags, contact, point, pose,
    accelerometer sources); also the number of unknown tag points.

    Raises
    ------
    MeasurementError
        A bad measurement (named by ``name``); an unknown payload type.
    """
    if isinstance(payload, TagMeasurement):
        return tag_parts(model, payload, pixel_sigma, name, skip_ids)
    if isinstance(payload, ContactMeasurement):
        return contact_parts(model, payload, contact_sigma, name), 0
    if isinstance(payload, PoseMeasurement):
        return pose_parts(payload, base, name), 0
    if isinstance(payload, PointMeasurement):
        return point_parts(payload, base, name), 0
    if isinstance(payload, GravityMeasurement):
        return gravity_parts(payload, base, name), 0
    raise MeasurementError(f"{name}: the online filter takes no {type(payload).__name__}")


def check_frames(model: Any, parts: Sequence[FramePart], name: str) -> None:
    """Every part's frames are links of the URDF.

    Raises
    ------
    MeasurementError
        Naming the frame and ``name``.
    """
    links: Mapping[str, Any] = model.robot.links
    for part in parts:
        for f in (part.ref, part.link):
            if f not in links:
                raise MeasurementError(f"{name}: frame {f!r} is not a link of the URDF ({model.robot.source})")
