"""Progress of long runs on stderr (``ppoe evaluate``, ``ppoe diagnose``): a bar for counted work, a ticker for stages.

Drawn only where a person watches: :func:`progress_wanted` is true when the stream is a terminal, unless
``--quiet`` (or forced with ``--progress`` / ``--no-progress``).  A redraw overwrites its own line (``\\r``) at
most every 0.1 s; the line is finished with a newline when the run ends, so what follows starts clean.  No
dependency (tqdm is not one of the package's).
"""

from __future__ import annotations

import sys
import threading
import time
from types import TracebackType
from typing import Any, TextIO

__all__ = ["progress_wanted", "ProgressBar", "Ticker"]

#: seconds between redraws: fast enough to look alive, slow enough to cost nothing
REDRAW_PERIOD = 0.1


def progress_wanted(quiet: bool = False, forced: bool | None = None, stream: TextIO | None = None) -> bool:
    """Whether to draw progress: never with ``quiet``; ``forced`` when given; else when ``stream`` (stderr) is a
    terminal."""
    if quiet:
        return False
    if forced is not None:
        return bool(forced)
    s = stream if stream is not None else sys.stderr
    return bool(getattr(s, "isatty", lambda: False)())


class ProgressBar:
    """A minimal text progress bar on a stream (stderr by default), throttled to 10 Hz.

    Parameters
    ----------
    total : int
        Number of steps.
    enabled : bool
        Draw nothing when False.
    label : str
    stream : file-like, optional
    """

    def __init__(self, total: int, enabled: bool, label: str = "evaluate", stream: Any = None) -> None:
        self.total = max(int(total), 1)
        self.enabled = bool(enabled)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self._last = 0.0
        self._t0 = time.monotonic()

    def update(self, done: int) -> None:
        """Redraw for ``done`` steps finished (at most every 0.1 s)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < REDRAW_PERIOD and done < self.total:
            return
        self._last = now
        frac = min(done / self.total, 1.0)
        width = 30
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        el = now - self._t0
        eta = f"{el / frac - el:6.1f}s" if frac > 0 else "     ?"
        self.stream.write(f"\r{self.label} [{bar}] {100 * frac:5.1f}% {el:6.1f}s eta {eta}")
        self.stream.flush()

    def close(self) -> None:
        """Finish the line."""
        if self.enabled:
            self.update(self.total)
            self.stream.write("\n")
            self.stream.flush()


class Ticker:
    """The current stage of a run and the time spent, redrawn by a background thread (for work that is not
    counted, e.g. a fit).  Use as a context manager; :meth:`stage` names what runs now.

    ``diagnose: fitting the effects (stage 2/5) 12.4 s``; at the end ``diagnose: done in 31.0 s``.
    """

    def __init__(self, label: str, enabled: bool, stream: Any = None, period: float = REDRAW_PERIOD) -> None:
        self.label = label
        self.enabled = bool(enabled)
        self.stream = stream if stream is not None else sys.stderr
        self.period = float(period)
        self.text = "starting"
        self._t0 = time.monotonic()
        self._width = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> Ticker:
        self._t0 = time.monotonic()
        if self.enabled:
            self._thread = threading.Thread(target=self._run, name=f"{self.label}-progress", daemon=True)
            self._thread.start()
        return self

    def stage(self, text: str) -> None:
        """What runs from now on (redrawn at once)."""
        self.text = text
        self._draw()

    def _line(self) -> str:
        return f"{self.label}: {self.text} {time.monotonic() - self._t0:.1f} s"

    def _draw(self, line: str | None = None) -> None:
        if not self.enabled:
            return
        with self._lock:
            line = self._line() if line is None else line
            pad = max(0, self._width - len(line))
            self._width = len(line)
            self.stream.write("\r" + line + " " * pad)
            self.stream.flush()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self._draw()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.enabled:
            word = "done" if exc_type is None else "stopped"
            self._draw(f"{self.label}: {word} in {time.monotonic() - self._t0:.1f} s")
            self.stream.write("\n")
            self.stream.flush()
