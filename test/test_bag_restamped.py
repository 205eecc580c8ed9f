"""Camera calibrations read at once (:func:`ppoe_core.io.rows.finish_restamped`): ``read_bag`` gives field by field
what it gives reading every message (the index off) when the messages are one message restamped, when the intrinsics
or the frame change on the way, and when every message is damaged the same way (the same rejections); the stamps
of :func:`ppoe_core.io.cdr.restamped_stamps` are :func:`ppoe_core.io.messages.stamp_seconds`' numbers."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import REPO, assert_same_data

import ppoe_core.io.mcap_index as mcap_index
import ppoe_core.io.reader as reader_module
from ppoe_core.errors import BagError
from ppoe_core.io import cdr
from ppoe_core.io.bagio import BagWriter, read_bag
from ppoe_core.io.messages import T_CAMERA_INFO, TOPIC_CAMERA_INFO, deserialize, serialize, stamp_seconds

K = np.array([[500.0, 0.0, 320.5], [0.0, 501.0, 240.25], [0.0, 0.0, 1.0]])
#: stamps [s]: fractions that are not whole nanoseconds in binary, up to the last second of int32
STAMPS = [0.0, 0.1, 0.3, 1.0 / 3.0, 7.000000001, 12.5, 99.99, 1234567.891, 2.0**31 - 1.5]



def _bag(path: Path, change: str = "", damaged: bool = False) -> Path:
    """Joint states and a camera calibration at every stamp of :data:`STAMPS`; ``change`` "K" or "frame": one message
    on the way differs there; ``damaged``: every calibration message has 12 non-zero trailing bytes."""
    with BagWriter(path) as bag:
        bag.write_robot_description((REPO / "config" / "robots" / "planar3.urdf").read_text(), 0.0)
        for i, t in enumerate(STAMPS):
            bag.write_joint_state(t, ["joint_1", "joint_2", "joint_3"], [0.1 * i, 0.2, 0.3])
            Ki = K + (i == 5 and change == "K") * np.diag([1e-9, 0.0, 0.0])
            frame = "cam_02" if i == 6 and change == "frame" else "camera"  # as long: one array of rows
            if not damaged:
                bag.write_camera_info(t, frame, 640, 480, Ki, [0.01, -0.002, 0.0, 0.0, 0.0])
                continue
            msg = deserialize(_calibration(t), T_CAMERA_INFO)
            bag.write_raw(TOPIC_CAMERA_INFO, T_CAMERA_INFO, int(round(t * 1e9)),
                          serialize(msg, T_CAMERA_INFO) + b"\x07" * 12, normalise=False)
    return path


def _calibration(t: float) -> bytes:
    """A CameraInfo message's bytes as the writer makes them."""
    from ppoe_core.io.writer import header_msg, stamp_to_ns
    from ppoe_core.io.messages import typestore

    types = typestore().types
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg = types[T_CAMERA_INFO](
        header=header_msg(stamp_to_ns(t), "camera"), height=480, width=640, distortion_model="plumb_bob",
        d=np.array([0.01, -0.002, 0.0, 0.0, 0.0]), k=K.reshape(-1).copy(), r=np.eye(3).reshape(-1),
        p=P.reshape(-1), binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    return serialize(msg, T_CAMERA_INFO)


def _both(path: Path, monkeypatch: pytest.MonkeyPatch, **kw: Any) -> tuple[Any, Any, list[bool]]:
    """read_bag with the index (recording what finish_restamped answered) and without it (message by message)."""
    answers: list[bool] = []
    real = reader_module.finish_restamped

    def spy(*a: Any) -> bool:
        answers.append(real(*a))
        return answers[-1]

    monkeypatch.setattr(reader_module, "finish_restamped", spy)
    at_once = read_bag(path, **kw)
    monkeypatch.setattr(mcap_index, "USE_INDEX", False)
    one_by_one = read_bag(path, **kw)
    monkeypatch.setattr(mcap_index, "USE_INDEX", True)
    return at_once, one_by_one, answers


@pytest.mark.parametrize("change", ["", "K", "frame"])
def test_calibrations_read_at_once_equal_those_read_one_by_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                change: str) -> None:
    at_once, one_by_one, answers = _both(_bag(tmp_path / "bag", change), monkeypatch)
    assert_same_data(at_once, one_by_one)
    assert answers == [change == ""]  # restamped: read at once; else message by message
    assert len(at_once.camera_info) == len(STAMPS)
    assert at_once.camera_info.stamps.tolist() == [float(s) for s in one_by_one.camera_info.stamps]


def test_damaged_calibrations_are_rejected_as_one_by_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _bag(tmp_path / "bag", damaged=True)
    at_once, one_by_one, answers = _both(path, monkeypatch, accept_partial=True)
    assert_same_data(at_once, one_by_one)
    assert answers == [False] and len(at_once.camera_info) == 0
    assert any(TOPIC_CAMERA_INFO in note for note in at_once.notes)
    with pytest.raises(BagError, match="camera_info"):
        read_bag(path)


def test_restamped_stamps_are_stamp_seconds_and_any_other_byte_refuses() -> None:
    raws = [_calibration(t) for t in STAMPS]
    raws[2] = raws[2][:4] + struct.pack("<iI", -3, 250_000_000) + raws[2][12:]  # a stamp before 1970
    arr = np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), -1).copy()
    got = cdr.restamped_stamps(arr)
    assert got is not None
    assert got.tolist() == [stamp_seconds(deserialize(r, T_CAMERA_INFO).header) for r in raws]
    assert got[2] == -2.75
    for col in (0, 3, 12, 20, arr.shape[1] - 1):  # encapsulation, frame id length, frame id, last byte
        bad = arr.copy()
        bad[4, col] ^= 1
        assert cdr.restamped_stamps(bad) is None, col
    assert cdr.restamped_stamps(arr[:0]) is None and cdr.restamped_stamps(arr[:, :11]) is None
