"""What a bag shows about the robot's sensors, for ``ppoe init`` (:class:`~ppoe_core.robot.model_init.BagFacts`).

* reflector topics ``/ground_truth/point[/<name>]`` and the link that carries each: the link whose motion explains
  the points best (:func:`reflector_links`: for every link, the rigid tracker registration and the reflector's
  position in the link are fitted to the points by alternating least squares; the smallest residual wins, among
  equal ones the link deepest in the tree);
* the camera's optical frame (``/camera/camera_info`` ``frame_id``), the IMUs' frames (``/imu/<name>``);
* the tags seen and the links carrying them (:mod:`ppoe_core.io.tag_facts`).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.errors import BagError
from ppoe_core.io.bag_joints import joints_at, moved_joints
from ppoe_core.io.tag_facts import tag_guesses, tag_sightings
from ppoe_core.robot.model_init import BagFacts, tie_key
from ppoe_core.robot.robot_model import Robot
from ppoe_core.robot.tree import KinematicTree

__all__ = ["bag_facts", "bag_urdf", "reflector_links", "ReflectorFit", "fit_reflector", "sessions_at",
           "TIE_RATIO"]

#: alternating least-squares rounds of the reflector fit (registration <-> position in the link); the fit's
#: residual settles within a few rounds on the robots we tried, 30 leaves a margin
FIT_ROUNDS = 30
#: links whose residual is within this factor of the best one explain the points equally (e.g. a flange and the
#: tool fixed to it): the deepest of them is named
TIE_RATIO = 1.05
#: a next link fitting within this factor of the best one is named as hardly worse (the choice is then weak)
AMBIGUOUS = 1.5
#: among links that explain the points equally, one named like a reflector is preferred (model_init.tie_key)
REFLECTOR_NAME = re.compile(r"prism|reflector|retro|smr|marker|tracker|target|^lr\d", re.IGNORECASE)
#: fewer points than this cannot fix a rigid registration (6) and a reflector position (3)
MIN_POINTS = 4


def bag_urdf(path: str | Path) -> str:
    """The bag's ``/robot_description``; raises :class:`BagError` naming the bag if it has none."""
    from ppoe_core.io.bagio import read_bag

    return read_bag(path, topics=["/robot_description"], load_images=False).require_robot_description()


class ReflectorFit:
    """One link's fit of the points: ``rms`` residual [m], reflector ``xyz`` in the link [m], registration
    ``R``, ``t`` (tracker <- root)."""

    def __init__(self, rms: float, xyz: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
        self.rms, self.xyz, self.R, self.t = rms, xyz, R, t


def _kabsch(P: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``R`` and translation ``t`` minimising ``|R P + t - M|`` (rows are points)."""
    cp, cm = P.mean(0), M.mean(0)
    U, _, Vt = np.linalg.svd((P - cp).T @ (M - cm))
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cm - R @ cp


def fit_reflector(T_root_link: np.ndarray, meas: np.ndarray, session: np.ndarray | None = None) -> ReflectorFit:
    """Fit ``meas_i = R_s (R_i xyz + t_i) + t_s`` (``T_root_link`` (N,4,4), ``meas`` (N,3) in the tracker frame,
    one registration ``R_s, t_s`` per ``session`` (N,) int, default one); ``R``, ``t`` of the result: session 0."""
    Ri, ti = T_root_link[:, :3, :3], T_root_link[:, :3, 3]
    sess = np.zeros(len(meas), dtype=int) if session is None else np.asarray(session)
    groups = [np.flatnonzero(sess == k) for k in np.unique(sess)]
    xyz = np.zeros(3)
    R, t = np.broadcast_to(np.eye(3), (len(meas), 3, 3)).copy(), np.zeros((len(meas), 3))
    for _ in range(FIT_ROUNDS):
        for g in groups:
            R[g], t[g] = _kabsch(Ri[g] @ xyz + ti[g], meas[g])
        back = np.einsum("nji,nj->ni", R, meas - t) - ti           # R_s^T (m_i - t_s) - t_i = R_i xyz
        xyz = np.linalg.lstsq(Ri.reshape(-1, 3), back.reshape(-1), rcond=None)[0]
    res = np.einsum("nij,nj->ni", R, Ri @ xyz + ti) + t - meas
    return ReflectorFit(float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))), xyz, R[0], t[0])


def sessions_at(path: str | Path, data: Any, stamps: np.ndarray, frame_ids: list[str]) -> np.ndarray:
    """(N,) registration session of each measurement: its ``header.frame_id`` and, in a bag with importer
    metadata ``/dataset/stop``, its station (the last stop description before it), as ``ppoe diagnose`` splits
    them."""
    from ppoe_core.io.stops import STOP_TOPIC, read_stop_info

    keys = list(frame_ids)
    info = read_stop_info(str(path)) if STOP_TOPIC in data.topics else []
    if info:
        t_info = np.array([t for t, _ in info])
        k = np.clip(np.searchsorted(t_info, stamps, side="right") - 1, 0, len(info) - 1)
        keys = [f"{f}:{info[i][1].get('station', '?')}" for f, i in zip(keys, k)]
    names = list(dict.fromkeys(keys))
    return np.array([names.index(key) for key in keys], dtype=int)


def reflector_links(data: Any, robot: Robot) -> dict[str, tuple[str | None, tuple[float, float, float], str]]:
    """Reflector topic -> (the link whose motion explains its points, reflector position there [m], how found)."""
    series = dict(data.ground_truth_points)
    if len(data.ground_truth_point):
        series["/ground_truth/point"] = data.ground_truth_point
    tree = KinematicTree(robot)
    candidates = [ln for ln in robot.links if any(robot.joints[j].movable for j in robot.path_from_root(ln))]
    out: dict[str, tuple[str | None, tuple[float, float, float], str]] = {}
    for topic, s in sorted(series.items()):
        good = np.all(np.isfinite(s.p), axis=1)
        if good.sum() < MIN_POINTS or not candidates:
            out[topic] = (None, (0.0, 0.0, 0.0), f"only {int(good.sum())} points")
            continue
        q = joints_at(data, robot, s.stamps[good])
        poses = tree.link_poses(q, links=candidates)
        sess = sessions_at(data.path, data, s.stamps[good], [f for f, g in zip(s.frame_ids, good) if g])
        fits = {ln: fit_reflector(np.asarray(poses[ln]), s.p[good], sess) for ln in candidates}
        best = min(f.rms for f in fits.values())
        tied = [ln for ln in candidates if fits[ln].rms <= best * TIE_RATIO + 1e-9]
        moved = moved_joints(q)
        link = max(tied, key=lambda ln: tie_key(robot, ln, REFLECTOR_NAME, moved))
        others = sorted((f.rms, ln) for ln, f in fits.items() if ln not in tied)
        how = (f"its motion fits {int(good.sum())} points to {best * 1e3:.2f} mm RMS"
               + (f"; next: {others[0][1]} {others[0][0] * 1e3:.2f} mm" if others else "")
               + ("; hardly better: the poses may not turn the tool enough to tell them apart"
                  if others and others[0][0] < AMBIGUOUS * best else ""))
        xyz = fits[link].xyz
        out[topic] = (link, (round(float(xyz[0]), 4) + 0.0, round(float(xyz[1]), 4) + 0.0,
                             round(float(xyz[2]), 4) + 0.0), how)   # + 0.0: no "-0"
    return out


def bag_facts(path: str | Path, robot: Robot) -> BagFacts:
    """Reflectors and their links, camera frame, IMU frames, tags and their links of a contract bag."""
    from ppoe_core.io.bagio import read_bag

    data = read_bag(path, load_images=True)
    facts = BagFacts(path=str(path))
    if data.ground_truth_points or len(data.ground_truth_point):
        if len(data.joint_states) == 0:
            raise BagError(f"bag {path}: tracker points but no /joint_states: the reflector's link cannot be found")
        facts.reflectors = reflector_links(data, robot)
    if len(data.camera_info):  # the camera with the most messages; the others named
        ids, counts = np.unique(data.camera_info.frame_ids, return_counts=True)
        ranked = [str(ids[i]) for i in np.argsort(-counts, kind="stable")]
        facts.camera_frame, facts.other_cameras = ranked[0], ranked[1:]
    facts.imus = {name: s.frame_ids[0] for name, s in data.imus.items() if s.frame_ids}
    if len(data.ground_truth_pose):
        facts.pose_frame = data.ground_truth_pose.frame_ids[0]
    sightings, facts.tag_note = tag_sightings(data)
    if data.images and not sightings:
        facts.tag_note = f"no tag36h11 tag found ({facts.tag_note})"
    facts.tags = {t: (g.link, g.xyz, g.size, g.how) for t, g in tag_guesses(data, robot, sightings).items()}
    return facts
