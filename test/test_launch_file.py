"""launch/ppoe.launch.py and the node parameter files, checked without launch_ros.

launch / launch_ros are not installable here, so the launch file is (1) read with
``ast`` for the executables and config files it names, and (2) executed against
small recording stand-ins of the launch classes to check the structure of what
``generate_launch_description()`` returns.  The node config files are checked
against the parameters the nodes declare, and for a comment on every key.
"""

from __future__ import annotations

import ast
import importlib.util
import sys
import types

import pytest
import yaml
from conftest import REPO

LAUNCH = REPO / "launch" / "ppoe.launch.py"


def _console_scripts() -> dict[str, str]:
    """console_scripts of setup.py, read with ast: name -> module:function."""
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "entry_points":
            entry_points = ast.literal_eval(node.value)
            return dict(s.replace(" ", "").split("=", 1) for s in entry_points["console_scripts"])
    raise AssertionError("setup.py has no entry_points")


def _launch_calls() -> list[ast.Call]:
    tree = ast.parse(LAUNCH.read_text(), filename=str(LAUNCH))
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "Node"]


def test_every_executable_exists_in_setup_py() -> None:
    scripts = _console_scripts()
    calls = _launch_calls()
    executables = []
    for call in calls:
        kw = {k.arg: k.value for k in call.keywords}
        assert isinstance(kw.get("executable"), ast.Constant), f"line {call.lineno}: executable must be a literal"
        executables.append(kw["executable"].value)
    missing = [e for e in executables if e not in scripts]
    assert not missing, f"launch file starts executables missing from setup.py: {missing}"
    node_scripts = sorted(s for s in scripts if s.endswith("_node"))
    assert sorted(executables) == node_scripts, "launch file must start every node exactly once"
    # each entry point's module exists in the package
    for name in executables:
        module = scripts[name].split(":")[0]
        path = REPO / module.replace(".", "/")
        assert path.with_suffix(".py").is_file() or (path / "__init__.py").is_file(), f"{name}: module {module} missing"


def test_every_config_file_named_exists() -> None:
    tree = ast.parse(LAUNCH.read_text())
    named = sorted({n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
                    and isinstance(n.value, str) and n.value.endswith((".yaml", ".yml"))})
    assert len(named) == 4, named
    missing = [f for f in named if not (REPO / "config" / "nodes" / f).is_file()]
    assert not missing, f"launch file names config files that do not exist in config/: {missing}"


class _Rec:
    """Stand-in of a launch class: remembers its arguments."""

    def __init__(self, *args, **kwargs):
        self.args = args
        self.kwargs = kwargs


def _stub_modules() -> dict[str, types.ModuleType]:
    names = {
        "launch": ["LaunchDescription"],
        "launch.actions": ["DeclareLaunchArgument"],
        "launch.conditions": ["IfCondition"],
        "launch.substitutions": ["LaunchConfiguration", "PathJoinSubstitution"],
        "launch_ros": [],
        "launch_ros.actions": ["Node"],
        "launch_ros.parameter_descriptions": ["ParameterValue"],
        "launch_ros.substitutions": ["FindPackageShare"],
    }
    mods = {}
    for mod_name, classes in names.items():
        mod = types.ModuleType(mod_name)
        for cls in classes:
            setattr(mod, cls, type(cls, (_Rec,), {}))
        mods[mod_name] = mod
    return mods


def test_generate_launch_description_structure(monkeypatch: pytest.MonkeyPatch) -> None:
    for name, mod in _stub_modules().items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location("ppoe_launch_under_test", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    ld = module.generate_launch_description()
    entities = ld.args[0]
    declared = {e.args[0] for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    nodes = [e for e in entities if type(e).__name__ == "Node"]
    assert {"model_file", "use_sim_time"} <= declared
    model_arg = next(e for e in entities if type(e).__name__ == "DeclareLaunchArgument" and e.args[0] == "model_file")
    assert "default_value" not in model_arg.kwargs, "model_file must be required"
    assert len(nodes) == 4
    for node in nodes:
        kw = node.kwargs
        exe = kw["executable"]
        assert kw["package"] == "ppoe_ros" and kw["name"] == exe
        params_file, overrides = kw["parameters"]
        assert params_file.args[0][1:] == ["config", "nodes", f"{exe}.yaml"]
        assert params_file.args[0][0].args == ("ppoe_ros",)
        assert overrides["model_file"].args == ("model_file",)
        assert overrides["use_sim_time"].kwargs["value_type"] is bool
        cond_arg = kw["condition"].args[0].args[0]
        assert cond_arg in declared, f"{exe}: condition on undeclared launch argument {cond_arg}"


NODES = ["kinematics_node", "contact_node", "tag_bearing_node", "fusion_node"]


def _params_of(node_name: str) -> dict:
    """``ros__parameters`` of config/<node>.yaml, under ``/**`` or the node's name (the launch file's name)."""
    data = yaml.safe_load((REPO / "config" / "nodes" / f"{node_name}.yaml").read_text())
    assert len(data) == 1 and list(data)[0] in ("/**", node_name), \
        f"{node_name}.yaml: parameters must sit under '/**:' or '{node_name}:' then 'ros__parameters:'"
    return next(iter(data.values()))["ros__parameters"]


@pytest.mark.parametrize("node_name", NODES)
def test_config_matches_declared_parameters(node_name: str) -> None:
    module = importlib.import_module(f"ppoe_ros.nodes.{node_name}")
    specs = {s.name: s for s in module.PARAMS}
    params = _params_of(node_name)
    assert set(params) == set(specs), f"config/{node_name}.yaml keys differ from ppoe_ros.nodes.{node_name}.PARAMS"
    for name, value in params.items():
        assert specs[name].validate(value) is None, f"config/{node_name}.yaml: {name} = {value!r} is refused"
        if node_name in ("kinematics_node", "contact_node"):  # these files list the defaults
            assert value == specs[name].default, f"{node_name}.yaml: {name} = {value!r} is not the default"


@pytest.mark.parametrize("node_name", NODES)
def test_every_config_key_has_a_comment(node_name: str) -> None:
    lines = (REPO / "config" / "nodes" / f"{node_name}.yaml").read_text().splitlines()
    keys = set(_params_of(node_name))
    for i, line in enumerate(lines):
        key = line.strip().split(":", 1)[0]
        if line.startswith("    ") and not line.strip().startswith("#") and key in keys:
            assert i > 0 and lines[i - 1].strip().startswith("#"), f"{node_name}.yaml:{i + 1}: '{key}' has no comment"
            comment = lines[i - 1].lower()
            j = i - 1
            while j > 0 and lines[j - 1].strip().startswith("#"):  # the whole comment block
                j -= 1
                comment = lines[j].lower() + comment
            assert "default" in comment, f"{node_name}.yaml:{i + 1}: comment of '{key}' names no default"
