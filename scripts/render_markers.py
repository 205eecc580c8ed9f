"""Render what RViz shows of ``ppoe/markers`` offline: the nodes run on a bag, the published MarkerArray is drawn.

Runs kinematics_node, tag_bearing_node, fusion_node and ppoe_markers (isolated DDS domain) on a bag played with
``ppoe play --clock``, records ``/ppoe/markers`` with ``ppoe record``, takes the recorded array whose correction
arrow is longest, and draws with matplotlib exactly what the message says: each ``SPHERE`` as the ellipsoid of
its pose (quaternion -> axes) and scale (full axis lengths), the ``ARROW`` between its two points, and the robot
(links of the bag's URDF at the joint state of the array's stamp) for orientation.  Usage::

    python scripts/render_markers.py --bag bags/table1_exp1 --model config/robots/rover_model.yaml \\
        --out docs/img/rviz_markers.png
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO))

LAG_TOLERANT = {"buffer_duration": 20.0, "qos_depth": 5000, "pending_timeout": 5.0}


def record_markers(bag: Path, model: str, work: Path, rate: float) -> Path:
    """Play ``bag`` through the nodes and record ``/ppoe/markers``; the recorded bag."""
    from ros_helpers import NodeProcess, ros_env

    env = ros_env(work)
    nodes = [("kinematics_node", {"model_file": model, "qos_depth": 5000}),
             ("tag_bearing_node", {"model_file": model, "qos_depth": 50}),
             ("fusion_node", {"model_file": model, **LAG_TOLERANT})]
    procs = [NodeProcess.node(m, env, work, params={"use_sim_time": True, **p}) for m, p in nodes]
    procs.append(NodeProcess([sys.executable, "-m", "ppoe_ros.common.markers", "--ros-args", "-p",
                              "use_sim_time:=true", "-p", "marker_rate:=10.0"], env, work / "markers.log"))
    out = work / "recorded"
    rec = NodeProcess.ppoe(["record", "--out", str(out), "/ppoe/markers"], env, work, "record")
    procs.append(rec)
    try:
        deadline = time.monotonic() + 90
        while "recording /ppoe/markers " not in rec.output():
            if time.monotonic() > deadline:
                raise RuntimeError("the recorder saw no /ppoe/markers publisher:\n" + rec.output()[-2000:])
            time.sleep(0.2)
        play = NodeProcess.ppoe(["play", str(bag), "--clock", "--rate", str(rate), "--wait-for-subscribers", "60",
                                 "--topics", "/robot_description", "/joint_states", "/camera/camera_info",
                                 "/camera/image_raw/compressed"], env, work, "play")
        procs.append(play)
        if play.wait(timeout=600) != 0:
            raise RuntimeError(play.output()[-3000:])
        time.sleep(5.0)  # the fusion node finishes what it buffered
        rec.stop(timeout=10)
    finally:
        for p in procs:
            p.stop()
    return out


def pick_array(recorded: Path) -> Any:
    """The recorded MarkerArray (rosbags message) with the longest correction arrow."""
    from ppoe_core.io.bagio import deserialize, iter_raw

    best, best_len = None, -1.0
    for raw in iter_raw(recorded, ["/ppoe/markers"]):
        msg = deserialize(raw.data, raw.msgtype, topic=raw.topic)
        for m in msg.markers:
            if m.ns == "correction" and len(m.points) == 2:
                a, b = m.points
                length = float(np.linalg.norm([b.x - a.x, b.y - a.y, b.z - a.z]))
                if length > best_len:
                    best, best_len = msg, length
    if best is None:
        raise RuntimeError(f"{recorded}: no MarkerArray with a fused pose")
    return best


def sphere_surface(m: Any, n: int = 28) -> np.ndarray:
    """(n, n, 3) surface of a SPHERE marker: its pose's rotation and position, half its scale as radii."""
    from ppoe_core import lie
    from ppoe_core.lie.ellipsoid import Ellipsoid, ellipsoid_surface

    q = np.array([m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w])
    c = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
    radii = 0.5 * np.array([m.scale.x, m.scale.y, m.scale.z])
    return ellipsoid_surface(Ellipsoid(c, lie.matrix_from_quat(q), radii, q), n)


def robot_lines(bag: Path, stamp_ns: int) -> list[np.ndarray]:
    """Parent-child link origin segments of the bag's robot at the joint state nearest ``stamp_ns``."""
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_core.robot.urdf import parse_urdf

    data = read_bag(bag, topics=["/robot_description", "/joint_states"], load_images=False)
    robot = parse_urdf(data.robot_description, text_source=f"bag {bag}")
    js = data.joint_states
    k = int(np.argmin(np.abs(np.asarray(js.stamps) - stamp_ns * 1e-9)))
    q = {n: float(js.positions[k, i]) for i, n in enumerate(js.names) if n in robot.joints}
    poses = KinematicTree(robot).link_poses(q)
    return [np.array([poses[j.parent][:3, 3], poses[j.child][:3, 3]]) for j in robot.joints.values()
            if j.parent in poses and j.child in poses]


def draw(msg: Any, lines: list[np.ndarray], out: Path) -> None:
    """The robot and the markers: a whole view and a close-up of the tool (equal axes, metres)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spheres = {m.ns: m for m in msg.markers if m.type == 2}
    arrow = next((m for m in msg.markers if m.type == 0), None)
    fig = plt.figure(figsize=(12, 5.6))
    centre = np.array([spheres["raw"].pose.position.x, spheres["raw"].pose.position.y, spheres["raw"].pose.position.z])
    for i, (title, half) in enumerate((("robot and markers", None), ("close-up of the tool", 0.04))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        if half is None:  # the robot for orientation (its segments would run out of the close-up's box)
            for seg in lines:
                ax.plot(*seg.T, color="0.35", lw=2)
        for ns in ("raw", "fused"):
            m = spheres[ns]
            s = sphere_surface(m)
            rgba = (m.color.r, m.color.g, m.color.b)
            ax.plot_surface(s[..., 0], s[..., 1], s[..., 2], color=rgba, alpha=0.2 if ns == "raw" else 0.7,
                            linewidth=0)
            ax.plot_wireframe(s[..., 0], s[..., 1], s[..., 2], color=rgba, lw=0.3, rstride=4, cstride=4,
                              label=f"{ns}: {1e3 * m.scale.x:.1f} x {1e3 * m.scale.y:.1f} x {1e3 * m.scale.z:.1f} mm")
        if arrow is not None:
            a, b = (np.array([p.x, p.y, p.z]) for p in arrow.points)
            ax.plot(*np.array([a, b]).T, color="k", lw=1.5, label=f"correction {1e3 * np.linalg.norm(b - a):.1f} mm")
        if half is None:
            pts = np.concatenate(lines)
            mid, half_all = 0.5 * (pts.max(0) + pts.min(0)), 0.5 * float(np.max(pts.max(0) - pts.min(0)))
            for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid):
                setter(c - half_all, c + half_all)
        else:
            for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
                setter(c - half, c + half)
            ax.legend(fontsize=7, loc="upper left")
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.set_title(f"{title} ({msg.markers[0].header.frame_id})", fontsize=9)
    fig.suptitle("/ppoe/markers as published (ppoe_markers), drawn offline: position ellipsoids at "
                 "marker_probability 0.95", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", default=str(REPO / "bags" / "table1_exp1"))
    parser.add_argument("--model", default=str(REPO / "config" / "robots" / "rover_model.yaml"))
    parser.add_argument("--out", default=str(REPO / "docs" / "img" / "rviz_markers.png"))
    parser.add_argument("--rate", type=float, default=1.0, help="playback rate")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        recorded = record_markers(Path(args.bag), args.model, Path(tmp), args.rate)
        msg = pick_array(recorded)
    stamp = msg.markers[0].header.stamp
    draw(msg, robot_lines(Path(args.bag), stamp.sec * 10**9 + stamp.nanosec), Path(args.out))
    print(f"wrote {args.out} (array at {stamp.sec}.{stamp.nanosec:09d} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
