"""THE iterated LG-EKF update on SE(3) (compiled, numba): paper eq. 19-24, gain of docs/conventions.md sec. 1.

One call of :func:`update_kernel` runs the whole update for the models whose linearisation is compiled here (the
tag bearing and the contact plane models: :data:`KIND_TAG`, :data:`KIND_CONTACT`).  Any other model
(:data:`KIND_EXTERNAL`: tracker points, 6D poses, accelerometers, chained or selected ones, numerical Jacobians)
runs the same loop with its linearisation given from outside: the kernel returns :data:`NEED_LINEARISATION` with the
pose to linearise at in the output buffer, the caller (:func:`ppoe_core.estimation.compiled_update.run_update`)
evaluates the model there and calls it again (the state of the loop lives in the buffers).  So the algorithm is
written once:

* prior seen from the iterate ``X_i``: ``e_i = Log(X_i^-1 X_0)``, ``P_i = Jr^-1(e_i) P_0 Jr^-T(e_i)``;
* innovation ``y_i = r_i - H_i e_i``, ``S_i = H_i P_i H_i^T + M_i R M_i^T`` (Cholesky, never inverted), gain
  ``K_i = P_i H_i^T S_i^-1``, step ``d_i = e_i + K_i y_i``, ``X_{i+1} = X_i Exp(d_i)``, until ``|d_i| <
  step_tolerance`` or ``max_iterations``; the NIS at the prior gates the measurement (iteration 1);
* covariance in Joseph form, moved to the new estimate with ``Jr(d)``, symmetrised and floored (:func:`spd`); the
  estimate's rotation re-orthonormalised (:func:`reorthonormalise`);
* the post-fit residual, the correction ``Log(X_0^-1 X)`` and the posterior cost (:func:`posterior_cost`).

The module docstring of :mod:`ppoe_core.estimation.fusion` states the approximations.  The numpy reference the tests
compare with is ``test/update_reference.py``.

Status codes returned by :func:`update_kernel`:
``0`` accepted, ``1`` rejected by the gate, ``2`` point ``ierr`` behind the camera (its depth in ``ferr``),
``3`` innovation covariance not positive definite (leading minor ``ierr``), ``4`` the prior pose or covariance
fails its check, ``5`` the measurement has NaN/inf, ``6`` (:data:`NEED_LINEARISATION`) give the linearisation at
``T`` of the output buffer and call again.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ppoe_core.estimation.camera_kernel import project_one
from ppoe_core.estimation.update_types import KIND_CONTACT, KIND_TAG
from ppoe_core.lie.kernels import (
    cholesky_into, mat_mul, mat_mul_t, sandwich, se3_exp_one, se3_inverse_one, se3_log_one, se3_mul,
    se3_right_jacobian_inv_one, se3_right_jacobian_one,
)

__all__ = ["KIND_TAG", "KIND_CONTACT", "KIND_EXTERNAL", "NEED_LINEARISATION", "update_kernel", "buffer_size",
           "output_views", "linearize", "spd", "reorthonormalise", "posterior_cost"]

#: a model whose linearisation the caller gives (KIND_TAG, KIND_CONTACT: compiled here, update_types)
KIND_EXTERNAL = 2
#: status: linearise the model at ``T`` of the output buffer and call again
NEED_LINEARISATION = 6


# --------------------------------------------------------------------------- linearisations
@njit(cache=True)
def _tag_linearize(X: np.ndarray, G: np.ndarray, pts: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool,
                   extra: bool, min_depth: float, h: np.ndarray, H: np.ndarray, M: np.ndarray) -> int:
    """``h``, ``H``, ``M`` of the tag model at ``X = T_ref_tool`` (``G = T_camera_ref``); returns -1, or the index of
    the first point closer than ``min_depth`` (then ``h[0]`` holds its depth)."""
    T = np.empty((4, 4))
    se3_mul(G, X, T)
    n = pts.shape[0]
    pc = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            pc[i, j] = pts[i, 0] * T[j, 0] + pts[i, 1] * T[j, 1] + pts[i, 2] * T[j, 2] + T[j, 3]
    for i in range(n):
        if pc[i, 2] < min_depth:
            h[0] = pc[i, 2]
            return i
    uv = np.empty(2)
    J = np.empty((2, 3))
    M[:, :] = 0.0
    for i in range(n):
        project_one(pc[i], K, D, pixel, uv, J)
        px, py, pz = pts[i, 0], pts[i, 1], pts[i, 2]
        for r in range(2):
            row = 2 * i + r
            h[row] = uv[r]
            M[row, row] = 1.0
            for c in range(3):  # J R [I, -[p]x]
                JR = J[r, 0] * T[0, c] + J[r, 1] * T[1, c] + J[r, 2] * T[2, c]
                H[row, c] = JR
            a0 = J[r, 0] * T[0, 0] + J[r, 1] * T[1, 0] + J[r, 2] * T[2, 0]
            a1 = J[r, 0] * T[0, 1] + J[r, 1] * T[1, 1] + J[r, 2] * T[2, 1]
            a2 = J[r, 0] * T[0, 2] + J[r, 1] * T[1, 2] + J[r, 2] * T[2, 2]
            H[row, 3] = -(a1 * pz - a2 * py)
            H[row, 4] = -(-a0 * pz + a2 * px)
            H[row, 5] = -(a0 * py - a1 * px)
            if extra:  # camera pose noise w: J [-I, [p_c]x]
                m = 2 * n
                qx, qy, qz = pc[i, 0], pc[i, 1], pc[i, 2]
                M[row, m + 0], M[row, m + 1], M[row, m + 2] = -J[r, 0], -J[r, 1], -J[r, 2]
                M[row, m + 3] = J[r, 1] * qz - J[r, 2] * qy
                M[row, m + 4] = -J[r, 0] * qz + J[r, 2] * qx
                M[row, m + 5] = J[r, 0] * qy - J[r, 1] * qx
    return -1


@njit(cache=True)
def _contact_linearize(X: np.ndarray, G: np.ndarray, pts: np.ndarray, extra: bool, h: np.ndarray, H: np.ndarray,
                       M: np.ndarray) -> int:
    """``h``, ``H``, ``M`` of the contact-plane model at ``X = T_ref_tool`` (``G = T_plane_ref``)."""
    T = np.empty((4, 4))
    se3_mul(G, X, T)
    p0, p1, p2 = pts[0, 0], pts[0, 1], pts[0, 2]
    q = np.empty(3)
    for j in range(3):
        q[j] = T[j, 0] * p0 + T[j, 1] * p1 + T[j, 2] * p2 + T[j, 3]
    h[0] = q[2]
    a0, a1, a2 = T[2, 0], T[2, 1], T[2, 2]
    H[0, 0], H[0, 1], H[0, 2] = a0, a1, a2
    H[0, 3] = -(a1 * p2 - a2 * p1)
    H[0, 4] = -(-a0 * p2 + a2 * p0)
    H[0, 5] = -(a0 * p1 - a1 * p0)
    M[0, :] = 0.0
    M[0, 2] = -1.0
    M[0, 3], M[0, 4], M[0, 5] = -q[1], q[0], 0.0
    if extra:
        M[0, 6] = 1.0
    return -1


@njit(cache=True)
def linearize(kind: int, X: np.ndarray, G: np.ndarray, pts: np.ndarray, K: np.ndarray, D: np.ndarray,
              pixel: bool, extra: bool, min_depth: float, h: np.ndarray, H: np.ndarray, M: np.ndarray) -> int:
    """``h(X)``, ``H``, ``M`` of a compiled model kind (the measurement models' own ``linearize`` calls this);
    returns -1, or the index of the first point closer than ``min_depth`` (its depth in ``h[0]``)."""
    if kind == KIND_TAG:
        return _tag_linearize(X, G, pts, K, D, pixel, extra, min_depth, h, H, M)
    return _contact_linearize(X, G, pts, extra, h, H, M)


# --------------------------------------------------------------------------- linear algebra
@njit(cache=True)
def _nonzeros(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column indices of the non-zeros of each row of ``A`` (``idx[i, :cnt[i]]``)."""
    m, k = A.shape
    idx = np.empty((m, k), dtype=np.int64)
    cnt = np.zeros(m, dtype=np.int64)
    for i in range(m):
        for j in range(k):
            if A[i, j] != 0.0:
                idx[i, cnt[i]] = j
                cnt[i] += 1
    return idx, cnt


@njit(cache=True)
def _mrm(M: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``M R M^T`` over the non-zeros of ``M`` and ``R`` (per row of the tag model one identity entry and the
    camera block; ``R`` block-diagonal): the sums of the dense product without its zero terms, symmetric."""
    m, k = M.shape
    im, cm = _nonzeros(M)
    ir, cr = _nonzeros(R)
    MR = np.zeros((m, k))
    for i in range(m):
        for q in range(cm[i]):
            j = im[i, q]
            a = M[i, j]
            for p in range(cr[j]):
                c = ir[j, p]
                MR[i, c] += a * R[j, c]
    out = np.empty((m, m))
    for i in range(m):
        for j in range(i, m):
            s = 0.0
            for q in range(cm[j]):
                c = im[j, q]
                s += MR[i, c] * M[j, c]
            out[i, j] = s
            out[j, i] = s
    return out


@njit(cache=True)
def _cho_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``S^-1 B`` for ``S = L L^T``, ``B`` (n, c)."""
    n, c = B.shape
    X = B.copy()
    for col in range(c):
        for i in range(n):
            s = X[i, col]
            for k in range(i):
                s -= L[i, k] * X[k, col]
            X[i, col] = s / L[i, i]
        for i in range(n - 1, -1, -1):
            s = X[i, col]
            for k in range(i + 1, n):
                s -= L[k, i] * X[k, col]
            X[i, col] = s / L[i, i]
    return X


@njit(cache=True)
def _pd_above(P: np.ndarray, c: float) -> bool:
    """True if the Cholesky factorisation of ``P - c I`` succeeds (every eigenvalue of ``P`` above ``c``, up to
    round-off); a quick test before an eigen-decomposition."""
    n = P.shape[0]
    L = np.zeros((n, n))
    A = P.copy()
    for i in range(n):
        A[i, i] -= c
    return cholesky_into(A, L) == 0


@njit(cache=True)
def spd(P: np.ndarray) -> np.ndarray:
    """Symmetrise ``P`` and lift tiny negative eigenvalues (round-off) to the floor ``1e-15 max eigenvalue``."""
    P = 0.5 * (P + P.T)
    if _pd_above(P, 1e-15 * np.trace(P)):  # smallest eigenvalue > 1e-15 trace >= the floor: nothing to lift
        return P
    w, V = np.linalg.eigh(P)
    floor = 1e-15 * max(w.max(), 1e-300)
    if w[0] < floor:
        w = np.maximum(w, floor)
        P = (V * w) @ V.T
        P = 0.5 * (P + P.T)
    return P


@njit(cache=True)
def _prior_ok(X0: np.ndarray, P0: np.ndarray) -> bool:
    """The checks of :func:`ppoe_core.estimation.checks.check_pose` and
    :func:`~ppoe_core.estimation.checks.check_noise_covariance` (6x6), without messages."""
    if not (np.all(np.isfinite(X0)) and np.all(np.isfinite(P0))):
        return False
    R = np.ascontiguousarray(X0[:3, :3])
    RtR = mat_mul(R.T.copy(), R)
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            if not abs(RtR[i, j] - e) <= 1e-6 + 1e-5 * e:
                return False
    det = R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]) - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0]) \
        + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0])
    if det < 0:
        return False
    for j in range(4):
        e = 1.0 if j == 3 else 0.0
        if not abs(X0[3, j] - e) <= 1e-8 + 1e-5 * e:
            return False
    scale = max(np.abs(P0).max(), 1e-300)
    if np.abs(P0 - P0.T).max() > 1e-9 * scale:
        return False
    C = 0.5 * (P0 + P0.T)
    lim = 1e-12 * scale + 1e-300
    if _pd_above(C, -lim):  # smallest eigenvalue > -lim: passes without the eigenvalues
        return True
    return np.linalg.eigvalsh(C).min() >= -lim


@njit(cache=True)
def reorthonormalise(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (its polar factor ``U V^T``; one Newton-Schulz step for a
    deviation below 1e-8): guards against round-off drift."""
    out = T.copy()
    R = np.ascontiguousarray(T[:3, :3])
    E = R.T @ R
    dev = 0.0
    for i in range(3):
        for j in range(3):
            dev = max(dev, abs(E[i, j] - (1.0 if i == j else 0.0)))
    if dev < 1e-8:  # one Newton-Schulz step R (3 I - R^T R) / 2: the polar factor U V^T to O(dev^2)
        out[:3, :3] = R @ (1.5 * np.eye(3) - 0.5 * E)
        return out
    U, _, Vt = np.linalg.svd(R)
    out[:3, :3] = U @ Vt
    return out


# --------------------------------------------------------------------------- the update
@njit(cache=True)
def _prior_at(Xi: np.ndarray, X0: np.ndarray, P0: np.ndarray, first: bool, e: np.ndarray) -> np.ndarray:
    """The prior seen from the iterate: ``e = Log(X_i^-1 X_0)`` into ``e`` and ``P_i = Jr^-1(e) P_0 Jr^-T(e)``."""
    if first:
        e[:] = 0.0
        return P0
    Xinv = np.empty((4, 4))
    D = np.empty((4, 4))
    se3_inverse_one(Xi, Xinv)
    se3_mul(Xinv, X0, D)
    se3_log_one(D, e)
    J = np.empty((6, 6))
    se3_right_jacobian_inv_one(e, J)
    return sandwich(J, P0)


@njit(cache=True)
def _posterior(K: np.ndarray, H: np.ndarray, Pi: np.ndarray, MRM: np.ndarray, d: np.ndarray,
               transport: bool) -> np.ndarray:
    """Joseph form ``(I-KH) P (I-KH)^T + K MRM K^T`` (eq. 23), moved with ``Jr(d)`` to the new estimate."""
    A = np.eye(6) - mat_mul(K, H)
    P = sandwich(A, Pi) + sandwich(K, MRM)
    if transport:
        J = np.empty((6, 6))
        se3_right_jacobian_one(d, J)
        P = sandwich(J, P)
    return spd(P)


@njit(cache=True)
def posterior_cost(r: np.ndarray, MRM: np.ndarray, corr: np.ndarray, P0: np.ndarray) -> float:
    """Cost of an iterated update's solution, ``r+^T (M R M^T)^-1 r+ + d^T P^+ d``: post-fit residual ``r+``, the
    correction ``d = Log(X_0^-1 X+)`` (tangent at the prior), ``P^+`` the pseudo-inverse of the prior covariance
    (eigenvalues above ``1e-12`` of the largest).  ``chi2(m)``-distributed for a linear Gaussian model (then equal to
    the prior NIS); NaN if ``M R M^T`` is not positive definite."""
    L = np.empty_like(MRM)
    if cholesky_into(0.5 * (MRM + MRM.T), L) != 0:
        return math.nan
    u = _cho_solve(L, r.reshape(-1, 1))
    s, U = np.linalg.eigh(0.5 * (P0 + P0.T))
    lim = 1e-12 * max(s.max(), 1e-300)
    out = 0.0
    for i in range(r.shape[0]):
        out += r[i] * u[i, 0]
    acc = 0.0
    for k in range(6):
        if s[k] > lim:
            du = U[0, k] * corr[0] + U[1, k] * corr[1] + U[2, k] * corr[2] + U[3, k] * corr[3] \
                + U[4, k] * corr[4] + U[5, k] * corr[5]
            acc += du * (du / s[k])
    return out + acc


@njit(cache=True)
def _finish(Xf: np.ndarray, X0: np.ndarray, P0: np.ndarray, res: np.ndarray, MRM: np.ndarray, want_cost: bool,
            corr: np.ndarray, fout: np.ndarray) -> None:
    """The correction ``Log(X_0^-1 X_f)`` and the posterior cost at the final estimate (``res``: its residual)."""
    Xinv = np.empty((4, 4))
    E = np.empty((4, 4))
    se3_inverse_one(X0, Xinv)
    se3_mul(Xinv, Xf, E)
    se3_log_one(E, corr)
    fout[1] = posterior_cost(res, MRM, corr, P0) if want_cost else math.nan


def buffer_size(m: int, max_it: int) -> int:
    """Length of the float output buffer of :func:`update_kernel` (see :func:`output_views`)."""
    return 16 + 36 + m + m * m + m + 12 * m + 6 + max_it + 3


@njit(cache=True)
def output_views(buf: np.ndarray, m: int, max_it: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                              np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                              np.ndarray, np.ndarray]:
    """The outputs in the float buffer: ``T (4, 4), cov (6, 6), y0 (m,), S0 (m, m), residual (m,), gain (6, m),
    H (m, 6), correction (6,), steps (max_it,), fout = [nis, posterior cost, error value]``."""
    sizes = (16, 36, m, m * m, m, 6 * m, 6 * m, 6, max_it, 3)
    o = np.zeros(11, dtype=np.int64)
    for i in range(10):
        o[i + 1] = o[i] + sizes[i]
    return (buf[o[0]:o[1]].reshape(4, 4), buf[o[1]:o[2]].reshape(6, 6), buf[o[2]:o[3]],
            buf[o[3]:o[4]].reshape(m, m), buf[o[4]:o[5]], buf[o[5]:o[6]].reshape(6, m), buf[o[6]:o[7]].reshape(m, 6),
            buf[o[7]:o[8]], buf[o[8]:o[9]], buf[o[9]:o[10]])


@njit(cache=True)
def _residual(kind: int, X: np.ndarray, z: np.ndarray, G: np.ndarray, pts: np.ndarray, K: np.ndarray,
              D: np.ndarray, pixel: bool, extra: bool, min_depth: float, ext_r: np.ndarray, ext_H: np.ndarray,
              ext_M: np.ndarray, r: np.ndarray, H: np.ndarray, M: np.ndarray, iout: np.ndarray,
              fout: np.ndarray) -> int:
    """The residual ``z ominus h(X)``, ``H`` and ``M`` at ``X``: compiled (``-1``, or status 2), or the caller's."""
    if kind == KIND_EXTERNAL:
        r[:], H[:, :], M[:, :] = ext_r, ext_H, ext_M
        return -1
    bad = linearize(kind, X, G, pts, K, D, pixel, extra, min_depth, r, H, M)
    if bad >= 0:
        iout[2], fout[2] = bad, r[0]
        return 2
    for i in range(r.shape[0]):
        r[i] = z[i] - r[i]
    return -1


@njit(cache=True)
def _step(it: int, Xi: np.ndarray, X0: np.ndarray, P0: np.ndarray, r: np.ndarray, H: np.ndarray, M: np.ndarray,
          R: np.ndarray, max_it: int, step_tol: float, gate: float, transport: bool, buf: np.ndarray,
          iout: np.ndarray, m: int) -> int:
    """Iteration ``it`` at ``Xi`` with its residual ``r``, ``H``, ``M``: the next iterate into ``Xi``; returns -1 to
    go on, 0 when done (covariance, gain written), 1 rejected by the gate, 3 ``S`` not positive definite."""
    _, cov_out, y0, S0, _, gain, H_last, _, steps, fout = output_views(buf, m, max_it)
    e = np.empty(6)
    Pi = _prior_at(Xi, X0, P0, it == 1, e)
    MRM = _mrm(M, R)
    HP = mat_mul(H, Pi)
    S = mat_mul_t(HP, H) + MRM
    S = 0.5 * (S + S.T)
    L = np.empty((m, m))
    minor = cholesky_into(S, L)
    if minor:
        iout[2] = minor
        return 3
    if it == 1:
        y0[:], S0[:, :], H_last[:, :] = r, S, H
        fout[0] = np.sum(r * _cho_solve(L, r.reshape(-1, 1))[:, 0])
        if not fout[0] <= gate:
            return 1
    Kg = _cho_solve(L, HP).T.copy()  # P H^T S^-1
    d = e + mat_mul(Kg, (r - mat_mul(H, e.reshape(6, 1))[:, 0]).reshape(-1, 1))[:, 0]
    E = np.empty((4, 4))
    Xn = np.empty((4, 4))
    se3_exp_one(d, E)
    se3_mul(Xi, E, Xn)
    Xi[:, :] = Xn
    steps[it - 1] = math.sqrt(np.sum(d * d))
    if steps[it - 1] < step_tol or it == max_it:
        iout[0], iout[1] = it, steps[it - 1] < step_tol
        cov_out[:, :] = _posterior(Kg, H, Pi, MRM, d, transport)
        gain[:, :], H_last[:, :] = Kg, H
        return 0
    return -1


@njit(cache=True)
def update_kernel(kind: int, X0: np.ndarray, P0_in: np.ndarray, z: np.ndarray, R: np.ndarray, G: np.ndarray,
                  pts: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool, extra: bool, min_depth: float,
                  max_it: int, step_tol: float, gate: float, transport: bool, want_cost: bool, buf: np.ndarray,
                  iout: np.ndarray, ext_r: np.ndarray, ext_H: np.ndarray, ext_M: np.ndarray) -> int:
    """The iterated update (module docstring), or its next part for :data:`KIND_EXTERNAL`.

    ``R`` is the checked noise covariance, ``G`` the model's ``T_camera_ref`` / ``T_plane_ref``, ``pts`` its points
    (n, 3), ``gate`` the NIS threshold (``inf``: no gating).  Outputs are written into ``buf`` (zeros of
    :func:`buffer_size`, laid out by :func:`output_views`) and ``iout = [iterations, converged, error index, phase,
    iteration]`` (zeros at the first call; phase 1: iterating, 2: finishing).  For :data:`KIND_EXTERNAL` every call
    after a :data:`NEED_LINEARISATION` brings ``ext_r`` (m,) = ``z ominus h(T)``, ``ext_H`` (m, 6), ``ext_M``
    (m, k) at the ``T`` of the buffer; ``z`` is not read.
    """
    m = z.shape[0]
    T_out, _, _, _, res, _, _, corr, _, fout = output_views(buf, m, max_it)
    r = np.empty(m)
    H = np.empty((m, 6))
    M = np.empty((m, R.shape[0]))
    if iout[3] == 0:
        fout[:] = np.nan
        if not _prior_ok(X0, P0_in):
            return 4
        if kind != KIND_EXTERNAL and not np.all(np.isfinite(z)):
            return 5
        T_out[:, :] = X0
        iout[3], iout[4] = 1, 1
        if kind == KIND_EXTERNAL:
            return NEED_LINEARISATION
    P0 = 0.5 * (P0_in + P0_in.T)
    while iout[3] == 1:
        bad = _residual(kind, T_out, z, G, pts, K, D, pixel, extra, min_depth, ext_r, ext_H, ext_M, r, H, M, iout,
                        fout)
        if bad >= 0:
            return bad
        status = _step(int(iout[4]), T_out, X0, P0, r, H, M, R, max_it, step_tol, gate, transport, buf, iout, m)
        if status > 0:
            return status
        if status == 0:
            T_out[:, :] = reorthonormalise(T_out)
            iout[3] = 2
        else:
            iout[4] += 1
        if kind == KIND_EXTERNAL:
            return NEED_LINEARISATION
    bad = _residual(kind, T_out, z, G, pts, K, D, pixel, extra, min_depth, ext_r, ext_H, ext_M, r, H, M, iout, fout)
    if bad >= 0:
        return bad
    res[:] = r
    _finish(T_out, X0, P0, r, _mrm(M, R), want_cost, corr, fout)
    return 0


