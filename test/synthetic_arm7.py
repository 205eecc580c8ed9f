"""Synthetic joint tracker + pixel data of the arm7 robot (``config/robots/arm7.urdf``): used by the joint-fit
tests and ``bench/bench_solver.py`` (runs without any dataset)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.pixels import PixelObs, predict_pixels
from ppoe_core.analysis.diagnose.stops import Stops, motion_signs
from ppoe_core.model.effects import Effect, make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

#: intrinsics [px] and plumb_bob distortion of the synthetic 640 x 480 camera
K_SYN = np.array([[300.0, 0.0, 320.0], [0.0, 300.0, 240.0], [0.0, 0.0, 1.0]])
D_SYN = np.array([-0.05, 0.02, 0.001, -0.001, 0.0])
#: tag points per link [m] (link coordinates)
TAGS_SYN = {"tool0": np.array([[0.03, 0.0, 0.05], [-0.03, 0.0, 0.05], [0.0, 0.04, 0.08], [0.0, -0.04, 0.02]]),
            "arm_link_3": np.array([[0.07, 0.0, 0.10], [0.0, 0.07, 0.15], [-0.07, 0.0, 0.2]])}
#: tracker reflector on tool0 [m]
REFLECTOR_SYN = np.array([0.0, 0.0, 0.02])


def arm7_truth(robot: Robot) -> list[Effect]:
    """A camera mount error (20 mm, 20 mrad) and two arm errors (a 3-component ``link_error`` at joint_4, a 4 mrad
    ``joint_offset`` at joint_2): all seen by the camera, the arm ones by the tracker too."""
    return [make_effect("camera_extrinsics", "camera_joint", robot, [0.02, 0.0, 0.0, 0.0, 0.0, 0.02]),
            make_effect("link_error", "joint_4", robot, [0.002, -0.003, 0.001], components=["x", "y", "z"]),
            make_effect("joint_offset", "joint_2", robot, [0.004])]


def arm7_joint_data(robot: Robot, effects: Sequence[Effect], n: int = 40, seed: int = 0, sigma_t: float = 1e-4,
                    sigma_px: float = 0.5) -> tuple[Stops, PixelObs]:
    """Tracker points (reflector on tool0, one session, random registration, noise ``sigma_t`` [m]) and pixels
    of the 7 tag points on tool0 and arm_link_3 seen by ``camera_optical_frame`` (noise ``sigma_px`` [px]) at
    ``n`` random poses, generated with the true ``effects``; points outside the 640 x 480 image dropped.
    Pixel ``pose`` = tracker row index."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(robot)
    names = tree.joint_names
    q = {j: rng.uniform(-0.9, 0.9, n) for j in names if robot.joints[j].type != "prismatic"}
    q.update({j: np.full(n, 0.01) for j in names if j not in q})
    t = np.arange(n) * 5.0
    sg = motion_signs(t, np.column_stack([q[j] for j in names]), t)
    signs = {j: sg[:, i] for i, j in enumerate(names)}
    ctx = {"time": t, "motion_sign": signs}
    dq, dxi = sum_effect_corrections(list(effects), q, ctx)
    x = (tree.link_poses(q, dq, dxi)["tool0"] @ np.append(REFLECTOR_SYN, 1.0))[:, :3]
    T = lie.from_xyz_rpy(rng.uniform(-3, 3, 3), [0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    stops = Stops(q=q, p_meas=x @ T[:3, :3].T + T[:3, 3] + rng.normal(0.0, sigma_t, x.shape), kind="point",
                  link="tool0", point=REFLECTOR_SYN, sigma=sigma_t, session=np.zeros(n, int), session_names=["s0"],
                  group=np.zeros(n, int), group_names=["synthetic"], reg_mask=np.ones(n, bool),
                  score_mask=np.ones(n, bool), context=ctx, base=robot.root)
    links = np.array([ln for ln, pts in TAGS_SYN.items() for _ in pts], dtype=object)
    pts = np.concatenate(list(TAGS_SYN.values()))
    pose = np.repeat(np.arange(n), len(pts))
    obs = PixelObs(q={j: v[pose] for j, v in q.items()}, link="tool0", links=np.tile(links, n),
                   point=np.tile(pts, (n, 1)), camera=np.zeros(len(pose), int), cameras=["camera_optical_frame"],
                   K=[K_SYN], D=[D_SYN], uv=np.zeros((len(pose), 2)), pose=pose, sigma_px=sigma_px, name="synthetic",
                   context={"time": t[pose], "motion_sign": {j: v[pose] for j, v in signs.items()}})
    obs.uv = predict_pixels(tree, obs, list(effects)) + rng.normal(0.0, sigma_px, (len(pose), 2))
    return stops, obs.subset(np.all((obs.uv > 0) & (obs.uv < [640, 480]), axis=1))
