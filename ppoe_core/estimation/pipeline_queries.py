"""Priors and fused-estimate queries between two measurements of an offline replay, in one call per pipeline.

``ppoe evaluate`` reads the fused estimate only at ground-truth stamps; between two measurements its pipelines take
priors and answer those queries, one Python call each (``add_priors`` of the priors before a query, then
``buffer.lookup_hold`` and ``fuse`` at its stamp).  :func:`priors_and_queries` makes exactly these calls in
order (the reference, ``batched=False``) or, where nothing else can happen (no pending measurement, at most one
carried correction, the default :class:`~ppoe_core.estimation.corrections.CorrectionPolicy`, validated priors with
increasing stamps newer than the buffer and queries not older than the newest prior before them), answers the
rest of the interval in one compiled call (:func:`ppoe_core.estimation.correction_kernels.held_queries_kernel`): the
same expiry checks at the same priors and queries, the same drops and counts, the same floats.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.estimation.corrections import CorrectionPolicy, MeasurementOutcome, correction_kernels
from ppoe_core.estimation.prior_buffer import Array

__all__ = ["QueryEstimates", "priors_and_queries"]


@dataclass
class QueryEstimates:
    """What :func:`priors_and_queries` gives per query (NaN where no prior: ``found`` False).

    Attributes
    ----------
    found : ndarray of bool, shape (m,)
        The buffer had a prior for the query (``lookup_hold``).
    T_base_tool : ndarray, shape (m, 4, 4)
        The fused estimate.
    cov_tool : ndarray, shape (m, 6, 6)
        Its covariance (tool tangent space at ``T_base_tool``).
    prior_T : ndarray, shape (m, 4, 4)
        The prior it was made from (zero-order hold of the newest prior, or the prior at that stamp).
    prior_cov : ndarray, shape (m, 6, 6)
        The prior's covariance (tool frame).
    prior_joints : ndarray, shape (m, n), optional
        The prior's joint positions (None when the priors have none).
    """

    found: Array
    T_base_tool: Array
    cov_tool: Array
    prior_T: Array
    prior_cov: Array
    prior_joints: Array | None

    @staticmethod
    def empty(m: int, n_joints: int | None) -> QueryEstimates:
        """``m`` queries, none found yet (``n_joints`` None: no joint positions)."""
        return QueryEstimates(np.zeros(m, dtype=bool), np.full((m, 4, 4), np.nan), np.full((m, 6, 6), np.nan),
                              np.full((m, 4, 4), np.nan), np.full((m, 6, 6), np.nan),
                              None if n_joints is None else np.full((m, n_joints), np.nan))


def priors_and_queries(pipe: Any, stamps: Array, T_base_tool: Array, cov_tool: Array, joints: Array | None,
                       query_stamps: Array, n_before: Array, out: QueryEstimates, rows: Array, *,
                       validated: bool = False, flush_margin: float | None = None,
                       batched: bool = True) -> list[MeasurementOutcome]:
    """Priors and queries of a :class:`~ppoe_core.estimation.pipeline.FusionPipeline` in their order: for each query
    ``j``, ``pipe.add_priors`` of the priors not added yet among the first ``n_before[j]``; then, if
    ``flush_margin`` is given and measurements are pending, ``pipe.flush(older_than=query_stamps[j] +
    flush_margin)``; then ``pipe.buffer.lookup_hold(query_stamps[j])`` and ``pipe.fuse`` of its prior into row
    ``rows[j]`` of ``out`` (left as it is where no prior); at the end ``add_priors`` of the remaining priors.

    Parameters
    ----------
    pipe : FusionPipeline
    stamps : ndarray, shape (n,)
        Prior stamps [s].
    T_base_tool : ndarray, shape (n, 4, 4)
    cov_tool : ndarray, shape (n, 6, 6) or (6, 6)
        Tool-frame covariances (one for all: (6, 6)).
    joints : ndarray, shape (n, k), optional
    query_stamps : ndarray, shape (m,)
        [s]
    n_before : ndarray of int, shape (m,)
        Priors before each query (non-decreasing, at most n).
    out : QueryEstimates
        Written at ``rows``.
    rows : ndarray of int, shape (m,)
    validated : bool
        As :meth:`FusionPipeline.add_priors`; only validated priors take the compiled path.
    flush_margin : float, optional
        See above [s] (``ppoe evaluate``: 1 us); None: no flush.
    batched : bool
        False: the calls one by one (the reference of the tests).

    Returns
    -------
    list of MeasurementOutcome
        Of the pending measurements processed meanwhile, in order.

    Raises
    ------
    ValueError
        ``n_before`` not non-decreasing counts in 0..n, or ``rows`` not m rows of ``out``.
    """
    c = np.ascontiguousarray  # (the compiled call takes contiguous arrays; no copy of what is)
    t = c(stamps, dtype=np.float64).reshape(-1)
    n = t.shape[0]
    T = c(T_base_tool, dtype=np.float64).reshape(n, 4, 4)
    cov = c(cov_tool, dtype=np.float64)
    Q = None if joints is None else c(joints, dtype=np.float64)
    if Q is not None and not (Q.ndim == 2 and Q.shape[0] == n):
        Q = Q.reshape(n, -1)
    tq, nb, rows = c(query_stamps, dtype=np.float64), c(n_before, dtype=np.int64), c(rows, dtype=np.int64)
    m = tq.shape[0]
    if tq.shape != (m,) or nb.shape != (m,) or rows.shape != (m,):
        raise ValueError(f"priors_and_queries: {m} queries need {m} counts n_before and {m} rows of out")
    outcomes: list[MeasurementOutcome] = []
    k = j = 0
    if batched and validated and type(pipe.policy) is CorrectionPolicy:
        while True:
            if not pipe.pending and len(pipe.corrections) <= 1:
                if _compiled(pipe, t[k:], T[k:], cov if cov.ndim == 2 else cov[k:], None if Q is None else Q[k:],
                             tq[j:], nb[j:] - k, out, rows[j:]):
                    return outcomes
                break  # not in order: the calls one by one
            if j == m:
                break
            k = _step(pipe, t, T, cov, Q, k, float(tq[j]), int(nb[j]), out, int(rows[j]), validated, flush_margin,
                      outcomes)
            j += 1
    if m and not 0 <= rows.min() <= rows.max() < out.found.shape[0]:
        raise ValueError(f"priors_and_queries: rows {rows.tolist()} are not rows of out ({out.found.shape[0]})")
    for jj in range(j, m):
        k = _step(pipe, t, T, cov, Q, k, float(tq[jj]), int(nb[jj]), out, int(rows[jj]), validated, flush_margin,
                  outcomes)
    if k < n:
        outcomes += pipe.add_priors(t[k:], T[k:], cov if cov.ndim == 2 else cov[k:], None if Q is None else Q[k:],
                                    validated=validated)
    return outcomes


def _step(pipe: Any, t: Array, T: Array, cov: Array, Q: Array | None, k: int, tq: float, b: int, out: QueryEstimates,
          r: int, validated: bool, flush_margin: float | None, outcomes: list[MeasurementOutcome]) -> int:
    """One query the reference way: ``add_priors`` of priors ``k .. b - 1``, then :func:`_query`; returns ``b``."""
    if b < k or b > t.shape[0]:
        raise ValueError(f"priors_and_queries: n_before must be non-decreasing counts in 0..{t.shape[0]}")
    if b > k:
        outcomes += pipe.add_priors(t[k:b], T[k:b], cov if cov.ndim == 2 else cov[k:b], None if Q is None else Q[k:b],
                                    validated=validated)
    _query(pipe, tq, flush_margin, out, r, outcomes)
    return b


def _query(pipe: Any, t: float, flush_margin: float | None, out: QueryEstimates, r: int,
           outcomes: list[MeasurementOutcome]) -> None:
    """A query at stamp ``t`` the reference way (flush, ``lookup_hold``, ``fuse``) into row ``r``."""
    if flush_margin is not None and pipe.pending:
        outcomes += pipe.flush(older_than=t + flush_margin)
    _, prior = pipe.buffer.lookup_hold(t)
    if prior is None:
        return
    fused = pipe.fuse(prior)
    out.found[r] = True
    out.T_base_tool[r], out.cov_tool[r] = fused.T_base_tool, fused.cov_tool
    out.prior_T[r], out.prior_cov[r] = prior.T_base_tool, prior.cov_tool
    if out.prior_joints is not None:
        out.prior_joints[r] = prior.joints


def _compiled(pipe: Any, t: Array, T: Array, cov: Array, Q: Array | None, tq: Array, nb: Array, out: QueryEstimates,
              rows: Array) -> bool:
    """The rest of :func:`priors_and_queries` in one compiled call
    (:func:`ppoe_core.estimation.correction_kernels.held_queries_kernel`), with the buffer's appends, the count and
    the drop of the correction; False (nothing done) if the data are not in the order it needs."""
    buf = pipe.buffer
    nj = 0 if Q is None else Q.shape[1]
    T_l, P_l, q_l = _EYE4, _EYE6, _NONE if Q is None else np.zeros(nj)  # (stand-ins when the buffer's is not held)
    if nb.shape[0] and nb[0] == 0 and buf.newest is not None:
        latest = buf.latest()
        q = latest.joints
        if (Q is None) != (q is None) or (q is not None and q.shape != (nj,)):
            return False  # joints unlike the run's: the reference decides
        T_l, P_l = np.ascontiguousarray(latest.T_base_tool), np.ascontiguousarray(latest.cov_tool)
        q_l = _NONE if q is None else np.ascontiguousarray(q)
    pol = pipe.policy
    corr = next(iter(pipe.corrections.values())) if pipe.corrections else None
    qa, T_rel, T_rel_l, H, R, z, anchor = _NONE, T, T_l, _NO_ROWS, _NONE, _NONE, 0.0
    if corr is not None:
        H, R, z, anchor = corr.H, corr.R, corr.z, corr.anchor.stamp
        q_a = corr.anchor.joints
        if pol.joint_motion > 0.0 and q_a is not None and Q is not None and q_a.shape == (nj,):
            qa = q_a
        if pol.tool_translation > 0.0 or pol.tool_rotation > 0.0:
            T_rel, T_rel_l = corr.T_anchor_inv @ T, corr.T_anchor_inv @ T_l  # numpy's products, as fuse takes them
    if out.prior_joints is not None:
        pq = out.prior_joints
    else:
        pq = np.zeros((out.found.shape[0], nj))
    newest = buf.newest
    status = correction_kernels().held_queries_kernel(
        t, T, cov.reshape(1, 6, 6) if cov.ndim == 2 else cov, 0 if cov.ndim == 2 else 1,
        _no_joints(t.shape[0]) if Q is None else Q, tq, nb, rows, newest is not None,
        0.0 if newest is None else newest, T_l, P_l, q_l, buf.max_hold, corr is not None, anchor, qa, T_rel, T_rel_l,
        pol.timeout, pol.joint_motion, pol.tool_translation, pol.tool_rotation, pol.decay == "linear", H, R, z,
        out.found, out.T_base_tool, out.cov_tool, out.prior_T, out.prior_cov, pq)
    if status == -2:
        raise ValueError(f"priors_and_queries: n_before must be non-decreasing counts in 0..{t.shape[0]} and rows "
                         f"rows of out ({out.found.shape[0]})")
    if status < 0:
        return False
    if status == 1:
        del pipe.corrections[next(iter(pipe.corrections))]
        pipe.counts["corrections_dropped"] += 1
    pipe.append_run(t, T, cov, Q)
    return True


#: stand-ins of what the compiled call does not read (never written)
_EYE4, _EYE6, _NONE, _NO_ROWS = np.eye(4), np.eye(6), np.zeros(0), np.zeros((0, 6))


def _no_joints(n: int) -> Array:
    """Joint positions of ``n`` priors without joints: (n, 0)."""
    return np.zeros((n, 0))
