"""Lifecycle (managed) variants of the nodes: ``ppoe_managed NODE [--ros-args ...]``.

A managed node starts *unconfigured* with only the lifecycle services (``~/change_state``, ``~/get_state`` ...,
``lifecycle_msgs``), so a launch file or a lifecycle manager brings the nodes up in order:

``configure``
    The node's own set-up runs (the same code as the plain node): parameters declared and checked, the model
    file read, the URDF taken (its parameter, else the latched ``robot_description`` topic, subscribed now),
    publishers, services and timers created.  A bad parameter or model file fails the transition with the
    reason logged and the node stays unconfigured; fix the parameters and restart it (a parameter is declared
    once per process, so neither a second ``configure`` after a failure nor ``cleanup`` is offered).
``activate``
    The input subscriptions are created: only now does the node receive joint states, images, priors ...
``deactivate``
    The input subscriptions are destroyed (the node keeps its model, buffers and counters).

How: the node class runs its constructor body at ``configure`` (a class between it and ``LifecycleNode``
turns its ``super().__init__`` into a no-op), and every subscription it creates then, except the URDF's, is
a :class:`DeferredSubscription` that exists in the middleware only while the node is active.  No node file is
changed for this; the nodes: :data:`MANAGED`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.subscription import Subscription

from ppoe_core.errors import PpoeError

__all__ = ["MANAGED", "DeferredSubscription", "managed_class", "main"]

#: node kind -> (module, class) of the nodes that have a managed variant
MANAGED = {
    "kinematics_node": ("ppoe_ros.nodes.kinematics_node", "KinematicsNode"),
    "tag_bearing_node": ("ppoe_ros.nodes.tag_bearing_node", "TagBearingNode"),
    "contact_node": ("ppoe_ros.nodes.contact_node", "ContactNode"),
    "fusion_node": ("ppoe_ros.nodes.fusion_node", "FusionNode"),
}


class DeferredSubscription:
    """A subscription created at ``activate`` and destroyed at ``deactivate``; attributes set on it before
    (e.g. the callback type) are applied to each real one, attributes read go to the real one (or to the
    ``Subscription`` class while there is none)."""

    def __init__(self, node: Any, args: tuple, kwargs: dict) -> None:
        object.__setattr__(self, "_spec", (node, args, kwargs, {}))
        object.__setattr__(self, "real", None)

    def create(self) -> None:
        node, args, kwargs, attrs = self._spec
        if self.real is None:
            real = super(_Between, node).create_subscription(*args, **kwargs)
            for k, v in attrs.items():
                setattr(real, k, v)
            object.__setattr__(self, "real", real)

    def destroy(self) -> None:
        if self.real is not None:
            self._spec[0].destroy_subscription(self.real)
            object.__setattr__(self, "real", None)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real if self.real is not None else Subscription, name)

    def __setattr__(self, name: str, value: Any) -> None:
        self._spec[3][name] = value
        if self.real is not None:
            setattr(self.real, name, value)


class _Between(LifecycleNode):
    """Sits between a node class and ``LifecycleNode`` in the MRO: the node class's ``super().__init__`` does
    nothing while it configures (the lifecycle node exists already), and its subscriptions are deferred."""

    _configuring = False

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if not self._configuring:
            LifecycleNode.__init__(self, *args, **kwargs)

    def create_subscription(self, msg_type: Any, topic: str, *args: Any, **kwargs: Any) -> Any:
        if not self._configuring or "robot_description" in topic:  # the URDF is part of configure
            return super().create_subscription(msg_type, topic, *args, **kwargs)
        sub = DeferredSubscription(self, (msg_type, topic, *args), kwargs)
        self._deferred.append(sub)
        return sub


def managed_class(kind: str) -> type:
    """The managed variant of node ``kind`` (a key of :data:`MANAGED`)."""
    import importlib

    if kind not in MANAGED:
        raise PpoeError(f"ppoe_managed: no managed node '{kind}' (one of {', '.join(MANAGED)})")
    module, cls_name = MANAGED[kind]
    plain = getattr(importlib.import_module(module), cls_name)

    class Managed(plain, _Between):  # type: ignore[valid-type, misc]
        __doc__ = f"Lifecycle variant of :class:`{module}.{cls_name}` (module docstring)."

        def __init__(self, **kwargs: Any) -> None:
            self._kwargs = kwargs
            self._deferred: list[DeferredSubscription] = []
            self._configured = False
            LifecycleNode.__init__(self, kind, **kwargs)

        def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
            if self._configured:
                return TransitionCallbackReturn.SUCCESS
            type(self)._configuring = True
            try:
                plain.__init__(self, **self._kwargs)
            except PpoeError as exc:
                self.get_logger().error(f"configure failed: {exc}")
                return TransitionCallbackReturn.FAILURE
            finally:
                type(self)._configuring = False
            self._configured = True
            self.get_logger().info(f"configured; {len(self._deferred)} input subscription(s) wait for activate")
            return TransitionCallbackReturn.SUCCESS

        def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
            for sub in self._deferred:
                sub.create()
            return super().on_activate(state)

        def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
            for sub in self._deferred:
                sub.destroy()
            return super().on_deactivate(state)

        def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
            self.get_logger().error("cleanup is not supported (parameters are declared once): restart the node")
            return TransitionCallbackReturn.FAILURE

    Managed.__name__ = Managed.__qualname__ = f"Managed{cls_name}"
    return Managed


def main(args: Sequence[str] | None = None) -> int:
    """``ppoe_managed NODE [--ros-args ...]``: the lifecycle variant of ``NODE`` (kinematics_node, ...)."""
    from ppoe_ros.common.runner import run_node

    argv = list(sys.argv if args is None else args)
    kind = argv[1] if len(argv) > 1 and not argv[1].startswith("-") else ""
    try:
        cls = managed_class(kind)
    except PpoeError as exc:
        print(f"[FATAL] {exc}", file=sys.stderr, flush=True)
        return 2
    return run_node(cls, [argv[0], *argv[2:]])


if __name__ == "__main__":
    raise SystemExit(main())
