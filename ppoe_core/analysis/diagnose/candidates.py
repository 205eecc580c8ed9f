"""Candidate effects of a tracker or pose measurement (catalogue x plausible locations of the measured chain), the
nominal prediction of its rows and their chain Jacobians."""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.model.effects import Effect, make_effect, sum_effect_corrections
from ppoe_core.robot.tree import KinematicTree, LinkPoses

_BENDING_EXTENSION = ("compliance_x", "compliance_y", "extension_x", "extension_y")


def carried_mass(tree: KinematicTree, joint: str) -> float:
    """Mass [kg] of everything ``joint`` carries (URDF inertials)."""
    m = 0.0
    for ln in tree.subtree_links(joint):
        inert = tree.robot.links[ln].inertial
        if inert is not None:
            m += inert.mass
    return m


def candidate_effects(tree: KinematicTree, stops: Stops) -> list[Effect]:
    """Catalogue effects at every plausible location of the measured chain (zero parameters).

    * ``joint_offset``: every movable joint on the path to the measured link;
    * ``gravity_compliance``: movable joints carrying mass (URDF inertials);
    * ``lateral_compliance``: revolute joints carrying mass (bending about the two axes
      perpendicular to the joint axis; each axis its own sign check);
    * ``mount_bending``: fixed and prismatic joints carrying mass (a telescopic segment bends
      at its overlap); at prismatic joints also with a compliance linear in the extension
      (``extension_x``, ``extension_y``: the overlap shrinks as the stage extends);
    * ``link_error`` (6 components; unidentifiable ones are pruned during selection): every
      joint on the path;
    * ``backlash``: independent movable joints whose last-motion sign changes (context);
    * ``thermal_growth``: joints with an origin offset above 5 cm, against the measured
      ``temperature`` (``/temperature``) if it varies by more than 1 K, else against time if the
      data span more than 10 minutes (the effect's ``variable`` says which);
    * ``time_offset``: if the joints move at the measurement times (context ``joint_velocity``);
    * ``base_tilt`` with ``variable="measured"`` (tracker points, an accelerometer on the root: context
      ``base_tilt``): the root rotated by the tilt that accelerometer measures at each stop (minus its
      session mean, which the registration absorbs), times one ``gain``: a robot rocking on its support.

    A constant ``base_tilt`` is a nuisance of the accelerometer block (per placement), ``camera_extrinsics``,
    ``camera_intrinsics`` and ``tag_offset`` are candidates of the pixel block; ``tracker_registration`` is always
    estimated per session.
    """
    robot = tree.robot
    path = stops.chain_joints(robot)
    if stops.kind == "pose" and stops.base and stops.base != robot.root:
        base_path = set(robot.path_from_root(stops.base))
        path = [j for j in path if j not in base_path]
    return chain_candidates(tree, path, stops.context, point=stops.kind == "point", stream_offset=True)


def chain_candidates(tree: KinematicTree, joints: Sequence[str], context: Mapping[str, Any], point: bool = True,
                     stream_offset: bool = False) -> list[Effect]:
    """The chain effects of :func:`candidate_effects` at ``joints`` (``context``: the rows' effect context);
    ``point``: a point measurement (a measured base tilt is offered with a ``base_tilt`` context);
    ``stream_offset``: offer the joint-state stream's ``time_offset``."""
    robot = tree.robot
    out: list[Effect] = []
    signs = context.get("motion_sign", {})
    vel = context.get("joint_velocity", {})
    for jn in joints:
        j = robot.joints[jn]
        if j.movable:
            out.append(make_effect("joint_offset", jn, tree))
        out.append(make_effect("link_error", jn, tree))
        mass = carried_mass(tree, jn)
        if j.movable and mass > 0.0:
            out.append(make_effect("gravity_compliance", jn, tree))
        if j.movable and j.type != "prismatic" and mass > 0.0:
            out.append(make_effect("lateral_compliance", jn, tree))
        if not j.movable and mass > 0.0:
            out.append(make_effect("mount_bending", jn, tree))
        if j.type == "prismatic" and mass > 0.0:  # telescopic: compliance growing with the extension (nested in it:
            out.append(make_effect("mount_bending", jn, tree, components=_BENDING_EXTENSION))  # the constant one)
        if j.independent and jn in signs and np.ptp(signs[jn]) > 0:
            out.append(make_effect("backlash", jn, tree))
        if np.linalg.norm(j.origin[:3, 3]) > 0.05:
            out.extend(_thermal(tree, jn, context))
    if stream_offset and vel and max(float(np.max(np.abs(v))) for v in vel.values()) > 1e-6:
        out.append(make_effect("time_offset", "/joint_states", tree))
    if point and "base_tilt" in context:
        out.append(make_effect("base_tilt", robot.root, tree, variable="measured"))
    return out


def _thermal(tree: KinematicTree, joint: str, context: Mapping) -> list[Effect]:
    """``thermal_growth`` at ``joint`` against the temperature (if it varies by > 1 K), else against time
    (if the data span > 10 min), else none."""
    temp, t = context.get("temperature"), context.get("time")
    if temp is not None and np.all(np.isfinite(temp)) and np.ptp(temp) > 1.0:
        return [make_effect("thermal_growth", joint, tree, variable="temperature",
                            reference=float(np.min(temp)))]
    if t is not None and np.ptp(t) > 600.0:
        return [make_effect("thermal_growth", joint, tree, variable="time", reference=float(np.min(t)))]
    return []


def predict_nominal(tree: KinematicTree, stops: Stops, declared: Sequence[Effect],
                    corrections: tuple[dict, dict] | None = None, motions: dict[str, np.ndarray] | None = None,
                    poses: LinkPoses | None = None) -> tuple[np.ndarray, np.ndarray | None, dict, dict, dict]:
    """Prediction of the measured points (and tool rotations for poses) with the effects ``declared`` (or their
    ``corrections`` ``(dq, dxi)`` if the caller has them); returns x0 (N,3), R0, poses (of the measured links, the
    base and their ancestors: :func:`pose_links`), dq, dxi.  ``motions``: :meth:`KinematicTree.link_poses`' cache
    for ``stops.q``; ``poses``: those link poses at these corrections, if the caller has them."""
    dq, dxi = corrections if corrections is not None else sum_effect_corrections(declared, stops.q, stops.context)
    if poses is None:
        poses = tree.link_poses(stops.q, dq, dxi, links=pose_links(stops), motions=motions)
    T = measured_link_poses(stops, poses)
    if stops.kind == "pose" and stops.base and stops.base != tree.root:
        T = lie.inverse(poses[stops.base]) @ T
    x0 = np.einsum("nij,nj->ni", T[:, :3, :3], stops.point_rows()) + T[:, :3, 3]
    return x0, (T[..., :3, :3] if stops.kind == "pose" else None), poses, dq, dxi


def pose_links(stops: Stops) -> list[str]:
    """The links whose poses :func:`predict_nominal` needs: the measured links and the base (with their
    ancestors)."""
    return [*stops.chain_links(), *([stops.base] if stops.base else [])]


def row_link_poses(poses: Mapping[str, np.ndarray], link: str, links: np.ndarray | None, n: int) -> np.ndarray:
    """``T_root_link`` of each of ``n`` rows, (n, 4, 4), from :meth:`KinematicTree.link_poses` output: the rows'
    own links ``links`` ((n,) of str), or ``link`` for every row when ``links`` is None."""
    T = np.broadcast_to(poses[link], (n, 4, 4))
    if links is None:
        return T
    for ln in dict.fromkeys(links.tolist()):
        T = np.where((links == ln)[:, None, None], np.broadcast_to(poses[ln], T.shape), T)
    return T


def measured_link_poses(stops: Stops, poses: Mapping[str, np.ndarray]) -> np.ndarray:
    """``T_root_link`` of each row's measured link, (N, 4, 4) (several reflectors: per row)."""
    return row_link_poses(poses, stops.link, stops.links, len(stops))


def chain_jacobians(tree: KinematicTree, stops: Stops, poses: Mapping[str, np.ndarray], dq: Mapping,
                    dxi: Mapping, joints: Collection[str] | None = None) -> tuple[dict, dict, dict, dict]:
    """Jacobians of each row's measured point and link frame w.r.t. the eq. 16 insertions (at ``joints`` only when
    given: :meth:`KinematicTree.frame_jacobian`).

    Returns ``(Jq, Jx, Fq, Fx)`` as :meth:`KinematicTree.point_jacobian` (root-frame position, (N, 3)
    and (N, 3, 6)) and :meth:`KinematicTree.frame_jacobian` (tangent at the link, (N, 6) and
    (N, 6, 6)); with several reflectors, each row takes its own link's Jacobian (zero for joints off
    that link's path).
    """
    point = stops.point_rows()

    def both(ln: str) -> tuple[dict, dict, dict, dict]:
        frame = tree.frame_jacobian(stops.q, ln, poses, dq, dxi, joints)
        return (*tree.point_jacobian(stops.q, ln, point, poses, dq, dxi, frame=frame), *frame)

    if stops.links is None:
        return both(stops.link)
    rows, n = stops.row_links(), len(stops)
    out: tuple[dict, dict, dict, dict] = ({}, {}, {}, {})
    for ln in stops.chain_links():
        m = rows == ln
        parts = both(ln)
        for acc, part, tail in zip(out, parts, ((3,), (3, 6), (6,), (6, 6))):
            for k, v in part.items():
                masked = np.where(m.reshape((n,) + (1,) * len(tail)), np.broadcast_to(v, (n, *tail)), 0.0)
                acc[k] = acc[k] + masked if k in acc else masked
    return out
