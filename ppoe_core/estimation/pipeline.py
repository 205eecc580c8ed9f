"""ROS-free core of the fusion node: prior buffer, measurement updates, carried correction.

The fusion node (``ppoe_ros/fusion_node.py``) and the offline replay (``ppoe evaluate``)
run the SAME code: this module.  It knows nothing about ROS messages; stamps are float
seconds, poses ``(4, 4)`` arrays, covariances ``(6, 6)`` arrays in the tangent space of the
tool frame (right perturbation ``T = Tbar @ Exp(xi)``, ``xi = [rho; theta]``).

Data flow (see ``docs/fusion_node.md`` for the design discussion)::

    add_prior(t, T_base_tool, cov_tool, joints)      # kinematics output, e.g. /ppoe/pose
        -> PriorBuffer (last `buffer_duration` s)   # SE(3) interpolation at any stamp inside
        -> pending measurements whose stamp is now covered are processed
        -> returns the fused estimate at t: prior (+) carried correction

    add_measurement(Measurement(t, source, payload))
        same source within `min_interval` -> skipped ("throttled"), counted
        t < oldest prior            -> dropped ("stale"), counted
        t > newest prior            -> pending until a prior covers it (or `flush`)
        otherwise                   -> prior at t (interpolated), the other sources' carried
                                       corrections applied, iterated LG-EKF update by the
                                       injected `updater` (gating inside), new carried
                                       correction of this source (replacing its old one)

A carried correction is an *equivalent measurement of the tool-frame error* of the prior:
information matrix ``I_c = P_post^-1 - P_prior^-1`` and information vector
``y_c = P_post^-1 delta`` with ``delta = Log(T_prior^-1 T_post)``.  For a later prior
``(T, P)`` and a weight ``w`` in [0, 1] (1 = fresh, decays with time and arm motion,
:class:`CorrectionPolicy`) the fused estimate is the Kalman update of ``(T, P)`` with the
equivalent measurements of all sources, noise scaled by ``1 / w``.  At the measurement's own
stamp (``w = 1``) it reproduces the posterior exactly; as ``w -> 0`` it falls back to the
prior; at ``w = 0`` the correction is dropped.

:data:`FUSION_SETTINGS` holds the settings with their defaults (the fusion node's parameters of
the same names) and :func:`make_pipeline` builds the pipeline from them, so the node and an
offline replay configured alike behave alike.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, PpoeError

__all__ = [
    "PriorSample",
    "PriorBuffer",
    "LookupStatus",
    "Measurement",
    "ToolUpdate",
    "MeasurementUpdater",
    "CorrectionPolicy",
    "CarriedCorrection",
    "FusedEstimate",
    "MeasurementOutcome",
    "FusionPipeline",
    "TagMeasurement",
    "ContactMeasurement",
    "ModelUpdater",
    "COUNT_KEYS",
    "posterior_cost",
    "apply_carried_corrections",
    "FUSION_SETTINGS",
    "make_pipeline",
    "make_updater",
    "source_key",
]

Array = np.ndarray

#: jitter [m^2 or rad^2] added to a covariance's diagonal before it is inverted
_INV_JITTER = 1e-14
#: 6x6 identity (read-only; built once instead of per prior)
_EYE6 = np.eye(6)
_EYE6.setflags(write=False)


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
        self._samples: list[PriorSample] = []

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
        return self._samples[-1] if self._samples else None

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
        if self._stamps and t < self._stamps[-1] - self.duration:
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
            return LookupStatus.OK, self._samples[i]
        a, b = self._samples[i - 1], self._samples[i]
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
            return LookupStatus.OK, _held(self._samples[-1], float(stamp))
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


# ----------------------------------------------------------------------------
# Measurements and the update hook
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Measurement:
    """A measurement waiting for its prior.

    Attributes
    ----------
    stamp : float
        Measurement time [s].
    source : str
        Where it came from, :func:`source_key` of topic and ``header.frame_id``: throttling
        (``min_interval``) and correction replacement are per source; also used in counts and
        error messages.
    payload : Any
        Whatever the injected updater needs (e.g. a measurement model and ``z``).
    """

    stamp: float
    source: str
    payload: Any


@dataclass(frozen=True)
class ToolUpdate:
    """What an updater returns.

    Attributes
    ----------
    T_base_tool : ndarray, shape (4, 4)
        Posterior mean (equal to the input prior if rejected).
    cov_tool : ndarray, shape (6, 6)
        Posterior covariance in the tangent space at the posterior mean (tool frame).
    accepted : bool
        False if the gate rejected the measurement.
    nis : float
        Normalised innovation squared at the prior (for diagnostics), NaN if unknown.
    """

    T_base_tool: Array
    cov_tool: Array
    accepted: bool
    nis: float = float("nan")


class MeasurementUpdater(Protocol):
    """``updater(T_base_tool, cov_tool, measurement, prior) -> ToolUpdate``.

    ``(T_base_tool, cov_tool)`` is the estimate to update (the prior at the measurement's
    stamp with the carried correction applied); ``cov_tool`` lives in the tangent space at
    ``T_base_tool``.  ``prior`` is the raw prior sample at that stamp (its ``joints`` place
    sensors on moving links).  Raises :class:`~ppoe_core.errors.MeasurementError` (or
    :class:`~ppoe_core.errors.CovarianceError`) for an unusable measurement.
    """

    def __call__(
        self, T_base_tool: Array, cov_tool: Array, measurement: Measurement, prior: PriorSample
    ) -> ToolUpdate:
        ...


# ----------------------------------------------------------------------------
# Carried correction
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class CorrectionPolicy:
    """When a carried correction fades and when it is dropped.

    Each enabled limit gives a ratio ``r`` = (change since the correction's measurement) /
    limit: elapsed time ``|dt| / timeout``, joint motion ``max_i |q_i - q_i,0| /
    joint_motion``, tool translation ``|dp| / tool_translation`` and rotation angle
    ``|dtheta| / tool_rotation`` (the tool motion is read off the priors, so it also works
    without joint positions).  With ``r = max`` over the enabled ratios the weight is
    ``w = 1 - r`` (``decay="linear"``) or ``w = 1`` while ``r < 1`` (``decay="step"``);
    the correction is dropped once ``r >= 1``.  A limit ``<= 0`` disables that ratio.

    Attributes
    ----------
    timeout : float
        [s], default 10.0.
    joint_motion : float
        [rad or m], max-abs over joints, default 0.05.
    tool_translation : float
        [m], default 0.05.
    tool_rotation : float
        [rad], default 0.1.
    decay : str
        ``"linear"`` (default) or ``"step"``.
    """

    timeout: float = 10.0
    joint_motion: float = 0.05
    tool_translation: float = 0.05
    tool_rotation: float = 0.1
    decay: str = "linear"

    def __post_init__(self) -> None:
        if self.decay not in ("linear", "step"):
            raise PpoeError(f"CorrectionPolicy.decay must be 'linear' or 'step', got {self.decay!r}")
        for name in ("timeout", "joint_motion", "tool_translation", "tool_rotation"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise PpoeError(f"CorrectionPolicy.{name} must be finite, got {v!r}")
        if max(self.timeout, self.joint_motion, self.tool_translation, self.tool_rotation) <= 0.0:
            raise PpoeError("CorrectionPolicy: every limit is disabled; a correction would never be dropped")

    def ratio(self, anchor: PriorSample, prior: PriorSample) -> float:
        """Largest change ratio between the correction's anchor prior and ``prior``."""
        r = 0.0
        if self.timeout > 0.0:
            r = max(r, abs(prior.stamp - anchor.stamp) / self.timeout)
        if self.joint_motion > 0.0 and anchor.joints is not None and prior.joints is not None:
            if anchor.joints.shape == prior.joints.shape:
                dq = np.abs(prior.joints - anchor.joints)
                dq = dq[np.isfinite(dq)]  # NaN = joint not (yet) known
                if dq.size:
                    r = max(r, float(dq.max()) / self.joint_motion)
        if self.tool_translation > 0.0 or self.tool_rotation > 0.0:
            T_rel = lie.inverse(anchor.T_base_tool) @ prior.T_base_tool
            if self.tool_translation > 0.0:
                r = max(r, float(np.linalg.norm(T_rel[:3, 3])) / self.tool_translation)
            if self.tool_rotation > 0.0:
                c = min(max((float(np.trace(T_rel[:3, :3])) - 1.0) / 2.0, -1.0), 1.0)  # np.clip, scalar
                r = max(r, float(np.arccos(c)) / self.tool_rotation)
        return r

    def weight(self, anchor: PriorSample, prior: PriorSample) -> float:
        """Weight in [0, 1] of the correction made at ``anchor`` when applied to ``prior``."""
        r = self.ratio(anchor, prior)
        if r >= 1.0:
            return 0.0
        return 1.0 - r if self.decay == "linear" else 1.0


@dataclass(frozen=True)
class CarriedCorrection:
    """The information the measurements added to the prior, as an equivalent measurement.

    Attributes
    ----------
    anchor : PriorSample
        The (interpolated) prior at the stamp of the last accepted measurement.
    H : ndarray, shape (r, 6)
        Observed directions in the tool tangent space (orthonormal rows).
    R : ndarray, shape (r,)
        Variances of the equivalent measurement along those directions.
    z : ndarray, shape (r,)
        Equivalent measurement of the tool-frame error of the prior.
    """

    anchor: PriorSample
    H: Array
    R: Array
    z: Array

    @staticmethod
    def from_update(
        anchor: PriorSample,
        T_post: Array,
        cov_post: Array,
        T_pre: Array | None = None,
        cov_pre: Array | None = None,
    ) -> CarriedCorrection | None:
        """Build the correction that turns ``(T_pre, cov_pre)`` into ``(T_post, cov_post)``.

        ``(T_pre, cov_pre)`` is the estimate the update started from (default: the raw
        prior ``anchor``; with corrections of other sources applied otherwise).  The
        equivalent measurement is finally re-expressed as a measurement of the error of the
        raw prior ``anchor.T_base_tool``: ``z += H Log(T_anchor^-1 T_pre)`` (first order).

        ``delta = Log(T_prior^-1 T_post)`` (tool frame); ``I_c = P_post^-1 - P_prior^-1``
        (clipped to PSD), ``y = P_post^-1 delta``; ``I_c = V diag(lam) V^T`` with the
        significant eigenvalues gives ``H = V^T``, ``R = 1 / lam``, ``z = R * (V^T y)``.
        Inverses are taken in the range ``U`` of ``P_prior`` (eigenvectors with non-negligible
        eigenvalues): a direction the prior is certain about carries no correction.
        ``cov_post`` is read as a covariance in the tool tangent space at ``T_post``; the
        change of tangent space between ``T_prior`` and ``T_post`` (second order in
        ``delta``) is neglected.  Returns None if the update added no information.
        """
        # work in the range of the prior covariance: directions the prior is certain about
        # carry no correction (and P_prior^-1 is not needed there)
        T_pre = anchor.T_base_tool if T_pre is None else np.asarray(T_pre, dtype=np.float64)
        cov_pre = anchor.cov_tool if cov_pre is None else cov_pre
        s0, U = np.linalg.eigh(_sym(cov_pre))
        keep0 = s0 > 1e-12 * max(float(s0.max()), 1e-300)
        if not np.any(keep0):
            return None
        U = U[:, keep0]
        info0 = np.diag(1.0 / s0[keep0])
        P1 = U.T @ _sym(cov_post) @ U
        P1 = _sym(P1) + _INV_JITTER * np.eye(P1.shape[0])
        info1 = np.linalg.inv(P1)
        delta = lie.log(lie.inverse(T_pre) @ T_post)
        y = info1 @ (U.T @ delta)
        lam, V = np.linalg.eigh(_sym(info1 - info0))
        keep = lam > 1e-9 * max(float(np.max(np.abs(lam))), 1e-300)
        if not np.any(keep):
            return None
        lam, V = lam[keep], V[:, keep]
        H = V.T @ U.T
        R = 1.0 / lam
        z = R * (V.T @ y) + H @ lie.log(lie.inverse(anchor.T_base_tool) @ T_pre)
        return CarriedCorrection(anchor, H, R, z)

    def apply(self, prior: PriorSample, weight: float) -> tuple[Array, Array]:
        """Fused ``(T_base_tool, cov_tool)`` for ``prior`` with this correction at ``weight``.

        Kalman update of ``(prior.T_base_tool, prior.cov_tool)`` with the equivalent
        measurement ``z = H e + n``, ``n ~ N(0, diag(R) / weight)``; covariance in Joseph form
        (tool tangent space at the returned pose).
        """
        return apply_carried_corrections(prior, [(self, weight)])


def apply_carried_corrections(
    prior: PriorSample, corrections: list[tuple[CarriedCorrection, float]]
) -> tuple[Array, Array]:
    """Apply several weighted corrections (independent equivalent measurements) at once.

    One linear Kalman update of the raw prior ``(T, P)`` with the stacked ``H``, ``z`` and
    ``diag(R / w)``; returns ``(T Exp(K z), (I-KH) P (I-KH)^T + K R K^T)`` (tool frame).
    """
    P = _sym(prior.cov_tool)
    active = [(c, w) for c, w in corrections if w > 0.0]
    if not active:
        return prior.T_base_tool, P
    if len(active) == 1:  # the common case: no stacking copies (same values)
        c, w = active[0]
        H, Rw, z = c.H, np.diag(c.R / w), c.z
    else:
        H = np.concatenate([c.H for c, _ in active])
        Rw = np.diag(np.concatenate([c.R / w for c, w in active]))
        z = np.concatenate([c.z for c, _ in active])
    S = H @ P @ H.T + Rw
    K = np.linalg.solve(S, H @ P).T  # P H^T S^-1
    m = K @ z
    IKH = _EYE6 - K @ H
    cov = _sym(IKH @ P @ IKH.T + K @ Rw @ K.T)
    return prior.T_base_tool @ lie.exp(m), cov


def _sym(A: Array) -> Array:
    A = np.asarray(A, dtype=np.float64)
    return 0.5 * (A + A.T)


# ----------------------------------------------------------------------------
# The pipeline
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class FusedEstimate:
    """Fused tool pose at a stamp.

    Attributes
    ----------
    stamp : float
        [s]
    T_base_tool : ndarray, shape (4, 4)
    cov_tool : ndarray, shape (6, 6)
        In the tangent space at ``T_base_tool`` (tool frame).
    weight : float
        Weight of the carried correction (0 = none applied, pure prior).
    prior : PriorSample
        The prior it was made from.
    """

    stamp: float
    T_base_tool: Array
    cov_tool: Array
    weight: float
    prior: PriorSample


@dataclass(frozen=True)
class MeasurementOutcome:
    """What happened to one measurement.

    ``status`` is one of ``"accepted"``, ``"rejected"`` (gate), ``"stale"`` (older than the
    buffer), ``"no_prior"`` (no prior within reach), ``"bad"`` (updater raised a
    PpoeError, e.g. MeasurementError; ``error`` holds the message) or ``"pending"``
    (waiting for a newer prior) or ``"throttled"`` (``min_interval``).  ``estimate`` is the
    posterior at the measurement stamp
    for accepted ones.
    """

    measurement: Measurement
    status: str
    estimate: FusedEstimate | None = None
    nis: float = float("nan")
    error: str = ""


COUNT_KEYS = (
    "priors",
    "priors_late",
    "resets",
    "measurements",
    "accepted",
    "rejected",
    "dropped_stale",
    "dropped_no_prior",
    "bad",
    "corrections_dropped",
    "throttled",
)


class FusionPipeline:
    """Prior buffer + measurement updates + carried correction; no ROS.

    Parameters
    ----------
    updater : MeasurementUpdater
        ``updater(T_base_tool, cov_tool, measurement, prior) -> ToolUpdate``: the iterated
        LG-EKF update with gating (``ppoe_core.estimation.fusion``) for the measurement's model, e.g.
        :class:`ModelUpdater`.
    buffer_duration : float
        History of priors kept [s] (default 1.0); older measurements are dropped.
    max_gap, max_hold : float
        See :class:`PriorBuffer` [s].
    policy : CorrectionPolicy
        When the carried correction fades and is dropped.
    max_pending : int
        Measurements newer than the newest prior waiting for it (oldest dropped beyond).
    reset_jump : float
        A prior stamp more than this [s] behind the newest one is a time jump (a bag
        restarted): buffer, pending measurements and correction are cleared.
    min_interval : float
        A measurement of a source less than this [s] (stamp difference) after the last
        processed one of that source is skipped and counted as ``throttled`` (0 = process
        all).  With per-source replacement (below) a 100 Hz contact stream adds nothing new
        every 10 ms; this bounds the CPU the updates take.

    Notes
    -----
    ``counts`` holds the counters listed in ``COUNT_KEYS``.  The order of calls is the order
    of arrival; a measurement older than a correction's anchor is still processed (the
    carried corrections are applied to its prior with weights from ``|dt|`` and the motion).

    Corrections are kept **per source** (``Measurement.source``: topic and frame, see
    :func:`source_key`; e.g. each camera of a topic shared by two cameras): a new accepted
    measurement of a source replaces that source's previous correction (the update starts
    from the prior with only the *other* sources' corrections applied), while different
    sources combine.  So a 100 Hz contact stream, or a camera re-observing the same tags with
    the same camera-chain error, does not count its (systematic) error again and again.
    """

    def __init__(
        self,
        updater: MeasurementUpdater | Callable[[Array, Array, Measurement, PriorSample], ToolUpdate],
        buffer_duration: float = 1.0,
        max_gap: float = 0.2,
        max_hold: float = 0.5,
        policy: CorrectionPolicy | None = None,
        max_pending: int = 200,
        reset_jump: float = 2.0,
        min_interval: float = 0.0,
    ) -> None:
        self.updater = updater
        self.buffer = PriorBuffer(buffer_duration, max_gap, max_hold)
        self.policy = policy if policy is not None else CorrectionPolicy()
        if max_pending < 0:
            raise PpoeError(f"FusionPipeline: max_pending must be >= 0, got {max_pending}")
        self.max_pending = int(max_pending)
        self.reset_jump = float(reset_jump)
        if not min_interval >= 0.0:
            raise PpoeError(f"FusionPipeline: min_interval must be >= 0 s, got {min_interval}")
        self.min_interval = float(min_interval)
        self._last_stamp: dict[str, float] = {}
        self.corrections: dict[str, CarriedCorrection] = {}
        self.pending: list[Measurement] = []
        self.counts: dict[str, int] = {k: 0 for k in COUNT_KEYS}
        self.last_nis: float = float("nan")

    # -- priors ---------------------------------------------------------------

    def add_prior(
        self,
        stamp: float,
        T_base_tool: Array,
        cov_tool: Array,
        joints: Array | None = None,
        validated: bool = False,
    ) -> tuple[FusedEstimate | None, list[MeasurementOutcome]]:
        """Add a kinematics prior; process pending measurements it covers.

        Parameters
        ----------
        stamp : float
            [s]
        T_base_tool : ndarray, shape (4, 4)
        cov_tool : ndarray, shape (6, 6)
            Covariance in the tangent space at ``T_base_tool`` (tool frame).
        joints : ndarray, shape (n,), optional
            Joint positions at ``stamp`` for the arm-motion limit.
        validated : bool
            The caller has already checked ``cov_tool`` with :func:`ppoe_core.lie.check_covariance`
            (e.g. a whole batch of forward-kinematics covariances at once, as ``ppoe evaluate``
            does): only its shape is checked here.  Default False: checked here (a message's
            covariance).

        Returns
        -------
        (estimate, outcomes)
            The fused estimate at ``stamp`` (None if the prior was too late to keep) and the
            outcomes of the pending measurements processed now.
        """
        T = np.asarray(T_base_tool, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise MeasurementError(f"prior at stamp {stamp}: T_base_tool must be a finite 4x4, got shape {T.shape}")
        if validated:
            cov = np.asarray(cov_tool, dtype=np.float64)
            if cov.shape != (6, 6):
                raise MeasurementError(f"prior at stamp {stamp}: cov_tool must be 6x6, got shape {cov.shape}")
        else:
            cov = lie.check_covariance(cov_tool, name=f"prior at stamp {stamp}", size=6)
        q = None if joints is None else np.asarray(joints, dtype=np.float64).reshape(-1)
        sample = PriorSample(float(stamp), T, cov, q)
        newest = self.buffer.newest
        if newest is not None and sample.stamp < newest - self.reset_jump:
            self.reset()
            self.counts["resets"] += 1
        if not self.buffer.add(sample):
            self.counts["priors_late"] += 1
            return None, []
        self.counts["priors"] += 1
        outcomes: list[MeasurementOutcome] = []
        if self.pending:
            ready = [m for m in self.pending if m.stamp <= sample.stamp]
            self.pending = [m for m in self.pending if m.stamp > sample.stamp]
            for m in ready:
                outcomes.append(self._process(m, hold=False))
        return self.fuse(sample), outcomes

    def reset(self) -> None:
        """Forget priors, pending measurements and the carried corrections (counts stay)."""
        self.buffer.clear()
        self.pending.clear()
        self.corrections.clear()
        self._last_stamp.clear()

    # -- measurements ---------------------------------------------------------

    def add_measurement(self, measurement: Measurement) -> MeasurementOutcome:
        """Process a measurement now, or keep it pending if no prior is new enough yet."""
        self.counts["measurements"] += 1
        last = self._last_stamp.get(measurement.source)
        if self.min_interval > 0.0 and last is not None and abs(measurement.stamp - last) < self.min_interval:
            self.counts["throttled"] += 1
            return MeasurementOutcome(measurement, "throttled")
        self._last_stamp[measurement.source] = measurement.stamp
        newest = self.buffer.newest
        if newest is not None and measurement.stamp > newest:
            self.pending.append(measurement)
            self.pending.sort(key=lambda m: m.stamp)
            while len(self.pending) > self.max_pending:
                old = self.pending.pop(0)
                self.counts["dropped_no_prior"] += 1
                if old is measurement:
                    return MeasurementOutcome(measurement, "no_prior")
            return MeasurementOutcome(measurement, "pending")
        return self._process(measurement, hold=False)

    def flush(self, older_than: float | None = None) -> list[MeasurementOutcome]:
        """Process pending measurements with a zero-order hold of the newest prior.

        Parameters
        ----------
        older_than : float, optional
            Only measurements with stamp ``< older_than`` [s] (e.g. node clock minus a
            waiting time); all if None (end of an offline replay).  Those further than
            ``max_hold`` from the newest prior are dropped as ``no_prior``.
        """
        if older_than is None:
            ready, self.pending = self.pending, []
        else:
            ready = [m for m in self.pending if m.stamp < older_than]
            self.pending = [m for m in self.pending if m.stamp >= older_than]
        return [self._process(m, hold=True) for m in ready]

    # -- queries --------------------------------------------------------------

    @property
    def correction(self) -> CarriedCorrection | None:
        """The most recent carried correction of any source (None if there is none)."""
        if not self.corrections:
            return None
        return max(self.corrections.values(), key=lambda c: c.anchor.stamp)

    def fuse(self, prior: PriorSample, exclude: str | None = None) -> FusedEstimate:
        """Apply the carried corrections (all sources but ``exclude``) to ``prior``.

        Expired corrections (weight 0) are dropped and counted, but only when ``prior`` is
        not older than their anchor (a late query must not erase a correction that is still
        valid now).  ``weight`` of the result is the largest weight applied.
        """
        applied: list[tuple[CarriedCorrection, float]] = []
        for source in list(self.corrections):
            corr = self.corrections[source]
            w = self.policy.weight(corr.anchor, prior)
            if w <= 0.0:
                if prior.stamp >= corr.anchor.stamp:
                    del self.corrections[source]
                    self.counts["corrections_dropped"] += 1
                continue
            if source != exclude:
                applied.append((corr, w))
        if not applied:
            return FusedEstimate(prior.stamp, prior.T_base_tool, prior.cov_tool, 0.0, prior)
        T, cov = apply_carried_corrections(prior, applied)
        return FusedEstimate(prior.stamp, T, cov, max(w for _, w in applied), prior)

    def fused_at(self, stamp: float) -> FusedEstimate | None:
        """Fused estimate at any stamp inside the buffer (None if no prior there)."""
        status, prior = self.buffer.lookup(stamp)
        if status != LookupStatus.OK or prior is None:
            return None
        return self.fuse(prior)

    def latest(self) -> FusedEstimate | None:
        """Fused estimate at the newest prior."""
        prior = self.buffer.latest()
        return None if prior is None else self.fuse(prior)

    # -- internals ------------------------------------------------------------

    def _process(self, measurement: Measurement, hold: bool) -> MeasurementOutcome:
        lookup = self.buffer.lookup_hold if hold else self.buffer.lookup
        status, prior = lookup(measurement.stamp)
        if status == LookupStatus.TOO_OLD:
            self.counts["dropped_stale"] += 1
            return MeasurementOutcome(measurement, "stale")
        if status != LookupStatus.OK or prior is None:
            self.counts["dropped_no_prior"] += 1
            return MeasurementOutcome(measurement, "no_prior")
        est = self.fuse(prior, exclude=measurement.source)
        try:
            res = self.updater(est.T_base_tool, est.cov_tool, measurement, prior)
        except PpoeError as exc:  # MeasurementError, CovarianceError, unknown frame/joint
            self.counts["bad"] += 1
            return MeasurementOutcome(measurement, "bad", error=f"{measurement.source}: {exc}")
        self.last_nis = float(res.nis)
        if not res.accepted:
            self.counts["rejected"] += 1
            return MeasurementOutcome(measurement, "rejected", nis=float(res.nis))
        self.counts["accepted"] += 1
        T_post = np.asarray(res.T_base_tool, dtype=np.float64)
        cov_post = _sym(res.cov_tool)
        corr = CarriedCorrection.from_update(prior, T_post, cov_post, est.T_base_tool, est.cov_tool)
        if corr is not None:
            self.corrections[measurement.source] = corr
        else:
            self.corrections.pop(measurement.source, None)
        post = FusedEstimate(prior.stamp, T_post, cov_post, 1.0, prior)
        return MeasurementOutcome(measurement, "accepted", post, nis=float(res.nis))


# ----------------------------------------------------------------------------
# Measurement payloads and the model-based updater (PPOEModel + fusion.py)
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class TagMeasurement:
    """Payload of one ``/tag_bearing/observations`` message (one image).

    Attributes
    ----------
    camera_frame : str
        Camera optical frame (URDF link; ``header.frame_id`` of the image).
    ids : ndarray, shape (n,), int
        Tag id of each point.
    corners : ndarray, shape (n,), int
        0 = tag centre, 1..4 = corners in the order of :mod:`ppoe_core.sensing.tags`.
    xy : ndarray, shape (n, 2)
        Undistorted normalised image coordinates ``(X/Z, Y/Z)``.
    uv : ndarray, shape (n, 2), optional
        Raw (distorted) pixels, used to infer the focal lengths when ``fx``/``fy`` are None.
    fx, fy : float, optional
        Focal lengths [px] (``camera_info`` K); they turn the pixel noise into normalised units.
    """

    camera_frame: str
    ids: Array
    corners: Array
    xy: Array
    uv: Array | None = None
    fx: float | None = None
    fy: float | None = None


@dataclass(frozen=True)
class ContactMeasurement:
    """Payload of one ``/contact/plane`` message: the tool point lies on this plane.

    Attributes
    ----------
    frame : str
        Frame the plane pose is given in (``header.frame_id``).
    T_frame_plane : ndarray, shape (4, 4)
        Plane pose; plane normal = plane z axis.
    cov_plane : ndarray, shape (6, 6)
        ``Sigma_v`` in the tangent space at the plane pose (plane frame, local convention).
    """

    frame: str
    T_frame_plane: Array
    cov_plane: Array


def _focal_from_points(uv: Array, xy: Array, where: str) -> tuple[float, float]:
    """Least-squares fit ``u = fx x + cx``, ``v = fy y + cy`` (distortion neglected)."""
    out = []
    for k, axis in enumerate("xy"):
        a = xy[:, k]
        if a.size < 2 or float(np.ptp(a)) < 1e-6:
            raise MeasurementError(
                f"{where}: no camera_info focal length and the points do not spread in {axis} "
                "to infer it"
            )
        A = np.stack([a, np.ones_like(a)], axis=1)
        f = float(np.linalg.lstsq(A, uv[:, k], rcond=None)[0][0])
        if not f > 0.0:
            raise MeasurementError(f"{where}: inferred focal length f{axis} = {f:.4g} is not positive")
        out.append(f)
    return out[0], out[1]


class ModelUpdater:
    """Iterated LG-EKF updates of ``T_base_tool`` for the project's measurement payloads.

    The measurement models of :mod:`ppoe_core.estimation.measurements` are built per measurement from
    the PPOE model: tag mounts (``tags`` section) and the contact tool point (``contact``
    section) in the tool frame via ``model.fk_mean(joints, tool, link)``; the camera pose
    ``T_base_camera`` and its PPOE covariance (camera frame) via ``model.fk(joints, base,
    camera)``, entering the tag model as noise through ``M``; a plane given in another
    frame is moved into ``base`` with ``model.fk_mean``.  ``joints`` are the prior's joint
    positions at the measurement's stamp (``model.joint_names`` order, NaN = unknown); a
    chain that needs an unknown joint makes the measurement bad (the error names it).

    Parameters
    ----------
    model : PPOEModel
    base_frame, tool_frame : str
        Frames of the state ``T_base_tool`` (the prior's ``header.frame_id`` and target).
    pixel_sigma : float, optional
        1-sigma pixel noise [px]; None = model YAML ``camera.pixel_sigma`` (default 0.5).
    max_iterations : int
        Relinearisations of the iterated update (1 = plain LG-EKF).
    gate_probability : float or None
        Chi-square gate probability (None = no gating).
    gating : {"posterior", "prior"}
        ``"prior"``: the NIS at the prior (``fusion.iterated_update``'s gate, exact for linear
        models).  ``"posterior"`` (default): the cost of the iterated solution,
        ``J = r+^T (M R M^T)^-1 r+ + d^T P^+ d`` with the post-fit residual ``r+`` and the
        correction ``d = Log(X0^-1 X+)`` (``P^+`` pseudo-inverse of the prior covariance),
        against the same chi-square quantile of the measurement dimension.  ``J`` equals the
        prior NIS for a linear model, but does not blow up when the prior is wide compared
        with the sensor (tags seen through 5 deg of plate bending: see docs/fusion_node.md).
    camera_covariance : bool
        Let the PPOE covariance of the camera chain enter the tag model.
    use_centre, use_corners : bool
        Which tag points enter the update (centre, corners 1..4).
    contact_distance_sigma : float
        Extra 1-sigma noise of the contact distance [m].
    """

    def __init__(
        self,
        model: Any,
        base_frame: str,
        tool_frame: str,
        pixel_sigma: float | None = None,
        max_iterations: int = 5,
        gate_probability: float | None = 0.9973,
        gating: str = "posterior",
        camera_covariance: bool = True,
        use_centre: bool = True,
        use_corners: bool = True,
        contact_distance_sigma: float = 0.0,
    ) -> None:
        if not (use_centre or use_corners):
            raise PpoeError("ModelUpdater: use_centre and use_corners are both false: no tag point would be used")
        self.model = model
        self.base_frame = base_frame
        self.tool_frame = tool_frame
        cfg = model.config
        cam_sigma = cfg.camera.pixel_sigma if getattr(cfg, "camera", None) is not None else 0.5
        self.pixel_sigma = float(cam_sigma if pixel_sigma is None else pixel_sigma)
        self.max_iterations = int(max_iterations)
        self.gate_probability = gate_probability
        if gating not in ("posterior", "prior"):
            raise PpoeError(f"ModelUpdater: gating must be 'posterior' or 'prior', got {gating!r}")
        self.gating = gating
        self.camera_covariance = bool(camera_covariance)
        self.use_centre = bool(use_centre)
        self.use_corners = bool(use_corners)
        self.contact_distance_sigma = float(contact_distance_sigma)
        self.tags = cfg.tags.by_id() if getattr(cfg, "tags", None) is not None else {}
        self.contact = getattr(cfg, "contact", None)
        #: tag points ignored because their id is not in the model YAML
        self.unknown_tag_points = 0
        self.last_result: Any = None

    def _joints(self, prior: PriorSample | None) -> dict[str, float]:
        if prior is None or prior.joints is None:
            return {}
        names = self.model.joint_names
        return {n: float(v) for n, v in zip(names, prior.joints) if math.isfinite(float(v))}

    def build(self, measurement: Measurement, prior: PriorSample | None) -> tuple[Any, Array]:
        """Measurement model and ``z`` for ``measurement`` (see class docstring)."""
        from ppoe_core.estimation import measurements as mm

        joints = self._joints(prior)
        p = measurement.payload
        where = f"{measurement.source} at stamp {measurement.stamp:.6f}"
        if isinstance(p, TagMeasurement):
            ids = np.asarray(p.ids).astype(int).reshape(-1)
            corners = np.asarray(p.corners).astype(int).reshape(-1)
            xy = np.asarray(p.xy, dtype=np.float64).reshape(-1, 2)
            if not (ids.shape[0] == corners.shape[0] == xy.shape[0]):
                raise MeasurementError(f"{where}: ids, corners and xy differ in length")
            if not np.all(np.isfinite(xy)):
                raise MeasurementError(f"{where}: NaN/inf in the normalised coordinates")
            fx, fy = p.fx, p.fy
            if fx is None or fy is None:
                if p.uv is None:
                    raise MeasurementError(f"{where}: no focal length (camera_info) and no pixels")
                fx, fy = _focal_from_points(np.asarray(p.uv, float).reshape(-1, 2), xy, where)
            pts, keep, labels = [], [], []
            T_tool_link: dict[str, Array] = {}
            obs: Any
            for i, (tid, c) in enumerate(zip(ids, corners)):
                item = self.tags.get(int(tid))
                if item is None:
                    self.unknown_tag_points += 1
                    continue
                if not 0 <= c <= 4:
                    raise MeasurementError(f"{where}: tag {tid} has corner index {c}, expected 0..4")
                if (c == 0 and not self.use_centre) or (c > 0 and not self.use_corners):
                    continue
                if item.link not in T_tool_link:
                    T_tool_link[item.link] = self.model.fk_mean(joints, self.tool_frame, item.link)
                pts.append(mm.tag_points(item.size, T_tool_link[item.link] @ item.T_link_tag)[c])
                keep.append(i)
                labels.append(f"tag {tid} corner {c}")
            if not pts:
                raise MeasurementError(
                    f"{where}: no point of a tag configured in the model YAML (ids {sorted(set(ids.tolist()))})"
                )
            if self.camera_covariance:
                T_base_cam, cov_cam = self.model.fk(joints, self.base_frame, p.camera_frame)
                if float(np.max(np.abs(cov_cam))) == 0.0:
                    cov_cam = None
            else:
                T_base_cam, cov_cam = self.model.fk_mean(joints, self.base_frame, p.camera_frame), None
            K = np.array([[fx, 0.0, 0.0], [0.0, fy, 0.0], [0.0, 0.0, 1.0]])
            obs = mm.TagBearingModel(
                np.asarray(pts), K, None, pixel_sigma=self.pixel_sigma, mode="normalized",
                T_ref_camera=T_base_cam, cov_camera=cov_cam, labels=labels, name=where,
            )
            return obs, xy[keep].reshape(-1)
        if isinstance(p, ContactMeasurement):
            if self.contact is None:
                raise MeasurementError(f"{where}: the model YAML has no 'contact' section (tool point)")
            T_base_frame = self.model.fk_mean(joints, self.base_frame, p.frame)
            T_tool_contact = self.model.fk_mean(joints, self.tool_frame, self.contact.tool_link)
            point_tool = T_tool_contact[:3, :3] @ self.contact.tool_xyz + T_tool_contact[:3, 3]
            obs = mm.ContactPlaneModel(
                T_base_frame @ np.asarray(p.T_frame_plane, float), p.cov_plane, point_tool,
                distance_sigma=self.contact_distance_sigma, name=where,
            )
            return obs, np.zeros(1)
        raise MeasurementError(f"{where}: unknown payload type {type(p).__name__}")

    def __call__(
        self, T_base_tool: Array, cov_tool: Array, measurement: Measurement, prior: PriorSample | None = None
    ) -> ToolUpdate:
        """Iterated LG-EKF update (``ppoe_core.estimation.fusion.iterated_update``) with gating."""
        from ppoe_core.estimation.fusion import chi2_gate, iterated_update

        obs, z = self.build(measurement, prior)
        prior_gate = self.gate_probability if self.gating == "prior" else None
        res = iterated_update(
            T_base_tool, cov_tool, z, obs,
            max_iterations=self.max_iterations, gate_probability=prior_gate,
        )
        self.last_result = res
        if self.gating == "prior" or self.gate_probability is None:
            return ToolUpdate(res.T, res.cov, bool(res.accepted), float(res.nis))
        cost = posterior_cost(obs, res.T, res.residual, res.correction, cov_tool)
        gate = chi2_gate(obs.dim, self.gate_probability)
        if not cost <= gate:
            return ToolUpdate(np.asarray(T_base_tool, float), np.asarray(cov_tool, float), False, cost)
        return ToolUpdate(res.T, res.cov, True, cost)


def posterior_cost(obs: Any, T_post: Array, residual: Array, correction: Array, cov_prior: Array) -> float:
    """Cost of an iterated update's solution, ``r+^T (M R M^T)^-1 r+ + d^T P^+ d``.

    Parameters
    ----------
    obs : measurement model (``ppoe_core.estimation.measurements``)
    T_post : ndarray, shape (4, 4)
        Posterior estimate.
    residual : ndarray, shape (m,)
        Post-fit residual ``z ominus h(T_post)``.
    correction : ndarray, shape (6,)
        ``Log(T_prior^-1 T_post)``, tangent space at the prior.
    cov_prior : ndarray, shape (6, 6)
        Prior covariance in the tangent space at the prior (tool frame); pseudo-inverted.

    Returns
    -------
    float
        ``chi2(m)``-distributed for a linear Gaussian model (then equal to the prior NIS).
    """
    M = obs.jacobian_noise(T_post)
    if M is None:
        from ppoe_core.estimation.fusion import numerical_jacobian_noise

        M = numerical_jacobian_noise(obs, T_post)
    MRM = _sym(M @ obs.noise_cov @ M.T)
    r = np.asarray(residual, dtype=float)
    d = np.asarray(correction, dtype=float)
    s, U = np.linalg.eigh(_sym(cov_prior))
    keep = s > 1e-12 * max(float(s.max()), 1e-300)
    dU = U[:, keep].T @ d
    return float(r @ np.linalg.solve(MRM, r) + dU @ (dU / s[keep]))


# ----------------------------------------------------------------------------
# One set of settings for the node and the offline replay
# ----------------------------------------------------------------------------


def source_key(topic: str, frame_id: str) -> str:
    """The :attr:`Measurement.source` of a message: its topic and its ``header.frame_id``.

    Throttling (``min_interval``) and correction replacement work per source.  Two cameras
    publishing on one topic (e.g. ``/tag_bearing/observations`` of ``ppoe import motoman``,
    same stamp, different optical frames) are two sources: neither throttles nor replaces the
    other's correction.  The fusion node and ``ppoe evaluate`` both build sources here.

    Parameters
    ----------
    topic : str
        Topic name, e.g. ``"/tag_bearing/observations"``.
    frame_id : str
        The message's ``header.frame_id`` (camera optical frame, contact plane frame); empty
        gives the topic alone.

    Returns
    -------
    str
        ``"<topic> [<frame_id>]"`` (or ``topic``).
    """
    return f"{topic} [{frame_id}]" if frame_id else topic

#: Fusion settings with their defaults: the fusion node's parameters of the same names
#: (``config/nodes/fusion_node.yaml`` documents meaning and unit) and ``ppoe evaluate``'s replay.
FUSION_SETTINGS: dict[str, Any] = {
    "buffer_duration": 1.0,  # s
    "max_gap": 0.2,  # s
    "max_hold": 0.5,  # s
    "max_pending": 200,
    "min_interval": 0.05,  # s, per source (topic + frame_id, source_key)
    "correction_timeout": 10.0,  # s
    "correction_joint_motion": 0.05,  # rad or m
    "correction_tool_translation": 0.05,  # m
    "correction_tool_rotation": 0.1,  # rad
    "correction_decay": "linear",
    "max_iterations": 5,
    "gate_probability": 0.9999,  # >= 1.0: no gating
    "gating": "posterior",
    "pixel_sigma": 0.0,  # px; <= 0: model YAML camera.pixel_sigma
    "use_tag_centre": True,
    "use_tag_corners": True,
    "camera_covariance": True,
    "contact_distance_sigma": 0.0,  # m
}


def make_pipeline(
    model: Any,
    base_frame: str,
    tool_frame: str,
    settings: dict[str, Any] | None = None,
    updater: Any = None,
) -> FusionPipeline:
    """A :class:`FusionPipeline` with a :class:`ModelUpdater`, configured by ``settings``.

    Parameters
    ----------
    model : PPOEModel
    base_frame, tool_frame : str
        Frames of the state ``T_base_tool``.
    settings : dict, optional
        Keys of :data:`FUSION_SETTINGS` (missing ones take the default).
    updater : callable, optional
        Use this updater instead of building a :class:`ModelUpdater` (``model`` may then be
        None), e.g. the node's wrapper that waits for the URDF.

    Raises
    ------
    PpoeError
        Unknown setting or a value the pipeline refuses (the message names the setting).
    """
    s = dict(FUSION_SETTINGS)
    if settings:
        unknown = sorted(set(settings) - set(FUSION_SETTINGS))
        if unknown:
            raise PpoeError(f"unknown fusion setting(s) {unknown}; known: {sorted(FUSION_SETTINGS)}")
        s.update(settings)
    if updater is None:
        updater = make_updater(model, base_frame, tool_frame, s)
    policy = CorrectionPolicy(
        timeout=float(s["correction_timeout"]), joint_motion=float(s["correction_joint_motion"]),
        tool_translation=float(s["correction_tool_translation"]),
        tool_rotation=float(s["correction_tool_rotation"]), decay=str(s["correction_decay"]),
    )
    return FusionPipeline(
        updater, buffer_duration=float(s["buffer_duration"]), max_gap=float(s["max_gap"]),
        max_hold=float(s["max_hold"]), policy=policy, max_pending=int(s["max_pending"]),
        min_interval=float(s["min_interval"]),
    )


def make_updater(
    model: Any, base_frame: str, tool_frame: str, settings: dict[str, Any] | None = None
) -> ModelUpdater:
    """The :class:`ModelUpdater` of ``settings`` (keys of :data:`FUSION_SETTINGS`)."""
    s = {**FUSION_SETTINGS, **(settings or {})}
    return ModelUpdater(
        model, base_frame, tool_frame,
        pixel_sigma=float(s["pixel_sigma"]) if float(s["pixel_sigma"]) > 0 else None,
        max_iterations=int(s["max_iterations"]),
        gate_probability=None if float(s["gate_probability"]) >= 1.0 else float(s["gate_probability"]),
        gating=str(s["gating"]), camera_covariance=bool(s["camera_covariance"]),
        use_centre=bool(s["use_tag_centre"]), use_corners=bool(s["use_tag_corners"]),
        contact_distance_sigma=float(s["contact_distance_sigma"]),
    )
