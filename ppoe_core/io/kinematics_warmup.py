"""The kinematics node's compiled path run once on a small robot: compiles (or loads from numba's cache) exactly the
kernel specialisations the node uses, and is what :func:`ppoe_core.aot.build` exports ahead of time.

The robot has what changes a kernel's argument types or code: a revolute joint about a tilted axis, a prismatic
joint, a mimic joint, perturbations given as sigmas and as a full covariance, joint noise; the node's steps are the
same calls as in :class:`ppoe_ros.nodes.kinematics_node.KinematicsNode`: the model YAML check, ``model.fk`` of one
configuration (orders 2 and 4), the ROS covariance and quaternion, the joint history's merge and the compiled
per-message path (:class:`ppoe_core.io.joint_pose.JointPoseFastPath`) of a learned name layout.
"""

from __future__ import annotations

import struct
from typing import Any, cast

import numpy as np

from ppoe_core import lie
from ppoe_core.io import cdr
from ppoe_core.io.cdr import PoseCovarianceWriter
from ppoe_core.io.joint_pose import JointPoseFastPath
from ppoe_core.model.joint_history import JointHistory
from ppoe_core.model.ppoe import PPOEModel

__all__ = ["WARM_URDF", "WARM_MODEL_YAML", "warm_kinematics"]

#: a small robot with every joint kind the chain programs distinguish
WARM_URDF = """<?xml version="1.0"?>
<robot name="warm_up">
  <link name="base_link"/>
  <link name="link1"/>
  <link name="link2"/>
  <link name="link3"/>
  <link name="tool0"/>
  <joint name="j1" type="revolute">
    <parent link="base_link"/><child link="link1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0.6 0.8"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="prismatic">
    <parent link="link1"/><child link="link2"/>
    <origin xyz="0.2 0 0" rpy="0.1 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="link2"/><child link="link3"/>
    <origin xyz="0 0.1 0" rpy="0 0 0.2"/><axis xyz="0 0 1"/>
    <mimic joint="j1" multiplier="0.5" offset="0.1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="tool" type="fixed">
    <parent link="link3"/><child link="tool0"/>
    <origin xyz="0.05 0 0" rpy="0 0 0"/>
  </joint>
</robot>
"""
#: its model: sigmas, a full covariance, joint noise, default frames
WARM_MODEL_YAML = """
perturbations:
  j1: {sigma: [0.001, 0.001, 0.002, 0.01, 0.01, 0.02]}
  j2: {covariance: [[1e-6, 0, 0, 0, 0, 0], [0, 1e-6, 0, 0, 0, 0], [0, 0, 1e-6, 0, 0, 0],
                    [0, 0, 0, 1e-4, 0, 0], [0, 0, 0, 0, 1e-4, 0], [0, 0, 0, 0, 0, 1e-4]]}
joint_noise:
  j1: 0.001
frames:
  base: base_link
  tool: tool0
"""


def _joint_state_cdr(stamp_ns: int, names: list[str], positions: list[float]) -> bytes:
    """A serialised ``sensor_msgs/JointState`` (CDR little endian) with empty velocity and effort."""
    out = bytearray(cdr.CDR_LE_HEADER)
    out += struct.pack("<iI", stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    frame = b"\x00"
    out += struct.pack("<I", len(frame)) + frame
    for seq in (names,):
        while (len(out) - 4) % 4:
            out += b"\x00"
        out += struct.pack("<I", len(seq))
        for n in seq:
            s = n.encode() + b"\x00"
            while (len(out) - 4) % 4:
                out += b"\x00"
            out += struct.pack("<I", len(s)) + s
    while (len(out) - 4) % 4:
        out += b"\x00"
    out += struct.pack("<I", len(positions))
    while (len(out) - 4) % 8:
        out += b"\x00"
    out += struct.pack(f"<{len(positions)}d", *positions)
    for _ in range(2):  # velocity, effort: empty
        out += struct.pack("<I", 0)
    return bytes(out)


def warm_kinematics(orders: tuple[int, ...] = (2, 4)) -> None:
    """Run the kinematics node's compiled path for each covariance order in ``orders`` (module docstring)."""
    model = PPOEModel.from_strings(WARM_URDF, WARM_MODEL_YAML)
    names = list(model.joint_names)
    for order in orders:
        T, cov = model.fk(np.zeros(len(names)), "base_link", "tool0", order=order)
        lie.cov_local_to_ros(T, cov)
        lie.quat_from_matrix(T[:3, :3])
        needed = list(model.chain_joints("base_link", "tool0"))
        history = JointHistory(needed, known=model.robot.joints)
        dst = np.array([names.index(n) for n in needed], dtype=np.intp)
        writer = PoseCovarianceWriter("base_link")
        lean = model.lean_program("base_link", "tool0")
        assert lean is not None
        fast = JointPoseFastPath(history, dst, len(names), [(lean, writer), (lean, PoseCovarianceWriter("b"))],
                                 order)
        fast.warm()
        for k in range(3):  # the Python path learns the layout, then the compiled one takes the message
            data = _joint_state_cdr(1_000_000_000 + k, needed, [0.1 * (k + 1)] * len(needed))
            if not fast.run(data):
                msg = cdr.parse_joint_state(data)
                upd = history.update(msg.names, cast(Any, msg.positions), msg.stamp_ns)  # as the node does
                if upd.values is not None:
                    q = np.zeros(len(names))
                    q[dst] = upd.values
                    model.fk(q, "base_link", "tool0", order=order)
                fast.learn(data, msg.names)
