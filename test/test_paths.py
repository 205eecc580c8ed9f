"""``package://`` URIs and relative paths (ppoe_core/io/paths.py, ppoe_ros/common/paths.py), without ROS nodes."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import yaml
from conftest import REPO

from ppoe_core.errors import ModelConfigError
from ppoe_core.io.paths import package_share_directory, resolve_path


def _prefix(root: Path, package: str) -> Path:
    (root / "share" / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (root / "share" / "ament_index" / "resource_index" / "packages" / package).write_text("")
    (root / "share" / package / "cfg").mkdir(parents=True)
    (root / "share" / package / "cfg" / "m.yaml").write_text("perturbations: {}\n")
    return root


def test_package_uri_from_the_ament_prefix_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    first, second = _prefix(tmp_path / "a", "my_robot"), _prefix(tmp_path / "b", "my_robot")
    monkeypatch.setenv("AMENT_PREFIX_PATH", os.pathsep.join([str(first), str(second)]))
    assert package_share_directory("my_robot") == first / "share" / "my_robot"
    assert resolve_path("package://my_robot/cfg/m.yaml") == str(first / "share" / "my_robot" / "cfg" / "m.yaml")
    with pytest.raises(ModelConfigError, match="parameter model_file: package://nope/x.yaml: package 'nope' not"):
        resolve_path("package://nope/x.yaml", what="parameter model_file")
    with pytest.raises(ModelConfigError, match="not of the form package://PACKAGE/PATH"):
        resolve_path("package://my_robot")


def test_ppoe_ros_falls_back_to_the_checkout(monkeypatch: pytest.MonkeyPatch) -> None:
    """Not installed anywhere (a source checkout on PYTHONPATH): package://ppoe_ros/ is the checkout."""
    monkeypatch.setenv("AMENT_PREFIX_PATH", "")
    monkeypatch.setattr(sys, "prefix", "/nonexistent-prefix")
    assert package_share_directory("ppoe_ros") == REPO.resolve()
    assert Path(resolve_path("package://ppoe_ros/config/robots/arm7.urdf")).is_file()
    with pytest.raises(ModelConfigError):
        package_share_directory("other_pkg")


def test_relative_paths_cwd_then_search_dirs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg, models, cwd = tmp_path / "cfg", tmp_path / "models", tmp_path / "deep" / "cwd"
    for d in (cfg, models, cwd):
        d.mkdir(parents=True)
    (models / "m.yaml").write_text("x: 1\n")
    (cwd / "local.yaml").write_text("x: 2\n")
    monkeypatch.chdir(cwd)
    assert resolve_path("local.yaml", [cfg]) == "local.yaml"  # the working directory first
    assert resolve_path("../models/m.yaml", [cfg]) == str(cfg / "../models/m.yaml")
    assert resolve_path("m.yaml", [cfg, models]) == str(models / "m.yaml")
    assert resolve_path("missing.yaml", [cfg]) == "missing.yaml"  # unchanged: the reader names it
    assert resolve_path(f"file://{models}/m.yaml") == str(models / "m.yaml")
    assert resolve_path("") == ""
    monkeypatch.setenv("HOME", str(models))
    assert resolve_path("~/m.yaml") == str(models / "m.yaml")


def test_params_file_dirs_and_node_parameters(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    from ppoe_ros.common.paths import params_file_dirs, resolve_path_parameters

    argv = ["node", "--params-file", "/not/ros/arg.yaml", "--ros-args", "-p", "a:=1", "--params-file",
            str(tmp_path / "cfg" / "p.yaml"), "--params-file", str(tmp_path / "cfg" / "q.yaml"), "--",
            "--params-file", "/after/terminator.yaml"]
    assert params_file_dirs(argv) == [(tmp_path / "cfg").resolve()]

    class _Node:
        def get_fully_qualified_name(self) -> str:
            return "/r1/fusion_node"

    (tmp_path / "cfg").mkdir()
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "m.yaml").write_text("x: 1\n")
    values = {"model_file": "../robots/m.yaml", "online_model_out": "", "other_file": "../robots/m.yaml"}
    monkeypatch.chdir("/")
    resolve_path_parameters(_Node(), values, argv)
    assert Path(values["model_file"]).resolve() == (tmp_path / "robots" / "m.yaml").resolve()
    assert values["online_model_out"] == "" and values["other_file"] == "../robots/m.yaml"
    values = {"model_file": "config/robots/rover_model.yaml"}  # the ppoe_ros share directory as last resort
    resolve_path_parameters(_Node(), values, [])
    assert Path(values["model_file"]).is_file()
    with pytest.raises(ModelConfigError, match="node /r1/fusion_node: parameter 'model_file'"):
        resolve_path_parameters(_Node(), {"model_file": "package://nope/m.yaml"}, [])


def test_shipped_node_configs_name_existing_files() -> None:
    """The model_file of every shipped node parameter file resolves (from any directory) to a file."""
    for path in sorted((REPO / "config" / "nodes").glob("*.yaml")):
        params = next(iter(yaml.safe_load(path.read_text()).values()))["ros__parameters"]
        if params.get("model_file"):
            assert Path(resolve_path(params["model_file"], [path.parent])).is_file(), path.name
