"""``ForkedResults``: items computed by forked worker processes, handed out in order, errors at their item, workers
stopped on close (the image workers of ``ppoe evaluate``, ``ppoe_core.sensing.forked``)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from ppoe_core.errors import BagError
from ppoe_core.sensing.forked import FORK_AVAILABLE, ForkedResults

pytestmark = pytest.mark.skipif(not FORK_AVAILABLE, reason="no fork start method on this platform")


def _square(i: int) -> tuple[int, np.ndarray, int]:
    time.sleep(0.002 * ((7 * i) % 3))  # workers finish out of order
    return i, np.full(3, i * i), os.getpid()


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_items_come_in_order_from_the_children(workers: int) -> None:
    got = list(ForkedResults(_square, 23, workers))
    assert [g[0] for g in got] == list(range(23))
    assert all(np.array_equal(g[1], np.full(3, g[0] ** 2)) for g in got)
    pids = {g[2] for g in got}
    assert os.getpid() not in pids and len(pids) == workers  # computed in the children, i % workers each


def test_the_children_see_the_parents_memory_at_the_fork() -> None:
    table = {i: f"image {i}" for i in range(9)}  # made here, never sent to the children
    assert list(ForkedResults(table.__getitem__, 9, 2)) == [table[i] for i in range(9)]


def _fails_at_5(i: int) -> int:
    if i == 5:
        raise BagError(f"bag b: message {i}: broken")
    return i


def test_an_error_is_raised_at_its_item_and_the_children_stop() -> None:
    it = ForkedResults(_fails_at_5, 12, 2)
    assert [next(it) for _ in range(5)] == [0, 1, 2, 3, 4]
    with pytest.raises(BagError, match="message 5: broken"):
        next(it)
    with pytest.raises(StopIteration):
        next(it)
    assert it._procs == []  # closed: every child joined


def _dies_at_3(i: int) -> int:
    if i == 3:
        os._exit(7)
    return i


def test_a_child_that_dies_is_named_with_its_exit_code() -> None:
    it = ForkedResults(_dies_at_3, 8, 2)
    assert [next(it) for _ in range(3)] == [0, 1, 2]
    with pytest.raises(RuntimeError, match=r"ppoe_images_1 ended \(exit code 7\) before item 3 of 8"):
        next(it)


def _slow(i: int) -> int:
    time.sleep(0.05)
    return i


def test_close_before_the_end_stops_the_children() -> None:
    it = ForkedResults(_slow, 400, 2)
    procs = list(it._procs)
    assert next(it) == 0
    t0 = time.perf_counter()
    it.close()
    assert time.perf_counter() - t0 < 5.0 and all(p.exitcode is not None for p in procs)
    with pytest.raises(StopIteration):
        next(it)


def test_an_unpicklable_result_is_an_error_at_its_item() -> None:
    it = ForkedResults(lambda i: (lambda: i) if i == 2 else i, 4, 1)
    assert [next(it), next(it)] == [0, 1]
    with pytest.raises(RuntimeError, match="item 2: result not sent to the parent process"):
        next(it)
    it.close()
