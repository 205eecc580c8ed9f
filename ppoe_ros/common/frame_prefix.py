"""Namespaces and ``frame_prefix``: several robots in one ROS graph (issue 11 item 5).

As robot_state_publisher (Jazzy) does it:

* every default topic of a node is **relative** (``joint_states``, ``robot_description``, ``ppoe/pose`` ...), so
  ``--ros-args -r __ns:=/robot1`` (or the launch file's ``namespace`` argument) moves it to ``/robot1/...``;
  ``/tf``, ``/tf_static`` and ``/diagnostics`` stay absolute (tf2 and diagnostic_aggregator listen there);
* ``frame_prefix`` (default empty) is prepended, as plain text, to every frame a node publishes (pose headers,
  TF parents and children) and expected on every frame it receives that names a frame of the robot; the URDF
  and the model YAML keep the plain names.  With ``frame_prefix: robot1/`` the tool frame is ``robot1/tool0``
  on the wire.

A bag keeps the absolute contract topics (docs/conventions.md sec. 3): ``ppoe play`` publishes ``/joint_states`` ...,
which nodes in the root namespace (the default) receive unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ppoe_ros.common.params import ParamSpec

__all__ = ["FRAME_PREFIX_PARAM", "prefixed", "unprefixed", "resolve_topics"]

#: the ``frame_prefix`` parameter of every node that publishes or expects frames of the robot
FRAME_PREFIX_PARAM = ParamSpec(
    "frame_prefix", "",
    "prepended to every frame of the robot the node publishes and expects (robot_state_publisher's frame_prefix, "
    "e.g. 'robot1/'); the URDF and the model YAML keep the plain names")


def prefixed(prefix: str, frame: str) -> str:
    """``prefix + frame`` (an empty frame stays empty)."""
    return prefix + frame if frame else frame


def unprefixed(prefix: str, frame: str, topic: str) -> str:
    """:func:`ppoe_core.estimation.sources.unprefixed` (THE rule; imported on the first call, so that a node that
    never receives a frame, e.g. the kinematics node, does not load the estimation layer and scipy with it)."""
    from ppoe_core.estimation.sources import unprefixed as rule

    return rule(prefix, frame, topic)


def resolve_topics(node: Any, params: dict[str, Any], keys: Sequence[str]) -> None:
    """Replace the (relative) topic parameters ``keys`` in ``params`` by their resolved names (namespace and
    remappings applied), so that subscriptions, publishers and every log line name the real topic; an empty topic
    (input off) stays empty."""
    for key in keys:
        if params[key]:
            params[key] = node.resolve_topic_name(params[key])
