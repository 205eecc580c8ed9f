"""The one YAML reader of ppoe_core: mappings and lists that remember their line numbers.

Every YAML file the tools read (model YAML, simulation scenarios, node model files) goes through
:func:`read_yaml_file` / :func:`read_yaml_text`, so every error names the file and the line.
YAML 1.2 floats: ``1e-5`` (no dot) is a float, as model files use it.  Duplicate keys are errors.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml

from ppoe_core.errors import ModelConfigError, PpoeError

__all__ = ["read_yaml_file", "read_yaml_text", "read_yaml_mapping"]


class LineDict(dict):
    """dict that remembers its own line and the line of each key (1-based)."""

    line: int | None = None
    key_lines: dict


class LineList(list):
    line: int | None = None


class _Loader(yaml.SafeLoader):
    pass


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> LineDict:
    loader.flatten_mapping(node)
    out = LineDict()
    out.line = node.start_mark.line + 1
    out.key_lines = {}
    for knode, vnode in node.value:
        key = loader.construct_object(knode, deep=True)
        if not isinstance(key, (str, int, float, bool)) and key is not None:
            raise ModelConfigError(f"line {knode.start_mark.line + 1}: mapping key must be a scalar")
        if key in out:
            raise ModelConfigError(
                f"{loader.name}:{knode.start_mark.line + 1}: duplicate key '{key}'"
            )
        out[key] = loader.construct_object(vnode, deep=True)
        out.key_lines[key] = knode.start_mark.line + 1
    return out


def _construct_sequence(loader: _Loader, node: yaml.SequenceNode) -> LineList:
    out = LineList(loader.construct_object(c, deep=True) for c in node.value)
    out.line = node.start_mark.line + 1
    return out


# YAML 1.2 floats: PyYAML (YAML 1.1) reads "1e-5" (no dot) as a string; model files use it a lot.
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)


def read_yaml_text(text: str, where: str, what: str = "YAML",
                   error: type[PpoeError] = ModelConfigError) -> Any:
    """Parse YAML text with line numbers (mappings are ``LineDict``, lists ``LineList``); ``None`` -> ``{}``.

    Raises
    ------
    error
        ``"{where}:{line}: {what} does not parse: {problem}"`` or a duplicate / non-scalar key.
    """
    try:
        loader = _Loader(text)
        loader.name = where
        try:
            data = loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise error(f"{where}{line}: {what} does not parse: {problem}") from None
    except ModelConfigError as exc:
        msg = str(exc)
        raise error(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return {} if data is None else data


def read_yaml_file(path: str | os.PathLike, what: str = "YAML",
                   error: type[PpoeError] = ModelConfigError) -> tuple[Any, str]:
    """Read and parse a YAML file: ``(data, where)`` with ``where`` the path as given.

    Raises
    ------
    error
        ``"{path}: cannot read {what} (...)"``, ``"{path}: {what} is not UTF-8 text (...)"`` or a
        parse error naming the line (:func:`read_yaml_text`).
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise error(f"{p}: {what} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    return read_yaml_text(text, str(p), what, error), str(p)


def read_yaml_mapping(path: str | os.PathLike, what: str = "YAML",
                      error: type[PpoeError] = ModelConfigError) -> dict[str, Any]:
    """A YAML file whose top level must be a mapping (an empty path or an empty file: ``{}``).

    Raises
    ------
    error
        As :func:`read_yaml_file`, or ``"{path}: top level of the {what} must be a mapping, got ..."``.
    """
    if not str(path):
        return {}
    data, where = read_yaml_file(path, what, error)
    if not isinstance(data, dict):
        raise error(f"{where}: top level of the {what} must be a mapping, got {type(data).__name__}")
    return data
