"""Compiled (numba) walks over MCAP records for :mod:`ppoe_core.io.mcap_index`: the Message records of chunks
(:func:`scan_messages`) and a block of equally long messages copied into one array (:func:`gather_rows`).

MCAP record: ``opcode u8, length u64, body``; a Message body is ``channel_id u16, sequence u32, log_time u64,
publish_time u64, data`` (little endian).  Declared with :func:`ppoe_core.jit.njit`: numba is imported on the first
call, not by ``import ppoe_core``.
"""

from __future__ import annotations

import numpy as np

from ppoe_core.jit import njit

__all__ = ["scan_messages", "gather_rows", "MESSAGE_OP", "MESSAGE_HEADER"]

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
