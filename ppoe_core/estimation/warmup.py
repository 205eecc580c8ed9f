"""Compile (or load from numba's cache) the compiled code of the estimation layer before it is needed: a node calls
:func:`warm_kernels` before it subscribes (``ppoe_ros.common.runner.warm_node_kernels``), the test session once
(``test/conftest.py``): on a fresh install the first call compiles for a few seconds, which must not fall on the
first message (inputs queue up and may be lost meanwhile)."""

from __future__ import annotations

import numpy as np

from ppoe_core import lie
from ppoe_core.lie.kernels import pose_cov_fields_into
from ppoe_core.estimation import pose_fields
from ppoe_core.estimation.corrections import CarriedCorrection, apply_carried_corrections
from ppoe_core.estimation.direct_measurements import PointObservation
from ppoe_core.estimation.fusion import iterated_update
from ppoe_core.estimation.measurements import ContactPlaneModel, TagBearingModel, tag_points
from ppoe_core.estimation.pipeline import FusionPipeline, Measurement, PriorSample, ToolUpdate
from ppoe_core.estimation.prior_buffer import Array

__all__ = ["warm_kernels", "warm_pipeline"]


def warm_kernels() -> None:
    """The measurement update (a tag update in pixels and normalised coordinates with camera noise, a contact
    update, a tracker point: the linearisation given from outside), a carried correction (applied and made), the
    quick covariance checks (one matrix, a batch) and the batched Lie maps."""
    T_cam = np.eye(4)
    X = np.eye(4)
    X[2, 3] = 0.5
    P = np.eye(6) * 1e-6
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    for mode in ("pixel", "normalized"):
        tags = TagBearingModel(tag_points(0.05), K, None, 0.5, mode=mode, T_ref_camera=T_cam, cov_camera=P)
        iterated_update(X, P, tags.h(X), tags, gate_probability=None, with_cost=True)
    iterated_update(X, P, [0.0], ContactPlaneModel(np.eye(4), P, [0.0, 0.0, -0.5]), with_cost=True)
    iterated_update(X, P, X[:3, 3], PointObservation(np.zeros(3), 1e-3), with_cost=True)
    prior = PriorSample(0.0, X, P)
    apply_carried_corrections(prior, [(CarriedCorrection(prior, np.eye(6)[:2], np.ones(2), np.zeros(2)), 1.0)])
    CarriedCorrection.from_update(prior, X, 0.5 * P)
    lie.check_covariance(P, "warm-up", size=6)
    lie.check_covariance(np.stack([P, P]), "warm-up", size=6)  # a batch (ppoe evaluate's priors)
    lie.log(lie.exp(np.zeros((2, 6))))


def warm_pipeline() -> None:
    """Run a small fusion pipeline (priors, one measurement, a run of priors, fused estimates) so that its compiled
    per-prior steps (prior check, correction ratio, one-correction fuse, run breaks) are compiled or loaded before
    a node's first message, not while its inputs queue up (``ppoe_ros.common.runner``)."""
    X, P = np.eye(4), np.eye(6) * 1e-6
    X_post = X.copy()
    X_post[0, 3] = 1e-4

    def updater(T: Array, cov: Array, meas: Measurement, prior: PriorSample) -> ToolUpdate:
        return ToolUpdate(X_post, 0.5 * cov, True, 0.0)

    pipe = FusionPipeline(updater)
    for k in range(3):
        pipe.add_prior(0.01 * k, X, P, np.zeros(2))
    pipe.add_measurement(Measurement(0.015, "warm-up", None))
    pipe.add_priors(0.03 + 0.01 * np.arange(3), np.repeat(X[None], 3, axis=0), P, np.zeros((3, 2)))
    pipe.add_prior(0.07, X, P, np.zeros(2))
    # the fusion node's message conversions: its own aligned copy in, the writer's buffer (unaligned doubles) out
    fields = np.zeros(pose_fields.FIELDS)
    fields[6] = 1.0
    pose_fields.prior_from_fields(fields, np.empty((4, 4)), np.empty((6, 6)))
    out = np.frombuffer(bytearray(4 + 8 * pose_fields.FIELDS), dtype="<f8", count=pose_fields.FIELDS, offset=4)
    pose_cov_fields_into(X, P, out)
