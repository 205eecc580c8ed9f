"""Tag detection in windows predicted by the forward kinematics (``ppoe evaluate``): the same tags with the same
corners, bit for bit, as detection on the whole image, and the whole image wherever the windows cannot promise that."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from test_tags import _frames

from ppoe_core.analysis.evaluate import replay
from ppoe_core.analysis.evaluate.inputs import required_joints
from ppoe_core.analysis.evaluate.options import EvaluateOptions
from ppoe_core.analysis.evaluate.tag_stream import TagStream
from ppoe_core.io.bagio import read_bag
from ppoe_core.sensing import tag_windows as tw
from ppoe_core.sensing import tags as tm
from ppoe_core.sensing.tag_rows import detect_tags_windowed

REPO = Path(__file__).resolve().parents[1]
#: shipped bags with images, and their model YAML
BAGS = {"table1_exp1": "rover_model.yaml", "table1_exp2": "rover_model.yaml",
        "effect_camera_extrinsics": "arm7_model.yaml"}


def _grey_images(bag: str) -> list[np.ndarray]:
    imgs = read_bag(REPO / "bags" / bag).images
    out = [imgs.decode(i) for i in range(len(imgs))]
    return [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im for im in out]


def _same(a: list[tm.TagDetection], b: list[tm.TagDetection]) -> bool:
    return len(a) == len(b) and all(x.id == y.id and np.array_equal(x.corners, y.corners)
                                    and np.array_equal(x.centre, y.centre) for x, y in zip(a, b))


def _margin(d: tm.TagDetection) -> int:
    """The clearance :func:`ppoe_core.sensing.tags.detect_tags_in_windows` keeps around ``d`` [px], rounded up."""
    perimeter = float(np.sum(np.linalg.norm(d.corners - np.roll(d.corners, -1, axis=0), axis=1)))
    return int(np.ceil(tw.WINDOW_CLEARANCE + tw.WINDOW_GROUP_REACH * perimeter))


def _window(d: tm.TagDetection, margin: int, shift: np.ndarray, expect: bool = True) -> tw.TagWindow:
    lo = np.floor(d.corners.min(axis=0)).astype(int) - margin + shift
    hi = np.ceil(d.corners.max(axis=0)).astype(int) + margin + shift
    return tw.TagWindow(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]), (d.id,) if expect else ())


@pytest.mark.parametrize("bag", sorted(BAGS))
@pytest.mark.parametrize("refine", ["edges", "subpix", "none"])
def test_windows_give_the_whole_image_corners_bit_for_bit(bag, refine):
    rng = np.random.default_rng(7)
    n = 0
    for img in _grey_images(bag):
        full = tm.detect_tags(img, "tag36h11", refine)
        if not full:
            continue
        wins = [_window(d, _margin(d) + 16, rng.integers(-14, 15, 2)) for d in full]
        # only the tags found, and an id that is not in the image: identification against those codes alone
        got = tw.detect_tags_in_windows(img, wins, "tag36h11", refine, ids=[d.id for d in full] + [25])
        assert got is not None and _same(got, full)
        n += 1
    assert n >= 18


def test_windows_refuse_what_they_cannot_promise():
    img = _grey_images("table1_exp1")[0]
    full = tm.detect_tags(img)
    assert len(full) >= 1
    d = full[0]
    zero = np.zeros(2, int)
    m = _margin(d) + 2
    got = tw.detect_tags_in_windows(img, [_window(d, m, zero)])
    assert got is not None and d.id in [x.id for x in got]
    assert all(_same([x], [y for y in full if y.id == x.id]) for x in got)
    # a window that cuts the tag, or leaves too little room around it (where the crop may change OpenCV's quads)
    assert tw.detect_tags_in_windows(img, [_window(d, -3, zero)]) is None
    assert tw.detect_tags_in_windows(img, [_window(d, m - 6, zero)]) is None
    # an expected id the window does not hold: the whole image
    far = tw.TagWindow(0, 0, 60, 60, (d.id,))
    assert tw.detect_tags_in_windows(img, [far]) is None
    assert tw.detect_tags_in_windows(img, [tw.TagWindow(0, 0, 60, 60, ())]) == []
    # no window in the image, a sliver of the image, OpenCV's own refinements, colour images
    assert tw.detect_tags_in_windows(img, [tw.TagWindow(-200, -200, -100, -100, (d.id,))]) is None
    assert tw.detect_tags_in_windows(img, [tw.TagWindow(-100, 10, 3, 100, ())]) is None
    assert tw.detect_tags_in_windows(img, [_window(d, m, zero)], refine="contour") is None
    assert tw.detect_tags_in_windows(np.dstack([img] * 3), [_window(d, m, zero)]) is None
    # detect_tags_windowed falls back to the whole image then, and says so
    dets, windowed = detect_tags_windowed(img, [far])
    assert not windowed and _same(dets, full)
    wins = [_window(w, _margin(w) + 2, zero) for w in full]
    dets, windowed = detect_tags_windowed(np.dstack([img] * 3), wins, ids=[1, 3])
    assert windowed and _same(dets, full)


def test_tags_outside_the_windows_or_of_other_ids_are_not_seen():
    img = _frames(3)[2]  # test_tags' rendered frames: the third has two tags
    full = tm.detect_tags(img)
    assert [d.id for d in full] == [0, 1]
    a, b = full
    zero = np.zeros(2, int)
    m = _margin(a) + 2
    for win, ids in (([_window(a, m, zero)], ()), ([_window(a, m, zero, expect=False)], (b.id,))):
        got = tw.detect_tags_in_windows(img, win, ids=ids)
        assert got is not None
        assert all(_same([d], [f for f in full if f.id == d.id]) for d in got)  # what is seen is the whole image's
        if ids:
            assert a.id not in [d.id for d in got]  # not looked for
        elif not (win[0].u0 <= b.corners[:, 0].min() and b.corners[:, 0].max() < win[0].u1
                  and win[0].v0 <= b.corners[:, 1].min() and b.corners[:, 1].max() < win[0].v1):
            assert b.id not in [d.id for d in got]  # outside the window


def test_merge_windows_unites_overlapping_windows():
    w = tw.merge_windows([tw.TagWindow(0, 0, 10, 10, (1,)), tw.TagWindow(20, 20, 30, 30, (2,)),
                          tw.TagWindow(5, 5, 22, 22, ())])
    assert w == [tw.TagWindow(0, 0, 30, 30, (1, 2))]
    w = tw.merge_windows([tw.TagWindow(0, 0, 10, 10, (1,)), tw.TagWindow(40, 0, 50, 10, (2,))])
    assert len(w) == 2


@pytest.mark.parametrize("bag", sorted(BAGS))
def test_evaluate_tag_stream_with_predicted_windows_equals_the_whole_images(bag):
    """The replay's tag measurements with the windows predicted from the priors' joint states are those of the
    whole images, and the windows gave most images."""
    path = REPO / "bags" / bag
    my = REPO / "config" / "robots" / BAGS[bag]
    data = read_bag(path)
    model = replay._load_model(data.require_robot_description(), my, str(path))
    base, tool, _ = replay._check_inputs(data, model, my, EvaluateOptions(), str(path))
    pri = replay._fk_priors(data.joint_states, model, base, tool, 2, str(path), my,
                            required_joints(model, {base, tool, *data.camera_info.frame_ids}))
    runs = []
    for priors in (None, (pri.stamps, pri.Q)):
        stream = TagStream(data, model, str(path), refine="edges", priors=priors)
        try:
            runs.append((stream.measurements(), dict(stream.counts), list(stream.windowed)))
        finally:
            stream.close()
    (whole, c0, w0), (win, c1, w1) = runs
    assert c0 == c1 and len(whole) == len(win) and not any(w0)
    assert sum(w1) >= 0.8 * len(w1), f"{sum(w1)} of {len(w1)} images from the windows"
    for a, b in zip(whole, win):
        assert a.stamp == b.stamp
        for f in ("ids", "corners", "xy", "uv"):
            np.testing.assert_array_equal(getattr(a.payload, f), getattr(b.payload, f))


def test_predicted_windows_without_a_prediction_leave_the_whole_image():
    from ppoe_core.analysis.evaluate.tag_prediction import predicted_windows

    path = REPO / "bags" / "table1_exp1"
    my = REPO / "config" / "robots" / BAGS["table1_exp1"]
    data = read_bag(path)
    model = replay._load_model(data.require_robot_description(), my, str(path))
    Q = np.zeros((1, len(model.joint_names)))
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    cam = data.camera_info.frame_ids[0]
    # a frame the URDF does not know, an image without a camera model
    wins = predicted_windows(model, ["no_such_frame", cam], np.array([1.0, 1.0]),
                             lambda i: None if i == 1 else (K, np.zeros(5)), np.array([0.0]), Q)
    assert wins == [None, None]
    # with a camera: every window is an integer box around a tag the model has, ids only of tags facing the camera
    got = predicted_windows(model, [cam], np.array([1.0]), lambda i: (K, np.zeros(5)), np.array([0.0]), Q)[0]
    known = {item.id for item in model.config.tags.items}
    assert got is None or all(w.u0 < w.u1 and w.v0 < w.v1 and set(w.ids) <= known for w in got)


def test_cli_tag_windows_gives_the_same_json_and_is_opt_in(capsys):
    """``ppoe evaluate --tag-windows`` scores a shipped bag exactly as the default whole-image detection does."""
    import json

    from ppoe_ros.cli import main

    assert EvaluateOptions().tag_windows is False
    docs = []
    for extra in ([], ["--tag-windows"]):
        assert main(["evaluate", str(REPO / "bags" / "table1_exp2"), "--model",
                     str(REPO / "config" / "robots" / "rover_model.yaml"), "--json", "--quiet", *extra]) == 0
        doc = json.loads(capsys.readouterr().out)
        doc.pop("wall_time_s", None)
        docs.append(doc)
    assert docs[0] == docs[1]
