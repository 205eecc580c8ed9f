"""``ppoe evaluate``'s tag measurements made by worker processes (or threads) started before the replay
(``TagStream``), and the garbage collector paused during an evaluation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from conftest import assert_same_data
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


class _Tags(SimpleNamespace):
    """A TagStream stand-in: slot k's measurement or None, counting the reads."""

    def get(self, k):
        self.reads.append(k)
        return self.items[k]


def test_measurement_slots_are_the_sorted_measurements_taken_when_asked():
    from ppoe_core.analysis.evaluate.replay import MeasurementSlots

    m = [SimpleNamespace(stamp=t, name=n) for t, n in [(2.0, "a"), (1.0, "b"), (2.0, "c"), (0.5, "d")]]
    tags = _Tags(stamps=[2.0, 1.0, 3.0, 2.0], items=[m[0], m[1], None, m[2]], reads=[])
    others = [m[3], SimpleNamespace(stamp=2.0, name="e")]
    slots = MeasurementSlots(tags, others)
    assert tags.reads == [] and len(slots) == 6  # nothing taken before it is asked for
    np.testing.assert_array_equal(slots.stamps, [0.5, 1.0, 2.0, 2.0, 2.0, 3.0])
    assert slots.get(5) is None and tags.reads == [2]
    expected = sorted([x for x in tags.items if x is not None] + others, key=lambda x: x.stamp)
    assert [x.name for x in slots.resolved()] == [x.name for x in expected] == ["d", "b", "a", "c", "e"]


REPO_BAGS = __import__("pathlib").Path(__file__).resolve().parents[1] / "bags"
ARM7_MODEL = REPO_BAGS.parent / "config" / "robots" / "arm7_model.yaml"



def test_read_bag_reads_the_first_topics_first_and_gives_the_same_data():
    from ppoe_core.analysis.evaluate.replay import TAG_INPUT_TOPICS
    from ppoe_core.io.bagio import read_bag

    bag = REPO_BAGS / "effect_camera_extrinsics"
    seen = {}

    def early(data):
        seen.update(images=len(data.images), camera_info=len(data.camera_info), urdf=bool(data.robot_description),
                    joint_states=len(data.joint_states), gt=len(data.ground_truth_pose), obj=data)

    phased = read_bag(bag, first=TAG_INPUT_TOPICS, on_first=early)
    whole = read_bag(bag)
    assert seen["obj"] is phased  # the same object, completed after the call
    assert seen["images"] == len(whole.images) > 0 and seen["camera_info"] == len(whole.camera_info) > 0
    assert seen["urdf"] and seen["joint_states"] == 0 and seen["gt"] == 0 < len(whole.ground_truth_pose)
    assert_same_data(phased, whole)


def test_evaluate_starts_the_image_workers_before_the_joint_states_are_read(monkeypatch):
    from ppoe_core.analysis.evaluate import EvaluateOptions, evaluate_bag
    from ppoe_core.analysis.evaluate import replay

    made = []

    class Recording(TagStream):
        def __init__(self, data, *args, **kwargs):
            made.append((len(data.joint_states), len(data.images), kwargs.get("priors")))
            super().__init__(data, *args, **kwargs)

    monkeypatch.setattr(replay, "TagStream", Recording)
    bag = REPO_BAGS / "effect_camera_extrinsics"
    ev = evaluate_bag(bag, ARM7_MODEL, EvaluateOptions(progress=False))
    assert len(made) == 1 and made[0][0] == 0 and made[0][1] == ev.summary["measurements"]["images"] > 0
    assert made[0][2] is None
    made.clear()
    evaluate_bag(bag, ARM7_MODEL, EvaluateOptions(progress=False, tag_windows=True))  # needs the priors: after them
    assert len(made) == 1 and made[0][0] > 0 and made[0][2] is not None


def test_early_tags_start_again_when_the_bag_is_read_again_record_by_record(monkeypatch):
    """A damaged file read again record by record gives another BagData than the early phase saw: the stream made
    on the first is closed and a new one made on the data returned."""
    from ppoe_core.analysis.evaluate import EvaluateOptions
    from ppoe_core.analysis.evaluate import replay

    streams = []

    class Fake:
        def __init__(self, data, *args, **kwargs):
            self.data, self.closed = data, False
            streams.append(self)

        def close(self):
            self.closed = True

    seen = SimpleNamespace(images="early", require_robot_description=lambda: "urdf")
    final = SimpleNamespace(images="rescued", require_robot_description=lambda: "urdf")

    def fake_read_bag(path, *, accept_partial, first, on_first):
        on_first(seen)
        return final

    monkeypatch.setattr(replay, "TagStream", Fake)
    monkeypatch.setattr(replay, "_load_model", lambda *a, **k: "model")
    monkeypatch.setattr("ppoe_core.io.bagio.read_bag", fake_read_bag)
    early = replay._EarlyTags("bag", "model.yaml", EvaluateOptions(progress=False))
    assert early.read() is final
    assert [s.data.images for s in streams] == ["early", "rescued"] and streams[0].closed and not streams[1].closed
    assert early.tags is streams[1] and early.model == "model"
    early.close()
    assert streams[1].closed


def test_evaluate_of_a_bag_read_record_by_record_is_the_same(tmp_path):
    """Without metadata.yaml the bag is read record by record (no early phase): the same scores, with a note."""
    import shutil

    from ppoe_core.analysis.evaluate import EvaluateOptions, evaluate_bag

    bag = tmp_path / "bag"
    shutil.copytree(REPO_BAGS / "effect_camera_extrinsics", bag)
    ref = evaluate_bag(bag, ARM7_MODEL, EvaluateOptions(progress=False)).summary
    (bag / "metadata.yaml").unlink()
    got = evaluate_bag(bag, ARM7_MODEL, EvaluateOptions(progress=False)).summary
    assert got.pop("bag_notes") and "bag_notes" not in ref
    assert {k: v for k, v in got.items() if k != "wall_time_s"} == {k: v for k, v in ref.items() if k != "wall_time_s"}
