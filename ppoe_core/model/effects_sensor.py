"""Sensor effects: the model of the sensor that measures the chain, not the chain itself.

``camera_intrinsics`` corrects a camera's ``camera_info`` (pinhole ``fx fy cx cy`` [px], plumb_bob distortion
``k1 k2 p1 p2 k3``); ``tag_offset`` corrects a tag's pose on its link (``x y z rx ry rz``, right perturbation of
``T_link_tag``).  Both are linear corrections that start at zero; their chain corrections are empty
(:attr:`Effect.sensor`): the measurement that uses the sensor applies them (:meth:`CameraIntrinsics.corrected`,
:meth:`TagOffset.corrected`) and owns their Jacobian (``ppoe_core.estimation.camera_intrinsics``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import ModelConfigError
from ppoe_core.model.effect_base import TWIST_KEYS, Effect, check_components
from ppoe_core.robot.tree import KinematicTree

__all__ = ["INTRINSIC_KEYS", "INTRINSIC_LEVELS", "CameraIntrinsics", "TagOffset", "tag_location", "tag_id_of"]

#: camera_intrinsics parameters: pinhole [px], then plumb_bob distortion [1] (ROS camera_info order of D)
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: nested model levels, simplest first: principal point, pinhole, + radial k1 k2, + p1 p2 k3
INTRINSIC_LEVELS: tuple[tuple[str, ...], ...] = (("cx", "cy"), ("fx", "fy", "cx", "cy"),
                                                 ("fx", "fy", "cx", "cy", "k1", "k2"), INTRINSIC_KEYS)


class CameraIntrinsics(Effect):
    """Correction of a camera's intrinsics: ``K[0,0] += fx``, ``K[1,1] += fy``, ``K[0,2] += cx``,
    ``K[1,2] += cy``, ``D[k] += k1 ... k3`` (``components``: the corrected subset).  ``location`` = the camera's
    optical frame (a URDF link)."""

    name = "camera_intrinsics"
    sensor = True
    all_components = INTRINSIC_KEYS

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] = INTRINSIC_KEYS) -> None:
        if location not in tree.robot.links:
            raise ModelConfigError(f"effect {self.name}: location '{location}' is not a link (camera optical frame) "
                                   f"of URDF {tree.robot.source}")
        self.components = check_components(self.name, location, components, INTRINSIC_KEYS)
        self.units = tuple("px" if c in INTRINSIC_KEYS[:4] else "1" for c in self.components)
        super().__init__(tree, location, self.components, params)

    def basis(self, q, context=None, poses=None):
        return {}, {}

    def full(self) -> np.ndarray:
        """The correction of all nine parameters (zeros where not a component), (9,)."""
        out = np.zeros(len(INTRINSIC_KEYS))
        for k, v in zip(self.param_names, self.params):
            out[INTRINSIC_KEYS.index(k)] = v
        return out

    def corrected(self, K: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The corrected ``(K (3, 3), D (5,))`` of a camera with intrinsics ``K`` and plumb_bob ``D``."""
        d = self.full()
        K2 = np.array(K, dtype=float, copy=True)
        K2[0, 0] += d[0]
        K2[1, 1] += d[1]
        K2[0, 2] += d[2]
        K2[1, 2] += d[3]
        D_in = np.asarray(D, dtype=float).ravel()
        D2 = np.zeros(max(5, D_in.size))
        D2[:D_in.size] = D_in
        D2[:5] += d[4:]
        return K2, D2


def tag_location(tag_id: int) -> str:
    """The ``location`` of a tag's effect: ``tag_<id>`` (the tag frame's name)."""
    return f"tag_{int(tag_id)}"


def tag_id_of(location: str) -> int:
    """The tag id of a ``tag_offset`` location ``tag_<id>`` (or a plain id).

    Raises
    ------
    ModelConfigError
        Neither form.
    """
    text = str(location)
    body = text[4:] if text.startswith("tag_") else text
    try:
        return int(body)
    except ValueError:
        raise ModelConfigError(f"effect tag_offset: location '{location}' must be a tag frame 'tag_<id>' or a tag "
                               "id") from None


class TagOffset(Effect):
    """Correction of a tag's pose on its link: ``T_link_tag <- T_link_tag Exp(delta)``, ``delta`` a twist with the
    ``components`` of ``x y z rx ry rz`` [m, rad] (tag frame).  ``location`` = ``tag_<id>``."""

    name = "tag_offset"
    sensor = True
    all_components = TWIST_KEYS

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 components: Sequence[str] = TWIST_KEYS) -> None:
        self.tag_id = tag_id_of(location)
        location = tag_location(self.tag_id)
        self.components = check_components(self.name, location, components, TWIST_KEYS)
        self.units = tuple("m" if c in "xyz" else "rad" for c in self.components)
        super().__init__(tree, location, self.components, params)

    def basis(self, q, context=None, poses=None):
        return {}, {}

    def twist(self) -> np.ndarray:
        """``delta`` (6,) with zeros where not a component."""
        out = np.zeros(6)
        for k, v in zip(self.param_names, self.params):
            out[TWIST_KEYS.index(k)] = v
        return out

    def corrected(self, T_link_tag: np.ndarray) -> np.ndarray:
        """``T_link_tag Exp(delta)`` (4, 4)."""
        return np.asarray(T_link_tag, dtype=float) @ lie.exp(self.twist())
