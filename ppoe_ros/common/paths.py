"""Path parameters of the nodes: ``package://`` URIs and paths relative to the node's parameter files.

The parameters in :data:`PATH_PARAMETERS` are resolved by :func:`ppoe_core.io.paths.resolve_path` when a node
declares them (:func:`ppoe_ros.common.params.declare_parameters`): ``package://ppoe_ros/config/robots/x.yaml``
is the installed file, and a relative path is taken from the working directory, else from the directory of
each ``--params-file`` on the node's command line (so ``model_file: ../robots/arm7_model.yaml`` in a parameter
file works from any directory, e.g. when ``ros2 launch`` starts the node), else from the ppoe_ros share
directory (``config/robots/rover_model.yaml`` names the installed example).  The parameter keeps the value as
given (``ros2 param get`` shows it); the node uses the resolved path.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ppoe_core.errors import ModelConfigError
from ppoe_core.io.paths import package_share_directory, resolve_path

__all__ = ["PATH_PARAMETERS", "params_file_dirs", "resolve_path_parameters"]

#: node parameters that name a file or directory (read: model_file; written: online_model_out, calibration_out)
PATH_PARAMETERS = ("model_file", "online_model_out", "calibration_out")


def params_file_dirs(argv: Sequence[str] | None = None) -> list[Path]:
    """Directories of the ``--params-file`` arguments after ``--ros-args`` (``sys.argv`` when None), in order."""
    args = list(sys.argv if argv is None else argv)
    dirs: list[Path] = []
    in_ros = False
    for i, a in enumerate(args):
        if a == "--ros-args":
            in_ros = True
        elif a == "--":
            in_ros = False
        elif in_ros and a == "--params-file" and i + 1 < len(args):
            d = Path(args[i + 1]).expanduser().resolve().parent
            if d not in dirs:
                dirs.append(d)
    return dirs


def resolve_path_parameters(node: Any, values: dict[str, Any], argv: Sequence[str] | None = None) -> None:
    """Replace the values of :data:`PATH_PARAMETERS` in ``values`` by resolved paths (in place).

    Raises
    ------
    ModelConfigError
        A ``package://`` URI of an unknown package (the message names node and parameter).
    """
    dirs: list[Path] = params_file_dirs(argv)
    try:
        dirs.append(package_share_directory("ppoe_ros"))
    except ModelConfigError:  # not installed and not a checkout: no last resort
        pass
    for name in PATH_PARAMETERS:
        if isinstance(values.get(name), str) and values[name]:
            values[name] = resolve_path(values[name], dirs,
                                        what=f"node {node.get_fully_qualified_name()}: parameter '{name}'")
