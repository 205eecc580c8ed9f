"""Unit tests of ppoe_core.estimation.pipeline without ROS: buffer, interpolation, carry/drop."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_pose
from hypothesis import given, settings
from hypothesis import strategies as st

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.estimation.pipeline import (
    CarriedCorrection,
    CorrectionPolicy,
    FusionPipeline,
    LookupStatus,
    Measurement,
    PriorBuffer,
    PriorSample,
    ToolUpdate,
    apply_carried_corrections,
)


def _random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return random_pose(rng, scale_t=scale, scale_r=scale)


def _random_cov(rng: np.random.Generator, scale: float = 1e-3) -> np.ndarray:
    A = rng.normal(size=(6, 6)) * scale
    return A @ A.T + 1e-8 * np.eye(6)


class LinearUpdater:
    """Test updater: linear measurement ``z = H Log(T^-1 T_meas) + n`` of the tool-frame error.

    payload = (T_meas (4,4), H (m,6), R (m,m)); gate at ``gate`` on the NIS.
    """

    def __init__(self, gate: float = 1e9) -> None:
        self.gate = gate
        self.calls = 0

    def __call__(self, T, P, m: Measurement, prior=None) -> ToolUpdate:
        self.calls += 1
        T_meas, H, R = m.payload
        if not np.all(np.isfinite(T_meas)):
            raise MeasurementError(f"{m.source}: NaN in measurement")
        r = H @ lie.log(lie.inverse(T) @ T_meas)
        S = H @ P @ H.T + R
        nis = float(r @ np.linalg.solve(S, r))
        if nis > self.gate:
            return ToolUpdate(T, P, False, nis)
        K = np.linalg.solve(S, H @ P).T
        IKH = np.eye(6) - K @ H
        return ToolUpdate(T @ lie.exp(K @ r), IKH @ P @ IKH.T + K @ R @ K.T, True, nis)


# ----------------------------------------------------------------------------
# PriorBuffer
# ----------------------------------------------------------------------------


def test_buffer_interpolates_on_se3_and_blends_covariance():
    rng = np.random.default_rng(1)
    buf = PriorBuffer(duration=1.0, max_gap=0.2)
    T0, T1 = _random_pose(rng), _random_pose(rng)
    P0, P1 = _random_cov(rng), _random_cov(rng)
    q0, q1 = np.array([0.0, 1.0]), np.array([1.0, 3.0])
    buf.add(PriorSample(10.0, T0, P0, q0))
    buf.add(PriorSample(10.1, T1, P1, q1))
    status, s = buf.lookup(10.025)
    assert status == LookupStatus.OK
    np.testing.assert_allclose(s.T_base_tool, lie.interpolate(T0, T1, 0.25), atol=1e-12)
    # the interpolated pose lies on the geodesic: Log(T0^-1 T) = 0.25 Log(T0^-1 T1)
    np.testing.assert_allclose(lie.ominus(s.T_base_tool, T0), 0.25 * lie.ominus(T1, T0), atol=1e-10)
    np.testing.assert_allclose(s.cov_tool, 0.75 * P0 + 0.25 * P1, atol=1e-15)
    np.testing.assert_allclose(s.joints, [0.25, 1.5])
    assert s.stamp == 10.025
    # exact stamps return the stored sample
    assert buf.lookup(10.1)[1].T_base_tool is T1


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 1.0), st.integers(0, 2**31 - 1))
def test_buffer_interpolation_endpoints_and_geodesic(s, seed):
    rng = np.random.default_rng(seed)
    T0, T1 = _random_pose(rng, 0.5), _random_pose(rng, 0.5)
    buf = PriorBuffer(duration=5.0, max_gap=1.0)
    buf.add(PriorSample(0.0, T0, np.eye(6)))
    buf.add(PriorSample(1.0, T1, 2 * np.eye(6)))
    status, smp = buf.lookup(s)
    assert status == LookupStatus.OK
    np.testing.assert_allclose(lie.ominus(smp.T_base_tool, T0), s * lie.ominus(T1, T0), atol=1e-9)
    np.testing.assert_allclose(np.diag(smp.cov_tool), 1.0 + s)


def test_buffer_status_codes_and_eviction():
    buf = PriorBuffer(duration=0.5, max_gap=0.2, max_hold=0.1)
    assert buf.lookup(1.0)[0] == LookupStatus.EMPTY
    for k in range(11):  # 0.0 .. 1.0 every 0.1 s
        assert buf.add(PriorSample(0.1 * k, np.eye(4), np.eye(6)))
    assert buf.oldest == pytest.approx(0.5) and buf.newest == pytest.approx(1.0)
    assert len(buf) == 6
    assert buf.lookup(0.45)[0] == LookupStatus.TOO_OLD
    assert buf.lookup(1.01)[0] == LookupStatus.TOO_NEW
    assert buf.lookup_hold(1.05)[0] == LookupStatus.OK
    assert buf.lookup_hold(1.2)[0] == LookupStatus.TOO_NEW
    # a prior older than the window is refused, an out-of-order one inside is inserted
    assert not buf.add(PriorSample(0.3, np.eye(4), np.eye(6)))
    assert buf.add(PriorSample(0.95, np.eye(4), 3 * np.eye(6)))
    assert buf.lookup(0.95)[1].cov_tool[0, 0] == 3.0


def test_buffer_gap_is_not_interpolated():
    """Between two stops of a static dataset the arm moved without joint states."""
    Ta, Tb = lie.exp([0.1, 0, 0, 0, 0, 0]), lie.exp([0.5, 0, 0, 0, 0, 0])
    buf = PriorBuffer(duration=10.0, max_gap=0.2, max_hold=0.3)
    buf.add(PriorSample(0.0, Ta, np.eye(6)))
    buf.add(PriorSample(2.0, Tb, np.eye(6)))
    status, s = buf.lookup(0.25)  # held from the stop at 0.0
    assert status == LookupStatus.OK
    np.testing.assert_allclose(s.T_base_tool, Ta)
    status, s = buf.lookup(1.9)
    np.testing.assert_allclose(s.T_base_tool, Tb)
    assert buf.lookup(1.0)[0] == LookupStatus.GAP


def test_buffer_rejects_bad_parameters():
    with pytest.raises(PpoeError, match="duration"):
        PriorBuffer(duration=0.0)
    with pytest.raises(PpoeError, match="max_gap"):
        PriorBuffer(max_gap=-1.0)


# ----------------------------------------------------------------------------
# CorrectionPolicy and CarriedCorrection
# ----------------------------------------------------------------------------


def test_policy_weights_and_drop_limits():
    pol = CorrectionPolicy(timeout=2.0, joint_motion=0.1, tool_translation=0.05, tool_rotation=0.2)
    a = PriorSample(0.0, np.eye(4), np.eye(6), np.zeros(3))
    assert pol.weight(a, a) == 1.0
    assert pol.weight(a, PriorSample(1.0, np.eye(4), np.eye(6), np.zeros(3))) == pytest.approx(0.5)
    assert pol.weight(a, PriorSample(2.0, np.eye(4), np.eye(6), np.zeros(3))) == 0.0
    assert pol.weight(a, PriorSample(0.0, np.eye(4), np.eye(6), np.array([0, 0.075, 0]))) == pytest.approx(0.25)
    assert pol.weight(a, PriorSample(0.0, np.eye(4), np.eye(6), np.array([0, -0.1, 0]))) == 0.0
    T_moved = lie.exp([0.04, 0, 0, 0, 0, 0])
    assert pol.weight(a, PriorSample(0.0, T_moved, np.eye(6), None)) == pytest.approx(0.2)
    T_rot = lie.exp([0, 0, 0, 0, 0.25, 0])
    assert pol.weight(a, PriorSample(0.0, T_rot, np.eye(6), None)) == 0.0
    step = CorrectionPolicy(timeout=2.0, decay="step")
    assert step.weight(a, PriorSample(1.9, np.eye(4), np.eye(6))) == 1.0
    assert step.weight(a, PriorSample(2.0, np.eye(4), np.eye(6))) == 0.0
    with pytest.raises(PpoeError, match="decay"):
        CorrectionPolicy(decay="exp")
    with pytest.raises(PpoeError, match="disabled"):
        CorrectionPolicy(timeout=0, joint_motion=0, tool_translation=0, tool_rotation=0)


@pytest.mark.parametrize("rows", [6, 3, 1])
def test_correction_reproduces_posterior_at_its_anchor_and_vanishes_at_zero_weight(rows):
    rng = np.random.default_rng(10 + rows)
    T = _random_pose(rng)
    P = _random_cov(rng, 0.05)
    H = rng.normal(size=(rows, 6))
    R = np.diag(rng.uniform(1e-4, 1e-3, rows))
    T_meas = T @ lie.exp(rng.multivariate_normal(np.zeros(6), P))
    res = LinearUpdater()(T, P, Measurement(0.0, "test", (T_meas, H, R)))
    anchor = PriorSample(0.0, T, P)
    corr = CarriedCorrection.from_update(anchor, res.T_base_tool, res.cov_tool)
    assert corr.H.shape == (rows, 6)
    T_f, P_f = corr.apply(anchor, 1.0)
    np.testing.assert_allclose(T_f, res.T_base_tool, atol=1e-9)
    np.testing.assert_allclose(P_f, res.cov_tool, atol=1e-9 * np.abs(P).max())
    T_0, P_0 = corr.apply(anchor, 0.0)
    np.testing.assert_allclose(T_0, T)
    np.testing.assert_allclose(P_0, P)
    # a half weight lies in between: covariance between posterior and prior (PSD order)
    _, P_h = corr.apply(anchor, 0.5)
    assert np.linalg.eigvalsh(P - P_h).min() > -1e-12
    assert np.linalg.eigvalsh(P_h - res.cov_tool).min() > -1e-12


def test_correction_with_rank_deficient_prior():
    """A prior certain about some directions (rank 3) must not break the inversion."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 3)) * 0.01
    P = A @ A.T
    T = _random_pose(rng)
    T_meas = T @ lie.exp(A @ rng.normal(size=3))
    res = LinearUpdater()(T, P, Measurement(0.0, "t", (T_meas, np.eye(6), 1e-6 * np.eye(6))))
    corr = CarriedCorrection.from_update(PriorSample(0.0, T, P), res.T_base_tool, res.cov_tool)
    T_f, P_f = corr.apply(PriorSample(0.0, T, P), 1.0)
    np.testing.assert_allclose(T_f, res.T_base_tool, atol=1e-9)
    np.testing.assert_allclose(P_f, res.cov_tool, atol=1e-12)


# ----------------------------------------------------------------------------
# FusionPipeline
# ----------------------------------------------------------------------------


def _setup(seed=0, **kw):
    rng = np.random.default_rng(seed)
    T_true = _random_pose(rng, 0.5)
    P = np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3])
    err = rng.multivariate_normal(np.zeros(6), P)
    T_prior = T_true @ lie.exp(-err)  # the kinematics is off by err
    upd = LinearUpdater(gate=kw.pop("gate", 1e9))
    pipe = FusionPipeline(upd, **kw)
    return rng, T_true, T_prior, P, upd, pipe


def _err(T, T_true):
    return float(np.linalg.norm(lie.ominus(T_true, T)[:3]))


def test_pipeline_correction_is_carried_to_newer_priors_and_decays():
    rng, T_true, T_prior, P, upd, pipe = _setup(
        policy=CorrectionPolicy(timeout=1.0, joint_motion=0, tool_translation=0, tool_rotation=0)
    )
    for k in range(5):
        pipe.add_prior(0.01 * k, T_prior, P)
    meas = Measurement(0.015, "/tag", (T_true, np.eye(6)[:3], 1e-8 * np.eye(3)))
    out = pipe.add_measurement(meas)
    assert out.status == "accepted"
    assert _err(out.estimate.T_base_tool, T_true) < 0.05 * _err(T_prior, T_true)
    # a newer prior (static arm, same kinematics error) gets the correction, weight 1 - dt/1s
    est, _ = pipe.add_prior(0.515, T_prior, P)
    assert est.weight == pytest.approx(0.5)
    assert _err(est.T_base_tool, T_true) < 0.6 * _err(T_prior, T_true)
    assert np.trace(est.cov_tool) < np.trace(P)
    est, _ = pipe.add_prior(0.05, T_prior, P)  # late but in the window: weight from |dt|
    assert est.weight == pytest.approx(1 - 0.035)
    # after the timeout it is dropped and counted, the prior passes unchanged
    est, _ = pipe.add_prior(1.1, T_prior, P)
    assert est.weight == 0.0 and pipe.correction is None
    np.testing.assert_allclose(est.T_base_tool, T_prior)
    assert pipe.counts["corrections_dropped"] == 1
    assert pipe.counts["accepted"] == 1


def test_pipeline_drops_correction_after_joint_motion():
    rng, T_true, T_prior, P, upd, pipe = _setup(policy=CorrectionPolicy(timeout=100, joint_motion=0.05))
    pipe.add_prior(0.0, T_prior, P, joints=np.zeros(7))
    pipe.add_prior(0.01, T_prior, P, joints=np.zeros(7))
    assert pipe.add_measurement(Measurement(0.005, "/tag", (T_true, np.eye(6), 1e-8 * np.eye(6)))).status == "accepted"
    q = np.zeros(7)
    q[3] = 0.02
    est, _ = pipe.add_prior(0.02, T_prior, P, joints=q)
    assert est.weight == pytest.approx(1 - 0.4, abs=1e-3)
    q[3] = 0.06
    est, _ = pipe.add_prior(0.03, T_prior, P, joints=q)
    assert est.weight == 0.0 and pipe.correction is None
    assert pipe.counts["corrections_dropped"] == 1


def test_pipeline_stale_pending_gap_and_flush():
    rng, T_true, T_prior, P, upd, pipe = _setup(buffer_duration=0.5, max_gap=0.05, max_hold=0.2)
    for k in range(101):  # 0 .. 1 s at 100 Hz
        pipe.add_prior(0.01 * k, T_prior, P)
    m = (T_true, np.eye(6), 1e-6 * np.eye(6))
    assert pipe.add_measurement(Measurement(0.2, "/tag", m)).status == "stale"
    assert pipe.counts["dropped_stale"] == 1
    # newer than the newest prior: pending until a prior covers it
    assert pipe.add_measurement(Measurement(1.005, "/tag", m)).status == "pending"
    assert upd.calls == 0
    est, outs = pipe.add_prior(1.01, T_prior, P)
    assert [o.status for o in outs] == ["accepted"]
    assert est.weight > 0.99 and _err(est.T_base_tool, T_true) < 0.1 * _err(T_prior, T_true)
    # the last stop ends; a measurement after it is held at the last prior by flush()
    assert pipe.add_measurement(Measurement(1.1, "/tag", m)).status == "pending"
    assert pipe.add_measurement(Measurement(1.5, "/tag", m)).status == "pending"
    assert pipe.flush(older_than=1.2)[0].status == "accepted"
    assert len(pipe.pending) == 1
    assert [o.status for o in pipe.flush()] == ["no_prior"]  # 0.49 s > max_hold
    assert pipe.counts["dropped_no_prior"] == 1
    assert pipe.counts["measurements"] == 4


def test_pipeline_gating_bad_input_and_time_jump():
    rng, T_true, T_prior, P, upd, pipe = _setup(gate=16.8)  # chi2(6) 99 %
    pipe.add_prior(0.0, T_prior, P)
    pipe.add_prior(0.1, T_prior, P)
    outlier = T_true @ lie.exp([0.5, 0, 0, 0, 0, 0])  # 50 sigma
    out = pipe.add_measurement(Measurement(0.05, "/tag", (outlier, np.eye(6), 1e-6 * np.eye(6))))
    assert out.status == "rejected" and out.nis > 16.8
    bad = np.full((4, 4), np.nan)
    out = pipe.add_measurement(Measurement(0.05, "/tag", (bad, np.eye(6), np.eye(6))))
    assert out.status == "bad" and "/tag" in out.error and "NaN" in out.error
    assert pipe.correction is None
    assert pipe.counts["rejected"] == 1 and pipe.counts["bad"] == 1
    with pytest.raises(PpoeError, match="stamp 0.2"):
        pipe.add_prior(0.2, T_prior, -np.eye(6))
    # a stamp far behind the newest (bag restarted) resets the buffer
    pipe.add_prior(50.0, T_prior, P)
    est, _ = pipe.add_prior(1.0, T_prior, P)
    assert est is not None and pipe.counts["resets"] == 1 and len(pipe.buffer) == 1


def test_pipeline_sequential_updates_accumulate_information():
    """Two partial measurements at the same static pose: the carried correction equals the
    joint linear update (information from both)."""
    rng, T_true, T_prior, P, upd, pipe = _setup(seed=5)
    pipe.add_prior(0.0, T_prior, P)
    pipe.add_prior(0.1, T_prior, P)
    Ra = 1e-6 * np.eye(3)
    pipe.add_measurement(Measurement(0.05, "/a", (T_true, np.eye(6)[:3], Ra)))
    pipe.add_measurement(Measurement(0.05, "/b", (T_true, np.eye(6)[3:], Ra)))
    est = pipe.fused_at(0.05)
    joint = LinearUpdater()(T_prior, P, Measurement(0.05, "/ab", (T_true, np.eye(6), 1e-6 * np.eye(6))))
    np.testing.assert_allclose(est.cov_tool, joint.cov_tool, rtol=1e-3, atol=1e-12)
    assert _err(est.T_base_tool, T_true) < 1e-3
    assert pipe.counts["accepted"] == 2


def test_pipeline_same_source_replaces_its_correction():
    """A source repeating the same (systematically wrong) measurement does not pile up
    confidence: the second update replaces the first; another source still combines."""
    rng, T_true, T_prior, P, upd, pipe = _setup(seed=6)
    pipe.add_prior(0.0, T_prior, P)
    pipe.add_prior(0.1, T_prior, P)
    m = Measurement(0.05, "/contact", (T_true, np.eye(6)[:1], np.array([[1e-4]])))
    pipe.add_measurement(m)
    cov_once = pipe.fused_at(0.05).cov_tool
    for _ in range(20):
        pipe.add_measurement(m)
    np.testing.assert_allclose(pipe.fused_at(0.05).cov_tool, cov_once, rtol=1e-6, atol=1e-14)
    assert len(pipe.corrections) == 1 and pipe.counts["accepted"] == 21
    # the single update equals the 1D linear Kalman update of the prior
    ref = LinearUpdater()(T_prior, P, m)
    np.testing.assert_allclose(cov_once, ref.cov_tool, rtol=1e-6, atol=1e-14)
    pipe.add_measurement(Measurement(0.05, "/tag", (T_true, np.eye(6)[1:2], np.array([[1e-4]]))))
    assert len(pipe.corrections) == 2
    assert pipe.fused_at(0.05).cov_tool[1, 1] < 0.6 * cov_once[1, 1]
    assert pipe.fused_at(0.05).cov_tool[0, 0] == pytest.approx(cov_once[0, 0], rel=0.2)


def test_pipeline_fused_error_monte_carlo_consistency():
    """Seeded Monte-Carlo: with a correct prior covariance and a 1D measurement, the fused
    error at a later static prior has the covariance the pipeline reports."""
    rng = np.random.default_rng(42)
    P = np.diag([4e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3])
    P[0, 4] = P[4, 0] = 5e-4  # correlated, as PPOE covariances are
    H = np.array([[1.0, 0, 0, 0, 0, 0]])
    R = np.array([[1e-6]])
    errs, covs = [], []
    for _ in range(400):
        e = rng.multivariate_normal(np.zeros(6), P)
        T_true = np.eye(4)
        T_prior = T_true @ lie.exp(-e)
        z_pose = T_true @ lie.exp(np.array([rng.normal() * 1e-3, 0, 0, 0, 0, 0]))
        pipe = FusionPipeline(LinearUpdater(), policy=CorrectionPolicy(timeout=10.0))
        pipe.add_prior(0.0, T_prior, P)
        pipe.add_measurement(Measurement(0.0, "/m", (z_pose, H, R)))
        est, _ = pipe.add_prior(0.5, T_prior, P)  # weight 0.95
        errs.append(lie.ominus(T_true, est.T_base_tool))
        covs.append(est.cov_tool)
    errs = np.array(errs)
    emp = np.cov(errs.T)
    rep = np.mean(covs, axis=0)
    # correlated rotation error is corrected through the correlation: x and ry shrink
    assert emp[0, 0] < 0.02 * P[0, 0]
    assert emp[4, 4] < 0.6 * P[4, 4]
    # reported covariance matches the empirical one (within Monte-Carlo error, 400 samples)
    for i in (0, 4):
        assert 0.7 < emp[i, i] / rep[i, i] < 1.4


# ----------------------------------------------------------------------------
# ModelUpdater with the project's PPOE models (rover tags, humanoid contact)
# ----------------------------------------------------------------------------


from conftest import CONFIG  # noqa: E402

from ppoe_core.estimation import measurements as mm  # noqa: E402
from ppoe_core.estimation.pipeline import ContactMeasurement, ModelUpdater, TagMeasurement  # noqa: E402

#: a rover configuration in which tag 0 faces the mast camera
ROVER_Q = {"pan_joint": -0.378, "tilt_joint": 1.477, "arm_joint_1": -0.247, "arm_joint_2": 1.532,
           "arm_joint_3": 0.302, "arm_joint_4": -0.302, "arm_joint_5": -0.991, "arm_joint_6": 1.294}


@pytest.fixture(scope="module")
def rover():
    from ppoe_core import PPOEModel

    return PPOEModel.from_files(CONFIG / "robots" / "rover.urdf", CONFIG / "robots" / "rover_model.yaml")


def rover_tag_points(model, T_base_tool_true, q, rng, pixel_sigma=0.5, f=600.0):
    """Simulated tag observation of the visible tags of ROVER_Q (normalised coords + noise)."""
    T_base_cam = model.fk_mean(q, "base_link", "camera_optical_frame")
    ids, corners, xy = [], [], []
    for tid, item in model.config.tags.by_id().items():
        T_tool_link = model.fk_mean(q, "tool_link", item.link)
        P_tool = mm.tag_points(item.size, T_tool_link @ item.T_link_tag)
        T_cam_tool = lie.inverse(T_base_cam) @ T_base_tool_true
        P = P_tool @ T_cam_tool[:3, :3].T + T_cam_tool[:3, 3]
        normal = (T_cam_tool @ T_tool_link @ item.T_link_tag)[:3, 2]
        if np.any(P[:, 2] < 0.1) or normal @ P[0] / np.linalg.norm(P[0]) > -0.3:
            continue
        ids += [tid] * 5
        corners += list(range(5))
        xy.append(P[:, :2] / P[:, 2:] + rng.normal(size=(5, 2)) * pixel_sigma / f)
    assert ids, "no tag visible in the rover test configuration"
    xy = np.concatenate(xy)
    return TagMeasurement("camera_optical_frame", np.array(ids), np.array(corners), xy, fx=f, fy=f)


def test_model_updater_tags_correct_the_rover_kinematics(rover):
    """Seeded simulation: true kinematics drawn from the PPOE model, one image of tag 0; the
    fused tool position is much closer to the truth than the kinematics prior."""
    rng = np.random.default_rng(7)
    q = np.array([ROVER_Q[n] for n in rover.joint_names])
    T_prior, P_prior = rover.fk(ROVER_Q, "base_link", "tool_link")
    err_prior, err_fused, nees, statuses = [], [], [], []
    for _ in range(25):
        T_true = rover.sample(ROVER_Q, "base_link", "tool_link", n=1, rng=rng)[0]
        pipe = FusionPipeline(ModelUpdater(rover, "base_link", "tool_link", max_iterations=5,
                                           gate_probability=0.9999))
        pipe.add_prior(0.0, T_prior, P_prior, q)
        pipe.add_prior(0.1, T_prior, P_prior, q)
        out = pipe.add_measurement(Measurement(0.05, "/tag_bearing/observations",
                                               TagMeasurement(**vars(rover_tag_points(rover, T_true, ROVER_Q, rng)))))
        assert out.status in ("accepted", "rejected"), out.error
        statuses.append(out.status)
        est, _ = pipe.add_prior(0.2, T_prior, P_prior, q)  # carried to the next prior
        err_prior.append(np.linalg.norm(T_prior[:3, 3] - T_true[:3, 3]))
        err_fused.append(np.linalg.norm(est.T_base_tool[:3, 3] - T_true[:3, 3]))
        e = lie.ominus(T_true, est.T_base_tool)
        if out.status == "accepted":
            nees.append(e @ np.linalg.solve(est.cov_tool, e))
    # the 99.73 % gate may reject an image whose linearisation is poor (5 deg plate bending)
    assert statuses.count("accepted") >= 22, statuses
    assert pipe.counts["accepted"] + pipe.counts["rejected"] == 1
    err_prior, err_fused = np.array(err_prior), np.array(err_fused)
    assert err_fused.mean() < 0.3 * err_prior.mean(), (err_fused.mean(), err_prior.mean())
    assert np.mean(err_fused < err_prior) > 0.8
    assert np.mean(nees) < 2 * 6  # consistent to within a factor 2 (weight 0.98 at 0.15 s)


def test_model_updater_bad_measurements_name_the_problem(rover):
    q = np.array([ROVER_Q[n] for n in rover.joint_names])
    T_prior, P_prior = rover.fk(ROVER_Q, "base_link", "tool_link")
    upd = ModelUpdater(rover, "base_link", "tool_link")
    pipe = FusionPipeline(upd)
    pipe.add_prior(0.0, T_prior, P_prior, q)
    rng = np.random.default_rng(1)
    good = rover_tag_points(rover, T_prior, ROVER_Q, rng)
    bad_frame = TagMeasurement("no_such_camera", good.ids, good.corners, good.xy, fx=600.0, fy=600.0)
    out = pipe.add_measurement(Measurement(0.0, "/obs", bad_frame))
    assert out.status == "bad" and "no_such_camera" in out.error
    unknown = TagMeasurement("camera_optical_frame", good.ids + 40, good.corners, good.xy, fx=600.0, fy=600.0)
    out = pipe.add_measurement(Measurement(0.0, "/obs", unknown))
    assert out.status == "bad" and "no point of a tag configured" in out.error
    assert upd.unknown_tag_points == len(good.ids)
    # joints unknown (NaN) but needed for the camera chain: the error names the joint
    pipe2 = FusionPipeline(ModelUpdater(rover, "base_link", "tool_link"))
    pipe2.add_prior(0.0, T_prior, P_prior, np.full(len(q), np.nan))
    out = pipe2.add_measurement(Measurement(0.0, "/obs", good))
    assert out.status == "bad" and "pan_joint" in out.error
    # focal length inferred from u, v when camera_info is missing
    uv = good.xy * 600.0 + [320.0, 240.0]
    inferred = TagMeasurement("camera_optical_frame", good.ids, good.corners, good.xy, uv=uv)
    assert pipe.add_measurement(Measurement(0.0, "/obs", inferred)).status == "accepted"


def test_model_updater_contact_corrects_distance_to_plane():
    """Humanoid contact study setup: the fingertip touches a plane; the fused fingertip lies
    much closer to the plane (along its normal) than the prior."""
    from ppoe_core import PPOEModel

    model = PPOEModel.from_files(CONFIG / "robots" / "humanoid.urdf", CONFIG / "robots" / "humanoid_model.yaml")
    base, tool = model.config.frames.base, model.config.frames.tool
    names = model.chain_joints(base, tool)
    q = {n: 0.2 for n in names}
    qv = np.array([q.get(n, 0.0) for n in model.joint_names])
    T_prior, P_prior = model.fk(q, base, tool)
    c = model.config.contact
    rng = np.random.default_rng(3)
    d_prior, d_fused = [], []
    for _ in range(20):
        T_true = model.sample(q, base, tool, n=1, rng=rng)[0]
        T_frame_plane = c.T_frame_plane.copy()
        n_plane = T_frame_plane[:3, 2]
        T_frame_plane[:3, 3] += n_plane * (n_plane @ (T_true[:3, 3] - T_frame_plane[:3, 3]))  # truth on plane
        pipe = FusionPipeline(ModelUpdater(model, base, tool))
        pipe.add_prior(0.0, T_prior, P_prior, qv)
        out = pipe.add_measurement(Measurement(0.0, "/contact/plane",
                                               ContactMeasurement(c.plane_frame, T_frame_plane, c.covariance)))
        assert out.status == "accepted", out.error
        d_prior.append(abs(n_plane @ (T_prior[:3, 3] - T_true[:3, 3])))
        d_fused.append(abs(n_plane @ (out.estimate.T_base_tool[:3, 3] - T_true[:3, 3])))
    # the plane tilt sigma (0.017 rad) at the fingertip's lever arm makes the contact a few-mm sensor
    assert np.mean(d_fused) < 0.7 * np.mean(d_prior), (np.mean(d_fused), np.mean(d_prior))


@pytest.mark.parametrize("gating", ["posterior", "prior"])
def test_model_updater_gates_a_10_sigma_outlier(rover, gating):
    """An image consistent with a tool pose 10 sigma away from the prior is rejected."""
    rng = np.random.default_rng(5)
    q = np.array([ROVER_Q[n] for n in rover.joint_names])
    T_prior, P_prior = rover.fk(ROVER_Q, "base_link", "tool_link")
    w, V = np.linalg.eigh(P_prior)
    T_far = T_prior @ lie.exp(10.0 * np.sqrt(w[-1]) * V[:, -1])
    upd = ModelUpdater(rover, "base_link", "tool_link", gating=gating)
    pipe = FusionPipeline(upd)
    pipe.add_prior(0.0, T_prior, P_prior, q)
    out = pipe.add_measurement(Measurement(0.0, "/obs", rover_tag_points(rover, T_far, ROVER_Q, rng)))
    assert out.status == "rejected" and out.nis > 100
    assert pipe.correction is None and pipe.counts["rejected"] == 1
    # a measurement of the prior's own pose passes, and the cost is small
    out = pipe.add_measurement(Measurement(0.0, "/obs", rover_tag_points(rover, T_prior, ROVER_Q, rng)))
    assert out.status == "accepted" and out.nis < 30


def test_posterior_cost_equals_prior_nis_for_a_linear_model():
    rng = np.random.default_rng(9)
    P = _random_cov(rng, 0.01)
    T = _random_pose(rng)
    obs = mm.PoseObservation(np.diag(rng.uniform(1e-6, 1e-5, 6)))
    z = T @ lie.exp(rng.multivariate_normal(np.zeros(6), P) * 1e-2)
    from update_reference import posterior_cost_reference

    from ppoe_core.estimation.fusion import iterated_update

    res = iterated_update(T, P, z, obs, max_iterations=10, gate_probability=None, with_cost=True)
    assert res.cost == pytest.approx(res.nis, rel=1e-3)
    assert res.cost == pytest.approx(posterior_cost_reference(obs, res.T, res.residual, res.correction, P), rel=1e-9)


def test_pipeline_min_interval_throttles_per_source():
    rng, T_true, T_prior, P, upd, pipe = _setup(min_interval=0.05)
    for k in range(11):
        pipe.add_prior(0.01 * k, T_prior, P)
    m = (T_true, np.eye(6)[:1], np.array([[1e-4]]))
    statuses = [pipe.add_measurement(Measurement(0.01 * k, "/contact", m)).status for k in range(11)]
    assert statuses == ["accepted", "throttled", "throttled", "throttled", "throttled", "accepted",
                        "throttled", "throttled", "throttled", "throttled", "accepted"]
    assert pipe.add_measurement(Measurement(0.01, "/tag", m)).status == "accepted"  # other source
    assert pipe.counts["throttled"] == 8 and upd.calls == 4


def test_two_cameras_on_one_topic_at_the_same_stamp_are_both_used():
    """Motoman bags: both cameras publish on /tag_bearing/observations with the same stamp and
    their own frame_id.  The source is topic + frame_id, so with the default min_interval
    neither throttles nor replaces the other: each corrects its own error component."""
    from ppoe_core.estimation.pipeline import FUSION_SETTINGS, source_key

    rng, T_true, T_prior, P, upd, pipe = _setup(min_interval=FUSION_SETTINGS["min_interval"])
    for k in range(3):
        pipe.add_prior(0.1 * k, T_prior, P)
    topic = "/tag_bearing/observations"
    cam1, cam2 = source_key(topic, "camera_1_optical_frame"), source_key(topic, "camera_2_optical_frame")
    assert cam1 != cam2 and topic in cam1
    assert source_key(topic, "") == topic
    R = np.array([[1e-10]])
    # camera 1 sees the x error, camera 2 the y error of the tool position, same stamp
    o1 = pipe.add_measurement(Measurement(0.1, cam1, (T_true, np.eye(6)[:1], R)))
    o2 = pipe.add_measurement(Measurement(0.1, cam2, (T_true, np.eye(6)[1:2], R)))
    assert (o1.status, o2.status) == ("accepted", "accepted")
    assert upd.calls == 2 and pipe.counts["throttled"] == 0
    assert set(pipe.corrections) == {cam1, cam2}
    est = pipe.fused_at(0.1)
    err_prior = lie.ominus(T_true, T_prior)
    err_fused = lie.ominus(T_true, est.T_base_tool)
    # both components corrected (to the 1e-5 m measurement noise), so both measurements were used
    assert abs(err_prior[0]) > 1e-3 or abs(err_prior[1]) > 1e-3
    assert abs(err_fused[0]) < 1e-4 and abs(err_fused[1]) < 1e-4
    # the same camera again at the same stamp is still throttled
    assert pipe.add_measurement(Measurement(0.1, cam1, (T_true, np.eye(6)[:1], R))).status == "throttled"


def test_make_pipeline_settings_and_node_defaults_agree(rover):
    """The node's parameter defaults and ppoe evaluate's replay use FUSION_SETTINGS."""
    from ppoe_core.estimation.pipeline import FUSION_SETTINGS, make_pipeline

    pipe = make_pipeline(rover, "base_link", "tool_link", {"min_interval": 0.2, "correction_decay": "step"})
    assert pipe.min_interval == 0.2 and pipe.policy.decay == "step"
    assert pipe.updater.gating == FUSION_SETTINGS["gating"]
    assert pipe.max_pending == FUSION_SETTINGS["max_pending"]
    with pytest.raises(PpoeError, match="unknown fusion setting.*'nope'"):
        make_pipeline(rover, "base_link", "tool_link", {"nope": 1})
    with pytest.raises(PpoeError, match="decay"):
        make_pipeline(rover, "base_link", "tool_link", {"correction_decay": "exp"})
    rclpy = pytest.importorskip("rclpy")  # noqa: F841
    from ppoe_ros.nodes.fusion_node import PARAMS

    defaults = {p.name: p.default for p in PARAMS}
    for k, v in FUSION_SETTINGS.items():
        assert defaults[k] == v, k


def test_add_prior_validated_skips_only_the_covariance_check():
    """validated=True (ppoe evaluate: the FK covariances are checked once as a batch) gives the same
    estimates; the shape is still checked, the PSD check is the caller's."""
    rng, T_true, T_prior, P, upd, pipe = _setup()
    _, _, _, _, _, pipe_v = _setup()
    m = Measurement(0.05, "/tag", (T_true, np.eye(6)[:3], 1e-6 * np.eye(3)))
    for k in range(4):
        T_k = T_prior @ lie.exp(np.r_[0.001 * k, 0, 0, 0, 0, 0])
        a, _ = pipe.add_prior(0.05 * k, T_k, P)
        b, _ = pipe_v.add_prior(0.05 * k, T_k, P, validated=True)
        assert np.array_equal(a.T_base_tool, b.T_base_tool) and np.array_equal(a.cov_tool, b.cov_tool)
        if k == 1:
            assert pipe.add_measurement(m).status == pipe_v.add_measurement(m).status == "accepted"
    with pytest.raises(MeasurementError, match="6x6"):
        pipe_v.add_prior(1.0, T_prior, np.eye(5), validated=True)
    from ppoe_core.errors import CovarianceError

    with pytest.raises(CovarianceError, match="prior at stamp"):
        pipe.add_prior(1.0, T_prior, -np.eye(6))


def test_add_prior_without_estimate_drops_and_counts_as_fuse():
    """``add_prior(estimate=False)`` (the offline replay) expires corrections exactly as ``fuse`` does: the same
    drops, counts and later estimates as a pipeline that fuses every prior."""
    rng = np.random.default_rng(21)
    policy = CorrectionPolicy(timeout=0.0, joint_motion=0.05, tool_translation=0.0, tool_rotation=0.0)
    pipes = [FusionPipeline(LinearUpdater(), policy=policy) for _ in range(2)]
    T = _random_pose(rng)
    out = {0: [], 1: []}
    for k in range(400):
        t = 0.01 * k
        T = T @ lie.exp(rng.normal(size=6) * 1e-3)
        q = np.array([0.1 * np.sin(2.0 * np.pi * k / 20.0), 0.0])  # out of the limit and back, every 20 priors
        cov = _random_cov(rng)
        m = Measurement(t, f"src{k % 2}", (T @ lie.exp(rng.normal(size=6) * 1e-3), np.eye(6)[:3], 1e-6 * np.eye(3)))
        for i, pipe in enumerate(pipes):
            est, _ = pipe.add_prior(t, T, cov, q, estimate=i == 0)
            assert (est is None) == (i == 1)
            if k % 40 == 0:
                pipe.add_measurement(m)
            if k % 20 == 19:  # back where the corrections were made
                out[i].append(pipe.fused_at(t))
    assert pipes[0].counts == pipes[1].counts
    assert pipes[0].counts["corrections_dropped"] > 0
    assert sorted(pipes[0].corrections) == sorted(pipes[1].corrections)
    for a, b in zip(out[0], out[1]):
        assert a.weight == b.weight


def _ratio_reference(pol: CorrectionPolicy, anchor: PriorSample, prior: PriorSample) -> float:
    """The former Python ``CorrectionPolicy.ratio`` (the compiled one must give its floats)."""
    import math

    r = 0.0
    if pol.timeout > 0.0:
        r = max(r, abs(prior.stamp - anchor.stamp) / pol.timeout)
    qa, qp = anchor.joints, prior.joints
    if pol.joint_motion > 0.0 and qa is not None and qp is not None and qa.shape == qp.shape:
        dq = [d for d in np.abs(qp - qa).tolist() if math.isfinite(d)]
        if dq:
            r = max(r, max(dq) / pol.joint_motion)
    if pol.tool_translation > 0.0 or pol.tool_rotation > 0.0:
        T_rel = (lie.inverse(anchor.T_base_tool) @ prior.T_base_tool).tolist()
        if pol.tool_translation > 0.0:
            x, y, z = T_rel[0][3], T_rel[1][3], T_rel[2][3]
            r = max(r, math.sqrt(x * x + y * y + z * z) / pol.tool_translation)
        if pol.tool_rotation > 0.0:
            c = min(max((T_rel[0][0] + T_rel[1][1] + T_rel[2][2] - 1.0) / 2.0, -1.0), 1.0)
            r = max(r, math.acos(c) / pol.tool_rotation)
    return r


def test_compiled_correction_ratio_equals_the_python_reference():
    """Bit for bit, including tiny rotations (the ill-conditioned acos), NaN joints, joints of another length and
    disabled limits."""
    rng = np.random.default_rng(44)
    pols = [CorrectionPolicy(), CorrectionPolicy(timeout=0.0, tool_rotation=0.0),
            CorrectionPolicy(timeout=3.0, joint_motion=0.0, tool_translation=0.0, tool_rotation=0.02)]
    for k in range(600):
        Ta = _random_pose(rng)
        qa = rng.normal(size=4)
        qp = qa + rng.normal(size=4) * 0.03
        if k % 5 == 0:
            qp[rng.integers(4)] = np.nan
        if k % 7 == 0:
            qp = qp[:3]
        anchor = PriorSample(float(rng.uniform(0, 5)), Ta, np.eye(6), qa)
        prior = PriorSample(float(rng.uniform(0, 5)), Ta @ lie.exp(rng.normal(size=6) * 10.0 ** rng.uniform(-9, 0)),
                            np.eye(6), None if k % 11 == 0 else qp)
        for pol in pols:
            assert pol.ratio(anchor, prior) == _ratio_reference(pol, anchor, prior)
            assert pol.ratio(anchor, prior, lie.inverse(Ta)) == _ratio_reference(pol, anchor, prior)


def _pipeline_state(pipe: FusionPipeline) -> tuple:
    """Everything add_priors must leave as the add_prior calls do."""
    buf = [(s.stamp, s.T_base_tool.tobytes(), s.cov_tool.tobytes(), None if s.joints is None else s.joints.tobytes())
           for s in pipe.buffer.samples()]
    corr = [(src, c.anchor.stamp, c.H.tobytes(), c.z.tobytes()) for src, c in pipe.corrections.items()]
    return dict(pipe.counts), list(pipe.buffer._stamps), buf, corr, [m.stamp for m in pipe.pending]


@pytest.mark.parametrize("seed", range(6))
def test_add_priors_equals_the_add_prior_sequence(seed):
    """Runs of priors through ``add_priors`` and through ``add_prior(estimate=False)`` one by one: the same buffer,
    corrections (expiring inside runs), counts, pending measurements and outcomes after every run, with
    measurements and queries between runs, pending measurements made ready inside a run, repeated and out-of-order
    stamps, a time jump, one covariance for all priors and a non-finite pose (the same error at the same prior)."""
    rng = np.random.default_rng(100 + seed)
    policy = CorrectionPolicy(timeout=0.5 if seed % 2 else 0.0, joint_motion=0.05,
                              tool_translation=0.0 if seed % 3 == 0 else 0.05, tool_rotation=0.1)
    grid = seed >= 3  # stamps on a dyadic grid: repeated stamps, a prior exactly at the buffer's cut-off
    pipes = [FusionPipeline(LinearUpdater(), policy=policy, buffer_duration=0.25 if grid else 0.3) for _ in range(2)]
    T, t, n_drop = _random_pose(rng), 0.0, 0
    cov_one = _random_cov(rng)
    for r in range(60):
        n = int(rng.integers(1, 40))
        dt = rng.integers(0, 3, size=n) * 0.0625 if grid else rng.uniform(0.0, 0.02, size=n)
        if r % 9 == 4:
            dt[n // 2] = -0.05  # out of order inside the run
        if r == 30:
            dt[0] = -5.0  # time jump: reset
        stamps = t + np.cumsum(dt)
        t = float(stamps.max())
        Ts = np.stack([T @ lie.exp(rng.normal(size=6) * 3e-3 * (k + 1)) for k in range(n)])
        T = Ts[-1]
        Q = 0.1 * np.sin(stamps[:, None] * np.array([3.0, 5.0]) + r)  # out of the joint limit and back
        covs = cov_one if r % 4 == 0 else np.stack([_random_cov(rng) for _ in range(n)])
        if r == 45:
            Ts[n // 2, 0, 0] = np.nan
        results = []
        for i, pipe in enumerate(pipes):
            try:
                if i == 0:
                    outs = pipe.add_priors(stamps, Ts, covs, Q, validated=True)
                else:
                    outs = []
                    for k in range(n):
                        outs += pipe.add_prior(float(stamps[k]), Ts[k], covs if covs.ndim == 2 else covs[k], Q[k],
                                               validated=True, estimate=False)[1]
                results.append(([(o.measurement.stamp, o.status) for o in outs], None))
            except MeasurementError as exc:
                results.append((None, str(exc)))
        assert results[0] == results[1]
        assert _pipeline_state(pipes[0]) == _pipeline_state(pipes[1])
        n_drop = pipes[0].counts["corrections_dropped"]
        m = Measurement(t + (0.01 if r % 3 == 0 else -0.005), f"src{r % 3}",
                        (T @ lie.exp(rng.normal(size=6) * 1e-3), np.eye(6)[: 2 + r % 4], 1e-6 * np.eye(2 + r % 4)))
        assert pipes[0].add_measurement(m).status == pipes[1].add_measurement(m).status
        a, b = pipes[0].fused_at(t - 0.01), pipes[1].fused_at(t - 0.01)
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a.T_base_tool, b.T_base_tool) and a.weight == b.weight
    assert n_drop > 0 and pipes[0].counts["resets"] == 1 and pipes[0].counts["accepted"] > 10


def test_fuse_with_one_correction_equals_weight_and_apply():
    """The one-correction path of ``fuse`` (weight, drop and update in one compiled call) gives the floats of
    ``policy.weight`` + ``apply_carried_corrections``, drops an expired correction only at a prior not older than
    its anchor, and counts the drop."""
    rng = np.random.default_rng(45)
    for decay in ("linear", "step"):
        policy = CorrectionPolicy(timeout=1.0, joint_motion=0.05, tool_translation=0.05, tool_rotation=0.1,
                                  decay=decay)
        for k in range(200):
            T = _random_pose(rng)
            anchor = PriorSample(1.0, T, _random_cov(rng), rng.normal(size=3))
            r = 1 + k % 6
            corr = CarriedCorrection(anchor, np.linalg.qr(rng.normal(size=(6, r)))[0].T, rng.uniform(1e-7, 1e-5, r),
                                     rng.normal(size=r) * 1e-3)
            prior = PriorSample(1.0 + rng.uniform(-1.2, 1.2), T @ lie.exp(rng.normal(size=6) * 0.02),
                                _random_cov(rng), anchor.joints + rng.normal(size=3) * 0.02)
            pipe = FusionPipeline(LinearUpdater(), policy=policy)
            pipe.corrections["cam"] = corr
            est = pipe.fuse(prior)
            w = policy.weight(anchor, prior, corr.T_anchor_inv)
            assert est.weight == w
            if w > 0.0:
                T_ref, cov_ref = apply_carried_corrections(prior, [(corr, w)])
                assert np.array_equal(est.T_base_tool, T_ref) and np.array_equal(est.cov_tool, cov_ref)
                assert "cam" in pipe.corrections
            else:
                assert est.T_base_tool is prior.T_base_tool and est.cov_tool is prior.cov_tool
                dropped = prior.stamp >= anchor.stamp
                assert ("cam" in pipe.corrections) != dropped and pipe.counts["corrections_dropped"] == int(dropped)


def test_warm_pipeline_compiles_the_per_prior_kernels_in_a_fresh_process():
    """The nodes call warm_pipeline before subscribing: afterwards the per-prior kernels are compiled (or loaded),
    so the first message does not pay for it."""
    import subprocess
    import sys

    code = ("from ppoe_core.estimation.warmup import warm_pipeline\n"
            "from ppoe_core.estimation import correction_kernels as ck\n"
            "names = ('prior_passes', 'correction_ratio', 'fuse_one_kernel', 'run_breaks')\n"
            "from ppoe_core.estimation import pose_fields as pf\n"
            "assert not any(getattr(ck, n).signatures for n in names)\n"
            "from ppoe_core.lie import kernels as lk\n"
            "assert not pf.prior_from_fields.signatures and not lk.pose_cov_fields_into.signatures\n"
            "warm_pipeline()\n"
            "print(','.join(n for n in names if not getattr(ck, n).signatures))\n"
            "print(','.join(n for n, m in (('prior_from_fields', pf), ('pose_cov_fields_into', lk))\n"
            "               if not getattr(m, n).signatures))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "", f"not compiled by warm_pipeline: {out.stdout}"
