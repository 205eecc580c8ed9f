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
from collections.abc import Callable
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, PpoeError
from ppoe_core.estimation.corrections import (
    COUNT_KEYS, CarriedCorrection, CorrectionPolicy, FusedEstimate, Measurement, MeasurementOutcome, MeasurementUpdater,
    ToolUpdate, correction_kernels, symmetric, apply_carried_corrections,
)
from ppoe_core.model.stamp_policy import StampResetPolicy
from ppoe_core.estimation.pipeline_queries import QueryEstimates, priors_and_queries
from ppoe_core.estimation.prior_buffer import Array, LookupStatus, PriorBuffer, PriorSample
from ppoe_core.estimation.updater import (
    FUSION_SETTINGS, ContactMeasurement, ModelUpdater, TagMeasurement, make_updater,
)

__all__ = [
    "PriorSample", "PriorBuffer", "LookupStatus", "Measurement", "ToolUpdate", "MeasurementUpdater", "CorrectionPolicy",
    "CarriedCorrection", "FusedEstimate", "MeasurementOutcome", "FusionPipeline", "TagMeasurement",
    "ContactMeasurement", "ModelUpdater", "COUNT_KEYS", "apply_carried_corrections", "FUSION_SETTINGS", "make_pipeline",
    "make_updater", "source_key", "QueryEstimates",
]


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

    def __init__(self, updater: MeasurementUpdater | Callable[[Array, Array, Measurement, PriorSample], ToolUpdate],
                 buffer_duration: float = 1.0, max_gap: float = 0.2, max_hold: float = 0.5,
                 policy: CorrectionPolicy | None = None, max_pending: int = 200, reset_jump: float = 2.0,
                 min_interval: float = 0.0) -> None:
        self.updater = updater
        self.buffer = PriorBuffer(buffer_duration, max_gap, max_hold)
        self.policy = policy if policy is not None else CorrectionPolicy()
        if max_pending < 0:
            raise PpoeError(f"FusionPipeline: max_pending must be >= 0, got {max_pending}")
        self.max_pending = int(max_pending)
        self.stamp_policy = StampResetPolicy(float(reset_jump))
        if not min_interval >= 0.0:
            raise PpoeError(f"FusionPipeline: min_interval must be >= 0 s, got {min_interval}")
        self.min_interval = float(min_interval)
        self._last_stamp: dict[str, float] = {}
        self.corrections: dict[str, CarriedCorrection] = {}
        self.pending: list[Measurement] = []
        self.counts: dict[str, int] = {k: 0 for k in COUNT_KEYS}

    # -- priors ---------------------------------------------------------------

    def add_prior(
        self,
        stamp: float,
        T_base_tool: Array,
        cov_tool: Array,
        joints: Array | None = None,
        validated: bool = False,
        estimate: bool = True,
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
        estimate : bool
            Return the fused estimate at ``stamp``.  False (an offline replay that reads estimates only at
            ground-truth stamps): the corrections are only checked for expiry, exactly as :meth:`fuse` does
            (the same drops and counts), and None is returned in its place.

        Returns
        -------
        (estimate, outcomes)
            The fused estimate at ``stamp`` (None if the prior was too late to keep) and the
            outcomes of the pending measurements processed now.
        """
        T = np.asarray(T_base_tool, dtype=np.float64)
        cov = cov_tool
        if not (T.shape == (4, 4) and type(cov) is np.ndarray and cov.dtype == np.float64 and cov.shape == (6, 6)
                and correction_kernels().prior_passes(T, cov, not validated)):
            cov = self._checked_prior(float(stamp), T, cov_tool, validated)  # the full checks: error or pass
        q = joints
        if q is not None and not (type(q) is np.ndarray and q.dtype == np.float64 and q.ndim == 1):
            q = np.asarray(joints, dtype=np.float64).reshape(-1)
        sample = PriorSample(float(stamp), T, cov, q)
        newest = self.buffer.newest
        if self.stamp_policy.new_timeline_s(sample.stamp, newest):
            self.reset()
            self.counts["resets"] += 1
        elif newest is not None and sample.stamp <= newest:
            self.counts["priors_out_of_order"] += 1  # still kept: it serves measurement lookups
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
        if not estimate:
            self._active_corrections(sample, None)
            return None, outcomes
        return self.fuse(sample), outcomes

    def add_priors(self, stamps: Array, T_base_tool: Array, cov_tool: Array, joints: Array | None = None,
                   validated: bool = False) -> list[MeasurementOutcome]:
        """A run of priors with no measurement added between them: exactly the calls ``add_prior(stamps[k],
        T_base_tool[k], cov_tool[k], joints[k], validated, estimate=False)`` in order (the same buffer, expiry
        drops at the same prior, counts and outcomes), vectorised where nothing but the expiry check happens.

        Parameters
        ----------
        stamps : ndarray, shape (n,)
            [s]
        T_base_tool : ndarray, shape (n, 4, 4)
        cov_tool : ndarray, shape (n, 6, 6) or (6, 6)
            Tool-frame covariances (one for all priors: shape (6, 6)).
        joints : ndarray, shape (n, m), optional
        validated : bool
            See :meth:`add_prior`.  Only validated priors (``ppoe evaluate`` checks the whole batch first) take the
            vectorised path: otherwise each prior's covariance is checked as :meth:`add_prior` does, one at a time.

        Returns
        -------
        list of MeasurementOutcome
            The outcomes of the pending measurements the priors made ready, in order.
        """
        t = np.asarray(stamps, dtype=np.float64).reshape(-1)
        n = t.shape[0]
        T = np.asarray(T_base_tool, dtype=np.float64)
        cov = np.asarray(cov_tool, dtype=np.float64)
        Q = None if joints is None or n == 0 else np.asarray(joints, dtype=np.float64).reshape(n, -1)
        if T.shape != (n, 4, 4) or cov.shape not in ((6, 6), (n, 6, 6)):
            raise MeasurementError(f"add_priors: {n} stamps need T_base_tool (n, 4, 4) and cov_tool (n, 6, 6) or "
                                   f"(6, 6), got shapes {T.shape} and {cov.shape}")
        one_cov = cov.ndim == 2
        outcomes: list[MeasurementOutcome] = []
        fast = validated and type(self.policy) is CorrectionPolicy
        # a run continues at k if its stamp is newer than the one before and its pose is finite
        finite = np.empty(n, dtype=np.bool_)
        breaks = correction_kernels().run_breaks(t, T, finite)
        i = 0
        while i < n:
            newest = self.buffer.newest
            if not fast or self.pending or not finite[i] or not (newest is None or t[i] > newest):
                outcomes += self.add_prior(float(t[i]), T[i], cov if one_cov else cov[i], None if Q is None else Q[i],
                                           validated=validated, estimate=False)[1]
                i += 1
                continue
            b = int(np.searchsorted(breaks, i + 1))
            j = int(breaks[b]) if b < len(breaks) else n
            self._add_run(t[i:j], T[i:j], cov if one_cov else cov[i:j], None if Q is None else Q[i:j])
            i = j
        return outcomes

    def _add_run(self, t: Array, T: Array, cov: Array, Q: Array | None) -> None:
        """:meth:`add_priors` of priors with increasing stamps newer than the buffer, finite poses, checked
        covariances and no pending measurement: only the expiry check and the buffer's appends happen."""
        for source, corr in list(self.corrections.items()):
            if self._first_expiry(corr, t, T, Q) >= 0:
                del self.corrections[source]
                self.counts["corrections_dropped"] += 1
        self.append_run(t, T, cov, Q)

    def append_run(self, t: Array, T: Array, cov: Array, Q: Array | None) -> None:
        """The buffer's appends and the prior count of a run of :meth:`add_priors` whose expiry checks the caller has
        made (increasing stamps newer than the buffer, finite poses, checked covariances, nothing pending)."""
        if not len(t):
            return
        self.counts["priors"] += len(t)
        # what the appends leave in the buffer: the priors not older than the last one minus its duration
        ts = t.tolist()
        k = bisect.bisect_left(ts, ts[-1] - self.buffer.duration)
        self.buffer.append_arrays(ts[k:], T[k:], cov if cov.ndim == 2 else cov[k:], None if Q is None else Q[k:])

    def priors_and_queries(self, stamps: Array, T_base_tool: Array, cov_tool: Array, joints: Array | None,
                           query_stamps: Array, n_before: Array, out: QueryEstimates, rows: Array, *,
                           validated: bool = False, flush_margin: float | None = None) -> list[MeasurementOutcome]:
        """Priors and fused-estimate queries in their order (query ``j`` after the first ``n_before[j]`` priors, into
        row ``rows[j]`` of ``out``): the calls :meth:`add_priors`, :meth:`flush` (``flush_margin``),
        ``buffer.lookup_hold`` and :meth:`fuse` would make, mostly in one compiled call
        (:func:`ppoe_core.estimation.pipeline_queries.priors_and_queries`, which documents the arguments)."""
        return priors_and_queries(self, stamps, T_base_tool, cov_tool, joints, query_stamps, n_before, out, rows,
                                  validated=validated, flush_margin=flush_margin)

    def _first_expiry(self, corr: CarriedCorrection, t: Array, T: Array, Q: Array | None) -> int:
        """Index of the first prior of a run at which ``corr`` expires (as :meth:`_active_corrections`), -1 if
        none."""
        pol = self.policy
        qa = corr.anchor.joints
        if pol.joint_motion > 0.0 and qa is not None and Q is not None and qa.shape == (Q.shape[1],):
            Qr, qa_r = Q, qa
        else:
            Qr, qa_r = np.zeros((len(t), 0)), np.zeros(0)
        if pol.tool_translation > 0.0 or pol.tool_rotation > 0.0:
            T_rel = corr.T_anchor_inv @ T  # numpy's stacked product: the floats of one product per prior
        else:
            T_rel = np.zeros((len(t), 4, 4))
        return int(correction_kernels().first_expiry(t, corr.anchor.stamp, Qr, qa_r, T_rel, pol.timeout,
                                                      pol.joint_motion, pol.tool_translation, pol.tool_rotation))

    @staticmethod
    def _checked_prior(stamp: float, T: Array, cov_tool: Array, validated: bool) -> Array:
        """The checks of a prior that failed the quick ones (or has unusual types): raise the error, or pass and
        return the covariance as :meth:`add_prior` keeps it."""
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise MeasurementError(f"prior at stamp {stamp}: T_base_tool must be a finite 4x4, got shape {T.shape}")
        if validated:
            cov = np.asarray(cov_tool, dtype=np.float64)
            if cov.shape != (6, 6):
                raise MeasurementError(f"prior at stamp {stamp}: cov_tool must be 6x6, got shape {cov.shape}")
            return cov
        return lie.check_covariance(cov_tool, name=f"prior at stamp {stamp}", size=6)

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
        if len(self.corrections) == 1 and exclude is None and type(self.policy) is CorrectionPolicy:
            return self._fuse_one(prior)
        applied = self._active_corrections(prior, exclude)
        if not applied:
            return FusedEstimate(prior.stamp, prior.T_base_tool, prior.cov_tool, 0.0, prior)
        T, cov = apply_carried_corrections(prior, applied)
        return FusedEstimate(prior.stamp, T, cov, applied[0][1] if len(applied) == 1 else max(w for _, w in applied),
                             prior)

    def _fuse_one(self, prior: PriorSample) -> FusedEstimate:
        """:meth:`fuse` with one correction (the common case) in one compiled call: the same weight, drop and
        floats as :meth:`_active_corrections` + :func:`apply_carried_corrections`."""
        (source, corr), = self.corrections.items()
        pol = self.policy
        qp, qa = pol.joint_args(prior.joints, corr.anchor.joints)
        T, P = prior.T_base_tool, prior.cov_tool
        T_out, cov_out = np.empty((4, 4)), np.empty((6, 6))
        w = correction_kernels().fuse_one_kernel(
            np.asarray(T, dtype=np.float64), np.asarray(P, dtype=np.float64),  # any layout: the same arithmetic
            pol.relative_pose(corr.T_anchor_inv, T), abs(prior.stamp - corr.anchor.stamp), qp, qa, pol.timeout,
            pol.joint_motion, pol.tool_translation, pol.tool_rotation, pol.decay == "linear", corr.H, corr.R, corr.z,
            T_out, cov_out)
        if w > 0.0:
            return FusedEstimate(prior.stamp, T_out, cov_out, w, prior)
        if prior.stamp >= corr.anchor.stamp:
            del self.corrections[source]
            self.counts["corrections_dropped"] += 1
        return FusedEstimate(prior.stamp, T, P, 0.0, prior)

    def _active_corrections(self, prior: PriorSample, exclude: str | None) -> list[tuple[CarriedCorrection, float]]:
        """The corrections to apply to ``prior`` with their weights (all sources but ``exclude``); expired ones are
        dropped and counted (see :meth:`fuse`)."""
        applied: list[tuple[CarriedCorrection, float]] = []
        if not self.corrections:
            return applied
        weight = self.policy.weight
        for source, corr in list(self.corrections.items()):
            w = weight(corr.anchor, prior, corr.T_anchor_inv)
            if w <= 0.0:
                if prior.stamp >= corr.anchor.stamp:
                    del self.corrections[source]
                    self.counts["corrections_dropped"] += 1
                continue
            if source != exclude:
                applied.append((corr, w))
        return applied

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
        if not res.accepted:
            self.counts["rejected"] += 1
            return MeasurementOutcome(measurement, "rejected", nis=float(res.nis))
        self.counts["accepted"] += 1
        T_post = np.asarray(res.T_base_tool, dtype=np.float64)
        cov_post = symmetric(res.cov_tool)
        corr = CarriedCorrection.from_update(prior, T_post, cov_post, est.T_base_tool, est.cov_tool)
        if corr is not None:
            self.corrections[measurement.source] = corr
        else:
            self.corrections.pop(measurement.source, None)
        post = FusedEstimate(prior.stamp, T_post, cov_post, 1.0, prior)
        return MeasurementOutcome(measurement, "accepted", post, nis=float(res.nis))


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


def make_pipeline(model: Any, base_frame: str, tool_frame: str, settings: dict[str, Any] | None = None,
                  updater: Any = None) -> FusionPipeline:
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
    policy = CorrectionPolicy(timeout=float(s["correction_timeout"]), joint_motion=float(s["correction_joint_motion"]),
                              tool_translation=float(s["correction_tool_translation"]),
                              tool_rotation=float(s["correction_tool_rotation"]), decay=str(s["correction_decay"]))
    return FusionPipeline(updater, buffer_duration=float(s["buffer_duration"]), max_gap=float(s["max_gap"]),
                          max_hold=float(s["max_hold"]), policy=policy, max_pending=int(s["max_pending"]),
                          min_interval=float(s["min_interval"]))
