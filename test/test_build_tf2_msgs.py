"""scripts/build_tf2_msgs.py: clear messages for a missing build tool, the include-path rewrite of the wheels'
exported CMake files, and (when it ran, as in .ci/run) the installed package: upstream Jazzy's type hash, an
import in a fresh interpreter with an empty environment, and a skip on the second run."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from conftest import REPO, load_script

SCRIPT = REPO / "scripts" / "build_tf2_msgs.py"
build = load_script(SCRIPT, "build_tf2_msgs")

BUILT = (Path(sys.prefix) / "share" / "tf2_msgs" / "msg" / "TFMessage.json").is_file()


def test_missing_cmake_compiler_or_python_headers_named(monkeypatch, tmp_path):
    real_which = build.shutil.which
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setattr(build.shutil, "which", lambda name: None if name == "cmake" else real_which(name))
    with pytest.raises(build.BuildError, match=r"cmake not found on PATH: install it \(.*apt-get install -y cmake"):
        build.check_tools()
    compilers = ("c++", "g++", "clang++")
    monkeypatch.setattr(build.shutil, "which", lambda name: None if name in compilers else f"/usr/bin/{name}")
    with pytest.raises(build.BuildError, match=r"no C\+\+ compiler found \(CXX or c\+\+, g\+\+, clang\+\+ on PATH\)"):
        build.check_tools()
    monkeypatch.setattr(build.shutil, "which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr(build.sysconfig, "get_paths", lambda: {"include": str(tmp_path / "nothing")})
    with pytest.raises(build.BuildError, match=r"Python headers missing: .*nothing/Python.h does not exist.*-dev"):
        build.check_tools()


def test_failure_exits_1_with_the_message(monkeypatch, capsys):
    monkeypatch.setattr(build, "importable", lambda *a, **k: False)
    monkeypatch.setattr(build.shutil, "which", lambda name: None)
    assert build.main([]) == 1
    assert "build_tf2_msgs: FAILED: cmake not found on PATH" in capsys.readouterr().err


def test_exported_include_paths_rewritten_once(tmp_path):
    import numpy

    cm = tmp_path / "share" / "geometry_msgs" / "cmake" / "export_geometry_msgs__rosidl_generator_pyExport.cmake"
    cm.parent.mkdir(parents=True)
    kept = tmp_path / "kept"
    kept.mkdir()
    text = ('set_target_properties(geometry_msgs::geometry_msgs__rosidl_generator_py PROPERTIES\n'
            '  INTERFACE_INCLUDE_DIRECTORIES "/opt/python/cp311-cp311/include/python3.11;'
            '/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include;${_IMPORT_PREFIX}/include;'
            f'{kept}"\n)\n')
    cm.write_text(text)
    assert build.fix_exported_includes(tmp_path) == [cm]
    entries = cm.read_text().split('INTERFACE_INCLUDE_DIRECTORIES "')[1].split('"')[0].split(";")
    assert entries == [sysconfig.get_paths()["include"], numpy.get_include(), "${_IMPORT_PREFIX}/include", str(kept)]
    assert build.fix_exported_includes(tmp_path) == []  # idempotent


@pytest.mark.skipif(not BUILT, reason="tf2_msgs was not built into this venv by scripts/build_tf2_msgs.py")
def test_built_package_has_upstream_type_hash_imports_bare_and_is_skipped_next_time():
    build.check_type_hash(Path(sys.prefix))
    r = subprocess.run([str(Path(sys.prefix) / "bin" / "python"), "-c", build.IMPORT_CHECK], env={},
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "tf2_msgs.msg._tf_message", r.stderr
    r = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "already importable: nothing to do" in r.stderr, r.stderr


def test_type_hash_mismatch_is_an_error(tmp_path):
    msg = tmp_path / "share" / "tf2_msgs" / "msg"
    msg.mkdir(parents=True)
    (msg / "TFMessage.json").write_text('{"type_hashes": [{"type_name": "tf2_msgs/msg/TFMessage", '
                                        '"hash_string": "RIHS01_00"}]}')
    with pytest.raises(build.BuildError, match="type hash of tf2_msgs/msg/TFMessage is RIHS01_00, upstream"):
        build.check_type_hash(tmp_path)
