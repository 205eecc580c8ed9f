"""JointHistory and StampResetPolicy: the one joint-history rule (split joint states merged per joint with a maximum
age, refused names, stamps, the history by stamp) of every node and of ``ppoe evaluate``."""

from __future__ import annotations

import numpy as np
import pytest

from ppoe_core.errors import JointValueError
from ppoe_core.model.joint_history import JointHistory
from ppoe_core.model.stamp_policy import StampRefused, StampResetPolicy

MS = 1_000_000
S = 1_000_000_000


def test_split_messages_merge_until_a_joint_is_too_old():
    m = JointHistory(["a", "b", "c"], max_age_ns=500 * MS)
    u = m.update(["a", "b"], [1.0, 2.0], 0)
    assert u.values is None and u.why == "needed joint(s) not seen yet: c" and u.kind == "incomplete"
    np.testing.assert_array_equal(m.update(["c", "gripper"], [3.0, 9.0], 10 * MS).values, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(m.update(["b", "a"], [5.0, 4.0], 400 * MS).values, [4.0, 5.0, 3.0])
    u = m.update(["a", "b"], [6.0, 7.0], 600 * MS)  # c is 590 ms old
    assert u.values is None and u.why == "needed joint(s) older than 0.5 s: c"
    u = m.update(["gripper"], [1.0], 610 * MS)
    assert u.values is None and u.kind == "ignored" and u.why == "carries none of the chain's joints"
    q = m.update(["a", "b", "c"], [1.0, 1.0, 1.0], 620 * MS).values
    np.testing.assert_array_equal(q, [1.0, 1.0, 1.0])
    q[0] = 99.0  # a returned vector is the caller's
    np.testing.assert_array_equal(m.update(["c"], [2.0], 630 * MS).values, [1.0, 1.0, 2.0])


def test_no_age_limit_and_bad_values():
    m = JointHistory(["a", "b"])
    m.update(["a"], [1.0], 0)
    np.testing.assert_array_equal(m.update(["b"], [2.0], 1000 * S).values, [1.0, 2.0])  # 1000 s later: still used
    with pytest.raises(JointValueError, match="'b'"):
        m.update(["a", "b"], [1.0, float("nan")], 1000 * S + 1)
    with pytest.raises(ValueError, match="2 names but 1 positions"):
        m.update(["a", "b"], [1.0], 1000 * S + 2)


def test_a_joint_named_twice_is_an_error_for_that_message():
    """Issue 25: the same joint name twice in one message refuses the message (named), whatever its values."""
    m = JointHistory(["a", "b"])
    m.update(["a", "b"], [1.0, 2.0], 0)
    with pytest.raises(JointValueError, match="lists joint\\(s\\) 'a' more than once"):
        m.update(["a", "b", "a"], [5.0, 2.0, 6.0], 10 * MS)
    np.testing.assert_array_equal(m.values, [1.0, 2.0])  # nothing of it was taken


def test_a_misspelt_needed_joint_does_not_reuse_the_held_value():
    """Issue 25: ``joint_２`` (full-width 2) where ``joint_2`` is needed: the message is refused, naming both, and the
    held value of the real joint is not used; a name outside the URDF next to every needed joint is fine."""
    urdf = ["joint_1", "joint_2", "gripper"]
    m = JointHistory(["joint_1", "joint_2"], known=urdf, max_age_ns=500 * MS)
    m.update(["joint_1", "joint_2"], [0.1, 0.2], 0)
    misspelt = "'joint_２' \\(looks like 'joint_2'\\).*lacks needed joint\\(s\\) 'joint_2'"
    with pytest.raises(JointValueError, match=misspelt):
        m.update(["joint_1", "joint_２"], [0.3, 0.4], 10 * MS)
    np.testing.assert_array_equal(m.update(["joint_1", "joint_2", "camera_tilt"], [0.5, 0.6, 1.0], 20 * MS).values,
                                  [0.5, 0.6])
    u = m.update(["joint_２"], [0.4], 30 * MS)  # no needed joint at all: ignored, the name said
    assert u.kind == "ignored" and "'joint_２' (looks like 'joint_2')" in u.why


def test_stamp_policy_drops_small_backward_jumps_and_starts_a_new_timeline_on_large_ones():
    m = JointHistory(["a"], policy=StampResetPolicy(1.0))
    m.update(["a"], [1.0], 10 * S)
    with pytest.raises(StampRefused, match="jumped back by 0.500000 s") as err:
        m.update(["a"], [2.0], 10 * S - 500 * MS)
    assert err.value.kind == "jumped_back"
    u = m.update(["a"], [3.0], 5 * S)
    assert "new timeline" in u.new_timeline and u.values is not None


def test_a_future_stamp_is_refused_and_does_not_hold_back_later_messages():
    """Issue 25: a stamp 0.9 s ahead of the clock is refused (not taken), and the valid messages after it are taken
    (before the fix it was taken, and every valid message for 1 s after it was dropped as jumped back)."""
    policy = StampResetPolicy(1.0, future_tolerance_s=0.5)
    m = JointHistory(["a"], policy=policy)
    now = 100 * S
    m.update(["a"], [1.0], now, now_ns=now)
    with pytest.raises(StampRefused, match="0.899 s ahead of the clock") as err:
        m.update(["a"], [2.0], now + 900 * MS, now_ns=now + 1 * MS)
    assert err.value.kind == "future_stamp"
    for k in range(1, 5):
        assert m.update(["a"], [3.0], now + 10 * k * MS, now_ns=now + 10 * k * MS).values is not None
    assert policy.check(now + 400 * MS, None, now).verdict == "accept"  # within the tolerance
    assert StampResetPolicy(1.0).check(now + 10 * S, now, now).verdict == "accept"  # tolerance 0: off


def test_history_by_stamp_and_the_bounded_hold():
    m = JointHistory(["a", "b"], max_age_ns=500 * MS, keep_ns=2 * S)
    assert m.at(0) is None
    m.update(["a"], [1.0], 1 * S)
    m.update(["b"], [2.0], 1 * S + 10 * MS)
    m.update(["a", "b"], [3.0, 4.0], 2 * S)
    np.testing.assert_array_equal(m.at(1 * S), [1.0, np.nan])  # partial: b unknown then
    np.testing.assert_array_equal(m.at(1 * S + 500 * MS), [1.0, 2.0])
    np.testing.assert_array_equal(m.at(5 * S), [3.0, 4.0])
    np.testing.assert_array_equal(m.at(1 * S - 400 * MS), [1.0, np.nan])  # all newer: the oldest within max_age
    assert m.at(1 * S - 600 * MS) is None
    m.update(["a", "b"], [5.0, 6.0], 4 * S)  # keeps 2 s
    assert m.history.stamps == [2 * S, 4 * S]


def test_merge_rows_is_update_row_by_row():
    """The batch of ``ppoe evaluate`` gives, row by row, what :meth:`update` gives message by message."""
    rng = np.random.default_rng(3)
    names = ["a", "b", "c"]
    N = 300
    stamps = np.cumsum(rng.uniform(0.0, 0.3, N)) + 100.0
    P = rng.uniform(-1, 1, (N, 3))
    P[rng.random((N, 3)) < 0.4] = np.nan
    batch = JointHistory(names, max_age_ns=500 * MS)
    Q, held = batch.merge_rows(stamps, P)
    one = JointHistory(names, max_age_ns=500 * MS)
    n_held = 0
    for k in range(N):
        carried = [i for i in range(3) if np.isfinite(P[k, i])]
        ns = int(round(stamps[k] * 1e9))
        one.update([names[i] for i in carried], P[k, carried], ns)
        vec = one.vector(ns)
        np.testing.assert_array_equal(Q[k], vec)
        n_held += int(np.isfinite(vec).sum()) - len(carried)
    assert held == n_held > 0
