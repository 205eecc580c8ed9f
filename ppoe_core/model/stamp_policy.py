"""THE stamp rule of the nodes and the fusion pipeline: a stamp against the last one taken (and the receiver's clock).

A stamp a little older than the last one is out of order (a node drops it), one much older starts a new timeline
(a bag replayed again, a simulator reset), one too far ahead of the receiver's clock is refused (a clock set wrong, a
corrupt stamp: taken, it would make every valid message after it look out of order).  Users:
:class:`~ppoe_core.model.joint_history.JointHistory` (kinematics node, fusion node, online hook), the contact
node's wrenches and :class:`~ppoe_core.estimation.pipeline.FusionPipeline`'s priors.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

from ppoe_core.errors import MeasurementError

__all__ = ["ACCEPT", "BACKWARD", "NEW_TIMELINE", "FUTURE", "StampCheck", "StampRefused", "StampResetPolicy"]

ACCEPT, BACKWARD, NEW_TIMELINE, FUTURE = "accept", "jumped_back", "new_timeline", "future_stamp"


class StampCheck(NamedTuple):
    """What :meth:`StampResetPolicy.check` decided: ``verdict`` (``accept``, ``jumped_back``, ``new_timeline``,
    ``future_stamp``) and why (empty for ``accept``)."""

    verdict: str
    why: str


class StampRefused(MeasurementError):
    """A message refused for its stamp (``kind`` = ``jumped_back`` or ``future_stamp``)."""

    def __init__(self, why: str, kind: str) -> None:
        super().__init__(why)
        self.kind = kind


@dataclass(frozen=True)
class StampResetPolicy:
    """THE rule for a stamp against the last one taken (every node and the fusion pipeline).

    Attributes
    ----------
    reset_threshold_s : float
        A stamp more than this [s] older than the last one starts a new timeline (a bag replayed again, a simulator
        reset); a stamp older by at most this is out of order (a node drops it).
    future_tolerance_s : float
        A stamp more than this [s] ahead of the receiver's clock is refused (a clock set wrong, a corrupt stamp):
        taken, it would make every valid message after it look out of order.  0 = off.
    """

    reset_threshold_s: float = 1.0
    future_tolerance_s: float = 0.0

    @cached_property
    def reset_ns(self) -> int:
        """:attr:`reset_threshold_s` in integer nanoseconds."""
        return int(round(self.reset_threshold_s * 1e9))

    @cached_property
    def future_ns(self) -> int:
        """:attr:`future_tolerance_s` in integer nanoseconds (0 = off)."""
        return int(round(self.future_tolerance_s * 1e9))

    def check(self, stamp_ns: int, last_ns: int | None, now_ns: int | None = None) -> StampCheck:
        """The verdict for a message stamped ``stamp_ns`` after one stamped ``last_ns`` (None: the first), received
        at ``now_ns`` on the receiver's clock (None: not checked for the future)."""
        future = self.future_ns
        if future > 0 and now_ns is not None and stamp_ns > now_ns + future:
            return StampCheck(FUTURE, f"stamp {stamp_ns * 1e-9:.9f} s is {(stamp_ns - now_ns) * 1e-9:.3f} s ahead of "
                                      f"the clock (> future tolerance {self.future_tolerance_s:g} s): refused")
        if last_ns is None or stamp_ns >= last_ns:
            return StampCheck(ACCEPT, "")
        jump = (last_ns - stamp_ns) * 1e-9
        if last_ns - stamp_ns <= self.reset_ns:
            return StampCheck(BACKWARD, f"stamp {stamp_ns * 1e-9:.9f} s jumped back by {jump:.6f} s: message dropped")
        return StampCheck(NEW_TIMELINE, f"stamp jumped back by {jump:.3f} s (> stamp_reset_threshold): new timeline")

    def new_timeline_s(self, stamp: float, last: float | None) -> bool:
        """:meth:`check`'s ``new_timeline`` for float stamps [s] (the fusion pipeline's priors)."""
        return last is not None and stamp < last - self.reset_threshold_s


