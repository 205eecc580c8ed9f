"""The kinematics node's per-message path as ONE compiled call: serialised ``sensor_msgs/JointState`` bytes in,
serialised ``geometry_msgs/PoseWithCovarianceStamped`` bytes out.

What the Python path does step by step (:func:`ppoe_core.io.cdr.parse_joint_state`,
:meth:`ppoe_core.model.joint_history.JointHistory.update`, the one-configuration :meth:`PPOEModel.fk
<ppoe_core.model.ppoe.PPOEModel.fk>`, :func:`ppoe_core.lie.quat_from_matrix`, :func:`ppoe_core.lie.cov_local_to_ros`,
:class:`ppoe_core.io.cdr.PoseCovarianceWriter`) costs about 30 us per message in Python and numpy dispatch;
the arithmetic is a few microseconds.  :class:`JointPoseFastPath` runs the same steps with the same compiled
pieces (:func:`ppoe_core.model.chain_kernel.fk_one`, the quaternion and covariance kernels of
:mod:`ppoe_core.lie.kernels`, the writer's own buffer) in one numba call, for the messages where nothing is
unusual: a name layout seen before (the bytes of the name sequence equal a learned one), every position finite,
the stamp not older than the last one nor beyond the future limit, the chain's joints all known and fresh (the
merge step is the history's own compiled :func:`~ppoe_core.model.joint_history.merge_into` /
:func:`~ppoe_core.model.joint_history.fresh_vector`).  Anything else returns "not
handled" BEFORE any state changed, and the caller runs its Python path, which produces the diagnostics (and
learns a new name layout for the next message).  Same floats as the Python path (``test/test_joint_pose.py``).
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
from ppoe_core.jit import njit

from ppoe_core.model.joint_history import NEVER_NS, JointHistory, fresh_vector, merge_into
from ppoe_core.io import cdr
from ppoe_core.io.cdr import PoseCovarianceWriter
from ppoe_core.lie.kernels import pose_cov_fields_into
from ppoe_core.model.chain_kernel import FOURTH_WORK, fk_one

__all__ = ["JointPoseFastPath", "joint_state_pose", "chain_pose_cdr", "MAX_LAYOUTS"]

#: name layouts (publishers) remembered at once; the oldest is forgotten first
MAX_LAYOUTS = 8
#: no future limit
NO_LIMIT = np.iinfo(np.int64).max
_align = njit(cache=True, inline="always")(cdr.align)  # the CDR alignment rule of ppoe_core.io.cdr, compiled


@njit(cache=True, inline="always")
def _u32(d: Any, p: int) -> Any:
    """The little-endian uint32 at byte ``p`` (an int64)."""
    return np.int64(d[p]) | (np.int64(d[p + 1]) << 8) | (np.int64(d[p + 2]) << 16) | (np.int64(d[p + 3]) << 24)


@njit(cache=True, inline="always")
def _f64(d: Any, p: int, scratch: np.ndarray) -> float:
    """The little-endian float64 at byte ``p`` (via ``scratch`` (1,) float64, the bit pattern written as uint64)."""
    x = np.uint64(0)
    for k in range(8):
        x |= np.uint64(d[p + k]) << np.uint64(8 * k)
    scratch.view(np.uint64)[0] = x
    return scratch[0]


@njit(cache=True)
def _layout(d: Any, lay: np.ndarray, blob: np.ndarray) -> tuple[int, int, int]:
    """Header, ``frame_id`` and name sequence of the JointState bytes ``d``: ``(layout row, stamp ns, position
    after the names)``, row -1 for anything :func:`ppoe_core.io.cdr.parse_joint_state` might refuse or a name
    sequence that is not a learned one (``lay`` rows ``[blob start, blob length, count, map start, map length]``)."""
    n = len(d)
    if n < 16 or d[0] != 0 or d[1] != 1:
        return -1, 0, 0
    sec = _u32(d, 4)
    if sec >= 2**31:
        sec -= 2**32
    stamp = sec * 1_000_000_000 + _u32(d, 8)
    flen = _u32(d, 12)
    fend = 16 + flen
    if flen == 0 or fend > n or d[fend - 1] != 0:
        return -1, 0, 0
    for i in range(16, fend - 1):
        if d[i] >= 128:  # not ASCII: the Python path checks the UTF-8
            return -1, 0, 0
    pos = _align(fend, 4)
    if pos + 4 > n:
        return -1, 0, 0
    count = _u32(d, pos)
    start = pos + 4
    for r in range(lay.shape[0]):
        b0, bl = lay[r, 0], lay[r, 1]
        if lay[r, 2] != count or start + bl > n:
            continue
        same = True
        for i in range(bl):
            if d[start + i] != blob[b0 + i]:
                same = False
                break
        if same:
            return r, stamp, start + bl
    return -1, 0, 0


@njit(cache=True)
def _merge(d: Any, pos: int, count: int, src: np.ndarray, dst: np.ndarray, stamp: int, values: np.ndarray,
           stamps: np.ndarray, max_age: int, scratch: np.ndarray) -> bool:
    """:meth:`JointHistory.update` of the positions at ``pos`` (``count`` of them, checked to fit) with the index
    maps ``src``/``dst`` when it gives a joint vector; False (nothing changed) when it would not or would raise."""
    npos = _u32(d, pos)
    pos = _align(pos + 4, 8) if npos else pos + 4
    if npos != count or pos + 8 * npos > len(d) or src.shape[0] == 0:
        return False
    carried = np.empty(src.shape[0])
    for i in range(src.shape[0]):
        carried[i] = _f64(d, pos + 8 * src[i], scratch)
        if not np.isfinite(carried[i]):
            return False
    new_v = values.copy()
    new_s = stamps.copy()
    merge_into(new_v, new_s, dst, carried, stamp)
    if fresh_vector(new_v, new_s, stamp, max_age, NEVER_NS, np.empty(new_v.shape[0])):
        return False
    values[:] = new_v
    stamps[:] = new_s
    return True


@njit(cache=True)
def chain_pose_cdr(q: np.ndarray, motion_col: np.ndarray, mult: np.ndarray, off: np.ndarray, program: tuple,
                   order: int, fourth: np.ndarray | None, stamp: int, out_u8: np.ndarray, out_f8: np.ndarray) -> bool:
    """One pose message of the chain ``program`` at the joint vector ``q`` into a
    :class:`~ppoe_core.io.cdr.PoseCovarianceWriter`'s buffer (``raw``, ``fields``): ``model.fk`` (one
    configuration), the quaternion, the ROS-convention covariance and ``header.stamp``; False (nothing written)
    for a non-finite joint value or a stamp whose seconds do not fit ``int32``.  ``fourth``: the fourth-order work
    array of :func:`~ppoe_core.model.chain_kernel.fk_one` for ``order`` 4, None for order 2 (the fourth-order code
    is then not compiled in)."""
    sec = stamp // 1_000_000_000
    nsec = stamp - sec * 1_000_000_000
    if sec < -(2**31) or sec >= 2**31:
        return False
    F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start = program
    T = np.empty((4, 4))
    cov = np.zeros((6, 6))
    if not fk_one(F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start, q, motion_col, mult, off, order, T, cov,
                  fourth):
        return False
    usec = sec + 2**32 if sec < 0 else sec
    for k in range(4):
        out_u8[4 + k] = (usec >> (8 * k)) & 0xFF
        out_u8[8 + k] = (nsec >> (8 * k)) & 0xFF
    pose_cov_fields_into(T, cov, out_f8)
    return True


@njit(cache=True)
def joint_state_pose(d: Any, lay: np.ndarray, blob: np.ndarray, src: np.ndarray, dst: np.ndarray,
                     values: np.ndarray, stamps: np.ndarray, max_age: int, clock: np.ndarray, limit: int,
                     model_dst: np.ndarray, q: np.ndarray, motion_col: np.ndarray, mult: np.ndarray, off: np.ndarray,
                     program: tuple, order: int, fourth: np.ndarray | None, out_u8: np.ndarray,
                     out_f8: np.ndarray) -> int:
    """The whole per-message path for the first target (module docstring): 1 when the pose message is in
    ``out_u8`` (``q`` holds the joint vector, ``clock`` = ``[last stamp ns, has one]`` the message's stamp), 0 when
    the message is left to the Python path (also a stamp after ``limit``, the clock plus the future tolerance)."""
    r, stamp, pos = _layout(d, lay, blob)
    if r < 0 or stamp > limit or (clock[1] != 0 and stamp < clock[0]):
        return 0
    pos = _align(pos, 4)
    if pos + 4 > len(d):
        return 0
    m0, ml = lay[r, 3], lay[r, 4]
    if not _merge(d, pos, lay[r, 2], src[m0:m0 + ml], dst[m0:m0 + ml], stamp, values, stamps, max_age,
                  np.empty(1)):
        return 0
    q[:] = 0.0
    for j in range(model_dst.shape[0]):
        q[model_dst[j]] = values[j]
    if not chain_pose_cdr(q, motion_col, mult, off, program, order, fourth, stamp, out_u8, out_f8):
        return 0  # an overflowing joint value or seconds beyond int32: the Python path reports it
    clock[0] = stamp
    clock[1] = 1
    return 1


class JointPoseFastPath:
    """:func:`joint_state_pose` with its state, for one node's model and targets (module docstring).

    Parameters
    ----------
    history : the node's joint history (its ``values`` / ``stamps`` / ``clock`` arrays are updated in place, shared
        with the Python path); its joints are the chain's, in the order of ``model_dst``
    model_dst : index of each of ``history.joints`` in the model's joint vector
    n_joints : length of the model's joint vector
    targets : per output ``(model.lean_program(reference, frame), writer)``
    order : covariance order (2 or 4)
    """

    def __init__(self, history: JointHistory, model_dst: np.ndarray, n_joints: int,
                 targets: list[tuple[Any, PoseCovarianceWriter]], order: int) -> None:
        if sys.byteorder != "little":  # pragma: no cover - the writer's doubles are little endian
            raise ValueError("JointPoseFastPath needs a little-endian host")
        self._history = history
        self._model_dst = np.ascontiguousarray(model_dst, dtype=np.int64)
        self._q = np.zeros(n_joints)
        self._order = int(order)
        self._fourth = np.empty(FOURTH_WORK + (1,)) if self._order == 4 else None
        self._targets = [(lean.program, lean.motion_col, lean.mult, lean.off, w.raw, w.fields) for lean, w in targets]
        self._layouts: dict[bytes, tuple[int, np.ndarray, np.ndarray]] = {}
        self._lay = np.zeros((0, 5), dtype=np.int64)
        self._blob = np.zeros(0, dtype=np.uint8)
        self._src = np.zeros(0, dtype=np.int64)
        self._dst = np.zeros(0, dtype=np.int64)

    def run(self, data: bytes, limit_ns: int = NO_LIMIT) -> bool:
        """Write every target's message into its writer's buffer; False: the message is the Python path's
        (``limit_ns``: a stamp after it is, the receiver's clock plus the future tolerance)."""
        program, col, mult, off, raw, fields = self._targets[0]
        h = self._history
        if not joint_state_pose(data, self._lay, self._blob, self._src, self._dst, h.values, h.stamps, h.max_age_ns,
                                h.clock, limit_ns, self._model_dst, self._q, col, mult, off, program, self._order,
                                self._fourth, raw, fields):
            return False
        for program, col, mult, off, raw, fields in self._targets[1:]:
            if not chain_pose_cdr(self._q, col, mult, off, program, self._order, self._fourth, int(h.clock[0]), raw,
                                  fields):
                return False  # (an overflowing mimic joint) the Python path redoes the message: same stamp, same merge
        return True

    def learn(self, data: bytes, names: tuple[str, ...]) -> None:
        """Remember the name layout of ``data``, a message the Python path just merged (its layout has no
        problem: a refused layout is never learned)."""
        lay = self._history.layout(names)
        if lay.problem:
            return
        count, key = cdr.joint_state_names_block(data)
        if key in self._layouts or count != len(names):
            return
        if len(self._layouts) >= MAX_LAYOUTS:
            del self._layouts[next(iter(self._layouts))]
        self._layouts[key] = (count, lay.src, lay.dst)
        rows, blobs, srcs, dsts = [], [], [], []
        b0 = m0 = 0
        for blob, (cnt, s, d) in self._layouts.items():
            rows.append((b0, len(blob), cnt, m0, len(s)))
            blobs.append(np.frombuffer(blob, dtype=np.uint8))
            srcs.append(s)
            dsts.append(d)
            b0 += len(blob)
            m0 += len(s)
        self._lay = np.array(rows, dtype=np.int64)
        self._blob = np.concatenate(blobs)
        self._src = np.concatenate(srcs)
        self._dst = np.concatenate(dsts)

    def warm(self) -> None:
        """Compile (or load from numba's cache) the kernels: a message of no learned layout (nothing changes)."""
        probe = bytes(cdr.CDR_LE_HEADER) + bytes(8) + b"\x01\x00\x00\x00\x00\x00\x00\x00" + bytes(8)
        self.run(probe)
        program, col, mult, off, raw, fields = self._targets[0]
        chain_pose_cdr(np.full(self._q.shape, np.nan), col, mult, off, program, self._order, self._fourth, 0, raw,
                       fields)
