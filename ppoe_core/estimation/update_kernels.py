"""Compiled (numba) iterated LG-EKF update for the tag-bearing and contact-plane models: one call per measurement.

The same algorithm as :func:`ppoe_core.estimation.fusion.iterated_update` (module docstring there: eq. 19-24,
gain ``K = P H^T S^-1``, Joseph form, prior moved to the iterate with ``Jr^-1``, posterior moved with ``Jr``),
with the linearisations of :class:`~ppoe_core.estimation.measurements.TagBearingModel` and
:class:`~ppoe_core.estimation.measurements.ContactPlaneModel` written for one point at a time, and the SE(3)
functions of :mod:`ppoe_core.lie.kernels`.  The Python wrapper (``fusion._compiled_update``) allocates the
outputs, turns the status codes below into the project's errors and builds the ``UpdateResult``; it falls back to
the Python path (which raises the exact message) for a prior that fails a check here.

Status codes returned by :func:`update_kernel`:
``0`` accepted, ``1`` rejected by the gate, ``2`` point ``ierr`` behind the camera (its depth in ``ferr``),
``3`` innovation covariance not positive definite (leading minor ``ierr``), ``4`` the prior pose or covariance
fails its check, ``5`` the measurement has NaN/inf.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ppoe_core.lie.kernels import (
    mat_mul,
    mat_mul_t,
    sandwich,
    se3_exp_one,
    se3_inverse_one,
    se3_log_one,
    se3_mul,
    se3_right_jacobian_inv_one,
    se3_right_jacobian_one,
)

__all__ = ["KIND_TAG", "KIND_CONTACT", "update_kernel", "buffer_size", "output_views"]

#: model kinds
KIND_TAG = 0
KIND_CONTACT = 1


# --------------------------------------------------------------------------- linearisations
@njit(cache=True)
def _project(p: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool, uv: np.ndarray, J: np.ndarray) -> None:
    """One camera point ``p`` (3,) -> ``uv`` (2,) and ``J = d uv / d p`` (2, 3), as
    :func:`ppoe_core.estimation.camera.project_points_jacobian` (normalised or plumb_bob pixels)."""
    X, Y, Z = p[0], p[1], p[2]
    x, y = X / Z, Y / Z
    jp00, jp02, jp11, jp12 = 1 / Z, -X / Z**2, 1 / Z, -Y / Z**2
    if not pixel:
        uv[0], uv[1] = x, y
        J[0, 0], J[0, 1], J[0, 2] = jp00, 0.0, jp02
        J[1, 0], J[1, 1], J[1, 2] = 0.0, jp11, jp12
        return
    k1, k2, p1, p2, k3 = D[0], D[1], D[2], D[3], D[4]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drad = k1 + 2 * k2 * r2 + 3 * k3 * r2**2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    d00 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    d01 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    d11 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    uv[0] = xd * K[0, 0] + yd * K[0, 1] + K[0, 2]
    uv[1] = xd * K[1, 0] + yd * K[1, 1] + K[1, 2]
    for i in range(2):
        a0 = K[i, 0] * d00 + K[i, 1] * d01  # (A Jd)[i, :]
        a1 = K[i, 0] * d01 + K[i, 1] * d11
        J[i, 0] = a0 * jp00
        J[i, 1] = a1 * jp11
        J[i, 2] = a0 * jp02 + a1 * jp12


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
        _project(pc[i], K, D, pixel, uv, J)
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
def _linearize(kind: int, X: np.ndarray, G: np.ndarray, pts: np.ndarray, K: np.ndarray, D: np.ndarray,
               pixel: bool, extra: bool, min_depth: float, h: np.ndarray, H: np.ndarray, M: np.ndarray) -> int:
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
def _cholesky(S: np.ndarray, L: np.ndarray) -> int:
    """Lower Cholesky factor of ``S`` into ``L``; returns 0, or the 1-based leading minor that is not positive."""
    n = S.shape[0]
    L[:, :] = 0.0
    for j in range(n):
        s = S[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return j + 1
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = S[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    return 0


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
    return _cholesky(A, L) == 0


@njit(cache=True)
def _spd(P: np.ndarray) -> np.ndarray:
    """Symmetrise and lift tiny negative eigenvalues to a floor, as ``fusion._spd``."""
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
    """The checks of ``fusion.check_pose`` and ``fusion.check_noise_covariance`` (6x6), without messages."""
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
def _reorthonormalise(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3), as ``fusion._reorthonormalise``."""
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
    """``e = Log(X_i^-1 X_0)`` into ``e`` and ``P_i = Jr^-1(e) P_0 Jr^-T(e)``, as ``fusion._prior_at``."""
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
    """Joseph form ``(I-KH) P (I-KH)^T + K MRM K^T``, moved with ``Jr(d)``, as ``fusion._posterior_covariance``."""
    A = np.eye(6) - mat_mul(K, H)
    P = sandwich(A, Pi) + sandwich(K, MRM)
    if transport:
        J = np.empty((6, 6))
        se3_right_jacobian_one(d, J)
        P = sandwich(J, P)
    return _spd(P)


@njit(cache=True)
def _posterior_cost(r: np.ndarray, MRM: np.ndarray, corr: np.ndarray, P0: np.ndarray) -> float:
    """``r+^T (M R M^T)^-1 r+ + d^T P^+ d``, as ``updater.posterior_cost`` (NaN if ``M R M^T`` is singular)."""
    L = np.empty_like(MRM)
    if _cholesky(0.5 * (MRM + MRM.T), L) != 0:
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
def _finish(kind: int, Xi: np.ndarray, X0: np.ndarray, P0: np.ndarray, z: np.ndarray, R: np.ndarray,
            G: np.ndarray, pts: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool, extra: bool,
            min_depth: float, want_cost: bool, T_out: np.ndarray, res: np.ndarray, corr: np.ndarray,
            fout: np.ndarray, iout: np.ndarray) -> int:
    """Re-orthonormalised estimate, post-fit residual, correction ``Log(X_0^-1 X)`` and the posterior cost."""
    Xf = _reorthonormalise(Xi)
    m = z.shape[0]
    h = np.empty(m)
    H = np.empty((m, 6))
    M = np.empty((m, R.shape[0]))
    bad = _linearize(kind, Xf, G, pts, K, D, pixel, extra, min_depth, h, H, M)
    if bad >= 0:
        iout[2], fout[2] = bad, h[0]
        return 2
    for i in range(m):
        res[i] = z[i] - h[i]
    Xinv = np.empty((4, 4))
    E = np.empty((4, 4))
    se3_inverse_one(X0, Xinv)
    se3_mul(Xinv, Xf, E)
    se3_log_one(E, corr)
    fout[1] = _posterior_cost(res, _mrm(M, R), corr, P0) if want_cost else math.nan
    T_out[:, :] = Xf
    return 0


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
def update_kernel(kind: int, X0: np.ndarray, P0_in: np.ndarray, z: np.ndarray, R: np.ndarray, G: np.ndarray,
                  pts: np.ndarray, K: np.ndarray, D: np.ndarray, pixel: bool, extra: bool, min_depth: float,
                  max_it: int, step_tol: float, gate: float, transport: bool, want_cost: bool, buf: np.ndarray,
                  iout: np.ndarray) -> int:
    """The iterated update of ``fusion.iterated_update`` for one tag / contact measurement (module docstring).

    ``R`` is the checked noise covariance, ``G`` the model's ``T_camera_ref`` / ``T_plane_ref``, ``pts`` its points
    (n, 3), ``gate`` the NIS threshold (``inf``: no gating).  Outputs are written into ``buf`` (zeros of
    :func:`buffer_size`, laid out by :func:`output_views`) and ``iout = [iterations, converged, error index]``.
    """
    m = z.shape[0]
    T_out, cov_out, y0, S0, res, gain, H_last, corr, steps, fout = output_views(buf, m, max_it)
    fout[:] = np.nan
    if not _prior_ok(X0, P0_in):
        return 4
    if not np.all(np.isfinite(z)):
        return 5
    P0 = 0.5 * (P0_in + P0_in.T)
    h = np.empty(m)
    H = np.empty((m, 6))
    M = np.empty((m, R.shape[0]))
    L = np.empty((m, m))
    e = np.empty(6)
    E = np.empty((4, 4))
    Xi = X0.copy()
    Xn = np.empty((4, 4))
    for it in range(1, max_it + 1):
        bad = _linearize(kind, Xi, G, pts, K, D, pixel, extra, min_depth, h, H, M)
        if bad >= 0:
            iout[2], fout[2] = bad, h[0]
            return 2
        r = z - h
        Pi = _prior_at(Xi, X0, P0, it == 1, e)
        MRM = _mrm(M, R)
        HP = mat_mul(H, Pi)
        S = mat_mul_t(HP, H) + MRM
        S = 0.5 * (S + S.T)
        minor = _cholesky(S, L)
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
        se3_exp_one(d, E)
        se3_mul(Xi, E, Xn)
        steps[it - 1] = math.sqrt(np.sum(d * d))
        if steps[it - 1] < step_tol or it == max_it:
            iout[0], iout[1] = it, steps[it - 1] < step_tol
            cov_out[:, :] = _posterior(Kg, H, Pi, MRM, d, transport)
            gain[:, :], H_last[:, :] = Kg, H
            break
        Xi[:, :] = Xn
    return _finish(kind, Xn, X0, P0, z, R, G, pts, K, D, pixel, extra, min_depth, want_cost, T_out, res, corr,
                   fout, iout)
