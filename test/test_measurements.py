"""Measurement models: analytic Jacobians vs central differences, eq. 25, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jacobian_check import SE3_PLUS, check_jacobian, numerical_jacobian

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, MeasurementError
from ppoe_core.estimation.measurements import (
    ChainedObservation,
    ContactPlaneModel,
    GravityObservation,
    PointObservation,
    PoseObservation,
    StackedObservation,
    TagBearingModel,
    tag_points,
)

K = np.array([[610.0, 0.3, 322.0], [0.0, 605.0, 241.0], [0.0, 0.0, 1.0]])
D = np.array([-0.21, 0.09, 0.0012, -0.0008, -0.015])
SIGMA_PLANE = np.diag([0.5, 0.5, 0.001, 0.017, 0.017, 0.17]) ** 2


from conftest import pose_from as _pose
from conftest import random_pose


def _rand_pose(rng, scale_t=0.3, scale_r=0.5):
    return random_pose(rng, scale_t=scale_t, scale_r=scale_r)


def _spd(rng, n, scale=1e-3):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + 0.1 * np.eye(n))


def _tag_setup(rng, mode="pixel", camera_noise=True):
    T_ref_camera = _rand_pose(rng)
    # tool 0.6 m in front of the camera, tag facing it (rotated by up to ~30 deg)
    T_cam_tool = _pose(
        np.r_[rng.normal(size=2) * 0.1, 0.6], np.r_[np.pi + rng.normal() * 0.3, rng.normal(size=2) * 0.3]
    )
    pts = np.vstack(
        [
            tag_points(0.05, lie.exp(np.r_[0.03, 0, 0, 0, 0, 0])),
            tag_points(0.04, lie.exp(np.r_[-0.03, 0.01, 0.0, 0.2, 0, 0])),
        ]
    )
    model = TagBearingModel(
        pts,
        K,
        D,
        pixel_sigma=0.5,
        mode=mode,
        T_ref_camera=T_ref_camera,
        cov_camera=_spd(rng, 6, 1e-5) if camera_noise else None,
    )
    return model, T_ref_camera @ T_cam_tool


def _models(rng):
    out = []
    for mode in ("pixel", "normalized"):
        for cam in (True, False):
            out.append(_tag_setup(rng, mode, cam))
    T_ref_plane = _rand_pose(rng)
    X = T_ref_plane @ lie.exp(np.r_[0.2, -0.1, 0.01, rng.normal(size=3)])
    out.append((ContactPlaneModel(T_ref_plane, SIGMA_PLANE, [0.01, 0.02, 0.05]), X))
    out.append((ContactPlaneModel(T_ref_plane, SIGMA_PLANE, [0.0, 0.0, 0.1], distance_sigma=1e-3), X))
    Xp = _rand_pose(rng)
    out.append((PointObservation([0.1, -0.05, 0.2], 0.0005), Xp))
    out.append((PointObservation([0.1, -0.05, 0.2], _spd(rng, 3, 1e-6), _rand_pose(rng), _spd(rng, 6, 1e-5)), Xp))
    out.append((PoseObservation(_spd(rng, 6)), Xp))
    out.append((GravityObservation(0.01, lie.so3_exp(rng.normal(size=3))), Xp))
    inner = PointObservation([0.1, 0.0, 0.0], 0.001)
    out.append((ChainedObservation(inner, _rand_pose(rng), _spd(rng, 6, 1e-5)), Xp))
    out.append((ChainedObservation(GravityObservation(0.01), _rand_pose(rng), _spd(rng, 6, 1e-5)), Xp))
    out.append(
        (
            StackedObservation(
                [PointObservation([0, 0, 0.1], 0.001), GravityObservation(0.01), PoseObservation(_spd(rng, 6))]
            ),
            Xp,
        )
    )
    return out


def _check_model_jacobians(model, X, H, M, rel=0.0, atol=0.0):
    """``H = d h(X Exp(xi)) / d xi`` and ``M = d h(X, v) / d v`` against the one Jacobian checker
    (measurement-space differences through ``model.residual``); tolerance ``atol`` or ``rel`` x scale."""
    minus = model.residual
    Hn = numerical_jacobian(model.h, X, dim=6, plus=SE3_PLUS, minus=minus)
    Mn = numerical_jacobian(lambda v: model.h(X, v), np.zeros(model.noise_dim), minus=minus)
    tol = atol or rel * max(1.0, np.abs(Hn).max(), np.abs(Mn).max())
    check_jacobian(model.h, X, H, dim=6, plus=SE3_PLUS, minus=minus, atol=tol, err_msg=f"{model.name} H")
    check_jacobian(lambda v: model.h(X, v), np.zeros(model.noise_dim), M, minus=minus, atol=tol,
                   err_msg=f"{model.name} M")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_analytic_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    for model, X in _models(rng):
        H = model.jacobian_state(X)
        M = model.jacobian_noise(X)
        assert H.shape == (model.dim, 6) and M.shape == (model.dim, model.noise_dim), model.name
        _check_model_jacobians(model, X, H, M, rel=1e-6)


@settings(max_examples=30, deadline=None)
@given(
    xi=st.lists(st.floats(-0.3, 0.3), min_size=6, max_size=6),
    d=st.lists(st.floats(-0.3, 0.3), min_size=5, max_size=5),
)
def test_tag_jacobian_property(xi, d):
    """Any moderate pose in front of the camera and any plumb_bob coefficients."""
    pts = tag_points(0.06)
    model = TagBearingModel(pts, K, np.asarray(d) * np.array([1, 1, 0.05, 0.05, 1]), cov_camera=np.eye(6) * 1e-4)
    X = _pose([0, 0, 0.8], [np.pi, 0, 0]) @ lie.exp(np.asarray(xi))
    _check_model_jacobians(model, X, model.jacobian_state(X), model.jacobian_noise(X), atol=2e-4)


def test_tag_reduces_to_paper_eq25():
    """One point at the tool origin, state T_camera_tool: z = [p1/p3 f1, p2/p3 f2] (eq. 25)."""
    f1, f2 = 600.0, 620.0
    Kz = np.diag([f1, f2, 1.0])
    model = TagBearingModel(np.zeros((1, 3)), Kz, None, mode="pixel")
    p = np.array([0.1, -0.2, 1.5])
    X = lie.exp(np.r_[0, 0, 0, 0.3, 0.1, 0.2])
    X[:3, 3] = p
    np.testing.assert_allclose(model.h(X), [p[0] / p[2] * f1, p[1] / p[2] * f2], rtol=1e-12)
    norm = TagBearingModel(np.zeros((1, 3)), Kz, None, mode="normalized")
    np.testing.assert_allclose(norm.h(X), p[:2] / p[2], rtol=1e-12)
    np.testing.assert_allclose(np.diag(norm.noise_cov), [(0.5 / f1) ** 2, (0.5 / f2) ** 2])


def test_tag_pixels_match_opencv():
    import cv2  # a hard dependency (setup.py): no skip

    rng = np.random.default_rng(5)
    model, X = _tag_setup(rng, "pixel", camera_noise=False)
    K0 = K.copy()
    K0[0, 1] = 0.0  # OpenCV ignores the skew entry
    model = TagBearingModel(model.points_tool, K0, D, T_ref_camera=model.T_ref_camera)
    T_cam_tool = lie.inverse(model.T_ref_camera) @ X
    rvec, _ = cv2.Rodrigues(T_cam_tool[:3, :3])
    uv, _ = cv2.projectPoints(model.points_tool, rvec, T_cam_tool[:3, 3], K0, D)
    np.testing.assert_allclose(model.h(X), uv.reshape(-1), atol=1e-6)


def test_contact_distance_and_sign():
    T_ref_plane = lie.exp(np.r_[0.1, 0.2, 0.7, 0.0, 0.0, 0.4])
    model = ContactPlaneModel(T_ref_plane, SIGMA_PLANE, [0, 0, 0.05])
    X = T_ref_plane @ lie.exp(np.r_[0.3, -0.2, 0.0, 0, 0, 0])  # tool frame on the plane, point 5 cm above
    np.testing.assert_allclose(model.h(X), [0.05], atol=1e-12)
    X2 = T_ref_plane @ lie.exp(np.r_[0.3, -0.2, -0.07, 0, 0, 0])
    np.testing.assert_allclose(model.h(X2), [-0.02], atol=1e-12)


def test_gravity_measures_tilt():
    model = GravityObservation(0.01)
    np.testing.assert_allclose(model.h(np.eye(4)), [0, 0, 9.80665])
    X = lie.exp(np.r_[1, 2, 3, 0, 0, 1.0])  # yaw does not change the reading
    np.testing.assert_allclose(model.h(X), [0, 0, 9.80665], atol=1e-12)
    H = model.jacobian_state(np.eye(4))
    assert np.allclose(H[:, :3], 0) and np.allclose(H[:, 5], 0) and np.linalg.matrix_rank(H) == 2


def test_chained_equals_direct_model_on_link():
    rng = np.random.default_rng(3)
    T_tool_L = _rand_pose(rng)
    inner = PointObservation([0.1, 0.2, 0.3], 0.001)
    chained = ChainedObservation(inner, T_tool_L, None)
    X = _rand_pose(rng)
    np.testing.assert_allclose(chained.h(X), inner.h(X @ T_tool_L), atol=1e-12)


# ---------------------------------------------------------------------------- bad input
def test_point_behind_camera_is_a_clear_error():
    model = TagBearingModel(
        tag_points(0.05), K, D, labels=["tag 7 centre"] + [f"tag 7 corner {i}" for i in range(1, 5)]
    )
    X = lie.exp(np.r_[0, 0, -0.5, 0, 0, 0])
    with pytest.raises(MeasurementError, match="tag 7 centre is behind the camera"):
        model.h(X)


def test_bad_construction_inputs():
    with pytest.raises(MeasurementError, match="points_tool"):
        TagBearingModel(np.zeros((3, 2)), K)
    with pytest.raises(MeasurementError, match="K must be"):
        TagBearingModel(np.zeros((1, 3)), np.zeros((3, 3)))
    with pytest.raises(MeasurementError, match="plumb_bob"):
        TagBearingModel(np.zeros((1, 3)), K, np.ones(8))
    with pytest.raises(CovarianceError, match="pixel_sigma"):
        TagBearingModel(np.zeros((1, 3)), K, pixel_sigma=-1.0)
    bad = np.diag([1.0, 1, 1, 1, 1, -1e-3])
    with pytest.raises(CovarianceError, match="cov_plane: not positive semi-definite"):
        ContactPlaneModel(np.eye(4), bad)
    with pytest.raises(CovarianceError, match="not symmetric"):
        PoseObservation(np.eye(6) + np.triu(np.ones((6, 6)), 1))
    with pytest.raises(CovarianceError, match="6x6"):
        PointObservation([0, 0, 0], 0.1, np.eye(4), np.eye(5))
    with pytest.raises(MeasurementError, match="rotation"):
        ContactPlaneModel(np.diag([1.0, 1.0, -1.0, 1.0]), SIGMA_PLANE)
    # a camera pose from user input is checked (pose_checked=True only for the caller's own FK)
    with pytest.raises(MeasurementError, match="T_ref_camera: rotation block is not a proper rotation"):
        TagBearingModel(np.zeros((1, 3)) + [0, 0, 1], K, T_ref_camera=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(MeasurementError, match="T_ref_camera: pose contains NaN"):
        TagBearingModel(np.zeros((1, 3)) + [0, 0, 1], K, T_ref_camera=np.full((4, 4), np.nan))


def test_validate_rejects_nan_and_wrong_shape():
    model = TagBearingModel(tag_points(0.05), K)
    with pytest.raises(MeasurementError, match=r"shape \(8,\), expected \(10,\)"):
        model.validate(np.zeros(8))
    z = np.zeros(10)
    z[3] = np.nan
    with pytest.raises(MeasurementError, match="NaN/inf at index \\[3\\]"):
        model.validate(z)
    with pytest.raises(MeasurementError, match="4x4"):
        PoseObservation(np.eye(6)).validate(np.eye(3))
    with pytest.raises(MeasurementError, match="noise vector"):
        model.h(lie.exp(np.r_[0, 0, 1, 0, 0, 0]), np.zeros(3))
