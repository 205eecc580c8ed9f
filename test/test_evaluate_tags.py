"""``ppoe evaluate``'s tag measurements made by worker processes (or threads) started before the replay
(``TagStream``), and the garbage collector paused during an evaluation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from test_tags import _frames

from ppoe_core.analysis.evaluate.tag_stream import TagStream, tag_measurements
from ppoe_core.errors import BagError

K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
D = np.array([-0.1, 0.05, 0.001, -0.001, 0.0])


def _data(frames: list[np.ndarray], stamps: list[float], camera_frame: str = "cam") -> SimpleNamespace:
    class Images(SimpleNamespace):
        def __len__(self) -> int:
            return len(frames)

    images = Images(topic="/camera/image_raw/compressed", stamps=np.asarray(stamps), frame_ids=["cam"] * len(frames),
                    decode=frames.__getitem__)
    info = SimpleNamespace(frame_ids=[camera_frame], stamps=np.array([0.0]), K=[K], D=[D])
    return SimpleNamespace(images=images, camera_info=info, tag_observations=[])


MODEL = SimpleNamespace(config=SimpleNamespace(tags=SimpleNamespace(family="tag36h11")))


@pytest.mark.parametrize("workers,processes", [(1, True), (2, True), (2, False)])
def test_tag_stream_equals_one_loop_over_the_images(workers, processes):
    frames = _frames(10)
    stamps = [1.0, 1.5, 1.25, 2.0, 2.0, 3.0, 2.5, 4.0, 4.5, 5.0]
    seq, counts = tag_measurements(_data(frames, stamps), MODEL, "bag", workers=1)
    assert counts["images"] == 10 and 0 < counts["images_without_tags"] < 10 and len(seq) < 10
    stream = TagStream(_data(frames, stamps), MODEL, "bag", workers=workers, processes=processes)
    try:
        assert stream.stamps == stamps
        late = stream.get(6)  # the images up to 6 are read in order
        assert stream.counts["images"] == 7
        got = stream.measurements()
    finally:
        stream.close()
    assert late is None or late in got
    assert stream.counts == counts and len(got) == len(seq)
    for a, b in zip(got, seq):
        assert a.stamp == b.stamp and a.source == b.source
        np.testing.assert_array_equal(a.payload.xy, b.payload.xy)
        np.testing.assert_array_equal(a.payload.uv, b.payload.uv)
        np.testing.assert_array_equal(a.payload.ids, b.payload.ids)
        np.testing.assert_array_equal(a.payload.corners, b.payload.corners)


def test_tag_stream_raises_the_first_error_in_image_order():
    frames = _frames(6)
    stream = TagStream(_data(frames, [float(i) for i in range(6)], camera_frame="other"), MODEL, "bag", workers=2)
    with pytest.raises(BagError, match=r"bag bag: topic /camera/image_raw/compressed message 0: no "
                                       r"/camera/camera_info with frame_id 'cam'"):
        stream.get(3)
    stream.close()


def test_evaluate_pauses_the_garbage_collector_and_restores_it():
    import gc

    from ppoe_core.analysis.evaluate.replay import _gc_paused

    assert gc.isenabled()
    with pytest.raises(BagError):
        with _gc_paused():
            assert not gc.isenabled()
            raise BagError("x")
    assert gc.isenabled()
    gc.disable()
    try:
        with _gc_paused():
            pass
        assert not gc.isenabled()  # left as the caller had it
    finally:
        gc.enable()
