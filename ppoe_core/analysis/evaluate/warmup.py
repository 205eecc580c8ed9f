"""Compile (or load from numba's cache) the kernels ``ppoe evaluate`` uses beyond the nodes' (``ppoe warmup``).

``ppoe warmup`` compiles each node's kernels; an offline replay uses a few more (the batched joint-history merge,
the batched FK panels, the PNG unfilter, the correction buffer's expiry, the batched SE(3) inverse: 5 kernels,
10-19 s on 2 cores).  Without this step a user's first ``ppoe evaluate`` after the set-up command compiled them
silently.  The warm-up simulates a two-second bag of the shipped rover (tags in PNG images, ground truth) into a
temporary directory and replays it: the very code paths and argument types of a real replay, so numba compiles
exactly the signatures a real run needs.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from ppoe_core.io.paths import package_share_directory

__all__ = ["warm_evaluate", "WARM_SCENARIO"]

#: a short rover scenario (``ppoe simulate`` format): 2 s, joint states at 50 Hz, 2 camera images per second with
#: the tags, ground-truth poses at 10 Hz (what a replay reads; the sizes only need to reach every code path)
WARM_SCENARIO = {
    "seed": 1,
    "start_time": 10.0,
    "truth": {"perturbations": "once", "joint_noise": True, "effects": []},
    "trajectory": {"joint_rate": 50.0, "smooth": {
        "duration": 2.0,
        "centre": {"pan_joint": -2.97, "tilt_joint": 0.65, "arm_joint_1": 0.37, "arm_joint_2": -0.54,  # tags in view
                   "arm_joint_3": 1.93, "arm_joint_4": -0.72, "arm_joint_5": 1.39, "arm_joint_6": 0.0},
        "amplitude": {"arm_joint_1": 0.05, "arm_joint_6": 0.2}, "period": {"arm_joint_1": 3.0, "arm_joint_6": 5.0}}},
    "camera": {"width": 640, "height": 480, "intrinsics": [600.0, 600.0, 320.0, 240.0], "D": [-0.05, 0.02, 0, 0, 0],
               "rate": 2.0, "during": "always", "format": "png"},
    "ground_truth": {"pose": {"frame": "base_link", "target": "tool_link", "rate": 10.0}},
}


def warm_evaluate() -> str:
    """Replay the warm-up bag once; returns what was done (or why not: the shipped rover files not found)."""
    from ppoe_core.analysis.evaluate.options import EvaluateOptions
    from ppoe_core.analysis.evaluate.replay import evaluate_bag
    import yaml

    from ppoe_core.sim.simulate import simulate

    robots = package_share_directory("ppoe_ros") / "config" / "robots"
    urdf, model = robots / "rover.urdf", robots / "rover_model.yaml"
    if not (urdf.is_file() and model.is_file()):
        return f"skipped: {urdf} or {model} not found"
    with tempfile.TemporaryDirectory(prefix="ppoe_warm_evaluate_") as tmp:
        scenario = Path(tmp) / "scenario.yaml"
        scenario.write_text(yaml.safe_dump({"robot": {"urdf": str(urdf), "model": str(model)}, **WARM_SCENARIO}))
        simulate(scenario, Path(tmp) / "bag", overwrite=True)
        ev = evaluate_bag(Path(tmp) / "bag", model, EvaluateOptions(progress=False))
    counts = ev.summary["methods"]["ppoe"]["measurements"]["counts"]
    return f"replayed a 2 s rover bag ({ev.summary['measurements'].get('images', 0)} images, " \
           f"{counts['accepted']} tag updates accepted)"
