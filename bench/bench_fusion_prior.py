"""Per-prior cost of the fusion node: ``/ppoe/pose`` message in -> ``/ppoe/fused_pose`` message out.

Replays the forward-kinematics priors of ``bags/table1_exp1`` (``PPOEModel.fk`` of every
``/joint_states`` message, as the kinematics node) and the bag's tag observations (as the tag
bearing node) through the fusion node's per-message code, without ROS transport: for every prior
``pose_cov_from_msg -> lie.cov_ros_to_local -> FusionPipeline.add_prior -> lie.cov_local_to_ros
-> pose_cov_stamped_msg`` (``FusionNode._prior`` and ``_publish``), measurements through
``add_measurement``.  Only the per-prior part is timed (process CPU time).

Baseline measured in the same run: the same replay with the single-input fast paths of
``ppoe_core.lie`` (``quat_from_matrix``, ``matrix_from_quat``, ``exp``, ``inverse`` of one input) replaced by the
batched code on a batch of one.  Both runs must give bit-identical fused poses (checked).  Since the per-prior
path went compiled (one-pose kernels for the message's pose and covariance, one kernel for the carried
correction's weight and update), of these only ``inverse`` and ``exp`` (a few per measurement) are still on it, so the
two variants now differ by noise; the number to read is ``per_prior_fast_paths`` (target <= 50 us).

Prints ``name: value unit`` lines.
Run: ``cd /work/main && python bench/bench_fusion_prior.py [--repeat N]``
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, before numpy is imported

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from ppoe_core import lie  # noqa: E402
from ppoe_core.analysis import evaluate  # noqa: E402
from ppoe_core.estimation.pipeline import make_pipeline  # noqa: E402
from ppoe_core.io.bagio import read_bag  # noqa: E402
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402
from ppoe_ros.common import pose_cov_from_msg, pose_cov_stamped_msg  # noqa: E402

__all__ = ["main"]

BAG = REPO / "bags" / "table1_exp1"
MODEL_YAML = REPO / "config" / "robots" / "rover_model.yaml"
_FAST = {"quat_from_matrix": lie.quat_from_matrix, "matrix_from_quat": lie.matrix_from_quat, "exp": lie.exp,
         "inverse": lie.inverse}


def _batched(name: str, ndim: int):
    fast = _FAST[name]
    return lambda x: fast(np.asarray(x, dtype=float)[None])[0] if np.ndim(x) == ndim else fast(x)


def _use_fast_paths(on: bool) -> None:
    for name, ndim in (("quat_from_matrix", 2), ("matrix_from_quat", 1), ("exp", 1), ("inverse", 2)):
        setattr(lie, name, _FAST[name] if on else _batched(name, ndim))


def _replay(model, base, tool, msgs, stamps, Q, meas) -> tuple[float, int, np.ndarray]:
    """(CPU seconds in the per-prior path, priors, fused poses (n, 4, 4))."""
    pipe = make_pipeline(model, base, tool)
    cpu, out, j = 0.0, [], 0
    for i, msg in enumerate(msgs):
        while j < len(meas) and meas[j].stamp <= stamps[i]:
            pipe.add_measurement(meas[j])
            j += 1
        t0 = time.process_time()
        T, cov_ros, stamp_ns, _ = pose_cov_from_msg(msg)
        est, _ = pipe.add_prior(stamp_ns * 1e-9, T, lie.cov_ros_to_local(T, cov_ros), Q[i])
        fused = pose_cov_stamped_msg(est.T_base_tool, lie.cov_local_to_ros(est.T_base_tool, est.cov_tool),
                                     msg.header.stamp, base)
        cpu += time.process_time() - t0
        out.append(est.T_base_tool)
        del fused
    return cpu, len(msgs), np.stack(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=10,
                    help="replays per variant; the fastest counts (10: on a shared VM single replays vary by 2x)")
    args = ap.parse_args(argv)
    data = read_bag(BAG)
    model = PPOEModel.from_strings(data.robot_description, MODEL_YAML)
    base, tool = model.config.frames.base, model.config.frames.tool
    js = data.joint_states
    order = np.argsort(js.stamps, kind="stable")
    stamps = js.stamps[order]
    Q, _ = evaluate.joint_matrix(js, model.joint_names, str(BAG))
    Q = Q[order]
    T_all, cov_all = model.fk({n: Q[:, k] for k, n in enumerate(model.joint_names)}, base, tool)
    msgs = [
        pose_cov_stamped_msg(T_all[i], lie.cov_local_to_ros(T_all[i], cov_all[i]), int(round(stamps[i] * 1e9)), base)
        for i in range(len(stamps))
    ]
    meas, _ = evaluate.tag_measurements(data, model, str(BAG))
    meas = sorted(meas, key=lambda m: m.stamp)
    res = {}
    for variant, on in (("batched_lie", False), ("fast_paths", True)):
        _use_fast_paths(on)
        runs = [_replay(model, base, tool, msgs, stamps, Q, meas) for _ in range(args.repeat)]
        res[variant] = min(runs, key=lambda r: r[0])
    _use_fast_paths(True)
    same = np.array_equal(res["batched_lie"][2], res["fast_paths"][2])
    n = res["fast_paths"][1]
    print(f"priors: {n} count")
    print(f"tag_measurements: {len(meas)} count")
    for variant, (cpu, _, _) in res.items():
        print(f"per_prior_{variant}: {1e6 * cpu / n:.1f} us")
    print(f"speedup_fast_paths_vs_batched_lie: {res['batched_lie'][0] / res['fast_paths'][0]:.2f} x")
    print(f"fused_poses_bit_identical: {int(same)} bool")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
