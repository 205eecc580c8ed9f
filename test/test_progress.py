"""Progress on stderr (ppoe_core/io/progress.py): when it is drawn, what it says, and the CLI switches."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time

import pytest
from conftest import REPO

from ppoe_core.io.progress import ProgressBar, Ticker, progress_wanted


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_wanted_terminal_quiet_and_forced() -> None:
    assert progress_wanted(stream=_Tty()) is True
    assert progress_wanted(stream=io.StringIO()) is False
    assert progress_wanted(quiet=True, stream=_Tty()) is False
    assert progress_wanted(quiet=True, forced=True, stream=_Tty()) is False
    assert progress_wanted(forced=True, stream=io.StringIO()) is True
    assert progress_wanted(forced=False, stream=_Tty()) is False


def test_ticker_names_the_stage_and_the_time() -> None:
    s = io.StringIO()
    with Ticker("diagnose", True, stream=s, period=0.01) as tick:
        tick.stage("reading 2 bag(s)")
        time.sleep(0.05)
        tick.stage("fitting")
        time.sleep(0.05)
    lines = s.getvalue().split("\r")
    assert any(line.startswith("diagnose: reading 2 bag(s) ") for line in lines)
    assert any(line.startswith("diagnose: fitting ") and line.rstrip().endswith(" s") for line in lines)
    assert lines[-1].startswith("diagnose: done in ") and s.getvalue().endswith("\n")
    s = io.StringIO()
    with pytest.raises(RuntimeError), Ticker("diagnose", True, stream=s, period=0.01) as tick:
        tick.stage("fitting")
        raise RuntimeError("boom")
    assert "diagnose: stopped in " in s.getvalue()
    s = io.StringIO()
    with Ticker("diagnose", False, stream=s) as tick:
        tick.stage("fitting")
    assert s.getvalue() == ""


def test_progress_bar_draws_percent_and_finishes_the_line() -> None:
    s = io.StringIO()
    bar = ProgressBar(4, True, label="evaluate", stream=s)
    bar.update(2)
    bar.close()
    assert "evaluate [" in s.getvalue() and "100.0%" in s.getvalue() and s.getvalue().endswith("\n")


def _cli(*args: str) -> subprocess.CompletedProcess:
    """Run ``ppoe``; stdout / stderr as text with the carriage returns kept (no newline translation)."""
    res = subprocess.run([sys.executable, "-m", "ppoe_ros.cli", *args], cwd=REPO, capture_output=True,
                         timeout=600, env={**os.environ, "PYTHONPATH": str(REPO)})
    return subprocess.CompletedProcess(res.args, res.returncode, res.stdout.decode(), res.stderr.decode())


@pytest.mark.parametrize("command", [
    ["diagnose", "bags/no_effect", "--model", "config/robots/arm7_model.yaml", "--pixels", "off",
     "--json"],
    ["evaluate", "bags/table1_exp1", "--model", "config/robots/rover_model.yaml", "--json"],
], ids=["diagnose", "evaluate"])
def test_cli_progress_forced_and_quiet(command: list[str]) -> None:
    """Piped stderr (not a terminal): no progress by default, progress with --progress, none with --quiet; stdout
    keeps the one JSON document either way."""
    import json

    plain, forced, quiet = _cli(*command), _cli(*command, "--progress"), _cli(*command, "--quiet")
    for res in (plain, forced, quiet):
        assert res.returncode == 0, res.stderr[-2000:]
        json.loads(res.stdout)
    label = command[0]
    assert "\r" not in plain.stderr and "\r" not in quiet.stderr
    assert f"\r{label}" in forced.stderr
    if label == "diagnose":
        assert "diagnose: fitting the effects" in forced.stderr and "diagnose: done in" in forced.stderr
