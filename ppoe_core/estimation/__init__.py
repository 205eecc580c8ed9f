"""ppoe_core.estimation."""
