"""ppoe_core.io."""
