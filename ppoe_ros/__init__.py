"""Thin rclpy nodes and tools around :mod:`ppoe_core` (parse, call core, publish)."""

__all__: list[str] = []
