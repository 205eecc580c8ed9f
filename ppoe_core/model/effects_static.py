"""Static geometric effects: constant corrections of the chain (joint zero offsets, link and camera-mount twists,
the root's tilt) and the tracker registration (a nuisance, no chain correction)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import ModelConfigError
from ppoe_core.model.effect_base import TWIST_KEYS, Effect, batch_shape, check_components, check_joint
from ppoe_core.robot.tree import KinematicTree

__all__ = ["JointOffset", "LinkError", "CameraExtrinsics", "BaseTilt", "TrackerRegistration"]


class JointOffset(Effect):
    """Joint zero offset: ``dq_j = offset``."""

    name = "joint_offset"
    units = ("rad or m",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        check_joint(tree, location, self.name, movable=True)
        super().__init__(tree, location, ("offset",), params)

    def basis(self, q, context=None, poses=None):
        return {self.location: np.ones(batch_shape(q) + (1,))}, {}


class LinkError(Effect):
    """Static non-zero-mean twist at a joint: ``dxi_j`` with a subset of ``x y z rx ry rz``."""

    name = "link_error"
    all_components = TWIST_KEYS

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] = TWIST_KEYS) -> None:
        check_joint(tree, location, self.name)
        self.components = check_components(self.name, location, components, TWIST_KEYS)
        self.units = tuple("m" if c in "xyz" else "rad" for c in self.components)
        super().__init__(tree, location, self.components, params)

    def basis(self, q, context=None, poses=None):
        S = np.zeros((6, len(self.components)))
        for i, c in enumerate(self.components):
            S[TWIST_KEYS.index(c), i] = 1.0
        return {}, {self.location: np.broadcast_to(S, batch_shape(q) + S.shape)}


class CameraExtrinsics(LinkError):
    """6D correction of the fixed joint that carries a camera frame (a link error there); a camera frame given as
    location maps to its parent joint (``frame`` keeps it)."""

    name = "camera_extrinsics"

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] = TWIST_KEYS) -> None:
        self.frame: str | None = None
        if location in tree.robot.links and location not in tree.robot.joints:
            pj = tree.robot.parent_joint(location)
            if pj is None:
                raise ModelConfigError(f"effect {self.name}: camera frame '{location}' is the root link")
            self.frame = location
            location = pj.name
        super().__init__(tree, location, params, components)


class BaseTilt(Effect):
    """Rotation of the root about its x and y axes: ``dxi`` on every joint hanging on the root.  With
    ``variable="measured"`` the tilt measured at each stop by an accelerometer fixed to the root (context
    ``base_tilt``; none without it) times ``gain`` (1: the robot rocks on its support as measured)."""

    name = "base_tilt"
    units: tuple[str, ...] = ("rad", "rad")

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 variable: str | None = None) -> None:
        if location != tree.root:
            raise ModelConfigError(f"effect {self.name}: location '{location}' must be the root link "
                                   f"'{tree.root}' of URDF {tree.robot.source}")
        if variable not in (None, "measured"):
            raise ModelConfigError(f"effect {self.name}: variable must be 'measured' or absent, got {variable!r}")
        self.variable = variable
        self.units = ("rad", "rad") if variable is None else ("1",)
        super().__init__(tree, location, ("tilt_x", "tilt_y") if variable is None else ("gain",), params)

    def basis(self, q, context=None, poses=None):
        w = (context or {}).get("base_tilt")
        if self.variable is not None and w is None:  # nothing measured (fk, nodes): no rocking to correct
            return {}, {}
        Ads = {jn: np.broadcast_to(lie.adjoint(lie.inverse(self.tree.robot.joints[jn].origin))[:, 3:5],
                                   batch_shape(q) + (6, 2)) for jn in self.tree.robot.children(self.tree.root)}
        return {}, {jn: Ad if self.variable is None else Ad @ np.asarray(w, dtype=float)[..., :, None]
                    for jn, Ad in Ads.items()}


class TrackerRegistration(Effect):
    """Per-session tracker-to-base transform ``T_tracker_base = from_xyz_rpy(x y z, rx ry rz)``.

    Not a chain correction (``corrections`` are empty); ``ppoe diagnose`` always estimates it as
    a nuisance per session.
    """

    name = "tracker_registration"
    units = ("m", "m", "m", "rad", "rad", "rad")
    sensor = True

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        super().__init__(tree, location, TWIST_KEYS, params)

    def transform(self) -> np.ndarray:
        """``T_tracker_base`` (4, 4)."""
        return lie.from_xyz_rpy(self.params[:3], self.params[3:])

    def basis(self, q, context=None, poses=None):
        return {}, {}
