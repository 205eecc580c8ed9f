"""A read-only install run by a user without a writable home: ``ppoe fk``, ``ppoe evaluate`` and a node start
(issue 25; was ``RuntimeError: cannot cache function '_op1': no locator available``), and the choice of the
numba cache directory (:mod:`ppoe_core.compile_cache`).

How the read-only install is made, as root and as any other user
-----------------------------------------------------------------
The packages ``ppoe_core`` and ``ppoe_ros`` are copied (without ``__pycache__``) into a sandbox and made
read-only (``chmod a-w``); ``HOME`` is an empty read-only directory and ``XDG_CACHE_HOME`` is unset, so
neither the package directory nor ``~/.cache`` can take numba's cache; ``TMPDIR`` is a writable sandbox
directory (the last fallback).  A non-root user cannot write into a directory without its ``w`` bit, even its
own.  Root can (``CAP_DAC_OVERRIDE``), and another user cannot run the interpreter here (it lives under the
``0700`` ``/root``), so as root every sandboxed command runs under
``setpriv --bounding-set=-dac_override,-dac_read_search,-fowner``: still uid 0, owner of the files (so it reads
them), but held to their mode bits like any user.  The test first checks that a write into the copied package
really fails under that wrapper, and skips (saying why) where it cannot be made to fail.

The sandbox sits at a fixed path per checkout (``<tmp>/ppoe-readonly-test-<hash>``): the copy is renewed every
run, the cache in its ``TMPDIR`` is kept, so only the first run compiles the kernels cold (30-60 s).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ros_helpers import random_domain_id

import pytest
from conftest import BAGS, CONFIG_ROBOTS, REPO
from ros_helpers import write_params_file

from ppoe_core import compile_cache

ARM7_URDF = CONFIG_ROBOTS / "arm7.urdf"
ARM7_MODEL = CONFIG_ROBOTS / "arm7_model.yaml"
NO_CAPS = ["setpriv", "--bounding-set=-dac_override,-dac_read_search,-fowner", "--"]


def _set_writable(root: Path, writable: bool) -> None:
    for path in [root, *root.rglob("*")]:
        if path.is_symlink():
            continue
        mode = path.stat().st_mode
        bits = stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH
        os.chmod(path, (mode | stat.S_IWUSR) if writable else (mode & ~bits))


#: why a read-only sandbox cannot be made here (None: it can): file modes and setpriv are Linux's, and root ignores
#: file modes unless setpriv drops its capabilities
NO_SANDBOX = ("file modes and setpriv: Linux only" if sys.platform != "linux" else
              "running as root without setpriv: cannot make a read-only directory unwritable for root"
              if os.getuid() == 0 and shutil.which("setpriv") is None else None)
pytestmark = pytest.mark.skipif(NO_SANDBOX is not None, reason=str(NO_SANDBOX))


def _wrapper() -> list[str]:
    return NO_CAPS if os.getuid() == 0 else []


@pytest.fixture(scope="module")
def sandbox() -> dict:
    """The read-only install: ``prefix`` (command wrapper), ``env``, ``root``, ``tmp`` (TMPDIR)."""
    root = Path(tempfile.gettempdir()) / f"ppoe-readonly-test-{hashlib.sha1(str(REPO).encode()).hexdigest()[:10]}"
    install, home, tmp = root / "install", root / "home", root / "tmp"
    for path in (install, home):
        if path.exists():
            _set_writable(path, True)
            shutil.rmtree(path)
    tmp.mkdir(parents=True, exist_ok=True)
    for pkg in ("ppoe_core", "ppoe_ros"):
        shutil.copytree(REPO / pkg, install / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    home.mkdir()
    _set_writable(install, False)
    _set_writable(home, False)
    env = {k: v for k, v in os.environ.items()
           if k not in ("XDG_CACHE_HOME", "NUMBA_CACHE_DIR", "PYTHONPATH", "HOME", "TMPDIR")}
    env.update(HOME=str(home), TMPDIR=str(tmp), PYTHONPATH=str(install), PYTHONDONTWRITEBYTECODE="1",
               ROS_DOMAIN_ID=str(random_domain_id()), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_LOG_DIR=str(tmp / "ros_log"), PYTHONUNBUFFERED="1", RCUTILS_COLORIZED_OUTPUT="0")
    prefix = _wrapper()
    probe = subprocess.run([*prefix, "touch", str(install / "ppoe_core" / "probe"), str(home / "probe")],
                           capture_output=True, text=True)
    assert probe.returncode != 0, ("the read-only sandbox is writable here (file modes not enforced): the test "
                                   f"cannot make the install read-only ({probe.stdout}{probe.stderr})")
    return {"prefix": prefix, "env": env, "root": root, "tmp": tmp, "install": install}


def _run(sandbox: dict, args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([*sandbox["prefix"], sys.executable, *args], env=sandbox["env"], cwd=str(sandbox["root"]),
                          capture_output=True, text=True, timeout=timeout)


def test_cache_goes_to_the_temp_dir_when_package_and_home_are_read_only(sandbox):
    res = _run(sandbox, ["-c", "import ppoe_core, ppoe_core.compile_cache as c; "
                               "print(ppoe_core.__file__); print(c.cache_location().describe())"])
    assert res.returncode == 0, res.stderr
    where, line = res.stdout.splitlines()
    assert where.startswith(str(sandbox["install"])), where  # the copy, not the checkout
    assert f"{sandbox['tmp']}/ppoe-cache-{os.getuid()} (temp; package directory not writable" in line, line
    assert "user cache not writable" in line and str(Path(sandbox["env"]["HOME"]) / ".cache") in line, line


def test_fk_evaluate_and_a_node_start_from_a_read_only_install(sandbox):
    fk = _run(sandbox, ["-m", "ppoe_ros.cli", "fk", "--urdf", str(ARM7_URDF), "--model", str(ARM7_MODEL), "--json",
                        "--joints", *[f"joint_{i}=0.1" for i in range(1, 8)]])
    assert fk.returncode == 0 and '"cov_ros"' in fk.stdout, fk.stderr
    assert "Traceback" not in fk.stderr, fk.stderr
    ev = _run(sandbox, ["-m", "ppoe_ros.cli", "evaluate", str(BAGS / "no_effect"), "--model", str(ARM7_MODEL),
                        "--json"])
    assert ev.returncode == 0 and '"methods"' in ev.stdout and "Traceback" not in ev.stderr, ev.stderr
    log = sandbox["tmp"] / "kinematics_node.log"
    params = write_params_file(sandbox["tmp"] / "params.yaml", {"robot_description": ARM7_URDF.read_text(),
                                                                 "model_file": str(ARM7_MODEL)})
    with open(log, "wb") as out:
        node = subprocess.Popen([*sandbox["prefix"], sys.executable, "-m", "ppoe_ros.nodes.kinematics_node",
                                 "--ros-args", "--params-file", str(params)],
                                env=sandbox["env"], cwd=str(sandbox["root"]), stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and "model from parameter robot_description" not in log.read_text():
            assert node.poll() is None, log.read_text()
            time.sleep(0.3)
        text = log.read_text()
        assert "model from parameter robot_description" in text and "Traceback" not in text, text
    finally:
        if node.poll() is None:
            os.killpg(node.pid, 2)
            try:
                node.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(node.pid, 9)
                node.wait()


def test_cold_compile_is_announced_with_its_time(tmp_path):
    """A kernel not in the cache: a line when compiling starts and, at exit, how many and how long; at
    WARNING (visible without logging set-up) when the cache is not the package directory."""
    (tmp_path / "kern.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef add(x):\n    return x + 1\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(tmp_path)]),
           "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    code = "import ppoe_core, kern; print(kern.add(1))"
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0 and first.stdout.strip() == "2", first.stderr
    second = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    # NUMBA_CACHE_DIR given by the user: INFO, so not shown without logging set-up
    assert "compil" not in first.stderr and "compil" not in second.stderr, first.stderr
    verbose = "import logging; logging.basicConfig(level=logging.INFO); " + code
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "cache2")
    cold = subprocess.run([sys.executable, "-c", verbose], env=env, capture_output=True, text=True, timeout=120)
    warm = subprocess.run([sys.executable, "-c", verbose], env=env, capture_output=True, text=True, timeout=120)
    assert "compiling numba kernels, not found in the cache" in cold.stderr, cold.stderr
    assert "compiled 1 numba kernel(s) in " in cold.stderr and str(tmp_path / "cache2") in cold.stderr, cold.stderr
    # loaded from the cache: nothing compiled, nothing said
    assert "compiling" not in warm.stderr and "compiled" not in warm.stderr, warm.stderr


def test_choice_order(tmp_path, monkeypatch):
    """NUMBA_CACHE_DIR -> package -> $XDG_CACHE_HOME/ppoe -> ~/.cache/ppoe -> private temp dir -> none."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "sub" / "k.py").write_text("")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {"HOME": str(tmp_path / "home"), "NUMBA_CACHE_DIR": str(tmp_path / "given")}
    assert compile_cache.choose_cache_location(pkg, env, tmp).kind == "environment"
    del env["NUMBA_CACHE_DIR"]
    assert compile_cache.choose_cache_location(pkg, env, tmp) == (pkg, "package", "")
    ro = tmp_path / "ro"
    ro.mkdir()

    def writable_except(blocked: list[Path]):
        real = compile_cache._writable_dir

        def fake(path: Path) -> str | None:
            return f"{path}: Read-only file system" if any(path.is_relative_to(b) for b in blocked) else real(path)
        return fake

    monkeypatch.setattr(compile_cache, "_writable_dir", writable_except([pkg]))
    loc = compile_cache.choose_cache_location(pkg, env, tmp)
    assert loc.directory == tmp_path / "home" / ".cache" / "ppoe" and loc.kind == "user"
    assert "package directory not writable" in loc.reason
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    assert compile_cache.choose_cache_location(pkg, env, tmp).directory == tmp_path / "xdg" / "ppoe"
    monkeypatch.setattr(compile_cache, "_writable_dir", writable_except([pkg, tmp_path / "xdg"]))
    loc = compile_cache.choose_cache_location(pkg, env, tmp)
    assert loc.kind == "temp" and loc.directory == tmp / f"ppoe-cache-{os.getuid()}", loc
    assert stat.S_IMODE(loc.directory.stat().st_mode) == 0o700
    loc.directory.chmod(0o777)  # someone else could write there: not ours, a fresh private one instead
    loc2 = compile_cache.choose_cache_location(pkg, env, tmp)
    assert loc2.kind == "temp" and loc2.directory != loc.directory and "not a private directory" in loc2.reason
    monkeypatch.setattr(compile_cache, "_writable_dir", writable_except([tmp_path]))
    monkeypatch.setattr(compile_cache.tempfile, "mkdtemp", lambda **kw: (_ for _ in ()).throw(OSError(30, "RO")))
    assert compile_cache.choose_cache_location(pkg, env, tmp).kind == "none"


def test_nothing_writable_switches_caching_off_instead_of_failing(tmp_path):
    """Kind ``none`` (no writable directory at all): the kernels compile in every process, no RuntimeError."""
    (tmp_path / "kern2.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef sub(x):\n    return x - 1\n")
    code = ("import ppoe_core.compile_cache as c\n"
            "c.choose_cache_location = lambda: c.CacheLocation(None, 'none', 'nothing writable (test)')\n"
            "print(c.configure_compile_cache(force=True).describe())\n"
            "import kern2\nprint(kern2.sub(1))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(tmp_path)])}
    env.pop("NUMBA_CACHE_DIR", None)
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines() == ["numba kernel cache: nowhere: caching is off, every process compiles the "
                                       "kernels (none; nothing writable (test))", "0"], res.stdout
    assert "compiled 1 numba kernel(s)" in res.stderr and "not cached (caching is off)" in res.stderr, res.stderr
    assert not list(tmp_path.rglob("*.nbi")), "nothing cached"


def test_a_changed_kernel_module_drops_the_kernels_that_inlined_it(tmp_path):
    """numba checks a cached kernel against its own module only: ``outer`` (module b) calls ``inner`` (module a);
    after a.py changes, numba alone still runs the old ``inner`` inside the cached ``outer``; with the stamp
    (``drop_stale_kernels``, run at ``import ppoe_core``) the package's kernels are dropped and recompiled."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef inner(x):\n    return x + 1\n")
    (pkg / "b.py").write_text("from numba import njit\nfrom pkg.a import inner\n\n"
                              "@njit(cache=True)\ndef outer(x):\n    return inner(x) * 10\n")
    cache = tmp_path / "cache"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(tmp_path)]), "NUMBA_CACHE_DIR": str(cache)}

    def run(drop: bool) -> tuple[str, str]:
        code = ("import logging, pathlib; logging.basicConfig(level=logging.INFO)\n"
                "import ppoe_core.compile_cache as c\n"
                f"loc = c.CacheLocation(pathlib.Path({str(cache)!r}), 'environment', '')\n"
                f"{'print(c.drop_stale_kernels(loc, pathlib.Path(' + repr(str(pkg)) + ')))' if drop else ''}\n"
                "import pkg.b\nprint(pkg.b.outer(1))\n")
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        return res.stdout.split()[-1], res.stderr

    assert run(drop=True)[0] == "20"  # first run: nothing to drop, the stamp is written
    assert run(drop=False)[0] == "20" and list(cache.rglob("*.nbi"))
    (pkg / "a.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef inner(x):\n    return x + 2\n")
    assert run(drop=False)[0] == "20", "numba alone keeps the stale inlined kernel (the reason for the stamp)"
    value, log = run(drop=True)
    assert value == "30" and "kernel sources changed since the cache was written: removed" in log, log
    value, log = run(drop=True)
    assert value == "30" and "removed" not in log  # stamp current: the fresh cache is kept
