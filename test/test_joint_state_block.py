"""``JointState`` messages read at once by one compiled pass (:func:`ppoe_core.io.cdr.joint_state_block_at`,
:func:`ppoe_core.io.mcap_kernel.gather_layout`) give what the numpy version before it gave (kept here as the reference,
:func:`rows_block_reference`), bit for bit: on the shipped bags' joint states, on messages with and without
velocities and efforts, and with any compared byte changed in one message (then both refuse: None)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import BAGS
from rosbags.rosbag2 import Reader

from ppoe_core.io import cdr
from ppoe_core.io.messages import T_JOINT_STATE
from ppoe_core.io.writer import cdr_joint_state

SHIPPED = sorted(p.parent for p in BAGS.glob("*/metadata.yaml"))


def rows_block_reference(arr: np.ndarray) -> cdr.JointStateBlock | None:
    """``joint_state_rows_block`` as it was (numpy on the (N, size) rows)."""
    if not arr.shape[0]:
        return None
    first = arr[0].tobytes()
    cdr.parse_fields(T_JOINT_STATE, first)
    lay = cdr.joint_state_layout(first)
    if lay is None or lay.size != arr.shape[1]:
        return None
    cols = np.concatenate([np.arange(2)] + [np.arange(at, at + len(seg)) for at, seg in lay.segments])
    words = np.ascontiguousarray(np.take(arr, np.concatenate([cols, np.zeros(-cols.shape[0] % 8, dtype=cols.dtype)]),
                                         axis=1)).view("<u8")
    ok = ~(words != words[0]).any(axis=1)
    if lay.size - lay.end > 8:
        ok &= ~arr[:, lay.end:].any(axis=1)
    if not ok.all():
        return None
    n_msg = arr.shape[0]
    sec = np.ascontiguousarray(arr[:, 4:8]).view("<i4")[:, 0].astype(np.float64)
    nsec = np.ascontiguousarray(arr[:, 8:12]).view("<u4")[:, 0].astype(np.float64)
    values = [np.ascontiguousarray(arr[:, at:at + 8 * n]).view("<f8") if n else np.zeros((n_msg, 0))
              for _, at, n in lay.spans]
    return cdr.JointStateBlock(sec + 1e-9 * nsec, lay.frame, lay.names, *values)


def _same(a: cdr.JointStateBlock | None, b: cdr.JointStateBlock | None) -> None:
    assert (a is None) == (b is None)
    if a is None or b is None:
        return
    assert (a.frame, a.names) == (b.frame, b.names)
    for x, y in zip((a.stamps, a.positions, a.velocities, a.effort), (b.stamps, b.positions, b.velocities, b.effort)):
        assert (x.dtype, x.shape, x.tobytes()) == (y.dtype, y.shape, y.tobytes())


def _rows(raws: list[bytes]) -> np.ndarray:
    return np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), -1).copy()


@pytest.mark.parametrize("bag", SHIPPED, ids=[p.name for p in SHIPPED])
def test_shipped_joint_states_at_once_as_before(bag: Path) -> None:
    with Reader(bag) as r:
        conns = [c for c in r.connections if c.msgtype == T_JOINT_STATE]
        raws = [bytes(d) for _, _, d in r.messages(connections=conns)]
    assert raws and len({len(x) for x in raws}) == 1, f"{bag.name}: the shipped joint states share one layout"
    arr = _rows(raws)
    got = cdr.joint_state_rows_block(arr)
    assert got is not None and got.stamps.shape[0] == len(raws)
    _same(got, rows_block_reference(arr))


@pytest.mark.parametrize("fields", ["positions", "all", "efforts"])
def test_one_changed_byte_anywhere_gives_the_same_answer_as_before(fields: str) -> None:
    rng = np.random.default_rng(len(fields))
    names = ["shoulder", "elbow", "wrist_2"]
    raws = []
    for _ in range(40):
        pos = rng.normal(size=3)
        vel = rng.normal(size=3) if fields == "all" else np.zeros(0)
        eff = rng.normal(size=3) if fields in ("all", "efforts") else np.zeros(0)
        raws.append(cdr_joint_state(int(rng.integers(0, 2**31 - 1)) * 10**9 + int(rng.integers(0, 10**9)), names,
                                    pos, vel, eff, frame_id="base"))
    arr = _rows(raws)
    _same(cdr.joint_state_rows_block(arr), rows_block_reference(arr))
    refused = 0
    for col in range(arr.shape[1]):
        bad = arr.copy()
        bad[17, col] ^= 0x10
        got = cdr.joint_state_rows_block(bad)
        _same(got, rows_block_reference(bad))
        refused += got is None
    assert refused >= 2 + len("base") + sum(len(n) for n in names)  # the compared bytes: every one counts
    trailing = np.concatenate([arr, np.zeros((arr.shape[0], 16), dtype=np.uint8)], axis=1)
    _same(cdr.joint_state_rows_block(trailing), rows_block_reference(trailing))  # 16 zero bytes after the last field
    trailing[3, -1] = 1
    assert cdr.joint_state_rows_block(trailing) is None and rows_block_reference(trailing) is None


def test_offsets_into_a_larger_buffer_read_the_same_messages() -> None:
    raws = [cdr_joint_state(10**9 * k + 5, ["a", "b"], np.array([k, -k], float), np.zeros(0), np.zeros(0))
            for k in range(6)]
    size = len(raws[0])
    buf = np.frombuffer(b"xyz" + b"".join(r + b"pad" for r in raws[::-1]), dtype=np.uint8)
    offsets = np.array([3 + (size + 3) * (5 - k) for k in range(6)], dtype=np.int64)
    _same(cdr.joint_state_block_at(buf, offsets, size), rows_block_reference(_rows(raws)))
