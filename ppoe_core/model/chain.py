"""Compiled kinematic chains of :class:`~ppoe_core.model.ppoe.PPOEModel`: a chain between two frames as a small program
(static transforms, joint motions, perturbation sites; paper eq. 16/17) and its batched evaluation.

Covariance columns are local (tangent space at the chain's end pose, docs/conventions.md)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ppoe_core import lie
from ppoe_core.robot.config import ModelConfig
from ppoe_core.robot.urdf import Robot

Array = np.ndarray


__all__ = ["OP_STATIC", "OP_ROT_Z", "OP_TRANS_Z", "OP_EFFECT", "OP_SITE", "Chain", "ChainProgram", "LeanChain",
           "compile_chain"]

# ----------------------------------------------------------------------------
# Small helpers
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



# ----------------------------------------------------------------------------
# Compiled chain
# ----------------------------------------------------------------------------

#: program op codes of :attr:`Chain.ops`
OP_STATIC, OP_ROT_Z, OP_TRANS_Z, OP_EFFECT, OP_SITE = 0, 1, 2, 3, 4


class ChainProgram(NamedTuple):
    """The arrays of a chain for :func:`ppoe_core.model.chain_kernel.eval_chain` (contiguous, fixed dtypes; the
    module docstring there says what each holds)."""

    F: Array  # (n_f, 4, 4) constant factors, identity at motion and effect slots
    kind: Array  # (n_f,) int64: 0 constant, 1 rotation about z, 2 translation along z, 3 effect factor
    arg: Array  # (n_f,) int64: motion or effect index of each factor
    col_pos: Array  # (m,) int64: suffix index of each covariance column
    X: Array  # (m, 2, 3): rows [v^T; w^T] of each column
    mot_pos: Array  # (n_motion,) int64: factor index of each motion
    mot_kind: Array  # (n_motion,) int64: 1 revolute, 2 prismatic
    site_start: Array  # (n_sites + 1,) int64: first column of each perturbation site


class LeanChain(NamedTuple):
    """What the one-configuration compiled path needs of a chain (:meth:`PPOEModel.lean_program`)."""

    program: ChainProgram
    motion_col: Array  # (n_motion,) index of each motion's master in the model's joint vector
    mult: Array  # (n_motion,) sign * mimic multiplier
    off: Array  # (n_motion,) sign * mimic offset


@dataclass
class Chain:
    """A compiled chain ``frm -> to``.

    ``ops`` is a list of ``(code, arg)``:
      * ``(OP_STATIC, M)``: multiply by the constant 4x4 ``M``;
      * ``(OP_ROT_Z, i)`` / ``(OP_TRANS_Z, i)``: rotate about / translate along local z by motion ``i``;
      * ``(OP_EFFECT, k)``: multiply by ``Exp(dxi)`` of effect site ``k`` (effects only);
      * ``(OP_SITE, k)``: perturbation site ``k`` (covariance columns from the product of everything after it).
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
    masters: list  # independent joints the chain needs, first-use order
    # perturbation sites
    site_L: list  # (6, r_k) factors in the canonical frame at the site (negated on the
    #               up-branch, where the link enters inverted: Exp(-xi)); the sign only
    #               matters for cross-covariances between chains (fk_multi)
    site_label: list  # "xi:<joint>" / "noise:<joint>"
    L_all: Array  # (m, 6) all factor columns stacked (rows = columns of L_k)
    col_ids: list  # (m,) (site label, column of its factor): identifies the random source
    # effect sites
    d_joint: list  # joint name of each OP_EFFECT site
    d_map: list  # (6, 6) map of the joint's dxi into the canonical twist (sign included)
    program: ChainProgram

    def lean(self) -> LeanChain:
        """:class:`LeanChain` of this chain."""
        return LeanChain(self.program, self.motion_col, self.motion_mult, self.motion_off)


def compile_chain(robot: Robot, config: ModelConfig, frm: str, to: str, with_effects: bool) -> Chain:
    """Build the program of the chain ``frm -> to`` (see :class:`Chain`)."""
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
            self.ops.append((OP_STATIC, self.pending))
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
        kind = OP_TRANS_Z if j.type == "prismatic" else OP_ROT_Z
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
        self.ops.append((OP_SITE, len(self.site_L)))
        self.site_L.append(L)
        self.site_label.append(label)

    def dsite(self, jn: str, M6: Array) -> None:
        if not self.with_effects:
            return
        self.flush()
        self.ops.append((OP_EFFECT, len(self.d_joint)))
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
    def columns(self) -> tuple[Array, Array, list[int]]:
        """Stacked low-rank columns (m, 6), the site of each column and the first column of each site (+ m)."""
        if not self.site_L:
            return np.zeros((0, 6)), np.zeros(0, dtype=int), [0]
        L_all = np.concatenate([L.T for L in self.site_L], axis=0)
        col_site = np.concatenate([np.full(L.shape[1], k) for k, L in enumerate(self.site_L)]).astype(int)
        start = np.concatenate([[0], np.cumsum([L.shape[1] for L in self.site_L])]).astype(int)
        return L_all, col_site, start.tolist()

    def factors(self) -> tuple[list, list, list, Array]:
        """Single-configuration program: factor list, motion / insertion factor positions, site positions."""
        factors: list = []
        f_motion_idx: list = []
        f_d_idx: list = []
        site_pos = np.zeros(len(self.site_L), dtype=int)
        for code, arg in self.ops:
            if code == OP_STATIC:
                factors.append(arg)
            elif code in (OP_ROT_Z, OP_TRANS_Z):
                f_motion_idx.append(len(factors))
                factors.append(np.eye(4))
            elif code == OP_EFFECT:
                f_d_idx.append(len(factors))
                factors.append(np.eye(4))
            else:
                site_pos[arg] = len(factors)
        if not factors:
            factors.append(np.eye(4))
        return factors, f_motion_idx, f_d_idx, site_pos

    def build(self, frm: str, to: str) -> Chain:
        up, down = self.robot.chain(frm, to)
        self.up(up)
        self.down(down)
        self.flush()
        L_all, col_site, site_start = self.columns()
        factors, f_motion_idx, f_d_idx, site_pos = self.factors()
        site_L, site_label = self.site_L, self.site_label
        slot = np.array([self.masters.index(m) for m in self.motion_master], dtype=int)
        return Chain(
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
            masters=self.masters,
            site_L=site_L,
            site_label=site_label,
            L_all=L_all,
            col_ids=[(site_label[k], i) for k, L in enumerate(site_L) for i in range(L.shape[1])],
            d_joint=self.d_joint,
            d_map=self.d_map,
            program=_program(factors, f_motion_idx, f_d_idx, self.motion_kind, site_pos[col_site], L_all, site_start),
        )


def _program(factors: list, f_motion_idx: list, f_d_idx: list, motion_kind: list, col_pos: Array,
             L_all: Array, site_start: list) -> ChainProgram:
    """The chain's :class:`ChainProgram`."""
    kind = np.zeros(len(factors), dtype=np.int64)
    arg = np.zeros(len(factors), dtype=np.int64)
    for i, (f, k) in enumerate(zip(f_motion_idx, motion_kind)):
        kind[f] = 1 if k == OP_ROT_Z else 2
        arg[f] = i
    for i, f in enumerate(f_d_idx):
        kind[f] = 3
        arg[f] = i
    return ChainProgram(
        np.ascontiguousarray(np.array(factors, dtype=float)), kind, arg, np.asarray(col_pos, dtype=np.int64),
        np.ascontiguousarray(L_all.reshape(-1, 2, 3), dtype=float), np.array(f_motion_idx, dtype=np.int64),
        np.array([1 if k == OP_ROT_Z else 2 for k in motion_kind], dtype=np.int64),
        np.array(site_start, dtype=np.int64),
    )
