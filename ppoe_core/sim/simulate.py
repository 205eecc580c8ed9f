"""``ppoe simulate``: record contract bags (CONTRACT.md sec. 3) of a simulated robot.

The *true* robot is the nominal URDF plus

* the declared perturbations ``xi_i`` of the model YAML, drawn from their covariance
  (once per bag, once per stop, or not at all) and the declared joint noise (per stop),
* named systematic effects from the scenario's ``truth.effects`` that the model may not
  declare (CONTRACT sec. 6 vocabulary, implemented here independently of
  :mod:`ppoe_core.model.effects` so that ``ppoe diagnose`` is tested against physics, not
  against its own code): ``joint_offset``, ``link_error``, ``gravity_compliance``,
  ``mount_bending``, ``base_tilt``, ``backlash``, ``thermal_growth``, ``time_offset``,
  ``camera_extrinsics``.

One link of the true chain is (paper eq. 16 with the effects inserted)::

    Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))

with ``dq_i`` from joint offsets, backlash, gravity compliance and joint noise, and
``dxi_i`` from link errors, mount bending, thermal growth and camera extrinsics.

Sensors: joint states (the commanded / measured values), camera images with the model's
tags rendered at their TRUE pose (:func:`ppoe_core.sensing.tags.render_tags`), contact wrenches
against a true plane, ground-truth tool poses (tracker noise), tracker points in an
unknown tracker frame, accelerometers.  Everything is deterministic for a seed.

The scenario YAML is documented key by key in :data:`SCENARIO_DOC` (also printed by
``ppoe simulate --help-scenario``); example files are in ``bags/``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import ModelConfigError, PpoeError, ScenarioError, UnknownFrameError, UnknownJointError, UrdfError
from ppoe_core.estimation.camera import project_points
from ppoe_core.io.bagio import BagWriter
from ppoe_core.robot.config import ModelConfig, load_model_config
from ppoe_core.robot.tree import GRAVITY, KinematicTree
from ppoe_core.robot.urdf import Robot, parse_urdf
from ppoe_core.robot.yaml_io import read_yaml_file
from ppoe_core.sensing.tags import render_tags, tag_points_local

__all__ = [
    "SCENARIO_DOC",
    "TRUTH_EFFECTS",
    "Scenario",
    "TrueRobot",
    "SimulationResult",
    "load_scenario",
    "simulate",
]

#: effects the simulator can put into the true robot, with their parameters
TRUTH_EFFECTS: dict[str, tuple[str, ...]] = {
    "joint_offset": ("offset",),
    "link_error": ("x", "y", "z", "rx", "ry", "rz"),
    "camera_extrinsics": ("x", "y", "z", "rx", "ry", "rz"),
    "gravity_compliance": ("compliance",),
    "mount_bending": ("compliance_x", "compliance_y"),
    "base_tilt": ("tilt_x", "tilt_y"),
    "backlash": ("play",),
    "thermal_growth": ("alpha",),
    "time_offset": ("dt",),
    # outside the CONTRACT sec. 6 vocabulary (for testing that diagnose reports it as unexplained):
    "transmission_error": ("amplitude", "periods"),
}

SCENARIO_DOC = """\
# ppoe simulate scenario (all keys; defaults in brackets). Paths are relative to the scenario file.
robot:
  urdf: ../config/robots/rover.urdf        # nominal URDF (written to /robot_description) [required]
  model: ../config/robots/rover_model.yaml # model YAML: perturbations, joint_noise, tags, camera, tracker, imus, contact [required]
seed: 0                    # RNG seed; `--seed` overrides [0]
start_time: 100.0          # stamp of the first message [s] [100.0]
truth:
  perturbations: once      # draw the model's perturbations xi: once | per_stop | none [once]
  perturbation_scale: 1.0  # multiplies the drawn xi [1.0]
  joint_noise: true        # add the model's joint_noise (per stop) to the true joint values [true]
  record_draws: false      # write each stop's window [s], drawn xi and joint errors to the truth file [false]
  effects:                 # systematic effects of the true robot, CONTRACT sec. 6 names [none]
    - {name: joint_offset, location: JOINT, parameters: {offset: 0.01}}        # q_true = q_meas + offset [rad|m]
    - {name: link_error, location: JOINT, parameters: {x: 0.001, rz: 0.002}}   # dxi at JOINT [m, rad]
    - {name: camera_extrinsics, location: JOINT, parameters: {x: .., rz: ..}}   # dxi at the camera's fixed joint [m, rad]
    - {name: gravity_compliance, location: JOINT, parameters: {compliance: 1e-4}}  # dq = c * gravity torque [rad/(N m)]
    - {name: mount_bending, location: JOINT, parameters: {compliance_x: 1e-4, compliance_y: 1e-4}}  # theta = c * moment [rad/(N m)]
    - {name: base_tilt, location: ROOT_LINK, parameters: {tilt_x: 0.002, tilt_y: 0.0}}  # robot tilted about root x, y [rad]
    - {name: backlash, location: JOINT, parameters: {play: 0.002}}             # dq = play * sign(last motion) [rad|m]
    - {name: thermal_growth, location: JOINT, parameters: {alpha: 1e-6}}      # origin of JOINT grows by alpha*(t - start_time) [1/s]
    - {name: time_offset, location: /joint_states, parameters: {dt: 0.02}}     # joint states stamped t carry q(t - dt) [s]
    - {name: transmission_error, location: JOINT, parameters: {amplitude: 0.003, periods: 3}}  # NOT in the
      # contract vocabulary: cyclic gear error dq = amplitude sin(periods q) [rad, periods per rad]
trajectory:
  joint_rate: 100.0        # /joint_states rate [Hz] (>= 50) [100.0]
  dwell: 0.5               # default time at each stop [s] [0.5]
  settle: 0.1              # time after arriving before the stop's measurements start [s] [0.1]
  move_time: 1.0           # min-jerk joint-space motion between stops [s] [1.0]
  extra_joints: {}         # joints published but not driven (name: value), e.g. a gripper [{}]
  start: {}                # values of joints not given in a stop [0 for each joint]
  stops:                   # configurations; each {joints: {name: value}, dwell: s, contact: {...}} [[]]
    - {joints: {joint_1: 0.3}, dwell: 0.5}
    # contact: {press_joint: JOINT, force: 10.0, approach: 0.15}: solve press_joint so the true
    # tool point presses the true plane with `force` [N]; an approach stop `approach` [rad|m] away is added.
  random_stops:            # optional, appended after `stops` [none]
    count: 20              # number of stops
    around: {}             # centre configuration (name: value); joints not listed come from `start`
    spread: 0.2            # uniform +- spread per joint [rad|m], or a mapping joint -> spread
    min_visible_tags: 0    # reject configurations where fewer model tags face the camera in view [0]
    min_link_z: {}         # reject configurations where a link's origin is below this root-frame z [m] [{}]
    max_tries: 5000        # give up after this many rejected draws [5000]
  smooth:                  # optional instead of stops: q_j(t) = centre + amplitude sin(2 pi t / period + phase)
    duration: 60.0         # [s]
    centre: {}             # [rad|m]
    amplitude: {}          # [rad|m]
    period: {}             # [s] [10 for each joint]
    phase: {}              # [rad] [0 for each joint]
camera:                    # optional; needs the model's camera and tags sections [none]
  frame: camera_optical_frame  # optical frame link [model camera.frame]
  width: 640               # [px] [640]
  height: 480              # [px] [480]
  intrinsics: [600, 600, 320, 240]   # fx, fy, cx, cy [px] [600, 600, width/2, height/2]
  D: [0, 0, 0, 0, 0]       # plumb_bob k1 k2 p1 p2 k3 [zeros]
  rate: 5.0                # image rate [Hz] (<= 30) [5.0]
  during: stops            # stops: only inside stops; always: whole bag [stops]
  format: png              # png | jpeg (/camera/image_raw/compressed) or raw (mono8 /camera/image_raw) [png]
  noise_sigma: 1.0         # Gaussian grey-level noise [1.0]
  blur_sigma: 0.0          # Gaussian blur before the noise [px] [0.0]
  background: 128          # grey level [128]
  time_offset: 0.0         # image stamps = true exposure time + this [s] [0.0]
ground_truth:
  pose:                    # /ground_truth/pose, optional [none]
    frame: base_link       # reference (header.frame_id) [model frames.base]
    target: tool0          # measured frame [model frames.tool]
    sigma_xyz: 0.0001      # tracker position noise 1-sigma [m] [0.0001]
    sigma_rot: 0.0002      # tracker rotation noise 1-sigma [rad] [0.0002]
    rate: 0.0              # [Hz]; 0 = once per stop [0.0]
  point:                   # /ground_truth/point, optional [none]
    link: tool0            # link carrying the reflector [model tracker.link]
    xyz: [0, 0, 0.02]      # reflector in that link [m] [model tracker.xyz]
    sigma: 0.0002          # noise 1-sigma per axis [m] [model tracker.sigma]
    frame: tracker         # header.frame_id (not in the URDF) [tracker]
    T_tracker_base: {xyz: [3, 1, 0.5], rpy: [0, 0, 2.5]}  # unknown registration [m, rad] [identity]
    rate: 0.0              # [Hz]; 0 = once per stop [0.0]
imus:                      # /imu/<name> for every IMU of the model, optional [none]
  rate: 0.0                # [Hz]; 0 = once per stop [0.0]
  sigma: null              # noise 1-sigma [m/s^2] [model imus.<name>.sigma]
contact:                   # /wrench, optional [none]
  plane: {frame: base_link, xyz: [0, 0, 0], rpy: [0, 0, 0]}  # TRUE plane pose, normal = z [model contact.plane]
  tool_point: {link: fingertip, xyz: [0, 0, 0]}  # contact point [model contact.tool_point]
  stiffness: 100000.0      # contact stiffness [N/m] [1e5]
  force_sigma: 0.1         # wrench noise 1-sigma per axis [N] [0.1]
  frame: fingertip         # wrench header.frame_id (force in its axes) [tool_point.link]
  rate: null               # [Hz] [trajectory.joint_rate]
"""

_TOP_KEYS = ("robot", "seed", "start_time", "truth", "trajectory", "camera", "ground_truth", "imus", "contact")


# =============================================================================
# scenario parsing
# =============================================================================


def _where(path: str, key: str) -> str:
    return f"scenario {path}: {key}"


def _check_keys(d: Any, allowed: Sequence[str], path: str, key: str) -> dict:
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ScenarioError(f"{_where(path, key)} must be a mapping, got {type(d).__name__}")
    bad = sorted(set(d) - set(allowed))
    if bad:
        raise ScenarioError(f"{_where(path, key)}: unknown keys {bad} (allowed: {list(allowed)})")
    return dict(d)


def _num(d: Mapping, k: str, default: Any, path: str, key: str, minimum: float | None = None,
         maximum: float | None = None) -> Any:
    v = d.get(k, default)
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ScenarioError(f"{_where(path, key + '.' + k)} must be a number, got {v!r}") from None
    if not math.isfinite(f) or (minimum is not None and f < minimum) or (maximum is not None and f > maximum):
        raise ScenarioError(f"{_where(path, key + '.' + k)} = {v!r} out of range [{minimum}, {maximum}]")
    return f


def _joints_map(d: Any, path: str, key: str, robot: Robot) -> dict[str, float]:
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ScenarioError(f"{_where(path, key)} must map joint names to values")
    out = {}
    for name, v in d.items():
        if name not in robot.joints or not robot.joints[name].movable:
            raise ScenarioError(f"{_where(path, key)}: '{name}' is not a movable joint of {robot.source}")
        try:
            out[str(name)] = float(v)
        except (TypeError, ValueError):
            raise ScenarioError(f"{_where(path, key + '.' + str(name))} must be a number, got {v!r}") from None
        if not math.isfinite(out[str(name)]):
            raise ScenarioError(f"{_where(path, key + '.' + str(name))} must be finite, got {v!r}")
    return out


def _pose_cfg(d: Any, path: str, key: str) -> np.ndarray:
    d = _check_keys(d, ("xyz", "rpy", "frame"), path, key)
    try:
        xyz = np.asarray(d.get("xyz", [0, 0, 0]), dtype=float).reshape(3)
        rpy = np.asarray(d.get("rpy", [0, 0, 0]), dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise ScenarioError(f"{_where(path, key)}: xyz and rpy must be 3 numbers each") from None
    return lie.from_xyz_rpy(xyz, rpy)


@dataclass
class Scenario:
    """A parsed, validated scenario (see :data:`SCENARIO_DOC`)."""

    path: str
    raw: dict
    robot: Robot
    model: ModelConfig
    urdf_text: str
    seed: int
    start_time: float


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read a scenario YAML and load its robot and model.

    Raises
    ------
    ScenarioError
        Missing file, YAML error, unknown key, bad value; the message names the file and key.
    """
    p = Path(path)
    raw, _ = read_yaml_file(p, "scenario", ScenarioError)
    raw = _check_keys(raw, _TOP_KEYS, str(p), "top level")
    rob = _check_keys(raw.get("robot"), ("urdf", "model"), str(p), "robot")
    if "urdf" not in rob or "model" not in rob:
        raise ScenarioError(f"{_where(str(p), 'robot')} needs 'urdf' and 'model'")
    urdf_path = (p.parent / str(rob["urdf"])).resolve()
    model_path = (p.parent / str(rob["model"])).resolve()
    try:
        urdf_text = urdf_path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{_where(str(p), 'robot.urdf')}: cannot read {urdf_path}: {exc}") from None
    try:
        robot = parse_urdf(str(urdf_path))
        model = load_model_config(str(model_path), robot)
    except (UrdfError, ModelConfigError, UnknownJointError, UnknownFrameError) as exc:
        raise ScenarioError(f"scenario {p}: {exc}") from None
    seed = raw.get("seed", 0)
    if not isinstance(seed, int) or seed < 0:
        raise ScenarioError(f"{_where(str(p), 'seed')} must be a non-negative integer, got {seed!r}")
    start = _num(raw, "start_time", 100.0, str(p), "top", minimum=0.0)
    return Scenario(str(p), raw, robot, model, urdf_text, int(seed), float(start))


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
    """

    def __init__(self, robot: Robot, effects: Sequence[Mapping[str, Any]], where: str = "truth.effects") -> None:
        self.robot = robot
        self.tree = KinematicTree(robot)
        self.order = self.tree.order
        self.effects: list[dict[str, Any]] = []
        for i, e in enumerate(effects):
            self.effects.append(self._validate(e, f"{where}[{i}]"))

    def _validate(self, e: Any, where: str) -> dict[str, Any]:
        if not isinstance(e, Mapping) or set(e) - {"name", "location", "parameters"} or "name" not in e:
            raise ScenarioError(f"{where}: an effect is {{name, location, parameters}}, got {e!r}")
        name = e["name"]
        if name not in TRUTH_EFFECTS:
            raise ScenarioError(f"{where}: unknown effect {name!r} (known: {list(TRUTH_EFFECTS)})")
        loc = str(e.get("location", ""))
        params = e.get("parameters") or {}
        bad = sorted(set(params) - set(TRUTH_EFFECTS[name]))
        if bad:
            raise ScenarioError(f"{where}: effect {name} has no parameters {bad} (has {list(TRUTH_EFFECTS[name])})")
        if name == "base_tilt":
            if loc != self.robot.root:
                raise ScenarioError(f"{where}: base_tilt location must be the root link '{self.robot.root}'")
        elif name != "time_offset":
            if loc not in self.robot.joints:
                raise ScenarioError(f"{where}: location '{loc}' is not a joint of {self.robot.source}")
            if name in ("joint_offset", "gravity_compliance", "backlash", "transmission_error") and not self.robot.joints[loc].movable:
                raise ScenarioError(f"{where}: {name} needs a movable joint, '{loc}' is {self.robot.joints[loc].type}")
        return {"name": name, "location": loc,
                "parameters": {k: float(params.get(k, 0.0)) for k in TRUTH_EFFECTS[name]}}

    def effect_param(self, name: str, key: str) -> float:
        """Sum of parameter ``key`` over the true effects called ``name`` (0 if none)."""
        return sum(e["parameters"][key] for e in self.effects if e["name"] == name)

    # -- chain ------------------------------------------------------------------
    def link_poses(self, q: Mapping[str, np.ndarray], dq: Mapping[str, np.ndarray],
                   dT: Mapping[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
        """``T_root_link`` (n, 4, 4) of every link with eq. 16 links ``Exp(p) dT Exp(zeta (q + dq))``,
        on the one kinematic tree (:class:`~ppoe_core.robot.tree.KinematicTree`).

        ``dT`` here already holds ``Exp(dxi_effects) Exp(xi)`` composed by the caller
        (as separate factors, see :meth:`poses`).
        """
        return self.tree.link_poses(q, dq, dT=dT)

    def gravity_moment(self, poses: Mapping[str, np.ndarray], joint: str, after_motion: bool) -> tuple[np.ndarray, np.ndarray]:
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

    def poses(self, q: Mapping[str, np.ndarray], xi: Mapping[str, np.ndarray], dq_noise: Mapping[str, np.ndarray],
              motion_sign: Mapping[str, np.ndarray], elapsed: np.ndarray, n: int) -> dict[str, np.ndarray]:
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
        dq: dict[str, np.ndarray] = {k: np.asarray(v, float).copy() for k, v in dq_noise.items()}
        fx: dict[str, np.ndarray] = {}  # effect twists per joint (n, 6)

        def add_dq(j: str, v: Any) -> None:
            dq[j] = dq.get(j, np.zeros(n)) + v

        def add_fx(j: str, v: np.ndarray) -> None:
            fx[j] = fx.get(j, np.zeros((n, 6))) + v

        for e in self.effects:
            nm, loc, p = e["name"], e["location"], e["parameters"]
            if nm == "joint_offset":
                add_dq(loc, p["offset"])
            elif nm == "transmission_error":
                add_dq(loc, p["amplitude"] * np.sin(p["periods"] * np.asarray(q[loc], float)))
            elif nm == "backlash":
                add_dq(loc, p["play"] * np.asarray(motion_sign.get(loc, np.zeros(n)), float))
            elif nm in ("link_error", "camera_extrinsics"):
                add_fx(loc, np.broadcast_to([p[k] for k in TRUTH_EFFECTS[nm]], (n, 6)))
            elif nm == "thermal_growth":
                o = self.robot.joints[loc].origin
                d = o[:3, :3].T @ o[:3, 3]
                v = np.zeros((n, 6))
                v[:, :3] = p["alpha"] * np.asarray(elapsed)[:, None] * d
                add_fx(loc, v)
            elif nm == "base_tilt":
                # everything hanging on the root rotates about the root's x and y axes:
                # Exp(w) Exp(p_j) = Exp(p_j) Exp(Ad(Exp(p_j)^-1) w) for each child joint j of the root
                w = np.array([0, 0, 0, p["tilt_x"], p["tilt_y"], 0.0])
                for jn in self.robot.children(self.robot.root):
                    Ad = lie.adjoint(lie.inverse(self.robot.joints[jn].origin))
                    add_fx(jn, np.broadcast_to(Ad @ w, (n, 6)))

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
        grav = [e for e in self.effects if e["name"] in ("gravity_compliance", "mount_bending")]
        if grav:
            base = build(dq, fx)
            for e in grav:
                loc, p = e["location"], e["parameters"]
                if e["name"] == "gravity_compliance":
                    j = self.robot.joints[loc]
                    F, M = self.gravity_moment(base, loc, after_motion=True)
                    tau = (F if j.type == "prismatic" else M) @ j.axis
                    add_dq(loc, p["compliance"] * tau)
                else:
                    _, M = self.gravity_moment(base, loc, after_motion=False)
                    v = np.zeros((n, 6))
                    v[:, 3] = p["compliance_x"] * M[:, 0]
                    v[:, 4] = p["compliance_y"] * M[:, 1]
                    add_fx(loc, v)
        return build(dq, fx)


# =============================================================================
# trajectory
# =============================================================================


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s * s)


@dataclass
class _Stop:
    q: dict[str, float]
    dwell: float
    contact: dict | None = None
    measure: bool = True
    draw: int = 0


@dataclass
class SimulationResult:
    """What :func:`simulate` wrote and the truth behind it."""

    bag: str
    counts: dict[str, int]
    truth: dict[str, Any]
    duration: float
    n_stops: int
    visible_tags: list[int] = field(default_factory=list)


class _Sim:
    """One simulation run (internal)."""

    def __init__(self, sc: Scenario, seed: int) -> None:
        self.sc = sc
        self.path = sc.path
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        raw = sc.raw
        self.robot = sc.robot
        self.model = sc.model
        truth = _check_keys(raw.get("truth"), ("perturbations", "perturbation_scale", "joint_noise", "effects",
                                               "record_draws"),
                            self.path, "truth")
        self.draw = truth.get("perturbations", "once")
        if self.draw not in ("once", "per_stop", "none"):
            raise ScenarioError(f"{_where(self.path, 'truth.perturbations')} must be once, per_stop or none")
        self.pscale = _num(truth, "perturbation_scale", 1.0, self.path, "truth", minimum=0.0)
        self.use_joint_noise = bool(truth.get("joint_noise", True))
        self.record_draws = bool(truth.get("record_draws", False))
        self.true = TrueRobot(self.robot, truth.get("effects") or [], where=f"scenario {self.path}: truth.effects")
        self.dt_js = self.true.effect_param("time_offset", "dt")
        self.joints = self.robot.independent_joints
        self._parse_trajectory(_check_keys(raw.get("trajectory"), (
            "joint_rate", "dwell", "settle", "move_time", "extra_joints", "start", "stops", "random_stops",
            "smooth"), self.path, "trajectory"))
        self._parse_sensors()

    # -- parsing -------------------------------------------------------------
    def _parse_trajectory(self, tr: dict) -> None:
        P = self.path
        self.rate = _num(tr, "joint_rate", 100.0, P, "trajectory", minimum=50.0, maximum=2000.0)
        self.dwell = _num(tr, "dwell", 0.5, P, "trajectory", minimum=0.0)
        self.settle = _num(tr, "settle", 0.1, P, "trajectory", minimum=0.0)
        self.move_time = _num(tr, "move_time", 1.0, P, "trajectory", minimum=0.01)
        extra = tr.get("extra_joints") or {}
        if not isinstance(extra, Mapping):
            raise ScenarioError(f"{_where(P, 'trajectory.extra_joints')} must map joint names to values")
        self.extra = {str(k): _num(extra, k, 0.0, P, "trajectory.extra_joints") for k in extra}
        clash = sorted(set(self.extra) & set(self.robot.independent_joints))
        if clash:
            raise ScenarioError(f"{_where(P, 'trajectory.extra_joints')}: {clash} are driven joints of the URDF")
        self.start = {j: 0.0 for j in self.joints}
        self.start.update(_joints_map(tr.get("start"), P, "trajectory.start", self.robot))
        self.smooth: Any = None
        self.stops: list[_Stop] = []
        if tr.get("smooth") is not None:
            sm = _check_keys(tr["smooth"], ("duration", "centre", "amplitude", "period", "phase"), P, "trajectory.smooth")
            self.smooth = {
                "duration": _num(sm, "duration", 60.0, P, "trajectory.smooth", minimum=0.1),
                "centre": {**self.start, **_joints_map(sm.get("centre"), P, "trajectory.smooth.centre", self.robot)},
                "amplitude": _joints_map(sm.get("amplitude"), P, "trajectory.smooth.amplitude", self.robot),
                "period": _joints_map(sm.get("period"), P, "trajectory.smooth.period", self.robot),
                "phase": _joints_map(sm.get("phase"), P, "trajectory.smooth.phase", self.robot),
            }
            if tr.get("stops") or tr.get("random_stops"):
                raise ScenarioError(f"{_where(P, 'trajectory')}: give either smooth or stops/random_stops")
            return
        for i, s in enumerate(tr.get("stops") or []):
            s = _check_keys(s, ("joints", "dwell", "contact"), P, f"trajectory.stops[{i}]")
            q = dict(self.start)
            q.update(_joints_map(s.get("joints"), P, f"trajectory.stops[{i}].joints", self.robot))
            c = None
            if s.get("contact") is not None:
                c = _check_keys(s["contact"], ("press_joint", "force", "approach"), P, f"trajectory.stops[{i}].contact")
                pj = c.get("press_joint")
                if pj not in self.joints:
                    raise ScenarioError(f"{_where(P, f'trajectory.stops[{i}].contact.press_joint')}: "
                                        f"{pj!r} is not an independent joint")
                c = {"press_joint": pj, "force": _num(c, "force", 10.0, P, f"trajectory.stops[{i}].contact", minimum=0.0),
                     "approach": _num(c, "approach", 0.15, P, f"trajectory.stops[{i}].contact")}
            self.stops.append(_Stop(q, _num(s, "dwell", self.dwell, P, f"trajectory.stops[{i}]", minimum=0.0), c))
        self.random_cfg: Any = None
        if tr.get("random_stops") is not None:
            rs = _check_keys(tr["random_stops"], ("count", "around", "spread", "min_visible_tags", "max_tries",
                                                  "min_link_z"), P, "trajectory.random_stops")
            min_z = rs.get("min_link_z") or {}
            if not isinstance(min_z, Mapping) or any(k not in self.robot.links for k in min_z):
                raise ScenarioError(f"{_where(P, 'trajectory.random_stops.min_link_z')} must map links of "
                                    f"{self.robot.source} to heights [m]")
            min_z = {str(k): _num(min_z, k, 0.0, P, "trajectory.random_stops.min_link_z") for k in min_z}
            spread = rs.get("spread", 0.2)
            around = {**self.start, **_joints_map(rs.get("around"), P, "trajectory.random_stops.around", self.robot)}
            if isinstance(spread, Mapping):
                spread = _joints_map(spread, P, "trajectory.random_stops.spread", self.robot)
            else:
                spread = {j: float(spread) for j in (rs.get("around") or {})}
            self.random_cfg = {"count": int(_num(rs, "count", 20, P, "trajectory.random_stops", minimum=1)),
                               "around": around, "spread": spread,
                               "min_visible": int(_num(rs, "min_visible_tags", 0, P, "trajectory.random_stops", minimum=0)),
                               "min_z": min_z,
                               "max_tries": int(_num(rs, "max_tries", 5000, P, "trajectory.random_stops", minimum=1))}
        if not self.stops and self.random_cfg is None:
            raise ScenarioError(f"{_where(P, 'trajectory')}: needs stops, random_stops or smooth")

    def _parse_sensors(self) -> None:
        P, raw, m = self.path, self.sc.raw, self.model
        self.cam: Any = None  # camera dict (frame, w, h, K, D, rate, ...) or None
        if raw.get("camera") is not None:
            c = _check_keys(raw["camera"], ("frame", "width", "height", "intrinsics", "D", "rate", "during", "format",
                                            "noise_sigma", "blur_sigma", "background", "time_offset"), P, "camera")
            if m.tags is None:
                raise ScenarioError(f"{_where(P, 'camera')}: the model {m.source} has no tags section to render")
            frame = c.get("frame") or (m.camera.frame if m.camera else None)
            if frame not in self.robot.links:
                raise ScenarioError(f"{_where(P, 'camera.frame')}: {frame!r} is not a link of {self.robot.source}")
            w = int(_num(c, "width", 640, P, "camera", minimum=16))
            h = int(_num(c, "height", 480, P, "camera", minimum=16))
            intr = c.get("intrinsics", [600.0, 600.0, w / 2.0, h / 2.0])
            D = np.asarray(c.get("D", [0.0] * 5), dtype=float).reshape(-1)
            if len(intr) != 4 or D.shape[0] != 5:
                raise ScenarioError(f"{_where(P, 'camera')}: intrinsics = [fx, fy, cx, cy], D = 5 plumb_bob numbers")
            fx, fy, cx, cy = (float(v) for v in intr)
            fmt = c.get("format", "png")
            if fmt not in ("png", "jpeg", "raw"):
                raise ScenarioError(f"{_where(P, 'camera.format')} must be png, jpeg or raw")
            during = c.get("during", "stops")
            if during not in ("stops", "always"):
                raise ScenarioError(f"{_where(P, 'camera.during')} must be stops or always")
            self.cam = {"frame": frame, "w": w, "h": h, "K": np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                        "D": D, "rate": _num(c, "rate", 5.0, P, "camera", minimum=0.01, maximum=30.0),
                        "during": during, "format": fmt,
                        "noise": _num(c, "noise_sigma", 1.0, P, "camera", minimum=0.0),
                        "blur": _num(c, "blur_sigma", 0.0, P, "camera", minimum=0.0),
                        "background": int(_num(c, "background", 128, P, "camera", minimum=0, maximum=255)),
                        "time_offset": _num(c, "time_offset", 0.0, P, "camera")}
        gt = _check_keys(raw.get("ground_truth"), ("pose", "point"), P, "ground_truth")
        self.gt_pose: Any = None
        if gt.get("pose") is not None:
            g = _check_keys(gt["pose"], ("frame", "target", "sigma_xyz", "sigma_rot", "rate"), P, "ground_truth.pose")
            frame = g.get("frame") or (m.frames.base if m.frames else self.robot.root)
            target = g.get("target") or (m.frames.tool if m.frames else None)
            for k, v in (("frame", frame), ("target", target)):
                if v not in self.robot.links:
                    raise ScenarioError(f"{_where(P, 'ground_truth.pose.' + k)}: {v!r} is not a link")
            self.gt_pose = {"frame": frame, "target": target,
                            "sx": _num(g, "sigma_xyz", 1e-4, P, "ground_truth.pose", minimum=0.0),
                            "sr": _num(g, "sigma_rot", 2e-4, P, "ground_truth.pose", minimum=0.0),
                            "rate": _num(g, "rate", 0.0, P, "ground_truth.pose", minimum=0.0)}
        self.gt_point: Any = None
        if gt.get("point") is not None:
            g = _check_keys(gt["point"], ("link", "xyz", "sigma", "frame", "T_tracker_base", "rate"), P,
                            "ground_truth.point")
            tr = m.tracker
            link = g.get("link") or (tr.link if tr else None)
            if link not in self.robot.links:
                raise ScenarioError(f"{_where(P, 'ground_truth.point.link')}: {link!r} is not a link")
            xyz = np.asarray(g.get("xyz", tr.xyz if tr else [0, 0, 0]), dtype=float).reshape(3)
            self.gt_point = {"link": link, "xyz": xyz,
                             "sigma": _num(g, "sigma", tr.sigma if tr else 2e-4, P, "ground_truth.point", minimum=0.0),
                             "frame": str(g.get("frame", "tracker")),
                             "T_tracker_base": _pose_cfg(g.get("T_tracker_base"), P, "ground_truth.point.T_tracker_base"),
                             "T_cfg": g.get("T_tracker_base") or {},
                             "rate": _num(g, "rate", 0.0, P, "ground_truth.point", minimum=0.0)}
        self.imu: Any = None
        if raw.get("imus") is not None:
            g = _check_keys(raw["imus"], ("rate", "sigma"), P, "imus")
            if not m.imus:
                raise ScenarioError(f"{_where(P, 'imus')}: the model {m.source} declares no imus")
            self.imu = {"rate": _num(g, "rate", 0.0, P, "imus", minimum=0.0),
                        "sigma": _num(g, "sigma", None, P, "imus", minimum=0.0)}
        self.contact: Any = None
        if raw.get("contact") is not None:
            c = _check_keys(raw["contact"], ("plane", "tool_point", "stiffness", "force_sigma", "frame", "rate"), P,
                            "contact")
            mc = m.contact
            if c.get("plane") is not None:
                pl = _check_keys(c["plane"], ("frame", "xyz", "rpy"), P, "contact.plane")
                frame = pl.get("frame", self.robot.root)
                T_fp = _pose_cfg(pl, P, "contact.plane")
            elif mc is not None:
                frame, T_fp = mc.plane_frame, mc.T_frame_plane
            else:
                raise ScenarioError(f"{_where(P, 'contact.plane')} is required (the model has no contact section)")
            tp = c.get("tool_point") or ({"link": mc.tool_link, "xyz": list(mc.tool_xyz)} if mc else None)
            if tp is not None:
                tp = _check_keys(tp, ("link", "xyz"), P, "contact.tool_point")
            if tp is None or tp.get("link") not in self.robot.links:
                raise ScenarioError(f"{_where(P, 'contact.tool_point')}: needs a link of the URDF")
            if frame not in self.robot.links:
                raise ScenarioError(f"{_where(P, 'contact.plane.frame')}: {frame!r} is not a link")
            self.contact = {"frame": frame, "T_frame_plane": T_fp, "link": tp["link"],
                            "xyz": np.asarray(tp.get("xyz", [0, 0, 0]), float).reshape(3),
                            "k": _num(c, "stiffness", 1e5, P, "contact", minimum=1.0),
                            "sigma": _num(c, "force_sigma", 0.1, P, "contact", minimum=0.0),
                            "wframe": str(c.get("frame", tp["link"])),
                            "rate": _num(c, "rate", self.rate, P, "contact", minimum=1.0)}
            if self.contact["wframe"] not in self.robot.links:
                raise ScenarioError(f"{_where(P, 'contact.frame')}: not a link")

    # -- random draws ----------------------------------------------------------
    def _draw_xi(self, n_sets: int) -> list[dict[str, np.ndarray]]:
        out = []
        for _ in range(n_sets):
            d = {}
            for jn, pert in self.model.perturbations.items():
                F = pert.factor
                d[jn] = self.pscale * (F @ self.rng.standard_normal(F.shape[1])) if self.draw != "none" else np.zeros(6)
            out.append(d)
        return out

    def _draw_noise(self, n_sets: int) -> list[dict[str, float]]:
        out = []
        for _ in range(n_sets):
            d = {}
            if self.use_joint_noise:
                for jn, s in self.model.joint_noise.items():
                    d[jn] = float(s * self.rng.standard_normal())
            out.append(d)
        return out

    # -- truth evaluation over a batch of samples --------------------------------
    def truth_poses(self, Q: np.ndarray, set_idx: np.ndarray, signs: np.ndarray, t: np.ndarray) -> dict[str, np.ndarray]:
        """True link poses for commanded joints Q (n, nj), draw-set index (n,), motion signs (n, nj), stamps."""
        n = Q.shape[0]
        q = {j: Q[:, i] for i, j in enumerate(self.joints)}
        xi = {jn: np.stack([self.xi_sets[k][jn] for k in set_idx]) for jn in self.model.perturbations} if n else {}
        noise = {jn: np.array([self.noise_sets[k].get(jn, 0.0) for k in set_idx]) for jn in self.model.joint_noise}
        sg = {j: signs[:, i] for i, j in enumerate(self.joints)}
        return self.true.poses(q, xi, noise, sg, t - self.sc.start_time, n)

    # -- visibility ----------------------------------------------------------
    def _tag_poses_cam(self, poses: Mapping[str, np.ndarray]) -> tuple[np.ndarray, list[int], np.ndarray]:
        T_root_cam = poses[self.cam["frame"]]
        T_cam_root = lie.inverse(T_root_cam)
        assert self.model.tags is not None  # a camera is simulated only with tags declared
        items = self.model.tags.items
        Ts = np.stack([T_cam_root @ poses[it.link] @ it.T_link_tag for it in items], axis=1)  # (n, k, 4, 4)
        return Ts, [it.id for it in items], np.array([it.size for it in items])

    def _visible(self, T_cam_tags: np.ndarray, sizes: np.ndarray) -> np.ndarray:
        """(n, k) bool: tag in front, facing the camera (< 70 deg) and all corners inside the image (margin 5 px)."""
        n, k = T_cam_tags.shape[:2]
        vis = np.zeros((n, k), bool)
        for a in range(n):
            for b in range(k):
                T = T_cam_tags[a, b]
                t = T[:3, 3]
                if t[2] < 0.1:
                    continue
                if -(T[:3, 2] @ t) / np.linalg.norm(t) < math.cos(math.radians(70)):
                    continue
                P = tag_points_local(sizes[b] * 1.25) @ T[:3, :3].T + t
                if np.any(P[:, 2] < 0.05):
                    continue
                uv = project_points(P, self.cam["K"], self.cam["D"])
                if np.all((uv[:, 0] > 5) & (uv[:, 0] < self.cam["w"] - 5) & (uv[:, 1] > 5) & (uv[:, 1] < self.cam["h"] - 5)):
                    vis[a, b] = True
        return vis

    # -- plan -----------------------------------------------------------------
    def plan(self) -> None:
        """Build the stop list (random stops, contact solving) and draw perturbation sets."""
        if self.smooth is None and self.random_cfg is not None:
            self._add_random_stops()
        n_stops = max(len(self.stops), 1)
        for k, s in enumerate(self.stops):
            s.draw = k
        n_sets = n_stops if self.draw == "per_stop" else 1
        self.xi_sets = self._draw_xi(n_sets)
        if n_sets == 1:
            self.xi_sets = self.xi_sets * n_stops
        # joint noise is drawn per stop in any case
        self.noise_sets = self._draw_noise(n_stops)
        if self.smooth is None:
            self._solve_contacts()

    def _add_random_stops(self) -> None:
        cfg = self.random_cfg
        need = cfg["count"]
        tries = 0
        names = list(cfg["spread"])
        lo_hi = {}
        for j in names:
            lim = self.robot.joints[j].limit
            lo_hi[j] = ((lim.lower if lim and lim.lower is not None else -np.inf),
                        (lim.upper if lim and lim.upper is not None else np.inf))
        got = 0
        while got < need:
            tries += 1
            if tries > cfg["max_tries"]:
                raise ScenarioError(f"{_where(self.path, 'trajectory.random_stops')}: only {got} of {need} "
                                    f"acceptable configurations (min_visible_tags, min_link_z) in {cfg['max_tries']} tries")
            q = dict(cfg["around"])
            for j in names:
                q[j] = float(np.clip(q[j] + self.rng.uniform(-cfg["spread"][j], cfg["spread"][j]), *lo_hi[j]))
            if cfg["min_z"]:
                Q = np.array([[q[j] for j in self.joints]])
                poses = self.true.poses({j: Q[:, i] for i, j in enumerate(self.joints)}, {}, {}, {}, np.zeros(1), 1)
                if any(poses[ln][0, 2, 3] < z for ln, z in cfg["min_z"].items()):
                    continue
            if cfg["min_visible"] > 0:
                if self.cam is None:
                    raise ScenarioError(f"{_where(self.path, 'trajectory.random_stops.min_visible_tags')} needs a camera")
                Q = np.array([[q[j] for j in self.joints]])
                poses = self.true.poses({j: Q[:, i] for i, j in enumerate(self.joints)}, {}, {}, {}, np.zeros(1), 1)
                Ts, _, sizes = self._tag_poses_cam(poses)
                if self._visible(Ts, sizes)[0].sum() < cfg["min_visible"]:
                    continue
            self.stops.append(_Stop(q, self.dwell))
            got += 1

    def _contact_penetration(self, poses: Mapping[str, np.ndarray]) -> np.ndarray:
        """Depth [m] of the true tool point below the true plane (positive = pressing), (n,)."""
        c = self.contact
        T_root_plane = poses[c["frame"]] @ c["T_frame_plane"]
        p = (poses[c["link"]] @ np.append(c["xyz"], 1.0))[:, :3]
        d = np.einsum("nij,nj->ni", np.swapaxes(T_root_plane[:, :3, :3], 1, 2), p - T_root_plane[:, :3, 3])
        return -d[:, 2]

    def _solve_contacts(self) -> None:
        new: list[_Stop] = []
        for k, s in enumerate(self.stops):
            if s.contact is None:
                new.append(s)
                continue
            if self.contact is None:
                raise ScenarioError(f"{_where(self.path, f'trajectory.stops[{k}].contact')} needs the contact section")
            pj = s.contact["press_joint"]
            target = s.contact["force"] / self.contact["k"]

            def depth(v: float) -> float:
                q = dict(s.q)
                q[pj] = v
                Q = np.array([[q[j] for j in self.joints]])
                P = self.truth_poses(Q, np.array([s.draw]), np.zeros_like(Q), np.array([self.sc.start_time]))
                return float(self._contact_penetration(P)[0])

            v = s.q[pj]
            for _ in range(30):  # secant / Newton with numeric slope
                f = depth(v) - target
                if abs(f) < 1e-10:
                    break
                h = 1e-4
                slope = (depth(v + h) - depth(v - h)) / (2 * h)
                if abs(slope) < 1e-9:
                    raise ScenarioError(f"{_where(self.path, f'trajectory.stops[{k}].contact')}: joint {pj} does not "
                                        "move the tool point towards the plane")
                v = v - f / slope
            else:
                raise ScenarioError(f"{_where(self.path, f'trajectory.stops[{k}].contact')}: could not reach the plane")
            slope = (depth(v + 1e-4) - depth(v - 1e-4)) / 2e-4
            away = -math.copysign(abs(s.contact["approach"]), slope)
            qa = dict(s.q)
            qa[pj] = v + away
            qc = dict(s.q)
            qc[pj] = v
            new.append(_Stop(qa, 0.2, None, measure=False, draw=s.draw))
            new.append(_Stop(qc, s.dwell, s.contact, draw=s.draw))
            new.append(_Stop(dict(qa), 0.2, None, measure=False, draw=s.draw))
        self.stops = new

    # -- time line ------------------------------------------------------------
    def timeline(self) -> None:
        """Commanded joints at the joint-state rate, stop windows, motion signs."""
        t0, dt = self.sc.start_time, 1.0 / self.rate
        nj = len(self.joints)
        if self.smooth is not None:
            t = t0 + np.arange(int(round(self.smooth["duration"] * self.rate)) + 1) * dt
            Q = self._smooth_q(t)
            self.t, self.Q = t, Q
            self.set_idx = np.zeros(t.shape[0], int)
            self.windows: list[tuple[float, float, int]] = []
        else:
            ts, qs, sets = [], [], []
            windows = []
            qprev = np.array([self.stops[0].q[j] for j in self.joints])
            now = t0
            for k, s in enumerate(self.stops):
                qk = np.array([s.q[j] for j in self.joints])
                if k > 0:
                    nmove = int(round(self.move_time * self.rate))
                    for i in range(nmove):
                        ts.append(now + i * dt)
                        qs.append(qprev + (qk - qprev) * _min_jerk(np.array(i / nmove)))
                        sets.append(s.draw)
                    now += nmove * dt
                ndw = max(int(round(s.dwell * self.rate)), 1)
                start = now
                for i in range(ndw):
                    ts.append(now + i * dt)
                    qs.append(qk)
                    sets.append(s.draw)
                now += ndw * dt
                if s.measure:
                    windows.append((start, now - dt, k))
                qprev = qk
            self.t, self.Q, self.set_idx = np.array(ts), np.array(qs), np.array(sets)
            self.windows = windows
        # sign of the last motion per joint (backlash)
        dQ = np.diff(self.Q, axis=0, prepend=self.Q[:1])
        sg = np.sign(np.where(np.abs(dQ) > 1e-12, dQ, 0.0))
        last = np.zeros(nj)
        signs = np.zeros_like(self.Q)
        for i in range(self.Q.shape[0]):
            nz = sg[i] != 0
            last = np.where(nz, sg[i], last)
            signs[i] = last
        self.signs = signs

    def _smooth_q(self, ts: np.ndarray) -> np.ndarray:
        """Commanded joints of the smooth motion at stamps ``ts`` (analytic), (n, nj)."""
        sm, t0 = self.smooth, self.sc.start_time
        Q = np.zeros((ts.shape[0], len(self.joints)))
        for i, j in enumerate(self.joints):
            a = sm["amplitude"].get(j, 0.0)
            per = sm["period"].get(j, 10.0)
            Q[:, i] = sm["centre"][j] + a * np.sin(2 * np.pi * (ts - t0) / per + sm["phase"].get(j, 0.0))
        return Q

    def sensor_times(self, rate: float, during: str = "stops") -> np.ndarray:
        """Sample stamps: inside each stop window after ``settle`` (rate 0 = once per stop), or the whole bag."""
        if self.smooth is not None or during == "always":
            if rate <= 0:
                raise ScenarioError(f"{_where(self.path, 'sensor rate')}: rate 0 (once per stop) needs stops")
            return np.arange(self.t[0], self.t[-1] + 1e-9, 1.0 / rate)
        out = []
        for a, b, _ in self.windows:
            s = a + self.settle
            if s > b:
                s = 0.5 * (a + b)
            if rate <= 0:
                out.append(s)
            else:
                out.extend(np.arange(s, b + 1e-9, 1.0 / rate).tolist())
        return np.array(out)

    def state_at(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Commanded joints (linear interpolation), draw set and motion signs at stamps ``ts``."""
        idx = np.clip(np.searchsorted(self.t, ts, side="right") - 1, 0, self.t.shape[0] - 1)
        nxt = np.minimum(idx + 1, self.t.shape[0] - 1)
        span = np.where(nxt > idx, self.t[nxt] - self.t[idx], 1.0)
        w = np.clip((ts - self.t[idx]) / span, 0.0, 1.0)[:, None]
        Q = self.Q[idx] * (1 - w) + self.Q[nxt] * w
        if self.smooth is not None:
            Q = self._smooth_q(ts)
        return Q, self.set_idx[idx], self.signs[idx]

    # -- run ------------------------------------------------------------------
    def run(self, out: str | os.PathLike, storage: str = "mcap", overwrite: bool = False) -> SimulationResult:
        self.plan()
        self.timeline()
        events: list[tuple[float, int, str, tuple]] = []  # (stamp, order, kind, payload)
        # joint states (time offset: a message stamped t carries the position at t - dt)
        names = list(self.joints) + list(self.extra)
        Qjs, _, _ = self.state_at(self.t - self.dt_js)
        extra_vals = [float(v) for v in self.extra.values()]
        for i, t in enumerate(self.t):
            events.append((float(t), 0, "js", (names, np.concatenate([Qjs[i], extra_vals]))))
        visible_ids: set[int] = set()
        if self.cam is not None:
            ts = self.sensor_times(self.cam["rate"], self.cam["during"])
            Q, S, G = self.state_at(ts)
            poses = self.truth_poses(Q, S, G, ts)
            Ts, ids, sizes = self._tag_poses_cam(poses)
            assert self.model.tags is not None
            for i, t in enumerate(ts):
                img, drawn = render_tags((self.cam["w"], self.cam["h"]), self.cam["K"], self.cam["D"], Ts[i], ids, sizes,
                                         dictionary=self.model.tags.family, background=self.cam["background"],
                                         noise_sigma=self.cam["noise"], rng=self.rng, blur_sigma=self.cam["blur"])
                visible_ids.update(drawn)
                st = float(t + self.cam["time_offset"])
                events.append((st, 1, "cam", (img,)))
        if self.gt_pose is not None:
            g = self.gt_pose
            ts = self.sensor_times(g["rate"])
            Q, S, G = self.state_at(ts)
            poses = self.truth_poses(Q, S, G, ts)
            T = lie.inverse(poses[g["frame"]]) @ poses[g["target"]]
            noise = np.concatenate([g["sx"] * self.rng.standard_normal((len(ts), 3)),
                                    g["sr"] * self.rng.standard_normal((len(ts), 3))], axis=1)
            T = T @ lie.exp(noise)
            for i, t in enumerate(ts):
                events.append((float(t), 2, "gtpose", (T[i],)))
        if self.gt_point is not None:
            g = self.gt_point
            ts = self.sensor_times(g["rate"])
            Q, S, G = self.state_at(ts)
            poses = self.truth_poses(Q, S, G, ts)
            p = (g["T_tracker_base"] @ poses[g["link"]] @ np.append(g["xyz"], 1.0))[:, :3]
            p = p + g["sigma"] * self.rng.standard_normal(p.shape)
            for i, t in enumerate(ts):
                events.append((float(t), 3, "gtpoint", (p[i],)))
        if self.imu is not None:
            ts = self.sensor_times(self.imu["rate"])
            Q, S, G = self.state_at(ts)
            poses = self.truth_poses(Q, S, G, ts)
            for name, cfg in self.model.imus.items():
                sig = self.imu["sigma"] if self.imu["sigma"] is not None else cfg.sigma
                R = poses[cfg.link][:, :3, :3]
                a = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, GRAVITY]))  # specific force at rest
                a = a + sig * self.rng.standard_normal(a.shape)
                for i, t in enumerate(ts):
                    events.append((float(t), 4, "imu", (name, cfg.link, a[i], sig)))
        if self.contact is not None:
            c = self.contact
            ts = np.arange(self.t[0], self.t[-1] + 1e-9, 1.0 / c["rate"])
            Q, S, G = self.state_at(ts)
            poses = self.truth_poses(Q, S, G, ts)
            depth = np.maximum(self._contact_penetration(poses), 0.0)
            T_root_plane = poses[c["frame"]] @ c["T_frame_plane"]
            f_root = c["k"] * depth[:, None] * T_root_plane[:, :3, 2]  # table pushes along its normal
            R_w = poses[c["wframe"]][:, :3, :3]
            f = np.einsum("nji,nj->ni", R_w, f_root) + c["sigma"] * self.rng.standard_normal((len(ts), 3))
            # torque of the contact force about the wrench frame origin
            p_c = (poses[c["link"]] @ np.append(c["xyz"], 1.0))[:, :3] - poses[c["wframe"]][:, :3, 3]
            tq = np.einsum("nji,nj->ni", R_w, np.cross(p_c, f_root)) + 0.01 * c["sigma"] * self.rng.standard_normal((len(ts), 3))
            for i, t in enumerate(ts):
                events.append((float(t), 5, "wrench", (f[i], tq[i])))
        events.sort(key=lambda e: (e[0], e[1]))
        counts = self._write(out, storage, overwrite, events)
        return SimulationResult(str(out), counts, self.truth_dict(), float(self.t[-1] - self.t[0]),
                                len(self.windows), sorted(visible_ids))

    def _write(self, out: str | os.PathLike, storage: str, overwrite: bool, events: list) -> dict[str, int]:
        cam_frame = self.cam["frame"] if self.cam else ""
        with BagWriter(out, storage=storage, overwrite=overwrite) as bag:
            bag.write_robot_description(self.sc.urdf_text, self.sc.start_time - 0.01)
            for t, _, kind, pl in events:
                if kind == "js":
                    bag.write_joint_state(t, pl[0], pl[1])
                elif kind == "cam":
                    bag.write_camera_info(t, cam_frame, self.cam["w"], self.cam["h"], self.cam["K"], self.cam["D"])
                    if self.cam["format"] == "raw":
                        bag.write_image(t, cam_frame, pl[0])
                    else:
                        bag.write_compressed_image(t, cam_frame, pl[0], self.cam["format"])
                elif kind == "gtpose":
                    bag.write_ground_truth_pose(t, self.gt_pose["frame"], pl[0])
                elif kind == "gtpoint":
                    bag.write_ground_truth_point(t, self.gt_point["frame"], pl[0])
                elif kind == "imu":
                    bag.write_imu(pl[0], t, pl[1], pl[2], accel_sigma=pl[3])
                elif kind == "wrench":
                    bag.write_wrench(t, self.contact["wframe"], pl[0], pl[1])
            return dict(bag.counts)

    def truth_dict(self) -> dict[str, Any]:
        """The truth of the bag (what the tools are never told), plain types for YAML."""
        d: dict[str, Any] = {
            "seed": self.seed,
            "start_time": self.sc.start_time,
            "perturbations": self.draw,
            "effects": [dict(e, parameters=dict(e["parameters"])) for e in self.true.effects],
        }
        for e in d["effects"]:
            if e["name"] == "thermal_growth":
                e["variable"] = "time"
                e["reference"] = self.sc.start_time
        if self.draw == "once" and self.xi_sets:
            d["xi"] = {k: [float(x) for x in v] for k, v in self.xi_sets[0].items()}
        if self.gt_point is not None:
            T = self.gt_point["T_tracker_base"]
            d["T_tracker_base"] = [[float(x) for x in row] for row in T]
            d["tracker_registration"] = {"frame": self.gt_point["frame"],
                                         "xyz": [float(x) for x in self.gt_point["T_cfg"].get("xyz", [0, 0, 0])],
                                         "rpy": [float(x) for x in self.gt_point["T_cfg"].get("rpy", [0, 0, 0])]}
        if self.cam is not None:
            d["camera"] = {"frame": self.cam["frame"], "K": self.cam["K"].tolist(), "D": self.cam["D"].tolist(),
                           "width": self.cam["w"], "height": self.cam["h"]}
        if self.contact is not None:
            d["contact_plane"] = {"frame": self.contact["frame"],
                                  "T_frame_plane": self.contact["T_frame_plane"].tolist(),
                                  "stiffness": self.contact["k"]}
        d["stops"] = len(self.windows)
        if self.record_draws:
            d["stop_draws"] = [{"start": float(a), "end": float(b),
                                "xi": {k: [float(x) for x in v] for k, v in self.xi_sets[self.stops[k_].draw].items()},
                                "joint_noise": {k: float(v) for k, v in self.noise_sets[self.stops[k_].draw].items()}}
                               for a, b, k_ in self.windows]
        return d


def simulate(scenario: str | os.PathLike | Scenario, out: str | os.PathLike, seed: int | None = None,
             storage: str = "mcap", overwrite: bool = False) -> SimulationResult:
    """Run a scenario and write the bag.

    Parameters
    ----------
    scenario
        Scenario YAML path (or a loaded :class:`Scenario`).
    out
        Bag directory to create.
    seed
        Overrides the scenario's ``seed``.
    storage
        ``mcap`` or ``sqlite3``.
    overwrite
        Replace an existing bag directory.

    Returns
    -------
    SimulationResult
        Message counts per topic and the truth (effects, drawn perturbations, registration).

    Raises
    ------
    ScenarioError
        Bad scenario; :class:`~ppoe_core.errors.BagError` if the bag cannot be written.
    """
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    try:
        sim = _Sim(sc, sc.seed if seed is None else int(seed))
        return sim.run(out, storage=storage, overwrite=overwrite)
    except PpoeError:
        raise
    except (KeyError, ValueError, TypeError, AttributeError) as exc:  # malformed values that slipped through
        raise ScenarioError(f"scenario {sc.path}: {type(exc).__name__}: {exc}") from exc
