"""Regenerate the module table of ``docs/ARCHITECTURE.md`` from the code's imports.

Usage (from the repository root)::

    python scripts/gen_architecture.py            # rewrite docs/ARCHITECTURE.md in place
    python scripts/gen_architecture.py --check    # exit 1 if the table is out of date

The table sits between the markers ``<!-- BEGIN MODULE TABLE -->`` and
``<!-- END MODULE TABLE -->``; the hand-written prose around it is left alone.  One row per
module of ``ppoe_core`` and ``ppoe_ros``: package, module, lines, the ``ppoe_core``/``ppoe_ros``
modules it imports (any import statement, also the ones inside functions) and the first line
of its docstring.

The import analysis here (:func:`iter_modules`, :func:`imports_of`) is also the one that
``test/test_architecture.py`` checks the layer rules with.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("ppoe_core", "ppoe_ros")
BEGIN = "<!-- BEGIN MODULE TABLE -->"
END = "<!-- END MODULE TABLE -->"


@dataclass(frozen=True)
class Module:
    """One Python module of the repository.

    ``name`` is the dotted module name (``ppoe_core.lie`` for ``ppoe_core/lie/__init__.py``),
    ``is_package`` tells whether the file is a package's ``__init__.py`` (relative imports resolve
    against the package itself then).
    """

    name: str
    path: Path
    is_package: bool

    @property
    def source(self) -> str:
        return self.path.read_text(encoding="utf-8")


def module_name(path: Path, root: Path = REPO) -> tuple[str, bool]:
    """Dotted name of the module at ``path`` (relative to ``root``) and whether it is a package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def iter_modules(root: Path = REPO, packages: tuple[str, ...] = PACKAGES) -> Iterator[Module]:
    """Every ``*.py`` file under ``root/<package>`` for each package, sorted by path."""
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            name, is_package = module_name(path, root)
            yield Module(name, path, is_package)


def _resolve_relative(module: str, is_package: bool, level: int, target: str | None) -> str:
    """Absolute name of ``from <level dots><target> import ...`` written in ``module``."""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


#: functions that load a module by its name (a lazily imported compiled module): ``compiled("ppoe_core.x")``
LOADERS = ("compiled", "import_module")


def loaded_by_name(node: ast.AST) -> str | None:
    """The module a call like ``compiled("ppoe_core.x")`` / ``importlib.import_module("ppoe_core.x")`` loads (a
    string literal of one of our packages), else None."""
    if not (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)):
        return None
    f = node.func
    name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
    arg = node.args[0].value
    return arg if name in LOADERS and isinstance(arg, str) and arg.split(".")[0] in PACKAGES else None


def imports_of(source: str, module: str, is_package: bool = False,
               exists: Callable[[str], bool] | None = None) -> set[str]:
    """Dotted names of every module ``source`` imports (anywhere in the file, also inside functions), and of the
    modules it loads by name (:func:`loaded_by_name`).

    ``from a.b import c`` gives ``a.b.c`` when ``exists("a.b.c")`` says that is a module, else
    ``a.b`` (``c`` is a name defined in ``a.b``).  ``exists`` defaults to "is a module of this
    repository"; relative imports are resolved against ``module``.
    """
    if exists is None:
        exists = _module_exists
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        by_name = loaded_by_name(node)
        if by_name is not None:
            found.add(by_name)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = (_resolve_relative(module, is_package, node.level, node.module)
                    if node.level else str(node.module))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if alias.name != "*" and exists(sub) else base)
    return found


def _module_exists(name: str) -> bool:
    path = REPO.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _first_doc_line(source: str) -> str:
    doc = ast.get_docstring(ast.parse(source)) or ""
    line = doc.strip().splitlines()[0] if doc.strip() else ""
    return line.replace("|", "\\|")


def _short(name: str) -> str:
    """``ppoe_core.estimation.fusion`` -> ``estimation.fusion`` (``ppoe_ros.`` kept)."""
    return name.removeprefix("ppoe_core.")


def table_rows(root: Path = REPO) -> list[str]:
    """Markdown rows of the module table (header included)."""
    rows = ["| package | module | lines | imports (ppoe_core / ppoe_ros) | what |", "|---|---|---|---|---|"]
    for mod in iter_modules(root):
        src = mod.source
        own = sorted({_short(i) for i in imports_of(src, mod.name, mod.is_package)
                      if i.split(".")[0] in PACKAGES and i != mod.name})
        package = ".".join(mod.name.split(".")[:2]) if "." in mod.name else mod.name
        rel = mod.path.relative_to(root).as_posix()
        deps = ", ".join(f"`{d}`" for d in own) or "-"
        rows.append(f"| `{package}` | `{rel}` | {len(src.splitlines())} | {deps} | {_first_doc_line(src)} |")
    return rows


def render(text: str, root: Path = REPO) -> str:
    """``text`` (the ARCHITECTURE.md content) with the table between the markers regenerated."""
    if BEGIN not in text or END not in text:
        raise SystemExit(f"docs/ARCHITECTURE.md: markers {BEGIN} / {END} missing")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    note = "<!-- generated by scripts/gen_architecture.py from the imports; do not edit by hand -->"
    return head + BEGIN + "\n" + note + "\n\n" + "\n".join(table_rows(root)) + "\n\n" + END + tail


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/ARCHITECTURE.md is out of date")
    args = parser.parse_args(argv)
    doc = REPO / "docs" / "ARCHITECTURE.md"
    old = doc.read_text(encoding="utf-8")
    new = render(old)
    if args.check:
        if new != old:
            print("docs/ARCHITECTURE.md is out of date: run python scripts/gen_architecture.py", file=sys.stderr)
            return 1
        return 0
    doc.write_text(new, encoding="utf-8")
    print(f"wrote {doc.relative_to(REPO)} ({len(table_rows()) - 2} modules)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
