"""Node health: counters (:class:`NodeStats`), the guarded callback wrapper and ``/diagnostics``."""

from __future__ import annotations

import functools
import re
import time
import traceback
from collections.abc import Callable, Iterable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from ppoe_core.errors import PpoeError
from ppoe_ros.common.qos import reliable_qos

# ------------------------------------------------------------------ counters, logs


class NodeStats:
    """Counters of a node plus throttled logging of bad messages.

    Parameters
    ----------
    node : rclpy.node.Node
        Node whose logger is used.
    keys : iterable of str
        Counters reported even while zero (``received``, ``published``, ``bad`` ...).
    throttle_sec : float
        At most one log line per (topic, kind) per this many seconds (steady clock);
        the next line says how many were suppressed.
    """

    def __init__(self, node: Node, keys: Iterable[str] = ("received", "published", "bad"),
                 throttle_sec: float = 2.0) -> None:
        self._logger = node.get_logger()
        self.context = getattr(node, "context", None)
        """The node's context: once shut down (Ctrl-C during a callback) a failing publish is not an error."""
        self.counts: dict[str, int] = {k: 0 for k in keys}
        self.throttle_sec = float(throttle_sec)
        self._last_log: dict[tuple[str, str], float] = {}
        self._suppressed: dict[tuple[str, str], int] = {}
        self.last_reason: str = ""
        self.warn_keys: set[str] = {"bad", "errors"}
        """Counters whose growth turns ``/diagnostics`` to WARN (losses and bad input)."""
        self.gap_counters: list[Any] = []
        """Per-input sequence-gap counters (:class:`ppoe_ros.common.losses.SequenceGaps`)."""

    def inc(self, key: str, n: int = 1) -> None:
        """Add ``n`` to counter ``key``."""
        self.counts[key] = self.counts.get(key, 0) + n

    def bad(self, topic: str, reason: str, kind: str = "bad") -> None:
        """Count a bad message on ``topic`` (counter ``kind``) and log it, throttled."""
        self.inc(kind)
        self.last_reason = f"{topic}: {reason}"
        self._log_throttled((topic, kind), f"{kind} message on {topic}: {reason}", error=False)

    def error(self, topic: str, exc: BaseException) -> None:
        """Count an unexpected exception in a callback (counter ``errors``) and log it, throttled."""
        self.inc("errors")
        self.last_reason = f"{topic}: {type(exc).__name__}: {exc}"
        tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
        self._log_throttled((topic, "errors"), f"unexpected error handling {topic}: {tb}", error=True)

    def _log_throttled(self, key: tuple[str, str], text: str, error: bool) -> None:
        now = time.monotonic()
        last = self._last_log.get(key)
        if last is not None and now - last < self.throttle_sec:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        n_sup = self._suppressed.pop(key, 0)
        if n_sup:
            text += f" ({n_sup} similar suppressed in the last {self.throttle_sec:g} s)"
        self._last_log[key] = now
        # two call sites: rclpy's logger refuses a severity change at one call site
        if error:
            self._logger.error(text)
        else:
            self._logger.warning(text)


def guarded(stats: NodeStats, topic: str,
            bad_types: tuple[type[BaseException], ...] = (PpoeError, ValueError, KeyError,
                                                          IndexError, TypeError)):
    """Decorator for a subscription callback: bad messages are counted, not fatal.

    Exceptions of ``bad_types`` count as a bad message on ``topic`` (message of the
    exception as the reason); any other ``Exception`` is counted as ``errors`` with
    its traceback logged.  Either way the node keeps spinning.
    """

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                return func(*args, **kwargs)
            except bad_types as exc:
                stats.bad(topic, str(exc) or type(exc).__name__)
            except Exception as exc:  # noqa: BLE001 - a node must survive any message
                # shutting down (context no longer ok): the publish failed because rclpy stopped, not an error
                if stats.context is None or stats.context.ok():
                    stats.error(topic, exc)
            return None

        return wrapper

    return deco


#: name of the check in a node's status, ``<namespace>/<node>: health`` (diagnostic_updater's "node: task" form)
HEALTH_CHECK = "health"

_ROBOT_NAME = re.compile(r"<robot\b[^>]*?\bname\s*=\s*[\"']([^\"']*)[\"']")


def status_name(fully_qualified_node: str, check: str = HEALTH_CHECK) -> str:
    """``DiagnosticStatus.name`` of a node's check: ``/robot1/kinematics_node: health`` (unique per robot)."""
    return f"{fully_qualified_node}: {check}"


def urdf_robot_name(urdf_xml: str) -> str:
    """The ``name`` of the ``<robot>`` element of a URDF text ("" when there is none)."""
    m = _ROBOT_NAME.search(urdf_xml)
    return m.group(1) if m else ""


class DiagnosticsPublisher:
    """Publish a node's :class:`NodeStats` on ``/diagnostics`` every ``period`` seconds.

    The status is named :func:`status_name` (``<namespace>/<node>: health``), so the statuses of two namespaced
    robots never collide; its ``hardware_id`` is the robot's name: ``hardware_id`` when given, else the
    ``<robot name>`` of the URDF (the node's ``robot_description`` parameter, else the latched
    ``robot_description_topic`` / ``robot_description`` topic of its namespace), and until a URDF is known the
    node's namespace (``robot1``; "" in the root namespace).

    Level WARN while bad messages, errors or losses (counters in ``NodeStats.warn_keys``)
    arrived in the last period, or while a watched input is silent (:meth:`watch_input`), else OK
    (or the level set by :meth:`set_status`).  A standing problem (:meth:`set_problem`: a part of the
    node that is off by configuration) raises the level to at least its own and leads the message.
    The timer runs on the steady clock.
    """

    def __init__(self, node: Node, stats: NodeStats, period: float = 1.0,
                 topic: str = "/diagnostics", hardware_id: str = "") -> None:
        self._node = node
        self._stats = stats
        self._pub = node.create_publisher(DiagnosticArray, topic, reliable_qos(10))
        self._name = status_name(node.get_fully_qualified_name())
        self._hardware_id = hardware_id or node.get_namespace().strip("/")
        self._robot_sub: Any = None if not hardware_id else False  # False: given, never looked up
        self._last_bad = 0
        self._level: bytes | None = None
        self._message = ""
        self._extra: dict[str, str] = {}
        self._problems: dict[str, tuple[bytes, str]] = {}
        self._watched: list[list[Any]] = []  # [topic, counter key, timeout s, last count, steady time of growth]
        self._timer = node.create_timer(float(period), self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def set_hardware_id(self, hardware_id: str) -> None:
        """Report ``hardware_id`` from now on (the robot's name), instead of the one looked up."""
        self._hardware_id = str(hardware_id)
        self._robot_sub = False

    def _look_up_robot_name(self) -> None:
        """The robot name from the ``robot_description`` parameter, else subscribe its latched topic (once)."""
        node = self._node
        if node.has_parameter("robot_description"):
            name = urdf_robot_name(str(node.get_parameter("robot_description").value or ""))
            if name:
                self.set_hardware_id(name)
                return
        topic = "robot_description"
        if node.has_parameter("robot_description_topic"):
            topic = str(node.get_parameter("robot_description_topic").value or topic)
        from std_msgs.msg import String

        from ppoe_ros.common.qos import LATCHED_QOS

        def on_urdf(msg: Any) -> None:
            name = urdf_robot_name(msg.data)
            if name and self._robot_sub is not False:
                self._hardware_id = name

        self._robot_sub = node.create_subscription(String, topic, on_urdf, LATCHED_QOS)

    def set_status(self, level: bytes | None, message: str, **extra: Any) -> None:
        """Override level/message (``DiagnosticStatus.OK/WARN/ERROR``; None = automatic) and add values."""
        self._level = level
        self._message = message
        self._extra.update({k: str(v) for k, v in extra.items()})

    def set_problem(self, key: str, message: str | None, level: bytes = DiagnosticStatus.WARN) -> None:
        """Report (or with ``message`` None clear) a standing problem ``key``; also a value ``key`` = message."""
        if message is None:
            self._problems.pop(key, None)
            self._extra.pop(key, None)
        else:
            self._problems[key] = (level, message)
            self._extra[key] = message

    def watch_input(self, topic: str, key: str, timeout: float) -> None:
        """WARN while counter ``key`` (messages of ``topic``) has not grown for ``timeout`` seconds (0: off)."""
        if timeout > 0:
            self._watched.append([topic, key, float(timeout), self._stats.counts.get(key, 0), time.monotonic()])

    def _silent_inputs(self) -> list[str]:
        """Messages for the watched inputs that are silent beyond their timeout."""
        now, out = time.monotonic(), []
        for w in self._watched:
            n = self._stats.counts.get(w[1], 0)
            if n != w[3]:
                w[3], w[4] = n, now
            elif now - w[4] >= w[2]:
                out.append(f"no {w[0]} for {now - w[4]:.1f} s (input_timeout {w[2]:g} s)")
        return out

    def _refresh_gap_counters(self) -> list[str]:
        """Give every sequence-gap counter its topic's publisher count; returns the paused topics."""
        paused = []
        for gaps in self._stats.gap_counters:
            gaps.refresh(self._node)
            if not gaps.tracking:
                paused.append(gaps.topic)
        return paused

    def publish(self) -> None:
        """Publish one ``DiagnosticArray`` now."""
        if self._robot_sub is None:
            self._look_up_robot_name()
        paused = self._refresh_gap_counters()
        silent = self._silent_inputs()
        counts = self._stats.counts
        n_bad = sum(counts.get(k, 0) for k in self._stats.warn_keys)
        status = DiagnosticStatus()
        status.name = self._name
        status.hardware_id = self._hardware_id
        if self._level is not None:
            status.level = self._level
            status.message = self._message
        elif n_bad > self._last_bad:
            status.level = DiagnosticStatus.WARN
            status.message = f"{n_bad - self._last_bad} bad or lost messages; last: {self._stats.last_reason}"
        elif silent:
            status.level = DiagnosticStatus.WARN
            status.message = "; ".join(silent)
        else:
            status.level = DiagnosticStatus.OK
            status.message = self._message or "ok"
        if self._problems:
            worst = max(level for level, _ in self._problems.values())
            if status.level < worst:
                status.level = worst
            ok = status.message in ("ok", "")
            status.message = "; ".join(m for _, m in self._problems.values()) + ("" if ok else "; " + status.message)
        self._last_bad = n_bad
        status.values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
        status.values += [KeyValue(key=k, value=v) for k, v in self._extra.items()]
        if self._stats.gap_counters:
            status.values.append(KeyValue(key="loss_tracking", value=(
                "on" if not paused else "paused (not exactly one publisher): " + ", ".join(paused))))
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.status = [status]
        self._pub.publish(msg)
