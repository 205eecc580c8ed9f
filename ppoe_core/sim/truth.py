"""The true robot of a simulation: nominal URDF + drawn perturbations + the scenario's effects, on the one kinematic
tree.

The effects' physics is the simulator's own (deliberately independent of :mod:`ppoe_core.model.effects`, so that
``ppoe diagnose`` is tested against physics, not against its own parametrisation)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import ScenarioError
from ppoe_core.robot.tree import GRAVITY, KinematicTree
from ppoe_core.robot.urdf import Robot
from ppoe_core.sim.scenario import TRUTH_EFFECTS
from ppoe_core.sim.schedule import Schedule, parse_value

#: effects whose parameters cannot change during a recording
_CONSTANT = ("time_offset", "camera_intrinsics", "tag_offset")


def tag_location(loc: Any, where: str) -> str:
    """``tag_<id>`` from a tag_offset location written as ``tag_<id>`` or as the id (an integer)."""
    s = str(loc)
    if isinstance(loc, bool) or not (s.isdigit() or (s.startswith("tag_") and s[4:].isdigit())):
        raise ScenarioError(f"{where}: tag_offset location must be tag_<id> or the tag id, got {loc!r}")
    return f"tag_{int(s[4:] if s.startswith('tag_') else s)}"


# =============================================================================
# true robot
# =============================================================================


class TrueRobot:
    """Forward kinematics of the true robot: nominal URDF + drawn xi + effects.

    Parameters
    ----------
    robot : Robot
    effects : list of dict
        ``{name, location, parameters}`` entries (validated here).
    where : str
        Used in error messages (scenario file).
    temperature : Schedule, optional
        Temperature [deg C] over time (s since start) for ``thermal_growth`` with ``variable: temperature``.

    A parameter is a float, or a :class:`~ppoe_core.sim.schedule.Schedule` when it changes during the recording
    (:mod:`ppoe_core.sim.schedule`); :meth:`poses` evaluates it at each sample's elapsed time.
    """

    def __init__(self, robot: Robot, effects: Sequence[Mapping[str, Any]], where: str = "truth.effects",
                 temperature: Schedule | None = None) -> None:
        self.robot = robot
        self.temperature = temperature
        self.tree = KinematicTree(robot)
        self.order = self.tree.order
        self.effects: list[dict[str, Any]] = []
        for i, e in enumerate(effects):
            self.effects.append(self._validate(e, f"{where}[{i}]"))

    def _validate(self, e: Any, where: str) -> dict[str, Any]:
        if (not isinstance(e, Mapping) or set(e) - {"name", "location", "parameters", "variable", "reference"}
                or "name" not in e):
            raise ScenarioError(f"{where}: an effect is {{name, location, parameters}}, got {e!r}")
        name = e["name"]
        if name not in TRUTH_EFFECTS:
            raise ScenarioError(f"{where}: unknown effect {name!r} (known: {list(TRUTH_EFFECTS)})")
        params = e.get("parameters") or {}
        bad = sorted(set(params) - set(TRUTH_EFFECTS[name]))
        if bad:
            raise ScenarioError(f"{where}: effect {name} has no parameters {bad} (has {list(TRUTH_EFFECTS[name])})")
        loc = self._location(name, e.get("location", ""), where)
        out: dict[str, Any] = {"name": name, "location": loc, "parameters": {}}
        for k in TRUTH_EFFECTS[name]:
            s = parse_value(params.get(k, 0.0), f"{where}.parameters.{k}")
            out["parameters"][k] = s.values[0] if len(s.values) == 1 else s
            if name in _CONSTANT and isinstance(out["parameters"][k], Schedule):
                raise ScenarioError(f"{where}: {name} {k} cannot change during the recording")
        if set(e) & {"variable", "reference"}:
            if name != "thermal_growth":
                raise ScenarioError(f"{where}: only thermal_growth takes 'variable' and 'reference'")
            out["variable"] = str(e.get("variable", "time"))
            if out["variable"] not in ("time", "temperature"):
                raise ScenarioError(f"{where}.variable must be time or temperature, got {out['variable']!r}")
            if out["variable"] == "temperature" and self.temperature is None:
                raise ScenarioError(f"{where}: variable temperature needs the scenario's temperature section")
            out["reference"] = parse_value(e.get("reference", 0.0), f"{where}.reference").values[0]
        return out

    def _location(self, name: str, raw: Any, where: str) -> str:
        """The checked location of a true effect ``name`` (root link, tag, camera frame, joint or topic)."""
        loc = str(raw)
        if name == "base_tilt":
            if loc != self.robot.root:
                raise ScenarioError(f"{where}: base_tilt location must be the root link '{self.robot.root}'")
        elif name == "tag_offset":
            loc = tag_location(raw, where)
        elif name == "camera_intrinsics":
            if loc not in self.robot.links:
                raise ScenarioError(f"{where}: camera_intrinsics location '{loc}' is not a link (the camera's optical "
                                    f"frame) of {self.robot.source}")
        elif name != "time_offset":
            if loc not in self.robot.joints:
                raise ScenarioError(f"{where}: location '{loc}' is not a joint of {self.robot.source}")
            if (
                name in ("joint_offset", "gravity_compliance", "backlash", "transmission_error")
                and not self.robot.joints[loc].movable
            ):
                raise ScenarioError(f"{where}: {name} needs a movable joint, '{loc}' is {self.robot.joints[loc].type}")
        return loc

    @staticmethod
    def params_at(e: Mapping[str, Any], elapsed: np.ndarray) -> dict[str, Any]:
        """Parameters of effect ``e`` at ``elapsed`` (n,) [s since start]: floats, or (n,) for schedules."""
        return {k: v(elapsed) if isinstance(v, Schedule) else v for k, v in e["parameters"].items()}

    def effect_param(self, name: str, key: str, location: str | None = None) -> float:
        """Sum of parameter ``key`` over the true effects called ``name`` (at ``location`` if given; 0 if none)."""
        return sum(e["parameters"][key] for e in self.effects
                   if e["name"] == name and (location is None or e["location"] == location))

    def true_camera(self, frame: str, K: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The TRUE intrinsics of the camera ``frame`` whose declared ``K`` (3, 3) [px] and plumb_bob ``D`` (5,)
        are given: plus the ``camera_intrinsics`` effects at ``frame`` (``fx fy cx cy`` [px], ``k1 k2 p1 p2 k3``)."""
        d = {k: self.effect_param("camera_intrinsics", k, frame) for k in TRUTH_EFFECTS["camera_intrinsics"]}
        K_true = np.array(K, dtype=float, copy=True)
        K_true[0, 0] += d["fx"]
        K_true[1, 1] += d["fy"]
        K_true[0, 2] += d["cx"]
        K_true[1, 2] += d["cy"]
        D_true = np.array(D, dtype=float, copy=True) + np.array([d[k] for k in ("k1", "k2", "p1", "p2", "k3")])
        return K_true, D_true

    def tag_offset(self, tag_id: int) -> np.ndarray:
        """``T_mount_true`` (4, 4): the true pose of tag ``tag_id`` in its declared (model YAML) pose, the product
        of ``Exp([x y z rx ry rz])`` of its ``tag_offset`` effects (identity without one)."""
        T = np.eye(4)
        for e in self.effects:
            if e["name"] == "tag_offset" and e["location"] == f"tag_{int(tag_id)}":
                T = T @ lie.exp(np.array([e["parameters"][k] for k in TRUTH_EFFECTS["tag_offset"]], dtype=float))
        return T

    # -- chain ------------------------------------------------------------------
    def link_poses(
        self, q: Mapping[str, np.ndarray], dq: Mapping[str, np.ndarray], dT: Mapping[str, np.ndarray], n: int
    ) -> dict[str, np.ndarray]:
        """``T_root_link`` (n, 4, 4) of every link with eq. 16 links ``Exp(p) dT Exp(zeta (q + dq))``,
        on the one kinematic tree (:class:`~ppoe_core.robot.tree.KinematicTree`).

        ``dT`` here already holds ``Exp(dxi_effects) Exp(xi)`` composed by the caller
        (as separate factors, see :meth:`poses`).
        """
        return self.tree.link_poses(q, dq, dT=dT)

    def gravity_moment(
        self, poses: Mapping[str, np.ndarray], joint: str, after_motion: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Weight of the links carried by ``joint``: force [N] (n,3) and moment [N m] (n,3) about the
        joint frame origin, in the joint frame axes (``after_motion``: the child frame; else the frame
        right after the joint's origin).  Gravity is -z of the root."""
        j = self.robot.joints[joint]
        T = poses[j.child] if after_motion else poses[j.parent] @ j.origin
        n = T.shape[0]
        F = np.zeros((n, 3))
        M = np.zeros((n, 3))
        g = np.array([0.0, 0.0, -GRAVITY])
        for ln in self.tree.subtree_links(joint):
            inert = self.robot.links[ln].inertial
            if inert is None or inert.mass <= 0:
                continue
            c = (poses[ln] @ inert.origin)[:, :3, 3]
            f = inert.mass * g
            F += f
            M += np.cross(c - T[:, :3, 3], f)
        Rt = np.swapaxes(T[:, :3, :3], 1, 2)
        return np.einsum("nij,nj->ni", Rt, F), np.einsum("nij,nj->ni", Rt, M)

    def poses(
        self,
        q: Mapping[str, np.ndarray],
        xi: Mapping[str, np.ndarray],
        dq_noise: Mapping[str, np.ndarray],
        motion_sign: Mapping[str, np.ndarray],
        elapsed: np.ndarray,
        n: int,
    ) -> dict[str, np.ndarray]:
        """True link poses (n, 4, 4) in the root frame.

        Parameters
        ----------
        q : joint -> (n,)
            Commanded (= recorded) joint values of the independent joints.
        xi : joint -> (n, 6)
            Drawn perturbations (paper eq. 16), tangent space right after the joint origin.
        dq_noise : joint -> (n,)
            Drawn joint-value errors (model ``joint_noise``).
        motion_sign : joint -> (n,)
            Sign of each joint's last motion (backlash).
        elapsed : (n,)
            Seconds since the start of the bag (thermal growth).
        n : int
            Number of samples (the batch size of every array above).

        Returns
        -------
        dict link -> (n, 4, 4) ``T_root_link`` of the true robot.
        """
        dq, fx = self._static_corrections(q, dq_noise, motion_sign, elapsed, n)

        def add_dq(j: str, v: Any) -> None:
            dq[j] = dq.get(j, np.zeros(n)) + v

        def add_fx(j: str, v: np.ndarray) -> None:
            fx[j] = fx.get(j, np.zeros((n, 6))) + v

        def build(dq_: Mapping[str, np.ndarray], fx_: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
            dx = {}
            for jn in set(xi) | set(fx_):
                T = np.broadcast_to(np.eye(4), (n, 4, 4))
                if jn in fx_:
                    T = T @ lie.exp(fx_[jn])
                if jn in xi:
                    T = T @ lie.exp(xi[jn])
                dx[jn] = T
            return self.link_poses(q, dq_, dx, n)

        # gravity-dependent effects: loads evaluated on the chain without them (first order in the
        # deflection); gravity is -z of the root link
        grav = [e for e in self.effects if e["name"] in ("gravity_compliance", "mount_bending", "lateral_compliance")]
        if grav:
            base = build(dq, fx)
            for e in grav:
                loc, p = e["location"], self.params_at(e, np.asarray(elapsed, float))
                if e["name"] == "gravity_compliance":
                    j = self.robot.joints[loc]
                    F, M = self.gravity_moment(base, loc, after_motion=True)
                    tau = (F if j.type == "prismatic" else M) @ j.axis
                    add_dq(loc, p["compliance"] * tau)
                elif e["name"] == "lateral_compliance":
                    add_fx(loc, self._lateral(base, loc, p))
                else:
                    _, M = self.gravity_moment(base, loc, after_motion=False)
                    v = np.zeros((n, 6))
                    v[:, 3] = p["compliance_x"] * M[:, 0]
                    v[:, 4] = p["compliance_y"] * M[:, 1]
                    add_fx(loc, v)
        return build(dq, fx)

    def _lateral(self, poses: Mapping[str, np.ndarray], joint: str, p: Mapping[str, float]) -> np.ndarray:
        """Twist (n, 6) at ``joint``'s origin of lateral compliance: in the child frame the link turns by
        ``c_u (M.u) u + c_v (M.v) v`` (``M`` the gravity moment there, ``u, v`` perpendicular to the axis); moved
        to the frame before the motion by the joint's rotation, which fixes the origin."""
        from ppoe_core.model.effects import perpendicular_axes

        j = self.robot.joints[joint]
        uv = perpendicular_axes(j.axis)
        _, M = self.gravity_moment(poses, joint, after_motion=True)
        theta_c = ((p["compliance_u"] * (M @ uv[0]))[:, None] * uv[0]
                   + (p["compliance_v"] * (M @ uv[1]))[:, None] * uv[1])
        T_a = poses[j.parent] @ j.origin
        R_ac = np.swapaxes(T_a[:, :3, :3], 1, 2) @ poses[j.child][:, :3, :3]
        v = np.zeros((theta_c.shape[0], 6))
        v[:, 3:] = np.einsum("nij,nj->ni", R_ac, theta_c)
        return v

    def _static_corrections(
        self,
        q: Mapping[str, np.ndarray],
        dq_noise: Mapping[str, np.ndarray],
        motion_sign: Mapping[str, np.ndarray],
        elapsed: np.ndarray,
        n: int,
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Joint-value errors ``dq`` (joint -> (n,)) and effect twists ``fx`` (joint -> (n, 6)) of the effects
        that do not depend on gravity (joint offset, transmission error, backlash, link error, camera
        extrinsics, thermal growth, base tilt), on top of the drawn joint noise."""
        dq: dict[str, np.ndarray] = {k: np.asarray(v, float).copy() for k, v in dq_noise.items()}
        fx: dict[str, np.ndarray] = {}  # effect twists per joint (n, 6)

        def add_dq(j: str, v: Any) -> None:
            dq[j] = dq.get(j, np.zeros(n)) + v

        def add_fx(j: str, v: np.ndarray) -> None:
            fx[j] = fx.get(j, np.zeros((n, 6))) + v

        el = np.broadcast_to(np.asarray(elapsed, float), (n,))
        for e in self.effects:
            nm, loc, p = e["name"], e["location"], self.params_at(e, el)
            if nm == "joint_offset":
                add_dq(loc, p["offset"])
            elif nm == "transmission_error":
                add_dq(loc, p["amplitude"] * np.sin(p["periods"] * np.asarray(q[loc], float)))
            elif nm == "backlash":
                add_dq(loc, p["play"] * np.asarray(motion_sign.get(loc, np.zeros(n)), float))
            elif nm in ("link_error", "camera_extrinsics"):
                add_fx(loc, np.stack([np.broadcast_to(p[k], (n,)) for k in TRUTH_EFFECTS[nm]], axis=-1))
            elif nm == "thermal_growth":
                o = self.robot.joints[loc].origin
                d = o[:3, :3].T @ o[:3, 3]
                u = el
                if e.get("variable") == "temperature":
                    assert self.temperature is not None  # checked in _validate
                    u = self.temperature(el) - e["reference"]
                elif "reference" in e:
                    u = el - e["reference"]
                v = np.zeros((n, 6))
                v[:, :3] = (p["alpha"] * u)[:, None] * d
                add_fx(loc, v)
            elif nm == "base_tilt":
                # everything hanging on the root rotates about the root's x and y axes:
                # Exp(w) Exp(p_j) = Exp(p_j) Exp(Ad(Exp(p_j)^-1) w) for each child joint j of the root
                w = np.zeros((n, 6))
                w[:, 3], w[:, 4] = p["tilt_x"], p["tilt_y"]
                for jn in self.robot.children(self.robot.root):
                    Ad = lie.adjoint(lie.inverse(self.robot.joints[jn].origin))
                    add_fx(jn, w @ Ad.T)
        return dq, fx
