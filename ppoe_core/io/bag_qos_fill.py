"""Old bags written again with an offered QoS per topic (:mod:`ppoe_core.io.bag_qos` says why a bag needs one):
for the bags written before :class:`~ppoe_core.io.writer.BagWriter` stored QoS."""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

from rosbags.interfaces import Qos
from rosbags.rosbag2 import Reader

from ppoe_core.errors import BagError
from ppoe_core.io.bag_qos import offered_qos, read_bag_metadata
from ppoe_core.io.writer import BagWriter

__all__ = ["fill_offered_qos"]


def fill_offered_qos(bag: str | Path, profiles: Mapping[str, Sequence[Qos]] | None = None) -> list[str]:
    """Write a bag again with an offered QoS for every topic recorded without any; the topics filled.

    ``profiles`` gives them per topic (default :func:`offered_qos`); topics that have profiles keep them.
    The QoS lives twice in a bag (``metadata.yaml`` and the mcap channel records, which rosbags' reader
    requires to agree), so the messages are copied into a new bag by :class:`~ppoe_core.io.writer.BagWriter`:
    every message keeps its topic, log time and bytes, in log-time order, and ``metadata.yaml`` is what the
    writer writes.  For the bags written before the writer stored QoS.

    Raises
    ------
    BagError
        No readable bag at ``bag``.
    """
    src = Path(bag)
    if not (src / "metadata.yaml").is_file():
        raise BagError(f"bag {bag}: no metadata.yaml")
    storage = str(read_bag_metadata(src / "metadata.yaml").get("storage_identifier", "mcap"))
    work = src.parent / f".{src.name}.qos_tmp"
    if work.exists():
        shutil.rmtree(work)
    filled: list[str] = []
    with Reader(src) as reader:
        had = {c.topic: list(getattr(c.ext, "offered_qos_profiles", [])) for c in reader.connections}
        missing = [c for c in reader.connections if not had[c.topic]]
        if not missing:
            return []
        with BagWriter(work / src.name, storage=storage) as writer:
            for conn in reader.connections:
                chosen = had[conn.topic] or (
                    list(profiles[conn.topic]) if profiles is not None and conn.topic in profiles
                    else offered_qos(conn.topic))
                writer.offered_qos[conn.topic] = list(chosen)
            for conn, stamp_ns, data in reader.messages():
                writer.write_raw(conn.topic, conn.msgtype, stamp_ns, data, normalise=False)
        filled = [c.topic for c in missing]
    old = src.parent / f".{src.name}.qos_old"
    src.rename(old)
    (work / src.name).rename(src)
    shutil.rmtree(old)
    shutil.rmtree(work)
    return filled
