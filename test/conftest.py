"""Shared test helpers: repository paths and pose helpers.

pytest imports this file before the tests and puts ``test/`` on ``sys.path`` (rootdir
conftest, no ``__init__.py``), so test modules use the plain names::

    from conftest import REPO, CONFIG_ROBOTS, random_pose
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from ppoe_core import lie

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config"
CONFIG_ROBOTS = CONFIG / "robots"      # example robots: URDF + model YAML
CONFIG_NODES = CONFIG / "nodes"        # node parameter files
BAGS = REPO / "bags"                   # shipped simulated bags
DATA = REPO / "test" / "data"          # small test-only robots
DATASETS = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets"))   # measured data



def load_script(path: Path, name: str) -> ModuleType:
    """A script or bench file (not a package module) loaded as module ``name``, registered in ``sys.modules``
    (dataclasses look their module up there)."""
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def assert_same_data(a: Any, b: Any, where: str = "data") -> None:
    """Two ``BagData`` (or any nest of dataclasses, dicts, lists and arrays) equal field by field: the same types,
    arrays of the same dtype, shape and bytes, other values ``==`` (``where`` names the field in a failure)."""
    import dataclasses

    assert type(a) is type(b), where
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same_data(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes()), where
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            assert_same_data(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same_data(x, y, f"{where}[{i}]")
    else:
        assert a == b, where

def pose_from(t, w) -> np.ndarray:
    """Pose ``(4, 4)`` with translation ``t`` (3,) and rotation ``so3_exp(w)`` (not ``lie.exp`` of a twist)."""
    T = np.eye(4)
    T[:3, :3] = lie.so3_exp(np.asarray(w, dtype=float))
    T[:3, 3] = t
    return T


def random_pose(rng: np.random.Generator, n: int | None = None, scale_t: float = 1.0,
                scale_r: float = 1.0) -> np.ndarray:
    """Random pose ``Exp(xi)``, ``xi = [rho; theta]`` standard normal scaled by ``scale_t`` / ``scale_r``.

    Shape ``(4, 4)``, or ``(n, 4, 4)`` for ``n`` poses.  Draws ``6`` (or ``n * 6``) normals from
    ``rng`` in one call, row by row.
    """
    shape = (6,) if n is None else (n, 6)
    xi = rng.normal(size=shape)
    if scale_t != 1.0 or scale_r != 1.0:
        xi = np.concatenate([xi[..., :3] * scale_t, xi[..., 3:] * scale_r], axis=-1)
    return lie.exp(xi)


def random_pose_quat(rng: np.random.Generator) -> np.ndarray:
    """Random pose ``(4, 4)``: rotation from a uniformly random unit quaternion, translation standard normal."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = lie.matrix_from_quat(q)
    T[:3, 3] = rng.normal(size=3)
    return T


@pytest.fixture(scope="session", autouse=True)
def _compiled_kernels() -> None:
    """Compile the numba kernels once (or load them from numba's cache) before any test, so that node
    processes started by the tests load them from the cache instead of compiling them (about 45 s on a clean
    checkout) while a test waits for their subscribers.  ``warm_node_kernels`` is what every node warms before
    it subscribes."""
    from ppoe_core.model.ppoe import PPOEModel

    from ppoe_core.model.fourth_order import compound_fourth_order

    model = PPOEModel.from_files(str(CONFIG_ROBOTS / "arm7.urdf"), str(CONFIG_ROBOTS / "arm7_model.yaml"))
    T, cov = model.fk(np.zeros(len(model.joint_names)))
    model.fk(np.zeros((2, len(model.joint_names))), order=4)
    model.jacobian_joints(np.zeros(len(model.joint_names)))
    compound_fourth_order(cov, cov)
    lie.cov_ros_to_local(T, lie.cov_local_to_ros(T, cov))
    lie.quat_from_matrix(T[:3, :3])
    from ppoe_ros.common.runner import warm_node_kernels

    warm_node_kernels()

