"""The paper's Table I study (Sec. V-C) in simulation, with ``config/robots/rover.*``.

Setup
-----
* State: the tool seen from the mast camera, ``T_camera_tool`` (``camera_optical_frame`` ->
  ``tool_link``), prior mean and PPOE covariance from ``PPOEModel.fk``; the "naive" prior has the
  same mean and the static ``naive`` covariance of the model YAML (7 cm lateral, 3 cm
  longitudinal, 5 / 15 deg, tool frame), as in the paper.
* True robots: nominal + a static perturbation of every perturbed joint (mount-plate bending,
  arm joints) drawn from the model's own covariances, the same for all configurations of one
  robot; ``--robots`` robots are simulated.
  ``--truth mismatch`` instead draws errors the model does not describe (isotropic 1 deg and
  3 mm at the mount and every arm joint), a robustness check.
* Camera: pinhole, f = 600 px, 1280 x 960, no distortion.  Measurement: the tag centres' pixel
  coordinates (the paper's eq. 25: 2D bearings, two numbers per tag) of every tag that faces
  the camera (incidence < 75 deg), 0.5 px noise.  ``--points all`` adds the four corners.
* Configurations (random search, seeded, pan/tilt aim the camera at the tool):
  - Experiment I, ``--n1`` (9) configurations: tool 0.5-0.9 m from the camera and strongly
    rotated w.r.t. it: every visible tag is inclined by 40-70 deg;
  - Experiment II, ``--n2`` (29) configurations: arm stretched out (shoulder-tool distance >=
    0.75 m), tool > 1.1 m from the camera, one tag facing the camera (incidence < 20 deg).
* Metric (paper): lateral error = distance between estimated and true tool position
  perpendicular to the tool's z axis (the peg axis), in cm; mean +- std over all robots and
  configurations.

Writes ``docs/img/study_table1.png`` (lateral errors per configuration) and prints the markdown
table (``--table FILE`` writes it too).

Usage::

    python scripts/study_table1.py [--robots 30] [--points centre|all] [--truth model|mismatch] [--seed 0]
                                   [--out docs/img/study_table1.png] [--table FILE]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from ppoe_core.estimation.fusion import iterated_update  # noqa: E402
from ppoe_core.estimation.measurements import TagBearingModel, tag_points  # noqa: E402
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402

__all__ = ["StaticErrors", "find_configurations", "run_study", "main"]

URDF = REPO / "config" / "robots" / "rover.urdf"
MODEL = REPO / "config" / "robots" / "rover_model.yaml"
CAMERA = "camera_optical_frame"
TOOL = "tool_link"
ARM = [f"arm_joint_{i}" for i in range(1, 7)]
K_CAM = np.array([[600.0, 0.0, 640.0], [0.0, 600.0, 480.0], [0.0, 0.0, 1.0]])
IMAGE = (1280, 960)
MAX_INCIDENCE = np.deg2rad(75.0)


class StaticErrors:
    """Effect object for ``PPOEModel(effects=[...])``: a fixed twist per perturbed joint,
    placed where the joint's perturbation sits (eq. 16)."""

    def __init__(self, dxi: Mapping[str, np.ndarray]) -> None:
        self.dxi = {k: np.asarray(v, dtype=float) for k, v in dxi.items()}

    def corrections(self, q: Mapping[str, Any], context: Mapping[str, Any]):
        return {}, dict(self.dxi)


def draw_robot(model: PPOEModel, rng: np.random.Generator) -> StaticErrors:
    """One true robot: ``xi_j ~ N(0, Sigma_j)`` for every perturbed joint of the model."""
    return StaticErrors({
        j: p.factor @ rng.standard_normal(p.factor.shape[1]) for j, p in model.config.perturbations.items()
    })


def draw_mismatched_robot(model: PPOEModel, rng: np.random.Generator) -> StaticErrors:
    """A true robot whose errors do NOT follow the model: isotropic 1 deg and 3 mm at the
    mount plate and at every arm joint (the model says 1/1/5 deg at the mount, 0.5 deg and no
    translation at the joints)."""
    sig = np.r_[0.003, 0.003, 0.003, np.deg2rad([1.0, 1.0, 1.0])]
    return StaticErrors({j: sig * rng.standard_normal(6) for j in model.config.perturbations})


def _aim(model: PPOEModel, q_arm: np.ndarray) -> np.ndarray:
    """pan / tilt (N, 2) that point the camera at the tool of arm configurations (N, 6)."""
    T_base_tool = model.fk_mean({n: q_arm[:, i] for i, n in enumerate(ARM)}, "base_link", TOOL)
    zero = np.zeros(q_arm.shape[0])
    T_base_tilt = model.fk_mean({"pan_joint": zero, "tilt_joint": zero}, "base_link", "tilt_link")
    d = T_base_tool[:, :3, 3] - T_base_tilt[:, :3, 3]
    pan = np.arctan2(d[:, 1], d[:, 0])
    tilt = np.arctan2(-d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    return np.stack([pan, np.clip(tilt, -1.2, 1.2)], axis=-1)


def _joints(q_arm: np.ndarray, pt: np.ndarray) -> dict:
    out = {n: q_arm[..., i] for i, n in enumerate(ARM)}
    out["pan_joint"] = pt[..., 0]
    out["tilt_joint"] = pt[..., 1]
    return out


def _tag_geometry(model: PPOEModel, joints: dict):
    """Per tag: camera-frame centre (N, 3) and incidence angle (N,) [rad]."""
    out = {}
    for item in model.config.tags.items:
        T = model.fk_mean(joints, CAMERA, item.link) @ item.T_link_tag
        p = T[..., :3, 3]
        n = T[..., :3, 2]
        cosang = -np.einsum("...i,...i->...", n, p) / np.linalg.norm(p, axis=-1)
        out[item.id] = (p, np.arccos(np.clip(cosang, -1, 1)))
    return out


def find_configurations(model: PPOEModel, experiment: int, n: int, rng: np.random.Generator,
                        batch: int = 4000, max_batches: int = 200) -> list[dict]:
    """Random search for ``n`` joint configurations of experiment I or II (module docstring)."""
    lo = np.array([model.robot.joints[j].limit.lower for j in ARM])
    hi = np.array([model.robot.joints[j].limit.upper for j in ARM])
    picked: list[np.ndarray] = []
    for _ in range(max_batches):
        q = rng.uniform(lo, hi, size=(batch, 6))
        pt = _aim(model, q)
        joints = _joints(q, pt)
        T_ct = model.fk_mean(joints, CAMERA, TOOL)
        dist = np.linalg.norm(T_ct[:, :3, 3], axis=-1)
        T_sh_tool = model.fk_mean({n: q[:, i] for i, n in enumerate(ARM)}, "arm_link_1", TOOL)
        reach = np.linalg.norm(T_sh_tool[:, :3, 3] - np.array([0.0, 0.0, 0.155]), axis=-1)
        geo = _tag_geometry(model, joints)
        inc = np.stack([g[1] for g in geo.values()], axis=-1)  # (N, tags)
        pc = np.stack([g[0] for g in geo.values()], axis=-2)  # (N, tags, 3)
        vis = (inc < MAX_INCIDENCE) & (pc[..., 2] > 0.2)
        uv = pc[..., :2] / np.where(pc[..., 2:] > 0.2, pc[..., 2:], 1.0) * 600.0 + np.array([640.0, 480.0])
        inside = (uv[..., 0] > 40) & (uv[..., 0] < IMAGE[0] - 40) & (uv[..., 1] > 40) & (uv[..., 1] < IMAGE[1] - 40)
        vis &= inside
        best = np.where(vis, inc, np.inf).min(axis=-1)
        # tool above the deck, not inside the rover body
        above = model.fk_mean({n: q[:, i] for i, n in enumerate(ARM)}, "base_link", TOOL)[:, 2, 3] > 0.1
        if experiment == 1:
            vis_inc = np.where(vis, inc, np.nan)
            ok = (dist > 0.5) & (dist < 0.9) & vis.any(-1) & above
            with np.errstate(invalid="ignore"):
                ok &= np.nanmin(np.where(vis, vis_inc, np.inf), axis=-1) > np.deg2rad(40)
                ok &= np.nanmax(np.where(vis, vis_inc, -np.inf), axis=-1) < np.deg2rad(70)
        else:
            ok = (dist > 1.1) & (reach >= 0.75) & (best < np.deg2rad(20)) & above
        for i in np.flatnonzero(ok):
            qi = np.r_[q[i], pt[i]]
            if all(np.linalg.norm(qi - p) > 0.5 for p in picked):  # spread the configurations
                picked.append(qi)
            if len(picked) == n:
                return [_joints(p[:6], p[6:]) for p in picked]
    raise RuntimeError(f"experiment {experiment}: found only {len(picked)} of {n} configurations")


def _observation(model: PPOEModel, joints: dict, points: str) -> TagBearingModel | None:
    """Tag model (state T_camera_tool) of the tags that face the camera in this configuration."""
    geo = _tag_geometry(model, joints)
    pts, labels = [], []
    for item in model.config.tags.items:
        p, inc = geo[item.id]
        if inc < MAX_INCIDENCE and p[2] > 0.2:
            T_tool_tag = model.fk_mean(joints, TOOL, item.link) @ item.T_link_tag
            tp = tag_points(item.size, T_tool_tag)
            sel = tp[:1] if points == "centre" else tp
            pts.append(sel)
            labels += [f"tag {item.id} point {k}" for k in range(sel.shape[0])]
    if not pts:
        return None
    sigma = model.config.camera.pixel_sigma if model.config.camera is not None else 0.5
    return TagBearingModel(np.vstack(pts), K_CAM, None, pixel_sigma=sigma, labels=labels, name="tags")


def _lateral_cm(T_est: np.ndarray, T_true: np.ndarray) -> float:
    e = T_true[:3, :3].T @ (T_est[:3, 3] - T_true[:3, 3])
    return 100.0 * float(np.hypot(e[0], e[1]))


def run_study(model: PPOEModel, configs: list[dict], n_robots: int, points: str, seed: int,
              truth: str = "model") -> dict:
    """Lateral errors [cm], arrays (robots, configs) for "fk", "ppoe", "naive"."""
    naive_cov = model.config.naive.covariance
    rng_robot = np.random.default_rng(seed)  # robots: independent of the measurement variant
    rng = np.random.default_rng(seed + 10_000)  # pixel noise
    out = {k: np.full((n_robots, len(configs)), np.nan) for k in ("fk", "ppoe", "naive", "diag")}
    n_tags, sig_lat = [], []
    cam_err = {k: [] for k in ("fk", "ppoe", "naive")}  # position errors in camera axes [m]
    for r in range(n_robots):
        draw = draw_robot if truth == "model" else draw_mismatched_robot
        true_model = PPOEModel(model.robot, model.config, effects=[draw(model, rng_robot)])
        for c, joints in enumerate(configs):
            X0, P = model.fk(joints, CAMERA, TOOL)
            X_true = true_model.fk_mean(joints, CAMERA, TOOL)
            obs = _observation(model, joints, points)
            out["fk"][r, c] = _lateral_cm(X0, X_true)
            cam_err["fk"].append(X0[:3, 3] - X_true[:3, 3])
            if r == 0:
                sig_lat.append(100.0 * np.sqrt(P[0, 0] + P[1, 1]))
            if obs is None:
                continue
            n_tags.append(obs.dim // (2 if points == "centre" else 10))
            z = obs.h(X_true) + rng.normal(0.0, obs.pixel_sigma, obs.dim)
            for key, cov in (("ppoe", P), ("naive", naive_cov), ("diag", np.diag(np.diag(P)))):
                res = iterated_update(X0, cov, z, obs, max_iterations=20, gate_probability=None)
                out[key][r, c] = _lateral_cm(res.T, X_true)
                if key in cam_err:
                    cam_err[key].append(res.T[:3, 3] - X_true[:3, 3])
    out["tags_per_image"] = float(np.mean(n_tags)) if n_tags else 0.0
    out["ppoe_lateral_sigma_cm"] = float(np.mean(sig_lat))
    out["camera_axes_rms_cm"] = {k: 100.0 * np.sqrt(np.mean(np.square(v), axis=0)) for k, v in cam_err.items()}
    return out


def _plot(results: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 3.4), gridspec_kw={"width_ratios": [1, 2.4]})
    for ax, (name, res) in zip(axes, results.items()):
        k = np.arange(res["fk"].shape[1])
        for key, label, color, dx in (("fk", "forward kinematics", "0.5", -0.22), ("ppoe", "2D, PPOE", "tab:blue", 0.0),
                                       ("naive", "2D, naive", "tab:orange", 0.22)):
            v = res[key]
            ax.errorbar(k + dx, np.nanmean(v, 0), yerr=np.nanstd(v, 0), fmt="o", ms=3, color=color,
                        label=label, capsize=2, lw=0.8)
        ax.set(xlabel="configuration", ylabel="lateral error [cm]", title=name)
        ax.set_xticks(k)
        ax.tick_params(axis="x", labelsize=6)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=30, help="simulated true robots (default 30)")
    ap.add_argument("--points", choices=("centre", "all"), default="centre",
                    help="tag centres only (paper eq. 25, default) or centre + corners")
    ap.add_argument("--n1", type=int, default=9, help="configurations of experiment I (default 9)")
    ap.add_argument("--n2", type=int, default=29, help="configurations of experiment II (default 29)")
    ap.add_argument("--truth", choices=("model", "mismatch"), default="model",
                    help="true errors drawn from the PPOE model (default) or from a different one")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img" / "study_table1.png")
    ap.add_argument("--table", type=Path, default=None, help="write the markdown table here too")
    args = ap.parse_args(argv)

    model = PPOEModel.from_files(URDF, MODEL)
    rng = np.random.default_rng(args.seed)
    exps = {
        f"Experiment I ({args.n1} close, rotated)": find_configurations(model, 1, args.n1, rng),
        f"Experiment II ({args.n2} stretched, facing)": find_configurations(model, 2, args.n2, rng),
    }
    results = {name: run_study(model, cfgs, args.robots, args.points, args.seed + 1 + i, args.truth)
               for i, (name, cfgs) in enumerate(exps.items())}
    _plot(results, args.out)

    def cell(v):
        return f"{np.nanmean(v):.2f} +- {np.nanstd(v):.2f}"

    names = list(results)
    lines = [
        f"Lateral error [cm], mean +- std over {args.robots} simulated robots x the configurations "
        f"(true errors: {'drawn from the PPOE model' if args.truth == 'model' else 'mismatched model'}); "
        f"measurement: tag {'centres' if args.points == 'centre' else 'centres and corners'}, 0.5 px noise.",
        "",
        "| method | covariance | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
        "| forward kinematics | - | " + " | ".join(cell(results[n]["fk"]) for n in names) + " |",
        "| 2D estimation | PPOE | " + " | ".join(cell(results[n]["ppoe"]) for n in names) + " |",
        "| 2D estimation | naive | " + " | ".join(cell(results[n]["naive"]) for n in names) + " |",
        "| 2D estimation | diagonal of PPOE | " + " | ".join(cell(results[n]["diag"]) for n in names) + " |",
        "| paper (real LRU): FK / PPOE / naive | | 0.82 / 0.29 / 0.44 | 1.48 / 0.50 / 0.52 |",
        "",
        "Visible tags per image: " + ", ".join(f"{n}: {results[n]['tags_per_image']:.2f}" for n in names) + ".",
        "PPOE lateral 1-sigma (sqrt(var x + var y), tool frame; naive: 9.9 cm): "
        + ", ".join(f"{n}: {results[n]['ppoe_lateral_sigma_cm']:.2f} cm" for n in names)
        + ".",
        "Position error RMS along the camera axes x, y (image plane), z (depth) [cm]: "
        + "; ".join(
            f"{n}: "
            + ", ".join(f"{k} {np.array2string(v, precision=2)}" for k, v in results[n]["camera_axes_rms_cm"].items())
            for n in names
        )
        + ".",
        "Share of (robot, configuration) pairs where PPOE beats naive: "
        + ", ".join(f"{n}: {100 * np.nanmean(results[n]['ppoe'] < results[n]['naive']):.0f} %" for n in names)
        + ".",
    ]
    text = "\n".join(lines)
    print(text)
    if args.table is not None:
        args.table.write_text(text + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
