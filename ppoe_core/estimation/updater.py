"""The fusion pipeline's measurement updater on a PPOE model: tag and contact measurements -> models -> iterated
LG-EKF."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.estimation.corrections import Measurement, ToolUpdate
from ppoe_core.estimation.prior_buffer import Array, PriorSample

# ----------------------------------------------------------------------------
# Measurement payloads and the model-based updater (PPOEModel + fusion.py)
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class TagMeasurement:
    """Payload of one ``/tag_bearing/observations`` message (one image).

    Attributes
    ----------
    camera_frame : str
        Camera optical frame (URDF link; ``header.frame_id`` of the image).
    ids : ndarray, shape (n,), int
        Tag id of each point.
    corners : ndarray, shape (n,), int
        0 = tag centre, 1..4 = corners in the order of :mod:`ppoe_core.sensing.tags`.
    xy : ndarray, shape (n, 2)
        Undistorted normalised image coordinates ``(X/Z, Y/Z)``.
    uv : ndarray, shape (n, 2), optional
        Raw (distorted) pixels, used to infer the focal lengths when ``fx``/``fy`` are None.
    fx, fy : float, optional
        Focal lengths [px] (``camera_info`` K); they turn the pixel noise into normalised units.
    """

    camera_frame: str
    ids: Array
    corners: Array
    xy: Array
    uv: Array | None = None
    fx: float | None = None
    fy: float | None = None


@dataclass(frozen=True)
class ContactMeasurement:
    """Payload of one ``/contact/plane`` message: the tool point lies on this plane.

    Attributes
    ----------
    frame : str
        Frame the plane pose is given in (``header.frame_id``).
    T_frame_plane : ndarray, shape (4, 4)
        Plane pose; plane normal = plane z axis.
    cov_plane : ndarray, shape (6, 6)
        ``Sigma_v`` in the tangent space at the plane pose (plane frame, local convention).
    """

    frame: str
    T_frame_plane: Array
    cov_plane: Array


def _check_unique_rows(ids: Array, corners: Array, where: str) -> None:
    """Refuse an observation that lists a (tag id, corner) twice: it would count as two measurements."""
    if ids.size == 0 or len(set(zip(ids.tolist(), corners.tolist()))) == ids.size:
        return
    pairs, counts = np.unique(np.column_stack([ids, corners]), axis=0, return_counts=True)
    if np.any(counts > 1):
        dup = ", ".join(f"tag {int(t)} corner {int(c)} x{int(n)}" for (t, c), n in zip(pairs, counts) if n > 1)
        raise MeasurementError(f"{where}: duplicated observation rows ({dup}); the whole image is refused")


@functools.cache
def _label(tid: int, corner: int) -> str:
    """``"tag <id> corner <c>"`` (made once per pair)."""
    return f"tag {tid} corner {corner}"


def _focal_from_points(uv: Array, xy: Array, where: str) -> tuple[float, float]:
    """Least-squares fit ``u = fx x + cx``, ``v = fy y + cy`` (distortion neglected)."""
    out = []
    for k, axis in enumerate("xy"):
        a = xy[:, k]
        if a.size < 2 or float(np.ptp(a)) < 1e-6:
            raise MeasurementError(
                f"{where}: no camera_info focal length and the points do not spread in {axis} to infer it"
            )
        A = np.stack([a, np.ones_like(a)], axis=1)
        f = float(np.linalg.lstsq(A, uv[:, k], rcond=None)[0][0])
        if not f > 0.0:
            raise MeasurementError(f"{where}: inferred focal length f{axis} = {f:.4g} is not positive")
        out.append(f)
    return out[0], out[1]


class ModelUpdater:
    """Iterated LG-EKF updates of ``T_base_tool`` for the project's measurement payloads.

    The measurement models of :mod:`ppoe_core.estimation.measurements` are built per measurement from
    the PPOE model: tag mounts (``tags`` section) and the contact tool point (``contact``
    section) in the tool frame via ``model.fk_mean(joints, tool, link)``; the camera pose
    ``T_base_camera`` and its PPOE covariance (camera frame) via ``model.fk(joints, base,
    camera)``, entering the tag model as noise through ``M``; a plane given in another
    frame is moved into ``base`` with ``model.fk_mean``.  ``joints`` are the prior's joint
    positions at the measurement's stamp (``model.joint_names`` order, NaN = unknown); a
    chain that needs an unknown joint makes the measurement bad (the error names it).

    Parameters
    ----------
    model : PPOEModel
    base_frame, tool_frame : str
        Frames of the state ``T_base_tool`` (the prior's ``header.frame_id`` and target).
    pixel_sigma : float, optional
        1-sigma pixel noise [px]; None = model YAML ``camera.pixel_sigma`` (default 0.5).
    max_iterations : int
        Relinearisations of the iterated update (1 = plain LG-EKF).
    gate_probability : float or None
        Chi-square gate probability (None = no gating).
    gating : {"posterior", "prior"}
        ``"prior"``: the NIS at the prior (``fusion.iterated_update``'s gate, exact for linear
        models).  ``"posterior"`` (default): the cost of the iterated solution,
        ``J = r+^T (M R M^T)^-1 r+ + d^T P^+ d`` with the post-fit residual ``r+`` and the
        correction ``d = Log(X0^-1 X+)`` (``P^+`` pseudo-inverse of the prior covariance;
        :func:`ppoe_core.estimation.update_kernels.posterior_cost`), against the same chi-square
        quantile of the measurement dimension.  ``J`` equals the
        prior NIS for a linear model, but does not blow up when the prior is wide compared
        with the sensor (tags seen through 5 deg of plate bending: see docs/fusion_node.md).
    camera_covariance : bool
        Let the PPOE covariance of the camera chain enter the tag model.
    use_centre, use_corners : bool
        Which tag points enter the update (centre, corners 1..4).
    contact_distance_sigma : float
        Extra 1-sigma noise of the contact distance [m].
    """

    def __init__(self, model: Any, base_frame: str, tool_frame: str, pixel_sigma: float | None = None,
                 max_iterations: int = 5, gate_probability: float | None = 0.9973, gating: str = "posterior",
                 camera_covariance: bool = True, use_centre: bool = True, use_corners: bool = True,
                 contact_distance_sigma: float = 0.0) -> None:
        if not (use_centre or use_corners):
            raise PpoeError("ModelUpdater: use_centre and use_corners are both false: no tag point would be used")
        self.model = model
        self.base_frame = base_frame
        self.tool_frame = tool_frame
        cfg = model.config
        cam_sigma = cfg.camera.pixel_sigma if getattr(cfg, "camera", None) is not None else 0.5
        self.pixel_sigma = float(cam_sigma if pixel_sigma is None else pixel_sigma)
        self.max_iterations = int(max_iterations)
        self.gate_probability = gate_probability
        if gating not in ("posterior", "prior"):
            raise PpoeError(f"ModelUpdater: gating must be 'posterior' or 'prior', got {gating!r}")
        self.gating = gating
        self.camera_covariance = bool(camera_covariance)
        self.use_centre = bool(use_centre)
        self.use_corners = bool(use_corners)
        self.contact_distance_sigma = float(contact_distance_sigma)
        self.tags = cfg.tags.by_id() if getattr(cfg, "tags", None) is not None else {}
        self.contact = getattr(cfg, "contact", None)
        #: tag points ignored because their id is not in the model YAML
        self.unknown_tag_points = 0
        self._rigid_tags: dict[int, tuple[Any, Any, Array]] = {}  # tag id -> (item, model, points in the tool frame)

    def _joints(self, prior: PriorSample | None) -> dict[str, float]:
        if prior is None or prior.joints is None:
            return {}
        q = prior.joints
        values = q.tolist() if type(q) is np.ndarray and q.ndim == 1 else [float(v) for v in q]  # Python floats
        return {n: v for n, v in zip(self.model.joint_names, values) if math.isfinite(v)}

    def build(self, measurement: Measurement, prior: PriorSample | None) -> tuple[Any, Array]:
        """Measurement model and ``z`` for ``measurement`` (see class docstring)."""
        joints = self._joints(prior)
        p = measurement.payload
        where = f"{measurement.source} at stamp {measurement.stamp:.6f}"
        if isinstance(p, TagMeasurement):
            return self._build_tags(p, joints, where)
        if isinstance(p, ContactMeasurement):
            return self._build_contact(p, joints, where)
        raise MeasurementError(f"{where}: unknown payload type {type(p).__name__}")

    def _build_tags(self, p: TagMeasurement, joints: Any, where: str) -> tuple[Any, Array]:
        """Tag bearing model (normalised coordinates, camera pose from the chain) and ``z``."""
        from ppoe_core.estimation import measurements as mm

        ids = np.asarray(p.ids).astype(int).reshape(-1)
        corners = np.asarray(p.corners).astype(int).reshape(-1)
        xy = np.asarray(p.xy, dtype=np.float64).reshape(-1, 2)
        if not (ids.shape[0] == corners.shape[0] == xy.shape[0]):
            raise MeasurementError(f"{where}: ids, corners and xy differ in length")
        if not np.isfinite(xy).all():
            raise MeasurementError(f"{where}: NaN/inf in the normalised coordinates")
        _check_unique_rows(ids, corners, where)
        fx, fy = p.fx, p.fy
        if fx is None or fy is None:
            if p.uv is None:
                raise MeasurementError(f"{where}: no focal length (camera_info) and no pixels")
            fx, fy = _focal_from_points(np.asarray(p.uv, float).reshape(-1, 2), xy, where)
        pts, keep, labels = self._tag_points_tool(ids, corners, joints, where)
        if self.camera_covariance:
            T_base_cam, cov_cam = self.model.fk(joints, self.base_frame, p.camera_frame)
            if not cov_cam.any():  # exactly zero (NaN counts as non-zero, as max |cov| == 0 would)
                cov_cam = None
        else:
            T_base_cam, cov_cam = self.model.fk_mean(joints, self.base_frame, p.camera_frame), None
        K = np.array([[fx, 0.0, 0.0], [0.0, fy, 0.0], [0.0, 0.0, 1.0]])
        obs = mm.TagBearingModel(
            np.asarray(pts),
            K,
            None,
            pixel_sigma=self.pixel_sigma,
            mode="normalized",
            T_ref_camera=T_base_cam,
            cov_camera=cov_cam,
            labels=labels,
            name=where,
            pose_checked=True,  # T_base_cam: the model's own forward kinematics
        )
        return obs, xy[keep].reshape(-1)

    def _tag_points_tool(
        self, ids: Array, corners: Array, joints: Any, where: str
    ) -> tuple[list[Array], list[int], list[str]]:
        """Tag points (centre 0, corners 1..4) in the tool frame for the observed rows the model knows."""
        pts, keep, labels = [], [], []
        T_tool_link: dict[str, Array] = {}
        tag_pts: dict[int, Array] = {}  # centre and corners of each tag in the tool frame
        for i, (tid, c) in enumerate(zip(ids.tolist(), corners.tolist())):
            item = self.tags.get(tid)
            if item is None:
                self.unknown_tag_points += 1
                continue
            if not 0 <= c <= 4:
                raise MeasurementError(f"{where}: tag {tid} has corner index {c}, expected 0..4")
            if (c == 0 and not self.use_centre) or (c > 0 and not self.use_corners):
                continue
            p = tag_pts.get(tid)
            if p is None:
                p = tag_pts[tid] = self._tag_points(tid, item, joints, T_tool_link)
            pts.append(p[c])
            keep.append(i)
            labels.append(_label(tid, c))
        if not pts:
            raise MeasurementError(
                f"{where}: no point of a tag configured in the model YAML (ids {sorted(set(ids.tolist()))})"
            )
        return pts, keep, labels

    def _tag_points(self, tid: int, item: Any, joints: Any, T_tool_link: dict[str, Array]) -> Array:
        """Centre and corners (5, 3) of tag ``item`` in the tool frame at ``joints``; kept for a tag whose link is
        fixed to the tool (no joint between them and no effects: the same at every configuration)."""
        from ppoe_core.estimation import measurements as mm

        kept = self._rigid_tags.get(tid)
        if kept is not None and kept[0] is item and kept[1] is self.model:
            return kept[2]
        if item.link not in T_tool_link:
            T_tool_link[item.link] = self.model.fk_mean(joints, self.tool_frame, item.link)
        p = mm.tag_points(item.size, T_tool_link[item.link] @ item.T_link_tag)
        if not self.model.effects and not self.model.chain_joints(self.tool_frame, item.link):
            self._rigid_tags[tid] = (item, self.model, p)
        return p

    def _build_contact(self, p: ContactMeasurement, joints: Any, where: str) -> tuple[Any, Array]:
        """Contact plane model (plane from the chain, tool point on the contact link) and ``z = 0``."""
        from ppoe_core.estimation import measurements as mm

        if self.contact is None:
            raise MeasurementError(f"{where}: the model YAML has no 'contact' section (tool point)")
        T_base_frame = self.model.fk_mean(joints, self.base_frame, p.frame)
        T_tool_contact = self.model.fk_mean(joints, self.tool_frame, self.contact.tool_link)
        point_tool = T_tool_contact[:3, :3] @ self.contact.tool_xyz + T_tool_contact[:3, 3]
        obs = mm.ContactPlaneModel(T_base_frame @ np.asarray(p.T_frame_plane, float), p.cov_plane, point_tool,
                                   distance_sigma=self.contact_distance_sigma, name=where)
        return obs, np.zeros(1)

    def __call__(
        self, T_base_tool: Array, cov_tool: Array, measurement: Measurement, prior: PriorSample | None = None
    ) -> ToolUpdate:
        """Iterated LG-EKF update (``ppoe_core.estimation.fusion.iterated_update``) with gating."""
        from ppoe_core.estimation.fusion import chi2_gate, iterated_update

        obs, z = self.build(measurement, prior)
        prior_gate = self.gate_probability if self.gating == "prior" else None
        posterior = self.gating == "posterior" and self.gate_probability is not None
        res = iterated_update(T_base_tool, cov_tool, z, obs, max_iterations=self.max_iterations,
                              gate_probability=prior_gate, with_cost=posterior)
        if not posterior:
            return ToolUpdate(res.T, res.cov, bool(res.accepted), float(res.nis))
        cost = res.cost  # the compiled update's posterior cost (NaN: M R M^T not positive definite -> rejected)
        gate = chi2_gate(obs.dim, self.gate_probability)
        if not cost <= gate:
            return ToolUpdate(np.asarray(T_base_tool, float), np.asarray(cov_tool, float), False, cost)
        return ToolUpdate(res.T, res.cov, True, cost)


#: Fusion settings with their defaults: the fusion node's parameters of the same names
#: (``config/nodes/fusion_node.yaml`` documents meaning and unit) and ``ppoe evaluate``'s replay.
FUSION_SETTINGS: dict[str, Any] = {
    "buffer_duration": 1.0,  # s
    "max_gap": 0.2,  # s
    "max_hold": 0.5,  # s
    "max_pending": 200,
    "min_interval": 0.05,  # s, per source (topic + frame_id, source_key)
    "correction_timeout": 10.0,  # s
    "correction_joint_motion": 0.05,  # rad or m
    "correction_tool_translation": 0.05,  # m
    "correction_tool_rotation": 0.1,  # rad
    "correction_decay": "linear",
    "max_iterations": 5,
    "gate_probability": 0.9999,  # >= 1.0: no gating
    "gating": "posterior",
    "pixel_sigma": 0.0,  # px; <= 0: model YAML camera.pixel_sigma
    "use_tag_centre": True,
    "use_tag_corners": True,
    "camera_covariance": True,
    "contact_distance_sigma": 0.0,  # m
}


#: inclusive ranges of the numeric :data:`FUSION_SETTINGS` (the fusion node's parameter ranges; a
#: test keeps them equal), checked by ``ppoe evaluate`` so that offline refuses what the node refuses
FUSION_RANGES: dict[str, tuple[float, float]] = {
    "buffer_duration": (1e-3, 3600.0),
    "max_gap": (1e-6, 3600.0),
    "max_hold": (0.0, 3600.0),
    "max_pending": (0, 100000),
    "min_interval": (0.0, 3600.0),
    "max_iterations": (1, 100),
    "gate_probability": (0.5, 1.0),
    "contact_distance_sigma": (0.0, 1e3),
}


def make_updater(model: Any, base_frame: str, tool_frame: str, settings: dict[str, Any] | None = None,
                 cls: type[ModelUpdater] | None = None) -> ModelUpdater:
    """The :class:`ModelUpdater` of ``settings`` (keys of :data:`FUSION_SETTINGS`); ``cls``: a subclass to build
    instead (the fusion node's :class:`~ppoe_core.estimation.source_updater.SourceUpdater`)."""
    s = {**FUSION_SETTINGS, **(settings or {})}
    return (cls or ModelUpdater)(
        model,
        base_frame,
        tool_frame,
        pixel_sigma=float(s["pixel_sigma"]) if float(s["pixel_sigma"]) > 0 else None,
        max_iterations=int(s["max_iterations"]),
        gate_probability=None if float(s["gate_probability"]) >= 1.0 else float(s["gate_probability"]),
        gating=str(s["gating"]),
        camera_covariance=bool(s["camera_covariance"]),
        use_centre=bool(s["use_tag_centre"]),
        use_corners=bool(s["use_tag_corners"]),
        contact_distance_sigma=float(s["contact_distance_sigma"]),
    )
