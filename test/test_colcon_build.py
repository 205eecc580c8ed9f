"""``colcon build`` of the package installs the executables under lib/ppoe_ros and the config under share/ppoe_ros.

The package sources are copied to a temporary workspace first, so the build
leaves nothing (egg-info, build/) in the repository.  Needs colcon-core,
colcon-ros and colcon-python-setup-py (PyPI).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

PACKAGE_ITEMS = ["package.xml", "setup.py", "setup.cfg", "resource", "ppoe_core", "ppoe_ros", "config", "launch"]
NODES = ["kinematics_node", "contact_node", "tag_bearing_node", "fusion_node"]

pytest.importorskip("colcon_core", reason="colcon-core not installed (pip install colcon-core colcon-ros "
                                          "colcon-python-setup-py)")


@pytest.fixture(scope="module")
def install_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    ws = tmp_path_factory.mktemp("colcon_ws")
    src = ws / "src" / "ppoe_ros"
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for item in PACKAGE_ITEMS:
        p = REPO / item
        if p.is_dir():
            shutil.copytree(p, src / item, ignore=ignore)
        else:
            shutil.copy2(p, src / item)
    colcon = [sys.executable, "-c", "import sys; from colcon_core.command import main; sys.exit(main())"]
    # setup.py runs `ppoe warmup` on the installed copy; here for one node only (the whole set takes minutes)
    env = dict(os.environ, COLCON_HOME=str(ws / "colcon_home"), PPOE_WARMUP_NODES="contact_node")
    env.pop("NUMBA_CACHE_DIR", None)
    res = subprocess.run(
        colcon + ["--log-base", str(ws / "log"), "build", "--base-paths", str(ws / "src"),
                  "--build-base", str(ws / "build"), "--install-base", str(ws / "install"),
                  "--event-handlers", "console_direct+"],
        cwd=ws, env=env, capture_output=True, text=True, timeout=300,
    )
    assert res.returncode == 0, f"colcon build failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    assert "Finished <<< ppoe_ros" in res.stdout
    return ws / "install" / "ppoe_ros"


def test_executables_installed_under_lib(install_dir: Path) -> None:
    lib = install_dir / "lib" / "ppoe_ros"
    for exe in NODES + ["ppoe"]:
        path = lib / exe
        assert path.is_file(), f"{path} not installed"
        assert os.access(path, os.X_OK), f"{path} is not executable"
        assert f"'{exe}'" in path.read_text(), f"{path} is not the {exe} entry point"


def test_config_and_launch_installed_under_share(install_dir: Path) -> None:
    share = install_dir / "share" / "ppoe_ros"
    assert (share / "package.xml").is_file()
    assert (install_dir / "share" / "ament_index" / "resource_index" / "packages" / "ppoe_ros").is_file()
    expected = sorted(str(p.relative_to(REPO / "config")) for p in (REPO / "config").rglob("*.*"))
    installed = sorted(str(p.relative_to(share / "config")) for p in (share / "config").rglob("*.*"))
    assert installed == expected
    assert {"nodes/kinematics_node.yaml", "nodes/contact_node.yaml", "robots/arm7.urdf"} <= set(installed)
    assert (share / "launch" / "ppoe.launch.py").is_file()


def test_installed_ppoe_entry_point_runs(install_dir: Path) -> None:
    site = next((install_dir / "lib").glob("python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    res = subprocess.run([sys.executable, str(install_dir / "lib" / "ppoe_ros" / "ppoe"), "play", "--help"],
                         cwd=install_dir, env=env, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "--clock" in res.stdout and "--rate" in res.stdout
    # the installed copy is the one that ran, not the repository
    probe = subprocess.run([sys.executable, "-c", "import ppoe_ros; print(ppoe_ros.__file__)"],
                           cwd=install_dir, env=env, capture_output=True, text=True, timeout=60)
    assert probe.stdout.strip().startswith(str(site))


def test_colcon_build_ran_ppoe_warmup_on_the_installed_copy(install_dir: Path) -> None:
    """setup.py's install step compiled the (here: contact) node's kernels into the installed package's cache."""
    site = next((install_dir / "lib").glob("python3*/site-packages"))
    index = list((site / "ppoe_core").rglob("__pycache__/*.nbi"))
    assert index, "no numba cache index in the installed package: ppoe warmup did not run"
    assert all(str(p).startswith(str(site)) for p in index)
