"""Reading contract bags: raw messages in log order (:func:`iter_raw`) and typed series (:func:`read_bag`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from ppoe_core.errors import BagError
from ppoe_core.io.cdr import (
    PARSE_ERRORS, JointStateBlock, as_bytes, header_rows_block, joint_state_block, joint_state_block_at,
)
from ppoe_core.io.mcap_index import McapIndex, index_messages
from ppoe_core.io.messages import T_POSE_COV, TOPIC_ROBOT_DESCRIPTION, deserialize, typestore
from ppoe_core.io.recovery import RecoveredMcap, ReadStatus, account, lost_messages, recording_in_progress
from ppoe_core.io.rows import (
    JOINT_STATE_KIND, RowKind, block_topic, expected_type, finish, finish_block, finish_joint_state_block,
    finish_restamped, restamped_topic, row_kind,
)
from ppoe_core.io.series import BagData, RawMessage


def _open_reader(path: str | Path) -> Any:
    """The rosbags reader of a bag directory; a bag it cannot open (no footer or no metadata: an
    unfinished recording) is read record by record instead (:class:`RecoveredMcap`, with a ``note``)."""
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise BagError(f"bag {p} does not exist")
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - any failure of rosbags: try the record-by-record scan
        if recording_in_progress(p):
            return RecoveredMcap(p, "the recording was never closed (its metadata.yaml is the recorder's interim one)")
        return RecoveredMcap(p, f"cannot open as a rosbag2 directory ({type(exc).__name__}: {exc})")
    return reader


def _messages(reader: Any, conns: list[Any], status: ReadStatus,
              validate: bool = False) -> Iterator[tuple[Any, int, Any]]:
    """``reader.messages`` that stops, instead of raising, where the file is damaged (noted in ``status``).

    ``validate``: deserialise each message of a known type and skip (count) those that do not parse.
    """
    known = typestore().types
    it = iter(reader.messages(connections=conns)) if conns else iter(())
    while True:
        try:
            conn, stamp_ns, data = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - ReaderError, struct/zstd errors, OverflowError of a damaged file
            status.error = f"{type(exc).__name__}: {exc}"
            return
        status.counts[conn.topic] = status.counts.get(conn.topic, 0) + 1
        if validate and conn.msgtype in known:
            try:
                deserialize(data, conn.msgtype, topic=conn.topic)
            except BagError as exc:
                status.reject(conn.topic, status.counts[conn.topic] - 1, exc)
                continue
        yield conn, stamp_ns, data


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topics of a bag -> (message type, message count), without reading messages."""
    reader = _open_reader(path)
    try:
        return {c.topic: (c.msgtype, int(c.msgcount)) for c in reader.connections}
    finally:
        reader.close()


class BagCheck(NamedTuple):
    """What :func:`check_bag` found: notes for the user, readable messages per topic, and whether the
    file had to be scanned record by record (pass ``scanned`` on to :func:`iter_raw`)."""

    notes: list[str]
    counts: dict[str, int]
    scanned: bool


def _count(reader: Any, topics: Iterable[str] | None) -> tuple[list[Any], ReadStatus]:
    """Read (and validate) every message of the wanted topics; the connections and what was read."""
    wanted = set(topics) if topics is not None else None
    conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
    status = ReadStatus()
    for _ in _messages(reader, conns, status, validate=True):
        pass
    return conns, status


def check_bag(path: str | Path, topics: Iterable[str] | None = None, *, accept_partial: bool = False) -> BagCheck:
    """Read every message (decoding it) and compare with the bag's metadata, before playing it.

    A damaged file is also scanned record by record (resynchronising over damaged bytes); the
    reading that recovers more messages is kept.

    Raises
    ------
    BagError
        Messages were lost (named per topic, read of expected) and ``accept_partial`` is False.
    """
    reader = _open_reader(path)
    try:
        conns, status = _count(reader, topics)
    finally:
        reader.close()
    if (status.problem() or lost_messages(path, conns, status)) and not isinstance(reader, RecoveredMcap):
        try:
            rescue = RecoveredMcap(Path(path), f"damaged ({status.problem() or 'messages missing'})")
            conns2, status2 = _count(rescue, topics)
            if sum(status2.counts.values()) > sum(status.counts.values()):
                reader, conns, status = rescue, conns2, status2
        except BagError:
            pass
    notes = account(path, reader, conns, status, accept_partial)
    return BagCheck(notes, dict(status.counts), isinstance(reader, RecoveredMcap))


def iter_raw(path: str | Path, topics: Iterable[str] | None = None, *, scanned: bool = False) -> Iterator[RawMessage]:
    """Yield the messages of a bag in log-time order as :class:`RawMessage` (for ``ppoe play``).

    ``topics`` restricts to these topic names (unknown names are ignored).  Messages that do not
    decode are skipped and reading stops quietly where the indexed reader fails: call
    :func:`check_bag` first to know what will be lost, and pass its ``scanned`` to read the file
    the way it recovered the most.
    """
    reader = RecoveredMcap(Path(path), "damaged") if scanned else _open_reader(path)
    try:
        wanted = set(topics) if topics is not None else None
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for conn, stamp_ns, data in _messages(reader, conns, ReadStatus(), validate=True):
            yield RawMessage(conn.topic, conn.msgtype, int(stamp_ns), bytes(data))
    finally:
        reader.close()


def read_bag(path: str | Path, *, topics: Iterable[str] | None = None, load_images: bool = True,
             accept_partial: bool = False, first: Iterable[str] = (),
             on_first: Callable[[BagData], None] | None = None) -> BagData:
    """Read a contract bag into numpy arrays.

    Parameters
    ----------
    path
        rosbag2 directory (mcap or sqlite3).
    topics
        Parse only these topics (all by default); the others are still listed in ``topics``.
    load_images
        Keep the encoded image bytes (``False`` keeps only stamps and formats).
    accept_partial
        Keep what could be read of a damaged bag (fewer messages than its ``metadata.yaml``
        says, or a file that stops being readable) instead of raising; :attr:`BagData.notes`
        then says per topic what was lost.  An unfinished recording (no footer or metadata) is
        always read record by record, with a note.
    first, on_first
        Read the topics ``first`` before the others and call ``on_first(data)`` with the ``BagData`` holding only
        them, complete, before the rest is read into the same object (``ppoe evaluate`` starts its image workers
        there, while the joint states are read).  Each topic's series are the same as in one pass (a topic's
        messages are read in the same order either way).  Not called for a file read record by record (an
        unfinished recording); a damaged file read again that way returns another ``BagData`` than the one
        ``on_first`` saw.

    Returns
    -------
    BagData

    Raises
    ------
    BagError
        Bag missing/unreadable, a contract topic with the wrong type, or a
        message that breaks the contract; the message names the topic.
    """
    reader = _open_reader(path)
    try:
        phases = None if on_first is None or isinstance(reader, RecoveredMcap) else (set(first), on_first)
        data, parse, status = _read_with(reader, path, topics, load_images, phases)
    finally:
        reader.close()
    if (status.problem() or lost_messages(path, parse, status)) and not isinstance(reader, RecoveredMcap):
        # a damaged file: the record-by-record scan may read more than the indexed reader
        try:
            rescue = RecoveredMcap(Path(path), f"damaged ({status.problem() or 'messages missing'})")
            data2, parse2, status2 = _read_with(rescue, path, topics, load_images)
            if sum(status2.counts.values()) > sum(status.counts.values()):
                reader, data, parse, status = rescue, data2, parse2, status2
        except BagError:
            pass
    data.notes = account(path, reader, parse, status, accept_partial)
    return data


def _read_with(reader: Any, path: str | Path, topics: Iterable[str] | None, load_images: bool,
               phases: tuple[set[str], Callable[[BagData], None]] | None = None
               ) -> tuple[BagData, list[Any], ReadStatus]:
    """Parse the wanted contract topics of an open reader; returns the data, the parsed connections
    and what was read.  ``phases``: the topics read first and the function called with the data once they are
    (:func:`read_bag`'s ``first`` and ``on_first``).  A single chunked mcap file is read through its message index
    (:mod:`ppoe_core.io.mcap_index`: the messages ``rosbags`` yields, in its order), the joint states and the
    fixed-layout topics at once where they allow it (:func:`_blocks`); any other bag through ``reader``."""
    data = BagData(path=str(path))
    conns = list(reader.connections)
    for c in conns:
        cnt = data.topics.get(c.topic, (c.msgtype, 0))[1] + int(c.msgcount)
        data.topics[c.topic] = (c.msgtype, cnt)
    wanted = set(topics) if topics is not None else None
    parse = []
    for c in conns:
        exp = expected_type(c.topic)
        if exp is not None and c.msgtype != exp:
            raise BagError(f"bag {path}: topic {c.topic} carries {c.msgtype}, the contract requires {exp}")
        if exp is None and c.msgtype != T_POSE_COV:
            data.unknown_topics[c.topic] = c.msgtype
            continue
        if wanted is not None and c.topic not in wanted:
            continue
        parse.append(c)
    acc: dict[str, list[Any]] = {}
    status = ReadStatus()
    kinds = {c.topic: row_kind(c.topic, c.msgtype) for c in parse if c.topic != TOPIC_ROBOT_DESCRIPTION}
    # /joint_states (most of a bag's messages) kept raw and read at once at the end where all share one layout
    held: dict[str, list[tuple[Any, int, Any]]] = {t: [] for t, kind in kinds.items() if kind is JOINT_STATE_KIND}
    index = None if isinstance(reader, RecoveredMcap) else index_messages(reader, parse)
    source: Any = reader if index is None else index
    parse_now = parse if index is None else [c for c in parse if c.topic not in held]  # held: from the index
    if phases is not None:
        early = _blocks(data, status, index, [c for c in parse_now if c.topic in phases[0]], load_images)
        _read_messages(data, acc, status, source, early, held, kinds, load_images)
        finish(data, acc)
        acc = {}
        phases[1](data)
        parse_now = [c for c in parse_now if c.topic not in phases[0]]
    _read_messages(data, acc, status, source, _blocks(data, status, index, parse_now, load_images), held, kinds,
                   load_images)
    for topic, msgs in held.items():
        if index is not None:
            _held_from_index(data, acc, status, index, [c for c in parse if c.topic == topic], kinds, load_images)
            continue
        block = _joint_state_block([raw for _, _, raw in msgs])
        if block is not None:
            finish_joint_state_block(data, topic, block)
            continue
        for conn, k, raw in msgs:  # one by one, as any other topic
            _add_message(data, acc, status, conn, k, raw, kinds[topic], load_images)
    finish(data, acc)
    return data, parse, status


def _blocks(data: BagData, status: ReadStatus, index: McapIndex | None, conns: list[Any],
            load_images: bool) -> list[Any]:
    """Read the :func:`~ppoe_core.io.rows.block_topic` and :func:`~ppoe_core.io.rows.restamped_topic` topics of
    ``conns`` at once from the index where their messages allow it (:func:`ppoe_core.io.cdr.header_rows_block`,
    :func:`~ppoe_core.io.rows.finish_block`, :func:`~ppoe_core.io.rows.finish_restamped`: the same series as one by
    one, and no message of theirs would raise or be rejected); returns the connections left to read one by one."""
    if index is None:
        return conns
    done = set()
    for topic in dict.fromkeys(c.topic for c in conns if block_topic(c.topic) or restamped_topic(c.topic)):
        mine = [c for c in conns if c.topic == topic]
        rows = index.rows(mine)
        if restamped_topic(topic):
            if rows is not None and finish_restamped(data, topic, mine[0].msgtype, rows, load_images):
                status.counts[topic] = status.counts.get(topic, 0) + rows.shape[0]
                done.add(topic)
            continue
        try:
            block = None if rows is None else header_rows_block(mine[0].msgtype, rows)
        except PARSE_ERRORS:
            block = None
        if block is not None and finish_block(data, topic, block):
            status.counts[topic] = status.counts.get(topic, 0) + block.stamps.shape[0]
            done.add(topic)
    return [c for c in conns if c.topic not in done]


def _held_from_index(data: BagData, acc: dict[str, list[Any]], status: ReadStatus, index: McapIndex,
                     conns: list[Any], kinds: dict[str, RowKind], load_images: bool) -> None:
    """One held topic's messages (``conns``) from the index: at once when they share one layout
    (:func:`ppoe_core.io.cdr.joint_state_block_at`), else one by one as any other topic."""
    topic = conns[0].topic
    found = index.spans(conns)
    try:
        block = None if found is None else joint_state_block_at(*found)
    except PARSE_ERRORS:
        block = None
    if block is None:
        _read_messages(data, acc, status, index, conns, {}, kinds, load_images)
        return
    status.counts[topic] = status.counts.get(topic, 0) + block.stamps.shape[0]
    finish_joint_state_block(data, topic, block)


def _read_messages(data: BagData, acc: dict[str, list[Any]], status: ReadStatus, reader: Any, conns: list[Any],
                   held: dict[str, list[tuple[Any, int, Any]]], kinds: dict[str, RowKind],
                   load_images: bool) -> None:
    """The messages of ``conns`` in log order as rows of ``acc``; the topics of ``held`` kept raw there."""
    for conn, _, raw in _messages(reader, conns, status):
        topic = conn.topic
        k = status.counts[topic] - 1
        if topic in held:
            held[topic].append((conn, k, raw))
            continue
        _add_message(data, acc, status, conn, k, raw, kinds.get(topic), load_images)


def _joint_state_block(raws: list[Any]) -> JointStateBlock | None:
    """:func:`ppoe_core.io.cdr.joint_state_block` of the messages (None also where the first does not parse)."""
    if not raws:
        return None
    try:
        return joint_state_block([as_bytes(r) for r in raws])
    except PARSE_ERRORS:
        return None


def _add_message(data: BagData, acc: dict[str, list[Any]], status: ReadStatus, conn: Any, k: int, raw: Any,
                 kind: RowKind | None, load_images: bool) -> None:
    """Message ``k`` of its topic -> a row of ``acc`` (or the robot description); a message the typed deserialiser
    refuses is rejected in ``status``."""
    topic = conn.topic
    fields = _raw_fields(kind, raw)
    if fields is None:  # typed deserialisation: robot description, other topics, and what the raw parser left
        try:
            msg = deserialize(raw, conn.msgtype, topic=topic)
        except BagError as exc:
            status.reject(topic, k, exc)
            return
    try:
        if kind is None:
            _description(data, msg, topic, k)
            return
        row = kind.build(kind.fields(msg) if fields is None else fields, topic, k, load_images)
    except BagError:
        raise
    except (ValueError, TypeError, AttributeError) as exc:
        raise BagError(f"bag {data.path}: topic {topic} message {k}: {exc}") from exc
    acc.setdefault(topic, []).append(row)


def _raw_fields(kind: RowKind | None, raw: Any) -> tuple | None:
    """The message's fields read from its raw bytes, or None where the typed deserialiser is needed."""
    if kind is None or kind.parse is None:
        return None
    try:
        return kind.parse(as_bytes(raw))
    except PARSE_ERRORS:
        return None


def _description(data: BagData, msg: Any, topic: str, k: int) -> None:
    """``/robot_description``: the first message, and every later one must equal it."""
    if data.robot_description is not None and msg.data != data.robot_description:
        raise BagError(f"topic {topic}: message {k} differs from the first (contract: once)")
    data.robot_description = msg.data
