"""An index of the messages of a chunked, single-file mcap bag: the messages ``rosbags`` reads, in its order, found
by one compiled walk over the chunks instead of Python per message.

``rosbags``' reader (``Reader.messages``) decompresses each chunk that holds a wanted channel, walks its records in
Python, sorts each chunk's messages by log time (stably) and merges the chunks with ``heapq.merge`` on ``(log time,
chunk offset)``: about 6 us per message, most of ``read_bag``'s time on a long bag (67205 messages of the 600 s
``bench/bench_evaluate.py`` bag: 0.3 s).  :class:`McapIndex` reads the same chunks (from the same chunk index of the
file's summary, the same bytes of the file), applies the same checks (chunk size, the chunk CRC when it is not zero,
every record inside its chunk, a Message record at least as long as its header) and one more (every channel with a
message in a chunk is counted in that chunk's index, so that a topic's messages do not depend on which topics are
asked for with it: the reader asks per phase and per topic), finds every Message record with
:func:`ppoe_core.io.mcap_kernel.scan_messages` and orders a request's messages by a stable sort on ``(log time,
chunk offset, record position)``: the same messages, in the same order, with the same bytes
(``test/test_mcap_index.py`` compares both on every shipped bag and on bags with many small chunks).

:func:`index_messages` returns None where the bag is not a plain case: more than one storage file, sqlite3,
per-file or per-message compression, no chunk index (an unchunked file), a chunk that does not read or check as
``rosbags`` requires, or anything unexpected.  The caller then uses ``rosbags``' reader, so a damaged file is read
(and stops, with its error) exactly as before.  :data:`USE_INDEX` turns the index off (the tests' reference).
"""

from __future__ import annotations

import mmap
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["McapIndex", "index_messages", "USE_INDEX"]

#: False: :func:`index_messages` always returns None (every bag is read by ``rosbags``' reader)
USE_INDEX = True

_CHUNK_PREFIX = 9 + 40  # opcode, record length, start/end time, uncompressed size, CRC, compression length, size
_CRC_AT = 9 + 24
_MAX_TIME = 2**63 - 1


class _NotIndexable(Exception):
    """The bag is read by ``rosbags``' reader instead (any reason: :func:`index_messages` gives None)."""


def index_messages(reader: Any, connections: Sequence[Any]) -> McapIndex | None:
    """The :class:`McapIndex` of an open ``rosbags`` reader for the messages of ``connections`` (and any subset of
    them), or None where ``rosbags``' reader must read the bag (module docstring)."""
    if not USE_INDEX or not connections:
        return None
    try:
        return McapIndex(reader, connections)
    except _NotIndexable:
        return None
    except Exception:  # noqa: BLE001 - anything unexpected in a file: rosbags' reader decides what it is
        return None


def _storage(reader: Any) -> Any:
    """The one ``McapReader`` of a rosbag2 directory without per-file or per-message compression."""
    from rosbags.rosbag2.reader import DirectoryReader
    from rosbags.rosbag2.storage_mcap import McapReader

    directory = getattr(reader, "storage", None)
    if type(directory) is not DirectoryReader or len(directory.storages) != 1 \
            or directory.metadata.compression_mode:
        raise _NotIndexable("not a single uncompressed mcap storage")
    storage = directory.storages[0]
    if type(storage) is not McapReader or not storage.chunks or storage.bio is None:
        raise _NotIndexable("not a chunked mcap file")
    return storage


def _channel_map(storage_connections: Sequence[Any], connections: Sequence[Any]) -> dict[int, Any]:
    """Channel id of the mcap file -> the directory's connection that ``rosbags`` yields for it (its rule: the
    first of ``connections`` with the same topic, type, serialisation and QoS, and a compatible type hash)."""
    out = {}
    for x in storage_connections:
        conn = next((y for y in connections if y.topic == x.topic and y.msgtype == x.msgtype and y.ext == x.ext
                     and (not x.digest or not y.digest or y.digest == x.digest)), None)
        if conn is not None:
            out[x.id] = conn
    return out


def _chunk_bytes(mm: Any, chunk: Any) -> Any:
    """The records of one chunk as ``rosbags`` reads and checks them (``bytes``); raises where it would."""
    from rosbags.rosbag2.storage_mcap import decompress

    base = chunk.chunk_start_offset
    start = base + _CHUNK_PREFIX + len(chunk.compression)
    if base + _CRC_AT + 4 > len(mm) or start + chunk.compressed_size > len(mm):
        raise _NotIndexable("truncated chunk")
    (crc,) = np.frombuffer(mm, dtype="<u4", count=1, offset=base + _CRC_AT).tolist()
    if chunk.compression == "":
        if chunk.compressed_size != chunk.uncompressed_size:
            raise _NotIndexable("chunk size mismatch")
        view = memoryview(mm)[start:start + chunk.compressed_size]
        try:
            if crc and zlib.crc32(view) != crc:
                raise _NotIndexable("chunk checksum mismatch")
        finally:
            view.release()
        return None  # read in place
    return decompress(mm[start:start + chunk.compressed_size], chunk.compression, chunk.uncompressed_size, crc)


def _check_counts(chunks: Sequence[Any], chan: np.ndarray, seg: np.ndarray, wanted: set[int]) -> None:
    """Every wanted channel with a message in a chunk is counted in that chunk's index (``rosbags`` reads a chunk
    only for the channels its index counts): then a topic's messages do not depend on which other topics are
    asked for with it, as :class:`McapIndex`'s users assume."""
    pairs = np.unique(seg * 65536 + chan)
    for s, cid in zip((pairs // 65536).tolist(), (pairs % 65536).tolist()):
        if cid in wanted and not chunks[s].channel_count.get(cid, 0):
            raise _NotIndexable(f"chunk {chunks[s].chunk_start_offset}: channel {cid} not in its index")


class McapIndex:
    """Every Message record of the chunks ``rosbags`` reads for ``connections``; :meth:`messages` and :meth:`rows`
    give a request's messages in ``rosbags``' order.

    Parameters
    ----------
    reader : rosbags.rosbag2.Reader
        Open, on a rosbag2 directory.
    connections : sequence of rosbags connections
        The directory's connections whose messages may be asked for.

    Raises
    ------
    Exception
        Any reason to read the bag with ``rosbags``' reader instead (use :func:`index_messages`).
    """

    def __init__(self, reader: Any, connections: Sequence[Any]) -> None:
        from ppoe_core.io.mcap_kernel import scan_messages

        storage = _storage(reader)
        self._storage_connections = list(storage.connections)
        wanted = set(_channel_map(self._storage_connections, connections))
        chunks = [c for c in storage.chunks if any(c.channel_count.get(cid, 0) for cid in wanted)]
        if len({c.chunk_start_offset for c in chunks}) != len(chunks):
            raise _NotIndexable("two chunk index records of one chunk")
        with Path(storage.path).open("rb") as f:
            mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        parts = [_chunk_bytes(mm, c) for c in chunks]
        if all(p is None for p in parts):  # uncompressed: the records are read where they are in the file
            self._raw: Any = mm
            starts = np.array([c.chunk_start_offset + _CHUNK_PREFIX for c in chunks], dtype=np.int64)
        else:
            pieces = [mm[c.chunk_start_offset + _CHUNK_PREFIX:c.chunk_start_offset + _CHUNK_PREFIX
                         + c.uncompressed_size] if p is None else p for c, p in zip(chunks, parts)]
            self._raw = b"".join(pieces)
            starts = np.cumsum([0] + [len(p) for p in pieces[:-1]], dtype=np.int64)
        sizes = np.array([c.uncompressed_size for c in chunks], dtype=np.int64)
        self._buf = np.frombuffer(self._raw, dtype=np.uint8)
        status, chan, log_time, self._off, self._len, seg = scan_messages(self._buf, starts, starts + sizes)
        if status < 0:
            raise _NotIndexable(f"chunk {chunks[-1 - status].chunk_start_offset} is not a whole number of records")
        if log_time.shape[0] and int(log_time.max()) > _MAX_TIME:
            raise _NotIndexable("a log time beyond int64")
        _check_counts(chunks, chan, seg, wanted)
        self._chan, self._time, self._seg = chan, log_time.astype(np.int64), seg
        self._chunks = chunks
        t0 = np.array([c.message_start_time for c in chunks], dtype=np.int64)  # OverflowError beyond int64
        t1 = np.array([c.message_end_time for c in chunks], dtype=np.int64)
        self._in_range = (self._time >= t0[seg]) & (self._time <= t1[seg])  # rosbags: start <= t < end + 1
        self._chunk_offset = np.array([c.chunk_start_offset for c in chunks], dtype=np.int64)

    def _select(self, connections: Sequence[Any]) -> tuple[np.ndarray, dict[int, Any]]:
        """Indices of the messages of ``connections`` in ``rosbags``' order, and channel id -> connection."""
        cmap = _channel_map(self._storage_connections, connections)
        wanted = np.array(sorted(cmap), dtype=np.int64)
        use_chunk = np.array([any(c.channel_count.get(cid, 0) for cid in cmap) for c in self._chunks], dtype=bool)
        mask = np.isin(self._chan, wanted) & use_chunk[self._seg] & self._in_range
        idx = np.flatnonzero(mask)
        order = np.lexsort((idx, self._chunk_offset[self._seg[idx]], self._time[idx]))
        return idx[order], cmap

    def messages(self, connections: Sequence[Any]) -> Iterator[tuple[Any, int, bytes]]:
        """``(connection, log time [ns], data)`` of the messages of ``connections``, as ``rosbags``' reader yields
        them."""
        idx, cmap = self._select(connections)
        raw = self._raw
        for cid, stamp, off, n in zip(self._chan[idx].tolist(), self._time[idx].tolist(), self._off[idx].tolist(),
                                      self._len[idx].tolist()):
            yield cmap[cid], stamp, raw[off:off + n]

    def rows(self, connections: Sequence[Any]) -> np.ndarray | None:
        """The data of the messages of ``connections`` in order as the rows of one (N, size) uint8 array (a copy),
        or None when there are none or they differ in length."""
        from ppoe_core.io.mcap_kernel import gather_rows

        found = self.spans(connections)
        return None if found is None else gather_rows(*found)

    def spans(self, connections: Sequence[Any]) -> tuple[np.ndarray, np.ndarray, int] | None:
        """Where the data of the messages of ``connections`` is, in order: ``(buf, offsets, size)``, message ``i``
        being ``buf[offsets[i]:offsets[i] + size]`` (``buf`` uint8, read-only: the file or its decompressed chunks);
        None when there are none or they differ in length."""
        idx = self._select(connections)[0]
        if not idx.shape[0]:
            return None
        lengths = self._len[idx]
        if (lengths != lengths[0]).any():
            return None
        return self._buf, self._off[idx], int(lengths[0])
