"""Every measurement kind live (issue 11 item 2): tracker points, 6D poses and accelerometers as sensor blocks of the
fusion node.

Offline: :class:`SourceUpdater` on each payload moves the tool pose toward the truth that generated the measurement,
a component mask drops the masked directions, a source's own gate is used, bad blocks are refused.  Live: the fusion
node started with a sensor block, fed priors + joint states + one simulated measurement of that kind through
topics; the fused pose moves toward the truth.  Bad input: an IMU message for a link the URDF lacks and a source
whose link is unknown are logged with topic and link, counted, and the node keeps running.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import CONFIG
from ppoe_core import PPOEModel, lie
from ppoe_core.errors import MeasurementError
from ppoe_core.estimation.corrections import Measurement
from ppoe_core.estimation.pipeline import make_updater
from ppoe_core.estimation.source_updater import (
    GravityMeasurement,
    PointMeasurement,
    PoseMeasurement,
    SelectedObservation,
    SourceUpdater,
    pose_from_xyz_rpy,
)
from ppoe_core.robot.tree import GRAVITY

ARM7_URDF = CONFIG / "robots" / "arm7.urdf"
ARM7_MODEL = CONFIG / "robots" / "arm7_model.yaml"
Q = {"joint_1": 0.3, "joint_2": -0.6, "joint_3": 0.2, "joint_4": 1.1, "joint_5": -0.4, "joint_6": 0.9,
     "joint_7": 0.1, "finger_left_joint": 0.01, "finger_right_joint": 0.01}
REFLECTOR = np.array([0.0, 0.0, 0.02])  # arm7_model.yaml tracker.xyz on tool0
T_BASE_TRACKER = pose_from_xyz_rpy([1.5, 0.2, 0.1, 0.0, 0.0, np.pi / 2])
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def arm7():
    model = PPOEModel.from_files(ARM7_URDF, ARM7_MODEL)
    T_prior, P_prior = model.fk(Q, "base_link", "tool0")
    T_true = model.sample(Q, "base_link", "tool0", n=1, rng=np.random.default_rng(7))[0]
    return model, T_prior, P_prior, T_true


def _tilt(T: np.ndarray) -> np.ndarray:
    """Up direction seen in the frame of ``T`` (what an accelerometer there measures, / g)."""
    return T[:3, :3].T @ UP


def _errors(T: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    return {
        "point": float(np.linalg.norm((T - T_true)[:3, :3] @ REFLECTOR + (T - T_true)[:3, 3])),
        "translation": float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])),
        "rotation": float(np.linalg.norm(lie.log(lie.inverse(T_true) @ T)[3:])),
        "tilt": float(np.arccos(np.clip(_tilt(T) @ _tilt(T_true), -1.0, 1.0))),
    }


def _payload(kind: str, T_true: np.ndarray, mask=None, gate=None):
    """A noise-free simulated measurement of ``T_true`` (base_link -> tool0) of one kind."""
    if kind == "point":
        p_tracker = lie.inverse(T_BASE_TRACKER) @ np.append(T_true[:3, :3] @ REFLECTOR + T_true[:3, 3], 1.0)
        return PointMeasurement("tool0", REFLECTOR, "tracker", p_tracker[:3], np.eye(3) * 0.0005**2,
                                T_BASE_TRACKER, mask, gate)
    if kind == "pose":
        return PoseMeasurement("tool0", "base_link", T_true, np.diag([1e-4] * 6) ** 2, None, mask, gate)
    return GravityMeasurement("tool0", GRAVITY * _tilt(T_true), np.eye(3) * 0.0004**2, UP, mask, gate)


#: which error each kind must shrink, and by how much at least
_SHRINKS = {"point": ("point", 0.2), "pose": ("translation", 0.2), "imu": ("tilt", 0.2)}


@pytest.mark.parametrize("kind", ["point", "pose", "imu"])
def test_source_updater_moves_the_tool_toward_the_truth(arm7, kind):
    model, T_prior, P_prior, T_true = arm7
    updater = make_updater(model, "base_link", "tool0", cls=SourceUpdater)
    assert isinstance(updater, SourceUpdater)
    key, factor = _SHRINKS[kind]
    before = _errors(T_prior, T_true)[key]
    assert before > 1e-3, before  # the seed gives an error worth correcting
    up = updater(T_prior, P_prior, Measurement(1.0, f"/{kind}", _payload(kind, T_true)))
    assert up.accepted, up
    after = _errors(up.T_base_tool, T_true)[key]
    assert after < factor * before, (kind, key, before, after)


def test_component_mask_keeps_the_masked_direction_untouched(arm7):
    model, T_prior, P_prior, T_true = arm7
    updater = make_updater(model, "base_link", "tool0", cls=SourceUpdater)
    full = updater(T_prior, P_prior, Measurement(1.0, "/pose", _payload("pose", T_true)))
    # x only: y, z and the rotation of the measurement are not used (they change only through the prior's
    # correlations); a 5-component mask gives a 5-dimensional model
    x_only = updater(T_prior, P_prior, Measurement(1.0, "/pose", _payload("pose", T_true, mask=np.array(
        [True, False, False, False, False, False]))))
    obs, _ = updater.build(Measurement(1.0, "/pose", _payload("pose", T_true, mask=np.array([True] * 5 + [False]))),
                           None)
    assert isinstance(obs, SelectedObservation) and obs.dim == 5
    assert full.accepted and x_only.accepted
    assert abs(full.T_base_tool[0, 3] - T_true[0, 3]) < 0.2 * abs(T_prior[0, 3] - T_true[0, 3])
    # the x-only update corrects less than the full one in total
    err = {k: np.linalg.norm(u.T_base_tool[:3, 3] - T_true[:3, 3]) for k, u in (("x", x_only), ("full", full))}
    assert err["x"] > err["full"], err
    with pytest.raises(MeasurementError, match="component mask"):
        SelectedObservation(obs.inner, [False] * 6)


def test_source_gate_is_used_and_unknown_link_is_named(arm7):
    model, T_prior, P_prior, T_true = arm7
    updater = make_updater(model, "base_link", "tool0", cls=SourceUpdater)
    far = T_true.copy()
    far[:3, 3] += [0.5, 0.0, 0.0]  # 0.5 m off: the node's gate rejects it
    assert not updater(T_prior, P_prior, Measurement(1.0, "/pose", _payload("pose", far))).accepted
    assert updater(T_prior, P_prior, Measurement(1.0, "/pose", _payload("pose", far, gate=1.0))).accepted
    assert updater.gate_probability == pytest.approx(0.9999)  # restored after the source's own gate
    bad = PointMeasurement("no_such_link", REFLECTOR, "tracker", np.zeros(3), np.eye(3) * 1e-6, T_BASE_TRACKER)
    with pytest.raises(MeasurementError, match="link 'no_such_link' is not a link of the URDF"):
        updater.build(Measurement(1.0, "/ground_truth/point", bad), None)


def test_parse_sources_refuses_blocks_that_do_not_fit_their_type():
    from ppoe_core.errors import ModelConfigError
    from ppoe_core.estimation.sources import parse_sources

    def params(**over):  # missing keys take their defaults
        return {"s.type": "pose", "s.topic": "mocap", "s.link": "tool0", **{f"s.{k}": v for k, v in over.items()}}

    (src,) = parse_sources(params(components=[True] * 5 + [False]), ["s"], "/fusion_node")
    assert src.kind == "pose" and src.mask.tolist() == [True] * 5 + [False] and src.gate is None
    for over, match in (({"components": [True, True, True]}, "needs 6 booleans"),
                        ({"sigma": [0.1]}, "needs 0 or 6 positive"),
                        ({"link": ""}, "link whose pose is measured is required"),
                        ({"sensor_pose": [0.0] * 6}, "with 'frame' set"),
                        ({"gate_probability": 0.3}, "must be 0"),
                        ({"type": "laser"}, "must be one of"),
                        ({"xyz": [0.0, 1.0]}, "needs a list of 0 or 3 values")):
        with pytest.raises(ModelConfigError, match=match) as info:
            parse_sources(params(**over), ["s"], "/fusion_node")
        assert "parameter 's." in str(info.value) and "/fusion_node" in str(info.value)


# ------------------------------------------------------------------------------------------------ live


def _source_params(kind: str) -> dict:
    """The node's sensor blocks for a live run of ``kind`` (+ a block whose link is unknown)."""
    blocks = {
        "point": {"type": "point", "topic": "ground_truth/point", "frame": "tracker",
                  "sensor_pose": [1.5, 0.2, 0.1, 0.0, 0.0, float(np.pi / 2)]},  # link, xyz, sigma: model YAML
        "pose": {"type": "pose", "topic": "mocap/tool", "link": "tool0", "frame": "base_link"},  # msg covariance
        "imu": {"type": "imu", "topic": "imu/tool"},  # sigma: message covariance (no model YAML imus entry)
    }
    return {"sources": [kind, "broken"], kind: blocks[kind],
            "broken": {"type": "point", "topic": "ground_truth/point/broken", "link": "no_such_link",
                       "xyz": [0.0, 0.0, 0.0], "sigma": [0.001]}}


def _message(kind: str, T_true: np.ndarray, stamp, frame: str | None = None):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import Imu
    from std_msgs.msg import Header

    from ppoe_ros.common import pose_cov_stamped_msg

    p = _payload(kind, T_true)
    if kind == "point":
        msg = PointStamped(header=Header(stamp=stamp, frame_id=frame or "tracker"))
        msg.point.x, msg.point.y, msg.point.z = (float(v) for v in p.point_frame)
        return msg
    if kind == "pose":
        cov = np.diag([1e-4] * 6) ** 2
        return pose_cov_stamped_msg(T_true, lie.cov_local_to_ros(T_true, cov), stamp, frame or "base_link")
    msg = Imu(header=Header(stamp=stamp, frame_id=frame or "tool0"))
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = (float(v) for v in p.accel)
    msg.linear_acceleration_covariance = (np.eye(3) * 0.0004**2).ravel().tolist()
    return msg


_TOPIC = {"point": "/ground_truth/point", "pose": "/mocap/tool", "imu": "/imu/tool"}


@pytest.mark.ros
@pytest.mark.timeout(150)
@pytest.mark.parametrize("kind", ["point", "pose", "imu"])
def test_fusion_node_fuses_each_kind_live_and_survives_unknown_links(tmp_path, arm7, kind):
    """Priors at a fixed configuration, one measurement of ``kind`` simulated from the true tool pose: the fused
    pose after it is closer to the truth.  The 'broken' block (link not in the URDF) is off with an error naming
    its topic and link; a message on it and (imu) an IMU message for an unknown link are counted, the node lives."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Header

    from ppoe_ros.common import matrix_from_pose_msg, ns_to_stamp, pose_cov_stamped_msg

    model, T_prior, P_prior, T_true = arm7
    msg_type = {"point": PointStamped, "pose": PoseWithCovarianceStamped, "imu": Imu}[kind]
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "fusion.yaml", {
        "model_file": str(ARM7_MODEL), "robot_description": ARM7_URDF.read_text(), "publish_tf": False,
        "diagnostics_period": 0.2, "log_throttle": 0.0, **_source_params(kind)})
    cov_ros = lie.cov_local_to_ros(T_prior, P_prior)
    n = 30
    with Probe(env) as probe, NodeProcess.node("fusion_node", env, tmp_path, params_file=pf) as proc:
        fused = probe.collect("/ppoe/fused_pose", PoseWithCovarianceStamped)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        pub_prior = probe.publisher("/ppoe/pose", PoseWithCovarianceStamped)
        pub_js = probe.publisher("/joint_states", JointState)
        pub_meas = probe.publisher(_TOPIC[kind], msg_type)
        pub_broken = probe.publisher("/ground_truth/point/broken", PointStamped)
        for pub in (pub_prior, pub_js, pub_meas, pub_broken):
            probe.wait_for_subscribers(pub, proc)
        t0 = probe.node.get_clock().now().nanoseconds
        for k in range(n):
            stamp = ns_to_stamp(t0 + k * 20_000_000)
            pub_js.publish(JointState(header=Header(stamp=stamp), name=list(Q), position=list(Q.values())))
            pub_prior.publish(pose_cov_stamped_msg(T_prior, cov_ros, stamp, "base_link"))
            if k == n // 2:
                probe.spin_for(0.3)
                pub_meas.publish(_message(kind, T_true, stamp))
                pub_broken.publish(PointStamped(header=Header(stamp=stamp, frame_id="base_link")))
                if kind == "imu":
                    pub_meas.publish(_message(kind, T_true, stamp, frame="ghost_link"))
            probe.spin_for(0.02)
        probe.spin_until(lambda: len(fused) >= n + 1, 30, proc, "every prior fused and one update")
        probe.spin_until(lambda: diags and int(_values(diags[-1]).get("unknown_link", 0)) >= (2 if kind == "imu"
                                                                                              else 1),
                         10, proc, "the unknown-link messages counted on /diagnostics")
        alive = proc.alive()
        log = proc.output()
    assert alive, log
    key, factor = _SHRINKS[kind]
    before = _errors(T_prior, T_true)[key]
    after = _errors(matrix_from_pose_msg(fused[-1].pose.pose), T_true)[key]
    assert after < factor * before, (kind, key, before, after, log[-3000:])
    values = _values(diags[-1])
    assert int(values["accepted"]) == 1, values
    # the source whose link is unknown: one error at start-up naming topic and link, on /diagnostics too
    assert "source 'broken' on /ground_truth/point/broken is off: link 'no_such_link' is not a link of the URDF" in log
    assert "no_such_link" in values["sources"]
    if kind == "imu":
        assert "IMU header.frame_id 'ghost_link': 'ghost_link' is not a link of the URDF" in log
        assert "/imu/tool" in log


def _values(status_array) -> dict[str, str]:
    return {kv.key: kv.value for kv in status_array.status[0].values}


def test_misspelled_block_key_is_reported_with_the_closest_name(tmp_path):
    """A typo inside a sensor block is an unknown parameter like any other: reported with the closest valid name,
    and the node still starts."""
    pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter
    from ros_helpers import Probe, ros_env

    from ppoe_ros.common.fusion_sources import source_specs
    from ppoe_ros.common.params import _report_unknown_overrides
    from ppoe_ros.nodes.fusion_node import PARAMS, FusionNode

    with Probe(ros_env(tmp_path)) as probe:
        node = FusionNode(context=probe.context, parameter_overrides=[
            Parameter("model_file", value=str(ARM7_MODEL)), Parameter("robot_description", value=ARM7_URDF.read_text()),
            Parameter("publish_tf", value=False), Parameter("sources", value=["tracker"]),
            Parameter("tracker.type", value="point"), Parameter("tracker.topic", value="ground_truth/point"),
            Parameter("tracker.sigm", value=[0.001]), Parameter("mocap.type", value="pose")])
        try:
            by_name = {s.name: s for s in PARAMS + source_specs(["tracker"])}
            lines = _report_unknown_overrides(node, by_name)
            (src,) = node.sources.sources
            # completed from the model YAML's tracker entry (arm7: tool0, xyz [0, 0, 0.02], sigma 0.5 mm)
            assert (src.link, src.xyz.tolist(), src.sigma.tolist(), src.off) == ("tool0", [0.0, 0.0, 0.02],
                                                                                 [0.0005], "")
        finally:
            node.destroy_node()
    assert any("unknown parameter 'tracker.sigm' ignored (did you mean 'tracker.sigma'?)" in line for line in lines)
    assert any("unknown parameter 'mocap.type'" in line for line in lines)  # a block not listed in sources
