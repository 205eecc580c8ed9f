"""Prior buffer of the fusion pipeline: kinematics priors (pose + covariance in the tool frame) by stamp,
interpolated on SE(3)."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from itertools import repeat

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import PpoeError

Array = np.ndarray

#: jitter [m^2 or rad^2] added to a covariance's diagonal before it is inverted
INV_JITTER = 1e-14


# ----------------------------------------------------------------------------
# Prior buffer
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class PriorSample:
    """One prior: the kinematics' estimate of the tool pose at a stamp.

    Attributes
    ----------
    stamp : float
        Time [s] (the joint-state stamp).
    T_base_tool : ndarray, shape (4, 4)
        Mean pose of the tool in the reference (base) frame.
    cov_tool : ndarray, shape (6, 6)
        Covariance in the tangent space at ``T_base_tool`` (tool frame, ``[rho; theta]``).
    joints : ndarray, shape (n,), optional
        Joint positions [rad or m] at ``stamp`` (used to measure arm motion), or None.
    """

    stamp: float
    T_base_tool: Array
    cov_tool: Array
    joints: Array | None = None


class _Run:
    """Priors appended at once (:meth:`PriorBuffer.append_arrays`), made into :class:`PriorSample` objects only when
    the buffer hands one out (an offline replay reads a few of them): the same stamps and array views as samples
    made at once.  The buffer holds the run itself in the place of each of its priors and finds the prior by its
    stamp (increasing within a run)."""

    __slots__ = ("stamps", "T", "cov", "joints")

    def __init__(self, stamps: list[float], T: Array, cov: Array, joints: Array | None) -> None:
        self.stamps, self.T, self.cov, self.joints = stamps, T, cov, joints

    def sample(self, m: int) -> PriorSample:
        cov = self.cov if self.cov.ndim == 2 else self.cov[m]
        return PriorSample(self.stamps[m], self.T[m], cov, None if self.joints is None else self.joints[m])


class LookupStatus:
    """Outcome codes of :meth:`PriorBuffer.lookup`."""

    OK = "ok"
    EMPTY = "empty"
    TOO_OLD = "too_old"  # older than the oldest prior kept
    TOO_NEW = "too_new"  # newer than the newest prior
    GAP = "gap"  # inside the buffer, but between two priors further apart than max_gap


class PriorBuffer:
    """Time-ordered buffer of priors with SE(3) interpolation at any stamp inside it.

    Parameters
    ----------
    duration : float
        Length [s] of history kept, counted back from the newest stamp.
    max_gap : float
        Two neighbouring priors further apart than this [s] are not interpolated between
        (the arm may have moved without joint states, e.g. between the stops of a static
        dataset); a stamp in such a gap takes the nearer prior if it is within ``max_hold``.
    max_hold : float
        How far [s] a stamp may lie from the nearest prior when interpolation is not possible
        (gap, or slightly newer than the newest prior in :meth:`lookup_hold`).

    Notes
    -----
    Interpolation between the bracketing priors ``(t0, T0, P0)`` and ``(t1, T1, P1)`` at
    ``s = (t - t0) / (t1 - t0)`` is the geodesic ``T0 Exp(s Log(T0^-1 T1))``
    (:func:`ppoe_core.lie.interpolate`); the covariance is blended linearly,
    ``(1 - s) P0 + s P1``, which is positive semi-definite and first-order exact for the short
    gaps between joint states (both live in the tool tangent spaces of nearby poses).
    """

    def __init__(self, duration: float = 1.0, max_gap: float = 0.2, max_hold: float = 0.5) -> None:
        if not (duration > 0.0 and math.isfinite(duration)):
            raise PpoeError(f"PriorBuffer: duration must be a positive number of seconds, got {duration!r}")
        if not (max_gap > 0.0):
            raise PpoeError(f"PriorBuffer: max_gap must be > 0 s, got {max_gap!r}")
        if not (max_hold >= 0.0):
            raise PpoeError(f"PriorBuffer: max_hold must be >= 0 s, got {max_hold!r}")
        self.duration = float(duration)
        self.max_gap = float(max_gap)
        self.max_hold = float(max_hold)
        self._stamps: list[float] = []
        # PriorSample, or the run of a prior not yet made into one (_get makes and keeps it)
        self._samples: list[PriorSample | _Run] = []

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def oldest(self) -> float | None:
        """Stamp [s] of the oldest prior kept, or None if empty."""
        return self._stamps[0] if self._stamps else None

    @property
    def newest(self) -> float | None:
        """Stamp [s] of the newest prior, or None if empty."""
        return self._stamps[-1] if self._stamps else None

    def latest(self) -> PriorSample | None:
        """The newest prior, or None."""
        return self._get(-1) if self._samples else None

    def samples(self) -> list[PriorSample]:
        """Every prior kept, oldest first."""
        return [self._get(i) for i in range(len(self._samples))]

    def _get(self, i: int) -> PriorSample:
        s = self._samples[i]
        if type(s) is _Run:
            s = self._samples[i] = s.sample(bisect.bisect_left(s.stamps, self._stamps[i]))
        return s  # type: ignore[return-value]

    def clear(self) -> None:
        """Forget every prior."""
        self._stamps.clear()
        self._samples.clear()

    def add(self, sample: PriorSample) -> bool:
        """Insert a prior; returns False (and keeps nothing) if it is older than the buffer.

        A stamp equal to a kept one replaces it.  Out-of-order stamps inside the window are
        inserted at their place.  Priors older than ``newest - duration`` are evicted.
        """
        t = float(sample.stamp)
        stamps = self._stamps
        if not stamps or t > stamps[-1]:  # in order (the common case): append, evict only if the oldest is out
            stamps.append(t)
            self._samples.append(sample)
            if stamps[0] < t - self.duration:
                k = bisect.bisect_left(stamps, t - self.duration)
                del stamps[:k]
                del self._samples[:k]
            return True
        if t < stamps[-1] - self.duration:
            return False
        i = bisect.bisect_left(self._stamps, t)
        if i < len(self._stamps) and self._stamps[i] == t:
            self._samples[i] = sample
        else:
            self._stamps.insert(i, t)
            self._samples.insert(i, sample)
        cutoff = self._stamps[-1] - self.duration
        k = bisect.bisect_left(self._stamps, cutoff)
        if k > 0:
            del self._stamps[:k]
            del self._samples[:k]
        return True

    def append_arrays(self, stamps: list[float], T: Array, cov: Array, joints: Array | None) -> None:
        """:meth:`add` of ``PriorSample(stamps[m], T[m], cov[m] (or cov if (6, 6)), joints[m] (or None))`` for each
        ``m`` in turn, for increasing stamps all newer than the buffer (the caller checks): appended, then the priors
        older than the newest minus ``duration`` evicted (what the single adds leave).  The samples are made when
        the buffer hands them out."""
        if not stamps:
            return
        self._stamps.extend(stamps)
        self._samples.extend(repeat(_Run(stamps, T, cov, joints), len(stamps)))
        cutoff = self._stamps[-1] - self.duration
        if self._stamps[0] < cutoff:
            k = bisect.bisect_left(self._stamps, cutoff)
            del self._stamps[:k]
            del self._samples[:k]

    def lookup(self, stamp: float) -> tuple[str, PriorSample | None]:
        """Prior at ``stamp``: interpolated inside the buffer (see class notes).

        Returns
        -------
        (status, sample)
            ``status`` one of :class:`LookupStatus`; ``sample`` is None unless ``OK``.
        """
        t = float(stamp)
        if not self._stamps:
            return LookupStatus.EMPTY, None
        if t < self._stamps[0]:
            return LookupStatus.TOO_OLD, None
        if t > self._stamps[-1]:
            return LookupStatus.TOO_NEW, None
        i = bisect.bisect_left(self._stamps, t)
        if self._stamps[i] == t:
            return LookupStatus.OK, self._get(i)
        a, b = self._get(i - 1), self._get(i)
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        if t1 - t0 > self.max_gap:
            near = a if (t - t0) <= (t1 - t) else b
            if abs(t - near.stamp) <= self.max_hold:
                return LookupStatus.OK, _held(near, t)
            return LookupStatus.GAP, None
        return LookupStatus.OK, _interpolate(a, b, t)

    def lookup_hold(self, stamp: float) -> tuple[str, PriorSample | None]:
        """Like :meth:`lookup`, but a stamp newer than the newest prior by at most
        ``max_hold`` takes the newest prior (zero-order hold: the arm is assumed at rest)."""
        status, sample = self.lookup(stamp)
        if status == LookupStatus.TOO_NEW and float(stamp) - self._stamps[-1] <= self.max_hold:
            return LookupStatus.OK, _held(self._get(-1), float(stamp))
        return status, sample


def _held(sample: PriorSample, t: float) -> PriorSample:
    return PriorSample(t, sample.T_base_tool, sample.cov_tool, sample.joints)


def _interpolate(a: PriorSample, b: PriorSample, t: float) -> PriorSample:
    s = (t - a.stamp) / (b.stamp - a.stamp)
    T = lie.interpolate(a.T_base_tool, b.T_base_tool, s)
    cov = (1.0 - s) * a.cov_tool + s * b.cov_tool
    joints = None
    if a.joints is not None and b.joints is not None and a.joints.shape == b.joints.shape:
        joints = (1.0 - s) * a.joints + s * b.joints
    return PriorSample(t, T, cov, joints)
