"""kinematics_node through live topics: a separate process in an isolated DDS domain.

The node gets the URDF of config/robots/arm7.urdf on the latched /robot_description topic
and config/robots/arm7_model.yaml; its /ppoe/pose output must equal PPOEModel.fk (pose and
cov_ros) and ``ppoe fk`` for the same joints; bad joint states are logged, counted
on /diagnostics, and the node keeps publishing on good input.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from ros_helpers import REPO, NodeProcess, Probe, ros_env, write_params_file  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from ppoe_core import lie  # noqa: E402
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402
from ppoe_ros.common import LATCHED_QOS, ns_to_stamp, pose_cov_from_msg, stamp_to_ns  # noqa: E402

pytestmark = pytest.mark.ros

URDF = REPO / "config" / "robots" / "arm7.urdf"
MODEL = REPO / "config" / "robots" / "arm7_model.yaml"
ARM = [f"joint_{i}" for i in range(1, 8)]
EXTRA = "camera_optical_frame"


@pytest.fixture(scope="module")
def model() -> PPOEModel:
    return PPOEModel.from_files(URDF, MODEL)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory):
    """One kinematics node process (URDF from the topic) and a probe, for the whole module."""
    tmp = tmp_path_factory.mktemp("kin")
    env = ros_env(tmp)
    with Probe(env) as probe:
        desc = probe.publisher("/robot_description", String, LATCHED_QOS)
        desc.publish(String(data=URDF.read_text()))
        poses = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        extra = probe.collect(f"/ppoe/{EXTRA}/pose", PoseWithCovarianceStamped)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        js = probe.publisher("/joint_states", JointState, 1000)
        with NodeProcess.node("kinematics_node", env, tmp, params={
                "model_file": str(MODEL), "extra_target_frames": [EXTRA], "diagnostics_period": 0.2,
                "log_throttle": 0.0}) as proc:
            probe.wait_for_subscribers(js, proc)
            probe.wait_for_publishers("/ppoe/pose", proc)
            probe.spin_until(lambda: "model from topic /robot_description" in proc.output(), 15, proc,
                             "the model to be built from /robot_description")
            yield {"probe": probe, "proc": proc, "js": js, "poses": poses, "extra": extra, "diags": diags,
                   "clock": [1000.0]}


def _send(live, names, positions) -> int:
    """Publish one JointState with the next stamp (10 ms steps); returns its stamp in ns."""
    live["clock"][0] += 0.01
    ns = int(round(live["clock"][0] * 1e9))
    msg = JointState(name=list(names), position=[float(p) for p in positions])
    msg.header.stamp = ns_to_stamp(ns)
    live["js"].publish(msg)
    return ns


def _send_at(live, ns, names, positions) -> None:
    msg = JointState(name=list(names), position=[float(p) for p in positions])
    msg.header.stamp = ns_to_stamp(ns)
    live["js"].publish(msg)


def _wait_count(live, box, n, what) -> None:
    live["probe"].spin_until(lambda: len(box) >= n, 10, live["proc"], what)


def _last_counts(live) -> dict[str, int]:
    for arr in reversed(live["diags"]):
        for st in arr.status:
            if st.name == "/kinematics_node: health":
                return {kv.key: int(kv.value) for kv in st.values if kv.value.isdigit()}
    return {}


def test_output_equals_model_fk(live, model) -> None:
    rng = np.random.default_rng(7)
    n0, e0 = len(live["poses"]), len(live["extra"])
    sent = []
    for _ in range(20):
        q = rng.uniform(-2.0, 2.0, 7)
        # shuffled order, plus a joint the chain does not use and one the URDF does not know
        names = ARM + ["finger_left_joint", "not_a_urdf_joint"]
        values = list(q) + [0.01, 3.0]
        perm = rng.permutation(len(names))
        stamp = _send(live, [names[i] for i in perm], [values[i] for i in perm])
        sent.append((stamp, q))
    _wait_count(live, live["poses"], n0 + 20, "20 poses")
    _wait_count(live, live["extra"], e0 + 20, f"20 poses of {EXTRA}")
    outs, extras = live["poses"][n0:], live["extra"][e0:]
    assert [stamp_to_ns(m.header.stamp) for m in outs] == [s for s, _ in sent]
    for (_, q), msg, msg_c in zip(sent, outs, extras):
        joints = dict(zip(ARM, q))
        T_ref, cov_ref = model.fk(joints, "base_link", "tool0")
        T, cov_ros, _, frame = pose_cov_from_msg(msg)
        assert frame == "base_link"
        np.testing.assert_allclose(T, T_ref, atol=1e-12)
        np.testing.assert_allclose(cov_ros, lie.cov_local_to_ros(T_ref, cov_ref), rtol=1e-10, atol=1e-18)
        # the ROS covariance is not the local one (rotated axes): the conversion was applied
        assert not np.allclose(cov_ros, cov_ref, rtol=1e-3)
        Tc_ref, covc_ref = model.fk(joints, "base_link", EXTRA)
        Tc, covc_ros, _, frame_c = pose_cov_from_msg(msg_c)
        assert frame_c == "base_link"
        np.testing.assert_allclose(Tc, Tc_ref, atol=1e-12)
        np.testing.assert_allclose(covc_ros, lie.cov_local_to_ros(Tc_ref, covc_ref), rtol=1e-10, atol=1e-18)


def test_output_equals_ppoe_fk_cli(live) -> None:
    q = [0.3, -0.7, 0.2, 1.1, -0.4, 0.9, 0.05]
    n0 = len(live["poses"])
    _send(live, ARM, q)
    _wait_count(live, live["poses"], n0 + 1, "one pose")
    T, cov_ros, _, _ = pose_cov_from_msg(live["poses"][n0])
    res = subprocess.run(
        [sys.executable, "-m", "ppoe_ros.cli", "fk", "--urdf", str(URDF), "--model", str(MODEL),
         "--from", "base_link", "--to", "tool0", "--json", "--joints", *[f"{n}={v!r}" for n, v in zip(ARM, q)]],
        cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    ref = json.loads(res.stdout)
    np.testing.assert_allclose(T, np.array(ref["T"]), atol=1e-12)
    np.testing.assert_allclose(cov_ros, np.array(ref["cov_ros"]), rtol=1e-9, atol=1e-18)


def test_bad_messages_logged_counted_and_node_survives(live, model) -> None:
    """Bad messages are counted and logged, the node survives; split joint states (a message lacking a chain
    joint) are merged with the latest value of that joint while it is at most joint_max_age (0.5 s) old."""
    probe, proc = live["probe"], live["proc"]
    n0 = len(live["poses"])
    c0 = _last_counts(live)
    good_q = [0.1] * 7
    s1 = _send(live, ARM, good_q)
    s_split = _send(live, ARM[:2] + ARM[3:], [0.2] * 6)              # joint_3 from s1 (10 ms old): merged
    _send(live, ["not_a_urdf_joint"], [0.2])                          # no chain joint: ignored, no output
    _send(live, ARM, [0.1, 0.1, float("nan"), 0.1, 0.1, 0.1, 0.1])   # NaN in a chain joint
    _send(live, ARM, [0.1] * 6)                                       # 7 names, 6 positions
    _send_at(live, s1 - 5_000_000, ARM, good_q)                       # stamp 5 ms before an earlier one
    live["clock"][0] += 1.0
    _send(live, ARM[:2] + ARM[3:], [0.1] * 6)                         # joint_3 now 1 s old: incomplete
    s_ok = _send(live, ARM + ["finger_left_joint"], good_q + [float("nan")])  # NaN in an unused joint: fine
    s_ok2 = _send(live, ARM, good_q)
    _wait_count(live, live["poses"], n0 + 4, "the good poses after the bad messages")
    probe.spin_for(0.3)
    got = [stamp_to_ns(m.header.stamp) for m in live["poses"][n0:]]
    assert got == [s1, s_split, s_ok, s_ok2], "only the valid (or merged) joint states are published, in order"
    q_split = {j: 0.2 for j in ARM} | {"joint_3": 0.1}
    T, _ = model.fk({**q_split, "finger_left_joint": 0.0}, "base_link", "tool0")
    p = live["poses"][n0 + 1].pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], T[:3, 3], atol=1e-9)

    def counts_reached() -> bool:
        c = _last_counts(live)
        return (c.get("bad", 0) >= c0.get("bad", 0) + 3 and c.get("ignored", 0) >= c0.get("ignored", 0) + 1
                and c.get("incomplete", 0) >= c0.get("incomplete", 0) + 1)

    probe.spin_until(counts_reached, 5, proc, "bad +3, ignored +1, incomplete +1 on /diagnostics")
    assert _last_counts(live)["bad"] == c0.get("bad", 0) + 3
    log = proc.output()
    assert "ignored message on /joint_states: carries none of the chain's joints" in log
    assert "incomplete message on /joint_states: needed joint(s) older than 0.5 s: joint_3" in log
    assert "NaN or infinite value for joint(s) 'joint_3'" in log
    assert "7 names but 6 positions" in log
    assert "jumped back by 0.015" in log
    assert "finger_left_joint" not in log.split("NaN or infinite")[-1], "unused joints are not checked"
    assert proc.alive()


def test_broken_urdf_on_topic_is_refused_and_old_model_kept(live, model) -> None:
    probe, proc = live["probe"], live["proc"]
    pub = probe.publisher("/robot_description", String, LATCHED_QOS)
    pub.publish(String(data="<robot name='x'><link name='a'/><joint name='j' type='revolute'></robot>"))
    probe.spin_until(lambda: "bad message on /robot_description: topic /robot_description:" in proc.output(),
                     10, proc, "the broken URDF to be reported")
    n0 = len(live["poses"])
    _send(live, ARM, [0.2] * 7)
    _wait_count(live, live["poses"], n0 + 1, "a pose after the broken URDF")
    probe.node.destroy_publisher(pub)
    T, cov_ros, _, _ = pose_cov_from_msg(live["poses"][n0])
    T_ref, cov_ref = model.fk(dict(zip(ARM, [0.2] * 7)), "base_link", "tool0")  # the old (arm7) model
    np.testing.assert_allclose(T, T_ref, atol=1e-12)
    np.testing.assert_allclose(cov_ros, lie.cov_local_to_ros(T_ref, cov_ref), rtol=1e-10, atol=1e-18)
    assert proc.alive()


def test_stamp_reset_starts_new_timeline(live) -> None:
    n0 = len(live["poses"])
    s_new = int((live["clock"][0] - 100.0) * 1e9)  # 100 s back: a bag loop
    _send_at(live, s_new, ARM, [0.3] * 7)
    live["clock"][0] -= 100.0
    s_next = _send(live, ARM, [0.3] * 7)
    _wait_count(live, live["poses"], n0 + 2, "poses after the clock reset")
    assert [stamp_to_ns(m.header.stamp) for m in live["poses"][n0:]] == [s_new, s_next]
    assert "(> stamp_reset_threshold): new timeline" in live["proc"].output()


def test_future_stamp_repeated_and_misspelt_joints_are_refused_and_counted(live) -> None:
    """Issue 25: a joint state stamped 0.9 s ahead of the node's clock is refused (not published) and the valid
    messages after it are published (before: it was published and every valid message of the next second was
    dropped as "jumped back"); a message naming a joint twice is refused, naming it (before: the last value was
    used); ``joint_２`` (full-width 2) instead of ``joint_2`` is refused, naming both (before: the pose used the held
    ``joint_2`` of an earlier message).  Each counted as bad, the node keeps publishing."""
    probe, proc = live["probe"], live["proc"]
    probe.spin_for(0.6)  # the counters of the earlier tests on /diagnostics first
    n0 = len(live["poses"])
    c0 = _last_counts(live)
    live["clock"][0] = time.time()  # stamps on the node's (wall) clock from here on
    q = [0.25] * 7
    s1 = _send(live, ARM, q)
    _send_at(live, int((live["clock"][0] + 0.9) * 1e9), ARM, q)          # 0.9 s in the future
    s2 = _send(live, ARM, q)
    _send(live, ARM + ["joint_1"], q + [0.5])                            # joint_1 twice
    _send(live, ["joint_1", "joint_\uff12"] + ARM[2:], [0.25, 0.9] + q[2:])  # joint_２: joint_2 missing
    s3 = _send(live, ARM, q)
    _wait_count(live, live["poses"], n0 + 3, "the valid poses around the refused ones")
    probe.spin_for(0.3)
    assert [stamp_to_ns(m.header.stamp) for m in live["poses"][n0:]] == [s1, s2, s3]
    probe.spin_until(lambda: _last_counts(live).get("bad", 0) >= c0.get("bad", 0) + 3, 5, proc, "bad +3")
    assert _last_counts(live)["bad"] == c0.get("bad", 0) + 3
    log = proc.output()
    assert "ahead of the clock (> future tolerance 0.5 s): refused" in log
    assert "lists joint(s) 'joint_1' more than once: message refused" in log
    assert "carries 'joint_\uff12' (looks like 'joint_2'), not a joint of the URDF, and lacks needed joint(s) " \
           "'joint_2'" in log
    assert "jumped back" not in log.split("ahead of the clock")[-1], "no valid message dropped after it"


def test_parameter_urdf_sim_time_and_synchronous_mode(tmp_path: Path) -> None:
    """URDF from the parameter, use_sim_time (diagnostics stamped from /clock), max_batch 1."""
    from rosgraph_msgs.msg import Clock

    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "p.yaml", {
        "robot_description": URDF.read_text(), "model_file": str(MODEL), "use_sim_time": True,
        "max_batch": 1, "diagnostics_period": 0.1, "target_frame": "arm_link_4", "pose_topic": "/elbow"})
    with Probe(env) as probe, NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf) as proc:
        clock = probe.publisher("/clock", Clock, 10)
        js = probe.publisher("/joint_states", JointState, 100)
        out = probe.collect("/elbow", PoseWithCovarianceStamped)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        probe.wait_for_subscribers(js, proc)
        probe.wait_for_subscribers(clock, proc)
        clock.publish(Clock(clock=ns_to_stamp(777_000_000_000)))
        msg = JointState(name=ARM[:4], position=[0.1, 0.2, 0.3, 0.4])  # the elbow needs joints 1-4 only
        msg.header.stamp = ns_to_stamp(5_000_000_000)
        js.publish(msg)
        probe.spin_until(lambda: len(out) >= 1, 10, proc, "an elbow pose")
        assert stamp_to_ns(out[0].header.stamp) == 5_000_000_000
        probe.spin_until(lambda: any(abs(stamp_to_ns(d.header.stamp) - 777e9) < 1e9 for d in diags), 10, proc,
                         "diagnostics stamped with the simulated time")
        T, _, _, _ = pose_cov_from_msg(out[0])
        ref = PPOEModel.from_files(URDF, MODEL).fk_mean(dict(zip(ARM[:4], [0.1, 0.2, 0.3, 0.4])),
                                                          "base_link", "arm_link_4")
        np.testing.assert_allclose(T, ref, atol=1e-12)


def test_invalid_parameter_refused_at_startup(tmp_path: Path) -> None:
    env = ros_env(tmp_path)
    proc = NodeProcess.node("kinematics_node", env, tmp_path, params={"order": 3})
    try:
        code = proc.wait(20)
    finally:
        proc.stop()
    assert code == 2
    assert "parameter 'order' must be 2 or 4, got 3" in proc.output()


# ---------------------------------------------------------------- ros_common helpers the node is built on


class _FakeLogger:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def warning(self, text: str) -> None:
        self.lines.append(("warn", text))

    def error(self, text: str) -> None:
        self.lines.append(("error", text))


class _FakeNode:
    def __init__(self) -> None:
        self.logger = _FakeLogger()

    def get_logger(self) -> _FakeLogger:
        return self.logger


def test_node_stats_throttles_and_counts(monkeypatch: pytest.MonkeyPatch) -> None:
    from ppoe_ros.common import diagnostics as ros_common

    now = [100.0]
    monkeypatch.setattr(ros_common.time, "monotonic", lambda: now[0])
    node = _FakeNode()
    stats = ros_common.NodeStats(node, ("received", "bad"), throttle_sec=2.0)
    for k in range(5):
        stats.bad("/joint_states", f"reason {k}")
        now[0] += 0.1
    stats.bad("/wrench", "other topic")  # a different topic has its own throttle
    assert stats.counts["bad"] == 6
    assert [t for _, t in node.logger.lines] == ["bad message on /joint_states: reason 0",
                                                 "bad message on /wrench: other topic"]
    now[0] += 2.0
    stats.bad("/joint_states", "reason 5")
    assert node.logger.lines[-1][1] == ("bad message on /joint_states: reason 5 "
                                        "(4 similar suppressed in the last 2 s)")


def test_guarded_counts_bad_and_unexpected_errors() -> None:
    from ppoe_core.errors import JointValueError
    from ppoe_ros.common import NodeStats, guarded

    node = _FakeNode()
    stats = NodeStats(node, throttle_sec=0.0)

    @guarded(stats, "/joint_states")
    def cb(kind: str) -> str:
        if kind == "bad":
            raise JointValueError("joint 'j1' is NaN")
        if kind == "bug":
            raise RuntimeError("boom")
        return "ok"

    assert cb("good") == "ok"
    assert cb("bad") is None and cb("bug") is None
    assert stats.counts["bad"] == 1 and stats.counts["errors"] == 1
    assert node.logger.lines[0] == ("warn", "bad message on /joint_states: joint 'j1' is NaN")
    assert node.logger.lines[1][0] == "error" and "RuntimeError: boom" in node.logger.lines[1][1]


def test_sequence_gaps_count_losses_and_pause_with_several_publishers() -> None:
    """Issue 13 item 6: messages lost before the callback are counted from sequence gaps."""
    from ppoe_ros.common import NodeStats, SequenceGaps

    stats = NodeStats(_FakeNode(), throttle_sec=0.0)
    gaps = SequenceGaps("/joint_states", stats)
    for seq in (1, 2, 5, 6, 10):
        gaps.observe({"publication_sequence_number": seq})
    assert stats.counts["lost_before_node"] == 2 + 3 and "sequence 6 -> 10" in stats.last_reason
    gaps.observe({"publication_sequence_number": 1})  # the publisher restarted: nothing lost
    gaps.observe({"publication_sequence_number": 2})
    assert stats.counts["lost_before_node"] == 5
    gaps.set_publishers(2)  # two publishers interleave their numbers: paused
    for seq in (3, 1, 7, 2):
        gaps.observe({"publication_sequence_number": seq})
    gaps.set_publishers(1)
    gaps.observe({"publication_sequence_number": 40})
    gaps.observe({"publication_sequence_number": 42})
    gaps.observe({"publication_sequence_number": None})  # an rmw without numbers
    assert stats.counts["lost_before_node"] == 6


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_burst_losses_are_counted_on_diagnostics(tmp_path: Path) -> None:
    """A burst into a 2-deep subscription: received + lost_before_node = sent, and /diagnostics WARNs."""
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "p.yaml", {
        "robot_description": URDF.read_text(), "model_file": str(MODEL), "max_batch": 1, "drain_max": 0,
        "qos_depth": 2, "diagnostics_period": 0.2})
    with Probe(env) as probe, NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf) as proc:
        js = probe.publisher("/joint_states", JointState, 5000)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        probe.wait_for_subscribers(js, proc)
        probe.spin_for(0.5)

        def kv() -> dict[str, str]:
            st = [s for d in diags for s in d.status if s.name == "/kinematics_node: health"]
            return {k.key: k.value for k in st[-1].values} if st else {}

        n = 3000
        # the first message sets the sequence baseline (what a publisher sent before it is not known)
        msg = JointState(name=ARM, position=[0.0] * 7)
        msg.header.stamp = ns_to_stamp(999_000_000)
        js.publish(msg)
        probe.spin_until(lambda: kv().get("received") == "1", 10, proc, "the first message")
        for k in range(1, n):
            msg = JointState(name=ARM, position=[0.01 * (k % 50)] * 7)
            msg.header.stamp = ns_to_stamp(1_000_000_000 + k * 1_000_000)
            js.publish(msg)
        probe.spin_for(1.0)
        msg.header.stamp = ns_to_stamp(10_000_000_000)  # a last message closes any trailing gap
        js.publish(msg)
        probe.spin_until(lambda: int(kv().get("received", 0)) + int(kv().get("lost_before_node", 0)) == n + 1,
                         30, proc, f"received + lost_before_node = {n + 1} (last {kv()})")
        c = kv()
        assert int(c["lost_before_node"]) > 0 and c["loss_tracking"] == "on", c
        assert int(c["published"]) == int(c["received"])
        assert any(s.level == DiagnosticStatus.WARN and "lost before the node" in s.message
                   for d in diags for s in d.status)


def test_pose_cov_message_round_trip() -> None:
    from ppoe_ros.common import pose_cov_stamped_msg

    rng = np.random.default_rng(11)
    for _ in range(50):
        T = lie.exp(rng.normal(size=6) * np.array([1, 1, 1, 2, 2, 2]))
        A = rng.normal(size=(6, 6))
        cov_ros = A @ A.T
        ns = int(rng.integers(0, 2**40))
        msg = pose_cov_stamped_msg(T, cov_ros, ns, "base_link")
        T2, cov2, ns2, frame = pose_cov_from_msg(msg)
        np.testing.assert_allclose(T2, T, atol=1e-12)
        np.testing.assert_array_equal(cov2, cov_ros)
        assert ns2 == ns and frame == "base_link"


def test_param_spec_validation_and_descriptor() -> None:
    from rcl_interfaces.msg import ParameterType

    from ppoe_ros.common import ParamSpec, check_length
    from ppoe_ros.nodes.kinematics_node import PARAMS

    spec = ParamSpec("rate", 1.0, "a rate", unit="Hz", min_value=0.0, max_value=10.0)
    assert spec.validate(5.0) is None
    assert spec.validate(-1.0) == "must be >= 0.0, got -1.0"
    assert spec.validate(11.0) == "must be <= 10.0, got 11.0"
    assert spec.validate(float("nan")) == "must be finite, got nan"
    desc = spec.descriptor()
    assert desc.type == ParameterType.PARAMETER_DOUBLE and desc.description == "a rate [Hz]"
    assert (desc.floating_point_range[0].from_value, desc.floating_point_range[0].to_value) == (0.0, 10.0)
    xyz = ParamSpec("xyz", [], "p", ptype=ParameterType.PARAMETER_DOUBLE_ARRAY, check=check_length(0, 3))
    assert xyz.validate([1.0, 2.0]) == "must have 0 or 3 elements, got 2"
    assert all(s.descriptor().description for s in PARAMS)


#: bag time [s] of the first joint state.  Under load the node's side of discovery can match the player's writers
#: seconds after the player saw the node's subscription (`--wait-for-subscribers` checks the player's side only):
#: the latched URDF still arrives, volatile joint states published before the match never reach the node (seen: the
#: first 20 of 120 with 1 s; the node received 100, counted nothing lost: they precede the first sequence number
#: it saw).  4 s leaves discovery the time; the loss itself is not the node's.
JOINTS_T0 = 4.0


def _split_expectation(q_all: np.ndarray) -> tuple[list[float], list[np.ndarray]]:
    """Stamps and merged joint values of the outputs for a bag whose arm (joint_1..6) and wrist + gripper
    (joint_7, finger) come in separate messages 2 ms apart: the first arm message cannot be completed."""
    stamps, qs = [], []
    for k, q in enumerate(q_all):
        if k > 0:
            stamps.append(JOINTS_T0 + 0.01 * k)
            qs.append(np.r_[q[:6], q_all[k - 1][6]])  # joint_7 held from the previous wrist message
        stamps.append(JOINTS_T0 + 0.01 * k + 0.002)
        qs.append(q)
    return stamps, qs


@pytest.mark.parametrize("split", [False, True], ids=["one_publisher", "arm_and_gripper_split"])
def test_bag_play_node_record_equals_fk(tmp_path: Path, model, split: bool) -> None:
    """ppoe play (with /clock) -> kinematics_node (use_sim_time) -> ppoe record; the recorded poses equal fk.
    Split: arm and wrist + gripper on separate joint-state messages, merged per joint by the node."""
    from ppoe_core.io.bagio import BagWriter, read_bag

    rng = np.random.default_rng(5)
    q_all = rng.uniform(-1.5, 1.5, (60, 7))
    src, rec = tmp_path / "src", tmp_path / "rec"
    with BagWriter(src) as bag:
        bag.write_robot_description(URDF.read_text(), 0.0)
        for k, q in enumerate(q_all):  # extra, unused joint in every message
            if split:
                bag.write_joint_state(JOINTS_T0 + 0.01 * k, ARM[:6], list(q[:6]))
                bag.write_joint_state(JOINTS_T0 + 0.01 * k + 0.002, ARM[6:] + ["finger_left_joint"], [q[6], 0.01])
            else:
                bag.write_joint_state(JOINTS_T0 + 0.01 * k, ARM + ["finger_left_joint"], list(q) + [0.01])
    stamps, qs = _split_expectation(q_all) if split else (list(JOINTS_T0 + 0.01 * np.arange(len(q_all))), list(q_all))
    env = ros_env(tmp_path)
    node = NodeProcess.node("kinematics_node", env, tmp_path, params={"model_file": str(MODEL),
                                                                       "use_sim_time": True,
                                                                       "joint_states_reliable": True})
    recorder = NodeProcess.ppoe(["record", "--out", str(rec), "--max-messages", str(len(qs)), "/ppoe/pose"], env,
                                tmp_path, "record")
    player = None
    try:
        # node and recorder up: the recorder subscribes /ppoe/pose once it sees the node's publisher
        # (polled, not a fixed sleep: on a loaded machine start-up takes longer)
        deadline = time.monotonic() + 30
        while "recording /ppoe/pose" not in recorder.output():
            assert node.alive() and recorder.alive() and time.monotonic() < deadline, \
                f"recorder never subscribed /ppoe/pose\n{recorder.output()[-2000:]}\n{node.output()[-2000:]}"
            time.sleep(0.05)
        time.sleep(0.5)  # let the new subscription match the node's publisher (discovery is asymmetric)
        player = NodeProcess.ppoe(["play", str(src), "--clock", "--wait-for-subscribers", "15"], env, tmp_path,
                                  "play")
        assert player.wait(40) == 0, player.output()
        # the recorder exits by itself after len(qs) poses (a fixed sleep lost the last one under load)
        assert recorder.wait(30) == 0, f"recorder did not get {len(qs)} poses\n{recorder.output()[-2000:]}"
        assert node.alive(), node.output()
    finally:
        if player is not None:
            player.stop()
        recorder.stop()
        node.stop()
    poses = read_bag(rec).poses_with_covariance["/ppoe/pose"]
    assert len(poses) == len(qs), f"{len(poses)} poses recorded\n{node.output()[-2000:]}"
    np.testing.assert_allclose(poses.stamps, stamps, atol=1e-9)
    for k, q in enumerate(qs):
        T_ref, cov_ref = model.fk(dict(zip(ARM, q)), "base_link", "tool0")
        np.testing.assert_allclose(poses.T[k], T_ref, atol=1e-12)
        np.testing.assert_allclose(poses.cov_ros[k], lie.cov_local_to_ros(T_ref, cov_ref), rtol=1e-10, atol=1e-18)
    assert set(poses.frame_ids) == {"base_link"}


def test_unknown_frame_or_model_file_refused_at_startup(tmp_path: Path) -> None:
    from rclpy.parameter import Parameter

    from ppoe_core.errors import ModelConfigError, UnknownFrameError, UnknownJointError
    from ppoe_ros.nodes.kinematics_node import KinematicsNode

    env = ros_env(tmp_path)
    urdf = Parameter("robot_description", value=URDF.read_text())
    with Probe(env) as probe:
        with pytest.raises(UnknownFrameError, match="parameter robot_description: unknown frame/link 'nope'"):
            KinematicsNode(context=probe.context, parameter_overrides=[urdf, Parameter("target_frame", value="nope")])
        with pytest.raises(ModelConfigError, match="/no/such.yaml: cannot read model file"):
            KinematicsNode(context=probe.context, parameter_overrides=[urdf,
                                                                       Parameter("model_file", value="/no/such.yaml")])
        bad = tmp_path / "bad_model.yaml"
        bad.write_text("frames: {base: base_link, tool: tool0}\n"
                       "perturbations:\n  joint_9: {sigma: [0, 0, 0, 0, 0, 1]}\n")
        with pytest.raises(
            UnknownJointError,
            match=r"parameter robot_description: .*bad_model.yaml:3: "
            r"perturbations.joint_9: unknown joint 'joint_9'",
        ):
            KinematicsNode(context=probe.context, parameter_overrides=[urdf, Parameter("model_file", value=str(bad))])
        with pytest.raises(ModelConfigError, match="'extra_target_frames' repeats 'tool0'"):
            KinematicsNode(
                context=probe.context,
                parameter_overrides=[urdf, Parameter("extra_target_frames", value=["arm_link_3", "tool0"])],
            )
        node = KinematicsNode(
            context=probe.context, parameter_overrides=[urdf, Parameter("model_file", value=str(MODEL))]
        )
        try:  # defaults from the model YAML frames section; needed joints = the arm's 7
            assert node.reference == "base_link" and node.targets[0].frame == "tool0"
            assert node._history.needed == ARM
        finally:
            node.destroy_node()


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_diagnostics_error_without_model_and_warn_when_the_input_is_silent(tmp_path: Path) -> None:
    """/diagnostics: ERROR 'no model' until the URDF arrives; OK while joint states flow; WARN 'no /joint_states
    for X s' once they stop for longer than input_timeout; OK again when they resume."""
    from std_msgs.msg import String

    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "p.yaml", {"model_file": str(MODEL), "input_timeout": 0.6,
                                                 "diagnostics_period": 0.2})
    with Probe(env) as probe, NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf) as proc:
        diags = probe.collect("/diagnostics", DiagnosticArray)
        js = probe.publisher("/joint_states", JointState, 100)

        def last() -> DiagnosticStatus | None:
            st = [s for d in diags for s in d.status if s.name == "/kinematics_node: health"]
            return st[-1] if st else None

        probe.spin_until(lambda: last() is not None, 15, proc, "/diagnostics")
        assert last().level == DiagnosticStatus.ERROR and "no model" in last().message
        desc = probe.publisher("/robot_description", String, LATCHED_QOS)
        desc.publish(String(data=URDF.read_text()))
        probe.wait_for_subscribers(js, proc)
        # the model is built from the URDF first (2 s and more on a loaded machine, in a container process too)
        probe.spin_until(lambda: "no model" not in last().message, 20, proc, "the model from /robot_description")
        t = [1.0]

        def feed(seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                t[0] += 0.02
                msg = JointState(name=ARM, position=[0.1] * 7)
                msg.header.stamp = ns_to_stamp(int(t[0] * 1e9))
                js.publish(msg)
                probe.spin_for(0.02)

        feed(1.0)
        assert last().level == DiagnosticStatus.OK, last().message
        probe.spin_until(lambda: last().level == DiagnosticStatus.WARN and "no /joint_states for" in last().message,
                         10, proc, "WARN: the input went silent")
        feed(0.6)
        assert last().level == DiagnosticStatus.OK, last().message
