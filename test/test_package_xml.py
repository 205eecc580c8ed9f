"""package.xml and setup.py name every third-party import of the package (so ``rosdep install`` / ``pip install``
bring what the code needs), and nothing it does not use.

Imports are read with ``ast`` from ppoe_core/, ppoe_ros/ and launch/ (tests, benchmarks and scripts have their own
extras).  :data:`ROSDEP_KEYS` maps an imported top-level module to its rosdep key: a new import without an entry
fails here until the key is added to the table and to package.xml.
"""

from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from conftest import REPO

SOURCES = ["ppoe_core", "ppoe_ros", "launch"]

#: imported top-level module -> rosdep key
ROSDEP_KEYS = {
    **{m: m for m in ("rclpy", "builtin_interfaces", "rcl_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs",
                      "diagnostic_msgs", "tf2_msgs", "rosgraph_msgs", "visualization_msgs", "std_srvs",
                      "lifecycle_msgs", "launch", "launch_ros", "ament_index_python", "xacro")},
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "yaml": "python3-yaml",
    "ruamel": "python3-ruamel.yaml",
    "cv2": "python3-opencv",
    "numba": "python3-numba",
    "matplotlib": "python3-matplotlib",
    "rosbags": "python3-rosbags-pip",
}

#: imported top-level module -> pip requirement name in setup.py install_requires (ROS packages come from ROS)
PIP_NAMES = {"numpy": "numpy", "scipy": "scipy", "yaml": "PyYAML", "ruamel": "ruamel.yaml",
             "cv2": "opencv-python-headless", "numba": "numba", "matplotlib": "matplotlib", "rosbags": "rosbags",
             "isal": "isal"}

#: optional imports (each inside ``try: ... except ImportError`` or inside the one function that needs it), not
#: required by package.xml / setup.py
OPTIONAL = {"gtsam": "diagnose's GTSAM cross-check (ppoe_core/analysis/diagnose/joint_gtsam.py)",
            "xacro": "a .xacro urdf in launch/ppoe.launch.py (listed in package.xml all the same)",
            "isal": "ISA-L inflate of PNG images (ppoe_core/io/png.py; zlib without it): in setup.py for pip users, "
                    "not in package.xml (no verified rosdep key; an unknown key fails `rosdep install`)"}

#: package.xml keys that are not imports: executables the launch file starts, and lifecycle_msgs, which
#: rclpy.lifecycle (ppoe_ros/common/lifecycle.py) needs at run time
EXECUTABLES = {"robot_state_publisher", "lifecycle_msgs"}


def _imports() -> dict[str, set[str]]:
    """Top-level third-party module -> files importing it; an import inside ``try: ... except ImportError`` or a
    function body is also listed with a trailing '?' (it may be optional)."""
    found: dict[str, set[str]] = {}
    for src in SOURCES:
        for path in sorted((REPO / src).rglob("*.py")):
            tree = ast.parse(path.read_text())
            guarded = {id(n) for t in ast.walk(tree) if isinstance(t, ast.Try)
                       and any(isinstance(h.type, ast.Name) and h.type.id in ("ImportError", "ModuleNotFoundError")
                               for h in t.handlers) for s in t.body for n in ast.walk(s)}
            guarded |= {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                        for n in ast.walk(f)}
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split(".")[0]
                    if top in sys.stdlib_module_names or top.startswith("ppoe_"):
                        continue
                    where = str(path.relative_to(REPO))
                    found.setdefault(top, set()).add(where)
                    if id(node) in guarded:
                        found.setdefault(top + "?", set()).add(where)
    return found


def _package_xml_deps() -> set[str]:
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    return {e.text.strip() for e in root if e.tag in ("depend", "exec_depend") and e.text}


def _install_requires() -> set[str]:
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "install_requires":
            reqs = ast.literal_eval(node.value)
            return {r.split(">")[0].split("=")[0].split("<")[0].strip() for r in reqs}
    raise AssertionError("setup.py has no install_requires")


def test_every_import_has_a_rosdep_key_in_package_xml() -> None:
    imports = _imports()
    modules = {k for k in imports if not k.endswith("?")}
    unmapped = sorted(m for m in modules if m not in ROSDEP_KEYS and m not in OPTIONAL)
    assert not unmapped, f"imports without a rosdep key in ROSDEP_KEYS: {[(m, sorted(imports[m])) for m in unmapped]}"
    unguarded = sorted(m for m in OPTIONAL if m in imports and imports[m] != imports.get(m + "?"))
    assert not unguarded, f"optional modules imported unguarded at module level: {unguarded}"
    required = modules - set(OPTIONAL)
    deps = _package_xml_deps()
    missing = sorted({ROSDEP_KEYS[m] for m in required} - deps)
    assert not missing, f"package.xml lacks exec_depend {missing}"
    used = {ROSDEP_KEYS[m] for m in modules if m in ROSDEP_KEYS} | EXECUTABLES
    stale = sorted(deps - used)
    assert not stale, f"package.xml depends on {stale}, which nothing imports"


def test_setup_py_requires_every_pip_import() -> None:
    required = {k for k in _imports() if not k.endswith("?")} - set(OPTIONAL)
    pip_needed = {PIP_NAMES[m] for m in required if m in PIP_NAMES}
    reqs = _install_requires()
    assert pip_needed <= reqs, f"setup.py install_requires lacks {sorted(pip_needed - reqs)}"
    ros = {m for m in required if m in ROSDEP_KEYS and m not in PIP_NAMES}
    assert not ros & {r.replace("-", "_") for r in reqs}, "ROS packages belong in package.xml / the ros extra"


def test_the_check_sees_guarded_and_plain_imports() -> None:
    """The scanner itself: launch/ppoe.launch.py imports launch_ros plainly, ament_index_python lazily, and
    xacro inside ``try``; joint_gtsam imports gtsam inside ``try``."""
    imports = _imports()
    assert "launch/ppoe.launch.py" in imports["launch_ros"]
    assert "launch/ppoe.launch.py" in imports["ament_index_python"]
    assert "launch/ppoe.launch.py" in imports["xacro?"]
    assert any("joint_gtsam" in f for f in imports.get("gtsam?", ())) or "gtsam" not in imports
    assert Path(REPO / "package.xml").read_text().count("<exec_depend>rclpy</exec_depend>") == 1
