"""ppoe_core.cli."""
