"""Launch the ppoe_ros nodes on a ROS 2 Jazzy install (``ros2 launch ppoe_ros ppoe.launch.py``).

Arguments
    model         model YAML (perturbations, frames, tags, contact, ...), required
                  (``model_file`` is accepted as its old name)
    urdf          URDF file given to every node as its ``robot_description`` parameter; empty (default) = the
                  nodes take the URDF from the ``robot_description`` topic of their namespace (robot_state_publisher,
                  or ``ppoe play`` of a recorded bag)
    namespace     ROS namespace of every node (default empty = root): with ``namespace:=robot1`` the topics are
                  ``/robot1/joint_states``, ``/robot1/ppoe/pose`` ...; ``/tf``, ``/tf_static``, ``/diagnostics``
                  stay absolute (robot_state_publisher's convention)
    frame_prefix  put in front of every frame of the robot the nodes publish and expect (default empty; e.g.
                  ``robot1/``, as robot_state_publisher's ``frame_prefix``)
    use_sim_time  true when a bag is replayed with ``ppoe play --clock`` (default false)
    kinematics, tag_bearing, contact, fusion
                  start that node (default true each)

Each node reads its parameters from ``share/ppoe_ros/config/nodes/<executable>.yaml`` (every key documented
there; they apply to any node name and namespace); the arguments above override the file, each only for the
nodes that have that parameter (:data:`NODE_OVERRIDES`).

Examples::

    ros2 launch ppoe_ros ppoe.launch.py model:=/path/arm7_model.yaml use_sim_time:=true
    ppoe play my_bag --clock
    # two robots in one graph
    ros2 launch ppoe_ros ppoe.launch.py namespace:=robot1 frame_prefix:=robot1/ urdf:=arm7.urdf model:=arm7_model.yaml
    ros2 launch ppoe_ros ppoe.launch.py namespace:=robot2 frame_prefix:=robot2/ urdf:=arm7.urdf model:=arm7_model.yaml
"""

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

__all__ = ["ARGUMENTS", "NODE_OVERRIDES", "generate_launch_description", "launch_nodes"]

PACKAGE = "ppoe_ros"

#: launch arguments: name -> (default, description)
ARGUMENTS = {
    "model": ("", "model YAML (perturbations, frames, tags, contact); required"),
    "model_file": ("", "old name of 'model'"),
    "urdf": ("", "URDF file for the robot_description parameter; empty = the robot_description topic"),
    "namespace": ("", "ROS namespace of every node, e.g. robot1 (topics /robot1/...; /tf stays /tf)"),
    "frame_prefix": ("", "prefix of every frame of the robot published and expected, e.g. robot1/"),
    "use_sim_time": ("false", "take time from /clock (replayed bags)"),
    "kinematics": ("true", "start kinematics_node"),
    "tag_bearing": ("true", "start tag_bearing_node"),
    "contact": ("true", "start contact_node"),
    "fusion": ("true", "start fusion_node"),
}

#: (executable, launch argument that switches it on, parameters of that node the launch arguments set)
NODE_OVERRIDES = (
    ("kinematics_node", "kinematics", ("model_file", "robot_description", "frame_prefix", "use_sim_time")),
    ("tag_bearing_node", "tag_bearing", ("model_file", "use_sim_time")),
    ("contact_node", "contact", ("model_file", "frame_prefix", "use_sim_time")),
    ("fusion_node", "fusion", ("model_file", "robot_description", "frame_prefix", "use_sim_time")),
)


def _true(text: str) -> bool:
    return text.strip().lower() in ("true", "1", "yes", "on")


def launch_nodes(context: object, *args: object, **kwargs: object) -> list:
    """The nodes, built once the argument values are known (``OpaqueFunction``: the URDF file is read here)."""
    from ament_index_python.packages import get_package_share_directory

    def value(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    model = value("model") or value("model_file")
    if not model:
        raise RuntimeError("ppoe.launch.py: the argument model:=MODEL.yaml is required")
    urdf = value("urdf")
    overrides = {
        "model_file": model,
        "robot_description": Path(urdf).read_text() if urdf else "",
        "frame_prefix": value("frame_prefix"),
        "use_sim_time": _true(value("use_sim_time")),
    }
    share = Path(get_package_share_directory(PACKAGE))
    nodes = []
    for executable, switch, keys in NODE_OVERRIDES:
        if not _true(value(switch)):
            continue
        nodes.append(Node(
            package=PACKAGE,
            executable=executable,
            name=executable,
            namespace=value("namespace"),
            output="screen",
            parameters=[str(share / "config" / "nodes" / f"{executable}.yaml"), {k: overrides[k] for k in keys}],
        ))
    return nodes


def generate_launch_description() -> "LaunchDescription":
    """The arguments of :data:`ARGUMENTS` and the nodes (:func:`launch_nodes`)."""
    if _MISSING is not None:
        raise RuntimeError(f"ppoe.launch.py needs the ROS 2 packages launch and launch_ros (ROS 2 Jazzy from apt, "
                           f"source /opt/ros/jazzy/setup.bash): {_MISSING}")
    arguments = [DeclareLaunchArgument(name, default_value=default, description=text)
                 for name, (default, text) in ARGUMENTS.items()]
    return LaunchDescription(arguments + [OpaqueFunction(function=launch_nodes)])
