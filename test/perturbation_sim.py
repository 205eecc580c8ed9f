"""A simulated robot of the perturbation tests (``test_perturbations*.py``, ``bench/study_perturbations.py``):
a 5-joint arm whose true PPOE perturbations differ per joint and per axis class, measured as 6D tool poses or
tracker points; the perturbations are drawn per stop on the nonlinear chain (``KinematicTree.link_poses`` with
``dxi``), not from the first-order model the estimator fits."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.perturbations import axis_projectors
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot, parse_urdf

ARM5_URDF = """<?xml version="1.0"?>
<robot name="soft5">
  <link name="base_link"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="l4"/><link name="l5"/>
  <link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base_link"/><child link="l1"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.25"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.45 0 0"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j4" type="revolute"><parent link="l3"/><child link="l4"/>
    <origin xyz="0.4 0 0"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j5" type="revolute"><parent link="l4"/><child link="l5"/>
    <origin xyz="0.12 0 0" rpy="0 0 0.3"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="l5"/><child link="tool"/><origin xyz="0.1 0.02 0.05"/></joint>
</robot>
"""

#: declared (the user's) 1-sigma per axis class: rotation about / perpendicular to the axis [rad], translation [m]
DECLARED = {j: {"axial": 1e-3, "lateral": 1e-3, "translation": 2e-4} for j in ("j1", "j2", "j3", "j4", "j5")}
#: the truth: j2 five times softer perpendicular to its axis, j3 three times softer about it
TRUTH = {j: dict(v) for j, v in DECLARED.items()}
TRUTH["j2"]["lateral"] = 5e-3
TRUTH["j3"]["axial"] = 3e-3


def soft5() -> Robot:
    return parse_urdf(ARM5_URDF)


def sigma_matrices(robot: Robot, classes: Mapping[str, Mapping[str, float]]) -> dict[str, np.ndarray]:
    """joint -> 6x6 ``Sigma_j`` from 1-sigmas per axis class."""
    out = {}
    for j, per in classes.items():
        P = axis_projectors(robot.joints[j].axis)
        out[j] = sum(s ** 2 * P[c] for c, s in per.items())
    return out


def simulate_poses(robot: Robot, truth: Mapping[str, np.ndarray], n: int, seed: int, sigma_p: float = 1e-4,
                   sigma_r: float = 2e-4, kind: str = "pose") -> Stops:
    """``n`` random stops with per-stop perturbations ``xi_j ~ N(0, truth[j])`` on the nonlinear chain and sensor
    noise (``pose``: position ``sigma_p`` [m] + rotation ``sigma_r`` [rad]; ``point``: tracker point on ``tool``,
    one session, identity registration)."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(robot)
    q = {j: rng.uniform(-1.5, 1.5, n) for j in tree.joint_names}
    xi = {j: rng.multivariate_normal(np.zeros(6), C, n) for j, C in truth.items()}
    T = tree.link_poses(q, dxi=xi)["tool"]
    p = T[:, :3, 3] + rng.normal(0.0, sigma_p, (n, 3))
    R = T[:, :3, :3] @ lie.exp(np.concatenate([np.zeros((n, 3)), rng.normal(0.0, sigma_r, (n, 3))], 1))[:, :3, :3]
    zeros = np.zeros(n, int)
    return Stops(q=q, p_meas=p, kind=kind, link="tool", point=np.zeros(3), sigma=sigma_p, session=zeros,
                 session_names=["s0"], group=zeros, group_names=["sim"], reg_mask=np.ones(n, bool),
                 score_mask=np.ones(n, bool), context={"time": np.arange(n) * 1.0},
                 R_meas=R if kind == "pose" else None, sigma_rot=sigma_r, base=robot.root)
