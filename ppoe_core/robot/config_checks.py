"""Value checks of the model YAML reader: every error names the file, the line and the key."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, ModelConfigError, UnknownFrameError
from ppoe_core.robot.urdf import Robot
from ppoe_core.robot.yaml_io import LineDict

# ----------------------------------------------------------------------------
# YAML with line numbers
# ----------------------------------------------------------------------------


# the line-aware loader lives in ppoe_core.robot.yaml_io (the one YAML reader)


# ----------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------


class CheckContext:
    """Where we are: file + path of keys, for messages."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.effect_wheres: list[str] = []

    def at(self, obj: Any = None, key: Any = None) -> str:
        line = None
        if key is not None and isinstance(obj, LineDict):
            line = obj.key_lines.get(key)
        if line is None and obj is not None:
            line = getattr(obj, "line", None)
        return f"{self.source}:{line}" if line else self.source

    def error(self, obj: Any, key: Any, path: str, msg: str) -> ModelConfigError:
        return ModelConfigError(f"{self.at(obj, key)}: {path}: {msg}")


def kind_of(val: Any) -> str:
    """What a YAML value is, in the user's words (no internal class names such as ``LineList``)."""
    if val is None:
        return "nothing (null)"
    if isinstance(val, Mapping):
        return "a mapping"
    if isinstance(val, str):
        return f"the string {val!r}"
    if isinstance(val, (list, tuple)):
        return f"a list of {len(val)} item{'' if len(val) == 1 else 's'}"
    if isinstance(val, bool):
        return f"the boolean {val}"
    if isinstance(val, (int, float)):
        return f"the number {val}"
    return type(val).__name__


def check_mapping(ctx: CheckContext, val: Any, parent: Any, key: Any, path: str) -> Mapping:
    if not isinstance(val, Mapping):
        raise ctx.error(parent, key, path, f"must be a mapping, got {kind_of(val)}")
    return val


def check_keys(ctx: CheckContext, d: Mapping, allowed: tuple, path: str, required: tuple = ()) -> None:
    for k in d:
        if k not in allowed:
            raise ctx.error(
                d, k, path, f"unknown key '{k}' (allowed: {', '.join(allowed)})"
            )
    for k in required:
        if k not in d:
            raise ctx.error(d, None, path, f"missing required key '{k}'")


def check_number(ctx: CheckContext, val: Any, parent: Any, key: Any, path: str, minimum: float | None = None,
            positive: bool = False) -> float:
    if isinstance(val, (bool, np.bool_)) or not isinstance(val, numbers.Real):
        raise ctx.error(parent, key, path, f"must be a number, got {val!r}")
    f = float(val)
    if not math.isfinite(f):
        raise ctx.error(parent, key, path, f"must be finite, got {val!r}")
    if minimum is not None and f < minimum:
        raise ctx.error(parent, key, path, f"must be >= {minimum}, got {f}")
    if positive and f <= 0:
        raise ctx.error(parent, key, path, f"must be > 0, got {f}")
    return f


def check_vector(ctx: CheckContext, val: Any, parent: Any, key: Any, path: str, n: int,
                 minimum: float | None = None) -> np.ndarray:
    if isinstance(val, np.ndarray):
        val = val.tolist()
    if not isinstance(val, (list, tuple)) or len(val) != n:
        raise ctx.error(parent, key, path, f"must be a list of {n} numbers, got {val!r}")
    return np.array([check_number(ctx, v, parent, key, path, minimum) for v in val], dtype=float)


def check_matrix(ctx: CheckContext, val: Any, parent: Any, key: Any, path: str, n: int) -> np.ndarray:
    if isinstance(val, np.ndarray):
        val = val.tolist()
    if not isinstance(val, (list, tuple)) or len(val) != n or not all(
        isinstance(r, (list, tuple)) and len(r) == n for r in val
    ):
        raise ctx.error(parent, key, path, f"must be a {n}x{n} list of lists")
    return np.array([[check_number(ctx, v, parent, key, path) for v in r] for r in val], dtype=float)


def check_covariance_value(ctx: CheckContext, val: Any, parent: Any, key: Any, path: str, what: str) -> np.ndarray:
    C = check_matrix(ctx, val, parent, key, path, 6)
    try:
        return lie.check_covariance(C, f"{ctx.at(parent, key)}: {path} ({what})", size=6)
    except CovarianceError:
        raise
    except Exception as exc:  # pragma: no cover - defensive
        raise CovarianceError(f"{ctx.at(parent, key)}: {path} ({what}): {exc}") from None


def sigma_or_covariance(ctx: CheckContext, d: Mapping, path: str, what: str) -> np.ndarray:
    check_keys(ctx, d, ("sigma", "covariance"), path)
    if ("sigma" in d) == ("covariance" in d):
        raise ctx.error(d, None, path, "give exactly one of 'sigma' (6 numbers) or 'covariance' (6x6)")
    if "sigma" in d:
        s = check_vector(ctx, d["sigma"], d, "sigma", path + ".sigma", 6, minimum=0.0)
        return np.diag(s**2)
    return check_covariance_value(ctx, d["covariance"], d, "covariance", path + ".covariance", what)


def low_rank_factor(cov: np.ndarray, rel_tol: float = 1e-12) -> np.ndarray:
    """Factor ``L`` with ``cov = L L^T``, keeping only the non-zero directions.

    A diagonal covariance gives the scaled unit columns of its non-zero sigmas; a full one
    its eigenvectors scaled by sqrt(eigenvalue) above ``rel_tol * max eigenvalue``.

    Parameters
    ----------
    cov : ndarray, shape (n, n)
        Symmetric positive semi-definite covariance (already validated), e.g. a joint's
        perturbation covariance in the tangent space at the joint origin (eq. 16).
    rel_tol : float
        Eigenvalues at or below ``rel_tol`` times the largest one are dropped.

    Returns
    -------
    ndarray, shape (n, r)
        ``r`` = number of kept directions (0 for a zero covariance); columns live in the same
        tangent space as ``cov``.
    """
    cov = np.asarray(cov, dtype=float)
    n = cov.shape[0]
    if np.count_nonzero(cov - np.diag(np.diag(cov))) == 0:
        d = np.diag(cov)
        idx = np.flatnonzero(d > 0)
        L = np.zeros((n, idx.size))
        L[idx, np.arange(idx.size)] = np.sqrt(d[idx])
        return L
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    keep = w > rel_tol * max(float(w.max()), 0.0)
    return V[:, keep] * np.sqrt(w[keep])


def check_link_name(ctx: CheckContext, robot: Robot | None, val: Any, parent: Any, key: Any, path: str) -> str:
    """A link name; checked against ``robot`` unless it is None (no URDF at hand)."""
    if not isinstance(val, str):
        raise ctx.error(parent, key, path, f"must be a link name, got {val!r}")
    if robot is not None and val not in robot.links:
        raise UnknownFrameError(
            f"{ctx.at(parent, key)}: {path}: unknown link '{val}' (not in URDF {robot.source})"
        )
    return val


def check_pose_entry(ctx: CheckContext, d: Mapping, path: str) -> np.ndarray:
    xyz = check_vector(ctx, d["xyz"], d, "xyz", path + ".xyz", 3) if "xyz" in d else np.zeros(3)
    rpy = check_vector(ctx, d["rpy"], d, "rpy", path + ".rpy", 3) if "rpy" in d else np.zeros(3)
    return lie.from_xyz_rpy(xyz, rpy)
