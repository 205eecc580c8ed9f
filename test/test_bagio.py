"""Round trips of ppoe_core.io.bagio: every contract topic written, read back, compared."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import random_pose_quat as _rand_pose

from ppoe_core.errors import BagError
from ppoe_core.io import bagio


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip_every_topic(tmp_path: Path, storage: str) -> None:
    rng = np.random.default_rng(1)
    path = tmp_path / "bag"
    K = np.array([[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]])
    D = np.array([0.1, -0.05, 0.001, 0.002, 0.01])
    img = (rng.random((48, 64)) * 255).astype(np.uint8)
    img_bgr = (rng.random((48, 64, 3)) * 255).astype(np.uint8)
    T_gt = _rand_pose(rng)
    T_pc = _rand_pose(rng)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    uv = rng.random((5, 2)) * 600
    xy = rng.normal(size=(5, 2))
    with bagio.BagWriter(path, storage=storage) as bag:
        bag.write_robot_description("<robot name='r'/>", 0.0)
        bag.write_joint_state(1.0, ["a", "b"], [0.1, 0.2], velocities=[1.0, 2.0])
        bag.write_camera_info(1.01, "cam", 64, 48, K, D)
        bag.write_compressed_image(1.01, "cam", img, "png")
        bag.write_wrench(1.02, "tool0", [1, 2, 3], [4, 5, 6])
        bag.write_ground_truth_pose(1.03, "base_link", T_gt)
        bag.write_ground_truth_point(1.04, "tracker", [1.5, -2.0, 0.25])
        bag.write_imu("base", 1.05, "base_link", [0.1, 0.2, 9.81], accel_sigma=0.01)
        bag.write_tag_observations(1.06, "cam", [3, 3, 3, 3, 3], [0, 1, 2, 3, 4], uv, xy)
        bag.write_pose_with_covariance("/ppoe/pose", 1.07, "base_link", T_pc, cov)
        bag.write_message("/chatter", bagio.typestore().types["std_msgs/msg/String"](data="hi"), 1.08)
    data = bagio.read_bag(path)
    assert data.robot_description == "<robot name='r'/>"
    js = data.joint_states
    assert js.names == ["a", "b"]
    np.testing.assert_allclose(js.positions, [[0.1, 0.2]])
    np.testing.assert_allclose(js.velocities, [[1.0, 2.0]])
    assert np.all(np.isnan(js.efforts))
    np.testing.assert_allclose(js.stamps, [1.0])
    np.testing.assert_allclose(data.camera_info.K[0], K)
    np.testing.assert_allclose(data.camera_info.D[0], D)
    assert data.camera_info.frame_ids == ["cam"] and data.camera_info.width[0] == 64
    assert data.images.formats == ["png"]
    np.testing.assert_array_equal(data.images.decode(0), img)
    np.testing.assert_allclose(data.wrench.force, [[1, 2, 3]])
    np.testing.assert_allclose(data.wrench.torque, [[4, 5, 6]])
    np.testing.assert_allclose(data.ground_truth_pose.T[0], T_gt, atol=1e-12)
    assert data.ground_truth_pose.frame_ids == ["base_link"]
    np.testing.assert_allclose(data.ground_truth_point.p, [[1.5, -2.0, 0.25]])
    np.testing.assert_allclose(data.imus["base"].linear_acceleration, [[0.1, 0.2, 9.81]])
    np.testing.assert_allclose(np.diag(data.imus["base"].accel_covariance[0]), [1e-4] * 3)
    to = data.tag_observations
    assert to.ids.tolist() == [3] * 5 and to.corners.tolist() == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(to.uv, uv)
    np.testing.assert_allclose(to.xy, xy)
    np.testing.assert_allclose(to.message(0)["uv"], uv)
    pc = data.poses_with_covariance["/ppoe/pose"]
    np.testing.assert_allclose(pc.T[0], T_pc, atol=1e-12)
    np.testing.assert_allclose(pc.cov_ros[0], cov)
    assert data.unknown_topics == {"/chatter": "std_msgs/msg/String"}
    assert data.topics["/joint_states"] == ("sensor_msgs/msg/JointState", 1)

    # a second bag with the bgr raw image and a jpeg
    path2 = tmp_path / "bag2"
    with bagio.BagWriter(path2, storage=storage) as bag:
        bag.write_image(2.0, "cam", img_bgr)
    d2 = bagio.read_bag(path2)
    np.testing.assert_array_equal(d2.images.decode(0), img_bgr)
    assert d2.images.decode(0, grey=True).shape == (48, 64)
    path3 = tmp_path / "bag3"
    with bagio.BagWriter(path3, storage=storage) as bag:
        bag.write_compressed_image(2.0, "cam", img_bgr, "jpeg")
    d3 = bagio.read_bag(path3)
    assert d3.images.formats == ["jpeg"] and d3.images.decode(0).shape == (48, 64, 3)


def test_joint_states_changing_order_and_extra_joints(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    with bagio.BagWriter(path) as bag:
        bag.write_joint_state(0.00, ["j1", "j2", "j3"], [1.0, 2.0, 3.0])
        bag.write_joint_state(0.01, ["j3", "j1", "j2"], [13.0, 11.0, 12.0])
        bag.write_joint_state(0.02, ["gripper", "j2", "j1", "j3"], [0.5, 22.0, 21.0, 23.0])
        bag.write_joint_state(0.03, ["j2"], [32.0])
    js = bagio.read_bag(path).joint_states
    assert js.names == ["j1", "j2", "j3", "gripper"]
    expected = np.array([[1, 2, 3, np.nan], [11, 12, 13, np.nan], [21, 22, 23, 0.5], [np.nan, 32, np.nan, np.nan]])
    np.testing.assert_array_equal(js.positions, expected)
    np.testing.assert_allclose(js.stamps, [0.0, 0.01, 0.02, 0.03])
    assert js.as_dict(3) == {"j2": 32.0}
    np.testing.assert_array_equal(js.column("j3")[:3], [3, 13, 23])
    with pytest.raises(BagError, match="joint 'nope'"):
        js.column("nope")
    assert bagio.read_bag(path).rate("/joint_states") == pytest.approx(100.0)


def test_contract_violations_name_the_topic(tmp_path: Path) -> None:
    ts = bagio.typestore()
    # wrong type on a contract topic
    path = tmp_path / "wrongtype"
    from rosbags.rosbag2 import Writer

    with Writer(path, version=9) as w:
        c = w.add_connection("/joint_states", "std_msgs/msg/String", typestore=ts)
        w.write(c, 1, bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String")))
    with pytest.raises(BagError, match="/joint_states"):
        bagio.read_bag(path)
    # writer refuses it as well
    with bagio.BagWriter(tmp_path / "w2") as bag:
        with pytest.raises(BagError, match="/wrench"):
            bag.write_message("/wrench", ts.types["std_msgs/msg/String"](data="x"), 0.0)
    # JointState with mismatched name / position lengths (written raw)
    path = tmp_path / "badjs"
    JS = ts.types["sensor_msgs/msg/JointState"]
    msg = JS(header=bagio.header_msg(0, ""), name=["a", "b"], position=np.array([1.0]),
             velocity=np.zeros(0), effort=np.zeros(0))
    with bagio.BagWriter(path) as bag:
        bag.write_raw("/joint_states", "sensor_msgs/msg/JointState", 5, bagio.serialize(msg, JS.__msgtype__))
    with pytest.raises(BagError, match="/joint_states: message 0 has 2 names but 1 positions"):
        bagio.read_bag(path)
    # corrupt png
    path = tmp_path / "badimg"
    with bagio.BagWriter(path) as bag:
        bag.write_compressed_image(1.0, "cam", b"not a png", "png")
    with pytest.raises(BagError, match="/camera/image_raw/compressed"):
        bagio.read_bag(path).images.decode(0)
    with pytest.raises(BagError, match="does not exist"):
        bagio.read_bag(tmp_path / "nothere")
    with pytest.raises(BagError, match="exists already"):
        bagio.BagWriter(path)


def test_raw_iteration_and_padding_tolerance(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    with bagio.BagWriter(path) as bag:
        bag.write_robot_description("<robot/>", 0.0)
        bag.write_joint_state(0.5, ["a"], [1.0])
    raws = list(bagio.iter_raw(path))
    assert [(r.topic, r.msgtype, r.stamp_ns) for r in raws] == [
        ("/robot_description", "std_msgs/msg/String", 0),
        ("/joint_states", "sensor_msgs/msg/JointState", 500_000_000)]
    # bytes with extra zero padding (as FastCDR may write) re-written via write_raw read back
    padded = raws[1].data + b"\x00" * 6
    path2 = tmp_path / "bag2"
    with bagio.BagWriter(path2) as bag:
        bag.write_raw(raws[1].topic, raws[1].msgtype, raws[1].stamp_ns, padded)
    js = bagio.read_bag(path2).joint_states
    np.testing.assert_allclose(js.positions, [[1.0]])
    assert list(bagio.iter_raw(path2, topics=["/nothing"])) == []
    assert bagio.bag_topics(path2) == {"/joint_states": ("sensor_msgs/msg/JointState", 1)}


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st

_NAMES = [f"j{i}" for i in range(6)]


@settings(max_examples=15, deadline=None)
@given(st.lists(st.permutations(_NAMES).flatmap(lambda p: st.integers(1, 6).map(lambda k: p[:k])),
                min_size=1, max_size=6),
       st.integers(0, 2**31 - 1))
def test_joint_alignment_property(tmp_path_factory: pytest.TempPathFactory, orders: list, seed: int) -> None:
    """Any order and subset of joints per message reads back aligned by name (NaN where absent)."""
    rng = np.random.default_rng(seed)
    path = tmp_path_factory.mktemp("prop") / "bag"
    truth = []
    with bagio.BagWriter(path) as bag:
        for i, names in enumerate(orders):
            vals = rng.normal(size=len(names))
            bag.write_joint_state(0.01 * (i + 1), names, vals)
            truth.append(dict(zip(names, vals)))
    js = bagio.read_bag(path).joint_states
    assert len(js) == len(orders)
    assert sorted(js.names) == sorted({n for o in orders for n in o})
    for i, row in enumerate(truth):
        for j, n in enumerate(js.names):
            if n in row:
                assert js.positions[i, j] == row[n]
            else:
                assert np.isnan(js.positions[i, j])


@pytest.mark.parametrize("names,pos,vel,eff", [
    ([], [], None, None),
    (["a"], [1.5], None, None),
    (["joint_1", "j2", "abc"], [0.1, -0.2, 3.0], [1.0, 2.0, 3.0], None),
    (["x" * 7, "yy"], [1e-9, -1e9], None, [4.0, 5.0]),
])
def test_fast_joint_state_cdr_equals_rosbags(names: list, pos: list, vel: list | None, eff: list | None) -> None:
    ts = bagio.typestore()
    JS = ts.types["sensor_msgs/msg/JointState"]
    arr = lambda a: np.asarray(a if a is not None else [], dtype=np.float64)  # noqa: E731
    for ns in (0, 1_234_567_891_011, 99):
        msg = JS(header=bagio.header_msg(ns, ""), name=names, position=arr(pos), velocity=arr(vel), effort=arr(eff))
        ref = bagio.serialize(msg, JS.__msgtype__)
        assert bagio.cdr_joint_state(ns, names, arr(pos), arr(vel), arr(eff)) == ref


def test_both_image_topics_and_empty_tag_observations(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    img = np.full((8, 10), 7, dtype=np.uint8)
    with bagio.BagWriter(path) as bag:
        bag.write_image(1.0, "cam", img)
        bag.write_compressed_image(1.0, "cam", img + 1)
        bag.write_tag_observations(1.0, "cam", [], [], np.zeros((0, 2)), np.zeros((0, 2)))
        bag.write_tag_observations(1.1, "cam", [4], [0], [[1.0, 2.0]], [[0.1, 0.2]])
    d = bagio.read_bag(path)
    assert d.images.topic == "/camera/image_raw/compressed" and d.images.decode(0)[0, 0] == 8
    assert d.raw_images.topic == "/camera/image_raw" and d.raw_images.decode(0)[0, 0] == 7
    assert d.rate("/camera/image_raw") == 0.0
    to = d.tag_observations
    assert len(to) == 2 and to.msg_index.tolist() == [1] and to.ids.tolist() == [4]
    assert to.message(0)["uv"].shape == (0, 2)
    with pytest.raises(BagError, match="/tag_bearing/observations: ids, corners, uv and xy"):
        with bagio.BagWriter(tmp_path / "b2") as bag:
            bag.write_tag_observations(1.0, "cam", [1, 2], [0], [[1.0, 2.0]], [[0.1, 0.2]])


def test_writer_in_a_path_that_cannot_be_created(tmp_path: Path) -> None:
    """A bag directory under a regular file: BagError naming the bag, not an OSError traceback."""
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(BagError, match=r"bag .*a_file/bag: cannot create the bag directory"):
        with bagio.BagWriter(blocker / "bag"):
            pass
