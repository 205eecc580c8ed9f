"""A first model YAML for a robot nobody configured yet (``ppoe init``): guesses from its URDF and, optionally, a bag.

:func:`guess_model` reads the tree -- base = the root link, tool = the leaf at the end of the longest chain (most
movable joints, then most joints), the other leaves listed as alternatives -- and gives every joint on the
base-to-tool chain a default prior (:data:`PRIOR_MOVABLE`, :data:`PRIOR_FIXED`: the loose prior of
``config/robots/cobot6_model.yaml``).  With a bag (:class:`BagFacts`, read by :mod:`ppoe_core.io.bag_facts`) it
adds what the bag's topics show: ``trackers`` from ``/ground_truth/point[/<name>]`` (the carrying link found by
:func:`ppoe_core.io.bag_facts.reflector_links`), the ``camera`` from ``camera_info``'s ``frame_id`` (and a prior
on the joint that mounts it), ``imus`` from ``/imu/<name>`` frames and the ids of the tags seen.
:func:`model_yaml` writes the commented YAML; every guess the user must confirm carries ``# GUESS: confirm``.
"""

from __future__ import annotations

import re
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field

from ppoe_core.robot.robot_model import Robot

__all__ = [
    "GUESS",
    "PRIOR_FIXED",
    "PRIOR_MOVABLE",
    "PRIOR_CAMERA_MOUNT",
    "JOINT_NOISE",
    "TRACKER_SIGMA",
    "TOOL_NAME",
    "BagFacts",
    "ModelGuess",
    "camera_mount_joint",
    "guess_frames",
    "guess_model",
    "model_yaml",
    "summary_lines",
    "tie_key",
]

#: link names that say "tool": tool, tool0, tcp, flange, ee, ee_link, end_effector (as words of the name)
TOOL_NAME = re.compile(r"(^|_)(tool\d*|tcp|flange|ee|ee_link|end_effector)($|_)", re.IGNORECASE)
#: marker of every guessed value in the written YAML
GUESS = "# GUESS: confirm"
#: 1-sigma [m, m, m, rad, rad, rad] of a movable joint's perturbation: 0.5 mm and 4 mrad per axis, the loose prior of
#: config/robots/cobot6_model.yaml (a few times a typical uncalibrated arm's geometric error, so diagnose can move it)
PRIOR_MOVABLE = (0.0005, 0.0005, 0.0005, 0.004, 0.004, 0.004)
#: 1-sigma of a fixed joint on the chain (mount plate, flange, tool): 0.5 mm and 3 mrad per axis (cobot6's pedestal
#: plate takes 3 mrad; a tool's offset is known to about a millimetre)
PRIOR_FIXED = (0.0005, 0.0005, 0.0005, 0.003, 0.003, 0.003)
#: 1-sigma of the fixed joint mounting a camera: 8 mm and 6 mrad per axis (cobot6's camera stand)
PRIOR_CAMERA_MOUNT = (0.008, 0.008, 0.008, 0.006, 0.006, 0.006)
#: 1-sigma joint-value noise [rad or m]: 0.3 mrad, cobot6's declared encoder repeatability
JOINT_NOISE = 0.0003
#: 1-sigma per axis of one tracker point [m]: 0.5 mm, the loader's default (a total station at a few metres)
TRACKER_SIGMA = 0.0005


@dataclass
class BagFacts:
    """What :func:`guess_model` uses of a bag (filled by :func:`ppoe_core.io.bag_facts.bag_facts`).

    Attributes
    ----------
    path : str
    reflectors : dict[str, tuple[str | None, tuple[float, float, float], str]]
        Reflector topic -> (link that carries it or None, reflector position in that link [m], how it was found).
    camera_frame : str | None
        ``header.frame_id`` of ``/camera/camera_info`` (the one with the most messages).
    other_cameras : list[str]
        Further ``camera_info`` frame ids (the model YAML holds one camera).
    pose_frame : str | None
        ``header.frame_id`` of ``/ground_truth/pose`` (the frame its tool poses are given in).
    imus : dict[str, str]
        IMU name (``/imu/<name>``) -> ``header.frame_id``.
    tags : dict[int, tuple[str | None, tuple[float, float, float], float | None, str]]
        Tag id -> (link that carries it or None, centre in that link [m], edge size [m] or None, how found).
    tag_note : str
        How the tags were seen (observations or images), or why none was.
    """

    path: str
    reflectors: dict[str, tuple[str | None, tuple[float, float, float], str]] = field(default_factory=dict)
    camera_frame: str | None = None
    other_cameras: list[str] = field(default_factory=list)
    pose_frame: str | None = None
    imus: dict[str, str] = field(default_factory=dict)
    tags: dict[int, tuple[str | None, tuple[float, float, float], float | None, str]] = field(default_factory=dict)
    tag_note: str = ""


@dataclass
class ModelGuess:
    """The guessed model: frames, the chain's joints, and the sections found in a bag.

    Attributes
    ----------
    base, tool : str
        Guessed ``frames`` (URDF links).
    alternatives : list[str]
        Other leaves (possible tools), longest chain first.
    chain : list[str]
        Joints between ``base`` and ``tool`` (fixed included; :meth:`Robot.chain`: up from ``base``, then down).
    extra_joints : dict[str, str]
        Further joints given a prior (e.g. a camera mount or another reflector's chain) -> why.
    facts : BagFacts | None
    """

    base: str
    tool: str
    alternatives: list[str]
    chain: list[str]
    extra_joints: dict[str, str]
    facts: BagFacts | None


def _leaves(robot: Robot) -> list[str]:
    parents = {j.parent for j in robot.joints.values()}
    return [ln for ln in robot.links if ln not in parents]


def _chain_length(robot: Robot, link: str) -> tuple[int, int]:
    path = robot.path_from_root(link)
    return sum(robot.joints[j].movable for j in path), len(path)


def _common_link(robot: Robot, leaves: Sequence[str]) -> str:
    """The deepest link above all of ``leaves``."""
    paths = [[robot.joints[j].child for j in robot.path_from_root(ln)] for ln in leaves]
    common = robot.root
    for links in zip(*paths):
        if len(set(links)) > 1:
            break
        common = links[0]
    return common


def _tool_below(robot: Robot, leaves: Sequence[str]) -> str:
    """One tool for leaves that branch only through fixed or prismatic joints (tags, gripper fingers): their common
    link, or the deepest link named like a tool (:data:`TOOL_NAME`) on the fixed run above it."""
    common = _common_link(robot, leaves)
    for ln in leaves:
        path = robot.path_from_root(ln)
        below = path[len(robot.path_from_root(common)):]
        if any(robot.joints[j].type in ("revolute", "continuous") for j in below):
            return leaves[0]
    cur = common
    while True:
        if TOOL_NAME.search(cur):
            return cur
        j = robot.parent_joint(cur)
        if j is None or j.movable:
            return common
        cur = j.parent


def guess_frames(robot: Robot) -> tuple[str, str, list[str]]:
    """``(base, tool, alternatives)``: the root; the leaf with the most movable joints above it (then the most
    joints, then URDF order) -- or, where several such leaves branch only through fixed or prismatic joints (tags,
    fingers), the link they hang on (:func:`_tool_below`); the other leaves in that order."""
    leaves = sorted(_leaves(robot), key=lambda ln: _chain_length(robot, ln), reverse=True) or [robot.root]
    top = [ln for ln in leaves if _chain_length(robot, ln)[0] == _chain_length(robot, leaves[0])[0]]
    tool = _tool_below(robot, top) if len(top) > 1 else leaves[0]
    return robot.root, tool, [ln for ln in leaves if ln != tool]


def tie_key(robot: Robot, link: str, name: re.Pattern, moved: Collection[str]) -> tuple[bool, bool, int, int, int]:
    """Order of links that explain a sensor equally (rigidly joined, or joined by joints that hardly moved): a name
    like the sensor's, a tool-like name (:data:`TOOL_NAME`), more of the joints that ``moved`` in the data above it
    (the sensor rides after them), fewer resting movable joints (not a finger that happened to rest), deeper."""
    path = robot.path_from_root(link)
    resting = sum(robot.joints[j].movable and j not in moved for j in path)
    return (bool(name.search(link)), bool(TOOL_NAME.search(link)), sum(j in moved for j in path), -resting,
            len(path))


def camera_mount_joint(robot: Robot, frame: str) -> str | None:
    """The topmost fixed joint of the run of fixed joints above ``frame`` (the camera stand rather than the optical
    rotation), or None when ``frame`` hangs directly on a movable joint or is the root."""
    found = None
    cur = frame
    while (j := robot.parent_joint(cur)) is not None and not j.movable:
        found, cur = j.name, j.parent
    return found


def guess_model(robot: Robot, facts: BagFacts | None = None) -> ModelGuess:
    """Frames, chain and extra prior joints of ``robot`` (and what ``facts`` of a bag add)."""
    base, tool, alternatives = guess_frames(robot)
    if facts is not None and facts.pose_frame in robot.links and facts.pose_frame != tool:
        base = str(facts.pose_frame)   # /ground_truth/pose relates its frame_id to the tool
    up, down = robot.chain(base, tool)
    chain = [*up, *down]
    extra: dict[str, str] = {}
    if facts is not None:
        for topic, (link, _, _) in facts.reflectors.items():
            if link is not None and link in robot.links:
                for jn in robot.path_from_root(link):
                    if jn not in chain and jn not in extra:
                        extra[jn] = f"on the chain of the reflector {topic}"
        sensors = {f"the IMU {n}": f for n, f in facts.imus.items()}
        if facts.camera_frame:
            sensors["the camera"] = facts.camera_frame
        for what, frame in sensors.items():
            if frame not in robot.links:
                continue
            for jn in robot.path_from_root(frame):
                if robot.joints[jn].movable and jn not in chain and jn not in extra:
                    extra[jn] = f"on the chain of {what}"
        if facts.camera_frame and facts.camera_frame in robot.links:
            mount = camera_mount_joint(robot, facts.camera_frame)
            if mount is not None and mount not in chain:
                extra[mount] = "mounts the camera"
    return ModelGuess(base, tool, alternatives, chain, extra, facts)


def _vec(values: Sequence[float]) -> str:
    return "[" + ", ".join(f"{v:g}" for v in values) + "]"


def _prior_lines(robot: Robot, guess: ModelGuess) -> list[str]:
    out = ["# perturbations: joint -> 1-sigma `sigma` of the 6D perturbation xi right after the joint's static origin",
           "# (paper eq. 16) [rho_x, rho_y, rho_z in m; theta_x, theta_y, theta_z in rad], joint-origin axes, or a",
           "# full 6x6 `covariance` (CONTRACT.md sec. 5). Default: {} (joints not listed are exact). ppoe init gives",
           "# every joint from frames.base to frames.tool the loose prior of config/robots/cobot6_model.yaml:",
           f"# movable joints {_vec(PRIOR_MOVABLE)} (0.5 mm, 4 mrad),",
           f"# fixed joints {_vec(PRIOR_FIXED)} (0.5 mm, 3 mrad).",
           "perturbations:"]
    for jn in guess.chain:
        j = robot.joints[jn]
        sigma = PRIOR_MOVABLE if j.movable else PRIOR_FIXED
        out.append(f"  {jn}: {{sigma: {_vec(sigma)}}}   # {j.type}, {j.parent} -> {j.child}; default prior, "
                   "tighten it if you know better")
    for jn, why in guess.extra_joints.items():
        j = robot.joints[jn]
        sigma = PRIOR_CAMERA_MOUNT if why == "mounts the camera" else PRIOR_MOVABLE if j.movable else PRIOR_FIXED
        out.append(f"  {jn}: {{sigma: {_vec(sigma)}}}   # {j.type}, {why} {GUESS}")
    movable = [jn for jn in [*guess.chain, *guess.extra_joints] if robot.joints[jn].movable]
    out += ["", "# joint_noise: joint -> 1-sigma of the measured joint value along its axis [rad or m] (paper IV-D).",
            f"# Default: {{}} (none). ppoe init: {JOINT_NOISE:g} (cobot6's declared encoder repeatability).",
            "joint_noise:" + ("" if movable else " {}")]
    out += [f"  {jn}: {JOINT_NOISE:g}   # {'m' if robot.joints[jn].type == 'prismatic' else 'rad'}" for jn in movable]
    return out


def _frames_lines(guess: ModelGuess) -> list[str]:
    alt = ", ".join(guess.alternatives[:8]) + (" ..." if len(guess.alternatives) > 8 else "")
    out = ["", "# frames: reference and target frames of ppoe fk, evaluate, diagnose and the nodes (URDF links).",
           "frames:",
           "  base: " + guess.base + "   # reference frame; default: the URDF root link"
           + (" (guessed: the root)" if guess.facts is None or guess.facts.pose_frame != guess.base
              else f" (guessed: /ground_truth/pose's frame_id) {GUESS}"),
           "  tool: " + guess.tool + f"   # target frame: the leaf at the end of the longest chain {GUESS}"]
    if guess.alternatives:
        out.append(f"  # other leaves that could be the tool: {alt}")
    return out


def _tracker_lines(facts: BagFacts) -> list[str]:
    out = ["", "# trackers: laser-tracker / total-station reflectors (CONTRACT.md sec. 5), one entry per topic.",
           "trackers:"]
    for topic, (link, xyz, how) in sorted(facts.reflectors.items()):
        if link is None:
            out += [f"  # {topic}: no link of the URDF explains its points ({how}); add an entry by hand"]
            continue
        out += [f"  - topic: {topic}   # PointStamped topic of this reflector",
                f"    link: {link}   # URDF link that carries it ({how}) {GUESS}",
                f"    xyz: {_vec(xyz)}   # reflector in that link [m]; default [0, 0, 0] {GUESS}",
                f"    sigma: {TRACKER_SIGMA:g}   # 1-sigma per axis of one point [m]; default 0.0005 {GUESS}"]
    return out


def _tag_lines(guess: ModelGuess, facts: BagFacts) -> list[str]:
    out = ["", f"# tags: the tags seen ({facts.tag_note}), each on the link whose motion explains where it was seen,",
           "# its centre there (xyz [m]) and its size (black-square edge [m]) from its apparent size. Its orientation",
           "# on the link (rpy [rad], z = the face's outward normal) cannot be seen from centres: set it, then",
           "# uncomment the section (tag family: tag36h11 unless yours differs).",
           "# tags:", "#   family: tag36h11", "#   items:"]
    for tag, (link, xyz, size, how) in sorted(facts.tags.items()):
        size_text = f"{size:g}" if size else "0.04"
        out.append(f"#     - {{id: {tag}, link: {link or guess.tool}, size: {size_text}, xyz: {_vec(xyz)}, "
                   f"rpy: [0, 0, 0]}}   # {how} {GUESS}")
    return out


def _sensor_lines(robot: Robot, guess: ModelGuess, facts: BagFacts) -> list[str]:
    out: list[str] = []
    if facts.reflectors:
        out += _tracker_lines(facts)
    if facts.camera_frame:
        out += ["", "# camera: the camera of /camera/camera_info."]
        if facts.other_cameras:
            out += [f"# (camera_info also names {', '.join(facts.other_cameras)}: the model holds one camera; this is "
                    "the one with the most messages)"]
        if facts.camera_frame in robot.links:
            out += ["camera:",
                    f"  frame: {facts.camera_frame}   # URDF link of the optical frame (z forward, x right, y down), "
                    "from camera_info's frame_id",
                    f"  pixel_sigma: 0.5   # 1-sigma pixel noise per image coordinate [px]; default 0.5 {GUESS}"]
        else:
            out += [f"# camera_info's frame_id '{facts.camera_frame}' is not a link of the URDF: add the camera's",
                    "# frames to the URDF (ppoe check names this too), then:",
                    f"# camera: {{frame: {facts.camera_frame}, pixel_sigma: 0.5}}"]
    if facts.tags:
        out += _tag_lines(guess, facts)
    elif facts.tag_note:
        out += ["", f"# tags: {facts.tag_note}"]
    if facts.imus:
        out += ["", "# imus: accelerometers (/imu/<name>); at rest they measure gravity, i.e. the link's tilt.",
                "imus:"]
        for name, frame in sorted(facts.imus.items()):
            if frame in robot.links:
                out += [f"  {name}:", f"    link: {frame}   # URDF link it is fixed to, from its frame_id",
                        f"    sigma: 0.0004   # 1-sigma per axis [m/s^2]; default 0.0004 {GUESS}"]
            else:
                out += [f"  # {name}: frame_id '{frame}' is not a link of the URDF: add it, then an entry"]
    return out


def model_yaml(robot: Robot, guess: ModelGuess, urdf_name: str, bag_names: Sequence[str] = ()) -> str:
    """The commented model YAML of ``guess`` (loads with :func:`ppoe_core.robot.config.load_model_config`)."""
    src = f"the URDF {urdf_name}" + (f" and the bag {', '.join(bag_names)}" if bag_names else "")
    movable = sum(robot.joints[j].movable for j in guess.chain)
    out = [f"# PPOE model of {robot.name}, written by `ppoe init` from {src}.",
           f"# Chain {guess.base} -> {guess.tool}: {len(guess.chain)} joints ({movable} movable).",
           f"# Every key: meaning [unit], default. Lines marked '{GUESS}' are guesses: check each one.",
           "# Then `ppoe check BAG --model THIS.yaml` compares a recording with it (docs/your_robot.md).", ""]
    out += _prior_lines(robot, guess)
    out += _frames_lines(guess)
    if guess.facts is not None:
        out += _sensor_lines(robot, guess, guess.facts)
    out += ["", "# effects: systematic effects known before (CONTRACT.md sec. 6 names). Default: [] (none).",
            "effects: []", ""]
    return "\n".join(out)


def summary_lines(guess: ModelGuess) -> list[str]:
    """What was guessed, one line each (for the terminal)."""
    out = [f"frames: base {guess.base}, tool {guess.tool} ({len(guess.chain)} joints on the chain)"]
    if guess.alternatives:
        out.append(f"other leaves: {', '.join(guess.alternatives[:8])}")
    facts = guess.facts
    if facts is not None:
        out += [f"tracker {t}: link {link} ({how})" for t, (link, _, how) in sorted(facts.reflectors.items())]
        if facts.camera_frame:
            out.append(f"camera: {facts.camera_frame}")
        out += [f"imu {n}: {f}" for n, f in sorted(facts.imus.items())]
        out += [f"tag {t}: link {v[0]} ({v[3]})" for t, v in sorted(facts.tags.items())]
    return out
