"""Inputs of the replay besides the fusion pipeline: the joint matrix of a bag's (possibly split) joint states and
a recorded estimate topic to score beside the replayed methods."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import BagError
from ppoe_core.model.joint_history import JointHistory

__all__ = ["JOINT_MAX_AGE_S", "joint_matrix", "recorded_estimate", "required_joints"]

#: a joint value a split joint-state message lacks is taken from an earlier message at most this old [s]
#: (the kinematics node's ``joint_max_age`` default)
JOINT_MAX_AGE_S = 0.5


def joint_matrix(js: Any, joint_names: Sequence[str], bag: str, max_age_s: float = JOINT_MAX_AGE_S,
                 required: set[str] | None = None) -> tuple[np.ndarray, int]:
    """Joint states -> (N, n) in ``joint_names`` order, merged per joint as the nodes merge them
    (:meth:`ppoe_core.model.joint_history.JointHistory.merge_rows`): a joint a message lacks (or has no finite
    value for) takes its latest earlier value while that is at most ``max_age_s`` old (0: no limit); rows that
    cannot be completed are NaN.

    Returns the matrix and the number of values held from a previous message.  A joint of ``required`` (default:
    every joint) that the bag never carries (or never with a finite value) is a BagError; another one is held at
    0 (a joint off every chain the evaluation uses, e.g. the other arm of a dual-arm robot).
    """
    cols = []
    for name in joint_names:
        if name not in js.names:
            if required is not None and name not in required:
                cols.append(-1)
                continue
            raise BagError(
                f"bag {bag}: topic /joint_states never carries joint {name!r} that the model chain needs "
                f"(carries {js.names})"
            )
        k = js.names.index(name)
        if not np.isfinite(js.positions[:, k]).any():
            raise BagError(f"bag {bag}: topic /joint_states: joint {name!r} has no finite value")
        cols.append(k)
    carried = [k for k in cols if k >= 0]
    Q_carried, held = JointHistory([js.names[k] for k in carried], max_age_ns=int(round(max_age_s * 1e9))).merge_rows(
        js.stamps, js.positions[:, carried])
    Q = np.zeros((len(js), len(joint_names)))
    Q[:, [j for j, k in enumerate(cols) if k >= 0]] = Q_carried
    return Q, held


def recorded_estimate(est_T: dict[str, np.ndarray], est_cov: dict[str, np.ndarray], data: Any, topic: str,
                      base: str, gt_stamps: np.ndarray, bag: str) -> None:
    """``est_T/est_cov["recorded"]``: the latest pose of ``topic`` (``PoseWithCovarianceStamped`` in the base
    frame, e.g. what ``ppoe record`` took of ``/ppoe/fused_pose``) at or before each ground-truth stamp (NaN before
    the first); its ROS covariance converted to the tool-frame tangent space."""
    series = data.poses_with_covariance.get(topic)
    if series is None or len(series) == 0:
        raise BagError(f"bag {bag}: --estimate {topic}: no PoseWithCovarianceStamped messages on it (has "
                       f"{sorted(data.poses_with_covariance)})")
    frames = sorted(set(series.frame_ids) - {base})
    if frames:
        raise BagError(f"bag {bag}: --estimate {topic}: frame_id {frames[0]!r}, expected the base frame {base!r}")
    order = np.argsort(series.stamps, kind="stable")
    st = series.stamps[order]
    j = np.searchsorted(st, gt_stamps, side="right") - 1
    ok = j >= 0
    T = np.full((len(gt_stamps), 4, 4), np.nan)
    C = np.full((len(gt_stamps), 6, 6), np.nan)
    T[ok] = series.T[order][j[ok]]
    C[ok] = lie.cov_ros_to_local(T[ok], series.cov_ros[order][j[ok]])
    est_T["recorded"], est_cov["recorded"] = T, C


def required_joints(model: Any, links: set[str]) -> set[str]:
    """Joints on the chains from the root to ``links`` and to every link the model YAML's sensors hang on
    (trackers, tags, camera, contact, IMUs); links not in the URDF are skipped."""
    cfg, robot = model.config, model.robot
    links = set(links) | {t.link for t in cfg.trackers} | {i.link for i in cfg.imus.values()}
    if cfg.tags is not None:
        links |= {it.link for it in cfg.tags.items}
    if cfg.camera is not None:
        links.add(cfg.camera.frame)
    if cfg.contact is not None:
        links |= {cfg.contact.plane_frame, cfg.contact.tool_link}
    return {j for ln in links if ln in robot.links for j in robot.path_from_root(ln)}
