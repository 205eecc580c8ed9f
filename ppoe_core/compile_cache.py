"""Where numba caches the compiled kernels: a writable directory chosen once, at ``import ppoe_core``.

numba picks a cache directory per ``@njit(cache=True)`` function *when the function is defined* (at import),
and raises ``RuntimeError: cannot cache function ...: no locator available`` when neither the package's
``__pycache__`` nor its own user cache directory can be written (a read-only install run by a service user
without a writable home, a read-only container).  :func:`configure_compile_cache` runs first thing in
``ppoe_core/__init__.py``, before any kernel module is imported, and chooses, in this order:

1. ``NUMBA_CACHE_DIR`` when the user set it and it is writable (kind ``"environment"``);
2. the package directory itself (numba's default: ``__pycache__`` next to each kernel module), when every
   ``__pycache__`` of the package can be written (kind ``"package"``);
3. ``$XDG_CACHE_HOME/ppoe``, else ``~/.cache/ppoe`` (kind ``"user"``);
4. ``<tempdir>/ppoe-cache-<uid>`` (private, mode 0700; kept until the temp dir is cleaned, e.g. at reboot),
   else a fresh ``mkdtemp`` (kind ``"temp"``);
5. nothing writable at all: caching is switched off, the kernels compile in every process (kind ``"none"``).

Choices 1, 3, 4 are applied through ``NUMBA_CACHE_DIR`` (so child processes make the same choice), and
``numba.config.CACHE_DIR`` when numba is already imported.  One log line (logger ``ppoe_core.compile_cache``,
INFO) says which directory and why.  A *cold* compile (a kernel not found in the cache) is announced when it
starts and, at exit, with the number of kernels and the seconds it took; both at WARNING (shown on stderr
without any logging set-up) when the cache is not the package directory, as that is where a silent
25-30 s first run surprises, else at INFO.  No numba import happens here: the compile timer is attached
when numba is first imported (:func:`ensure_compile_timer`), so commands that never compile (``ppoe record``)
stay fast.

numba checks a cached kernel only against the modification time of *its own* module: a kernel that calls (and
so inlines) a kernel of another module keeps the old code when only that other module changes (an upgrade
installs new files beside the old caches, which pip does not remove).  So the cache carries a stamp, the SHA-1
of every package module that mentions numba (:func:`kernel_sources_digest`, about 4 ms); when the sources no
longer match it, :func:`drop_stale_kernels` removes this package's cached kernels before numba reads them (one
log line says how many), and writes the new stamp.  A location that cannot be written (a read-only install
warmed at install time) is left as it is.

Public API (issue 24's warm-up builds on it): :func:`configure_compile_cache`, :func:`cache_location`,
:func:`kernel_cache_dir`, :func:`compile_stats`, :class:`CacheLocation`, :class:`CompileStats`.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import importlib.abc
import importlib.util
import logging
import os
import stat
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

__all__ = [
    "CacheLocation",
    "CompileStats",
    "ENV_CACHE_DIR",
    "cache_location",
    "choose_cache_location",
    "compile_stats",
    "configure_compile_cache",
    "drop_stale_kernels",
    "ensure_compile_timer",
    "kernel_sources_digest",
    "kernel_cache_dir",
]

LOG = logging.getLogger(__name__)

#: numba's environment variable for a user-provided cache directory (read at numba import)
ENV_CACHE_DIR = "NUMBA_CACHE_DIR"
#: name of our directory under the user cache root ($XDG_CACHE_HOME or ~/.cache) and prefix of the temp one
CACHE_NAME = "ppoe"
#: the package whose kernels are cached (this file's directory)
PACKAGE_DIR = Path(__file__).resolve().parent
#: file, in the first cache directory of the package, holding the kernel sources' digest the cache was built from
STAMP_NAME = "ppoe_kernel_sources.sha1"
#: numba's cache files: the index (``.nbi``) and the compiled code (``.nbc``)
NUMBA_CACHE_SUFFIXES = (".nbi", ".nbc")


class CacheLocation(NamedTuple):
    """The chosen cache directory.

    Attributes
    ----------
    directory : Path or None
        ``NUMBA_CACHE_DIR`` given to numba; for kind ``"package"`` the package directory (numba then writes
        ``__pycache__`` next to each kernel module); ``None`` for kind ``"none"``.
    kind : str
        ``"environment"``, ``"package"``, ``"user"``, ``"temp"`` or ``"none"`` (module docstring).
    reason : str
        Why this one: the candidates before it that could not be written, and why.
    """

    directory: Path | None
    kind: str
    reason: str

    def describe(self) -> str:
        """One line: where the compiled kernels go and why."""
        where = {"package": f"__pycache__ next to the kernel modules in {self.directory}",
                 "none": "nowhere: caching is off, every process compiles the kernels"}.get(
            self.kind, str(self.directory))
        return f"numba kernel cache: {where} ({self.kind}{'; ' + self.reason if self.reason else ''})"


@dataclass
class CompileStats:
    """Kernels compiled (cache misses) in this process.

    Attributes
    ----------
    kernels : int
        Top-level compilations (one per kernel signature not found in the cache).
    seconds : float
        Wall time spent in them [s].
    """

    kernels: int = 0
    seconds: float = 0.0


_state: dict[str, Any] = {"location": None, "stats": CompileStats(), "timer": False}


def _writable_dir(path: Path) -> str | None:
    """``None`` if ``path`` can be created and a file written in it (numba's own test), else the reason."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError as exc:
        return f"{path}: {exc.strerror or exc}"
    return None


def _package_dirs(package_dir: Path) -> list[Path]:
    """Every directory of the package holding Python modules (where numba's in-tree cache would write)."""
    dirs = []
    for root, subdirs, files in os.walk(package_dir):
        subdirs[:] = [d for d in subdirs if d != "__pycache__" and not d.startswith(".")]
        if any(f.endswith(".py") for f in files):
            dirs.append(Path(root))
    return dirs


def _user_cache_root(environ: Mapping[str, str]) -> Path | None:
    """``$XDG_CACHE_HOME`` (absolute only, as the XDG spec says), else ``~/.cache``; None without a home."""
    xdg = environ.get("XDG_CACHE_HOME", "")
    if xdg and os.path.isabs(xdg):
        return Path(xdg)
    home = environ.get("HOME") or None
    if home is None:
        try:
            home = str(Path.home())
        except (RuntimeError, KeyError):
            return None
    return Path(home) / ".cache"


def _private_temp_dir(tmp_root: Path) -> tuple[Path | None, str]:
    """``tmp_root/ppoe-cache-<uid>``, if it is (or can be made) a private directory of ours, else a fresh one."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    path = tmp_root / f"{CACHE_NAME}-cache-{uid}"
    try:
        path.mkdir(mode=0o700, exist_ok=True)
        st = os.lstat(path)
        private = stat.S_ISDIR(st.st_mode) and st.st_uid == uid and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        if private and _writable_dir(path) is None:
            return path, ""
        note = f"{path}: not a private directory of uid {uid}"
    except OSError as exc:
        note = f"{path}: {exc.strerror or exc}"
    try:
        return Path(tempfile.mkdtemp(prefix=f"{CACHE_NAME}-cache-", dir=tmp_root)), note
    except OSError as exc:
        return None, f"{note}; {tmp_root}: {exc.strerror or exc}"


def choose_cache_location(package_dir: Path | None = None, environ: Mapping[str, str] | None = None,
                          tmp_root: Path | None = None) -> CacheLocation:
    """Choose the cache directory (module docstring, steps 1-5); creates it, changes nothing else.

    Parameters
    ----------
    package_dir : Path, optional
        The package whose ``__pycache__`` directories are tried (default: ``ppoe_core``).
    environ : mapping, optional
        Environment to read ``NUMBA_CACHE_DIR``, ``XDG_CACHE_HOME`` and ``HOME`` from (default ``os.environ``).
    tmp_root : Path, optional
        Temporary directory root (default :func:`tempfile.gettempdir`).
    """
    env = os.environ if environ is None else environ
    package_dir = PACKAGE_DIR if package_dir is None else Path(package_dir)
    why: list[str] = []
    given = env.get(ENV_CACHE_DIR, "")
    if given:
        problem = _writable_dir(Path(given))
        if problem is None:
            return CacheLocation(Path(given), "environment", f"{ENV_CACHE_DIR} is set")
        why.append(f"{ENV_CACHE_DIR} not writable ({problem})")
    problems = [p for p in (_writable_dir(d / "__pycache__") for d in _package_dirs(package_dir)) if p]
    if not problems:
        return CacheLocation(package_dir, "package", "; ".join(why))
    why.append(f"package directory not writable ({problems[0]})")
    root = _user_cache_root(env)
    if root is not None:
        problem = _writable_dir(root / CACHE_NAME)
        if problem is None:
            return CacheLocation(root / CACHE_NAME, "user", "; ".join(why))
        why.append(f"user cache not writable ({problem})")
    else:
        why.append("no home directory")
    temp, note = _private_temp_dir(Path(tmp_root or tempfile.gettempdir()))
    if note:
        why.append(note)
    if temp is not None:
        return CacheLocation(temp, "temp", "; ".join(why) + "; it is lost when the temp directory is cleaned")
    return CacheLocation(None, "none", "; ".join(why))


def configure_compile_cache(force: bool = False) -> CacheLocation:
    """Choose the cache directory once per process and point numba at it (idempotent; ``force`` chooses again).

    Must run before any ``@njit(cache=True)`` kernel is defined; ``ppoe_core/__init__.py`` calls it first.
    """
    if _state["location"] is not None and not force:
        return _state["location"]
    loc = choose_cache_location()
    if loc.kind in ("user", "temp"):
        os.environ[ENV_CACHE_DIR] = str(loc.directory)
    elif loc.kind in ("package", "none"):
        os.environ.pop(ENV_CACHE_DIR, None)  # an unwritable user value would only make numba fail
    _state["location"] = loc
    drop_stale_kernels(loc)
    if "numba" in sys.modules:
        ensure_compile_timer()
    elif not any(isinstance(finder, _AfterNumbaImport) for finder in sys.meta_path):
        sys.meta_path.insert(0, _AfterNumbaImport())
    LOG.info(loc.describe())
    return loc


def kernel_sources_digest(package_dir: Path | None = None) -> str:
    """SHA-1 over the path and bytes of every module of the package that mentions numba (sorted by path)."""
    package_dir = PACKAGE_DIR if package_dir is None else Path(package_dir)
    digest = hashlib.sha1()
    for directory in _package_dirs(package_dir):
        for path in sorted(directory.glob("*.py")):
            data = path.read_bytes()
            if b"numba" in data:
                digest.update(str(path.relative_to(package_dir)).encode() + b"\0" + data)
    return digest.hexdigest()


def drop_stale_kernels(loc: CacheLocation, package_dir: Path | None = None) -> int:
    """Remove the package's cached kernels when its kernel sources changed since the stamp; return how many files.

    Writes the current digest as the stamp (nothing happens where the cache cannot be written).
    """
    package_dir = PACKAGE_DIR if package_dir is None else Path(package_dir)
    if loc.directory is None:
        return 0
    dirs = [kernel_cache_dir(d / "__init__.py", loc) for d in _package_dirs(package_dir)]
    stamp = dirs[0] / STAMP_NAME if dirs and dirs[0] is not None else None
    if stamp is None:
        return 0
    now = kernel_sources_digest(package_dir)
    try:
        if stamp.read_text().strip() == now:
            return 0
    except OSError:
        pass
    removed = 0
    for directory in dirs:
        for path in directory.glob("*") if directory is not None and directory.is_dir() else ():
            if path.suffix in NUMBA_CACHE_SUFFIXES:
                with contextlib.suppress(OSError):
                    path.unlink()
                    removed += 1
    try:
        stamp.parent.mkdir(parents=True, exist_ok=True)
        stamp.write_text(now + "\n")
    except OSError:
        return removed
    if removed:
        LOG.info(f"kernel sources changed since the cache was written: removed {removed} cached kernel file(s)")
    return removed


def cache_location() -> CacheLocation:
    """The location chosen for this process (:func:`configure_compile_cache` runs if it has not)."""
    return configure_compile_cache()


def kernel_cache_dir(source_file: str | os.PathLike[str], loc: CacheLocation | None = None) -> Path | None:
    """Directory where numba caches the kernels of module file ``source_file`` at location ``loc`` (default:
    the chosen one; numba's own layout: ``__pycache__`` beside it for kind ``"package"``, else
    ``<dir>/<parent>_<sha1>``); ``None`` when caching is off."""
    loc = cache_location() if loc is None else loc
    src = Path(os.path.abspath(source_file))
    if loc.directory is None:
        return None
    if loc.kind == "package":
        return src.parent / "__pycache__"
    return loc.directory / f"{src.parent.name}_{hashlib.sha1(str(src.parent).encode()).hexdigest()}"


def compile_stats() -> CompileStats:
    """Kernels compiled so far in this process and the time they took (zero when all came from the cache)."""
    return _state["stats"]


def ensure_compile_timer() -> None:
    """Attach the cold-compile timer to numba (and switch caching off for kind ``"none"``); once per process."""
    if _state["timer"]:
        return
    _state["timer"] = True
    from numba.core import event

    event.register("numba:compile", _make_listener_class()())
    if _state["location"] is not None and _state["location"].kind == "none":
        from numba.core.dispatcher import Dispatcher

        # keep numba's NullCache: no locator would be found
        Dispatcher.enable_caching = lambda self: None  # type: ignore[method-assign]
    atexit.register(_report_at_exit)


def _make_listener_class() -> type:
    """A :class:`numba.core.event.Listener` (defined here: numba is imported by the time it is needed)."""
    from numba.core import event

    class Listener(event.Listener):
        """Counts top-level compilations and their wall time; announces the first one."""

        def __init__(self) -> None:
            self._depth = 0
            self._t0 = 0.0
            self._lock = threading.Lock()

        def on_start(self, event: Any) -> None:
            with self._lock:
                self._depth += 1
                if self._depth == 1:
                    self._t0 = time.perf_counter()
                    if compile_stats().kernels == 0:
                        _log(f"compiling numba kernels, not found in the cache (first run with this cache; "
                             f"all of them take 30-60 s on 2 cores); {cache_location().describe()}")

        def on_end(self, event: Any) -> None:
            with self._lock:
                self._depth -= 1
                if self._depth == 0:
                    stats = compile_stats()
                    stats.kernels += 1
                    stats.seconds += time.perf_counter() - self._t0

    return Listener


def _log(message: str) -> None:
    loc = _state["location"]
    LOG.log(logging.INFO if loc is None or loc.kind in ("package", "environment") else logging.WARNING, message)


def _report_at_exit() -> None:
    stats = compile_stats()
    if stats.kernels:
        loc = cache_location()
        where = "not cached (caching is off)" if loc.kind == "none" else f"cached for the next run ({loc.kind})"
        _log(f"compiled {stats.kernels} numba kernel(s) in {stats.seconds:.1f} s, {where}")


class _AfterNumbaImport(importlib.abc.MetaPathFinder):
    """One-shot import hook: lets ``import numba`` run as usual, then calls :func:`ensure_compile_timer`."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname != "numba":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(fullname)
        loader = spec.loader if spec is not None else None
        if loader is None or not hasattr(loader, "exec_module"):
            return spec
        exec_module = loader.exec_module

        def exec_then_attach(module: Any) -> None:
            exec_module(module)
            ensure_compile_timer()

        loader.exec_module = exec_then_attach  # type: ignore[method-assign]
        return spec
