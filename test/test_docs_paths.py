"""Every repository path the documentation names exists (docs/*.md, every README.md, config/README.md ...).

A path is a backticked span or a markdown link target whose first component is a top-level entry of the
repository (``ppoe_core/sim/truth.py``, ``config/robots/arm7.*``, ``docs/img/fig3.png``); ``<name>``
placeholders and ``*`` match any name; ``file.py::test_name`` also needs that test (or class) in the file;
a dotted ``ppoe_core.x.y`` / ``ppoe_ros.x.y`` reference must be a module, or a name defined in one.
Paths outside the repository (``/tmp/...``, ``../../shared/...``) and generated outputs are not checked.
"""

from __future__ import annotations

import ast
import glob
import re
from pathlib import Path

import pytest
from conftest import REPO

DOCS = sorted({*REPO.glob("docs/*.md"), *REPO.glob("**/README.md")} - set(REPO.glob(".venv/**/README.md")))
TOP = {p.name for p in REPO.iterdir() if not p.name.startswith(".git")}
_SPAN = re.compile(r"`([^`\n]+)`|\]\(([^)\s#]+)(?:#[^)]*)?\)")
_PATHLIKE = re.compile(r"^[\w.*<>\-/]+(?:::[\w\[\]\-.]+)?$")
_DOTTED = re.compile(r"^(ppoe_core|ppoe_ros)(\.\w+)+$")


def _candidates(text: str) -> list[str]:
    out = []
    for m in _SPAN.finditer(text):
        span = (m.group(1) or m.group(2) or "").strip()
        for word in span.split():  # a command line names several paths
            word = word.strip(",;:()'\"").split("=", 1)[-1]
            if _PATHLIKE.match(word) and "/" in word and word.split("/", 1)[0] in TOP:
                out.append(word)
            elif _DOTTED.match(word.split("(")[0]):
                out.append(word.split("(")[0])
    return out


def _path_exists(doc: Path, ref: str) -> str | None:
    """None when ``ref`` exists, else what is missing."""
    path, _, test = ref.partition("::")
    pattern = re.sub(r"<[^>]+>", "*", path.rstrip("/"))
    hits = [Path(h) for base in (REPO, doc.parent) for h in glob.glob(str(base / pattern))]
    if not hits:
        return f"{path} does not exist"
    if test:
        name = test.split("[", 1)[0]
        tree = ast.parse(hits[0].read_text())
        defined = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        if name not in defined:
            return f"{path} has no test {name}"
    return None


def _dotted_exists(ref: str) -> str | None:
    parts = ref.split(".")
    for k in range(len(parts), 0, -1):
        base = REPO.joinpath(*parts[:k])
        module = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        if module.is_file():
            rest = parts[k:]
            if not rest:
                return None
            tree = ast.parse(module.read_text())
            names = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef,
                                                                       ast.AsyncFunctionDef))}
            names |= {t.id for n in ast.walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign))
                      for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
            names |= {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
            return None if rest[0] in names else f"{'.'.join(parts[:k])} defines no {rest[0]}"
    return f"no module {ref}"


def test_the_check_finds_paths_and_refuses_missing_ones(tmp_path: Path) -> None:
    doc = tmp_path / "x.md"
    text = ("Run `ppoe_core/sim/truth.py`, see [conv](docs/conventions.md) and `config/robots/<name>.urdf`; "
            "`test/test_bag_qos.py::test_playback_rule_is_rosbag2s`, `ppoe_core.io.bag_qos.offered_qos`, "
            "`ppoe_core/simulate.py`, `ppoe_core.io.bag_qos.nothing`, `/tmp/out/errors.png`.")
    found = _candidates(text)
    assert found == ["ppoe_core/sim/truth.py", "docs/conventions.md", "config/robots/<name>.urdf",
                     "test/test_bag_qos.py::test_playback_rule_is_rosbag2s", "ppoe_core.io.bag_qos.offered_qos",
                     "ppoe_core/simulate.py", "ppoe_core.io.bag_qos.nothing"]
    missing = [r for r in found if (_dotted_exists(r) if _DOTTED.match(r) else _path_exists(doc, r))]
    assert missing == ["ppoe_core/simulate.py", "ppoe_core.io.bag_qos.nothing"]
    assert _path_exists(doc, "test/test_bag_qos.py::test_nope") == "test/test_bag_qos.py has no test test_nope"


@pytest.mark.parametrize("doc", DOCS, ids=[str(d.relative_to(REPO)) for d in DOCS])
def test_every_path_a_doc_names_exists(doc: Path) -> None:
    text = doc.read_text()
    missing = []
    for ref in dict.fromkeys(_candidates(text)):
        why = _dotted_exists(ref) if _DOTTED.match(ref) else _path_exists(doc, ref)
        if why is not None:
            line = text[:text.find(ref)].count("\n") + 1
            missing.append(f"{doc.relative_to(REPO)}:{line}: {why}")
    assert not missing, "\n".join(missing)
