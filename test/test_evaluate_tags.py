"""``ppoe evaluate``'s tag measurements made on worker threads while the replay runs (``TagStream``) and the
replay's measurement order (``MeasurementSlots``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from test_tags import _frames

from ppoe_core.analysis.evaluate.tag_stream import MeasurementSlots, TagStream, tag_measurements
from ppoe_core.errors import BagError
from ppoe_core.estimation.pipeline import Measurement

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


@pytest.mark.parametrize("workers", [1, 2])
def test_tag_stream_equals_one_loop_over_the_images(workers):
    frames = _frames(10)
    stamps = [1.0, 1.5, 1.25, 2.0, 2.0, 3.0, 2.5, 4.0, 4.5, 5.0]  # not in image order
    seq, counts = tag_measurements(_data(frames, stamps), MODEL, "bag", workers=1)
    assert counts["images"] == 10 and 0 < counts["images_without_tags"] < 10 and len(seq) < 10
    stream = TagStream(_data(frames, stamps), MODEL, "bag", workers=workers)
    contact = [Measurement(2.0, "/contact/plane", None), Measurement(0.5, "/contact/plane", None)]
    slots = MeasurementSlots(stream, contact)
    try:
        assert slots.stamps == sorted(stamps + [2.0, 0.5])
        got = [slots.get(k) for k in range(len(slots))]  # in stamp order, images out of image order
    finally:
        stream.close()
    ref = sorted(seq + contact, key=lambda m: m.stamp)  # the order of the replay before the slots
    kept = [m for m in got if m is not None]
    assert len(kept) == len(ref) and all(a is b for a, b in zip(slots.measurements(), kept))
    assert stream.counts == counts
    for a, b in zip(kept, ref):
        assert a.stamp == b.stamp and a.source == b.source
        if a.payload is not None:
            np.testing.assert_array_equal(a.payload.xy, b.payload.xy)
            np.testing.assert_array_equal(a.payload.ids, b.payload.ids)


def test_tag_stream_raises_the_first_error_in_image_order():
    frames = _frames(6)
    stream = TagStream(_data(frames, [float(i) for i in range(6)], camera_frame="other"), MODEL, "bag", workers=2)
    with pytest.raises(BagError, match=r"bag bag: topic /camera/image_raw/compressed message 0: no "
                                       r"/camera/camera_info with frame_id 'cam'"):
        stream.get(3)
    stream.close()


def test_evaluate_pauses_the_garbage_collector_and_restores_it():
    import gc

    from ppoe_core.analysis.evaluate.replay import _replay_settings

    assert gc.isenabled()
    with pytest.raises(BagError):
        with _replay_settings():
            assert not gc.isenabled()
            raise BagError("x")
    assert gc.isenabled()
    gc.disable()
    try:
        with _replay_settings():
            pass
        assert not gc.isenabled()  # left as the caller had it
    finally:
        gc.enable()
