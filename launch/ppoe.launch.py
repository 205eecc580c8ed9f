"""Launch the ppoe_ros nodes on a ROS 2 Jazzy install (``ros2 launch ppoe_ros ppoe.launch.py``).

Arguments
    model         model YAML (perturbations, frames, tags, contact, ...), required (``model_file`` is accepted
                  as its old name)
    urdf          URDF file given to every node as its ``robot_description`` parameter (a ``.xacro`` file is
                  expanded with the ``xacro`` Python package); empty (default) = the nodes take the URDF from the
                  ``robot_description`` topic of their namespace (robot_state_publisher, or a played bag)
    params_file   a parameter file applied to every node after its shipped defaults
                  (``share/ppoe_ros/config/nodes/<executable>.yaml``) and before the arguments here; list each
                  node's parameters under its name (``fusion_node: {ros__parameters: {...}}``) or under ``/**``
    log_level     log level of every node started here (debug, info, warn, error, fatal; default info)
    robot_state_publisher
                  also start robot_state_publisher with the ``urdf`` (needs ``urdf``; default false); do not set
                  the kinematics node's ``publish_tf`` then (both would publish the same frames)
    namespace     ROS namespace of every node (default empty = root): with ``namespace:=robot1`` the topics are
                  ``/robot1/joint_states``, ``/robot1/ppoe/pose`` ...; ``/tf``, ``/tf_static``, ``/diagnostics``
                  stay absolute (robot_state_publisher's convention)
    frame_prefix  put in front of every frame of the robot the nodes publish and expect (default empty; e.g.
                  ``robot1/``, as robot_state_publisher's ``frame_prefix``)
    use_sim_time  true when a bag is replayed with ``ppoe play --clock`` (default false)
    kinematics, tag_bearing, contact, fusion
                  start that node (default true each)
    lifecycle     start the managed (lifecycle) variants (``ppoe_managed NODE``, ppoe_ros/common/lifecycle.py):
                  unconfigured first; with ``autostart`` (default true) the launch configures each one and activates
                  it once it is inactive, else a lifecycle manager does (default false)
    autostart     with ``lifecycle``: configure and activate the nodes (default true)
    markers       also start ppoe_markers: the raw and fused position ellipsoids on ``ppoe/markers`` (default false)
    rviz          also start rviz2 with ``share/ppoe_ros/config/rviz/ppoe.rviz`` (default false)

Paths (``model``, ``urdf``, ``params_file``) may be ``package://PKG/PATH`` URIs or relative paths: a relative
path is taken from the directory ``ros2 launch`` runs in, else from the ppoe_ros share directory (so
``model:=config/robots/arm7_model.yaml`` names the installed example from anywhere); the nodes get absolute
paths (:func:`ppoe_core.io.paths.resolve_path`).  ``model_file`` values inside parameter files are resolved
by the nodes the same way, relative to the parameter file (``ppoe_ros/common/paths.py``).

Examples::

    ros2 launch ppoe_ros ppoe.launch.py model:=package://ppoe_ros/config/robots/arm7_model.yaml use_sim_time:=true
    ppoe play my_bag --clock
    # URDF from a xacro file, robot_state_publisher beside the nodes, a parameter file of your own
    ros2 launch ppoe_ros ppoe.launch.py model:=my_model.yaml urdf:=my_robot.urdf.xacro robot_state_publisher:=true \\
        params_file:=my_params.yaml log_level:=debug
    # two robots in one graph
    ros2 launch ppoe_ros ppoe.launch.py namespace:=robot1 frame_prefix:=robot1/ urdf:=arm7.urdf model:=arm7_model.yaml
    ros2 launch ppoe_ros ppoe.launch.py namespace:=robot2 frame_prefix:=robot2/ urdf:=arm7.urdf model:=arm7_model.yaml
"""

import os
from pathlib import Path

try:
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    from launch import LaunchDescription
except ImportError as _exc:  # a pip install has no launch / launch_ros: the file still imports (tests, tools)
    _MISSING: ImportError | None = _exc
else:
    _MISSING = None

__all__ = ["ARGUMENTS", "NODE_OVERRIDES", "LOG_LEVELS", "generate_launch_description", "launch_nodes",
           "read_urdf"]

PACKAGE = "ppoe_ros"

#: launch arguments: name -> (default, description)
ARGUMENTS = {
    "model": ("", "model YAML (perturbations, frames, tags, contact); path or package:// URI; required"),
    "model_file": ("", "old name of 'model'"),
    "urdf": ("", "URDF (or .xacro) file for the robot_description parameter; empty = the robot_description topic"),
    "params_file": ("", "parameter file applied to every node after its shipped defaults; empty = none"),
    "log_level": ("info", "log level of the nodes: debug, info, warn, error or fatal"),
    "robot_state_publisher": ("false", "also start robot_state_publisher with the urdf (needs urdf)"),
    "namespace": ("", "ROS namespace of every node, e.g. robot1 (topics /robot1/...; /tf stays /tf)"),
    "frame_prefix": ("", "prefix of every frame of the robot published and expected, e.g. robot1/"),
    "use_sim_time": ("false", "take time from /clock (replayed bags)"),
    "kinematics": ("true", "start kinematics_node"),
    "tag_bearing": ("true", "start tag_bearing_node"),
    "contact": ("true", "start contact_node"),
    "fusion": ("true", "start fusion_node"),
    "lifecycle": ("false", "start the managed (lifecycle) variants of the nodes"),
    "autostart": ("true", "with lifecycle: configure and activate them"),
    "markers": ("false", "start ppoe_markers (covariance ellipsoids on ppoe/markers for RViz)"),
    "rviz": ("false", "start rviz2 with config/rviz/ppoe.rviz"),
}

#: (executable, launch argument that switches it on, parameters of that node the launch arguments set)
NODE_OVERRIDES = (
    ("kinematics_node", "kinematics", ("model_file", "robot_description", "frame_prefix", "use_sim_time")),
    ("tag_bearing_node", "tag_bearing", ("model_file", "use_sim_time")),
    ("contact_node", "contact", ("model_file", "frame_prefix", "use_sim_time")),
    ("fusion_node", "fusion", ("model_file", "robot_description", "frame_prefix", "use_sim_time")),
)

#: what ``--log-level`` accepts (rcutils severities)
LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")


def _true(text: str) -> bool:
    return text.strip().lower() in ("true", "1", "yes", "on")


def _path(value: str, what: str, share: Path) -> str:
    """A path argument as an absolute path (package:// URI, launch directory, then the package share)."""
    from ppoe_core.errors import PpoeError
    from ppoe_core.io.paths import resolve_path

    try:
        path = Path(resolve_path(value, [os.getcwd(), share], what=f"ppoe.launch.py: {what}"))
    except PpoeError as exc:
        raise RuntimeError(str(exc)) from None
    if not path.is_file():
        raise RuntimeError(f"ppoe.launch.py: {what}:={value}: no such file ({path})")
    return str(path.resolve())


def read_urdf(path: str) -> str:
    """The URDF text of a ``.urdf`` file, or of a ``.xacro`` file expanded by the ``xacro`` package."""
    if not path.endswith(".xacro"):
        return Path(path).read_text()
    try:
        import xacro
    except ImportError:
        raise RuntimeError(f"ppoe.launch.py: urdf:={path} is a xacro file and the xacro package is not installed "
                           f"(apt install ros-jazzy-xacro, or pip install xacro)") from None
    return str(xacro.process_file(path).toprettyxml(indent="  "))


def launch_nodes(context: object, *args: object, **kwargs: object) -> list:
    """The nodes, built once the argument values are known (``OpaqueFunction``: files are read here)."""
    from ament_index_python.packages import get_package_share_directory

    def value(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    share = Path(get_package_share_directory(PACKAGE))
    model = value("model") or value("model_file")
    if not model:
        raise RuntimeError("ppoe.launch.py: the argument model:=MODEL.yaml is required")
    level = value("log_level").strip().lower()
    if level not in LOG_LEVELS:
        raise RuntimeError(f"ppoe.launch.py: log_level:={level} is not one of {', '.join(LOG_LEVELS)}")
    urdf = _path(value("urdf"), "urdf", share) if value("urdf") else ""
    user_params = [_path(value("params_file"), "params_file", share)] if value("params_file") else []
    overrides = {
        "model_file": _path(model, "model", share),
        "robot_description": read_urdf(urdf) if urdf else "",
        "frame_prefix": value("frame_prefix"),
        "use_sim_time": _true(value("use_sim_time")),
    }
    common = {"namespace": value("namespace"), "output": "screen", "ros_arguments": ["--log-level", level]}
    nodes = []
    if _true(value("robot_state_publisher")):
        nodes.append(_robot_state_publisher(overrides, common))
    managed = _true(value("lifecycle"))
    for executable, switch, keys in NODE_OVERRIDES:
        if not _true(value(switch)):
            continue
        params = [str(share / "config" / "nodes" / f"{executable}.yaml"), *user_params,
                  {k: overrides[k] for k in keys}]
        if managed:
            nodes += _managed_node(executable, common, params, _true(value("autostart")))
        else:
            nodes.append(Node(package=PACKAGE, executable=executable, name=executable, **common, parameters=params))
    if _true(value("markers")):
        nodes.append(Node(package=PACKAGE, executable="ppoe_markers", name="ppoe_markers", **common,
                          parameters=[{"use_sim_time": overrides["use_sim_time"]}]))
    if _true(value("rviz")):
        _require("rviz2", "rviz:=true", "ros-jazzy-rviz2")
        nodes.append(Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
                          arguments=["-d", str(share / "config" / "rviz" / "ppoe.rviz")],
                          parameters=[{"use_sim_time": overrides["use_sim_time"]}]))
    return nodes


def _managed_node(executable: str, common: dict, params: list, autostart: bool) -> list:
    """The lifecycle variant of ``executable`` (``ppoe_managed``) and, with ``autostart``, the events that configure
    it and activate it once it is inactive (the pattern of launch_ros' lifecycle examples)."""
    from launch.actions import EmitEvent, RegisterEventHandler
    from launch.events import matches_action
    from launch_ros.actions import LifecycleNode
    from launch_ros.event_handlers import OnStateTransition
    from launch_ros.events.lifecycle import ChangeState
    from lifecycle_msgs.msg import Transition

    node = LifecycleNode(package=PACKAGE, executable="ppoe_managed", name=executable, arguments=[executable],
                         parameters=params, **common)
    if not autostart:
        return [node]

    def change(transition: int) -> "EmitEvent":
        return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(node), transition_id=transition))

    activate = RegisterEventHandler(OnStateTransition(target_lifecycle_node=node, start_state="configuring",
                                                      goal_state="inactive",
                                                      entities=[change(Transition.TRANSITION_ACTIVATE)]))
    return [node, activate, change(Transition.TRANSITION_CONFIGURE)]


def _require(package: str, why: str, apt: str) -> None:
    """RuntimeError naming the apt package when ``package`` is not installed."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        get_package_prefix(package)
    except PackageNotFoundError:
        raise RuntimeError(f"ppoe.launch.py: {why}, but the package {package} is not installed "
                           f"(apt install {apt})") from None


def _robot_state_publisher(overrides: dict, common: dict) -> "Node":
    """robot_state_publisher with the launch's URDF, frame prefix and clock."""
    if not overrides["robot_description"]:
        raise RuntimeError("ppoe.launch.py: robot_state_publisher:=true needs urdf:=FILE")
    _require("robot_state_publisher", "robot_state_publisher:=true", "ros-jazzy-robot-state-publisher")
    params = {k: overrides[k] for k in ("robot_description", "frame_prefix", "use_sim_time")}
    return Node(package="robot_state_publisher", executable="robot_state_publisher", name="robot_state_publisher",
                **common, parameters=[params])


def generate_launch_description() -> "LaunchDescription":
    """The arguments of :data:`ARGUMENTS` and the nodes (:func:`launch_nodes`)."""
    if _MISSING is not None:
        raise RuntimeError(f"ppoe.launch.py needs the ROS 2 packages launch and launch_ros (ROS 2 Jazzy from apt, "
                           f"source /opt/ros/jazzy/setup.bash): {_MISSING}")
    arguments = [DeclareLaunchArgument(name, default_value=default, description=text)
                 for name, (default, text) in ARGUMENTS.items()]
    return LaunchDescription(arguments + [OpaqueFunction(function=launch_nodes)])
