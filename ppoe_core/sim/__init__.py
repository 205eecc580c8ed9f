"""ppoe_core.sim."""
