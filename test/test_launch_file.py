"""launch/ppoe.launch.py and the node parameter files, checked without launch_ros.

launch / launch_ros are not installable here (no PyPI wheel of either for Jazzy), so the launch file is executed
against small recording stand-ins of the launch classes, with the real ament_index_python over an ament prefix
made of this checkout (:func:`ament_prefix`): the arguments it declares, the nodes :func:`launch_nodes` builds
from their values, and that every parameter it sets is one the node declares.  test/test_launch_run.py starts
the nodes it describes.  The node config files are checked against the parameters the nodes declare, and for a
comment on every key.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from pathlib import Path

import pytest
import yaml
from conftest import REPO
from launch_helpers import LAUNCH, launch_context
from launch_helpers import load_launch as _load_launch

_context = launch_context


def _console_scripts() -> dict[str, str]:
    """console_scripts of setup.py, read with ast: name -> module:function."""
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "entry_points":
            entry_points = ast.literal_eval(node.value)
            return dict(s.replace(" ", "").split("=", 1) for s in entry_points["console_scripts"])
    raise AssertionError("setup.py has no entry_points")


def test_every_executable_exists_in_setup_py(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    module = _load_launch(monkeypatch, tmp_path)
    scripts = _console_scripts()
    executables = [exe for exe, _, _ in module.NODE_OVERRIDES]
    missing = [e for e in executables if e not in scripts]
    assert not missing, f"launch file starts executables missing from setup.py: {missing}"
    node_scripts = sorted(s for s in scripts if s.endswith("_node"))
    assert sorted(executables) == node_scripts, "launch file must start every node exactly once"
    for name in executables:
        module_name = scripts[name].split(":")[0]
        path = REPO / module_name.replace(".", "/")
        assert path.with_suffix(".py").is_file() or (path / "__init__.py").is_file(), f"{name}: {module_name} missing"


def test_launch_arguments_set_real_node_parameters(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Every parameter a launch argument sets is declared by that node (else the node would report it as an
    unknown key), and the arguments the issue asks for exist."""
    module = _load_launch(monkeypatch, tmp_path)
    ld = module.generate_launch_description()
    entities = ld.args[0]
    declared = {e.kwargs.get("name", e.args[0] if e.args else None) for e in entities
                if type(e).__name__ == "DeclareLaunchArgument"}
    assert {"namespace", "urdf", "model", "frame_prefix", "use_sim_time"} <= declared
    assert declared == set(module.ARGUMENTS)
    (opaque,) = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
    assert opaque.kwargs["function"] is module.launch_nodes
    for exe, switch, keys in module.NODE_OVERRIDES:
        assert switch in declared
        names = {s.name for s in importlib.import_module(f"ppoe_ros.nodes.{exe}").PARAMS}
        unknown = [k for k in keys if k not in names and k != "use_sim_time"]
        assert not unknown, f"{exe}: the launch file sets parameters the node does not have: {unknown}"
        if "frame_prefix" in names:
            assert "frame_prefix" in keys, f"{exe}: frame_prefix argument not passed on"


def test_launch_nodes_namespace_urdf_model_prefix(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    module = _load_launch(monkeypatch, tmp_path / "prefix")
    share = tmp_path / "prefix" / "share" / "ppoe_ros"
    urdf = tmp_path / "robot.urdf"
    urdf.write_text("<robot name='r'/>")
    model = tmp_path / "m.yaml"
    model.write_text("perturbations: {}\n")
    ctx = _context(module, model=str(model), urdf=str(urdf), namespace="robot1", frame_prefix="robot1/",
                   use_sim_time="true", contact="false", log_level="DEBUG")
    nodes = module.launch_nodes(ctx)
    assert [n.kwargs["executable"] for n in nodes] == ["kinematics_node", "tag_bearing_node", "fusion_node"]
    for node in nodes:
        kw = node.kwargs
        exe = kw["executable"]
        assert kw["package"] == "ppoe_ros" and kw["name"] == exe and kw["namespace"] == "robot1"
        assert kw["ros_arguments"] == ["--log-level", "debug"]
        params_file, overrides = kw["parameters"]
        assert params_file == str(share / "config" / "nodes" / f"{exe}.yaml")
        assert overrides["model_file"] == str(model) and overrides["use_sim_time"] is True
        if exe != "tag_bearing_node":
            assert overrides["robot_description"] == "<robot name='r'/>"
            assert overrides["frame_prefix"] == "robot1/"
    # defaults: root namespace, URDF from the topic, no prefix; the old argument name still works
    nodes = module.launch_nodes(_context(module, model_file=str(model)))
    assert len(nodes) == 4 and all(n.kwargs["namespace"] == "" for n in nodes)
    fusion = nodes[-1].kwargs["parameters"][1]
    assert fusion == {"model_file": str(model), "robot_description": "", "frame_prefix": "", "use_sim_time": False}
    assert nodes[0].kwargs["ros_arguments"] == ["--log-level", "info"]
    with pytest.raises(RuntimeError, match="model:=MODEL.yaml is required"):
        module.launch_nodes(_context(module))


def test_launch_paths_package_uris_relative_and_params_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """package:// URIs, paths relative to the launch directory or to the package share, a params_file between the
    shipped defaults and the arguments; a missing file or a bad level is named."""
    module = _load_launch(monkeypatch, tmp_path / "prefix")
    share = (tmp_path / "prefix" / "share" / "ppoe_ros").resolve()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mine.yaml").write_text("kinematics_node:\n  ros__parameters:\n    order: 4\n")
    monkeypatch.chdir(elsewhere)
    ctx = _context(module, model="package://ppoe_ros/config/robots/arm7_model.yaml", urdf="config/robots/arm7.urdf",
                   params_file="mine.yaml", tag_bearing="false", contact="false", fusion="false")
    (node,) = module.launch_nodes(ctx)
    defaults, mine, overrides = node.kwargs["parameters"]
    assert defaults == str(share / "config" / "nodes" / "kinematics_node.yaml")
    assert mine == str((elsewhere / "mine.yaml").resolve())
    assert overrides["model_file"] == str((REPO / "config" / "robots" / "arm7_model.yaml").resolve())
    assert overrides["robot_description"] == (REPO / "config" / "robots" / "arm7.urdf").read_text()
    with pytest.raises(RuntimeError, match="params_file:=nope.yaml: no such file"):
        module.launch_nodes({**ctx, "params_file": "nope.yaml"})
    with pytest.raises(RuntimeError, match="package 'no_such_pkg' not found"):
        module.launch_nodes({**ctx, "model": "package://no_such_pkg/m.yaml"})
    with pytest.raises(RuntimeError, match="log_level:=loud is not one of"):
        module.launch_nodes({**ctx, "log_level": "loud"})


def test_launch_expands_xacro_and_starts_robot_state_publisher(monkeypatch: pytest.MonkeyPatch,
                                                               tmp_path: Path) -> None:
    """A .xacro URDF is expanded (the xacro package, when installed) and given to robot_state_publisher and the
    nodes; robot_state_publisher is refused without a URDF or when it is not installed."""
    pytest.importorskip("xacro")
    module = _load_launch(monkeypatch, tmp_path / "prefix")
    xacro_file = tmp_path / "arm.urdf.xacro"
    xacro_file.write_text('<robot name="arm" xmlns:xacro="http://www.ros.org/wiki/xacro">'
                          '<xacro:property name="len" value="0.5"/><link name="base_link"/><link name="tool0"/>'
                          '<joint name="j" type="fixed"><parent link="base_link"/><child link="tool0"/>'
                          '<origin xyz="0 0 ${len * 2}"/></joint></robot>')
    model = tmp_path / "m.yaml"
    model.write_text("perturbations: {}\n")
    ctx = _context(module, model=str(model), urdf=str(xacro_file), tag_bearing="false", contact="false",
                   fusion="false", frame_prefix="r/", robot_state_publisher="true")
    rsp_prefix = tmp_path / "prefix"  # make robot_state_publisher "installed" in the same prefix
    (rsp_prefix / "share" / "ament_index" / "resource_index" / "packages" / "robot_state_publisher").write_text("")
    rsp, kin = module.launch_nodes(ctx)
    assert (rsp.kwargs["package"], rsp.kwargs["executable"]) == ("robot_state_publisher", "robot_state_publisher")
    (params,) = rsp.kwargs["parameters"]
    assert params["frame_prefix"] == "r/" and 'xyz="0 0 1.0"' in params["robot_description"]
    assert "xacro:" not in params["robot_description"]
    assert kin.kwargs["parameters"][-1]["robot_description"] == params["robot_description"]
    (rsp_prefix / "share" / "ament_index" / "resource_index" / "packages" / "robot_state_publisher").unlink()
    with pytest.raises(RuntimeError, match="robot_state_publisher is not installed"):
        module.launch_nodes(ctx)
    with pytest.raises(RuntimeError, match="needs urdf:=FILE"):
        module.launch_nodes({**ctx, "urdf": ""})


def test_launch_markers_and_rviz(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """markers:=true starts ppoe_markers in the namespace; rviz:=true starts rviz2 with the shipped config (refused,
    naming the apt package, when rviz2 is not installed)."""
    module = _load_launch(monkeypatch, tmp_path / "prefix")
    share = tmp_path / "prefix" / "share" / "ppoe_ros"
    model = tmp_path / "m.yaml"
    model.write_text("perturbations: {}\n")
    ctx = _context(module, model=str(model), kinematics="false", tag_bearing="false", contact="false",
                   fusion="false", markers="true", namespace="r1", use_sim_time="true")
    (markers,) = module.launch_nodes(ctx)
    assert (markers.kwargs["executable"], markers.kwargs["namespace"]) == ("ppoe_markers", "r1")
    assert markers.kwargs["parameters"] == [{"use_sim_time": True}]
    assert "ppoe_markers" in _console_scripts()
    with pytest.raises(RuntimeError, match="apt install ros-jazzy-rviz2"):
        module.launch_nodes({**ctx, "rviz": "true"})
    (tmp_path / "prefix" / "share" / "ament_index" / "resource_index" / "packages" / "rviz2").write_text("")
    _, rviz = module.launch_nodes({**ctx, "rviz": "true"})
    config = Path(rviz.kwargs["arguments"][1])
    assert rviz.kwargs["arguments"][0] == "-d" and config == share / "config" / "rviz" / "ppoe.rviz"
    assert config.is_file()


def test_launch_lifecycle_nodes_and_autostart(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """lifecycle:=true starts ppoe_managed NODE as a LifecycleNode with the same parameters, and (autostart) the
    configure event plus an activate once the node went configuring -> inactive; autostart:=false leaves them to a
    lifecycle manager."""
    from lifecycle_msgs.msg import Transition

    module = _load_launch(monkeypatch, tmp_path / "prefix")
    model = tmp_path / "m.yaml"
    model.write_text("perturbations: {}\n")
    ctx = _context(module, model=str(model), tag_bearing="false", contact="false", lifecycle="true", namespace="r1")
    actions = module.launch_nodes(ctx)
    kinds = [type(a).__name__ for a in actions]
    assert kinds == ["LifecycleNode", "RegisterEventHandler", "EmitEvent"] * 2
    plain = module.launch_nodes({**ctx, "lifecycle": "false"})
    for node, twin in zip(actions[::3], plain):
        kw = node.kwargs
        assert (kw["executable"], kw["arguments"]) == ("ppoe_managed", [twin.kwargs["executable"]])
        assert kw["name"] == twin.kwargs["executable"] and kw["namespace"] == "r1"
        assert kw["parameters"] == twin.kwargs["parameters"]
    handler, configure = actions[1].args[0], actions[2].kwargs["event"]
    assert configure.kwargs["transition_id"] == Transition.TRANSITION_CONFIGURE
    assert configure.kwargs["lifecycle_node_matcher"] == ("matches", actions[0])
    assert handler.kwargs["target_lifecycle_node"] is actions[0]
    assert (handler.kwargs["start_state"], handler.kwargs["goal_state"]) == ("configuring", "inactive")
    (activate,) = handler.kwargs["entities"]
    assert activate.kwargs["event"].kwargs["transition_id"] == Transition.TRANSITION_ACTIVATE
    manual = module.launch_nodes({**ctx, "autostart": "false"})
    assert [type(a).__name__ for a in manual] == ["LifecycleNode"] * 2
    assert "ppoe_managed" in _console_scripts()


def test_config_files_exist_for_every_node() -> None:
    missing = [f"{n}.yaml" for n in NODES if not (REPO / "config" / "nodes" / f"{n}.yaml").is_file()]
    assert not missing, missing


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


def test_launch_file_imports_without_launch_ros_and_says_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without launch_ros (a pip install) the file still imports; building the description names what is missing."""
    monkeypatch.setitem(sys.modules, "launch_ros", None)  # import launch_ros -> ImportError
    monkeypatch.setitem(sys.modules, "launch_ros.actions", None)
    spec = importlib.util.spec_from_file_location("ppoe_launch_plain", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert {"namespace", "urdf", "model", "frame_prefix"} <= set(module.ARGUMENTS)
    with pytest.raises(RuntimeError, match="needs the ROS 2 packages launch and launch_ros"):
        module.generate_launch_description()
