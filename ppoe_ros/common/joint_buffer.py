"""Joint positions by stamp for the fusion node: split joint-state messages merged per joint, looked up at a
prior's stamp (camera on a pan-tilt mast, tag mounts behind joints, the joint-motion limit of a correction)."""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

__all__ = ["JointBuffer"]


class JointBuffer:
    """Joint positions (``model.joint_names`` order, NaN = unknown) by stamp, last ``duration`` s."""

    def __init__(self, duration_ns: int) -> None:
        self.duration_ns = duration_ns
        self.names: list[str] = []
        self.index: dict[str, int] = {}
        self.current: np.ndarray = np.zeros(0)
        self.stamps: list[int] = []
        self.values: list[np.ndarray] = []

    def set_names(self, names: Sequence[str]) -> None:
        self.names = list(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.current = np.full(len(self.names), np.nan)
        self.stamps.clear()
        self.values.clear()

    def add(self, stamp_ns: int, joints: dict[str, float]) -> None:
        cur = self.current.copy()
        for n, v in joints.items():
            i = self.index.get(n)
            if i is not None:
                cur[i] = v if math.isfinite(v) else np.nan
        self.current = cur
        if self.stamps and stamp_ns < self.stamps[-1]:
            self.stamps.clear()  # time went backwards: new timeline
            self.values.clear()
        self.stamps.append(stamp_ns)
        self.values.append(cur)
        cut = bisect.bisect_left(self.stamps, stamp_ns - self.duration_ns)
        if cut:
            del self.stamps[:cut]
            del self.values[:cut]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """The latest joint positions at or before ``stamp_ns``; the oldest kept ones if all are
        newer (the prior overtook its joint state); None if there are none."""
        if not self.stamps:
            return None
        i = bisect.bisect_right(self.stamps, stamp_ns)
        return self.values[max(i - 1, 0)]
