"""What a model YAML holds once validated: perturbations (paper eq. 16, local ``[rho; theta]``), frames, camera,
tags, contact plane, trackers, IMUs, naive filter settings and effects (docs/conventions.md sec. 5)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Effect names of docs/conventions.md section 6.
EFFECT_NAMES = (
    "joint_offset",
    "link_error",
    "gravity_compliance",
    "mount_bending",
    "lateral_compliance",
    "base_tilt",
    "backlash",
    "thermal_growth",
    "time_offset",
    "camera_extrinsics",
    "camera_intrinsics",
    "tag_offset",
    "tracker_registration",
)


# ----------------------------------------------------------------------------
# Data classes
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Perturbation:
    """Perturbation ``xi`` of one joint (paper eq. 16), zero mean.

    Attributes
    ----------
    joint : str
    covariance : ndarray, shape (6, 6)
        ``E[xi xi^T]`` of ``[rho; theta]`` [m^2, rad^2], in the tangent space right after
        the joint's static origin ``Exp(p_i)`` (the frame ``F_{i,p}`` of paper Fig. 2).
    factor : ndarray, shape (6, r)
        ``covariance = factor @ factor.T`` with only the non-zero directions (r <= 6).
    """

    joint: str
    covariance: np.ndarray
    factor: np.ndarray


@dataclass(frozen=True)
class Frames:
    """Default frames for fk / evaluate / nodes (URDF link names)."""

    base: str
    tool: str | None


@dataclass(frozen=True)
class CameraConfig:
    """``camera``: optical frame (URDF link, z forward) and pixel noise 1-sigma [px]."""

    frame: str
    pixel_sigma: float = 0.5


@dataclass(frozen=True)
class TagItem:
    """One tag fixed to a link.

    Attributes
    ----------
    id : int
    link : str
    size : float
        Edge of the black square [m].
    T_link_tag : ndarray, shape (4, 4)
        Tag centre pose in link coordinates (tag z = normal out of the tag).
    """

    id: int
    link: str
    size: float
    T_link_tag: np.ndarray


@dataclass(frozen=True)
class TagsConfig:
    """``tags``: tag family (default ``tag36h11``) and the tags."""

    family: str
    items: tuple[TagItem, ...]

    def by_id(self) -> dict[int, TagItem]:
        """Tags keyed by id."""
        return {t.id: t for t in self.items}


@dataclass(frozen=True)
class ContactConfig:
    """``contact``: a known plane the tool touches (paper section V).

    Attributes
    ----------
    plane_frame : str
        URDF link the plane pose is given in.
    T_frame_plane : ndarray, shape (4, 4)
        Plane pose; plane normal = plane z axis.
    covariance : ndarray, shape (6, 6)
        ``Sigma_v`` of the contact, in the tangent space at the plane pose (plane frame).
    tool_link : str
    tool_xyz : ndarray, shape (3,)
        Contact point in ``tool_link`` coordinates [m].
    force_threshold, release_threshold : float
        Contact enters above / leaves below these force magnitudes [N]. Defaults 5.0 / 2.0.
    """

    plane_frame: str
    T_frame_plane: np.ndarray
    covariance: np.ndarray
    tool_link: str
    tool_xyz: np.ndarray
    force_threshold: float = 5.0
    release_threshold: float = 2.0


#: topic of a single tracker's points (docs/conventions.md sec. 3); several reflectors use ``<this>/<name>``
TOPIC_GT_POINT = "/ground_truth/point"


@dataclass(frozen=True)
class TrackerConfig:
    """A point reflector on a link, measured by an external tracker (``tracker`` or one ``trackers`` entry).

    ``xyz`` [m] in ``link`` coordinates, ``sigma`` 1-sigma per axis [m] (default 0.0005), ``topic`` the
    ``PointStamped`` topic of its measurements (``/ground_truth/point`` or ``/ground_truth/point/<name>``).
    """

    link: str
    xyz: np.ndarray
    sigma: float = 0.0005
    topic: str = TOPIC_GT_POINT


@dataclass(frozen=True)
class ImuConfig:
    """One accelerometer on a link; ``sigma`` 1-sigma per axis [m/s^2] (default 0.0004)."""

    name: str
    link: str
    sigma: float = 0.0004


@dataclass(frozen=True)
class NaiveConfig:
    """``naive``: the naive diagonal covariance (tool frame tangent space) for comparisons."""

    covariance: np.ndarray


@dataclass(frozen=True)
class ModelConfig:
    """The validated model YAML.

    Attributes
    ----------
    perturbations : dict[str, Perturbation]
        Keyed by joint name (any URDF joint, fixed joints included).
    joint_noise : dict[str, float]
        1-sigma joint-value noise along the joint axis [rad or m] (paper IV-D, ``xi = zeta``);
        movable joints only.
    frames : Frames
    camera, tags, contact, tracker, naive : optional sections (None if absent); ``tracker`` is also
        set when ``trackers`` has exactly one entry
    trackers : tuple[TrackerConfig, ...]
        Every reflector (docs/conventions.md sec. 5); a ``tracker`` section gives one entry with topic
        ``/ground_truth/point``.
    imus : dict[str, ImuConfig]
    effects : list[dict]
        ``{"name", "location", "parameters"[, "ci", "variable", "reference"]}``, names from
        docs/conventions.md section 6.
    effect_wheres : list[str]
        ``file:line`` of each effect entry (for messages of ``effects.effect_from_config``).
    source : str
        File name, ``"<string>"`` or ``"<dict>"``.
    """

    perturbations: dict[str, Perturbation] = field(default_factory=dict)
    joint_noise: dict[str, float] = field(default_factory=dict)
    frames: Frames | None = None
    camera: CameraConfig | None = None
    tags: TagsConfig | None = None
    contact: ContactConfig | None = None
    tracker: TrackerConfig | None = None
    trackers: tuple[TrackerConfig, ...] = ()
    imus: dict[str, ImuConfig] = field(default_factory=dict)
    naive: NaiveConfig | None = None
    effects: list[dict] = field(default_factory=list)
    effect_wheres: list[str] = field(default_factory=list)
    source: str = "<dict>"
