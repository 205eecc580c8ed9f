"""``ppoe diagnose``: trace the residual of a PPOE model to systematic effects, add them, report.

Pipeline (issue 6, CONTRACT sec. 6):

1. **Residuals.**  Static stops (:class:`Stops`): measured tracker points (a reflector on a link,
   in the tracker's own frame, the tracker-to-base registration is a nuisance estimated per
   session) or ground-truth poses (in the base frame).  The nominal model includes the effects
   already declared in the model YAML.
2. **Candidates.**  Every catalogue effect (:mod:`ppoe_core.model.effects`) at every plausible location
   of the measured chain.  All effects are linear in their parameters and small, so the
   measured quantity is linearised once at the nominal chain, ``x = x0 + G theta``; the
   linearisation error is checked on the final model with the full nonlinear chain.
3. **Fit.**  Gauss-Newton over the effect parameters and the per-session registrations
   (left perturbation ``T <- Exp(delta) T``), the registrations eliminated by a Schur complement.
4. **Selection.**  Greedy forward selection by held-out residual (cross-validation over stops
   within sessions, or leave-one-group-out over bags/files): a candidate is added when it is
   identifiable together with the registration and the effects already chosen (scaled
   reduced information matrix: condition number below ``max_condition``; components a
   ``link_error`` cannot separate are dropped), and when it lowers the held-out mean squared
   error by at least ``min_gain`` (relative) with a paired one-sided t statistic of at least
   ``min_t`` over the held-out stops (default 4: about 50 candidates are tested per round and
   held-out errors within a session are correlated, so the usual 2-3 would over-select).
   Compliances must come out non-negative (a structure yields along its load): a candidate
   whose fit needs a negative compliance is rejected as unphysical rather than used to absorb
   a residual of another shape.  What no candidate explains is reported as unexplained.
5. **Confidence intervals** from the Gauss-Newton covariance ``s^2 H_red^-1`` (``s^2`` the
   residual variance), 95 % two-sided normal.
6. **Sigma refit.**  The first-order PPOE covariance of the measured point (model perturbations
   and joint noise, eq. 18 to first order) plus the sensor noise is scaled by ``k^2`` so that the
   mean held-out NEES equals its expectation (the measurement dimension).
7. **Report**: JSON (contract keys ``effects``, ``residual_before``, ``residual_after``),
   markdown, a PNG plot and the updated model YAML.
8. **Tag pixels** (second stage, :func:`diagnose_pixels`): reprojection residuals of tag points
   through link -> root -> camera (plumb_bob), whitened by the pixel sigma plus the declared
   covariance propagated to the pixels; ``camera_extrinsics`` candidates at each camera's mount
   joint, selected by cross-validation over poses, CIs from a pose-clustered sandwich
   covariance; held-out pixel RMS, noise floor and NEES per camera.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional
from collections.abc import Mapping, Sequence

import numpy as np
import yaml

from ppoe_core import lie
from ppoe_core.model.effects import Effect, KinematicTree, apply_corrections, effect_from_config, make_effect
from ppoe_core.errors import BagError, MeasurementError, ModelConfigError, PpoeError
from ppoe_core.robot.urdf import Robot

__all__ = [
    "Stops",
    "Candidate",
    "FitResult",
    "DiagnoseOptions",
    "DiagnoseResult",
    "LinearProblem",
    "candidate_effects",
    "motion_signs",
    "kabsch",
    "diagnose",
    "stops_from_bag",
    "stops_from_hilti",
    "protocol_scores",
    "stops_from_motoman",
    "imu_tilt_residuals",
    "make_folds",
    "load_model",
    "write_model_yaml",
    "write_report",
    "PixelObs",
    "PixelDiagnosis",
    "pixels_from_motoman",
    "pixels_from_bag",
    "predict_pixels",
    "pixel_jacobian",
    "pixel_chain_jacobians",
    "pixel_covariance",
    "pixel_rms",
    "pixel_stats",
    "pixel_candidates",
    "camera_mount_joint",
    "diagnose_pixels",
    "concat_pixel_obs",
    "add_pixel_diagnosis",
    "diagnose_imu",
    "imu_candidates",
    "imu_tilt_covariance",
]

_CHI2_DIM = {3: 3.0, 6: 6.0}


# =============================================================================
# Data
# =============================================================================


@dataclass
class Stops:
    """Static measurements, one row per stop.

    Attributes
    ----------
    q : dict[str, ndarray (N,)]
        Independent joint values [rad or m].
    p_meas : ndarray (N, 3)
        ``kind="point"``: reflector position in the tracker frame [m]; ``kind="pose"``: tool
        position in the base frame [m].
    R_meas : ndarray (N, 3, 3) or None
        ``kind="pose"``: measured tool orientation in the base frame.
    kind : str
        ``"point"`` (tracker point, registration per session) or ``"pose"``.
    link : str
        Link that carries the reflector (``point``) or the tool frame (``pose``).
    point : ndarray (3,)
        Reflector position in ``link`` [m] (zeros for ``pose``).
    sigma : float
        1-sigma per axis of the position measurement [m].
    sigma_rot : float
        1-sigma per axis of the orientation measurement [rad] (``pose`` only).
    session : ndarray (N,) int
        Registration session of each stop (index into ``session_names``).
    group : ndarray (N,) int
        Source bag/file of each stop (index into ``group_names``), for leave-one-group-out.
    reg_mask : ndarray (N,) bool
        Stops allowed to define their session's registration when it is fitted for scoring
        (Hilti: the stationing points).
    score_mask : ndarray (N,) bool
        Stops that are scored in such a session (Hilti: the evaluation points).
    context : dict
        Effect context per stop (``time`` (N,), ``motion_sign`` {joint: (N,)},
        ``joint_velocity`` {joint: (N,)}, ``gravity`` (N, 3)).
    imus : dict name -> (link, specific force (N, 3) [m/s^2] in that link's axes)
        Accelerometers at each stop; fitted by :func:`diagnose_imu` (base tilt per group and
        IMU-visible effects), and they break location ties of the point / pose stage.
    """

    q: dict[str, np.ndarray]
    p_meas: np.ndarray
    kind: str
    link: str
    point: np.ndarray
    sigma: float
    session: np.ndarray
    session_names: list[str]
    group: np.ndarray
    group_names: list[str]
    reg_mask: np.ndarray
    score_mask: np.ndarray
    context: dict[str, Any] = field(default_factory=dict)
    R_meas: np.ndarray | None = None
    sigma_rot: float = 1e-3
    base: str = ""
    imus: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.p_meas.shape[0])

    @property
    def dim(self) -> int:
        """Residual dimension per stop (3 for points, 6 for poses)."""
        return 3 if self.kind == "point" else 6

    @staticmethod
    def concat(parts: Sequence[Stops]) -> Stops:
        """Stack stops of several bags/files (sessions and groups kept apart)."""
        if not parts:
            raise BagError("no stops to diagnose")
        first = parts[0]
        for p in parts[1:]:
            if (p.kind, p.link) != (first.kind, first.link):
                raise BagError(f"cannot mix measurements: {first.kind} on {first.link} and "
                               f"{p.kind} on {p.link} ({p.group_names})")
        so = np.cumsum([0] + [len(p.session_names) for p in parts])
        go = np.cumsum([0] + [len(p.group_names) for p in parts])
        joints = set.intersection(*[set(p.q) for p in parts])
        ctx: dict[str, Any] = {}
        for key in ("time", "temperature", "gravity"):
            if all(key in p.context for p in parts):
                ctx[key] = np.concatenate([p.context[key] for p in parts])
        for key in ("motion_sign", "joint_velocity"):
            if all(key in p.context for p in parts):
                names = set.intersection(*[set(p.context[key]) for p in parts])
                ctx[key] = {n: np.concatenate([p.context[key][n] for p in parts]) for n in names}
        return Stops(
            q={j: np.concatenate([p.q[j] for p in parts]) for j in joints},
            p_meas=np.concatenate([p.p_meas for p in parts]),
            R_meas=None if first.R_meas is None else np.concatenate([p.R_meas for p in parts]),
            kind=first.kind, link=first.link, point=first.point, sigma=first.sigma,
            sigma_rot=first.sigma_rot, base=first.base,
            session=np.concatenate([p.session + o for p, o in zip(parts, so)]),
            session_names=[n for p in parts for n in p.session_names],
            group=np.concatenate([p.group + o for p, o in zip(parts, go)]),
            group_names=[n for p in parts for n in p.group_names],
            reg_mask=np.concatenate([p.reg_mask for p in parts]),
            score_mask=np.concatenate([p.score_mask for p in parts]),
            context=ctx,
            imus={k: (first.imus[k][0], np.concatenate([p.imus[k][1] for p in parts]))
                  for k in first.imus if all(k in p.imus for p in parts)},
        )

    def subset(self, rows: np.ndarray) -> Stops:
        """The stops ``rows`` (index or bool array); session/group numbering is kept."""
        def sub_ctx(v: Any) -> Any:
            return {k: a[rows] for k, a in v.items()} if isinstance(v, dict) else v[rows]
        return Stops(q={k: v[rows] for k, v in self.q.items()}, p_meas=self.p_meas[rows],
                     R_meas=None if self.R_meas is None else self.R_meas[rows], kind=self.kind,
                     link=self.link, point=self.point, sigma=self.sigma, sigma_rot=self.sigma_rot,
                     base=self.base, session=self.session[rows], session_names=self.session_names,
                     group=self.group[rows], group_names=self.group_names,
                     reg_mask=self.reg_mask[rows], score_mask=self.score_mask[rows],
                     context={k: sub_ctx(v) for k, v in self.context.items()},
                     imus={k: (ln, a[rows]) for k, (ln, a) in self.imus.items()})


def motion_signs(stamps: np.ndarray, positions: np.ndarray, at: np.ndarray,
                 threshold: float = 1e-5) -> np.ndarray:
    """Sign of each joint's last motion before each time ``at`` (backlash context).

    Parameters
    ----------
    stamps : (M,) joint-state times [s], increasing
    positions : (M, J) joint values
    at : (N,) query times [s]
    threshold : float
        Changes between consecutive samples below this [rad or m] are not motion.

    Returns
    -------
    ndarray (N, J) of -1, 0, +1 (0: no motion seen yet).
    """
    d = np.diff(positions, axis=0)
    s = np.where(np.abs(d) > threshold, np.sign(d), 0.0)
    last = np.zeros_like(positions)
    cur = np.zeros(positions.shape[1])
    for k in range(1, positions.shape[0]):
        cur = np.where(s[k - 1] != 0, s[k - 1], cur)
        last[k] = cur
    idx = np.clip(np.searchsorted(stamps, at, side="right") - 1, 0, len(stamps) - 1)
    return last[idx]


def _paired_t(d: np.ndarray) -> float:
    """Paired one-sample t statistic of the held-out error reductions ``d`` (N,); 0 if constant."""
    d = np.asarray(d, dtype=float)
    sd = float(d.std(ddof=1)) if d.size > 1 else 0.0
    return float(d.mean() / (sd / math.sqrt(d.size))) if sd > 0 else 0.0


#: rigid fit of corresponding points (Kabsch, no scale): :func:`ppoe_core.lie.fit_rigid`
kabsch = lie.fit_rigid


# =============================================================================
# Candidates and the linearised problem
# =============================================================================


@dataclass
class Candidate:
    """A candidate effect with its linearised measurement Jacobian.

    ``G``: (N, dim, P) derivative of the predicted measurement (position in the base frame,
    then for poses the right-tangent rotation of the tool) w.r.t. the effect parameters.
    """

    effect: Effect
    G: np.ndarray

    @property
    def key(self) -> str:
        comps = "" if self.effect.name != "link_error" else "[" + ",".join(self.effect.param_names) + "]"
        return f"{self.effect.name}@{self.effect.location}{comps}"


def _carried_mass(tree: KinematicTree, joint: str) -> float:
    m = 0.0
    for ln in tree.subtree_links(joint):
        inert = tree.robot.links[ln].inertial
        if inert is not None:
            m += inert.mass
    return m


def candidate_effects(tree: KinematicTree, stops: Stops) -> list[Effect]:
    """Catalogue effects at every plausible location of the measured chain (zero parameters).

    * ``joint_offset``: every movable joint on the path to the measured link;
    * ``gravity_compliance``: movable joints carrying mass (URDF inertials);
    * ``mount_bending``: fixed and prismatic joints carrying mass (a telescopic segment bends
      at its overlap);
    * ``link_error`` (6 components; unidentifiable ones are pruned during selection): every
      joint on the path;
    * ``backlash``: independent movable joints whose last-motion sign changes (context);
    * ``thermal_growth`` over time: joints with an origin offset above 5 cm, if the data span
      more than 10 minutes;
    * ``time_offset``: if the joints move at the measurement times (context ``joint_velocity``).

    ``base_tilt`` is fitted by the accelerometer stage (:func:`diagnose_imu`) and
    ``camera_extrinsics`` by the pixel stage (:func:`diagnose_pixels`); ``tracker_registration``
    is always estimated per session.
    """
    robot = tree.robot
    path = robot.path_from_root(stops.link)
    if stops.kind == "pose" and stops.base and stops.base != robot.root:
        base_path = set(robot.path_from_root(stops.base))
        path = [j for j in path if j not in base_path]
    out: list[Effect] = []
    signs = stops.context.get("motion_sign", {})
    t = stops.context.get("time")
    vel = stops.context.get("joint_velocity", {})
    for jn in path:
        j = robot.joints[jn]
        if j.movable:
            out.append(make_effect("joint_offset", jn, tree))
        out.append(make_effect("link_error", jn, tree))
        mass = _carried_mass(tree, jn)
        if j.movable and mass > 0.0:
            out.append(make_effect("gravity_compliance", jn, tree))
        if (not j.movable or j.type == "prismatic") and mass > 0.0:
            out.append(make_effect("mount_bending", jn, tree))
        if j.independent and jn in signs and np.ptp(signs[jn]) > 0:
            out.append(make_effect("backlash", jn, tree))
        if t is not None and np.ptp(t) > 600.0 and np.linalg.norm(j.origin[:3, 3]) > 0.05:
            out.append(make_effect("thermal_growth", jn, tree, variable="time",
                                   reference=float(np.min(t))))
    if vel and max(float(np.max(np.abs(v))) for v in vel.values()) > 1e-6:
        out.append(make_effect("time_offset", "/joint_states", tree))
    return out


def _predict_nominal(tree: KinematicTree, stops: Stops, declared: Sequence[Effect]
                     ) -> tuple[np.ndarray, np.ndarray | None, dict, dict, dict]:
    """Nominal prediction with the declared effects; returns x0 (N,3), R0, poses, dq, dxi."""
    dq, dxi = apply_corrections(declared, stops.q, stops.context)
    poses = tree.link_poses(stops.q, dq, dxi)
    T = poses[stops.link]
    if stops.kind == "pose" and stops.base and stops.base != tree.root:
        T = lie.inverse(poses[stops.base]) @ T
    x0 = (T @ np.append(stops.point, 1.0))[..., :3]
    return x0, (T[..., :3, :3] if stops.kind == "pose" else None), poses, dq, dxi


def _measurement_jacobian(tree: KinematicTree, stops: Stops, eff: Effect, nominal: Mapping,
                          chain: tuple, base_R: np.ndarray | None) -> np.ndarray:
    """(N, dim, P): derivative of the predicted measurement w.r.t. the effect parameters."""
    Jq, Jx, Fq, Fx = chain
    Bq, Bx = eff.basis(stops.q, stops.context, nominal)
    n = len(stops)
    G = np.zeros((n, stops.dim, eff.n_params))
    for k, b in Bq.items():
        if k in Jq:
            G[:, :3] += Jq[k][:, :, None] * b[:, None, :]
            if stops.dim == 6:
                G[:, 3:] += Fq[k][:, 3:, None] * b[:, None, :]
    for k, b in Bx.items():
        if k in Jx:
            G[:, :3] += Jx[k] @ b
            if stops.dim == 6:
                G[:, 3:] += Fx[k][:, 3:] @ b
    if base_R is not None:  # position derivative into the pose's base frame
        G[:, :3] = np.einsum("nji,njp->nip", base_R, G[:, :3])
    return G


@dataclass
class FitResult:
    """Result of one fit: parameters, registrations, covariance and identifiability."""

    theta: np.ndarray
    regs: dict[int, np.ndarray]
    cov: np.ndarray
    s2: float
    condition: float
    absorbed: np.ndarray
    rows: np.ndarray


class LinearProblem:
    """The linearised diagnosis problem ``x = x0 + G theta`` with per-session registration.

    Parameters
    ----------
    stops : Stops
    x0 : (N, 3) nominal predicted positions (base frame)
    R0 : (N, 3, 3) or None, nominal tool orientation (``pose`` only)
    W_base : (N, 3, 3) or None
        Whitening of the position residual in base-frame axes, ``L_i^-1`` with
        ``L_i L_i^T = C_i`` the expected residual covariance of stop ``i`` (the model's PPOE
        covariance of the point plus the sensor noise); None: ``I / sigma``.
    W_rot : (N, 3, 3) or None
        ``pose`` only: whitening of the rotation residual (tangent at the tool), from the
        rotation block of the model's covariance plus ``sigma_rot^2 I``; None: ``I / sigma_rot``.
    """

    def __init__(self, stops: Stops, x0: np.ndarray, R0: np.ndarray | None,
                 W_base: np.ndarray | None = None, W_rot: np.ndarray | None = None) -> None:
        self.stops = stops
        self.x0 = x0
        self.R0 = R0
        self.register = stops.kind == "point"
        self.W = (np.broadcast_to(np.eye(3) / stops.sigma, (len(stops), 3, 3)) if W_base is None
                  else W_base)
        self.W_rot = (np.broadcast_to(np.eye(3) / stops.sigma_rot, (len(stops), 3, 3)) if W_rot is None
                      else W_rot)
        if stops.kind == "pose":
            assert stops.R_meas is not None and R0 is not None  # pose stops carry measured rotations
            self.r0_rot = lie.so3_log(np.swapaxes(R0, -1, -2) @ stops.R_meas)

    # -- residuals ---------------------------------------------------------------
    def _per_row(self, regs: Mapping[int, np.ndarray], sess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Registration of each row (n, 4, 4) and whether its session has one (n,)."""
        table = np.full((len(self.stops.session_names) + 1, 4, 4), np.nan)
        for k, T in regs.items():
            table[k] = T
        Tn = table[sess]
        return Tn, np.isfinite(Tn[:, 0, 0])

    def residuals(self, G: np.ndarray, theta: np.ndarray, regs: Mapping[int, np.ndarray],
                  rows: np.ndarray) -> np.ndarray:
        """Residuals measured minus predicted, (n, dim) [m, rad], NaN where no registration."""
        s = self.stops
        x = self.x0[rows] + (G[rows, :3] @ theta if theta.size else 0.0)
        if self.register:
            Tn, _ = self._per_row(regs, s.session[rows])
            return s.p_meas[rows] - (np.einsum("nij,nj->ni", Tn[:, :3, :3], x) + Tn[:, :3, 3])
        out = np.empty((rows.size, s.dim))
        out[:, :3] = s.p_meas[rows] - x
        out[:, 3:] = self.r0_rot[rows] - (G[rows, 3:] @ theta if theta.size else 0.0)
        return out

    def whitened(self, r: np.ndarray, regs: Mapping[int, np.ndarray], rows: np.ndarray) -> np.ndarray:
        """Residuals (n, dim) whitened: position part rotated into base axes, times ``W``."""
        out = np.array(r, dtype=float)
        if self.register:
            Tn, _ = self._per_row(regs, self.stops.session[rows])
            rb = np.einsum("nji,nj->ni", Tn[:, :3, :3], r[:, :3])
        else:
            rb = r[:, :3]
            out[:, 3:] = np.einsum("nij,nj->ni", self.W_rot[rows], r[:, 3:])
        out[:, :3] = np.einsum("nij,nj->ni", self.W[rows], rb)
        return out

    def kabsch_regs(self, G: np.ndarray, theta: np.ndarray, rows: np.ndarray) -> dict[int, np.ndarray]:
        """Registration per session from ``rows`` with ``theta`` fixed (Kabsch, batched over
        sessions; sessions with fewer than 3 rows or collinear points get none)."""
        s = self.stops
        if not self.register or rows.size == 0:
            return {}
        rows = rows[np.argsort(s.session[rows], kind="stable")]
        x = self.x0[rows] + (G[rows, :3] @ theta if theta.size else 0.0)
        p = s.p_meas[rows]
        sids, starts, counts = np.unique(s.session[rows], return_index=True, return_counts=True)
        xc = np.add.reduceat(x, starts, axis=0) / counts[:, None]
        pc = np.add.reduceat(p, starts, axis=0) / counts[:, None]
        inv = np.repeat(np.arange(sids.size), counts)
        H = np.add.reduceat(np.einsum("ni,nj->nij", x - xc[inv], p - pc[inv]), starts, axis=0)
        U, S, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
        D = np.broadcast_to(np.eye(3), H.shape).copy()
        D[:, 2, 2] = d
        R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
        t = pc - np.einsum("sij,sj->si", R, xc)
        good = (counts >= 3) & (S[:, 1] > 1e-8 * np.maximum(S[:, 0], 1e-300))
        return {int(k): lie.from_rt(R[i], t[i]) for i, k in enumerate(sids) if good[i]}

    # -- fit ------------------------------------------------------------------------
    def fit(self, G: np.ndarray, rows: np.ndarray, iterations: int = 2) -> FitResult:
        """Gauss-Newton over ``theta`` and the registrations of the sessions of ``rows``.

        Returns the estimate, the covariance ``s^2 H_red^-1`` of ``theta`` (H_red: information
        reduced by the registrations, Schur complement), the condition number of the
        column-scaled ``H_red`` and, per parameter, the fraction of its information absorbed
        by the registrations.
        """
        s = self.stops
        P = G.shape[-1]
        theta = np.zeros(P)
        regs = self.kabsch_regs(G, theta, rows)
        if self.register:
            rows = rows[np.isin(s.session[rows], list(regs))]
            rows = rows[np.argsort(s.session[rows], kind="stable")]
        Gr = G[rows]
        Wr = self.W[rows]
        if self.register:
            sids, starts, inv = np.unique(s.session[rows], return_index=True, return_inverse=True)
            T = np.stack([regs[int(k)] for k in sids]) if sids.size else np.zeros((0, 4, 4))

            def seg(a: np.ndarray) -> np.ndarray:  # per-session sums of per-row terms
                return np.add.reduceat(a, starts, axis=0) if a.shape[0] else a[:0]
        H_red = np.zeros((P, P))
        H_tt = np.zeros((P, P))
        for it in range(iterations):
            if self.register:
                x = self.x0[rows] + Gr[:, :3] @ theta
                Tn = T[inv]  # per-row registration
                y = np.einsum("nij,nj->ni", Tn[:, :3, :3], x) + Tn[:, :3, 3]
                A = Wr @ np.swapaxes(Tn[:, :3, :3], -1, -2)  # whitening in the tracker axes
                r = (A @ (s.p_meas[rows] - y)[:, :, None])[..., 0]
                Js = -A @ np.concatenate([np.broadcast_to(np.eye(3), (y.shape[0], 3, 3)), -lie.hat3(y)],
                                         axis=-1)
                JsT = np.swapaxes(Js, -1, -2)
                Jts = -(Wr @ Gr[:, :3])
                Hss = seg(JsT @ Js) + 1e-12 * np.eye(6)
                Hst = seg(JsT @ Jts)
                gs = seg((JsT @ r[:, :, None])[..., 0])
                Jf = Jts.reshape(Jts.shape[0] * 3, P)
                H_tt = Jf.T @ Jf
                g_t = Jf.T @ r.reshape(-1)
                Hinv = np.linalg.inv(Hss)
                HiHst = Hinv @ Hst  # (S, 6, P)
                H_red = H_tt - np.einsum("sap,saq->pq", Hst, HiHst)
                g_red = g_t - np.einsum("sap,sa->p", Hst, np.einsum("sab,sb->sa", Hinv, gs))
                dtheta = -_solve(H_red, g_red) if P else np.zeros(0)
                d = -(np.einsum("sab,sb->sa", Hinv, gs) + HiHst @ dtheta)
                T = lie.exp(d) @ T
                theta = theta + dtheta
                if it > 0 and np.abs(d).max(initial=0.0) < 1e-12 and np.all(np.abs(dtheta) <= 1e-10 * (1 + np.abs(theta))):
                    break
            else:
                r = self.whitened(self.residuals(G, theta, regs, rows), regs, rows)
                Jw = -np.concatenate([Wr @ Gr[:, :3], self.W_rot[rows] @ Gr[:, 3:]], axis=1)
                Jf = Jw.reshape(Jw.shape[0] * Jw.shape[1], P)
                H_tt = H_red = Jf.T @ Jf
                dtheta = -_solve(H_red, Jf.T @ r.reshape(-1)) if P else np.zeros(0)
                theta = theta + dtheta
                break  # linear in theta
        if self.register:
            regs = {int(k): T[i] for i, k in enumerate(sids)}
        r = self.whitened(self.residuals(G, theta, regs, rows), regs, rows)
        n_par = P + 6 * len(regs)
        s2 = float(np.nansum(r ** 2) / max(r.size - n_par, 1))
        cond, absorbed = _identifiability(H_red, H_tt, r.size)
        cov = s2 * np.linalg.pinv(H_red) if P else np.zeros((0, 0))
        return FitResult(theta, regs, cov, s2, cond, absorbed, rows)

    def heldout(self, G: np.ndarray, folds: Sequence[tuple[np.ndarray, np.ndarray]]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Held-out residuals over ``folds``: ``(r_meas, r_base, e2w)``; ``r_meas`` and ``r_base``
        (N, 3) [m], NaN where a stop is not scored, in the measurement frame and rotated into
        the robot base frame axes; ``e2w`` (N,) the whitened squared position error
        ``|W r_base|^2`` (Mahalanobis distance under the model's covariance).

        A test stop whose session has training rows uses that session's training registration;
        otherwise the registration is fitted on the session's ``reg_mask`` test rows with theta
        fixed and only its ``score_mask`` rows that did not define it are scored (the Hilti
        protocol).
        """
        s = self.stops
        R = np.full((len(s), 3), np.nan)
        Rb = np.full((len(s), 3), np.nan)
        for train, test in folds:
            fit = self.fit(G, train)
            regs = dict(fit.regs)
            scored = test
            if self.register:
                missing = np.setdiff1d(np.unique(s.session[test]), list(regs))
                if missing.size:
                    reg_rows = test[np.isin(s.session[test], missing) & s.reg_mask[test]]
                    regs.update(self.kabsch_regs(G, fit.theta, reg_rows))
                    own = np.isin(s.session[test], missing)
                    split = s.score_mask[test] & ~s.reg_mask[test]
                    # a session without separate scored stops is scored on the stops that
                    # registered it (rigid fit per session, as in the Motoman README)
                    whole = own & ~np.isin(s.session[test], s.session[test][own & split])
                    scored = test[~own | split | whole]
            r = self.residuals(G, fit.theta, regs, scored)[:, :3]
            R[scored] = r
            if self.register:
                for sid in np.unique(s.session[scored]):
                    if int(sid) in regs:
                        m = s.session[scored] == sid
                        Rb[scored[m]] = r[m] @ regs[int(sid)][:3, :3]
            else:
                Rb[scored] = r
        return R, Rb, np.sum(np.einsum("nij,nj->ni", self.W, Rb) ** 2, axis=1)


def _ssr(problem: LinearProblem, G: np.ndarray, rows: np.ndarray) -> float:
    """In-sample sum of squared residuals after a fit (screening of candidates)."""
    fit = problem.fit(G, rows, iterations=1)
    return float(np.nansum(problem.whitened(problem.residuals(G, fit.theta, fit.regs, fit.rows),
                                            fit.regs, fit.rows) ** 2))


def _solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Minimum-norm solution of ``H x = g`` with column scaling; parameters that do not act
    (information below 1e-12, see :func:`_identifiability`) stay at zero."""
    x = np.zeros(len(g))
    act = np.diag(H) > 1e-12
    if not act.any():
        return x
    Ha = H[np.ix_(act, act)]
    d = np.sqrt(np.diag(Ha))
    Hs = Ha / d[:, None] / d[None, :]
    x[act] = np.linalg.lstsq(Hs, g[act] / d, rcond=1e-12)[0] / d
    return x


def _identifiability(H_red: np.ndarray, H_tt: np.ndarray, n_res: int) -> tuple[float, np.ndarray]:
    """Condition number of the column-scaled reduced information, and per parameter the
    fraction of its information absorbed by the registrations (1 = fully absorbed; also 1 for
    a parameter that moves the weighted measurement by less than 1e-6 sigma per unit over
    the ``n_res`` residuals, i.e. does not act on it at all)."""
    P = H_red.shape[0]
    if P == 0:
        return 1.0, np.zeros(0)
    dt = np.diag(H_tt)
    acts = dt > 1e-12 * max(n_res, 1)
    absorbed = np.where(acts, 1.0 - np.diag(H_red) / np.where(acts, dt, 1.0), 1.0)
    d = np.sqrt(np.maximum(np.diag(H_red), 1e-300))
    ev = np.linalg.eigvalsh(H_red / d[:, None] / d[None, :])
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
    if np.any(np.diag(H_red) <= 0):
        cond = math.inf
    return cond, absorbed


# =============================================================================
# Selection
# =============================================================================


@dataclass
class DiagnoseOptions:
    """Selection settings.

    Attributes
    ----------
    folds : int
        Stop-wise cross-validation folds (within sessions) when there are fewer than 3 groups
        or ``cv="stops"``.
    cv : str
        ``"auto"`` (leave-one-group-out with >= 3 groups, else stops), ``"groups"``, ``"stops"``.
    min_gain : float
        Minimum relative reduction of the held-out mean squared error to accept an effect.
    min_t : float
        Minimum paired one-sided t statistic of that reduction over held-out stops.
    max_condition : float
        Identifiability limit of the scaled reduced information matrix.
    max_absorbed : float
        A parameter whose information is absorbed by the registration beyond this fraction is
        not separable from it.
    max_effects : int
    screen : int
        Per round, only the candidates with the largest in-sample gain are cross-validated.
    seed : int
        Fold assignment.
    imu_sigma : dict or None
        Accelerometer 1-sigma per axis [m/s^2] by IMU name (model ``imus`` section); default 4e-4.
    candidates : list of str or None
        Only candidate keys that start with one of these (e.g. ``"mount_bending"``).
    """

    folds: int = 5
    cv: str = "auto"
    min_gain: float = 0.03
    min_t: float = 4.0
    max_condition: float = 1e6
    max_absorbed: float = 0.999
    max_effects: int = 8
    screen: int = 6
    seed: int = 0
    candidates: list[str] | None = None
    imu_sigma: dict[str, float] | None = None


@dataclass
class DiagnoseResult:
    """Everything ``ppoe diagnose`` reports."""

    effects: list[dict[str, Any]]
    residual_before: float
    residual_after: float
    residual_before_insample: float
    residual_after_insample: float
    noise_floor: float
    unexplained: float
    steps: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    nees_before: float
    nees_after: float
    sigma_scale: float
    linearisation_error: float
    cv: str
    n_stops: int
    n_sessions: int
    e2_before: np.ndarray
    e2_after: np.ndarray
    chosen: list[Effect]
    summary: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The contract JSON (sec. 6) plus details."""
        return {
            "effects": self.effects,
            "residual_before": self.residual_before,
            "residual_after": self.residual_after,
            "residual_before_insample": self.residual_before_insample,
            "residual_after_insample": self.residual_after_insample,
            "noise_floor": self.noise_floor,
            "unexplained": self.unexplained,
            "nees_before": self.nees_before,
            "nees_after": self.nees_after,
            "sigma_scale": self.sigma_scale,
            "linearisation_error": self.linearisation_error,
            "cv": self.cv,
            "n_stops": self.n_stops,
            "n_sessions": self.n_sessions,
            "steps": self.steps,
            "rejected": self.rejected,
            "summary": self.summary,
            **self.extra,
        }


def make_folds(stops: Stops, options: DiagnoseOptions) -> tuple[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Cross-validation folds ``(train_rows, test_rows)``; returns the scheme and the folds."""
    n = len(stops)
    groups = np.unique(stops.group)
    mode = options.cv
    if mode == "auto":
        mode = "groups" if groups.size >= 3 else "stops"
    if mode == "groups":
        if groups.size < 2:
            raise PpoeError("diagnose: leave-one-group-out needs at least 2 bags/files")
        return mode, [(np.flatnonzero(stops.group != g), np.flatnonzero(stops.group == g)) for g in groups]
    rng = np.random.default_rng(options.seed)
    fold = np.zeros(n, dtype=int)
    for sid in np.unique(stops.session):
        idx = np.flatnonzero(stops.session == sid)
        fold[idx] = rng.permutation(np.arange(idx.size) % options.folds)
    return mode, [(np.flatnonzero(fold != k), np.flatnonzero(fold == k)) for k in range(options.folds)]


def _stack(cands: Sequence[Candidate], n: int, dim: int) -> np.ndarray:
    if not cands:
        return np.zeros((n, dim, 0))
    return np.concatenate([c.G for c in cands], axis=-1)


def _restrict(c: Candidate, keep: Sequence[int], tree: KinematicTree) -> Candidate:
    e = c.effect
    comps = [e.param_names[i] for i in keep]
    eff = make_effect(e.name, e.location, tree, components=comps)
    return Candidate(eff, c.G[..., list(keep)])


def _identifiable_subset(problem: LinearProblem, chosen: Sequence[Candidate], cand: Candidate,
                         options: DiagnoseOptions, tree: KinematicTree, rows: np.ndarray
                         ) -> tuple[Candidate | None, str, float]:
    """Candidate (possibly with fewer link_error components) identifiable together with the
    registration and ``chosen``, with physically signed parameters; also its in-sample SSR.

    Returns ``(candidate or None, reason if None, in-sample weighted SSR)``.
    """
    base = _stack(chosen, len(problem.stops), problem.stops.dim)
    nb = base.shape[-1]

    def check(G_c: np.ndarray, names: Sequence[str]) -> tuple[bool, str, float]:
        G = np.concatenate([base, G_c], axis=-1)
        fit = problem.fit(G, rows, iterations=1)
        if np.any(fit.absorbed[nb:] > options.max_absorbed):
            return False, "not separable from the tracker registration", math.inf
        if fit.condition > options.max_condition:
            return False, (f"not separable from the effects already chosen (condition "
                           f"{fit.condition:.2g})"), math.inf
        th = fit.theta[nb:]
        sd = np.sqrt(np.maximum(np.diag(fit.cov)[nb:], 0.0))
        neg = [k for k, v, s in zip(names, th, sd) if k in cand.effect.nonnegative and v + 1.96 * s < 0]
        if neg:
            return False, f"fitted {', '.join(neg)} < 0: unphysical sign", math.inf
        ssr = float(np.nansum(problem.whitened(problem.residuals(G, fit.theta, fit.regs, fit.rows),
                                               fit.regs, fit.rows) ** 2))
        return True, "", ssr

    ok, why, ssr = check(cand.G, cand.effect.param_names)
    if ok:
        return cand, "", ssr
    if cand.effect.name != "link_error" or "unphysical" in why:
        return None, why, math.inf
    keep: list[int] = []
    for i in range(cand.G.shape[-1]):
        ok_i, _, ssr_i = check(cand.G[..., keep + [i]], [cand.effect.param_names[j] for j in keep + [i]])
        if ok_i:
            keep.append(i)
            ssr = ssr_i
    if not keep:
        return None, why, math.inf
    return _restrict(cand, keep, tree), "", ssr


def diagnose(robot: Robot, stops: Stops, declared: Sequence[Effect] = (),
             perturbation_cov: Mapping[str, np.ndarray] | None = None,
             joint_noise: Mapping[str, float] | None = None,
             options: DiagnoseOptions | None = None) -> DiagnoseResult:
    """Find the catalogue effects that explain the residual of ``stops`` (module docstring).

    Parameters
    ----------
    robot : Robot
    stops : Stops
    declared : effects the model already declares (part of the nominal prediction)
    perturbation_cov : joint -> 6x6 covariance of the model's perturbation xi_j, in the tangent
        space right after the joint's origin (CONTRACT sec. 5)
    joint_noise : joint -> 1-sigma along the joint axis [rad or m]
    options : DiagnoseOptions

    Returns
    -------
    DiagnoseResult
    """
    options = options or DiagnoseOptions()
    tree = KinematicTree(robot)
    n = len(stops)
    if n < 6:
        raise PpoeError(f"diagnose: only {n} stops with measurements; need at least 6")
    bad = ~np.all(np.isfinite(stops.p_meas), axis=1)
    for jn, v in stops.q.items():
        if jn in robot.path_from_root(stops.link):
            bad |= ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeasurementError(f"diagnose: {int(bad.sum())} stops have non-finite measurements or joint "
                               f"values (first: stop {i} of {stops.group_names[stops.group[i]]}, session "
                               f"{stops.session_names[stops.session[i]]})")
    x0, R0, poses, dq0, dxi0 = _predict_nominal(tree, stops, declared)
    base_R = None
    Jq, Jx = tree.point_jacobian(stops.q, stops.link, stops.point, poses, dq0, dxi0)
    Fq, Fx = tree.frame_jacobian(stops.q, stops.link, poses, dq0, dxi0)
    if stops.kind == "pose" and stops.base and stops.base != tree.root:
        base_R = poses[stops.base][..., :3, :3]
    nominal = tree.link_poses(stops.q)
    C_exp = _point_covariance(tree, stops, poses, dq0, dxi0, perturbation_cov or {}, joint_noise or {})
    C_exp = C_exp + stops.sigma ** 2 * np.eye(3)
    W_base = np.linalg.inv(np.linalg.cholesky(C_exp))
    W_rot = None
    if stops.kind == "pose":
        C_rot = _rotation_covariance(stops, Fq, Fx, perturbation_cov or {}, joint_noise or {})
        W_rot = np.linalg.inv(np.linalg.cholesky(C_rot + stops.sigma_rot ** 2 * np.eye(3)))
    problem = LinearProblem(stops, x0, R0, W_base, W_rot)
    cands = []
    for eff in candidate_effects(tree, stops):
        c = Candidate(eff, _measurement_jacobian(tree, stops, eff, nominal, (Jq, Jx, Fq, Fx), base_R))
        if options.candidates and not any(c.key.startswith(p) for p in options.candidates):
            continue
        if np.abs(c.G).max() > 0.0:
            cands.append(c)
    mode, folds = make_folds(stops, options)
    all_rows = np.arange(n)

    chosen: list[Candidate] = []
    R_before, Rb_before, e2 = problem.heldout(_stack(chosen, n, stops.dim), folds)
    R_after, Rb_after = R_before, Rb_before
    steps: list[dict[str, Any]] = []
    rejected: dict[str, str] = {}
    while len(chosen) < options.max_effects:
        best = None
        screened = []
        G_now = _stack(chosen, n, stops.dim)
        ssr_now = _ssr(problem, G_now, all_rows)
        for c in cands:
            if c.key in rejected or any(c.key == k.key for k in chosen):
                continue
            if any(ch.effect.name == c.effect.name and ch.effect.location == c.effect.location for ch in chosen):
                continue
            c2, why, ssr = _identifiable_subset(problem, chosen, c, options, tree, all_rows)
            if c2 is None:
                rejected[c.key] = why
                continue
            screened.append((1.0 - ssr / ssr_now, c, c2))
        screened.sort(key=lambda z: -z[0])
        for _, c, c2 in screened[:options.screen]:
            Rc, Rbc, e2c = problem.heldout(_stack(chosen + [c2], n, stops.dim), folds)
            ok = np.isfinite(e2) & np.isfinite(e2c)
            if ok.sum() < 3:
                continue
            mse0, mse1 = float(np.mean(e2[ok])), float(np.mean(e2c[ok]))
            d = e2[ok] - e2c[ok]
            t = _paired_t(d)
            z = _signed_rank_z(d)
            gain = 1.0 - mse1 / mse0
            if best is None or mse1 < best[1]:
                best = (c2, mse1, gain, (t, z), e2c, c.key, Rc, Rbc)
    # (mse: mean whitened squared held-out error; reported RMS values are in metres)
        if best is None:
            break
        c2, mse1, gain, (t, z), e2c, key, Rc, Rbc = best
        step = {"candidate": c2.key, "accepted": bool(gain >= options.min_gain and t >= options.min_t),
                "heldout_rms": _rms_m(Rc), "heldout_mahalanobis2": mse1, "gain": gain, "t": t, "z": z}
        steps.append(step)
        if not step["accepted"]:
            break
        chosen.append(c2)
        e2 = e2c
        R_after, Rb_after = Rc, Rbc

    # locations the tracker cannot tell apart: let the accelerometers decide (not fitted to them)
    relocated = _relocate_by_imu(tree, problem, stops, declared, chosen, cands, all_rows) if stops.imus else []

    # final fit on all stops, relinearised at the estimate (Gauss-Newton on the full chain)
    G = _stack(chosen, n, stops.dim)
    fit = problem.fit(G, all_rows, iterations=6)
    fit0 = problem.fit(G[..., :0], all_rows)
    ins_before = _rms3(problem.residuals(G[..., :0], np.zeros(0), fit0.regs, fit0.rows))
    ins_after = _rms3(problem.residuals(G, fit.theta, fit.regs, fit.rows))
    theta = fit.theta.copy()
    lin_err = 0.0
    for _ in range(3 if chosen else 0):
        current = _with_thetas(chosen, theta)
        xk, Rk, pk, dqk, dxik = _predict_nominal(tree, stops, list(declared) + current)
        chain = (*tree.point_jacobian(stops.q, stops.link, stops.point, pk, dqk, dxik),
                 *tree.frame_jacobian(stops.q, stops.link, pk, dqk, dxik))
        Gk = np.concatenate([_measurement_jacobian(tree, stops, c.effect, nominal, chain, base_R)
                             for c in chosen], axis=-1)
        pk_problem = LinearProblem(stops, xk, Rk, W_base, W_rot)
        gn_step = pk_problem.fit(Gk, all_rows, iterations=6)
        theta = theta + gn_step.theta
        ins_after = _rms3(pk_problem.residuals(Gk, gn_step.theta, gn_step.regs, gn_step.rows))
        fit = FitResult(theta.copy(), gn_step.regs, gn_step.cov, gn_step.s2, gn_step.condition, gn_step.absorbed,
                        gn_step.rows)
        if np.all(np.abs(gn_step.theta) <= 1e-8 * np.abs(theta) + 1e-15):
            break
    if chosen:  # accuracy of the linear model used during selection, at the final estimate
        x_nl = _predict_nominal(tree, stops, list(declared) + _with_thetas(chosen, theta))[0]
        lin_err = float(np.max(np.linalg.norm(x_nl - (x0 + G[:, :3] @ theta), axis=1)))
    effects_out: list[dict[str, Any]] = []
    found: list[Effect] = []
    i = 0
    mse_before = _rms_m(R_before) ** 2
    for k, c in enumerate(chosen):
        P = c.effect.n_params
        th = fit.theta[i:i + P]
        sd = np.sqrt(np.maximum(np.diag(fit.cov)[i:i + P], 0.0))
        i += P
        eff = c.effect.with_params(th)
        found.append(eff)
        entry = eff.to_config()
        entry["ci"] = {name: [float(v - 1.96 * s), float(v + 1.96 * s)]
                       for name, v, s in zip(eff.param_names, th, sd)}
        entry["sigma"] = {name: float(s) for name, s in zip(eff.param_names, sd)}
        prev = mse_before if k == 0 else steps[k - 1]["heldout_rms"] ** 2
        entry["share"] = float((prev - steps[k]["heldout_rms"] ** 2) / mse_before)
        effects_out.append(entry)

    # sigma refit (NEES on held-out stops)
    ok = np.isfinite(e2)
    nees_before, nees_after, k_scale, fitted_jn = _refit_sigma(
        tree, stops, poses, dq0, dxi0, perturbation_cov or {}, joint_noise or {}, Rb_after)
    floor = math.sqrt(float(np.mean(np.trace(C_exp, axis1=-2, axis2=-1))))
    rms_b = _rms_m(R_before)
    rms_a = _rms_m(R_after)
    unexplained = math.sqrt(max(rms_a ** 2 - floor ** 2, 0.0))
    res = DiagnoseResult(
        effects=effects_out, residual_before=rms_b, residual_after=rms_a,
        residual_before_insample=ins_before, residual_after_insample=ins_after,
        noise_floor=floor, unexplained=unexplained, steps=steps,
        rejected=[{"candidate": k, "reason": v} for k, v in rejected.items()],
        nees_before=nees_before, nees_after=nees_after, sigma_scale=k_scale,
        linearisation_error=lin_err, cv=mode, n_stops=int(ok.sum()), n_sessions=len(np.unique(stops.session)),
        e2_before=np.sum(R_before ** 2, axis=1), e2_after=np.sum(R_after ** 2, axis=1), chosen=found)
    res.extra["per_group"] = {stops.group_names[g]: {"before": _scores(R_before[stops.group == g]),
                                                     "after": _scores(R_after[stops.group == g])}
                              for g in np.unique(stops.group)}
    if fitted_jn:
        res.extra["fitted_joint_noise"] = fitted_jn
    if relocated:
        res.extra["relocated_by_imu"] = relocated
    if stops.imus:  # accelerometer tilt residuals, before / after (in-sample, not used by the fit)
        before = imu_tilt_residuals(tree, stops, list(declared))
        after = imu_tilt_residuals(tree, stops, list(declared) + found)
        res.extra["imu_tilt"] = {k: {"link": before[k]["link"], "n": before[k]["n"],
                                     "rms_before": before[k]["rms"], "rms_after": after[k]["rms"]}
                                 for k in before}
        # accelerometer stage: per-file base tilt and IMU-visible effects on top of declared + found
        imu_fit = diagnose_imu(robot, stops, list(declared) + found, seed=options.seed,
                               sigma=options.imu_sigma if options.imu_sigma else 4e-4,
                               perturbation_cov=perturbation_cov, joint_noise=joint_noise)
        res.extra["imu_fit"] = {k: v for k, v in imu_fit.items() if k not in ("found", "tilt")}
    # a systematic residual remains if the held-out mean squared Mahalanobis distance under the
    # declared covariance exceeds its expectation 3 by more than 3 standard errors (chi^2_3 mean)
    m2 = float(np.nanmean(e2))
    n_ok = int(np.isfinite(e2).sum())
    res.extra["heldout_mahalanobis2"] = m2
    res.extra["unexplained_significant"] = bool(m2 > 3.0 + 3.0 * math.sqrt(6.0 / max(n_ok, 1)))
    res.summary = _summary(res)
    return res


def _signed_rank_z(d: np.ndarray) -> float:
    """Normal-approximation z of the one-sided Wilcoxon signed-rank test that ``d > 0``."""
    from scipy.stats import rankdata

    d = d[d != 0]
    n = d.size
    if n < 3:
        return 0.0
    w = float(np.sum(rankdata(np.abs(d))[d > 0]))
    mu = n * (n + 1) / 4.0
    sd = math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
    return (w - mu) / sd


def _imu_cost(tree: KinematicTree, stops: Stops, effects: Sequence[Effect]) -> float:
    """Sum over accelerometers of the mean squared tilt residual [rad^2]."""
    return float(sum(sum(v ** 2 for v in r["rms"]) for r in imu_tilt_residuals(tree, stops, effects).values()))


def _relocate_by_imu(tree: KinematicTree, problem: LinearProblem, stops: Stops, declared: Sequence[Effect],
                     chosen: list[Candidate], cands: Sequence[Candidate], rows: np.ndarray) -> list[dict]:
    """Swap a chosen effect for the same effect at another location when the tracker data fit
    both equally well (in-sample weighted SSR within 0.5 %) and the accelerometer tilt residuals
    prefer the other location; ``chosen`` is modified in place.  Returns the swaps made."""
    swaps: list[dict] = []
    for k, c in enumerate(list(chosen)):
        others = [x for i, x in enumerate(chosen) if i != k]

        def fitted(cand: Candidate) -> tuple[float, list[Effect]]:
            G = _stack(others + [cand], len(stops), stops.dim)
            fit = problem.fit(G, rows, iterations=2)
            ssr = float(np.nansum(problem.whitened(problem.residuals(G, fit.theta, fit.regs, fit.rows),
                                                   fit.regs, fit.rows) ** 2))
            return ssr, _with_thetas(others + [cand], fit.theta)

        ssr0, effs0 = fitted(c)
        best = (_imu_cost(tree, stops, list(declared) + effs0), c)
        for alt in cands:
            if alt.effect.name != c.effect.name or alt.effect.location == c.effect.location \
                    or alt.G.shape[-1] != c.G.shape[-1] or any(alt.effect.location == o.effect.location
                                                               and alt.effect.name == o.effect.name for o in others):
                continue
            ssr1, effs1 = fitted(alt)
            if ssr1 > 1.005 * ssr0:
                continue
            th = effs1[-1].params
            if any(v < 0 for name, v in zip(alt.effect.param_names, th) if name in alt.effect.nonnegative):
                continue
            cost = _imu_cost(tree, stops, list(declared) + effs1)
            if cost < 0.8 * best[0]:
                best = (cost, alt)
        if best[1] is not c:
            swaps.append({"from": c.key, "to": best[1].key, "imu_cost_from": _imu_cost(tree, stops, list(declared) + effs0),
                          "imu_cost_to": best[0]})
            chosen[k] = best[1]
    return swaps


def imu_tilt_residuals(tree: KinematicTree, stops: Stops, effects: Sequence[Effect]) -> dict[str, dict]:
    """Tilt residuals of the accelerometers (measured minus predicted, small angles about the
    sensor's x and y axes [rad]) with each session's mean removed (the session's base tilt and
    the sensor's mounting are nuisances), for a model with ``effects``.

    The predicted up direction in the sensor frame is ``R_root_link^T z_root``; the measured one
    the normalised specific force.  Returns ``{imu: {"link", "rms": [rx, ry], "n"}}``.
    """
    out: dict[str, dict] = {}
    if not stops.imus:
        return out
    dq, dxi = apply_corrections(list(effects), stops.q, stops.context)
    poses = tree.link_poses(stops.q, dq, dxi, links=[ln for ln, _ in stops.imus.values()])
    for name, (link, acc) in stops.imus.items():
        u_m = acc / np.linalg.norm(acc, axis=1)[:, None]
        u_p = poses[link][..., 2, :3]  # third row of R_root_link = R^T z
        d = np.column_stack([u_m[:, 1] - u_p[:, 1], -(u_m[:, 0] - u_p[:, 0])])
        ok = np.all(np.isfinite(d), axis=1)
        for sid in np.unique(stops.session):
            m = ok & (stops.session == sid)
            d[m] -= d[m].mean(axis=0)
        out[name] = {"link": link, "rms": [float(v) for v in np.sqrt(np.mean(d[ok] ** 2, axis=0))],
                     "n": int(ok.sum())}
    return out


def _with_thetas(chosen: Sequence[Candidate], theta: np.ndarray) -> list[Effect]:
    """The chosen effects with their slices of the stacked parameter vector."""
    out, i = [], 0
    for c in chosen:
        out.append(c.effect.with_params(theta[i:i + c.effect.n_params]))
        i += c.effect.n_params
    return out


def _rms_m(R: np.ndarray) -> float:
    """RMS 3D norm [m] of the finite rows of residuals (N, 3)."""
    e2 = np.sum(R ** 2, axis=1)
    e2 = e2[np.isfinite(e2)]
    return float(np.sqrt(np.mean(e2))) if e2.size else float("nan")


def _rms3(r: np.ndarray) -> float:
    r = r[np.all(np.isfinite(r), axis=1)]
    return float(np.sqrt(np.mean(np.sum(r[:, :3] ** 2, axis=1)))) if r.size else float("nan")


def _summary(res: DiagnoseResult) -> str:
    if res.effects:
        names = ", ".join(f"{e['name']} at {e['location']}" for e in res.effects)
        head = f"found {len(res.effects)} effect(s): {names}"
    else:
        head = "no catalogue effect explains the residual significantly"
    tail = (f"held-out RMS {1e3 * res.residual_before:.3f} mm -> {1e3 * res.residual_after:.3f} mm "
            f"(noise floor {1e3 * res.noise_floor:.3f} mm)")
    if res.extra.get("unexplained_significant"):
        tail += (f"; UNEXPLAINED: {1e3 * res.unexplained:.3f} mm RMS above the noise floor is not "
                 f"explained by any catalogue effect (held-out mean Mahalanobis^2 "
                 f"{res.extra['heldout_mahalanobis2']:.2f}, expected 3)")
    return head + "; " + tail


def _rotation_covariance(stops: Stops, Fq: Mapping, Fx: Mapping, pert: Mapping[str, np.ndarray],
                         jnoise: Mapping[str, float]) -> np.ndarray:
    """First-order PPOE covariance (N, 3, 3) of the measured frame's rotation (right tangent at
    the frame) from the perturbation covariances and joint noise (rotation rows of eq. 18)."""
    C = np.zeros((len(stops), 3, 3))
    for jn, F in Fx.items():
        if jn in pert:
            C += F[:, 3:] @ pert[jn] @ np.swapaxes(F[:, 3:], -1, -2)
    for jn, sd in jnoise.items():
        if jn in Fq:
            C += sd ** 2 * Fq[jn][:, 3:, None] * Fq[jn][:, None, 3:]
    return C


def _point_covariance(tree: KinematicTree, stops: Stops, poses: Mapping, dq: Mapping, dxi: Mapping,
                      pert: Mapping[str, np.ndarray], jnoise: Mapping[str, float]) -> np.ndarray:
    """First-order PPOE covariance (N, 3, 3) of the measured point in the base/root frame axes,
    from the perturbation covariances (tangent right after each joint's origin) and joint noise."""
    Jq, Jx = tree.point_jacobian(stops.q, stops.link, stops.point, poses, dq, dxi)
    C = np.zeros((len(stops), 3, 3))
    for jn, J in Jx.items():
        if jn in pert:
            C += J @ pert[jn] @ np.swapaxes(J, -1, -2)
    for jn, s in jnoise.items():
        if jn in Jq:
            C += s ** 2 * Jq[jn][:, :, None] * Jq[jn][:, None, :]
    return C


def _scores(R: np.ndarray) -> dict[str, float]:
    """Error statistics of residuals (n, 3) [m] in a z-up frame: RMS 3D, max 3D, r95 xy, r95 z."""
    R = R[np.all(np.isfinite(R), axis=1)]
    if not R.size:
        return {"n": 0}
    n3 = np.linalg.norm(R, axis=1)
    return {"n": int(R.shape[0]), "rms": float(np.sqrt(np.mean(n3 ** 2))), "max": float(n3.max()),
            "r95_xy": float(np.percentile(np.linalg.norm(R[:, :2], axis=1), 95)),
            "r95_z": float(np.percentile(np.abs(R[:, 2]), 95))}


def _refit_sigma(tree: KinematicTree, stops: Stops, poses: Mapping, dq: Mapping, dxi: Mapping,
                 pert: Mapping[str, np.ndarray], jnoise: Mapping[str, float], Rb: np.ndarray
                 ) -> tuple[float, float, float, dict[str, float] | None]:
    """Scale ``k`` of the model covariance so that the mean held-out NEES is 3.

    ``C_i = k^2 C_model,i + sigma^2 I`` with ``C_model`` the first-order PPOE covariance of the
    measured point (base-frame axes) and ``Rb`` the held-out residuals in base-frame axes.
    A model without any uncertainty gets a common joint noise ``k`` [rad or m] on the movable
    joints of the chain instead.  Returns ``(NEES at k=1, NEES at k, k, fitted joint noise)``.
    """
    fitted: dict[str, float] | None = None
    if pert or jnoise:
        C_model = _point_covariance(tree, stops, poses, dq, dxi, pert, jnoise)
    else:
        unit = {j: 1.0 for j in tree.robot.path_from_root(stops.link) if tree.robot.joints[j].independent}
        C_model = _point_covariance(tree, stops, poses, dq, dxi, {}, unit)
    ok = np.all(np.isfinite(Rb), axis=1)
    if not ok.any():
        return float("nan"), float("nan"), 1.0, None
    S0 = stops.sigma ** 2 * np.eye(3)

    def nees(k: float) -> float:
        C = k * k * C_model[ok] + S0
        return float(np.mean(np.einsum("ni,nij,nj->n", Rb[ok], np.linalg.inv(C), Rb[ok])))

    n1 = nees(1.0) if (pert or jnoise) else float("nan")
    lo, hi = 1e-9, 1e4
    if nees(lo) <= 3.0:
        k = lo
    elif nees(hi) >= 3.0:
        k = hi
    else:
        for _ in range(100):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if nees(mid) > 3.0 else (lo, mid)
        k = math.sqrt(lo * hi)
    if not (pert or jnoise):
        fitted = {j: float(k) for j in tree.robot.path_from_root(stops.link) if tree.robot.joints[j].independent}
    return n1, nees(k), k, fitted


# =============================================================================
# Bags, model YAML, report
# =============================================================================


def stops_from_motoman(path: str | Path, robot: Robot, tracker_link: str = "LR1",
                       sigma: float = 2e-4) -> Stops:
    """The Leica tracker points of a Motoman ``.mat`` file (``../shared/datasets/motoman_leica``)
    as :class:`Stops` (one pose per row, poses without a Leica point dropped; one registration
    session per file; ``sigma`` is an assumed tracker noise, the files give none)."""
    from ppoe_core.io.importers.motoman import JOINT_NAMES, load_motoman

    ds = load_motoman(path)
    ok = ds.has_tracker
    J = ds.joints[ok]
    n = int(ok.sum())
    name = Path(path).stem
    return Stops(q={j: J[:, i] for i, j in enumerate(JOINT_NAMES)}, p_meas=ds.leica[ok], kind="point",
                 link=tracker_link, point=np.zeros(3), sigma=sigma, base=robot.root,
                 session=np.zeros(n, dtype=int), session_names=[name], group=np.zeros(n, dtype=int),
                 group_names=[name], reg_mask=np.ones(n, dtype=bool), score_mask=np.ones(n, dtype=bool),
                 context={"motion_sign": {j: s for j, s in zip(JOINT_NAMES, motion_signs(
                     np.arange(n, dtype=float), J, np.arange(n, dtype=float)).T)}})


def protocol_scores(robot: Robot, stops: Stops, effects: Sequence[Effect] = ()) -> dict[str, float]:
    """Score a model with ``effects`` by the stationing protocol, with nothing fitted but the
    registrations: per session Kabsch on the ``reg_mask`` stops, error of the ``score_mask``
    stops (measured minus predicted, measurement frame).  Returns RMS / max 3D, r95 xy and z [m]
    and ``n`` (see the Hilti README "Baseline").
    """
    tree = KinematicTree(robot)
    x = _predict_nominal(tree, stops, list(effects))[0]
    problem = LinearProblem(stops, x, None)
    G0 = np.zeros((len(stops), 3, 0))
    regs = problem.kabsch_regs(G0, np.zeros(0), np.flatnonzero(stops.reg_mask))
    rows = np.flatnonzero(stops.score_mask & ~stops.reg_mask & np.isin(stops.session, list(regs)))
    return _scores(problem.residuals(G0, np.zeros(0), regs, rows))


def _stop_info(path: str | Path) -> list[tuple[float, dict]]:
    """``/dataset/stop`` JSON objects of a bag (importer metadata), with their stamps."""
    from ppoe_core.io import bagio

    out = []
    for msg in bagio.iter_raw(path, ["/dataset/stop"]):
        m = bagio.deserialize(msg.data, msg.msgtype, topic=msg.topic)
        try:
            out.append((msg.stamp_ns * 1e-9, json.loads(m.data)))
        except (ValueError, AttributeError) as exc:
            raise BagError(f"bag {path}: topic /dataset/stop: message is not JSON: {exc}") from None
    return out


def _sample_joint(t: np.ndarray, v: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Joint values at times ``at``: linear interpolation between samples, but the last sample
    is held across a gap longer than 5 median sample periods (a static stop's burst followed
    by its measurements, CONTRACT sec. 3)."""
    if t.size == 0:
        return np.full(at.shape, np.nan)
    if t.size == 1:
        return np.full(at.shape, v[0])
    dt = np.diff(t)
    gap = 5.0 * float(np.median(dt[dt > 0])) if np.any(dt > 0) else 0.0
    i = np.clip(np.searchsorted(t, at, side="right") - 1, 0, t.size - 1)
    j = np.minimum(i + 1, t.size - 1)
    hold = (t[j] - t[i]) > gap
    return np.where(hold | (at <= t[0]), v[i], np.interp(at, t, v))


def stops_from_bag(path: str | Path, robot: Robot, *, tracker_link: str | None = None,
                   tracker_xyz: Sequence[float] = (0.0, 0.0, 0.0), tracker_sigma: float = 5e-4,
                   base: str | None = None, tool: str | None = None, pose_sigma: float = 5e-4,
                   pose_sigma_rot: float = 1e-3, stationing_set: str | None = "cross",
                   group_name: str | None = None, measurement: str = "auto") -> Stops:
    """Measurements of a contract bag as :class:`Stops`.

    ``/ground_truth/point`` (preferred by ``measurement="auto"``) or ``/ground_truth/pose``
    (``measurement="point"`` / ``"pose"`` forces one); joint values are interpolated
    at each measurement stamp; context ``time``, ``motion_sign`` and ``joint_velocity`` come
    from ``/joint_states``, ``gravity`` (direction in the root frame) from the first ``/imu/<name>``
    on a link rigidly fixed to the root, if any.  One registration session per bag unless the bag carries importer
    metadata ``/dataset/stop`` (``station``, ``role``, ``point_sets``): then one session per
    station, stationing stops (of ``stationing_set`` if given) define the registration and
    evaluation stops are scored.
    """
    from ppoe_core.io import bagio

    data = bagio.read_bag(path, load_images=False)
    js = data.joint_states
    if len(js) == 0:
        raise BagError(f"bag {path}: no /joint_states")
    name = group_name or Path(path).name
    if measurement not in ("auto", "point", "pose"):
        raise PpoeError(f"diagnose: measurement must be auto, point or pose, not {measurement!r}")
    use_point = len(data.ground_truth_point) > 0 and measurement in ("auto", "point")
    use_pose = len(data.ground_truth_pose) > 0 and measurement in ("auto", "pose")
    if use_point:
        kind, meas, stamps = "point", data.ground_truth_point.p, data.ground_truth_point.stamps
        link = tracker_link
        if link is None:
            raise ModelConfigError(f"bag {path} has /ground_truth/point but neither --tool nor the "
                                   f"model's tracker.link names the link carrying the reflector")
        point = np.asarray(tracker_xyz, dtype=float)
        sigma, R_meas = tracker_sigma, None
    elif use_pose:
        kind, stamps = "pose", data.ground_truth_pose.stamps
        frame_ids = set(data.ground_truth_pose.frame_ids)
        if base is not None and frame_ids - {base}:
            raise BagError(f"bag {path}: /ground_truth/pose is in frame(s) {sorted(frame_ids)}, "
                           f"not the base frame {base!r} given by --base/frames.base")
        base = base or next(iter(frame_ids))
        meas, R_meas = data.ground_truth_pose.T[:, :3, 3], data.ground_truth_pose.T[:, :3, :3]
        link = tool
        if link is None:
            raise ModelConfigError(f"bag {path} has /ground_truth/pose but no --tool/frames.tool")
        point, sigma = np.zeros(3), pose_sigma
    else:
        raise BagError(f"bag {path}: no /ground_truth/point or /ground_truth/pose "
                       f"(measurement={measurement}): nothing to diagnose against")
    robot.check_link(link)
    order = np.argsort(js.stamps, kind="stable")
    t_js = js.stamps[order]
    q: dict[str, np.ndarray] = {}
    vel: dict[str, np.ndarray] = {}
    pos_cols = []
    jnames = [j for j in robot.independent_joints if j in js.names]
    missing = [j for j in robot.path_from_root(link) if robot.joints[j].independent and j not in js.names]
    if missing:
        raise BagError(f"bag {path}: /joint_states never carries {missing} (needed for link {link})")
    for jn in jnames:
        col = js.positions[order, js.names.index(jn)]
        good = np.isfinite(col)
        tg, cg = t_js[good], col[good]
        q[jn] = _sample_joint(tg, cg, stamps)
        pos_cols.append(np.interp(t_js, tg, cg))
        v = np.gradient(cg, tg) if good.sum() > 1 else np.zeros(good.sum())
        vel[jn] = _sample_joint(tg, v, stamps)
    signs = motion_signs(t_js, np.column_stack(pos_cols), stamps) if pos_cols else np.zeros((len(stamps), 0))
    ctx = {"time": stamps - t_js[0], "motion_sign": {j: signs[:, i] for i, j in enumerate(jnames)},
           "joint_velocity": vel}
    # gravity direction in the root frame from an accelerometer on a link rigidly fixed to the root
    tree = KinematicTree(robot)
    for imu_name, imu in sorted(data.imus.items()):
        frame = imu.frame_ids[0] if imu.frame_ids else ""
        if (len(imu) and frame in robot.links
                and not any(robot.joints[j].movable for j in robot.path_from_root(frame))):
            R = tree.link_poses({}, links=[frame])[frame][:3, :3]
            a = imu.linear_acceleration / np.linalg.norm(imu.linear_acceleration, axis=1)[:, None]
            g = -np.column_stack([_sample_joint(imu.stamps, a[:, k], stamps) for k in range(3)]) @ R.T
            ctx["gravity"] = g / np.linalg.norm(g, axis=1)[:, None]
            break
    imus: dict[str, tuple[str, np.ndarray]] = {}
    for imu_name, imu in sorted(data.imus.items()):
        frame = imu.frame_ids[0] if imu.frame_ids else ""
        if len(imu) and frame in robot.links:
            imus[imu_name] = (frame, np.column_stack([_sample_joint(imu.stamps, imu.linear_acceleration[:, k], stamps)
                                                      for k in range(3)]))
    n = len(stamps)
    session = np.zeros(n, dtype=int)
    session_names = [name]
    reg = np.ones(n, dtype=bool)
    score = np.ones(n, dtype=bool)
    info = _stop_info(path) if "/dataset/stop" in data.topics else []
    if info:
        t_info = np.array([t for t, _ in info])
        k = np.clip(np.searchsorted(t_info, stamps, side="right") - 1, 0, len(info) - 1)
        stations = [info[i][1].get("station", "?") for i in k]
        session_names = [f"{name}:{s}" for s in dict.fromkeys(stations)]
        session = np.array([session_names.index(f"{name}:{s}") for s in stations])
        roles = [info[i][1].get("role", "") for i in k]
        sets = [info[i][1].get("point_sets", []) for i in k]
        reg = np.array([r == "stationing" and (stationing_set is None or stationing_set in s)
                        for r, s in zip(roles, sets)])
        score = np.array([r == "evaluation" for r in roles])
    return Stops(q=q, p_meas=np.asarray(meas, dtype=float), R_meas=R_meas, kind=kind, link=link, point=point,
                 sigma=float(sigma), sigma_rot=pose_sigma_rot, base=base or robot.root, session=session,
                 session_names=session_names, group=np.zeros(n, dtype=int), group_names=[name],
                 reg_mask=reg, score_mask=score, context=ctx, imus=imus)


def stops_from_hilti(path: str | Path, robot: Robot, stationing_set: str | None = "cross",
                     tracker_link: str = "prism", sigma: float = 0.75e-3) -> Stops:
    """A Hilti stationing dataset file (``../shared/datasets/hilti_stationing/*.yaml``) as
    :class:`Stops`, read directly (same content as its ``ppoe import hilti`` bag).

    One registration session per station (column height, solution space); the stationing points
    of ``stationing_set`` define it when scored, evaluation points are scored (README protocol);
    context ``time`` and ``motion_sign`` from the time-ordered waypoints, and ``gravity`` (the
    direction of gravity in ``base_link``) from the base accelerometer ``tilt_sensor_base``
    (mounted with rpy 0 on ``column_base``, which has rpy 0 in ``base_link``), so gravity
    torques and moments follow the tilt of the robot on uneven ground.
    """
    from ppoe_core.io.importers.hilti import load_hilti

    ds = load_hilti(path)
    stops = ds.stops
    J = np.array([s.joints for s in stops])
    t = np.array([s.time for s in stops])
    a_base = np.array([s.accel_base for s in stops])  # specific force: points up
    q = {name: J[:, i] for i, name in enumerate(ds.joint_names)}
    signs = motion_signs(t, J, t)
    name = Path(path).stem
    stations = list(dict.fromkeys(s.station for s in stops))
    return Stops(
        q=q, p_meas=np.array([s.prism_position for s in stops]), kind="point", link=tracker_link,
        point=np.zeros(3), sigma=sigma, base=robot.root,
        session=np.array([stations.index(s.station) for s in stops]),
        session_names=[f"{name}:{st}" for st in stations], group=np.zeros(len(stops), dtype=int),
        group_names=[name],
        reg_mask=np.array([s.role == "stationing" and (stationing_set is None or stationing_set in s.point_sets)
                           for s in stops]),
        score_mask=np.array([s.role == "evaluation" and s.solution_space != 4 for s in stops]),
        context={"time": t - t[0], "motion_sign": {n: signs[:, i] for i, n in enumerate(ds.joint_names)},
                 "gravity": -a_base / np.linalg.norm(a_base, axis=1)[:, None]},
        imus={"base": ("tilt_sensor_base", a_base),
              "column_tip": ("tilt_sensor_column_tip", np.array([s.accel_column_tip for s in stops]))},
    )


def write_model_yaml(model_yaml: str | Path | Mapping | None, result: DiagnoseResult, out_path: str | Path,
                     scale_sigmas: bool = True) -> Path:
    """Updated model YAML: the input plus the found ``effects`` (with ``ci``) and, if
    ``scale_sigmas``, perturbation sigmas / covariances and joint noise scaled by the NEES fit.
    Comments of the input are not preserved (a header says where it came from)."""
    if model_yaml is None:
        doc: dict[str, Any] = {}
    elif isinstance(model_yaml, Mapping):
        doc = dict(model_yaml)
    else:
        with open(model_yaml, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh) or {}
    effects = list(doc.get("effects") or [])
    for e in result.effects:
        entry = {"name": e["name"], "location": e["location"], "parameters": e["parameters"]}
        for key in ("variable", "reference"):
            if key in e:
                entry[key] = e[key]
        entry["ci"] = {k: [float(a), float(b)] for k, (a, b) in e["ci"].items()}
        effects.append(entry)
    doc["effects"] = effects
    k = result.sigma_scale
    if scale_sigmas and math.isfinite(k):
        pert = doc.get("perturbations") or {}
        if pert:
            for jn, entry in pert.items():
                if "sigma" in entry:
                    entry["sigma"] = [float(v * k) for v in entry["sigma"]]
                if "covariance" in entry:
                    entry["covariance"] = [[float(v * k * k) for v in row] for row in entry["covariance"]]
            jn_sec = doc.get("joint_noise") or {}
            for jn in list(jn_sec):
                jn_sec[jn] = float(jn_sec[jn] * k)
        elif not doc.get("joint_noise") and result.extra.get("fitted_joint_noise"):
            doc["joint_noise"] = result.extra["fitted_joint_noise"]
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    header = ("# Model updated by `ppoe diagnose`: effects found (with 95 % CIs) appended to `effects`,\n"
              f"# perturbation sigmas scaled by {k:.4g} for held-out NEES = 3.\n")
    out_path.write_text(header + yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return out_path


def write_report(result: DiagnoseResult, out_dir: str | Path, title: str = "ppoe diagnose") -> dict[str, Path]:
    """``diagnose.json``, ``diagnose.md`` and ``diagnose.png`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "diagnose.json", "md": out / "diagnose.md", "png": out / "diagnose.png"}
    paths["json"].write_text(json.dumps(result.to_json(), indent=2), encoding="utf-8")
    lines = [f"# {title}", "", result.summary, "",
             f"* held-out residual (RMS 3D, {result.cv} cross-validation, {result.n_stops} stops, "
             f"{result.n_sessions} sessions): before **{1e3 * result.residual_before:.3f} mm**, after "
             f"**{1e3 * result.residual_after:.3f} mm**",
             f"* in-sample: {1e3 * result.residual_before_insample:.3f} mm -> "
             f"{1e3 * result.residual_after_insample:.3f} mm; noise floor (declared PPOE covariance + sensor noise) "
             f"{1e3 * result.noise_floor:.3f} mm; unexplained above it {1e3 * result.unexplained:.3f} mm",
             f"* NEES (held-out, expectation 3): {result.nees_before:.3g} with the model's sigmas, "
             f"{result.nees_after:.3g} after scaling them by {result.sigma_scale:.4g}",
             f"* linearisation error of the selection stage at the final estimate (the final fit is "
             f"relinearised on the full chain): {1e6 * result.linearisation_error:.3f} um", "",
             "| effect | location | parameter | value | 95 % CI | share of residual |",
             "|---|---|---|---|---|---|"]
    for e in result.effects:
        for i, (k, v) in enumerate(e["parameters"].items()):
            lo, hi = e["ci"][k]
            share = f"{100 * e['share']:.1f} %" if i == 0 else ""
            lines.append(f"| {e['name'] if i == 0 else ''} | {e['location'] if i == 0 else ''} | {k} | "
                         f"{v:.6g} | [{lo:.6g}, {hi:.6g}] | {share} |")
    if not result.effects:
        lines.append("| (none) | | | | | |")
    if result.extra.get("imu_tilt"):
        lines += ["", "## Accelerometer tilt residuals (not used by the fit; per-session mean removed)", "",
                  "| IMU | link | stops | RMS rx, ry before [mrad] | after [mrad] |", "|---|---|---|---|---|"]
        for k, v in result.extra["imu_tilt"].items():
            lines.append(f"| {k} | {v['link']} | {v['n']} | {1e3 * v['rms_before'][0]:.3f}, "
                         f"{1e3 * v['rms_before'][1]:.3f} | {1e3 * v['rms_after'][0]:.3f}, "
                         f"{1e3 * v['rms_after'][1]:.3f} |")
    fit = result.extra.get("imu_fit")
    if fit:
        lines += ["", "## Accelerometer stage (base tilt per bag/file, effects seen by the IMUs)", "",
                  f"Reference IMU (its mounting is part of the base tilt): {fit['reference_imu']}. "
                  "Held-out tilt RMS per IMU, rx / ry [mrad]: "
                  + ", ".join(f"{k} {1e3 * b[0]:.3f} / {1e3 * b[1]:.3f} -> {1e3 * fit['tilt_rms_after'][k][0]:.3f}"
                              f" / {1e3 * fit['tilt_rms_after'][k][1]:.3f}" for k, b in fit["tilt_rms_before"].items())
                  + ".", ""]
        for e in fit["effects"]:
            if e["name"] == "base_tilt":
                for g, v in e["per_group"].items():
                    lines.append(f"* base_tilt {g}: tilt_x {1e3 * v['tilt_x']:.3f} mrad "
                                 f"[{1e3 * v['ci']['tilt_x'][0]:.3f}, {1e3 * v['ci']['tilt_x'][1]:.3f}], "
                                 f"tilt_y {1e3 * v['tilt_y']:.3f} mrad "
                                 f"[{1e3 * v['ci']['tilt_y'][0]:.3f}, {1e3 * v['ci']['tilt_y'][1]:.3f}]")
            else:
                lines.append(f"* {e['name']}@{e['location']}: " + ", ".join(
                    f"{k} {v:.4g} [{e['ci'][k][0]:.4g}, {e['ci'][k][1]:.4g}]" for k, v in e["parameters"].items()))
        if not fit["effects"]:
            lines.append("* nothing found (no base tilt, no IMU-visible effect)")
    if result.extra.get("pixels"):
        px = result.extra["pixels"]
        lines += ["", f"## Tag pixels ({px['n']} points; effects marked `measurement: pixels` above, share = of "
                  "the pixel residual)", ""]
        if "pixel_rms_declared_only" in px:
            lines += ["In-sample RMS with only the declared effects (without the tracker/pose effects above): "
                      + ", ".join(f"{f} {v:.2f} px" for f, v in px["pixel_rms_declared_only"].items()), ""]
        lines += ["| camera frame | held-out RMS before [px] | after [px] | in-sample before | after |",
                  "|---|---|---|---|---|"]
        for f in px["pixel_rms_before"]:
            lines.append(f"| {f} | {px['pixel_rms_before'][f]:.2f} | {px['pixel_rms_after'][f]:.2f} | "
                         f"{px['pixel_rms_before_insample'][f]:.2f} | {px['pixel_rms_after_insample'][f]:.2f} |")
    lines += ["", "## Selection steps", "", "| candidate | accepted | held-out RMS [mm] | gain | t |",
              "|---|---|---|---|---|"]
    for s in result.steps:
        lines.append(f"| {s['candidate']} | {s['accepted']} | {1e3 * s['heldout_rms']:.3f} | "
                     f"{100 * s['gain']:.1f} % | {s['t']:.2f} |")
    if result.rejected:
        lines += ["", "## Not identifiable (never attributed)", ""]
        lines += [f"* {r['candidate']}: {r['reason']}" for r in result.rejected]
    paths["md"].write_text("\n".join(lines) + "\n", encoding="utf-8")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ok = np.isfinite(result.e2_before) & np.isfinite(result.e2_after)
        eb, ea = 1e3 * np.sqrt(result.e2_before[ok]), 1e3 * np.sqrt(result.e2_after[ok])
        bins = np.linspace(0, max(eb.max(initial=1e-3), ea.max(initial=1e-3)), 40)
        ax[0].hist(eb, bins, alpha=0.6, label="before")
        ax[0].hist(ea, bins, alpha=0.6, label="after")
        ax[0].set_xlabel("held-out 3D error [mm]")
        ax[0].legend()
        rms = [1e3 * result.residual_before] + [1e3 * s["heldout_rms"] for s in result.steps if s["accepted"]]
        ax[1].plot(range(len(rms)), rms, "o-")
        ax[1].axhline(1e3 * result.noise_floor, ls="--", color="k", label="noise floor")
        ax[1].set_xticks(range(len(rms)), ["nominal"] + [f"+{e['name']}\n{e['location']}" for e in result.effects
                                                         if e.get("measurement") != "pixels"],
                         fontsize=6, rotation=30)
        ax[1].set_ylabel("held-out RMS [mm]")
        ax[1].legend()
        fig.tight_layout()
        fig.savefig(paths["png"], dpi=100)
        plt.close(fig)
    except ImportError:  # matplotlib is optional for the report
        paths.pop("png")
    return paths


def load_model(model_yaml: str | Path | None, robot: Robot) -> tuple[Any, list[Effect], dict, dict]:
    """Model YAML -> (config, declared effects, perturbation covariances, joint noise)."""
    from ppoe_core.robot.config import load_model_config

    cfg = load_model_config(str(model_yaml) if model_yaml is not None else None, robot)
    tree = KinematicTree(robot)
    declared = [effect_from_config(e, tree, where=w) for e, w in
                zip(cfg.effects, cfg.effect_wheres or [f"{model_yaml} effects[{i}]" for i in range(len(cfg.effects))])]
    pert = {j: p.covariance for j, p in cfg.perturbations.items()}
    return cfg, declared, pert, dict(cfg.joint_noise)


# =============================================================================
# Marker pixels: reprojection residuals and camera_extrinsics
# =============================================================================


@dataclass
class PixelObs:
    """Marker-centre pixels: one row per (pose, marker, camera) observation.

    Attributes
    ----------
    q : dict joint -> ndarray, shape (M,)
        Joint values of each observation [rad, m].
    link : str
        Link that carries the markers (e.g. ``EE1`` or ``tool0``).
    point : ndarray, shape (M, 3)
        Marker origin (the point whose image is measured) in ``link`` coordinates [m].
    camera : ndarray, shape (M,), int
        Index into ``cameras``.
    cameras : list[str]
        Camera optical frames (URDF links; z forward, x right, y down).
    K : list of ndarray (3, 3); D : list of ndarray (5,)
        Intrinsics [px] and plumb_bob distortion of each camera.
    uv : ndarray, shape (M, 2)
        Measured raw (distorted) pixels.
    pose : ndarray, shape (M,), int
        Robot pose index of each observation (cross-validation folds keep a pose together).
    sigma_px : float
        Pixel noise, 1-sigma per axis [px]: residuals are whitened with it.
    name : str
        Source (file or bag), used in messages.
    context : dict
        Effect context per observation (``motion_sign``: joint -> (M,), ``time`` (M,),
        ``joint_velocity``: joint -> (M,)), as in :class:`Stops`.
    """

    q: dict[str, np.ndarray]
    link: str
    point: np.ndarray
    camera: np.ndarray
    cameras: list[str]
    K: list[np.ndarray]
    D: list[np.ndarray]
    uv: np.ndarray
    pose: np.ndarray
    sigma_px: float = 1.0
    name: str = ""
    context: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def subset(self, rows: np.ndarray) -> PixelObs:
        """The observations ``rows`` (index or boolean array)."""
        return PixelObs(q={k: v[rows] for k, v in self.q.items()}, link=self.link, point=self.point[rows],
                        camera=self.camera[rows], cameras=self.cameras, K=self.K, D=self.D, uv=self.uv[rows],
                        pose=self.pose[rows], sigma_px=self.sigma_px, name=self.name,
                        context=_map_ctx(lambda v: v[rows], [self.context]))


def _map_ctx(fn: Any, ctxs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Apply ``fn`` to the per-observation arrays of one or several contexts (keys of the first;
    nested joint dictionaries kept)."""
    out: dict[str, Any] = {}
    for k, v in ctxs[0].items():
        if isinstance(v, Mapping):
            out[k] = {j: fn(*[c[k][j] for c in ctxs]) for j in v if all(j in c.get(k, {}) for c in ctxs)}
        elif all(k in c for c in ctxs):
            out[k] = fn(*[c[k] for c in ctxs])
    return out


def pixels_from_motoman(path: str | Path, robot: Robot, model_yaml: str | Path,
                        sigma_px: float = 1.0) -> PixelObs:
    """Marker pixels of a Motoman ``.mat`` file (``../shared/datasets/motoman_leica``).

    Markers hang on ``EE1`` (poses from the dataset's ``model.yaml``); cameras 1 and 2 are
    ``camera_1_optical_frame`` / ``camera_2_optical_frame`` of ``motoman_right.urdf``.
    """
    from ppoe_core.io.importers.motoman import (CAMERA_FRAMES, JOINT_NAMES, load_marker_poses, load_motoman,
                                    load_motoman_cameras)

    ds = load_motoman(path)
    cams = load_motoman_cameras(model_yaml)
    markers = load_marker_poses(model_yaml)
    for f in CAMERA_FRAMES.values():
        if f not in robot.links:
            raise ModelConfigError(f"{path}: camera frame '{f}' is not a link of URDF {robot.source}")
    missing = sorted(set(ds.obs_face.tolist()) - set(markers))
    if missing:
        raise ModelConfigError(f"{model_yaml}: markers/poses has no entry for faces {missing} used in {path}")
    order = sorted(cams)
    point = np.array([markers[int(f)][:3, 3] for f in ds.obs_face])
    J = ds.joints[ds.obs_pose]
    P = len(ds.pose_ids)
    # motion sign: the poses are taken as visited in file order (as stops_from_motoman)
    signs = motion_signs(np.arange(P, dtype=float), ds.joints, np.arange(P, dtype=float))[ds.obs_pose]
    ctx = {"motion_sign": {j: signs[:, i] for i, j in enumerate(JOINT_NAMES)},
           "time": ds.obs_pose.astype(float)}
    return PixelObs(q={j: J[:, i] for i, j in enumerate(JOINT_NAMES)}, link="EE1", point=point, context=ctx,
                    camera=np.array([order.index(int(c)) for c in ds.obs_camera]),
                    cameras=[cams[n].frame for n in order], K=[cams[n].K for n in order],
                    D=[cams[n].D for n in order], uv=ds.obs_uv.copy(), pose=ds.obs_pose.copy(),
                    sigma_px=float(sigma_px), name=Path(path).stem)


def _camera_points(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect]
                   ) -> tuple[np.ndarray, dict, dict, dict]:
    """Marker points in their camera's optical frame, shape (M, 3) [m], with the chain used."""
    dq, dxi = apply_corrections(list(effects), obs.q, obs.context)
    poses = tree.link_poses(obs.q, dq, dxi, links=[obs.link, *obs.cameras])
    p_root = np.einsum("mij,mj->mi", poses[obs.link][:, :3, :3], obs.point) + poses[obs.link][:, :3, 3]
    P = np.empty_like(p_root)  # filled per camera
    for c, frame in enumerate(obs.cameras):
        m = obs.camera == c
        T = poses[frame][m]
        P[m] = np.einsum("mji,mj->mi", T[:, :3, :3], p_root[m] - T[:, :3, 3])
    return P, poses, dq, dxi


def predict_pixels(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> np.ndarray:
    """Predicted raw pixels (M, 2): marker origin on ``obs.link`` -> root -> camera optical frame,
    projected with the intrinsics and plumb_bob distortion (:func:`ppoe_core.sensing.tags.project_points`).

    Raises
    ------
    MeasurementError
        A marker is behind its camera (names the source and the observation row).
    """
    from ppoe_core.sensing.tags import project_points

    P = _camera_points(tree, obs, effects)[0]
    bad = P[:, 2] <= 1e-6
    if np.any(bad):
        raise MeasurementError(f"{obs.name}: observation {int(np.flatnonzero(bad)[0])}: marker is behind "
                               f"camera '{obs.cameras[int(obs.camera[bad][0])]}' (z = {P[bad][0, 2]:.3g} m)")
    uv = np.empty((len(obs), 2))
    for c in range(len(obs.cameras)):
        m = obs.camera == c
        uv[m] = project_points(P[m], obs.K[c], obs.D[c])
    return uv


def _projection_jacobian(P: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """``d uv / d P`` (M, 2, 3) of the plumb_bob projection at camera-frame points ``P`` (M, 3)."""
    import cv2

    if len(P) == 0:
        return np.zeros((0, 2, 3))
    _, jac = cv2.projectPoints(P.reshape(-1, 3), np.zeros(3), np.zeros(3), np.asarray(K, float),
                               np.asarray(D, float).reshape(-1))
    # columns: d/d rvec (3), d/d tvec (3), ...; with rvec = tvec = 0, d/d tvec = d/d P
    return jac[:, 3:6].reshape(len(P), 2, 3)


def pixel_chain_jacobians(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()
                          ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Analytic derivatives of the predicted pixels w.r.t. the eq. 16 insertions, on the chain
    corrected by ``effects``.

    With the right perturbations ``xi_cam`` of ``T_root_cam`` and ``xi_l`` of ``T_root_link``
    (:meth:`KinematicTree.frame_jacobian`),
    ``dP_cam = R_cam^T R_l [I, -[p]x] xi_l + [-I, [P_cam]x] xi_cam``, then the plumb_bob
    projection Jacobian ``d uv / d P_cam``.

    Returns
    -------
    J_dq : dict joint -> ndarray (M, 2)
        ``d uv / d dq_j`` [px/rad or px/m].
    J_dxi : dict joint -> ndarray (M, 2, 6)
        ``d uv / d dxi_j`` (tangent right after joint ``j``'s origin, ``[rho; theta]``).
    """
    P, poses, dq, dxi = _camera_points(tree, obs, effects)
    n = len(obs)
    Jq_l, Jx_l = tree.frame_jacobian(obs.q, obs.link, poses, dq, dxi)
    R_l = poses[obs.link][:, :3, :3]
    B_l = np.concatenate([R_l, -R_l @ lie.hat3(obs.point)], axis=-1)  # (M, 3, 6): d p_root / d xi_l
    A = np.zeros((n, 3, 3))   # d P_cam / d p_root = R_cam^T
    B_c = np.zeros((n, 3, 6))  # d P_cam / d xi_cam
    Jproj = np.zeros((n, 2, 3))
    cam_jac = []
    for c, frame in enumerate(obs.cameras):
        m = obs.camera == c
        if not np.any(m):
            continue
        A[m] = np.swapaxes(poses[frame][m][:, :3, :3], -1, -2)
        B_c[m] = np.concatenate([-np.broadcast_to(np.eye(3), (int(m.sum()), 3, 3)), lie.hat3(P[m])], axis=-1)
        Jproj[m] = _projection_jacobian(P[m], obs.K[c], obs.D[c])
        cam_jac.append((m, tree.frame_jacobian(obs.q, frame, poses, dq, dxi)))
    G_l = Jproj @ A @ B_l  # (M, 2, 6): d uv / d xi_l
    J_dq: dict[str, np.ndarray] = {k: np.einsum("mij,mj->mi", G_l, v) for k, v in Jq_l.items()}
    J_dxi: dict[str, np.ndarray] = {k: G_l @ v for k, v in Jx_l.items()}
    G_c = Jproj @ B_c
    for m, (Jq_c, Jx_c) in cam_jac:
        for k, v in Jq_c.items():  # rows of this camera only
            J_dq[k] = J_dq[k].copy() if k in J_dq else np.zeros((n, 2))
            J_dq[k][m] += np.einsum("mij,mj->mi", G_c[m], v[m])
        for k, v in Jx_c.items():
            J_dxi[k] = J_dxi[k].copy() if k in J_dxi else np.zeros((n, 2, 6))
            J_dxi[k][m] += G_c[m] @ v[m]
    return J_dq, J_dxi


def pixel_jacobian(tree: KinematicTree, obs: PixelObs, effect: Effect,
                   effects: Sequence[Effect] = ()) -> np.ndarray:
    """Analytic derivative (M, 2, P) of the predicted pixels w.r.t. ``effect``'s parameters,
    evaluated on the chain corrected by ``effects``: :func:`pixel_chain_jacobians` times
    :meth:`Effect.basis` (evaluated on the nominal chain)."""
    Jq, Jx = pixel_chain_jacobians(tree, obs, effects)
    Bq, Bx = effect.basis(obs.q, obs.context, tree.link_poses(obs.q))
    out = np.zeros((len(obs), 2, effect.n_params))
    for k, b in Bq.items():
        if k in Jq:
            out = out + Jq[k][:, :, None] * b[:, None, :]
    for k, b in Bx.items():
        if k in Jx:
            out = out + Jx[k] @ b
    return out


def pixel_covariance(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = (),
                     pert: Mapping[str, np.ndarray] | None = None,
                     jnoise: Mapping[str, float] | None = None) -> np.ndarray:
    """Expected covariance (M, 2, 2) of each pixel residual [px^2], image axes: the first-order
    PPOE covariance (paper eq. 18 to first order: ``pert`` = 6x6 covariances of the insertions,
    tangent right after each joint's origin; ``jnoise`` = joint 1-sigma [rad, m]) propagated
    through :func:`pixel_chain_jacobians`, plus ``obs.sigma_px^2 I``."""
    C = np.broadcast_to(float(obs.sigma_px) ** 2 * np.eye(2), (len(obs), 2, 2)).copy()
    if pert or jnoise:
        Jq, Jx = pixel_chain_jacobians(tree, obs, effects)
        for jn, S in (pert or {}).items():
            if jn in Jx:
                C += Jx[jn] @ np.asarray(S, float) @ np.swapaxes(Jx[jn], -1, -2)
        for jn, sg in (jnoise or {}).items():
            if jn in Jq:
                C += float(sg) ** 2 * Jq[jn][:, :, None] * Jq[jn][:, None, :]
    return C


def camera_mount_joint(robot: Robot, frame: str) -> str:
    """The fixed joint a ``camera_extrinsics`` correction of camera ``frame`` sits at: the first
    fixed joint after the last movable joint on the path from the root to ``frame``."""
    if frame not in robot.links:
        raise ModelConfigError(f"camera frame '{frame}' is not a link of URDF {robot.source}")
    path = robot.path_from_root(frame)
    if not path:
        raise ModelConfigError(f"camera frame '{frame}' is the root link of URDF {robot.source}")
    k = len(path)
    while k > 0 and not robot.joints[path[k - 1]].movable:
        k -= 1
    if k == len(path):
        raise ModelConfigError(f"camera frame '{frame}' hangs on movable joint '{path[-1]}' (URDF {robot.source})")
    return path[k]


def pixel_candidates(robot: Robot, obs: PixelObs) -> list[Effect]:
    """Candidate effects of the pixel residual: ``camera_extrinsics`` (6-DoF) at the mount joint
    of every camera that has observations (:func:`camera_mount_joint`)."""
    tree = KinematicTree(robot)
    out: list[Effect] = []
    for c, frame in enumerate(obs.cameras):
        if np.any(obs.camera == c):
            out.append(make_effect("camera_extrinsics", camera_mount_joint(robot, frame), tree))
    return out


@dataclass
class PixelDiagnosis:
    """Result of :func:`diagnose_pixels`.

    ``effects``: list of ``{name, location, frame, parameters, ci, sigma, share}`` (``ci``: 95 %
    interval per parameter; ``location`` the camera's mount joint, ``frame`` its optical frame);
    ``rms_before`` / ``rms_after``: held-out (cross-validated over poses) pixel RMS per camera
    frame [px], the norm of the 2D error; ``*_insample``: the same on all data with the final fit;
    ``steps`` and ``rejected``: the selection; ``fitted``: the effect objects (parameters set).
    ``noise_floor``: per camera, the RMS [px] the expected covariance (:func:`pixel_covariance`)
    predicts; ``unexplained``: held-out RMS above it [px]; ``nees_before`` / ``nees_after``:
    held-out mean squared Mahalanobis distance per point (expectation 2); ``unexplained_flag``:
    ``nees_after`` exceeds 2 by more than 3 standard errors (per-pose means).
    ``stats_before`` / ``stats_after``: in-sample :func:`pixel_stats` (n, RMS, median, max).
    """

    effects: list[dict[str, Any]]
    fitted: list[Effect]
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    rms_before_insample: dict[str, float]
    rms_after_insample: dict[str, float]
    steps: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    sigma_scale: float
    n: int
    noise_floor: dict[str, float] = field(default_factory=dict)
    unexplained: dict[str, float] = field(default_factory=dict)
    nees_before: float = float("nan")
    nees_after: float = float("nan")
    unexplained_flag: bool = False
    stats_before: dict[str, dict[str, float]] = field(default_factory=dict)
    stats_after: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (pixel RMS in px)."""
        return {"effects": self.effects, "pixel_rms_before": self.rms_before, "pixel_rms_after": self.rms_after,
                "pixel_noise_floor": self.noise_floor, "pixel_unexplained": self.unexplained,
                "pixel_nees_before": self.nees_before, "pixel_nees_after": self.nees_after,
                "pixel_unexplained_flag": self.unexplained_flag,
                "pixel_stats_before_insample": self.stats_before, "pixel_stats_after_insample": self.stats_after,
                "pixel_rms_before_insample": self.rms_before_insample,
                "pixel_rms_after_insample": self.rms_after_insample, "steps": self.steps,
                "rejected": self.rejected, "sigma_scale": self.sigma_scale, "n": self.n}


def pixel_stats(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> dict[str, dict[str, float]]:
    """Per camera frame: ``n``, ``rms``, ``median`` and ``max`` of the 2D reprojection error [px]
    (norm of measured minus predicted pixel, every observation counted)."""
    e = np.linalg.norm(obs.uv - predict_pixels(tree, obs, effects), axis=1)
    return {f: {"n": int(np.sum(obs.camera == c)), "rms": float(np.sqrt(np.mean(e[obs.camera == c] ** 2))),
                "median": float(np.median(e[obs.camera == c])), "max": float(np.max(e[obs.camera == c]))}
            for c, f in enumerate(obs.cameras) if np.any(obs.camera == c)}


def pixel_rms(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = ()) -> dict[str, float]:
    """RMS of the 2D reprojection error [px] per camera frame (cameras without rows omitted)."""
    e = obs.uv - predict_pixels(tree, obs, effects)
    return {f: float(np.sqrt(np.mean(np.sum(e[obs.camera == c] ** 2, axis=1))))
            for c, f in enumerate(obs.cameras) if np.any(obs.camera == c)}


def _pose_folds(pose: np.ndarray, folds: int, seed: int = 0) -> list[np.ndarray]:
    """Test masks of ``folds`` folds over poses (all observations of a pose in one fold)."""
    ids = np.unique(pose)
    perm = np.random.default_rng(seed).permutation(ids)
    return [np.isin(pose, perm[k::folds]) for k in range(folds)]


def _lstsq(G: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    H = G.T @ G
    s = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / np.outer(s, s)
    th = np.linalg.solve(Hs + 1e-12 * np.eye(len(s)), (G.T @ r) / s) / s
    return th, Hs


def diagnose_pixels(robot: Robot, obs: PixelObs, declared: Sequence[Effect] = (),
                    candidates: Sequence[Effect] | None = None, folds: int = 5, min_gain: float = 0.03,
                    min_t: float = 4.0, max_condition: float = 1e6, max_effects: int = 4,
                    iterations: int = 3, seed: int = 0, robust: bool = True,
                    pert: Mapping[str, np.ndarray] | None = None,
                    jnoise: Mapping[str, float] | None = None) -> PixelDiagnosis:
    """Trace the marker-pixel residual to ``camera_extrinsics`` (or given candidate) effects.

    The pixel residual (measured minus predicted with ``declared``), whitened by its expected
    covariance (:func:`pixel_covariance`: ``obs.sigma_px`` plus, if given, the declared
    perturbations ``pert`` and joint noise ``jnoise`` propagated to the pixels), is linearised
    at the declared chain, ``e = e0 - G theta``
    (:func:`pixel_jacobian`).  Greedy forward selection as in :func:`diagnose`: a candidate is
    accepted when the column-scaled normal matrix of the chosen set has condition number below
    ``max_condition`` and the held-out mean squared error (``folds``-fold cross-validation over
    poses) drops by at least ``min_gain`` with a paired t statistic >= ``min_t`` over the held-out
    poses.  The final fit is Gauss-Newton on the nonlinear chain (``iterations``); CIs are
    ``theta +- 1.96 sigma``.  With ``robust`` (default) the parameter covariance is the
    cluster-robust sandwich ``H^-1 (sum_pose g g^T) H^-1 * P/(P-1)`` (``g = G_pose^T r_pose``):
    the points seen at one pose share that pose's arm and camera error, so they are not
    independent; otherwise ``s^2 H^-1`` (``s^2`` the whitened residual variance, reported as
    ``sigma_scale``: the factor by which ``obs.sigma_px`` underestimates the residual).

    Raises
    ------
    MeasurementError
        Fewer than ``folds`` poses, or a marker behind its camera.
    """
    tree = KinematicTree(robot)
    declared = list(declared)
    cands = list(candidates) if candidates is not None else pixel_candidates(robot, obs)
    if len(np.unique(obs.pose)) < folds:
        raise MeasurementError(f"{obs.name}: {len(np.unique(obs.pose))} poses with pixels, need >= {folds} folds")
    C = pixel_covariance(tree, obs, declared, pert, jnoise)  # (M, 2, 2) [px^2]
    W = np.linalg.inv(np.linalg.cholesky(C))  # whitening: W C W^T = I
    e_raw = obs.uv - predict_pixels(tree, obs, declared)  # (M, 2) [px]
    e0 = np.einsum("mij,mj->mi", W, e_raw)
    J_raw = [pixel_jacobian(tree, obs, c, declared) for c in cands]  # (M, 2, P) [px / unit]
    Gs = [W @ J for J in J_raw]
    test_masks = _pose_folds(obs.pose, folds, seed)
    poses_u, pose_idx = np.unique(obs.pose, return_inverse=True)

    def heldout(idx: Sequence[int]) -> np.ndarray:
        """Per-pose held-out sum of squared whitened errors with candidates ``idx``."""
        err = np.zeros(len(obs))
        for test in test_masks:
            G = np.concatenate([Gs[i] for i in idx], axis=2) if idx else np.zeros((len(obs), 2, 0))
            r = e0.copy()
            if idx:
                th, _ = _lstsq(G[~test].reshape(-1, G.shape[2]), e0[~test].reshape(-1))
                r = e0 - G @ th
            err[test] = np.sum(r[test] ** 2, axis=1)
        return np.bincount(pose_idx, err, minlength=len(poses_u))

    chosen: list[int] = []
    steps: list[dict[str, Any]] = []
    rejected: list[dict[str, Any]] = []
    base = heldout(chosen)
    hist = [float(base.sum())]
    while len(chosen) < max_effects:
        best = None
        for i in range(len(cands)):
            if i in chosen:
                continue
            idx = chosen + [i]
            G = np.concatenate([Gs[k] for k in idx], axis=2).reshape(-1, sum(Gs[k].shape[2] for k in idx))
            _, Hs = _lstsq(G, e0.reshape(-1))
            cond = float(np.linalg.cond(Hs))
            key = cands[i].describe()
            if not np.isfinite(cond) or cond > max_condition:
                rejected.append({"effect": key, "reason": f"not identifiable (condition {cond:.3g})"})
                continue
            new = heldout(idx)
            d = base - new
            gain = float(d.sum() / max(base.sum(), 1e-300))
            t = _paired_t(d)
            if best is None or gain > best[1]:
                best = (i, gain, t, new, cond)
        if best is None:
            break
        i, gain, t, new, cond = best
        step = {"effect": cands[i].describe(), "heldout_gain": gain, "t": t, "condition": cond}
        if gain < min_gain or t < min_t:
            rejected.append({**step, "reason": f"held-out gain {gain:.3f} (min {min_gain}), t {t:.2f} (min {min_t})"})
            break
        steps.append(step)
        chosen.append(i)
        base = new
        hist.append(float(new.sum()))

    # final nonlinear Gauss-Newton fit on all data
    fitted = [cands[i].with_params(np.zeros(cands[i].n_params)) for i in chosen]
    sizes = [f.n_params for f in fitted]
    theta = np.zeros(sum(sizes))
    Hs = np.zeros((0, 0))
    G = np.zeros((len(obs) * 2, 0))
    r = e0.reshape(-1)
    for _ in range(iterations if fitted else 0):
        cur = declared + fitted
        r = np.einsum("mij,mj->mi", W, obs.uv - predict_pixels(tree, obs, cur)).reshape(-1)
        G = np.concatenate([W @ pixel_jacobian(tree, obs, f, cur) for f in fitted], axis=2).reshape(len(r), -1)
        dth, Hs = _lstsq(G, r)
        theta = theta + dth
        fitted = [f.with_params(p) for f, p in zip(fitted, np.split(theta, np.cumsum(sizes)[:-1]))]
    cur = declared + fitted
    r = np.einsum("mij,mj->mi", W, obs.uv - predict_pixels(tree, obs, cur)).reshape(-1)
    dof = max(len(r) - len(theta), 1)
    s2 = float(r @ r / dof)
    effects_out: list[dict[str, Any]] = []
    if fitted:
        H_inv = np.linalg.pinv(G.T @ G)
        if robust:
            # cluster-robust (sandwich) covariance, clusters = poses: errors of the points seen at
            # one pose share that pose's arm and camera error
            rp = r.reshape(len(obs), 2)
            Gp = G.reshape(len(obs), 2, -1)
            S = np.zeros((G.shape[1], G.shape[1]))
            for g in range(len(poses_u)):
                m = pose_idx == g
                sg = np.einsum("mki,mk->i", Gp[m], rp[m])
                S += np.outer(sg, sg)
            n_g = len(poses_u)
            cov_theta = H_inv @ S @ H_inv * (n_g / max(n_g - 1, 1))
        else:
            cov_theta = H_inv * s2
        sig = np.sqrt(np.maximum(np.diag(cov_theta), 0.0))
        for k, (f, sg) in enumerate(zip(fitted, np.split(sig, np.cumsum(sizes)[:-1]))):
            frame = next((cf for cf in obs.cameras if camera_mount_joint(robot, cf) == f.location), None)
            effects_out.append({
                "name": f.name, "location": f.location, "frame": frame, "measurement": "pixels",
                "parameters": {p: float(v) for p, v in zip(f.param_names, f.params)},
                "ci": {p: [float(v - 1.96 * s), float(v + 1.96 * s)] for p, v, s in zip(f.param_names, f.params, sg)},
                "sigma": {p: float(s) for p, s in zip(f.param_names, sg)},
                "share": float((hist[k] - hist[k + 1]) / hist[0]) if hist[0] > 0 else 0.0,
            })

    def cv_errors(idx: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Held-out squared raw error [px^2] and Mahalanobis^2 per observation."""
        sq = np.zeros(len(obs))
        maha = np.zeros(len(obs))
        for test in test_masks:
            rr, ww = e_raw, e0
            if idx:
                Gi = np.concatenate([Gs[k] for k in idx], axis=2)
                th, _ = _lstsq(Gi[~test].reshape(-1, Gi.shape[2]), e0[~test].reshape(-1))
                rr = e_raw - np.concatenate([J_raw[k] for k in idx], axis=2) @ th
                ww = e0 - Gi @ th
            sq[test] = np.sum(rr[test] ** 2, axis=1)
            maha[test] = np.sum(ww[test] ** 2, axis=1)
        return sq, maha

    def per_cam(v: np.ndarray, root: bool = True) -> dict[str, float]:
        return {f: float(np.sqrt(np.mean(v[obs.camera == c])) if root else np.mean(v[obs.camera == c]))
                for c, f in enumerate(obs.cameras) if np.any(obs.camera == c)}

    sq0, m0 = cv_errors([])
    sq1, m1 = cv_errors(chosen)
    floor = per_cam(np.trace(C, axis1=1, axis2=2))
    unexplained = {f: float(np.sqrt(max(per_cam(sq1)[f] ** 2 - floor[f] ** 2, 0.0))) for f in floor}
    # held-out mean Mahalanobis^2 per point (expectation 2 if the declared covariance is right);
    # standard error from the per-pose sums (points of a pose are correlated)
    counts = np.maximum(np.bincount(pose_idx, minlength=len(poses_u)), 1)
    pm = np.bincount(pose_idx, m1, minlength=len(poses_u)) / counts
    se = float(np.std(pm, ddof=1) / math.sqrt(len(pm))) if len(pm) > 1 else float("inf")
    nees_after = float(np.mean(m1))
    flagged = nees_after > 2.0 + 3.0 * se
    return PixelDiagnosis(effects=effects_out, fitted=fitted, rms_before=per_cam(sq0), rms_after=per_cam(sq1),
                          rms_before_insample=pixel_rms(tree, obs, declared),
                          rms_after_insample=pixel_rms(tree, obs, cur), stats_before=pixel_stats(tree, obs, declared),
                          stats_after=pixel_stats(tree, obs, cur), steps=steps, rejected=rejected,
                          sigma_scale=math.sqrt(s2), n=len(obs), noise_floor=floor, unexplained=unexplained,
                          nees_before=float(np.mean(m0)), nees_after=nees_after, unexplained_flag=bool(flagged))


def pixels_from_bag(path: str | Path, robot: Robot, model_yaml: str | Path, sigma_px: float = 1.0,
                    refine: str = "subpix") -> PixelObs:
    """Tag pixels of a contract bag as :class:`PixelObs` (centre and corner points).

    ``/tag_bearing/observations`` if the bag has it (e.g. the Motoman importer: marker centres),
    else tags detected on the camera images with the tag bearing node's function
    (:func:`ppoe_core.sensing.tag_rows.observe_tags`).  Tags (id -> link, size, pose) come from the
    model YAML's ``tags`` section; intrinsics from ``/camera/camera_info`` (per ``frame_id``);
    joint values from ``/joint_states`` at each observation stamp.  Each message is one pose.

    Raises
    ------
    BagError
        No tag observations or images, a camera frame without CameraInfo, an observed id the
        model does not list, tags on more than one link.
    """
    from ppoe_core.io import bagio
    from ppoe_core.estimation.measurements import tag_points
    from ppoe_core.sensing.tag_rows import observe_tags

    cfg = load_model(model_yaml, robot)[0]
    if cfg.tags is None or not cfg.tags.items:
        raise BagError(f"{model_yaml}: no 'tags' section: pixels of bag {path} cannot be attributed to links")
    by_id = cfg.tags.by_id()
    links = sorted({t.link for t in cfg.tags.items})
    if len(links) != 1:
        raise BagError(f"{model_yaml}: tags on several links {links}; pixel diagnosis supports one tag link")
    data = bagio.read_bag(path, load_images=True)
    ci = data.camera_info
    intr: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for i, f in enumerate(ci.frame_ids):
        intr.setdefault(f, (ci.K[i], ci.D[i]))
    rows_all: list[np.ndarray] = []  # [msg, id, corner, u, v]
    frames: list[str] = []
    stamps: list[float] = []
    obs = data.tag_observations
    if len(obs):
        for i in range(len(obs)):
            m = obs.message(i)
            frames.append(obs.frame_ids[i])
            stamps.append(float(obs.stamps[i]))
            rows_all.append(np.column_stack([np.full(m["ids"].shape, i), m["ids"], m["corners"], m["uv"]]))
    elif len(data.images):
        imgs = data.images
        for i in range(len(imgs)):
            f = imgs.frame_ids[i]
            if f not in intr:
                raise BagError(f"bag {path}: topic {imgs.topic} message {i}: "
                               f"no /camera/camera_info with frame_id {f!r}")
            r, _ = observe_tags(imgs.decode(i), *intr[f], cfg.tags.family, tuple(by_id), refine)
            frames.append(f)
            stamps.append(float(imgs.stamps[i]))
            rows_all.append(np.column_stack([np.full(len(r), i), r[:, :4]]))
    else:
        raise BagError(f"bag {path}: neither /tag_bearing/observations nor camera images")
    rows = np.concatenate(rows_all) if rows_all else np.zeros((0, 5))
    if len(rows) == 0:
        raise BagError(f"bag {path}: no tag observed in {len(frames)} messages")
    msg = rows[:, 0].astype(int)
    ids = np.rint(rows[:, 1]).astype(int)
    unknown = sorted(set(ids.tolist()) - set(by_id))
    if unknown:
        raise BagError(f"bag {path}: observed tag ids {unknown} are not in {model_yaml} tags")
    corner = np.rint(rows[:, 2]).astype(int)
    point = np.array([tag_points(by_id[t].size, by_id[t].T_link_tag)[c] for t, c in zip(ids, corner)])
    cams = sorted(set(frames[k] for k in np.unique(msg)))
    missing = [f for f in cams if f not in intr]
    if missing:
        raise BagError(f"bag {path}: no /camera/camera_info for camera frames {missing}")
    for f in cams:
        if f not in robot.links:
            raise BagError(f"bag {path}: camera frame {f!r} is not a link of URDF {robot.source}")
    js = data.joint_states
    at = np.asarray(stamps)[msg]
    order = np.argsort(js.stamps, kind="stable")
    t_js = js.stamps[order]
    q: dict[str, np.ndarray] = {}
    vel: dict[str, np.ndarray] = {}
    cols = []
    for j in KinematicTree(robot).joint_names:
        col = js.column(j)[order]
        good = np.isfinite(col)
        if not np.any(good):
            raise BagError(f"bag {path}: /joint_states carries no value of joint {j!r}")
        q[j] = _sample_joint(t_js[good], col[good], at)
        cols.append(np.interp(t_js, t_js[good], col[good]))
        v = np.gradient(col[good], t_js[good]) if good.sum() > 1 else np.zeros(good.sum())
        vel[j] = _sample_joint(t_js[good], v, at)
    signs = motion_signs(t_js, np.column_stack(cols), at)
    ctx = {"time": at - t_js[0], "joint_velocity": vel,
           "motion_sign": {j: signs[:, i] for i, j in enumerate(q)}}
    return PixelObs(q=q, context=ctx, link=links[0], point=point, camera=np.array([cams.index(frames[k]) for k in msg]),
                    cameras=cams, K=[intr[f][0] for f in cams], D=[intr[f][1] for f in cams], uv=rows[:, 3:5].copy(),
                    pose=msg, sigma_px=float(sigma_px), name=Path(path).name)


def concat_pixel_obs(parts: Sequence[PixelObs]) -> PixelObs:
    """Join :class:`PixelObs` of several sources (same marker link); poses and cameras renumbered."""
    if not parts:
        raise MeasurementError("concat_pixel_obs: no pixel observations given")
    links = {p.link for p in parts}
    if len(links) != 1:
        raise MeasurementError(f"concat_pixel_obs: markers on different links {sorted(links)} "
                               f"({', '.join(p.name for p in parts)})")
    cams: list[str] = []
    K: list[np.ndarray] = []
    D: list[np.ndarray] = []
    for p in parts:
        for c, f in enumerate(p.cameras):
            if f not in cams:
                cams.append(f)
                K.append(p.K[c])
                D.append(p.D[c])
            elif not (np.allclose(K[cams.index(f)], p.K[c]) and np.allclose(D[cams.index(f)], p.D[c])):
                raise MeasurementError(f"{p.name}: camera '{f}' has other intrinsics than in {parts[0].name}")
    off = 0
    pose = []
    for p in parts:
        pose.append(p.pose + off)
        off += int(p.pose.max()) + 1 if len(p) else 0
    names = set().union(*[p.q for p in parts])
    return PixelObs(q={j: np.concatenate([p.q[j] for p in parts]) for j in names}, link=parts[0].link,
                    point=np.concatenate([p.point for p in parts]),
                    camera=np.concatenate([[cams.index(p.cameras[c]) for c in p.camera] for p in parts]).astype(int),
                    cameras=cams, K=K, D=D, uv=np.concatenate([p.uv for p in parts]), pose=np.concatenate(pose),
                    sigma_px=parts[0].sigma_px, name="+".join(p.name for p in parts),
                    context=_map_ctx(lambda *v: np.concatenate(v), [p.context for p in parts]))


def add_pixel_diagnosis(result: DiagnoseResult, robot: Robot, obs: PixelObs, declared: Sequence[Effect] = (),
                        **options: Any) -> PixelDiagnosis:
    """Run :func:`diagnose_pixels` on top of a tracker/pose ``result`` and merge it.

    The pixels are predicted with the declared effects plus the effects ``result`` found (the
    arm's errors move the markers too).  The pixel effects found are appended to
    ``result.effects`` (so the contract JSON and :func:`write_model_yaml` carry them),
    ``result.extra["pixels"]`` holds :meth:`PixelDiagnosis.to_json` and the summary says the
    pixel RMS before -> after (and UNEXPLAINED when the held-out pixel NEES is too large).
    ``options`` go to :func:`diagnose_pixels` (e.g. ``pert``, ``jnoise``: the declared
    covariance, ``folds``).
    """
    tree = KinematicTree(robot)
    keys = ("name", "location", "parameters", "variable", "reference")
    found = [effect_from_config({k: e[k] for k in keys if k in e}, tree,
                                where=f"diagnose effect {e['name']}@{e['location']}") for e in result.effects]
    pres = diagnose_pixels(robot, obs, list(declared) + found, **options)
    if pres.unexplained_flag:
        result.summary += (f"\nTag pixels UNEXPLAINED: held-out mean Mahalanobis^2 {pres.nees_after:.3g} per point "
                           f"(expected 2); RMS above the noise floor: "
                           + ", ".join(f"{f} {v:.2f} px" for f, v in pres.unexplained.items()))
    result.effects.extend(pres.effects)
    result.extra["pixels"] = pres.to_json()
    # the tracker/pose effects can move the markers away from the pixels (components a tracker
    # registration absorbs are seen by a camera fixed to the base): report the pixels without them
    result.extra["pixels"]["pixel_rms_declared_only"] = pixel_rms(tree, obs, declared)
    per = ", ".join(f"{f} {pres.rms_before[f]:.2f} -> {pres.rms_after[f]:.2f} px" for f in pres.rms_before)
    names = ", ".join(f"{e['name']}@{e['location']}" for e in pres.effects) or "none"
    result.summary += f"\nTag pixels ({pres.n} points): effects {names}; held-out RMS {per}."
    return pres


# =============================================================================
# Accelerometer stage (base tilt and the effects upstream of the IMU links)
# =============================================================================


def _imu_tilt_raw(tree: KinematicTree, stops: Stops, effects: Sequence[Effect],
                  tilt_group: np.ndarray | None = None) -> np.ndarray:
    """Tilt residuals (measured minus predicted) of every accelerometer, shape (N, K, 2) [rad].

    Predicted up direction in the IMU link: ``u = R_root_link^T Exp(-w_g) z_root`` with
    ``w_g = [tilt_x, tilt_y, 0]`` the base tilt of the stop's group (``tilt_group`` (G, 2), root
    axes: the root is rotated by ``Exp(w_g)`` w.r.t. gravity, the ``base_tilt`` effect); measured:
    the normalised specific force.  Components: small rotations about the link's x and y axes.
    """
    dq, dxi = apply_corrections(list(effects), stops.q, stops.context)
    links = [ln for ln, _ in stops.imus.values()]
    poses = tree.link_poses(stops.q, dq, dxi, links=links)
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (len(stops), 3))
    if tilt_group is not None:
        w = np.zeros((len(stops), 3))
        w[:, :2] = np.asarray(tilt_group)[stops.group]
        up = np.einsum("nji,nj->ni", lie.exp(np.concatenate([np.zeros_like(w), w], axis=1))[:, :3, :3], up)
    out = np.empty((len(stops), len(stops.imus), 2))
    for k, (link, acc) in enumerate(stops.imus.values()):
        u_m = acc / np.linalg.norm(acc, axis=1)[:, None]
        u_p = np.einsum("nji,nj->ni", poses[link][:, :3, :3], up)
        out[:, k, 0] = u_m[:, 1] - u_p[:, 1]
        out[:, k, 1] = -(u_m[:, 0] - u_p[:, 0])
    return out


def imu_candidates(tree: KinematicTree, stops: Stops) -> list[Effect]:
    """Effects that rotate an accelerometer's link w.r.t. gravity (zero parameters):
    ``joint_offset``, ``gravity_compliance`` and ``mount_bending`` on the paths from the root to
    the IMU links (rotations only; ``link_error`` is left out: a constant rotation is the sensor's
    mounting).  ``base_tilt`` is handled separately, per group (bag / file = robot placement)."""
    robot = tree.robot
    out: list[Effect] = []
    seen: set[str] = set()
    for link, _ in stops.imus.values():
        for jn in robot.path_from_root(link):
            if jn in seen:
                continue
            seen.add(jn)
            j = robot.joints[jn]
            mass = _carried_mass(tree, jn)
            if j.movable and j.type != "prismatic":
                out.append(make_effect("joint_offset", jn, tree))
                if mass > 0.0:
                    out.append(make_effect("gravity_compliance", jn, tree))
            if (not j.movable or j.type == "prismatic") and mass > 0.0:
                out.append(make_effect("mount_bending", jn, tree))
    return out


def _imu_jacobian(tree: KinematicTree, stops: Stops, effect: Effect | None, current: Sequence[Effect],
                  tilt_group: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central finite-difference Jacobian (N, K, 2, P) of the tilt *prediction* w.r.t. the
    parameters of ``effect`` (``None``: the per-group base tilt, P = 2 G), at ``current``."""
    cols = []
    if effect is None:
        for i in range(tilt_group.size):
            d = np.zeros(tilt_group.size)
            d[i] = h
            rp = _imu_tilt_raw(tree, stops, current, tilt_group + d.reshape(tilt_group.shape))
            rm = _imu_tilt_raw(tree, stops, current, tilt_group - d.reshape(tilt_group.shape))
            cols.append(-(rp - rm) / (2 * h))
    else:
        others = [e for e in current if not (e.name == effect.name and e.location == effect.location)]
        for i in range(effect.n_params):
            d = np.zeros(effect.n_params)
            d[i] = h
            rp = _imu_tilt_raw(tree, stops, others + [effect.with_params(effect.params + d)], tilt_group)
            rm = _imu_tilt_raw(tree, stops, others + [effect.with_params(effect.params - d)], tilt_group)
            cols.append(-(rp - rm) / (2 * h))
    return np.stack(cols, axis=-1)


def imu_tilt_covariance(tree: KinematicTree, stops: Stops, declared: Sequence[Effect], sigma: np.ndarray,
                        perturbation_cov: Mapping[str, np.ndarray] | None = None,
                        joint_noise: Mapping[str, float] | None = None) -> np.ndarray:
    """Expected covariance (N, K, 2, 2) [rad^2] of the tilt residuals of :func:`_imu_tilt_raw`.

    ``(sigma_k / |a|)^2 I`` (``sigma`` (K,) accelerometer 1-sigma per axis [m/s^2]) plus the
    first-order PPOE covariance of the IMU link's rotation (right tangent at the link, rotation
    rows of eq. 18, :func:`_rotation_covariance`; ``perturbation_cov``: joint -> 6x6 in the
    tangent space right after the joint's origin) mapped to the tilt angles: for
    ``R' = R Exp(phi)`` the up direction ``u = R^T z`` becomes ``u + u x phi``.
    """
    n, K = len(stops), len(stops.imus)
    dq_d, dxi_d = apply_corrections(list(declared), stops.q, stops.context)
    poses_d = tree.link_poses(stops.q, dq_d, dxi_d)
    C_tilt = np.zeros((n, K, 2, 2))
    for k, (link, acc) in enumerate(stops.imus.values()):
        C_tilt[:, k] = (sigma[k] / np.linalg.norm(acc, axis=1))[:, None, None] ** 2 * np.eye(2)
        if perturbation_cov or joint_noise:
            Fq, Fx = tree.frame_jacobian(stops.q, link, poses_d, dq_d, dxi_d)
            C_rot = _rotation_covariance(stops, Fq, Fx, perturbation_cov or {}, joint_noise or {})
            u = poses_d[link][:, 2, :3]  # up in the link
            A = np.zeros((n, 2, 3))
            A[:, 0, 0], A[:, 0, 2] = u[:, 2], -u[:, 0]
            A[:, 1, 1], A[:, 1, 2] = u[:, 2], -u[:, 1]
            C_tilt[:, k] += A @ C_rot @ np.swapaxes(A, -1, -2)
    return C_tilt


def diagnose_imu(robot: Robot, stops: Stops, declared: Sequence[Effect] = (),
                 sigma: float | Mapping[str, float] = 4e-4, candidates: Sequence[Effect] | None = None,
                 folds: int = 5, min_gain: float = 0.03, min_t: float = 4.0, max_condition: float = 1e6,
                 max_effects: int = 3, iterations: int = 3, seed: int = 0,
                 perturbation_cov: Mapping[str, np.ndarray] | None = None,
                 joint_noise: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Fit the accelerometers: per-group ``base_tilt`` and the effects that rotate the IMU links.

    Residual per stop and accelerometer: the two tilt angles (measured minus predicted up
    direction in the IMU link, :func:`_imu_tilt_raw`), whitened by ``sigma / |a|`` [rad]
    (``sigma`` [m/s^2] per axis, one value or per IMU name; model ``imus`` section, default
    4e-4) plus the declared PPOE covariance of the IMU link's rotation (``perturbation_cov``:
    joint -> 6x6 in the tangent space right after the joint's origin, ``joint_noise``: joint ->
    1-sigma; first order, rotation rows of eq. 18, right tangent at the IMU link) mapped to the
    two tilt angles.  The IMU nearest the root is the reference: its mounting is part of the base
    tilt; every other IMU gets a constant mounting rotation (2 nuisance parameters, always fitted).
    Candidates: ``base_tilt`` (2 parameters per group = bag / file, one robot placement each) and
    :func:`imu_candidates`.  Selection as in :func:`diagnose_pixels` (same helpers): linearised at
    the declared chain (central finite-difference Jacobian), greedy forward selection, ``folds``-fold
    CV over stops (all IMUs of a stop in one fold), accepted when the column-scaled normal matrix
    has condition < ``max_condition``, the held-out mean squared whitened error drops by
    >= ``min_gain`` with a paired t >= ``min_t`` over stops, and compliances are not negative.
    Final fit: Gauss-Newton on the nonlinear chain; 95 % CIs ``theta +- 1.96 sigma`` from
    ``max(s^2, 1) H^-1``.

    Returns
    -------
    dict with ``effects`` (as in :func:`diagnose`, ``"measurement": "imu"``; ``base_tilt`` has
    ``per_group`` {group: {tilt_x, tilt_y, ci}}), ``steps``, ``rejected``, ``tilt_rms_before`` /
    ``tilt_rms_after`` (held-out, per IMU [rad], x / y), ``sigma_scale``, ``n``.
    """
    if not stops.imus:
        raise MeasurementError("diagnose_imu: the stops carry no accelerometer (/imu/<name>) data")
    tree = KinematicTree(robot)
    declared = list(declared)
    n, K = len(stops), len(stops.imus)
    if n < folds:
        raise MeasurementError(f"diagnose_imu: {n} stops with accelerometer data, need >= {folds}")
    sig = np.array([sigma.get(k, 4e-4) if isinstance(sigma, Mapping) else float(sigma) for k in stops.imus])
    C_tilt = imu_tilt_covariance(tree, stops, declared, sig, perturbation_cov, joint_noise)
    W = np.linalg.inv(np.linalg.cholesky(C_tilt))  # (N, K, 2, 2) whitening

    def wh(x: np.ndarray) -> np.ndarray:
        """Whiten (N, K, 2) residuals or (N, K, 2, P) Jacobians."""
        return np.einsum("nkij,nkj...->nki...", W, x)

    n_grp = len(stops.group_names)
    zero_tilt = np.zeros((n_grp, 2))
    e_raw = _imu_tilt_raw(tree, stops, declared, zero_tilt)
    if not np.all(np.isfinite(e_raw)):
        i = int(np.flatnonzero(~np.all(np.isfinite(e_raw), axis=(1, 2)))[0])
        raise MeasurementError(f"diagnose_imu: non-finite accelerometer or joint values (first: stop {i} "
                               f"of {stops.group_names[stops.group[i]]})")
    e0 = wh(e_raw).reshape(n, -1)  # (N, 2K) whitened
    cands = list(candidates) if candidates is not None else imu_candidates(tree, stops)
    names = ["base_tilt@" + tree.root] + [c.describe() for c in cands]
    effs: list[Effect | None] = [None] + cands
    Gs = [wh(_imu_jacobian(tree, stops, e, declared, zero_tilt)).reshape(n, 2 * K, -1)
          for e in effs]
    test_masks = _pose_folds(np.arange(n), folds, seed)
    # mounting of every IMU but the reference (the one nearest the root, whose mounting is part of
    # the base tilt): a constant small rotation, additive on its two tilt components (nuisance)
    depth = [len(robot.path_from_root(ln)) for ln, _ in stops.imus.values()]
    ref = int(np.argmin(depth))
    mount_imus = [k for k in range(K) if k != ref]
    Gm_axes = np.zeros((n, K, 2, 2 * len(mount_imus)))
    for c, k in enumerate(mount_imus):
        Gm_axes[:, k, 0, 2 * c] = 1.0
        Gm_axes[:, k, 1, 2 * c + 1] = 1.0
    Gm = wh(Gm_axes).reshape(n, 2 * K, -1)
    nm = Gm.shape[2]

    def stacked(idx: Sequence[int]) -> np.ndarray:
        return np.concatenate([Gm] + [Gs[i] for i in idx], axis=2)

    def heldout(idx: Sequence[int]) -> np.ndarray:
        err = np.zeros(n)
        G = stacked(idx)
        for test in test_masks:
            r = e0
            if G.shape[2]:
                Gt = G[~test].reshape(-1, G.shape[2])
                live = np.any(Gt != 0.0, axis=0)  # groups without training stops stay at 0
                th = np.zeros(G.shape[2])
                th[live], _ = _lstsq(Gt[:, live], e0[~test].reshape(-1))
                r = e0 - G @ th
            err[test] = np.sum(r[test] ** 2, axis=1)
        return err

    chosen: list[int] = []
    steps: list[dict[str, Any]] = []
    rejected: list[dict[str, Any]] = []
    base = heldout(chosen)
    base0 = base.copy()
    while len(chosen) < max_effects:
        best = None
        for i in range(len(effs)):
            if i in chosen or any(r.get("effect") == names[i] for r in rejected):
                continue
            idx = chosen + [i]
            G = stacked(idx).reshape(-1, stacked(idx).shape[2])
            th, Hs = _lstsq(G, e0.reshape(-1))
            cond = float(np.linalg.cond(Hs))
            if not np.isfinite(cond) or cond > max_condition:
                rejected.append({"effect": names[i], "reason": f"not identifiable (condition {cond:.3g})"})
                continue
            P = Gs[i].shape[2]
            eff = effs[i]
            if eff is not None and any(th[-P + k] < 0 for k, p in enumerate(eff.param_names) if p in eff.nonnegative):
                rejected.append({"effect": names[i], "reason": "negative compliance"})
                continue
            new = heldout(idx)
            d = base - new
            gain = float(d.sum() / max(base.sum(), 1e-300))
            t = _paired_t(d)
            if best is None or gain > best[1]:
                best = (i, gain, t, new, cond)
        if best is None:
            break
        i, gain, t, new, cond = best
        step = {"effect": names[i], "heldout_gain": gain, "t": t, "condition": cond}
        if gain < min_gain or t < min_t:
            rejected.append({**step, "reason": f"held-out gain {gain:.3f} (min {min_gain}), t {t:.2f} (min {min_t})"})
            break
        steps.append(step)
        chosen.append(i)
        base = new

    # final Gauss-Newton on the nonlinear chain
    tilt = zero_tilt.copy()
    fitted = {i: e.with_params(np.zeros(e.n_params)) for i in chosen if (e := effs[i]) is not None}
    sizes = [Gs[i].shape[2] for i in chosen]
    theta = np.zeros(nm + sum(sizes))
    G = np.zeros((n * 2 * K, 0))
    live = np.zeros(0, dtype=bool)
    mount = np.zeros((K, 2))

    def unpack(th: np.ndarray) -> None:
        nonlocal tilt
        mount[mount_imus] = th[:nm].reshape(-1, 2)
        for i, p in zip(chosen, np.split(th[nm:], np.cumsum(sizes)[:-1])):
            if effs[i] is None:
                tilt = p.reshape(n_grp, 2).copy()
            else:
                fitted[i] = fitted[i].with_params(p)

    for _ in range(iterations):
        cur = declared + list(fitted.values())
        r = wh(_imu_tilt_raw(tree, stops, cur, tilt) - mount).reshape(-1)
        G = np.concatenate([Gm.reshape(n * 2 * K, -1)] + [wh(_imu_jacobian(tree, stops, fitted.get(i), cur, tilt))
                            .reshape(n * 2 * K, -1) for i in chosen], axis=1)
        live = np.any(G != 0.0, axis=0)
        dth = np.zeros(G.shape[1])
        dth[live], _ = _lstsq(G[:, live], r)
        theta = theta + dth
        unpack(theta)
    cur = declared + list(fitted.values())
    r = wh(_imu_tilt_raw(tree, stops, cur, tilt) - mount).reshape(-1)
    s2 = float(r @ r / max(r.size - int(live.sum()), 1))
    cov = np.zeros((theta.size, theta.size))
    if theta.size:
        cov[np.ix_(live, live)] = np.linalg.pinv(G[:, live].T @ G[:, live]) * max(s2, 1.0)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    mount_sd = sd[:nm].reshape(-1, 2)
    mounting = {list(stops.imus)[k]: {"rx": float(mount[k, 0]), "ry": float(mount[k, 1]),
                                      "sigma": [float(v) for v in mount_sd[c]]}
                for c, k in enumerate(mount_imus)}
    theta, sd = theta[nm:], sd[nm:]
    effects_out: list[dict[str, Any]] = []
    tot0 = float(base0.sum())
    prev = tot0
    for k, (i, th, s) in enumerate(zip(chosen, np.split(theta, np.cumsum(sizes)[:-1]),
                                       np.split(sd, np.cumsum(sizes)[:-1]))):
        share = float(steps[k]["heldout_gain"] * prev / tot0) if tot0 > 0 else 0.0
        prev = prev * (1.0 - steps[k]["heldout_gain"])
        if effs[i] is None:
            tv, ts = th.reshape(n_grp, 2), s.reshape(n_grp, 2)
            per = {g: {"tilt_x": float(tv[j, 0]), "tilt_y": float(tv[j, 1]),
                       "ci": {"tilt_x": [float(tv[j, 0] - 1.96 * ts[j, 0]), float(tv[j, 0] + 1.96 * ts[j, 0])],
                              "tilt_y": [float(tv[j, 1] - 1.96 * ts[j, 1]), float(tv[j, 1] + 1.96 * ts[j, 1])]},
                       "sigma": {"tilt_x": float(ts[j, 0]), "tilt_y": float(ts[j, 1])}}
                   for j, g in enumerate(stops.group_names) if np.any(stops.group == j)}
            effects_out.append({"name": "base_tilt", "location": tree.root, "measurement": "imu",
                                "per_group": per, "share": share})
        else:
            f = fitted[i]
            effects_out.append({"name": f.name, "location": f.location, "measurement": "imu",
                                "parameters": {p: float(v) for p, v in zip(f.param_names, th)},
                                "ci": {p: [float(v - 1.96 * q), float(v + 1.96 * q)]
                                       for p, v, q in zip(f.param_names, th, s)},
                                "sigma": {p: float(q) for p, q in zip(f.param_names, s)}, "share": share})

    def rms_per_imu(err_idx: Sequence[int]) -> dict[str, list[float]]:
        G = stacked(err_idx)
        rr = np.zeros_like(e0)
        for test in test_masks:
            r_ = e0
            if G.shape[2]:
                Gt = G[~test].reshape(-1, G.shape[2])
                lv = np.any(Gt != 0.0, axis=0)
                th = np.zeros(G.shape[2])
                th[lv], _ = _lstsq(Gt[:, lv], e0[~test].reshape(-1))
                r_ = e0 - G @ th
            rr[test] = r_[test]
        raw = np.einsum("nkij,nkj->nki", np.linalg.inv(W), rr.reshape(n, K, 2))
        return {k: [float(v) for v in np.sqrt(np.mean(raw[:, j] ** 2, axis=0))] for j, k in enumerate(stops.imus)}

    return {"effects": effects_out, "steps": steps, "rejected": rejected,
            "tilt_rms_before": rms_per_imu([]), "tilt_rms_after": rms_per_imu(chosen),
            "heldout_mahalanobis2_before": float(np.mean(base0)) / (2 * K),
            "heldout_mahalanobis2_after": float(np.mean(base)) / (2 * K),
            "sigma_scale": math.sqrt(s2), "n": n, "reference_imu": list(stops.imus)[ref], "mounting": mounting, "imus": {k: ln for k, (ln, _) in stops.imus.items()},
            "found": list(fitted.values()), "tilt": tilt}
