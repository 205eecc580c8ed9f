"""Joint fit: one robust nonlinear least-squares problem over tracker points and tag pixels with shared effects.

The tracker stage (:mod:`engine`) and the pixel stage (:mod:`pixel_stage`) fit their effects one after the
other: a rigid part of the arm error that the tracker registration absorbs is then blamed on the cameras.
:func:`joint_fit` fits one effect set to all data at once on the full nonlinear chain:

* tracker rows (``Stops``, ``kind="point"``, any reflectors on any links): whitened residual
  ``(p_meas - T_reg_s x(theta)) / sigma``, one registration ``T_reg_s = Exp(d_s) T0_s`` per session
  (``T0_s`` Kabsch on the declared chain, ``d_s`` 6 unknowns, ``[rho; theta]``);
* pixel rows (:class:`PixelObs`, tags on any links, any cameras): ``(uv - predict_pixels(theta)) / sigma_px``.

Solved with :func:`scipy.optimize.least_squares` (``trf``, analytic dense Jacobian blocks from
:func:`chain_jacobians` / :func:`measurement_jacobian` and :func:`predict_pixels_with_jacobians` /
:func:`effect_jacobian`, robust ``soft_l1`` loss at ``robust_scale`` whitened units).  Noise weights: with
both sensors, each sensor's declared noise is first scaled by the robust spread of its residual in its own
fit (:func:`sensor_noise`), then ``rescale`` rounds re-estimate both from the joint solution (1.4826 MAD of
the whitened residuals) and solve again (variance components: a sensor whose residuals are 10 x its declared
noise must not outweigh the other one ten-fold).  Covariance of all unknowns: the robust (IRLS-weighted)
Gauss-Newton information ``H = J^T W J`` at the solution and, by default, the sandwich
``H^-1 (sum_pose g g^T) H^-1 G/(G-1)`` clustered by pose (tracker and pixel rows of one robot pose
share its arm error), else ``s^2 H^-1``; effect CIs are the marginal (registrations not fixed) 95 % normal
intervals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.candidates import chain_jacobians, measured_link_poses, measurement_jacobian
from ppoe_core.analysis.diagnose.linear import LinearProblem
from ppoe_core.analysis.diagnose.pixels import (
    PixelObs,
    _map_ctx,
    effect_jacobian,
    predict_pixels,
    predict_pixels_with_jacobians,
)
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import MeasurementError
from ppoe_core.model.effects import Effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree


@dataclass
class JointFit:
    """Result of :func:`joint_fit`.

    Attributes
    ----------
    fitted : list of Effect
        The effects with the fitted parameters.
    effects : list of dict
        ``{name, location, measurement: "joint", parameters, ci (95 %), sigma}`` per effect.
    regs : dict session -> ndarray (4, 4)
        Tracker registration ``T_tracker_root`` of each fitted session.
    pixel_rms : dict camera frame -> float
        In-sample RMS of the 2D reprojection error per camera [px].
    tracker_rms : float
        In-sample RMS of the 3D tracker residual [m] (NaN without tracker rows).
    sensor_sigma : dict
        ``tracker`` [m] and ``pixels`` [px]: the noise used in the final solve (declared, or re-estimated
        with ``rescale``).
    iterations : int
        Function evaluations of the final solve (``least_squares`` ``nfev``), summed over the solves.
    cost : float
        Final robust cost ``sum rho(r^2)/2`` of the whitened residuals.
    cov : ndarray (P + 6 S, P + 6 S)
        Covariance of all unknowns (effect parameters, then 6 per session).
    """

    fitted: list[Effect]
    effects: list[dict[str, Any]]
    regs: dict[int, np.ndarray]
    pixel_rms: dict[str, float]
    tracker_rms: float
    sensor_sigma: dict[str, float]
    iterations: int
    cost: float
    cov: np.ndarray
    message: str = ""
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))


def subset_stops(stops: Stops, rows: np.ndarray) -> Stops:
    """The stops ``rows`` (index or boolean array) of ``stops``; accelerometers dropped."""
    n = len(stops)
    out: dict[str, Any] = {}
    for f in fields(stops):
        v = getattr(stops, f.name)
        if f.name == "q":
            out[f.name] = {k: a[rows] for k, a in v.items()}
        elif f.name == "context":
            out[f.name] = _map_ctx(lambda a: a[rows] if np.ndim(a) and np.shape(a)[0] == n else a, [v])
        elif f.name == "imus":
            out[f.name] = {}
        elif isinstance(v, np.ndarray) and v.ndim and v.shape[0] == n and f.name != "point" or (
                f.name == "point" and np.ndim(v) == 2):
            out[f.name] = v[rows]
        else:
            out[f.name] = v
    return replace(stops, **out)


def tracker_points(tree: KinematicTree, stops: Stops, effects: Sequence[Effect]) -> tuple[np.ndarray, tuple]:
    """Reflector positions ``x_root`` (N, 3) [m] in the root frame on the chain corrected by ``effects``, and
    the chain ``(poses, dq, dxi)``."""
    dq, dxi = sum_effect_corrections(list(effects), stops.q, stops.context)
    poses = tree.link_poses(stops.q, dq, dxi, links=stops.chain_links())
    T = measured_link_poses(stops, poses)
    return np.einsum("nij,nj->ni", T[:, :3, :3], stops.point_rows()) + T[:, :3, 3], (poses, dq, dxi)


class JointProblem:
    """Whitened residuals and analytic Jacobian of the joint tracker + pixel problem (module docstring).

    Parameters
    ----------
    tree : KinematicTree
    effects : effects to fit (their current parameters are the start)
    stops : tracker points (``kind="point"``) or None
    pixels : tag pixels or None
    declared : effects of the model (fixed, part of the prediction)
    sigma_tracker, sigma_px : float or None
        Override of the sensor noise (1-sigma per axis, [m] / [px]); None: ``stops.sigma_rows()`` /
        ``pixels.sigma_px``.
    scale_t, scale_px : float
        Factors on that noise (noise re-estimation; per-row tracker sigmas keep their ratios).

    Unknowns ``x = [theta (P), d_s (6 per session)]``; residuals: tracker rows (3 each) then pixel rows (2 each).
    """

    def __init__(self, tree: KinematicTree, effects: Sequence[Effect], stops: Stops | None = None,
                 pixels: PixelObs | None = None, declared: Sequence[Effect] = (),
                 sigma_tracker: float | None = None, sigma_px: float | None = None, scale_t: float = 1.0,
                 scale_px: float = 1.0) -> None:
        if stops is not None and stops.kind != "point":
            raise MeasurementError(f"joint fit: {stops.group_names}: only tracker points (kind 'point') are "
                                   f"supported, not {stops.kind!r}")
        self.tree, self.declared = tree, list(declared)
        self.effects = list(effects)
        self.sizes = [e.n_params for e in self.effects]
        self.P = int(sum(self.sizes))
        self.pixels = pixels
        self.sigma_px = 1.0 if pixels is None else float(pixels.sigma_px if sigma_px is None else sigma_px) * scale_px
        self.stops, self.sessions, self.T0 = self._registrations(stops)
        self.sigma_t = scale_t * (np.full(len(self.stops), float(sigma_tracker)) if sigma_tracker is not None
                                  else self.stops.sigma_rows().astype(float)) if self.stops is not None else np.zeros(0)
        self.nom_t = tree.link_poses(self.stops.q) if self.stops is not None else {}
        self.nom_p = tree.link_poses(pixels.q) if pixels is not None else {}

    def _registrations(self, stops: Stops | None) -> tuple[Stops | None, list[int], np.ndarray]:
        """Kabsch registration per session on the chain with the start effects; rows of sessions without one
        (fewer than 3 stops, collinear) are dropped."""
        self.rows_t = np.arange(0 if stops is None else len(stops))
        if stops is None or len(stops) == 0:
            return None, [], np.zeros((0, 4, 4))
        x_root = tracker_points(self.tree, stops, self.declared + self.effects)[0]
        n = len(stops)
        regs = LinearProblem(stops, x_root, None).kabsch_regs(np.zeros((n, 3, 0)), np.zeros(0), np.arange(n))
        if not regs:
            raise MeasurementError(f"joint fit: {stops.group_names}: no session has 3 non-collinear tracker points")
        keep = np.isin(stops.session, list(regs))
        self.rows_t = np.flatnonzero(keep)
        stops = stops if keep.all() else subset_stops(stops, keep)
        sessions = sorted(regs)
        return stops, sessions, np.stack([regs[k] for k in sessions])

    # -- model ------------------------------------------------------------------------------------
    def split(self, x: np.ndarray) -> tuple[list[Effect], np.ndarray]:
        """The effects with parameters ``x[:P]`` and the registrations ``Exp(d_s) T0_s`` (S, 4, 4)."""
        th = np.split(x[:self.P], np.cumsum(self.sizes)[:-1]) if self.effects else []
        fitted = [e.with_params(p) for e, p in zip(self.effects, th)]
        d = x[self.P:].reshape(-1, 6)
        return fitted, (lie.exp(d) @ self.T0 if len(d) else self.T0)

    def x0(self) -> np.ndarray:
        """Start: the effects' current parameters, registrations at ``T0``."""
        th = [e.params for e in self.effects]
        return np.concatenate([*th, np.zeros(6 * len(self.sessions))]) if th or self.sessions else np.zeros(0)

    @property
    def n_tracker(self) -> int:
        return 0 if self.stops is None else len(self.stops)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Whitened residuals, measured minus predicted: tracker (N*3) then pixels (M*2)."""
        return self.evaluate(x, jac=False)[0]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Analytic Jacobian (N*3 + M*2, P + 6 S) of :meth:`residuals`."""
        J = self.evaluate(x, jac=True)[1]
        assert J is not None
        return J

    def evaluate(self, x: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Residuals and (``jac``) their Jacobian."""
        fitted, T_reg = self.split(np.asarray(x, dtype=float))
        cur = self.declared + fitted
        parts_r: list[np.ndarray] = []
        parts_J: list[np.ndarray] = []
        ncol = self.P + 6 * len(self.sessions)
        if self.stops is not None:
            r, J = self._tracker_block(x, fitted, cur, T_reg, jac, ncol)
            parts_r.append(r)
            parts_J.append(J)
        if self.pixels is not None:
            obs = self.pixels
            if jac:
                uv, Jq, Jx = predict_pixels_with_jacobians(self.tree, obs, cur)
            else:
                uv = predict_pixels(self.tree, obs, cur)
            parts_r.append(((obs.uv - uv) / self.sigma_px).reshape(-1))
            if jac:
                G = [effect_jacobian(Jq, Jx, e, obs.q, obs.context, self.nom_p, (len(obs), 2)) for e in fitted]
                Jp = np.zeros((2 * len(obs), ncol))
                if G:
                    Jp[:, :self.P] = -np.concatenate(G, axis=2).reshape(2 * len(obs), self.P) / self.sigma_px
                parts_J.append(Jp)
        r_all = np.concatenate(parts_r) if parts_r else np.zeros(0)
        return r_all, (np.concatenate(parts_J) if jac else None)

    def _tracker_block(self, x: np.ndarray, fitted: list[Effect], cur: list[Effect], T_reg: np.ndarray, jac: bool,
                       ncol: int) -> tuple[np.ndarray, np.ndarray]:
        """Whitened tracker residuals (N*3) and, with ``jac``, their Jacobian (N*3, ncol)."""
        s = self.stops
        assert s is not None
        x_root, (poses, dq, dxi) = tracker_points(self.tree, s, cur)
        sidx = np.searchsorted(self.sessions, s.session)
        Tn = T_reg[sidx]
        y = np.einsum("nij,nj->ni", Tn[:, :3, :3], x_root) + Tn[:, :3, 3]
        w = 1.0 / self.sigma_t[:, None]
        r = ((s.p_meas - y) * w).reshape(-1)
        if not jac:
            return r, np.zeros((0, ncol))
        n = len(s)
        J = np.zeros((n, 3, ncol))
        if fitted:
            chain = chain_jacobians(self.tree, s, poses, dq, dxi)
            G = np.concatenate([measurement_jacobian(self.tree, s, e, self.nom_t, chain, None) for e in fitted], axis=2)
            J[:, :, :self.P] = -(Tn[:, :3, :3] @ G) * w[:, :, None]
        d = x[self.P:].reshape(-1, 6)
        B = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), -lie.hat3(y)], axis=-1)  # dy / d(left eps)
        for k in range(len(self.sessions)):
            m = sidx == k
            J[m, :, self.P + 6 * k:self.P + 6 * k + 6] = -(B[m] @ lie.left_jacobian(d[k])) * w[m][:, :, None]
        return r, J.reshape(3 * n, ncol)

    # -- clusters -----------------------------------------------------------------------------------
    def residual_clusters(self, pose_t: np.ndarray | None, pose_p: np.ndarray | None) -> np.ndarray:
        """Cluster (pose) id of every residual component, (N*3 + M*2,): tracker rows then pixel rows.

        ``pose_t``: pose of each row of the ``stops`` given to the constructor (None: every stop its own);
        ``pose_p``: of each pixel row (None: ``pixels.pose``)."""
        out = []
        if self.stops is not None:
            out.append(np.repeat(np.arange(self.n_tracker) if pose_t is None else pose_t[self.rows_t], 3))
        if self.pixels is not None:
            out.append(np.repeat(self.pixels.pose if pose_p is None else pose_p, 2))
        return np.concatenate(out) if out else np.zeros(0, dtype=int)


# =============================================================================
# Solve
# =============================================================================


def _loss_weights(r: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """IRLS weights ``rho'(z)``, ``z = (r / f_scale)^2``, of scipy's ``loss`` per residual component."""
    z = (r / f_scale) ** 2
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))
    if loss == "linear":
        return np.ones_like(r)
    raise MeasurementError(f"joint fit: loss must be soft_l1, huber or linear, not {loss!r}")


def _robust_sd(r: np.ndarray) -> float:
    """1.4826 x median absolute whitened residual (the noise scale of one sensor)."""
    return float(1.4826 * np.median(np.abs(r))) if r.size else 1.0


def joint_covariance(J: np.ndarray, r: np.ndarray, w: np.ndarray, clusters: np.ndarray | None) -> np.ndarray:
    """Covariance of the unknowns from the whitened Jacobian ``J`` (R, U), residuals ``r`` (R,) and IRLS weights
    ``w`` (R,): cluster sandwich ``H^-1 (sum_g g g^T) H^-1 G/(G-1)``, ``H = J^T W J``, ``g = J_g^T W_g r_g``
    (``clusters`` (R,) ids), or ``s^2 H^-1`` with ``s^2 = sum w r^2 / (sum w - U)`` when ``clusters`` is None."""
    U = J.shape[1]
    H_inv = np.linalg.pinv((J * w[:, None]).T @ J)
    if clusters is None:
        s2 = float(np.sum(w * r ** 2) / max(float(np.sum(w)) - U, 1.0))
        return H_inv * s2
    ids, inv = np.unique(clusters, return_inverse=True)
    score = np.zeros((ids.size, U))
    np.add.at(score, inv, J * (w * r)[:, None])
    n_g = ids.size
    return H_inv @ (score.T @ score) @ H_inv * (n_g / max(n_g - 1, 1))


def joint_fit(tree: KinematicTree, effects: Sequence[Effect], stops: Stops | None = None,
              pixels: PixelObs | None = None, declared: Sequence[Effect] = (), *, loss: str = "soft_l1",
              robust_scale: float = 3.0, rescale: int = 1, clustered: bool = True,
              pose_t: np.ndarray | None = None, max_nfev: int = 200, sigma_tracker: float | None = None,
              sigma_px: float | None = None, presolve: bool = True) -> JointFit:
    """Fit ``effects`` to the tracker points and tag pixels at once (module docstring).

    Parameters
    ----------
    tree : KinematicTree
    effects : effects to fit (start at their parameters; e.g. zeros)
    stops : tracker points (``kind="point"``), or None
    pixels : tag pixels, or None
    declared : fixed effects of the model
    loss : ``soft_l1`` (default), ``huber`` or ``linear`` (scipy ``least_squares`` losses)
    robust_scale : the loss turns robust beyond this many sensor sigmas
    rescale : rounds of re-estimating each sensor's noise from the solution and solving again (0: none)
    clustered : pose-clustered sandwich covariance (else ``s^2 H^-1``)
    pose_t : (N,) robot pose of each tracker row, shared with ``pixels.pose`` for the clusters (see
        :func:`ppoe_core.analysis.diagnose.joint_cv.joint_pose_ids`); None: every stop its own cluster
    max_nfev : function evaluations per solve
    sigma_tracker, sigma_px : declared noise (1-sigma per axis, [m] / [px]); None: the data's
    presolve : with both sensors, scale the declared noise of the first joint solve per sensor by that sensor's
        own fit (:func:`sensor_noise`)

    Returns
    -------
    JointFit
    """
    from scipy.optimize import least_squares

    if stops is None and pixels is None:
        raise MeasurementError("joint fit: neither tracker points nor pixels given")
    scale_t = scale_px = 1.0
    if presolve and stops is not None and pixels is not None:
        scale_t, scale_px = sensor_noise(tree, effects, stops, pixels, declared, loss=loss, robust_scale=robust_scale,
                                         max_nfev=max_nfev, sigma_tracker=sigma_tracker, sigma_px=sigma_px)
    prob = JointProblem(tree, effects, stops, pixels, declared, sigma_tracker, sigma_px, scale_t, scale_px)
    x = prob.x0()
    nfev = 0
    sol = None
    for rnd in range(1 + int(rescale)):
        if rnd:  # variance components: each sensor's noise from its whitened residuals
            r = prob.residuals(x)
            nt = 3 * prob.n_tracker
            scale_t *= _robust_sd(r[:nt]) if nt else 1.0
            scale_px *= _robust_sd(r[nt:]) if r.size > nt else 1.0
            prob = JointProblem(tree, prob.split(x)[0], stops, pixels, declared, sigma_tracker, sigma_px, scale_t,
                                scale_px)
            x = np.concatenate([x[:prob.P], np.zeros(6 * len(prob.sessions))])  # T0 re-registered
        if x.size == 0:
            break
        sol = least_squares(prob.residuals, x, jac=prob.jacobian, method="trf", loss=loss, f_scale=robust_scale,
                            x_scale=1.0, max_nfev=max_nfev, xtol=1e-10, ftol=1e-10, gtol=1e-10)
        x, nfev = sol.x, nfev + int(sol.nfev)
    r, J = prob.evaluate(x, jac=True)
    assert J is not None
    w = _loss_weights(r, loss, robust_scale)
    clusters = prob.residual_clusters(pose_t, None) if clustered else None
    cov = joint_covariance(J, r, w, clusters) if J.shape[1] else np.zeros((0, 0))
    fitted, T_reg = prob.split(x)
    return JointFit(fitted=fitted, effects=_effect_entries(fitted, cov), regs=dict(zip(prob.sessions, T_reg)),
                    pixel_rms=_pixel_rms(tree, pixels, declared, fitted),
                    tracker_rms=_tracker_rms(prob, r), iterations=nfev,
                    cost=float(sol.cost) if sol is not None else 0.0, cov=cov,
                    sensor_sigma={"tracker": float(np.median(prob.sigma_t)) if prob.n_tracker else float("nan"),
                                  "pixels": prob.sigma_px if pixels is not None else float("nan")},
                    message=str(sol.message) if sol is not None else "nothing to fit", x=x)


def sensor_noise(tree: KinematicTree, effects: Sequence[Effect], stops: Stops, pixels: PixelObs,
                 declared: Sequence[Effect] = (), **options: Any) -> tuple[float, float]:
    """Noise of each sensor from its own fit of ``effects``, as factors ``(scale_t, scale_px)`` on its declared
    noise: the robust scale (1.4826 MAD) of the whitened residual of a tracker-only / pixel-only
    :func:`joint_fit` (no rescale; ``options`` go to it).  The start of the joint solve: with the declared noise,
    a sensor whose residual is far above it (model error, not sensor noise; Motoman pixels: 10 px at 1 px
    declared) would outweigh the other one and bend the shared effects towards it."""
    out = []
    sig = {"sigma_tracker": options.pop("sigma_tracker", None), "sigma_px": options.pop("sigma_px", None)}
    for st, px in ((stops, None), (None, pixels)):
        fit = joint_fit(tree, effects, st, px, declared, rescale=0, clustered=False, presolve=False, **sig, **options)
        prob = JointProblem(tree, fit.fitted, st, px, declared, **sig)
        th = np.concatenate([e.params for e in fit.fitted]) if fit.fitted else np.zeros(0)
        out.append(max(_robust_sd(prob.residuals(np.concatenate([th, np.zeros(6 * len(prob.sessions))]))), 1e-6))
    return out[0], out[1]


def _effect_entries(fitted: Sequence[Effect], cov: np.ndarray) -> list[dict[str, Any]]:
    """``{name, location, measurement, parameters, ci, sigma}`` of each fitted effect (marginal 95 % CI)."""
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    out = []
    k = 0
    for e in fitted:
        sg = sig[k:k + e.n_params]
        k += e.n_params
        trip = list(zip(e.param_names, e.params, sg))
        out.append({"name": e.name, "location": e.location, "measurement": "joint",
                    "parameters": {p: float(v) for p, v, _ in trip},
                    "ci": {p: [float(v - 1.96 * s), float(v + 1.96 * s)] for p, v, s in trip},
                    "sigma": {p: float(s) for p, _, s in trip}})
    return out


def _pixel_rms(tree: KinematicTree, obs: PixelObs | None, declared: Sequence[Effect],
               fitted: Sequence[Effect]) -> dict[str, float]:
    from ppoe_core.analysis.diagnose.pixels import pixel_rms

    return {} if obs is None else pixel_rms(tree, obs, [*declared, *fitted])


def _tracker_rms(prob: JointProblem, r: np.ndarray) -> float:
    """RMS of the 3D tracker residual [m] from the whitened residual vector."""
    if not prob.n_tracker:
        return float("nan")
    e = r[:3 * prob.n_tracker].reshape(-1, 3) * prob.sigma_t[:, None]
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
