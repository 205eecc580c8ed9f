"""``--out DIR`` of ``ppoe evaluate`` / ``ppoe diagnose``: checked, created and locked before the run, not after it.

One folder may hold the results of several kinds of run (``evaluate``, ``evaluate --online``, ``diagnose``), but
never of two runs at once, and a run never leaves a mix of its own old and new files (issue 25):

* **lock**: :func:`prepare_out_dir` creates ``DIR/.ppoe.lock`` exclusively (pid, host, command, run id); a
  second run into the same folder while the first runs is refused, naming the lock and the run holding it.  A
  lock left by a run that no longer runs on this host (killed) is taken over, with a warning.  The lock goes at
  :func:`finish_out_dir` / :func:`release_out_dir`, or at process exit;
* **run id**: ``<UTC time>-<pid>``, in the lock and, per finished run, one line of ``DIR/ppoe_runs.jsonl``
  (command, run id, start and end, the files it wrote);
* **other runs' files** (of another kind, or not ours) are never touched; :func:`prepare_out_dir` warns which
  are there.  :func:`finish_out_dir` removes the files of the run's own kind that it did not rewrite (an
  ``errors.png`` of an earlier run, say), so what its kind's files say is this run's.
"""

from __future__ import annotations

import atexit
import fnmatch
import json
import os
import socket
import tempfile
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ppoe_core.errors import PpoeError, PpoeWarning

__all__ = ["LOCK_NAME", "RUN_FILES", "RUNS_LOG", "finish_out_dir", "prepare_out_dir", "release_out_dir"]

LOCK_NAME = ".ppoe.lock"
RUNS_LOG = "ppoe_runs.jsonl"
#: the files each kind of run writes (patterns): a run removes or replaces only these
RUN_FILES: dict[str, tuple[str, ...]] = {
    "evaluate": ("evaluation.md", "evaluation.json", "errors.png", "trajectory_*.tum"),
    "evaluate --online": ("online.json", "online_parameters.png", "model_online.yaml"),
    "diagnose": ("diagnose.md", "diagnose.json", "diagnose.png", "model_diagnosed.yaml", "robot_calibrated.urdf",
                 "model_calibrated.yaml"),
}
#: at most this many file names in a message
NAMED_AT_MOST = 8


@dataclass
class _Run:
    path: Path
    kind: str | None
    run_id: str
    started: float
    notes: list[str] = field(default_factory=list)


_RUNS: dict[Path, _Run] = {}


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read_lock(lock: Path) -> dict:
    try:
        data = json.loads(lock.read_text(encoding="utf-8"))
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def _acquire(path: Path, option: str, kind: str | None) -> _Run:
    """Create the lock exclusively (or take over a stale one of this host); the run it stands for."""
    lock = path / LOCK_NAME
    run = _Run(path, kind, f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}", time.time())
    record = {"pid": os.getpid(), "host": socket.gethostname(), "command": f"ppoe {kind or '?'}",
              "run_id": run.run_id, "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            held = _read_lock(lock)
            stale = held.get("host") == record["host"] and isinstance(held.get("pid"), int) \
                and (held["pid"] == os.getpid() or not _pid_alive(held["pid"]))
            if not stale:
                who = f"{held.get('command', 'a ppoe run')} pid {held.get('pid', '?')} on {held.get('host', '?')}, " \
                      f"run {held.get('run_id', '?')} since {held.get('started', '?')}" if held else "unreadable"
                raise PpoeError(f"{option} {path}: another run is writing there (lock {lock}: {who}); wait for it to "
                                "finish or choose another folder (remove the lock only if no run uses it)") from None
            lock.unlink(missing_ok=True)
            run.notes.append(f"{option} {path}: took over the lock of run {held.get('run_id')} (pid {held['pid']} "
                             "no longer runs: killed?); its files may be incomplete")
            continue
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(record, f)
        return run
    raise PpoeError(f"{option} {path}: cannot take the lock {lock}")


def _matches(name: str, kind: str) -> bool:
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in RUN_FILES.get(kind, ()))


def _named(names: Sequence[str]) -> str:
    return ", ".join(names[:NAMED_AT_MOST]) + (f" and {len(names) - NAMED_AT_MOST} more"
                                               if len(names) > NAMED_AT_MOST else "")


def prepare_out_dir(out: str | os.PathLike, option: str = "--out", kind: str | None = None) -> Path:
    """Create ``out`` (with parents), check that files can be written there, and lock it for this run.

    Parameters
    ----------
    out : path
        The output folder.
    option : str
        The option's name, for messages.
    kind : str, optional
        The kind of run (a key of :data:`RUN_FILES`): files of other kinds already there are named in a warning.
        A second call for the same folder in the same process keeps the first lock (re-entrant).

    Raises
    ------
    PpoeError
        ``out`` is an existing file, cannot be created, is not writable, or another run holds its lock; the
        message names it.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise PpoeError(f"{option} {path}: is an existing file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".ppoe_write_check_"):
            pass
    except OSError as exc:
        raise PpoeError(f"{option} {path}: cannot write there ({exc.strerror or exc})") from None
    key = path.resolve()
    if key in _RUNS:
        if kind is not None and _RUNS[key].kind is None:
            _RUNS[key].kind = kind
        return path
    run = _acquire(path, option, kind)
    _RUNS[key] = run
    others = sorted(e.name for e in path.iterdir() if e.name not in (LOCK_NAME, RUNS_LOG)
                    and not e.name.startswith(".ppoe_write_check_") and not (kind and _matches(e.name, kind)))
    if others and kind is not None:
        run.notes.append(f"{option} {path} also holds {len(others)} file(s) this run does not write "
                         f"({_named(others)}): left as they are (another run's results?)")
    for note in run.notes:
        warnings.warn(note, PpoeWarning, stacklevel=2)
    return path


def finish_out_dir(out: str | os.PathLike, written: Sequence[str | os.PathLike]) -> str:
    """After a successful run: remove the files of the run's kind it did not rewrite, log the run in
    ``ppoe_runs.jsonl`` and release the lock.  Returns the run id."""
    key = Path(out).resolve()
    run = _RUNS.get(key)
    if run is None:
        raise PpoeError(f"--out {out}: finish_out_dir without prepare_out_dir")
    names = sorted({Path(p).name for p in written})
    stale = sorted(e.name for e in run.path.iterdir() if run.kind and _matches(e.name, run.kind)
                   and e.name not in names)
    for name in stale:
        (run.path / name).unlink(missing_ok=True)
    entry = {"run_id": run.run_id, "command": f"ppoe {run.kind}", "started": run.started, "finished": time.time(),
             "wrote": names, "removed_stale": stale}
    with open(run.path / RUNS_LOG, "a", encoding="utf-8") as f:
        f.write(json.dumps(entry) + "\n")
    release_out_dir(out)
    return run.run_id


def release_out_dir(out: str | os.PathLike) -> None:
    """Remove this process's lock of ``out`` (if it holds one)."""
    run = _RUNS.pop(Path(out).resolve(), None)
    if run is None:
        return
    lock = run.path / LOCK_NAME
    if _read_lock(lock).get("pid") == os.getpid():
        lock.unlink(missing_ok=True)


@atexit.register
def _release_all() -> None:
    for key in list(_RUNS):
        release_out_dir(key)
