"""``ppoe warmup``'s evaluate step: after it, ``ppoe evaluate`` of a shipped bag compiles nothing.

Both run as fresh processes on one empty numba cache directory (``NUMBA_CACHE_DIR``): the warm-up replays its
simulated two-second rover bag (:func:`ppoe_core.analysis.evaluate.warmup.warm_evaluate`), then the replay of
``bags/table1_exp1`` must find every kernel it uses in the cache (no "compiling" log line).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

from conftest import REPO

LOGGING = "import logging, sys; logging.basicConfig(level=logging.INFO); "


def _run(code: str, cache: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-c", LOGGING + code], env=env, cwd=REPO, capture_output=True, text=True,
                         timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return res


def test_after_the_evaluate_warmup_a_shipped_bag_compiles_nothing(tmp_path):
    cache = str(tmp_path / "cache")
    warm = _run("from ppoe_core.analysis.evaluate.warmup import warm_evaluate; print(warm_evaluate())", cache)
    m = re.search(r"replayed a 2 s rover bag \((\d+) images, (\d+) tag updates accepted\)", warm.stdout)
    assert m and int(m.group(1)) > 0 and int(m.group(2)) > 0, warm.stdout
    assert "compiled" in warm.stderr  # it did compile, into the empty cache
    replay = _run("from ppoe_ros.cli import main; sys.exit(main(['evaluate', 'bags/table1_exp1', '--model', "
                  "'config/robots/rover_model.yaml', '--json', '--quiet']))", cache)
    assert '"methods"' in replay.stdout
    assert "compiling" not in replay.stderr, [ln for ln in replay.stderr.splitlines() if "compiling" in ln]
