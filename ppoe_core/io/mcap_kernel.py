"""Compiled (numba) walks over MCAP records for :mod:`ppoe_core.io.mcap_index`: the Message records of chunks
(:func:`scan_messages`), a block of equally long messages copied into one array (:func:`gather_rows`), or checked
against a first message and only some of their bytes copied (:func:`gather_layout`).

MCAP record: ``opcode u8, length u64, body``; a Message body is ``channel_id u16, sequence u32, log_time u64,
publish_time u64, data`` (little endian).  Declared with :func:`ppoe_core.jit.njit`: numba is imported on the first
call, not by ``import ppoe_core``.
"""

from __future__ import annotations

import numpy as np

from ppoe_core.jit import njit

__all__ = ["scan_messages", "gather_rows", "gather_layout", "MESSAGE_OP", "MESSAGE_HEADER"]

#: opcode of a Message record
MESSAGE_OP = 0x05
#: bytes of a Message body before its data (channel id, sequence, log time, publish time)
MESSAGE_HEADER = 22


@njit(cache=True, nogil=True)
def _u64(buf: np.ndarray, pos: int) -> np.uint64:
    v = np.uint64(0)
    for b in range(8):
        v |= np.uint64(buf[pos + b]) << np.uint64(8 * b)
    return v


@njit(cache=True, nogil=True)
def _walk(buf: np.ndarray, start: int, end: int, seg: int, n: int, out_chan: np.ndarray, out_time: np.ndarray,
          out_off: np.ndarray, out_len: np.ndarray, out_seg: np.ndarray, fill: bool) -> int:
    """The records of ``buf[start:end]``: counts (and with ``fill`` writes from index ``n``) its Message records;
    returns the new count, or -1 where a record does not fit or a Message body is shorter than its header."""
    pos = start
    while pos < end:
        if end - pos < 9:
            return -1
        length = _u64(buf, pos + 1)
        if length > np.uint64(end - pos - 9):
            return -1
        body = pos + 9
        nxt = body + np.int64(length)
        if buf[pos] == MESSAGE_OP:
            if nxt - body < MESSAGE_HEADER:
                return -1
            if fill:
                out_chan[n] = np.int64(buf[body]) | (np.int64(buf[body + 1]) << 8)
                out_time[n] = _u64(buf, body + 6)
                out_off[n] = body + MESSAGE_HEADER
                out_len[n] = nxt - body - MESSAGE_HEADER
                out_seg[n] = seg
            n += 1
        pos = int(nxt)
    return n


@njit(cache=True, nogil=True)
def scan_messages(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray
                  ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The Message records of the record segments ``buf[starts[s]:ends[s]]`` (the records of chunks), in order.

    Parameters
    ----------
    buf : ndarray, uint8, shape (B,)
    starts, ends : ndarray, int64, shape (S,)
        Each segment's first and past-the-end byte; every segment must be a whole number of records.

    Returns
    -------
    status : int
        ``-1 - s``: segment ``s`` is not a whole number of records or holds a Message body shorter than its
        header (the arrays are then empty); else the number of messages ``N``.
    channel, log_time (uint64), offset, length, segment : ndarray, shape (N,)
        Per message: channel id, log time [ns], where its data starts in ``buf``, its data length, its segment.
    """
    total = 0
    empty = np.zeros(0, dtype=np.int64)
    for s in range(starts.shape[0]):
        got = _walk(buf, starts[s], ends[s], s, total, empty, np.zeros(0, dtype=np.uint64), empty, empty, empty,
                    False)
        if got < 0:
            return -1 - s, empty, np.zeros(0, dtype=np.uint64), empty, empty, empty
        total = got
    chan = np.empty(total, dtype=np.int64)
    log_time = np.empty(total, dtype=np.uint64)
    off = np.empty(total, dtype=np.int64)
    length = np.empty(total, dtype=np.int64)
    seg = np.empty(total, dtype=np.int64)
    n = 0
    for s in range(starts.shape[0]):
        n = _walk(buf, starts[s], ends[s], s, n, chan, log_time, off, length, seg, True)
    return n, chan, log_time, off, length, seg


@njit(cache=True, nogil=True)
def gather_rows(buf: np.ndarray, offsets: np.ndarray, size: int) -> np.ndarray:
    """``buf[offsets[i]:offsets[i] + size]`` as the rows of one (N, size) uint8 array."""
    out = np.empty((offsets.shape[0], size), dtype=np.uint8)
    for i in range(offsets.shape[0]):
        out[i, :] = buf[offsets[i]:offsets[i] + size]
    return out


@njit(cache=True, nogil=True, inline="always")
def _copy_piece(buf: np.ndarray, src: int, out: np.ndarray, i: int) -> None:
    for b in range(out.shape[1]):
        out[i, b] = buf[src + b]


@njit(cache=True, nogil=True)
def gather_layout(buf: np.ndarray, offsets: np.ndarray, first: np.ndarray, cols: np.ndarray, zero_from: int,
                  starts: np.ndarray, out0: np.ndarray, out1: np.ndarray, out2: np.ndarray, out3: np.ndarray) -> bool:
    """Messages ``buf[offsets[i]:offsets[i] + S]`` (S = ``first.shape[0]``) laid out as ``first``: False as soon as one
    differs from ``first`` at a byte of ``cols`` or has a byte other than 0 at ``zero_from`` or after; else each
    message's bytes ``starts[k]`` on copied into row ``i`` of ``out<k>`` (N, width_k) uint8, and True.

    Parameters
    ----------
    buf : ndarray, uint8, shape (B,)
    offsets : ndarray, int64, shape (N,)
    first : ndarray, uint8, shape (S,)
    cols : ndarray, int64
        The byte positions compared with ``first``.
    zero_from : int
        The first of the bytes that must be 0 (S: none).
    starts : ndarray, int64, shape (4,)
    out0, out1, out2, out3 : ndarray, uint8, shape (N, width_k)
    """
    size = first.shape[0]
    for i in range(offsets.shape[0]):
        o = offsets[i]
        for c in cols:
            if buf[o + c] != first[c]:
                return False
        for b in range(zero_from, size):
            if buf[o + b] != 0:
                return False
        _copy_piece(buf, o + starts[0], out0, i)
        _copy_piece(buf, o + starts[1], out1, i)
        _copy_piece(buf, o + starts[2], out2, i)
        _copy_piece(buf, o + starts[3], out3, i)
    return True
