"""The kinematics node on its ahead-of-time kernels (ppoe_core.aot): numba is never imported, and it publishes the same
bytes and counts as on numba's kernels for the same stream of joint states (split, reordered, malformed, NaN, stamp
jumps; orders 2 and 4, two targets); a module built for other sources is refused."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
#: the ahead-of-time module is built by numba's pycc with the system's C compiler: without one there is nothing to test
pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None and shutil.which("gcc") is None,
                                reason="no C compiler (cc, gcc): ppoe warmup cannot build the ahead-of-time module")

from conftest import REPO  # noqa: E402

#: runs the node's per-message path on test_joint_pose's stream; prints a JSON summary
_SCRIPT = r"""
import hashlib, json, sys
sys.path.insert(0, {test!r})
from ppoe_core import aot
status = aot.load()
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
import test_joint_pose as tj
from ppoe_ros.nodes.kinematics_node import KinematicsNode
ctx = Context()
rclpy.init(context=ctx, domain_id={domain})
h = hashlib.sha256()
counts = {{}}
for order in (2, 4):
    out = []
    node = KinematicsNode(context=ctx, parameter_overrides=[
        Parameter("robot_description", value=tj.URDF.read_text()), Parameter("model_file", value=str(tj.MODEL)),
        Parameter("extra_target_frames", value=[tj.EXTRA]), Parameter("order", value=order),
        Parameter("log_throttle", value=3600.0)])
    for t in node.targets:
        t.pub = tj._Capture(t.frame, out)
    for raw in tj._stream(order, 1500):
        node._on_joint_state(raw)
    for topic, data in out:
        h.update(topic.encode()); h.update(data)
    counts[order] = dict(node.stats.counts)
    node.destroy_node()
ctx.try_shutdown()
print(json.dumps({{"usable": status.usable, "why": status.why, "numba": "numba" in sys.modules,
                  "llvmlite": "llvmlite" in sys.modules, "digest": h.hexdigest(), "counts": counts}}))
"""


def _run(env: dict[str, str], domain: int) -> dict:
    code = _SCRIPT.format(test=str(REPO / "test"), domain=domain)
    res = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def aot_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory holding the ahead-of-time module, built by ``ppoe warmup`` (kinematics node only); the numba
    kernels stay in the install's cache (shared with the other tests: compiled once per run, not once more here)."""
    cache = tmp_path_factory.mktemp("aot_cache")
    env = dict(os.environ, PPOE_AOT_DIR=str(cache), PYTHONPATH=str(REPO))
    res = subprocess.run([sys.executable, "-m", "ppoe_ros.cli", "warmup", "--nodes", "kinematics_node"], env=env,
                         cwd=REPO, capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "no ahead-of-time module" not in res.stdout, f"ppoe warmup built no module: {res.stdout[-800:]}"
    return cache


@pytest.mark.timeout(1500)
def test_node_on_the_ahead_of_time_kernels_without_numba_same_bytes(aot_cache: Path) -> None:
    env = dict(os.environ, PPOE_AOT_DIR=str(aot_cache), PYTHONPATH=str(REPO))
    ahead = _run(env, 151)
    assert ahead["usable"], ahead["why"]
    assert not ahead["numba"] and not ahead["llvmlite"], "numba was imported by the node's path"
    jit = _run(dict(env, PPOE_AOT="0"), 152)
    assert not jit["usable"] and jit["numba"]
    assert ahead["counts"] == jit["counts"]
    assert ahead["counts"]["2"]["published"] > 500
    assert ahead["digest"] == jit["digest"]


@pytest.mark.timeout(300)
def test_module_built_for_other_sources_is_refused(aot_cache: Path, tmp_path: Path) -> None:
    """A manifest whose source hash differs (the kernels changed after `ppoe warmup`) is not loaded: the node uses
    numba and says why."""
    manifest = next(aot_cache.glob("*.json"))
    info = json.loads(manifest.read_text())
    info["sources_hash"] = "0" * 40
    stale = tmp_path / "aot"
    stale.mkdir()
    for f in aot_cache.iterdir():
        (stale / f.name).write_bytes(f.read_bytes())
    (stale / manifest.name).write_text(json.dumps(info))
    env = dict(os.environ, PPOE_AOT_DIR=str(stale), PYTHONPATH=str(REPO))
    code = "from ppoe_core import aot; s = aot.load(); print(s.usable, s.why)"
    res = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.stdout.startswith("False") and "sources changed" in res.stdout and "ppoe warmup" in res.stdout
