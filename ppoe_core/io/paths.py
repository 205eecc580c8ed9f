"""File paths as ROS users write them: ``package://`` URIs, ``file://`` URIs, and paths relative to a config file.

``package://PKG/REL`` is ``<share of PKG>/REL``, where the share directory is found the way
``ament_index_python.get_package_share_directory`` finds it (no ROS import): the first prefix of
``AMENT_PREFIX_PATH`` that holds ``share/ament_index/resource_index/packages/PKG``, then this Python's prefix
(a ``pip install`` puts the package's ``data_files`` there), then, for ``ppoe_ros`` only, the source checkout
this module runs from (its ``package.xml`` names ``ppoe_ros``).

A relative path is taken from the working directory when it exists there, else from the first of
``search_dirs`` that has it (the nodes pass the directories of their ``--params-file`` files, so a parameter
file's ``model_file: ../robots/arm7_model.yaml`` works from any directory); a path found nowhere is returned
unchanged (the reader then names it).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from pathlib import Path

from ppoe_core.errors import ModelConfigError

__all__ = ["PACKAGE_URI", "package_share_directory", "resolve_path"]

PACKAGE_URI = "package://"
_FILE_URI = "file://"
_SELF = "ppoe_ros"


def _source_checkout() -> Path | None:
    """The repository root this code runs from, when it is a ppoe_ros source checkout."""
    root = Path(__file__).resolve().parents[2]
    xml = root / "package.xml"
    if xml.is_file() and f"<name>{_SELF}</name>" in xml.read_text(errors="replace"):
        return root
    return None


def package_share_directory(package: str) -> Path:
    """The share directory of ``package`` (see the module docstring for the search order).

    Raises
    ------
    ModelConfigError
        No prefix has the package; the message lists where it looked.
    """
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    for prefix in prefixes:
        if (Path(prefix) / "share" / "ament_index" / "resource_index" / "packages" / package).is_file():
            return Path(prefix) / "share" / package
    if package == _SELF and (root := _source_checkout()) is not None:
        return root
    raise ModelConfigError(f"package '{package}' not found (searched AMENT_PREFIX_PATH and {sys.prefix}; "
                           f"source the workspace's setup.bash or install the package)")


def resolve_path(value: str, search_dirs: Sequence[str | os.PathLike[str]] = (), *, what: str = "path") -> str:
    """``value`` as a file system path: URIs resolved, ``~`` expanded, relative paths searched.

    Parameters
    ----------
    value : str
        ``package://PKG/REL``, ``file:///abs``, an absolute or a relative path, or "" (returned as is).
    search_dirs : sequence of path
        Where a relative path that is not in the working directory is looked for, in order.
    what : str
        Named in the error (e.g. ``"parameter model_file"``).

    Raises
    ------
    ModelConfigError
        A ``package://`` URI without a path or of an unknown package.
    """
    if not value:
        return value
    if value.startswith(PACKAGE_URI):
        package, _, rel = value[len(PACKAGE_URI):].partition("/")
        if not package or not rel:
            raise ModelConfigError(f"{what}: '{value}' is not of the form package://PACKAGE/PATH")
        try:
            return str(package_share_directory(package) / rel)
        except ModelConfigError as exc:
            raise ModelConfigError(f"{what}: {value}: {exc}") from None
    if value.startswith(_FILE_URI):
        value = value[len(_FILE_URI):]
    path = Path(value).expanduser()
    if path.is_absolute() or path.exists():
        return str(path)
    for base in search_dirs:
        if (Path(base) / path).exists():
            return str(Path(base) / path)
    return str(path)
