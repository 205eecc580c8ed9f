"""ppoe_core.model: PPOEModel (2nd/4th order, sampling) and the effect catalogue, on ppoe_core.robot."""
