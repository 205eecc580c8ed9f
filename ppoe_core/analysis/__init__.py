"""ppoe_core.analysis."""
