"""The simulated camera: tags at their TRUE pose on their links (``tag_offset``) seen through the TRUE intrinsics
(``camera_intrinsics``), while ``/camera/camera_info`` carries the declared ones.

Two outputs (scenario ``camera.format``): rendered images (:func:`ppoe_core.sensing.tags.render_tags`; the tools
detect the tags), or ``observations``: the corners of every tag in view projected through the true camera, with
Gaussian pixel noise, turned into the rows the tag bearing node publishes on ``/tag_bearing/observations``
(:func:`ppoe_core.sensing.tag_rows.rows_from_detections` with the declared intrinsics: undistorted coordinates and
the centre from the corners), so a bag needs no image decoding and no detector (fast, and the pixel noise is
known exactly).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import ScenarioError
from ppoe_core.estimation.camera import project_points
from ppoe_core.sensing.tag_rows import rows_from_detections
from ppoe_core.sensing.tags import TagDetection, render_tags, tag_points_local
from ppoe_core.sim.scenario_checks import key_location

__all__ = ["check_camera_truth", "tag_poses_cam", "visible_tags", "camera_events", "observation_rows"]

#: a tag counts as in view when it faces the camera within this angle [deg] ...
MAX_VIEW_ANGLE_DEG = 70.0
#: ... and all its corners (of a square 1.25x the tag, the quiet zone) are this far inside the image [px]
EDGE_MARGIN_PX = 5.0


def check_camera_truth(sim: Any) -> None:
    """The camera and tag truths of simulator ``sim`` fit its scenario: ``camera_intrinsics`` at the scenario
    camera's frame, ``tag_offset`` at a tag of the model; sets ``sim.cam["K_true"]`` / ``["D_true"]``."""
    for i, e in enumerate(sim.true.effects):
        where = key_location(sim.path, f"truth.effects[{i}]")
        if e["name"] == "camera_intrinsics" and (sim.cam is None or e["location"] != sim.cam["frame"]):
            raise ScenarioError(f"{where}: camera_intrinsics at '{e['location']}' needs the scenario camera with "
                                f"that frame (camera.frame = {sim.cam['frame'] if sim.cam else None!r})")
        if e["name"] == "tag_offset":
            ids = [f"tag_{it.id}" for it in sim.model.tags.items] if sim.model.tags is not None else []
            if e["location"] not in ids:
                raise ScenarioError(f"{where}: tag_offset at '{e['location']}': the model {sim.model.source} has "
                                    f"the tags {ids}")
    if sim.cam is not None:
        sim.cam["K_true"], sim.cam["D_true"] = sim.true.true_camera(sim.cam["frame"], sim.cam["K"], sim.cam["D"])


def tag_poses_cam(sim: Any, poses: Mapping[str, np.ndarray]) -> tuple[np.ndarray, list[int], np.ndarray]:
    """True tag poses in the camera's optical frame (n, k, 4, 4), their ids and sizes [m], from the true link
    poses ``poses`` and the true tag mounts (model mount @ tag offset)."""
    T_cam_root = lie.inverse(poses[sim.cam["frame"]])
    items = sim.model.tags.items
    Ts = np.stack([T_cam_root @ poses[it.link] @ it.T_link_tag @ sim.true.tag_offset(it.id) for it in items], axis=1)
    return Ts, [it.id for it in items], np.array([it.size for it in items])


def visible_tags(cam: Mapping[str, Any], T_cam_tags: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(n, k) bool: tag in front, facing the camera (< :data:`MAX_VIEW_ANGLE_DEG`) and all corners of its quiet
    zone inside the image (margin :data:`EDGE_MARGIN_PX`), through the TRUE intrinsics."""
    n, k = T_cam_tags.shape[:2]
    vis = np.zeros((n, k), bool)
    K, D = cam.get("K_true", cam["K"]), cam.get("D_true", cam["D"])
    for a in range(n):
        for b in range(k):
            T = T_cam_tags[a, b]
            t = T[:3, 3]
            if t[2] < 0.1:
                continue
            if -(T[:3, 2] @ t) / np.linalg.norm(t) < math.cos(math.radians(MAX_VIEW_ANGLE_DEG)):
                continue
            P = tag_points_local(sizes[b] * 1.25) @ T[:3, :3].T + t
            if np.any(P[:, 2] < 0.05):
                continue
            uv = project_points(P, K, D)
            m = EDGE_MARGIN_PX
            if np.all((uv[:, 0] > m) & (uv[:, 0] < cam["w"] - m) & (uv[:, 1] > m) & (uv[:, 1] < cam["h"] - m)):
                vis[a, b] = True
    return vis


def observation_rows(cam: Mapping[str, Any], T_cam_tags: np.ndarray, ids: list[int], sizes: np.ndarray,
                     visible: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``/tag_bearing/observations`` rows ``[id, corner, u, v, x, y]`` of one image: the corners of the ``visible``
    (k,) tags (poses ``T_cam_tags`` (k, 4, 4)) through the TRUE camera plus N(0, ``pixel_sigma``^2) per pixel
    coordinate, then the tag bearing node's rows with the DECLARED intrinsics."""
    dets = []
    for b in np.flatnonzero(visible):
        P = tag_points_local(sizes[b])[1:] @ T_cam_tags[b, :3, :3].T + T_cam_tags[b, :3, 3]
        uv = project_points(P, cam["K_true"], cam["D_true"]) + cam["pixel_sigma"] * rng.standard_normal((4, 2))
        dets.append(TagDetection(int(ids[b]), uv, uv.mean(axis=0)))
    rows, _ = rows_from_detections(dets, cam["K"], cam["D"])
    return rows


def camera_events(sim: Any, events: list[tuple[float, int, str, tuple]]) -> set[int]:
    """Images (or observation rows) of the tags at their true poses, stamped with the camera's time offset; the
    ids seen."""
    cam = sim.cam
    seen: set[int] = set()
    ts = sim.sensor_times(cam["rate"], cam["during"])
    Q, S, G = sim.state_at(ts)
    poses = sim.truth_poses(Q, S, G, ts)
    Ts, ids, sizes = tag_poses_cam(sim, poses)
    vis = visible_tags(cam, Ts, sizes) if cam["format"] == "observations" else None
    for i, t in enumerate(ts):
        st = float(t + cam["time_offset"])
        if vis is not None:
            rows = observation_rows(cam, Ts[i], ids, sizes, vis[i], sim.rng)
            seen.update(int(v) for v in rows[:, 0])
            events.append((st, 1, "obs", (rows,)))
            continue
        img, drawn = render_tags((cam["w"], cam["h"]), cam["K_true"], cam["D_true"], Ts[i], ids, sizes,
                                 dictionary=sim.model.tags.family, background=cam["background"],
                                 noise_sigma=cam["noise"], rng=sim.rng, blur_sigma=cam["blur"])
        seen.update(drawn)
        events.append((st, 1, "cam", (img,)))
    return seen
