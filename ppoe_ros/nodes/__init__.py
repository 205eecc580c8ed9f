"""ppoe_ros.nodes: the ROS 2 nodes (parse, call ppoe_core, publish)."""
