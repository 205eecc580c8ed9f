"""Batching worker of the online pipeline (the kinematics node's FK worker), ROS-free and tested without DDS.

A producer (a subscription callback) only validates a message and :meth:`BatchWorker.put` s its item; one worker
thread hands whatever queued up since its last call to ``process`` (e.g. one vectorised ``PPOEModel.fk`` over the
batch).  At low rates every batch holds one item (no added latency); when ``process`` falls behind, batches grow and
the vectorised work catches up.  A queue longer than ``max_queue`` drops its oldest items, each reported through
``on_dropped``; an exception in ``process`` is reported through ``on_error`` and the worker goes on.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["BatchWorker"]


class BatchWorker:
    """Worker thread that processes queued items in batches of at most ``max_batch`` (module docstring)."""

    def __init__(self, process: Callable[[list[Any]], None], max_batch: int, max_queue: int,
                 on_dropped: Callable[[str], None], on_error: Callable[[BaseException], None],
                 name: str = "ppoe_fk_worker") -> None:
        if max_batch < 1 or max_queue < 1:
            raise ValueError(f"BatchWorker: max_batch and max_queue must be >= 1, got {max_batch}, {max_queue}")
        self._process = process
        self._max_batch = max_batch
        self._max_queue = max_queue
        self._on_dropped = on_dropped
        self._on_error = on_error
        self._queue: collections.deque = collections.deque()
        self._cv = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item: Any) -> None:
        """Queue ``item``; beyond ``max_queue`` the oldest item is dropped and reported."""
        with self._cv:
            self._queue.append(item)
            if len(self._queue) > self._max_queue:
                self._queue.popleft()
                self._on_dropped(f"FK queue longer than {self._max_queue}: oldest dropped")
            self._cv.notify()

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait(0.2)
                if self._stop:
                    return
                n = min(len(self._queue), self._max_batch)
                batch = [self._queue.popleft() for _ in range(n)]
            try:
                self._process(batch)
            except Exception as exc:  # noqa: BLE001 - the worker must survive anything
                self._on_error(exc)

    def pending(self) -> int:
        """Items queued and not yet handed to ``process``."""
        with self._cv:
            return len(self._queue)

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread (items still queued are not processed)."""
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(timeout=timeout)
