"""Where a planned pose may be: the candidate configurations and the constraints every one of them passes.

Candidates are drawn uniformly inside each independent joint's limits shrunk by a margin (or inside a narrower
``region`` the user gives); a draw is kept when it passes every declared constraint (:class:`Constraints`):

* **joint limits** with ``margin`` [rad or m] (continuous joints: ``[-pi, pi]``);
* **workspace box** (optional): every measured point (tracker reflector) inside ``[lo, hi]`` (root frame) [m];
* **self-collision**: capsules from the URDF's ``<collision>`` geometry (sphere: a point with a radius; cylinder:
  a segment along its z with its radius; box: a segment along its longest axis, radius the half-diagonal of the
  other two; meshes are not modelled and counted), every pair of links not rigidly attached to each other nor
  neighbours through one movable joint must be ``clearance`` apart;
* **tracker line of sight** (optional, ``tracker_at`` in the root frame): the segment from the tracker to each
  reflector clears every capsule of the links not rigidly attached to that reflector's link;
* **tags in view** (optional, with a camera's intrinsics): at least ``min_tags`` of the model's tags with their
  centre at least :data:`MIN_DEPTH` in front of the camera, their normal within ``max_view_angle`` of the line of
  sight and all four corners of its quiet zone (:data:`QUIET_ZONE` times its size) inside the image with a
  :data:`EDGE_MARGIN_PX` margin.

:func:`violations` evaluates every constraint over a batch of configurations (the same function the tests call on
every planned pose).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import PpoeError
from ppoe_core.estimation.camera import project_points
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Capsule", "CameraView", "Constraints", "collision_capsules", "violations", "sample_candidates",
           "joint_bounds", "rigid_bodies", "tags_visible", "QUIET_ZONE", "segment_distance", "MIN_DEPTH",
           "EDGE_MARGIN_PX"]

#: a tag nearer than this to the camera (along its optical axis) is not usable [m]
MIN_DEPTH = 0.1
#: tag corners must be this far inside the image border [px]
EDGE_MARGIN_PX = 10.0
#: a detector needs the white border around the tag: this multiple of the tag's size must be in the image
QUIET_ZONE = 1.25


@dataclass(frozen=True)
class Capsule:
    """A segment ``p0``-``p1`` in ``link`` coordinates [m] swept by a sphere of ``radius`` [m]."""

    link: str
    p0: np.ndarray
    p1: np.ndarray
    radius: float


@dataclass
class CameraView:
    """A camera for the tags-in-view constraint: optical frame (URDF link), intrinsics ``K`` (3, 3), plumb_bob ``D``
    (5,), image ``width`` x ``height`` [px]."""

    frame: str
    K: np.ndarray
    D: np.ndarray
    width: int
    height: int


@dataclass
class Constraints:
    """Every constraint of a plan (module docstring).  ``tags``: the model's tag items (``id``, ``link``, ``size``,
    ``T_link_tag``); ``points``: the measured points as ``(link, xyz)``."""

    margin: float = 0.05
    region: dict[str, tuple[float, float]] = field(default_factory=dict)
    box: tuple[np.ndarray, np.ndarray] | None = None
    capsules: list[Capsule] = field(default_factory=list)
    skipped_meshes: int = 0
    clearance: float = 0.0
    tracker_at: np.ndarray | None = None
    camera: CameraView | None = None
    tags: Sequence = ()
    min_tags: int = 1
    max_view_angle: float = 60.0
    points: list[tuple[str, np.ndarray]] = field(default_factory=list)


def joint_bounds(tree: KinematicTree, c: Constraints) -> dict[str, tuple[float, float]]:
    """Sampling interval of each independent joint: its limits shrunk by the margin, intersected with the region.

    Raises
    ------
    PpoeError
        A prismatic joint without limits, an interval that is empty (margin or region), a region on an unknown joint.
    """
    robot = tree.robot
    bad = sorted(set(c.region) - set(robot.independent_joints))
    if bad:
        raise PpoeError(f"plan: region names {bad}, not independent joints of the URDF")
    out = {}
    for jn in robot.independent_joints:
        j, lim = robot.joints[jn], robot.joints[jn].limit
        if lim is not None and lim.lower is not None and lim.upper is not None and j.type != "continuous":
            lo, hi = float(lim.lower) + c.margin, float(lim.upper) - c.margin
        elif j.type == "prismatic":
            raise PpoeError(f"plan: prismatic joint {jn} has no limits in the URDF")
        else:
            lo, hi = -math.pi, math.pi
        if jn in c.region:
            lo, hi = max(lo, c.region[jn][0]), min(hi, c.region[jn][1])
        if not hi > lo:
            raise PpoeError(f"plan: joint {jn}: no room inside its limits with margin {c.margin} and region "
                            f"{c.region.get(jn)} (interval [{lo:.4g}, {hi:.4g}])")
        out[jn] = (lo, hi)
    return out


def _capsule_of(link: str, el: ET.Element) -> Capsule | None:
    """The capsule of one ``<collision>`` element (None for a mesh or nothing)."""
    o = el.find("origin")
    xyz = np.array([float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()])
    rpy = np.array([float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()])
    T = lie.from_xyz_rpy(xyz, rpy)
    g = el.find("geometry")
    if g is None:
        return None
    axis, half, radius = np.zeros(3), 0.0, 0.0
    if (s := g.find("sphere")) is not None:
        radius = float(s.get("radius", "0"))
    elif (s := g.find("cylinder")) is not None or (s := g.find("capsule")) is not None:
        radius, half, axis = float(s.get("radius", "0")), float(s.get("length", "0")) / 2, np.array([0.0, 0.0, 1.0])
    elif (s := g.find("box")) is not None:
        size = np.array([float(v) for v in s.get("size", "0 0 0").split()])
        k = int(np.argmax(size))
        axis = np.eye(3)[k]
        half = size[k] / 2
        radius = float(np.linalg.norm(np.delete(size, k)) / 2)
    else:
        return None
    p0 = T[:3, :3] @ (-half * axis) + T[:3, 3]
    p1 = T[:3, :3] @ (half * axis) + T[:3, 3]
    return Capsule(link, p0, p1, radius)


def collision_capsules(urdf_text: str) -> tuple[list[Capsule], int]:
    """Capsules of every link's ``<collision>`` elements (module docstring) and the number of meshes skipped."""
    root = ET.fromstring(urdf_text)
    out, meshes = [], 0
    for link in root.findall("link"):
        for el in link.findall("collision"):
            cap = _capsule_of(link.get("name", ""), el)
            if cap is None:
                meshes += 1
            else:
                out.append(cap)
    return out, meshes


def rigid_bodies(tree: KinematicTree) -> dict[str, str]:
    """Link -> the first link of its rigid body (links joined by fixed joints are one body)."""
    robot = tree.robot
    group = {ln: ln for ln in robot.links}

    def find(x: str) -> str:
        while group[x] != x:
            x = group[x]
        return x

    for j in robot.joints.values():
        if not j.movable:
            group[find(j.child)] = find(j.parent)
    return {ln: find(ln) for ln in robot.links}


def _rigid_neighbours(tree: KinematicTree) -> set[frozenset[str]]:
    """Pairs of links that may touch: rigidly attached (fixed joints) or neighbours through one movable joint."""
    robot = tree.robot
    body = rigid_bodies(tree)
    near = {frozenset((body[j.parent], body[j.child])) for j in robot.joints.values()}
    out = set()
    for a in robot.links:
        for b in robot.links:
            if body[a] == body[b] or frozenset((body[a], body[b])) in near:
                out.add(frozenset((a, b)))
    return out


def segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Shortest distance between segments ``a0 a1`` and ``b0 b1`` (..., 3) (clamped closest points)."""
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    a, b, c = (u * u).sum(-1), (u * v).sum(-1), (v * v).sum(-1)
    d, e = (u * w).sum(-1), (v * w).sum(-1)
    den = a * c - b * b
    s = np.where(den > 1e-12, np.clip((b * e - c * d) / np.where(den > 1e-12, den, 1.0), 0, 1), 0.0)
    t = np.where(c > 1e-12, np.clip((b * s + e) / np.where(c > 1e-12, c, 1.0), 0, 1), 0.0)
    s = np.where(a > 1e-12, np.clip((b * t - d) / np.where(a > 1e-12, a, 1.0), 0, 1), 0.0)
    return np.linalg.norm(w + s[..., None] * u - t[..., None] * v, axis=-1)


def _world(poses: Mapping[str, np.ndarray], cap: Capsule) -> tuple[np.ndarray, np.ndarray]:
    T = poses[cap.link]
    return (T[..., :3, :3] @ cap.p0 + T[..., :3, 3], T[..., :3, :3] @ cap.p1 + T[..., :3, 3])


def _collisions(tree: KinematicTree, poses: Mapping[str, np.ndarray], c: Constraints, n: int) -> np.ndarray:
    bad = np.zeros(n, bool)
    skip = _rigid_neighbours(tree)
    world = [_world(poses, cap) for cap in c.capsules]
    for i, ci in enumerate(c.capsules):
        for k in range(i + 1, len(c.capsules)):
            ck = c.capsules[k]
            if frozenset((ci.link, ck.link)) in skip:
                continue
            dist = segment_distance(*world[i], *world[k])
            bad |= dist < ci.radius + ck.radius + c.clearance
    return bad


def _line_of_sight(tree: KinematicTree, poses: Mapping[str, np.ndarray], c: Constraints, n: int) -> np.ndarray:
    bad = np.zeros(n, bool)
    if c.tracker_at is None:
        return bad
    src = np.broadcast_to(np.asarray(c.tracker_at, dtype=float), (n, 3))
    body = rigid_bodies(tree)
    for link, xyz in c.points:
        p = poses[link][..., :3, :3] @ xyz + poses[link][..., :3, 3]
        for cap in c.capsules:
            if body[cap.link] == body[link]:  # the reflector's own body carries it
                continue
            bad |= segment_distance(src, p, *_world(poses, cap)) < cap.radius + c.clearance
    return bad


def tags_visible(poses: Mapping[str, np.ndarray], c: Constraints, n: int) -> np.ndarray:
    """(n, k) bool: tag ``c.tags[k]`` usable in configuration ``i`` (module docstring: in front, facing the camera
    within ``max_view_angle``, the tag and its quiet zone (:data:`QUIET_ZONE` times its size) inside the image)."""
    cam = c.camera
    if cam is None or not c.tags:
        return np.zeros((n, 0), bool)
    T_cam_root = lie.inverse(poses[cam.frame])
    out = np.zeros((n, len(c.tags)), bool)
    cos_max = math.cos(math.radians(c.max_view_angle))
    for k, it in enumerate(c.tags):
        T = T_cam_root @ poses[it.link] @ it.T_link_tag  # (n, 4, 4) tag in the optical frame
        t = T[:, :3, 3]
        facing = -(T[:, :3, 2] * t).sum(-1) / np.maximum(np.linalg.norm(t, axis=-1), 1e-12)
        h = QUIET_ZONE * it.size / 2
        corners = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]])
        P = np.einsum("nij,kj->nki", T[:, :3, :3], corners) + t[:, None, :]
        ok = (t[:, 2] >= MIN_DEPTH) & (facing >= cos_max) & np.all(P[..., 2] > 0.05, axis=1)
        uv = project_points(np.where(P[..., 2:3] > 0.05, P, 1.0).reshape(-1, 3), cam.K, cam.D).reshape(n, 4, 2)
        m = EDGE_MARGIN_PX
        inside = np.all((uv[..., 0] > m) & (uv[..., 0] < cam.width - m) & (uv[..., 1] > m)
                        & (uv[..., 1] < cam.height - m), axis=1)
        out[:, k] = ok & inside
    return out


def _tags_hidden(poses: Mapping[str, np.ndarray], c: Constraints, n: int) -> np.ndarray:
    if c.camera is None or not c.tags:
        return np.zeros(n, bool)
    return tags_visible(poses, c, n).sum(axis=1) < c.min_tags


def violations(tree: KinematicTree, q: Mapping[str, np.ndarray], c: Constraints) -> dict[str, np.ndarray]:
    """Per constraint, which of the configurations ``q`` (joint -> (n,)) violate it, (n,) bool each:
    ``joint_limits``, ``workspace_box``, ``self_collision``, ``line_of_sight``, ``tags_in_view``."""
    n = len(next(iter(q.values())))
    bounds = joint_bounds(tree, c)
    lim = np.zeros(n, bool)
    for jn, (lo, hi) in bounds.items():
        v = np.asarray(q[jn], dtype=float)
        lim |= (v < lo - 1e-12) | (v > hi + 1e-12)
    poses = tree.link_poses(q)
    box = np.zeros(n, bool)
    if c.box is not None:
        for link, xyz in c.points:
            p = poses[link][..., :3, :3] @ xyz + poses[link][..., :3, 3]
            box |= np.any((p < c.box[0]) | (p > c.box[1]), axis=-1)
    return {"joint_limits": lim, "workspace_box": box, "self_collision": _collisions(tree, poses, c, n),
            "line_of_sight": _line_of_sight(tree, poses, c, n), "tags_in_view": _tags_hidden(poses, c, n)}


def _draw(rng: np.random.Generator, lo: float, hi: float, n: int, extremes: float) -> np.ndarray:
    """``n`` uniform draws in ``[lo, hi]``, each replaced by ``lo`` or ``hi`` with probability ``extremes``."""
    v = rng.uniform(lo, hi, n)
    snap = rng.random(n) < extremes
    return np.where(snap, np.where(rng.random(n) < 0.5, lo, hi), v)


def sample_candidates(tree: KinematicTree, c: Constraints, count: int, rng: np.random.Generator,
                      max_draws: int | None = None, extremes: float = 0.0
                      ) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """``count`` random feasible configurations (joint -> (count,)) and, per constraint, how many draws it rejected.
    ``extremes``: probability that a joint's draw is put at an end of its interval instead (D-optimal designs sit
    at the ends of what the constraints allow; uniform draws in many joints rarely reach them).

    Raises
    ------
    PpoeError
        No draw is feasible (empty feasible set), naming the constraint that rejected most.
    """
    bounds = joint_bounds(tree, c)
    max_draws = max_draws or 50 * count
    got: list[dict[str, np.ndarray]] = []
    rejected = {k: 0 for k in ("joint_limits", "workspace_box", "self_collision", "line_of_sight", "tags_in_view")}
    drawn, have = 0, 0
    while have < count and drawn < max_draws:
        batch = min(max(2 * (count - have), 64), max_draws - drawn)
        q = {jn: _draw(rng, lo, hi, batch, extremes) for jn, (lo, hi) in bounds.items()}
        v = violations(tree, q, c)
        ok = np.ones(batch, bool)
        for k, m in v.items():
            rejected[k] += int((m & ok).sum())
            ok &= ~m
        got.append({jn: a[ok] for jn, a in q.items()})
        have += int(ok.sum())
        drawn += batch
    if have == 0:
        worst = max(rejected, key=lambda k: rejected[k])
        raise PpoeError(f"plan: empty feasible set: none of {drawn} random configurations passes the constraints "
                        f"(rejections: {rejected}; most by {worst})")
    out = {jn: np.concatenate([g[jn] for g in got])[:count] for jn in bounds}
    return out, rejected
