"""Measurement updates and carried corrections of the fusion pipeline: what an updater returns, how a correction is
carried to later priors and how several are applied at once (covariances in the tool frame, docs/conventions.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ppoe_core import lie
from ppoe_core.lie.compiled import compiled
from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.estimation.prior_buffer import INV_JITTER, Array, PriorSample

#: 6x6 identity (read-only; built once instead of per prior)
_EYE6 = np.eye(6)
_EYE6.setflags(write=False)
_EYE4 = np.eye(4)
_EYE4.setflags(write=False)
#: no joint positions (the joint ratio is skipped)
_NO_JOINTS = np.zeros(0)
_NO_JOINTS.setflags(write=False)

_CORRECTION_KERNELS = "ppoe_core.estimation.correction_kernels"


def correction_kernels() -> Any:
    """:mod:`ppoe_core.estimation.correction_kernels`, imported on first use (numba) and kept."""
    return compiled(_CORRECTION_KERNELS)


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

    def ratio(self, anchor: PriorSample, prior: PriorSample, T_anchor_inv: Array | None = None) -> float:
        """Largest change ratio between the correction's anchor prior and ``prior`` (``T_anchor_inv``: the
        anchor pose's inverse when the caller has it, :attr:`CarriedCorrection.T_anchor_inv`); compiled,
        :func:`ppoe_core.estimation.correction_kernels.correction_ratio`."""
        qp, qa = self.joint_args(prior.joints, anchor.joints)
        T_inv = lie.inverse(anchor.T_base_tool) if T_anchor_inv is None else T_anchor_inv
        return correction_kernels().correction_ratio(
            abs(prior.stamp - anchor.stamp), qp, qa, self.relative_pose(T_inv, prior.T_base_tool), self.timeout,
            self.joint_motion, self.tool_translation, self.tool_rotation)

    def joint_args(self, q: Array | None, q_anchor: Array | None) -> tuple[Array, Array]:
        """The joint positions of a prior and of an anchor as the compiled ratio takes them: float (n,) each, or
        both empty when the joint ratio does not apply (disabled, unknown joints, different lengths)."""
        if self.joint_motion > 0.0 and q_anchor is not None and q is not None and q_anchor.shape == q.shape:
            if q.dtype != np.float64 or q.ndim != 1:
                q = np.asarray(q, dtype=np.float64).reshape(-1)
            if q_anchor.dtype != np.float64 or q_anchor.ndim != 1:
                q_anchor = np.asarray(q_anchor, dtype=np.float64).reshape(-1)
            return q, q_anchor  # NaN = joint not (yet) known: skipped
        return _NO_JOINTS, _NO_JOINTS

    def relative_pose(self, T_anchor_inv: Array, T_prior: Array) -> Array:
        """``T_anchor^-1 T_prior`` for the tool-motion ratios (identity when both are disabled).  numpy's product
        on purpose: the angle from the trace is ill-conditioned near 0 (d acos / dc ~ 1 / angle), a product summed
        in another order moves a small angle in its 8th digit."""
        if self.tool_translation > 0.0 or self.tool_rotation > 0.0:
            return T_anchor_inv @ T_prior
        return _EYE4

    def weight(self, anchor: PriorSample, prior: PriorSample, T_anchor_inv: Array | None = None) -> float:
        """Weight in [0, 1] of the correction made at ``anchor`` when applied to ``prior``."""
        r = self.ratio(anchor, prior, T_anchor_inv)
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
    T_anchor_inv : ndarray, shape (4, 4)
        ``anchor.T_base_tool^-1`` (computed once: every later prior's weight needs it).
    """

    anchor: PriorSample
    H: Array
    R: Array
    z: Array
    T_anchor_inv: Array = None  # type: ignore[assignment]  # set in __post_init__

    def __post_init__(self) -> None:
        if self.T_anchor_inv is None:
            object.__setattr__(self, "T_anchor_inv", lie.inverse(self.anchor.T_base_tool))
        for name in ("H", "R", "z"):  # contiguous float64 once here, not per prior in the compiled update
            object.__setattr__(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float64))

    @staticmethod
    def from_update(anchor: PriorSample, T_post: Array, cov_post: Array, T_pre: Array | None = None,
                    cov_pre: Array | None = None) -> CarriedCorrection | None:
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

        Compiled (:func:`ppoe_core.estimation.correction_kernels.from_update_kernel`; the numpy reference of the
        tests is ``test/update_reference.py``).

        Raises
        ------
        MeasurementError
            Poses not (4, 4), covariances not (6, 6), or an input with NaN / inf.
        """
        c = np.ascontiguousarray
        T_a = c(anchor.T_base_tool, dtype=np.float64)
        T_pre_a = T_a if T_pre is None else c(T_pre, dtype=np.float64)
        cov_pre_a = c(anchor.cov_tool if cov_pre is None else cov_pre, dtype=np.float64)
        T_post_a, cov_post_a = c(T_post, dtype=np.float64), c(cov_post, dtype=np.float64)
        if not (T_a.shape == T_pre_a.shape == T_post_a.shape == (4, 4) and cov_pre_a.shape == cov_post_a.shape
                == (6, 6)):
            raise MeasurementError(f"carried correction at {anchor.stamp}: poses must be 4x4 and covariances 6x6, got "
                                   f"{T_pre_a.shape}, {T_post_a.shape}, {cov_pre_a.shape}, {cov_post_a.shape}")
        H, R, z, T_inv = np.empty((6, 6)), np.empty(6), np.empty(6), np.empty((4, 4))
        r = correction_kernels().from_update_kernel(T_a, T_pre_a, T_pre_a is T_a, cov_pre_a, T_post_a, cov_post_a,
                                                     INV_JITTER, H, R, z, T_inv)
        if r < 0:
            raise MeasurementError(f"carried correction at {anchor.stamp}: a pose or covariance of the update is not "
                                   "finite")
        return CarriedCorrection(anchor, H[:r], R[:r], z[:r], T_inv) if r else None

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
    if len(corrections) == 1 and corrections[0][1] > 0.0:  # the common case: no stacking copies (same values)
        c, w = corrections[0]
        H, Rw, z = c.H, c.R / w, c.z
    else:
        active = [(c, w) for c, w in corrections if w > 0.0]
        if not active:
            return prior.T_base_tool, symmetric(prior.cov_tool)
        H = np.concatenate([c.H for c, _ in active])
        Rw = np.concatenate([c.R / w for c, w in active])
        z = np.concatenate([c.z for c, _ in active])
    T_out, cov = np.empty((4, 4)), np.empty((6, 6))
    # the kernel symmetrises the covariance itself ((P + P^T) / 2 of a symmetric P is P: the same floats)
    correction_kernels().apply_corrections_kernel(
        np.ascontiguousarray(prior.T_base_tool, dtype=np.float64),
        np.ascontiguousarray(prior.cov_tool, dtype=np.float64), np.ascontiguousarray(H, dtype=np.float64), Rw,
        np.ascontiguousarray(z, dtype=np.float64), T_out, cov)
    return T_out, cov


def symmetric(A: Array) -> Array:
    """``(A + A^T) / 2`` as float64."""
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
    "priors", "priors_late", "priors_out_of_order", "resets", "measurements", "accepted", "rejected", "dropped_stale",
    "dropped_no_prior", "bad", "corrections_dropped", "throttled",
)
