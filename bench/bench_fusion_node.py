#!/usr/bin/env python3
"""Benchmark: the fusion node as a process at 1 kHz priors + 1 kHz joint states + 30 Hz two-tag observations.

The 7-DOF arm (config/arm7*) moves slowly around a configuration in which both gripper tags (10, 11) face the
camera.  A feeder process publishes, stamped with the wall clock at publication:

* ``/ppoe/pose`` at 1 kHz: the PPOE prior of each configuration (as the kinematics node publishes it);
* ``/joint_states`` at 1 kHz (the fusion node keeps them for its corrections);
* ``/tag_bearing/observations`` at 30 Hz (every 33rd prior): centre and corners of both tags projected through the
  camera (``camera_info`` of ``bags/effect_camera_extrinsics``, also published), stamped as the prior of the same
  configuration, as the tag bearing node would publish them (two tags, 10 rows).  arm7's two tags sit on opposite
  faces of the gripper (one in view at a time), so this benchmark's model (:func:`bench_model`) puts tag 11 beside
  tag 10 on the +x face;

and this process receives ``/ppoe/fused_pose``.  Measured over ``--seconds`` after ``--warmup``:

* CPU share of the fusion node process (1.0 = one core);
* latency of the fused output that carries an image's update: the node publishes the latest estimate again when a
  measurement is accepted (``publish_on_update``), so the first fused pose whose stamp repeats the previous one
  after an observation is that output; latency = its receipt here minus the observation's publication
  (median, p99, max; ``update_outputs`` counts them);
* latency of the per-prior output (receipt minus the prior's stamp).

Baselines in the same run: ``relay`` (``bench_nodes.relay``: a bare rclpy relay on the events executor, raw bytes
in and out, one output per prior: the floor of any node at 1 kHz), and ``classic`` (the fusion node on rclpy's
``SingleThreadedExecutor``, ``PPOE_EXECUTOR=single``: how it ran before).  Targets (issue 24): <= 0.35 cores,
fused output p99 <= 5 ms after the image.

Usage::

    python bench/bench_fusion_node.py [--seconds 20] [--warmup 5] [--modes relay,classic,node]
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

URDF = REPO / "config" / "robots" / "arm7.urdf"
MODEL = REPO / "config" / "robots" / "arm7_model.yaml"
CAMERA_BAG = REPO / "bags" / "effect_camera_extrinsics"
ARM = [f"joint_{i}" for i in range(1, 8)] + ["finger_left_joint"]
#: image period in priors (1 kHz / 33 = 30.3 Hz)
IMAGE_EVERY = 33

__all__ = ["main", "trajectory", "observation_rows"]


def bench_model(directory: Path) -> Path:
    """arm7's model YAML with tag 11 moved beside tag 10 (both on the gripper's +x face: two tags in view)."""
    text = MODEL.read_text()
    old = "- {id: 11, link: gripper_link, size: 0.04, xyz: [-0.041, 0.0, 0.03], rpy: [0.0, -1.57079633, 0.0]}"
    new = "- {id: 11, link: gripper_link, size: 0.04, xyz: [0.041, 0.0, 0.08], rpy: [0.0, 1.57079633, 0.0]}"
    if old not in text:
        raise RuntimeError(f"{MODEL}: tag 11 line changed; update bench_fusion_node.bench_model")
    out = directory / "arm7_two_tags_model.yaml"
    out.write_text(text.replace(old, new))
    return out


def _env(domain: int, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1",
               PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""), **extra)
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def _camera() -> tuple[bytes, np.ndarray, np.ndarray]:
    """The bag's serialised camera_info and its K (3, 3), D (5,)."""
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import CameraInfo

    with Reader(CAMERA_BAG) as reader:
        conn = next(c for c in reader.connections if c.topic == "/camera/camera_info")
        raw = bytes(next(iter(reader.messages(connections=[conn])))[2])
    info = deserialize_message(raw, CameraInfo)
    return raw, np.array(info.k, dtype=float).reshape(3, 3), np.array(info.d, dtype=float)


def _visible_start(model: Any, K: np.ndarray, D: np.ndarray) -> dict[str, float]:
    """The bag's stop (its joint state at an image) in which both tags are in the image, farthest from its edges."""
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import JointState

    image_times = []
    with Reader(CAMERA_BAG) as reader:
        conns = [c for c in reader.connections if c.topic in ("/joint_states", "/camera/image_raw/compressed")]
        last: dict[str, float] = {}
        for conn, _, raw in reader.messages(connections=conns):
            if conn.topic == "/joint_states":
                msg = deserialize_message(bytes(raw), JointState)
                last.update(zip(msg.name, msg.position))
            elif last:
                image_times.append(dict(last))
    best, margin = None, 0.0
    for q in image_times:
        rows = observation_rows(model, q, K, D)
        if len(rows) == 10:
            m = float(min(rows[:, 2].min(), rows[:, 3].min(), 639 - rows[:, 2].max(), 479 - rows[:, 3].max()))
            if m > margin:
                best, margin = q, m
    if best is None:
        raise RuntimeError("no stop of the camera bag shows both tags")
    return best


def observation_rows(model: Any, q: dict[str, float], K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Rows ``[id, corner, u, v, x, y]`` of the tags fully in the 640x480 image at ``q`` (tag bearing node's
    format), projected with the model's mean FK."""
    from ppoe_core import lie
    from ppoe_core.estimation.camera import project_points
    from ppoe_core.estimation.measurements import tag_points

    cam = model.config.camera.frame if getattr(model.config, "camera", None) is not None else "camera_optical_frame"
    T_base_cam = model.fk_mean(q, "base_link", cam)
    rows = []
    for item in model.config.tags.items:
        T_cam_link = lie.inverse(T_base_cam) @ model.fk_mean(q, "base_link", item.link)
        p = tag_points(item.size, T_cam_link @ item.T_link_tag)
        if np.any(p[:, 2] <= 0.05):
            continue
        normal = (T_cam_link @ item.T_link_tag)[:3, 2]
        if normal @ p[0] >= 0:  # facing away from the camera
            continue
        uv = project_points(p, K, D)
        if np.any(uv < 0) or np.any(uv[:, 0] > 639) or np.any(uv[:, 1] > 479):
            continue
        for corner in range(5):
            rows.append([item.id, corner, uv[corner, 0], uv[corner, 1], p[corner, 0] / p[corner, 2],
                         p[corner, 1] / p[corner, 2]])
    return np.array(rows, dtype=float).reshape(-1, 6)


def trajectory(q0: dict[str, float], n: int) -> list[dict[str, float]]:
    """``n`` configurations at 1 kHz: +-0.02 rad sinusoids about ``q0`` (both tags stay in view)."""
    ph = np.linspace(0.0, 1.0, len(ARM))
    return [{name: q0.get(name, 0.0) + (0.02 * np.sin(0.5 * k / 1000.0 + ph[i]) if i < 7 else 0.0)
             for i, name in enumerate(ARM)} for k in range(n)]


def feed(seconds: float) -> int:
    """Feeder process (module docstring); prints ``sent PRIORS OBSERVATIONS WALL LATE`` and each observation's
    publication time (ns) on one line."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CameraInfo, JointState, PointCloud2
    from std_msgs.msg import Header

    from ppoe_core import lie
    from ppoe_core.io.cdr import PoseCovarianceWriter
    from ppoe_core.model.ppoe import PPOEModel
    from ppoe_ros.common import reliable_qos, sensor_qos
    from ppoe_ros.common.tag_cloud import cloud_from_observations

    model = PPOEModel.from_files(URDF, Path(os.environ["BENCH_MODEL"]))
    info, K, D = _camera()
    q0 = _visible_start(model, K, D)
    n = int(round(seconds * 1000))
    traj = trajectory(q0, n)
    writer = PoseCovarianceWriter("base_link")
    poses, joints, clouds = [], [], {}
    for k, q in enumerate(traj):
        T, cov = model.fk(q, "base_link", "tool0")
        poses.append((T[:3, 3].copy(), lie.quat_from_matrix(T[:3, :3]), lie.cov_local_to_ros(T, cov)))
        joints.append(serialize_message(JointState(name=ARM, position=[q[a] for a in ARM])))
        if k % IMAGE_EVERY == 0:
            clouds[k] = serialize_message(cloud_from_observations(observation_rows(model, q, K, D),
                                                                  Header(frame_id="camera_optical_frame")))
    rclpy.init()
    node = rclpy.create_node("bench_fusion_feeder")
    prior_pub = node.create_publisher(PoseWithCovarianceStamped, "/ppoe/pose", sensor_qos(1000))
    js_pub = node.create_publisher(JointState, "/joint_states", sensor_qos(1000))
    obs_pub = node.create_publisher(PointCloud2, "/tag_bearing/observations", reliable_qos(50))
    info_pub = node.create_publisher(CameraInfo, "/camera/camera_info", sensor_qos(10))
    end = time.monotonic() + 30
    while prior_pub.get_subscription_count() == 0 and time.monotonic() < end:
        time.sleep(0.05)
    time.sleep(0.5)
    sent_obs = []
    late = 0
    t0 = time.monotonic()
    for k in range(n):
        target = t0 + k / 1000.0
        now = time.monotonic()
        if target > now:
            time.sleep(target - now)
        elif now - target > 0.005:
            late += 1
        stamp_ns = time.time_ns()
        head = struct.pack("<iI", stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
        js = joints[k]
        js_pub.publish(js[:4] + head + js[12:])
        pos, quat, cov = poses[k]
        prior_pub.publish(writer.serialize(stamp_ns, pos, quat, cov))
        cloud = clouds.get(k)
        if cloud is not None:
            info_pub.publish(info[:4] + head + info[12:])
            sent_obs.append(time.time_ns())
            obs_pub.publish(cloud[:4] + head + cloud[12:])
    wall = time.monotonic() - t0
    print(f"sent {n} {len(sent_obs)} {wall:.6f} {late}", flush=True)
    print(" ".join(str(t) for t in sent_obs), flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_mode(mode: str, seconds: float, warmup: float) -> dict[str, float]:
    """One process in ``mode`` (relay, classic, node) fed for ``warmup + seconds``; the measured numbers."""
    import rclpy
    import yaml
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    domain = random.SystemRandom().randint(1, 200)
    tmp = Path(tempfile.mkdtemp(prefix="bench_fusion_node_"))
    model = bench_model(tmp)
    env = _env(domain, BENCH_MODEL=str(model), **({"PPOE_EXECUTOR": "single"} if mode == "classic" else {}))
    params = tmp / "fusion.yaml"
    params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {
        "robot_description": URDF.read_text(), "model_file": str(model), "qos_depth": 1000}}}))
    if mode == "relay":
        cmd = [sys.executable, str(REPO / "bench" / "bench_nodes.py"), "--role", "relay", "--in-topic", "/ppoe/pose",
               "--in-pose", "--out-topic", "/ppoe/fused_pose"]
    else:
        cmd = [sys.executable, "-m", "ppoe_ros.nodes.fusion_node", "--ros-args", "--params-file",
               str(REPO / "config" / "nodes" / "fusion_node.yaml"), "--params-file", str(params)]
    log_path = tmp / f"{mode}.log"  # a file, not a pipe nobody reads (a node's warnings would fill it and block it)
    log = open(log_path, "wb")
    proc = subprocess.Popen(cmd, env=env, cwd=REPO, start_new_session=True, stdout=log, stderr=subprocess.STDOUT)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("bench_fusion_receiver", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    window = [0, 2**63]
    prior_lat: list[int] = []
    updates: list[int] = []  # receipt times [ns] of outputs repeating the previous stamp (update outputs)
    last_stamp = [-1]
    n_out = [0]

    def on_fused(raw: bytes) -> None:
        now = time.time_ns()
        sec, nsec = struct.unpack_from("<iI", raw, 4)
        stamp = sec * 1_000_000_000 + nsec
        n_out[0] += 1
        if stamp == last_stamp[0]:
            updates.append(now)
        elif window[0] <= stamp <= window[1]:
            prior_lat.append(now - stamp)
        last_stamp[0] = stamp

    node.create_subscription(PoseWithCovarianceStamped, "/ppoe/fused_pose", on_fused, 5000, raw=True)
    counters: dict[str, str] = {}  # the node's last /diagnostics counters (accepted, rejected, pending, ...)

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            if "fusion_node" in st.name:
                counters.update({kv.key: kv.value for kv in st.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    feeder = None
    try:
        end = time.monotonic() + 60
        while node.count_publishers("/ppoe/fused_pose") == 0 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        feeder = subprocess.Popen([sys.executable, __file__, "--role", "feed", "--seconds", str(warmup + seconds)],
                                  env=env, cwd=REPO, start_new_session=True, stdout=subprocess.PIPE, text=True)
        while not n_out[0] and feeder.poll() is None:
            ex.spin_once(timeout_sec=0.05)
        t_end = time.monotonic() + warmup
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        window[0] = time.time_ns()
        cpu0, wall0 = _cpu_seconds(proc.pid), time.monotonic()
        while feeder.poll() is None and time.monotonic() < wall0 + seconds:
            ex.spin_once(timeout_sec=0.01)
        window[1] = time.time_ns()
        cpu1, wall1 = _cpu_seconds(proc.pid), time.monotonic()
        while feeder.poll() is None:
            ex.spin_once(timeout_sec=0.01)
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        lines = feeder.stdout.read().splitlines() if feeder.stdout else []
    finally:
        for p in (feeder, proc):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait(5)
        node.destroy_node()
        ctx.try_shutdown()
        log.close()
    node_log = log_path.read_text(errors="replace").splitlines()
    shutil.rmtree(tmp, ignore_errors=True)  # the model, parameter file and log of this mode
    for line in [ln for ln in node_log if "WARN" in ln or "ERROR" in ln][:5]:
        print(f"{mode}.log: {line[:300]}")
    keys = ("priors", "measurements", "accepted", "rejected", "throttled", "dropped_stale", "dropped_no_prior",
            "pending", "bad", "errors", "published")
    print(f"{mode}.node_counters: " + ", ".join(f"{k} {counters[k]}" for k in keys if k in counters) + " -")
    head = lines[0].split()
    obs_times = [int(t) for t in lines[1].split()] if len(lines) > 1 else []
    # each update output: the latest observation published before it
    upd_lat = []
    j = 0
    for t in updates:
        while j + 1 < len(obs_times) and obs_times[j + 1] <= t:
            j += 1
        if obs_times and obs_times[j] <= t and window[0] <= obs_times[j] <= window[1]:
            upd_lat.append(t - obs_times[j])
    upd = np.array(upd_lat) * 1e-6
    pri = np.array(prior_lat) * 1e-6
    return {"cpu_share": (cpu1 - cpu0) / (wall1 - wall0), "priors_sent": int(head[1]),
            "observations_sent": int(head[2]), "feeder_late": int(head[4]), "outputs": n_out[0],
            "update_outputs": len(upd),
            "update_latency_median": float(np.median(upd)) if len(upd) else float("nan"),
            "update_latency_p99": float(np.percentile(upd, 99)) if len(upd) else float("nan"),
            "update_latency_max": float(upd.max()) if len(upd) else float("nan"),
            "prior_latency_median": float(np.median(pri)) if len(pri) else float("nan"),
            "prior_latency_p99": float(np.percentile(pri, 99)) if len(pri) else float("nan"),
            **({"accepted": float(counters["accepted"])} if "accepted" in counters else {})}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--warmup", type=float, default=5.0)
    ap.add_argument("--modes", default="relay,classic,node")
    ap.add_argument("--role", choices=["feed"], help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "feed":
        return feed(args.seconds)
    print(f"bench_fusion_node.load_avg_1min: {os.getloadavg()[0]:.2f} -", flush=True)
    results = {}
    for mode in args.modes.split(","):
        r = results[mode] = run_mode(mode, args.seconds, args.warmup)
        for k, v in r.items():
            unit = "cores" if k == "cpu_share" else "ms" if "latency" in k else "count"
            print(f"{mode}.{k}: {v:.4g} {unit}", flush=True)
    if "node" in results:
        r = results["node"]
        floor = results.get("relay", {}).get("cpu_share", float("nan"))
        classic = results.get("classic", {}).get("cpu_share", float("nan"))
        met = r["cpu_share"] <= 0.35
        print(f"row: fusion node CPU at 1 kHz priors + 30 Hz two-tag images = {r['cpu_share']:.3f} cores (relay floor "
              f"{floor:.3f}, classic executor {classic:.3f}) target <= 0.35 cores: {'met' if met else 'MISSED'}")
        # the updates the node accepted (its counters; else the observations sent) inside the timed window: half of
        # them must be seen as update outputs to judge the latency
        expected = r.get("accepted", r["observations_sent"]) * args.seconds / (args.seconds + args.warmup)
        met = r["update_latency_p99"] <= 5.0 and r["update_outputs"] >= 0.5 * expected
        print(f"row: fused output after the image, p99 = {r['update_latency_p99']:.2f} ms (median "
              f"{r['update_latency_median']:.2f} ms, {r['update_outputs']} update outputs of about {expected:.0f} "
              f"accepted updates; classic executor "
              f"{results.get('classic', {}).get('update_latency_p99', float('nan')):.2f} ms) target <= 5 ms: "
              f"{'met' if met else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
