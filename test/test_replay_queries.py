"""The compiled path of ``FusionPipeline.priors_and_queries`` (ppoe_core.estimation.pipeline_queries) against the
calls one by one (``batched=False``, the reference: add_priors, flush, lookup_hold, fuse), on randomized event
sequences: corrections expiring by time, joint motion and tool motion (the weight not monotone in either), drops
between queries, several sources, pending measurements, queries without a prior, priors out of order."""

from __future__ import annotations

import numpy as np
import pytest

from ppoe_core import lie
from ppoe_core.errors import MeasurementError
from ppoe_core.estimation import correction_kernels as ck
from ppoe_core.estimation.corrections import correction_kernels
from ppoe_core.estimation.pipeline import (
    CorrectionPolicy, FusionPipeline, Measurement, PriorSample, ToolUpdate, apply_carried_corrections,
)
from ppoe_core.estimation.pipeline_queries import QueryEstimates, priors_and_queries

FLUSH = 1e-6


class ShiftUpdater:
    """Test updater: the posterior is the estimate moved by the payload's twist (tool frame) with its covariance
    scaled down; a payload of None is rejected."""

    def __call__(self, T, P, m: Measurement, prior=None) -> ToolUpdate:
        if m.payload is None:
            return ToolUpdate(T, P, False, 50.0)
        xi, scale = m.payload
        return ToolUpdate(T @ lie.exp(np.asarray(xi)), P * scale, True, 1.0)


@pytest.fixture
def kernel_calls(monkeypatch):
    """Counts the compiled path's calls."""
    mod = correction_kernels()
    calls = []
    real = mod.held_queries_kernel

    def counting(*args):
        status = real(*args)
        calls.append(status)
        return status

    monkeypatch.setattr(mod, "held_queries_kernel", counting)
    return calls


def _pipe(policy: CorrectionPolicy, **kw) -> FusionPipeline:
    return FusionPipeline(ShiftUpdater(), buffer_duration=kw.get("buffer_duration", 1.0), max_gap=0.2,
                          max_hold=kw.get("max_hold", 0.05), policy=policy, min_interval=kw.get("min_interval", 0.0))


def _trajectory(rng, n, dt=0.01, step_t=2e-3, step_r=4e-3, step_q=3e-3, n_joints=3):
    """Stamps, poses (a random walk with back-and-forth swings: the motion since an anchor is not monotone), joints
    and covariances of ``n`` priors."""
    t = 10.0 + dt * np.arange(n)
    T = np.empty((n, 4, 4))
    T[0] = np.eye(4)
    swing = np.sin(np.arange(n) * rng.uniform(0.05, 0.3))[:, None]
    xi = rng.normal(size=(n, 6)) * np.r_[[step_t] * 3, [step_r] * 3] + swing * rng.normal(size=6) * 0.5 * np.r_[
        [step_t] * 3, [step_r] * 3]
    for k in range(1, n):
        T[k] = T[k - 1] @ lie.exp(xi[k])
    Q = np.cumsum(rng.normal(size=(n, n_joints)) * step_q, axis=0) + swing * 0.01
    A = rng.normal(size=(n, 6, 6)) * 1e-2
    cov = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(6)
    return t, T, cov, Q


def _events(rng, t, n_meas, n_gt, sources, pending_every=0):
    """Measurements (stamp, source, payload) at prior stamps (or between, for pending ones) and ground-truth stamps
    (some exactly at priors, some after the last one)."""
    idx = np.sort(rng.choice(np.arange(5, len(t) - 1), size=n_meas, replace=False))
    meas = []
    for c, k in enumerate(idx):
        stamp = float(t[k]) + (0.004 if pending_every and c % pending_every == 0 else 0.0)
        payload = None if rng.random() < 0.1 else (rng.normal(size=6) * 1e-3, rng.uniform(0.2, 0.8))
        meas.append(Measurement(stamp, sources[c % len(sources)], payload))
    gt = np.sort(np.concatenate([rng.uniform(t[0] - 0.05, t[-1] + 0.2, n_gt - n_gt // 3),
                                 t[rng.choice(len(t), n_gt // 3, replace=False)]]))
    return meas, gt


def _replay(pipe, t, T, cov, Q, meas, gt, batched, shared_cov=False):
    """The event loop of ppoe evaluate (priors, then measurements, then ground truth at equal stamps), intervals
    between measurements through priors_and_queries."""
    ev_t = np.concatenate([t, [m.stamp for m in meas], gt])
    kind = np.concatenate([np.zeros(len(t), int), np.ones(len(meas), int), np.full(len(gt), 2)])
    idx = np.concatenate([np.arange(len(t)), np.arange(len(meas)), np.arange(len(gt))])
    order = np.lexsort((idx, kind, ev_t))
    kind, idx = kind[order], idx[order]
    out = QueryEstimates.empty(len(gt), None if Q is None else Q.shape[1])
    outcomes = []

    def interval(a, b):
        ks, gs = kind[a:b], idx[a:b]
        pri = gs[ks == 0]
        pa, pb = (int(pri[0]), int(pri[-1]) + 1) if len(pri) else (int(np.sum(kind[:a] == 0)),) * 2
        rows = gs[ks == 2]
        n_before = np.array([pa + np.sum(ks[:p] == 0) for p in np.flatnonzero(ks == 2)], dtype=np.int64) - pa
        c = cov[0] if shared_cov else cov[pa:pb]
        outcomes.extend((o.measurement.stamp, o.status) for o in priors_and_queries(
            pipe, t[pa:pb], T[pa:pb], c, None if Q is None else Q[pa:pb], gt[rows], n_before, out, rows,
            validated=True, flush_margin=FLUSH, batched=batched))

    start = 0
    for e in np.flatnonzero(kind == 1):
        interval(start, e)
        o = pipe.add_measurement(meas[idx[e]])
        outcomes.append((o.measurement.stamp, o.status))
        start = e + 1
    interval(start, len(kind))
    outcomes.extend((o.measurement.stamp, o.status) for o in pipe.flush())
    return out, outcomes


def _same(a: QueryEstimates, b: QueryEstimates):
    np.testing.assert_array_equal(a.found, b.found)
    for name in ("T_base_tool", "cov_tool", "prior_T", "prior_cov", "prior_joints"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None
            continue
        assert np.array_equal(x, y, equal_nan=True), name  # bit for bit


POLICIES = {
    "time": CorrectionPolicy(timeout=0.15, joint_motion=0.0, tool_translation=0.0, tool_rotation=0.0),
    "joints": CorrectionPolicy(timeout=0.0, joint_motion=0.01, tool_translation=0.0, tool_rotation=0.0),
    "translation": CorrectionPolicy(timeout=0.0, joint_motion=0.0, tool_translation=0.004, tool_rotation=0.0),
    "rotation": CorrectionPolicy(timeout=0.0, joint_motion=0.0, tool_translation=0.0, tool_rotation=0.008),
    "all": CorrectionPolicy(timeout=0.3, joint_motion=0.02, tool_translation=0.006, tool_rotation=0.012),
    "step": CorrectionPolicy(timeout=0.2, joint_motion=0.02, tool_translation=0.006, tool_rotation=0.012,
                             decay="step"),
}


@pytest.mark.parametrize("policy", sorted(POLICIES))
@pytest.mark.parametrize("seed", range(4))
def test_compiled_path_equals_the_calls_one_by_one(policy, seed, kernel_calls):
    rng = np.random.default_rng(100 * seed + len(policy))
    t, T, cov, Q = _trajectory(rng, 400)
    sources = ["/cam [a]"] if seed % 2 == 0 else ["/cam [a]", "/cam [b]"]
    meas, gt = _events(rng, t, 12, 150, sources, pending_every=3 if seed >= 2 else 0)
    shared = seed == 3
    ref = _pipe(POLICIES[policy])
    ref_out, ref_outcomes = _replay(ref, t, T, cov, Q, meas, gt, batched=False, shared_cov=shared)
    assert not kernel_calls
    fast = _pipe(POLICIES[policy])
    out, outcomes = _replay(fast, t, T, cov, Q, meas, gt, batched=True, shared_cov=shared)
    _same(ref_out, out)
    assert outcomes == ref_outcomes
    assert fast.counts == ref.counts
    assert {s: c.anchor.stamp for s, c in fast.corrections.items()} == \
        {s: c.anchor.stamp for s, c in ref.corrections.items()}
    assert len(kernel_calls) >= 5 and any(s >= 0 for s in kernel_calls)
    assert ref.counts["corrections_dropped"] > 0  # the sequences do exercise the drops
    assert ref_out.found.sum() > 100 and (~ref_out.found).sum() > 0


def test_the_random_sequences_drop_at_priors_and_at_queries_between_queries():
    """The randomized sequences above reach both drop sites: a prior inside an interval (between two queries) and a
    query itself (its own stamp further from the anchor than the prior it holds)."""
    rng = np.random.default_rng(7)
    t, T, cov, Q = _trajectory(rng, 400)
    meas, gt = _events(rng, t, 12, 150, ["/cam [a]"])
    at_prior = at_query = 0
    pipe = _pipe(POLICIES["time"])
    real_add, real_fuse = pipe.add_priors, pipe.fuse

    def add_priors(*a, **k):
        nonlocal at_prior
        before = pipe.counts["corrections_dropped"]
        res = real_add(*a, **k)
        at_prior += pipe.counts["corrections_dropped"] - before
        return res

    def fuse(*a, **k):
        nonlocal at_query
        before = pipe.counts["corrections_dropped"]
        res = real_fuse(*a, **k)
        at_query += pipe.counts["corrections_dropped"] - before
        return res

    pipe.add_priors, pipe.fuse = add_priors, fuse
    _replay(pipe, t, T, cov, Q, meas, gt, batched=False)
    assert at_prior > 0 and at_query > 0


def _one_correction(policy, n=60, q_path=None, T_path=None):
    """A pipeline with priors 0..9 and one correction anchored at prior 9 (stamp 10.09), and the next ``n`` priors
    (joints ``q_path``, poses ``T_path``)."""
    t = 10.0 + 0.01 * np.arange(10 + n)
    T = np.repeat(np.eye(4)[None], len(t), axis=0) if T_path is None else T_path
    Q = np.zeros((len(t), 2)) if q_path is None else q_path
    cov = np.repeat((np.eye(6) * 1e-4)[None], len(t), axis=0)
    pipe = _pipe(policy, max_hold=0.5)
    pipe.add_priors(t[:10], T[:10], cov[:10], Q[:10], validated=True)
    o = pipe.add_measurement(Measurement(float(t[9]), "/cam", (np.full(6, 1e-3), 0.5)))
    assert o.status == "accepted" and len(pipe.corrections) == 1
    return pipe, t[10:], T[10:], cov[10:], Q[10:]


@pytest.mark.parametrize("batched", [False, True])
def test_a_correction_dropped_at_a_prior_stays_dropped_when_the_arm_comes_back(batched, kernel_calls):
    """Joints swing out past the limit at prior 20 and back: a query before it gets the correction, every query after
    it the bare prior, although the joints are back within the limit (the weight is not monotone in the motion)."""
    n = 60
    q = np.zeros((10 + n, 2))
    q[10:, 0] = 0.03 * np.sin(np.pi * np.arange(n) / 40.0)  # peak 0.03 at prior 20 of the run, back to 0 at 40
    pipe, t, T, cov, Q = _one_correction(CorrectionPolicy(timeout=0.0, joint_motion=0.02, tool_translation=0.0,
                                                          tool_rotation=0.0), n, q_path=q)
    first_out = int(np.argmax(np.abs(Q[:, 0]) >= 0.02))
    assert 5 < first_out < 20
    tq = np.array([t[3], t[first_out - 1], t[first_out], t[45], t[55]])
    nb = np.array([4, first_out, first_out + 1, 46, 56])
    out = QueryEstimates.empty(5, 2)
    priors_and_queries(pipe, t, T, cov, Q, tq, nb, out, np.arange(5), validated=True, batched=batched)
    assert out.found.all()
    moved = ~np.all(out.T_base_tool == out.prior_T, axis=(1, 2))
    np.testing.assert_array_equal(moved, [True, True, False, False, False])
    assert abs(Q[nb[3] - 1, 0]) < 0.02  # back within the limit, still not applied
    assert not pipe.corrections and pipe.counts["corrections_dropped"] == 1
    assert len(kernel_calls) == int(batched)


@pytest.mark.parametrize("batched", [False, True])
def test_a_query_drops_the_correction_its_prior_kept(batched, kernel_calls):
    """Time limit 0.1 s from the anchor at 10.09 s: the priors up to 10.14 s keep the correction, the query at
    10.195 s holding the prior of 10.14 s is past the limit (weight 0, not older than the anchor): it drops the
    correction (no later prior would); the query at 10.145 s has the weight of its own stamp, not its prior's."""
    pipe, t, T, cov, Q = _one_correction(CorrectionPolicy(timeout=0.1, joint_motion=0.0, tool_translation=0.0,
                                                          tool_rotation=0.0), 5)
    corr = next(iter(pipe.corrections.values()))
    tq = np.array([10.12, 10.145, 10.195])
    out = QueryEstimates.empty(3, 2)
    priors_and_queries(pipe, t, T, cov, Q, tq, np.array([3, 5, 5]), out, np.arange(3), validated=True,
                       batched=batched)
    moved = ~np.all(out.T_base_tool == out.prior_T, axis=(1, 2))
    np.testing.assert_array_equal(moved, [True, True, False])
    assert not pipe.corrections and pipe.counts["corrections_dropped"] == 1
    w = 1.0 - abs(tq[1] - corr.anchor.stamp) / 0.1
    T_exp, cov_exp = apply_carried_corrections(PriorSample(tq[1], T[4], cov[4], Q[4]), [(corr, w)])
    np.testing.assert_array_equal(out.T_base_tool[1], T_exp)
    np.testing.assert_array_equal(out.cov_tool[1], cov_exp)
    assert len(kernel_calls) == int(batched)


@pytest.mark.parametrize("batched", [False, True])
def test_tool_motion_drops_at_the_prior_not_at_the_next_query(batched, kernel_calls):
    """The tool moves 3 cm away at prior 5 of the run and back at prior 6 (limit 2 cm): the query after prior 6 sees
    no correction, one after prior 4 sees it."""
    n = 10
    T = np.repeat(np.eye(4)[None], 10 + n, axis=0)
    T[15, 0, 3] = 0.03
    pipe, t, T, cov, Q = _one_correction(CorrectionPolicy(timeout=0.0, joint_motion=0.0, tool_translation=0.02,
                                                          tool_rotation=0.0), n, T_path=T)
    out = QueryEstimates.empty(2, 2)
    priors_and_queries(pipe, t, T, cov, Q, np.array([t[4], t[6]]), np.array([5, 7]), out, np.arange(2),
                       validated=True, batched=batched)
    moved = ~np.all(out.T_base_tool == out.prior_T, axis=(1, 2))
    np.testing.assert_array_equal(moved, [True, False])
    assert pipe.counts["corrections_dropped"] == 1


def test_queries_without_a_prior_and_the_buffers_newest_prior(kernel_calls):
    """An empty buffer (queries before the first prior: none), a query held from the buffer's newest prior before
    the run's first, a query further than max_hold from the newest prior (none), a query exactly at a prior."""
    rng = np.random.default_rng(3)
    t, T, cov, Q = _trajectory(rng, 30)
    outs = []
    for batched in (False, True):
        pipe = _pipe(POLICIES["all"], max_hold=0.05)
        out = QueryEstimates.empty(6, 3)
        priors_and_queries(pipe, t[:10], T[:10], cov[:10], Q[:10], np.array([9.0, 9.99]), np.array([0, 0]), out,
                           np.array([0, 1]), validated=True, batched=batched)
        pipe.add_measurement(Measurement(float(t[9]), "/cam", (np.full(6, 1e-3), 0.5)))
        priors_and_queries(pipe, t[10:], T[10:], cov[10:], Q[10:], np.array([t[9] + 0.003, t[12], t[29] + 0.04,
                                                                             t[29] + 0.06]),
                           np.array([0, 3, 20, 20]), out, np.array([2, 3, 4, 5]), validated=True, batched=batched)
        outs.append(out)
    _same(*outs)
    np.testing.assert_array_equal(outs[1].found, [False, False, True, True, True, False])
    np.testing.assert_array_equal(outs[1].prior_T[3], T[12])
    assert len(kernel_calls) == 2


def test_priors_out_of_order_take_the_calls_one_by_one(kernel_calls):
    rng = np.random.default_rng(4)
    t, T, cov, Q = _trajectory(rng, 40)
    t[25] = t[23]  # out of order
    outs = []
    for batched in (False, True):
        pipe = _pipe(POLICIES["all"])
        pipe.add_priors(t[:10], T[:10], cov[:10], Q[:10], validated=True)
        pipe.add_measurement(Measurement(float(t[9]), "/cam", (np.full(6, 1e-3), 0.5)))
        out = QueryEstimates.empty(3, 3)
        priors_and_queries(pipe, t[10:29], T[10:29], cov[10:29], Q[10:29], np.array([t[12], t[24], t[28]]),
                           np.array([3, 15, 19]), out, np.arange(3), validated=True, batched=batched)
        outs.append((out, dict(pipe.counts)))
    _same(outs[0][0], outs[1][0])
    assert outs[0][1] == outs[1][1] and outs[1][1]["priors_out_of_order"] == 1
    assert kernel_calls == [-1]  # tried, refused, nothing done


@pytest.mark.parametrize("batched", [False, True])
def test_a_pose_that_is_not_finite_is_refused_as_add_priors_refuses_it(batched):
    rng = np.random.default_rng(5)
    t, T, cov, Q = _trajectory(rng, 20)
    T[12, 0, 0] = np.nan
    out = QueryEstimates.empty(1, 3)
    with pytest.raises(MeasurementError, match="finite"):
        priors_and_queries(_pipe(POLICIES["all"]), t, T, cov, Q, t[15:16], np.array([16]), out, np.arange(1),
                           validated=True, batched=batched)


def test_n_before_and_rows_are_checked():
    pipe = _pipe(POLICIES["all"])
    t = 10.0 + 0.01 * np.arange(3)
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    out = QueryEstimates.empty(2, None)
    with pytest.raises(ValueError, match="n_before"):
        priors_and_queries(pipe, t, T, np.eye(6) * 1e-4, None, t[:2], np.array([2, 1]), out, np.arange(2),
                           validated=True)
    with pytest.raises(ValueError, match="rows"):
        priors_and_queries(pipe, t, T, np.eye(6) * 1e-4, None, t[:2], np.array([1, 2]), out, np.array([0, 2]),
                           validated=True)


def test_numpy_stacked_and_single_products_give_the_same_floats():
    """The compiled path takes the tool motion of every prior from one stacked product ``T_anchor^-1 @ T``, the
    reference (``fuse``) from one product per prior: the angle from the trace is ill-conditioned near 0, so the two
    must be the same floats."""
    rng = np.random.default_rng(9)
    A = lie.inverse(lie.exp(rng.normal(size=6)))
    T = lie.exp(rng.normal(size=(200, 6)) * 1e-3)
    stacked = A @ T
    for k in range(len(T)):
        assert np.array_equal(stacked[k], A @ T[k])


def test_the_kernel_module_exports_the_compiled_path():
    assert "held_queries_kernel" in ck.__all__ and "held_queries_checks" in ck.__all__
