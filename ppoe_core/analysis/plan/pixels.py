"""Tag pixels in the design: the rows the engine's pixel block would fit at a candidate configuration.

With a camera (``--camera-info``) and the model's tags, every candidate configuration also contributes one image:
the centre and four corners of every tag usable there (:func:`~ppoe_core.analysis.plan.constraints.tags_visible`),
as rows of the engine's :class:`~ppoe_core.analysis.diagnose.block_pixels.PixelBlock` at the nominal model (the
predicted pixels as measurements).  Its :meth:`linearise` gives the derivative of each pixel w.r.t. the target
parameters and w.r.t. the camera's pose, ``camera_extrinsics`` at the camera's mount joint, which the design treats
as a nuisance (eliminated with the tracker registration: the camera's pose is not known to better than the data
say).  Rows are whitened with the model's ``camera.pixel_sigma``.  A configuration's rows are padded to all tags
(zeros for a tag not usable there), so every configuration has ``10 k`` pixel components (``k`` tags).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ppoe_core.analysis.diagnose.block_pixels import PixelBlock
from ppoe_core.analysis.diagnose.noise import NoiseScales, whitening
from ppoe_core.analysis.diagnose.pixels import PixelObs, camera_mount_joint, project
from ppoe_core.analysis.plan.constraints import Constraints, tags_visible
from ppoe_core.model.effects import Effect, make_effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.estimation.measurements import tag_points

__all__ = ["pixel_rows", "POINTS_PER_TAG"]

#: centre and four corners
POINTS_PER_TAG = 5


def _observations(tree: KinematicTree, c: Constraints, q: Mapping[str, np.ndarray], vis: np.ndarray,
                  sigma_px: float, declared: Sequence[Effect]) -> tuple[PixelObs, np.ndarray, np.ndarray]:
    """The predicted observations of the usable tags (``vis`` (M, k)), their configuration and tag index per row."""
    cam = c.camera
    assert cam is not None
    u, k = np.nonzero(vis)
    u, k = np.repeat(u, POINTS_PER_TAG), np.repeat(k, POINTS_PER_TAG)
    corner = np.tile(np.arange(POINTS_PER_TAG), int(vis.sum()))
    items = list(c.tags)
    point = np.array([tag_points(items[t].size, items[t].T_link_tag)[i] for t, i in zip(k, corner)])
    local = np.array([tag_points(items[t].size)[i] for t, i in zip(k, corner)])
    links = np.array([items[t].link for t in k], dtype=object)
    ids = np.array([items[t].id for t in k], dtype=int)
    obs = PixelObs(q={j: np.asarray(v, dtype=float)[u] for j, v in q.items()}, link=str(links[0]), point=point,
                   camera=np.zeros(u.size, dtype=int), cameras=[cam.frame], K=[cam.K], D=[cam.D],
                   uv=np.zeros((u.size, 2)), pose=u, sigma_px=float(sigma_px), name="plan",
                   links=links if len(set(links.tolist())) > 1 else None, tag=ids, tag_point=local,
                   tag_poses={it.id: np.asarray(it.T_link_tag, dtype=float) for it in items})
    obs.uv = project(tree, obs, list(declared)).uv
    return obs, u, k * POINTS_PER_TAG + corner


def pixel_rows(tree: KinematicTree, c: Constraints, q: Mapping[str, np.ndarray], targets: Sequence,
               sigma_px: float, declared: Sequence[Effect] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Whitened pixel columns of the targets ``G`` (M, 10 k, P) and of the camera pose ``N`` (M, 10 k, 6) at the
    configurations ``q`` (joint -> (M,)) (module docstring); zeros where a tag is not usable."""
    M = len(next(iter(q.values())))
    P = sum(len(t.comps) for t in targets)
    k = len(c.tags)
    G = np.zeros((M, k * POINTS_PER_TAG, 2, P))
    N = np.zeros((M, k * POINTS_PER_TAG, 2, 6))
    vis = tags_visible(tree.link_poses(q), c, M)
    if vis.any():
        assert c.camera is not None
        obs, u, slot = _observations(tree, c, q, vis, sigma_px, declared)
        cam_pose = make_effect("camera_extrinsics", camera_mount_joint(tree.robot, c.camera.frame), tree)
        lin = PixelBlock(tree, obs).linearise(list(declared), [*(t.effect for t in targets), cam_pose], {}, {})
        W = whitening(lin.S, np.zeros_like(lin.S), NoiseScales(a=1.0, k=0.0))
        J = np.concatenate([Jc[:, :, t.comps] for Jc, t in zip(lin.J[:-1], targets)], axis=2)
        G[u, slot] = W @ J
        N[u, slot] = W @ lin.J[-1]
    return G.reshape(M, -1, P), N.reshape(M, -1, 6)
