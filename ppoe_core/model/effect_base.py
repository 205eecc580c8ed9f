"""The base of every catalogued effect: parameters, the eq. 16 corrections and their exact basis.

Every effect is a small physical parametrisation that changes the kinematic chain through the two hooks of paper
eq. 16, ``Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))``:

* ``dq``: an offset added to a joint value (for a mimic master it propagates through the mimic multiplier), and
* ``dxi``: a non-zero-mean twist ``[rho; theta]`` placed right after a joint's static origin ``p_i``, where the
  joint's perturbation ``xi_i`` sits,

or, for a *sensor* effect (:attr:`Effect.sensor` true: camera intrinsics, a tag's pose on its link), the model of
the sensor that measures the chain; those have no chain corrections (their :meth:`Effect.basis` is empty) and
their Jacobians belong to the measurement that uses them.

All catalogued effects are *linear in their parameters*: ``corrections(q, context)`` is ``basis(q, context) @
params``, where :meth:`Effect.basis` gives the exact analytic derivative of the corrections with respect to the
parameters (the chain part follows with :meth:`KinematicTree.frame_jacobian` /
:meth:`KinematicTree.point_jacobian`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core.errors import ModelConfigError, UnknownJointError
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Effect", "Corrections", "TWIST_KEYS", "batch_shape", "check_joint", "sum_effect_corrections"]

#: twist components of ``link_error``, ``camera_extrinsics``, ``tag_offset``: ``[rho; theta]`` [m, rad]
TWIST_KEYS = ("x", "y", "z", "rx", "ry", "rz")

Corrections = tuple[dict[str, np.ndarray], dict[str, np.ndarray]]


def batch_shape(q: Mapping[str, Any]) -> tuple[int, ...]:
    """The broadcast batch shape of joint values ``q`` (``()`` for scalars or no joints)."""
    return np.broadcast_shapes(*[np.shape(v) for v in q.values()]) if q else ()


class Effect:
    """One systematic effect: parameters, corrections (eq. 16 hooks) and their Jacobian.

    Attributes
    ----------
    name : str
        Contract vocabulary name.
    location : str
        URDF joint or link, topic, sensor frame or tag.
    param_names : tuple[str, ...]
    params : ndarray, shape (P,)
    units : tuple[str, ...]
    """

    name = ""
    units: tuple[str, ...] = ()
    #: parameters that are physically non-negative (a compliance yields along the load)
    nonnegative: tuple[str, ...] = ()
    context_keys: tuple[str, ...] = ()  #: context it cannot do without (``ppoe_core.model.context``)
    #: a sensor model (camera intrinsics, tag pose) rather than a chain correction: no :meth:`basis` terms
    sensor = False
    #: the parameters in catalogue order (an effect with ``components`` may use a subset)
    all_components: tuple[str, ...] = ()

    def __init__(self, tree: KinematicTree, location: str, param_names: Sequence[str],
                 params: Sequence[float] | None = None) -> None:
        self.tree = tree
        self.location = location
        self.param_names = tuple(param_names)
        p = np.zeros(len(self.param_names)) if params is None else np.asarray(params, dtype=float)
        if p.shape != (len(self.param_names),):
            raise ModelConfigError(f"effect {self.name} at '{location}': expected "
                                   f"{len(self.param_names)} parameters, got shape {p.shape}")
        self.params = p

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def key(self) -> str:
        """``name@location`` plus the components when they are a subset (e.g. ``link_error@j3[x,rz]``)."""
        full = tuple(self.all_components) if self.all_components else self.param_names
        comps = "" if self.param_names == full else "[" + ",".join(self.param_names) + "]"
        return f"{self.name}@{self.location}{comps}"

    def options(self) -> dict[str, Any]:
        """Constructor options besides the parameters (``components``, ``variable``, ``reference``)."""
        out: dict[str, Any] = {}
        if self.all_components and self.param_names != tuple(self.all_components):
            out["components"] = self.param_names
        for key in ("variable", "reference"):
            if getattr(self, key, None) is not None:
                out[key] = getattr(self, key)
        return out

    def with_params(self, params: Sequence[float] | np.ndarray) -> Effect:
        """A copy with other parameter values."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.params = np.asarray(params, dtype=float).copy()
        return new

    def basis(self, q: Mapping[str, Any], context: Mapping[str, Any] | None = None,
              poses: Mapping[str, np.ndarray] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Exact derivative of the corrections w.r.t. the parameters.

        Returns
        -------
        dq_basis : dict joint -> ndarray (..., P)
        dxi_basis : dict joint -> ndarray (..., 6, P)
        """
        raise NotImplementedError

    def corrections(self, q: Mapping[str, Any], context: Mapping[str, Any] | None = None,
                    poses: Mapping[str, np.ndarray] | None = None) -> Corrections:
        """``(dq: joint -> (...), dxi: joint -> (..., 6))`` at joint values ``q`` (eq. 16)."""
        Bq, Bx = self.basis(q, context or {}, poses)
        return ({k: v @ self.params for k, v in Bq.items()},
                {k: v @ self.params for k, v in Bx.items()})

    def point_jacobian(self, q: Mapping[str, Any], link: str, point: Any,
                       context: Mapping[str, Any] | None = None) -> np.ndarray:
        """Derivative ``(..., 3, P)`` of the root-frame position of ``point`` on ``link``
        w.r.t. this effect's parameters (analytic: chain Jacobian at the corrected chain times
        :meth:`basis`, which is evaluated on the nominal chain)."""
        nominal = self.tree.link_poses(q)
        Bq, Bx = self.basis(q, context or {}, nominal)
        dq = {k: v @ self.params for k, v in Bq.items()}
        dxi = {k: v @ self.params for k, v in Bx.items()}
        Jq, Jx = self.tree.point_jacobian(q, link, point, None, dq, dxi)
        out = np.zeros(batch_shape(q) + (3, self.n_params))
        for k, b in Bq.items():
            if k in Jq:
                out = out + Jq[k][..., :, None] * b[..., None, :]
        for k, b in Bx.items():
            if k in Jx:
                out = out + Jx[k] @ b
        return out

    def to_config(self, ci: Sequence[float] | None = None) -> dict[str, Any]:
        """YAML entry ``{name, location, parameters[, ci]}`` (floats, for the model file)."""
        out: dict[str, Any] = {"name": self.name, "location": self.location,
                               "parameters": {k: float(v) for k, v in zip(self.param_names, self.params)}}
        for key in ("variable", "reference"):  # what a context-driven effect is driven by (thermal, base tilt)
            if getattr(self, key, None) is not None:
                out[key] = getattr(self, key)
        if ci is not None:
            out["ci"] = {k: float(v) for k, v in zip(self.param_names, ci)}
        return out

    def describe(self) -> str:
        return f"{self.name}@{self.location}"

    def __repr__(self) -> str:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in zip(self.param_names, self.params))
        return f"{type(self).__name__}({self.location!r}, {ps})"


def check_joint(tree: KinematicTree, joint: str, effect: str, movable: bool = False) -> None:
    """``joint`` must be a joint of the tree's URDF (and movable if asked).

    Raises
    ------
    UnknownJointError, ModelConfigError
        Naming the effect, the location and the URDF.
    """
    if joint not in tree.robot.joints:
        raise UnknownJointError(f"effect {effect}: location '{joint}' is not a joint of URDF "
                                f"{tree.robot.source}")
    if movable and not tree.robot.joints[joint].movable:
        raise ModelConfigError(f"effect {effect}: location '{joint}' is a "
                               f"{tree.robot.joints[joint].type} joint; it must be movable")


def check_components(effect: str, location: str, components: Sequence[str], allowed: Sequence[str]) -> tuple[str, ...]:
    """``components`` as a tuple in catalogue order; a non-empty subset of ``allowed`` or a ModelConfigError."""
    comps = tuple(components)
    if not comps or any(c not in allowed for c in comps) or len(set(comps)) != len(comps):
        raise ModelConfigError(f"effect {effect} at '{location}': components {list(comps)} must be a non-empty "
                               f"subset of {list(allowed)}")
    return tuple(c for c in allowed if c in comps)


def sum_effect_corrections(effects: Sequence[Effect], q: Mapping[str, Any],
                           context: Mapping[str, Any] | None = None,
                           poses: Mapping[str, np.ndarray] | None = None,
                           start: Corrections | None = None) -> Corrections:
    """Sum the corrections of several effects: ``(dq, dxi)`` dictionaries (eq. 16 hooks), added to ``start``'s.
    Sensor effects (:attr:`Effect.sensor`) add nothing."""
    dq: dict[str, np.ndarray] = dict(start[0]) if start else {}
    dxi: dict[str, np.ndarray] = dict(start[1]) if start else {}
    for eff in effects:
        if eff.sensor:
            continue
        a, b = eff.corrections(q, context or {}, poses)
        for k, v in a.items():
            dq[k] = dq.get(k, 0.0) + v
        for k, v in b.items():
            dxi[k] = dxi.get(k, 0.0) + v
    return dq, dxi
