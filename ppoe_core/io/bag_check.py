"""What a bag holds against what a model needs (``ppoe check``): one table, a verdict per line, an exit code.

:func:`check_bags` reads each bag once (images not decoded) and compares it with the model YAML (loaded against the
bag's own ``/robot_description``):

* **topics**: ``/robot_description``, ``/joint_states`` (count, rate), every measurement the model declares
  (``trackers`` topics, ``camera`` images or tag observations, ``imus``, the ``contact`` plane's ``/wrench``),
  reflector or IMU topics the model does not declare, and whether anything at all can be diagnosed against;
* **joints**: the joints the measured links need, present / missing in ``/joint_states`` (with the closest
  name the bag has, e.g. a renamed joint), names the URDF does not know;
* **frames**: ``camera_info``, IMU and ``/ground_truth/pose`` frames known to the URDF and agreeing with the model;
* **time**: span and stamp problems (zero stamps, stamps going back, measurements outside the joint states);
* **stops**: measurements taken at rest (:func:`static_rows`) and the distinct poses among them;
* **identifiable**: per movable joint of the measured chain, whether a zero offset can be told from the tracker
  registration with these data (:func:`offset_identifiability`), and whether the joint moves enough
  (:data:`MIN_RANGE_DEG`) to tell its offset from a fixed link error.

Verdicts: ``ok``, ``warn`` (diagnose runs, but learns less), ``FAIL`` (diagnose would refuse the bag or mis-read
it).  Exit code (:attr:`CheckReport.exit_code`): 0 all ok, 1 warnings only, 2 a failure.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.errors import PpoeError
from ppoe_core.io.bag_facts import sessions_at
from ppoe_core.io.bag_joints import joints_at
from ppoe_core.io.messages import TOPIC_GT_POINT, TOPIC_JOINT_STATES
from ppoe_core.io.stops import STOP_TOPIC
from ppoe_core.model.context import at_rest
from ppoe_core.robot.robot_model import Robot

__all__ = ["CheckRow", "CheckReport", "check_bags", "static_rows", "offset_identifiability", "MIN_RANGE_DEG",
           "MIN_STOPS", "MIN_SIGNATURE", "MIN_RATE"]

#: a joint offset differs from a fixed rotation of its link only through the joint's own motion: below 3 deg
#: (sin 3 deg = 0.052) of motion that difference is about 5 % of the offset's effect (the issue's rule of thumb)
MIN_RANGE_DEG = 3.0
#: diagnose needs at least 6 measured stops (ppoe_core.analysis.diagnose.engine.check_stops)
MIN_STOPS = 6
#: static measurements whose joint values differ by less than this [rad or m] are one stop
SAME_STOP = 1e-3
#: an offset whose signature is more than 95 % a rigid motion of the tracker registration leaves under 5 % of it
#: in the residual: it cannot be told from the registration
MIN_SIGNATURE = 0.05
#: CONTRACT.md sec. 3: /joint_states at >= 50 Hz
MIN_RATE = 50.0

VERDICTS = ("ok", "warn", "FAIL")


@dataclass(frozen=True)
class CheckRow:
    """One line of the table: ``bag`` (directory name), ``item``, what the bag ``holds``, what the model ``needs``,
    ``verdict`` (``ok`` / ``warn`` / ``FAIL``), and ``scope``: the commands it matters to (``all``; ``diagnose``:
    its static stops; ``check``: what diagnose and evaluate refuse themselves, in one line -- an unreadable bag,
    no URDF, a model that does not load)."""

    bag: str
    item: str
    holds: str
    needs: str
    verdict: str
    scope: str = "all"


@dataclass
class CheckReport:
    """Every row of every bag; :attr:`exit_code`, :meth:`failures`, :meth:`markdown`, :meth:`summary`."""

    rows: list[CheckRow] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """0 all ok, 1 warnings only, 2 at least one failure."""
        return max((VERDICTS.index(r.verdict) for r in self.rows), default=0)

    def failures(self, command: str | None = None) -> list[CheckRow]:
        """The FAIL rows (those that matter to ``command``, ``diagnose`` or ``evaluate``, if given)."""
        return [r for r in self.rows if r.verdict == "FAIL" and (command is None or r.scope in ("all", command))]

    def markdown(self) -> str:
        """The table (markdown)."""
        lines = ["| bag | check | the bag holds | the model needs | verdict |", "|---|---|---|---|---|"]
        lines += [f"| {r.bag} | {r.item} | {r.holds} | {r.needs} | {r.verdict} |" for r in self.rows]
        return "\n".join(lines)

    def summary(self) -> str:
        """One line: the verdict and counts, the first failure or warning named."""
        n_fail, n_warn = len(self.failures()), sum(r.verdict == "warn" for r in self.rows)
        bags = len(dict.fromkeys(r.bag for r in self.rows))
        word = ("FAIL" if n_fail else "WARN" if n_warn else "OK")
        first = next((r for r in self.rows if r.verdict == ("FAIL" if n_fail else "warn")), None)
        tail = f"; first: {first.bag}: {first.item}: {first.holds} (needs: {first.needs})" if first else ""
        return f"ppoe check: {word}: {n_fail} failure(s), {n_warn} warning(s) in {bags} bag(s){tail}"


class _Rows:
    """Rows of one bag being checked."""

    def __init__(self, bag: str) -> None:
        self.bag, self.rows = bag, []  # type: str, list[CheckRow]

    def add(self, item: str, holds: str, needs: str, verdict: str = "ok", scope: str = "all") -> None:
        self.rows.append(CheckRow(self.bag, item, holds.replace("|", "/"), needs.replace("|", "/"), verdict, scope))


def _names(items: Any, at_most: int = 6) -> str:
    items = list(items)
    return ", ".join(items[:at_most]) + (f" (+{len(items) - at_most} more)" if len(items) > at_most else "")


def check_bags(bags: list[str], model: str, identifiability: bool = True) -> CheckReport:
    """Check every bag against the model YAML ``model`` (see the module docstring); ``identifiability=False``
    skips the identifiability rows (warnings only, and the slowest part: what diagnose / evaluate skip)."""
    report = CheckReport()
    for bag in bags:
        report.rows += _check_one(bag, model, identifiability)
    return report


def _check_one(bag: str, model: str, identifiability: bool) -> list[CheckRow]:
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.config import load_model_config
    from ppoe_core.robot.urdf import parse_urdf

    out = _Rows(Path(bag).name)
    try:
        data = read_bag(bag, load_images=False)
    except PpoeError as exc:
        out.add("bag", f"unreadable: {exc}", "a rosbag2 directory (mcap or sqlite3)", "FAIL", "check")
        return out.rows
    if not data.robot_description:
        out.add("/robot_description", "absent", "the URDF, once, first (CONTRACT.md sec. 3)", "FAIL", "check")
        return out.rows
    try:
        robot = parse_urdf(data.robot_description, text_source=f"{bag} /robot_description")
        out.add("/robot_description", f"URDF '{robot.name}': {len(robot.movable_joints)} movable joints",
                "the robot's URDF")
        cfg = load_model_config(model, robot)
        out.add("model", f"{Path(model).name} loads against this URDF", "joints and links of the URDF")
    except PpoeError as exc:
        out.add("model", str(exc), "joints and links of the bag's URDF", "FAIL", "check")
        return out.rows
    _topic_rows(out, data, cfg)
    needed = _needed_links(robot, cfg)
    _joint_rows(out, data, robot, needed)
    _frame_rows(out, data, robot, cfg)
    rows = _measurement_stamps(data)
    _time_rows(out, data, rows)
    if rows.size and len(data.joint_states):
        _stop_rows(out, data, robot, cfg, rows, identifiability)
    return out.rows


def _reflectors(data: Any) -> dict[str, Any]:
    series = dict(data.ground_truth_points)
    if len(data.ground_truth_point):
        series[TOPIC_GT_POINT] = data.ground_truth_point
    return series


def _topic_rows(out: _Rows, data: Any, cfg: Any) -> None:
    js = data.joint_states
    if not len(js):
        out.add(TOPIC_JOINT_STATES, "absent", f"joint values, >= {MIN_RATE:g} Hz", "FAIL")
    else:
        rate = data.rate(TOPIC_JOINT_STATES)
        out.add(TOPIC_JOINT_STATES, f"{len(js)} messages, {rate:.0f} Hz", f">= {MIN_RATE:g} Hz",
                "ok" if rate >= MIN_RATE else "warn")
    refl = _reflectors(data)
    declared = {t.topic for t in cfg.trackers}
    for t in cfg.trackers:
        n = len(refl[t.topic]) if t.topic in refl else 0
        out.add(t.topic, f"{n} points" if n else "absent", f"points of the reflector on {t.link} (trackers)",
                "ok" if n else "FAIL")
    for topic in sorted(set(refl) - declared):
        if declared or topic != TOPIC_GT_POINT:
            out.add(topic, f"{len(refl[topic])} points", "an entry in the model's trackers (diagnose refuses "
                    "undeclared reflectors; `ppoe init --bag` guesses one)", "FAIL")
        else:
            out.add(topic, f"{len(refl[topic])} points", "a trackers entry, or --tool LINK on the command line "
                    "(`ppoe init --bag` guesses the entry)", "warn")
    if len(data.ground_truth_pose):
        out.add("/ground_truth/pose", f"{len(data.ground_truth_pose)} poses", "optional (6D tool poses)")
    _sensor_topic_rows(out, data, cfg)
    if STOP_TOPIC in data.topics:
        out.add(STOP_TOPIC, f"{data.topics[STOP_TOPIC][1]} stop descriptions", "optional: stations and stop roles")
    other = [f"{t} ({data.topics[t][1]})" for t in sorted(data.unknown_topics) if t in data.topics and t != STOP_TOPIC]
    if other:
        out.add("other topics", _names(other), "not used by the model (ignored)")
    if not (refl or len(data.ground_truth_pose) or data.imus or len(data.tag_observations) or len(data.images)):
        out.add("measurements", "no tracker points, poses, images, tag observations or IMUs",
                "something to diagnose against", "FAIL")


def _sensor_topic_rows(out: _Rows, data: Any, cfg: Any) -> None:
    pictures = len(data.images) + len(data.tag_observations)
    if cfg.camera is not None:
        out.add("camera", f"{len(data.camera_info)} camera_info, {len(data.images)} images, "
                f"{len(data.tag_observations)} tag observations", f"images of {cfg.camera.frame}",
                "ok" if pictures and (len(data.camera_info) or len(data.tag_observations)) else "FAIL")
    elif pictures:
        out.add("camera", f"{len(data.images)} images, {len(data.tag_observations)} tag observations",
                "a camera section to use them (unused now)", "warn")
    for name in sorted(cfg.imus):
        n = len(data.imus[name]) if name in data.imus else 0
        out.add(f"/imu/{name}", f"{n} messages" if n else "absent", f"accelerometer on {cfg.imus[name].link}",
                "ok" if n else "FAIL")
    for name in sorted(set(data.imus) - set(cfg.imus)):
        out.add(f"/imu/{name}", f"{len(data.imus[name])} messages", "an imus entry to use it (unused now)", "warn")
    if cfg.contact is not None:
        out.add("/wrench", f"{len(data.wrench)} messages" if len(data.wrench) else "absent",
                "forces at the tool (contact plane)", "ok" if len(data.wrench) else "FAIL")


def _needed_links(robot: Robot, cfg: Any) -> list[str]:
    """Links whose pose the model's measurements need: tool, reflector links, camera, IMU and tag links."""
    links = [cfg.frames.tool] if cfg.frames and cfg.frames.tool else []
    links += [t.link for t in cfg.trackers] + [i.link for i in cfg.imus.values()]
    if cfg.camera is not None:
        links.append(cfg.camera.frame)
    if cfg.tags is not None:
        links += [t.link for t in cfg.tags.items]
    return list(dict.fromkeys(ln for ln in links if ln in robot.links))


def _chain_joints(robot: Robot, links: list[str]) -> list[str]:
    """Independent joints that move any of ``links`` (mimic joints by their master)."""
    out = []
    for ln in links:
        for jn in robot.path_from_root(ln):
            j = robot.joints[jn]
            if j.movable:
                out.append(j.mimic_root[0] if j.mimic_root else jn)
    return list(dict.fromkeys(out))


def _joint_rows(out: _Rows, data: Any, robot: Robot, needed: list[str]) -> None:
    names = list(data.joint_states.names)
    need = _chain_joints(robot, needed)
    missing = [j for j in need if j not in names]
    unknown = [n for n in names if n not in robot.joints]
    for jn in missing:
        close = difflib.get_close_matches(jn, unknown, n=1, cutoff=0.5)
        hint = f"; the bag has '{close[0]}', not in the URDF: renamed?" if close else ""
        out.add(f"joint {jn}", f"absent from {TOPIC_JOINT_STATES}{hint}", f"moves {_names(needed, 3)}", "FAIL")
    present = [j for j in need if j in names]
    if present:
        out.add("joints", f"{len(present)} of {len(need)} needed joints present", _names(need), "ok")
    if unknown:
        out.add("joints not in the URDF", _names(unknown), "ignored", "warn" if not missing else "ok")


def _frame_rows(out: _Rows, data: Any, robot: Robot, cfg: Any) -> None:
    frames = {"camera_info": set(data.camera_info.frame_ids),
              "/ground_truth/pose": set(data.ground_truth_pose.frame_ids)}
    frames.update({f"/imu/{n}": set(s.frame_ids) for n, s in data.imus.items()})
    for what, ids in frames.items():
        for fid in sorted(ids):
            if fid not in robot.links:
                out.add(f"frame {fid}", f"{what} frame_id, not a link of the URDF", "a URDF link", "FAIL")
            elif what == "camera_info" and cfg.camera is not None and fid != cfg.camera.frame:
                out.add(f"frame {fid}", "camera_info frame_id of another camera than the model's (its data unused)",
                        f"camera.frame {cfg.camera.frame}", "warn")
            elif what.startswith("/imu/") and what[5:] in cfg.imus and cfg.imus[what[5:]].link != fid:
                out.add(f"frame {fid}", f"{what} frame_id", f"imus.{what[5:]}.link {cfg.imus[what[5:]].link}", "FAIL")
            else:
                out.add(f"frame {fid}", f"{what} frame_id, a URDF link", "a URDF link")


def _measurement_stamps(data: Any) -> np.ndarray:
    return _measurements(data)[0]


def _measurements(data: Any) -> tuple[np.ndarray, list[str]]:
    """Stamps (sorted) and frame ids of every tracker point (else every ground-truth pose)."""
    series = list(_reflectors(data).values()) or ([data.ground_truth_pose] if len(data.ground_truth_pose) else [])
    if not series:
        return np.zeros(0), []
    stamps = np.concatenate([s.stamps for s in series])
    frames = [f for s in series for f in s.frame_ids]
    order = np.argsort(stamps, kind="stable")
    return stamps[order], [frames[i] for i in order]


def _time_rows(out: _Rows, data: Any, rows: np.ndarray) -> None:
    js = data.joint_states.stamps
    if not js.size:
        return
    back = int(np.sum(np.diff(js) < 0))
    zero = int(np.sum(js <= 0.0)) + int(np.sum(rows <= 0.0))
    outside = int(np.sum((rows < js.min()) | (rows > js.max())))
    out.add("time", f"{js.max() - js.min():.1f} s of joint states", "one clock", "ok")
    problems = [f"{zero} zero stamps"] * bool(zero) + [f"{back} joint states stamped before the previous"] * bool(back)
    problems += [f"{outside} measurements outside the joint states' span"] * bool(outside)
    if problems:
        out.add("stamps", "; ".join(problems), "increasing stamps on one clock (diagnose drops measurements "
                "outside the joint states)", "FAIL" if zero else "warn")
    else:
        out.add("stamps", "increasing, measurements inside the joint states", "increasing stamps on one clock")


def static_rows(data: Any, joints: list[str], stamps: np.ndarray) -> np.ndarray:
    """(N,) bool: at each stamp no joint of ``joints`` moves faster than :data:`ppoe_core.model.context.REST_SPEED`
    (:func:`ppoe_core.model.context.at_rest`, the rest test diagnose's accelerometer rows use too)."""
    js = data.joint_states
    order = np.argsort(js.stamps, kind="stable")
    cols = [js.names.index(j) for j in joints if j in js.names]
    q = js.positions[order][:, cols] if cols else np.zeros((len(order), 0))
    return at_rest(js.stamps[order], q, stamps)


def _distinct(q: dict[str, np.ndarray], joints: list[str]) -> int:
    """Number of stops: runs of consecutive rows whose joint values stay within :data:`SAME_STOP`."""
    if not joints or not len(q[joints[0]]):
        return 0
    Q = np.stack([q[j] for j in joints], axis=1)
    return 1 + int(np.sum(np.max(np.abs(np.diff(Q, axis=0)), axis=1) > SAME_STOP))


def offset_identifiability(robot: Robot, q: dict[str, np.ndarray], links: list[str],
                           points: list[np.ndarray], session: np.ndarray | None = None) -> dict[str, float]:
    """Joint -> share (0..1) of its zero offset's signature on the reflector points that a rigid motion of the
    tracker registration cannot explain: ``|c - A A^+ c| / |c|`` with ``c`` (3N,) the points' root-frame motion per
    radian (or metre) of the offset and ``A`` (3N, 6 S) the small motions ``[I, -[p_i]x]`` of each of the S
    registrations (``session`` (N,) int of every pose, default one)."""
    from ppoe_core import lie
    from ppoe_core.robot.tree import KinematicTree

    tree = KinematicTree(robot)
    cols: dict[str, list[np.ndarray]] = {}
    regs = []
    for link, xyz in zip(links, points):
        poses = tree.link_poses(q, links=[link])
        T = np.asarray(poses[link])
        p = T[:, :3, :3] @ xyz + T[:, :3, 3]
        small = np.concatenate([np.broadcast_to(np.eye(3), (len(p), 3, 3)), -lie.hat3(p)], axis=2)   # (N, 3, 6)
        sess = np.zeros(len(p), dtype=int) if session is None else np.asarray(session)
        onehot = (sess[:, None] == np.unique(sess)[None, :]).astype(float)                    # (N, S)
        regs.append(np.einsum("nij,ns->nisj", small, onehot).reshape(3 * len(p), -1))
        J_dq, _ = tree.point_jacobian(q, link, xyz, poses=poses)
        for jn, J in J_dq.items():
            cols.setdefault(jn, []).append(np.asarray(J).reshape(-1))
    A = np.concatenate(regs)
    out = {}
    for jn, parts in cols.items():
        c = np.concatenate(parts) if len(parts) == len(links) else None
        if c is None or not np.linalg.norm(c):
            continue
        resid = c - A @ np.linalg.lstsq(A, c, rcond=None)[0]
        out[jn] = float(np.linalg.norm(resid) / np.linalg.norm(c))
    return out


def _stop_rows(out: _Rows, data: Any, robot: Robot, cfg: Any, stamps: np.ndarray, identifiability: bool) -> None:
    refl = _reflectors(data)
    links = [t.link for t in cfg.trackers if t.topic in refl] or ([cfg.frames.tool] if cfg.frames.tool else [])
    # the joints that move the measured links; without a tool or tracker link, every joint the bag has
    joints = _chain_joints(robot, links) or [j for j in robot.independent_joints if j in data.joint_states.names]
    still = static_rows(data, joints, stamps)
    q = joints_at(data, robot, stamps[still])
    frames = [f for f, k in zip(_measurements(data)[1], still) if k]
    n_stops = _distinct(q, joints)
    out.add("stops", f"{n_stops} stops at rest ({int(still.sum())} of {len(stamps)} measurements)",
            f">= {MIN_STOPS} stops, measured at rest (ppoe diagnose)", "ok" if n_stops >= MIN_STOPS else "FAIL",
            "diagnose")
    if n_stops < 2 or not identifiability:
        return
    share = {}
    used = [(t.link, np.asarray(t.xyz, float)) for t in cfg.trackers if t.topic in refl]
    if refl and not used and links:  # undeclared reflectors: as if on the tool (their row above says FAIL)
        used = [(links[0], np.zeros(3))]
    if used:
        session = sessions_at(data.path, data, stamps[still], frames)
        share = offset_identifiability(robot, q, [u[0] for u in used], [u[1] for u in used], session)
    _identifiable_rows(out, robot, q, joints, share)


def _identifiable_rows(out: _Rows, robot: Robot, q: dict[str, np.ndarray], joints: list[str],
                       share: dict[str, float]) -> None:
    good = []
    moves = {jn: float(np.ptp(q[jn])) if len(q[jn]) else 0.0 for jn in joints}
    rev = {jn: robot.joints[jn].type in ("revolute", "continuous") for jn in joints}
    # the first joint that moves turns every point about one fixed axis: its offset is always a rigid motion
    first = next((jn for jn in joints if not rev[jn] or np.degrees(moves[jn]) >= MIN_RANGE_DEG), None)
    for jn in joints:
        small = rev[jn] and np.degrees(moves[jn]) < MIN_RANGE_DEG
        why = f"{jn} never moves more than {MIN_RANGE_DEG:g}° (range {np.degrees(moves[jn]):.1f}°)"
        if jn in share and share[jn] < MIN_SIGNATURE:
            cause = (why if small else "as the first joint that moves it turns every point about one fixed axis"
                     if jn == first else f"its effect on the points is almost a rigid motion ({share[jn]:.0%} left: "
                     "poses that turn the joints before it more, unless its axis parallels theirs)")
            text = f"{jn}'s zero offset cannot be told from the tracker registration: {cause}; diagnose cannot name it"
            out.add(f"joint_offset@{jn}", text, "an identifiable effect", "ok" if jn == first and not small else "warn")
        elif small:
            out.add(f"joint_offset@{jn}", f"{jn}'s zero offset cannot be told from a link_error at {jn}: {why}",
                    "an identifiable effect", "warn")
        else:
            good.append(jn)
    if good:
        out.add("joint offsets", f"identifiable: {_names(good, 8)}", "an identifiable effect")
