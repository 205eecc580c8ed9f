"""The replay's loop: priors, measurements and ground-truth stamps in time order through the fusion pipelines, as the
nodes see them; between two measurements each pipeline takes the priors and answers the ground-truth stamps in one
call (:meth:`ppoe_core.estimation.pipeline.FusionPipeline.priors_and_queries`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.analysis.evaluate.metrics import METHODS
from ppoe_core.analysis.evaluate.sources import measurement_dim
from ppoe_core.estimation.pipeline_queries import QueryEstimates
from ppoe_core.io.progress import ProgressBar

__all__ = [
    "FLUSH_MARGIN", "MeasurementSlots", "ReplayEvents", "ReplayRun", "chunk_bounds", "replay_events", "replay_order",
]

#: a ground-truth stamp flushes the measurements pending up to this much after it [s]: stamps near 1.7e9 s resolve
#: ~0.24 us in float64
FLUSH_MARGIN = 1e-6


@dataclass
class ReplayRun:
    """What the replay gives per method (``fk``, ``ppoe``, ``naive``) at every ground-truth stamp (NaN where no
    prior): tool pose and covariance (tool frame), the joints of the prior, and the measurement outcomes."""

    est_T: dict[str, np.ndarray]
    est_cov: dict[str, np.ndarray]
    gt_joints: np.ndarray
    nis: dict[str, list[tuple[float, int]]]
    outcomes: dict[str, dict[str, int]]
    errors: dict[str, list[str]]
    #: the last measurement recorded, the tag ids it was counted with and its dimension (the pipelines record the
    #: same measurement in turn, with the same tags)
    _dim: tuple[Any, Any, int] = (None, None, 0)

    def record(self, name: str, outs: Sequence[Any], known_tags: Any) -> None:
        """Count measurement outcomes; NIS with its dimension; the first 20 errors."""
        for o in outs:
            self.outcomes[name][o.status] = self.outcomes[name].get(o.status, 0) + 1
            if o.status in ("accepted", "rejected") and math.isfinite(o.nis):
                m, last = o.measurement, self._dim
                if not (last[0] is m and (last[1] is known_tags or last[1].keys() == known_tags.keys())):
                    self._dim = last = (m, known_tags, measurement_dim(m.payload, known_tags))
                self.nis[name].append((o.nis, last[2]))
            if o.status == "bad" and len(self.errors[name]) < 20:
                self.errors[name].append(o.error)


class MeasurementSlots:
    """The measurements of a replay in time order (stable: equal stamps in the order given), each taken when asked:
    the tag slots of a :class:`~ppoe_core.analysis.evaluate.tag_stream.TagStream` (image ``k``'s measurement, or None
    for an image without tags, waits for its detection) first, then ``others`` (contact planes, sources: made
    already).  ``stamps``: per slot, in order.
    """

    def __init__(self, tags: Any, others: list[Any]) -> None:
        stamps = np.array(list(tags.stamps) + [m.stamp for m in others], dtype=float)
        self._order = np.argsort(stamps, kind="stable")
        self.stamps = stamps[self._order]
        self._tags, self._others, self._n_tags = tags, others, len(tags.stamps)

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def get(self, j: int) -> Any:
        """The measurement of slot ``j`` (time order), None for an image without tags."""
        s = int(self._order[j])
        return self._tags.get(s) if s < self._n_tags else self._others[s - self._n_tags]

    def resolved(self) -> list[Any]:
        """Every measurement (None slots left out), in time order: ``sorted(tags + others, key=stamp)``."""
        return [m for m in map(self.get, range(len(self))) if m is not None]


@dataclass
class ReplayEvents:
    """The replay's events in order (priors, then measurements, then ground truth at equal stamps): ``kind`` 0 / 1 /
    2 and ``index`` per event; ``priors_before[e]`` priors among the events before ``e``; ``gt_at`` the events of
    the ground-truth stamps."""

    kind: np.ndarray
    index: np.ndarray
    priors_before: np.ndarray
    gt_at: np.ndarray


def replay_order(prior_stamps: np.ndarray, slot_stamps: np.ndarray, gt_stamps: np.ndarray) -> ReplayEvents:
    """The events of priors, measurement slots and ground-truth stamps in replay order (stamp, then kind, then
    index)."""
    t = np.concatenate([prior_stamps, slot_stamps, gt_stamps])
    kind = np.concatenate([np.zeros(len(prior_stamps), int), np.ones(len(slot_stamps), int),
                           np.full(len(gt_stamps), 2)])
    index = np.concatenate([np.arange(len(prior_stamps)), np.arange(len(slot_stamps)), np.arange(len(gt_stamps))])
    order = np.lexsort((index, kind, t))
    kind, index = kind[order], index[order]
    priors_before = np.concatenate([[0], np.cumsum(kind == 0)])
    return ReplayEvents(kind, index, priors_before, np.flatnonzero(kind == 2))


def chunk_bounds(ev: ReplayEvents, a: int, b: int) -> tuple[int, int, np.ndarray, np.ndarray]:
    """The events ``a .. b - 1`` (priors, ground-truth stamps, slots without a measurement): ``(pa, pb, gt, n_before)``,
    their priors ``pa .. pb - 1`` (the prior events' indices are 0, 1, ... in event order: the events are in stamp
    order and the priors sorted by stamp), their ground-truth samples ``gt`` and the priors before each of them."""
    pa, pb = int(ev.priors_before[a]), int(ev.priors_before[b])
    at = ev.gt_at[np.searchsorted(ev.gt_at, a):np.searchsorted(ev.gt_at, b)]
    return pa, pb, ev.index[at], ev.priors_before[at] - pa


def replay_events(pri: Any, slots: MeasurementSlots, gt_stamps: np.ndarray, pipes: dict[str, Any],
                  updaters: dict[str, Any], n_joints: int, progress: bool) -> ReplayRun:
    """Priors (``pri``: stamps, ``T_all``, ``cov_all``, ``cov_naive``, ``Q``), measurements and ground-truth stamps
    in time order through the pipelines (as the nodes see them).

    Between two measurements (a slot without one, an image without tags, is no boundary) each pipeline takes the
    priors and answers the ground-truth stamps with ``priors_and_queries`` (``add_priors`` of the priors before a
    stamp, measurements pending up to :data:`FLUSH_MARGIN` after it flushed, the fused estimate of its
    ``lookup_hold`` prior).  ``fk`` is the PPOE pipeline's prior at each stamp."""
    ev = replay_order(pri.stamps, slots.stamps, gt_stamps)
    n_gt = len(gt_stamps)
    est = {name: QueryEstimates.empty(n_gt, n_joints) for name in pipes}
    outcomes: dict[str, dict[str, int]] = {m: {} for m in pipes}
    run = ReplayRun({m: np.full((n_gt, 4, 4), np.nan) for m in METHODS},
                    {m: np.full((n_gt, 6, 6), np.nan) for m in METHODS}, np.full((n_gt, n_joints), np.nan),
                    {m: [] for m in pipes}, outcomes, {m: [] for m in pipes})
    n_ev = len(ev.kind)
    bar = ProgressBar(n_ev, progress)
    start = 0
    for e, i in zip(np.flatnonzero(ev.kind == 1).tolist(), ev.index[ev.kind == 1].tolist()):
        m = slots.get(i)
        if m is None:  # the priors before and after it go on as one interval
            continue
        _interval(run, pri, ev, start, e, gt_stamps, pipes, updaters, est)
        for name, pipe in pipes.items():
            o = pipe.add_measurement(m)
            if o.status != "pending":
                run.record(name, [o], updaters[name].tags)
        start = e + 1
        bar.update(start)
    _interval(run, pri, ev, start, n_ev, gt_stamps, pipes, updaters, est)
    for name, pipe in pipes.items():
        run.record(name, pipe.flush(), updaters[name].tags)
        run.est_T[name], run.est_cov[name] = est[name].T_base_tool, est[name].cov_tool
    if "ppoe" in est:
        run.est_T["fk"], run.est_cov["fk"] = est["ppoe"].prior_T, est["ppoe"].prior_cov
        run.gt_joints = est["ppoe"].prior_joints  # type: ignore[assignment]
    bar.close()
    return run


def _interval(run: ReplayRun, pri: Any, ev: ReplayEvents, a: int, b: int, gt_stamps: np.ndarray,
              pipes: dict[str, Any], updaters: dict[str, Any], est: dict[str, QueryEstimates]) -> None:
    """The events ``a .. b - 1`` (no measurement among them) through every pipeline; the estimates at their
    ground-truth stamps into ``est``."""
    pa, pb, gt, n_before = chunk_bounds(ev, a, b)
    if pa == pb and not len(gt):
        return
    tq = gt_stamps[gt]
    for name, pipe in pipes.items():
        cov = pri.cov_all[pa:pb] if name == "ppoe" else pri.cov_naive
        outs = pipe.priors_and_queries(pri.stamps[pa:pb], pri.T_all[pa:pb], cov, pri.Q[pa:pb], tq, n_before,
                                       est[name], gt, validated=True, flush_margin=FLUSH_MARGIN)
        if outs:
            run.record(name, outs, updaters[name].tags)
    if not pipes and len(gt):  # no fusion at all: FK from the nearest joint state
        j = np.clip(np.searchsorted(pri.stamps, tq, side="right") - 1, 0, len(pri.stamps) - 1)
        run.est_T["fk"][gt], run.est_cov["fk"][gt], run.gt_joints[gt] = pri.T_all[j], pri.cov_all[j], pri.Q[j]
