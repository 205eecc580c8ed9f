"""Architecture rules of the code base (issue 9), checked statically with ``ast``.

- size: no module over 600 lines, no function body over 60 lines (docstring excluded) in
  ``ppoe_core/`` and ``ppoe_ros/``;
- ``ppoe_core`` never imports rclpy, a ROS package, or ``ppoe_ros``;
- layers of ``ppoe_core`` (a lower layer may not import a higher one):
  errors < lie < robot < model < estimation < sensing < io < sim < analysis < cli;
  ``analysis`` does not import ``io.importers``;
- a node module (``ppoe_ros/nodes/*``) does not import another node module;
- no module imports another module's underscore name (``from m import _x``, ``m._x``): make it public where it
  belongs, or move the code (:data:`PRIVATE_IMPORTS_ALLOWED` lists the exceptions, each with its reason);
- no function-level import dodges an import cycle (a module that imports, inside a function, a module that imports
  it back at module level): split the modules along what they offer (:data:`CYCLE_IMPORTS_ALLOWED`);
- a compiled module loaded by name (``compiled("ppoe_core.x.y")``, ``importlib.import_module("...")``) counts as an
  import of the module that names it (layers and cycles apply);
- ``ruff check .`` is clean (mypy runs in ``.ci/run``, not here).

Each checker is a function of a source string, so the tests at the end feed it violations
and show that it can fail.  The import analysis is ``scripts/gen_architecture.py``'s, the one
that also writes the module table of ``docs/ARCHITECTURE.md``.
"""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
from collections.abc import Callable

import pytest
from conftest import REPO, load_script

gen = load_script(REPO / "scripts" / "gen_architecture.py", "gen_architecture")

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 60
LAYERS = ("compile_cache", "jit", "aot", "errors", "lie", "robot", "model", "estimation", "sensing", "io", "sim",
          "analysis", "cli")
FORBIDDEN = {"analysis": ("ppoe_core.io.importers",)}   # layer -> module prefixes it may not import
ROS_TOP_LEVEL = {
    "rclpy", "rcl", "rcl_interfaces", "rclpy_message_converter", "rosidl_runtime_py", "rosidl_parser",
    "rosgraph_msgs", "builtin_interfaces", "launch", "launch_ros", "launch_testing", "ament_index_python",
    "rosbag2_py", "tf2_ros", "tf2_py", "message_filters", "cv_bridge", "ros2cli", "rpyutils",
}
MODULES = list(gen.iter_modules())

#: (importing module, imported module, name) -> why the underscore name is still imported
PRIVATE_IMPORTS_ALLOWED: dict[tuple[str, str, str], str] = {}
#: (module, lazily imported module) -> why a function-level import of a module that imports it back is kept
CYCLE_IMPORTS_ALLOWED: dict[tuple[str, str], str] = {}


def is_ros_package(name: str) -> bool:
    """True for rclpy and ROS packages (``*_msgs``, ``*_srvs``, ``*_interfaces``, ...); ``rosbags`` is not ROS."""
    top = name.split(".")[0]
    return top in ROS_TOP_LEVEL or top.endswith(("_msgs", "_srvs", "_interfaces", "_actions"))


def layer_of(module: str) -> str | None:
    """Layer of a ``ppoe_core`` module (``ppoe_core.estimation.fusion`` -> ``estimation``); the
    top-level package ``ppoe_core`` (the user-API facade) has none."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "ppoe_core" else None


def size_violations(source: str, where: str) -> list[str]:
    """Module over MAX_MODULE_LINES lines, function bodies over MAX_FUNCTION_LINES (docstring excluded)."""
    out = []
    n = len(source.splitlines())
    if n > MAX_MODULE_LINES:
        out.append(f"{where}: module has {n} lines > {MAX_MODULE_LINES}")
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                and isinstance(body[0].value.value, str):
            body = body[1:]
        if not body:
            continue
        length = (body[-1].end_lineno or body[-1].lineno) - body[0].lineno + 1
        if length > MAX_FUNCTION_LINES:
            out.append(f"{where}:{node.lineno}: function {node.name} body has {length} lines > {MAX_FUNCTION_LINES}")
    return out


def import_violations(source: str, module: str, is_package: bool = False,
                      exists: Callable[[str], bool] | None = None) -> list[str]:
    """Layer, ROS and node-to-node import rules for the module ``module`` with text ``source``."""
    out = []
    imported = gen.imports_of(source, module, is_package, exists)
    mine = layer_of(module)
    for name in sorted(imported):
        if name == module:
            continue
        if module.split(".")[0] == "ppoe_core":
            if is_ros_package(name):
                out.append(f"{module}: imports ROS package {name} (ppoe_core is ROS-free)")
            if name.split(".")[0] == "ppoe_ros":
                out.append(f"{module}: imports {name} (ppoe_core may not import ppoe_ros)")
            theirs = layer_of(name)
            if mine is not None and name == "ppoe_core":
                out.append(f"{module}: imports the ppoe_core facade; import from the defining module")
            if mine in LAYERS and theirs in LAYERS and LAYERS.index(theirs) > LAYERS.index(mine):
                out.append(f"{module}: layer {mine} imports {name} of higher layer {theirs}")
            for prefix in FORBIDDEN.get(mine or "", ()):
                if name == prefix or name.startswith(prefix + "."):
                    out.append(f"{module}: layer {mine} may not import {name}")
        if _is_node(module) and _is_node(name) and name != module:
            out.append(f"{module}: node module imports node module {name}")
    return out


def _is_node(module: str) -> bool:
    parts = module.split(".")
    return len(parts) == 3 and parts[:2] == ["ppoe_ros", "nodes"]


def _module_of(expr: ast.expr, aliases: dict[str, str]) -> str | None:
    """The ppoe module an expression names (``cdr`` after ``from ppoe_core.io import cdr``), else None."""
    if isinstance(expr, ast.Name):
        return aliases.get(expr.id)
    if isinstance(expr, ast.Attribute):
        base = _module_of(expr.value, aliases)
        return f"{base}.{expr.attr}" if base is not None else None
    return None


def private_imports(source: str, module: str, is_package: bool = False,
                    exists: Callable[[str], bool] | None = None) -> list[tuple[str, str, int]]:
    """``(imported module, underscore name, line)`` of every use of another ppoe module's underscore name in
    ``source``: ``from m import _x`` and ``m._x`` for an imported module ``m`` (dunder names excepted)."""
    exists = exists or gen._module_exists
    out: list[tuple[str, str, int]] = []
    aliases: dict[str, str] = {}
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = gen._resolve_relative(module, is_package, node.level, node.module) if node.level \
                else str(node.module)
            if base.split(".")[0] not in gen.PACKAGES:
                continue
            for a in node.names:
                if exists(f"{base}.{a.name}"):
                    aliases[a.asname or a.name] = f"{base}.{a.name}"
                elif a.name.startswith("_") and not a.name.startswith("__") and base != module:
                    out.append((base, a.name, node.lineno))
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in gen.PACKAGES:
                    aliases[a.asname or a.name.split(".")[0]] = a.asname and a.name or a.name.split(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            mod = _module_of(node.value, aliases)
            if mod is not None and mod != module and exists(mod):
                out.append((mod, node.attr, node.lineno))
    return out


def _import_nodes(tree: ast.AST, top_level: bool) -> list[ast.stmt | ast.Call]:
    """Module-level import statements (``top_level``; not inside functions, not under ``TYPE_CHECKING``), or the
    imports and the loads by name (``compiled("...")``) inside functions."""
    out: list[ast.stmt | ast.Call] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, (ast.Import, ast.ImportFrom)) or gen.loaded_by_name(child):
                if inner != top_level:
                    out.append(child)  # type: ignore[arg-type]
            visit(child, inner)

    visit(tree, False)
    return out


def cycle_dodges(sources: dict[str, tuple[str, bool]]) -> list[tuple[str, str, int]]:
    """``(module, imported module, line)`` of every function-level import of a module that (transitively, by
    module-level imports) imports the importing module: an import cycle dodged.  ``sources``: module -> (text,
    is_package)."""
    def imported(name: str, top: bool) -> list[tuple[str, int]]:
        text, pkg = sources[name]
        out = []
        for node in _import_nodes(ast.parse(text), top):
            for m in gen.imports_of(ast.unparse(node), name, pkg, lambda n: n in sources):
                if m in sources and m != name:
                    out.append((m, node.lineno))
        return out

    graph = {n: {m for m, _ in imported(n, True)} for n in sources}

    def reaches(a: str, b: str) -> bool:
        seen, stack = {a}, [a]
        while stack:
            for y in graph[stack.pop()]:
                if y == b:
                    return True
                if y not in seen:
                    seen.add(y)
                    stack.append(y)
        return False

    return [(n, m, line) for n in sources for m, line in imported(n, False) if reaches(m, n)]


# ----------------------------------------------------------------------------- the code base


def test_modules_found():
    names = {m.name for m in MODULES}
    assert {"ppoe_core.lie", "ppoe_core.errors", "ppoe_ros.nodes.fusion_node"} <= names, sorted(names)
    assert all(layer_of(n) in LAYERS for n in names if n.startswith("ppoe_core.")), sorted(names)


def test_module_and_function_sizes():
    bad = [v for m in MODULES for v in size_violations(m.source, m.path.relative_to(REPO).as_posix())]
    print("\n".join(bad))
    assert not bad, "over the size limits (split into named steps):\n" + "\n".join(bad)


def test_imports_follow_the_layers():
    bad = [v for m in MODULES for v in import_violations(m.source, m.name, m.is_package)]
    print("\n".join(bad))
    assert not bad, "import rule violations:\n" + "\n".join(bad)


def test_no_module_imports_another_modules_underscore_name():
    found = {(m.name, mod, n): line for m in MODULES
             for mod, n, line in private_imports(m.source, m.name, m.is_package)}
    bad = [f"{m}:{line}: uses {n} of {mod}" for (m, mod, n), line in found.items()
           if (m, mod, n) not in PRIVATE_IMPORTS_ALLOWED]
    stale = [k for k in PRIVATE_IMPORTS_ALLOWED if k not in found]
    assert not bad, "underscore names of other modules (make them public where they belong):\n" + "\n".join(bad)
    assert not stale, f"allowed exceptions that no longer occur (remove them): {stale}"


def test_no_function_level_import_dodges_a_cycle():
    found = {(m, i): line for m, i, line in cycle_dodges({m.name: (m.source, m.is_package) for m in MODULES})}
    bad = [f"{m}:{line}: imports {i} inside a function, and {i} imports {m}" for (m, i), line in found.items()
           if (m, i) not in CYCLE_IMPORTS_ALLOWED]
    stale = [k for k in CYCLE_IMPORTS_ALLOWED if k not in found]
    assert not bad, "import cycles dodged by function-level imports (split the modules):\n" + "\n".join(bad)
    assert not stale, f"allowed exceptions that no longer occur (remove them): {stale}"


def test_ruff_clean():
    if importlib.util.find_spec("ruff") is None:
        pytest.fail("ruff is not installed (pip install -e '.[test]'): the lint rules cannot be checked")
    res = subprocess.run([sys.executable, "-m", "ruff", "check", "."], cwd=REPO,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr


# ----------------------------------------------------------------------------- the checkers can fail


def _exists(name: str) -> bool:
    """Synthetic module set for the checker tests."""
    return name in {"ppoe_core.lie", "ppoe_core.errors", "ppoe_core.model", "ppoe_core.model.ppoe",
                    "ppoe_core.io", "ppoe_core.io.importers", "ppoe_ros.nodes.kinematics_node",
                    "ppoe_ros.nodes.fusion_node", "ppoe_ros.common"}


def _function(name: str, body_lines: int, docstring: bool = True) -> str:
    doc = '    """Doc\n\n    more doc.\n    """\n' if docstring else ""
    return f"def {name}():\n" + doc + "".join(f"    x{i} = {i}\n" for i in range(body_lines))


def test_size_checker_detects_long_function_and_module():
    assert size_violations(_function("ok", MAX_FUNCTION_LINES), "m.py") == []
    bad = size_violations(_function("too_long", MAX_FUNCTION_LINES + 1), "m.py")
    assert len(bad) == 1 and "too_long" in bad[0] and f"{MAX_FUNCTION_LINES + 1} lines" in bad[0]
    nested = "class A:\n    " + _function("method", MAX_FUNCTION_LINES + 5, docstring=False).replace("\n", "\n    ")
    assert any("method" in v for v in size_violations(nested, "m.py"))
    big = "\n".join(f"x{i} = {i}" for i in range(MAX_MODULE_LINES + 1))
    assert size_violations(big, "m.py") == [f"m.py: module has {MAX_MODULE_LINES + 1} lines > {MAX_MODULE_LINES}"]


@pytest.mark.parametrize("module, source, what", [
    ("ppoe_core.lie", "import rclpy\n", "ROS package rclpy"),
    ("ppoe_core.estimation.fusion", "def f():\n    from geometry_msgs.msg import Pose\n",
     "ROS package geometry_msgs.msg"),
    ("ppoe_core.sim.simulate", "from ppoe_ros.common import x\n", "may not import ppoe_ros"),
    ("ppoe_core.lie", "from ppoe_core.model.ppoe import PPOEModel\n", "layer lie imports ppoe_core.model.ppoe"),
    ("ppoe_core.robot.urdf", "from ppoe_core import lie, model\n", "layer robot imports ppoe_core.model"),
    ("ppoe_core.robot.urdf", "from ..model import ppoe\n", "layer robot imports ppoe_core.model.ppoe"),
    ("ppoe_core.analysis.evaluate", "from ppoe_core.io.importers import hilti\n",
     "may not import ppoe_core.io.importers"),
    ("ppoe_core.lie", "from ppoe_core import PPOEModel\n", "facade"),
    ("ppoe_ros.nodes.fusion_node", "from ppoe_ros.nodes.kinematics_node import x\n", "node module imports"),
    ("ppoe_ros.nodes.fusion_node", "from . import kinematics_node\n", "node module imports"),
])
def test_import_checker_detects_violations(module, source, what):
    bad = import_violations(source, module, exists=_exists)
    assert any(what in v for v in bad), bad


@pytest.mark.parametrize("module, source", [
    ("ppoe_core.model.ppoe", "import numpy\nfrom ppoe_core import lie\nfrom ppoe_core.errors import PpoeError\n"),
    ("ppoe_core.io.bagio", "from rosbags.rosbag2 import Reader\n"),
    ("ppoe_core.cli.fk", "from ppoe_core.io.importers import hilti\nfrom ppoe_core.model.ppoe import PPOEModel\n"),
    ("ppoe_ros.nodes.fusion_node", "import rclpy\nfrom ppoe_ros.common import x\nfrom ppoe_core.model import ppoe\n"),
])
def test_import_checker_accepts_allowed_imports(module, source):
    assert import_violations(source, module, exists=_exists) == []


@pytest.mark.parametrize("module, source, found", [
    ("ppoe_core.lie.se3", "from ppoe_core.lie.so3 import _coeffs, hat3\n", [("ppoe_core.lie.so3", "_coeffs")]),
    ("ppoe_core.io.rows", "from ppoe_core.io import cdr\nx = cdr._names\n", [("ppoe_core.io.cdr", "_names")]),
    ("ppoe_core.io.rows", "import ppoe_core.io.cdr\nx = ppoe_core.io.cdr._names\n", [("ppoe_core.io.cdr", "_names")]),
    ("ppoe_core.lie.se3", "from .so3 import _f\n", [("ppoe_core.lie.so3", "_f")]),
    ("ppoe_core.lie.se3", "from ppoe_core.lie.so3 import hat3, __all__\nx = self._y\n", []),
    ("ppoe_core.lie.se3", "import numpy as np\nx = np._NoValue\n", []),
])
def test_private_import_checker(module, source, found):
    exists = lambda n: n in {"ppoe_core.lie.so3", "ppoe_core.lie.se3", "ppoe_core.io.cdr", "ppoe_core.io",  # noqa: E731
                             "ppoe_core.io.rows", "ppoe_core.lie", "ppoe_core"}
    assert [(m, n) for m, n, _ in private_imports(source, module, exists=exists)] == found


def test_cycle_checker_finds_a_dodged_cycle_and_not_a_lazy_import():
    sources = {
        "ppoe_core.a": ("from ppoe_core import b\n", False),
        "ppoe_core.b": ("def f():\n    from ppoe_core import a\n", False),  # a imports b: dodged
        "ppoe_core.c": ("def f():\n    from ppoe_core import d\n", False),  # d does not import c: lazy only
        "ppoe_core.d": ("import numpy\n", False),
        "ppoe_core.e": ("from ppoe_core import f\n", False),
        "ppoe_core.f": ("def g():\n    return compiled('ppoe_core.e')\n", False),  # a load by name counts
        "ppoe_core.g": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ppoe_core import h\n", False),
        "ppoe_core.h": ("def f():\n    from ppoe_core import g\n", False),  # g imports h for types only: fine
    }
    assert sorted((m, i) for m, i, _ in cycle_dodges(sources)) == [("ppoe_core.b", "ppoe_core.a"),
                                                                    ("ppoe_core.f", "ppoe_core.e")]
