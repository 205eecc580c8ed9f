"""The iterated update's driver: :func:`run_update` calls :func:`ppoe_core.estimation.update_kernels.update_kernel`
(THE implementation of the update), gives it the model's linearisation at each iterate when the model's own is not
compiled, turns its status codes into the project's errors and builds the
:class:`~ppoe_core.estimation.update_types.UpdateResult`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ppoe_core.errors import CovarianceError, MeasurementError, PpoeError
from ppoe_core.estimation.checks import check_noise_covariance, check_pose
from ppoe_core.estimation.update_types import CompiledModel, UpdateResult
from ppoe_core.lie.compiled import compiled

__all__ = ["run_update", "Linearisation"]

#: ``linearise(T) -> (residual z ominus h(T) (m,), H (m, 6), M (m, k))`` of a model whose linearisation is not compiled
Linearisation = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

_NONE_3 = np.eye(3)
_NONE_5 = np.zeros(5)
_NONE_PTS = np.zeros((1, 3))
_NONE_R, _NONE_H, _NONE_M = np.zeros(0), np.zeros((0, 6)), np.zeros((0, 0))


def run_update(X0: Any, P0: Any, z: np.ndarray, model: Any, R: np.ndarray, spec: CompiledModel | None,
               linearise: Linearisation | None, max_iterations: int, step_tolerance: float, gate: float,
               transport: bool, want_cost: bool) -> UpdateResult:
    """One iterated update (arguments as :func:`ppoe_core.estimation.fusion.iterated_update`; ``R`` the checked
    noise covariance, ``gate`` the NIS threshold or ``inf``): ``spec`` the model's compiled linearisation (``z`` then
    the validated measurement), else ``linearise`` gives it at each iterate.

    Raises
    ------
    MeasurementError, CovarianceError
        As the update's module docstring lists (a point behind the camera, ``S`` not positive definite, a bad
        prior or measurement).
    """
    k = compiled("ppoe_core.estimation.update_kernels")
    X0 = np.ascontiguousarray(X0, dtype=np.float64)
    P0 = np.ascontiguousarray(P0, dtype=np.float64)
    if X0.shape != (4, 4) or P0.shape != (6, 6):
        _raise_prior(model, X0, P0)
    m = int(model.dim)
    buf, iout = np.zeros(k.buffer_size(m, max_iterations)), np.zeros(5, dtype=np.int64)
    if spec is not None:
        kind, G, pts, K, D, pixel, extra, min_depth = spec
        zv = z
    else:
        kind, G, pts, K, D, pixel, extra, min_depth = k.KIND_EXTERNAL, X0, _NONE_PTS, _NONE_3, _NONE_5, False, \
            False, 0.0
        zv = np.zeros(m)
    r, H, M = _NONE_R, _NONE_H, _NONE_M  # (the first call reads no linearisation)
    while True:
        status = k.update_kernel(kind, X0, P0, zv, R, G, pts, K, D, pixel, extra, min_depth, max_iterations,
                                 step_tolerance, gate, transport, want_cost, buf, iout, r, H, M)
        if status != k.NEED_LINEARISATION:
            break
        assert linearise is not None
        r, H, M = linearise(k.output_views(buf, m, max_iterations)[0].copy())
    return _result(k, status, buf, iout, model, X0, P0, z, m, max_iterations, gate)


def _raise_prior(model: Any, X0: np.ndarray, P0: np.ndarray) -> None:
    check_pose(X0, f"{model.name}: prior pose")
    check_noise_covariance(P0, 6, f"{model.name}: prior covariance")
    raise PpoeError(f"{model.name}: the prior fails the compiled update's check but passes check_pose / "
                    "check_noise_covariance")  # pragma: no cover - the two apply the same rules


def _result(k: Any, status: int, buf: np.ndarray, iout: np.ndarray, model: Any, X0: np.ndarray, P0: np.ndarray,
            z: Any, m: int, max_iterations: int, gate: float) -> UpdateResult:
    """The :class:`UpdateResult` of a finished kernel run, or the error its status code means."""
    T, cov, y0, S0, res, gain, H, corr, steps, fout = k.output_views(buf, m, max_iterations)
    if status == 4:
        _raise_prior(model, X0, P0)
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
