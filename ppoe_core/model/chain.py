"""Compiled kinematic chains of :class:`~ppoe_core.model.ppoe.PPOEModel`: a chain between two frames as a small program
(static transforms, joint motions, perturbation sites; paper eq. 16/17) and its batched evaluation.

Covariance columns are local (tangent space at the chain's end pose, docs/conventions.md)."""

from __future__ import annotations

from collections.abc import Sequence
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
    program: tuple  # arrays of the compiled evaluation (ppoe_core.model.chain_kernel: F, kind, arg, col_pos, X,
    #                 mot_pos, mot_kind, site_start)


def _compile(robot: Robot, config: ModelConfig, frm: str, to: str, with_effects: bool) -> _Chain:
    """Build the program of the chain ``frm -> to`` (see :class:`_Chain`)."""
    return _ChainBuilder(robot, config, with_effects).build(frm, to)


class _ChainBuilder:
    """Emits the program of a chain (paper eq. 16/17): static factors, joint motions about z, perturbation and
    joint-noise sites (low-rank covariance columns, local tangent) and effect insertion points."""

    def __init__(self, robot: Robot, config: ModelConfig, with_effects: bool) -> None:
        self.robot, self.config, self.with_effects = robot, config, with_effects
        self.ops: list = []
        self.pending = np.eye(4)  # constant factor not yet emitted
        self.has_pending = False
        self.motion_joint: list[Any] = []
        self.motion_master: list[Any] = []
        self.motion_mult: list[Any] = []
        self.motion_off: list[Any] = []
        self.motion_sign: list[Any] = []
        self.motion_kind: list[Any] = []
        self.site_L: list = []
        self.site_label: list = []
        self.d_joint: list = []
        self.d_map: list = []
        self.masters: list = []

    # -- emitters ---------------------------------------------------------------------------------------------------
    def static(self, M: Array) -> None:
        self.pending = self.pending @ M
        self.has_pending = True

    def flush(self) -> None:
        if self.has_pending and not np.array_equal(self.pending, np.eye(4)):
            self.ops.append((_S, self.pending))
        self.pending = np.eye(4)
        self.has_pending = False

    def motion(self, jn: str, sign: float) -> None:
        j = self.robot.joints[jn]
        if j.mimic_root is not None:
            master, mult, off = j.mimic_root
        else:
            master, mult, off = jn, 1.0, 0.0
        if master not in self.masters:
            self.masters.append(master)
        self.flush()
        kind = _TZ if j.type == "prismatic" else _RZ
        self.ops.append((kind, len(self.motion_joint)))
        self.motion_joint.append(jn)
        self.motion_master.append(master)
        self.motion_mult.append(sign * mult)
        self.motion_off.append(sign * off)
        self.motion_sign.append(sign)
        self.motion_kind.append(kind)

    def site(self, L: Array, label: str) -> None:
        if L.shape[1] == 0:
            return
        self.flush()
        self.ops.append((_SITE, len(self.site_L)))
        self.site_L.append(L)
        self.site_label.append(label)

    def dsite(self, jn: str, M6: Array) -> None:
        if not self.with_effects:
            return
        self.flush()
        self.ops.append((_D, len(self.d_joint)))
        self.d_joint.append(jn)
        self.d_map.append(M6)

    def noise_L(self, jn: str) -> Array:
        sigma = self.config.joint_noise.get(jn, 0.0)
        if sigma <= 0.0:
            return np.zeros((6, 0))
        L = np.zeros((6, 1))
        L[2 if self.robot.joints[jn].type == "prismatic" else 5, 0] = sigma
        return L

    def xi_L(self, jn: str) -> Array:
        p = self.config.perturbations.get(jn)
        return np.zeros((6, 0)) if p is None else p.factor

    # -- branches ---------------------------------------------------------------------------------------------------
    def up(self, joints: Sequence[str]) -> None:
        """Up-branch: ``(O Exp(d) Exp(xi) Q Mz(q) Q^T Exp(n))^-1
        = Q Exp(-Ad_{Q^T} n) Mz(-q) Exp(-Ad_{Q^T} xi) Exp(-Ad_{Q^T} d) Q^T O^-1``."""
        for jn in joints:
            j = self.robot.joints[jn]
            if j.movable:
                Q = _rot_z_to(j.axis)
                self.static(lie.from_rt(Q, np.zeros(3)))
                self.site(-self.noise_L(jn), "noise:" + jn)  # Exp(-n): already along z in the Q frame
                self.motion(jn, -1.0)
                self.site(-_rot6(Q.T) @ self.xi_L(jn), "xi:" + jn)
                self.dsite(jn, -_rot6(Q.T))
                self.static(lie.from_rt(Q.T, np.zeros(3)) @ lie.inverse(j.origin))
            else:
                self.site(-self.xi_L(jn), "xi:" + jn)
                self.dsite(jn, -np.eye(6))
                self.static(lie.inverse(j.origin))

    def down(self, joints: Sequence[str]) -> None:
        """Down-branch: ``O Exp(d) Exp(xi) Q Mz(q) Q^T Exp(n)
        = (O Q) Exp(Ad_{Q^T} d) Exp(Ad_{Q^T} xi) Mz(q) Exp(Ad_{Q^T} n) Q^T``."""
        for jn in joints:
            j = self.robot.joints[jn]
            if j.movable:
                Q = _rot_z_to(j.axis)
                self.static(j.origin @ lie.from_rt(Q, np.zeros(3)))
                self.dsite(jn, _rot6(Q.T))
                self.site(_rot6(Q.T) @ self.xi_L(jn), "xi:" + jn)
                self.motion(jn, 1.0)
                self.site(self.noise_L(jn), "noise:" + jn)
                self.static(lie.from_rt(Q.T, np.zeros(3)))
            else:
                self.static(j.origin)
                self.dsite(jn, np.eye(6))
                self.site(self.xi_L(jn), "xi:" + jn)

    # -- compiled tables --------------------------------------------------------------------------------------------
    def columns(self) -> tuple[Array, Array, list, list]:
        """Stacked low-rank columns (m, 6), their site per column, and per site the dense / sparse column data."""
        site_L = self.site_L
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
        return L_all, col_site, site_cols, site_sparse

    def factors(self) -> tuple[list, list, list, Array]:
        """Single-configuration program: factor list, motion / insertion factor positions, site positions."""
        factors: list = []
        f_motion_idx: list = []
        f_d_idx: list = []
        site_pos = np.zeros(len(self.site_L), dtype=int)
        for code, arg in self.ops:
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
        return factors, f_motion_idx, f_d_idx, site_pos

    def build(self, frm: str, to: str) -> _Chain:
        up, down = self.robot.chain(frm, to)
        self.up(up)
        self.down(down)
        self.flush()
        L_all, col_site, site_cols, site_sparse = self.columns()
        factors, f_motion_idx, f_d_idx, site_pos = self.factors()
        motion_kind, site_L, site_label = self.motion_kind, self.site_L, self.site_label
        slot = np.array([self.masters.index(m) for m in self.motion_master], dtype=int)
        return _Chain(
            frm=frm,
            to=to,
            ops=self.ops,
            motion_joint=self.motion_joint,
            motion_master=self.motion_master,
            motion_slot=slot,
            motion_col=np.array([self.robot.independent_joints.index(mj) for mj in self.motion_master], dtype=int),
            motion_mult=np.array(self.motion_mult, dtype=float),
            motion_off=np.array(self.motion_off, dtype=float),
            motion_sign=np.array(self.motion_sign, dtype=float),
            motion_kind=motion_kind,
            masters=self.masters,
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
            d_joint=self.d_joint,
            d_map=self.d_map,
            f_static=np.array(factors),
            f_motion_idx=np.array(f_motion_idx, dtype=int),
            f_rz=(np.array([i for i, k in enumerate(motion_kind) if k == _RZ], dtype=int),
                  np.array([f_motion_idx[i] for i, k in enumerate(motion_kind) if k == _RZ], dtype=int)),
            f_tz=(np.array([i for i, k in enumerate(motion_kind) if k == _TZ], dtype=int),
                  np.array([f_motion_idx[i] for i, k in enumerate(motion_kind) if k == _TZ], dtype=int)),
            f_d_idx=np.array(f_d_idx, dtype=int),
            site_pos=site_pos,
            program=_program(factors, f_motion_idx, f_d_idx, motion_kind, site_pos[col_site], L_all,
                             [c[4] for c in site_cols] + [L_all.shape[0]]),
        )


def _program(factors: list, f_motion_idx: list, f_d_idx: list, motion_kind: list, col_pos: Array,
             L_all: Array, site_start: list) -> tuple:
    """The chain's arrays for :func:`ppoe_core.model.chain_kernel.eval_chain` (contiguous, fixed dtypes)."""
    kind = np.zeros(len(factors), dtype=np.int64)
    arg = np.zeros(len(factors), dtype=np.int64)
    for i, (f, k) in enumerate(zip(f_motion_idx, motion_kind)):
        kind[f] = 1 if k == _RZ else 2
        arg[f] = i
    for i, f in enumerate(f_d_idx):
        kind[f] = 3
        arg[f] = i
    return (
        np.ascontiguousarray(np.array(factors, dtype=float)), kind, arg, np.asarray(col_pos, dtype=np.int64),
        np.ascontiguousarray(L_all.reshape(-1, 2, 3), dtype=float), np.array(f_motion_idx, dtype=np.int64),
        np.array([1 if k == _RZ else 2 for k in motion_kind], dtype=np.int64), np.array(site_start, dtype=np.int64),
    )
