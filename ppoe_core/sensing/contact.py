"""Contact detection and the contact plane measurement (no ROS).

The contact node (``ppoe_ros/contact_node.py``) and ``ppoe evaluate`` (``ppoe_core/evaluate.py``)
share this module, so a replayed ``/wrench`` gives exactly the ``/contact/plane`` messages the
live node publishes:

* :class:`ContactDetector`: force threshold with hysteresis on a force measure
  (:func:`force_measure`: the force norm or one signed axis of the wrench frame);
* :func:`plane_from_config`: the plane pose ``T_frame_plane`` and its ``Sigma_v`` (paper
  sec. V, plane tangent space) from the model YAML ``contact`` section, overridable by the
  node's parameters;
* :func:`contact_stamps`: the stamps of a wrench stream at which the node publishes the plane
  (one per wrench while in contact; a non-finite wrench or a stamp older than the previous one
  is bad and ignored, as the node does).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, MeasurementError, ModelConfigError
from ppoe_core.robot.config import ContactConfig

__all__ = [
    "FORCE_COMPONENTS",
    "DEFAULT_FORCE_THRESHOLD",
    "DEFAULT_RELEASE_THRESHOLD",
    "ContactDetector",
    "PublishedPlane",
    "plane_from_config",
    "force_measure",
    "contact_stamps",
]

#: force measures: the force norm, or one signed axis of the wrench frame
FORCE_COMPONENTS: tuple[str, ...] = ("norm", "x", "y", "z", "-x", "-y", "-z")
#: force [N] that starts a contact when neither a parameter nor the model YAML gives one
DEFAULT_FORCE_THRESHOLD = 5.0
#: force [N] below which a contact ends when neither a parameter nor the model YAML gives one
DEFAULT_RELEASE_THRESHOLD = 2.0


def force_measure(force: np.ndarray, component: str = "norm") -> np.ndarray:
    """The force measure the detector thresholds.

    Parameters
    ----------
    force : ndarray, shape (..., 3)
        Force [N] in the wrench frame.
    component : str
        ``"norm"`` (``|f|``) or a signed axis ``"x"``, ``"-z"``, ... (``+-f_axis``).

    Returns
    -------
    ndarray, shape (...)
        [N].

    Raises
    ------
    ModelConfigError
        ``component`` not in :data:`FORCE_COMPONENTS`.
    """
    if component not in FORCE_COMPONENTS:
        raise ModelConfigError(f"force_component must be one of {FORCE_COMPONENTS}, got {component!r}")
    f = np.asarray(force, dtype=np.float64)
    if component == "norm":
        return np.linalg.norm(f, axis=-1)
    sign = -1.0 if component.startswith("-") else 1.0
    return sign * f[..., "xyz".index(component[-1])]


class ContactDetector:
    """Force threshold with hysteresis: contact begins at ``force >= enter`` and ends at
    ``force < release`` (``release < enter``).

    Parameters
    ----------
    enter : float
        Force measure [N] that starts a contact (``force_threshold``).
    release : float
        Force measure [N] below which a contact ends (``release_threshold``).

    Raises
    ------
    ModelConfigError
        ``release >= enter`` or a non-finite threshold.
    """

    def __init__(self, enter: float, release: float) -> None:
        self.enter = float(enter)
        self.release = float(release)
        self.check_thresholds(self.enter, self.release)
        #: current state (True = in contact)
        self.in_contact = False

    @staticmethod
    def check_thresholds(enter: float, release: float) -> None:
        """Raise :class:`ModelConfigError` unless ``release < enter``, both finite [N]."""
        if not (np.isfinite(enter) and np.isfinite(release)):
            raise ModelConfigError(f"force thresholds must be finite, got force_threshold {enter} N, "
                                   f"release_threshold {release} N")
        if not release < enter:
            raise ModelConfigError(f"release_threshold ({release} N) must be below force_threshold ({enter} N)")

    def update(self, force: float) -> bool:
        """Feed one force measure [N]; returns the contact state after it."""
        if self.in_contact:
            if force < self.release:
                self.in_contact = False
        elif force >= self.enter:
            self.in_contact = True
        return self.in_contact


class PublishedPlane:
    """The contact plane as the contact node publishes it.

    Attributes
    ----------
    frame : str
        Frame the plane pose is given in (``header.frame_id`` of ``/contact/plane``).
    T_frame_plane : ndarray, shape (4, 4)
        Plane pose; plane normal = plane z axis.
    cov_plane : ndarray, shape (6, 6)
        Sigma_v in the tangent space at ``T_frame_plane`` (plane frame, right perturbation).
    cov_ros : ndarray, shape (6, 6)
        The same in the ROS convention (axes of ``frame``, docs/conventions.md sec. 2).
    """

    def __init__(self, frame: str, T_frame_plane: np.ndarray, cov_plane: np.ndarray) -> None:
        self.frame = frame
        self.T_frame_plane = T_frame_plane
        self.cov_plane = cov_plane
        self.cov_ros = lie.cov_local_to_ros(T_frame_plane, cov_plane)


#: plane parameters of the contact node, "empty" = take the model YAML's value
_PLANE_PARAM_DEFAULTS: dict[str, Any] = {"plane_frame": "", "plane_xyz": [], "plane_rpy": [], "plane_sigma": []}


def plane_from_config(contact: ContactConfig | None, frames_base: str | None,
                      params: Mapping[str, Any] | None = None, where: str = "contact") -> PublishedPlane:
    """Plane pose and Sigma_v from parameters, falling back on the model YAML ``contact`` section.

    Parameters
    ----------
    contact : ContactConfig or None
        The model YAML's ``contact`` section, validated by
        :func:`ppoe_core.robot.config.load_contact_config` (None: the YAML has none).
    frames_base : str or None
        The model YAML's ``frames.base``: plane frame when neither the parameter nor a
        ``contact`` section gives one.
    params : mapping, optional
        Contact node parameters ``plane_frame``, ``plane_xyz`` (3, m), ``plane_rpy`` (3, rad)
        and ``plane_sigma`` (6, 1-sigma of ``[rho; theta]`` in the plane frame, m and rad);
        missing or empty = the model YAML's value.
    where : str
        Node or file, for error messages.

    Returns
    -------
    PublishedPlane
        ``cov_plane`` in the tangent space at ``T_frame_plane`` (plane frame).

    Raises
    ------
    ModelConfigError
        No frame or no Sigma_v in either place, or malformed values (message names ``where`` and the key).
    """
    p = {**_PLANE_PARAM_DEFAULTS, **(params or {})}
    frame = p["plane_frame"] or (contact.plane_frame if contact is not None else frames_base)
    if not frame:
        raise ModelConfigError(f"{where}: no contact plane frame (parameter plane_frame, contact.plane.frame "
                               "or frames.base)")
    T = contact.T_frame_plane.copy() if contact is not None else np.eye(4)
    for name, size in (("plane_xyz", 3), ("plane_rpy", 3), ("plane_sigma", 6)):
        try:
            v = np.asarray(p[name], dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ModelConfigError(f"{where}: parameter {name} must be numbers, got {p[name]!r}") from None
        if not np.all(np.isfinite(v)):
            raise ModelConfigError(f"{where}: parameter {name} must be finite numbers, got {p[name]!r}")
        if v.size not in (0, size):
            raise ModelConfigError(f"{where}: parameter {name} must have 0 or {size} values, got {v.size}")
    if len(p["plane_xyz"]):
        T[:3, 3] = np.asarray(p["plane_xyz"], dtype=float)
    if len(p["plane_rpy"]):
        T[:3, :3] = lie.from_xyz_rpy(np.zeros(3), np.asarray(p["plane_rpy"], dtype=float))[:3, :3]
    if len(p["plane_sigma"]):
        cov = np.diag(np.square(np.asarray(p["plane_sigma"], dtype=float)))
    elif contact is not None:
        cov = contact.covariance
    else:
        raise ModelConfigError(f"{where}: no plane Sigma_v (parameter plane_sigma, contact.sigma or "
                               "contact.covariance)")
    try:
        cov = lie.check_covariance(cov, f"{where}: contact plane Sigma_v", size=6)
    except CovarianceError as exc:
        raise ModelConfigError(str(exc)) from None
    return PublishedPlane(str(frame), T, cov)


def contact_stamps(stamps: np.ndarray, force: np.ndarray, detector: ContactDetector,
                   component: str = "norm", where: str = "/wrench") -> tuple[np.ndarray, dict[str, int]]:
    """Run a recorded wrench stream through ``detector`` as the contact node does.

    Messages are taken in the given (arrival) order.  A message with a non-finite force or a
    stamp older than the previous good one is *bad*: counted and ignored (no detector update,
    no output), exactly as the node's ``/wrench`` callback.

    Parameters
    ----------
    stamps : ndarray, shape (n,)
        Wrench stamps [s], in arrival order.
    force : ndarray, shape (n, 3)
        Forces [N] in the wrench frame.
    detector : ContactDetector
        Updated in place (its state carries over between calls).
    component : str
        Force measure, see :func:`force_measure`.
    where : str
        Topic name for error messages.

    Returns
    -------
    (in_contact_stamps, counts)
        ``in_contact_stamps`` (m,): stamps of the wrenches after which the detector is in
        contact (the node publishes the plane with each of these stamps); ``counts``:
        ``received``, ``bad``, ``contacts`` (onsets), ``published``.

    Raises
    ------
    MeasurementError
        ``stamps`` and ``force`` do not have matching shapes (n,) and (n, 3).
    """
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    f = np.asarray(force, dtype=np.float64)
    if f.shape != (t.size, 3):
        raise MeasurementError(f"{where}: {t.size} stamps but force of shape {f.shape}, expected ({t.size}, 3)")
    measure = force_measure(f, component)
    counts = {"received": int(t.size), "bad": 0, "contacts": 0, "published": 0}
    out: list[float] = []
    last = -np.inf
    for ti, fi, mi in zip(t, f, measure):
        if not (np.all(np.isfinite(fi)) and np.isfinite(ti)) or ti < last:
            counts["bad"] += 1
            continue
        last = ti
        was = detector.in_contact
        if detector.update(float(mi)):
            counts["contacts"] += int(not was)
            out.append(float(ti))
    counts["published"] = len(out)
    return np.asarray(out, dtype=np.float64), counts
