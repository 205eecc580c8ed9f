"""The kinematics node's compiled per-message path (ppoe_core/io/joint_pose.py) against its Python path.

Two nodes in this process get the same random stream of serialised joint states: one as shipped (the compiled
path, falling back to Python for anything unusual), one with the compiled path switched off.  The published
bytes (every target) and the diagnostics counters must be identical, and most messages must have taken the
compiled path.
"""

from __future__ import annotations

import inspect
import struct
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from ros_helpers import REPO, Probe, ros_env  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from ppoe_core.io.joint_pose import MAX_LAYOUTS, JointPoseFastPath, chain_pose_cdr, joint_state_pose  # noqa: E402

URDF = REPO / "config" / "robots" / "arm7.urdf"
MODEL = REPO / "config" / "robots" / "arm7_model.yaml"
ARM = [f"joint_{i}" for i in range(1, 8)]
EXTRA = "camera_optical_frame"
MS = 1_000_000


class _Capture:
    """Stands in for a pose publisher: keeps what is published."""

    def __init__(self, topic: str, out: list) -> None:
        self.topic_name = topic
        self._out = out

    def publish(self, data: bytes) -> None:
        self._out.append((self.topic_name, data))


def _serialise(stamp_ns: int, names: list[str], positions: list[float], frame: str = "base") -> bytes:
    msg = JointState(name=names, position=[float(p) for p in positions])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.header.frame_id = frame
    return serialize_message(msg)


def _layouts(rng: np.random.Generator) -> list[list[str]]:
    """Name layouts: the whole arm (with and without extra joints, in several orders) and split ones."""
    out = [ARM + ["finger_left_joint"], list(ARM), ["finger_left_joint", "mast_pan"] + ARM[::-1]]
    out += [list(rng.permutation(ARM + ["other_joint"])) for _ in range(MAX_LAYOUTS + 2)]
    # split, none of the chain, repeated names; the last has as many chain entries as the chain has joints but
    # lacks joint_7 (the merger's whole-chain step takes it)
    out += [ARM[:4], ARM[4:] + ["finger_left_joint"], ["gripper"], ARM[:3] + ARM[:1], ARM + ["joint_1"],
            ARM[:6] + ["joint_1"]]
    return out


def _stream(seed: int, n: int) -> list[bytes]:
    """Joint states with split messages, reordered names, extra joints, stale joints, NaN, stamp jumps and
    malformed bytes."""
    rng = np.random.default_rng(seed)
    layouts = _layouts(rng)
    t = 1_000 * 10**9
    # first the chain-sized message without joint_7, then a split one: joint_7 has a stamp but no value
    out = [_serialise(t, ARM[:6] + ["joint_1"], [0.1] * 7), _serialise(t, ARM[:4], [0.2] * 4)]
    for _ in range(n):
        r = rng.random()
        t += int(rng.choice([MS, 0, 700 * MS, -2 * MS, -3 * 10**9], p=[0.9, 0.03, 0.02, 0.03, 0.02]))
        names = layouts[int(rng.integers(3))] if r < 0.6 else layouts[int(rng.integers(len(layouts)))]
        pos = list(rng.uniform(-3, 3, len(names)))
        if rng.random() < 0.03:
            pos[int(rng.integers(len(pos)))] = float(rng.choice([np.nan, np.inf, -np.inf]))
        raw = _serialise(max(t, 0), list(names), pos, "base" if rng.random() < 0.97 else "bäse")
        if rng.random() < 0.02:
            raw = _serialise(max(t, 0), list(names), pos[:-1])  # one position short
        if rng.random() < 0.02:
            raw = raw[:int(rng.integers(len(raw)))]  # truncated
        out.append(raw)
    # stamps before 1970 (a new timeline, then negative seconds in the output)
    out += [_serialise(-5 * 10**9 + k * MS, ARM, list(rng.uniform(-3, 3, 7))) for k in range(20)]
    # seconds beyond int32 in the output (nanoseconds > 1e9 carry over): the Python path's error, both ways
    out.append(bytes(raw[:4]) + struct.pack("<iI", 2**31 - 1, 4_000_000_000) + bytes(raw[12:]))
    return out


def _node(probe: Probe, order: int, fast: bool, out: list):
    from ppoe_ros.nodes.kinematics_node import KinematicsNode

    node = KinematicsNode(context=probe.context, parameter_overrides=[
        Parameter("robot_description", value=URDF.read_text()), Parameter("model_file", value=str(MODEL)),
        Parameter("extra_target_frames", value=[EXTRA]), Parameter("order", value=order),
        Parameter("log_throttle", value=3600.0)])
    for t in node.targets:
        t.pub = _Capture(t.frame, out)
    if not fast:
        node._fast = None
    return node


@pytest.mark.parametrize("order,seed", [(2, 1), (4, 2), (2, 3)])
def test_compiled_path_publishes_the_same_bytes_and_counts(tmp_path: Path, order: int, seed: int) -> None:
    stream = _stream(seed, 3000)
    with Probe(ros_env(tmp_path)) as probe:
        fast_out: list = []
        slow_out: list = []
        fast = _node(probe, order, True, fast_out)
        slow = _node(probe, order, False, slow_out)
        try:
            assert isinstance(fast._fast, JointPoseFastPath)
            taken = [0]
            run = fast._fast.run

            def counted(data: bytes, limit: int) -> bool:
                ok = run(data, limit)
                taken[0] += ok
                return ok

            fast._fast.run = counted  # type: ignore[method-assign]
            for raw in stream:
                fast._on_joint_state(raw)
                slow._on_joint_state(raw)
            assert fast.stats.counts == slow.stats.counts
            assert fast.stats.counts["published"] > len(stream) // 2
            assert taken[0] > 0.5 * fast.stats.counts["published"]
            assert len(fast_out) == len(slow_out) == 2 * fast.stats.counts["published"]
            for k, (a, b) in enumerate(zip(fast_out, slow_out)):
                assert a == b, f"output {k} differs"
            np.testing.assert_array_equal(fast._history.values, slow._history.values)
            np.testing.assert_array_equal(fast._history.stamps, slow._history.stamps)
            assert fast._history.last_ns == slow._history.last_ns
            # the kernels were compiled for exactly the types the node passes: one specialisation per covariance
            # order (the `fourth` argument: None for order 2, the fourth-order work array for order 4)
            for kernel in (joint_state_pose, chain_pose_cdr):
                at = list(inspect.signature(kernel.py_func).parameters).index("fourth")
                fourth = {str(sig[at]) for sig in kernel.signatures}
                assert len(kernel.signatures) == len(fourth) <= 2, kernel.signatures
        finally:
            fast.destroy_node()
            slow.destroy_node()


def test_compiled_path_off_with_tf_or_worker(tmp_path: Path) -> None:
    """The Python path stays the only one where the compiled one does not apply (TF, batched FK)."""
    from ppoe_ros.nodes.kinematics_node import KinematicsNode

    urdf = Parameter("robot_description", value=URDF.read_text())
    with Probe(ros_env(tmp_path)) as probe:
        node = KinematicsNode(context=probe.context, parameter_overrides=[urdf, Parameter("max_batch", value=10)])
        try:
            assert node._fast is None
        finally:
            node.destroy_node()
