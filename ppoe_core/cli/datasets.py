"""Dataset-specific readers (Motoman .mat, Hilti YAML) -> diagnose stops and pixels."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ppoe_core.analysis.diagnose.pixels import PixelObs
from ppoe_core.analysis.diagnose.stops import Stops, base_tilt_context, motion_signs
from ppoe_core.errors import ModelConfigError
from ppoe_core.robot.urdf import Robot

# =============================================================================
# Bags, model YAML, report
# =============================================================================


def stops_from_motoman(path: str | Path, robot: Robot, tracker_link: str = "LR1",
                       sigma: float = 2e-4) -> Stops:
    """The Leica tracker points of a Motoman ``.mat`` file (``../shared/datasets/motoman_leica``)
    as :class:`Stops` (one pose per row, poses without a Leica point dropped; one registration
    session per file; ``sigma`` is an assumed tracker noise, the files give none)."""
    from ppoe_core.io.importers.motoman import JOINT_NAMES, load_motoman

    ds = load_motoman(path)
    ok = ds.has_tracker
    J = ds.joints[ok]
    n = int(ok.sum())
    name = Path(path).stem
    return Stops(q={j: J[:, i] for i, j in enumerate(JOINT_NAMES)}, p_meas=ds.leica[ok], kind="point",
                 link=tracker_link, point=np.zeros(3), sigma=sigma, base=robot.root,
                 session=np.zeros(n, dtype=int), session_names=[name], group=np.zeros(n, dtype=int),
                 group_names=[name], reg_mask=np.ones(n, dtype=bool), score_mask=np.ones(n, dtype=bool),
                 context={"motion_sign": {j: s for j, s in zip(JOINT_NAMES, motion_signs(
                     np.arange(n, dtype=float), J, np.arange(n, dtype=float)).T)}})


def stops_from_hilti(path: str | Path, robot: Robot, stationing_set: str | None = "cross",
                     tracker_link: str = "prism", sigma: float = 0.75e-3) -> Stops:
    """A Hilti stationing dataset file (``../shared/datasets/hilti_stationing/*.yaml``) as
    :class:`Stops`, read directly (same content as its ``ppoe import hilti`` bag).

    One registration session per station (column height, solution space); the stationing points
    of ``stationing_set`` define it when scored, evaluation points are scored (README protocol);
    context ``time`` and ``motion_sign`` from the time-ordered waypoints, and ``gravity`` (the
    direction of gravity in ``base_link``) from the base accelerometer ``tilt_sensor_base``
    (mounted with rpy 0 on ``column_base``, which has rpy 0 in ``base_link``), so gravity
    torques and moments follow the tilt of the robot on uneven ground, and ``base_tilt`` (that tilt minus
    its station mean: the robot rocking on its support between stops).
    """
    from ppoe_core.io.importers.hilti import load_hilti

    ds = load_hilti(path)
    stops = ds.stops
    J = np.array([s.joints for s in stops])
    t = np.array([s.time for s in stops])
    a_base = np.array([s.accel_base for s in stops])  # specific force: points up
    q = {name: J[:, i] for i, name in enumerate(ds.joint_names)}
    signs = motion_signs(t, J, t)
    name = Path(path).stem
    stations = list(dict.fromkeys(s.station for s in stops))
    session = np.array([stations.index(s.station) for s in stops])
    gravity = -a_base / np.linalg.norm(a_base, axis=1)[:, None]
    return Stops(
        q=q, p_meas=np.array([s.prism_position for s in stops]), kind="point", link=tracker_link,
        point=np.zeros(3), sigma=sigma, base=robot.root,
        session=session, session_names=[f"{name}:{st}" for st in stations], group=np.zeros(len(stops), dtype=int),
        group_names=[name],
        reg_mask=np.array([s.role == "stationing" and (stationing_set is None or stationing_set in s.point_sets)
                           for s in stops]),
        score_mask=np.array([s.role == "evaluation" and s.solution_space != 4 for s in stops]),
        context={"time": t - t[0], "motion_sign": {n: signs[:, i] for i, n in enumerate(ds.joint_names)},
                 "gravity": gravity, "base_tilt": base_tilt_context(gravity, session)},
        imus={"base": ("tilt_sensor_base", a_base),
              "column_tip": ("tilt_sensor_column_tip", np.array([s.accel_column_tip for s in stops]))},
    )


def pixels_from_motoman(path: str | Path, robot: Robot, model_yaml: str | Path,
                        sigma_px: float = 1.0) -> PixelObs:
    """Marker pixels of a Motoman ``.mat`` file (``../shared/datasets/motoman_leica``).

    Markers hang on ``EE1`` (poses from the dataset's ``model.yaml``); cameras 1 and 2 are
    ``camera_1_optical_frame`` / ``camera_2_optical_frame`` of ``motoman_right.urdf``.
    """
    from ppoe_core.io.importers.motoman import (
        CAMERA_FRAMES,
        JOINT_NAMES,
        load_marker_poses,
        load_motoman,
        load_motoman_cameras,
    )

    ds = load_motoman(path)
    cams = load_motoman_cameras(model_yaml)
    markers = load_marker_poses(model_yaml)
    for f in CAMERA_FRAMES.values():
        if f not in robot.links:
            raise ModelConfigError(f"{path}: camera frame '{f}' is not a link of URDF {robot.source}")
    missing = sorted(set(ds.obs_face.tolist()) - set(markers))
    if missing:
        raise ModelConfigError(f"{model_yaml}: markers/poses has no entry for faces {missing} used in {path}")
    order = sorted(cams)
    point = np.array([markers[int(f)][:3, 3] for f in ds.obs_face])
    J = ds.joints[ds.obs_pose]
    P = len(ds.pose_ids)
    # motion sign: the poses are taken as visited in file order (as stops_from_motoman)
    signs = motion_signs(np.arange(P, dtype=float), ds.joints, np.arange(P, dtype=float))[ds.obs_pose]
    ctx = {"motion_sign": {j: signs[:, i] for i, j in enumerate(JOINT_NAMES)},
           "time": ds.obs_pose.astype(float)}
    return PixelObs(q={j: J[:, i] for i, j in enumerate(JOINT_NAMES)}, link="EE1", point=point, context=ctx,
                    camera=np.array([order.index(int(c)) for c in ds.obs_camera]),
                    cameras=[cams[n].frame for n in order], K=[cams[n].K for n in order],
                    D=[cams[n].D for n in order], uv=ds.obs_uv.copy(), pose=ds.obs_pose.copy(),
                    sigma_px=float(sigma_px), name=Path(path).stem)
