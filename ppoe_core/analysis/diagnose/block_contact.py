"""Contacts: the tool point touches a known plane (paper sec. V), one residual per contact, no nuisance.

Row ``i`` (one contact, the joint values while pressing): the signed distance of the tool point from the plane
along its normal, ``z_i = e_z^T T_root_plane^-1 p_root``, measured as 0 (residual ``-z_i`` [m]).  The plane is
``T_root_plane = T_root_frame T_frame_plane`` (the model's ``contact`` section; its frame may hang on the chain).
Derivatives of the prediction: ``n_root^T`` times the tool point's Jacobian, plus ``e_z^T [-I, [P]x] Ad(T_fp^-1)``
times the plane frame's frame Jacobian (``P`` the point in plane coordinates).  Noise: the plane's normal variance
``Sigma_v[2, 2]`` plus the declared prior.  This block is the whole of the contact measurement: a new measurement
kind is one such file (data, residual, derivatives, noise, candidates).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock, chain_columns, prior_covariance
from ppoe_core.analysis.diagnose.block_tracker import configuration_columns, time_columns
from ppoe_core.analysis.diagnose.candidates import chain_candidates
from ppoe_core.model.effects import Effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Contacts", "ContactBlock", "concat_contacts"]


@dataclass
class Contacts:
    """Contacts of the tool point with a known plane.

    Attributes
    ----------
    q : dict joint -> ndarray (n,)
        Joint values while in contact.
    link : str
        Link that carries the contact point; ``point`` (3,) its position there [m].
    plane_frame : str
        URDF link the plane is given in; ``T_frame_plane`` (4, 4) the plane (normal = its z axis).
    sigma : float
        1-sigma of the plane along its normal [m] (``Sigma_v[2, 2]``).
    group : ndarray (n,) int; group_names : list of str
        Source bag of each contact.
    context : dict
        Effect context per contact.
    """

    q: dict[str, np.ndarray]
    link: str
    point: np.ndarray
    plane_frame: str
    T_frame_plane: np.ndarray
    sigma: float
    group: np.ndarray
    group_names: list[str]
    context: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.group.size)


def concat_contacts(parts: Sequence[Contacts]) -> Contacts:
    """Contacts of several bags (one plane: the model's)."""
    first = parts[0]
    names: list[str] = []
    groups = []
    for p in parts:
        groups.append(np.array([len(names) + g for g in p.group], dtype=int))
        names.extend(p.group_names)
    joints = [j for j in first.q if all(j in p.q for p in parts)]  # in order (a set's varies per run)
    ctx: dict[str, Any] = {}
    for key, v in first.context.items():
        if isinstance(v, Mapping):
            ctx[key] = {j: np.concatenate([p.context[key][j] for p in parts]) for j in v}
        else:
            ctx[key] = np.concatenate([p.context[key] for p in parts])
    return Contacts({j: np.concatenate([p.q[j] for p in parts]) for j in joints}, first.link, first.point,
                    first.plane_frame, first.T_frame_plane, first.sigma, np.concatenate(groups), names, ctx)


class ContactBlock(ResidualBlock):
    """Contact distances (module docstring)."""

    kind = "contact"
    dim = 1
    nuisance_dim = 0
    unit = "m"

    def __init__(self, tree: KinematicTree, contacts: Contacts) -> None:
        self.data = contacts
        super().__init__(tree, contacts.q, contacts.context, np.full(len(contacts), -1), [], contacts.group,
                         contacts.group_names)
        self.dropped = 0

    def linearise(self, effects: Sequence[Effect], candidates: Sequence[Effect], pert: Mapping[str, np.ndarray],
                  jnoise: Mapping[str, float], chain: bool = False) -> Linearisation:
        c, n = self.data, len(self.data)
        dq, dxi = self.corrections(effects)
        poses = self.tree.link_poses(self.q, dq, dxi, links=[c.link, c.plane_frame])
        T_plane = poses[c.plane_frame] @ c.T_frame_plane
        p_root = (poses[c.link] @ np.append(c.point, 1.0))[:, :3]
        P = np.einsum("nji,nj->ni", T_plane[:, :3, :3], p_root - T_plane[:, :3, 3])
        r = -P[:, 2:3]
        Jq: dict[str, np.ndarray] = {}
        Jx: dict[str, np.ndarray] = {}
        if chain or candidates or pert or jnoise:
            normal = T_plane[:, :3, 2]  # (n, 3) in root axes
            pq, px = self.tree.point_jacobian(self.q, c.link, c.point, poses, dq, dxi)
            for j, v in pq.items():
                Jq[j] = np.einsum("ni,ni->n", normal, v)[:, None]
            for j, v in px.items():
                Jx[j] = np.einsum("ni,nij->nj", normal, v)[:, None, :]
            B = np.concatenate([-np.broadcast_to(np.eye(3), (n, 3, 3)), lie.hat3(P)], axis=-1)[:, 2:3, :]
            B = B @ lie.adjoint(lie.inverse(c.T_frame_plane))
            fq, fx = self.tree.frame_jacobian(self.q, c.plane_frame, poses, dq, dxi)
            for j, v in fq.items():
                Jq[j] = Jq.get(j, np.zeros((n, 1))) + np.einsum("nij,nj->ni", B, v)
            for j, v in fx.items():
                Jx[j] = Jx.get(j, np.zeros((n, 1, 6))) + B @ v
        J = [chain_columns(Jq, Jx, self.basis(e), e.n_params, (n, 1)) for e in candidates]
        S = np.full((n, 1, 1), c.sigma ** 2)
        return Linearisation(r, J, np.zeros((n, 1, 0)), S, prior_covariance(Jq, Jx, pert, jnoise, (n, 1)), Jq=Jq)

    def candidates(self) -> list[Effect]:
        robot = self.tree.robot
        joints = list(dict.fromkeys([*robot.path_from_root(self.data.link), *robot.path_from_root(
            self.data.plane_frame)]))
        return chain_candidates(self.tree, joints, self.context, point=True)

    def chain_links(self) -> list[str]:
        return [self.data.link]

    def structure_columns(self, lin: Linearisation) -> dict[str, np.ndarray]:
        return {**configuration_columns(self.tree, self.q, lin.Jq),
                "time": time_columns(self.context.get("time"), self.group, 1)}
