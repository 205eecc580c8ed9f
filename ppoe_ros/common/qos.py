"""QoS profiles of the nodes: sensor data (best effort, depth), reliable, latched (transient local)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# --------------------------------------------------------------------------- QoS


def sensor_qos(depth: int = 100) -> QoSProfile:
    """Sensor-data QoS (best effort, volatile, keep last ``depth``) for high-rate inputs.

    Same policies as ``rclpy.qos.qos_profile_sensor_data`` but with a deeper
    history (its default of 5 drops messages of a 1 kHz topic as soon as one
    callback is late by 5 ms).  A best-effort subscription matches both reliable
    and best-effort publishers.
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def reliable_qos(depth: int = 100) -> QoSProfile:
    """Reliable, volatile, keep last ``depth``: the default for the nodes' outputs."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


#: Transient-local ("latched") QoS of ``/robot_description``, as robot_state_publisher uses.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
