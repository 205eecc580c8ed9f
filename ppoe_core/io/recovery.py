"""Reading what can be read of a damaged or unfinished bag.

Two cases the ``rosbags`` reader refuses or reads only in part:

* **An unfinished recording** (``ppoe record`` or ``ros2 bag record`` killed with ``-9``, power
  loss): the mcap file has no summary and no footer, and ``metadata.yaml`` may be missing.
  :class:`RecoveredMcap` scans the file's records from the start (MCAP format: magic, then
  ``opcode u8, length u64, body``; schemas, channels and messages, also inside chunks) and
  keeps every complete record, up to the first truncated or unreadable one.
* **A damaged bag** (a zeroed or overwritten block): ``metadata.yaml`` holds the true message
  count of each topic; :func:`expected_counts` reads them so that the reader can say per topic
  what was lost (:func:`loss_report`).

:class:`RecoveredMcap` offers the part of the ``rosbags`` reader interface that
:mod:`ppoe_core.io.reader` uses (``connections``, ``messages(connections=...)``, ``close()``).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ppoe_core.errors import BagError

__all__ = ["RECORDING_KEY", "ReadStatus", "RecoveredConnection", "RecoveredMcap", "account", "expected_counts",
           "loss_report", "lost_messages", "recording_in_progress"]

#: ``custom_data`` key of the interim ``metadata.yaml`` a recorder writes while the bag is open
RECORDING_KEY = "ppoe_recording"

_MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_FOOTER = 0x03, 0x04, 0x05, 0x06, 0x02
_NONZERO = re.compile(b"[^\\x00]")
_OPS = frozenset(range(0x01, 0x10))  # header .. data end: every opcode of MCAP version 0


@dataclass(frozen=True)
class RecoveredConnection:
    """One channel of a scanned mcap file (the fields of a ``rosbags`` connection used here)."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


def _string(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    return buf[pos + 4:pos + 4 + n].decode("utf-8"), pos + 4 + n


class _Scan:
    """Records of one mcap file: schemas, channels, messages, and where and why the scan stopped."""

    def __init__(self) -> None:
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
        self.messages: list[tuple[int, int, bytes]] = []  # (log time ns, channel id, data)
        self.damage: list[str] = []
        self.bad_chunks = 0
        self.footer = False

    def records(self, buf: bytes, start: int, end: int, in_chunk: bool) -> None:
        """Parse the records in ``buf[start:end]``; over damaged bytes, resynchronise on the next plausible record."""
        pos = start
        while pos < end:
            if not self._plausible(buf, pos, end):
                nxt = self._resync(buf, pos + 1, end)
                self.damage.append(f"{(nxt or end) - pos} unreadable bytes at {pos}"
                                   + (" (in a chunk)" if in_chunk else ""))
                if nxt is None:
                    return
                pos = nxt
            op = buf[pos]
            (length,) = struct.unpack_from("<Q", buf, pos + 1)
            body = pos + 9
            if op == _OP_FOOTER and not in_chunk:
                self.footer = True
                return
            try:
                self._record(op, buf, body, body + length)
            except (struct.error, UnicodeDecodeError, ValueError, IndexError) as exc:
                self.damage.append(f"unreadable record (opcode 0x{op:02x}) at {pos}: {exc}")
            pos = body + length

    def _plausible(self, buf: bytes, pos: int, end: int) -> bool:
        """A record can start at ``pos``: known opcode, its length fits, and a record or the end follows."""
        if pos + 9 > end or buf[pos] not in _OPS:
            return False
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        nxt = pos + 9 + length
        if nxt > end:
            return False
        if buf[pos] == _OP_MESSAGE and (length < 22 or struct.unpack_from("<H", buf, pos + 9)[0] not in self.channels):
            return False
        if nxt == end:
            return True
        if nxt + 9 > end or buf[nxt] not in _OPS:
            return False
        return nxt + 9 + struct.unpack_from("<Q", buf, nxt + 1)[0] <= end

    def _resync(self, buf: bytes, pos: int, end: int) -> int | None:
        """The first position at or after ``pos`` where a plausible record starts (None: none)."""
        while pos < end:
            hit = _NONZERO.search(buf, pos, end)  # skip zeros fast
            if hit is None:
                return None
            pos = hit.start()
            if self._plausible(buf, pos, end):
                return pos
            pos += 1
        return None

    def _record(self, op: int, buf: bytes, pos: int, end: int) -> None:
        if op == _OP_SCHEMA:
            (sid,) = struct.unpack_from("<H", buf, pos)
            self.schemas[sid], _ = _string(buf, pos + 2)
        elif op == _OP_CHANNEL:
            cid, sid = struct.unpack_from("<HH", buf, pos)
            topic, _ = _string(buf, pos + 4)
            self.channels[cid] = (topic, sid)
        elif op == _OP_MESSAGE:
            cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", buf, pos)
            self.messages.append((log_time, cid, bytes(buf[pos + 22:end])))
        elif op == _OP_CHUNK:
            self._chunk(buf, pos, end)

    def _chunk(self, buf: bytes, pos: int, end: int) -> None:
        from rosbags.rosbag2.storage_mcap import decompress

        _t0, _t1, size, crc = struct.unpack_from("<QQQI", buf, pos)
        compression, p = _string(buf, pos + 28)
        (n,) = struct.unpack_from("<Q", buf, p)
        try:
            raw = decompress(bytes(buf[p + 8:p + 8 + n]), compression, size, crc)
        except Exception:  # noqa: BLE001 - a damaged chunk: skip it, count it, go on
            self.bad_chunks += 1
            return
        self.records(raw, 0, len(raw), in_chunk=True)


class RecoveredMcap:
    """The messages of a bag directory's mcap file(s), read record by record without the index.

    Parameters
    ----------
    path : Path
        Bag directory.
    reason : str
        Why the normal reader could not open it (named in :attr:`note`).

    Raises
    ------
    BagError
        No mcap file, or no message could be recovered.
    """

    def __init__(self, path: Path, reason: str) -> None:
        files = sorted(path.glob("*.mcap")) if path.is_dir() else []
        if not files:
            raise BagError(f"bag {path}: cannot open as a rosbag2 directory: {reason}")
        scan, stops = _Scan(), []
        for f in files:
            buf = f.read_bytes()
            if not buf.startswith(_MAGIC):
                raise BagError(f"bag {path}: cannot open as a rosbag2 directory: {reason}; "
                               f"{f.name} does not start with the MCAP magic, nothing to recover")
            scan.records(buf, 8, len(buf), in_chunk=False)
            if scan.damage:
                stops.append(f"{f.name}: {', '.join(scan.damage[:3])}"
                             + (f" and {len(scan.damage) - 3} more" if len(scan.damage) > 3 else ""))
                scan.damage = []
        if not scan.messages:
            raise BagError(f"bag {path}: cannot open as a rosbag2 directory: {reason}; no complete message "
                           "found to recover" + (f" ({'; '.join(stops)})" if stops else ""))
        scan.messages.sort(key=lambda m: m[0])
        counts: dict[int, int] = {}
        for _, cid, _ in scan.messages:
            counts[cid] = counts.get(cid, 0) + 1
        self.connections = [RecoveredConnection(cid, topic, scan.schemas.get(sid, "?"), counts.get(cid, 0))
                            for cid, (topic, sid) in sorted(scan.channels.items())]
        self._messages = scan.messages
        self._by_id = {c.id: c for c in self.connections}
        where = "; ".join(stops + ([f"{scan.bad_chunks} damaged chunk(s) skipped"] if scan.bad_chunks else []))
        self.note = (f"bag {path}: {reason}: recovered {len(scan.messages)} messages record by record"
                     + ("" if scan.footer else " (the file has no footer)")
                     + (f"; skipped: {where}" if where else ""))

    def messages(self, connections: Sequence[Any] | None = None) -> Iterator[tuple[Any, int, bytes]]:
        """``(connection, log time ns, raw CDR)`` in log-time order, of ``connections`` (default all)."""
        wanted = None if connections is None else {c.id for c in connections}
        for log_time, cid, data in self._messages:
            if wanted is None or cid in wanted:
                conn = self._by_id.get(cid)
                if conn is not None:
                    yield conn, log_time, data

    def close(self) -> None:
        """Nothing to release (the file was read at construction)."""


def expected_counts(path: Path) -> dict[str, int] | None:
    """Message count per topic from the bag's ``metadata.yaml``, or None if it has none (or unreadable)."""
    import yaml

    meta = Path(path) / "metadata.yaml"
    try:  # libyaml's parser where PyYAML has it (0.7 against 6 ms for a 4 kB file; the same safe constructor)
        doc = yaml.load(meta.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        topics = doc["rosbag2_bagfile_information"]["topics_with_message_count"]
        return {str(t["topic_metadata"]["name"]): int(t["message_count"]) for t in topics}
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None


def recording_in_progress(path: Path) -> bool:
    """True if the bag's ``metadata.yaml`` is a recorder's interim one (:data:`RECORDING_KEY`): never closed."""
    import yaml

    try:
        doc = yaml.safe_load((Path(path) / "metadata.yaml").read_text())
        return RECORDING_KEY in (doc["rosbag2_bagfile_information"].get("custom_data") or {})
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return False


def loss_report(path: Path | str, read: Mapping[str, int], expected: Mapping[str, int],
                error: str = "") -> str | None:
    """One line saying per topic what was lost (``read`` fewer than ``expected``), or None if nothing."""
    lost = {t: (read.get(t, 0), n) for t, n in expected.items() if read.get(t, 0) < n}
    if not lost and not error:
        return None
    n_read = sum(min(read.get(t, 0), n) for t, n in expected.items())
    parts = ", ".join(f"{t} {r} of {n}" for t, (r, n) in sorted(lost.items()))
    return (f"bag {path}: damaged: read {n_read} of {sum(expected.values())} messages"
            + (f" ({parts})" if parts else "") + (f"; reading stopped: {error}" if error else ""))


class ReadStatus:
    """Messages read per topic and why reading stopped early (empty if it did not)."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}  # read and decodable
        self.error = ""
        self.undecodable = 0
        self.first_undecodable = ""

    def reject(self, topic: str, k: int, exc: Exception) -> None:
        """Message ``k`` of ``topic`` was read but its bytes do not parse (damaged): not counted as read."""
        self.counts[topic] -= 1
        self.undecodable += 1
        self.first_undecodable = self.first_undecodable or f"{topic} message {k}: {exc}"

    def problem(self) -> str:
        """Why messages are missing beyond the per-topic counts ('' if nothing went wrong)."""
        bad = (f"{self.undecodable} message(s) read but undecodable (first: {self.first_undecodable})"
               if self.undecodable else "")
        return "; ".join(p for p in (self.error, bad) if p)


def account(path: str | Path, reader: Any, conns: list[Any], status: ReadStatus,
            accept_partial: bool) -> list[str]:
    """Compare what was read with ``metadata.yaml`` (else the file's own counts); returns notes for the user.

    Raises
    ------
    BagError
        Messages were lost (per topic, read of expected) and ``accept_partial`` is False.
    """
    notes = [reader.note] if isinstance(reader, RecoveredMcap) else []
    meta = expected_counts(Path(path))
    topics = {c.topic for c in conns}
    if meta is not None:
        expected = {t: n for t, n in meta.items() if t in topics}
    elif isinstance(reader, RecoveredMcap):
        expected = {}  # nothing to compare with: the note says it was recovered
    else:
        expected = {c.topic: int(c.msgcount) for c in conns}
    report = loss_report(path, status.counts, expected, status.problem())
    if report is not None:
        if not accept_partial:
            raise BagError(report + "; pass --accept-partial to use what was read")
        notes.append(report + " (accepted: --accept-partial)")
    return notes


def lost_messages(path: str | Path, parse: list[Any], status: ReadStatus) -> bool:
    meta = expected_counts(Path(path)) or {c.topic: int(c.msgcount) for c in parse}
    return any(status.counts.get(c.topic, 0) < meta.get(c.topic, 0) for c in parse)
