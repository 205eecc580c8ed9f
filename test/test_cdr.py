"""Hand-written CDR of the kinematics node's hot path against rclpy's own serialisation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ppoe_core.errors import MeasurementError
from ppoe_core.io.cdr import PoseCovarianceWriter, parse_joint_state

rclpy_serialization = pytest.importorskip("rclpy.serialization")
JointState = pytest.importorskip("sensor_msgs.msg").JointState
PoseWithCovarianceStamped = pytest.importorskip("geometry_msgs.msg").PoseWithCovarianceStamped

_frame = st.text(alphabet=st.characters(min_codepoint=32, blacklist_categories=("Cs",)), max_size=9)
_name = st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=0x2FF), min_size=1, max_size=13)


def _joint_state(stamp_ns, frame, names, positions, n_vel):
    msg = JointState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.header.frame_id = frame
    msg.name = list(names)
    msg.position = list(positions)
    msg.velocity = [0.5] * n_vel
    return msg


@settings(max_examples=60, deadline=None)
@given(stamp_ns=st.integers(0, 2**40), frame=_frame, names=st.lists(_name, max_size=9),
       n_vel=st.integers(0, 3), data=st.data())
def test_joint_state_parse_equals_rclpy(stamp_ns, frame, names, n_vel, data):
    positions = data.draw(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=len(names),
                                   max_size=len(names)))
    raw = rclpy_serialization.serialize_message(_joint_state(stamp_ns, frame, names, positions, n_vel))
    js = parse_joint_state(raw)
    assert js.stamp_ns == stamp_ns and js.frame_id == frame and js.names == tuple(names)
    np.testing.assert_array_equal(js.positions, np.array(positions, dtype=float))
    js2 = parse_joint_state(raw)  # names from the cache
    assert js2.names == tuple(names)


def test_joint_state_bad_bytes_named():
    raw = rclpy_serialization.serialize_message(_joint_state(5, "base", ["j1", "j2"], [0.1, 0.2], 0))
    for cut in (3, 14, 30, 44, 60):  # header, frame, names, position count, positions
        with pytest.raises(MeasurementError, match="JointState CDR"):
            parse_joint_state(raw[:cut])
    with pytest.raises(MeasurementError, match="little-endian"):
        parse_joint_state(b"\x00\x00\x00\x00" + raw[4:])  # big-endian header


@settings(max_examples=40, deadline=None)
@given(stamp_ns=st.integers(0, 2**40), frame=_frame,
       vals=st.lists(st.floats(-1e6, 1e6), min_size=43, max_size=43))
def test_pose_writer_equals_rclpy(stamp_ns, frame, vals):
    v = np.array(vals)
    raw = PoseCovarianceWriter(frame).serialize(stamp_ns, v[:3], v[3:7], v[7:].reshape(6, 6))
    msg = rclpy_serialization.deserialize_message(raw, PoseWithCovarianceStamped)
    assert (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, msg.header.frame_id) == (stamp_ns, frame)
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    np.testing.assert_array_equal([p.x, p.y, p.z, o.x, o.y, o.z, o.w], v[:7])
    np.testing.assert_array_equal(np.array(msg.pose.covariance), v[7:])
    ref = rclpy_serialization.serialize_message(msg)
    head = 17 + len(frame.encode())  # up to the frame's NUL; then alignment padding (not initialised by rclpy)
    assert ref[:head] == raw[:head] and ref[len(raw) - 8 * 43:len(raw)] == raw[-8 * 43:]
