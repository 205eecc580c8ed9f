#!/usr/bin/env python3
"""Benchmark: kinematics_node fed 1 kHz joint states of the 7-DOF arm (config/arm7*), beside a bare relay.

Each mode runs one node process (isolated DDS domain); a feeder process publishes ``/joint_states`` at ``--rate``
Hz for ``--warmup + --seconds`` seconds, stamped with the wall clock at publication; this process receives
``/ppoe/pose`` (raw) and measures, for the joint states stamped in the ``--seconds`` after the warm-up:

* latency = receipt time here minus the joint-state stamp: median, p99, max;
* CPU share of the node process over that window (user + system time / wall time, 1.0 = one core);
* messages sent / received and published by the node (its /diagnostics counters) / received here.

Modes:

``relay``
    The floor, measured in the same run: a bare rclpy relay on the same executor and path as the node
    (``EventsExecutor``, raw bytes in and out, sensor-data QoS in, reliable out): one fixed
    ``PoseWithCovarianceStamped`` (the input's stamp copied in) per joint state, no math.
``node``
    ``kinematics_node`` with its defaults (``config/nodes/kinematics_node.yaml``): FK in the callback.
``batched``
    ``max_batch: 100``, ``drain_max: 200`` (FK on a worker thread over what queued up), for comparison.

Summary lines: ``relay_floor_cpu_share``, ``relay_floor_latency_p99``, ``kinematics_node_cpu_share``,
``kinematics_node_latency_p99`` and their ratios (node over relay).  Targets (issue "fast enough"):
node <= 0.25 cores, p99 <= 2 ms, every message out, within about 1.5x of the relay.
``bench_nodes.load_avg_1min`` tells how busy the machine was.  ``fk_call`` is one ``PPOEModel.fk`` + ROS
covariance conversion in this process, for scale; ``callback_python`` / ``callback_compiled`` are the node's
subscription callback per message in this process (no DDS traffic: serialised joint states handed to it,
the median of alternating repetitions) with its Python path only / as shipped (one compiled call,
:mod:`ppoe_core.io.joint_pose`).

Usage::

    python bench/bench_nodes.py                 # 30 s per mode: relay, node
    python bench/bench_nodes.py --seconds 10 --modes relay,node,batched
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

URDF = REPO / "config" / "robots" / "arm7.urdf"
MODEL = REPO / "config" / "robots" / "arm7_model.yaml"
ARM = [f"joint_{i}" for i in range(1, 8)] + ["finger_left_joint"]

__all__ = ["feed", "relay", "run_mode", "fk_call_us", "callback_us", "main"]


def _env(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1",
               PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""))
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def feed(rate: float, seconds: float) -> int:
    """Feeder process: publish joint states at ``rate`` Hz, then print the count."""
    import rclpy
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import ns_to_stamp

    rclpy.init()
    node = rclpy.create_node("bench_feeder")
    pub = node.create_publisher(JointState, "/joint_states", 1000)
    end = time.monotonic() + 20
    while pub.get_subscription_count() == 0 and time.monotonic() < end:
        time.sleep(0.05)
    time.sleep(0.5)
    msg = JointState(name=ARM)
    n = int(round(rate * seconds))
    t0 = time.monotonic()
    phases = np.linspace(0.0, 1.0, len(ARM))
    late = 0
    for k in range(n):
        target = t0 + k / rate
        now = time.monotonic()
        if target > now:
            time.sleep(target - now)
        elif now - target > 0.005:
            late += 1
        t = k / rate
        msg.position = (0.8 * np.sin(0.5 * t + phases)).tolist()
        msg.header.stamp = ns_to_stamp(time.time_ns())
        pub.publish(msg)
    wall = time.monotonic() - t0
    print(f"sent {n} {wall:.6f} {late}", flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def relay(in_topic: str = "/joint_states", out_topic: str = "/ppoe/pose", in_pose: bool = False) -> int:
    """Relay process (the floor): raw joint states (``in_pose``: poses) in on ``in_topic``, one fixed raw pose (the
    input's stamp) out per message on ``out_topic``."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import reliable_qos, run_node, sensor_qos

    def factory() -> object:
        node = rclpy.create_node("bench_relay")
        pub = node.create_publisher(PoseWithCovarianceStamped, out_topic, reliable_qos(1000))
        template = bytearray(serialize_message(PoseWithCovarianceStamped()))

        def on_joint_state(raw: bytes) -> None:
            template[4:12] = raw[4:12]  # header.stamp
            pub.publish(bytes(template))

        node.create_subscription(PoseWithCovarianceStamped if in_pose else JointState, in_topic, on_joint_state,
                                 sensor_qos(1000), raw=True)
        return node

    return run_node(factory, [], executor="events")


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_mode(mode: str, rate: float, seconds: float, warmup: float) -> dict[str, float]:
    """One node process in ``mode``; returns the measured numbers."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    domain = random.SystemRandom().randint(1, 200)
    env = _env(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    params_file = Path(f"/tmp/bench_nodes_{os.getpid()}_{mode}.yaml")
    import yaml

    params: dict[str, object] = {"robot_description": URDF.read_text(), "model_file": str(MODEL), "qos_depth": 1000}
    if mode == "batched":
        params.update(max_batch=100, drain_max=200)
    params_file.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    cmd = [sys.executable, __file__, "--role", "relay"] if mode == "relay" else [
        sys.executable, "-m", "ppoe_ros.nodes.kinematics_node", "--ros-args", "--params-file", str(params_file)]
    node_proc = subprocess.Popen(cmd, env=env, cwd=REPO, start_new_session=True,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    feeder = None
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("bench_receiver", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    lat_ns: list[int] = []
    n_out = [0]
    diag: dict[str, int] = {}
    t_measure = [0, 2**63]  # stamps of the measurement window [ns]

    def on_pose(raw: bytes) -> None:
        # raw CDR (little endian): 4-byte encapsulation, then header.stamp (int32 sec, uint32 nanosec);
        # reading only the stamp keeps this receiver light, so its own lag stays out of the latency
        now = time.time_ns()
        sec, nsec = struct.unpack_from("<iI", raw, 4)
        stamp = sec * 1_000_000_000 + nsec
        n_out[0] += 1
        if t_measure[0] <= stamp <= t_measure[1]:
            lat_ns.append(now - stamp)

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == "/kinematics_node: health":
                diag.update({kv.key: int(kv.value) for kv in st.values if kv.value.isdigit()})

    def on_pose_burst(raw: bytes) -> None:
        # take what already waits too: one executor wake-up per burst keeps this receiver's
        # own backlog out of the latency (same trick as the node's drain_max)
        on_pose(raw)
        while True:
            with sub.handle:
                taken = sub.handle.take_message(PoseWithCovarianceStamped, True)
            if taken is None:
                return
            on_pose(taken[0])

    sub = node.create_subscription(PoseWithCovarianceStamped, "/ppoe/pose", on_pose_burst, 5000, raw=True)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    try:
        end = time.monotonic() + 30
        while node.count_publishers("/ppoe/pose") == 0 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        feeder = subprocess.Popen([sys.executable, __file__, "--role", "feed", "--rate", str(rate), "--seconds",
                                   str(warmup + seconds)], env=env, cwd=REPO, start_new_session=True,
                                  stdout=subprocess.PIPE, text=True)
        # wait for the first output, then the warm-up, then measure
        while not n_out[0] and feeder.poll() is None:
            ex.spin_once(timeout_sec=0.05)
        t_end_warm = time.monotonic() + warmup
        while time.monotonic() < t_end_warm:
            ex.spin_once(timeout_sec=0.01)
        t_measure[0] = time.time_ns()
        cpu0, wall0 = _cpu_seconds(node_proc.pid), time.monotonic()
        end_measure = wall0 + seconds
        while feeder.poll() is None and time.monotonic() < end_measure:
            ex.spin_once(timeout_sec=0.01)
        t_measure[1] = time.time_ns()
        cpu1, wall1 = _cpu_seconds(node_proc.pid), time.monotonic()
        while feeder.poll() is None:
            ex.spin_once(timeout_sec=0.01)
        # drain: until the node's counters settle (diagnostics every 1 s)
        last, still = None, 0
        while still < 3:
            t_next = time.monotonic() + 1.0
            while time.monotonic() < t_next:
                ex.spin_once(timeout_sec=0.01)
            cur = (diag.get("received"), diag.get("published"), n_out[0]) if mode != "relay" else n_out[0]
            still = still + 1 if cur == last else 0
            last = cur
        out = feeder.stdout.read().split()
        n_sent_total, feed_wall, late = int(out[1]), float(out[2]), int(out[3])
    finally:
        for p in (feeder, node_proc):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait(5)
        node.destroy_node()
        ctx.try_shutdown()
        params_file.unlink(missing_ok=True)
    lat_ms = np.array(lat_ns) * 1e-6
    measured_wall = wall1 - wall0
    return {
        "sent_total": n_sent_total, "feed_rate": n_sent_total / feed_wall, "feeder_late": late,
        "node_received": diag.get("received", 0), "node_published": diag.get("published", 0),
        "node_bad": diag.get("bad", 0), "node_dropped": diag.get("dropped", 0),
        "window": measured_wall, "out_received": n_out[0], "latency_samples": len(lat_ms),
        "lat_median": float(np.median(lat_ms)) if len(lat_ms) else float("nan"),
        "lat_p99": float(np.percentile(lat_ms, 99)) if len(lat_ms) else float("nan"),
        "lat_max": float(lat_ms.max()) if len(lat_ms) else float("nan"),
        "cpu_share": (cpu1 - cpu0) / measured_wall,
    }


def fk_call_us(n: int = 500) -> float:
    """Median time of one PPOEModel.fk + cov_local_to_ros in this process [us]."""
    from ppoe_core import lie
    from ppoe_core.model.ppoe import PPOEModel

    model = PPOEModel.from_files(URDF, MODEL)
    q = np.full(len(model.joint_names), 0.3)
    times = []
    for _ in range(n):
        t = time.perf_counter()
        T, cov = model.fk(q, "base_link", "tool0")
        lie.cov_local_to_ros(T, cov)
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e6)


def callback_us(n: int = 5000, reps: int = 5) -> tuple[float, float]:
    """The kinematics node's callback per joint state in this process [us]: (Python path, as shipped)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from ppoe_ros.common.runner import warm_node_kernels
    from ppoe_ros.nodes.kinematics_node import KinematicsNode

    warm_node_kernels(["kinematics_node"])
    rng = np.random.default_rng(1)
    data = []
    for k in range(n):
        msg = JointState(name=ARM, position=[float(v) for v in rng.uniform(-1.0, 1.0, len(ARM))])
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + k // 1000, (k % 1000) * 1_000_000
        data.append(serialize_message(msg))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=random.randint(100, 200))
    node = KinematicsNode(context=ctx, parameter_overrides=[Parameter("robot_description", value=URDF.read_text()),
                                                             Parameter("model_file", value=str(MODEL))])
    try:
        fast, times = node._fast, {False: [], True: []}
        for _ in range(reps):
            for compiled in (False, True):
                node._fast, node._last_ns = (fast if compiled else None), None
                t = time.perf_counter()
                for raw in data:
                    node._on_joint_state_burst(raw)
                times[compiled].append((time.perf_counter() - t) / n * 1e6)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return float(np.median(times[False])), float(np.median(times[True]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=30.0, help="measured seconds per mode (default 30)")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds fed before measuring (default 2)")
    ap.add_argument("--rate", type=float, default=1000.0, help="joint-state rate [Hz] (default 1000)")
    ap.add_argument("--modes", default="relay,node", help="comma list of relay, node, batched (default relay,node)")
    ap.add_argument("--role", default="bench", choices=("bench", "feed", "relay"), help=argparse.SUPPRESS)
    ap.add_argument("--in-topic", default="/joint_states", help=argparse.SUPPRESS)  # relay role
    ap.add_argument("--out-topic", default="/ppoe/pose", help=argparse.SUPPRESS)
    ap.add_argument("--in-pose", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "feed":
        return feed(args.rate, args.seconds)
    if args.role == "relay":
        return relay(args.in_topic, args.out_topic, args.in_pose)
    print(f"bench_nodes.cpus: {os.cpu_count()} cores")
    print(f"bench_nodes.load_avg_1min: {os.getloadavg()[0]:.2f}")
    print(f"fk_call: {fk_call_us():.1f} us")
    py_us, compiled_us = callback_us()
    print(f"callback_python: {py_us:.1f} us")
    print(f"callback_compiled: {compiled_us:.1f} us")
    results = {}
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        r = run_mode(mode, args.rate, args.seconds, args.warmup)
        results[mode] = r
        if not r["out_received"]:
            print(f"error: mode {mode}: no output received (the node process failed?)", file=sys.stderr)
            return 1
        p = f"bench_nodes.{mode}"
        print(f"{p}.feed_rate: {r['feed_rate']:.1f} Hz")
        print(f"{p}.feeder_late_over_5ms: {r['feeder_late']} msgs")
        print(f"{p}.measured_window: {r['window']:.2f} s")
        print(f"{p}.messages_sent: {r['sent_total']} msgs")
        print(f"{p}.messages_in: {r['node_received']} msgs")
        print(f"{p}.messages_out: {r['node_published']} msgs")
        print(f"{p}.outputs_received_by_bench: {r['out_received']} msgs")
        print(f"{p}.in_per_sent: {r['node_received'] / max(r['sent_total'], 1):.4f} ratio")
        print(f"{p}.out_per_in: {r['node_published'] / max(r['node_received'], 1):.4f} ratio")
        print(f"{p}.latency_samples: {r['latency_samples']} msgs")
        print(f"{p}.bad: {r['node_bad']} msgs")
        print(f"{p}.dropped: {r['node_dropped']} msgs")
        print(f"{p}.latency_median: {r['lat_median']:.3f} ms")
        print(f"{p}.latency_p99: {r['lat_p99']:.3f} ms")
        print(f"{p}.latency_max: {r['lat_max']:.3f} ms")
        print(f"{p}.cpu_share: {r['cpu_share']:.3f} cores")
        sys.stdout.flush()
    for key, mode in (("relay_floor", "relay"), ("kinematics_node", "node"), ("kinematics_node_batched", "batched")):
        if mode in results:
            print(f"{key}_cpu_share: {results[mode]['cpu_share']:.3f} cores")
            print(f"{key}_latency_p99: {results[mode]['lat_p99']:.3f} ms")
    if "relay" in results and "node" in results:
        r, n = results["relay"], results["node"]
        print(f"ratio.kinematics_node_over_relay_cpu_share: {n['cpu_share'] / max(r['cpu_share'], 1e-9):.2f} x")
        print(f"ratio.kinematics_node_over_relay_latency_p99: {n['lat_p99'] / r['lat_p99']:.2f} x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
