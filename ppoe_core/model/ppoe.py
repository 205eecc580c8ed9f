"""The Probabilistic Product-of-Exponentials (PPOE) model of a URDF robot.

One link of the chain is (paper eq. 16, CONTRACT section 1)::

    X_i,i+1(q_i) = Exp(p_i) [Exp(dxi_i)] Exp(xi_i) Exp(zeta_i q_i) [Exp(zeta_i n_i)]

with ``Exp(p_i)`` the joint's static URDF origin, ``xi_i ~ N(0, Sigma_i)`` its
perturbation (model YAML ``perturbations``), ``zeta_i`` the unit joint twist,
``n_i ~ N(0, sigma_i^2)`` the optional joint-value noise (``joint_noise``, the
``xi = zeta`` case of paper IV-D) and ``dxi_i`` the non-zero-mean twist of
systematic effects (``effects``, ARCHITECTURE.md "Effects hook").  The chain
between ANY two links ``frm`` and ``to`` goes up from ``frm`` to the lowest common
ancestor (each link inverted: ``(X Exp(xi))^-1 = Exp(-xi) X^-1``, again a
zero-mean perturbation at another place) and down to ``to`` (eq. 17).

Mean pose = the chain with every ``xi = 0``, ``n = 0`` (eq. 17).  Covariance in
the tangent space at ``T_frm_to`` (right perturbation, frame ``to``):

* ``order=2``: paper eq. 15/18, ``Sigma = sum_k Ad_{B_k^-1} Sigma_k Ad_{B_k^-1}^T``
  with ``B_k`` the product of everything after perturbation ``k``;
* ``order=4``: Barfoot & Furgale (2014), "Associating uncertainty with
  three-dimensional poses for use in estimation problems", IEEE T-RO 30(3),
  fourth-order compounding, applied sequentially (chain order) to the local
  perturbations ``Ad_{B_k^-1} xi_k`` (right form: ``X1 Exp(x1) X2 Exp(x2) = X1 X2
  Exp(Ad_{X2^-1} x1) Exp(x2)``).  The fourth-order terms are ported from
  pytransform3d's ``concat_globally_uncertain_transforms`` (BSD-3), written here in
  our ``[rho; theta]`` order, batched.

Implementation notes (speed): every chain ``(frm, to)`` is compiled once into a
program of constant 4x4 factors and joint motions about the local z axis (each
joint frame is rotated by a constant ``Q`` with ``Q e_z = axis``, so a revolute
motion only mixes two columns).  The chain is evaluated from its END: the running
product ``B`` is exactly the paper's "everything after perturbation k", so no
inverse is needed.  The batched path keeps poses as ``(3, 4, N)`` (batch last,
structure of arrays, chunks of ``_CHUNK`` configurations), the single-configuration
path uses a log-depth suffix product over stacked ``(K, 4, 4)`` factors.
Covariances use the low-rank factors ``Sigma_k = L_k L_k^T`` (only the non-zero
sigmas): ``Sigma = G^T G`` with rows ``G = [Ad_{B_k^-1} L_k]_k``.

Effects: ``dq`` of a joint shifts that joint's own motion (a mimic joint does not
inherit its master's ``dq``); ``dxi`` sits right before the joint's ``xi``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Union
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core import lie
from ppoe_core.robot.config import ModelConfig, load_model_config
from ppoe_core.errors import JointValueError, ModelConfigError, UnknownFrameError, UnknownJointError
from ppoe_core.robot.urdf import Robot, parse_urdf

__all__ = ["PPOEModel", "compound_fourth_order"]

Array = np.ndarray
Joints = Union[Mapping[str, ArrayLike], ArrayLike]


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


def _pose(R: Array, t: Array | None = None) -> Array:
    T = np.eye(4)
    T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def _inv(T: Array) -> Array:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


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


def _covop1(A: Array) -> Array:
    """Barfoot's ``<<A>> = -tr(A) I + A`` for ``(..., 3, 3)``."""
    tr = np.trace(A, axis1=-2, axis2=-1)
    return A - tr[..., None, None] * np.eye(3)


def _covop2(A: Array, B: Array) -> Array:
    """Barfoot's ``<<A, B>> = <<A>> <<B>> + <<B A>>``."""
    return _covop1(A) @ _covop1(B) + _covop1(B @ A)


def compound_fourth_order(cov1: ArrayLike, cov2: ArrayLike) -> Array:
    """Covariance of ``Exp(xi1) Exp(xi2)`` to fourth order (Barfoot & Furgale 2014, eq. 55).

    Both covariances live in the SAME tangent space (transport them first, e.g. for right
    perturbations ``X1 Exp(x1) X2 Exp(x2) = X1 X2 Exp(Ad_{X2^-1} x1) Exp(x2)`` gives
    ``cov1 = Ad_{X2^-1} Sigma_1 Ad^T``, ``cov2 = Sigma_2``, both at ``X1 X2``).  Ported from
    pytransform3d's ``_compound_cov_fourth_order_terms`` (which orders twists
    ``[omega; v]``) to our ``[rho; theta]`` order, broadcasting over batch axes.

    Parameters
    ----------
    cov1, cov2 : array_like, shape (..., 6, 6)
        Covariances of the left and the right factor's twist ``[rho; theta]``.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        ``cov1 + cov2 + (A1 cov2 + cov2 A1^T + A2 cov1 + cov1 A2^T) / 12 + B / 4``.
    """
    c1 = np.asarray(cov1, dtype=float)
    c2 = np.asarray(cov2, dtype=float)
    if c1.shape != c2.shape:
        c1, c2 = np.broadcast_arrays(c1, c2)
    rr1, rt1, tt1 = c1[..., :3, :3], c1[..., :3, 3:], c1[..., 3:, 3:]
    rr2, rt2, tt2 = c2[..., :3, :3], c2[..., :3, 3:], c2[..., 3:, 3:]
    tr1 = np.swapaxes(rt1, -1, -2)
    tr2 = np.swapaxes(rt2, -1, -2)
    # all <<.>> and <<., .>> operands stacked, so the work is a handful of numpy calls
    # <<A, B>> = <<A>> <<B>> + <<B A>> for the pairs of Barfoot & Furgale's B blocks:
    #   B_rr = <<tt1, rr2>> + <<tr1, rt2>> + <<rt1, tr2>> + <<rr1, tt2>>
    #   B_rt = <<tt1, tr2>> + <<tr1, tt2>>,   B_tt = <<tt1, tt2>>
    left = np.stack([tt1, tr1, rt1, rr1, tt1, tr1, tt1])
    right = np.stack([rr2, rt2, tr2, tt2, tr2, tt2, tt2])
    ops = _covop1(np.concatenate([left, right, right @ left, np.stack([rt1 + tr1, rt2 + tr2])]))
    n = 7
    pair = ops[:n] @ ops[n:2 * n] + ops[2 * n:3 * n]
    shape = c1.shape
    B = np.empty(shape)
    B[..., :3, :3] = pair[0] + pair[1] + pair[2] + pair[3]
    B12 = pair[4] + pair[5]
    B[..., :3, 3:] = B12
    B[..., 3:, :3] = np.swapaxes(B12, -1, -2)
    B[..., 3:, 3:] = pair[6]
    # A_i = [[<<tt_i>>, <<rt_i + rt_i^T>>], [0, <<tt_i>>]]
    A1 = np.zeros(shape)
    A1[..., :3, :3] = A1[..., 3:, 3:] = ops[0]  # <<tt1>> (left[0] = tt1)
    A1[..., :3, 3:] = ops[3 * n]
    A2 = np.zeros(shape)
    A2[..., :3, :3] = A2[..., 3:, 3:] = ops[n + 3]  # <<tt2>> (right[3] = tt2)
    A2[..., :3, 3:] = ops[3 * n + 1]
    X = A1 @ c2 + A2 @ c1
    return c1 + c2 + (X + np.swapaxes(X, -1, -2)) / 12.0 + B / 4.0


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
            static(_pose(Q))
            site(-noise_L(jn), "noise:" + jn)  # Exp(-n): already along z in the Q frame
            motion(jn, -1.0)
            site(-_rot6(Q.T) @ xi_L(jn), "xi:" + jn)
            dsite(jn, -_rot6(Q.T))
            static(_pose(Q.T) @ _inv(j.origin))
        else:
            site(-xi_L(jn), "xi:" + jn)
            dsite(jn, -np.eye(6))
            static(_inv(j.origin))
    # down-branch: O Exp(d) Exp(xi) Q Mz(q) Q^T Exp(n)
    #            = (O Q) Exp(Ad_{Q^T} d) Exp(Ad_{Q^T} xi) Mz(q) Exp(Ad_{Q^T} n) Q^T
    for jn in down:
        j = robot.joints[jn]
        if j.movable:
            Q = _rot_z_to(j.axis)
            static(j.origin @ _pose(Q))
            dsite(jn, _rot6(Q.T))
            site(_rot6(Q.T) @ xi_L(jn), "xi:" + jn)
            motion(jn, 1.0)
            site(noise_L(jn), "noise:" + jn)
            static(_pose(Q.T))
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
# The model
# ----------------------------------------------------------------------------


class PPOEModel:
    """PPOE forward kinematics of a URDF robot: mean pose and 6x6 covariance between links.

    Parameters
    ----------
    robot : Robot
    config : ModelConfig, optional
        Perturbations, joint noise, effects, ... (None: every joint exact).
    effects : sequence of effect objects, optional
        Overrides ``config.effects``: objects with ``corrections(q, context) -> (dq, dxi)``
        (see ``ppoe_core.model.effects``).  None: built from ``config.effects`` with
        ``ppoe_core.model.effects.effect_from_config`` (imported only if there are any).

    Attributes
    ----------
    robot : Robot
    config : ModelConfig
    joint_names : list[str]
        Independent movable joints (no fixed, no mimic) in URDF order: the order of an
        array ``joints`` argument.
    """

    def __init__(self, robot: Robot, config: ModelConfig | None = None, effects: Sequence[Any] | None = None) -> None:
        self.robot = robot
        self.config = config if config is not None else load_model_config(None, robot)
        self.joint_names: list[str] = robot.independent_joints
        self._index = {n: i for i, n in enumerate(self.joint_names)}
        self._chains: dict[tuple[str, str, bool], _Chain] = {}
        self._effects: list | None = list(effects) if effects is not None else None

    # -- construction -----------------------------------------------------------
    @classmethod
    def from_files(cls, urdf_path: str | os.PathLike, model_yaml_path: str | os.PathLike | None = None) -> PPOEModel:
        """Model from a URDF file and an optional model YAML file."""
        robot = parse_urdf(os.fspath(urdf_path) if not isinstance(urdf_path, os.PathLike) else urdf_path)
        return cls(robot, load_model_config(model_yaml_path, robot))

    @classmethod
    def from_strings(cls, urdf_xml: str, yaml_text_or_dict: str | Mapping | os.PathLike | None = None, *,
                     urdf_source: str | None = None) -> PPOEModel:
        """Model from URDF XML text (e.g. a ``robot_description``) and an optional model YAML.

        Parameters
        ----------
        urdf_xml : str
            URDF XML text (never a path: use :meth:`from_files`).
        yaml_text_or_dict : str, mapping, path-like or None
            Model YAML text, an already-parsed mapping, or a ``pathlib.Path`` (any
            ``os.PathLike``) of a model YAML file; give the path where there is one, so that
            errors name the file and line (text reads as ``<string>``, a mapping as ``<dict>``).
        urdf_source : str, optional
            Where the URDF text came from (e.g. ``"bag run1 /robot_description"``), named in
            errors instead of ``<string>``.

        Raises
        ------
        UrdfError, ModelConfigError, UnknownJointError, UnknownFrameError, CovarianceError
            As :func:`~ppoe_core.robot.urdf.parse_urdf` and :func:`~ppoe_core.robot.config.load_model_config`.
        """
        if not urdf_xml.lstrip().startswith("<"):
            from ppoe_core.errors import UrdfError

            raise UrdfError("from_strings: URDF text must start with '<' (use from_files for paths)")
        robot = parse_urdf(urdf_xml, text_source=urdf_source)
        return cls(robot, load_model_config(yaml_text_or_dict, robot, is_text=True))

    def with_effects(self, effects: Sequence[Any]) -> PPOEModel:
        """A model sharing robot and config whose effects are ``effects`` (e.g. candidates)."""
        return PPOEModel(self.robot, self.config, effects=effects)

    @property
    def effects(self) -> list:
        """The effect objects applied in :meth:`fk` (built lazily from ``config.effects``)."""
        if self._effects is None:
            if self.config.effects:
                from ppoe_core.model import effects as _effects_mod  # lazy: only when effects are configured

                wheres = list(self.config.effect_wheres) + ["effects"] * len(self.config.effects)
                self._effects = [
                    _effects_mod.effect_from_config(e, self.robot, where=f"{wheres[i]}: effects[{i}]")
                    for i, e in enumerate(self.config.effects)
                ]
            else:
                self._effects = []
        return self._effects

    # -- chains -----------------------------------------------------------------
    def _frames(self, frm: str | None, to: str | None) -> tuple[str, str]:
        frames = self.config.frames
        if frm is None:
            frm = frames.base if frames is not None else self.robot.root
        if to is None:
            to = frames.tool if frames is not None else None
            if to is None:
                raise UnknownFrameError(
                    f"no target frame given and the model has no default tool frame (URDF {self.robot.source})"
                )
        self.robot.check_link(frm)
        self.robot.check_link(to)
        return frm, to

    def _chain(self, frm: str, to: str, with_effects: bool) -> _Chain:
        key = (frm, to, with_effects)
        ch = self._chains.get(key)
        if ch is None:
            ch = _compile(self.robot, self.config, frm, to, with_effects)
            self._chains[key] = ch
        return ch

    def chain_joints(self, frm: str | None = None, to: str | None = None) -> list[str]:
        """Independent joints whose values the chain ``frm -> to`` needs."""
        frm, to = self._frames(frm, to)
        return list(self._chain(frm, to, False).masters)

    # -- joint values -----------------------------------------------------------
    def _joint_values(self, joints: Joints, names: list[str], frm: str, to: str) -> tuple[Array, tuple]:
        """Values of ``names`` as ``(len(names), N)`` and the batch shape."""
        if isinstance(joints, Mapping):
            cols = []
            for n in names:
                if n not in joints:
                    raise JointValueError(
                        f"missing value for joint '{n}' (needed by the chain {frm} -> {to}; got "
                        f"{', '.join(sorted(map(str, joints))) or 'no joints'})"
                    )
                try:
                    v = np.asarray(joints[n], dtype=float)
                except (TypeError, ValueError):
                    raise JointValueError(f"joint '{n}': value is not numeric: {joints[n]!r}") from None
                cols.append(v)
            try:
                shape = np.broadcast_shapes(*[c.shape for c in cols]) if cols else ()
            except ValueError:
                raise JointValueError(
                    "joint values have incompatible batch shapes: "
                    + ", ".join(f"{n}{c.shape}" for n, c in zip(names, cols))
                ) from None
            N = int(np.prod(shape)) if shape else 1
            q = np.empty((len(names), N))
            for i, c in enumerate(cols):
                q[i] = np.broadcast_to(c, shape).reshape(N)
        else:
            try:
                arr = np.asarray(joints, dtype=float)
            except (TypeError, ValueError):
                raise JointValueError(f"joint values must be a mapping name -> value or a numeric array, got {type(joints).__name__}") from None
            n_joints = len(self.joint_names)
            if arr.ndim == 0 or arr.shape[-1] != n_joints:
                raise JointValueError(
                    f"joint array must have shape (..., {n_joints}) in model.joint_names order "
                    f"({', '.join(self.joint_names)}), got shape {arr.shape}"
                )
            shape = arr.shape[:-1]
            N = int(np.prod(shape)) if shape else 1
            idx = [self._index[m] for m in names]
            q = np.ascontiguousarray(arr.reshape(N, n_joints)[:, idx].T)
        if not np.all(np.isfinite(q)):
            bad = [names[i] for i in range(len(names)) if not np.all(np.isfinite(q[i]))]
            raise JointValueError(f"NaN or infinite value for joint(s) {', '.join(repr(b) for b in bad)}")
        return q, tuple(shape)

    def _all_joint_dict(self, joints: Joints, shape: tuple) -> dict[str, Array]:
        """Every available joint value (independent given + mimic derived), batch shape ``shape``."""
        out: dict[str, Array] = {}
        if isinstance(joints, Mapping):
            for n in self.joint_names:
                if n in joints:
                    out[n] = np.broadcast_to(np.asarray(joints[n], dtype=float), shape)
        else:
            arr = np.asarray(joints, dtype=float)
            for i, n in enumerate(self.joint_names):
                out[n] = arr[..., i]
        for j in self.robot.joints.values():
            if j.mimic_root is not None and j.mimic_root[0] in out:
                m, mult, off = j.mimic_root
                out[j.name] = mult * out[m] + off
        return out

    # -- core evaluation ----------------------------------------------------------
    def _lookup(self, frm: str | None, to: str | None) -> _Chain:
        with_effects = bool(self._effects) if self._effects is not None else bool(self.effects)
        ch = self._chains.get((frm, to, with_effects))  # type: ignore[arg-type]
        if ch is None:
            frm, to = self._frames(frm, to)
            ch = self._chain(frm, to, with_effects)
            self._chains[(frm, to, with_effects)] = ch
        return ch

    def _single_theta(self, joints: Joints, ch: _Chain) -> Array | None:
        """Lean path: motion values of ONE configuration without effects, or None (use the
        general path, which also produces the error messages)."""
        if self._effects:
            return None
        if type(joints) is np.ndarray:
            if joints.ndim != 1 or joints.shape[0] != len(self.joint_names) or joints.dtype.kind != "f":
                return None
            th = joints[ch.motion_col]
        elif isinstance(joints, dict):
            try:
                th = np.array([joints[n] for n in ch.motion_master], dtype=float)
            except (KeyError, TypeError, ValueError):
                return None
            if th.ndim != 1:
                return None
        else:
            return None
        if not np.isfinite(th).all():
            return None
        return th * ch.motion_mult + ch.motion_off

    def _prepare(self, joints: Joints, frm: str | None, to: str | None, context: Mapping | None):
        """Chain, motion values ``theta`` (n_motion, N), effect factors, batch shape, N."""
        ch = self._lookup(frm, to)
        q, shape = self._joint_values(joints, ch.masters, ch.frm, ch.to)
        N = q.shape[1]
        if len(ch.motion_joint):
            theta = ch.motion_mult[:, None] * q[ch.motion_slot] + ch.motion_off[:, None]
        else:
            theta = np.zeros((0, N))
        D = None
        effects = self._effects
        if effects:
            qd = self._all_joint_dict(joints, shape)
            dq_tot: dict[str, Array] = {}
            dxi_tot: dict[str, Array] = {}
            for eff in effects:
                dq, dxi = eff.corrections(qd, dict(context or {}))
                for k, v in dq.items():
                    dq_tot[k] = dq_tot.get(k, 0.0) + np.broadcast_to(np.asarray(v, dtype=float), shape).reshape(N)
                for k, v in dxi.items():
                    dxi_tot[k] = dxi_tot.get(k, 0.0) + np.broadcast_to(np.asarray(v, dtype=float), shape + (6,)).reshape(N, 6)
            for k in list(dq_tot) + list(dxi_tot):
                if k not in self.robot.joints:
                    raise UnknownJointError(f"an effect returned a correction for unknown joint '{k}'")
            if dq_tot:
                theta = theta.copy()
                for i, jn in enumerate(ch.motion_joint):
                    if jn in dq_tot:
                        theta[i] += ch.motion_sign[i] * dq_tot[jn]
            if len(ch.d_joint):
                D = np.empty((len(ch.d_joint), 4, 4, N))
                for k, jn in enumerate(ch.d_joint):
                    if jn in dxi_tot:
                        D[k] = _exp_batch_last((dxi_tot[jn] @ ch.d_map[k].T).T)
                    else:
                        D[k] = np.eye(4)[:, :, None]
        return ch, theta, D, shape, N

    def fk_mean(self, joints: Joints, frm: str | None = None, to: str | None = None,
                context: Mapping[str, Any] | None = None) -> Array:
        """Mean pose ``T_frm_to`` (eq. 17 with all perturbations zero, effects applied).

        Parameters
        ----------
        joints : mapping name -> float/array, or array (..., n) in ``joint_names`` order
        frm, to : str, optional
            URDF links; default ``config.frames.base`` / ``.tool``.
        context : mapping, optional
            Passed to the effects (e.g. temperature).

        Returns
        -------
        ndarray, shape (..., 4, 4)
        """
        ch = self._lookup(frm, to)
        th = self._single_theta(joints, ch)
        if th is not None:
            return _eval_single(ch, th, None)[0]
        ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
        if N == 1:
            T, _ = _eval_single(ch, theta[:, 0], None if D is None else D[..., 0])
            return T.reshape(shape + (4, 4))
        T = np.zeros((N, 4, 4))
        T[:, 3, 3] = 1.0
        for a in range(0, N, _CHUNK):
            b = min(N, a + _CHUNK)
            B, _, _ = _eval_backward(ch, theta[:, a:b], None if D is None else D[..., a:b], False, False)
            T[a:b, :3, :] = np.moveaxis(B, 2, 0)
        return T.reshape(shape + (4, 4))

    def fk(self, joints: Joints, frm: str | None = None, to: str | None = None, order: int = 2,
           context: Mapping[str, Any] | None = None) -> tuple[Array, Array]:
        """Mean pose and covariance of ``T_frm_to`` (paper eq. 15-18).

        Parameters
        ----------
        joints : mapping name -> float/array, or array (..., n) in ``joint_names`` order
            Names the chain does not use are ignored; mimic joints follow their master.
        frm, to : str, optional
            URDF links (any two links of the tree); default ``config.frames.base`` / ``.tool``.
        order : {2, 4}
            2: paper eq. 15/18; 4: Barfoot & Furgale (2014) fourth-order compounding.
        context : mapping, optional
            Passed to the effects.

        Returns
        -------
        T_frm_to : ndarray, shape (..., 4, 4)
        cov_to : ndarray, shape (..., 6, 6)
            Covariance of ``[rho; theta]`` in the tangent space at ``T_frm_to`` (frame ``to``,
            right perturbation).

        Raises
        ------
        UnknownFrameError, JointValueError, ModelConfigError
        """
        if order != 2 and order != 4:
            raise ModelConfigError(f"fk: order must be 2 or 4, got {order!r}")
        ch = self._lookup(frm, to)
        m = ch.L_all.shape[0]
        th = self._single_theta(joints, ch)
        if th is not None and order == 2:
            T, S = _eval_single(ch, th, None)
            if m == 0:
                return T, np.zeros((6, 6))
            G = _local_columns_single(ch, S)
            return T, G.T @ G
        ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
        if N == 1:
            T, S = _eval_single(ch, theta[:, 0], None if D is None else D[..., 0])
            if m == 0:
                return T.reshape(shape + (4, 4)), np.zeros(shape + (6, 6))
            G = _local_columns_single(ch, S)  # (m, 6)
            cov = G.T @ G if order == 2 else _fourth_order(ch, G[:, None, :])[0]
            return T.reshape(shape + (4, 4)), cov.reshape(shape + (6, 6))
        T = np.zeros((N, 4, 4))
        T[:, 3, 3] = 1.0
        cov = np.zeros((N, 6, 6))
        # chunks keep the (3, 4, n) working set in cache
        for a in range(0, N, _CHUNK):
            b = min(N, a + _CHUNK)
            Dc = None if D is None else D[..., a:b]
            B, G_chunk, _ = _eval_backward(ch, theta[:, a:b], Dc, m > 0, False)
            T[a:b, :3, :] = np.moveaxis(B, 2, 0)
            if m == 0:
                continue
            assert G_chunk is not None
            G = G_chunk
            if order == 2:
                cc = np.empty((6, 6, b - a))
                for i in range(6):
                    Gi = G[:, i]
                    for j in range(i, 6):
                        cc[i, j] = np.einsum("mn,mn->n", Gi, G[:, j])
                        if j != i:
                            cc[j, i] = cc[i, j]
                cov[a:b] = cc.transpose(2, 0, 1)
            else:
                cov[a:b] = _fourth_order_batch_last(ch, G).transpose(2, 0, 1)
        return T.reshape(shape + (4, 4)), cov.reshape(shape + (6, 6))

    def fk_multi(self, joints: Joints, frm: str | None, tos: Sequence[str],
                 context: Mapping[str, Any] | None = None) -> tuple[Array, Array]:
        """Mean poses of several frames and their JOINT second-order covariance.

        Chains that share perturbations (e.g. ``base -> tool`` and ``base -> camera``) are
        correlated; this returns the full covariance of the stacked local twists (eq. 15/18
        applied to every target at once: ``cov = G^T G`` with the columns of each shared
        perturbation ``L_k`` transported to every target).

        Parameters
        ----------
        joints : as in :meth:`fk`
        frm : str or None
            Common reference link (default ``config.frames.base``).
        tos : sequence of str
            Target links.

        Returns
        -------
        T : ndarray, shape (..., k, 4, 4)
            ``T_frm_to`` for each target.
        cov : ndarray, shape (..., 6k, 6k)
            Block ``(i, j)`` = ``E[xi_i xi_j^T]``, ``xi_i`` the right perturbation of target
            ``i`` in the tangent space at ``T[..., i]`` (frame ``tos[i]``).
        """
        tos = list(tos)
        if not tos:
            raise UnknownFrameError("fk_multi: no target frames given")
        Ts, Gs, ids = [], [], []
        shape: tuple = ()
        N = 1
        for to in tos:
            ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
            B, G, _ = _eval_backward(ch, theta, D, ch.L_all.shape[0] > 0, False)
            Ts.append(_rows_to_T(B))
            Gs.append(G)
            ids.append(ch.col_ids)
        index: dict = {}
        for cid in ids:
            for key in cid:
                index.setdefault(key, len(index))
        k = len(tos)
        Gall = np.zeros((len(index), 6 * k, N))
        for i, (G, cid) in enumerate(zip(Gs, ids)):
            if G is not None and cid:
                Gall[[index[key] for key in cid], 6 * i:6 * i + 6] = G
        cov = np.einsum("min,mjn->nij", Gall, Gall)
        T = np.stack(Ts, axis=1)
        return T.reshape(shape + (k, 4, 4)), cov.reshape(shape + (6 * k, 6 * k))

    def sample(self, joints: Joints, frm: str | None = None, to: str | None = None, n: int = 1000,
               rng: np.random.Generator | None = None, context: Mapping[str, Any] | None = None) -> Array:
        """Monte-Carlo samples of ``T_frm_to`` from the same model.

        Every perturbation ``xi_k ~ N(0, Sigma_k)`` (and joint noise) is drawn independently
        and inserted into the chain at its place (eq. 16-17); nothing is linearised.

        Returns
        -------
        ndarray, shape (n, ..., 4, 4)
        """
        rng = np.random.default_rng() if rng is None else rng
        n = int(n)
        if n < 1:
            raise ModelConfigError(f"sample: n must be >= 1, got {n}")
        ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
        NN = n * N
        theta_r = np.tile(theta, (1, n))
        D_r = None if D is None else np.tile(D, (1, 1, 1, n))
        pert = []
        for L in ch.site_L:
            z = rng.standard_normal((L.shape[1], NN))
            pert.append(_exp_batch_last(L @ z))
        P = _eval_forward(ch, theta_r, D_r, pert)
        return _rows_to_T(P).reshape((n,) + shape + (4, 4))

    def jacobian_joints(self, joints: Joints, frm: str | None = None, to: str | None = None,
                        context: Mapping[str, Any] | None = None) -> Array:
        """Right-tangent derivative of ``T_frm_to`` w.r.t. the independent joint values.

        ``T(q + dq) ~= T(q) Exp(J dq)``; mimic joints contribute through their master
        (times the multiplier); effects are held fixed.

        Returns
        -------
        ndarray, shape (..., 6, len(joint_names))
            Columns in ``joint_names`` order (zero for joints off the chain), in the tangent
            space at ``T_frm_to`` (frame ``to``).
        """
        ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
        _, _, Jm = _eval_backward(ch, theta, D, False, True)
        J = np.zeros((6, len(self.joint_names), N))
        if Jm is not None:
            for i in range(len(ch.motion_joint)):
                J[:, self._index[ch.motion_master[i]]] += ch.motion_mult[i] * Jm[i]
        return np.moveaxis(J, 2, 0).reshape(shape + (6, len(self.joint_names)))

    def perturbation_labels(self, frm: str | None = None, to: str | None = None) -> list[str]:
        """Perturbation sites on the chain (``"xi:<joint>"``, ``"noise:<joint>"``), chain order."""
        frm, to = self._frames(frm, to)
        return list(self._chain(frm, to, False).site_label)


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


def _fourth_order(ch: _Chain, G: Array) -> Array:
    """Sequential fourth-order compounding of the local site covariances.

    ``G`` (m, N, 6) local columns; returns ``(N, 6, 6)``.
    """
    cov = None
    for k in range(len(ch.site_L)):
        Gk = G[ch.col_site == k]  # (r, N, 6)
        Sk = np.einsum("rni,rnj->nij", Gk, Gk)
        cov = Sk if cov is None else compound_fourth_order(cov, Sk)
    assert cov is not None
    return cov


def _mm3(A: Array, B: Array) -> Array:
    """3x3 matrix products over trailing batch axes: ``(3, 3, ...) x (3, 3, ...)``."""
    out = np.empty(np.broadcast_shapes(A.shape, B.shape))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return out


def _op1(A: Array) -> Array:
    """``<<A>> = -tr(A) I + A`` for ``(3, 3, ...)``."""
    out = A.copy()
    tr = A[0, 0] + A[1, 1] + A[2, 2]
    for i in range(3):
        out[i, i] -= tr
    return out


def _compound4_batch_last(c1: Array, c2: Array) -> Array:
    """:func:`compound_fourth_order` for covariances ``(6, 6, N)`` (batch last, elementwise)."""
    rr1, rt1, tt1 = c1[:3, :3], c1[:3, 3:], c1[3:, 3:]
    rr2, rt2, tt2 = c2[:3, :3], c2[:3, 3:], c2[3:, 3:]
    tr1, tr2 = rt1.swapaxes(0, 1), rt2.swapaxes(0, 1)
    left = np.stack([tt1, tr1, rt1, rr1, tt1, tr1, tt1], axis=2)  # (3, 3, 7, N)
    right = np.stack([rr2, rt2, tr2, tt2, tr2, tt2, tt2], axis=2)
    oL, oR = _op1(left), _op1(right)
    pair = _mm3(oL, oR) + _op1(_mm3(right, left))
    out = c1 + c2
    out[:3, :3] += (pair[:, :, 0] + pair[:, :, 1] + pair[:, :, 2] + pair[:, :, 3]) / 4.0
    B12 = (pair[:, :, 4] + pair[:, :, 5]) / 4.0
    out[:3, 3:] += B12
    out[3:, :3] += B12.swapaxes(0, 1)
    out[3:, 3:] += pair[:, :, 6] / 4.0
    # X = A1 c2 + A2 c1 with A_i = [[a_i, b_i], [0, a_i]], a_i = <<tt_i>>, b_i = <<rt_i + tr_i>>
    a1, a2 = oL[:, :, 0], oR[:, :, 3]
    b1, b2 = _op1(rt1 + tr1), _op1(rt2 + tr2)
    P = _mm3(
        np.stack([a1, a1, a1, a1, b1, b1, a2, a2, a2, a2, b2, b2], axis=2),
        np.stack([rr2, rt2, tr2, tt2, tr2, tt2, rr1, rt1, tr1, tt1, tr1, tt1], axis=2),
    )
    X = np.empty_like(c1)
    X[:3, :3] = P[:, :, 0] + P[:, :, 4] + P[:, :, 6] + P[:, :, 10]
    X[:3, 3:] = P[:, :, 1] + P[:, :, 5] + P[:, :, 7] + P[:, :, 11]
    X[3:, :3] = P[:, :, 2] + P[:, :, 8]
    X[3:, 3:] = P[:, :, 3] + P[:, :, 9]
    out += (X + X.swapaxes(0, 1)) / 12.0
    return out


def _fourth_order_batch_last(ch: _Chain, G: Array) -> Array:
    """Sequential fourth-order compounding, ``G`` (m, 6, N) -> ``(6, 6, N)``."""
    cov = None
    for k in range(len(ch.site_L)):
        _, _, _, _, c0, c1 = ch.site_cols[k]
        Gk = G[c0:c1]
        Sk = np.einsum("rin,rjn->ijn", Gk, Gk)
        cov = Sk if cov is None else _compound4_batch_last(cov, Sk)
    assert cov is not None
    return cov
