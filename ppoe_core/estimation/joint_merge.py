"""Joint values of a chain from joint-state messages that each carry only some joints.

With ros2_control an arm, a mast and a gripper often publish ``/joint_states`` separately; a message then lacks
joints the measured chain needs.  :class:`JointMerger` keeps the latest value and stamp of every needed joint
and gives the chain's joint vector at a message's stamp when every needed joint has a value at most
``max_age`` old (0: no age limit).  A message whose names list every needed joint takes the fast path (one
cached index map, as before).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core.errors import JointValueError

__all__ = ["JointMerger"]


class JointMerger:
    """Latest value of each of ``needed`` joints (module docstring).

    Parameters
    ----------
    needed : joint names, in the order of the returned vectors
    max_age_ns : a held value older than this [ns] is not used (0: no limit)
    """

    def __init__(self, needed: Sequence[str], max_age_ns: int = 0) -> None:
        self.needed = list(needed)
        self.max_age_ns = int(max_age_ns)
        self._index = {n: i for i, n in enumerate(self.needed)}
        self.values = np.full(len(self.needed), np.nan)
        self.stamps = np.full(len(self.needed), np.iinfo(np.int64).min, dtype=np.int64)
        self._names: tuple[str, ...] | None = None
        self._src = np.zeros(0, dtype=np.intp)
        self._dst = np.zeros(0, dtype=np.intp)

    def index_maps(self) -> tuple[tuple[str, ...] | None, np.ndarray, np.ndarray]:
        """``(names, src, dst)`` of the last :meth:`update`: its names, and which of them (``src``) go to which
        needed joint (``dst``)."""
        return self._names, self._src, self._dst

    def update(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int) -> tuple[np.ndarray | None, str]:
        """Take one message; returns ``(joint vector (len(needed),), "")`` or ``(None, why not)``.

        Raises
        ------
        JointValueError
            A needed joint the message carries is NaN or infinite (named).
        ValueError
            ``names`` and ``positions`` differ in length.
        """
        if len(names) != len(positions):
            raise ValueError(f"{len(names)} names but {len(positions)} positions")
        names = tuple(names)  # no copy for a tuple (the CDR parser's cached names)
        if names != self._names:  # name layout changed: rebuild the index maps
            where = [(i, self._index[n]) for i, n in enumerate(names) if n in self._index]
            self._src = np.array([w[0] for w in where], dtype=np.intp)
            self._dst = np.array([w[1] for w in where], dtype=np.intp)
            self._names = names
        if self._src.size == 0:
            return None, "carries none of the chain's joints"
        values = np.asarray(positions, dtype=float)[self._src]
        if not np.all(np.isfinite(values)):
            bad = [self.needed[d] for d, v in zip(self._dst, values) if not np.isfinite(v)]
            raise JointValueError(f"NaN or infinite value for joint(s) {', '.join(repr(b) for b in bad)}")
        if self._src.size == len(self.needed):  # the whole chain in one message
            self.values[self._dst] = values
            self.stamps[:] = stamp_ns
            return self.values.copy(), ""
        self.values[self._dst] = values
        self.stamps[self._dst] = stamp_ns
        never = self.stamps == np.iinfo(np.int64).min
        stale = ~never & (self.max_age_ns > 0) & (stamp_ns - self.stamps > self.max_age_ns)
        if never.any() or stale.any():
            parts = ([f"not seen yet: {', '.join(np.array(self.needed)[never])}"] if never.any() else []) + (
                [f"older than {self.max_age_ns * 1e-9:g} s: {', '.join(np.array(self.needed)[stale])}"]
                if stale.any() else [])
            return None, "needed joint(s) " + "; ".join(parts)
        return self.values.copy(), ""
