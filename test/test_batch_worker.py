"""The kinematics node's FK batching worker (ppoe_core.estimation.batch_worker), without DDS."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import CONFIG_ROBOTS

from ppoe_core.estimation.batch_worker import BatchWorker
from ppoe_core.model.ppoe import PPOEModel


def _wait(cond, timeout: float = 5.0) -> None:
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    assert cond(), "timed out"


def test_batches_grow_when_processing_falls_behind_and_order_is_kept():
    """While one batch is processed, the items queued meanwhile arrive together in the next batch, in order."""
    gate = threading.Event()
    batches: list[list[int]] = []

    def process(batch: list[int]) -> None:
        batches.append(batch)
        gate.wait(5.0)

    w = BatchWorker(process, max_batch=100, max_queue=1000, on_dropped=pytest.fail, on_error=pytest.fail)
    try:
        w.put(0)
        _wait(lambda: len(batches) == 1)
        for i in range(1, 51):
            w.put(i)
        gate.set()
        _wait(lambda: sum(len(b) for b in batches) == 51)
    finally:
        w.stop()
    assert batches[0] == [0] and batches[1] == list(range(1, 51))


def test_max_batch_splits_and_overflow_drops_oldest_with_a_report():
    gate = threading.Event()
    seen: list[list[int]] = []
    dropped: list[str] = []

    def process(batch: list[int]) -> None:
        seen.append(batch)
        gate.wait(5.0)

    w = BatchWorker(process, max_batch=4, max_queue=6, on_dropped=dropped.append, on_error=pytest.fail)
    try:
        w.put(-1)
        _wait(lambda: len(seen) == 1)  # the worker is busy with [-1]
        for i in range(10):
            w.put(i)
        assert len(dropped) == 4 and "longer than 6" in dropped[0]
        assert w.pending() == 6
        gate.set()
        _wait(lambda: w.pending() == 0 and sum(len(b) for b in seen) == 7)
    finally:
        w.stop()
    assert seen[1:] == [[4, 5, 6, 7], [8, 9]]  # oldest (0..3) dropped, the rest in batches of at most 4


def test_an_exception_is_reported_and_the_worker_goes_on():
    errors: list[BaseException] = []
    done: list[list[int]] = []

    def process(batch: list[int]) -> None:
        if 13 in batch:
            raise ValueError("unlucky joint state")
        done.append(batch)

    w = BatchWorker(process, max_batch=1, max_queue=10, on_dropped=pytest.fail, on_error=errors.append)
    try:
        for i in (12, 13, 14):
            w.put(i)
        _wait(lambda: len(done) == 2)
    finally:
        w.stop()
    assert done == [[12], [14]] and isinstance(errors[0], ValueError)


def test_worker_runs_the_vectorised_fk_like_the_node():
    """One batched PPOEModel.fk over the queued joint vectors equals the per-message FK."""
    model = PPOEModel.from_files(CONFIG_ROBOTS / "arm7.urdf", CONFIG_ROBOTS / "arm7_model.yaml")
    rng = np.random.default_rng(3)
    Q = rng.uniform(-1.0, 1.0, (40, len(model.joint_names)))
    out: list[tuple[np.ndarray, np.ndarray]] = []

    def process(batch: list[np.ndarray]) -> None:
        T, cov = model.fk(np.stack(batch), "base_link", "tool0")
        out.extend(zip(T, cov))

    w = BatchWorker(process, max_batch=16, max_queue=100, on_dropped=pytest.fail, on_error=pytest.fail)
    try:
        for q in Q:
            w.put(q)
        _wait(lambda: len(out) == len(Q))
    finally:
        w.stop()
    for q, (T, cov) in zip(Q, out):
        T1, cov1 = model.fk(q, "base_link", "tool0")
        np.testing.assert_allclose(T, T1, atol=1e-12)
        np.testing.assert_allclose(cov, cov1, atol=1e-15)


def test_bad_sizes_refused():
    with pytest.raises(ValueError, match="max_batch"):
        BatchWorker(lambda b: None, 0, 10, print, print)
