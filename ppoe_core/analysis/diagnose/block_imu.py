"""Accelerometer tilts: at rest an accelerometer on a link measures gravity, i.e. the link's tilt.

Row ``i`` (a stop) has two components per accelerometer ``k``: the small rotations about the sensor link's x and y
axes between the measured up direction ``u_m`` (the normalised specific force) and the predicted one, ``[u_m,y -
u_p,y, -(u_m,x - u_p,x)]`` with ``u_p = R_root_link^T z_root`` on the corrected chain.  A right perturbation ``phi``
of the link's rotation moves ``u_p`` by ``u_p x phi``: the tilt prediction moves by ``A phi``, ``A = [[u_z, 0,
-u_x], [0, u_z, -u_y]]``, and the chain part is the rotation rows of :meth:`KinematicTree.frame_jacobian`.

Nuisances, per session (a bag, or a station of a mobile robot: one placement): the base tilt ``w`` of the placement
relative to the first one (2, root axes: ``u_p = R^T Exp(-w) z``, ``du/dw = R^T Exp(-w) [z]x J_r(-w)`` (x, y
columns); none for the first placement, whose tilt is the ``base_tilt`` effect: the reference accelerometer, the one
nearest the root, is taken as mounted as declared), and the mounting of every other accelerometer (2 each, additive
on its two tilt components); their current values are the block's state (the solver's steps update it).
``base_tilt`` driven by the measured tilt is made of these readings: it is not a prediction of them (zero Jacobian,
left out of the prediction).  Noise: ``sigma / |a|`` per component (``sigma`` per accelerometer [m/s^2], model
``imus``; default 4e-4) plus the declared prior on the link's rotation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock, chain_columns, prior_covariance
from ppoe_core.analysis.diagnose.block_tracker import configuration_columns, time_columns
from ppoe_core.analysis.diagnose.candidates import carried_mass
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import MeasurementError
from ppoe_core.model.context import REST_SPEED
from ppoe_core.model.effects import Effect, make_effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["ImuBlock", "DEFAULT_IMU_SIGMA", "at_rest"]

#: accelerometer 1-sigma per axis [m/s^2] when the model's ``imus`` section gives none
DEFAULT_IMU_SIGMA = 4e-4


def at_rest(stops: Stops) -> np.ndarray:
    """Rows (N,) where no joint moves faster than :data:`~ppoe_core.model.context.REST_SPEED` (an accelerometer
    measures gravity only at rest: elsewhere its specific force holds the motion's acceleration): context
    ``at_rest`` (:func:`ppoe_core.model.context.at_rest`, encoder noise taken off) where the stops carry it, else the
    context ``joint_velocity``; all rows without either."""
    if "at_rest" in stops.context:
        return np.asarray(stops.context["at_rest"], dtype=bool)
    vel = stops.context.get("joint_velocity") or {}
    if not vel:
        return np.ones(len(stops), dtype=bool)
    return np.max(np.abs(np.stack([np.asarray(v, dtype=float) for v in vel.values()])), axis=0) <= REST_SPEED


def _measured_tilt(effect: Effect) -> bool:
    """A ``base_tilt`` driven by the measured tilt (made of the accelerometers' readings)."""
    return effect.name == "base_tilt" and getattr(effect, "variable", None) == "measured"


class ImuBlock(ResidualBlock):
    """Accelerometer tilts (module docstring)."""

    kind = "imu"
    unit = "rad"

    def __init__(self, tree: KinematicTree, stops: Stops, sigma: Mapping[str, float] | None = None) -> None:
        if not stops.imus:
            raise MeasurementError("imu block: the stops carry no accelerometer (/imu/<name>) data")
        rest = at_rest(stops)
        self.dropped = int((~rest).sum())
        if not rest.all():
            stops = stops.subset(rest)
        self.names = list(stops.imus)
        self.links = [ln for ln, _ in stops.imus.values()]
        acc = np.stack([a for _, a in stops.imus.values()], axis=1)  # (n, K, 3)
        bad = ~np.all(np.isfinite(acc), axis=(1, 2))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise MeasurementError(f"imu block: non-finite accelerometer values (first: stop {i} of "
                                   f"{stops.group_names[stops.group[i]]})")
        self.norm = np.linalg.norm(acc, axis=2)
        self.u_m = acc / self.norm[..., None]
        self.sigma = np.array([(sigma or {}).get(k, DEFAULT_IMU_SIGMA) for k in self.names])
        self.K = len(self.names)
        self.dim = 2 * self.K
        self.nuisance_dim = 2 * self.K
        self.ref = int(np.argmin([len(tree.robot.path_from_root(ln)) for ln in self.links]))
        self.stops = stops
        super().__init__(tree, stops.q, stops.context, stops.session, stops.session_names, stops.group,
                         stops.group_names)
        self.nu = np.zeros((len(stops.session_names), 2 * self.K))

    def _poses(self, effects: Sequence[Effect]) -> tuple[dict, dict, dict]:
        eff = [e for e in effects if not _measured_tilt(e)]
        return self.chain(eff)

    def pose_links(self) -> list[str]:
        return list(self.links)

    def linearise(self, effects: Sequence[Effect], candidates: Sequence[Effect], pert: Mapping[str, np.ndarray],
                  jnoise: Mapping[str, float], chain: bool = False) -> Linearisation:
        poses, dq, dxi = self._poses(effects)
        n, K = len(self), self.K
        N, S = np.zeros((n, 2 * K, 2 * K)), np.zeros((n, 2 * K, 2 * K))
        Jq: dict[str, np.ndarray] = {}
        Jx: dict[str, np.ndarray] = {}
        need = chain or bool(candidates) or bool(pert) or bool(jnoise)
        r, w, Rw, ups = self._tilts(poses)
        joints = self.chain_joints(candidates, pert, jnoise, chain)
        # d Exp(-w) z / d w = Exp(-w) [z]x J_r(-w) (x, y columns: the tilt has no z part)
        dg = (Rw @ lie.hat3(np.array([0.0, 0.0, 1.0])) @ lie.so3_right_jacobian(w))[:, :, :2]
        for k, link in enumerate(self.links):
            R, u = poses[link][:, :3, :3], ups[k]
            sl = slice(2 * k, 2 * k + 2)
            S[:, sl, sl] = (self.sigma[k] / self.norm[:, k])[:, None, None] ** 2 * np.eye(2)
            A = np.zeros((n, 2, 3))  # d tilt / d phi (right perturbation of the link's rotation)
            A[:, 0, 0], A[:, 0, 2] = u[:, 2], -u[:, 0]
            A[:, 1, 1], A[:, 1, 2] = u[:, 2], -u[:, 1]
            du = np.einsum("nji,njk->nik", R, dg)  # d u / d w
            N[:, sl, 0:2] = np.stack([du[:, 1, :], -du[:, 0, :]], axis=1) * (self.segment > 0)[:, None, None]
            if k != self.ref:
                c = 2 + 2 * self._mount_slot(k)
                N[:, sl, c:c + 2] = np.eye(2)
            if need:
                Fq, Fx = self.tree.frame_jacobian(self.q, link, poses, dq, dxi, joints)
                for j, F in Fq.items():
                    Jq.setdefault(j, np.zeros((n, 2 * K)))[:, sl] = np.einsum("nij,nj->ni", A, F[:, 3:])
                for j, F in Fx.items():
                    Jx.setdefault(j, np.zeros((n, 2 * K, 6)))[:, sl] = A @ F[:, 3:]
        J = [np.zeros((n, 2 * K, c.n_params)) if _measured_tilt(c)
             else chain_columns(Jq, Jx, self.basis(c), c.n_params, (n, 2 * K)) for c in candidates]
        return Linearisation(r, J, N, S, prior_covariance(Jq, Jx, pert, jnoise, (n, 2 * K)), Jq=Jq)

    def residual(self, effects: Sequence[Effect]) -> np.ndarray:
        """:meth:`linearise`'s ``r`` alone (no Jacobians, nuisance columns or covariances: a refit's trial)."""
        return self._tilts(self._poses(effects)[0])[0]

    def _tilts(self, poses: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """Residual rows (n, 2K) at the link ``poses`` and the current placements, the placement tilts ``w`` (n, 3)
        with ``Exp(-w)`` (n, 3, 3), and per sensor the predicted up direction ``u`` (n, 3) in its link frame."""
        n, K = len(self), self.K
        r = np.empty((n, 2 * K))
        nu = self.nu[self.segment]  # (n, 2K): placement tilt, then the mountings
        w = np.zeros((n, 3))
        w[:, :2] = -nu[:, :2]
        Rw = lie.so3_exp(w)
        g = Rw[:, :, 2]  # Exp(-w) z: the up direction in the tilted root frame
        ups = []
        for k, link in enumerate(self.links):
            u = np.einsum("nji,nj->ni", poses[link][:, :3, :3], g)  # R^T Exp(-w) z
            sl = slice(2 * k, 2 * k + 2)
            mount = nu[:, 2 + 2 * self._mount_slot(k):4 + 2 * self._mount_slot(k)] if k != self.ref else 0.0
            r[:, sl] = np.column_stack([self.u_m[:, k, 1] - u[:, 1], -(self.u_m[:, k, 0] - u[:, 0])]) - mount
            ups.append(u)
        return r, w, Rw, ups

    def _mount_slot(self, k: int) -> int:
        """Index of accelerometer ``k``'s mounting among the non-reference ones."""
        return k if k < self.ref else k - 1

    def apply_nuisance(self, step: np.ndarray) -> None:
        self.nu = self.nu + np.asarray(step, dtype=float).reshape(self.nu.shape)

    def nuisance_state(self) -> np.ndarray:
        return self.nu.copy()

    def set_nuisance_state(self, state: np.ndarray) -> None:
        self.nu = state.copy()

    def placement_tilts(self) -> dict[str, list[float]]:
        """The placement tilt of each session [rad, about the root's x and y] (the reference sensor's mounting
        included): the nuisance values of the last fit."""
        return {name: [float(v) for v in self.nu[g, :2]] for g, name in enumerate(self.segment_names)}

    def candidates(self) -> list[Effect]:
        """``base_tilt`` (the first placement's), ``joint_offset`` (revolute), ``gravity_compliance`` and
        ``mount_bending`` on the paths to the sensors (rotations; a constant rotation of another sensor's link is its
        mounting)."""
        robot, seen = self.tree.robot, set()
        out = [make_effect("base_tilt", robot.root, self.tree)]
        for link in self.links:
            for jn in robot.path_from_root(link):
                if jn in seen:
                    continue
                seen.add(jn)
                j, mass = robot.joints[jn], carried_mass(self.tree, jn)
                if j.movable and j.type != "prismatic":
                    out.append(make_effect("joint_offset", jn, self.tree))
                    if mass > 0.0:
                        out.append(make_effect("gravity_compliance", jn, self.tree))
                if (not j.movable or j.type == "prismatic") and mass > 0.0:
                    out.append(make_effect("mount_bending", jn, self.tree))
        return out

    def chain_links(self) -> list[str]:
        return list(self.links)

    def structure_columns(self, lin: Linearisation) -> dict[str, np.ndarray]:
        return {**configuration_columns(self.tree, self.q, lin.Jq),
                "time": time_columns(self.context.get("time"), self.group, self.dim)}

    def report_groups(self) -> dict[str, np.ndarray]:
        return {}

    def error_norm(self, r: np.ndarray) -> np.ndarray:
        """RMS over the sensors of the tilt angle [rad] per stop."""
        return np.sqrt(np.sum(r ** 2, axis=-1) / self.K)
