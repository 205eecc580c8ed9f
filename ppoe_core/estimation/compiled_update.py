"""The compiled path of :func:`ppoe_core.estimation.fusion.iterated_update`: models with a ``compiled_args()``
(tag bearing, contact plane) run the whole iterated update in one call of
:func:`ppoe_core.estimation.update_kernels.update_kernel`; this wrapper allocates its outputs, raises the project's
errors for its status codes and builds the :class:`~ppoe_core.estimation.fusion.UpdateResult`."""

from __future__ import annotations

from typing import Any

import numpy as np

from ppoe_core.errors import CovarianceError, MeasurementError

__all__ = ["compiled_update", "checked_noise_covariance", "warm_kernels"]


def checked_noise_covariance(model: Any) -> np.ndarray | None:
    """``model.noise_cov`` if the model built it from checked blocks (``model._checked_noise_cov is
    model.noise_cov``: the blocks passed :func:`ppoe_core.estimation.fusion.check_noise_covariance` with their own
    scale, so the whole passes too), else None (check it)."""
    R = getattr(model, "noise_cov", None)
    return R if R is not None and getattr(model, "_checked_noise_cov", None) is R else None


def compiled_update(X0: Any, P0: Any, z: np.ndarray, model: Any, R: np.ndarray, max_iterations: int,
                    step_tolerance: float, gate: float, transport: bool, want_cost: bool) -> Any:
    """One compiled iterated update (arguments as ``fusion.iterated_update``; ``R`` the checked noise
    covariance, ``gate`` the NIS threshold or ``inf``).

    Returns
    -------
    UpdateResult or None
        None when the prior fails a check: the caller's Python path then raises the exact error.
    """
    from ppoe_core.estimation.fusion import UpdateResult
    from ppoe_core.estimation.update_kernels import buffer_size, output_views, update_kernel

    X0 = np.ascontiguousarray(X0, dtype=np.float64)
    P0 = np.ascontiguousarray(P0, dtype=np.float64)
    if X0.shape != (4, 4) or P0.shape != (6, 6):
        return None
    m = int(model.dim)
    buf, iout = np.zeros(buffer_size(m, max_iterations)), np.zeros(3, dtype=np.int64)
    kind, G, pts, K, D, pixel, extra, min_depth = model.compiled_args()
    status = update_kernel(kind, X0, P0, z, R, G, pts, K, D, pixel, extra, min_depth, max_iterations,
                           step_tolerance, gate, transport, want_cost, buf, iout)
    T, cov, y0, S0, res, gain, H, corr, steps, fout = output_views(buf, m, max_iterations)
    if status == 4:
        return None
    if status == 5:
        model.validate(z)  # raises the model's message
    if status == 2:
        i = int(iout[2])
        raise MeasurementError(f"{model.name}: {model.labels[i]} is behind the camera or too close "
                               f"(z = {fout[2]:.4g} m < min_depth {model.min_depth} m)")
    if status == 3:
        raise CovarianceError(
            f"{model.name}: innovation covariance H P H^T + M R M^T is not positive definite "
            f"({int(iout[2])}-th leading minor of the array is not positive definite); give the measurement a "
            "non-zero noise")
    nis = float(fout[0])
    if status == 1:
        return UpdateResult(T=X0.copy(), cov=0.5 * (P0 + P0.T), accepted=False, nis=nis, gate=gate, iterations=0,
                            converged=False, innovation=y0, S=S0, residual=y0.copy(), gain=np.zeros((6, m)), H=H,
                            correction=np.zeros(6), steps=())
    n_it = int(iout[0])
    return UpdateResult(T=T, cov=cov, accepted=True, nis=nis, gate=gate, iterations=n_it, converged=bool(iout[1]),
                        innovation=y0, S=S0, residual=res, gain=gain, H=H, correction=corr,
                        steps=tuple(steps[:n_it].tolist()), cost=float(fout[1]))


def warm_kernels() -> None:
    """Compile (or load from numba's cache) the kernels of the fusion path: a tag update (pixel and normalised,
    with camera noise), a contact update, a carried correction (applied and made) and the quick covariance checks (one
    matrix, a batch).  The nodes call it
    before subscribing (``ppoe_ros.common.runner.warm_node_kernels``), the test session once (``test/conftest.py``)."""
    from ppoe_core import lie
    from ppoe_core.estimation.corrections import CarriedCorrection, apply_carried_corrections
    from ppoe_core.estimation.fusion import iterated_update
    from ppoe_core.estimation.measurements import ContactPlaneModel, TagBearingModel, tag_points
    from ppoe_core.estimation.prior_buffer import PriorSample

    T_cam = np.eye(4)
    X = np.eye(4)
    X[2, 3] = 0.5
    P = np.eye(6) * 1e-6
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    for mode in ("pixel", "normalized"):
        tags = TagBearingModel(tag_points(0.05), K, None, 0.5, mode=mode, T_ref_camera=T_cam, cov_camera=P)
        iterated_update(X, P, tags.h(X), tags, gate_probability=None, with_cost=True)
    iterated_update(X, P, [0.0], ContactPlaneModel(np.eye(4), P, [0.0, 0.0, -0.5]), with_cost=True)
    prior = PriorSample(0.0, X, P)
    apply_carried_corrections(prior, [(CarriedCorrection(prior, np.eye(6)[:2], np.ones(2), np.zeros(2)), 1.0)])
    CarriedCorrection.from_update(prior, X, 0.5 * P)
    lie.check_covariance(P, "warm-up", size=6)
    lie.check_covariance(np.stack([P, P]), "warm-up", size=6)  # a batch (ppoe evaluate's priors)
