"""Benchmark and real-data result of ``ppoe diagnose``.

1. Hilti stationing data (``$PPOE_DATASETS/hilti_stationing``, README protocol: per-station
   Kabsch on the cross stationing points, score on the evaluation points):
   * ``diagnose`` on all five files with leave-one-file-out cross-validation (the effect
     parameters scored on a file are fitted on the four others), timed;
   * nested leave-one-file-out: effects *selected and fitted* on four files only, the fifth
     scored by the protocol; per-file RMS 3D and r95 xy / z before -> after.
2. Motoman marker pixels (``$PPOE_DATASETS/motoman_leica``): pixel RMS per camera with the
   published chains, ``camera_extrinsics`` found on the 6x6x6 set (5-fold CV over poses), fit on
   even poses -> score odd poses, fit on 6x6x6 -> score the table/wall files, the same with arm
   candidates added, and ``ppoe diagnose`` on an imported 6x6x6 bag (temporary directory).
2b. Motoman joint tracker + pixel fit (right arm, 6x6x6; ``joint_fit`` / ``joint_heldout``): held-out pixel RMS
   per camera and tracker RMS (5-fold over poses) of effect sets: registration only, tracker only (the tracker
   stage's effects refitted on the tracker points), cameras only (pixels),
   staged (tracker-stage effects fixed, cameras fitted), joint A (tracker-stage effects + cameras), joint B
   (A + joint offsets S1..T1), joint C (A + the marker plate's ``link_error@T1_to_EE1``), joint A with the
   declared noise (0.2 mm / 1 px); each fitted on all of 6x6x6 and
   scored on the higher / lower / wall files.
3. A 10-minute simulated bag of the arm7 robot (100 Hz joint states, a static tracker stop every
   5 s, gravity compliance injected), written to a temporary directory: ``ppoe diagnose`` time.

Prints ``name: value unit`` lines; ratios are against the nominal baseline measured in the same
run.  Usage: ``python bench/bench_diagnose.py [--quick] [--skip-hilti] [--skip-bag] [--skip-motoman]
[--skip-joint]``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ppoe_core import lie  # noqa: E402
from ppoe_core.analysis.diagnose import DiagnoseOptions, Stops, diagnose, protocol_scores  # noqa: E402
from ppoe_core.cli.datasets import stops_from_hilti  # noqa: E402
from ppoe_core.robot.urdf import parse_urdf  # noqa: E402

FILES = ["flat", "pallet", "orthogonal_wood", "wood_left_track", "diagonal_wood"]


def hilti(quick: bool) -> None:
    d = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets")) / "hilti_stationing"
    robot = parse_urdf(d / "trailblazer.urdf")
    t0 = time.perf_counter()
    parts = {f: stops_from_hilti(d / f"{f}.yaml", robot) for f in FILES}
    print(f"hilti_load_time: {time.perf_counter() - t0:.2f} s")
    opts = DiagnoseOptions(cv="groups", max_effects=4 if quick else 8)
    t0 = time.perf_counter()
    res = diagnose(robot, Stops.concat([parts[f] for f in FILES]), options=opts)
    print(f"hilti_diagnose_time_5files: {time.perf_counter() - t0:.1f} s")
    print("hilti_effects_found: " + "; ".join(
        f"{e['name']}@{e['location']}" + "(" + ", ".join(f"{k}={v:.4g}" for k, v in e["parameters"].items()) + ")"
        for e in res.effects))
    print(f"hilti_lofo_rms_before: {1e3 * res.residual_before:.3f} mm")
    print(f"hilti_lofo_rms_after: {1e3 * res.residual_after:.3f} mm")
    print("| file | eval pts | RMS 3D before -> after [mm] | max 3D [mm] | r95 xy [mm] | r95 z [mm] |")
    print("|---|---|---|---|---|---|")
    for f in FILES:
        b, a = res.extra["per_group"][f]["before"], res.extra["per_group"][f]["after"]
        print(f"| {f} | {b['n']} | {1e3 * b['rms']:.2f} -> {1e3 * a['rms']:.2f} | {1e3 * b['max']:.1f} -> "
              f"{1e3 * a['max']:.1f} | {1e3 * b['r95_xy']:.1f} -> {1e3 * a['r95_xy']:.1f} | "
              f"{1e3 * b['r95_z']:.1f} -> {1e3 * a['r95_z']:.1f} |")
    if quick:
        return
    # nested: selection and fit on the other four files only
    print("nested leave-one-file-out (selection + fit on the 4 other files):")
    print("| file | effects (selected on the others) | RMS 3D before -> after [mm] | r95 xy [mm] | r95 z [mm] |")
    print("|---|---|---|---|---|")
    ratios = []
    t0 = time.perf_counter()
    for f in FILES:
        train = Stops.concat([parts[g] for g in FILES if g != f])
        r = diagnose(robot, train, options=opts)
        b = protocol_scores(robot, parts[f])
        a = protocol_scores(robot, parts[f], r.chosen)
        ratios.append(a["r95_xy"] / b["r95_xy"])
        print(
            f"| {f} | {', '.join(e.describe() for e in r.chosen)} | {1e3 * b['rms']:.2f} -> {1e3 * a['rms']:.2f} | "
            f"{1e3 * b['r95_xy']:.1f} -> {1e3 * a['r95_xy']:.1f} | {1e3 * b['r95_z']:.1f} -> {1e3 * a['r95_z']:.1f} |",
            flush=True,
        )
    print(f"hilti_nested_time: {time.perf_counter() - t0:.1f} s")
    print(f"hilti_nested_r95xy_ratio_mean: {np.mean(ratios):.3f} (after/before)")


def ten_minute_bag() -> None:
    from ppoe_core.io.bagio import BagWriter
    from ppoe_core.model.effects import make_effect, sum_effect_corrections
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_ros.cli import main

    urdf = (REPO / "config" / "robots" / "arm7.urdf").read_text()
    robot = parse_urdf(urdf)
    tree = KinematicTree(robot)
    rng = np.random.default_rng(0)
    names = tree.joint_names
    n_stops, period, rate = 120, 5.0, 100.0
    targets = rng.uniform(-1.2, 1.2, (n_stops, len(names)))
    eff = make_effect("gravity_compliance", "joint_2", robot, [2e-4])
    T_tracker_base = lie.from_xyz_rpy([3.0, -1.0, 0.4], [0.0, 0.0, 2.0])
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "ten_minutes"
        t0 = time.perf_counter()
        with BagWriter(bag) as w:
            w.write_robot_description(urdf, 0.0)
            prev = targets[0]
            for k in range(n_stops):
                ts = np.arange(0.0, period, 1.0 / rate)
                s = np.clip(ts / (0.6 * period), 0.0, 1.0)[:, None]
                qs = prev + (targets[k] - prev) * (3 * s**2 - 2 * s**3)  # move, then rest
                for t, qv in zip(k * period + ts, qs):
                    w.write_joint_state(float(t), names, qv)
                q = {j: np.array(targets[k][i]) for i, j in enumerate(names)}
                dq, dxi = sum_effect_corrections([eff], q, {})
                x = (tree.link_poses(q, dq, dxi)["tool0"] @ np.array([0.0, 0.0, 0.02, 1.0]))[:3]
                p = T_tracker_base[:3, :3] @ x + T_tracker_base[:3, 3] + rng.normal(0, 2e-4, 3)
                w.write_ground_truth_point(k * period + period - 0.5, "tracker", p)
                prev = targets[k]
        print(f"bag10min_write_time: {time.perf_counter() - t0:.1f} s")
        print(f"bag10min_joint_states: {n_stops * int(period * rate)} messages")
        buf = io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(buf):
            main(["diagnose", str(bag), "--model", str(REPO / "config" / "robots" / "arm7_model.yaml"), "--json"])
        dt = time.perf_counter() - t0
        doc = json.loads(buf.getvalue())
        print(f"bag10min_diagnose_time: {dt:.1f} s")
        print(
            "bag10min_effects_found: "
            + "; ".join(f"{e['name']}@{e['location']} {e['parameters']}" for e in doc["effects"])
            + " (injected: gravity_compliance@joint_2 2e-4)"
        )
        print(f"bag10min_realtime_ratio: {600.0 / dt:.1f} bag s per wall s")


def motoman() -> None:
    from ppoe_core.analysis.diagnose import diagnose_pixels, pixel_candidates, pixel_rms, pixel_stats
    from ppoe_core.cli.datasets import pixels_from_motoman
    from ppoe_core.model.effects import make_effect
    from ppoe_core.robot.tree import KinematicTree
    from ppoe_ros.cli import main

    d = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets")) / "motoman_leica"
    robot = parse_urdf(d / "motoman_right.urdf")
    tree = KinematicTree(robot)
    files = ["right_hand_6x6x6", "higher_table1_5x5", "lower_table1_5x5", "wall_table1_5x5", "rep_table1"]
    obs = {f: pixels_from_motoman(d / f"leica_{f}_dataset.mat", robot, d / "model.yaml") for f in files}
    short = {"camera_1_optical_frame": "cam1", "camera_2_optical_frame": "cam2"}

    def fmt(r: dict) -> str:
        return " / ".join(f"{r[k]:.2f}" for k in short if k in r)

    for f in files:
        st = pixel_stats(tree, obs[f])
        print(
            f"motoman_pixel_nominal_{f}: "
            + " / ".join(
                f"{short[k]} RMS {v['rms']:.2f} median {v['median']:.2f} max {v['max']:.2f} (n {v['n']})"
                for k, v in st.items()
            )
            + " px"
        )
    o = obs[files[0]]
    t0 = time.perf_counter()
    res = diagnose_pixels(robot, o)
    print(f"motoman_pixel_diagnose_time_6x6x6: {time.perf_counter() - t0:.2f} s ({res.n} observations)")
    for e in res.effects:
        print(
            f"motoman_pixel_effect: {e['name']}@{e['location']} ({e['frame']}) "
            + ", ".join(f"{k}={v:.4g} [{e['ci'][k][0]:.4g}, {e['ci'][k][1]:.4g}]" for k, v in e["parameters"].items())
        )
    print(f"motoman_pixel_cv_rms_6x6x6: {fmt(res.rms_before)} -> {fmt(res.rms_after)} px (5-fold over poses)")
    print(f"motoman_pixel_insample_rms_6x6x6: {fmt(res.rms_before_insample)} -> {fmt(res.rms_after_insample)} px")
    even, odd = o.subset(o.pose % 2 == 0), o.subset(o.pose % 2 == 1)
    r2 = diagnose_pixels(robot, even)
    print(f"motoman_pixel_even_to_odd: {fmt(pixel_rms(tree, odd))} -> {fmt(pixel_rms(tree, odd, r2.fitted))} px")
    for f in files[1:]:
        print(
            f"motoman_pixel_6x6x6_to_{f}: {fmt(pixel_rms(tree, obs[f]))} -> "
            f"{fmt(pixel_rms(tree, obs[f], res.fitted))} px"
        )
        rf = diagnose_pixels(robot, obs[f])
        print(
            f"motoman_pixel_infile_cv_{f}: effects {[e['location'] for e in rf.effects]}, "
            f"{fmt(rf.rms_before)} -> {fmt(rf.rms_after)} px"
        )
    arm = [
        make_effect("joint_offset", j, robot)
        for j in ["joint_S1", "joint_L1", "joint_U1", "joint_R1", "joint_B1", "joint_T1"]
    ]
    arm.append(make_effect("link_error", "T1_to_EE1", robot))
    r3 = diagnose_pixels(robot, o, candidates=pixel_candidates(robot, o) + arm, max_effects=8)
    print("motoman_pixel_arm_candidates_effects: " + ", ".join(s["effect"] for s in r3.steps))
    print(f"motoman_pixel_arm_candidates_cv_rms_6x6x6: {fmt(r3.rms_before)} -> {fmt(r3.rms_after)} px")
    for f in files[1:]:
        print(
            f"motoman_pixel_arm_candidates_6x6x6_to_{f}: {fmt(pixel_rms(tree, obs[f]))} -> "
            f"{fmt(pixel_rms(tree, obs[f], r3.fitted))} px"
        )
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "m666"
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            main(
                [
                    "import",
                    "motoman",
                    str(d / "leica_right_hand_6x6x6_dataset.mat"),
                    "--model-yaml",
                    str(d / "model.yaml"),
                    "--out",
                    str(bag),
                ]
            )
        model = next(Path(tmp).glob("*.yaml"), None) or next(bag.glob("*.yaml"))
        buf = io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(buf):
            main(["diagnose", str(bag), "--model", str(model), "--json", "--max-effects", "3"])
        doc = json.loads(buf.getvalue())
        print(f"motoman_bag_diagnose_time: {time.perf_counter() - t0:.1f} s (model {model.name})")
        print("motoman_bag_effects: " + "; ".join(f"{e['name']}@{e['location']}" for e in doc["effects"]))
        print(f"motoman_bag_tracker_rms: {1e3 * doc['residual_before']:.3f} -> {1e3 * doc['residual_after']:.3f} mm")
        if "pixels" in doc:
            px = doc["pixels"]
            print(f"motoman_bag_pixel_rms_declared_only: {fmt(px['pixel_rms_declared_only'])} px")
            print(
                f"motoman_bag_pixel_rms: {fmt(px['pixel_rms_before'])} -> {fmt(px['pixel_rms_after'])} px "
                "(held-out, with the tracker effects)"
            )
            print(f"motoman_bag_pixel_noise_floor: {fmt(px['pixel_noise_floor'])} px (declared covariance)")
            print(
                f"motoman_bag_pixel_unexplained: {fmt(px['pixel_unexplained'])} px; held-out NEES "
                f"{px['pixel_nees_before']:.3g} -> {px['pixel_nees_after']:.3g} (expectation 2), "
                f"flag {px['pixel_unexplained_flag']}"
            )


def motoman_joint() -> None:
    from ppoe_core.analysis.diagnose import pixel_candidates
    from ppoe_core.analysis.diagnose.joint_cv import joint_heldout, joint_pose_ids, score_joint
    from ppoe_core.analysis.diagnose.joint_fit import joint_fit
    from ppoe_core.analysis.diagnose.pixel_structure import pixel_residual_structure
    from ppoe_core.cli.datasets import pixels_from_motoman, stops_from_motoman
    from ppoe_core.model.effects import make_effect
    from ppoe_core.robot.tree import KinematicTree

    d = Path(os.environ.get("PPOE_DATASETS", REPO.parent / "shared" / "datasets")) / "motoman_leica"
    robot = parse_urdf(d / "motoman_right.urdf")
    tree = KinematicTree(robot)
    files = ["right_hand_6x6x6", "higher_table1_5x5", "lower_table1_5x5", "wall_table1_5x5"]
    S = {f: stops_from_motoman(d / f"leica_{f}_dataset.mat", robot) for f in files}
    O = {f: pixels_from_motoman(d / f"leica_{f}_dataset.mat", robot, d / "model.yaml") for f in files}
    st, ob = S[files[0]], O[files[0]]
    pose_t, _ = joint_pose_ids(st, ob)
    t0 = time.perf_counter()
    res = diagnose(robot, st)
    print(f"motoman_joint_tracker_stage: {[e.describe() for e in res.chosen]} ({time.perf_counter() - t0:.1f} s)")
    cams = [e for e in pixel_candidates(robot, ob) if e.name == "camera_extrinsics"]
    trk = [e.with_params(np.zeros(e.n_params)) for e in res.chosen]
    offsets = [make_effect("joint_offset", j, tree) for j in ("joint_S1", "joint_L1", "joint_U1", "joint_R1",
                                                               "joint_B1", "joint_T1")]

    def fmt(r: dict) -> str:
        return " / ".join(f"{v:.2f}" for v in r.values())

    Opp = {f: swapped_principal_point(o) for f, o in O.items()}
    obp = Opp[files[0]]
    sets = [("registration_only", [], st, ob, (), {}), ("tracker_only", trk, st, None, (), {}),
            ("cameras_only", cams, None, ob, (), {}), ("staged", cams, None, ob, res.chosen, {}),
            ("joint_A", trk + cams, st, ob, (), {}), ("joint_B", trk + cams + offsets, st, ob, (), {}),
            ("joint_C", trk + cams + [make_effect("link_error", "T1_to_EE1", tree)], st, ob, (), {}),
            ("joint_A_declared_noise", trk + cams, st, ob, (), {"presolve": False}),
            ("pp_cameras_only", cams, None, obp, (), {}), ("pp_staged", cams, None, obp, res.chosen, {}),
            ("pp_joint_A", trk + cams, st, obp, (), {})]
    for label, effs, stops, pixels, declared, kw in sets:
        t0 = time.perf_counter()
        h = joint_heldout(tree, effs, stops, pixels, declared, **kw)
        fit = joint_fit(tree, effs, stops, pixels, declared, pose_t=None if stops is None else pose_t, **kw)
        print(f"motoman_joint_{label}: held-out pixels {fmt(h['pixel_rms'])} px, tracker "
              f"{1e3 * h['tracker_rms']:.3f} mm; in-sample {fmt(fit.pixel_rms)} px, {1e3 * fit.tracker_rms:.3f} mm; "
              f"noise {fit.sensor_sigma}; nfev {fit.iterations}; {time.perf_counter() - t0:.1f} s")
        if label in ("joint_A", "pp_joint_A", "pp_cameras_only"):
            structure_lines(label, pixel_residual_structure(pixels, h["pixel_residual"], tree))
        obs_of = Opp if label.startswith("pp_") else O
        for f in files[1:]:
            sc = score_joint(tree, fit, S[f], obs_of[f], declared)
            print(f"motoman_joint_{label}_to_{f}: pixels {fmt(sc['pixel_rms'])} px, tracker "
                  f"{1e3 * sc['tracker_rms']:.3f} mm")
        if label in ("joint_A", "pp_joint_A"):
            for e in fit.effects:
                print(f"motoman_joint_{label}_effect: {e['name']}@{e['location']} " + ", ".join(
                    f"{k} {v:.5f} +- {1.96 * e['sigma'][k]:.5f}" for k, v in e["parameters"].items()))


def swapped_principal_point(obs: Any) -> Any:
    """The Motoman marker pixels with each camera's principal point (cx, cy) exchanged (docs/diagnose.md:
    the source's values fit a portrait image, the detections a landscape one)."""
    out = obs.subset(np.arange(len(obs)))
    out.K = [K.copy() for K in obs.K]
    for K in out.K:
        K[0, 2], K[1, 2] = K[1, 2], K[0, 2]
    return out


def structure_lines(label: str, structure: dict) -> None:
    for f, s in structure.items():
        print(f"motoman_joint_{label}_structure_{f}: held-out {s['rms']:.2f} px; per-pose common "
              f"{s['per_pose_mean_rms']:.2f}, within image {s['within_pose_rms']:.2f}; after tag (marker) offsets "
              f"{s['rms_after_tag_bias']:.2f}, after image position {s['rms_after_image_position']:.2f}, both "
              f"{s['rms_after_tag_bias_and_image_position']:.2f} px; explained by {s['explained_by']}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="at most 4 effects, no nested leave-one-file-out")
    ap.add_argument("--skip-hilti", action="store_true")
    ap.add_argument("--skip-bag", action="store_true")
    ap.add_argument("--skip-motoman", action="store_true")
    ap.add_argument("--skip-joint", action="store_true")
    args = ap.parse_args()
    if not args.skip_joint:
        motoman_joint()
    if not args.skip_motoman:
        motoman()
    if not args.skip_bag:
        ten_minute_bag()
    if not args.skip_hilti:
        hilti(args.quick)
