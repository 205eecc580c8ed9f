"""A bag's recorded QoS (rosbags ``Qos``, :mod:`ppoe_core.io.bag_qos`) to and from rclpy's ``QoSProfile``."""

from __future__ import annotations

from typing import Any

from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

__all__ = ["qos_to_rclpy", "qos_from_rclpy"]

_NS = 1_000_000_000

def _to_rclpy_policy(value: Any, rclpy_enum: type) -> Any:
    known = value.name in rclpy_enum.__members__ and value.name != "UNKNOWN"  # no publisher offers UNKNOWN
    return rclpy_enum[value.name] if known else rclpy_enum.SYSTEM_DEFAULT


def _to_bag_policy(value: Any, bag_enum: type) -> Any:
    return bag_enum[value.name] if value.name in bag_enum.__members__ else bag_enum.UNKNOWN


def _duration(t: QosTime) -> Duration:
    return Duration(nanoseconds=int(t.sec) * _NS + int(t.nsec))


def _qos_time(d: Duration) -> QosTime:
    ns = int(d.nanoseconds)
    return QosTime(ns // _NS, ns % _NS)


def qos_to_rclpy(qos: Qos, depth: int | None = None) -> QoSProfile:
    """An rclpy profile with the policies of a recorded one; ``depth`` replaces its history depth."""
    return QoSProfile(
        history=_to_rclpy_policy(qos.history, HistoryPolicy),
        depth=int(depth if depth is not None else qos.depth),
        reliability=_to_rclpy_policy(qos.reliability, ReliabilityPolicy),
        durability=_to_rclpy_policy(qos.durability, DurabilityPolicy),
        deadline=_duration(qos.deadline),
        lifespan=_duration(qos.lifespan),
        liveliness=_to_rclpy_policy(qos.liveliness, LivelinessPolicy),
        liveliness_lease_duration=_duration(qos.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions),
    )


def qos_from_rclpy(profile: QoSProfile) -> Qos:
    """The recorded form of a live endpoint's profile (``get_publishers_info_by_topic(...).qos_profile``)."""
    return Qos(
        _to_bag_policy(profile.history, QosHistory),
        int(profile.depth),
        _to_bag_policy(profile.reliability, QosReliability),
        _to_bag_policy(profile.durability, QosDurability),
        _qos_time(profile.deadline),
        _qos_time(profile.lifespan),
        _to_bag_policy(profile.liveliness, QosLiveliness),
        _qos_time(profile.liveliness_lease_duration),
        bool(profile.avoid_ros_namespace_conventions),
    )
