"""``one(0) .. one(n - 1)`` computed in worker processes forked from this one, handed out in order
(:class:`ForkedResults`): ``ppoe evaluate``'s image decoding, tag detection and observation rows
(:class:`ppoe_core.analysis.evaluate.tag_stream.TagStream`).

Why processes: the detection threads of :class:`ppoe_core.sensing.tag_rows.ImageDetections` need the GIL between
OpenCV's calls, so next to the (pure Python) fusion replay they and the replay wait for each other.  A forked child
shares nothing with the parent but the memory it had at the fork (copy-on-write: the bag's encoded images, the
camera lookup, the predicted windows), so the replay can run while the images are detected.  The results (a few
hundred bytes per image) come back pickled through one pipe per worker; image ``i`` is done by worker
``i % workers``, each worker in image order, so the parent can take the images in order while they are made.
"""

from __future__ import annotations

import multiprocessing as mp
import sys
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any

__all__ = ["FORK_AVAILABLE", "ForkedResults"]

#: forking is used on Linux only (macOS has ``fork`` but its system libraries are not safe in a forked child:
#: Python's default there is ``spawn``); elsewhere the caller uses threads
FORK_AVAILABLE = sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods()
#: seconds a worker may take to stop after :meth:`ForkedResults.close` before it is killed
_STOP_TIMEOUT_S = 2.0


def _serve(one: Callable[[int], Any], conn: Connection, indices: Sequence[int]) -> None:
    """In the child: ``(i, True, one(i))`` for each index, or ``(i, False, error)`` and stop at the first error (as
    a loop over the images stops)."""
    try:
        for i in indices:
            try:
                out: tuple[int, bool, Any] = (i, True, one(i))
            except Exception as exc:  # noqa: BLE001 - handed to the parent, raised there at its image
                out = (i, False, exc)
            try:
                conn.send(out)
            except Exception as exc:  # noqa: BLE001 - a result or error that does not pickle
                conn.send((i, False, RuntimeError(f"item {i}: result not sent to the parent process: {exc!r}")))
                return
            if not out[1]:
                return
    except (BrokenPipeError, EOFError):  # the parent closed its end (stopped early): nothing more to do
        return
    finally:
        conn.close()


class ForkedResults:
    """Iterator over ``one(0) .. one(n - 1)`` in order, computed by ``workers`` forked processes started here.

    ``one`` runs in the children on the memory of this process at the fork; it must not need anything of the
    parent made later, nor threads or locks the parent holds (it decodes and detects).  An exception ``one``
    raises in a child is raised here at its item (the child then stops); a child that dies gives a
    ``RuntimeError`` naming it.  :meth:`close` stops the children (also after an error or before the end).

    OpenCV's own threads are set to one while forking (a child has none of the parent's pool threads).
    """

    def __init__(self, one: Callable[[int], Any], n: int, workers: int) -> None:
        import cv2

        self._n, self._next, self._workers = n, 0, max(1, int(workers))
        self._got: dict[int, tuple[bool, Any]] = {}
        self._conns: list[Connection] = []
        self._procs: list[Any] = []
        ctx = mp.get_context("fork")
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            for w in range(self._workers):
                recv, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_serve, args=(one, send, range(w, n, self._workers)), daemon=True,
                                   name=f"ppoe_images_{w}")
                proc.start()
                send.close()
                self._conns.append(recv)
                self._procs.append(proc)
        except BaseException:
            self.close()
            raise
        finally:
            cv2.setNumThreads(threads)

    def __iter__(self) -> ForkedResults:
        return self

    def __next__(self) -> Any:
        if self._next >= self._n:
            self.close()
            raise StopIteration
        i = self._next
        while i not in self._got:
            self._receive(i % self._workers, i)
        self._drain()
        ok, value = self._got.pop(i)
        self._next += 1
        if not ok:
            self.close()
            raise value
        return value

    def _receive(self, w: int, i: int) -> None:
        """One result of worker ``w`` (blocking); ``i``: the item waited for (named if the worker died)."""
        try:
            k, ok, value = self._conns[w].recv()
        except (EOFError, OSError):
            proc, n = self._procs[w], self._n
            proc.join(_STOP_TIMEOUT_S)
            self.close()
            raise RuntimeError(f"worker process {proc.name} ended (exit code {proc.exitcode}) before item {i} "
                               f"of {n}") from None
        self._got[k] = (ok, value)

    def _drain(self) -> None:
        """Take every result already sent (a worker blocks on a full pipe otherwise)."""
        for conn in self._conns:
            while not conn.closed and conn.poll():
                try:
                    k, ok, value = conn.recv()
                except (EOFError, OSError):
                    break
                self._got[k] = (ok, value)

    def close(self) -> None:
        """Stop the children (the items not handed out are dropped) and wait for them."""
        for conn in self._conns:
            conn.close()
        for proc in self._procs:
            proc.join(0.0 if proc.exitcode is None and self._next < self._n else _STOP_TIMEOUT_S)
            if proc.exitcode is None:
                proc.terminate()
                proc.join(_STOP_TIMEOUT_S)
            if proc.exitcode is None:  # pragma: no cover - a child ignoring SIGTERM
                proc.kill()
                proc.join()
        self._conns, self._procs = [], []
        self._n = self._next
