"""Tests of ppoe_core.lie: group axioms, Exp/Log round trips over batch shapes and
near-identity / near-pi inputs, Jacobians against central finite differences,
the adjoint identity and the ROS covariance convention."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays
from jacobian_check import numerical_jacobian

import lie_reference as ref

from ppoe_core import lie
from ppoe_core.errors import CovarianceError

FINITE = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
SETTINGS = settings(max_examples=60, deadline=None)


def batch_twists(max_angle: float = 3.0):
    """Twists of random batch shape; rotation angle below ``max_angle``."""
    return arrays(
        np.float64, array_shapes(min_dims=1, max_dims=3, max_side=4).map(lambda s: s + (6,)), elements=FINITE
    ).map(lambda xi: _clip_angle(xi, max_angle))


def _clip_angle(xi: np.ndarray, max_angle: float) -> np.ndarray:
    xi = xi.copy()
    n = np.linalg.norm(xi[..., 3:], axis=-1, keepdims=True)
    xi[..., 3:] *= np.minimum(1.0, max_angle / np.maximum(n, 1e-300))
    return xi


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------
# hat / vee and round trips
# ---------------------------------------------------------------------------


@SETTINGS
@given(batch_twists())
def test_hat_vee_round_trip(xi):
    assert np.allclose(lie.vee(lie.hat(xi)), xi)
    assert lie.hat(xi).shape == xi.shape[:-1] + (4, 4)


@SETTINGS
@given(batch_twists(max_angle=3.1))
def test_exp_log_round_trip_batched(xi):
    T = lie.exp(xi)
    assert T.shape == xi.shape[:-1] + (4, 4)
    R = T[..., :3, :3]
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(lie.log(T), xi, atol=1e-9)


@SETTINGS
@given(
    arrays(np.float64, (3,), elements=st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 1e-3), st.floats(-12, -3)
)
def test_near_identity_round_trip(axis, log_angle):
    w = unit(axis) * 10.0**log_angle
    xi = np.concatenate([np.array([0.3, -0.2, 0.1]), w])
    assert np.allclose(lie.log(lie.exp(xi)), xi, rtol=1e-9, atol=1e-15)
    # exp of a small rotation equals its second-order expansion up to O(angle^3)
    R = lie.so3_exp(w)
    W = lie.hat3(w)
    assert np.allclose(R, np.eye(3) + W + 0.5 * W @ W, atol=10.0 ** (3 * log_angle) + 1e-15)


@SETTINGS
@given(
    arrays(np.float64, (3,), elements=st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 1e-3), st.floats(-10, -2)
)
def test_near_pi_round_trip(axis, log_gap):
    angle = np.pi - 10.0**log_gap
    w = unit(axis) * angle
    R = lie.so3_exp(w)
    w_back = lie.so3_log(R)
    assert np.allclose(lie.so3_exp(w_back), R, atol=1e-12)
    assert np.allclose(w_back, w, atol=1e-7)
    xi = np.concatenate([np.array([0.1, 0.2, 0.3]), w])
    assert np.allclose(lie.exp(lie.log(lie.exp(xi))), lie.exp(xi), atol=1e-9)


def test_log_at_exactly_pi_and_zero():
    for axis in np.eye(3):
        R = lie.so3_exp(np.pi * axis)
        w = lie.so3_log(R)
        assert np.isclose(np.linalg.norm(w), np.pi)
        assert np.allclose(np.abs(w), np.pi * axis, atol=1e-12)
    assert np.array_equal(lie.so3_log(np.eye(3)), np.zeros(3))
    assert np.allclose(lie.log(np.eye(4)), 0.0)


# ---------------------------------------------------------------------------
# group axioms
# ---------------------------------------------------------------------------


@SETTINGS
@given(batch_twists(), st.integers(0, 2**31 - 1))
def test_group_axioms(xi, seed):
    rng = np.random.default_rng(seed)
    A = lie.exp(xi)
    B = lie.exp(rng.normal(size=xi.shape))
    C = lie.exp(rng.normal(size=xi.shape))
    eye = np.broadcast_to(np.eye(4), A.shape)
    assert np.allclose(lie.compose(A, lie.inverse(A)), eye, atol=1e-12)
    assert np.allclose(lie.compose(lie.inverse(A), A), eye, atol=1e-12)
    assert np.allclose(lie.compose(lie.compose(A, B), C), lie.compose(A, lie.compose(B, C)), atol=1e-10)
    assert np.allclose(lie.inverse(A @ B), lie.inverse(B) @ lie.inverse(A), atol=1e-12)
    # exp(-xi) is the inverse of exp(xi)
    assert np.allclose(lie.exp(-xi), lie.inverse(A), atol=1e-12)


@SETTINGS
@given(batch_twists(), st.integers(0, 2**31 - 1))
def test_adjoint_identity(xi, seed):
    """T Exp(x) T^-1 = Exp(Ad_T x) (paper eq. 5-6) and Ad is a homomorphism."""
    rng = np.random.default_rng(seed)
    T = lie.exp(xi)
    x = 0.5 * rng.normal(size=xi.shape)
    lhs = T @ lie.exp(x) @ lie.inverse(T)
    rhs = lie.exp(np.einsum("...ij,...j->...i", lie.adjoint(T), x))
    assert np.allclose(lhs, rhs, atol=1e-9)
    U = lie.exp(rng.normal(size=xi.shape))
    assert np.allclose(lie.adjoint(T @ U), lie.adjoint(T) @ lie.adjoint(U), atol=1e-9)
    assert np.allclose(lie.adjoint(lie.inverse(T)), np.linalg.inv(lie.adjoint(T)), atol=1e-8)
    # curly hat is the derivative of the adjoint: ad(x) y = -ad(y) x
    y = rng.normal(size=xi.shape)
    assert np.allclose(
        np.einsum("...ij,...j->...i", lie.curly_hat(x), y),
        -np.einsum("...ij,...j->...i", lie.curly_hat(y), x),
    )


def test_curly_hat_is_derivative_of_adjoint():
    rng = np.random.default_rng(3)
    x = rng.normal(size=6)
    num = numerical_jacobian(lambda e: lie.adjoint(lie.exp(e[0] * x)).ravel(), np.zeros(1), eps=1e-6)[:, 0]
    assert np.allclose(num.reshape(6, 6), lie.curly_hat(x), atol=1e-8)


# ---------------------------------------------------------------------------
# Jacobians against central finite differences
# ---------------------------------------------------------------------------

JAC_CASES = [
    np.array([0.3, -0.5, 0.2, 0.4, -0.7, 0.9]),
    np.array([1.0, 2.0, -1.0, 1e-7, -2e-7, 5e-8]),  # near identity rotation
    np.concatenate([[0.2, 0.1, -0.3], unit(np.array([1.0, -2.0, 0.5])) * (np.pi - 1e-3)]),  # near pi
    np.zeros(6),
]


@pytest.mark.parametrize("xi", JAC_CASES)
def test_right_jacobian_fd(xi):
    """Log(Exp(xi)^-1 Exp(xi + d)) ~= J_r(xi) d."""
    num = numerical_jacobian(lambda x: lie.ominus(lie.exp(x), lie.exp(xi)), xi)
    assert np.allclose(num, lie.right_jacobian(xi), atol=1e-7)
    assert np.allclose(lie.right_jacobian_inv(xi) @ lie.right_jacobian(xi), np.eye(6), atol=1e-9)


@pytest.mark.parametrize("xi", JAC_CASES)
def test_left_jacobian_fd(xi):
    """Log(Exp(xi + d) Exp(xi)^-1) ~= J_l(xi) d."""
    num = numerical_jacobian(lambda x: lie.log(lie.exp(x) @ lie.inverse(lie.exp(xi))), xi)
    assert np.allclose(num, lie.left_jacobian(xi), atol=1e-7)
    assert np.allclose(lie.left_jacobian_inv(xi) @ lie.left_jacobian(xi), np.eye(6), atol=1e-9)


@pytest.mark.parametrize("xi", JAC_CASES)
def test_right_jacobian_inverse_is_log_derivative(xi):
    """Log(Exp(xi) Exp(d)) ~= xi + J_r^-1(xi) d."""
    num = numerical_jacobian(lambda d: lie.log(lie.exp(xi) @ lie.exp(d)), np.zeros(6))
    assert np.allclose(num, lie.right_jacobian_inv(xi), atol=1e-6)


@pytest.mark.parametrize("w", [np.array([0.3, -1.2, 0.7]), np.array([1e-8, 0.0, -3e-8]), unit(np.ones(3)) * 3.0])
def test_so3_jacobians_fd(w):
    num = numerical_jacobian(lambda x: lie.so3_log(lie.so3_exp(w).T @ lie.so3_exp(x)), w)
    assert np.allclose(num, lie.so3_right_jacobian(w), atol=1e-7)
    assert np.allclose(lie.so3_right_jacobian_inv(w) @ lie.so3_right_jacobian(w), np.eye(3), atol=1e-9)
    assert np.allclose(lie.so3_left_jacobian_inv(w) @ lie.so3_left_jacobian(w), np.eye(3), atol=1e-9)


def test_jacobians_batched_match_single():
    rng = np.random.default_rng(1)
    xi = rng.normal(size=(3, 2, 6))
    for f in (lie.left_jacobian, lie.right_jacobian, lie.left_jacobian_inv, lie.right_jacobian_inv):
        out = f(xi)
        assert out.shape == (3, 2, 6, 6)
        assert np.allclose(out[2, 1], f(xi[2, 1]))


# ---------------------------------------------------------------------------
# conversions
# ---------------------------------------------------------------------------


@SETTINGS
@given(arrays(np.float64, (4, 3), elements=st.floats(-3.1, 3.1)))
def test_rpy_and_quaternion_round_trip(rpy):
    rpy[:, 1] = np.clip(rpy[:, 1], -1.5, 1.5)
    R = lie.matrix_from_rpy(rpy)
    assert np.allclose(lie.matrix_from_rpy(lie.rpy_from_matrix(R)), R, atol=1e-10)
    q = lie.quat_from_matrix(R)
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0)
    assert np.allclose(lie.matrix_from_quat(q), R, atol=1e-12)


def test_urdf_rpy_convention():
    """URDF rpy is fixed-axis XYZ: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = 0.1, -0.4, 1.2
    Rx = lie.so3_exp([r, 0, 0])
    Ry = lie.so3_exp([0, p, 0])
    Rz = lie.so3_exp([0, 0, y])
    assert np.allclose(lie.matrix_from_rpy([r, p, y]), Rz @ Ry @ Rx)
    T = lie.from_xyz_rpy([1, 2, 3], [r, p, y])
    assert np.allclose(T[:3, 3], [1, 2, 3])


def test_interpolate_endpoints_and_midpoint():
    rng = np.random.default_rng(2)
    T0, T1 = lie.exp(rng.normal(size=6)), lie.exp(rng.normal(size=6))
    assert np.allclose(lie.interpolate(T0, T1, 0.0), T0)
    assert np.allclose(lie.interpolate(T0, T1, 1.0), T1, atol=1e-10)
    mid = lie.interpolate(T0, T1, 0.5)
    assert np.allclose(lie.ominus(mid, T0), 0.5 * lie.ominus(T1, T0), atol=1e-10)
    assert lie.interpolate(T0, T1, np.array([0.0, 0.5, 1.0])).shape == (3, 4, 4)


def test_ros_covariance_convention_monte_carlo():
    """cov_ros = B S B^T is the covariance of (t - t_bar, rotation vector in parent axes)."""
    rng = np.random.default_rng(7)
    T = lie.exp(np.array([1.0, -2.0, 0.5, 0.4, 1.1, -0.3]))
    L = rng.normal(size=(6, 6)) * 0.01
    S = L @ L.T
    xi = rng.multivariate_normal(np.zeros(6), S, size=200_000)
    Ts = T @ lie.exp(xi)
    dt = Ts[:, :3, 3] - T[:3, 3]
    dth = lie.so3_log(Ts[:, :3, :3] @ T[:3, :3].T)  # rotation in parent axes
    emp = np.cov(np.concatenate([dt, dth], axis=1).T)
    ros = lie.cov_local_to_ros(T, S)
    assert np.linalg.norm(emp - ros) / np.linalg.norm(ros) < 0.03
    # and it is NOT Ad S Ad^T when the translation is large
    ad = lie.adjoint(T) @ S @ lie.adjoint(T).T
    assert np.linalg.norm(emp - ad) / np.linalg.norm(ros) > 0.1
    assert np.allclose(lie.cov_ros_to_local(T, ros), S)


def test_check_covariance_errors():
    good = np.diag([1.0, 2, 3, 4, 5, 6])
    checked = lie.check_covariance(good.tolist(), "ok", size=6)  # a list is accepted and returned as an array
    assert isinstance(checked, np.ndarray) and checked.dtype == float
    np.testing.assert_array_equal(checked, good)
    with pytest.raises(CovarianceError, match="joint_a.*symmetric"):
        bad = good.copy()
        bad[0, 1] = 0.5
        lie.check_covariance(bad, "joint_a")
    with pytest.raises(CovarianceError, match="joint_b.*semi-definite"):
        lie.check_covariance(np.diag([1.0, -1, 1, 1, 1, 1]), "joint_b")
    with pytest.raises(CovarianceError, match="6x6"):
        lie.check_covariance(np.eye(3), "joint_c", size=6)
    with pytest.raises(CovarianceError, match="NaN"):
        lie.check_covariance(np.full((6, 6), np.nan), "joint_d")


# ----------------------------------------------------------------------------
# fit_rigid (Kabsch / Umeyama without scale)
# ----------------------------------------------------------------------------


def test_fit_rigid_recovers_random_transforms_noise_free_batched():
    rng = np.random.default_rng(21)
    T_dst_src = lie.exp(rng.normal(size=(4, 2, 6)) * [1, 1, 1, 1.5, 1.5, 1.5])
    P_src = rng.normal(size=(4, 2, 7, 3))
    P_dst = np.einsum("...ij,...nj->...ni", T_dst_src[..., :3, :3], P_src) + T_dst_src[..., None, :3, 3]
    T_fit = lie.fit_rigid(P_src, P_dst)
    assert T_fit.shape == (4, 2, 4, 4)
    np.testing.assert_allclose(T_fit, T_dst_src, atol=1e-12)
    # exactly 3 points (the minimum) are enough
    np.testing.assert_allclose(lie.fit_rigid(P_src[0, 0, :3], P_dst[0, 0, :3]), T_dst_src[0, 0], atol=1e-12)


def test_fit_rigid_with_noise_is_the_least_squares_fit():
    rng = np.random.default_rng(22)
    T = lie.exp(rng.normal(size=6))
    P = rng.normal(size=(200, 3))
    sigma = 1e-3
    Q = P @ T[:3, :3].T + T[:3, 3] + sigma * rng.normal(size=P.shape)
    T_fit = lie.fit_rigid(P, Q)
    assert np.linalg.det(T_fit[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    # close to the truth: a few sigma * sqrt(3 / n) in translation [m] and rotation [rad]
    # (points spread ~1 m; 8 seeds gave at most 2.2 resp. 1.3 of that)
    err = lie.ominus(T_fit, T)
    tol = 5 * sigma * np.sqrt(3 / 200)
    assert np.linalg.norm(err[:3]) < tol and np.linalg.norm(err[3:]) < tol

    # and a least-squares minimum: no small perturbation lowers the residual
    def cost(Tc):
        return float(np.sum((P @ Tc[:3, :3].T + Tc[:3, 3] - Q) ** 2))

    c0 = cost(T_fit)
    assert c0 <= cost(T) + 1e-15
    for d in rng.normal(size=(50, 6)) * 1e-5:
        assert cost(T_fit @ lie.exp(d)) >= c0 - 1e-15


def test_fit_rigid_turns_a_reflection_into_a_proper_rotation():
    rng = np.random.default_rng(23)
    P = rng.normal(size=(10, 3))
    Q = P * [1.0, 1.0, -1.0]  # mirror image: no rotation maps P onto Q
    T_fit = lie.fit_rigid(P, Q)
    assert np.linalg.det(T_fit[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(T_fit[:3, :3] @ T_fit[:3, :3].T, np.eye(3), atol=1e-12)
    # planar points mirrored in their plane's normal are fitted exactly by a rotation
    Pp = np.column_stack([rng.normal(size=(6, 2)), np.zeros(6)])
    np.testing.assert_allclose(lie.fit_rigid(Pp, Pp * [1.0, 1.0, -1.0]), np.eye(4), atol=1e-12)


def test_fit_rigid_bad_input():
    from ppoe_core.errors import MeasurementError

    with pytest.raises(MeasurementError, match="at least 3"):
        lie.fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(MeasurementError, match=r"\(\.\.\., n, 3\)"):
        lie.fit_rigid(np.zeros((4, 3)), np.zeros((5, 3)))
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(MeasurementError, match="collinear"):
        lie.fit_rigid(line, line)
    P = np.eye(3)
    with pytest.raises(MeasurementError, match="NaN"):
        lie.fit_rigid(P, np.where(P > 0, np.nan, 0.0))


# ----------------------------------------------------------------------------
# the compiled maps (THE implementation) against their numpy references (test/lie_reference.py), one input = batch
# ----------------------------------------------------------------------------


def _twists(rng: np.random.Generator) -> list[np.ndarray]:
    """Twists at every angle scale (both sides of the series thresholds) and at angle pi."""
    xis = [rng.normal(size=6) * s for s in (0.0, 1e-7, 9e-4, 1.1e-3, 9e-3, 1.1e-2, 1e-3, 0.1, 1.0, 3.0)
           for _ in range(100)]
    return xis + [np.r_[rng.normal(size=3), np.pi * unit(v)] for v in rng.normal(size=(50, 3))]


def test_compiled_maps_equal_their_numpy_references():
    rng = np.random.default_rng(30)
    xis = np.array(_twists(rng))
    T = lie.exp(xis)
    np.testing.assert_allclose(T, ref.exp_reference(xis), rtol=0, atol=1e-14)
    np.testing.assert_allclose(lie.log(T), ref.log_reference(T), rtol=0, atol=1e-12)
    np.testing.assert_allclose(lie.inverse(T), ref.inverse_reference(T), rtol=0, atol=0)
    np.testing.assert_allclose(lie.left_jacobian(xis), ref.left_jacobian_reference(xis), rtol=0, atol=1e-12)
    np.testing.assert_allclose(lie.left_jacobian_inv(xis), ref.left_jacobian_inv_reference(xis), rtol=1e-12,
                               atol=1e-12)
    np.testing.assert_allclose(lie.right_jacobian(xis), ref.left_jacobian_reference(-xis), rtol=0, atol=1e-12)
    w = xis[:, 3:]
    np.testing.assert_allclose(lie.so3_exp(w), ref.so3_exp_reference(w), rtol=0, atol=1e-14)
    np.testing.assert_allclose(lie.so3_log(T[:, :3, :3]), ref.so3_log_reference(T[:, :3, :3]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(lie.so3_left_jacobian(w), ref.so3_left_jacobian_reference(w), rtol=0, atol=1e-14)
    np.testing.assert_allclose(lie.so3_left_jacobian_inv(w), ref.so3_left_jacobian_inv_reference(w), rtol=1e-12,
                               atol=1e-12)
    q = lie.quat_from_matrix(T[:, :3, :3])
    np.testing.assert_allclose(q, ref.quat_from_matrix_reference(T[:, :3, :3]), rtol=0, atol=1e-15)
    qs = q * rng.uniform(0.5, 2.0, (len(q), 1))  # not normalised
    np.testing.assert_allclose(lie.matrix_from_quat(qs), ref.matrix_from_quat_reference(qs), rtol=0, atol=1e-15)


def test_single_inputs_are_the_batched_kernels_bit_for_bit():
    rng = np.random.default_rng(31)
    for xi in _twists(rng):
        T = lie.exp(xi)
        assert np.array_equal(T, lie.exp(xi[None])[0]), xi
        assert np.array_equal(lie.quat_from_matrix(T[:3, :3]), lie.quat_from_matrix(T[None, :3, :3])[0]), xi
        assert np.array_equal(lie.log(T), lie.log(T[None])[0]), xi
        assert np.array_equal(lie.inverse(T), lie.inverse(T[None])[0]), xi
        q = lie.quat_from_matrix(T[:3, :3]) * rng.uniform(0.5, 2.0)  # not normalised
        assert np.array_equal(lie.matrix_from_quat(q), lie.matrix_from_quat(q[None])[0]), xi
    # every Shepperd pivot, including exact ties on diagonal matrices
    for R in (np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        assert np.array_equal(lie.quat_from_matrix(R), lie.quat_from_matrix(R[None])[0])
        np.testing.assert_array_equal(lie.quat_from_matrix(R), ref.quat_from_matrix_reference(R))
    # non-finite input gives NaN, no exception; a zero quaternion NaN
    assert np.all(np.isnan(lie.exp(np.full(6, np.nan))[:3]))
    assert np.all(np.isnan(lie.quat_from_matrix(np.full((3, 3), np.nan))))
    assert np.all(np.isnan(lie.matrix_from_quat(np.zeros(4))))
    with pytest.raises(ValueError, match="expected an array of shape \\(..., 6\\)"):
        lie.exp(np.zeros(5))


def test_one_pose_kernels_are_bit_identical_to_the_batched_kernels():
    """The one-pose kernels of the message path (covariance rotation, quaternion of a strided ``T[:3, :3]``, pose
    from a quaternion) give the floats of the batched kernels."""
    from ppoe_core.lie import kernels

    rng = np.random.default_rng(32)
    for s in (0.0, 1e-6, 1e-2, 1.0, 3.0):
        for _ in range(200):
            T = lie.exp(rng.normal(size=6) * s)
            A = rng.normal(size=(6, 6))
            cov = A @ A.T
            for inverse in (False, True):
                out = np.empty((1, 6, 6))
                kernels.rotate_covariance_kernel(T[None], cov[None], inverse, out)
                one = lie.cov_ros_to_local(T, cov) if inverse else lie.cov_local_to_ros(T, cov)
                assert np.array_equal(one, out[0])
            q = np.empty((1, 4))
            kernels.quat_from_matrix_kernel(np.ascontiguousarray(T[None, :3, :3]), q)
            assert np.array_equal(lie.quat_from_matrix(T[:3, :3]), q[0])
            qn = q[0] * rng.uniform(0.5, 2.0)
            P = np.empty((4, 4))
            kernels.pose_from_quat_one(*qn.tolist(), *T[:3, 3].tolist(), P)
            assert np.array_equal(P[:3, :3], lie.matrix_from_quat(qn))
            assert np.array_equal(P[:3, 3], T[:3, 3]) and np.array_equal(P[3], [0.0, 0.0, 0.0, 1.0])


def test_batched_log_rows_equal_single_logs():
    """``CarriedCorrection.from_update`` takes two logarithms in one batched call: each row must be the single
    call's floats, at every angle scale."""
    rng = np.random.default_rng(33)
    for _ in range(1000):
        s = 10.0 ** rng.uniform(-9, 0.5)
        A, B = lie.exp(rng.normal(size=6) * s), lie.exp(rng.normal(size=6) * 0.1 * s)
        L = lie.log(np.stack([A, B]))
        assert np.array_equal(L[0], lie.log(A)) and np.array_equal(L[1], lie.log(B))
