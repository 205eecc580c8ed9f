"""ppoe_core.robot."""
