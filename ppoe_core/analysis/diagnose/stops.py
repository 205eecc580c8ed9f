"""Static stops of a diagnose run (:class:`Stops`): tracker points or 6D poses, with accelerometers and context.
Reading them from a bag: :mod:`ppoe_core.analysis.diagnose.load_stops`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core.errors import BagError
from ppoe_core.model.context import motion_signs
from ppoe_core.robot.urdf import Robot

__all__ = ["Stops", "base_tilt_context", "motion_signs"]

# =============================================================================
# Data
# =============================================================================


@dataclass
class Stops:
    """Static measurements, one row per stop.

    Attributes
    ----------
    q : dict[str, ndarray (N,)]
        Independent joint values [rad or m].
    p_meas : ndarray (N, 3)
        ``kind="point"``: reflector position in the tracker frame [m]; ``kind="pose"``: tool
        position in the base frame [m].
    R_meas : ndarray (N, 3, 3) or None
        ``kind="pose"``: measured tool orientation in the base frame.
    kind : str
        ``"point"`` (tracker point, registration per session) or ``"pose"``.
    link : str
        Link that carries the reflector (``point``) or the tool frame (``pose``); with several
        reflectors (``links`` set) the first one.
    point : ndarray (3,) or (N, 3)
        Reflector position in its link [m] (zeros for ``pose``), or one per row.
    sigma : float or ndarray (N,)
        1-sigma per axis of the position measurement [m], or one per row.
    links : ndarray (N,) of str or None
        Several reflectors (the model's ``trackers``): the link of each row's reflector.  Rows of
        reflectors measured in the same tracker frame share a session (one registration).
    sigma_rot : float
        1-sigma per axis of the orientation measurement [rad] (``pose`` only).
    session : ndarray (N,) int
        Registration session of each stop (index into ``session_names``).
    group : ndarray (N,) int
        Source bag/file of each stop (index into ``group_names``), for leave-one-group-out.
    reg_mask : ndarray (N,) bool
        Stops allowed to define their session's registration when it is fitted for scoring
        (Hilti: the stationing points).
    score_mask : ndarray (N,) bool
        Stops that are scored in such a session (Hilti: the evaluation points).
    context : dict
        Effect context per stop (``time`` (N,), ``motion_sign`` {joint: (N,)},
        ``joint_velocity`` {joint: (N,)}, ``gravity`` (N, 3)).
    imus : dict name -> (link, specific force (N, 3) [m/s^2] in that link's axes)
        Accelerometers at each stop; fitted by :func:`diagnose_imu` (base tilt per group and
        IMU-visible effects), and they break location ties of the point / pose stage.
    """

    q: dict[str, np.ndarray]
    p_meas: np.ndarray
    kind: str
    link: str
    point: np.ndarray
    sigma: float | np.ndarray
    session: np.ndarray
    session_names: list[str]
    group: np.ndarray
    group_names: list[str]
    reg_mask: np.ndarray
    score_mask: np.ndarray
    context: dict[str, Any] = field(default_factory=dict)
    R_meas: np.ndarray | None = None
    sigma_rot: float = 1e-3
    base: str = ""
    imus: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    links: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.p_meas.shape[0])

    def row_links(self) -> np.ndarray:
        """The link of each row's measured point / frame, (N,) of str."""
        return self.links if self.links is not None else np.full(len(self), self.link, dtype=object)

    def chain_links(self) -> list[str]:
        """The measured links, in first-seen order (one unless several reflectors)."""
        return list(dict.fromkeys(self.row_links().tolist())) if self.links is not None else [self.link]

    def point_rows(self) -> np.ndarray:
        """Reflector position of each row in its link, (N, 3) [m]."""
        return np.broadcast_to(np.asarray(self.point, dtype=float), (len(self), 3))

    def sigma_rows(self) -> np.ndarray:
        """1-sigma per axis of each row's position measurement, (N,) [m]."""
        return np.broadcast_to(np.asarray(self.sigma, dtype=float), (len(self),))

    def chain_joints(self, robot: Robot) -> list[str]:
        """Joints on the path from the root to any measured link (root first, no repeats)."""
        return list(dict.fromkeys(j for ln in self.chain_links() for j in robot.path_from_root(ln)))

    @property
    def dim(self) -> int:
        """Residual dimension per stop (3 for points, 6 for poses)."""
        return 3 if self.kind == "point" else 6

    @staticmethod
    def concat(parts: Sequence[Stops]) -> Stops:
        """Stack stops of several bags/files (sessions and groups kept apart)."""
        if not parts:
            raise BagError("no stops to diagnose")
        first = parts[0]
        for p in parts[1:]:
            if p.kind != first.kind or (p.kind == "pose" and p.link != first.link):
                raise BagError(f"cannot mix measurements: {first.kind} on {first.link} and "
                               f"{p.kind} on {p.link} ({p.group_names})")
        several = (first.links is not None or np.ndim(first.point) == 2 or np.ndim(first.sigma) == 1
                   or any(p.links is not None or p.link != first.link or np.ndim(p.point) == 2
                          or np.ndim(p.sigma) == 1 or not np.allclose(p.point, first.point)
                          or p.sigma != first.sigma for p in parts[1:]))
        so = np.cumsum([0] + [len(p.session_names) for p in parts])
        go = np.cumsum([0] + [len(p.group_names) for p in parts])
        joints = sorted(set.intersection(*[set(p.q) for p in parts]))  # a named order, not the strings' hashes
        ctx: dict[str, Any] = {}
        for key in ("time", "temperature", "gravity", "base_tilt", "at_rest"):
            if all(key in p.context for p in parts):
                ctx[key] = np.concatenate([p.context[key] for p in parts])
        for key in ("motion_sign", "joint_velocity"):
            if all(key in p.context for p in parts):
                names = sorted(set.intersection(*[set(p.context[key]) for p in parts]))
                ctx[key] = {n: np.concatenate([p.context[key][n] for p in parts]) for n in names}
        return Stops(
            q={j: np.concatenate([p.q[j] for p in parts]) for j in joints},
            p_meas=np.concatenate([p.p_meas for p in parts]),
            R_meas=None if first.R_meas is None else np.concatenate([p.R_meas for p in parts]),
            kind=first.kind, link=first.link,
            point=np.concatenate([p.point_rows() for p in parts]) if several else first.point,
            sigma=np.concatenate([p.sigma_rows() for p in parts]) if several else first.sigma,
            links=np.concatenate([p.row_links() for p in parts]) if several else None,
            sigma_rot=first.sigma_rot, base=first.base,
            session=np.concatenate([p.session + o for p, o in zip(parts, so)]),
            session_names=[n for p in parts for n in p.session_names],
            group=np.concatenate([p.group + o for p, o in zip(parts, go)]),
            group_names=[n for p in parts for n in p.group_names],
            reg_mask=np.concatenate([p.reg_mask for p in parts]),
            score_mask=np.concatenate([p.score_mask for p in parts]),
            context=ctx,
            imus={k: (first.imus[k][0], np.concatenate([p.imus[k][1] for p in parts]))
                  for k in first.imus if all(k in p.imus for p in parts)},
        )

    def subset(self, rows: np.ndarray) -> Stops:
        """The stops ``rows`` (index or bool array); session/group numbering is kept."""
        def sub_ctx(v: Any) -> Any:
            return {k: a[rows] for k, a in v.items()} if isinstance(v, dict) else v[rows]
        return Stops(q={k: v[rows] for k, v in self.q.items()}, p_meas=self.p_meas[rows],
                     R_meas=None if self.R_meas is None else self.R_meas[rows], kind=self.kind,
                     link=self.link, point=self.point if np.ndim(self.point) == 1 else self.point[rows],
                     sigma=self.sigma if np.ndim(self.sigma) == 0 else np.asarray(self.sigma)[rows],
                     links=None if self.links is None else self.links[rows], sigma_rot=self.sigma_rot,
                     base=self.base, session=self.session[rows], session_names=self.session_names,
                     group=self.group[rows], group_names=self.group_names,
                     reg_mask=self.reg_mask[rows], score_mask=self.score_mask[rows],
                     context={k: sub_ctx(v) for k, v in self.context.items()},
                     imus={k: (ln, a[rows]) for k, (ln, a) in self.imus.items()})


def base_tilt_context(gravity: np.ndarray, session: np.ndarray) -> np.ndarray:
    """Context ``base_tilt`` (N, 2) [rad]: the root's tilt about its x and y axes, ``[-g_y, g_x]`` of the
    measured gravity direction ``g`` (N, 3) in the root frame, minus its mean per ``session`` (a constant
    tilt is part of the session's registration; what is left is the robot rocking from stop to stop)."""
    tilt = np.column_stack([-gravity[:, 1], gravity[:, 0]])
    counts = np.maximum(np.bincount(session), 1)
    means = np.stack([np.bincount(session, tilt[:, k]) / counts for k in range(2)], axis=1)
    return tilt - means[session]
