"""Run launch/ppoe.launch.py without launch / launch_ros (neither has a PyPI wheel for Jazzy).

* :func:`ament_prefix`: an install prefix of this checkout as colcon lays out its share part (the ament index
  marker, ``share/ppoe_ros`` with config/, launch/, package.xml linked), for the real ament_index_python.
* :func:`load_launch`: the launch file executed against recording stand-ins of the launch classes: each
  ``Node(...)`` / ``DeclareLaunchArgument(...)`` keeps its arguments (``.args``, ``.kwargs``).
* :func:`node_command`: the command line launch_ros builds for a recorded ``Node`` (``--ros-args``, the
  ros_arguments, ``__node`` / ``__ns`` remaps, one ``--params-file`` per parameter entry, a dict written to a
  temporary file under ``/**`` as launch_ros does), running ``python -m ppoe_ros.nodes.<executable>`` (the
  entry point colcon installs as ``lib/ppoe_ros/<executable>``).
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path
from typing import Any

import pytest
import yaml
from conftest import REPO

LAUNCH = REPO / "launch" / "ppoe.launch.py"

__all__ = ["LAUNCH", "ament_prefix", "load_launch", "launch_context", "node_command"]


class _Rec:
    """Stand-in of a launch class: remembers its arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.kwargs = kwargs


class _LaunchConfiguration(_Rec):
    def perform(self, context: dict[str, str]) -> str:
        return context[self.args[0]]


def _stub_modules() -> dict[str, types.ModuleType]:
    names = {
        "launch": ["LaunchDescription"],
        "launch.actions": ["DeclareLaunchArgument", "OpaqueFunction", "EmitEvent", "RegisterEventHandler"],
        "launch.substitutions": [],
        "launch.events": [],
        "launch_ros": [],
        "launch_ros.actions": ["Node", "LifecycleNode"],
        "launch_ros.event_handlers": ["OnStateTransition"],
        "launch_ros.events": [],
        "launch_ros.events.lifecycle": ["ChangeState"],
    }
    mods = {}
    for mod_name, classes in names.items():
        mod = types.ModuleType(mod_name)
        for cls in classes:
            setattr(mod, cls, type(cls, (_Rec,), {}))
        mods[mod_name] = mod
    mods["launch.substitutions"].LaunchConfiguration = _LaunchConfiguration  # type: ignore[attr-defined]
    mods["launch.events"].matches_action = lambda action: ("matches", action)  # type: ignore[attr-defined]
    return mods


def ament_prefix(root: Path) -> Path:
    """``root`` made an ament install prefix of ppoe_ros (share part only); returns it."""
    index = root / "share" / "ament_index" / "resource_index" / "packages"
    index.mkdir(parents=True)
    (index / "ppoe_ros").write_text("")
    share = root / "share" / "ppoe_ros"
    share.mkdir()
    for item in ("config", "launch", "package.xml"):
        (share / item).symlink_to(REPO / item)
    return root


def load_launch(monkeypatch: pytest.MonkeyPatch, prefix: Path) -> Any:
    """The launch file, with launch / launch_ros stand-ins and AMENT_PREFIX_PATH = ``prefix`` (made by
    :func:`ament_prefix` when it has no index yet)."""
    if not (prefix / "share" / "ament_index").exists():
        ament_prefix(prefix)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    for name, mod in _stub_modules().items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location("ppoe_launch_under_test", LAUNCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def launch_context(module: Any, **values: str) -> dict[str, str]:
    """Launch argument values: the declared defaults, overridden by ``values``."""
    return {**{k: d for k, (d, _) in module.ARGUMENTS.items()}, **values}


def console_scripts() -> dict[str, str]:
    """console_scripts of setup.py, read with ast: name -> module (``ppoe_ros.nodes.kinematics_node``)."""
    import ast

    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "entry_points":
            scripts = ast.literal_eval(node.value)["console_scripts"]
            return {k.strip(): v.strip().split(":")[0] for k, v in (s.split("=", 1) for s in scripts)}
    raise AssertionError("setup.py has no entry_points")


def node_command(node: Any, tmp_dir: Path) -> list[str]:
    """The command line launch_ros runs for the recorded ``Node`` / ``LifecycleNode`` action ``node`` (see the
    module docstring); the executable as ``python -m`` of its console script's module."""
    kw = node.kwargs
    module = console_scripts()[kw["executable"]]
    cmd = [sys.executable, "-m", module, *kw.get("arguments", []), "--ros-args", *kw.get("ros_arguments", [])]
    cmd += ["-r", f"__node:={kw['name']}"]
    if kw.get("namespace"):
        cmd += ["-r", f"__ns:=/{kw['namespace'].strip('/')}"]
    for i, entry in enumerate(kw.get("parameters", [])):
        if isinstance(entry, dict):
            path = tmp_dir / f"launch_params_{kw['name']}_{i}.yaml"
            path.write_text(yaml.safe_dump({"/**": {"ros__parameters": entry}}))
            entry = str(path)
        cmd += ["--params-file", str(entry)]
    return cmd
