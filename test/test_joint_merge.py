"""JointMerger: joint states split over several publishers, merged per joint with a maximum age."""

from __future__ import annotations

import numpy as np
import pytest

from ppoe_core.errors import JointValueError
from ppoe_core.estimation.joint_merge import JointMerger

MS = 1_000_000


def test_split_messages_merge_until_a_joint_is_too_old():
    m = JointMerger(["a", "b", "c"], max_age_ns=500 * MS)
    q, why = m.update(["a", "b"], [1.0, 2.0], 0)
    assert q is None and why == "needed joint(s) not seen yet: c"
    q, why = m.update(["c", "gripper"], [3.0, 9.0], 10 * MS)
    np.testing.assert_array_equal(q, [1.0, 2.0, 3.0])
    q, _ = m.update(["b", "a"], [5.0, 4.0], 400 * MS)  # another order: the index map is rebuilt
    np.testing.assert_array_equal(q, [4.0, 5.0, 3.0])
    q, why = m.update(["a", "b"], [6.0, 7.0], 600 * MS)  # c is 590 ms old
    assert q is None and why == "needed joint(s) older than 0.5 s: c"
    q, why = m.update(["gripper"], [1.0], 610 * MS)
    assert q is None and why == "carries none of the chain's joints"
    q, _ = m.update(["a", "b", "c"], [1.0, 1.0, 1.0], 620 * MS)  # the whole chain: fast path
    np.testing.assert_array_equal(q, [1.0, 1.0, 1.0])
    q[0] = 99.0  # a returned vector is the caller's
    np.testing.assert_array_equal(m.update(["c"], [2.0], 630 * MS)[0], [1.0, 1.0, 2.0])


def test_no_age_limit_and_bad_values():
    m = JointMerger(["a", "b"], max_age_ns=0)
    m.update(["a"], [1.0], 0)
    np.testing.assert_array_equal(m.update(["b"], [2.0], 10**12)[0], [1.0, 2.0])  # 1000 s later: still used
    with pytest.raises(JointValueError, match="'b'"):
        m.update(["a", "b"], [1.0, float("nan")], 10**12 + 1)
    with pytest.raises(ValueError, match="2 names but 1 positions"):
        m.update(["a", "b"], [1.0], 10**12 + 2)
