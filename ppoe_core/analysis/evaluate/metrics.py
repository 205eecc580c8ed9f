"""Error metrics of ``ppoe evaluate``: position/rotation errors, their statistics, NEES of a pose or point
covariance."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import CovarianceError

#: scored methods, in report order
METHODS = ("fk", "ppoe", "naive", "recorded")
#: diagonal regularisation [m^2 / rad^2] of covariances before NEES: a model with exact joints
#: gives a singular FK covariance (a direction it is certain of), still scored
_NEES_JITTER = 1e-12


def error_stats(values: np.ndarray) -> dict[str, float]:
    """``mean``, ``std`` (population), ``rms``, ``median``, ``p95``, ``max`` and ``n`` of non-NaN values (NaN if
    none)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size == 0:
        nan = float("nan")
        return {"mean": nan, "std": nan, "rms": nan, "median": nan, "p95": nan, "max": nan, "n": 0}
    return {
        "mean": float(np.mean(v)),
        "std": float(np.std(v)),
        "rms": float(np.sqrt(np.mean(v * v))),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(np.max(v)),
        "n": int(v.size),
    }


def position_errors(p_est: np.ndarray, p_gt: np.ndarray, z_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3D and lateral position errors.

    Parameters
    ----------
    p_est, p_gt : ndarray, shape (n, 3)
        Estimated and true positions in the base frame [m].
    z_axis : ndarray, shape (n, 3)
        Unit tool z axis in the base frame (the direction that does not count as lateral).

    Returns
    -------
    (e3d, elat) : ndarray, shape (n,) each
        ``|e|`` and ``|e - (e . z) z|`` with ``e = p_est - p_gt`` [m].
    """
    e = np.asarray(p_est, float) - np.asarray(p_gt, float)
    z = np.asarray(z_axis, float)
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    lat = e - np.sum(e * z, axis=-1, keepdims=True) * z
    return np.linalg.norm(e, axis=-1), np.linalg.norm(lat, axis=-1)


def rotation_errors(T_est: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """Rotation angle of ``R_est^T R_gt`` [rad], shape (n,)."""
    R = np.swapaxes(np.asarray(T_est)[..., :3, :3], -1, -2) @ np.asarray(T_gt)[..., :3, :3]
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(c)


def point_covariance(T_base_tool: np.ndarray, cov_tool: np.ndarray, p_tool: np.ndarray) -> np.ndarray:
    """Covariance of ``p_base = T_base_tool p_tool`` from the pose covariance.

    Parameters
    ----------
    T_base_tool : ndarray, shape (n, 4, 4)
    cov_tool : ndarray, shape (n, 6, 6)
        In the tangent space at ``T_base_tool`` (tool frame, right perturbation).
    p_tool : ndarray, shape (n, 3)
        The point in tool coordinates [m].

    Returns
    -------
    ndarray, shape (n, 3, 3)
        In base-frame axes [m^2]: ``J cov J^T`` with ``J = R [I, -[p]x]`` (first order).
    """
    R = np.asarray(T_base_tool)[..., :3, :3]
    J = np.concatenate([R, -R @ lie.hat3(np.asarray(p_tool, float))], axis=-1)
    return J @ np.asarray(cov_tool) @ np.swapaxes(J, -1, -2)


def regularised(cov: np.ndarray) -> np.ndarray:
    """``cov`` (..., n, n) symmetrised, plus ``_NEES_JITTER`` on the diagonal (same frame)."""
    return 0.5 * (cov + np.swapaxes(cov, -1, -2)) + _NEES_JITTER * np.eye(cov.shape[-1])


def nees_named(compute: Callable[[], np.ndarray], bag: str | Path, method: str) -> np.ndarray:
    """NEES samples from ``ppoe_core.estimation.fusion``; a covariance that is not positive definite is an
    error naming the bag and the method (not a numpy traceback)."""
    try:
        return compute()
    except CovarianceError as exc:
        raise CovarianceError(f"bag {bag}: method {method}: {exc}") from None


def nees_stats(nees: np.ndarray, dof: int) -> dict[str, Any]:
    """Mean NEES with its two-sided 95 % chi-square bounds and the fraction inside per sample.

    For ``n`` samples of a consistent estimator ``n * mean`` is chi-square with ``n * dof``
    degrees of freedom; a single sample lies in ``[chi2(0.025, dof), chi2(0.975, dof)]``
    with 95 % probability.
    """
    import scipy.stats

    v = np.asarray(nees, float)
    v = v[np.isfinite(v)]
    n = int(v.size)
    if n == 0:
        return {
            "mean": float("nan"),
            "dof": dof,
            "n": 0,
            "bounds95": [float("nan")] * 2,
            "fraction_inside": float("nan"),
        }
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], n * dof) / n
    slo, shi = scipy.stats.chi2.ppf([0.025, 0.975], dof)
    return {
        "mean": float(np.mean(v)),
        "median": float(np.median(v)),
        "dof": dof,
        "n": n,
        "bounds95": [float(lo), float(hi)],
        "fraction_inside": float(np.mean((v >= slo) & (v <= shi))),
    }
