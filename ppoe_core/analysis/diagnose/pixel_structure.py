"""Where a held-out pixel residual concentrates: per tag point, per robot pose, over the image.

The catalogue effects move whole links and cameras; two things they cannot express leave a typical print in
the residual of the tag pixels:

* **tag point on its link** (a wrong tag pose on its plate): a 3D offset of that point on its link, i.e. the
  pixel change it makes at each pose (``tag_bias``; without a chain: a constant pixel offset per tag);
* **camera intrinsics / distortion** (a wrong principal point, focal length or distortion centre): a smooth
  function of where the point falls in the image, the same for every tag and pose (``image_position``: a
  quadratic in the normalised image coordinates, per axis).

:func:`pixel_residual_structure` measures how much of each camera's residual each model predicts on held-out
robot poses (k folds over ``PixelObs.pose``, as the pixel stage's CV), and the split into a per-pose common part
(shared by all points of one image: arm or camera pose) and the scatter within an image.  It attributes
nothing by itself: it says where the rest is, so that a model error outside the catalogue is found and named.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.pixels import PixelObs, predict_pixels
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

#: a model "explains" the residual when it lowers the held-out RMS by this fraction at least
EXPLAINS_FRACTION = 0.3


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if len(r) else float("nan")


def _cv_predict(X: np.ndarray, r: np.ndarray, groups: np.ndarray, folds: int, seed: int) -> np.ndarray:
    """Held-out prediction of ``r`` (M, 2) by least squares on the design ``X`` (M, 2, p) (row i, axis a:
    ``r[i, a] ~ X[i, a] @ b``), k folds over ``groups``; a parameter not seen in training predicts 0."""
    ids = np.unique(groups)
    perm = np.random.default_rng(seed).permutation(ids)
    out = np.zeros_like(r)
    for k in range(min(folds, len(ids))):
        test = np.isin(groups, perm[k::folds])
        if not (~test).any():
            continue
        A = X[~test].reshape(-1, X.shape[2])
        b = np.linalg.lstsq(A, r[~test].reshape(-1), rcond=None)[0]
        out[test] = X[test] @ b
    return out


def _tag_keys(obs: PixelObs, rows: np.ndarray) -> np.ndarray:
    links = obs.row_links()[rows]
    keys = [f"{ln}:{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}" for ln, p in zip(links, obs.point[rows])]
    return np.unique(np.array(keys), return_inverse=True)[1].reshape(-1)


def _per_axis(F: np.ndarray) -> np.ndarray:
    """Design (M, 2, 2p) fitting the columns of ``F`` (M, p) to u and v with separate coefficients."""
    Z = np.zeros_like(F)
    return np.stack([np.concatenate([F, Z], axis=1), np.concatenate([Z, F], axis=1)], axis=1)


def _image_features(uv_pred: np.ndarray, K: np.ndarray) -> np.ndarray:
    x = (uv_pred[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv_pred[:, 1] - K[1, 2]) / K[1, 1]
    return _per_axis(np.column_stack([np.ones_like(x), x, y, x * x, y * y, x * y]))


def _tag_design(tag: np.ndarray, J: np.ndarray | None) -> np.ndarray:
    """Per-tag design: a constant pixel offset per tag (``J`` None), or the pixel change of a 3D offset of the
    tag point on its link (``J`` (M, 2, 3): d uv / d point)."""
    onehot = (tag[:, None] == np.arange(tag.max() + 1)[None, :]).astype(float)
    if J is None:
        return _per_axis(onehot)
    return (J[:, :, None, :] * onehot[:, None, :, None]).reshape(len(tag), 2, -1)


def point_jacobian(tree: KinematicTree, obs: PixelObs, effects: Sequence[Effect] = (), h: float = 1e-4) -> np.ndarray:
    """d uv / d point (M, 2, 3) [px/m]: how each row's pixel moves with its tag point on its link (central
    differences of :func:`predict_pixels`)."""
    J = np.zeros((len(obs), 2, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        hi, lo = obs.subset(np.arange(len(obs))), obs.subset(np.arange(len(obs)))
        hi.point, lo.point = obs.point + d, obs.point - d
        J[:, :, k] = (predict_pixels(tree, hi, effects) - predict_pixels(tree, lo, effects)) / (2 * h)
    return J


def _camera_structure(obs: PixelObs, c: int, r: np.ndarray, J: np.ndarray | None, folds: int,
                      seed: int) -> dict[str, Any]:
    rows = (obs.camera == c) & np.all(np.isfinite(r), axis=1)
    R, P = r[rows], obs.pose[rows]
    tag = _tag_keys(obs, rows)
    tags = _tag_design(tag, None if J is None else J[rows])
    img = _image_features(obs.uv[rows] - R, obs.K[c])
    pose_mean = np.zeros_like(R)
    for p in np.unique(P):
        pose_mean[P == p] = R[P == p].mean(axis=0)
    rms = _rms(R)
    out: dict[str, Any] = {"n": int(rows.sum()), "rms": rms, "tags": int(tag.max() + 1),
                           "tag_model": "pixel offset" if J is None else "point offset on its link",
                           "per_pose_mean_rms": _rms(pose_mean), "within_pose_rms": _rms(R - pose_mean)}
    for name, X in (("tag_bias", tags), ("image_position", img),
                    ("tag_bias_and_image_position", np.concatenate([tags, img], axis=2))):
        out[f"rms_after_{name}"] = _rms(R - _cv_predict(X, R, P, folds, seed))
    gains = {name: 1.0 - out[f"rms_after_{name}"] / rms for name in ("tag_bias", "image_position")}
    out["explained_by"] = sorted((n for n, g in gains.items() if g >= EXPLAINS_FRACTION), key=lambda n: -gains[n])
    return out


def pixel_residual_structure(obs: PixelObs, residual: np.ndarray, tree: KinematicTree | None = None,
                             effects: Sequence[Effect] = (), folds: int = 5,
                             seed: int = 0) -> dict[str, dict[str, Any]]:
    """Structure of a (held-out) pixel residual, per camera (module docstring).

    Parameters
    ----------
    obs : PixelObs
        The observations (``uv`` measured; the image position of a row is ``uv - residual``).
    residual : ndarray, shape (M, 2)
        Measured minus predicted pixels [px] (NaN rows are skipped), e.g. held out by pose.
    tree, effects : KinematicTree, effects, optional
        With ``tree``, a tag's error is a 3D offset of its point on its link (the pixel change by
        :func:`point_jacobian` on the chain with ``effects``); without, a constant pixel offset per tag.

    Returns
    -------
    dict
        Camera frame -> ``n``, ``rms``, ``tags``, ``per_pose_mean_rms`` (the part common to one image),
        ``within_pose_rms``, ``rms_after_tag_bias`` / ``rms_after_image_position`` /
        ``rms_after_tag_bias_and_image_position`` (held-out RMS after that model, k folds over poses) [px],
        ``explained_by``: the models that lower it by at least ``EXPLAINS_FRACTION``, best first.
    """
    r = np.asarray(residual, dtype=float)
    if r.shape != (len(obs), 2):
        raise ValueError(f"{obs.name}: residual has shape {r.shape}, expected ({len(obs)}, 2)")
    J = None if tree is None else point_jacobian(tree, obs, effects)
    return {f: _camera_structure(obs, c, r, J, folds, seed) for c, f in enumerate(obs.cameras)
            if np.any((obs.camera == c) & np.all(np.isfinite(r), axis=1))}


#: what each structure model stands for, in words (summary lines)
MEANING = {"image_position": "camera intrinsics / distortion (principal point, focal length, distortion centre), "
                             "outside the effect catalogue",
           "tag_bias": "tag points off their nominal place on their links, not among the fitted effects"}


def structure_summary(structure: dict[str, dict[str, Any]]) -> str:
    """Summary lines for the cameras whose held-out residual a structure model explains ("" if none): model
    errors the fitted effects do not cover."""
    lines = []
    for f, s in structure.items():
        for name in s["explained_by"]:
            lines.append(f"\nTag pixels of {f}: the held-out residual ({s['rms']:.2f} px) follows the "
                         f"{name.replace('_', ' ')} ({s[f'rms_after_{name}']:.2f} px without it): "
                         f"{MEANING[name]}.")
    return "".join(lines)
