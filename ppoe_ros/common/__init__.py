"""Shared helpers of the ``ppoe_ros`` nodes: parameters, counters, diagnostics, QoS, conversions.

Every node of the package is thin (parse, call :mod:`ppoe_core`, publish) and uses
the same pieces from here:

* :class:`ParamSpec` + :func:`declare_parameters`: ROS parameters declared with a
  descriptor (description, unit, range, read-only) and validated; a bad value is
  refused with the reason, both at start-up (:class:`~ppoe_core.errors.ModelConfigError`
  naming node and parameter) and on a later ``set_parameters`` call.
* :class:`NodeStats`: counters (``received``, ``published``, ``bad``, ...) and
  throttled logging of bad messages, naming the topic and the reason.
* :class:`DiagnosticsPublisher`: the counters on ``/diagnostics`` once per period
  (steady-clock timer, so it also runs while a replayed ``/clock`` is paused).
* :func:`guarded`: wraps a subscription callback so that a bad message is logged,
  counted and dropped while the node keeps running.
* QoS profiles (:func:`sensor_qos`, :data:`LATCHED_QOS`, :func:`reliable_qos`) and
  message <-> numpy conversions, among them :func:`pose_cov_stamped_msg` which fills
  a ``PoseWithCovarianceStamped`` with a covariance already in the ROS convention
  (CONTRACT.md section 2, ``cov_ros``).
* :func:`run_node`: the standard ``main()`` of a node.

This module imports rclpy and ROS message packages: it is ``ppoe_ros`` only,
never imported by :mod:`ppoe_core`.
"""

from __future__ import annotations

import functools
import importlib
import math
import sys
import time
import traceback
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np
import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseWithCovarianceStamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from ppoe_core import lie
from ppoe_core.errors import ModelConfigError, PpoeError

__all__ = [
    "ParamSpec",
    "declare_parameters",
    "NodeStats",
    "DiagnosticsPublisher",
    "guarded",
    "take_robot_description",
    "sensor_qos",
    "reliable_qos",
    "LATCHED_QOS",
    "stamp_to_ns",
    "ns_to_stamp",
    "pose_msg_from_matrix",
    "matrix_from_pose_msg",
    "pose_cov_stamped_msg",
    "pose_cov_from_msg",
    "cov_ros_to_msg_array",
    "wrench_to_numpy",
    "joint_positions",
    "run_node",
    "check_positive",
    "check_nonnegative",
    "check_nonempty",
    "check_length",
    "mapping_get",
    "message_class",
]


# --------------------------------------------------------------------------- QoS


def sensor_qos(depth: int = 100) -> QoSProfile:
    """Sensor-data QoS (best effort, volatile, keep last ``depth``) for high-rate inputs.

    Same policies as ``rclpy.qos.qos_profile_sensor_data`` but with a deeper
    history (its default of 5 drops messages of a 1 kHz topic as soon as one
    callback is late by 5 ms).  A best-effort subscription matches both reliable
    and best-effort publishers.
    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def reliable_qos(depth: int = 100) -> QoSProfile:
    """Reliable, volatile, keep last ``depth``: the default for the nodes' outputs."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


#: Transient-local ("latched") QoS of ``/robot_description``, as robot_state_publisher uses.
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


# ---------------------------------------------------------------------- parameters

Checker = Callable[[Any], "str | None"]

_PTYPE_OF_PYTHON = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
}
_RCLPY_TYPE = {
    ParameterType.PARAMETER_BOOL: Parameter.Type.BOOL,
    ParameterType.PARAMETER_INTEGER: Parameter.Type.INTEGER,
    ParameterType.PARAMETER_DOUBLE: Parameter.Type.DOUBLE,
    ParameterType.PARAMETER_STRING: Parameter.Type.STRING,
    ParameterType.PARAMETER_BOOL_ARRAY: Parameter.Type.BOOL_ARRAY,
    ParameterType.PARAMETER_INTEGER_ARRAY: Parameter.Type.INTEGER_ARRAY,
    ParameterType.PARAMETER_DOUBLE_ARRAY: Parameter.Type.DOUBLE_ARRAY,
    ParameterType.PARAMETER_STRING_ARRAY: Parameter.Type.STRING_ARRAY,
}


@dataclass(frozen=True)
class ParamSpec:
    """One ROS parameter of a node.

    Parameters
    ----------
    name : str
        Parameter name (``a.b`` for nested YAML keys).
    default : bool | int | float | str | list
        Default value; with ``ptype`` unset its Python type gives the parameter type
        (a list needs ``ptype``, because an empty list has no element type).
    description : str
        Meaning of the parameter; the unit is appended in the descriptor.
    unit : str
        Unit ("N", "s", "m", "" for none).
    ptype : int | None
        ``rcl_interfaces.msg.ParameterType`` constant; inferred from ``default`` when None.
    check : callable or None
        ``check(value) -> reason | None``; a returned reason refuses the value.
    read_only : bool
        Refuse changes after start-up (structure parameters: topics, frames, files).
    min_value, max_value : float | None
        Inclusive range, put into the descriptor and checked.
    """

    name: str
    default: Any
    description: str
    unit: str = ""
    ptype: int | None = None
    check: Checker | None = None
    read_only: bool = True
    min_value: float | None = None
    max_value: float | None = None

    def parameter_type(self) -> int:
        """The ``ParameterType`` constant of this parameter."""
        if self.ptype is not None:
            return self.ptype
        for py_type, ptype in _PTYPE_OF_PYTHON.items():
            if type(self.default) is py_type:
                return ptype
        raise TypeError(f"ParamSpec '{self.name}': give ptype for default {self.default!r}")

    def descriptor(self) -> ParameterDescriptor:
        """The descriptor shown by ``ros2 param describe``."""
        ptype = self.parameter_type()
        text = self.description + (f" [{self.unit}]" if self.unit else "")
        desc = ParameterDescriptor(
            name=self.name, type=ptype, description=text, read_only=self.read_only
        )
        if self.min_value is not None or self.max_value is not None:
            lo = -math.inf if self.min_value is None else self.min_value
            hi = math.inf if self.max_value is None else self.max_value
            constraint = f"{lo} <= value <= {hi}"
            desc.additional_constraints = constraint
            if ptype == ParameterType.PARAMETER_DOUBLE and math.isfinite(lo) and math.isfinite(hi):
                desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi))]
            elif ptype == ParameterType.PARAMETER_INTEGER and math.isfinite(lo) and math.isfinite(hi):
                desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi))]
        return desc

    def validate(self, value: Any) -> str | None:
        """Reason why ``value`` is refused, or None when it is fine."""
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be finite, got {value}"
        if self.min_value is not None and value < self.min_value:
            return f"must be >= {self.min_value}, got {value}"
        if self.max_value is not None and value > self.max_value:
            return f"must be <= {self.max_value}, got {value}"
        if self.check is not None:
            return self.check(value)
        return None


def check_positive(value: Any) -> str | None:
    """Checker: value > 0."""
    return None if value > 0 else f"must be > 0, got {value}"


def check_nonnegative(value: Any) -> str | None:
    """Checker: value >= 0."""
    return None if value >= 0 else f"must be >= 0, got {value}"


def check_nonempty(value: Any) -> str | None:
    """Checker: a non-empty string / list."""
    return None if len(value) > 0 else "must not be empty"


def check_length(*lengths: int) -> Checker:
    """Checker factory: a list of one of the given lengths (e.g. ``check_length(0, 6, 36)``)."""

    def _check(value: Any) -> str | None:
        if len(value) in lengths:
            return None
        return f"must have {' or '.join(map(str, lengths))} elements, got {len(value)}"

    return _check


def declare_parameters(
    node: Node,
    specs: Sequence[ParamSpec],
    on_change: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Declare and validate the node's parameters; return ``{name: value}``.

    Values come from ``--ros-args -p`` / ``--params-file`` overrides, else the
    spec's default.  A later ``set_parameters`` call is refused with the reason
    when a value fails its check (or the parameter is read-only); accepted
    changes of writable parameters are passed to ``on_change({name: value})``,
    which may refuse them by raising :class:`PpoeError` (its message is the reason).

    Raises
    ------
    ModelConfigError
        A start-up value fails its check; the message names node, parameter and reason.
    """
    values: dict[str, Any] = {}
    by_name = {s.name: s for s in specs}
    enforce_read_only: set[str] = set()  # read-only enforced by the callback (typed list defaults)
    node_name = node.get_fully_qualified_name()
    for spec in specs:
        ptype = spec.parameter_type()
        desc = spec.descriptor()
        try:
            if isinstance(spec.default, (list, tuple)):
                # A list default may be empty (no element type): declare statically typed,
                # then fill in the default when no override gave a value.  A read-only
                # descriptor would refuse that fill-in, so read-only is enforced below.
                if desc.read_only:
                    desc.read_only = False
                    enforce_read_only.add(spec.name)
                value = node.declare_parameter(spec.name, _RCLPY_TYPE[ptype], desc).value
                if value is None:
                    value = list(spec.default)
                    node.set_parameters([Parameter(spec.name, _RCLPY_TYPE[ptype], value)])
                value = list(value)
            else:
                value = node.declare_parameter(spec.name, spec.default, desc).value
        except PpoeError:
            raise
        except Exception as exc:  # rclpy raises its own types for an override of the wrong type
            raise ModelConfigError(f"node {node_name}: parameter '{spec.name}': {exc}") from None
        reason = spec.validate(value)
        if reason is not None:
            raise ModelConfigError(f"node {node_name}: parameter '{spec.name}' {reason}")
        values[spec.name] = value

    def _on_set(params: list[Parameter]) -> SetParametersResult:
        changed: dict[str, Any] = {}
        for p in params:
            spec = by_name.get(p.name)
            if spec is None:
                continue
            if p.name in enforce_read_only:
                return SetParametersResult(successful=False, reason=f"parameter '{p.name}' is read-only")
            reason = spec.validate(p.value)
            if reason is not None:
                return SetParametersResult(successful=False, reason=f"parameter '{p.name}' {reason}")
            changed[p.name] = p.value
        if changed and on_change is not None:
            try:
                on_change(changed)
            except PpoeError as exc:  # the node refuses the combination (e.g. release >= enter)
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(_on_set)
    return values


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
        self.counts: dict[str, int] = {k: 0 for k in keys}
        self.throttle_sec = float(throttle_sec)
        self._last_log: dict[tuple[str, str], float] = {}
        self._suppressed: dict[tuple[str, str], int] = {}
        self.last_reason: str = ""

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
                stats.error(topic, exc)
            return None

        return wrapper

    return deco


def take_robot_description(node: Node, params: Mapping[str, Any], stats: NodeStats,
                           set_model: Callable[[str, str], None],
                           on_message: Callable[[Any], None]) -> None:
    """Get the URDF as robot_state_publisher's consumers do.

    From the ``robot_description`` parameter when it is set (a bad URDF there is a start-up
    error: ``set_model`` raises), else by subscribing ``robot_description_topic`` with
    :data:`LATCHED_QOS`; a bad URDF on the topic is counted by :func:`guarded` and the node
    keeps its previous model.
    """
    if params["robot_description"]:
        set_model(params["robot_description"], "parameter robot_description")
        return
    from std_msgs.msg import String

    topic = params["robot_description_topic"]
    node.create_subscription(String, topic, guarded(stats, topic)(on_message), LATCHED_QOS)
    node.get_logger().info(f"waiting for the URDF on {topic}")


class DiagnosticsPublisher:
    """Publish a node's :class:`NodeStats` on ``/diagnostics`` every ``period`` seconds.

    Level WARN while bad messages or errors arrived in the last period, else OK
    (or the level set by :meth:`set_status`).  The timer runs on the steady clock.
    """

    def __init__(self, node: Node, stats: NodeStats, period: float = 1.0,
                 topic: str = "/diagnostics", hardware_id: str = "") -> None:
        self._node = node
        self._stats = stats
        self._pub = node.create_publisher(DiagnosticArray, topic, reliable_qos(10))
        self._name = f"{node.get_name()}"
        self._hardware_id = hardware_id
        self._last_bad = 0
        self._level: bytes | None = None
        self._message = ""
        self._extra: dict[str, str] = {}
        self._timer = node.create_timer(
            float(period), self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME)
        )

    def set_status(self, level: bytes | None, message: str, **extra: Any) -> None:
        """Override level/message (``DiagnosticStatus.OK/WARN/ERROR``; None = automatic) and add values."""
        self._level = level
        self._message = message
        self._extra.update({k: str(v) for k, v in extra.items()})

    def publish(self) -> None:
        """Publish one ``DiagnosticArray`` now."""
        counts = self._stats.counts
        n_bad = counts.get("bad", 0) + counts.get("errors", 0)
        status = DiagnosticStatus()
        status.name = self._name
        status.hardware_id = self._hardware_id
        if self._level is not None:
            status.level = self._level
            status.message = self._message
        elif n_bad > self._last_bad:
            status.level = DiagnosticStatus.WARN
            status.message = f"{n_bad - self._last_bad} bad messages; last: {self._stats.last_reason}"
        else:
            status.level = DiagnosticStatus.OK
            status.message = self._message or "ok"
        self._last_bad = n_bad
        status.values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
        status.values += [KeyValue(key=k, value=v) for k, v in self._extra.items()]
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.status = [status]
        self._pub.publish(msg)


# --------------------------------------------------------------------- conversions


def stamp_to_ns(stamp: TimeMsg) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> TimeMsg:
    """Integer nanoseconds -> ``builtin_interfaces/Time``."""
    ns = int(ns)
    return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def pose_msg_from_matrix(T: np.ndarray, out: Pose | None = None) -> Pose:
    """Homogeneous ``(4, 4)`` -> ``geometry_msgs/Pose`` (quaternion x, y, z, w)."""
    pose = Pose() if out is None else out
    q = lie.quat_from_matrix(np.asarray(T, dtype=float)[:3, :3])
    p = pose.position
    p.x, p.y, p.z = (float(v) for v in T[:3, 3])
    o = pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return pose


def matrix_from_pose_msg(pose: Pose) -> np.ndarray:
    """``geometry_msgs/Pose`` -> homogeneous ``(4, 4)``; the quaternion is normalised."""
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
    nq = np.linalg.norm(q)
    if not np.isfinite(nq) or nq < 1e-9:
        raise ValueError(f"pose quaternion {q.tolist()} is not a rotation")
    T = np.eye(4)
    T[:3, :3] = lie.matrix_from_quat(q / nq)
    T[:3, 3] = (pose.position.x, pose.position.y, pose.position.z)
    return T


def cov_ros_to_msg_array(cov_ros: np.ndarray) -> list[float]:
    """A ``(6, 6)`` covariance (ROS convention, order x y z rx ry rz) -> 36 row-major floats."""
    cov = np.asarray(cov_ros, dtype=float)
    if cov.shape != (6, 6):
        raise ValueError(f"covariance must be 6x6, got shape {cov.shape}")
    return cov.reshape(36).tolist()


def pose_cov_stamped_msg(T_parent_child: np.ndarray, cov_ros: np.ndarray, stamp: TimeMsg | int,
                         frame_id: str) -> PoseWithCovarianceStamped:
    """Build a ``PoseWithCovarianceStamped``.

    Parameters
    ----------
    T_parent_child : (4, 4)
        Pose of the child frame in ``frame_id`` (the parent).
    cov_ros : (6, 6)
        Covariance in the ROS convention of CONTRACT.md sec. 2: order
        ``(x, y, z, rot_x, rot_y, rot_z)``, translation and small rotation both in
        the axes of ``frame_id``.  Convert a local (right-perturbation) covariance
        ``cov_child`` with ``lie.cov_local_to_ros(T_parent_child, cov_child)`` first.
    stamp : builtin_interfaces/Time or int
        Header stamp (int = nanoseconds).
    frame_id : str
        Parent frame.
    """
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = ns_to_stamp(stamp) if isinstance(stamp, (int, np.integer)) else stamp
    msg.header.frame_id = frame_id
    pose_msg_from_matrix(T_parent_child, msg.pose.pose)
    msg.pose.covariance = cov_ros_to_msg_array(cov_ros)
    return msg


def pose_cov_from_msg(msg: PoseWithCovarianceStamped) -> tuple[np.ndarray, np.ndarray, int, str]:
    """``PoseWithCovarianceStamped`` -> ``(T (4,4), cov_ros (6,6), stamp_ns, frame_id)``.

    ``cov_ros`` is in the ROS convention (CONTRACT.md sec. 2, axes of ``frame_id``).
    """
    T = matrix_from_pose_msg(msg.pose.pose)
    cov_ros = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)
    return T, cov_ros, stamp_to_ns(msg.header.stamp), msg.header.frame_id


def wrench_to_numpy(msg: Any) -> np.ndarray:
    """``geometry_msgs/WrenchStamped`` or ``Wrench`` -> ``(6,)`` ``[fx, fy, fz, tx, ty, tz]``."""
    w = getattr(msg, "wrench", msg)
    return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z])


def joint_positions(msg: Any, topic: str = "/joint_states") -> dict[str, float]:
    """``sensor_msgs/JointState`` -> ``{name: position}``.

    Raises
    ------
    ValueError
        ``name`` and ``position`` differ in length, or a name repeats (message names the topic).
    """
    names = msg.name
    pos = msg.position
    if len(names) != len(pos):
        raise ValueError(f"{topic}: {len(names)} names but {len(pos)} positions")
    out = dict(zip(names, (float(p) for p in pos)))
    if len(out) != len(names):
        repeated = sorted(n for n in set(names) if list(names).count(n) > 1)
        raise ValueError(f"{topic}: repeated joint names {repeated}")
    return out


# ---------------------------------------------------------------------------- main


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """The standard ``main()`` of a node: init, build, spin, shut down; returns the exit code.

    Parameters
    ----------
    factory : callable
        Builds the node (after ``rclpy.init``).  A :class:`PpoeError` from it (bad
        parameter, unreadable model file) is printed as one line and gives exit code 2.
    args : sequence of str or None
        Command line (``sys.argv`` when None), including ``--ros-args``.

    Notes
    -----
    A ``SingleThreadedExecutor``: rclpy's experimental ``EventsExecutor`` (Jazzy) received
    no messages and spun at 100 % CPU after SIGTERM in a trial here, so it is not offered.
    """
    rclpy.init(args=list(sys.argv if args is None else args))
    node: Node | None = None
    code = 0
    try:
        node = factory()
        ex = rclpy.executors.SingleThreadedExecutor()
        ex.add_node(node)
        ex.spin()
    except PpoeError as exc:
        print(f"[FATAL] {exc}", file=sys.stderr, flush=True)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        if node is not None:
            try:
                node.destroy_node()
            except Exception:  # noqa: BLE001 - best effort during shutdown
                pass
        rclpy.try_shutdown()
    return code


def mapping_get(d: Mapping[str, Any] | None, *keys: str, default: Any = None) -> Any:
    """``d[k1][k2]...`` or ``default`` when any level is missing (for optional YAML sections)."""
    cur: Any = d
    for k in keys:
        if not isinstance(cur, Mapping) or k not in cur:
            return default
        cur = cur[k]
    return cur


def message_class(type_name: str) -> type:
    """ROS message class from its type name (``"sensor_msgs/msg/JointState"`` or ``"sensor_msgs/JointState"``).

    Raises
    ------
    PpoeError
        Malformed name, or the message package is not installed (message names the type).
    """
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise PpoeError(f"message type '{type_name}' is not of the form package/msg/Name")
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f"{pkg}.{kind}")
        cls = getattr(module, name)
    except (ImportError, AttributeError):
        raise PpoeError(
            f"message type '{type_name}' is not installed (no Python module {pkg}.{kind}.{name})") from None
    return cls
