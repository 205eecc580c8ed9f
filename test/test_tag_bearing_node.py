"""Tag bearing node: pure helpers in-process, and the node through live topics."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")

import cv2  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from ppoe_core import lie  # noqa: E402
from ppoe_core.errors import MeasurementError  # noqa: E402
from ppoe_core.estimation import camera
from ppoe_core.sensing import tags
from ppoe_core.sensing.tag_rows import observe_tags  # noqa: E402  (what the node publishes)
from ppoe_ros.common.tag_cloud import cloud_from_observations, observations_from_cloud  # noqa: E402
from ppoe_core.io.images import camera_from_info, decode_image  # noqa: E402

W, H = 640, 480
K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])
D = np.array([-0.08, 0.02, 0.001, -0.0005, 0.0])
TAG_IDS = [3, 7]
SIZE = 0.06


def _scene():
    """Two tags in front of the camera, slightly tilted; returns (image, T_cam_tag list)."""
    T1 = lie.from_xyz_rpy([-0.07, 0.02, 0.5], [np.pi + 0.25, -0.2, 0.1])
    T2 = lie.from_xyz_rpy([0.08, -0.03, 0.55], [np.pi - 0.15, 0.3, -0.4])
    img, drawn = tags.render_tags((W, H), K, D, [T1, T2], TAG_IDS, SIZE, supersample=4)
    assert sorted(drawn) == TAG_IDS
    return img, [T1, T2]


def _truth(T_list):
    """True [id, corner, u, v, x, y] rows from the known poses (centre + 4 corners per tag)."""
    rows = []
    for tid, T in zip(TAG_IDS, T_list):
        P = tags.tag_points_local(SIZE) @ T[:3, :3].T + T[:3, 3]
        uv = camera.project_points(P, K, D)
        xy = P[:, :2] / P[:, 2:]
        for c in range(5):
            rows.append([tid, c, *uv[c], *xy[c]])
    return np.array(rows)


def test_observe_tags_matches_known_projection():
    img, T_list = _scene()
    rows, dets = observe_tags(img, K, D, "tag36h11")
    truth = _truth(T_list)
    assert rows.shape == truth.shape
    np.testing.assert_array_equal(rows[:, :2], truth[:, :2])
    err_px = np.linalg.norm(rows[:, 2:4] - truth[:, 2:4], axis=1)
    assert err_px.max() < 0.5, err_px
    # normalised coordinates: the same error scaled by 1/f (~0.5 px / 600 px)
    err_n = np.linalg.norm(rows[:, 4:6] - truth[:, 4:6], axis=1)
    assert err_n.max() < 0.5 / 600 * 1.5
    # x, y are exactly the undistorted coordinates of u, v (centre: distorted back)
    np.testing.assert_allclose(camera.undistort_pixels(rows[:, 2:4], K, D), rows[:, 4:6], atol=1e-9)
    # filtering by id
    rows7, _ = observe_tags(img, K, D, "tag36h11", tag_ids=[7])
    assert set(rows7[:, 0]) == {7.0} and rows7.shape == (5, 6)
    assert observe_tags(np.full((H, W), 128, np.uint8), K, D)[0].shape == (0, 6)


def test_cloud_round_trip_and_layout():
    rows = np.arange(30, dtype=float).reshape(5, 6)
    msg = cloud_from_observations(rows, Header(frame_id="cam"))
    assert [f.name for f in msg.fields] == ["id", "corner", "u", "v", "x", "y"]
    assert msg.point_step == 48 and msg.width == 5 and len(msg.data) == 240
    back = observations_from_cloud(msg)
    np.testing.assert_array_equal(np.column_stack([back[k] for k in ("id", "corner", "u", "v", "x", "y")]), rows)
    msg.fields = msg.fields[:3]
    with pytest.raises(MeasurementError, match="no field 'v'"):
        observations_from_cloud(msg)


def test_decode_image_and_camera_info_errors():
    img = (np.arange(12, dtype=np.uint8).reshape(3, 4) * 20)
    ok, png = cv2.imencode(".png", img)
    np.testing.assert_array_equal(decode_image(CompressedImage(format="png", data=png.tobytes()), True), img)
    with pytest.raises(MeasurementError, match="empty"):
        decode_image(CompressedImage(format="png", data=b""), True)
    with pytest.raises(MeasurementError, match="cannot decode"):
        decode_image(CompressedImage(format="png", data=b"\x89PNG garbage" * 10), True)
    rgb = np.dstack([img, img + 1, img + 2])
    raw = Image(height=3, width=4, encoding="rgb8", step=12, data=rgb.tobytes())
    np.testing.assert_array_equal(decode_image(raw, False), rgb[..., ::-1])
    raw.step = 20  # padded rows
    raw.data = np.pad(rgb.reshape(3, 12), ((0, 0), (0, 8))).tobytes()
    np.testing.assert_array_equal(decode_image(raw, False), rgb[..., ::-1])
    with pytest.raises(MeasurementError, match="does not fit"):
        decode_image(Image(height=3, width=4, encoding="mono8", step=4, data=b"\0" * 5), False)
    with pytest.raises(MeasurementError, match="encoding 'yuv422'"):
        decode_image(Image(height=1, width=1, encoding="yuv422", step=2, data=b"\0\0"), False)
    info = CameraInfo(k=K.ravel().tolist(), d=D.tolist(), distortion_model="plumb_bob")
    K2, D2 = camera_from_info(info)
    np.testing.assert_array_equal(K2, K)
    with pytest.raises(MeasurementError, match="K is not a camera matrix"):
        camera_from_info(CameraInfo(k=[0.0] * 9, d=D.tolist(), distortion_model="plumb_bob"))
    with pytest.raises(MeasurementError, match="equidistant"):
        camera_from_info(CameraInfo(k=K.ravel().tolist(), d=[0.1] * 4, distortion_model="equidistant"))


# ----------------------------------------------------------------------------- live


@pytest.mark.ros
@pytest.mark.timeout(90)
def test_node_live_good_bad_good(tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from ros_helpers import NodeProcess, Probe, ros_env

    img, T_list = _scene()
    truth = _truth(T_list)
    ok, png = cv2.imencode(".png", img)
    env = ros_env(tmp_path)
    params = {"tag_ids": TAG_IDS, "publish_debug_image": True, "diagnostics_period": 0.2, "log_throttle": 0.0}
    with Probe(env) as probe, NodeProcess.node("tag_bearing_node", env, tmp_path, params=params) as proc:
        obs = probe.collect("/tag_bearing/observations", PointCloud2)
        dbg = probe.collect("/tag_bearing/debug_image", Image)
        diags = probe.collect("/diagnostics", DiagnosticArray)
        pub_img = probe.publisher("/camera/image_raw/compressed", CompressedImage)
        pub_info = probe.publisher("/camera/camera_info", CameraInfo)
        probe.wait_for_subscribers(pub_img, proc)
        probe.wait_for_subscribers(pub_info, proc)

        def header(k):
            return Header(frame_id="camera_optical_frame", stamp=probe.node.get_clock().now().to_msg()) \
                if k is None else Header(frame_id="camera_optical_frame", stamp={"sec": k, "nanosec": 0})

        def send_info(k_list):
            pub_info.publish(CameraInfo(header=header(None), width=W, height=H, k=k_list, d=D.tolist(),
                                        distortion_model="plumb_bob"))

        def send_img(data, sec):
            m = CompressedImage(format="png", data=data)
            m.header.frame_id = "camera_optical_frame"
            m.header.stamp.sec = sec
            pub_img.publish(m)

        probe.spin_for(0.5)  # let discovery settle in both directions

        def counts():
            return {kv.key: kv.value for kv in diags[-1].status[0].values} if diags else {}

        # image before any camera_info: dropped, counted (resent: best effort may lose one)
        for _ in range(5):
            send_img(png.tobytes(), 1)
            probe.spin_for(0.5)
            if counts().get("dropped", "0") != "0":
                break
        send_info(K.ravel().tolist())
        probe.spin_for(0.3)
        send_img(png.tobytes(), 2)
        probe.spin_until(lambda: len(obs) >= 1, 20, proc, "first observation")
        # bad input: zero K, empty image, corrupt image
        send_info([0.0] * 9)
        send_img(b"", 3)
        send_img(b"\x89PNG\r\n\x1a\n" + b"\x00garbage" * 50, 4)
        probe.spin_for(0.5)
        send_img(png.tobytes(), 5)
        probe.spin_until(lambda: len(obs) >= 2 and len(dbg) >= 2, 20, proc, "output after the bad input")
        probe.spin_until(lambda: counts().get("bad") == "3" and counts().get("published") == "2", 10, proc,
                         "diagnostics with bad = 3, published = 2")
        assert proc.alive()
        log = proc.output()
    assert [m.header.stamp.sec for m in obs] == [2, 5]
    for m in obs:
        assert m.header.frame_id == "camera_optical_frame"
        d = observations_from_cloud(m)
        rows = np.column_stack([d[k] for k in ("id", "corner", "u", "v", "x", "y")])
        np.testing.assert_array_equal(rows[:, :2], truth[:, :2])
        assert np.abs(rows[:, 2:4] - truth[:, 2:4]).max() < 0.5
    assert len(dbg) >= 2 and dbg[0].encoding == "bgr8" and dbg[0].width == W
    last = {kv.key: kv.value for kv in diags[-1].status[0].values}
    assert int(last["dropped"]) >= 1 and last["published"] == "2" and last["detections"] == "4"
    assert "K is not a camera matrix" in log and "empty image" in log and "cannot decode" in log


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_node_refuses_unknown_dictionary(tmp_path):
    from ros_helpers import NodeProcess, ros_env

    env = ros_env(tmp_path)
    proc = NodeProcess.node("tag_bearing_node", env, tmp_path, params={"dictionary": "tag99h1"})
    code = proc.wait(timeout=40)
    out = proc.output()
    proc.stop()
    assert code == 2
    assert "parameter 'dictionary'" in out and "tag99h1" in out


def test_image_size_read_from_the_header_and_huge_images_refused_before_decoding():
    """A small PNG that decodes to a huge image is refused from its header (issue 13 item 8); an image whose
    size differs from camera_info is refused naming both sizes (item 3)."""
    import struct
    import zlib

    import cv2
    from sensor_msgs.msg import CompressedImage

    from ppoe_core.io.images import check_image_size, image_size_from_header

    ok, png = cv2.imencode(".png", np.zeros((48, 64), np.uint8))
    ok2, jpg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))
    assert ok and ok2
    assert image_size_from_header(png.tobytes()) == (64, 48)
    assert image_size_from_header(jpg.tobytes()) == (64, 48)
    assert image_size_from_header(b"not an image") is None
    # the IHDR of the small PNG rewritten to 8000 x 8000 (CRC fixed): decoding would allocate 64 M pixels
    data = bytearray(png.tobytes())
    data[16:24] = struct.pack(">II", 8000, 8000)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    msg = CompressedImage(format="png", data=bytes(data))
    with pytest.raises(MeasurementError, match="8000x8000 pixels .* larger than max_image_pixels"):
        decode_image(msg, compressed=True)
    assert decode_image(CompressedImage(format="png", data=png.tobytes()), compressed=True).shape == (48, 64)
    check_image_size(np.zeros((480, 640), np.uint8), (640, 480))
    with pytest.raises(MeasurementError, match="image is 1280x960 but camera_info gives 640x480"):
        check_image_size(np.zeros((960, 1280), np.uint8), (640, 480))
