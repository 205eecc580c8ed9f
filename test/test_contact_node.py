"""contact_node: hysteresis (detector unit tests: test_contact_detector.py), plane + Sigma_v output through live
topics, bad input, parameters.

The node runs as a separate process in an isolated DDS domain with the contact
section of config/robots/humanoid_model.yaml; parameter validation is checked on a node
built inside the test process.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

import yaml  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped, WrenchStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_helpers import REPO, NodeProcess, Probe, ros_env  # noqa: E402
from std_msgs.msg import Bool  # noqa: E402

from ppoe_core import lie  # noqa: E402
from ppoe_core.errors import ModelConfigError  # noqa: E402
from ppoe_ros.common import ns_to_stamp, pose_cov_from_msg, stamp_to_ns  # noqa: E402
from ppoe_ros.nodes.contact_node import ContactNode  # noqa: E402

pytestmark = pytest.mark.ros

MODEL = REPO / "config" / "robots" / "humanoid_model.yaml"


def _wrench(ns: int, force: tuple[float, float, float]) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.stamp = ns_to_stamp(ns)
    msg.header.frame_id = "fingertip"
    # floats: rclpy accepts an int in a float64 field but serialises garbage for it
    msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = (float(f) for f in force)
    return msg


def test_wrench_hysteresis_plane_and_bad_input_live(tmp_path: Path) -> None:
    cfg = yaml.safe_load(MODEL.read_text())["contact"]
    T_plane = lie.from_xyz_rpy(cfg["plane"]["xyz"], cfg["plane"]["rpy"])
    cov_ros_ref = lie.cov_local_to_ros(T_plane, np.diag(np.square(cfg["sigma"])))
    env = ros_env(tmp_path)
    with (
        Probe(env) as probe,
        NodeProcess.node("contact_node", env, tmp_path, params={"model_file": str(MODEL), "log_throttle": 0.0}) as proc,
    ):
        pub = probe.publisher("/wrench", WrenchStamped, 100)
        out = probe.collect("/contact/plane", PoseWithCovarianceStamped)
        probe.wait_for_subscribers(pub, proc)
        probe.wait_for_publishers("/contact/plane", proc)
        # force norms 0, 3, 6 (enter), 4, 2.5 (stay), NaN (bad), 1.9 (leave), 4 (stay off), 5 (enter), 1 (leave)
        forces = [
            (0, 0, 0),
            (0, 3, 0),
            (0, 0, -6),
            (4, 0, 0),
            (1.5, 2, 0),
            (float("nan"), 0, 0),
            (0, 0, 1.9),
            (0, 4, 0),
            (3, 0, 4),
            (1, 0, 0),
        ]
        stamps = [int(10e9) + k * 10_000_000 for k in range(len(forces))]
        for ns, f in zip(stamps, forces):
            pub.publish(_wrench(ns, f))
        expected = [stamps[i] for i in (2, 3, 4, 8)]
        probe.spin_until(lambda: len(out) >= len(expected), 10, proc, "the in-contact planes")
        probe.spin_for(0.3)
        assert [stamp_to_ns(m.header.stamp) for m in out] == expected
        for msg in out:
            T, cov_ros, _, frame = pose_cov_from_msg(msg)
            assert frame == cfg["plane"]["frame"]
            np.testing.assert_allclose(T, T_plane, atol=1e-12)
            np.testing.assert_allclose(cov_ros, cov_ros_ref, rtol=1e-12, atol=1e-15)
        # a stamp jumping backwards is ignored, a later good one still works
        pub.publish(_wrench(stamps[0], (0, 0, 9.0)))
        pub.publish(_wrench(stamps[-1] + 10_000_000, (0, 0, 9.0)))
        probe.spin_until(lambda: len(out) >= len(expected) + 1, 10, proc, "a plane after the bad stamp")
        probe.spin_for(0.2)
        assert stamp_to_ns(out[-1].header.stamp) == stamps[-1] + 10_000_000 and len(out) == len(expected) + 1
        log = proc.output()
        assert "bad message on /wrench: non-finite wrench" in log
        assert "bad message on /wrench: stamp " in log and "jumped back by 0.090000 s: message dropped" in log
        assert log.count("contact begins") == 3 and log.count("contact ends") == 2
        # a clock reset (bag loop, simulator restart: 10 s back, > stamp_reset_threshold) starts a new
        # timeline instead of rejecting every later wrench (issue 13 item 7)
        n0 = len(out)
        reset = [int(0.5e9) + k * 10_000_000 for k in range(3)]
        for ns in reset:
            pub.publish(_wrench(ns, (0, 0, 9.0)))
        probe.spin_until(lambda: len(out) >= n0 + 3, 10, proc, "planes after the clock reset")
        assert [stamp_to_ns(m.header.stamp) for m in out[n0:]] == reset
        log = proc.output()
        assert "(> stamp_reset_threshold): new timeline, contact state reset" in log
        assert proc.alive()


def test_contact_flag_topic_and_plane_parameters_live(tmp_path: Path) -> None:
    env = ros_env(tmp_path)
    params = {
        "contact_flag_topic": "/in_contact",
        "plane_frame": "base_link",
        "plane_xyz": [0.1, 0.2, 0.3],
        "plane_rpy": [0.0, 0.0, 0.5],
        "plane_sigma": [0.1, 0.1, 0.002, 0.01, 0.01, 0.1],
    }
    with Probe(env) as probe, NodeProcess.node("contact_node", env, tmp_path, params=params) as proc:
        pub = probe.publisher("/in_contact", Bool, 100)
        out = probe.collect("/contact/plane", PoseWithCovarianceStamped)
        probe.wait_for_subscribers(pub, proc)
        for flag in [False, True, True, False, True]:
            pub.publish(Bool(data=flag))
        probe.spin_until(lambda: len(out) >= 3, 10, proc, "three planes")
        probe.spin_for(0.3)
        assert len(out) == 3
        T, cov_ros, _, frame = pose_cov_from_msg(out[0])
        T_ref = lie.from_xyz_rpy([0.1, 0.2, 0.3], [0.0, 0.0, 0.5])
        assert frame == "base_link"
        np.testing.assert_allclose(T, T_ref, atol=1e-12)
        cov_local = np.diag(np.square([0.1, 0.1, 0.002, 0.01, 0.01, 0.1]))
        np.testing.assert_allclose(cov_ros, lie.cov_local_to_ros(T_ref, cov_local), rtol=1e-12, atol=1e-15)
        # rotated about z: the in-plane x/y variances mix, the normal (z) variance stays
        assert cov_ros[2, 2] == pytest.approx(0.002**2) and abs(cov_ros[0, 1]) == pytest.approx(0.0, abs=1e-15)


def test_parameters_validated_in_process(tmp_path: Path) -> None:
    env = ros_env(tmp_path)
    with Probe(env) as probe:
        overrides = [Parameter("model_file", value=str(MODEL))]
        node = ContactNode(context=probe.context, parameter_overrides=overrides)
        try:
            assert (node.detector.enter, node.detector.release) == (5.0, 2.0)  # from the model YAML
            res = node.set_parameters([Parameter("release_threshold", value=8.0)])[0]
            assert not res.successful and "must be below force_threshold" in res.reason
            res = node.set_parameters([Parameter("force_threshold", value=-1.0)])[0]
            assert not res.successful and "must be >= 0.0" in res.reason
            res = node.set_parameters([Parameter("plane_frame", value="other")])[0]
            assert not res.successful and "read-only" in res.reason
            assert node.set_parameters([Parameter("force_threshold", value=9.0)])[0].successful
            assert node.detector.enter == 9.0
        finally:
            node.destroy_node()
        with pytest.raises(ModelConfigError, match="parameter 'force_component' must be one of"):
            ContactNode(
                context=probe.context, parameter_overrides=overrides + [Parameter("force_component", value="sideways")]
            )
        with pytest.raises(ModelConfigError, match="no plane Sigma_v"):
            ContactNode(context=probe.context, parameter_overrides=[Parameter("plane_frame", value="base_link")])
        with pytest.raises(ModelConfigError, match="release_threshold .* must be below"):
            ContactNode(
                context=probe.context, parameter_overrides=overrides + [Parameter("release_threshold", value=6.0)]
            )
        # a malformed contact section is refused naming file, line and key (validated by ppoe_core.robot.config)
        bad = tmp_path / "bad_model.yaml"
        bad.write_text(
            "contact:\n  plane: {frame: table}\n  sigma: [0.1, x, 0.1, 0.1, 0.1, 0.1]\n  tool_point: {link: tip}\n"
        )
        with pytest.raises(ModelConfigError, match=r"bad_model.yaml:3: contact.sigma"):
            ContactNode(context=probe.context, parameter_overrides=[Parameter("model_file", value=str(bad))])


def test_node_callback_gives_the_planes_evaluate_replays(tmp_path: Path) -> None:
    """The shipped contact bag's /wrench through the node's own callback (in process, publisher
    captured) gives, as the fusion node reads them, exactly the contact measurements that
    ``ppoe evaluate`` replays: same stamps, frame, and bit-identical plane pose and Sigma_v."""
    from ppoe_core.analysis.evaluate import EVALUATE_SETTINGS, contact_measurements
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.model.ppoe import PPOEModel

    bag = REPO / "bags" / "contact"
    data = read_bag(bag, topics=["/robot_description", "/wrench"])
    wr = data.wrench
    model = PPOEModel.from_strings(data.robot_description, MODEL.read_text())
    replayed, counts = contact_measurements(data, model, MODEL, dict(EVALUATE_SETTINGS))
    env = ros_env(tmp_path)
    with Probe(env) as probe:
        node = ContactNode(context=probe.context, parameter_overrides=[Parameter("model_file", value=str(MODEL))])
        try:
            sent: list[tuple] = []
            # capture instead of DDS: the fusion node's reading of the message at publish time
            node._pub.publish = lambda msg: sent.append(pose_cov_from_msg(msg))
            for t, f in zip(wr.stamps, wr.force):
                node._wrench(_wrench(int(round(t * 1e9)), tuple(f)))
        finally:
            node.destroy_node()
    assert len(sent) == len(replayed) == counts["contact_planes"] > 0
    assert counts["wrench"]["contacts"] == 8
    for (T, cov_ros, stamp_ns, frame), m in zip(sent, replayed):
        # as the fusion node turns the message into a measurement (ppoe_ros/fusion_node.py _contact)
        cov_plane = lie.cov_ros_to_local(T, cov_ros)
        assert abs(stamp_ns * 1e-9 - m.stamp) < 1e-9 and frame == m.payload.frame
        np.testing.assert_array_equal(T, m.payload.T_frame_plane)
        np.testing.assert_array_equal(cov_plane, m.payload.cov_plane)
