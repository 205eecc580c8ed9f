#!/usr/bin/env python3
"""Soak and burst of the kinematics node: is every lost message counted, and does memory stay flat?

The node runs as a separate process (isolated DDS domain, arm7 URDF by parameter, its default
parameters otherwise).  A feeder process publishes ``/joint_states``; this process subscribes
``/ppoe/pose`` (reliable) and ``/diagnostics``.  The feeder starts once the node is up (its first
``/diagnostics``): what is sent while a node starts cannot be counted (``ppoe_ros/common/losses.py``).

* ``soak``: ``--rate`` Hz (default 1000) for ``--seconds`` (default 600 = 10 minutes).
* ``burst``: ``--burst`` messages (default 50000) published as fast as the feeder can, then
  one more message after a pause (so that a trailing gap is seen).

Per mode it prints ``name: value unit`` lines:

* ``sent``: messages the feeder published;
* the node's ``/diagnostics`` counters: ``received``, ``published``, ``dropped`` (its FK
  queue), ``bad``, ``lost_before_node`` (publisher sequence gaps, see
  ``ppoe_ros/common/losses.py``), ``lost_in_transport`` (the middleware's lost event),
  ``loss_tracking_paused`` (how often the node paused gap counting: not exactly one publisher) and
  ``received_untracked`` (messages received while paused);
* ``uncounted_input_loss = sent - received - lost_before_node``: messages that vanished on the
  way in without any counter knowing (goal 0);
* ``out_received`` by this process, ``out_gaps`` (sequence gaps this subscriber saw: poses the
  node published that never arrived, e.g. its output history overflowed) and
  ``uncounted_output_loss = published - out_received - out_gaps`` (goal 0);
* ``rss`` of the node process over time (MB), first / max / last, and one line per sample.

Usage::

    python bench/bench_soak.py                              # soak 600 s, then burst 50000
    python bench/bench_soak.py --modes soak --seconds 60
    python bench/bench_soak.py --modes burst --burst 20000
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from bench_nodes import ARM, MODEL, URDF, _env  # noqa: E402

__all__ = ["feed", "run", "main"]


def feed(rate: float, n: int) -> int:
    """Feeder process: ``n`` joint states at ``rate`` Hz (0 = as fast as possible), then one more
    after 1 s; prints ``sent <count>``."""
    import rclpy
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import ns_to_stamp

    rclpy.init()
    node = rclpy.create_node("soak_feeder")
    pub = node.create_publisher(JointState, "/joint_states", 1000)
    end = time.monotonic() + 20
    while pub.get_subscription_count() == 0 and time.monotonic() < end:
        time.sleep(0.05)
    time.sleep(1.0)
    msg = JointState(name=ARM)
    phases = np.linspace(0.0, 1.0, len(ARM))
    t0 = time.monotonic()
    for k in range(n + 1):
        if k == n:
            time.sleep(1.0)  # the last message closes any trailing gap
        elif rate > 0:
            wait = t0 + k / rate - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        msg.position = (0.8 * np.sin(0.5 * k / 1000.0 + phases)).tolist()
        msg.header.stamp = ns_to_stamp(time.time_ns())
        pub.publish(msg)
    print(f"sent {n + 1}", flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class _Receiver:
    """This process's ROS side: poses counted with their sequence gaps, the node's diagnostics."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("soak_receiver", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.n_out, self.gaps, self.last_seq = 0, 0, None
        self.diag: dict[str, int] = {}
        self.node.create_subscription(PoseWithCovarianceStamped, "/ppoe/pose", self._pose, 10000, raw=True)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 10)

    def _pose(self, raw: bytes, info: dict) -> None:
        self.n_out += 1
        seq = info.get("publication_sequence_number")
        if seq and self.last_seq is not None and seq > self.last_seq + 1:
            self.gaps += seq - self.last_seq - 1
        self.last_seq = seq or self.last_seq

    def _diag(self, msg: object) -> None:
        for st in msg.status:  # type: ignore[attr-defined]
            if st.name == "/kinematics_node: health":
                self.diag.update({kv.key: int(kv.value) for kv in st.values if kv.value.isdigit()})

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _stop(proc: subprocess.Popen | None) -> None:
    if proc is not None and proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)


def run(mode: str, rate: float, n: int, samples: int = 10) -> dict[str, object]:
    """One node process fed ``n`` messages at ``rate`` (0 = burst); returns the counts and RSS."""
    import yaml

    domain = random.SystemRandom().randint(1, 200)
    env = _env(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    params = Path(f"/tmp/bench_soak_{os.getpid()}.yaml")
    params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {
        "robot_description": URDF.read_text(), "model_file": str(MODEL)}}}))
    node_proc = subprocess.Popen([sys.executable, "-m", "ppoe_ros.nodes.kinematics_node", "--ros-args",
                                  "--params-file", str(params)], env=env, cwd=REPO, start_new_session=True,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rx = _Receiver(domain)
    feeder = None
    rss: list[tuple[float, float]] = []
    try:
        # the node is up once it publishes /diagnostics (it spins, and it has looked at its inputs' publishers):
        # what a publisher sends while the node still starts (its subscription exists, it does not take yet) is
        # dropped from the subscription's history and cannot be told from a late join (losses.py); a numba
        # compile of 20-30 s at the first start, ~1 s under load with a warm cache: 1177 "uncounted" at 11:03
        end = time.monotonic() + 120
        while not rx.diag and time.monotonic() < end:
            rx.spin(0.05)
        rx.spin(1.5)  # one more diagnostics period: the node saw no /joint_states publisher
        feeder = subprocess.Popen([sys.executable, __file__, "--role", "feed", "--rate", str(rate), "--n", str(n)],
                                  env=env, cwd=REPO, start_new_session=True, stdout=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        period = max(n / rate, 1.0) / samples if rate > 0 else 1.0
        next_sample = t0
        while feeder.poll() is None:
            if time.monotonic() >= next_sample:
                rss.append((time.monotonic() - t0, _rss_mb(node_proc.pid)))
                next_sample += period
            rx.spin(0.05)
        last, still = None, 0
        while still < 3:  # until the node's counters and this receiver settle
            rx.spin(1.0)
            cur = (rx.diag.get("received"), rx.diag.get("published"), rx.n_out)
            still, last = (still + 1 if cur == last else 0), cur
        rss.append((time.monotonic() - t0, _rss_mb(node_proc.pid)))
        sent = int(feeder.stdout.read().split()[1])  # type: ignore[union-attr]
    finally:
        _stop(feeder)
        _stop(node_proc)
        rx.close()
        params.unlink(missing_ok=True)
    d = rx.diag
    return {"sent": sent, **{k: d.get(k, 0) for k in ("received", "published", "dropped", "bad",
                                                        "lost_before_node", "lost_in_transport",
                                                        "loss_tracking_paused", "received_untracked")},
            "out_received": rx.n_out, "out_gaps": rx.gaps, "rss": rss}


def _print(mode: str, r: dict) -> None:
    p = f"kinematics_node.{mode}"
    for k in ("sent", "received", "published", "dropped", "bad", "lost_before_node", "lost_in_transport",
              "loss_tracking_paused", "received_untracked", "out_received", "out_gaps"):
        print(f"{p}.{k}: {r[k]} msgs")
    print(f"{p}.uncounted_input_loss: {r['sent'] - r['received'] - r['lost_before_node']} msgs")
    print(f"{p}.uncounted_output_loss: {r['published'] - r['out_received'] - r['out_gaps']} msgs")
    mb = [m for _, m in r["rss"]]
    print(f"{p}.rss_first: {mb[0]:.1f} MB")
    print(f"{p}.rss_max: {max(mb):.1f} MB")
    print(f"{p}.rss_last: {mb[-1]:.1f} MB")
    print(f"{p}.rss_growth_last_over_first: {mb[-1] / mb[0]:.3f} ratio")
    for t, m in r["rss"]:
        print(f"{p}.rss_at_{t:.0f}s: {m:.1f} MB")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--modes", default="soak,burst", help="comma list of soak, burst (default both)")
    ap.add_argument("--seconds", type=float, default=600.0, help="soak duration [s] (default 600)")
    ap.add_argument("--rate", type=float, default=1000.0, help="soak rate [Hz] (default 1000)")
    ap.add_argument("--burst", type=int, default=50000, help="burst size [messages] (default 50000)")
    ap.add_argument("--role", default="bench", choices=("bench", "feed"), help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "feed":
        return feed(args.rate, args.n)
    print(f"bench_soak.cpus: {os.cpu_count()} cores")
    print(f"bench_soak.load_avg_1min: {os.getloadavg()[0]:.2f}")
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        if mode == "soak":
            _print(mode, run(mode, args.rate, int(round(args.rate * args.seconds))))
        elif mode == "burst":
            _print(mode, run(mode, 0.0, args.burst))
        else:
            ap.error(f"unknown mode {mode!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
