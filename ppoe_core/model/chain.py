"""Compiled kinematic chains of :class:`~ppoe_core.model.ppoe.PPOEModel`: a chain between two frames as a small program
(static transforms, joint motions, perturbation sites; paper eq. 16/17) and its batched evaluation.

Covariance columns are local (tangent space at the chain's end pose, docs/conventions.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.robot.config import ModelConfig
from ppoe_core.robot.urdf import Robot

Array = np.ndarray


# ----------------------------------------------------------------------------
# Small private helpers
# ----------------------------------------------------------------------------


def _rot_z_to(axis: Array) -> Array:
    """A rotation ``Q`` (3, 3) with ``Q @ e_z = axis`` (identity for axis = e_z)."""
    a = np.asarray(axis, dtype=float)
    if np.allclose(a, [0.0, 0.0, 1.0], atol=0.0, rtol=0.0):
        return np.eye(3)
    ez = np.array([0.0, 0.0, 1.0])
    v = np.cross(ez, a)
    s = float(np.linalg.norm(v))
    c = float(a[2])
    if s < 1e-12:  # a = -e_z
        return np.diag([1.0, -1.0, -1.0])
    return lie.so3_exp(v / s * np.arctan2(s, c))


def _rot6(R: Array) -> Array:
    """``blockdiag(R, R)`` = adjoint of a pure rotation."""
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[3:, 3:] = R
    return out


# Levi-Civita tensor: hat(t)[i, j] = sum_k _EPS[i, j, k] t[k]
_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = -1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = 1.0


# ----------------------------------------------------------------------------
# Compiled chain
# ----------------------------------------------------------------------------

#: batch chunk size of the batched path (working set stays in cache)
_CHUNK = 2048

# program op codes
_S, _RZ, _TZ, _D, _SITE = 0, 1, 2, 3, 4


@dataclass
class _Chain:
    """A compiled chain ``frm -> to``.

    ``ops`` is a list of ``(code, arg)``:
      * ``(_S, M)``: multiply by the constant 4x4 ``M``;
      * ``(_RZ, i)`` / ``(_TZ, i)``: rotate about / translate along local z by motion ``i``;
      * ``(_D, k)``: multiply by ``Exp(dxi)`` of effect site ``k`` (effects only);
      * ``(_SITE, k)``: perturbation site ``k`` (covariance columns from the product of
        everything after it).
    """

    frm: str
    to: str
    ops: list
    # motions (one per movable joint on the chain)
    motion_joint: list  # joint name
    motion_master: list  # independent master joint name
    motion_slot: Array  # (n_motion,) index into `masters`
    motion_col: Array  # (n_motion,) index of the master in robot.independent_joints
    motion_mult: Array  # (n_motion,) sign * multiplier
    motion_off: Array  # (n_motion,) sign * offset
    motion_sign: Array  # (n_motion,) +1 down, -1 up
    motion_kind: list  # _RZ or _TZ
    masters: list  # independent joints the chain needs, first-use order
    # perturbation sites
    site_L: list  # (6, r_k) factors in the canonical frame at the site (negated on the
    #               up-branch, where the link enters inverted: Exp(-xi)); the sign only
    #               matters for cross-covariances between chains (fk_multi)
    site_label: list  # "xi:<joint>" / "noise:<joint>"
    L_all: Array  # (m, 6) all factor columns stacked (rows = columns of L_k)
    H_all: Array  # (m, 3, 3) hat of the rotational part of each column
    X_rows: Array  # (m, 2, 3) rows [v^T; w^T] of each column
    col_pos: Array  # (m,) suffix index (site position) of each column
    col_site: Array  # (m,) site index of each column
    col_ids: list  # (m,) (site label, column of its factor): identifies the random source
    site_cols: list  # per site: (LvT (r, 3), LwT (r, 3), H (r, 3, 3), rot_only, c0, c1)
    site_sparse: list  # per site: None (dense) or [(column, v non-zeros, w non-zeros), ...]
    # effect sites
    d_joint: list  # joint name of each _D site
    d_map: list  # (6, 6) map of the joint's dxi into the canonical twist (sign included)
    # single-configuration program
    f_static: Array  # (n_f, 4, 4) factors with identities at motion/D slots
    f_motion_idx: Array  # factor index of each motion
    f_rz: tuple  # (motion indices, factor indices) of the revolute motions
    f_tz: tuple  # (motion indices, factor indices) of the prismatic motions
    f_d_idx: Array  # factor index of each D op
    site_pos: Array  # (n_sites,) number of factors before each site


def _compile(robot: Robot, config: ModelConfig, frm: str, to: str, with_effects: bool) -> _Chain:
    """Build the program of the chain ``frm -> to`` (see :class:`_Chain`)."""
    up, down = robot.chain(frm, to)
    ops: list = []
    pending = np.eye(4)  # constant factor not yet emitted
    has_pending = False

    def static(M: Array) -> None:
        nonlocal pending, has_pending
        pending = pending @ M
        has_pending = True

    def flush() -> None:
        nonlocal pending, has_pending
        if has_pending and not np.array_equal(pending, np.eye(4)):
            ops.append((_S, pending))
        pending = np.eye(4)
        has_pending = False

    motion_joint: list[Any]
    motion_master: list[Any]
    motion_mult: list[Any]
    motion_off: list[Any]
    motion_sign: list[Any]
    motion_kind: list[Any]
    motion_joint, motion_master, motion_mult, motion_off, motion_sign, motion_kind = [], [], [], [], [], []
    site_L: list = []
    site_label: list = []
    d_joint: list = []
    d_map: list = []
    masters: list = []

    def motion(jn: str, sign: float) -> None:
        j = robot.joints[jn]
        if j.mimic_root is not None:
            master, mult, off = j.mimic_root
        else:
            master, mult, off = jn, 1.0, 0.0
        if master not in masters:
            masters.append(master)
        flush()
        kind = _TZ if j.type == "prismatic" else _RZ
        ops.append((kind, len(motion_joint)))
        motion_joint.append(jn)
        motion_master.append(master)
        motion_mult.append(sign * mult)
        motion_off.append(sign * off)
        motion_sign.append(sign)
        motion_kind.append(kind)

    def site(L: Array, label: str) -> None:
        if L.shape[1] == 0:
            return
        flush()
        ops.append((_SITE, len(site_L)))
        site_L.append(L)
        site_label.append(label)

    def dsite(jn: str, M6: Array) -> None:
        if not with_effects:
            return
        flush()
        ops.append((_D, len(d_joint)))
        d_joint.append(jn)
        d_map.append(M6)

    def noise_L(jn: str) -> Array:
        sigma = config.joint_noise.get(jn, 0.0)
        if sigma <= 0.0:
            return np.zeros((6, 0))
        L = np.zeros((6, 1))
        L[2 if robot.joints[jn].type == "prismatic" else 5, 0] = sigma
        return L

    def xi_L(jn: str) -> Array:
        p = config.perturbations.get(jn)
        return np.zeros((6, 0)) if p is None else p.factor

    # up-branch: (O Exp(d) Exp(xi) Q Mz(q) Q^T Exp(n))^-1
    #          = Exp(-n) Q Mz(-q) Q^T Exp(-xi) Exp(-d) O^-1
    #          = Q Exp(-Ad_{Q^T} n) Mz(-q) Exp(-Ad_{Q^T} xi) Exp(-Ad_{Q^T} d) Q^T O^-1
    for jn in up:
        j = robot.joints[jn]
        if j.movable:
            Q = _rot_z_to(j.axis)
            static(lie.from_rt(Q, np.zeros(3)))
            site(-noise_L(jn), "noise:" + jn)  # Exp(-n): already along z in the Q frame
            motion(jn, -1.0)
            site(-_rot6(Q.T) @ xi_L(jn), "xi:" + jn)
            dsite(jn, -_rot6(Q.T))
            static(lie.from_rt(Q.T, np.zeros(3)) @ lie.inverse(j.origin))
        else:
            site(-xi_L(jn), "xi:" + jn)
            dsite(jn, -np.eye(6))
            static(lie.inverse(j.origin))
    # down-branch: O Exp(d) Exp(xi) Q Mz(q) Q^T Exp(n)
    #            = (O Q) Exp(Ad_{Q^T} d) Exp(Ad_{Q^T} xi) Mz(q) Exp(Ad_{Q^T} n) Q^T
    for jn in down:
        j = robot.joints[jn]
        if j.movable:
            Q = _rot_z_to(j.axis)
            static(j.origin @ lie.from_rt(Q, np.zeros(3)))
            dsite(jn, _rot6(Q.T))
            site(_rot6(Q.T) @ xi_L(jn), "xi:" + jn)
            motion(jn, 1.0)
            site(noise_L(jn), "noise:" + jn)
            static(lie.from_rt(Q.T, np.zeros(3)))
        else:
            static(j.origin)
            dsite(jn, np.eye(6))
            site(xi_L(jn), "xi:" + jn)
    flush()

    # stacked low-rank columns
    if site_L:
        L_all = np.concatenate([L.T for L in site_L], axis=0)
        col_site = np.concatenate([np.full(L.shape[1], k) for k, L in enumerate(site_L)]).astype(int)
    else:
        L_all = np.zeros((0, 6))
        col_site = np.zeros(0, dtype=int)

    site_cols = []
    site_sparse: list = []
    c0 = 0
    for L in site_L:
        r = L.shape[1]
        site_cols.append((L[:3].T.copy(), L[3:].T.copy(), lie.hat3(L[3:].T), not np.any(L[:3]), c0, c0 + r))
        if all(np.count_nonzero(L[:, i]) <= 2 for i in range(r)):
            site_sparse.append([
                (c0 + i,
                 tuple((j, float(L[j, i])) for j in range(3) if L[j, i] != 0.0),
                 tuple((j, float(L[3 + j, i])) for j in range(3) if L[3 + j, i] != 0.0))
                for i in range(r)
            ])
        else:
            site_sparse.append(None)
        c0 += r

    # single-config program: factor list
    factors, f_motion_idx, f_d_idx = [], [], []
    site_pos = np.zeros(len(site_L), dtype=int)
    for code, arg in ops:
        if code == _S:
            factors.append(arg)
        elif code in (_RZ, _TZ):
            f_motion_idx.append(len(factors))
            factors.append(np.eye(4))
        elif code == _D:
            f_d_idx.append(len(factors))
            factors.append(np.eye(4))
        else:
            site_pos[arg] = len(factors)
    if not factors:
        factors.append(np.eye(4))
    slot = np.array([masters.index(m) for m in motion_master], dtype=int)
    return _Chain(
        frm=frm,
        to=to,
        ops=ops,
        motion_joint=motion_joint,
        motion_master=motion_master,
        motion_slot=slot,
        motion_col=np.array([robot.independent_joints.index(mj) for mj in motion_master], dtype=int),
        motion_mult=np.array(motion_mult, dtype=float),
        motion_off=np.array(motion_off, dtype=float),
        motion_sign=np.array(motion_sign, dtype=float),
        motion_kind=motion_kind,
        masters=masters,
        site_L=site_L,
        site_label=site_label,
        L_all=L_all,
        H_all=lie.hat3(L_all[:, 3:]),
        X_rows=L_all.reshape(-1, 2, 3).copy(),
        col_pos=site_pos[col_site],
        col_site=col_site,
        col_ids=[(site_label[k], i) for k, L in enumerate(site_L) for i in range(L.shape[1])],
        site_cols=site_cols,
        site_sparse=site_sparse,
        d_joint=d_joint,
        d_map=d_map,
        f_static=np.array(factors),
        f_motion_idx=np.array(f_motion_idx, dtype=int),
        f_rz=(np.array([i for i, k in enumerate(motion_kind) if k == _RZ], dtype=int),
              np.array([f_motion_idx[i] for i, k in enumerate(motion_kind) if k == _RZ], dtype=int)),
        f_tz=(np.array([i for i, k in enumerate(motion_kind) if k == _TZ], dtype=int),
              np.array([f_motion_idx[i] for i, k in enumerate(motion_kind) if k == _TZ], dtype=int)),
        f_d_idx=np.array(f_d_idx, dtype=int),
        site_pos=site_pos,
    )


# ----------------------------------------------------------------------------
# Chain evaluation
# ----------------------------------------------------------------------------


def _eval_single(ch: _Chain, theta: Array, D: Array | None) -> tuple[Array, Array]:
    """One configuration: ``theta`` (n_motion,), ``D`` (n_d, 4, 4) or None.

    Returns ``(T (4, 4), suffixes (n_f + 1, 4, 4))`` with ``suffixes[k]`` = product of the
    factors ``k, k+1, ...`` (``suffixes[n_f]`` = identity, ``suffixes[0]`` = T).
    """
    F = ch.f_static.copy()
    if theta.size:
        rz, fz = ch.f_rz
        if fz.size:
            th = theta[rz]
            c, s = np.cos(th), np.sin(th)
            F[fz, 0, 0] = c
            F[fz, 1, 1] = c
            F[fz, 0, 1] = -s
            F[fz, 1, 0] = s
        tz, ft = ch.f_tz
        if ft.size:
            F[ft, 2, 3] = theta[tz]
    if D is not None and len(ch.f_d_idx):
        F[ch.f_d_idx] = D
    # Hillis-Steele inclusive suffix product (log depth, order-preserving)
    n = F.shape[0]
    S = np.empty((n + 1, 4, 4))
    S[:n] = F
    S[n] = np.eye(4)
    d = 1
    while d < n:
        S[: n - d] = S[: n - d] @ S[d:n]
        d *= 2
    return S[0], S


def _columns(B: Array, LvT: Array, LwT: Array, H: Array, rot_only: bool) -> Array:
    """``Ad_{B^-1} L`` for poses ``B`` as rows ``(3, 4, N)``; returns ``(r, 6, N)``.

    ``Ad_{B^-1} [v; w] = [R^T (v + w x t); R^T w]`` (paper eq. 7 for the inverse pose).
    """
    R = B[:, :3]
    t = B[:, 3]
    r = LwT.shape[0]
    N = B.shape[-1]
    out = np.empty((r, 6, N))
    out[:, 3:] = np.tensordot(LwT, R, axes=1)
    u = np.tensordot(H, t, axes=1)  # (r, 3, N): w x t
    if not rot_only:
        u += LvT[:, :, None]
    out[:, :3] = u[:, 0, None] * R[0] + u[:, 1, None] * R[1] + u[:, 2, None] * R[2]
    return out


# (e_j x t) = sum over (k, sign, l): sign * t_l e_k
_CROSS_E = (((1, -1.0, 2), (2, 1.0, 1)), ((0, 1.0, 2), (2, -1.0, 0)), ((0, -1.0, 1), (1, 1.0, 0)))


def _sparse_column(B: Array, vnz: tuple, wnz: tuple, out: Array) -> None:
    """``Ad_{B^-1} L`` for one column with few non-zeros, written into ``out`` (6, N).

    ``vnz`` / ``wnz``: ``((j, value), ...)`` of the translational / rotational part; the
    result is ``[R^T (v + w x t); R^T w]`` with ``R^T e_j`` = row ``j`` of ``R``.
    """
    R = B[:, :3]
    t = B[:, 3]
    first_v = True
    first_w = True
    for j, b in wnz:
        if first_w:
            np.multiply(R[j], b, out=out[3:])
            first_w = False
        else:
            out[3:] += b * R[j]
        for k, sg, l in _CROSS_E[j]:
            term = (sg * b) * t[l] * R[k]
            if first_v:
                out[:3] = term
                first_v = False
            else:
                out[:3] += term
    for j, a in vnz:
        if first_v:
            np.multiply(R[j], a, out=out[:3])
            first_v = False
        else:
            out[:3] += a * R[j]
    if first_w:
        out[3:] = 0.0
    if first_v:
        out[:3] = 0.0


def _eval_backward(
    ch: _Chain, theta: Array, D: Array | None, want_cov: bool, want_jac: bool
) -> tuple[Array, Array | None, Array | None]:
    """Many configurations, walking the chain backwards with ``B`` = product of the rest.

    At a perturbation site, ``B`` is the paper's "everything after it", so the site's local
    columns are ``Ad_{B^-1} L_k`` (eq. 15/18) without any inverse; at the end ``B = T``.

    Parameters
    ----------
    theta : (n_motion, N)
    D : (n_d, 4, 4, N) or None

    Returns
    -------
    B : (3, 4, N) rows of ``T_frm_to``
    G : (m, 6, N) local covariance columns (``cov = G^T G``) or None
    J : (n_motion, 6, N) local joint-motion columns (unit joint speed, before the sign /
        multiplier) or None
    """
    N = theta.shape[1]
    B: Array | None = None  # None = identity
    G = np.empty((ch.L_all.shape[0], 6, N)) if want_cov else None
    J = np.empty((len(ch.motion_joint), 6, N)) if want_jac else None
    c: Any = None
    s: Any = None
    if theta.size:
        c, s = np.cos(theta), np.sin(theta)

    def ident() -> Array:
        out = np.zeros((3, 4, N))
        out[0, 0] = out[1, 1] = out[2, 2] = 1.0
        return out

    for code, arg in reversed(ch.ops):
        if code == _S:
            if B is None:
                B = np.repeat(arg[:3, :, None], N, axis=2)
            else:
                B = np.tensordot(arg[:3, :3], B, axes=1)
                B[:, 3] += arg[:3, 3, None]
            continue
        if B is None:
            B = ident()
        if code == _RZ or code == _TZ:
            if J is not None:
                if code == _RZ:  # Ad_{B^-1} [0; e_z]: [R^T (e_z x t); R^T e_z]
                    J[arg, 3:] = B[2, :3]
                    J[arg, :3] = B[1, :3] * B[0, 3] - B[0, :3] * B[1, 3]
                else:  # Ad_{B^-1} [e_z; 0]
                    J[arg, :3] = B[2, :3]
                    J[arg, 3:] = 0.0
            if code == _RZ:
                b0 = B[0].copy()
                ci, si = c[arg], s[arg]
                B[0] = ci * b0 - si * B[1]
                B[1] = si * b0 + ci * B[1]
            else:
                B[2, 3] += theta[arg]
        elif code == _D:
            assert D is not None  # a _D step exists only when displacements were given
            Dk = D[arg]
            Bn = np.einsum("ijn,jkn->ikn", Dk[:3, :3], B)
            Bn[:, 3] += Dk[:3, 3]
            B = Bn
        elif G is not None:  # site
            LvT, LwT, H, rot_only, c0, c1 = ch.site_cols[arg]
            sparse = ch.site_sparse[arg]
            if sparse is None:
                G[c0:c1] = _columns(B, LvT, LwT, H, rot_only)
            else:
                for col, vnz, wnz in sparse:
                    _sparse_column(B, vnz, wnz, G[col])
    if B is None:
        B = ident()
    return B, G, J


def _eval_forward(ch: _Chain, theta: Array, D: Array | None, pert: list) -> Array:
    """Forward product of the chain for many configurations with sampled perturbations.

    Used by the Monte-Carlo sampler: every perturbation ``Exp(xi_k)`` is inserted at its
    place (eq. 16-17), nothing is linearised.

    Parameters
    ----------
    theta : (n_motion, N)
    D : (n_d, 4, 4, N) or None
        ``Exp(dxi)`` per effect site.
    pert : list of (4, 4, N)
        ``Exp(xi_k)`` per perturbation site, right-multiplied at the site.

    Returns
    -------
    ndarray, shape (3, 4, N)
        Rows of ``T_frm_to``.
    """
    N = theta.shape[1]
    P = np.zeros((3, 4, N))
    P[0, 0] = P[1, 1] = P[2, 2] = 1.0
    if theta.size:
        c, s = np.cos(theta), np.sin(theta)
    for code, arg in ch.ops:
        if code == _S:
            P = np.einsum("ijn,jk->ikn", P, arg)
        elif code == _RZ:
            p0 = P[:, 0].copy()
            p1 = P[:, 1]
            P[:, 0] = p0 * c[arg] + p1 * s[arg]
            P[:, 1] = p1 * c[arg] - p0 * s[arg]
        elif code == _TZ:
            P[:, 3] += P[:, 2] * theta[arg]
        elif code == _D:
            assert D is not None
            P = _mul_rows(P, D[arg])
        else:  # perturbation site
            P = _mul_rows(P, pert[arg])
    return P


def _exp_batch_last(xi: Array) -> Array:
    """SE(3) ``Exp`` for twists ``(6, N)`` -> ``(4, 4, N)`` (batch last, elementwise).

    Same map as :func:`ppoe_core.lie.exp` (paper eq. 3): ``R = I + A W + B W^2``,
    ``t = (I + B W + C W^2) rho`` with ``A = sin t / t``, ``B = (1 - cos t) / t^2``,
    ``C = (t - sin t) / t^3`` (Taylor series below ``t^2 < 1e-6``) and ``W^2 = w w^T - t^2 I``.
    """
    rho, w = xi[:3], xi[3:]
    N = xi.shape[1]
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    small = t2 < 1e-6
    ts = np.sqrt(np.where(small, 1.0, t2))
    st, ct = np.sin(ts), np.cos(ts)
    A = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, st / ts)
    B = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - ct) / np.where(small, 1.0, t2))
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (ts - st) / (ts * np.where(small, 1.0, t2)))
    out = np.zeros((4, 4, N))
    # W w-cross matrix entries: W[0,1] = -w2, W[0,2] = w1, W[1,2] = -w0
    for i in range(3):
        for j in range(3):
            ww = w[i] * w[j]
            out[i, j] = B * ww
            if i == j:
                out[i, j] += 1.0 - B * t2
    out[0, 1] -= A * w[2]
    out[1, 0] += A * w[2]
    out[0, 2] += A * w[1]
    out[2, 0] -= A * w[1]
    out[1, 2] -= A * w[0]
    out[2, 1] += A * w[0]
    # t = rho + B (w x rho) + C (w x (w x rho)),  w x (w x rho) = w (w.rho) - t2 rho
    wxr = np.stack([w[1] * rho[2] - w[2] * rho[1], w[2] * rho[0] - w[0] * rho[2], w[0] * rho[1] - w[1] * rho[0]])
    wr = w[0] * rho[0] + w[1] * rho[1] + w[2] * rho[2]
    out[:3, 3] = rho + B * wxr + C * (w * wr - t2 * rho)
    out[3, 3] = 1.0
    return out


def _mul_rows(P: Array, E: Array) -> Array:
    """``P @ E`` for pose rows ``P`` (3, 4, N) and poses ``E`` (4, 4, N) (last row 0 0 0 1)."""
    out = np.empty_like(P)
    p0, p1, p2 = P[:, 0], P[:, 1], P[:, 2]
    for k in range(4):
        out[:, k] = p0 * E[0, k] + p1 * E[1, k] + p2 * E[2, k]
    out[:, 3] += P[:, 3]
    return out


# ----------------------------------------------------------------------------
# Covariance pieces
# ----------------------------------------------------------------------------


def _rows_to_T(P: Array) -> Array:
    """``(3, 4, N)`` pose rows -> ``(N, 4, 4)``."""
    N = P.shape[-1]
    T = np.zeros((N, 4, 4))
    T[:, :3, :] = np.moveaxis(P, 2, 0)
    T[:, 3, 3] = 1.0
    return T


def _local_columns_single(ch: _Chain, S: Array) -> Array:
    """``G`` (m, 6): columns ``Ad_{B_k^-1} L_k`` for one configuration (suffixes ``S``).

    ``Ad_{B^-1} [v; w] = [R^T (v + w x t); R^T w]``, evaluated as row vectors
    ``[(v + w x t)^T; w^T] @ R`` for all columns in one stacked product.
    """
    Bk = S[ch.col_pos]  # (m, 4, 4): everything after each column's site
    X = ch.X_rows.copy()  # (m, 2, 3): rows [v^T; w^T]
    X[:, 0] += (ch.H_all @ Bk[:, :3, 3:])[:, :, 0]  # + (w x t)^T
    return (X @ Bk[:, :3, :3]).reshape(-1, 6)
