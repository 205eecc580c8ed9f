"""The compiled fusion path: SE(3) on one element (ppoe_core.lie.kernels), the compiled iterated update of the tag and
contact models (ppoe_core.estimation.update_kernels / compiled_update), the compiled correction update and the quick
covariance check, each against the numpy code it replaces and against central differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from jacobian_check import SE3_MINUS, SE3_PLUS, check_jacobian

import lie_reference as ref
import update_reference as upd_ref

from conftest import pose_from
from ppoe_core import lie
from ppoe_core.errors import CovarianceError, MeasurementError
from ppoe_core.estimation import update_kernels as uk
from ppoe_core.estimation.corrections import CarriedCorrection, apply_carried_corrections
from ppoe_core.estimation.fusion import iterated_update
from ppoe_core.estimation.measurements import ContactPlaneModel, TagBearingModel, tag_points
from ppoe_core.estimation.prior_buffer import PriorSample
from ppoe_core.lie import kernels as lk

SETTINGS = settings(max_examples=60, deadline=None)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _exp(xi: np.ndarray) -> np.ndarray:
    T = np.empty((4, 4))
    lk.se3_exp_one(np.asarray(xi, dtype=float), T)
    return T


def _log(T: np.ndarray) -> np.ndarray:
    xi = np.empty(6)
    lk.se3_log_one(np.ascontiguousarray(T, dtype=float), xi)
    return xi


def _jr(xi: np.ndarray, inverse: bool = False) -> np.ndarray:
    J = np.empty((6, 6))
    (lk.se3_right_jacobian_inv_one if inverse else lk.se3_right_jacobian_one)(np.asarray(xi, dtype=float), J)
    return J


# --------------------------------------------------------------------------- SE(3) on one element
def test_compiled_se3_equals_the_numpy_references():
    rng = np.random.default_rng(3)
    for scale in (0.0, 1e-7, 1e-4, 1e-2, 0.3, 1.0, 2.5):
        for _ in range(40):
            xi = rng.normal(size=6) * scale
            T = ref.exp_reference(xi)
            np.testing.assert_allclose(_exp(xi), T, rtol=0, atol=1e-14)
            np.testing.assert_allclose(_log(T), ref.log_reference(T), rtol=0, atol=1e-13)
            np.testing.assert_allclose(_jr(xi), ref.left_jacobian_reference(-xi), rtol=0, atol=1e-13)
            np.testing.assert_allclose(_jr(xi, True), ref.left_jacobian_inv_reference(-xi), rtol=0, atol=1e-11)
            inv, prod = np.empty((4, 4)), np.empty((4, 4))
            lk.se3_inverse_one(T, inv)
            np.testing.assert_array_equal(inv, ref.inverse_reference(T))
            lk.se3_mul(T, inv, prod)
            np.testing.assert_allclose(prod, np.eye(4), atol=1e-12)


@SETTINGS
@given(arrays(np.float64, (3,), elements=st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 1e-3),
       st.floats(-12, -3))
def test_compiled_near_identity_round_trip(axis, log_angle):
    xi = np.concatenate([[0.3, -0.2, 0.1], _unit(axis) * 10.0**log_angle])
    np.testing.assert_allclose(_log(_exp(xi)), xi, rtol=1e-9, atol=1e-15)


@SETTINGS
@given(arrays(np.float64, (3,), elements=st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 1e-3),
       st.floats(-10, -2))
def test_compiled_near_pi_round_trip(axis, log_gap):
    w = _unit(axis) * (np.pi - 10.0**log_gap)
    xi = np.concatenate([[0.1, 0.2, 0.3], w])
    T = _exp(xi)
    np.testing.assert_allclose(_exp(_log(T)), T, atol=1e-9)
    np.testing.assert_allclose(_log(T)[3:], w, atol=1e-7)


def test_compiled_log_at_exactly_pi_and_identity():
    for axis in np.eye(3):
        w = _log(lie.exp(np.r_[0.0, 0.0, 0.0, np.pi * axis]))[3:]
        assert math.isclose(np.linalg.norm(w), np.pi)
    np.testing.assert_array_equal(_log(np.eye(4)), np.zeros(6))


@pytest.mark.parametrize("xi", [
    np.array([0.1, -0.2, 0.3, 0.4, -0.1, 0.2]),
    np.array([0.5, 0.1, -0.3, 1e-7, -2e-7, 1e-7]),  # series branch
    np.r_[[0.2, 0.1, -0.3], _unit(np.array([1.0, -2.0, 0.5])) * (np.pi - 1e-3)],  # near pi
])
def test_compiled_right_jacobians_central_differences(xi):
    # Exp(xi + d) = Exp(xi) Exp(Jr(xi) d); Log(Exp(xi) Exp(d)) = xi + Jr^-1(xi) d
    check_jacobian(_exp, xi, _jr(xi), minus=SE3_MINUS, atol=1e-6, err_msg="Jr")
    check_jacobian(lambda T: _log(T), _exp(xi), _jr(xi, True), dim=6, plus=SE3_PLUS, atol=1e-6, err_msg="Jr^-1")


# --------------------------------------------------------------------------- the compiled update
K_CAM = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])
D_CAM = np.array([-0.2, 0.08, 0.001, -0.001, -0.01])
T_BASE_CAM = pose_from([0.2, 0.0, 1.0], [-2.0, 0.0, 0.0])


def _tag_model(mode: str = "pixel", camera: bool = True, D=D_CAM) -> TagBearingModel:
    rng = np.random.default_rng(1)
    pts = np.vstack([tag_points(0.04, pose_from([0.03, 0, 0], [0, 0, 0])),
                     tag_points(0.04, pose_from([-0.03, 0, 0], [0, 0, 0]))])
    A = rng.normal(size=(6, 6))
    cov_cam = 1e-5 * (A @ A.T / 6 + 0.1 * np.eye(6)) if camera else None
    return TagBearingModel(pts, K_CAM, D, 0.5, mode=mode, T_ref_camera=T_BASE_CAM, cov_camera=cov_cam)


def _contact_model(distance_sigma: float = 0.0) -> ContactPlaneModel:
    sigma_v = np.diag([0.5, 0.5, 0.001, 0.017, 0.017, 0.17]) ** 2
    return ContactPlaneModel(pose_from([0.1, 0.2, 0.0], [0.1, 0.0, 0.2]), sigma_v, [0.0, 0.0, 0.02],
                             distance_sigma=distance_sigma)


def _python_path(model, *args, **kw):
    """The same update by the numpy reference (test/update_reference.py)."""
    return upd_ref.iterated_update_reference(*args, model, **kw)


class _External:
    """A model seen without its compiled linearisation: the update gets it from outside at each iterate."""

    compiled = None

    def __init__(self, model):
        self._model = model

    def __getattr__(self, name):
        return getattr(self._model, name)


def _external_path(model, *args, **kw):
    """The same update with the linearisation given from outside (as a model without a compiled one)."""
    return iterated_update(*args, _External(model), **kw)


def _random_cov(rng, scale=1e-5, singular=False):
    B = rng.normal(size=(6, 6))
    P = scale * (B @ B.T / 6 + 0.1 * np.eye(6))
    if singular:  # a direction the prior is certain about, as PPOE covariances have
        P[5, :] = P[:, 5] = 0.0
    return P


def _assert_same(r1, r2):
    assert (r1.accepted, r1.iterations, r1.converged) == (r2.accepted, r2.iterations, r2.converged)
    for name in ("T", "cov", "nis", "innovation", "S", "gain", "H", "steps"):
        a, b = np.asarray(getattr(r1, name), float), np.asarray(getattr(r2, name), float)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * max(np.abs(b).max(initial=0.0), 1e-300),
                                   err_msg=name)
    # differences of nearly equal numbers (z - h(T), Log(X0^-1 T)): round-off of the terms, not of the result
    np.testing.assert_allclose(r1.residual, r2.residual, rtol=0, atol=1e-15 * 1000.0, err_msg="residual")
    np.testing.assert_allclose(r1.correction, r2.correction, rtol=0, atol=1e-14, err_msg="correction")


@pytest.mark.parametrize("mode,camera,D", [("pixel", True, D_CAM), ("pixel", False, None),
                                           ("normalized", True, None), ("normalized", False, None)])
def test_compiled_tag_update_equals_the_python_path(mode, camera, D):
    rng = np.random.default_rng(7)
    tags = _tag_model(mode, camera, D)
    for trial in range(12):
        X0 = T_BASE_CAM @ pose_from([0.02, -0.01, 0.6], [np.pi, 0.2, 0.1]) @ lie.exp(rng.normal(size=6) * 0.01)
        P = _random_cov(rng, singular=trial % 3 == 0)
        z = tags.h(X0 @ lie.exp(0.003 * rng.normal(size=6)))
        for kw in (dict(max_iterations=3, step_tolerance=0.0), dict(), dict(gate_probability=0.5),
                   dict(max_iterations=1, transport_covariance=False), dict(gate_probability=None, with_cost=True)):
            r1 = iterated_update(X0, P, z, tags, **kw)
            _assert_same(r1, _python_path(tags, X0, P, z, **kw))
            _assert_same(r1, _external_path(tags, X0, P, z, **kw))
            if kw.get("with_cost"):
                assert math.isclose(r1.cost, upd_ref.posterior_cost_reference(tags, r1.T, r1.residual, r1.correction,
                                                                               P), rel_tol=1e-9)


@pytest.mark.parametrize("distance_sigma", [0.0, 0.001])
def test_compiled_contact_update_equals_the_python_path(distance_sigma):
    rng = np.random.default_rng(8)
    contact = _contact_model(distance_sigma)
    for _ in range(12):
        X = pose_from([0.4, 0.1, -0.018], [0.0, 0.0, 0.3]) @ lie.exp(rng.normal(size=6) * 0.01)
        P = _random_cov(rng)
        for kw in (dict(), dict(gate_probability=None, with_cost=True), dict(max_iterations=1)):
            r1 = iterated_update(X, P, [0.0], contact, **kw)
            _assert_same(r1, _python_path(contact, X, P, [0.0], **kw))
            _assert_same(r1, _external_path(contact, X, P, [0.0], **kw))
            if kw.get("with_cost"):
                assert math.isclose(r1.cost, upd_ref.posterior_cost_reference(contact, r1.T, r1.residual,
                                                                               r1.correction, P), rel_tol=1e-9)


def _kernel_linearize(model, X):
    h, H, M = np.empty(model.dim), np.empty((model.dim, 6)), np.empty((model.dim, model.noise_dim))
    spec = model.compiled
    assert uk.linearize(spec.kind, X, *spec[1:], h, H, M) == -1
    return h, H, M


@pytest.mark.parametrize("model", [_tag_model(), _tag_model("normalized"), _contact_model(0.002)],
                         ids=["tag_pixel", "tag_normalized", "contact"])
def test_compiled_linearisations_central_differences(model):
    rng = np.random.default_rng(9)
    X = (T_BASE_CAM @ pose_from([0.02, -0.01, 0.6], [np.pi, 0.2, 0.1]) if isinstance(model, TagBearingModel)
         else pose_from([0.4, 0.1, -0.018], [0.0, 0.0, 0.3])) @ lie.exp(0.01 * rng.normal(size=6))
    h, H, M = _kernel_linearize(model, X)
    np.testing.assert_allclose(h, model.h(X, np.zeros(model.noise_dim)), rtol=1e-12, atol=1e-12)
    scale = 1.0 if getattr(model, "mode", "") == "pixel" else 1e-3
    check_jacobian(model.h, X, H, dim=6, plus=SE3_PLUS, atol=1e-4 * scale, err_msg="H")
    check_jacobian(lambda v: model.h(X, v), np.zeros(model.noise_dim), M, atol=1e-4 * scale, err_msg="M")


def test_compiled_update_errors_name_the_problem():
    tags = _tag_model()
    X_behind = T_BASE_CAM @ pose_from([0.0, 0.0, -0.5], [0.0, 0.0, 0.0])
    with pytest.raises(MeasurementError, match="behind the camera"):
        iterated_update(X_behind, np.eye(6) * 1e-6, np.zeros(tags.dim), tags)
    X = pose_from([0.4, 0.1, -0.018], [0.0, 0.0, 0.3])
    with pytest.raises(MeasurementError, match="prior pose: pose contains NaN"):
        iterated_update(np.full((4, 4), np.nan), np.eye(6), [0.0], _contact_model())
    with pytest.raises(CovarianceError, match="prior covariance: not positive semi-definite"):
        iterated_update(X, -np.eye(6), [0.0], _contact_model())
    with pytest.raises(MeasurementError, match="measurement contains NaN"):
        iterated_update(X, np.eye(6), [np.nan], _contact_model())
    flat = ContactPlaneModel(np.eye(4), np.zeros((6, 6)), [0.0, 0.0, 0.0])
    with pytest.raises(CovarianceError, match="innovation covariance .* not positive definite"):
        iterated_update(X, np.zeros((6, 6)), [0.0], flat)


# --------------------------------------------------------------------------- per-prior kernels
def _apply_numpy(prior, H, Rw, z):
    """``apply_carried_corrections`` as written in numpy before the compiled kernel."""
    P = 0.5 * (prior.cov_tool + prior.cov_tool.T)
    S = H @ P @ H.T + np.diag(Rw)
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(6) - K @ H
    cov = IKH @ P @ IKH.T + K @ np.diag(Rw) @ K.T
    return prior.T_base_tool @ lie.exp(K @ z), 0.5 * (cov + cov.T)


def test_compiled_correction_update_equals_the_numpy_formula():
    rng = np.random.default_rng(11)
    for _ in range(20):
        prior = PriorSample(1.0, lie.exp(rng.normal(size=6)), _random_cov(rng, 1e-4))
        corrs = []
        for _ in range(rng.integers(1, 3)):
            r = int(rng.integers(1, 7))
            H = np.linalg.qr(rng.normal(size=(6, r)))[0].T
            corrs.append((CarriedCorrection(prior, H, rng.uniform(1e-6, 1e-4, r), 1e-3 * rng.normal(size=r)),
                          float(rng.uniform(0.1, 1.0))))
        T, cov = apply_carried_corrections(prior, corrs)
        H = np.concatenate([c.H for c, _ in corrs])
        T_ref, cov_ref = _apply_numpy(prior, H, np.concatenate([c.R / w for c, w in corrs]),
                                      np.concatenate([c.z for c, _ in corrs]))
        np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-14)
        np.testing.assert_allclose(cov, cov_ref, rtol=1e-10, atol=1e-22)


@pytest.mark.parametrize("case", ["pd", "singular", "tiny_negative", "negative", "asymmetric", "nan"])
def test_quick_covariance_check_agrees_with_the_eigenvalues(case):
    rng = np.random.default_rng(12)
    B = rng.normal(size=(6, 6))
    C = B @ B.T
    if case == "singular":
        C[2, :] = C[:, 2] = 0.0
    elif case == "tiny_negative":
        C[2, :] = C[:, 2] = 0.0
        C[2, 2] = -1e-14 * np.abs(C).max()  # inside the tolerance: passes
    elif case == "negative":
        C[2, 2] = -1e-3 * np.abs(C).max()
    elif case == "asymmetric":
        C[0, 1] += 1e-6 * np.abs(C).max()
    elif case == "nan":
        C[1, 1] = np.nan
    passes = lk.covariance_passes_kernel(np.ascontiguousarray(C), 1e-9, 1e-12)
    assert passes == (case in ("pd", "singular", "tiny_negative"))
    if case in ("pd", "singular", "tiny_negative"):
        out = lie.check_covariance(C, "c", size=6, tol=1e-9, eig_tol=1e-12, symmetrize=True)
        np.testing.assert_array_equal(out, 0.5 * (C + C.T))
        assert lie.check_covariance(C, "c", size=6, tol=1e-9, eig_tol=1e-12) is not None
    else:
        with pytest.raises(CovarianceError, match="c: "):
            lie.check_covariance(C, "c", size=6, tol=1e-9, eig_tol=1e-12)


def _check_same_correction(got: CarriedCorrection | None, ref: CarriedCorrection | None) -> None:
    assert (got is None) == (ref is None)
    if got is None or ref is None:
        return
    np.testing.assert_array_equal(got.T_anchor_inv, ref.T_anchor_inv)
    assert got.H.shape == ref.H.shape and got.anchor is ref.anchor
    for name in ("H", "R", "z"):
        a, b = getattr(got, name), getattr(ref, name)
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12 * np.abs(b).max(), err_msg=name)


def test_compiled_from_update_equals_the_numpy_reference():
    """``CarriedCorrection.from_update`` (compiled) against ``from_update_reference``: random updates from the raw
    prior or from a corrected estimate, a prior certain about some directions, an update that adds nothing, inputs
    of other types; a non-finite covariance or wrong shapes are a MeasurementError."""
    rng = np.random.default_rng(12)
    for k in range(200):
        T = lie.exp(rng.normal(size=6))
        P = _random_cov(rng, 10.0 ** rng.uniform(-6, -2))
        if k % 5 == 0:  # certain about x and the rotation about z
            P[0, :] = P[:, 0] = P[5, :] = P[:, 5] = 0.0
        anchor = PriorSample(0.1 * k, T, P)
        corrected = k % 2 == 1
        T_pre = T @ lie.exp(1e-3 * rng.normal(size=6)) if corrected else None
        P_pre = 0.8 * P if corrected else None
        T_post = (T if T_pre is None else T_pre) @ lie.exp(1e-3 * rng.normal(size=6))
        P_post = 0.5 * P + (_random_cov(rng, 1e-8) if k % 3 else 0.0)
        _check_same_correction(CarriedCorrection.from_update(anchor, T_post, P_post, T_pre, P_pre),
                               upd_ref.from_update_reference(anchor, T_post, P_post, T_pre, P_pre))
    anchor = PriorSample(0.0, np.eye(4), np.eye(6) * 1e-4)
    assert CarriedCorrection.from_update(anchor, np.eye(4), np.eye(6) * 1e-4) is None  # no information added
    assert CarriedCorrection.from_update(PriorSample(0.0, np.eye(4), np.zeros((6, 6))), np.eye(4), np.eye(6)) is None
    _check_same_correction(CarriedCorrection.from_update(anchor, np.eye(4).tolist(), (np.eye(6) * 1e-5).tolist()),
                           upd_ref.from_update_reference(anchor, np.eye(4), np.eye(6) * 1e-5))
    with pytest.raises(MeasurementError, match="covariances 6x6"):
        CarriedCorrection.from_update(anchor, np.eye(4), np.eye(5))
    bad = np.eye(6) * 1e-5
    bad[2, 2] = np.nan
    with pytest.raises(MeasurementError, match="not finite"):  # numpy's eigh raised LinAlgError here before
        CarriedCorrection.from_update(anchor, np.eye(4), bad)


def test_batched_covariance_check_passes_and_fails_as_the_eigenvalues():
    """The compiled quick pass of a batch (each matrix with its own scale) returns what the batched eigenvalue
    check returns; a batch with one bad matrix still gets the eigenvalue check's error."""
    rng = np.random.default_rng(13)
    C = np.stack([_random_cov(rng, 10.0 ** rng.uniform(-8, 0)) for _ in range(50)])
    assert lk.covariances_pass_kernel(C, 1e-9, 1e-9)
    assert lie.check_covariance(C, "batch", size=6) is C
    np.testing.assert_array_equal(lie.check_covariance(C, "batch", size=6, symmetrize=True),
                                  0.5 * (C + np.swapaxes(C, 1, 2)))
    C[17, 3, 3] = -1e-3 * np.abs(C).max()
    assert not lk.covariances_pass_kernel(C, 1e-9, 1e-9)
    with pytest.raises(CovarianceError, match="batch: not positive semi-definite"):
        lie.check_covariance(C, "batch", size=6)
