"""Joint values per joint and by stamp from joint-state messages that each carry some joints: THE joint-history rule
of the kinematics node, the fusion node, the online hook and ``ppoe evaluate`` (docs/fusion_node.md, "Joint states").

With ros2_control an arm, a mast and a gripper often publish ``/joint_states`` separately.  :class:`JointHistory`

* merges per joint: it keeps the latest value and stamp of every joint; a message's joint vector uses the value of
  a joint the message lacks while that value is at most ``max_age`` old (0: no age limit), NaN otherwise;
* refuses a message (:class:`~ppoe_core.errors.JointValueError`, naming what) that lists a joint twice, has a NaN or
  infinite value for a needed joint, or lacks a needed joint while it carries a name the URDF does not have (a
  misspelt joint, e.g. ``joint_２``: the held value of the real joint is not used silently);
* takes stamps through one :class:`StampResetPolicy`: a stamp a little older than the last one is dropped, one
  much older starts a new timeline (the held values are forgotten), one too far ahead of the clock is refused;
* keeps the joint vectors by stamp (``keep_ns``) for :meth:`JointHistory.at`: the latest at or before a stamp, or,
  when every kept one is newer (a prior that overtook its joint state), the oldest if at most ``max_age`` newer.

The merge step itself is the compiled :func:`merge_into` / :func:`fresh_vector` (for one message in one call:
:func:`merge_message`), the same functions the kinematics node's compiled per-message path
(:mod:`ppoe_core.io.joint_pose`) and the batch of :meth:`JointHistory.merge_rows` (``ppoe evaluate``) run.
"""

from __future__ import annotations

import bisect
import unicodedata
from collections.abc import Collection, Sequence
from typing import Any, NamedTuple

import numpy as np
from ppoe_core.jit import njit

from ppoe_core.errors import JointValueError
from ppoe_core.model.stamp_policy import BACKWARD, FUTURE, NEW_TIMELINE, StampCheck, StampRefused, StampResetPolicy

__all__ = [
    "NEVER_NS", "StampResetPolicy", "StampCheck", "StampRefused", "JointUpdate", "JointHistory", "StampedHistory",
    "merge_into", "fresh_vector", "merge_message",
]

#: the stamp of a joint never seen
NEVER_NS = np.iinfo(np.int64).min

# ----------------------------------------------------------------------------
# The merge step (compiled: the kinematics node's fast path runs the same functions)
# ----------------------------------------------------------------------------


@njit(cache=True)
def merge_into(values: np.ndarray, stamps: np.ndarray, dst: np.ndarray, carried: np.ndarray, stamp: Any) -> None:
    """Joint ``dst[i]`` takes the value ``carried[i]`` and the stamp ``stamp`` (the message's)."""
    for i in range(dst.shape[0]):
        values[dst[i]] = carried[i]
        stamps[dst[i]] = stamp


@njit(cache=True)
def fresh_vector(values: np.ndarray, stamps: np.ndarray, stamp: Any, max_age: Any, never: Any,
                 out: np.ndarray) -> int:
    """The joint vector at a message stamped ``stamp`` into ``out``: each joint's value, NaN where never seen
    (``stamps == never``) or older than ``max_age`` (> 0); returns the number of NaN entries."""
    missing = 0
    for j in range(values.shape[0]):
        if stamps[j] == never or (max_age > 0 and stamp - stamps[j] > max_age):
            out[j] = np.nan
            missing += 1
        else:
            out[j] = values[j]
    return missing


@njit(cache=True)
def merge_message(values: np.ndarray, stamps: np.ndarray, pos: np.ndarray, src: np.ndarray, dst: np.ndarray,
                 needed_src: np.ndarray, needed_idx: np.ndarray, stamp: Any, max_age: Any, never: Any, reset: bool,
                 vec: np.ndarray) -> int:
    """:meth:`JointHistory.update`'s merge in one call: -1 (nothing changed) when a needed joint's value ``pos``
    carries is not finite; else every held value forgotten when ``reset``, the message's finite values merged
    (:func:`merge_into`), every joint's vector into ``vec`` (:func:`fresh_vector`) and the number of needed joints
    without a fresh value returned."""
    for i in range(needed_src.shape[0]):
        if not np.isfinite(pos[needed_src[i]]):
            return -1
    if reset:
        values[:] = np.nan
        stamps[:] = never
    m = 0
    d = np.empty(src.shape[0], dtype=np.int64)
    c = np.empty(src.shape[0])
    for i in range(src.shape[0]):
        if np.isfinite(pos[src[i]]):  # a joint outside the needed ones without a value: not taken
            d[m] = dst[i]
            c[m] = pos[src[i]]
            m += 1
    merge_into(values, stamps, d[:m], c[:m], stamp)
    fresh_vector(values, stamps, stamp, max_age, never, vec)
    missing = 0
    for i in range(needed_idx.shape[0]):
        if np.isnan(vec[needed_idx[i]]):
            missing += 1
    return missing


@njit(cache=True)
def _merge_rows(stamps: np.ndarray, P: np.ndarray, max_age: float, Q: np.ndarray) -> int:
    """:meth:`JointHistory.merge_rows`: row ``k`` of ``P`` (NaN = not carried) merged, its vector into ``Q[k]``;
    returns the number of values held from earlier rows."""
    n = P.shape[1]
    values = np.full(n, np.nan)
    last = np.full(n, -np.inf)
    held = 0
    dst = np.empty(n, dtype=np.int64)
    carried = np.empty(n)
    for k in range(P.shape[0]):
        m = 0
        for j in range(n):
            if np.isfinite(P[k, j]):
                dst[m] = j
                carried[m] = P[k, j]
                m += 1
        merge_into(values, last, dst[:m], carried[:m], stamps[k])
        fresh_vector(values, last, stamps[k], max_age, -np.inf, Q[k])
        held += int(np.sum(np.isfinite(Q[k]))) - m
    return held


# ----------------------------------------------------------------------------
# History by stamp
# ----------------------------------------------------------------------------


class StampedHistory:
    """Values by stamp [ns], the last ``keep_ns``, in stamp order (a new timeline clears it).

    :meth:`at`: the latest value at or before a stamp; when every kept value is newer, the oldest if it is at most
    ``hold_ns`` newer (0: never); else None.
    """

    def __init__(self, keep_ns: int, hold_ns: int = 0) -> None:
        self.keep_ns = int(keep_ns)
        self.hold_ns = int(hold_ns)
        self.stamps: list[int] = []
        self.values: list[Any] = []

    def clear(self) -> None:
        self.stamps.clear()
        self.values.clear()

    def add(self, stamp_ns: int, value: Any) -> None:
        """Keep ``value`` at ``stamp_ns``; a stamp older than the newest clears the history first (the caller's
        :class:`StampResetPolicy` decided it is a new timeline)."""
        if self.stamps and stamp_ns < self.stamps[-1]:
            self.clear()
        self.stamps.append(stamp_ns)
        self.values.append(value)
        cut = bisect.bisect_left(self.stamps, stamp_ns - self.keep_ns)
        if cut:
            del self.stamps[:cut], self.values[:cut]

    @property
    def newest(self) -> int | None:
        return self.stamps[-1] if self.stamps else None

    def at(self, stamp_ns: int) -> Any:
        """Class docstring."""
        i = bisect.bisect_right(self.stamps, stamp_ns) - 1
        if i >= 0:
            return self.values[i]
        if self.stamps and self.hold_ns > 0 and self.stamps[0] - stamp_ns <= self.hold_ns:
            return self.values[0]
        return None


# ----------------------------------------------------------------------------
# The joint history
# ----------------------------------------------------------------------------


class JointUpdate(NamedTuple):
    """What :meth:`JointHistory.update` gives.

    Attributes
    ----------
    values : ndarray, shape (len(needed),), or None
        The needed joints' values at the message (a copy), None when not all are known and fresh.
    why : str
        Why ``values`` is None ("" otherwise).
    kind : str
        ``""``, ``"ignored"`` (the message carries no needed joint) or ``"incomplete"``.
    new_timeline : str
        The policy's note when this message started a new timeline ("" otherwise).
    """

    values: np.ndarray | None
    why: str
    kind: str
    new_timeline: str


class _Layout(NamedTuple):
    """A name layout (one publisher's names): which of them go to which joint, and the problem it has."""

    src: np.ndarray  # index into the message's names of each joint it carries
    dst: np.ndarray  # index into ``joints`` of those
    needed_src: np.ndarray  # index into the message's names of each needed joint it carries
    problem: str  # why every message of this layout is refused ("" = none)
    strange: str  # its names that are not joints of the URDF, as the messages say them ("" = none)


def _normal(name: str) -> str:
    """A name as a reader sees it (``joint_２`` and ``Joint_2`` both look like ``joint_2``)."""
    return unicodedata.normalize("NFKC", name).casefold()


class JointHistory:
    """Latest value per joint and joint vectors by stamp (module docstring).

    Parameters
    ----------
    joints : joint names, the order of :meth:`vector` and :meth:`at`
    needed : the joints a message's vector must have (:attr:`JointUpdate.values`, in this order); default ``joints``
    known : every joint name of the URDF (a name outside it in a message that lacks a needed joint is refused);
        default: no such check
    max_age_ns : a held value older than this [ns] is not used (0: no limit)
    keep_ns : joint vectors kept by stamp for :meth:`at` (0: none)
    policy : the stamp rule (default :class:`StampResetPolicy`)
    """

    def __init__(self, joints: Sequence[str], *, needed: Sequence[str] | None = None,
                 known: Collection[str] | None = None, max_age_ns: int = 0, keep_ns: int = 0,
                 policy: StampResetPolicy | None = None) -> None:
        self.joints = list(joints)
        self.needed = list(self.joints if needed is None else needed)
        self.index = {n: i for i, n in enumerate(self.joints)}
        missing = [n for n in self.needed if n not in self.index]
        if missing:
            raise JointValueError(f"JointHistory: needed joint(s) {missing} are not among the joints")
        self.known = None if known is None else frozenset(known)
        self.max_age_ns = int(max_age_ns)
        self.policy = policy if policy is not None else StampResetPolicy()
        self.needed_idx = np.array([self.index[n] for n in self.needed], dtype=np.int64)
        self.values = np.full(len(self.joints), np.nan)
        self.stamps = np.full(len(self.joints), NEVER_NS, dtype=np.int64)
        #: ``[stamp of the last merged message ns, has one]``, shared with the compiled fast path
        self.clock = np.zeros(2, dtype=np.int64)
        self.history = StampedHistory(keep_ns, self.max_age_ns)
        self._layouts: dict[tuple[str, ...], _Layout] = {}
        self._names: tuple[str, ...] | None = None
        self._layout: _Layout | None = None
        self._scratch = np.empty(len(self.joints))

    @property
    def last_ns(self) -> int | None:
        """Stamp of the last merged message [ns] (None before the first)."""
        return int(self.clock[0]) if self.clock[1] else None

    def reset(self) -> None:
        """Forget every value and the history (a new timeline)."""
        self.values[:] = np.nan
        self.stamps[:] = NEVER_NS
        self.clock[:] = 0
        self.history.clear()

    def layout(self, names: tuple[str, ...]) -> _Layout:
        """The index maps and the problem of a name layout (cached: a publisher sends the same names)."""
        lay = self._layouts.get(names)
        if lay is None:
            lay = self._layouts[names] = self._make_layout(names)
            if len(self._layouts) > 64:
                self._layouts.pop(next(iter(self._layouts)))
        return lay

    def _make_layout(self, names: tuple[str, ...]) -> _Layout:
        where = [(i, self.index[n]) for i, n in enumerate(names) if n in self.index]
        src = np.array([w[0] for w in where], dtype=np.int64)
        dst = np.array([w[1] for w in where], dtype=np.int64)
        carried = {n: i for i, n in enumerate(names)}
        needed_src = np.array([carried[n] for n in self.needed if n in carried], dtype=np.int64)
        lacking = [n for n in self.needed if n not in carried]
        look = {_normal(n): n for n in lacking}
        strange = ", ".join(f"{n!r} (looks like {look[_normal(n)]!r})" if _normal(n) in look else repr(n)
                            for n in names if self.known is not None and n not in self.known)
        problem = ""
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            problem = f"lists joint(s) {', '.join(repr(n) for n in twice)} more than once: message refused"
        elif lacking and needed_src.size and strange:
            problem = (f"carries {strange}, not a joint of the URDF, and lacks needed joint(s) "
                       f"{', '.join(repr(n) for n in lacking)}: a misspelt name? message refused (the held "
                       "values are not used)")
        return _Layout(src, dst, needed_src, problem, strange)

    def update(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int,
               now_ns: int | None = None) -> JointUpdate:
        """Take one message (module docstring).

        Raises
        ------
        StampRefused
            Its stamp jumped back by at most the policy's threshold, or is too far ahead of ``now_ns``.
        JointValueError
            A joint listed twice, a NaN/infinite needed joint, a misspelt needed joint (each named).
        ValueError
            ``names`` and ``positions`` differ in length.
        """
        if len(names) != len(positions):
            raise ValueError(f"{len(names)} names but {len(positions)} positions")
        names = tuple(names)  # no copy for a tuple (the CDR parser's cached names)
        lay = self._layout if names == self._names and self._layout is not None else self.layout(names)
        self._names, self._layout = names, lay
        if lay.problem:
            raise JointValueError(lay.problem)
        check = self.policy.check(stamp_ns, self.last_ns, now_ns)
        if check.verdict in (BACKWARD, FUTURE):
            raise StampRefused(check.why, check.verdict)
        if lay.src.size == 0:
            extra = f" (names not in the URDF: {lay.strange})" if lay.strange else ""
            return JointUpdate(None, "carries none of the chain's joints" + extra, "ignored", "")
        pos = np.asarray(positions, dtype=np.float64)
        new_timeline = check.verdict == NEW_TIMELINE
        vec = self._scratch
        missing = merge_message(self.values, self.stamps, pos, lay.src, lay.dst, lay.needed_src, self.needed_idx,
                               stamp_ns, self.max_age_ns, NEVER_NS, new_timeline, vec)
        if missing < 0:
            bad = [names[i] for i in lay.needed_src if not np.isfinite(pos[i])]
            raise JointValueError(f"NaN or infinite value for joint(s) {', '.join(repr(b) for b in bad)}")
        if new_timeline:
            self.history.clear()  # (the values and stamps: forgotten by merge_message)
        self.clock[0], self.clock[1] = stamp_ns, 1
        if self.history.keep_ns > 0:
            self.history.add(stamp_ns, vec.copy())
        if missing == 0:
            return JointUpdate(vec[self.needed_idx], "", "", check.why)
        return JointUpdate(None, self._why_incomplete(stamp_ns), "incomplete", check.why)

    def _why_incomplete(self, stamp_ns: int) -> str:
        st = self.stamps[self.needed_idx]
        never = [n for n, s in zip(self.needed, st) if s == NEVER_NS]
        stale = [n for n, s in zip(self.needed, st) if s != NEVER_NS and stamp_ns - s > self.max_age_ns > 0]
        parts = ([f"not seen yet: {', '.join(never)}"] if never else []) + (
            [f"older than {self.max_age_ns * 1e-9:g} s: {', '.join(stale)}"] if stale else [])
        return "needed joint(s) " + "; ".join(parts)

    def vector(self, stamp_ns: int) -> np.ndarray:
        """Every joint's value at ``stamp_ns`` (NaN where never seen or older than ``max_age``)."""
        out = np.empty(len(self.joints))
        fresh_vector(self.values, self.stamps, stamp_ns, self.max_age_ns, NEVER_NS, out)
        return out

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """The joint vector (every joint, NaN = unknown or too old) kept at or before ``stamp_ns`` (class
        docstring: a bounded hold when all kept ones are newer); None if there is none."""
        return self.history.at(stamp_ns)

    def merge_rows(self, stamps_s: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, int]:
        """A recorded stream at once (``ppoe evaluate``): row ``k`` of ``positions`` (N, len(joints)), NaN where
        message ``k`` does not carry a joint, merged as :meth:`update` merges it, in the given (log) order.

        Returns ``(Q, held)``: ``Q`` (N, len(joints)) each message's joint vector (NaN where unknown or older than
        ``max_age``), ``held`` the number of values taken from earlier messages.  The stamp policy is not applied
        (a bag's order is its log's; the caller sorts by stamp) and the history is not touched.
        """
        P = np.ascontiguousarray(positions, dtype=np.float64)
        Q = np.empty_like(P)
        held = _merge_rows(np.ascontiguousarray(stamps_s, dtype=np.float64), P, self.max_age_ns * 1e-9, Q)
        return Q, int(held)
