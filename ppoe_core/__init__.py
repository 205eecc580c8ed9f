"""ppoe_core: the Probabilistic Product-of-Exponentials robot model, its estimation and analysis (no ROS).

Public API::

    from ppoe_core import PPOEModel, parse_urdf, load_model_config
    model = PPOEModel.from_files("config/robots/arm7.urdf", "config/robots/arm7_model.yaml")
    T_base_tool, cov_tool = model.fk({"joint_1": 0.1, ...}, "base_link", "tool0")

No ROS import anywhere in this package.  It needs numpy and PyYAML; the compiled maps and updates need numba
(imported on the first call, its kernel cache configured by :mod:`ppoe_core.compile_cache`), the measurement update
and the statistics scipy, tag detection and image decoding OpenCV, bag reading and writing rosbags (and the plots
matplotlib): each is imported by the module that uses it, not by ``import ppoe_core``.
"""

from __future__ import annotations

# first: numba's kernel cache must point at a writable directory before any kernel module is imported
from ppoe_core.compile_cache import configure_compile_cache

configure_compile_cache()

from ppoe_core.errors import (  # noqa: E402
    BagError,
    CovarianceError,
    DatasetError,
    JointValueError,
    MeasurementError,
    ModelConfigError,
    PpoeError,
    ScenarioError,
    UnknownFrameError,
    UnknownJointError,
    UrdfError,
)
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402
from ppoe_core.robot.config import ModelConfig, load_model_config  # noqa: E402
from ppoe_core.robot.urdf import Joint, Link, Robot, parse_urdf  # noqa: E402

__all__ = [
    "PPOEModel",
    "parse_urdf",
    "load_model_config",
    "Robot",
    "Joint",
    "Link",
    "ModelConfig",
    "PpoeError",
    "UrdfError",
    "ModelConfigError",
    "UnknownJointError",
    "UnknownFrameError",
    "JointValueError",
    "CovarianceError",
    "MeasurementError",
    "BagError",
    "ScenarioError",
    "DatasetError",
]
