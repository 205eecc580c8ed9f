"""docs/your_robot.md runs as written, and prints what it quotes.

Every ```bash block after a ``<!-- tutorial -->`` marker (``<!-- tutorial: exit N -->``: the block must end with
exit code N) runs in order, in one empty folder, with ``ppoe`` = ``python -m ppoe_ros.cli`` of this repository
(the README's user-API test extracts its block the same way: test/test_user_api.py).  A ```text block after an
``<!-- output -->`` marker quotes the previous command block's output (stdout and stderr, one stream): its table
rows and summary lines must be printed as quoted.  Then what the tutorial claims is checked on the files it made.

``python test/test_tutorial.py --write`` runs the blocks and writes their outputs into the doc's output blocks.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "your_robot.md"
#: seconds one block may take (the slowest, diagnose or evaluate, takes about 20 s under load)
BLOCK_TIMEOUT = 300
#: lines of an output block compared with what the command printed: table rows and summary lines
COMPARED = ("| ", "Found ", "ppoe check:", "ppoe init:", "    link:", "  - topic:")
BLOCK_RE = re.compile(r"<!-- tutorial(?::\s*exit\s+(\d+))?\s*-->\s*```bash\n(.*?)```"
                      r"(?:\s*<!-- output -->\s*```text\n(.*?)```)?", re.S)


@dataclass
class Block:
    """One command block: its script, the exit code it must end with, its quoted output (or None)."""

    script: str
    exit_code: int
    quoted: str | None
    span: tuple[int, int] | None     # where the quoted output sits in the doc


def blocks(text: str) -> list[Block]:
    """The tutorial's command blocks, in order."""
    out = []
    for m in BLOCK_RE.finditer(text):
        out.append(Block(m.group(2), int(m.group(1) or 0), m.group(3), m.span(3) if m.group(3) is not None else None))
    return out


def run_block(block: Block, cwd: Path) -> subprocess.CompletedProcess:
    """Run one block with bash -e in ``cwd``; ``ppoe`` is this repository's CLI."""
    prelude = f'set -e\nppoe() {{ "{sys.executable}" -m ppoe_ros.cli "$@"; }}\n'
    env = dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", COLUMNS="200")
    return subprocess.run(["bash", "-c", prelude + block.script], cwd=cwd, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=BLOCK_TIMEOUT)


def printed(proc: subprocess.CompletedProcess) -> str:
    """What the block printed, stdout and stderr as a terminal shows them (one stream)."""
    return proc.stdout


@pytest.fixture(scope="module")
def tutorial(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[tuple[Block, subprocess.CompletedProcess]]]:
    cwd = tmp_path_factory.mktemp("your_robot")
    done = []
    for block in blocks(DOC.read_text(encoding="utf-8")):
        proc = run_block(block, cwd)
        done.append((block, proc))
        assert proc.returncode == block.exit_code, (f"block ended with {proc.returncode}, the doc says "
                                                    f"{block.exit_code}:\n{block.script}\n{printed(proc)}")
    return cwd, done


def test_doc_has_the_steps():
    text = DOC.read_text(encoding="utf-8")
    scripts = "\n".join(b.script for b in blocks(text))
    for command in ("ppoe urdf from-dh", "ppoe init", "ppoe plan", "stops_csv: shelf_plan/poses.csv",
                    "ppoe simulate", "ppoe check", "ppoe diagnose", "ppoe evaluate",
                    "--urdf shelf_diagnosis/robot_calibrated.urdf"):
        assert command in scripts, command


def test_quoted_output_is_what_the_commands_print(tutorial):
    _, done = tutorial
    quoted = [(b, p) for b, p in done if b.quoted is not None]
    assert len(quoted) >= 5
    for block, proc in quoted:
        assert block.quoted is not None
        lines = [ln for ln in block.quoted.splitlines() if ln.startswith(COMPARED)]
        assert lines, f"nothing to compare in the output quoted after:\n{block.script}"
        for line in lines:
            assert line in printed(proc), f"quoted but not printed: {line!r}\n--- printed:\n{printed(proc)}"


def test_what_the_tutorial_claims(tutorial):
    cwd, done = tutorial
    # ppoe init --bag found the reflector's link and position (truth: tcp, [0.02, 0.03, 0.01])
    model = (cwd / "shelf_model.yaml").read_text()
    assert re.search(r"link: tcp\b", model)
    xyz = [float(v) for v in re.search(r"xyz: \[([^\]]+)\]", model).group(1).split(",")]
    assert max(abs(a - b) for a, b in zip(xyz, (0.02, 0.03, 0.01))) < 0.003
    # the second check passes; diagnose names the hidden offset, its interval holding the truth
    second = next(p for b, p in done if "--bag shelf_bag" in b.script)
    assert "ppoe check: OK" in printed(second)
    res = json.loads((cwd / "shelf_diagnosis" / "diagnose.json").read_text())
    found = {(e["name"], e["location"]): e for e in res["effects"]}
    assert ("joint_offset", "j3") in found, res["effects"]
    lo, hi = found[("joint_offset", "j3")]["ci"]["offset"]
    assert lo <= 0.006 <= hi
    # the recording was made at the planned stops, and its interval is tighter than 30 random stops' predicted one
    plan = json.loads((cwd / "shelf_plan" / "plan.json").read_text())
    assert all(len(v) == 30 for v in plan["poses"].values())
    assert len((cwd / "shelf_plan" / "poses.csv").read_text().splitlines()) == 31   # the header, 30 stops
    assert (hi - lo) / 2 < plan["random_n"]["ci95"]["joint_offset@j3:offset"], (lo, hi, plan["random_n"])
    # the calibrated URDF scores better on the other recording
    rms = [float(v) for v in re.findall(r"forward kinematics \| \d+ \| [0-9.]+ ± [0-9.]+ \(rms ([0-9.]+)",
                                        printed(done[-1][1]))]
    assert len(rms) == 2 and rms[1] < rms[0] - 0.4 and rms[1] < 0.75, rms   # 3D noise: sqrt(3) 0.3 = 0.52 mm


def write_outputs() -> None:
    """Run the blocks and put what they print into the doc's output blocks."""
    text = DOC.read_text(encoding="utf-8")
    with tempfile.TemporaryDirectory() as tmp:
        edits = []
        for block in blocks(text):
            proc = run_block(block, Path(tmp))
            if proc.returncode != block.exit_code:
                sys.exit(f"block ended with {proc.returncode}, not {block.exit_code}:\n{printed(proc)}")
            if block.span is not None:
                edits.append((block.span, printed(proc).rstrip("\n") + "\n"))
    for (a, b), new in reversed(edits):
        text = text[:a] + new + text[b:]
    DOC.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    if "--write" in sys.argv:
        write_outputs()
