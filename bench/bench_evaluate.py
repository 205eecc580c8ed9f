"""Speed of ``ppoe evaluate`` on a long simulated bag.

Generates (in a temp dir, with ``ppoe_core.sim.simulate``) a 10-minute bag of the rover of the
Table I study: ``/joint_states`` at 100 Hz on a smooth trajectory near the "close and rotated"
configuration of experiment I, camera images (PNG, 640x480) at ``--camera-rate`` with the tags
rendered, ``/ground_truth/pose`` at ``--gt-rate``.  Then runs the full offline replay
(:func:`ppoe_core.analysis.evaluate.evaluate_bag`: batched PPOE FK of every joint state, tag detection
on every image, the PPOE and the naive fusion pipelines, scoring) and, as the baselines measured
in the same run, only reading the bag (:func:`ppoe_core.io.bagio.read_bag`); then the replay with the tags detected
in windows the forward kinematics predicts (``--tag-windows``, ``EvaluateOptions(tag_windows=True)``; ``windows_*``
lines: its speed-up over the default and whether both summaries are equal); then the default replay with the images
on two threads instead of two worker processes (``EvaluateOptions(image_processes=False)``, third, so warm too:
``processes_*`` lines, the processes' speed-up over it, and ``threads_same_summary``).

Prints ``name: value unit`` lines, among them ``joint_states_per_s`` and
``bag_seconds_per_wall_second`` (wall clock), and the same per second of process CPU time
(``*_per_cpu_s``, all threads of this process and of its image worker processes: the images are decoded and
detected by ``image_workers`` processes forked for each evaluation, whose CPU time counts too), which is the
fairer number on a shared machine; ``evaluate_parent_cpu_time`` and ``evaluate_workers_cpu_time`` split the first
replay's CPU time between this process (reading the bag, forward kinematics, the fusion replay, scoring) and the image
workers (decoding, detection, observation rows), which start as soon as the images are read (before the joint states).

Run: ``cd /work/main && python bench/bench_evaluate.py [--duration 600] [--keep DIR]``
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, before numpy is imported

import argparse  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from ppoe_core.analysis.evaluate import EvaluateOptions, evaluate_bag  # noqa: E402
from ppoe_core.analysis.evaluate.tag_stream import IMAGE_WORKERS  # noqa: E402
from ppoe_core.io.bagio import read_bag  # noqa: E402
from ppoe_core.sim.simulate import simulate  # noqa: E402

#: issue 24's target: bag seconds per wall second of ``evaluate_bag``
TARGET_REAL_TIME = 400.0

__all__ = ["main", "scenario"]

#: experiment I centre configuration of bags/table1_exp1.yaml [rad]
_CENTRE = {"pan_joint": -2.97, "tilt_joint": 0.65, "arm_joint_1": 0.37, "arm_joint_2": -0.54,
           "arm_joint_3": 1.93, "arm_joint_4": -0.72, "arm_joint_5": 1.39, "arm_joint_6": 0.0}


def scenario(duration: float, rate: float, camera_rate: float, gt_rate: float) -> dict:
    """The benchmark scenario (``ppoe simulate`` format, see ``--help-scenario``)."""
    return {
        "robot": {
            "urdf": str(REPO / "config" / "robots" / "rover.urdf"),
            "model": str(REPO / "config" / "robots" / "rover_model.yaml"),
        },
        "seed": 5,
        "start_time": 100.0,
        "truth": {"perturbations": "once", "joint_noise": True, "effects": []},
        "trajectory": {
            "joint_rate": rate,
            "smooth": {
                "duration": duration,
                "centre": _CENTRE,
                "amplitude": {"arm_joint_1": 0.05, "arm_joint_2": 0.04, "arm_joint_4": 0.1, "arm_joint_6": 0.2},
                "period": {"arm_joint_1": 23.0, "arm_joint_2": 17.0, "arm_joint_4": 29.0, "arm_joint_6": 31.0},
            },
        },
        "camera": {
            "width": 640,
            "height": 480,
            "intrinsics": [600.0, 600.0, 320.0, 240.0],
            "D": [-0.05, 0.02, 0.0, 0.0, 0.0],
            "rate": camera_rate,
            "during": "always",
            "format": "png",
        },
        "ground_truth": {"pose": {"frame": "base_link", "target": "tool_link", "rate": gt_rate}},
    }


def _cpu() -> float:
    """CPU seconds of this process and of its children that ended (the image workers, joined by evaluate_bag)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + kids.ru_utime + kids.ru_stime


def _children_cpu() -> float:
    """CPU seconds of this process's children that ended (the image workers)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return kids.ru_utime + kids.ru_stime


def _scores(summary: dict) -> dict:
    """The summary without its wall time (the rest must not depend on where the tags were looked for)."""
    return {k: v for k, v in summary.items() if k != "wall_time_s"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="bag length [s] (default 600)")
    ap.add_argument("--rate", type=float, default=100.0, help="joint-state rate [Hz] (default 100)")
    ap.add_argument("--camera-rate", type=float, default=1.0, help="image rate [Hz] (default 1)")
    ap.add_argument("--gt-rate", type=float, default=10.0, help="ground-truth rate [Hz] (default 10)")
    ap.add_argument("--keep", default=None, help="generate the bag here and keep it")
    args = ap.parse_args(argv)

    tmp = None
    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench_evaluate_")
        work = Path(tmp.name)
    try:
        sc = work / "scenario.yaml"
        sc.write_text(yaml.safe_dump(scenario(args.duration, args.rate, args.camera_rate, args.gt_rate)))
        bag = work / "bag"
        t0 = time.perf_counter()
        simulate(sc, bag, overwrite=True)
        t_gen = time.perf_counter() - t0

        t0, c0 = time.perf_counter(), _cpu()
        data = read_bag(bag)
        t_read, c_read = time.perf_counter() - t0, _cpu() - c0
        n_js = len(data.joint_states)
        span = float(data.joint_states.stamps[-1] - data.joint_states.stamps[0])

        model = REPO / "config" / "robots" / "rover_model.yaml"
        # ``ppoe evaluate`` as it runs by default (tags on the whole images), the first replay of the process as
        # always; then the same replay with ``--tag-windows`` (second, so it starts warm: its speed-up is if anything
        # overstated)
        t0, c0, k0 = time.perf_counter(), _cpu(), _children_cpu()
        ev = evaluate_bag(bag, model, EvaluateOptions(progress=False))
        t_eval, c_eval, k_eval = time.perf_counter() - t0, _cpu() - c0, _children_cpu() - k0
        t0, c0 = time.perf_counter(), _cpu()
        windows = evaluate_bag(bag, model, EvaluateOptions(progress=False, tag_windows=True))
        t_win, c_win = time.perf_counter() - t0, _cpu() - c0
        t0, c0 = time.perf_counter(), _cpu()
        threads = evaluate_bag(bag, model, EvaluateOptions(progress=False, image_processes=False))
        t_thr, c_thr = time.perf_counter() - t0, _cpu() - c0
        same = _scores(windows.summary) == _scores(ev.summary)
        same_threads = _scores(threads.summary) == _scores(ev.summary)
        s = ev.summary
        counts = s["methods"]["ppoe"]["measurements"]["counts"]
        print(f"bag_duration: {span:.1f} s")
        print(f"joint_states: {n_js} messages")
        print(f"images: {s['measurements'].get('images', 0)} messages")
        print(f"ground_truth_samples: {s['ground_truth']['samples']} messages")
        print(f"tag_updates_accepted: {counts['accepted']} updates")
        print(f"generate_time: {t_gen:.2f} s")
        print(f"read_bag_time: {t_read:.2f} s")
        print(f"read_bag_cpu_time: {c_read:.2f} s")
        print(f"evaluate_time: {t_eval:.2f} s")
        print(f"evaluate_cpu_time: {c_eval:.2f} s")
        # where the CPU went: this process (reading, forward kinematics, the fusion replay, scoring) and the image
        # workers (PNG decoding, tag detection, observation rows)
        print(f"evaluate_parent_cpu_time: {c_eval - k_eval:.2f} s")
        print(f"evaluate_workers_cpu_time: {k_eval:.2f} s")
        print(f"image_workers: {IMAGE_WORKERS} processes")  # images decoded and detected by these (CPU time counts all)
        print(f"joint_states_per_s: {n_js / t_eval:.0f} 1/s")
        print(f"bag_seconds_per_wall_second: {span / t_eval:.1f} s/s")
        # the machine may be shared: the same rates per second of this process's CPU time
        print(f"joint_states_per_cpu_s: {n_js / c_eval:.0f} 1/s")
        print(f"bag_seconds_per_cpu_second: {span / c_eval:.1f} s/s")
        print(f"evaluate_over_read_bag_cpu_ratio: {c_eval / c_read:.2f} x")
        print(f"evaluate_tag_windows_time: {t_win:.2f} s")
        print(f"evaluate_tag_windows_cpu_time: {c_win:.2f} s")
        print(f"windows_speedup_wall: {t_eval / t_win:.2f} x")
        print(f"windows_speedup_cpu: {c_eval / c_win:.2f} x")
        print(f"windows_same_summary: {same}")
        print(f"evaluate_threads_time: {t_thr:.2f} s")  # third replay: the images on threads, not processes
        print(f"evaluate_threads_cpu_time: {c_thr:.2f} s")
        print(f"processes_speedup_wall: {t_thr / t_eval:.2f} x")
        print(f"processes_speedup_cpu: {c_thr / c_eval:.2f} x")
        print(f"threads_same_summary: {same_threads}")
        fk, pp = s["methods"]["fk"]["lateral"], s["methods"]["ppoe"]["lateral"]
        print(f"fk_lateral_mean: {1e3 * fk['mean']:.2f} mm")
        print(f"ppoe_lateral_mean: {1e3 * pp['mean']:.2f} mm")
        rate = span / t_eval
        print(f"row: ppoe evaluate = {rate:.0f}x real time (baseline read_bag alone {span / t_read:.0f}x; "
              f"{span / c_eval:.0f} bag-s per CPU-s) target >= {TARGET_REAL_TIME:g}x: "
              f"{'met' if rate >= TARGET_REAL_TIME else 'MISSED'}")
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
