#!/usr/bin/env python3
"""Benchmark of issue 24 "Lean on the robot's computer": start-up, memory, one process for the suite.

Every row is measured in one run with its baseline, in a fresh numba cache directory (``NUMBA_CACHE_DIR`` = a new
temporary directory: nothing compiled, no ahead-of-time module), on the 7-DOF arm (config/arm7*):

``startup_cold``
    ``kinematics_node`` started with nothing compiled (a fresh install that skipped ``ppoe warmup``): seconds from
    the process start to the first ``/ppoe/pose`` received here (joint states are published at 200 Hz from before
    the start); includes Python, rclpy, the model and compiling the node's kernels.  The node's log lines that
    say what it compiles and why are counted (``startup_cold_compile_log_lines``).  Target <= 20 s.
``warmup``
    ``ppoe warmup`` (the README's set-up command runs it) into that cache: every node's kernels and the kinematics
    node's ahead-of-time module; a set-up cost, printed for the record.
``startup``
    ``kinematics_node`` after ``ppoe warmup`` (ahead-of-time kernels), and ``startup_jit`` (numba's cache only,
    ``PPOE_AOT=0``); baseline: ``startup_relay_floor``, a bare rclpy relay (Python + rclpy + one publisher,
    ``bench_nodes.relay``) started the same way.  Target <= 5 s.
``rss``
    Resident memory (``VmRSS``) of the kinematics node after ``--seconds`` at 1 kHz (steady: the last sample,
    and the largest), ahead-of-time and numba; baseline: the bare relay under the same feed.  Target <= 150 MB.
``container``
    All four nodes in ONE process (``ppoe_container``) against the same four as separate processes (baseline, same
    run), under the same feed (joint states 1 kHz, 640x480 PNG images with two tags and camera_info at 30 Hz,
    wrenches at 100 Hz) for ``--seconds``: total RSS.  Target <= 350 MB.

Each row prints ``name: value unit``, then ``row: <what> = <value> (baseline <value>) target <t>: met|MISSED``.
The load average is printed: on a shared machine start-up times grow with it.

Usage::

    python bench/bench_lean.py [--seconds 15] [--skip-cold]
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

URDF = REPO / "config" / "robots" / "arm7.urdf"
MODEL = REPO / "config" / "robots" / "arm7_model.yaml"
IMAGE_BAG = REPO / "bags" / "effect_camera_extrinsics"  # arm7, 640x480 PNG images of tags 10/11
NODES = ("kinematics_node", "fusion_node", "tag_bearing_node", "contact_node")

__all__ = ["main", "first_output", "node_params"]


def _env(domain: int, cache: Path, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1",
               NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""), **extra)
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def node_params(tmp: Path) -> dict[str, Path]:
    """A parameter file per node (arm7, its camera and tags; a contact plane for the contact node)."""
    import yaml

    urdf = URDF.read_text()
    per_node: dict[str, dict[str, Any]] = {
        "kinematics_node": {"robot_description": urdf, "model_file": str(MODEL), "qos_depth": 1000},
        "fusion_node": {"robot_description": urdf, "model_file": str(MODEL)},
        "tag_bearing_node": {"model_file": str(MODEL)},
        "contact_node": {"plane_frame": "base_link", "plane_xyz": [0.0, 0.0, 0.0], "plane_rpy": [0.0, 0.0, 0.0],
                         "plane_sigma": [0.001, 0.001, 0.001, 0.01, 0.01, 0.01], "force_threshold": 5.0},
    }
    out = {}
    for name, params in per_node.items():
        out[name] = tmp / f"{name}.yaml"
        out[name].write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    return out


def _node_cmd(name: str, params: Path) -> list[str]:
    return [sys.executable, "-m", f"ppoe_ros.nodes.{name}", "--ros-args", "--params-file",
            str(REPO / "config" / "nodes" / f"{name}.yaml"), "--params-file", str(params)]


def _relay_cmd() -> list[str]:
    return [sys.executable, str(REPO / "bench" / "bench_nodes.py"), "--role", "relay"]


def _stop(proc: subprocess.Popen | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def first_output(cmd: list[str], env: dict[str, str], domain: int, timeout: float = 300.0) -> tuple[float, str]:
    """Seconds from starting ``cmd`` to the first ``/ppoe/pose`` received here (joint states at 200 Hz published
    from before the start), and the process's output."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import ns_to_stamp

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("bench_lean_probe", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    got: list[float] = []
    node.create_subscription(PoseWithCovarianceStamped, "/ppoe/pose",
                             lambda raw: got.append(time.monotonic()) if not got else None, 10, raw=True)
    pub = node.create_publisher(JointState, "/joint_states", 100)
    names = [f"joint_{i}" for i in range(1, 8)] + ["finger_left_joint"]
    msg = JointState(name=names, position=[0.1] * len(names))

    def tick() -> None:
        msg.header.stamp = ns_to_stamp(time.time_ns())
        pub.publish(msg)

    node.create_timer(0.005, tick)
    log = tempfile.TemporaryFile()
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, env=env, cwd=REPO, start_new_session=True, stdout=log, stderr=subprocess.STDOUT)
    try:
        while not got and proc.poll() is None and time.monotonic() - t0 < timeout:
            ex.spin_once(timeout_sec=0.01)
    finally:
        _stop(proc)
        node.destroy_node()
        ctx.try_shutdown()
    log.seek(0)
    out = log.read().decode(errors="replace")
    return (got[0] - t0 if got else float("nan")), out


def feed_all(seconds: float) -> int:
    """Feeder process: joint states at 1 kHz, the image bag's PNG images and camera_info at 30 Hz (cycled), wrenches
    at 100 Hz (a contact every other second); prints the count of joint states sent."""
    import numpy as np
    import rclpy
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import qos_profile_sensor_data
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import CameraInfo, CompressedImage, JointState

    from ppoe_ros.common import ns_to_stamp

    images: list[bytes] = []
    info: bytes = b""
    with Reader(IMAGE_BAG) as reader:
        conns = [c for c in reader.connections if c.topic in ("/camera/image_raw/compressed", "/camera/camera_info")]
        for conn, _, raw in reader.messages(connections=conns):
            if conn.topic == "/camera/camera_info":
                info = bytes(raw)
            else:
                images.append(bytes(raw))
    rclpy.init()
    node = rclpy.create_node("bench_lean_feeder")
    js_pub = node.create_publisher(JointState, "/joint_states", 1000)
    img_pub = node.create_publisher(CompressedImage, "/camera/image_raw/compressed", qos_profile_sensor_data)
    info_pub = node.create_publisher(CameraInfo, "/camera/camera_info", qos_profile_sensor_data)
    w_pub = node.create_publisher(WrenchStamped, "/wrench", qos_profile_sensor_data)
    time.sleep(2.0)
    names = [f"joint_{i}" for i in range(1, 8)] + ["finger_left_joint"]
    msg = JointState(name=names)
    wrench = WrenchStamped()
    wrench.header.frame_id = "tool0"
    phases = np.linspace(0.0, 1.0, len(names))
    n = int(seconds * 1000)
    t0 = time.monotonic()
    for k in range(n):
        target = t0 + k / 1000.0
        now = time.monotonic()
        if target > now:
            time.sleep(target - now)
        stamp_ns = time.time_ns()
        msg.position = (0.8 * np.sin(0.5 * k / 1000.0 + phases)).tolist()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        js_pub.publish(msg)
        if k % 33 == 0:  # 30 Hz: the stamp of the serialised messages is rewritten to now
            stamp = ns_to_stamp(stamp_ns)
            head = stamp.sec.to_bytes(4, "little", signed=True) + stamp.nanosec.to_bytes(4, "little")
            img = images[(k // 33) % len(images)]
            info_pub.publish(info[:4] + head + info[12:])
            img_pub.publish(img[:4] + head + img[12:])
        if k % 10 == 0:
            wrench.header.stamp = ns_to_stamp(stamp_ns)
            wrench.wrench.force.z = 20.0 if (k // 1000) % 2 else 0.0
            w_pub.publish(wrench)
    print(f"sent {n}", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def rss_under_feed(procs: list[tuple[list[str], dict[str, str]]], env: dict[str, str], seconds: float,
                   feeder: str = "all") -> tuple[float, float, list[str]]:
    """Start ``procs``, feed them ``seconds`` (plus 5 s to settle), sample their total RSS every second: (last,
    max, outputs)."""
    logs = [tempfile.TemporaryFile() for _ in procs]
    running = [subprocess.Popen(cmd, env=e, cwd=REPO, start_new_session=True, stdout=log, stderr=subprocess.STDOUT)
               for (cmd, e), log in zip(procs, logs)]
    feed = None
    samples: list[float] = []
    try:
        time.sleep(3.0)
        role = ["--role", "feed_all", "--seconds", str(seconds + 5)] if feeder == "all" else None
        feed_cmd = [sys.executable, __file__, *role] if role else [
            sys.executable, str(REPO / "bench" / "bench_nodes.py"), "--role", "feed", "--rate", "1000",
            "--seconds", str(seconds + 5)]
        feed = subprocess.Popen(feed_cmd, env=env, cwd=REPO, start_new_session=True, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        time.sleep(7.0)  # the feeder starts, the nodes settle
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            samples.append(sum(_rss_mb(p.pid) for p in running if p.poll() is None))
            time.sleep(1.0)
        dead = [p.args for p in running if p.poll() is not None]
    finally:
        _stop(feed)
        for p in running:
            _stop(p)
    outs = []
    for log in logs:
        log.seek(0)
        outs.append(log.read().decode(errors="replace"))
    if dead:
        raise RuntimeError(f"a process died during the feed: {dead}\n" + "\n".join(o[-2000:] for o in outs))
    return samples[-1], max(samples), outs


def _row(what: str, value: float, unit: str, baseline: str, target: float, better: str = "lower") -> None:
    met = value <= target if better == "lower" else value >= target
    print(f"row: {what} = {value:.2f} {unit} ({baseline}) target {'<=' if better == 'lower' else '>='} "
          f"{target:g} {unit}: {'met' if met else 'MISSED'}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=15.0, help="steady-state window of the RSS rows (default 15)")
    ap.add_argument("--skip-cold", action="store_true", help="skip the cold start (minutes on a busy machine)")
    ap.add_argument("--role", choices=["feed_all"], help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "feed_all":
        return feed_all(args.seconds)
    print(f"bench_lean.load_avg_1min: {os.getloadavg()[0]:.2f} -", flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench_lean_"))
    cache = tmp / "numba_cache"
    cache.mkdir()
    params = node_params(tmp)
    rnd = random.SystemRandom()
    try:
        kin = _node_cmd("kinematics_node", params["kinematics_node"])
        if not args.skip_cold:
            d = rnd.randint(1, 200)
            t_cold, out = first_output(kin, _env(d, cache), d, timeout=900.0)
            lines = [ln for ln in out.splitlines() if "compiling" in ln]
            print(f"startup_cold_first_pose: {t_cold:.2f} s")
            print(f"startup_cold_compile_log_lines: {len(lines)} count")
            for ln in lines[:3]:
                print(f"startup_cold_log: {ln[:200]}")
            _row("first start, nothing compiled (cold), to first pose", t_cold, "s",
                 f"{len(lines)} log lines name what is compiled", 20.0)
        t0 = time.monotonic()
        w = subprocess.run([sys.executable, "-m", "ppoe_ros.cli", "warmup"], env=_env(rnd.randint(1, 200), cache),
                           cwd=REPO, capture_output=True, text=True, check=False)
        print(f"warmup_time: {time.monotonic() - t0:.1f} s")
        for ln in (w.stdout + w.stderr).splitlines():
            print(f"warmup_log: {ln[:200]}")
        d = rnd.randint(1, 200)
        t_relay, _ = first_output(_relay_cmd(), _env(d, cache), d)
        d = rnd.randint(1, 200)
        t_aot, out_aot = first_output(kin, _env(d, cache), d)
        d = rnd.randint(1, 200)
        t_jit, _ = first_output(kin, _env(d, cache, PPOE_AOT="0"), d)
        print(f"startup_relay_floor_first_output: {t_relay:.2f} s")
        print(f"startup_first_pose: {t_aot:.2f} s")
        print(f"startup_jit_first_pose: {t_jit:.2f} s")
        print(f"startup_kernels: {next((ln for ln in out_aot.splitlines() if 'compiled kernels' in ln), '?')[:200]}")
        _row("first start after ppoe warmup, to first pose", t_aot, "s",
             f"relay floor {t_relay:.2f} s; numba cache only {t_jit:.2f} s", 5.0)
        d = rnd.randint(1, 200)
        env = _env(d, cache)
        relay_rss, relay_max, _ = rss_under_feed([(_relay_cmd(), env)], env, args.seconds, feeder="joints")
        aot_rss, aot_max, _ = rss_under_feed([(kin, env)], env, args.seconds, feeder="joints")
        env_jit = _env(d, cache, PPOE_AOT="0")
        jit_rss, jit_max, _ = rss_under_feed([(kin, env_jit)], env_jit, args.seconds, feeder="joints")
        print(f"rss_relay_floor: {relay_rss:.1f} MB (max {relay_max:.1f})")
        print(f"rss_kinematics_node: {aot_rss:.1f} MB (max {aot_max:.1f})")
        print(f"rss_kinematics_node_jit: {jit_rss:.1f} MB (max {jit_max:.1f})")
        _row("kinematics node RSS, steady at 1 kHz", aot_rss, "MB",
             f"relay floor {relay_rss:.1f} MB; numba kernels {jit_rss:.1f} MB", 150.0)
        d = rnd.randint(1, 200)
        env = _env(d, cache)
        sep_rss, sep_max, _ = rss_under_feed([(_node_cmd(n, params[n]), env) for n in NODES], env, args.seconds)
        spec = [f"{n}:{REPO / 'config' / 'nodes' / (n + '.yaml')},{params[n]}" for n in NODES]
        cont_rss, cont_max, outs = rss_under_feed(
            [([sys.executable, "-m", "ppoe_ros.nodes.container", *spec], env)], env, args.seconds)
        print(f"rss_four_processes: {sep_rss:.1f} MB (max {sep_max:.1f})")
        print(f"rss_container: {cont_rss:.1f} MB (max {cont_max:.1f})")
        _row("all four nodes in one process, total RSS", cont_rss, "MB",
             f"four processes {sep_rss:.1f} MB", 350.0)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
