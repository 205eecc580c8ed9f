"""The mcap message index (:mod:`ppoe_core.io.mcap_index`) against ``rosbags``' reader: the same messages in the same
order with the same bytes on every shipped bag and on a bag written here with many small chunks, interleaved
channels, log times out of order inside chunks and equal log times across chunks; ``read_bag`` equal field by field
with the index on and off; a damaged chunk (bad CRC, a record running out of its chunk) keeps ``rosbags``' reader."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import BAGS, REPO, assert_same_data
from rosbags.rosbag2 import Reader

import ppoe_core.io.mcap_index as mcap_index
import ppoe_core.io.reader as reader_module
from ppoe_core.errors import BagError
from ppoe_core.io import cdr
from ppoe_core.io.bagio import BagWriter, read_bag
from ppoe_core.io.messages import T_POINT, T_POSE, T_WRENCH
from ppoe_core.io.mcap_index import index_messages

SHIPPED = sorted(p.parent for p in BAGS.glob("*/metadata.yaml"))
_TOPICS = ("/joint_states", "/ground_truth/pose", "/wrench", "/camera/camera_info", "/camera/image_raw/compressed",
           "/ground_truth/point")
_NAMES = ["joint_1", "joint_2", "joint_3"]


def _messages(source: Any, conns: list[Any]) -> list[tuple[str, int, bytes]]:
    """(topic, log time, bytes) of every message ``source`` yields for ``conns``."""
    return [(c.topic, int(t), bytes(d)) for c, t, d in source.messages(connections=conns)]


def _requests(conns: list[Any]) -> list[list[Any]]:
    """All connections, each alone, and every other one: the connection sets the reader asks for."""
    return [conns, *([c] for c in conns), conns[::2], conns[1::2]]


def _tangled_bag(path: Path, uniform: bool = True) -> tuple[Path, list[float]]:
    """Seven chunks of randomly interleaved contract messages whose stamps (= log times) come from a few values:
    out of order inside a chunk, equal across channels and chunks, chunk time ranges overlapping.  ``uniform``
    False: one joint state lists a fourth joint (the joint states no longer share one layout), one pose, wrench and
    point each has another frame (their blocks are read message by message).  Returns the bag and the stamps in
    writing order."""
    rng = np.random.default_rng(7)
    stamps: list[float] = []
    written: list[str] = []
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    with BagWriter(path) as bag:
        bag.write_robot_description((REPO / "config" / "robots" / "planar3.urdf").read_text(), 1.0)
        for chunk in range(7):
            for _ in range(25):
                t = 1.0 + 0.01 * int(rng.integers(0, 12)) + 0.02 * chunk
                topic = _TOPICS[int(rng.integers(0, len(_TOPICS)))]
                stamps.append(t)
                if topic == "/joint_states":
                    extra = int(not uniform and chunk == 2 and "joint_4" not in written)
                    written += ["joint_4"] * extra
                    bag.write_joint_state(t, _NAMES + ["joint_4"] * extra, rng.normal(size=3 + extra))
                elif topic == "/ground_truth/pose":
                    T = np.eye(4)
                    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, -1]
                    T[:3, 3] = rng.normal(size=3)
                    bag.write_ground_truth_pose(t, "base_link" if uniform or chunk != 3 else "world", T)
                elif topic == "/wrench":
                    bag.write_wrench(t, "tool" if uniform or chunk != 4 else "flange", rng.normal(size=3),
                                     rng.normal(size=3))
                elif topic == "/ground_truth/point":
                    bag.write_ground_truth_point(t, "tracker" if uniform or chunk != 5 else "leica", rng.normal(size=3))
                elif topic == "/camera/camera_info":
                    bag.write_camera_info(t, "camera", 640, 480, K, [0.01, 0, 0, 0, 0])
                else:
                    bag.write_compressed_image(t, "camera", rng.integers(0, 255, (6, 8), dtype=np.uint8))
            bag.flush()  # one chunk
    return path, stamps


@pytest.fixture(scope="module")
def tangled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _tangled_bag(tmp_path_factory.mktemp("tangled") / "bag")[0]



@pytest.mark.parametrize("bag", SHIPPED, ids=[p.name for p in SHIPPED])
def test_index_yields_what_rosbags_yields_on_every_shipped_bag(bag: Path) -> None:
    with Reader(bag) as r:
        conns = list(r.connections)
        index = index_messages(r, conns)
        assert index is not None
        for request in _requests(conns):
            assert _messages(index, request) == _messages(r, request), [c.topic for c in request]


def test_index_orders_a_tangled_bag_as_rosbags(tmp_path: Path) -> None:
    """Seven chunks, log times out of order within chunks and repeated across chunks and channels: the index gives
    rosbags' order (a stable sort by log time, ties across chunks by chunk position), not the file's."""
    bag, written = _tangled_bag(tmp_path / "bag")
    with Reader(bag) as r:
        chunks = r.storage.storages[0].chunks
        assert len(chunks) >= 7
        assert any(a.message_end_time > b.message_start_time for a, b in zip(chunks, chunks[1:]))  # ranges overlap
        conns = list(r.connections)
        index = index_messages(r, conns)
        assert index is not None
        for request in _requests(conns):
            assert _messages(index, request) == _messages(r, request), [c.topic for c in request]
        got = [t for _, t, _ in _messages(index, conns)]
    assert written != sorted(written)  # the file order is not the log-time order: the index sorted
    assert got == sorted(got) and len(got) == len(written) + 1
    assert len(set(got)) < len(got)  # equal log times: the tie rule decided


@pytest.mark.parametrize("uniform", [True, False], ids=["one_layout", "two_layouts"])
def test_read_bag_is_the_same_with_and_without_the_index(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          uniform: bool) -> None:
    """Every series of ``read_bag`` (one pass, two phases, without images) equal with the index on and off, on the
    tangled bag (joint states read as one block, or one by one when a message lists another joint)."""
    bag = _tangled_bag(tmp_path / "bag", uniform)[0]
    used: list[Any] = []
    real = reader_module.index_messages
    monkeypatch.setattr(reader_module, "index_messages", lambda r, c: used.append(real(r, c)) or used[-1])
    blocks: list[tuple[str, bool]] = []
    real_block = reader_module.header_rows_block
    monkeypatch.setattr(reader_module, "header_rows_block",
                        lambda t, rows: blocks.append((t, real_block(t, rows) is not None)) or real_block(t, rows))
    first = ("/robot_description", "/camera/camera_info", "/camera/image_raw/compressed")
    for kw in ({}, {"load_images": False}, {"first": first}):
        seen: dict[bool, tuple[int, int]] = {}
        results = {}
        for on in (True, False):
            monkeypatch.setattr(mcap_index, "USE_INDEX", on)

            def early(d: Any, on: bool = on, seen: dict[bool, tuple[int, int]] = seen) -> None:
                seen[on] = (len(d.images), len(d.joint_states))

            results[on] = read_bag(bag, **kw, on_first=early if "first" in kw else None)
        assert_same_data(results[True], results[False])
        assert seen.get(True) == seen.get(False)
    assert len(used) == 6 and all(u is not None for u in used[::2]) and all(u is None for u in used[1::2])
    data = results[True]
    assert len(data.joint_states) > 20 and len(data.images) > 5 and len(data.ground_truth_pose) > 5
    assert ("joint_4" in data.joint_states.names) == (not uniform)
    assert len(data.wrench) > 5 and len(data.ground_truth_point) > 5
    # the index's pass read pose, wrench and point at once (one frame each), or tried and read them one by one
    assert sorted(set(blocks)) == sorted((t, uniform) for t in (T_POSE, T_POINT, T_WRENCH))


def test_a_bad_message_is_the_same_error_with_and_without_the_index(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A ground-truth pose with a zero quaternion among good ones: the same error, naming the same message."""
    bag = tmp_path / "bag"
    with BagWriter(bag) as w:
        w.write_robot_description((REPO / "config" / "robots" / "planar3.urdf").read_text(), 0.5)
        for k in range(30):
            w.write_joint_state(1.0 + 0.01 * k, _NAMES, np.full(3, 0.1 * k))
            T = np.eye(4)
            T[0, 3] = k
            w.write_ground_truth_pose(1.0 + 0.01 * k, "base_link", T)
        w.write_raw("/ground_truth/pose", T_POSE, 1_400_000_000, cdr.write(cdr.SCHEMAS[T_POSE],
                                                                            [(1_400_000_000, "base_link"), [0.0] * 7]))
    errors = []
    for on in (True, False):
        monkeypatch.setattr(mcap_index, "USE_INDEX", on)
        with pytest.raises(BagError, match="message 30: invalid quaternion") as exc:
            read_bag(bag)
        errors.append(str(exc.value))
    assert errors[0] == errors[1]


@pytest.mark.parametrize("bag", [BAGS / "effect_camera_extrinsics", BAGS / "contact"], ids=["images", "wrench"])
def test_read_bag_is_the_same_with_and_without_the_index_on_shipped_bags(bag: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    ref = read_bag(bag)
    monkeypatch.setattr(mcap_index, "USE_INDEX", False)
    assert_same_data(ref, read_bag(bag))


def _chunk_records(chunk: Any) -> tuple[int, int]:
    """Where a chunk's records start in the file, and their length."""
    return chunk.chunk_start_offset + 49 + len(chunk.compression), chunk.uncompressed_size


def _damage(bag: Path, how: str) -> None:
    """Damage the third chunk: a wrong CRC, the right CRC (not damage: rosbags then checks it), the first Message
    record's length running past the chunk, its time range in the summary's chunk index starting 1 ns after its
    first messages (which rosbags then skips), or its joint states not counted in the chunk index (rosbags then
    reads them only when other topics are asked for with them)."""
    (mcap,) = bag.glob("*.mcap")
    with Reader(bag) as r:
        chunk = r.storage.storages[0].chunks[2]
        (channel,) = [c.id for c in r.storage.storages[0].connections if c.topic == "/joint_states"]
    buf = bytearray(mcap.read_bytes())
    start, size = _chunk_records(chunk)
    crc_at = chunk.chunk_start_offset + 9 + 24
    if how == "bad_crc":
        struct.pack_into("<I", buf, crc_at, zlib.crc32(buf[start:start + size]) ^ 1)
    elif how == "good_crc":
        struct.pack_into("<I", buf, crc_at, zlib.crc32(buf[start:start + size]))
    elif how in ("narrow_range", "uncounted"):
        key = struct.pack("<QQQ", chunk.message_start_time, chunk.message_end_time, chunk.chunk_start_offset)
        at = buf.rindex(key)  # the chunk index record in the summary
        if how == "narrow_range":
            struct.pack_into("<Q", buf, at, chunk.message_start_time + 1)
        else:  # its message index offsets name channel 999 instead of /joint_states': not counted there
            (n,) = struct.unpack_from("<I", buf, at + 32)
            entries = [at + 36 + 10 * k for k in range(n // 10)]
            (pos,) = [e for e in entries if struct.unpack_from("<H", buf, e)[0] == channel]
            struct.pack_into("<H", buf, pos, 999)
    else:
        pos = start
        while buf[pos] != 0x05:
            pos += 9 + struct.unpack_from("<Q", buf, pos + 1)[0]
        struct.pack_into("<Q", buf, pos + 1, size)
    mcap.write_bytes(bytes(buf))


@pytest.mark.parametrize("how", ["bad_crc", "record_past_chunk", "good_crc", "narrow_range", "uncounted"])
def test_a_damaged_chunk_keeps_the_rosbags_reader(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str) -> None:
    """A chunk rosbags refuses (its CRC, a record that does not fit) makes the index refuse the bag, so it is read
    as before (the same messages up to the damage, the same notes); a correct non-zero CRC is checked and passes;
    messages outside their chunk's indexed time range are skipped as rosbags skips them."""
    bag = _tangled_bag(tmp_path / "bag")[0]
    _damage(bag, how)
    with Reader(bag) as r:
        conns = list(r.connections)
        index = index_messages(r, conns)
        if how in ("good_crc", "narrow_range"):
            assert index is not None
            for request in _requests(conns):
                assert _messages(index, request) == _messages(r, request)
        else:
            assert index is None
            if how == "uncounted":
                alone = _messages(r, [c for c in conns if c.topic == "/joint_states"])
                assert 0 < len(alone) < len([m for m in _messages(r, conns) if m[0] == "/joint_states"])
            else:
                with pytest.raises(Exception, match="checksum" if how == "bad_crc" else "."):
                    _messages(r, conns)
    first = ("/robot_description", "/camera/camera_info", "/camera/image_raw/compressed")
    for kw in ({}, {"first": first, "on_first": lambda d: None}):
        ref = read_bag(bag, accept_partial=True, **kw)
        monkeypatch.setattr(mcap_index, "USE_INDEX", False)
        old = read_bag(bag, accept_partial=True, **kw)
        monkeypatch.setattr(mcap_index, "USE_INDEX", True)
        assert_same_data(ref, old)
        # narrow_range, uncounted: metadata.yaml counts messages rosbags skips
        assert bool(ref.notes) == (how not in ("good_crc", "uncounted")), ref.notes
