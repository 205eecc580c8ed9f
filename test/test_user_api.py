"""The README's five-line user API runs as written and does what the README says.

The code block after the ``<!-- user-api -->`` marker in ``README.md`` is executed from the
repository root; then its variables are checked: a PPOE pose + covariance from the model, and
one tracker point fused into it by the iterated LG-EKF.
"""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
from conftest import REPO

MARKER = "<!-- user-api -->"


def readme_user_api() -> str:
    """The ```python block right after MARKER in README.md."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert MARKER in text, f"README.md has no {MARKER} marker"
    match = re.search(r"```python\n(.*?)```", text.split(MARKER, 1)[1], flags=re.S)
    assert match is not None, f"no ```python block after {MARKER} in README.md"
    return match.group(1)


@pytest.fixture(scope="module")
def run() -> dict:
    code = readme_user_api()
    namespace: dict = {"__name__": "readme_user_api"}
    cwd = os.getcwd()
    os.chdir(REPO)          # the README's paths are relative to the repository root
    try:
        exec(compile(code, "README.md (user API)", "exec"), namespace)
    finally:
        os.chdir(cwd)
    return namespace


def test_block_is_five_lines():
    lines = [line for line in readme_user_api().splitlines() if line.strip()]
    assert len(lines) == 5, lines


def test_pose_and_covariance(run: dict):
    model, T, cov = run["model"], run["T_base_tool"], run["cov_tool"]
    assert (model.config.frames.base, model.config.frames.tool) == ("base_link", "tool0")
    np.testing.assert_allclose(T, model.fk_mean({n: 0.3 for n in model.joint_names}, "base_link", "tool0"),
                               atol=1e-12)
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > -1e-12)
    assert np.sqrt(cov[0, 0]) > 0.005          # the arm7 model is uncertain at the cm level


def test_fused_measurement(run: dict):
    fused, T, cov = run["fused"], run["T_base_tool"], run["cov_tool"]
    assert fused.accepted and fused.converged
    # the measured tool position (README: [0.166, 0.021, 1.303] m) pulls the estimate towards it
    z = np.array([0.166, 0.021, 1.303])
    assert np.linalg.norm(fused.T[:3, 3] - z) < 0.6 * np.linalg.norm(T[:3, 3] - z)
    assert fused.residual.shape == (3,) and np.linalg.norm(fused.residual) < np.linalg.norm(fused.innovation)
    # and the position covariance shrinks to about the 1 mm tracker sigma
    assert np.all(np.sqrt(np.diag(fused.cov)[:3]) < 1.1e-3)
    assert np.trace(fused.cov) < np.trace(cov)
