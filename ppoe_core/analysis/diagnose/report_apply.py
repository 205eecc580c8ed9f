"""The report's "How to apply" section and the corrected ``camera_info`` files of a diagnosis.

``ppoe diagnose --out DIR`` writes three model files; this module says in the report which one to use where, with
commands and parameter names of this repository (``ppoe fk``, ``ppoe evaluate``, ``launch/ppoe.launch.py``, the
nodes' ``model_file``, ``robot_description``, ``camera_info_topic``) and robot_state_publisher's
``robot_description``, what the calibrated URDF applies (:func:`~ppoe_core.analysis.diagnose.calibrated_urdf.
plan_calibration`) and what it leaves out, and writes a camera calibration file
(``camera_info_<frame>.yaml``, the camera_calibration_parsers format ``camera_info_manager`` reads) for each
camera whose intrinsics diagnose corrected: the nodes take ``K`` and ``D`` from the ``CameraInfo`` topic, not from
the model, so a corrected camera is applied where the camera driver publishes it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ppoe_core.analysis.diagnose.calibrated_urdf import CalibrationPlan
from ppoe_core.analysis.diagnose.results import DiagnoseResult, EffectReport

__all__ = ["apply_section", "camera_info_name", "camera_info_yaml", "camera_sizes", "write_camera_infos"]

#: file names ``ppoe diagnose --out DIR`` writes (ppoe_core/cli/diagnose.py)
URDF_FILE, CAL_MODEL_FILE, DIAG_MODEL_FILE = "robot_calibrated.urdf", "model_calibrated.yaml", "model_diagnosed.yaml"


def camera_info_name(frame: str) -> str:
    """File name of a camera's corrected calibration (``camera_info_<frame>.yaml``)."""
    return f"camera_info_{frame.replace('/', '_')}.yaml"


def camera_sizes(bags: Sequence[str | Path]) -> dict[str, tuple[int, int]]:
    """``frame_id -> (width, height)`` of the first ``/camera/camera_info`` per frame in ``bags`` (none: {})."""
    from ppoe_core.io.messages import TOPIC_CAMERA_INFO
    from ppoe_core.io.reader import read_bag

    out: dict[str, tuple[int, int]] = {}
    for bag in bags:
        ci = read_bag(bag, topics=[TOPIC_CAMERA_INFO], load_images=False, accept_partial=True).camera_info
        for k, frame in enumerate(ci.frame_ids):
            out.setdefault(frame, (int(ci.width[k]), int(ci.height[k])))
    return out


def camera_info_yaml(frame: str, camera_info: Mapping[str, Any], size: tuple[int, int] | None) -> str:
    """A camera calibration file (camera_calibration_parsers' YAML, as ``camera_info_manager`` loads from a
    ``camera_info_url``): the corrected ``K`` and ``D``, identity rectification, ``P = [K | 0]``; ``size``
    (width, height) [px] from the bag's ``camera_info`` (0 x 0 when unknown: then fill it in)."""
    K = [float(v) for v in camera_info["K"]]
    D = [float(v) for v in camera_info["D"]]
    P = [K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, K[6], K[7], K[8], 0.0]
    w, h = size if size is not None else (0, 0)

    def mat(rows: int, cols: int, data: Sequence[float]) -> str:
        return f"  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(v) for v in data)}]\n"

    return (f"# {frame}: intrinsics corrected by ppoe diagnose (camera_intrinsics effect); camera_calibration_parsers\n"
            f"# format: give it to the camera driver as camera_info_url:=file:///ABSOLUTE/PATH/{camera_info_name(frame)}"
            f"\n{'' if size else '# image size unknown (no camera_info in the bags): set image_width / image_height'}\n"
            f"image_width: {w}\nimage_height: {h}\ncamera_name: {frame}\n"
            f"camera_matrix:\n{mat(3, 3, K)}distortion_model: {camera_info.get('distortion_model', 'plumb_bob')}\n"
            f"distortion_coefficients:\n{mat(1, len(D), D)}"
            f"rectification_matrix:\n{mat(3, 3, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])}"
            f"projection_matrix:\n{mat(3, 4, P)}")


def write_camera_infos(result: DiagnoseResult, out_dir: str | Path,
                       sizes: Mapping[str, tuple[int, int]] | None = None) -> list[Path]:
    """``camera_info_<frame>.yaml`` in ``out_dir`` for every ``camera_intrinsics`` effect found."""
    out = []
    for e in result.effects:
        if e.camera_info is None:
            continue
        frame = e.frame or e.location
        path = Path(out_dir) / camera_info_name(frame)
        path.write_text(camera_info_yaml(frame, e.camera_info, (sizes or {}).get(frame)), encoding="utf-8")
        out.append(path)
    return out


def _effect_args(result: DiagnoseResult, plan: CalibrationPlan) -> list[str]:
    """``--effects`` arguments that refit the applied components only (the effects that stay in the model as
    found; a static effect with nothing applied left out)."""
    args = []
    for e in result.found:
        comps = plan.applied.get(e.key)
        if e.key in plan.in_model or (comps is not None and len(comps) == e.n_params):
            args.append(f"'{e.key}'")
        elif comps:
            args.append(f"'{e.name}@{e.location}[{','.join(comps)}]'")
    return args


def apply_section(result: DiagnoseResult, plan: CalibrationPlan, out_dir: str | Path,
                  declared: Sequence[str] = ()) -> list[str]:
    """Markdown lines of "How to apply" (module docstring); ``declared``: keys of the model YAML's static
    effects (folded in full)."""
    d = str(Path(out_dir).resolve())
    applied = [f"`{k}` ({', '.join(c)})" for k, c in plan.applied.items()]
    folded = applied + [f"`{k}` (declared in the model YAML)" for k in declared]
    lines = ["", "## How to apply", "",
             f"Three model files are written to `{d}`:", "",
             (f"* `{URDF_FILE}`: the URDF with " + ", ".join(folded) + " folded into the joint origins; link and "
              "joint names unchanged." if folded else f"* `{URDF_FILE}`: the original URDF with a comment only: no "
              "significant static component (joint_offset, link_error, camera_extrinsics) to fold in."),
             f"* `{CAL_MODEL_FILE}`: the model YAML that goes with it: static effects removed (they are in the URDF)"
             + (", " + ", ".join(f"`{k}`" for k in plan.in_model) + " kept as effects" if plan.in_model else "")
             + (f"; perturbation sigmas and joint noise scaled by {result.sigma_scale:.3g} (the declared prior's scale "
                "as the data estimate it)." if math.isfinite(result.sigma_scale) else "."),
             f"* `{DIAG_MODEL_FILE}`: the alternative for the original, unchanged URDF: every effect found (also the "
             "components left out of the calibrated URDF) as model effects.", ""]
    lines += _not_applied(result, plan)
    lines += ["Check the calibration and score it on another recording of the same robot:", "", "```bash",
              f"ppoe fk --urdf {d}/{URDF_FILE} --model {d}/{CAL_MODEL_FILE} --joints NAME=VALUE ...",
              f"ppoe evaluate OTHER_BAG --urdf {d}/{URDF_FILE} --model {d}/{CAL_MODEL_FILE}",
              "```", "",
              "On the robot: robot_state_publisher publishes the calibrated URDF (latched `robot_description` topic "
              "and TF); the ppoe nodes take the URDF from that topic (`robot_description_topic`) and the model from "
              "`model_file`:", "", "```bash",
              f'ros2 run robot_state_publisher robot_state_publisher --ros-args -p robot_description:="$(cat '
              f'{d}/{URDF_FILE})"',
              f"ros2 run ppoe_ros kinematics_node --ros-args -p model_file:={d}/{CAL_MODEL_FILE}",
              f"ros2 run ppoe_ros fusion_node --ros-args -p model_file:={d}/{CAL_MODEL_FILE}",
              "# or all of it: launch/ppoe.launch.py",
              f"ros2 launch ppoe_ros ppoe.launch.py urdf:={d}/{URDF_FILE} model:={d}/{CAL_MODEL_FILE} "
              "robot_state_publisher:=true",
              "# keeping the original URDF instead: the same nodes with",
              f"#   -p model_file:={d}/{DIAG_MODEL_FILE}",
              "```"]
    lines += _camera_lines(result, d)
    return lines


def _not_applied(result: DiagnoseResult, plan: CalibrationPlan) -> list[str]:
    """The table of found static components left out of the calibrated URDF, and how to refit without them."""
    if not plan.not_applied:
        return []
    lines = ["Not applied (left out of the calibrated URDF and of the calibrated model, kept in the diagnosed model "
             "for the record): a component whose 95 % interval contains zero cannot be told from zero by these data, "
             "and folding its estimate would move a joint origin by noise.", "",
             "| effect | component | value | 95 % CI | why |", "|---|---|---|---|---|"]
    lines += [f"| {n.effect} | {n.parameter} | {n.value:.6g} | [{n.ci[0]:.6g}, {n.ci[1]:.6g}] | {n.reason} |"
              for n in plan.not_applied]
    args = _effect_args(result, plan)
    if args:
        lines += ["", "To refit the applied components alone (their values then do not lean on the ones left out):",
                  "", "```bash", "ppoe diagnose BAG... --model MODEL.yaml --out DIR --effects " + " ".join(args),
                  "```"]
    return lines + [""]


def _camera_lines(result: DiagnoseResult, d: str) -> list[str]:
    """How to apply corrected camera intrinsics and extrinsics."""
    lines: list[str] = []
    cams: list[EffectReport] = [e for e in result.effects if e.camera_info is not None]
    if cams:
        lines += ["", "Camera intrinsics cannot go into a URDF. `ppoe evaluate` applies the model's "
                  "`camera_intrinsics` entry to the bag's camera_info; the nodes do not: `tag_bearing_node` and "
                  "`fusion_node` read `K` and `D` from the `CameraInfo` on their `camera_info_topic`. On the robot, "
                  "give the corrected calibration to the camera driver (`camera_info_url`, read by "
                  "camera_info_manager):", ""]
        for e in cams:
            frame = e.frame or e.location
            lines.append(f"* `{frame}`: `{d}/{camera_info_name(frame)}` (e.g. "
                         f"`camera_info_url:=file://{d}/{camera_info_name(frame)}`)")
    if any(e.name == "camera_extrinsics" for e in result.effects):
        lines += ["", "Camera extrinsics are a correction of the camera's mount joint: with the calibrated URDF, "
                  "robot_state_publisher publishes the corrected camera frame itself; with the original URDF and "
                  f"`{DIAG_MODEL_FILE}`, `fusion_node` publishes it on `/tf_static` as the camera frame plus "
                  "`tf_camera_suffix` (default `_calibrated`)."]
    return lines
