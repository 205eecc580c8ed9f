"""The Probabilistic Product-of-Exponentials (PPOE) model of a URDF robot.

One link of the chain is (paper eq. 16, docs/conventions.md section 1)::

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
inverse is needed.  One compiled kernel (numba, :mod:`ppoe_core.model.chain_kernel`)
evaluates one or many configurations, in chunks with the batch axis innermost (SIMD).
Covariances use the low-rank factors ``Sigma_k = L_k L_k^T`` (only the non-zero
sigmas): ``Sigma = G^T G`` with rows ``G = [Ad_{B_k^-1} L_k]_k``.

Effects: ``dq`` of an independent joint shifts its motion and, times the multiplier, its mimic joints'
(they follow the master's true value, as :class:`~ppoe_core.robot.tree.KinematicTree` and the calibrated
URDF); ``dq`` of a mimic joint shifts that joint only; ``dxi`` sits right before the joint's ``xi``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ppoe_core.errors import JointValueError, ModelConfigError, UnknownFrameError, UnknownJointError
from ppoe_core.model.chain import Array, Chain, LeanChain, compile_chain
from ppoe_core.model.chain_eval import evaluate, evaluate_one, exp_batch_last, forward_product, rows_to_poses
from ppoe_core.robot.config import ModelConfig, load_model_config
from ppoe_core.robot.urdf import Robot, parse_urdf

__all__ = ["PPOEModel", "Joints"]
Joints = Mapping[str, ArrayLike] | ArrayLike


def _off_chain(ch: Any, joint: str) -> bool:
    """``joint`` is neither moved nor perturbed on the compiled chain ``ch`` (an effect's correction there changes
    nothing the chain computes)."""
    return joint not in ch.motion_joint and joint not in ch.d_joint and joint not in ch.masters


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
        self._chains: dict[tuple[str, str, bool], Chain] = {}
        self._effects: list | None = list(effects) if effects is not None else None
        # per chain (by id; the chains live in _chains as long as the model): the one-configuration path's constants
        self._single_consts: dict[int, tuple[list[str], Array]] = {}

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

    def _chain(self, frm: str, to: str, with_effects: bool) -> Chain:
        key = (frm, to, with_effects)
        ch = self._chains.get(key)
        if ch is None:
            ch = compile_chain(self.robot, self.config, frm, to, with_effects)
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
                raise JointValueError(
                    "joint values must be a mapping name -> value or a numeric array, "
                    f"got {type(joints).__name__}"
                ) from None
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
    def _lookup(self, frm: str | None, to: str | None) -> Chain:
        with_effects = bool(self._effects) if self._effects is not None else bool(self.effects)
        ch = self._chains.get((frm, to, with_effects))  # type: ignore[arg-type]
        if ch is None:
            frm, to = self._frames(frm, to)
            ch = self._chain(frm, to, with_effects)
            self._chains[(frm, to, with_effects)] = ch
        return ch

    def _single(self, joints: Joints, ch: Chain, order: int) -> tuple[Array, Array] | None:
        """Lean path: ``(T, cov)`` of ONE configuration without effects, or None (use the general path, which also
        produces the error messages): a dict becomes one array of the motions' masters, an array is used as it is,
        and one compiled call (:func:`~ppoe_core.model.chain_eval.evaluate_one`) does the rest, checks included."""
        if self._effects:
            return None
        if type(joints) is np.ndarray:
            if (joints.ndim != 1 or joints.shape[0] != len(self.joint_names) or joints.dtype != np.float64
                    or not joints.flags.c_contiguous):
                return None
            return evaluate_one(ch, joints, ch.motion_col, order)
        if not isinstance(joints, dict):
            return None
        single = self._single_of(ch)
        try:
            qm = np.array([joints[n] for n in single[0]], dtype=float)
        except (KeyError, TypeError, ValueError):
            return None
        if qm.ndim != 1:
            return None
        return evaluate_one(ch, qm, single[1], order)

    def _single_of(self, ch: Chain) -> tuple[list[str], Array]:
        """The one-configuration path's per-chain constants (made on first use): the master of each motion and
        ``arange(n_motion)`` (the dict path's joint array holds the motions' masters in order)."""
        single = self._single_consts.get(id(ch))
        if single is None:
            single = self._single_consts[id(ch)] = (list(ch.motion_master),
                                                    np.arange(len(ch.motion_master), dtype=np.int64))
        return single

    def lean_program(self, frm: str | None, to: str | None) -> LeanChain | None:
        """What the one-configuration path of :meth:`fk` evaluates for ``frm -> to``, for a compiled caller
        (:mod:`ppoe_core.io.joint_pose`): the :class:`~ppoe_core.model.chain.LeanChain` (the chain program of
        :func:`ppoe_core.model.chain_kernel.eval_chain` and ``theta = q[motion_col] * mult + off`` for ``q`` in
        :attr:`joint_names` order); None when effects are on (:meth:`fk` then takes the general path)."""
        ch = self._lookup(frm, to)
        if self._effects:
            return None
        return ch.lean()

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
        if effects and isinstance(joints, Mapping):
            theta, shape, N = _batch_over_all_joints(theta, shape, joints)
        if effects:
            qd = self._all_joint_dict(joints, shape)
            dq_tot: dict[str, Array] = {}
            dxi_tot: dict[str, Array] = {}
            for eff in effects:
                if context is None and getattr(eff, "context_keys", None) and _off_chain(ch, eff.location):
                    continue  # reads a context but corrects a joint off this chain: changes nothing here
                dq, dxi = eff.corrections(qd, dict(context or {}))
                for k, v in dq.items():
                    dq_tot[k] = dq_tot.get(k, 0.0) + np.broadcast_to(np.asarray(v, dtype=float), shape).reshape(N)
                for k, v in dxi.items():
                    dxi_tot[k] = dxi_tot.get(k, 0.0) + np.broadcast_to(
                        np.asarray(v, dtype=float), shape + (6,)
                    ).reshape(N, 6)
            for k in list(dq_tot) + list(dxi_tot):
                if k not in self.robot.joints:
                    raise UnknownJointError(f"an effect returned a correction for unknown joint '{k}'")
            if dq_tot:
                theta = _shift_motions(ch, theta, dq_tot)
            if len(ch.d_joint):
                D = np.empty((len(ch.d_joint), 4, 4, N))
                for k, jn in enumerate(ch.d_joint):
                    if jn in dxi_tot:
                        D[k] = exp_batch_last((dxi_tot[jn] @ ch.d_map[k].T).T)
                    else:
                        D[k] = np.eye(4)[:, :, None]
        return ch, theta, D, shape, N

    def fk_mean(
        self, joints: Joints, frm: str | None = None, to: str | None = None, context: Mapping[str, Any] | None = None
    ) -> Array:
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
        one = self._single(joints, ch, 0)
        if one is not None:
            return one[0]
        ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
        T = evaluate(ch, theta, D, order=0)[0]
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
        one = self._single(joints, ch, order)
        if one is not None:
            return one
        ch, theta, D, shape, N = self._prepare(joints, frm, to, context)
        T, cov, _, _ = evaluate(ch, theta, D, order=order)
        assert cov is not None
        return T.reshape(shape + (4, 4)), cov.reshape(shape + (6, 6))

    def fk_multi(
        self, joints: Joints, frm: str | None, tos: Sequence[str], context: Mapping[str, Any] | None = None
    ) -> tuple[Array, Array]:
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
            T_to, _, G, _ = evaluate(ch, theta, D, order=0, want_cols=ch.L_all.shape[0] > 0)
            Ts.append(T_to)
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
                Gall[[index[key] for key in cid], 6 * i : 6 * i + 6] = G
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
            pert.append(exp_batch_last(L @ z))
        P = forward_product(ch, theta_r, D_r, pert)
        return rows_to_poses(P).reshape((n,) + shape + (4, 4))

    def jacobian_joints(
        self, joints: Joints, frm: str | None = None, to: str | None = None, context: Mapping[str, Any] | None = None
    ) -> Array:
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
        _, _, _, Jm = evaluate(ch, theta, D, order=0, want_jac=True)
        J = np.zeros((6, len(self.joint_names), N))
        if Jm is not None:
            for i in range(len(ch.motion_joint)):
                J[:, self._index[ch.motion_master[i]]] += ch.motion_mult[i] * Jm[i]
        return np.moveaxis(J, 2, 0).reshape(shape + (6, len(self.joint_names)))

    def perturbation_labels(self, frm: str | None = None, to: str | None = None) -> list[str]:
        """Perturbation sites on the chain (``"xi:<joint>"``, ``"noise:<joint>"``), chain order."""
        frm, to = self._frames(frm, to)
        return list(self._chain(frm, to, False).site_label)


def _shift_motions(ch: Chain, theta: Array, dq: Mapping[str, Array]) -> Array:
    """Motion values ``theta`` (n_motion, N) plus the joint offsets ``dq``: a mimic joint follows its master's true
    value (``dq`` of the master times the multiplier) and adds its own ``dq``."""
    theta = theta.copy()
    for i, jn in enumerate(ch.motion_joint):
        master = ch.motion_master[i]
        if master != jn and master in dq:
            theta[i] += ch.motion_mult[i] * dq[master]
        if jn in dq:
            theta[i] += ch.motion_sign[i] * dq[jn]
    return theta


def _batch_over_all_joints(theta: Array, shape: tuple, joints: Mapping[str, Any]) -> tuple[Array, tuple, int]:
    """Effects may depend on joints off the chain (gravity loads): the motion values ``theta`` (n_motion, N)
    broadcast to the batch shape of every given joint value (a chain without moving joints has shape ``()``)."""
    full = np.broadcast_shapes(shape, *(np.shape(v) for v in joints.values()))
    N = int(np.prod(full)) if full else 1
    if full == shape:
        return theta, shape, N
    lead = (theta.shape[0],) + (1,) * (len(full) - len(shape))
    theta = np.broadcast_to(theta.reshape(lead + tuple(shape)), (theta.shape[0], *full))
    return theta.reshape(theta.shape[0], N), full, N
