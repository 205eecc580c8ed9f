"""Simulation scenario files: schema (:data:`SCENARIO_DOC`), checks with file and key in every error,
:class:`Scenario`."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ppoe_core.errors import ModelConfigError, ScenarioError, UnknownFrameError, UnknownJointError, UrdfError
from ppoe_core.robot.config import ModelConfig, load_model_config
from ppoe_core.robot.dh import dh_to_urdf
from ppoe_core.robot.urdf import Robot, parse_urdf
from ppoe_core.robot.yaml_io import read_yaml_file
from ppoe_core.sim.scenario_checks import check_keys, check_number, key_location
from ppoe_core.sim.schedule import TEMPERATURE_DOC

#: effects the simulator can put into the true robot, with their parameters
TRUTH_EFFECTS: dict[str, tuple[str, ...]] = {
    "joint_offset": ("offset",),
    "link_error": ("x", "y", "z", "rx", "ry", "rz"),
    "camera_extrinsics": ("x", "y", "z", "rx", "ry", "rz"),
    "gravity_compliance": ("compliance",),
    "mount_bending": ("compliance_x", "compliance_y"),
    "lateral_compliance": ("compliance_u", "compliance_v"),
    "base_tilt": ("tilt_x", "tilt_y"),
    "backlash": ("play",),
    "thermal_growth": ("alpha",),
    "time_offset": ("dt",),
    "camera_intrinsics": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
    "tag_offset": ("x", "y", "z", "rx", "ry", "rz"),
    # outside the docs/conventions.md sec. 6 vocabulary (for testing that diagnose reports it as unexplained):
    "transmission_error": ("amplitude", "periods"),
}

SCENARIO_DOC = """\
# ppoe simulate scenario (all keys; defaults in brackets). Paths are relative to the scenario file.
extends: _base.yaml        # optional: a base scenario merged under this file (this file's keys win; mappings
                           # merge key by key, lists are replaced; the base's paths are relative to the base) [none]
robot:
  urdf: ../config/robots/rover.urdf        # nominal URDF (written to /robot_description) [required, or dh]
  dh: ../config/robots/ind6_dh.yaml        # instead of urdf: a DH table (ppoe urdf from-dh), its URDF is written
  model: ../config/robots/rover_model.yaml # model YAML: perturbations, joint_noise, tags, camera, tracker, imus,
  contact [required]
seed: 0                    # RNG seed; `--seed` overrides [0]
start_time: 100.0          # stamp of the first message [s] [100.0]
truth:
  perturbations: once      # draw the model's perturbations xi: once | per_stop | none [once]
  perturbation_scale: 1.0  # multiplies the drawn xi [1.0]
  joint_noise: true        # add the model's joint_noise (per stop) to the true joint values [true]
  record_draws: false      # write each stop's window [s], drawn xi and joint errors to the truth file [false]
  encoder_noise: 0.0       # white noise on every recorded /joint_states sample (also at rest), not on the true
                           # robot: a number for every driven joint or {joint: sigma} [rad|m] [0]
  effects:                 # systematic effects of the true robot, docs/conventions.md sec. 6 names [none]
    - {name: joint_offset, location: JOINT, parameters: {offset: 0.01}}        # q_true = q_meas + offset [rad|m]
    - {name: link_error, location: JOINT, parameters: {x: 0.001, rz: 0.002}}   # dxi at JOINT [m, rad]
    - {name: camera_extrinsics, location: JOINT, parameters: {x: .., rz: ..}}   # dxi at the camera's fixed joint [m,
    rad]
    - {name: gravity_compliance, location: JOINT, parameters: {compliance: 1e-4}}  # dq = c * gravity torque [rad/(N m)]
    - {name: mount_bending, location: JOINT, parameters: {compliance_x: 1e-4, compliance_y: 1e-4}}  # theta = c *
    moment [rad/(N m)]
    - {name: base_tilt, location: ROOT_LINK, parameters: {tilt_x: 0.002, tilt_y: 0.0}}  # robot tilted about root x,
    y [rad]
    - {name: backlash, location: JOINT, parameters: {play: 0.002}}             # dq = play * sign(last motion) [rad|m]
    - {name: thermal_growth, location: JOINT, parameters: {alpha: 1e-6}}      # origin of JOINT grows by alpha*(t -
    start_time) [1/s]
    - {name: time_offset, location: /joint_states, parameters: {dt: 0.02}}     # joint states stamped t carry q(t -
    dt) [s]
    - {name: camera_intrinsics, location: CAMERA_FRAME, parameters: {fx: 5.0, cx: -3.0, k1: 0.02}}  # the TRUE
      # camera = the scenario camera's K, D (written to /camera/camera_info) + these [px, 1]; constant
    - {name: tag_offset, location: tag_3, parameters: {x: 0.002, rz: 0.01}}  # true pose of tag 3 on its link =
      # the model's mount @ Exp([x y z rx ry rz]) (local, tag axes) [m, rad]; constant
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
  stops_csv: poses.csv     # optional, appended after `stops`: one stop per row of a CSV whose header names joints
                           # (the `ppoe fk --batch` / `ppoe plan` poses.csv format; path relative to this file) [none]
  random_stops:            # optional, appended after `stops` and `stops_csv` [none]
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
  format: png              # png | jpeg (/camera/image_raw/compressed), raw (mono8 /camera/image_raw), or
                           # observations: no image, the tag pixels (centre + 4 corners) of the tags in view on
                           # /tag_bearing/observations as the tag bearing node would publish them [png]
  pixel_sigma: 0.3         # observations: Gaussian noise per corner pixel coordinate [px] [0.3]
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
    covariance_topic: /mocap/tool  # also as PoseWithCovarianceStamped here, an independent noise draw with its
                           # covariance: a 6D pose sensor to fuse while /ground_truth/pose scores [none]
  point:                   # /ground_truth/point, optional [none]
    link: tool0            # link carrying the reflector [model tracker.link]
    xyz: [0, 0, 0.02]      # reflector in that link [m] [model tracker.xyz]
    sigma: 0.0002          # noise 1-sigma per axis [m] [model tracker.sigma]
    frame: tracker         # header.frame_id (not in the URDF) [tracker]
    T_tracker_base: {xyz: [3, 1, 0.5], rpy: [0, 0, 2.5]}  # unknown registration [m, rad] [identity]
    rate: 0.0              # [Hz]; 0 = once per stop [0.0]
    during: stops          # stops: only inside stops; always: whole bag, also while moving (rate > 0) [stops]
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
""" + TEMPERATURE_DOC

_TOP_KEYS = ("extends", "robot", "seed", "start_time", "truth", "trajectory", "camera", "ground_truth", "imus",
             "contact", "temperature")


# =============================================================================
# scenario parsing
# =============================================================================


#: how deep ``extends`` may chain (a cycle is an error long before)
_MAX_EXTENDS = 8


def _merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``: mappings merged key by key (recursively), anything else replaced."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def read_scenario_raw(path: str | os.PathLike, depth: int = 0) -> dict[str, Any]:
    """A scenario file's mapping, with its ``extends: BASE.yaml`` (relative to the file) merged under it: the file's
    keys win, mappings merge key by key, lists and values are replaced; the base's robot paths are made absolute
    (they are relative to the base).  Every file ``extends`` reaches is listed in :func:`scenario_files`.

    Raises
    ------
    ScenarioError
        Unreadable file, YAML error, unknown key, ``extends`` deeper than 8 (a cycle); names the file and key.
    """
    p = Path(path)
    raw, _ = read_yaml_file(p, "scenario", ScenarioError)
    raw = check_keys(raw, _TOP_KEYS, str(p), "top level")
    rob = raw.get("robot")
    if isinstance(rob, Mapping):
        raw["robot"] = {k: str((p.parent / str(v)).resolve()) if k in ("urdf", "dh", "model") else v
                        for k, v in rob.items()}
    tr = raw.get("trajectory")
    if isinstance(tr, Mapping) and tr.get("stops_csv") is not None:  # relative to the file that names it
        raw["trajectory"] = {**tr, "stops_csv": str((p.parent / str(tr["stops_csv"])).resolve())}
    base = raw.pop("extends", None)
    if base is None:
        return raw
    if depth >= _MAX_EXTENDS:
        raise ScenarioError(f"{key_location(str(p), 'extends')}: more than {_MAX_EXTENDS} levels (a cycle?)")
    return _merged(read_scenario_raw(p.parent / str(base), depth + 1), raw)


def scenario_files(path: str | os.PathLike) -> list[Path]:
    """The scenario file, the files its ``extends`` chain reaches, and the robot files (URDF or DH table, model
    YAML) they name: what a bag made from it depends on besides the simulator's code."""
    p = Path(path).resolve()
    out = [p]
    for _ in range(_MAX_EXTENDS):
        raw, _ = read_yaml_file(out[-1], "scenario", ScenarioError)
        if not isinstance(raw, Mapping) or raw.get("extends") is None:
            break
        out.append((out[-1].parent / str(raw["extends"])).resolve())
    rob = read_scenario_raw(p).get("robot") or {}
    return out + [Path(str(rob[k])) for k in ("urdf", "dh", "model") if k in rob]


def _robot_text(p: Path, rob: Mapping[str, Any]) -> tuple[str, str]:
    """URDF text of the scenario's robot (``robot.urdf``, or ``robot.dh`` through ``ppoe urdf from-dh``) and its
    source for messages."""
    if "dh" in rob:
        dh_path = (p.parent / str(rob["dh"])).resolve()
        try:
            return dh_to_urdf(dh_path), f"{dh_path} (from-dh)"
        except ModelConfigError as exc:
            raise ScenarioError(f"{key_location(str(p), 'robot.dh')}: {exc}") from None
    urdf_path = (p.parent / str(rob["urdf"])).resolve()
    try:
        return urdf_path.read_text(), str(urdf_path)
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{key_location(str(p), 'robot.urdf')}: cannot read {urdf_path}: {exc}") from None


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
    raw = read_scenario_raw(p)
    rob = check_keys(raw.get("robot"), ("urdf", "dh", "model"), str(p), "robot")
    if ("urdf" in rob) == ("dh" in rob) or "model" not in rob:
        raise ScenarioError(f"{key_location(str(p), 'robot')} needs 'model' and one of 'urdf' or 'dh'")
    model_path = (p.parent / str(rob["model"])).resolve()
    urdf_text, urdf_source = _robot_text(p, rob)
    try:
        robot = parse_urdf(urdf_text, text_source=urdf_source)
        model = load_model_config(str(model_path), robot)
    except (UrdfError, ModelConfigError, UnknownJointError, UnknownFrameError) as exc:
        raise ScenarioError(f"scenario {p}: {exc}") from None
    seed = raw.get("seed", 0)
    if not isinstance(seed, int) or seed < 0:
        raise ScenarioError(f"{key_location(str(p), 'seed')} must be a non-negative integer, got {seed!r}")
    start = check_number(raw, "start_time", 100.0, str(p), "top", minimum=0.0)
    return Scenario(str(p), raw, robot, model, urdf_text, int(seed), float(start))
