"""Effects that read a context beyond the joint values (``ppoe_core.model.context``): backlash (the sign of each
joint's last motion), thermal growth (temperature or time) and a sensor's time offset (joint velocities)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core.errors import ModelConfigError
from ppoe_core.model.effect_base import Effect, batch_shape, check_joint
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Backlash", "ThermalGrowth", "TimeOffset"]


class Backlash(Effect):
    """Backlash: ``dq_j = play * sign(last motion of j)`` (context ``motion_sign``)."""

    name = "backlash"
    units = ("rad or m",)
    context_keys = ("motion_sign",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        check_joint(tree, location, self.name, movable=True)
        super().__init__(tree, location, ("play",), params)

    def basis(self, q, context=None, poses=None):
        signs = (context or {}).get("motion_sign")
        if signs is None or self.location not in signs:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context "
                                   f"'motion_sign' for joint '{self.location}'")
        s = np.broadcast_to(np.asarray(signs[self.location], dtype=float), batch_shape(q))
        return {self.location: s[..., None]}, {}


class ThermalGrowth(Effect):
    """Length change of the link before a joint: ``rho = alpha (u - reference) R_p^T t_p``.

    ``u`` is context ``variable`` (``temperature`` or ``time``); ``t_p, R_p`` the joint origin.
    """

    name = "thermal_growth"
    units = ("1/unit of variable",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None,
                 variable: str = "temperature", reference: float = 0.0) -> None:
        check_joint(tree, location, self.name)
        if variable not in ("temperature", "time"):
            raise ModelConfigError(f"effect {self.name} at '{location}': variable must be "
                                   f"'temperature' or 'time', got {variable!r}")
        self.variable, self.reference, self.context_keys = variable, float(reference), (variable,)
        super().__init__(tree, location, ("alpha",), params)

    def basis(self, q, context=None, poses=None):
        u = (context or {}).get(self.variable)
        if u is None:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context "
                                   f"'{self.variable}'")
        o = self.tree.robot.joints[self.location].origin
        d = o[:3, :3].T @ o[:3, 3]
        du = np.broadcast_to(np.asarray(u, dtype=float) - self.reference, batch_shape(q))
        B = np.zeros(du.shape + (6, 1))
        B[..., :3, 0] = du[..., None] * d
        return {}, {self.location: B}


class TimeOffset(Effect):
    """Time offset of the joint states w.r.t. a sensor: ``dq_j = dt * qdot_j`` for every joint.

    With context ``sensor`` (the sensor of each row, e.g. a camera frame), only the rows of the sensor named
    by ``location`` are shifted: each camera or tracker stream has its own offset.
    """

    name = "time_offset"
    units = ("s",)
    context_keys = ("joint_velocity",)

    def __init__(self, tree: KinematicTree, location: str, params: Sequence[float] | None = None) -> None:
        super().__init__(tree, location, ("dt",), params)

    def basis(self, q, context=None, poses=None):
        vel = (context or {}).get("joint_velocity")
        if vel is None:
            raise ModelConfigError(f"effect {self.name} at '{self.location}' needs context 'joint_velocity'")
        b = batch_shape(q)
        sensor = (context or {}).get("sensor")
        mask = 1.0 if sensor is None else (np.asarray(sensor) == self.location).astype(float)
        return {k: np.broadcast_to(np.asarray(v, dtype=float) * mask, b)[..., None]
                for k, v in vel.items() if k in q}, {}
