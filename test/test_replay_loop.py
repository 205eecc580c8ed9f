"""The replay's loop (ppoe_core.analysis.evaluate.replay_loop): intervals between measurements, slots without a
measurement inside an interval, the ground-truth stamps of an interval with the priors before each."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from ppoe_core.analysis.evaluate.replay_loop import MeasurementSlots, chunk_bounds, replay_events, replay_order


class _Tags(SimpleNamespace):
    """A TagStream stand-in: slot k's measurement or None, counting the reads."""

    def get(self, k):
        self.reads.append(k)
        return self.items[k]


class _Pipe:
    """Records what the loop hands a pipeline."""

    def __init__(self):
        self.calls = []
        self.pending = []

    def priors_and_queries(self, stamps, T, cov, Q, tq, n_before, out, rows, *, validated, flush_margin):
        self.calls.append(("interval", stamps.tolist(), tq.tolist(), n_before.tolist(), rows.tolist()))
        out.found[rows] = True
        out.T_base_tool[rows] = T[np.maximum(n_before - 1, 0)] if len(T) else np.eye(4)
        return []

    def add_measurement(self, m):
        self.calls.append(("measurement", m.stamp))
        return SimpleNamespace(status="pending")

    def flush(self):
        self.calls.append(("flush",))
        return []


def _priors(stamps):
    n = len(stamps)
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 0, 3] = stamps
    return SimpleNamespace(stamps=np.asarray(stamps, float), T_all=T, cov_all=np.repeat(np.eye(6)[None], n, axis=0),
                           cov_naive=np.eye(6), Q=np.zeros((n, 2)))


def test_an_interval_goes_on_across_slots_without_a_measurement():
    # events: p0 p1 s0 p2 s1 p3 s2 p4 s3 gt0 p5 (s2 alone has a measurement)
    tags = _Tags(stamps=[1.5, 2.5, 3.5, 4.5], items=[None, None, SimpleNamespace(stamp=3.5), None], reads=[])
    slots = MeasurementSlots(tags, [])
    pri = _priors([1.0, 1.2, 2.0, 3.0, 4.0, 5.0])
    pipe = _Pipe()
    run = replay_events(pri, slots, np.array([4.7]), {"ppoe": pipe}, {"ppoe": SimpleNamespace(tags={})}, 2, False)
    assert pipe.calls == [
        ("interval", [1.0, 1.2, 2.0, 3.0], [], [], []),  # the empty slots 0 and 1 do not split the priors
        ("measurement", 3.5),
        ("interval", [4.0, 5.0], [4.7], [1], [0]),  # the empty slot 3 neither; gt0 after one prior of the interval
        ("flush",),
    ]
    assert tags.reads == [0, 1, 2, 3]  # taken in time order
    np.testing.assert_array_equal(run.est_T["ppoe"][0], pri.T_all[4])


def test_chunk_bounds_give_the_priors_and_the_ground_truth_of_events():
    ev = replay_order(np.array([1.0, 2.0, 3.0, 4.0]), np.array([2.0]), np.array([0.5, 2.0, 3.5, 9.0]))
    # order: gt0(0.5) p0(1) p1(2) s0(2) gt1(2) p2(3) gt2(3.5) p3(4) gt3(9)
    np.testing.assert_array_equal(ev.kind, [2, 0, 0, 1, 2, 0, 2, 0, 2])
    pa, pb, gt, n_before = chunk_bounds(ev, 0, 3)
    assert (pa, pb) == (0, 2) and gt.tolist() == [0] and n_before.tolist() == [0]
    pa, pb, gt, n_before = chunk_bounds(ev, 4, 9)
    assert (pa, pb) == (2, 4) and gt.tolist() == [1, 2, 3] and n_before.tolist() == [0, 1, 2]
