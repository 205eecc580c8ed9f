"""ament_python package ``ppoe_ros`` (Python packages ``ppoe_core`` and ``ppoe_ros``).

``colcon build`` installs the node executables under ``lib/ppoe_ros`` and the
config under ``share/ppoe_ros``; ``pip install .`` gives the same executables as
console scripts.  The ROS 2 Jazzy wheels from PyPI are behind the ``ros`` extra
so that users with ROS 2 from apt install without them.

After installing into its final place (``colcon build``, ``python setup.py install``/``develop``: not a wheel
being built in a staging directory), ``ppoe warmup`` runs on the installed copy: the nodes' kernels are compiled
then, not at their first start (docs/performance.md, "Start-up").  ``PPOE_WARMUP=0`` skips it;
``PPOE_WARMUP_NODES`` (space-separated node names) limits it.  A pip install runs it as the README's set-up
command says (pip builds a wheel in an isolated environment, where this hook cannot reach the final place).
"""

import os
import subprocess
import sys
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.develop import develop
from setuptools.command.install import install

PACKAGE = "ppoe_ros"


def _warmup(install_lib: str) -> None:
    """``ppoe warmup`` on the copy installed in ``install_lib`` (the module docstring); never fails the install."""
    if os.environ.get("PPOE_WARMUP", "1") == "0":
        print("ppoe warmup skipped (PPOE_WARMUP=0): the nodes compile their kernels at their first start")
        return
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (install_lib, os.environ.get("PYTHONPATH")) if p))
    nodes = os.environ.get("PPOE_WARMUP_NODES", "").split()
    cmd = [sys.executable, "-m", "ppoe_ros.cli", "warmup"] + (["--nodes", *nodes] if nodes else [])
    try:
        code = subprocess.call(cmd, env=env, cwd=install_lib)
    except OSError as exc:
        code = str(exc)
    if code:
        print(f"ppoe warmup did not finish ({code}): the nodes compile their kernels at their first start "
              f"(run 'ppoe warmup' later)")


class InstallAndWarm(install):
    """``install``, then ``ppoe warmup`` on the installed copy (not when staging a wheel: ``--root``)."""

    def run(self):
        super().run()
        if not self.root:
            _warmup(self.install_lib)


class DevelopAndWarm(develop):
    """``develop`` (``colcon build --symlink-install``), then ``ppoe warmup`` on the source tree."""

    def run(self):
        super().run()
        if not getattr(self, "uninstall", False):
            _warmup(os.path.dirname(os.path.abspath(__file__)))

setup(
    name=PACKAGE,
    cmdclass={"install": InstallAndWarm, "develop": DevelopAndWarm},
    version="0.1.0",
    packages=find_packages(include=["ppoe_core", "ppoe_core.*", "ppoe_ros", "ppoe_ros.*"]),
    package_data={"ppoe_core": ["py.typed"], "ppoe_ros": ["py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/config", sorted(glob("config/*.*"))),
        ("share/" + PACKAGE + "/config/robots", sorted(glob("config/robots/*.*"))),
        ("share/" + PACKAGE + "/config/nodes", sorted(glob("config/nodes/*.*"))),
        ("share/" + PACKAGE + "/config/rviz", sorted(glob("config/rviz/*.rviz"))),
        ("share/" + PACKAGE + "/launch", sorted(glob("launch/*.py"))),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "PyYAML>=6",
        "opencv-python-headless>=4.8",
        "rosbags>=0.10",
        "matplotlib>=3.7",
        "ruamel.yaml>=0.18",
        "numba>=0.59",
        "isal>=1.6",  # ISA-L inflate of PNG images (ppoe_core/io/png.py; zlib without it, twice the time)
    ],
    extras_require={
        "ros": [
            "ros-jazzy-rclpy",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-rmw-fastrtps-cpp",
        ],
        "test": [
            "pytest>=7",
            "hypothesis>=6",
            "pytest-timeout>=2",
            "pytest-xdist>=3",    # the README's test command runs the suite on 2 workers (-n 2 --dist loadfile)
            "pytransform3d>=3.6",
            "gtsam>=4.3",         # test_diagnose_joint: GTSAM factor graph vs scipy (importorskip)
            "xacro>=2.0",         # test_launch_file: a .xacro urdf expanded by the launch file (importorskip)
            "colcon-core",
            "colcon-ros",
            "colcon-python-setup-py",
            "ruff>=0.17,<0.18",   # lint, .ci/run (ruff.toml)
            "mypy>=2.4,<2.5",     # types of ppoe_core, .ci/run (mypy.ini)
        ],
    },
    zip_safe=True,
    maintainer="ppoe_ros developers",
    maintainer_email="ppoe@example.com",
    description="Probabilistic Product-of-Exponentials kinematics and Lie-group EKF fusion for ROS 2 Jazzy",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "ppoe = ppoe_ros.cli:main",
            "kinematics_node = ppoe_ros.nodes.kinematics_node:main",
            "tag_bearing_node = ppoe_ros.nodes.tag_bearing_node:main",
            "contact_node = ppoe_ros.nodes.contact_node:main",
            "fusion_node = ppoe_ros.nodes.fusion_node:main",
            "ppoe_container = ppoe_ros.nodes.container:main",
            "ppoe_markers = ppoe_ros.common.markers:main",
            "ppoe_calibration = ppoe_ros.common.calibration:main",
            "ppoe_managed = ppoe_ros.common.lifecycle:main",
        ],
    },
)
