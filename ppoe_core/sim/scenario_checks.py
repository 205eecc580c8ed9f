"""Checks of a simulation scenario file's values: each error names the file and the key (``scenario <path>:
<key>``), as :class:`~ppoe_core.errors.ScenarioError`.  Used by :mod:`ppoe_core.sim.scenario`,
:mod:`ppoe_core.sim.sim_config`, :mod:`ppoe_core.sim.simulate` and :mod:`ppoe_core.sim.camera_sim`."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import ScenarioError
from ppoe_core.robot.urdf import Robot

__all__ = ["key_location", "check_keys", "check_number", "check_joint_values", "check_pose"]


def key_location(path: str, key: str) -> str:
    """Where a value is, for errors: ``scenario <path>: <key>``."""
    return f"scenario {path}: {key}"


def check_keys(d: Any, allowed: Sequence[str], path: str, key: str) -> dict:
    """The section ``key`` as a dict ({} for None); :class:`ScenarioError` if it is not a mapping or has a key not in
    ``allowed``."""
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ScenarioError(f"{key_location(path, key)} must be a mapping, got {type(d).__name__}")
    bad = sorted(set(d) - set(allowed))
    if bad:
        raise ScenarioError(f"{key_location(path, key)}: unknown keys {bad} (allowed: {list(allowed)})")
    return dict(d)


def check_number(
    d: Mapping, k: str, default: Any, path: str, key: str, minimum: float | None = None, maximum: float | None = None
) -> Any:
    """``d[k]`` (``default`` if absent) as a finite float in [``minimum``, ``maximum``], None if it is None;
    :class:`ScenarioError` naming ``key.k`` otherwise."""
    v = d.get(k, default)
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ScenarioError(f"{key_location(path, key + '.' + k)} must be a number, got {v!r}") from None
    if not math.isfinite(f) or (minimum is not None and f < minimum) or (maximum is not None and f > maximum):
        raise ScenarioError(f"{key_location(path, key + '.' + k)} = {v!r} out of range [{minimum}, {maximum}]")
    return f


def check_joint_values(d: Any, path: str, key: str, robot: Robot) -> dict[str, float]:
    """The mapping ``key`` of movable joint names of ``robot`` to finite values ({} for None)."""
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ScenarioError(f"{key_location(path, key)} must map joint names to values")
    out = {}
    for name, v in d.items():
        if name not in robot.joints or not robot.joints[name].movable:
            raise ScenarioError(f"{key_location(path, key)}: '{name}' is not a movable joint of {robot.source}")
        try:
            out[str(name)] = float(v)
        except (TypeError, ValueError):
            raise ScenarioError(f"{key_location(path, key + '.' + str(name))} must be a number, got {v!r}") from None
        if not math.isfinite(out[str(name)]):
            raise ScenarioError(f"{key_location(path, key + '.' + str(name))} must be finite, got {v!r}")
    return out


def check_pose(d: Any, path: str, key: str) -> np.ndarray:
    """The pose entry ``key`` (``xyz`` [m], ``rpy`` [rad], optional ``frame``) as a (4, 4) transform."""
    d = check_keys(d, ("xyz", "rpy", "frame"), path, key)
    try:
        xyz = np.asarray(d.get("xyz", [0, 0, 0]), dtype=float).reshape(3)
        rpy = np.asarray(d.get("rpy", [0, 0, 0]), dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise ScenarioError(f"{key_location(path, key)}: xyz and rpy must be 3 numbers each") from None
    return lie.from_xyz_rpy(xyz, rpy)
