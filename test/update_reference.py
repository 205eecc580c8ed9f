"""numpy references of the compiled iterated update (:mod:`ppoe_core.estimation.update_kernels`, THE
implementation) and of its pieces: the tests compare the kernel with these, nothing else uses them.  The formulas of
:mod:`ppoe_core.estimation.fusion`'s module docstring (paper eq. 19-24) in scipy / numpy."""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

import lie_reference as ref
from ppoe_core.estimation.checks import check_noise_covariance, check_pose
from ppoe_core.estimation.fusion import UpdateResult, _linearize, chi2_gate


def spd_reference(P: np.ndarray) -> np.ndarray:
    """Symmetrise ``P`` and lift tiny negative eigenvalues (round-off) to a small floor."""
    P = 0.5 * (P + P.T)
    w, V = np.linalg.eigh(P)
    floor = 1e-15 * max(float(np.max(w)), 1e-300)
    if w[0] < floor:
        w = np.maximum(w, floor)
        P = (V * w) @ V.T
        P = 0.5 * (P + P.T)
    return P


def reorthonormalise_reference(T: np.ndarray) -> np.ndarray:
    """The rotation block's polar factor ``U V^T``."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def posterior_cost_reference(obs: Any, T_post: np.ndarray, residual: np.ndarray, correction: np.ndarray,
                             cov_prior: np.ndarray) -> float:
    """``r+^T (M R M^T)^-1 r+ + d^T P^+ d``."""
    _, _, M = _linearize(obs, T_post, "auto")
    MRM = M @ obs.noise_cov @ M.T
    MRM = 0.5 * (MRM + MRM.T)
    r = np.asarray(residual, dtype=float)
    d = np.asarray(correction, dtype=float)
    s, U = np.linalg.eigh(0.5 * (cov_prior + cov_prior.T))
    keep = s > 1e-12 * max(float(s.max()), 1e-300)
    dU = U[:, keep].T @ d
    return float(r @ np.linalg.solve(MRM, r) + dU @ (dU / s[keep]))


def iterated_update_reference(T_prior: Any, cov_prior: Any, z: Any, model: Any, *, max_iterations: int = 10,
                              step_tolerance: float = 1e-10, gate_probability: float | None = 0.9973,
                              transport_covariance: bool = True, jacobians: str = "auto",
                              with_cost: bool = False) -> UpdateResult:
    """The iterated LG-EKF update in numpy (the loop the kernel runs)."""
    X0 = check_pose(T_prior, f"{model.name}: prior pose")
    P0 = check_noise_covariance(cov_prior, 6, f"{model.name}: prior covariance")
    R = check_noise_covariance(model.noise_cov, model.noise_dim, f"{model.name}: noise covariance")
    z = model.validate(z)
    Xi, steps, gate = X0, [], float("inf")
    for it in range(1, max_iterations + 1):
        z_pred, H, M = _linearize(model, Xi, jacobians)
        r = np.asarray(model.residual(z, z_pred), dtype=float)
        if it == 1:
            e, Pi = np.zeros(6), P0
        else:
            e = ref.log_reference(ref.inverse_reference(Xi) @ X0)
            J = ref.left_jacobian_inv_reference(-e)
            Pi = J @ P0 @ J.T
        MRM = M @ R @ M.T
        S = H @ Pi @ H.T + MRM
        S = 0.5 * (S + S.T)
        cho = scipy.linalg.cho_factor(S, lower=True)
        if it == 1:
            y0, S0 = r, S
            nis = float(r @ scipy.linalg.cho_solve(cho, r))
            if gate_probability is not None:
                gate = chi2_gate(int(model.dim), float(gate_probability))
                if not nis <= gate:
                    return UpdateResult(T=X0.copy(), cov=P0.copy(), accepted=False, nis=nis, gate=gate, iterations=0,
                                        converged=False, innovation=r, S=S, residual=r,
                                        gain=np.zeros((6, model.dim)), H=H, correction=np.zeros(6), steps=())
        K = scipy.linalg.cho_solve(cho, H @ Pi).T
        d = e + K @ (r - H @ e)
        X_next = Xi @ ref.exp_reference(d)
        steps.append(float(np.linalg.norm(d)))
        Xi = X_next
        if steps[-1] < step_tolerance or it == max_iterations:
            A = np.eye(6) - K @ H
            P_post = A @ Pi @ A.T + K @ MRM @ K.T
            if transport_covariance:
                Jr = ref.left_jacobian_reference(-d)
                P_post = Jr @ P_post @ Jr.T
            P_post = spd_reference(P_post)
            break
    Xi = reorthonormalise_reference(Xi)
    res = np.asarray(model.residual(z, model.h(Xi)), dtype=float)
    corr = ref.log_reference(ref.inverse_reference(X0) @ Xi)
    cost = posterior_cost_reference(model, Xi, res, corr, P0) if with_cost else float("nan")
    return UpdateResult(T=Xi, cov=P_post, accepted=True, nis=nis, gate=gate, iterations=len(steps),
                        converged=steps[-1] < step_tolerance, innovation=y0, S=S0, residual=res, gain=K, H=H,
                        correction=corr, steps=tuple(steps), cost=cost)


def from_update_reference(anchor: Any, T_post: np.ndarray, cov_post: np.ndarray, T_pre: np.ndarray | None = None,
                          cov_pre: np.ndarray | None = None) -> Any:
    """:meth:`ppoe_core.estimation.corrections.CarriedCorrection.from_update` in numpy."""
    from ppoe_core import lie
    from ppoe_core.estimation.corrections import CarriedCorrection
    from ppoe_core.estimation.prior_buffer import INV_JITTER

    def sym(A: np.ndarray) -> np.ndarray:
        A = np.asarray(A, dtype=np.float64)
        return 0.5 * (A + A.T)

    # work in the range of the prior covariance: directions the prior is certain about carry no correction
    T_pre = anchor.T_base_tool if T_pre is None else np.asarray(T_pre, dtype=np.float64)
    cov_pre = anchor.cov_tool if cov_pre is None else cov_pre
    s0, U = np.linalg.eigh(sym(cov_pre))
    keep0 = s0 > 1e-12 * max(float(s0.max()), 1e-300)
    if not np.any(keep0):
        return None
    U = U[:, keep0]
    info0 = np.diag(1.0 / s0[keep0])
    P1 = U.T @ sym(cov_post) @ U
    P1 = sym(P1) + INV_JITTER * np.eye(P1.shape[0])
    info1 = np.linalg.inv(P1)
    T_anchor_inv = lie.inverse(anchor.T_base_tool)
    T_pre_inv = T_anchor_inv if T_pre is anchor.T_base_tool else lie.inverse(T_pre)
    delta, pre = lie.log(np.stack([T_pre_inv @ T_post, T_anchor_inv @ T_pre]))
    y = info1 @ (U.T @ delta)
    lam, V = np.linalg.eigh(sym(info1 - info0))
    keep = lam > 1e-9 * max(float(np.max(np.abs(lam))), 1e-300)
    if not np.any(keep):
        return None
    lam, V = lam[keep], V[:, keep]
    H = V.T @ U.T
    R = 1.0 / lam
    z = R * (V.T @ y) + H @ pre
    return CarriedCorrection(anchor, H, R, z, T_anchor_inv)
