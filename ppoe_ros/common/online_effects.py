"""Online effects live: the ROS side of :class:`ppoe_core.estimation.online_effects.OnlineEffects` and its drift
monitor (docs/online.md).

:class:`OnlineEffectsHook` runs the core filter inside a node (the fusion node, or :class:`OnlineEffectsNode`
alone).  It subscribes the model's tracker topics (``PointStamped``, ``trackers`` of the model YAML) and
accelerometers (``/imu/<name>``, ``sensor_msgs/Imu``, its ``imus``), ``online_temperature_topic``
(``sensor_msgs/Temperature``) and ``online_joint_states_topic`` (merged per joint, as the kinematics node does);
every other measurement of the node reaches it through :meth:`OnlineEffectsHook.measure` (tag pixels, contact planes,
the fusion node's ``sources``: 6D poses, points, accelerometers) and the cameras' intrinsics through
:meth:`OnlineEffectsHook.camera_info`.  All go through :class:`~ppoe_core.estimation.online_inputs.OnlineInputs`,
the code ``ppoe evaluate --online`` replays.  After each update the estimate is published on
``online_estimates_topic`` as a ``std_msgs/Float64MultiArray``:

* ``layout.data_offset = 1``; ``data[0]`` is the stamp of the update [s] (the measurement's ``header.stamp``);
* then a P x (P + 1) row-major array, ``layout.dim[0]`` (label = the parameter labels
  ``<name>@<location>/<parameter>`` joined by ``,``; size P; stride P (P + 1)) and ``layout.dim[1]`` (label
  ``mean,covariance``; size P + 1; stride P + 1): row ``i`` is ``[theta_i, P_i0 ... P_i(P-1)]`` in the
  parameters' units (rad, 1/K, rad/(N m), m).

**Drift.**  When the drift monitor alarms, the event is logged, ``/diagnostics`` turns WARN naming the effects that
explain the drift with their held-out gain (until the monitor is quiet for a window), and the named effects'
estimate is published on ``online_drift_topic`` in the same layout (``data[0]`` = the alarm's stamp; P = 0 when no
candidate explains it).  With ``online_monitor_add`` the named effects join the state.

:meth:`OnlineEffectsHook.correct_prior` moves a kinematics prior (the static model's ``T_base_tool``) to the
online estimate, with the parameters' covariance added; :meth:`OnlineEffectsHook.write_model` writes the model
YAML with the current estimate (``online_model_out``, at every ``online_write_period`` and at shutdown).
Bad input (a tracker frame without registration, an IMU frame that is not its link, NaN, a changed
``camera_info``, a tag seen by two cameras at once, a temperature stream that stopped) is counted and logged
(throttled); the node keeps running.

``python -m ppoe_ros.common.online_effects --ros-args -p model_file:=MODEL.yaml ...`` runs the hook alone
(:class:`OnlineEffectsNode`, which also subscribes tag observations, camera_info, contact planes and ``sources``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from geometry_msgs.msg import PointStamped
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState, Temperature
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from ppoe_core.analysis.drift_naming import make_monitor
from ppoe_core.analysis.evaluate.online_config import MONITOR_PARAMS, settings_from_params
from ppoe_core.errors import ModelConfigError, PpoeError
from ppoe_core.estimation.online_effects import OnlineEffects, parse_online_config
from ppoe_core.estimation.online_inputs import IMU_TOPIC, OnlineInputs, OnlineMeasurement, OnlineStep
from ppoe_core.estimation.source_updater import GravityMeasurement, PointMeasurement
from ppoe_core.estimation.sources import complete_source
from ppoe_core.robot.yaml_io import read_yaml_mapping
from ppoe_ros.common.conversions import stamp_to_ns
from ppoe_ros.common.diagnostics import DiagnosticsPublisher, NodeStats
from ppoe_ros.common.losses import counted_subscription
from ppoe_ros.common.params import ParamSpec, check_nonempty, declare_parameters
from ppoe_ros.common.qos import reliable_qos
from ppoe_ros.common.runner import run_node, take_robot_description

__all__ = ["ONLINE_PARAMS", "OnlineEffectsHook", "OnlineEffectsNode", "drift_msg", "estimates_msg",
           "estimates_from_msg", "main"]

ONLINE_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("online_enable", False, "track drifting effects online (docs/online.md)"),
    ParamSpec("online_effects", [], "tracked effects '<name>:<location>' (base_tilt, thermal_growth, "
              "gravity_compliance, mount_bending, camera_extrinsics, joint_offset, link_error); empty = the model's "
              "trackable effects and the base tilt when a stream sees it", ptype=ParameterType.PARAMETER_STRING_ARRAY),
    ParamSpec("online_process_noise", [], "random-walk intensity, one per online_effects entry, in the parameter's "
              "unit per sqrt(s) (base_tilt rad, thermal_growth 1/K, gravity_compliance rad/(N m), camera_extrinsics "
              "m and rad); empty = defaults", unit="unit/sqrt(s)", ptype=ParameterType.PARAMETER_DOUBLE_ARRAY),
    ParamSpec("online_initial_sigma", [], "prior 1-sigma of a parameter the model does not hold (and after a jump), "
              "one per entry; empty = defaults", unit="parameter unit", ptype=ParameterType.PARAMETER_DOUBLE_ARRAY),
    ParamSpec("online_thermal_reference", 20.0, "temperature at which a tracked thermal_growth is zero", unit="degC"),
    ParamSpec("online_jump_probability", 1e-6, "NIS tail probability above which a measurement re-opens the "
              "parameters' covariance (a placement change); 0 = off", min_value=0.0, max_value=0.5),
    ParamSpec("online_temperature_topic", "temperature", "sensor_msgs/Temperature for thermal_growth"),
    ParamSpec("online_temperature_timeout", 10.0, "a temperature older than this at a measurement is stale "
              "(counted as online_temperature_stale, logged); 0 = off", unit="s", min_value=0.0, max_value=1e6),
    ParamSpec("online_joint_states_topic", "joint_states", "joint states of the measurements", check=check_nonempty),
    ParamSpec("online_reorder_window", 0.1, "a measurement waits for a joint state this long after its stamp, so that "
              "the measurements of several topics are taken in stamp order (as ppoe evaluate --online takes them)",
              unit="s", min_value=0.0, max_value=60.0),
    ParamSpec("online_joint_max_age", 0.5, "a joint value a split message lacks is held this long; 0 = no limit",
              unit="s", min_value=0.0, max_value=3600.0),
    ParamSpec("online_estimates_topic", "ppoe/online_effects", "estimates out (std_msgs/Float64MultiArray, layout "
              "in docs/online.md)", check=check_nonempty),
    ParamSpec("online_drift_topic", "ppoe/online_drift", "at each drift alarm: the named effects' estimate "
              "(std_msgs/Float64MultiArray, the estimates' layout)", check=check_nonempty),
    ParamSpec("online_model_out", "", "write the model YAML with the current estimate here; empty = never"),
    ParamSpec("online_write_period", 0.0, "write online_model_out this often; 0 = only at shutdown", unit="s",
              min_value=0.0, max_value=1e6),
) + tuple(ParamSpec(name, default, meaning, min_value=0.0 if not isinstance(default, bool) else None)
          for name, (_, default, meaning) in MONITOR_PARAMS.items())

_COUNTS = ("online_points", "online_jumps", "online_waiting", "online_no_joints", "online_dropped_pending",
           "online_no_model", "online_published", "online_bad", "online_drift_alarms", "online_camera_info_changed",
           "online_tags_seen_twice", "online_temperature_stale", "online_unknown_tag_points")


def _array_msg(stamp_s: float, labels: list[str], theta: np.ndarray, P: np.ndarray) -> Float64MultiArray:
    n = len(labels)
    msg = Float64MultiArray()
    msg.layout.data_offset = 1
    msg.layout.dim = [MultiArrayDimension(label=",".join(labels), size=n, stride=n * (n + 1)),
                      MultiArrayDimension(label="mean,covariance", size=n + 1, stride=n + 1)]
    msg.data = [float(stamp_s)] + np.concatenate([np.asarray(theta, float).reshape(n, 1),
                                                  np.asarray(P, float).reshape(n, n)], axis=1).ravel().tolist()
    return msg


def estimates_msg(filt: OnlineEffects, stamp_s: float) -> Float64MultiArray:
    """The estimate as ``Float64MultiArray`` (module docstring: stamp in the padding, P x (P + 1))."""
    return _array_msg(stamp_s, filt.labels, filt.theta, filt.P)


def drift_msg(event: Any) -> Float64MultiArray:
    """A drift event's named effects (their window estimate and covariance) in the estimates' layout."""
    n = event.naming
    named = n.named if n is not None else []
    labels = [f"{e.key}/{p}" for e in named for p in e.effect.param_names]
    theta = np.concatenate([e.effect.params for e in named]) if named else np.zeros(0)
    P = np.zeros((len(labels), len(labels)))
    if named and n.cov is not None:
        k = n.cov.shape[0] - len(labels)
        P = n.cov[k:, k:]
    return _array_msg(event.stamp, labels, theta, P)


def estimates_from_msg(msg: Any) -> tuple[float, list[str], np.ndarray, np.ndarray]:
    """Inverse of :func:`estimates_msg`: ``(stamp [s], labels, theta (P,), P (P, P))``."""
    P = int(msg.layout.dim[0].size)
    arr = np.asarray(msg.data[msg.layout.data_offset:], dtype=float).reshape(P, P + 1)
    labels = msg.layout.dim[0].label.split(",") if P else []
    return float(msg.data[0]), labels, arr[:, 0].copy(), arr[:, 1:].copy()


class OnlineEffectsHook:
    """The online filter inside ``node`` (module docstring).

    Parameters
    ----------
    node : rclpy Node
    params : mapping
        The node's values of :data:`ONLINE_PARAMS` (declared by the node with its own parameters), and its
        ``sources`` blocks if it has them.
    stats : NodeStats
        The node's counters; the hook adds ``online_*`` counters.
    model_file : str
        The model YAML (written back with the estimate by :meth:`write_model`).
    diagnostics : DiagnosticsPublisher, optional
        Where a drift alarm turns WARN.
    """

    def __init__(self, node: Node, params: Mapping[str, Any], stats: NodeStats, model_file: str,
                 diagnostics: DiagnosticsPublisher | None = None) -> None:
        self.node, self.p, self.stats, self.model_file = node, dict(params), stats, model_file
        self.diagnostics = diagnostics
        for k in _COUNTS:
            stats.counts.setdefault(k, 0)
        stats.warn_keys |= {"online_bad", "online_camera_info_changed", "online_tags_seen_twice",
                            "online_temperature_stale"}
        self.settings = settings_from_params(self.p, f"node {node.get_fully_qualified_name()}")
        self.filter: OnlineEffects | None = None
        self.inputs: OnlineInputs | None = None
        self._subscribed: set[str] = set()
        self._notes = 0
        self.pub = node.create_publisher(Float64MultiArray, self.p["online_estimates_topic"], reliable_qos(1000))
        self.drift_pub = node.create_publisher(Float64MultiArray, self.p["online_drift_topic"], reliable_qos(100))
        qos = reliable_qos(1000)
        counted_subscription(node, stats, JointState, self.p["online_joint_states_topic"], self._joint_state, qos)
        if self.p["online_temperature_topic"]:
            counted_subscription(node, stats, Temperature, self.p["online_temperature_topic"], self._temperature, qos)
        raw = read_yaml_mapping(model_file, "model file")  # tracker topics now: inputs are subscribed at start-up
        topics = [str(t.get("topic", "/ground_truth/point")) for t in (raw.get("trackers") or [])]
        for topic in topics + (["/ground_truth/point"] if raw.get("tracker") else []):
            if topic not in self._subscribed:
                self._subscribed.add(topic)
                counted_subscription(node, stats, PointStamped, topic,
                                     lambda msg, topic=topic: self._point(msg, topic), qos)
        for name in raw.get("imus") or {}:
            self._subscribed.add(f"{IMU_TOPIC}{name}")
            counted_subscription(node, stats, Imu, f"{IMU_TOPIC}{name}",
                                 lambda msg, name=str(name): self._point(msg, f"{IMU_TOPIC}{name}", name), qos)
        if self.p["online_write_period"] > 0 and self.p["online_model_out"]:
            node.create_timer(self.p["online_write_period"], self.write_model)
        from ppoe_ros.common.services import add_save_model_service

        add_save_model_service(node, self.write_model, self.p["online_model_out"])  # ~/save_model

    def set_model(self, model: Any) -> None:
        """Build the filter for ``model`` (the diagnosed PPOEModel), its input alignment and drift monitor."""
        st = self.settings
        for s in st.sources:
            s.off = complete_source(s, model)
        self.filter = OnlineEffects(model, parse_online_config(st.entries, model, sources=st.sources),
                                    st.jump_probability)
        monitor = make_monitor(st.monitor, st.naming) if st.monitor is not None else None
        self.inputs = OnlineInputs(self.filter, int(self.p["online_joint_max_age"] * 1e9), monitor=monitor,
                                   temperature_timeout_ns=int(round(st.temperature_timeout * 1e9)),
                                   reorder_ns=int(round(self.p["online_reorder_window"] * 1e9)))
        try:  # load the compiled kernels now, not while the first measurements wait (messages would pile up)
            self.filter.tool_pose({j: 0.0 for j in model.joint_names}, model.robot.root, list(model.robot.links)[-1])
        except PpoeError:
            pass
        self.node.get_logger().info(f"online effects: tracking {self.filter.labels} from "
                                    f"{sorted(self._subscribed)} and the node's measurements; drift monitor "
                                    + ("off" if monitor is None else f"on ({monitor.settings})"))

    # ---------------------------------------------------------------- callbacks
    def _joint_state(self, msg: JointState) -> None:
        if self.inputs is not None:
            self._publish(self.inputs.joint_state(msg.name, msg.position, stamp_to_ns(msg.header.stamp)))

    def _temperature(self, msg: Temperature) -> None:
        if self.inputs is not None:
            self._publish(self.inputs.temperature(stamp_to_ns(msg.header.stamp), msg.temperature))

    def _point(self, msg: Any, topic: str, imu: str | None = None) -> None:
        """A tracker point (``PointStamped``) or an accelerometer message (``Imu``, topic ``/imu/<name>``)."""
        if self.inputs is None:
            self.stats.inc("online_no_model")
            return
        v = msg.linear_acceleration if imu is not None else msg.point
        m = OnlineMeasurement(stamp_to_ns(msg.header.stamp), topic, msg.header.frame_id,
                              np.array([v.x, v.y, v.z], dtype=float), imu)
        self._publish(self.inputs.measurement(m))

    def measure(self, m: Any) -> None:
        """A measurement of the node (:class:`~ppoe_core.estimation.corrections.Measurement`: tags, contact, a
        source's point / pose / accelerometer payload).  A point or accelerometer source on a topic the hook
        subscribes itself (the model's trackers and imus) is left out: the hook has it already."""
        if self.inputs is None:
            self.stats.inc("online_no_model")
            return
        topic, _, frame = str(m.source).partition(" [")
        if isinstance(m.payload, (PointMeasurement, GravityMeasurement)) and topic in self._subscribed:
            return
        om = OnlineMeasurement(int(round(m.stamp * 1e9)), topic, frame[:-1] if frame else "", payload=m.payload)
        try:  # never into the caller: the fusion node hands the same measurement to its pipeline next
            self._publish(self.inputs.measurement(om))
        except Exception as exc:  # noqa: BLE001 - counted and logged, the node's measurement goes on
            self.stats.bad(str(m.source), f"online effects: {exc}", kind="online_bad")

    def camera_info(self, frame: str, K: Any, D: Any) -> None:
        """A camera's ``camera_info`` (a change mid-run is counted and logged)."""
        if self.inputs is not None:
            try:
                self.inputs.camera_info(frame, K, D)
            except Exception as exc:  # noqa: BLE001 - counted and logged, the node's camera_info goes on
                self.stats.bad(frame, f"online effects: camera_info: {exc}", kind="online_bad")
            self._sync()

    def _publish(self, steps: list[OnlineStep]) -> None:
        """The estimate after each step, the drift events; the counters synced with the alignment's."""
        assert self.inputs is not None and self.filter is not None
        for step in steps:
            self.stats.inc("online_points")
            self.pub.publish(_array_msg(step.stamp_ns * 1e-9, list(step.labels), step.theta, step.P))
            self.stats.inc("online_published")
            if step.drift is not None:
                self._drift(step.drift)
        self._sync()

    def _drift(self, event: Any) -> None:
        text = event.describe()
        self.stats.inc("online_drift_alarms")
        self.node.get_logger().warning(f"online effects: {text}")
        self.drift_pub.publish(drift_msg(event))
        if self.diagnostics is not None:
            self.diagnostics.set_problem("online_drift", text)

    def _sync(self) -> None:
        assert self.inputs is not None
        c, s = self.inputs.counts, self.stats.counts
        s["online_jumps"], s["online_waiting"] = c.jumps, c.waiting
        s["online_no_joints"], s["online_dropped_pending"] = c.no_joints, c.dropped_pending
        for key in ("bad", "camera_info_changed", "tags_seen_twice", "temperature_stale", "unknown_tag_points"):
            s[f"online_{key}"] = getattr(c, key)
        log = self.node.get_logger()
        for kind, note in self.inputs.notes[self._notes:]:
            self.stats.last_reason = f"online effects: {note}"
            log.warning(f"online effects ({kind}): {note} (the node keeps running)")
        self._notes = len(self.inputs.notes)
        mon = self.inputs.monitor
        if self.diagnostics is not None and mon is not None and not mon.in_alarm:
            self.diagnostics.set_problem("online_drift", None)

    # ---------------------------------------------------------------- outputs
    def correct_prior(self, stamp_ns: int, T_base_tool: np.ndarray, cov_tool: np.ndarray, base: str,
                      tool: str) -> tuple[np.ndarray, np.ndarray]:
        """The prior moved to the online estimate (:meth:`OnlineInputs.correct_prior
        <ppoe_core.estimation.online_inputs.OnlineInputs.correct_prior>`); unchanged while there is no model."""
        if self.inputs is None:
            return T_base_tool, cov_tool
        return self.inputs.correct_prior(stamp_ns, T_base_tool, cov_tool, base, tool)

    def write_model(self) -> Path | None:
        """Write the model YAML with the current estimate to ``online_model_out`` (None when off or no model)."""
        out = self.p["online_model_out"]
        if not out or self.filter is None:
            return None
        raw = read_yaml_mapping(self.model_file, "model file")
        text = ("# written by the online effects of " + self.node.get_fully_qualified_name() + " (docs/online.md)\n"
                + yaml.safe_dump(self.filter.model_yaml(_plain(raw)), sort_keys=False, default_flow_style=None))
        Path(out).write_text(text)
        return Path(out)


def _plain(x: Any) -> Any:
    """Plain dict/list copy of a YAML mapping that remembers line numbers (for ``yaml.safe_dump``)."""
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


_NODE_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("model_file", "", "the diagnosed model YAML (required)", check=check_nonempty),
    ParamSpec("robot_description", "", "URDF XML; empty = take it from robot_description_topic"),
    ParamSpec("robot_description_topic", "robot_description", "latched std_msgs/String with the URDF",
              check=check_nonempty),
    ParamSpec("observations_topic", "tag_bearing/observations", "tag observations (PointCloud2); empty = off"),
    ParamSpec("camera_info_topic", "camera/camera_info", "CameraInfo: the focal lengths of the tag points"),
    ParamSpec("contact_topic", "contact/plane", "contact plane (PoseWithCovarianceStamped); empty = off"),
    ParamSpec("diagnostics_period", 1.0, "period of /diagnostics", unit="s", min_value=0.01, max_value=3600.0),
) + tuple(s for s in ONLINE_PARAMS if s.name != "online_enable")


class OnlineEffectsNode(Node):
    """The hook alone in a node (``online_effects_node``): every measurement kind + joints + temperature ->
    estimates and drift alarms."""

    def __init__(self, **kwargs: Any) -> None:
        from ppoe_ros.common.fusion_sources import SOURCES_PARAM, source_names, source_specs
        from ppoe_ros.common.online_inputs import subscribe_measurements

        super().__init__("online_effects_node", **kwargs)
        names = source_names(self)
        p = declare_parameters(self, _NODE_PARAMS + (SOURCES_PARAM,) + source_specs(names))
        self.p_topic = p["robot_description_topic"]
        self.stats = NodeStats(self, ("received", "published", "bad"))
        self.diagnostics = DiagnosticsPublisher(self, self.stats, p["diagnostics_period"])
        self.hook = OnlineEffectsHook(self, p, self.stats, p["model_file"], self.diagnostics)
        self.inputs = subscribe_measurements(self, p, names, self.stats, self.hook)
        self._urdf: str | None = None
        take_robot_description(self, p, self.stats, self._set_model, self._robot_description)

    def _set_model(self, urdf_xml: str, where: str) -> None:
        from ppoe_core.model.ppoe import PPOEModel

        try:
            model = PPOEModel.from_strings(urdf_xml, Path(self.hook.model_file), urdf_source=where)
            self.hook.set_model(model)
            self.inputs.set_model(model)
        except ModelConfigError as exc:
            raise ModelConfigError(f"{where}: {exc}") from None
        self._urdf = urdf_xml

    def _robot_description(self, msg: String) -> None:
        if msg.data != self._urdf:
            self._set_model(msg.data, f"topic {self.p_topic}")

    def destroy_node(self) -> None:
        self.hook.write_model()
        super().destroy_node()


def main(args: Any = None) -> int:
    """``python -m ppoe_ros.common.online_effects --ros-args -p model_file:=... [-p online_effects:=[...]]``."""
    return run_node(OnlineEffectsNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
