"""Confidence ellipsoids of position covariances (ppoe_core/lie/ellipsoid.py): geometry and a Monte-Carlo check."""

from __future__ import annotations

import numpy as np
import pytest

from ppoe_core import lie
from ppoe_core.errors import CovarianceError
from ppoe_core.lie.ellipsoid import (
    ellipsoid_surface,
    position_covariance_from_local,
    position_ellipsoid,
    sigma_scale,
)


def _random_cov(rng: np.random.Generator, *batch: int) -> np.ndarray:
    A = rng.normal(size=(*batch, 3, 3)) * np.array([3e-3, 1e-3, 2e-4])
    return A @ np.swapaxes(A, -1, -2) + 1e-10 * np.eye(3)


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
def test_axes_radii_and_quaternion_reproduce_the_covariance(batch: tuple[int, ...]) -> None:
    rng = np.random.default_rng(1)
    P = _random_cov(rng, *batch)
    c = rng.normal(size=(*batch, 3))
    e = position_ellipsoid(c, P, k=2.0)
    assert e.center.shape == (*batch, 3) and e.rotation.shape == (*batch, 3, 3) and e.quat_xyzw.shape == (*batch, 4)
    R = e.rotation
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert np.all(np.diff(e.radii, axis=-1) <= 0)  # largest first
    rebuilt = R @ (((e.radii / 2.0) ** 2)[..., None] * np.swapaxes(R, -1, -2))
    np.testing.assert_allclose(rebuilt, P, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(lie.matrix_from_quat(e.quat_xyzw), R, atol=1e-12)
    np.testing.assert_allclose(e.scale, 2.0 * e.radii)


def test_monte_carlo_probability_inside() -> None:
    """Seeded Monte-Carlo: the fraction of N(c, P) samples inside the sigma_scale(p) ellipsoid is p."""
    rng = np.random.default_rng(7)
    P = _random_cov(rng)
    c = np.array([0.4, -0.2, 1.1])
    for prob in (0.199, 0.95, 0.997):
        e = position_ellipsoid(c, P, k=sigma_scale(prob))
        x = rng.multivariate_normal(c, P, size=200_000)
        y = (x - e.center) @ e.rotation / e.radii
        inside = np.mean(np.sum(y**2, axis=1) <= 1.0)
        assert abs(inside - prob) < 4 * np.sqrt(prob * (1 - prob) / 200_000) + 1e-4, (prob, inside)
    from scipy.stats import chi2

    assert sigma_scale(float(chi2.cdf(1.0, 3))) == pytest.approx(1.0, abs=1e-9)
    assert sigma_scale(0.95) == pytest.approx(2.7955, abs=1e-4)
    with pytest.raises(ValueError):
        sigma_scale(1.0)


def test_surface_lies_on_the_ellipsoid_and_degenerate_covariances() -> None:
    rng = np.random.default_rng(3)
    P = _random_cov(rng)
    e = position_ellipsoid(np.zeros(3), P, k=3.0)
    pts = ellipsoid_surface(e, n=12).reshape(-1, 3)
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", pts, np.linalg.inv(P), pts), 9.0, rtol=1e-9)
    flat = position_ellipsoid(np.zeros(3), np.diag([4e-6, 1e-6, 0.0]))
    np.testing.assert_allclose(flat.radii, [2e-3, 1e-3, 0.0], atol=1e-15)
    zero = position_ellipsoid(np.ones(3), np.zeros((3, 3)))
    assert np.all(zero.radii == 0) and np.allclose(np.linalg.det(zero.rotation), 1.0)
    with pytest.raises(CovarianceError, match="positive semi-definite"):
        position_ellipsoid(np.zeros(3), np.diag([1e-6, -1e-6, 1e-6]))
    with pytest.raises(CovarianceError, match="symmetric"):
        position_ellipsoid(np.zeros(3), np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]))
    with pytest.raises(CovarianceError, match=r"\(\.\.\., 3, 3\)"):
        position_ellipsoid(np.zeros(3), np.eye(2))


def test_position_block_from_a_local_covariance_is_the_ros_one() -> None:
    rng = np.random.default_rng(5)
    T = lie.exp(rng.normal(size=6))
    A = rng.normal(size=(6, 6)) * 1e-3
    S = A @ A.T
    np.testing.assert_allclose(position_covariance_from_local(T, S), lie.cov_local_to_ros(T, S)[:3, :3],
                               rtol=1e-12, atol=1e-20)
