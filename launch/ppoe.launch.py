"""Launch the ppoe_ros nodes on a ROS 2 Jazzy install (``ros2 launch ppoe_ros ppoe.launch.py``).

Arguments
    model_file    model YAML (perturbations, frames, tags, contact, ...), required
    use_sim_time  true when a bag is replayed with ``ppoe play --clock`` (default false)
    kinematics, tag_bearing, contact, fusion
                  start that node (default true each)

Each node reads its parameters from ``share/ppoe_ros/config/nodes/<executable>.yaml``
(every key documented there); ``model_file`` and ``use_sim_time`` given here
override the file.  The kinematics node takes the URDF from ``/robot_description``
(robot_state_publisher, or ``ppoe play`` of a recorded bag).

Example::

    ros2 launch ppoe_ros ppoe.launch.py model_file:=/path/arm7_model.yaml use_sim_time:=true
    ppoe play my_bag --clock
"""

from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

__all__ = ["generate_launch_description"]

PACKAGE = "ppoe_ros"


def generate_launch_description() -> LaunchDescription:
    """The four nodes with their config files; see the module docstring for the arguments."""
    share = FindPackageShare(PACKAGE)
    common = {
        "model_file": LaunchConfiguration("model_file"),
        "use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool),
    }
    arguments = [
        DeclareLaunchArgument("model_file", description="model YAML (perturbations, frames, tags, contact)"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="take time from /clock (replayed bags)"),
        DeclareLaunchArgument("kinematics", default_value="true", description="start kinematics_node"),
        DeclareLaunchArgument("tag_bearing", default_value="true", description="start tag_bearing_node"),
        DeclareLaunchArgument("contact", default_value="true", description="start contact_node"),
        DeclareLaunchArgument("fusion", default_value="true", description="start fusion_node"),
    ]
    nodes = [
        Node(
            package=PACKAGE,
            executable="kinematics_node",
            name="kinematics_node",
            output="screen",
            parameters=[PathJoinSubstitution([share, "config", "nodes", "kinematics_node.yaml"]), common],
            condition=IfCondition(LaunchConfiguration("kinematics")),
        ),
        Node(
            package=PACKAGE,
            executable="tag_bearing_node",
            name="tag_bearing_node",
            output="screen",
            parameters=[PathJoinSubstitution([share, "config", "nodes", "tag_bearing_node.yaml"]), common],
            condition=IfCondition(LaunchConfiguration("tag_bearing")),
        ),
        Node(
            package=PACKAGE,
            executable="contact_node",
            name="contact_node",
            output="screen",
            parameters=[PathJoinSubstitution([share, "config", "nodes", "contact_node.yaml"]), common],
            condition=IfCondition(LaunchConfiguration("contact")),
        ),
        Node(
            package=PACKAGE,
            executable="fusion_node",
            name="fusion_node",
            output="screen",
            parameters=[PathJoinSubstitution([share, "config", "nodes", "fusion_node.yaml"]), common],
            condition=IfCondition(LaunchConfiguration("fusion")),
        ),
    ]
    return LaunchDescription(arguments + nodes)
