"""ppoe_core.sensing."""
