"""Tag pixels (and contacts) of a contract bag: :func:`pixels_from_bag`, :func:`contacts_from_bag`."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.block_contact import Contacts
from ppoe_core.analysis.diagnose.load_stops import static_mean
from ppoe_core.analysis.diagnose.pixels import PixelObs
from ppoe_core.errors import BagError
from ppoe_core.model.context import motion_band, motion_signs, sample_series
from ppoe_core.robot.config import load_model_config
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["pixels_from_bag", "contacts_from_bag"]


def pixels_from_bag(path: str | Path, robot: Robot, model_yaml: str | Path | Any, sigma_px: float = 1.0,
                    refine: str = "subpix", accept_partial: bool = False,
                    group_name: str | None = None) -> PixelObs:
    """Tag pixels of a contract bag as :class:`PixelObs` (centre and corner points).

    ``/tag_bearing/observations`` if the bag has it (e.g. the Motoman importer: marker centres),
    else tags detected on the camera images with the tag bearing node's function
    (:func:`ppoe_core.sensing.tag_rows.observe_tags`).  Tags (id -> link, size, pose) come from the
    model YAML's ``tags`` section; intrinsics from ``/camera/camera_info`` (per ``frame_id``);
    joint values from ``/joint_states`` at each observation stamp.  Each message is one pose.  ``model_yaml``: the
    model file or its loaded config; ``group_name``: the bag's name in a diagnosis (default: its directory's).

    Raises
    ------
    BagError
        No tag observations or images, a camera frame without CameraInfo, an observed id the
        model does not list.  Tags on several links give a per-row ``links`` array.
    """
    from ppoe_core.estimation.measurements import tag_points
    from ppoe_core.io import bagio

    cfg = model_yaml if hasattr(model_yaml, "tags") else load_model_config(str(model_yaml), robot)
    if cfg.tags is None or not cfg.tags.items:
        raise BagError(f"{model_yaml}: no 'tags' section: pixels of bag {path} cannot be attributed to links")
    by_id = cfg.tags.by_id()
    links = sorted({t.link for t in cfg.tags.items})
    data = bagio.read_bag(path, load_images=True, accept_partial=accept_partial)
    ci = data.camera_info
    intr: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for i, f in enumerate(ci.frame_ids):
        intr.setdefault(f, (ci.K[i], ci.D[i]))
    rows_all, frames, stamps = _pixel_rows(data, path, intr, cfg, by_id, refine)
    rows = np.concatenate(rows_all) if rows_all else np.zeros((0, 5))
    if len(rows) == 0:
        raise BagError(f"bag {path}: no tag observed in {len(frames)} messages")
    msg = rows[:, 0].astype(int)
    ids = np.rint(rows[:, 1]).astype(int)
    unknown = sorted(set(ids.tolist()) - set(by_id))
    if unknown:
        raise BagError(f"bag {path}: observed tag ids {unknown} are not in {model_yaml} tags")
    corner = np.rint(rows[:, 2]).astype(int)
    point = np.array([tag_points(by_id[t].size, by_id[t].T_link_tag)[c] for t, c in zip(ids, corner)])
    cams = sorted(set(frames[k] for k in np.unique(msg)))
    missing = [f for f in cams if f not in intr]
    if missing:
        raise BagError(f"bag {path}: no /camera/camera_info for camera frames {missing}")
    for f in cams:
        if f not in robot.links:
            raise BagError(f"bag {path}: camera frame {f!r} is not a link of URDF {robot.source}")
    q, ctx = _joints_at(data.joint_states, robot, np.asarray(stamps)[msg], path, [*links, *cams])
    ctx["sensor"] = np.array([frames[k] for k in msg])  # the camera of each row (a camera's time_offset)
    row_links = np.array([by_id[t].link for t in ids], dtype=object)
    tag_point = np.array([tag_points(by_id[t].size)[c] for t, c in zip(ids, corner)])
    return PixelObs(q=q, context=ctx, link=str(row_links[0]), point=point,
                    camera=np.array([cams.index(frames[k]) for k in msg]), cameras=cams,
                    K=[intr[f][0] for f in cams], D=[intr[f][1] for f in cams], uv=rows[:, 3:5].copy(),
                    pose=msg, sigma_px=float(sigma_px), name=Path(path).name,
                    links=row_links if len(set(row_links.tolist())) > 1 else None, tag=ids, tag_point=tag_point,
                    tag_poses={t: np.asarray(by_id[t].T_link_tag, dtype=float) for t in set(ids.tolist())},
                    group=np.zeros(len(ids), dtype=int), group_names=[group_name or Path(path).name])


def _pixel_rows(data: Any, path: str | Path, intr: dict[str, tuple[np.ndarray, np.ndarray]], cfg: Any,
                by_id: dict, refine: str) -> tuple[list[np.ndarray], list[str], list[float]]:
    """Rows ``[message, id, corner, u, v]`` per message from ``/tag_bearing/observations`` or, without it, from
    tags detected on the images (the tag bearing node's function); camera frame and stamp per message."""
    from ppoe_core.sensing.tag_rows import observe_tags

    rows_all: list[np.ndarray] = []  # [msg, id, corner, u, v]
    frames: list[str] = []
    stamps: list[float] = []
    obs = data.tag_observations
    if len(obs):
        for i in range(len(obs)):
            m = obs.message(i)
            frames.append(obs.frame_ids[i])
            stamps.append(float(obs.stamps[i]))
            rows_all.append(np.column_stack([np.full(m["ids"].shape, i), m["ids"], m["corners"], m["uv"]]))
    elif len(data.images):
        imgs = data.images
        for i in range(len(imgs)):
            f = imgs.frame_ids[i]
            if f not in intr:
                raise BagError(f"bag {path}: topic {imgs.topic} message {i}: "
                               f"no /camera/camera_info with frame_id {f!r}")
            r, _ = observe_tags(imgs.decode(i), *intr[f], cfg.tags.family, tuple(by_id), refine)
            frames.append(f)
            stamps.append(float(imgs.stamps[i]))
            rows_all.append(np.column_stack([np.full(len(r), i), r[:, :4]]))
    else:
        raise BagError(f"bag {path}: neither /tag_bearing/observations nor camera images")
    return rows_all, frames, stamps


def _joints_at(js: Any, robot: Robot, at: np.ndarray, path: str | Path,
               links: Sequence[str] = ()) -> tuple[dict[str, np.ndarray], dict]:
    """Joint values at the observation stamps ``at`` and the context (time, joint velocity, motion sign).

    A joint the bag never carries is held at 0 when it is off the chains of ``links`` (markers, cameras: e.g.
    the other arm of a dual-arm robot), else an error naming it."""
    order = np.argsort(js.stamps, kind="stable")
    t_js = js.stamps[order]
    q: dict[str, np.ndarray] = {}
    vel: dict[str, np.ndarray] = {}
    cols = []
    needed = {j for ln in links for j in robot.path_from_root(ln)}
    for j in KinematicTree(robot).joint_names:
        if j not in js.names and links and j not in needed:
            q[j], vel[j] = np.zeros(len(at)), np.zeros(len(at))
            cols.append(np.zeros(len(t_js)))
            continue
        col = js.column(j)[order]
        good = np.isfinite(col)
        if not np.any(good):
            raise BagError(f"bag {path}: /joint_states carries no value of joint {j!r}")
        q[j] = sample_series(t_js[good], col[good], at)
        cols.append(np.interp(t_js, t_js[good], col[good]))
        v = np.gradient(col[good], t_js[good]) if good.sum() > 1 else np.zeros(good.sum())
        vel[j] = sample_series(t_js[good], v, at)
    P = np.column_stack(cols)
    band = motion_band(P)
    signs = motion_signs(t_js, P, at, band)
    names = list(q)
    q = dict(zip(names, static_mean(t_js, P, at, band, np.column_stack([q[j] for j in names])).T))
    ctx = {"time": at - t_js[0], "joint_velocity": vel,
           "motion_sign": {j: signs[:, i] for i, j in enumerate(q)}}
    return q, ctx


def contacts_from_bag(path: str | Path, robot: Robot, cfg: Any, group_name: str | None = None,
                      accept_partial: bool = False) -> Contacts | None:
    """The contacts of a bag's ``/wrench`` stream with the model's ``contact`` plane (None: no wrench or no
    ``contact`` section): the wrenches run through the contact node's detector
    (:func:`ppoe_core.sensing.contact.contact_stamps`), one contact per episode in contact, at its middle stamp
    (the robot presses and rests); joint values from ``/joint_states`` there."""
    from ppoe_core.io import bagio
    from ppoe_core.sensing.contact import ContactDetector, contact_stamps, plane_from_config

    contact = getattr(cfg, "contact", None)
    if contact is None:
        return None
    data = bagio.read_bag(path, load_images=False, accept_partial=accept_partial)
    w = data.wrench
    if w is None or len(w) == 0:
        return None
    det = ContactDetector(contact.force_threshold, contact.release_threshold)
    t_in, _ = contact_stamps(w.stamps, w.force, det)
    if t_in.size == 0:
        return None
    dt = np.diff(t_in)
    gap = 5.0 * float(np.median(dt)) if dt.size else 1.0
    starts = np.r_[0, np.flatnonzero(dt > gap) + 1]
    ends = np.r_[starts[1:], t_in.size]
    mid = np.array([t_in[(a + b - 1) // 2] for a, b in zip(starts, ends)])
    plane = plane_from_config(contact, None)
    q, ctx = _joints_at(data.joint_states, robot, mid, path, [contact.tool_link, plane.frame])
    n = mid.size
    return Contacts(q=q, link=contact.tool_link, point=np.asarray(contact.tool_xyz, dtype=float),
                    plane_frame=plane.frame, T_frame_plane=plane.T_frame_plane,
                    sigma=float(np.sqrt(plane.cov_plane[2, 2])), group=np.zeros(n, dtype=int),
                    group_names=[group_name or Path(path).name], context=ctx)
